//! Surfels as a struct of arrays: every attribute of the paper's eq. gaussian-primitive.
//!
//! Values are stored *activated* (linear scale, opacity in [0, 1], materials in [0, 1]), as in
//! the files; optimisers keep their own unconstrained copies.

use crate::error::{Error, Result};
use std::path::Path;

/// Highest spherical-harmonics degree a surfel carries (KHR_gaussian_splatting allows 3).
pub const MAX_SH_DEGREE: u8 = 3;

/// Number of SH coefficients (each an RGB triple) for a degree: (L + 1)².
pub const fn sh_coeffs(degree: u8) -> usize {
    (degree as usize + 1) * (degree as usize + 1)
}

/// The zeroth-order real SH basis value, 1 / (2 √π).
pub const SH_C0: f32 = 0.282_094_8;

/// 2D Gaussian surfels (eq. gaussian-primitive): centre μ, rotation q, in-plane scale (s_u, s_v),
/// opacity α, SH appearance f, base colour a, metallic m, roughness r.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Surfels {
    /// Centre μ, metres.
    pub position: Vec<[f32; 3]>,
    /// Unit quaternion (x, y, z, w); the normal is the third column of R(q).
    pub rotation: Vec<[f32; 4]>,
    /// In-plane scale (s_u, s_v) > 0, metres (one standard deviation).
    pub scale: Vec<[f32; 2]>,
    /// Opacity α ∈ [0, 1].
    pub opacity: Vec<f32>,
    /// Degree L of the SH appearance, 0..=3.
    pub sh_degree: u8,
    /// SH coefficients, `sh_coeffs(sh_degree)` RGB triples per surfel, surfel-major,
    /// KHR_gaussian_splatting order (degree, then coefficient n = 0..2l).
    pub sh: Vec<[f32; 3]>,
    /// Base colour a ∈ [0, 1]³, scene-linear.
    pub base_color: Vec<[f32; 3]>,
    /// Metallic m ∈ [0, 1].
    pub metallic: Vec<f32>,
    /// Roughness r ∈ [0, 1].
    pub roughness: Vec<f32>,
}

impl Surfels {
    /// Empty surfels with the given SH degree.
    pub fn with_sh_degree(sh_degree: u8) -> Self {
        Surfels {
            sh_degree,
            ..Default::default()
        }
    }

    pub fn len(&self) -> usize {
        self.position.len()
    }

    pub fn is_empty(&self) -> bool {
        self.position.is_empty()
    }

    /// SH triples per surfel.
    pub fn sh_stride(&self) -> usize {
        sh_coeffs(self.sh_degree)
    }

