//! The one-bounce radiance estimator (paper § Differentiable one-bounce path tracing,
//! eqs. rendering-equation and path-estimator) and the forward renderer built on it.
//!
//! **One path sample** of a camera ray: composite the primary surface record (eq.
//! surface-record). No hit: the environment along the ray, `env.eval(dir)` exactly, so the
//! background is the one Cycles' world shading gives. Otherwise the record (mean position,
//! renormalised normal facing the ray, weighted-mean material) is shaded with
//! (a) one environment next-event sample, visibility by [`Placed::transmittance`];
//! (b) one BSDF continuation (cosine / GGX-VNDF mixture, [`brdf::sample`]) traced with
//! [`Placed::composite`]: where it escapes it sees the environment, where it meets a secondary
//! record that record is shaded by two environment samples (next-event only, with visibility,
//! no further bounce). (a) and the escaping part of (b) estimate the same integral and are
//! combined by the power heuristic (β = 2). This is the paper's "one primary environment
//! next-event sample, one BSDF continuation, at most one secondary hit, and two environment
//! samples at that hit" (§ Experimental setup).
//!
//! **Partial coverage.** Surfels are semi-transparent, so a composited record has an alpha
//! `α ∈ [0, 1)`. A camera ray returns `L = α · L_surface + (1 − α) · E(dir)`: the surface seen
//! through a fraction α of the pixel ray, the environment through the rest. The continuation
//! uses the same rule for its secondary record: it adds `α₂ · L_secondary + (1 − α₂) · w · E(ωᵢ)`,
//! where `(1 − α₂)` is the continuation's transmittance, the quantity the next-event sample's
//! visibility also estimates; so the two MIS strategies estimate the same visibility-weighted
//! integral and the combination stays unbiased. Every term is linear in the environment texels
//! and, for a diffuse scene, in the base colours (docs/design.md §5).
//!
//! **Self-intersection.** Surfels are overlapping discs tangent to the surface, and the
//! composited position is a mean of hits on several of them, so a ray leaving it meets the
//! neighbours of the very surfels it was composited from: on a surface of radius R, the plane of
//! a neighbour at distance b lies b²/(2R) above the point, and a ray leaving along the normal
//! crosses it b away from that neighbour's centre, where its opacity is still α·exp(−½ b²/σ²).
//! Secondary rays therefore start at `x + ε n` with `t_min = ε`, and ε is tied to the surfels'
//! size, not only to the scene's: [`self_hit_epsilon`] = [`EPS_SCALE`] × the median surfel scale
//! σ (at least [`EPS_REL`] × the scene's diagonal, for f32 precision far from the origin). With
//! ε = 0.3 σ every neighbour within the 3σ support is cleared on surfaces of radius ≥ 15 σ
//! ((3σ)²/(2·15σ) = 0.3σ); a surfelized scene at 1 cm spacing gets ε = 3 mm, below the scale of
//! contact-shadow detail that such a scene resolves anyway.
//!
//! **Replay.** Every random number comes from the Sobol [`Sampler`] of the pixel, indexed by the
//! path's sample index and a fixed dimension ([`dim`]), so a path is a pure function of
//! (pixel, sample index, seed) and can be replayed exactly.

use super::brdf;
use super::envmap::EnvMap;
use super::replay::{Bounce, PathReplay, Term, MAX_BOUNCES};
use super::sobol::Sampler;
use crate::scene::Material;
use crate::scene::{Camera, Scene, State};
use crate::trace::{Placed, SurfaceRecord, TraceRay, WeightedHit};
use glam::Vec3;

