//! What compositing along a ray yields (eq. surface-record).

use crate::shade::brdf::Material;

/// Front-to-back composite of the hits along one ray (eq. surface-record). The fields are the
/// weighted sums Σ w_j z_j with `w_j = α_j Π_{k<j}(1 − α_k)`, i.e. the numerators of the paper's
/// z̄; the `mean_*` accessors divide by `alpha` = Σ w_j. Keeping the sums makes records additive
/// and keeps "no hit" exactly zero (DESIGN §2: no hit = depth 0).
///
/// Normals are world space and turned to face the ray (`n` flipped when `n·d > 0`) before they
/// are summed, so the two faces of a surfel composite alike.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SurfaceRecord {
    /// Σ w t: `t` is the ray parameter (distance for a unit direction). A camera's planar depth
    /// is `t · (d · forward)`.
    pub depth: f32,
    /// Σ w x, world space.
    pub position: [f32; 3],
    /// Σ w n, world space, facing the ray; see [`SurfaceRecord::unit_normal`].
    pub normal: [f32; 3],
    /// Σ w a.
    pub base_color: [f32; 3],
    /// Σ w m.
    pub metallic: f32,
    /// Σ w r.
    pub roughness: f32,
    /// Σ w = 1 − transmittance (up to [`super::T_MIN`]).
    pub alpha: f32,
    /// Hits composited.
    pub hits: u32,
}

impl SurfaceRecord {
    /// Adds one hit of weight `w`.
    #[inline]
    pub(crate) fn add(&mut self, w: f32, t: f32, x: [f32; 3], n: [f32; 3], m: &Material) {
        self.depth += w * t;
        for k in 0..3 {
            self.position[k] += w * x[k];
            self.normal[k] += w * n[k];
            self.base_color[k] += w * m.base_color[k];
        }
        self.metallic += w * m.metallic;
        self.roughness += w * m.roughness;
        self.alpha += w;
        self.hits += 1;
    }

    fn per_alpha(&self) -> f32 {
        if self.alpha > 0.0 {
            1.0 / self.alpha
        } else {
            0.0
        }
    }

    /// Composited depth z̄ = Σ w t / Σ w; 0 when nothing was hit.
    pub fn mean_depth(&self) -> f32 {
        self.depth * self.per_alpha()
    }

    pub fn mean_position(&self) -> [f32; 3] {
        self.position.map(|x| x * self.per_alpha())
    }

    /// The composited normal, renormalised (paper: "renormalized before shading"); zero when
    /// nothing was hit or the normals cancel out.
    pub fn unit_normal(&self) -> [f32; 3] {
        let len = self.normal.iter().map(|x| x * x).sum::<f32>().sqrt();
        if len > 0.0 {
            self.normal.map(|x| x / len)
        } else {
            [0.0; 3]
        }
    }

    pub fn mean_base_color(&self) -> [f32; 3] {
        self.base_color.map(|x| x * self.per_alpha())
    }

    pub fn mean_metallic(&self) -> f32 {
        self.metallic * self.per_alpha()
    }

    pub fn mean_roughness(&self) -> f32 {
        self.roughness * self.per_alpha()
    }
}
