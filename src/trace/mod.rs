//! Ray tracing 2D Gaussian surfels (paper §"2D Gaussian ray tracing"): a BVH per component,
//! ray–surfel hits with the Gaussian response, and front-to-back compositing of geometry and
//! material along a ray.
//!
//! **Two levels.** [`TraceScene`] builds one BVH (an `obvhs` compressed wide BVH8) per component,
//! in the component's own frame (the reference state's world frame, docs/design.md §2), once
//! (stage 2, whose surfels move at every step, refits its boxes between builds: [`TraceScene::refit`]).
//! [`TraceScene::place`] takes a state's or a layout's rigid transforms and returns a [`Placed`]
//! scene: the top level is the list of instances with their world bounds, so a rearrangement
//! costs a few hundred nanoseconds and never touches a component's BVH. A ray is moved into
//! each instance's frame instead; the transforms are rigid, so the ray parameter `t` (and thus
//! depth and the hit order) is the same in both frames. A scene has a background and a handful
//! of objects, so the top level is a flat list culled by world bounds rather than a BVH.
//!
//! **Hits** (eq. gaussian-response): the ray meets the surfel's plane at `x`, projected onto the
//! scaled tangent axes `ξ = ((x−μ)·t_u/s_u, (x−μ)·t_v/s_v)`; the hit's opacity is
//! `α_eff = min(α·exp(−½|ξ|²), MAX_OPACITY)`. Hits with `|ξ| > CUTOFF` or `α_eff < MIN_ALPHA`
//! are dropped, as is a ray lying in the plane (`d·n = 0`: an edge-on disc has no area).
//!
//! **Compositing** (eq. surface-record): hits are taken in order of `t`, ties broken by
//! (component, surfel index) so the order is total; `w_j = α_j Π_{k<j}(1−α_k)`. They are gathered
//! in sorted batches of [`BATCH`] nearest hits: one BVH traversal keeps a small sorted buffer and
//! prunes everything beyond its last entry, or beyond the hit where the transmittance drops below
//! [`T_MIN`]; the next batch resumes strictly after the last hit of the previous one, and its
//! traversal enters no node lying wholly before that hit (`node`: obvhs's own node test has no
//! lower clip, so every batch used to re-test all the surfels of the batches before it). Visibility
//! rays ([`Placed::transmittance`]) need no order: they multiply `1 − α_eff` in whatever order the
//! BVH yields hits and stop at [`T_MIN`].
//!
//! **Backward** ([`Placed::composite_backward`]): the adjoint of the composite for a batch of
//! rays, with respect to the hit surfels' stored parameters and the components' placements; it
//! re-walks each ray with the forward's own traversal and the kernel's compositing adjoint.
//!
//! [`mod@reference`] holds the slow, obviously correct f64 versions the tests compare against.

mod backward;
mod batch;
mod isa;
mod node;
mod placed;
mod record;
pub mod reference;
mod refit;
mod scene;
mod surfel;

pub use crate::kernel::{CUTOFF, MAX_OPACITY, MIN_ALPHA, T_MIN};
pub use backward::{
    scatter_material_grad, MaterialGrads, TraceGradients, TraceRay, TraceSurfelGrads, RAY_CHUNK,
};
pub use isa::Isa;
pub use placed::{Placed, RayStats};
pub use record::{RecordGrad, SurfaceRecord, WeightedHit};
pub use scene::TraceScene;
pub use surfel::surfel_bounds;

/// Hits gathered per sorted batch. A surfelized surface covers a point with ~28 surfels
/// (σ = spacing, support 3σ: π·3² lattice sites), but a learned one (stage 1's output) is made
/// of larger, fainter, overlapping surfels: a camera ray composites ~50 hits before the
/// transmittance falls below [`T_MIN`], some rays well over 100. A batch that holds them all
/// ends the ray in one traversal that prunes everything behind the hit that ends it; on stage 1's
/// reconstruction of the demo, 128 rather than 32 took a camera ray from 2.2 traversals and 411
/// leaf tests to 0.9 and 194 (the 200k room: unchanged). The buffer is 3 kB on the stack, and an
/// insert costs what lies behind it, not the buffer (see `batch`).
pub const BATCH: usize = 128;