/// Sobol dimensions of one path sample. Fixed, so a path replays from (pixel, sample, seed).
///
/// | dims | use |
/// |---|---|
/// | 0–1 | pixel position (filter importance sample) |
/// | 2–3 | primary environment next-event direction |
/// | 4 | primary BSDF lobe choice |
/// | 5–6 | primary BSDF direction |
/// | 7–8 | first environment sample at the secondary hit |
/// | 9–10 | second environment sample at the secondary hit |
pub mod dim {
    pub const PIXEL: u32 = 0;
    pub const ENV_NEE: u32 = 2;
    pub const LOBE: u32 = 4;
    pub const BSDF: u32 = 5;
    pub const SECONDARY_ENV: [u32; 2] = [7, 9];
    /// Dimensions used per path sample by the paper's one-bounce estimator.
    pub const COUNT: u32 = 11;
    /// Dimensions each vertex past the secondary record draws, from `COUNT + PER_DEEPER · j`:
    /// lobe choice, BSDF direction (2), next-event direction at the record met (2).
    pub const PER_DEEPER: u32 = 5;
}

/// Secondary-ray offset per unit of median surfel scale (see the module docs).
pub const EPS_SCALE: f32 = 0.3;
/// Least secondary-ray offset relative to the scene's bounding-box diagonal: f32 positions
/// ~1e-7 relative, so this keeps the offset well above rounding.
pub const EPS_REL: f32 = 1e-5;

/// The secondary-ray offset ε for a scene in a placement (see the module docs).
pub fn self_hit_epsilon(scene: &Scene, state: &State) -> f32 {
    let mut scales: Vec<f32> = scene
        .components
        .iter()
        .flat_map(|c| c.surfels.scale.iter().map(|s| s[0].max(s[1])))
        .filter(|s| s.is_finite())
        .collect();
    let median = if scales.is_empty() {
        0.0
    } else {
        let mid = scales.len() / 2;
        *scales.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    let diag = scene
        .bounds_in_state(state)
        .map(|(lo, hi)| (Vec3::from_array(hi) - Vec3::from_array(lo)).length())
        .filter(|d| d.is_finite() && *d > 0.0)
        .unwrap_or(1.0);
    (EPS_SCALE * median).max(EPS_REL * diag)
}

/// Cycles' default pixel filter width (Blackman–Harris), in pixels.
pub const DEFAULT_FILTER_WIDTH: f32 = 1.5;

/// What one camera-ray path sample returns.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PathSample {
    /// Radiance, scene-linear Rec.709.
    pub radiance: [f32; 3],
    /// The primary record (eq. surface-record).
    pub record: SurfaceRecord,
    /// Rays traced (composite and visibility queries).
    pub rays: u32,
}

/// Which sampling strategies a path sample uses.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "snake_case")]
pub enum Strategy {
    /// The paper's: environment next-event estimation and a BSDF continuation combined by MIS at
    /// the primary record, two next-event samples at the secondary record (module doc).
    #[default]
    Full,
    /// The paper's Table 4 baseline: no next-event estimation and no MIS. The primary record
    /// draws one cosine-hemisphere continuation; where it escapes it sees the environment,
    /// where it meets a secondary record that record draws one more cosine-hemisphere direction
    /// and sees the environment through its transmittance. Unbiased, only noisier.
    Naive,
    /// No re-tracing (a ReCap-like baseline of `lightfuse evaluate`): the primary record lit by
    /// the environment as if nothing else were in the scene. The same next-event sample and
    /// BSDF sample as [`Strategy::Full`], combined by the same MIS weights, but no visibility
    /// ray and no continuation ray: every direction sees the environment (no shadows, no
    /// inter-reflection). Camera rays still composite the scene. An evaluation row, not a
    /// training choice (`lightfuse invert --estimator` does not offer it).
    #[value(skip)]
    Unshadowed,
}

/// The one-bounce estimator over one placed scene and one environment.
#[derive(Clone, Copy)]
pub struct Estimator<'a> {
    pub scene: &'a Placed<'a>,
    pub env: &'a EnvMap,
    /// Offset of secondary-ray origins along the normal, and their `t_min` (world units).
    pub eps: f32,
    pub strategy: Strategy,
    /// Indirect bounces ([`Strategy::Full`] only): 1 is the paper's one-bounce estimator;
    /// each more continues the path from the last record by one BSDF sample and shades the
    /// record it meets by one environment next-event sample (module doc, "Deeper vertices").
    /// Cycles' `max_bounces` counts the same way.
    pub bounces: u32,
}

