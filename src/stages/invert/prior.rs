//! Stage 3's base-colour prior: where neighbouring surfels looked alike in colour to stage 1,
//! their base colours are drawn together, robustly, so that a shadow is explained by occlusion
//! rather than painted into the floor. Not in the paper (its eq. training-objectives has only
//! the image term and the environments' TV); added for issue 44, where the paper's objective
//! baked each training state's shadows into a plain floor (the ghost shadows of
//! `tests/separation.rs` and the demo's `albedo_uniformity`).
//!
//! **Why it helps.** Base colour is shared by every state and each state has its own
//! environment, so a shadow that moves between states cannot be paint in all of them; but the
//! objective does not forbid a compromise (a surfel shadowed in one state of three darkened a
//! little), and per-surfel base colour reaches that compromise faster than the environment
//! grows a sun sharp enough to cast the shadow. Intrinsic-image methods meet the same ambiguity
//! with the Retinex observation: reflectance is piecewise constant and its edges change
//! chromaticity, while shading changes brightness at nearly constant chromaticity (Land &
//! McCann 1971; the chromaticity-weighted smoothness of Bell et al. 2014, "Intrinsic Images in
//! the Wild", and of IntrinsicNeRF, Ye et al. 2023).
//!
//! **The term.** For surfel i and its neighbours j ∈ N(i) (up to [`NEIGHBOURS`] nearest of its
//! component within [`RADIUS_SCALES`] of its larger scale, facing within 60°), with weights
//! ω_ij = exp(−‖c_i − c_j‖² / 2σ²) on the chromaticities c = rgb / (r + g + b) of stage 1's
//! colour (its SH DC term, the captures' average appearance; σ = [`CHROMA_SIGMA`]):
//!
//!   T_i = Σ_j ω_ij Σ_c ρ(ln a_ic − ln a_jc) / Σ_j ω_ij,   ρ(x) = √(x² + δ²) − δ,
//!
//! ρ Charbonnier (δ = [`DELTA`]): quadratic below a 2 % difference, absolute above, so a real
//! edge costs its height once and is kept where the captures show it in every state.
//!
//! **Where and how much.** The term is taken at the surfels the iteration's pixels land on
//! (their primary records' hits, each with its compositing weight), λ Ī / N per pixel (Ī the
//! drawn captures' mean, N the pixels): an image term's pull on a surfel's base colour is about
//! Ī / (3 N a) per channel and pixel, the prior's at most λ Ī / (N a), so λ is the prior's
//! largest pull in units of 3 pixels' data (λ = 0.1: a third of one pixel's), whatever the
//! scene's brightness, image count or surfel count.
//!
//! **What it does and does not do** (measured, docs/benchmarks.md): with λ 0.3 (and
//! `--env-update shared`) the ghost of `tests/separation.rs`'s plain floor goes (0.91 → 0.97-0.99
//! of the open floor), but a checker of one chromaticity is flattened with it (dark / light 0.98
//! for 0.57), and on the demo λ 0.1 changed neither Table 1 (26.11 against 26.19 dB) nor the
//! ghost share (41 % against 39 %). Hence off by default: a prior that tells a moving shadow
//! from a texture needs the states themselves (a shadow differs between them, a texture does
//! not), which this one does not use.

use crate::scene::{quat_axes, Surfels, SH_C0};
use crate::spatial::KdTree;
use crate::trace::{MaterialGrads, WeightedHit};
use glam::Vec3;
use rayon::prelude::*;

/// Neighbours per surfel at most.
pub const NEIGHBOURS: usize = 8;
/// Neighbours are searched within this many of the surfel's larger scale (σ: one standard
/// deviation of its Gaussian; stage 1's surfels are spaced about one σ apart).
pub const RADIUS_SCALES: f32 = 2.5;
/// σ of the chromaticity weight: chromaticities differ by ~0.01 across a shadow's edge under
/// a bluish sky, by ≥ 0.05 between differently coloured paints.
pub const CHROMA_SIGMA: f32 = 0.03;
/// Charbonnier's δ on log base colour.
pub const DELTA: f32 = 0.02;

