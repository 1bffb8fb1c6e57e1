//! The 2D Gaussian splatting tile rasteriser of Huang et al. 2024 ("2D Gaussian Splatting for
//! Geometrically Accurate Radiance Fields"), forward and backward, on the CPU. It renders the
//! splatting appearance, opacity, depth and normal maps that the reconstruction objective
//! (eq. reconstruction-objective) compares with the captures, and returns gradients for every
//! surfel parameter (eq. gaussian-primitive) and every component's rigid placement
//! (eq. state-assembly).
//!
//! **Hit** (eq. gaussian-response, in 2DGS's exact ray–splat form). The pixel ray
//! `x(t) = o + t d` (with `d · forward = 1`, so `t` is planar depth) meets the surfel's plane at
//! `t = (μ − o)·n / (d·n)`; the hit is projected onto the scaled tangent axes,
//! `ξ = ((x − μ)·t_u / s_u, (x − μ)·t_v / s_v)`, giving `ρ_3d = |ξ|²`. 2DGS's object-space
//! low-pass filter takes `Ĝ = max(G(ξ), G(|p − c| / σ))` with `σ = √2/2` pixel and `c` the
//! projected centre, i.e. `ρ = min(ρ_3d, ρ_2d)` with `ρ_2d = 2 |p − c|²` and `Ĝ = exp(−½ ρ)`.
//! When the filter wins, the hit takes the centre's depth (as 2DGS does), otherwise the plane's.
//! The hit's opacity is `α = min(MAX_OPACITY, o_i Ĝ)`. A hit is dropped when `ρ > CUTOFF²`
//! (finite support), `α < MIN_ALPHA`, or its depth is below [`NEAR`]. A surfel whose centre is
//! nearer than [`NEAR`] is culled (2DGS's frustum test), so `c` is always defined.
//!
//! **Order.** Within a 16×16 tile, surfels are composited in the order of their *centre* depth
//! (ties by global index), as 2DGS does; one global sort, then a stable bucketing into tiles.
//! Per-hit depth order would be exact for interpenetrating surfels but needs a sort per pixel;
//! the reference sorts by the same key, so the tests compare like with like.
//!
//! **Compositing** (eq. surface-record): `w_j = α_j Π_{k<j} (1 − α_k)`, front to back; a pixel
//! stops after the hit that takes its transmittance below [`T_MIN`] (that hit is composited, as in
//! `trace`).
//!
//! **Outputs** ([`SplatImage`]) per pixel: colour `Σ w c` (over black; `c` from SH, see
//! [`sh`]), opacity `A = Σ w`, depth `Σ w z / A` (planar, 0 with no hit, as docs/design.md §2 asks),
//! 2DGS's median depth (the depth of the last hit entered with transmittance above ½), and
//! normal `Σ w n` (world space, each `n` turned to face the camera; *not* divided by `A` nor
//! renormalised, as 2DGS renders it: the loss decides).
//!
//! **Backward** ([`Forward::backward`]): per tile, back to front from each pixel's last
//! contributor, recovering `T_j = T_{j+1} / (1 − α_j)` (α ≤ 0.99 keeps this stable) and carrying
//! the composite of everything behind. Gradients are accumulated per (tile, surfel) in the
//! tile's own slice of a buffer, then summed per surfel: no atomics, and the result does not
//! depend on the thread count.
//!
//! [`mod@reference`] is the slow f64 version the tests compare against.

mod backward;
mod forward;
mod project;
pub mod reference;
pub mod sh;

use crate::scene::transform::TransformGrad;
use crate::scene::{Camera, Rigid, Surfels};

pub use crate::kernel::{CUTOFF, MAX_OPACITY, MIN_ALPHA, T_MIN};

/// Side of a square tile, pixels (2DGS's BLOCK_X = BLOCK_Y = 16).
pub const TILE: u32 = 16;

/// Pixels per tile.
pub(crate) const TILE_PIXELS: usize = (TILE * TILE) as usize;

/// Near plane, metres: surfels whose centre is nearer are culled and hits nearer are dropped.
/// 2DGS uses 0.2 scene units for its normalised scenes; ours are in metres and a camera can
/// stand a hand's width from a wall, so one centimetre.
pub const NEAR: f32 = 0.01;

/// Variance of the object-space low-pass filter, pixels²: σ = √2/2 (2DGS), so
/// `ρ_2d = |p − c|² / σ² = 2 |p − c|²`.
pub const FILTER_INV_VARIANCE: f32 = 2.0;

/// One component to splat: its surfels, in the component's own frame, and its placement
/// (object to world, eq. state-assembly: it moves centres and orientations only; SH is not
/// rotated). The background is placed by [`Rigid::IDENTITY`].
#[derive(Clone, Copy, Debug)]
pub struct Placement<'a> {
    pub surfels: &'a Surfels,
    pub transform: Rigid,
}

/// Every component of `scene` placed as `state` places it (eq. state-assembly).
pub fn placements<'a>(
    scene: &'a crate::scene::Scene,
    state: &crate::scene::State,
) -> Vec<Placement<'a>> {
    scene
        .components
        .iter()
        .zip(&state.transforms)
        .map(|(c, t)| Placement {
            surfels: &c.surfels,
            transform: *t,
        })
        .collect()
}