/// Sample `index` of `sampler`: the Sobol dimensions one path sample draws ([`dim`]).
#[derive(Clone, Copy)]
struct Draw<'s> {
    sampler: &'s Sampler,
    index: u32,
}

impl Draw<'_> {
    #[inline]
    fn get(&self, d: u32) -> f32 {
        self.sampler.get(self.index, d)
    }

    #[inline]
    fn get_2d(&self, d: u32) -> [f32; 2] {
        self.sampler.get_2d(self.index, d)
    }
}

/// Power heuristic, β = 2 (Veach 1995), for a sample of density `a` against strategy `b`.
#[inline]
fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 && (a2 + b2).is_finite() {
        a2 / (a2 + b2)
    } else if a.is_infinite() {
        1.0
    } else {
        0.0
    }
}

#[inline]
fn add_scaled(acc: &mut [f32; 3], v: [f32; 3], s: f32) {
    for c in 0..3 {
        acc[c] += v[c] * s;
    }
}

/// A record's shading point: mean position, unit normal facing the ray, mean material.
#[derive(Clone, Copy)]
struct Shading {
    x: Vec3,
    n: Vec3,
    material: Material,
}

impl Shading {
    /// `None` when the normals cancel out (nothing to shade).
    fn of(record: &SurfaceRecord) -> Option<Shading> {
        let n = Vec3::from_array(record.unit_normal());
        if n == Vec3::ZERO || !n.is_finite() {
            return None;
        }
        Some(Shading {
            x: Vec3::from_array(record.mean_position()),
            n,
            material: Material {
                base_color: record.mean_base_color(),
                metallic: record.mean_metallic(),
                roughness: record.mean_roughness(),
            },
        })
    }
}

impl<'a> Estimator<'a> {
    /// The estimator with secondary-ray offset `eps` (usually [`self_hit_epsilon`]).
    pub fn new(scene: &'a Placed<'a>, env: &'a EnvMap, eps: f32) -> Self {
        Estimator {
            scene,
            env,
            eps,
            strategy: Strategy::Full,
            bounces: 1,
        }
    }

    /// The same estimator with other sampling strategies.
    pub fn with_strategy(self, strategy: Strategy) -> Self {
        Estimator { strategy, ..self }
    }

    /// The same estimator with `bounces` indirect bounces (1 to [`MAX_BOUNCES`]).
    pub fn with_bounces(self, bounces: u32) -> Self {
        assert!(
            (1..=MAX_BOUNCES).contains(&bounces),
            "bounces: 1 to {MAX_BOUNCES}, found {bounces}"
        );
        Estimator { bounces, ..self }
    }

    /// One path sample along the camera ray `origin + t dir` (`dir` unit length), drawing
    /// sample `index` of `sampler` (dimensions [`dim`]).
    pub fn radiance(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        sampler: &Sampler,
        index: u32,
    ) -> PathSample {
        let p = self.replay(origin, dir, sampler, index);
        PathSample {
            radiance: p.radiance(self.env),
            record: p.record,
            rays: p.rays,
        }
    }

    /// The path sample [`Estimator::radiance`] draws, as its decisions and terms
    /// ([`PathReplay`]): the forward pass and path replay are this one walk.
    pub fn replay(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        sampler: &Sampler,
        index: u32,
    ) -> PathReplay {
        let camera = TraceRay {
            origin,
            dir,
            t_min: 0.0,
            t_max: f32::INFINITY,
        };
        let record = self.scene.composite(origin, dir, 0.0, f32::INFINITY);
        let mut p = self.replay_from(camera, record, sampler, index);
        p.rays += 1;
        p
    }

    /// [`Estimator::replay`] from a camera ray whose record is already known (traced once and
    /// kept, with its materials current: geometry alone decides it); the rays counted are the
    /// ones traced here, without the camera ray.
    pub fn replay_from(
        &self,
        camera: TraceRay,
        record: SurfaceRecord,
        sampler: &Sampler,
        index: u32,
    ) -> PathReplay {
        self.walk(camera, record, sampler, index, None)
    }

