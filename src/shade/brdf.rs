//! The surface BRDF: glTF 2.0's metallic-roughness model (spec Appendix B), Lambert diffuse +
//! GGX microfacet specular, and its sampling from a cosine / GGX visible-normal mixture (the
//! "BSDF continuation" of the paper's path estimator, eq. path-estimator).
//!
//! # The model (glTF 2.0 Appendix B, written out)
//!
//! ```text
//! α      = max(roughness², MIN_ALPHA)                       glTF: α = roughness²
//! D(h)   = α² / (π ((n·h)² (α² − 1) + 1)²)                   GGX / Trowbridge–Reitz
//! V      = G2 / (4 |n·o| |n·i|)                             Smith, height-correlated G2
//!        = 0.5 / (n·i √((n·o)²(1−α²)+α²) + n·o √((n·i)²(1−α²)+α²))
//! s      = (1 − |o·h|)⁵                                     Schlick weight
//! F      = F0 + (1 − F0) s,  F0 = mix(0.04, base_color, metallic)
//! f_spec = F D V
//! f_diff = (1 − metallic) (1 − F_d) base_color / π,  F_d = 0.04 + 0.96 s
//! f      = f_diff + f_spec
//! ```
//!
//! This is exactly `mix(dielectric_brdf, metal_brdf, metallic)` of the spec with
//! `dielectric_brdf = fresnel_mix(ior 1.5, diffuse, specular)` and
//! `metal_brdf = conductor_fresnel(base_color, specular)`: the specular terms of the two add up
//! to one Schlick Fresnel with the mixed F0, and the diffuse is weighted by (1 − F_d), the
//! *dielectric* (scalar, F0 = 0.04) Fresnel of the layer above it. (The spec's "implementation"
//! section writes (1 − F) with the mixed F0; the two agree for metallic ∈ {0, 1}.)
//!
//! Like the spec's model it is single scattering and is not exactly energy conserving: rough
//! GGX loses energy (no multiple-scattering term), and the (1 − F_d(o·h)) diffuse weight is a
//! per-direction approximation of a layer, so for a white dielectric seen at grazing angles the
//! albedo can exceed one (measured in `tests/shade.rs`). Cycles' Principled BSDF differs here
//! (albedo-scaled layering, multiple-scattering GGX); this is a known gap, not a bug.
//!
//! # Conventions
//!
//! `n` is the unit shading normal and must face `wo` (the caller flips a two-sided surfel's
//! normal toward the viewer); `wo` points away from the surface toward the viewer, `wi` toward
//! the light; both unit length. Everything below the horizon (n·wo ≤ 0 or n·wi ≤ 0) is zero:
//! reflection only.

use crate::scene::material::{Material, DIELECTRIC_F0, MIN_ALPHA};
use glam::Vec3;
use std::f32::consts::PI;

/// Least probability of either lobe when both are non-zero, so that a poor albedo guess never
/// starves a lobe (variance, not bias: the mixture pdf stays positive wherever f is).
const MIN_LOBE_PROB: f32 = 0.05;
/// Rec.709 luminance weights (scene-linear), for the lobe-selection heuristic.
const LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// A direction drawn by [`sample`]: `weight` = f·cosθi / pdf, `pdf` = the mixture density
/// ([`pdf`]) in solid angle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub wi: Vec3,
    pub weight: [f32; 3],
    pub pdf: f32,
}

/// The two lobes of f (without the cosine), evaluated separately: `diffuse + specular = f`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lobes {
    pub diffuse: [f32; 3],
    pub specular: [f32; 3],
}

/// An orthonormal frame with `n` as local +z (Duff et al. 2017, "Building an orthonormal basis,
/// revisited": branchless and continuous except across n.z = 0's sign).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub t: Vec3,
    pub b: Vec3,
    pub n: Vec3,
}

impl Frame {
    pub fn new(n: Vec3) -> Frame {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        Frame {
            t: Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
            b: Vec3::new(b, sign + n.y * n.y * a, -n.y),
            n,
        }
    }

