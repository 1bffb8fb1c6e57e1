//! The paper's per-surfel material (eq. gaussian-primitive): glTF 2.0's metallic-roughness
//! parameters. The data lives here, beside the surfels that carry it, because the tracer's hit
//! records, the scene files and the shading all need it; what it *does* to light (the BRDF, its
//! sampling and its adjoint) is `shade::brdf`.

/// Smallest GGX α: roughness 0 would make D a delta; at α = 1e-3 the peak D = 1/(πα²) ≈ 3e5
/// stays finite in f32 and the lobe is narrower than any texel of a 256x128 environment.
pub const MIN_ALPHA: f32 = 1e-3;
/// Normal-incidence reflectance of the dielectric layer: glTF's ior 1.5, ((1.5−1)/(1.5+1))².
pub const DIELECTRIC_F0: f32 = 0.04;

/// The paper's per-surfel material (eq. gaussian-primitive): base colour a, metallic m,
/// roughness r, all activated values in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    pub base_color: [f32; 3],
    pub metallic: f32,
    pub roughness: f32,
}

impl Material {
    /// GGX α = roughness² (glTF), clamped to [`MIN_ALPHA`].
    pub fn alpha(&self) -> f32 {
        (self.roughness * self.roughness).max(MIN_ALPHA)
    }

    /// F0 = mix(0.04, base_color, metallic).
    pub fn f0(&self) -> [f32; 3] {
        let m = self.metallic;
        self.base_color.map(|c| DIELECTRIC_F0 * (1.0 - m) + c * m)
    }

    /// Diffuse colour (1 − metallic) · base_color (before the 1/π and the Fresnel weight).
    pub fn diffuse_color(&self) -> [f32; 3] {
        self.base_color.map(|c| c * (1.0 - self.metallic))
    }
}