/// Each surfel's neighbours and weights, per component.
#[derive(Clone, Debug, Default)]
pub struct BaseColorPrior {
    /// Per component: surfel i's neighbours are `neighbours[c][start[c][i]..start[c][i + 1]]`,
    /// each (index, ω / Σω).
    start: Vec<Vec<u32>>,
    neighbours: Vec<Vec<(u32, f32)>>,
}

/// Stage 1's colour of surfel `i` (SH DC, 3DGS's offset) as a chromaticity.
fn chromaticity(s: &Surfels, i: usize) -> [f32; 3] {
    let dc = s.sh[i * s.sh_stride()];
    let c = dc.map(|v| (SH_C0 * v + 0.5).max(1e-3));
    let sum = c[0] + c[1] + c[2];
    c.map(|v| v / sum)
}

impl BaseColorPrior {
    /// The neighbour graph of every component (the surfels' geometry and stage-1 colour are
    /// fixed during stage 3).
    pub fn build(components: &[&Surfels]) -> BaseColorPrior {
        let mut prior = BaseColorPrior::default();
        for s in components {
            let tree = KdTree::new(&s.position);
            let normals: Vec<Vec3> = s
                .rotation
                .iter()
                .map(|&q| Vec3::from(quat_axes(q)[2]))
                .collect();
            let chroma: Vec<[f32; 3]> = (0..s.len()).map(|i| chromaticity(s, i)).collect();
            let lists: Vec<Vec<(u32, f32)>> = (0..s.len())
                .into_par_iter()
                .map(|i| {
                    let r = RADIUS_SCALES * s.scale[i][0].max(s.scale[i][1]);
                    let mut near = Vec::new();
                    tree.within(&s.position[i], r * r, &mut near);
                    near.retain(|&(j, _)| j != i && normals[i].dot(normals[j]).abs() > 0.5);
                    near.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
                    near.truncate(NEIGHBOURS);
                    let mut out: Vec<(u32, f32)> = near
                        .iter()
                        .map(|&(j, _)| {
                            let d2: f32 =
                                (0..3).map(|c| (chroma[i][c] - chroma[j][c]).powi(2)).sum();
                            (j as u32, (-d2 / (2.0 * CHROMA_SIGMA * CHROMA_SIGMA)).exp())
                        })
                        .collect();
                    let total: f32 = out.iter().map(|n| n.1).sum();
                    for n in &mut out {
                        n.1 /= total.max(1e-12);
                    }
                    out
                })
                .collect();
            let mut start = vec![0u32];
            let mut flat = Vec::new();
            for l in lists {
                flat.extend(l);
                start.push(flat.len() as u32);
            }
            prior.start.push(start);
            prior.neighbours.push(flat);
        }
        prior
    }

    /// Surfel `i` of component `c`'s neighbours, (index, normalised weight).
    pub fn neighbours(&self, c: usize, i: usize) -> &[(u32, f32)] {
        let s = &self.start[c];
        &self.neighbours[c][s[i] as usize..s[i + 1] as usize]
    }

