//! What splatting and tracing share (docs/design.md §4): the surfel response of eq. gaussian-response
//! with its cut-offs, the front-to-back compositing step of eq. surface-record and its adjoint,
//! and the gradient through a normalised quaternion. One copy each, so that the rasteriser and
//! the ray tracer agree on which hits exist and how they are weighted.

pub mod composite;
mod response;

pub use response::{quat_grad, r2_max, response, Response, R2_SLACK};

/// Support of the surfel response in standard deviations (2DGS uses 3σ): hits with
/// |ξ| > CUTOFF are dropped, and the BVH bounds are built from it.
pub const CUTOFF: f32 = 3.0;

/// Cap on the effective opacity of one hit (paper §"2D Gaussian ray tracing": 0.99). It keeps
/// 1 − α away from zero, so a backward pass can recover the transmittance in front of a hit
/// by division, and one hit never makes a surface fully opaque.
pub const MAX_OPACITY: f32 = 0.99;

/// Below this effective opacity a hit is invisible in an 8-bit image, so it is dropped.
pub const MIN_ALPHA: f32 = 1.0 / 255.0;

/// Transmittance below which a ray is treated as fully absorbed: whatever lies further along
/// can change any composited attribute by at most this fraction of its value, far below the
/// noise of a path-traced estimate.
pub const T_MIN: f32 = 1e-4;