    pub fn to_local(self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.t), v.dot(self.b), v.dot(self.n))
    }

    pub fn to_world(self, v: Vec3) -> Vec3 {
        self.t * v.x + self.b * v.y + self.n * v.z
    }
}

/// GGX normal distribution D(h) for cos θh = n·h.
pub fn ggx_d(cos_h: f32, alpha: f32) -> f32 {
    if cos_h <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let t = cos_h * cos_h * (a2 - 1.0) + 1.0;
    a2 / (PI * t * t)
}

/// Smith G1 for GGX (the masking of one direction), cos θ = n·v > 0:
/// 2 cosθ / (cosθ + √(α² + (1 − α²) cos²θ)).
pub fn smith_g1(cos: f32, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    2.0 * cos / (cos + (a2 + (1.0 - a2) * cos * cos).sqrt())
}

/// Height-correlated Smith visibility V = G2 / (4 (n·o)(n·i)), both cosines > 0.
pub fn smith_v_height_correlated(cos_o: f32, cos_i: f32, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    let lo = cos_i * (cos_o * cos_o * (1.0 - a2) + a2).sqrt();
    let li = cos_o * (cos_i * cos_i * (1.0 - a2) + a2).sqrt();
    0.5 / (lo + li)
}

/// Schlick's weight (1 − cos)⁵.
fn schlick_weight(cos: f32) -> f32 {
    let m = (1.0 - cos).clamp(0.0, 1.0);
    let m2 = m * m;
    m2 * m2 * m
}

fn luminance(c: [f32; 3]) -> f32 {
    c[0] * LUMA[0] + c[1] * LUMA[1] + c[2] * LUMA[2]
}

/// Both lobes in the local frame (n = +z); zero below the horizon.
fn lobes_local(wo: Vec3, wi: Vec3, m: &Material) -> Lobes {
    let zero = Lobes {
        diffuse: [0.0; 3],
        specular: [0.0; 3],
    };
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return zero;
    }
    let h = (wo + wi).normalize_or_zero();
    if h == Vec3::ZERO {
        return zero;
    }
    let alpha = m.alpha();
    let s = schlick_weight(wo.dot(h).abs());
    let dv = ggx_d(h.z, alpha) * smith_v_height_correlated(wo.z, wi.z, alpha);
    let f0 = m.f0();
    let f_d = DIELECTRIC_F0 + (1.0 - DIELECTRIC_F0) * s;
    let diffuse_scale = (1.0 - f_d) / PI;
    let diff = m.diffuse_color();
    Lobes {
        diffuse: diff.map(|c| c * diffuse_scale),
        specular: f0.map(|f| (f + (1.0 - f) * s) * dv),
    }
}

/// f(wo, wi) split into its diffuse and specular lobes (no cosine).
pub fn eval_lobes(n: Vec3, wo: Vec3, wi: Vec3, m: &Material) -> Lobes {
    let frame = Frame::new(n);
    lobes_local(frame.to_local(wo), frame.to_local(wi), m)
}

/// The BRDF value f(wo, wi) alone, without the cosine.
pub fn eval_f(n: Vec3, wo: Vec3, wi: Vec3, m: &Material) -> [f32; 3] {
    let l = eval_lobes(n, wo, wi, m);
    [0, 1, 2].map(|c| l.diffuse[c] + l.specular[c])
}

/// f(wo, wi) · cos θi: the integrand of the rendering equation (eq. rendering-equation) per
/// unit incident radiance.
pub fn eval_f_cos(n: Vec3, wo: Vec3, wi: Vec3, m: &Material) -> [f32; 3] {
    let cos_i = n.dot(wi);
    if cos_i <= 0.0 {
        return [0.0; 3];
    }
    eval_f(n, wo, wi, m).map(|v| v * cos_i)
}

/// dL/d(material) for one material: the adjoint [`eval_f_cos_grad`] returns, and what path
/// replay sends to a surface record's mean material.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MaterialGrad {
    pub base_color: [f32; 3],
    pub metallic: f32,
    pub roughness: f32,
}