impl<'a> Placement<'a> {
    /// Surfels already in the world frame.
    pub fn world(surfels: &'a Surfels) -> Self {
        Placement {
            surfels,
            transform: Rigid::IDENTITY,
        }
    }
}

/// Per-pixel maps, row-major (`y * width + x`). Also used for the gradient of a loss with
/// respect to each map ([`ImageGrad`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SplatImage {
    pub width: u32,
    pub height: u32,
    /// Σ w c: scene-linear colour over black (premultiplied).
    pub color: Vec<[f32; 3]>,
    /// A = Σ w, the accumulated opacity of eq. alpha-coverage.
    pub alpha: Vec<f32>,
    /// Σ w z / A: alpha-weighted expected planar depth, metres; 0 where nothing is hit.
    pub depth: Vec<f32>,
    /// 2DGS median depth: depth of the last hit entered with transmittance above ½; 0 if none.
    pub median_depth: Vec<f32>,
    /// Σ w n: world-space normals facing the camera, not normalised.
    pub normal: Vec<[f32; 3]>,
}

/// dL/d(each output map) for [`Forward::backward`], same layout as [`SplatImage`].
pub type ImageGrad = SplatImage;

impl SplatImage {
    /// All maps zero (also "no gradient").
    pub fn zeros(width: u32, height: u32) -> Self {
        let n = width as usize * height as usize;
        SplatImage {
            width,
            height,
            color: vec![[0.0; 3]; n],
            alpha: vec![0.0; n],
            depth: vec![0.0; n],
            median_depth: vec![0.0; n],
            normal: vec![[0.0; 3]; n],
        }
    }

    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// Gradients with respect to one component's surfel parameters, in the component's frame and
/// with respect to the stored (activated) values: position, the raw quaternion (x, y, z, w) as
/// stored (it is normalised before use, so the gradient is orthogonal to it), scale (s_u, s_v),
/// post-sigmoid opacity (see [`logit_grad`]) and every SH triple (surfel-major, as in
/// [`Surfels::sh`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SurfelGrads {
    pub position: Vec<[f32; 3]>,
    pub rotation: Vec<[f32; 4]>,
    pub scale: Vec<[f32; 2]>,
    pub opacity: Vec<f32>,
    pub sh: Vec<[f32; 3]>,
}

impl SurfelGrads {
    pub fn zeros(n: usize, sh_stride: usize) -> Self {
        SurfelGrads {
            position: vec![[0.0; 3]; n],
            rotation: vec![[0.0; 4]; n],
            scale: vec![[0.0; 2]; n],
            opacity: vec![0.0; n],
            sh: vec![[0.0; 3]; n * sh_stride],
        }
    }
}

/// Everything [`Forward::backward`] returns, one entry per [`Placement`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Gradients {
    pub surfels: Vec<SurfelGrads>,
    pub transforms: Vec<TransformGrad>,
}

/// dL/d(logit α) from dL/dα for a post-sigmoid opacity α: `dα/dx = α (1 − α)`.
pub fn logit_grad(opacity: f32, d_opacity: f32) -> f32 {
    d_opacity * opacity * (1.0 - opacity)
}

/// dL/d(ln s) from dL/ds for a scale stored linearly: `ds/d(ln s) = s`.
pub fn log_scale_grad(scale: f32, d_scale: f32) -> f32 {
    d_scale * scale
}

/// A rendered frame and what its backward pass needs (the projected surfels, the tile lists and
/// each pixel's final transmittance and last contributor).
pub struct Forward<'a> {
    pub image: SplatImage,
    components: Vec<Placement<'a>>,
    view: project::View,
    prepared: project::Prepared,
    bins: project::Bins,
    pixels: Vec<forward::PixelState>,
    /// Global index of each component's first surfel, plus the total.
    offsets: Vec<usize>,
}

/// Renders the components with the camera's image size (`camera.w × camera.h`; zero is
/// allowed and gives empty maps). Non-finite surfels are culled rather than trusted.
pub fn forward<'a>(components: &[Placement<'a>], camera: &Camera) -> Forward<'a> {
    let view = project::View::new(camera);
    let mut offsets = Vec::with_capacity(components.len() + 1);
    let mut total = 0;
    for c in components {
        offsets.push(total);
        total += c.surfels.len();
    }
    offsets.push(total);
    let prepared = project::prepare(&view, components, &offsets);
    let bins = project::bin(&view, &prepared.splats, &prepared.order);
    let (image, pixels) = forward::rasterize(&view, &prepared.splats, &bins);
    Forward {
        image,
        components: components.to_vec(),
        view,
        prepared,
        bins,
        pixels,
        offsets,
    }
}

/// Renders world-space surfels: [`forward`] of one identity placement, image only.
pub fn render(surfels: &Surfels, camera: &Camera) -> SplatImage {
    forward(&[Placement::world(surfels)], camera).image
}

impl Forward<'_> {
    /// Gradients of a loss L for every surfel parameter and every placement, given dL/d(each
    /// output map). `grad` must have the image's size.
    pub fn backward(&self, grad: &ImageGrad) -> Gradients {
        assert_eq!(
            (grad.width, grad.height),
            (self.image.width, self.image.height),
            "gradient maps must have the rendered image's size"
        );
        backward::backward(self, grad)
    }
}
