//! The surfel response α_eff = min(α·exp(−½|ξ|²), MAX_OPACITY) (eq. gaussian-response), the
//! early-out bound on |ξ|² both hit tests use, and dL/dq through a normalised quaternion.

use super::{CUTOFF, MAX_OPACITY, MIN_ALPHA};
use glam::{Mat3, Vec4};

/// Slack on the opacity part of [`r2_max`]. The bound is only a prefilter: the exact test in
/// [`response`] decides, so a larger slack costs a few wasted `exp`s and never changes a result,
/// while too small a one could let f32 rounding of `ln` drop a hit the exact test would keep.
/// 1e-3 in |ξ|² is ~1e-4 relative at the edge of the support, far above that rounding.
pub const R2_SLACK: f32 = 1e-3;

/// Largest |ξ|² that can pass both the support and the opacity threshold:
/// α·exp(−½ r²) ≥ MIN_ALPHA ⇔ r² ≤ 2 ln(α / MIN_ALPHA), plus [`R2_SLACK`], and at most
/// CUTOFF². An opacity of 0 gives −∞: never hit.
#[inline(always)]
pub fn r2_max(opacity: f32) -> f32 {
    (2.0 * (opacity / MIN_ALPHA).ln() + R2_SLACK).min(CUTOFF * CUTOFF)
}

/// One kept hit's response.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Response {
    /// α_eff = min(opacity·g, MAX_OPACITY).
    pub alpha: f32,
    /// g = exp(−½ |ξ|²).
    pub g: f32,
    /// opacity·g exceeded MAX_OPACITY: α_eff does not depend on the surfel's parameters.
    pub capped: bool,
}

/// The response at squared distance `r2 = |ξ|²` (which the caller has already checked against
/// [`r2_max`]), or `None` when the hit is fainter than [`MIN_ALPHA`].
#[inline(always)]
pub fn response(opacity: f32, r2: f32) -> Option<Response> {
    let g = (-0.5 * r2).exp();
    let raw = opacity * g;
    let alpha = raw.min(MAX_OPACITY);
    if alpha < MIN_ALPHA {
        return None;
    }
    Some(Response {
        alpha,
        g,
        capped: raw > MAX_OPACITY,
    })
}

/// dL/dq for the raw quaternion q = (x, y, z, w) that is normalised and turned into R(q̂), given
/// dL/dR as columns. The result is orthogonal to q: scaling q does not change R.
pub fn quat_grad(q_raw: [f32; 4], g: Mat3) -> [f32; 4] {
    let qv = Vec4::from_array(q_raw);
    let len = qv.length();
    let [x, y, z, w] = (qv / len).to_array();
    // G[r][c] = dL/dR[r][c]; columns of g are the columns of R.
    let m = |r: usize, c: usize| g.col(c)[r];
    let gx = 2.0 * y * (m(0, 1) + m(1, 0))
        + 2.0 * z * (m(0, 2) + m(2, 0))
        + 2.0 * w * (m(2, 1) - m(1, 2))
        - 4.0 * x * (m(1, 1) + m(2, 2));
    let gy = 2.0 * x * (m(0, 1) + m(1, 0))
        + 2.0 * w * (m(0, 2) - m(2, 0))
        + 2.0 * z * (m(1, 2) + m(2, 1))
        - 4.0 * y * (m(0, 0) + m(2, 2));
    let gz = 2.0 * w * (m(1, 0) - m(0, 1))
        + 2.0 * x * (m(0, 2) + m(2, 0))
        + 2.0 * y * (m(1, 2) + m(2, 1))
        - 4.0 * z * (m(0, 0) + m(1, 1));
    let gw = 2.0 * z * (m(1, 0) - m(0, 1))
        + 2.0 * y * (m(0, 2) - m(2, 0))
        + 2.0 * x * (m(2, 1) - m(1, 2));
    // Through the normalisation: (I − q̂ q̂ᵀ) / |q|.
    let gq = Vec4::new(gx, gy, gz, gw);
    let qh = qv / len;
    ((gq - qh * qh.dot(gq)) / len).to_array()
}