    /// Appends one surfel. `sh` must hold `sh_stride()` triples.
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        position: [f32; 3],
        rotation: [f32; 4],
        scale: [f32; 2],
        opacity: f32,
        sh: &[[f32; 3]],
        base_color: [f32; 3],
        metallic: f32,
        roughness: f32,
    ) {
        assert_eq!(sh.len(), self.sh_stride(), "SH triples per surfel");
        self.position.push(position);
        self.rotation.push(rotation);
        self.scale.push(scale);
        self.opacity.push(opacity);
        self.sh.extend_from_slice(sh);
        self.base_color.push(base_color);
        self.metallic.push(metallic);
        self.roughness.push(roughness);
    }

    /// Appends all surfels of `other` (same SH degree required; lower degrees are padded with 0).
    pub fn extend(&mut self, other: &Surfels) {
        let stride = self.sh_stride();
        let other_stride = other.sh_stride();
        assert!(other_stride <= stride, "cannot append higher SH degree");
        self.position.extend_from_slice(&other.position);
        self.rotation.extend_from_slice(&other.rotation);
        self.scale.extend_from_slice(&other.scale);
        self.opacity.extend_from_slice(&other.opacity);
        for i in 0..other.len() {
            self.sh
                .extend_from_slice(&other.sh[i * other_stride..(i + 1) * other_stride]);
            self.sh
                .extend(std::iter::repeat_n([0.0; 3], stride - other_stride));
        }
        self.base_color.extend_from_slice(&other.base_color);
        self.metallic.extend_from_slice(&other.metallic);
        self.roughness.extend_from_slice(&other.roughness);
    }

    /// The SH triples of surfel `i`.
    pub fn sh_of(&self, i: usize) -> &[[f32; 3]] {
        let s = self.sh_stride();
        &self.sh[i * s..(i + 1) * s]
    }

    /// Axis-aligned bounds of the centres, or `None` when empty.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let mut it = self.position.iter();
        let first = *it.next()?;
        Some(it.fold((first, first), |(mut lo, mut hi), p| {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
            (lo, hi)
        }))
    }

    /// Checks every invariant of eq. gaussian-primitive. `file` and `what` name the source in
    /// the error, e.g. `scene.glb` and `component "chair"`.
    pub fn validate(&self, file: &Path, what: &str) -> Result<()> {
        let n = self.len();
        let bad = |field: &str, message: String| {
            Error::invalid(file, format!("{what}: {field}"), message)
        };
        if self.sh_degree > MAX_SH_DEGREE {
            return Err(bad(
                "sh_degree",
                format!("expected 0..=3, found {}", self.sh_degree),
            ));
        }
        let lens = [
            ("rotation", self.rotation.len()),
            ("scale", self.scale.len()),
            ("opacity", self.opacity.len()),
            ("base_color", self.base_color.len()),
            ("metallic", self.metallic.len()),
            ("roughness", self.roughness.len()),
            ("sh", self.sh.len() / self.sh_stride().max(1)),
        ];
        for (name, len) in lens {
            if len != n {
                return Err(bad(
                    name,
                    format!("expected {n} values (one per position), found {len}"),
                ));
            }
        }
        if self.sh.len() != n * self.sh_stride() {
            return Err(bad(
                "sh",
                format!(
                    "expected {} triples, found {}",
                    n * self.sh_stride(),
                    self.sh.len()
                ),
            ));
        }
        let finite = |v: &[f32]| v.iter().position(|x| !x.is_finite());
        let checks: [(&str, &[f32], usize); 8] = [
            ("position", flat3(&self.position), 3),
            ("rotation", bytemuck::cast_slice(&self.rotation), 4),
            ("scale", bytemuck::cast_slice(&self.scale), 2),
            ("opacity", &self.opacity, 1),
            ("sh", flat3(&self.sh), 3 * self.sh_stride()),
            ("base_color", flat3(&self.base_color), 3),
            ("metallic", &self.metallic, 1),
            ("roughness", &self.roughness, 1),
        ];
        for (name, values, per) in checks {
            if let Some(k) = finite(values) {
                return Err(bad(
                    name,
                    format!(
                        "surfel {}: expected a finite number, found {}",
                        k / per,
                        values[k]
                    ),
                ));
            }
        }
        for (i, q) in self.rotation.iter().enumerate() {
            let norm2 = q.iter().map(|x| x * x).sum::<f32>();
            // Anything this short is not a rotation: normalising it would amplify noise.
            if norm2 < 1e-12 {
                return Err(bad(
                    "rotation",
                    format!("surfel {i}: expected a unit quaternion, found zero"),
                ));
            }
        }
        for (i, s) in self.scale.iter().enumerate() {
            if !(s[0] > 0.0 && s[1] > 0.0) {
                return Err(bad(
                    "scale",
                    format!(
                        "surfel {i}: expected positive in-plane scale, found ({}, {})",
                        s[0], s[1]
                    ),
                ));
            }
        }
        let unit = |name: &str, v: &[f32], per: usize| -> Result<()> {
            if let Some(k) = v.iter().position(|x| !(0.0..=1.0).contains(x)) {
                return Err(bad(
                    name,
                    format!(
                        "surfel {}: expected a value in [0, 1], found {}",
                        k / per,
                        v[k]
                    ),
                ));
            }
            Ok(())
        };
        unit("opacity", &self.opacity, 1)?;
        unit("base_color", flat3(&self.base_color), 3)?;
        unit("metallic", &self.metallic, 1)?;
        unit("roughness", &self.roughness, 1)?;
        Ok(())
    }
}

fn flat3(v: &[[f32; 3]]) -> &[f32] {
    bytemuck::cast_slice(v)
}

/// Rotation matrix columns (tangent u, tangent v, normal) of a unit quaternion (x, y, z, w).
pub fn quat_axes(q: [f32; 4]) -> [[f32; 3]; 3] {
    let m = glam::Mat3::from_quat(glam::Quat::from_array(q).normalize());
    [
        m.x_axis.to_array(),
        m.y_axis.to_array(),
        m.z_axis.to_array(),
    ]
}