    /// [`Estimator::replay_from`], also appending the continuation record's composited hits
    /// (surfel and weight w_j, front to back; none when no continuation was traced) to `hits`:
    /// what the secondary gradient of [`PathReplay::record_grads`] is scattered through
    /// ([`crate::trace::scatter_material_grad`]) without tracing the continuation again. The
    /// walk is the same (the same composite, only its visitor differs).
    pub fn replay_from_hits(
        &self,
        camera: TraceRay,
        record: SurfaceRecord,
        sampler: &Sampler,
        index: u32,
        hits: &mut Vec<WeightedHit>,
    ) -> PathReplay {
        self.walk(camera, record, sampler, index, Some(hits))
    }

    fn walk(
        &self,
        camera: TraceRay,
        record: SurfaceRecord,
        sampler: &Sampler,
        index: u32,
        hits: Option<&mut Vec<WeightedHit>>,
    ) -> PathReplay {
        let mut p = PathReplay::new(camera, record);
        let draw = Draw { sampler, index };
        let d = Vec3::from_array(camera.dir);
        let a = if record.hits == 0 {
            0.0
        } else {
            record.alpha.max(0.0)
        };
        // Seen through the record (or, with no hit, only the environment: exactly its value,
        // the world shading of Cycles).
        p.push(Term {
            scale: 1.0 - a,
            primary: None,
            secondary: None,
            tail: [1.0; 3],
            env_dir: d,
        });
        if a > 0.0 {
            if let Some(s) = Shading::of(&record) {
                p.materials[0] = s.material;
                match self.strategy {
                    Strategy::Full => self.shade_primary(&s, -d, a, draw, &mut p, hits),
                    Strategy::Naive => self.shade_naive(&s, -d, a, draw, &mut p, hits),
                    Strategy::Unshadowed => self.shade_unshadowed(&s, -d, a, draw, &mut p),
                }
            }
        }
        p
    }

    /// The continuation's record, its hits appended to `hits` when asked for.
    #[inline]
    fn continuation(&self, ray: &TraceRay, hits: Option<&mut Vec<WeightedHit>>) -> SurfaceRecord {
        let (o, d) = (ray.origin, ray.dir);
        match hits {
            Some(h) => self.scene.composite_hits(o, d, ray.t_min, ray.t_max, h),
            None => self.scene.composite(o, d, ray.t_min, ray.t_max),
        }
    }

    /// Visibility of the environment from `s` along `wi`: the transmittance of the offset ray.
    #[inline]
    fn visibility(&self, s: &Shading, wi: Vec3, rays: &mut u32) -> f32 {
        *rays += 1;
        let o = s.x + self.eps * s.n;
        self.scene
            .transmittance(o.to_array(), wi.to_array(), self.eps, f32::INFINITY)
    }

