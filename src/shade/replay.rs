//! Path replay (Vicini, Speierer and Jakob 2021, "Path Replay Backpropagation"), for the
//! one-bounce estimator and its deeper vertices (below): what one path sample decided, kept so
//! that its radiance can be re-evaluated with other materials and environment texels, and
//! differentiated.
//!
//! # A path sample as a sum of terms
//!
//! [`super::estimator::Estimator::replay`] walks the path exactly as the forward estimator does
//! (the forward estimator *is* that walk: `radiance` sums the replay's terms) and records every
//! decision that depends on the geometry or on the sampling distributions: the camera and
//! continuation rays with their surface records (hits, weights w_j, mean positions and normals),
//! the sampled directions, the densities, the MIS weights and the visibilities. What is left is
//! a sum of at most [`MAX_TERMS`] terms, each
//!
//! ```text
//! term = s · f₁(m₁) ⊙ f₂(m₂) ⊙ E(ω)
//! ```
//!
//! with `s` a frozen scalar (coverage, transmittance, MIS weight over density), `f₁` the BRDF
//! times cosine at the primary record for its (wo, wi) (or 1), `f₂` the same at the secondary
//! record (or 1), and `E(ω)` the environment's bilinear lookup. The terms of one sample:
//!
//! | term | s | f₁ | f₂ | ω |
//! |---|---|---|---|---|
//! | seen through the primary record | 1 − α₁ | | | camera ray |
//! | primary next-event | α₁ T w_nee / p_env | (wo₁, ω_nee) | | ω_nee |
//! | continuation escapes | α₁ (1 − α₂) w_bsdf / p_bsdf | (wo₁, ω_b) | | ω_b |
//! | secondary next-event, k = 1, 2 | α₁ α₂ T_k / (2 p_bsdf p_env,k) | (wo₁, ω_b) | (wo₂, ω_k) | ω_k |
//!
//! With the decisions held fixed (the replay), the radiance is exactly linear in the
//! environment's texels and, since f is linear in the base colour (F0 = mix(0.04, a, m) and the
//! diffuse lobe (1 − m) a), linear in each record's mean base colour; `tests/replay.rs` checks
//! both.
//!
//! # The adjoint
//!
//! For an upstream gradient ȳ = dL/d(radiance), a term sends
//! `ȳ ⊙ s f₁ f₂` to the four texels of E's bilinear footprint (the lookup's own weights,
//! [`EnvMap::texel_weights`], so forward and adjoint read the same texels at the poles and across
//! the seam), `ȳ ⊙ s f₂ E` through [`brdf::eval_f_cos_grad`] to the primary record's mean
//! material, and `ȳ ⊙ s f₁ E` to the secondary record's. A record's mean material is
//! Σ w_j m_j / Σ w_j with the w_j fixed by the geometry, so [`PathReplay::record_grads`] hands
//! [`crate::trace::Placed::composite_backward`] the chain rule to every hit surfel.
//!
//! # Deeper vertices (not in the paper)
//!
//! The paper's estimator stops at the secondary record, so light that reaches a surface after
//! two or more diffuse bounces is missing: in a room of white walls and a plain floor that is
//! a large share of what lights the shadows (the plain-family sunroom: the true materials
//! through the one-bounce estimator relight at 23.85 dB against Cycles' four bounces), and
//! stage 3 puts it back the only way it can, by brightening the base colour. With
//! [`super::estimator::Estimator::bounces`] = B > 1 the path goes on from the secondary
//! record by B − 1 BSDF continuations, and each record met adds one next-event term
//!
//! ```text
//! term = s · f₁(m₁) ⊙ f₂(m₂) ⊙ tail ⊙ E(ω),   tail = Π f_j cos θ_j (frozen)
//! ```
//!
//! where `f₂` is now the secondary record's factor toward the continuation (not toward a
//! next-event direction) and `tail` the factors at the records past it, frozen at the
//! materials the walk saw: the radiance stays linear in the texels and in the first two
//! records' materials, and the adjoint is the same with `ȳ ⊙ tail` for `ȳ`. The materials of
//! the third and later records get no gradient from such a term (they are "detached", as in
//! inverse renderers that hold the deep indirect light fixed); they get their own from the
//! paths on which they are the primary or the secondary record. The value is unbiased; the
//! gradient misses only those detached derivatives, a small share (each is damped by two
//! albedos and two cosines) that no other parameter would otherwise absorb.
//!
//! Holding the densities and MIS weights fixed is what PRB and Mitsuba's `prb.py` do with
//! detached sampling: the combined estimator Σᵢ wᵢ f/pᵢ with Σᵢ wᵢ = 1 estimates ∫ f for any
//! weights, so differentiating only f (weights and densities frozen at the current parameters)
//! estimates ∫ ∂f without bias. Nothing is taped: a sample's replay is a fixed-size value,
//! recomputed by re-tracing the same Sobol sample, so memory does not grow with spp.

