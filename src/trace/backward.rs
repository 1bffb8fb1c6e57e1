//! The ray tracer's backward pass: the adjoint of [`Placed::composite`] (eq. surface-record)
//! with respect to every hit surfel's stored parameters and, optionally, each component's rigid
//! placement (eq. state-assembly).
//!
//! **Per ray.** The hits are collected by the very traversal the forward pass runs
//! ([`Placed::walk`]), so they are the same hits in the same order under the same rules (the
//! MAX_OPACITY cap, the support and MIN_ALPHA cut-offs, the T_MIN stop). They are then walked
//! back to front with the kernel's compositing adjoint ([`Back`]), which yields each hit's
//! weight w and dL/dα. A hit contributes `w · z` to every sum, so dL/dz = w · dL/dΣ for
//! z ∈ {t, x, n, a, m, r}, and α and t carry dL/dα and dL/dt into the surfel's geometry.
//!
//! **Hit geometry** (eq. gaussian-response), in the world: with μ = R_T μ_c + t_T and axes
//! (t_u, t_v, n) = R_T R(q̂), `t = −(o − μ)·n / (d·n)`, `p = o − μ + t d`,
//! `ξ = (p·t_u / s_u, p·t_v / s_v)`, `α = min(opacity·exp(−½|ξ|²), MAX_OPACITY)`, the position
//! `x = o + t d` and the normal `±n`, turned to face the ray. World gradients are carried back to
//! the component frame (Rᵀ), through R(q̂) to the raw quaternion ([`quat_grad`]), and to the
//! placement's left increment `x ↦ exp([ω]×) R x + t + δ` as [`TransformGrad`] does for splatting.
//!
//! **Documented choices.** A capped hit's α (opacity·g > MAX_OPACITY) does not depend on the
//! surfel's parameters, so it passes no gradient to them (its t, x and n still do). The support
//! and MIN_ALPHA cut-offs, the T_MIN stop and the facing flip of the normal are discontinuities:
//! the hit set, its order and the flip are held fixed and their measure-zero boundary terms are
//! ignored, as in splatting.
//!
//! **Determinism.** Rays are processed in fixed chunks of [`RAY_CHUNK`] in parallel; each chunk
//! emits its per-hit contributions in ray and hit order, and they are scatter-added sequentially
//! in chunk order. No float is ever reduced in an order that depends on the thread count.

use super::batch::Hit;
use super::placed::Placed;
use super::record::{RecordGrad, WeightedHit};
use crate::kernel::composite::{Back, Front};
use crate::kernel::{quat_grad, MAX_OPACITY};
use crate::scene::transform::TransformGrad;
use crate::scene::Surfels;
use glam::{Mat3, Quat, Vec3};
use rayon::prelude::*;

/// One ray of a batch: `origin + t dir`, `t_min < t < t_max`, as [`Placed::composite`] takes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceRay {
    pub origin: [f32; 3],
    pub dir: [f32; 3],
    pub t_min: f32,
    pub t_max: f32,
}

/// Gradients for one component's surfels, by the component's own surfel index, with respect to
/// the stored values in the component frame (like `splat::SurfelGrads`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TraceSurfelGrads {
    pub position: Vec<[f32; 3]>,
    /// Raw quaternion (x, y, z, w); orthogonal to it, since it is normalised before use.
    pub rotation: Vec<[f32; 4]>,
    pub scale: Vec<[f32; 2]>,
    /// The stored (post-sigmoid) opacity.
    pub opacity: Vec<f32>,
    pub base_color: Vec<[f32; 3]>,
    pub metallic: Vec<f32>,
    pub roughness: Vec<f32>,
}

impl TraceSurfelGrads {
    pub fn zeros(n: usize) -> Self {
        TraceSurfelGrads {
            position: vec![[0.0; 3]; n],
            rotation: vec![[0.0; 4]; n],
            scale: vec![[0.0; 2]; n],
            opacity: vec![0.0; n],
            base_color: vec![[0.0; 3]; n],
            metallic: vec![0.0; n],
            roughness: vec![0.0; n],
        }
    }