    /// The terms of the outgoing radiance towards `wo` of a primary record of coverage `a`
    /// (eq. rendering-equation with L_e = 0, estimated by eq. path-estimator with S = 1):
    /// (a) environment next-event estimation, MIS against the BSDF density; (b) one BSDF
    /// continuation, its escaped share MIS-weighted against the environment density and its
    /// secondary record shaded by next-event estimation only.
    fn shade_primary(
        &self,
        s: &Shading,
        wo: Vec3,
        a: f32,
        draw: Draw,
        p: &mut PathReplay,
        hits: Option<&mut Vec<WeightedHit>>,
    ) {
        // (a)
        if let Some((b, scale)) = self.env_nee(s, wo, draw.get_2d(dim::ENV_NEE), true, &mut p.rays)
        {
            p.push(Term {
                scale: a * scale,
                primary: Some(b),
                secondary: None,
                tail: [1.0; 3],
                env_dir: b.wi,
            });
        }
        // (b)
        let u_lobe = draw.get(dim::LOBE);
        let u_dir = draw.get_2d(dim::BSDF);
        let Some(bs) = brdf::sample(s.n, wo, &s.material, u_dir, u_lobe) else {
            return;
        };
        let o = s.x + self.eps * s.n;
        p.rays += 1;
        let ray = TraceRay {
            origin: o.to_array(),
            dir: bs.wi.to_array(),
            t_min: self.eps,
            t_max: f32::INFINITY,
        };
        let rec2 = self.continuation(&ray, hits);
        p.continuation = Some((ray, rec2));
        let first = Bounce {
            n: s.n,
            wo,
            wi: bs.wi,
            f: brdf::eval_f_cos(s.n, wo, bs.wi, &s.material),
        };
        let a2 = if rec2.hits == 0 {
            0.0
        } else {
            rec2.alpha.max(0.0)
        };
        let escaped = 1.0 - a2;
        if escaped > 0.0 {
            let w = power_heuristic(bs.pdf, self.env.pdf(bs.wi));
            p.push(Term {
                scale: a * escaped * w / bs.pdf,
                primary: Some(first),
                secondary: None,
                tail: [1.0; 3],
                env_dir: bs.wi,
            });
        }
        if a2 > 0.0 {
            let Some(s2) = Shading::of(&rec2) else {
                return;
            };
            p.materials[1] = s2.material;
            // The secondary record: the mean of two environment next-event samples with
            // visibility (no MIS: no BSDF strategy competes at the last vertex).
            let n = dim::SECONDARY_ENV.len() as f32;
            for d in dim::SECONDARY_ENV {
                if let Some((b2, scale)) =
                    self.env_nee(&s2, -bs.wi, draw.get_2d(d), false, &mut p.rays)
                {
                    p.push(Term {
                        scale: a * a2 / bs.pdf * scale / n,
                        primary: Some(first),
                        secondary: Some(b2),
                        tail: [1.0; 3],
                        env_dir: b2.wi,
                    });
                }
            }
            if self.bounces > 1 {
                self.shade_deeper(&s2, -bs.wi, a * a2 / bs.pdf, first, draw, p);
            }
        }
    }

    /// The vertices past the secondary record `s2` (reached along −`wo2`, with the frozen
    /// prefix `scale` and the primary factor `first`): `bounces − 1` more BSDF continuations,
    /// each record met shaded by one environment next-event sample with visibility (no MIS,
    /// as at the secondary record: escaped continuations are not counted, the next-event
    /// samples estimate the direct light at every vertex). The first continuation's factor at
    /// `s2` is the term's secondary factor (its material differentiated); the factors past it
    /// go into the frozen tail.
    fn shade_deeper(
        &self,
        s2: &Shading,
        wo2: Vec3,
        scale: f32,
        first: Bounce,
        draw: Draw,
        p: &mut PathReplay,
    ) {
        let mut at = *s2;
        let mut wo = wo2;
        let mut scale = scale;
        let mut second: Option<Bounce> = None;
        let mut tail = [1.0f32; 3];
        for j in 0..self.bounces - 1 {
            let base = dim::COUNT + dim::PER_DEEPER * j;
            let Some(bs) = brdf::sample(
                at.n,
                wo,
                &at.material,
                draw.get_2d(base + 1),
                draw.get(base),
            ) else {
                return;
            };
            let f = brdf::eval_f_cos(at.n, wo, bs.wi, &at.material);
            match second {
                None => {
                    second = Some(Bounce {
                        n: at.n,
                        wo,
                        wi: bs.wi,
                        f,
                    })
                }
                Some(_) => {
                    for c in 0..3 {
                        tail[c] *= f[c];
                    }
                }
            }
            let o = at.x + self.eps * at.n;
            p.rays += 1;
            let rec = self
                .scene
                .composite(o.to_array(), bs.wi.to_array(), self.eps, f32::INFINITY);
            let alpha = if rec.hits == 0 {
                0.0
            } else {
                rec.alpha.max(0.0)
            };
            if alpha <= 0.0 {
                return;
            }
            let Some(next) = Shading::of(&rec) else {
                return;
            };
            scale *= alpha / bs.pdf;
            if !scale.is_finite() || scale == 0.0 {
                return;
            }
            if let Some((b, s)) =
                self.env_nee(&next, -bs.wi, draw.get_2d(base + 3), false, &mut p.rays)
            {
                p.push(Term {
                    scale: scale * s,
                    primary: Some(first),
                    secondary: second,
                    tail: [0, 1, 2].map(|c| tail[c] * b.f[c]),
                    env_dir: b.wi,
                });
            }
            wo = -bs.wi;
            at = next;
        }
    }