impl MaterialGrad {
    /// Adds `o` field by field.
    pub fn add(&mut self, o: &MaterialGrad) {
        for c in 0..3 {
            self.base_color[c] += o.base_color[c];
        }
        self.metallic += o.metallic;
        self.roughness += o.roughness;
    }
}

/// The adjoint of [`eval_f_cos`] in the material: given `g` = dL/d(f·cos θi) (three
/// channels), dL/d(base colour, metallic, roughness). Directions and normal are held fixed.
///
/// With F0_c = 0.04 (1 − m) + a_c m, F_c = F0_c + (1 − F0_c) s, k = (1 − F_d)/π and DV the
/// specular D·V (module doc), f_c = (1 − m) a_c k + F_c DV, so
///
/// ```text
/// ∂f_c/∂a_c = (1 − m) k + m (1 − s) DV
/// ∂f_c/∂m   = −a_c k + (a_c − 0.04) (1 − s) DV
/// ∂f_c/∂r   = F_c ∂(DV)/∂α · ∂α/∂r,   ∂α/∂r = 2r where r² > MIN_ALPHA, else 0 (the clamp)
/// ∂D/∂α = 2α/(π q²) · (1 − 2α² c²/q),  q = c² (α² − 1) + 1, c = n·h
/// ∂V/∂α = −2V² (cos_i ∂A/∂α + cos_o ∂B/∂α),  A = √(cos_o²(1 − α²) + α²), ∂A/∂α = α (1 − cos_o²)/A
/// ```
///
/// (B likewise with cos_i), each times cos θi. Zero wherever `eval_f_cos` is the constant zero.
pub fn eval_f_cos_grad(n: Vec3, wo: Vec3, wi: Vec3, m: &Material, g: [f32; 3]) -> MaterialGrad {
    let zero = MaterialGrad::default();
    let cos_i = n.dot(wi);
    let frame = Frame::new(n);
    let (wo, wi) = (frame.to_local(wo), frame.to_local(wi));
    if cos_i <= 0.0 || wo.z <= 0.0 || wi.z <= 0.0 {
        return zero;
    }
    let h = (wo + wi).normalize_or_zero();
    if h == Vec3::ZERO {
        return zero;
    }
    let alpha = m.alpha();
    let s = schlick_weight(wo.dot(h).abs());
    let d = ggx_d(h.z, alpha);
    let v = smith_v_height_correlated(wo.z, wi.z, alpha);
    let dv = d * v;
    let k = (1.0 - (DIELECTRIC_F0 + (1.0 - DIELECTRIC_F0) * s)) / PI;
    // d(DV)/dα.
    let a2 = alpha * alpha;
    let c2 = h.z * h.z;
    let q = c2 * (a2 - 1.0) + 1.0;
    let dd = if h.z > 0.0 {
        2.0 * alpha / (PI * q * q) * (1.0 - 2.0 * a2 * c2 / q)
    } else {
        0.0
    };
    let big_a = (wo.z * wo.z * (1.0 - a2) + a2).sqrt();
    let big_b = (wi.z * wi.z * (1.0 - a2) + a2).sqrt();
    let da = alpha * (1.0 - wo.z * wo.z) / big_a;
    let db = alpha * (1.0 - wi.z * wi.z) / big_b;
    let dvv = -2.0 * v * v * (wi.z * da + wo.z * db);
    let ddv = dd * v + d * dvv;
    let r = m.roughness;
    let dalpha_dr = if r * r > MIN_ALPHA { 2.0 * r } else { 0.0 };
    let mm = m.metallic;
    let f0 = m.f0();
    let mut out = zero;
    for c in 0..3 {
        let gc = g[c] * cos_i;
        let a = m.base_color[c];
        let fc = f0[c] + (1.0 - f0[c]) * s;
        out.base_color[c] = gc * ((1.0 - mm) * k + mm * (1.0 - s) * dv);
        out.metallic += gc * (-a * k + (a - DIELECTRIC_F0) * (1.0 - s) * dv);
        out.roughness += gc * fc * ddv * dalpha_dr;
    }
    out
}