    /// Adds `other`'s gradients (same component, same surfels), e.g. from another state's rays.
    pub fn add(&mut self, other: &TraceSurfelGrads) {
        fn acc<const K: usize>(a: &mut [[f32; K]], b: &[[f32; K]]) {
            for (x, y) in a.iter_mut().zip(b) {
                for k in 0..K {
                    x[k] += y[k];
                }
            }
        }
        fn acc1(a: &mut [f32], b: &[f32]) {
            for (x, y) in a.iter_mut().zip(b) {
                *x += y;
            }
        }
        acc(&mut self.position, &other.position);
        acc(&mut self.rotation, &other.rotation);
        acc(&mut self.scale, &other.scale);
        acc1(&mut self.opacity, &other.opacity);
        acc(&mut self.base_color, &other.base_color);
        acc1(&mut self.metallic, &other.metallic);
        acc1(&mut self.roughness, &other.roughness);
    }
}

/// dL/d(each surfel's stored material) for one component, by the component's surfel index: the
/// material share of [`TraceSurfelGrads`], for callers whose geometry is fixed (stage 3).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MaterialGrads {
    pub base_color: Vec<[f32; 3]>,
    pub metallic: Vec<f32>,
    pub roughness: Vec<f32>,
}

impl MaterialGrads {
    pub fn zeros(n: usize) -> Self {
        MaterialGrads {
            base_color: vec![[0.0; 3]; n],
            metallic: vec![0.0; n],
            roughness: vec![0.0; n],
        }
    }
}

/// The material part of the adjoint of a record whose hits are known
/// ([`Placed::composite_hits`]): its material sums are Σ w_j m_j with the weights fixed by the
/// geometry, so dL/dm_j = w_j · dL/dΣ — what [`Placed::composite_backward`] sends to the
/// materials, without re-deriving the weights or any geometry gradient. Adds into `out`, one
/// entry per component.
pub fn scatter_material_grad(hits: &[WeightedHit], g: &RecordGrad, out: &mut [MaterialGrads]) {
    for h in hits {
        let o = &mut out[h.component as usize];
        let i = h.index as usize;
        for k in 0..3 {
            o.base_color[i][k] += h.w * g.base_color[k];
        }
        o.metallic[i] += h.w * g.metallic;
        o.roughness[i] += h.w * g.roughness;
    }
}

/// Everything [`Placed::composite_backward`] returns, one entry per component.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TraceGradients {
    pub surfels: Vec<TraceSurfelGrads>,
    /// All zero unless asked for.
    pub transforms: Vec<TransformGrad>,
}

/// Rays per parallel work item: large enough to amortise the chunk's buffers, small enough to
/// balance a batch of a few thousand rays over the cores. Fixed, so results do not depend on
/// the thread count.
pub const RAY_CHUNK: usize = 64;

/// Floats one hit contributes to its surfel: position 3, rotation 4, scale 2, opacity 1,
/// base colour 3, metallic 1, roughness 1.
const NG: usize = 15;

/// One hit's gradient, waiting for the ordered scatter-add.
#[derive(Clone, Copy, Debug)]
struct Contribution {
    component: u32,
    index: u32,
    g: [f32; NG],
}

/// What a chunk of rays emits.
struct ChunkOut {
    hits: Vec<Contribution>,
    /// Per component: dL/dδ, dL/dω.
    transforms: Vec<[f32; 6]>,
}