    /// [`Strategy::Unshadowed`]'s terms: [`Estimator::shade_primary`]'s next-event sample and
    /// escaped continuation with visibility 1 and nothing traced.
    fn shade_unshadowed(&self, s: &Shading, wo: Vec3, a: f32, draw: Draw, p: &mut PathReplay) {
        let es = self.env.sample(draw.get_2d(dim::ENV_NEE));
        if es.pdf > 0.0 {
            let f = brdf::eval_f_cos(s.n, wo, es.dir, &s.material);
            if f.iter().any(|&v| v > 0.0) {
                let w = power_heuristic(es.pdf, brdf::pdf(s.n, wo, es.dir, &s.material));
                p.push(Term {
                    // Grouped as shade_primary's a · (T · w / pdf) with T = 1.
                    scale: a * (w / es.pdf),
                    primary: Some(Bounce {
                        n: s.n,
                        wo,
                        wi: es.dir,
                        f,
                    }),
                    secondary: None,
                    tail: [1.0; 3],
                    env_dir: es.dir,
                });
            }
        }
        let u_lobe = draw.get(dim::LOBE);
        let u_dir = draw.get_2d(dim::BSDF);
        if let Some(bs) = brdf::sample(s.n, wo, &s.material, u_dir, u_lobe) {
            let w = power_heuristic(bs.pdf, self.env.pdf(bs.wi));
            p.push(Term {
                scale: a * w / bs.pdf,
                primary: Some(Bounce {
                    n: s.n,
                    wo,
                    wi: bs.wi,
                    f: brdf::eval_f_cos(s.n, wo, bs.wi, &s.material),
                }),
                secondary: None,
                tail: [1.0; 3],
                env_dir: bs.wi,
            });
        }
    }

    /// [`Strategy::Naive`]'s terms for a primary record of coverage `a`: one cosine-hemisphere
    /// continuation (Sobol dimensions of the BSDF sample), and at a secondary record one more
    /// (the dimensions of its first environment sample) seen through its transmittance.
    fn shade_naive(
        &self,
        s: &Shading,
        wo: Vec3,
        a: f32,
        draw: Draw,
        p: &mut PathReplay,
        hits: Option<&mut Vec<WeightedHit>>,
    ) {
        let Some((wi, pdf)) = brdf::sample_cosine(s.n, draw.get_2d(dim::BSDF)) else {
            return;
        };
        let o = s.x + self.eps * s.n;
        p.rays += 1;
        let ray = TraceRay {
            origin: o.to_array(),
            dir: wi.to_array(),
            t_min: self.eps,
            t_max: f32::INFINITY,
        };
        let rec2 = self.continuation(&ray, hits);
        p.continuation = Some((ray, rec2));
        let first = Bounce {
            n: s.n,
            wo,
            wi,
            f: brdf::eval_f_cos(s.n, wo, wi, &s.material),
        };
        let a2 = if rec2.hits == 0 {
            0.0
        } else {
            rec2.alpha.max(0.0)
        };
        p.push(Term {
            scale: a * (1.0 - a2) / pdf,
            primary: Some(first),
            secondary: None,
            tail: [1.0; 3],
            env_dir: wi,
        });
        if a2 <= 0.0 {
            return;
        }
        let Some(s2) = Shading::of(&rec2) else {
            return;
        };
        p.materials[1] = s2.material;
        let u = draw.get_2d(dim::SECONDARY_ENV[0]);
        let Some((wi2, pdf2)) = brdf::sample_cosine(s2.n, u) else {
            return;
        };
        let f2 = brdf::eval_f_cos(s2.n, -wi, wi2, &s2.material);
        if f2.iter().all(|&v| v <= 0.0) {
            return;
        }
        let tr = self.visibility(&s2, wi2, &mut p.rays);
        if tr > 0.0 {
            p.push(Term {
                scale: a * a2 / pdf * tr / pdf2,
                primary: Some(first),
                secondary: Some(Bounce {
                    n: s2.n,
                    wo: -wi,
                    wi: wi2,
                    f: f2,
                }),
                tail: [1.0; 3],
                env_dir: wi2,
            });
        }
    }