/// Probability of drawing from the GGX lobe for a view at cos θo: the Schlick estimate of the
/// specular albedo against the diffuse albedo left under it (luminance), each lobe kept at
/// least `MIN_LOBE_PROB` when the diffuse lobe is present at all.
pub fn specular_probability(cos_o: f32, m: &Material) -> f32 {
    let diffuse = luminance(m.diffuse_color());
    if diffuse <= 0.0 {
        return 1.0;
    }
    let s = schlick_weight(cos_o);
    let spec = luminance(m.f0().map(|f| f + (1.0 - f) * s));
    let diff = diffuse * (1.0 - (DIELECTRIC_F0 + (1.0 - DIELECTRIC_F0) * s));
    let p = spec / (spec + diff).max(f32::MIN_POSITIVE);
    p.clamp(MIN_LOBE_PROB, 1.0 - MIN_LOBE_PROB)
}

/// Density of the GGX visible normals reflected about h, in solid angle of wi (Heitz 2018):
/// D_wo(h) / (4 wo·h) = G1(wo) D(h) / (4 n·wo). Local frame; zero below the horizon.
fn pdf_vndf_reflected(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return 0.0;
    }
    let h = (wo + wi).normalize_or_zero();
    if h == Vec3::ZERO {
        return 0.0;
    }
    smith_g1(wo.z, alpha) * ggx_d(h.z, alpha) / (4.0 * wo.z)
}

fn pdf_local(wo: Vec3, wi: Vec3, m: &Material) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return 0.0;
    }
    let p_spec = specular_probability(wo.z, m);
    p_spec * pdf_vndf_reflected(wo, wi, m.alpha()) + (1.0 - p_spec) * wi.z / PI
}

/// The mixture density of [`sample`] in solid angle: p_spec · VNDF-reflected + (1 − p_spec) ·
/// cos θi / π. Zero below the horizon, where `sample` returns `None` instead of a direction.
pub fn pdf(n: Vec3, wo: Vec3, wi: Vec3, m: &Material) -> f32 {
    let frame = Frame::new(n);
    pdf_local(frame.to_local(wo), frame.to_local(wi), m)
}

/// A GGX visible normal for view `wo` (local, wo.z > 0), Heitz 2018, "Sampling the GGX
/// Distribution of Visible Normals" (JCGT 7(4)), isotropic α.
fn sample_vndf(wo: Vec3, alpha: f32, u: [f32; 2]) -> Vec3 {
    // Stretch the view to the hemisphere configuration (α = 1).
    let vh = Vec3::new(alpha * wo.x, alpha * wo.y, wo.z).normalize();
    let len2 = vh.x * vh.x + vh.y * vh.y;
    let t1 = if len2 > 0.0 {
        Vec3::new(-vh.y, vh.x, 0.0) / len2.sqrt()
    } else {
        Vec3::X
    };
    let t2 = vh.cross(t1);
    // A point on the projected disc, warped to the visible half.
    let r = u[0].sqrt();
    let phi = 2.0 * PI * u[1];
    let p1 = r * phi.cos();
    let s = 0.5 * (1.0 + vh.z);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * (r * phi.sin());
    let nh = t1 * p1 + t2 * p2 + vh * (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
    // Unstretch.
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(0.0)).normalize()
}

/// Cosine-weighted hemisphere (Malley): a uniform disc point lifted to the hemisphere, local
/// frame (n = +z), density cos θ / π.
fn cosine_local(u: [f32; 2]) -> Vec3 {
    let r = u[0].sqrt();
    let phi = 2.0 * PI * u[1];
    Vec3::new(r * phi.cos(), r * phi.sin(), (1.0 - u[0]).max(0.0).sqrt())
}

