//! One surfel as the hit test sees it (eq. gaussian-response), and its bounds.

use super::CUTOFF;
use crate::kernel::{r2_max, response};
use crate::scene::quat_axes;
use glam::Vec3;

/// Everything the hit test reads, precomputed and packed into one cache line: a traversal
/// touches surfels in leaf order, so one line per test beats gathering from separate arrays.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(64))]
pub(crate) struct HitSurfel {
    /// Centre μ.
    pub mu: [f32; 3],
    /// Opacity α.
    pub alpha: f32,
    /// Unit normal n (third column of R(q)).
    pub n: [f32; 3],
    /// Largest |ξ|² that can pass both the support and the opacity threshold
    /// ([`crate::kernel::r2_max`]); the exact test in `hit` decides.
    pub r2_max: f32,
    /// t_u / s_u: (x − μ)·u is ξ_u.
    pub u: [f32; 3],
    _pad0: f32,
    /// t_v / s_v.
    pub v: [f32; 3],
    _pad1: f32,
}

impl HitSurfel {
    pub fn new(position: [f32; 3], rotation: [f32; 4], scale: [f32; 2], opacity: f32) -> Self {
        let [tu, tv, n] = quat_axes(rotation);
        let u = Vec3::from_array(tu) / scale[0];
        let v = Vec3::from_array(tv) / scale[1];
        HitSurfel {
            mu: position,
            alpha: opacity,
            n,
            r2_max: r2_max(opacity),
            u: u.to_array(),
            _pad0: 0.0,
            v: v.to_array(),
            _pad1: 0.0,
        }
    }

    /// The hit of the ray `o + t d` with `t` in `[t_lo, t_hi]` (inclusive; callers apply their
    /// own strictness and tie-breaks): `(t, α_eff)`, or `None` when the plane is missed, the
    /// hit lies outside the support or is fainter than [`super::MIN_ALPHA`]. Never yields NaN: a ray in
    /// the plane gives t = NaN or ±∞, which every comparison below rejects.
    #[inline(always)]
    pub fn hit(&self, o: Vec3, d: Vec3, t_lo: f32, t_hi: f32) -> Option<(f32, f32)> {
        let mu = Vec3::from_array(self.mu);
        let n = Vec3::from_array(self.n);
        let om = o - mu;
        let t = -om.dot(n) / d.dot(n);
        if !(t >= t_lo && t <= t_hi && t < f32::INFINITY) {
            return None;
        }
        let p = om + t * d;
        let xu = p.dot(Vec3::from_array(self.u));
        let xv = p.dot(Vec3::from_array(self.v));
        let r2 = xu * xu + xv * xv;
        // Written so that a NaN r² (from a degenerate ray) is rejected too.
        if r2.is_nan() || r2 > self.r2_max {
            return None;
        }
        // eq. gaussian-response, capped and thresholded as the rasteriser does.
        response(self.alpha, r2).map(|r| (t, r.alpha))
    }
}

/// Axis-aligned bounds of a surfel's support, the disc |ξ| ≤ CUTOFF: along world axis k the
/// ellipse with semi-axes CUTOFF·s_u·t_u and CUTOFF·s_v·t_v reaches
/// ±CUTOFF·sqrt((s_u t_u[k])² + (s_v t_v[k])²).
pub fn surfel_bounds(
    position: [f32; 3],
    rotation: [f32; 4],
    scale: [f32; 2],
) -> ([f32; 3], [f32; 3]) {
    let [tu, tv, _] = quat_axes(rotation);
    let mut lo = [0.0; 3];
    let mut hi = [0.0; 3];
    for k in 0..3 {
        let a = scale[0] * tu[k];
        let b = scale[1] * tv[k];
        let r = CUTOFF * (a * a + b * b).sqrt();
        lo[k] = position[k] - r;
        hi[k] = position[k] + r;
    }
    (lo, hi)
}