    /// `scale` · Σ over `touches` (surfels with a weight each) of weight · T_i, with the base
    /// colours of `components`; adds its gradient with respect to each base colour (value, not
    /// logit) to `d_mat`. Returns the value.
    pub fn add(
        &self,
        components: &[&Surfels],
        touches: &[WeightedHit],
        scale: f64,
        d_mat: &mut [MaterialGrads],
    ) -> f64 {
        let mut value = 0.0f64;
        for h in touches {
            let (c, i) = (h.component as usize, h.index as usize);
            let s = components[c];
            let k = scale * h.w as f64;
            let ai = s.base_color[i];
            for &(j, w) in self.neighbours(c, i) {
                let aj = s.base_color[j as usize];
                for ch in 0..3 {
                    let (pi, pj) = (ai[ch].max(1e-6) as f64, aj[ch].max(1e-6) as f64);
                    let x = pi.ln() - pj.ln();
                    let d = DELTA as f64;
                    let r = (x * x + d * d).sqrt();
                    value += k * w as f64 * (r - d);
                    let g = k * w as f64 * x / r;
                    d_mat[c].base_color[i][ch] += (g / pi) as f32;
                    d_mat[c].base_color[j as usize][ch] -= (g / pj) as f32;
                }
            }
        }
        value
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::SplitMix;

    /// A 6×6 grid of surfels 1 cm apart facing +Z, σ = 1 cm, the left half reddish and the
    /// right half greenish in stage 1's colour, base colours random in [0.2, 0.8].
    fn grid(rng: &mut SplitMix) -> Surfels {
        let mut s = Surfels::with_sh_degree(0);
        for y in 0..6 {
            for x in 0..6 {
                let rgb: [f32; 3] = if x < 3 {
                    [0.6, 0.3, 0.3]
                } else {
                    [0.3, 0.6, 0.3]
                };
                let dc = rgb.map(|v| (v - 0.5) / SH_C0);
                let a = [0, 1, 2].map(|_| 0.2 + 0.6 * rng.f32());
                s.push(
                    [0.01 * x as f32, 0.01 * y as f32, 0.0],
                    [0.0, 0.0, 0.0, 1.0],
                    [0.01, 0.01],
                    0.9,
                    &[dc],
                    a,
                    0.0,
                    0.5,
                );
            }
        }
        s
    }

    /// Neighbours: up to 8, the nearest first, never the surfel itself, weights summing to 1;
    /// across the colour edge the weights are far below those within a half (chromaticities
    /// 0.5/0.25 against 0.25/0.5 differ by ~0.35, 12 σ).
    #[test]
    fn neighbours_follow_distance_and_chromaticity() {
        let s = grid(&mut SplitMix(3));
        let p = BaseColorPrior::build(&[&s]);
        for i in 0..s.len() {
            let n = p.neighbours(0, i);
            assert!(!n.is_empty() && n.len() <= NEIGHBOURS);
            assert!(n.iter().all(|&(j, _)| j as usize != i));
            let total: f32 = n.iter().map(|x| x.1).sum();
            assert!((total - 1.0).abs() < 1e-5);
            let side = |j: usize| (j % 6) < 3;
            for &(j, w) in n {
                if side(j as usize) != side(i) {
                    assert!(w < 1e-6, "{i}-{j} across the edge: {w}");
                }
            }
        }
        // An interior surfel has its 4 edge neighbours (1 cm) and 4 diagonal ones (1.41 cm).
        assert_eq!(p.neighbours(0, 6 + 1).len(), 8);
    }

    /// The gradient against central differences of the value, in f64 on base colours in
    /// [0.2, 0.8] (h = 1e-4: Charbonnier is smooth, its curvature ≤ 1/δ = 50 in log space, so
    /// the truncation error ≲ 1e-6 relative; f32 storage of a ± h rounds at ~1e-7/1e-4 = 1e-3
    /// relative, which the tolerance covers). Touches repeat a surfel, as pixels do.
    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = SplitMix(5);
        let s = grid(&mut rng);
        let p = BaseColorPrior::build(&[&s]);
        let touches: Vec<WeightedHit> = [7usize, 8, 8, 14, 20, 33]
            .iter()
            .map(|&i| WeightedHit {
                component: 0,
                index: i as u32,
                w: 0.3 + 0.1 * (i % 4) as f32,
            })
            .collect();
        let mut d = vec![MaterialGrads::zeros(s.len())];
        p.add(&[&s], &touches, 0.7, &mut d);
        let value = |s: &Surfels| {
            let mut z = vec![MaterialGrads::zeros(s.len())];
            p.add(&[s], &touches, 0.7, &mut z)
        };
        let mut checked = 0;
        for i in 0..s.len() {
            for c in 0..3 {
                let h = 1e-4f32;
                let (mut sp, mut sm) = (s.clone(), s.clone());
                sp.base_color[i][c] += h;
                sm.base_color[i][c] -= h;
                let fd = (value(&sp) - value(&sm))
                    / (sp.base_color[i][c] as f64 - sm.base_color[i][c] as f64);
                let g = d[0].base_color[i][c] as f64;
                assert!(
                    (fd - g).abs() < 2e-3 * (1.0 + g.abs()),
                    "surfel {i} channel {c}: {g} vs {fd}"
                );
                checked += (g != 0.0) as usize;
            }
        }
        assert!(checked > 30, "only {checked} non-zero derivatives");
    }
}