impl Placed<'_> {
    /// The adjoint of [`Placed::composite`] for a batch of rays: `grads[r]` is dL/d(the record
    /// of `rays[r]`). Same hits, same order, same rules as `composite` (see the module doc for
    /// what is held fixed); deterministic for any thread count. `components` are the surfels
    /// the [`super::TraceScene`] was built from, in the same order.
    ///
    /// Panics if `rays` and `grads` differ in length or `components` does not match the scene.
    pub fn composite_backward(
        &self,
        components: &[&Surfels],
        rays: &[TraceRay],
        grads: &[RecordGrad],
        with_transforms: bool,
    ) -> TraceGradients {
        assert_eq!(rays.len(), grads.len(), "one RecordGrad per ray");
        assert_eq!(
            components.len(),
            self.scene.blas.len(),
            "composite_backward: the components the TraceScene was built from"
        );
        for (s, blas) in components.iter().zip(&self.scene.blas) {
            assert_eq!(
                s.len(),
                blas.index.len(),
                "component changed since the BVH build"
            );
        }
        let chunks: Vec<ChunkOut> = rays
            .par_chunks(RAY_CHUNK)
            .zip(grads.par_chunks(RAY_CHUNK))
            .map(|(rays, grads)| {
                let mut out = ChunkOut {
                    hits: Vec::new(),
                    transforms: vec![[0.0; 6]; components.len()],
                };
                let mut hits = Vec::new();
                for (ray, g) in rays.iter().zip(grads) {
                    if !g.is_zero() {
                        self.ray_backward(components, ray, g, &mut hits, &mut out, with_transforms);
                    }
                }
                out
            })
            .collect();

        let mut surfels: Vec<TraceSurfelGrads> = components
            .iter()
            .map(|s| TraceSurfelGrads::zeros(s.len()))
            .collect();
        let mut tf = vec![[0.0f32; 6]; components.len()];
        for chunk in &chunks {
            for h in &chunk.hits {
                let s = &mut surfels[h.component as usize];
                let i = h.index as usize;
                let g = &h.g;
                for k in 0..3 {
                    s.position[i][k] += g[k];
                    s.base_color[i][k] += g[10 + k];
                }
                for k in 0..4 {
                    s.rotation[i][k] += g[3 + k];
                }
                s.scale[i][0] += g[7];
                s.scale[i][1] += g[8];
                s.opacity[i] += g[9];
                s.metallic[i] += g[13];
                s.roughness[i] += g[14];
            }
            for (a, b) in tf.iter_mut().zip(&chunk.transforms) {
                for k in 0..6 {
                    a[k] += b[k];
                }
            }
        }
        TraceGradients {
            surfels,
            transforms: tf
                .iter()
                .map(|t| TransformGrad {
                    translation: [t[0], t[1], t[2]],
                    rotation: [t[3], t[4], t[5]],
                })
                .collect(),
        }
    }

    /// The material part of [`Placed::composite_backward`] alone (geometry fixed): each ray is
    /// traced again for its hits and weights and [`scatter_material_grad`] applied, in ray
    /// order (deterministic for any thread count). Adds into `out`, one entry per component
    /// (e.g. [`MaterialGrads::zeros`] of each component's surfel count).
    pub fn material_backward(
        &self,
        rays: &[TraceRay],
        grads: &[RecordGrad],
        out: &mut [MaterialGrads],
    ) {
        assert_eq!(rays.len(), grads.len(), "one RecordGrad per ray");
        assert_eq!(
            out.len(),
            self.scene.blas.len(),
            "material_backward: one MaterialGrads per component"
        );
        // Per chunk: every ray's hits, and where each ray's start (then scattered in order).
        let chunks: Vec<(Vec<WeightedHit>, Vec<usize>)> = rays
            .par_chunks(RAY_CHUNK)
            .map(|rays| {
                let mut hits = Vec::new();
                let mut starts = Vec::with_capacity(rays.len() + 1);
                for r in rays {
                    starts.push(hits.len());
                    self.composite_hits(r.origin, r.dir, r.t_min, r.t_max, &mut hits);
                }
                starts.push(hits.len());
                (hits, starts)
            })
            .collect();
        for ((hits, starts), grads) in chunks.iter().zip(grads.chunks(RAY_CHUNK)) {
            for (r, g) in grads.iter().enumerate() {
                scatter_material_grad(&hits[starts[r]..starts[r + 1]], g, out);
            }
        }
    }

    /// One ray: collect its hits as `composite` does, then walk them back to front.
    fn ray_backward(
        &self,
        components: &[&Surfels],
        ray: &TraceRay,
        g: &RecordGrad,
        hits: &mut Vec<(usize, Hit)>,
        out: &mut ChunkOut,
        with_transforms: bool,
    ) {
        let o = Vec3::from_array(ray.origin);
        let d = Vec3::from_array(ray.dir);
        hits.clear();
        self.walk_hits(o, d, ray.t_min, ray.t_max, hits);
        // The transmittance behind the last hit, multiplied in the forward's order.
        let mut front = Front::default();
        for (_, h) in hits.iter() {
            front.step(h.alpha);
        }
        let mut back = Back::new(front.trans);
        for &(c, h) in hits.iter().rev() {
            let s = components[c];
            let i = self.scene.blas[c].index[h.slot as usize] as usize;
            let inst = &self.instances[c];
            let (rot, trans) = (inst.rotation, inst.translation);

            // The hit in the world, from the stored parameters (eq. gaussian-response).
            let q_raw = s.rotation[i];
            let axes = rot * Mat3::from_quat(Quat::from_array(q_raw).normalize());
            let (tu, tv, n) = (axes.x_axis, axes.y_axis, axes.z_axis);
            let mu = rot * Vec3::from_array(s.position[i]) + trans;
            let [su, sv] = s.scale[i];
            let opacity = s.opacity[i];
            let om = o - mu;
            let den = d.dot(n);
            let t = -om.dot(n) / den;
            let p = om + t * d;
            let (xu, xv) = (p.dot(tu) / su, p.dot(tv) / sv);
            let gauss = (-0.5 * (xu * xu + xv * xv)).exp();
            let capped = opacity * gauss > MAX_OPACITY;
            // The normal as composited: turned to face the ray (the sign is held fixed).
            let sign = if den > 0.0 { -1.0 } else { 1.0 };
            let x = o + h.t * d;
            let m = crate::scene::Material {
                base_color: s.base_color[i],
                metallic: s.metallic[i],
                roughness: s.roughness[i],
            };

            // eq. surface-record, adjoint: weight and dL/dα from the kernel's recurrence.
            let gdot = g.dot_hit(h.t, x.to_array(), (sign * n).to_array(), &m);
            let (w, d_alpha) = back.step(h.alpha, gdot);

            // dL/dt from depth and position (x = o + t d), dL/dn from the composited normal.
            let mut g_t = w * (g.depth + Vec3::from_array(g.position).dot(d));
            let mut g_n = sign * w * Vec3::from_array(g.normal);
            let (mut g_tu, mut g_tv) = (Vec3::ZERO, Vec3::ZERO);
            let (mut g_su, mut g_sv, mut g_op) = (0.0, 0.0, 0.0);
            let mut g_p = Vec3::ZERO;
            if !capped {
                // α = opacity·exp(−½ r²): dα/dopacity = g, dα/dr² = −½ α.
                g_op = d_alpha * gauss;
                let g_r2 = -0.5 * opacity * gauss * d_alpha;
                let (g_xu, g_xv) = (2.0 * g_r2 * xu, 2.0 * g_r2 * xv);
                // ξ_u = p·t_u / s_u.
                g_p = tu * (g_xu / su) + tv * (g_xv / sv);
                g_tu = p * (g_xu / su);
                g_tv = p * (g_xv / sv);
                g_su = -g_xu * xu / su;
                g_sv = -g_xv * xv / sv;
            }
            // p = o − μ + t d, t = −(o − μ)·n / (d·n): dt/d(o − μ) = −n / (d·n),
            // dt/dn = −p / (d·n).
            g_t += g_p.dot(d);
            let g_om = g_p - n * (g_t / den);
            g_n -= p * (g_t / den);
            let g_mu = -g_om;

            // World → component frame: μ = R_T μ_c + t_T, axes = R_T R(q̂).
            let rt = rot.transpose();
            let g_rq = Mat3::from_cols(rt * g_tu, rt * g_tv, rt * g_n);
            let gq = quat_grad(q_raw, g_rq);
            let gp = rt * g_mu;
            out.hits.push(Contribution {
                component: c as u32,
                index: i as u32,
                g: [
                    gp.x,
                    gp.y,
                    gp.z,
                    gq[0],
                    gq[1],
                    gq[2],
                    gq[3],
                    g_su,
                    g_sv,
                    g_op,
                    w * g.base_color[0],
                    w * g.base_color[1],
                    w * g.base_color[2],
                    w * g.metallic,
                    w * g.roughness,
                ],
            });
            if with_transforms {
                // Left increment: δμ = ω × (μ − t_T) + δ, δ(axis) = ω × axis.
                let omega =
                    (mu - trans).cross(g_mu) + tu.cross(g_tu) + tv.cross(g_tv) + n.cross(g_n);
                let acc = &mut out.transforms[c];
                for (a, v) in acc
                    .iter_mut()
                    .zip([g_mu.x, g_mu.y, g_mu.z, omega.x, omega.y, omega.z])
                {
                    *a += v;
                }
            }
        }
    }
}
