//! What compositing along a ray yields (eq. surface-record).

use crate::scene::Material;
use crate::scene::Surfels;

/// Front-to-back composite of the hits along one ray (eq. surface-record). The fields are the
/// weighted sums Σ w_j z_j with `w_j = α_j Π_{k<j}(1 − α_k)`, i.e. the numerators of the paper's
/// z̄; the `mean_*` accessors divide by `alpha` = Σ w_j. Keeping the sums makes records additive
/// and keeps "no hit" exactly zero (docs/design.md §2: no hit = depth 0).
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

/// One hit a record composited: the surfel (its component, and its index in that component's
/// [`Surfels`]) and its weight `w = T α` (eq. surface-record).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WeightedHit {
    pub component: u32,
    pub index: u32,
    pub w: f32,
}

impl SurfaceRecord {
    /// Recomputes the material sums (Σ w a, Σ w m, Σ w r) from the record's hits and the
    /// surfels' current materials; geometry, `alpha` and `hits` stay. With the hits
    /// [`super::Placed::composite_hits`] returned and unchanged materials, the record is the one
    /// `composite` returns (up to the order of float additions, which is the same).
    pub fn set_materials(&mut self, hits: &[WeightedHit], components: &[&Surfels]) {
        let (mut a, mut m, mut r) = ([0.0f32; 3], 0.0f32, 0.0f32);
        for h in hits {
            let s = components[h.component as usize];
            let i = h.index as usize;
            for (a, c) in a.iter_mut().zip(s.base_color[i]) {
                *a += h.w * c;
            }
            m += h.w * s.metallic[i];
            r += h.w * s.roughness[i];
        }
        self.base_color = a;
        self.metallic = m;
        self.roughness = r;
    }
}

/// dL/d(each sum of a [`SurfaceRecord`]) for one ray: the upstream gradient of
/// [`super::Placed::composite_backward`]. Same fields as the record, minus `hits`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RecordGrad {
    pub depth: f32,
    pub position: [f32; 3],
    pub normal: [f32; 3],
    pub base_color: [f32; 3],
    pub metallic: f32,
    pub roughness: f32,
    pub alpha: f32,
}

impl RecordGrad {
    /// Adds `o` field by field (gradients of a sum of losses add).
    pub fn add(&mut self, o: &RecordGrad) {
        self.depth += o.depth;
        for k in 0..3 {
            self.position[k] += o.position[k];
            self.normal[k] += o.normal[k];
            self.base_color[k] += o.base_color[k];
        }
        self.metallic += o.metallic;
        self.roughness += o.roughness;
        self.alpha += o.alpha;
    }

    /// Every field times `s` (a loss weight).
    pub fn scaled(&self, s: f32) -> RecordGrad {
        RecordGrad {
            depth: self.depth * s,
            position: self.position.map(|x| x * s),
            normal: self.normal.map(|x| x * s),
            base_color: self.base_color.map(|x| x * s),
            metallic: self.metallic * s,
            roughness: self.roughness * s,
            alpha: self.alpha * s,
        }
    }

    /// ⟨self, f⟩ where `f` is what one hit contributes to the sums (weight 1): the upstream
    /// gradient of that hit's values, `gdot` of [`crate::kernel::composite::Back::step`].
    #[inline(always)]
    pub(crate) fn dot_hit(&self, t: f32, x: [f32; 3], n: [f32; 3], m: &Material) -> f32 {
        let mut s = self.depth * t + self.metallic * m.metallic + self.roughness * m.roughness;
        for k in 0..3 {
            s += self.position[k] * x[k]
                + self.normal[k] * n[k]
                + self.base_color[k] * m.base_color[k];
        }
        s + self.alpha
    }

    pub fn is_zero(&self) -> bool {
        *self == RecordGrad::default()
    }
}

impl SurfaceRecord {
    /// Chain rule for z̄ = Σwt / Σw ([`SurfaceRecord::mean_depth`]) with dL/dz̄ = `g`:
    /// dL/dΣwt = g / Σw, dL/dΣw = −g z̄ / Σw. Zero when nothing was hit (z̄ is then the constant 0).
    pub fn mean_depth_grad(&self, g: f32) -> RecordGrad {
        let inv = self.per_alpha();
        RecordGrad {
            depth: g * inv,
            alpha: -g * self.depth * inv * inv,
            ..RecordGrad::default()
        }
    }

    /// Chain rule for Σwx / Σw ([`SurfaceRecord::mean_position`]).
    pub fn mean_position_grad(&self, g: [f32; 3]) -> RecordGrad {
        let inv = self.per_alpha();
        let dot: f32 = (0..3).map(|k| g[k] * self.position[k]).sum();
        RecordGrad {
            position: g.map(|x| x * inv),
            alpha: -dot * inv * inv,
            ..RecordGrad::default()
        }
    }

    /// Chain rule for N / |N|, N = Σwn ([`SurfaceRecord::unit_normal`]):
    /// dL/dN = (g − n̂ (n̂·g)) / |N|; zero where the unit normal is the constant 0.
    pub fn unit_normal_grad(&self, g: [f32; 3]) -> RecordGrad {
        let len = self.normal.iter().map(|x| x * x).sum::<f32>().sqrt();
        if len <= 0.0 {
            return RecordGrad::default();
        }
        let nh = self.normal.map(|x| x / len);
        let dot: f32 = (0..3).map(|k| g[k] * nh[k]).sum();
        RecordGrad {
            normal: [0, 1, 2].map(|k| (g[k] - nh[k] * dot) / len),
            ..RecordGrad::default()
        }
    }

    /// Chain rule for the mean material (Σwa, Σwm, Σwr) / Σw, given dL/d of each mean.
    pub fn mean_material_grad(
        &self,
        base_color: [f32; 3],
        metallic: f32,
        roughness: f32,
    ) -> RecordGrad {
        let inv = self.per_alpha();
        let dot: f32 = (0..3)
            .map(|k| base_color[k] * self.base_color[k])
            .sum::<f32>()
            + metallic * self.metallic
            + roughness * self.roughness;
        RecordGrad {
            base_color: base_color.map(|x| x * inv),
            metallic: metallic * inv,
            roughness: roughness * inv,
            alpha: -dot * inv * inv,
            ..RecordGrad::default()
        }
    }
}