use super::brdf::{self, MaterialGrad};
use super::envmap::EnvMap;
use crate::scene::Material;
use crate::trace::{RecordGrad, SurfaceRecord, TraceRay};
use glam::Vec3;

/// Indirect bounces a path sample may take at most ([`super::estimator::Estimator::bounces`];
/// the paper's estimator takes one).
pub const MAX_BOUNCES: u32 = 4;

/// `bounces` if an estimator can take it (1 to [`MAX_BOUNCES`]), else a usage error naming
/// `option`, where it came from. The one check of the bound for every input that sets it.
pub fn check_bounces(bounces: u32, option: &str) -> crate::Result<u32> {
    if (1..=MAX_BOUNCES).contains(&bounces) {
        Ok(bounces)
    } else {
        Err(crate::Error::Usage(format!(
            "{option}: expected 1 to {MAX_BOUNCES} indirect bounces, found {bounces}"
        )))
    }
}

/// Terms one path sample has at most (see the module table): the paper's five, and one
/// next-event term per vertex past the secondary record.
pub const MAX_TERMS: usize = 5 + (MAX_BOUNCES as usize - 1);

/// One BRDF factor f(wo, wi)·cos θi of a term, at a record's shading point, with its value at
/// the replayed materials.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounce {
    /// Unit shading normal, facing `wo`.
    pub n: Vec3,
    pub wo: Vec3,
    pub wi: Vec3,
    /// f·cos θi at the record's mean material when the path was walked.
    pub f: [f32; 3],
}

impl Bounce {
    fn eval(&self, m: &Material) -> [f32; 3] {
        brdf::eval_f_cos(self.n, self.wo, self.wi, m)
    }
}

/// `scale · f₁ ⊙ f₂ ⊙ E(env_dir)` (module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Term {
    pub scale: f32,
    /// The factor at the primary record.
    pub primary: Option<Bounce>,
    /// The factor at the secondary record (only together with `primary`).
    pub secondary: Option<Bounce>,
    /// The frozen product of the f·cos θi factors past the secondary record (1 for the
    /// paper's terms; their densities and coverages are in `scale`). Its materials are
    /// detached: see the module doc's "Deeper vertices".
    pub tail: [f32; 3],
    /// Where the environment is looked up (world direction).
    pub env_dir: Vec3,
}

const NO_MATERIAL: Material = Material {
    base_color: [0.0; 3],
    metallic: 0.0,
    roughness: 0.0,
};

const NO_TERM: Term = Term {
    scale: 0.0,
    primary: None,
    secondary: None,
    tail: [1.0; 3],
    env_dir: Vec3::ZERO,
};

/// Everything one path sample decided (module doc), as the forward pass walked it.
#[derive(Clone, Copy, Debug)]
pub struct PathReplay {
    /// The camera ray and its composited record.
    pub camera: TraceRay,
    pub record: SurfaceRecord,
    /// The BSDF continuation's ray and its record, when one was traced.
    pub continuation: Option<(TraceRay, SurfaceRecord)>,
    /// The mean materials of the primary and secondary records (zero when not shaded).
    pub materials: [Material; 2],
    /// Rays traced (composite and visibility queries).
    pub rays: u32,
    terms: [Term; MAX_TERMS],
    len: usize,
}

#[inline]
fn f_or_one(b: &Option<Bounce>) -> [f32; 3] {
    b.as_ref().map_or([1.0; 3], |b| b.f)
}

impl PathReplay {
    pub(crate) fn new(camera: TraceRay, record: SurfaceRecord) -> PathReplay {
        PathReplay {
            camera,
            record,
            continuation: None,
            materials: [NO_MATERIAL; 2],
            rays: 0,
            terms: [NO_TERM; MAX_TERMS],
            len: 0,
        }
    }

    /// Adds a term; a zero scale adds nothing and is dropped (so a path that contributes
    /// nothing has no terms and receives no gradient).
    pub(crate) fn push(&mut self, t: Term) {
        if t.scale != 0.0 {
            assert!(
                self.len < MAX_TERMS,
                "a path sample has at most {MAX_TERMS} terms"
            );
            self.terms[self.len] = t;
            self.len += 1;
        }
    }