    /// One environment next-event sample at a shading point: the BRDF factor at the sampled
    /// direction and the frozen scale T / pdf, times the power heuristic against the BSDF
    /// density when `mis` (a BSDF continuation competes). `None` when it contributes nothing
    /// (then no visibility ray is traced when f is zero).
    fn env_nee(
        &self,
        s: &Shading,
        wo: Vec3,
        u: [f32; 2],
        mis: bool,
        rays: &mut u32,
    ) -> Option<(Bounce, f32)> {
        let es = self.env.sample(u);
        if es.pdf <= 0.0 {
            return None;
        }
        let f = brdf::eval_f_cos(s.n, wo, es.dir, &s.material);
        if f.iter().all(|&v| v <= 0.0) {
            return None;
        }
        let tr = self.visibility(s, es.dir, rays);
        if tr <= 0.0 {
            return None;
        }
        let w = if mis {
            power_heuristic(es.pdf, brdf::pdf(s.n, wo, es.dir, &s.material))
        } else {
            1.0
        };
        let b = Bounce {
            n: s.n,
            wo,
            wi: es.dir,
            f,
        };
        Some((b, tr * w / es.pdf))
    }
}

/// Importance sampling of a separable pixel filter: Cycles' Blackman–Harris window (support
/// `[−width, width]` pixels about the centre for a filter width `width`, Cycles doubling the
/// width for this window), or a box over the pixel for `width ≤ 0`. Every sample then has
/// weight one and the pixel is the plain mean of its samples, as in Cycles.
#[derive(Clone, Debug)]
pub struct PixelFilter {
    /// Inverse CDF of the offset from the pixel centre, `TABLE + 1` entries; empty for a box.
    inverse_cdf: Vec<f32>,
}

impl PixelFilter {
    const TABLE: usize = 1024;

    pub fn new(width: f32) -> PixelFilter {
        if width.is_nan() || width <= 0.0 {
            return PixelFilter {
                inverse_cdf: Vec::new(),
            };
        }
        // Tabulate the window on a fine grid, integrate, invert.
        let full = 2.0 * width as f64;
        let n = 4096;
        let bh = |x: f64| {
            let t = 2.0 * std::f64::consts::PI * (x / full + 0.5);
            (0.35875 - 0.48829 * t.cos() + 0.14128 * (2.0 * t).cos() - 0.01168 * (3.0 * t).cos())
                .max(0.0)
        };
        let xs: Vec<f64> = (0..=n)
            .map(|i| -width as f64 + full * i as f64 / n as f64)
            .collect();
        let mut cdf = vec![0.0f64; n + 1];
        for i in 0..n {
            cdf[i + 1] = cdf[i] + 0.5 * (bh(xs[i]) + bh(xs[i + 1])) * (xs[i + 1] - xs[i]);
        }
        let total = cdf[n];
        let mut inverse_cdf = Vec::with_capacity(Self::TABLE + 1);
        let mut j = 0;
        for k in 0..=Self::TABLE {
            let u = total * k as f64 / Self::TABLE as f64;
            while j + 1 < n && cdf[j + 1] < u {
                j += 1;
            }
            let span = cdf[j + 1] - cdf[j];
            let f = if span > 0.0 {
                ((u - cdf[j]) / span).clamp(0.0, 1.0)
            } else {
                0.5
            };
            inverse_cdf.push((xs[j] + f * (xs[j + 1] - xs[j])) as f32);
        }
        PixelFilter { inverse_cdf }
    }