/// A cosine-weighted direction about `n` and its density cos θ / π (the naive estimator's only
/// strategy); `None` for the measure-zero directions at the horizon.
pub fn sample_cosine(n: Vec3, u: [f32; 2]) -> Option<(Vec3, f32)> {
    let frame = Frame::new(n);
    let wi = frame.to_world(cosine_local(u)).normalize();
    let cos = n.dot(wi);
    (cos > 0.0).then_some((wi, cos / PI))
}

/// Draws wi from the cosine / GGX-VNDF mixture: `u_lobe` picks the lobe (GGX when
/// `u_lobe < specular_probability`), `u` drives the chosen lobe. `None` when wo is below the
/// horizon or the reflected direction falls below it (the VNDF's G2/G1 loss); the estimator
/// then adds nothing, which keeps it unbiased since [`pdf`] has no mass there.
pub fn sample(n: Vec3, wo: Vec3, m: &Material, u: [f32; 2], u_lobe: f32) -> Option<Sample> {
    let frame = Frame::new(n);
    let wo_l = frame.to_local(wo);
    if wo_l.z <= 0.0 {
        return None;
    }
    let wi_l = if u_lobe < specular_probability(wo_l.z, m) {
        let h = sample_vndf(wo_l, m.alpha(), u);
        2.0 * wo_l.dot(h) * h - wo_l
    } else {
        cosine_local(u)
    };
    if wi_l.z <= 0.0 {
        return None;
    }
    // Evaluate at the direction handed back, through the same frame as `pdf` and `eval_f`:
    // the weight is then exactly their ratio, not one off by the round trip's rounding.
    let wi = frame.to_world(wi_l).normalize();
    let wi_l = frame.to_local(wi);
    if wi_l.z <= 0.0 {
        return None;
    }
    let pdf = pdf_local(wo_l, wi_l, m);
    if pdf <= 0.0 || !pdf.is_finite() {
        return None;
    }
    let l = lobes_local(wo_l, wi_l, m);
    let weight = [0, 1, 2].map(|c| (l.diffuse[c] + l.specular[c]) * wi_l.z / pdf);
    Some(Sample { wi, weight, pdf })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_is_orthonormal_and_round_trips() {
        for n in [
            Vec3::Z,
            -Vec3::Z,
            Vec3::X,
            Vec3::new(0.3, -0.5, 0.8).normalize(),
            Vec3::new(-0.1, 0.2, -0.97).normalize(),
        ] {
            let f = Frame::new(n);
            assert!(f.t.dot(f.b).abs() < 1e-6 && f.t.dot(n).abs() < 1e-6);
            assert!((f.t.cross(f.b) - n).length() < 1e-5, "right-handed");
            let v = Vec3::new(0.2, 0.7, -0.4);
            assert!((f.to_world(f.to_local(v)) - v).length() < 1e-6);
        }
    }

    #[test]
    fn roughness_zero_stays_finite() {
        let m = Material {
            base_color: [1.0; 3],
            metallic: 1.0,
            roughness: 0.0,
        };
        let wo = Vec3::new(0.3, 0.0, 0.95).normalize();
        let mirror = Vec3::new(-wo.x, -wo.y, wo.z);
        let f = eval_f(Vec3::Z, wo, mirror, &m);
        assert!(f.iter().all(|v| v.is_finite() && *v > 0.0), "{f:?}");
        let s = sample(Vec3::Z, wo, &m, [0.3, 0.6], 0.5).expect("a mirror sample");
        assert!((s.wi - mirror).length() < 1e-2);
        assert!(s.weight.iter().all(|w| w.is_finite()));
    }

    #[test]
    fn below_horizon_is_zero() {
        let m = Material {
            base_color: [0.5; 3],
            metallic: 0.0,
            roughness: 0.5,
        };
        let up = Vec3::new(0.0, 0.6, 0.8);
        let down = Vec3::new(0.0, 0.6, -0.8);
        assert_eq!(eval_f(Vec3::Z, up, down, &m), [0.0; 3]);
        assert_eq!(pdf(Vec3::Z, down, up, &m), 0.0);
        assert!(sample(Vec3::Z, down, &m, [0.5, 0.5], 0.9).is_none());
    }
}