    pub fn terms(&self) -> &[Term] {
        &self.terms[..self.len]
    }

    /// The sample's radiance, as the forward pass computed it.
    pub fn radiance(&self, env: &EnvMap) -> [f32; 3] {
        let mut out = [0.0f32; 3];
        for t in self.terms() {
            let e = env.eval(t.env_dir);
            let (f1, f2) = (f_or_one(&t.primary), f_or_one(&t.secondary));
            for c in 0..3 {
                out[c] += t.scale * f1[c] * f2[c] * t.tail[c] * e[c];
            }
        }
        out
    }

    /// The radiance with the decisions replayed but the records' mean materials replaced by
    /// `materials` and the texels by `env`'s (its sampling distribution is not used): the
    /// function [`PathReplay::adjoint`] differentiates.
    pub fn radiance_with(&self, materials: &[Material; 2], env: &EnvMap) -> [f32; 3] {
        let mut out = [0.0f32; 3];
        for t in self.terms() {
            let e = env.eval(t.env_dir);
            let f1 = t.primary.map_or([1.0; 3], |b| b.eval(&materials[0]));
            let f2 = t.secondary.map_or([1.0; 3], |b| b.eval(&materials[1]));
            for c in 0..3 {
                out[c] += t.scale * f1[c] * f2[c] * t.tail[c] * e[c];
            }
        }
        out
    }

    /// The adjoint of [`PathReplay::radiance_with`] at the replayed materials and `env`'s
    /// texels, for dL/d(radiance) = `ybar`: returns dL/d(mean material) of the primary and the
    /// secondary record and calls `texel(index, dL/d texel)` for every texel a term reads
    /// (index `y · width + x`, as [`EnvMap::texel_weights`]; a texel may be reported more than
    /// once).
    pub fn adjoint(
        &self,
        env: &EnvMap,
        ybar: [f32; 3],
        mut texel: impl FnMut(usize, [f32; 3]),
    ) -> [MaterialGrad; 2] {
        let mut out = [MaterialGrad::default(); 2];
        for t in self.terms() {
            let e = env.eval(t.env_dir);
            let (f1, f2) = (f_or_one(&t.primary), f_or_one(&t.secondary));
            let y = [0, 1, 2].map(|c| ybar[c] * t.tail[c]);
            let ge = [0, 1, 2].map(|c| y[c] * t.scale * f1[c] * f2[c]);
            if ge.iter().any(|&g| g != 0.0) {
                for (i, w) in env.texel_weights(t.env_dir) {
                    if w != 0.0 {
                        texel(i, ge.map(|g| g * w));
                    }
                }
            }
            if let Some(b) = &t.primary {
                let g = [0, 1, 2].map(|c| y[c] * t.scale * f2[c] * e[c]);
                out[0].add(&brdf::eval_f_cos_grad(
                    b.n,
                    b.wo,
                    b.wi,
                    &self.materials[0],
                    g,
                ));
            }
            if let Some(b) = &t.secondary {
                let g = [0, 1, 2].map(|c| y[c] * t.scale * f1[c] * e[c]);
                out[1].add(&brdf::eval_f_cos_grad(
                    b.n,
                    b.wo,
                    b.wi,
                    &self.materials[1],
                    g,
                ));
            }
        }
        out
    }

    /// The records' gradients for [`crate::trace::Placed::composite_backward`], from the mean
    /// materials' gradients [`PathReplay::adjoint`] returned: the camera ray's, then the
    /// continuation's (when traced and non-zero). Geometry is fixed in path replay, so only the
    /// material sums receive gradient (the Σw share of the chain rule is dropped).
    pub fn record_grads(&self, g: &[MaterialGrad; 2]) -> [Option<(TraceRay, RecordGrad)>; 2] {
        let one = |rec: &SurfaceRecord, g: &MaterialGrad| {
            let mut r = rec.mean_material_grad(g.base_color, g.metallic, g.roughness);
            r.alpha = 0.0;
            r
        };
        let primary = Some((self.camera, one(&self.record, &g[0]))).filter(|(_, r)| !r.is_zero());
        let secondary = self
            .continuation
            .map(|(ray, rec)| (ray, one(&rec, &g[1])))
            .filter(|(_, r)| !r.is_zero());
        [primary, secondary]
    }
}