    /// Sample `index`'s camera ray through pixel (x, y): the filter-importance-sampled offset
    /// from the pixel centre, drawn from `sampler`'s [`dim::PIXEL`] dimensions. Returns the ray's
    /// origin and unit direction.
    #[inline]
    pub fn camera_ray(
        &self,
        camera: &Camera,
        (x, y): (u32, u32),
        sampler: &Sampler,
        index: u32,
    ) -> ([f32; 3], [f32; 3]) {
        let [ux, uy] = sampler.get_2d(index, dim::PIXEL);
        camera.ray(
            x as f32 + 0.5 + self.offset(ux),
            y as f32 + 0.5 + self.offset(uy),
        )
    }

    /// Offset from the pixel centre for a uniform `u ∈ [0, 1)`.
    #[inline]
    pub fn offset(&self, u: f32) -> f32 {
        if self.inverse_cdf.is_empty() {
            return u - 0.5;
        }
        let x = u * Self::TABLE as f32;
        let i = (x as usize).min(Self::TABLE - 1);
        let f = x - i as f32;
        self.inverse_cdf[i] + f * (self.inverse_cdf[i + 1] - self.inverse_cdf[i])
    }
}

/// One pixel of a rendered image: the mean radiance and coverage over its samples, and the
/// AOVs of the record at the pixel centre (as Blender renders its passes for the dataset).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pixel {
    pub rgb: [f32; 3],
    /// Mean composited alpha over the samples (coverage).
    pub alpha: f32,
    /// Planar depth along the camera's viewing axis (docs/design.md §2); 0 without a hit.
    pub depth: f32,
    /// Unit world normal facing the camera; 0 without a hit.
    pub normal: [f32; 3],
    /// Mean base colour; 0 without a hit.
    pub albedo: [f32; 3],
    /// Mean metallic and roughness; 0 without a hit.
    pub metallic: f32,
    pub roughness: f32,
    /// Rays traced for this pixel.
    pub rays: u32,
}

/// The camera's viewing axis in world space (−Z of the camera-to-world matrix).
pub fn camera_forward(camera: &Camera) -> Vec3 {
    -Vec3::from_array(camera.axis(2)).normalize()
}

impl Estimator<'_> {
    /// Renders pixel (x, y) of `camera` with `spp` samples of the stream of pixel id
    /// `y · w + x` under `seed`.
    pub fn pixel(
        &self,
        camera: &Camera,
        filter: &PixelFilter,
        (x, y): (u32, u32),
        spp: u32,
        seed: u32,
    ) -> Pixel {
        let sampler = Sampler::new(y * camera.w + x, seed);
        let (cx, cy) = (x as f32 + 0.5, y as f32 + 0.5);
        let mut px = Pixel::default();
        for i in 0..spp {
            let (o, d) = filter.camera_ray(camera, (x, y), &sampler, i);
            let p = self.radiance(o, d, &sampler, i);
            add_scaled(&mut px.rgb, p.radiance, 1.0);
            px.alpha += p.record.alpha;
            px.rays += p.rays;
        }
        let inv = 1.0 / spp.max(1) as f32;
        px.rgb = px.rgb.map(|v| v * inv);
        px.alpha *= inv;
        let (o, d) = camera.ray(cx, cy);
        let rec = self.scene.composite(o, d, 0.0, f32::INFINITY);
        px.rays += 1;
        if rec.hits > 0 && rec.alpha > 0.0 {
            px.depth = rec.mean_depth() * Vec3::from_array(d).dot(camera_forward(camera));
            px.normal = rec.unit_normal();
            px.albedo = rec.mean_base_color();
            px.metallic = rec.mean_metallic();
            px.roughness = rec.mean_roughness();
        }
        px
    }
}
