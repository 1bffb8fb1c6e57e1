//! Background / object decomposition of a reference-state reconstruction, in the spirit of
//! GaussianCut (Jain et al. 2024; paper §"Object segmentation and completion").
//!
//! 1. Votes: every surfel centre is projected into every observation of the reference state.
//!    Where it is visible there it votes for the mask id at that pixel (see [`mask_votes`]).
//! 2. Unary costs: −ln of the smoothed vote shares, floored; a surfel no view sees gets the
//!    same cost for every label, so only its neighbours decide.
//! 3. Pairwise costs: a contrast-sensitive Potts model on the k-nearest-neighbour graph of the
//!    centres (within a radius): neighbours that are close, parallel and alike in colour pay
//!    the most to take different labels, so cuts run along creases and colour edges, such as
//!    where an object rests on the floor.
//! 4. Minimisation over {background, objects} by α-expansion (Boykov, Veksler, Zabih 2001),
//!    each move a minimum cut from [`super::maxflow::MaxFlow`].

use super::maxflow::MaxFlow;
use crate::error::{Error, Result};
use crate::io::dataset::Observation;
use crate::scene::{quat_axes, Camera, Surfels, SH_C0};
use rayon::prelude::*;
use std::collections::HashMap;

/// Settings of the segmentation; the defaults suit captures like the demo (cameras 2–5 m
/// away, pixel footprints of a few centimetres, surfels about 1 cm apart).
#[derive(Clone, Debug, PartialEq)]
pub struct SegmentParams {
    /// A surfel is visible in a view when its planar depth d and the observed depth D at its
    /// pixel agree: |d − D| ≤ `depth_tolerance` · D. Relative, because depth maps quantise
    /// and surfels sit up to half a pixel off the pixel centre, both growing with depth: over
    /// half a pixel a surface at angle θ to the ray changes depth by D / (2 f tan θ), so with
    /// f ≈ 120 px (the demo) 2 % admits surfaces down to θ ≈ 12°, while an occluder 2 % of
    /// the depth in front of a surface (8 cm at 4 m) still hides it.
    pub depth_tolerance: f32,
    /// Pseudo-count added to every label's votes before taking shares (Laplace smoothing):
    /// one stray vote among few cannot make a label impossible.
    pub vote_prior: f32,
    /// Smallest share used in −ln(share), bounding every unary cost by −ln(floor).
    pub share_floor: f32,
    /// Neighbours per surfel in the pairwise graph (the graph is the union of both directions).
    pub neighbours: usize,
    /// Largest neighbour distance, metres.
    pub radius: f32,
    /// λ: weight of one pair of identical, coincident neighbours taking different labels,
    /// in the units of the unary costs (nats).
    pub smoothness: f32,
    /// σ_n: the normal factor is exp(−(1 − n_i·n_j) / σ_n); 0.1 makes a 90° crease ~e⁻¹⁰ cheap
    /// to cut while neighbours 20° apart (curved objects at this sampling) keep ~60 %.
    pub normal_sigma: f32,
    /// Upper bound on α-expansion sweeps over all labels (it stops earlier when a sweep
    /// lowers the energy by less than 1e-9 relative).
    pub max_sweeps: usize,
}

impl Default for SegmentParams {
    fn default() -> Self {
        SegmentParams {
            depth_tolerance: 0.02,
            vote_prior: 1.0,
            share_floor: 1e-3,
            neighbours: 8,
            radius: 0.03,
            smoothness: 1.0,
            normal_sigma: 0.1,
            max_sweeps: 8,
        }
    }
}

/// What the segmentation needs of each surfel: world centre, world unit normal and a colour.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SurfelPoints {
    pub position: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
    /// Any colour space in which Euclidean distance means "looks different" (scene-linear is
    /// fine: the contrast scale adapts to the mean difference).
    pub color: Vec<[f32; 3]>,
}

impl SurfelPoints {
    /// Centres, normals (third axis of R(q)) and the colour of the SH DC term of `surfels`.
    pub fn from_surfels(surfels: &Surfels) -> Self {
        let stride = surfels.sh_stride();
        SurfelPoints {
            position: surfels.position.clone(),
            normal: surfels.rotation.iter().map(|&q| quat_axes(q)[2]).collect(),
            color: (0..surfels.len())
                .map(|i| {
                    let dc = surfels.sh[i * stride];
                    dc.map(|c| SH_C0 * c + 0.5)
                })
                .collect(),
        }
    }

    pub fn len(&self) -> usize {
        self.position.len()
    }

    pub fn is_empty(&self) -> bool {
        self.position.is_empty()
    }
}

/// Result of [`segment`].
#[derive(Clone, Debug, PartialEq)]
pub struct Segmentation {
    /// Label per surfel: 0 = background, otherwise the object id of the masks.
    pub labels: Vec<u8>,
    /// Number of labels L (= 1 + the largest id in any mask); votes are `n × L`, surfel-major.
    pub n_labels: usize,
    pub votes: Vec<u32>,
    /// Per-surfel argmin of the unary costs (the "argmax of votes" labelling), where the
    /// expansion starts.
    pub initial_labels: Vec<u8>,
    /// Energy of `initial_labels` and of `labels`.
    pub energy_before: f64,
    pub energy_after: f64,
    /// Pairwise graph edges used.
    pub edge_count: usize,
    /// α-expansion sweeps run.
    pub sweeps: usize,
}

/// Segments `points` into background and objects from the observations of the same state.
/// Errors when an observation's images do not match its camera or a length differs.
pub fn segment(
    points: &SurfelPoints,
    observations: &[Observation],
    params: &SegmentParams,
) -> Result<Segmentation> {
    let n = points.len();
    for (name, len) in [
        ("normal", points.normal.len()),
        ("color", points.color.len()),
    ] {
        if len != n {
            return Err(Error::invalid(
                "surfel points",
                name,
                format!("expected one per surfel ({n}), found {len}"),
            ));
        }
    }
    let n_labels = 1 + observations
        .iter()
        .flat_map(|o| o.mask.iter())
        .copied()
        .max()
        .unwrap_or(0) as usize;
    let votes = mask_votes(
        &points.position,
        observations,
        n_labels,
        params.depth_tolerance,
    )?;
    let unary = unary_costs(&votes, n_labels, params.vote_prior, params.share_floor);
    let pairs = neighbour_pairs(&points.position, params.neighbours, params.radius);
    let edges = potts_weights(points, &pairs, params);
    let potts = Potts {
        n_labels,
        unary,
        edges,
    };
    let initial_labels = potts.unary_argmin();
    let energy_before = potts.energy(&initial_labels);
    let (labels, sweeps) = potts.alpha_expansion(initial_labels.clone(), params.max_sweeps);
    let energy_after = potts.energy(&labels);
    Ok(Segmentation {
        labels,
        n_labels,
        votes,
        initial_labels,
        energy_before,
        energy_after,
        edge_count: potts.edges.len(),
        sweeps,
    })
}

/// Projects world point `p` into `camera`: the pixel index (row-major) and the planar depth,
/// or None when it lies behind the camera or outside the image.
pub fn project(camera: &Camera, p: [f32; 3]) -> Option<(usize, f32)> {
    let ([u, v], depth) = camera.project(p)?;
    if !(u >= 0.0 && v >= 0.0 && u < camera.w as f32 && v < camera.h as f32) {
        return None;
    }
    let (x, y) = (u as usize, v as usize);
    Some((y * camera.w as usize + x, depth))
}

/// Mask votes, `n × n_labels` counts surfel-major: surfel i votes in view v for the mask id at
/// the pixel its centre projects to, when it is visible there: in front of the camera, inside
/// the image, the pixel saw something (depth > 0) and |d − D| ≤ `depth_tolerance` · D. A
/// surfel hidden behind an occluder fails the depth test and does not vote in that view.
pub fn mask_votes(
    positions: &[[f32; 3]],
    observations: &[Observation],
    n_labels: usize,
    depth_tolerance: f32,
) -> Result<Vec<u32>> {
    for o in observations {
        let px = o.camera.w as usize * o.camera.h as usize;
        let field = |f: &str| format!("state {} view {}: {f}", o.state, o.view);
        if o.depth.len() != px || o.mask.len() != px {
            return Err(Error::invalid(
                "observations",
                field("depth/mask"),
                format!(
                    "expected {px} pixels like the camera, found {} depth and {} mask",
                    o.depth.len(),
                    o.mask.len()
                ),
            ));
        }
        if let Some(&m) = o.mask.iter().find(|&&m| m as usize >= n_labels) {
            return Err(Error::invalid(
                "observations",
                field("mask"),
                format!("expected ids below {n_labels}, found {m}"),
            ));
        }
    }
    let mut votes = vec![0u32; positions.len() * n_labels];
    votes
        .par_chunks_mut(n_labels.max(1))
        .zip(positions.par_iter())
        .for_each(|(row, &p)| {
            for o in observations {
                if let Some((pix, d)) = project(&o.camera, p) {
                    let observed = o.depth[pix];
                    if observed > 0.0 && (d - observed).abs() <= depth_tolerance * observed {
                        row[o.mask[pix] as usize] += 1;
                    }
                }
            }
        });
    Ok(votes)
}

/// Unary costs U_i(l) = −ln max(share, floor), share = (votes_l + prior) / (Σ votes + L·prior).
/// With no votes every share is 1/L: the same cost for every label.
pub fn unary_costs(votes: &[u32], n_labels: usize, prior: f32, floor: f32) -> Vec<f64> {
    votes
        .chunks(n_labels.max(1))
        .flat_map(|row| {
            let total: f64 =
                row.iter().map(|&c| c as f64).sum::<f64>() + n_labels as f64 * prior as f64;
            row.iter().map(move |&c| {
                let share = if total > 0.0 {
                    (c as f64 + prior as f64) / total
                } else {
                    1.0 / n_labels as f64
                };
                -share.max(floor as f64).ln()
            })
        })
        .collect()
}

/// Undirected pairs (i < j) of the k-nearest-neighbour graph within `radius`, sorted: each
/// surfel keeps its `k` nearest others closer than `radius` (found in a hash grid of cells of
/// side `radius`), and a pair is kept when either end chose it.
pub fn neighbour_pairs(positions: &[[f32; 3]], k: usize, radius: f32) -> Vec<(u32, u32)> {
    if k == 0 || radius.is_nan() || radius <= 0.0 || positions.len() < 2 {
        return Vec::new();
    }
    let cell = |p: [f32; 3]| -> [i32; 3] { p.map(|x| (x / radius).floor() as i32) };
    let mut grid: HashMap<[i32; 3], Vec<u32>> = HashMap::new();
    for (i, &p) in positions.iter().enumerate() {
        if p.iter().all(|x| x.is_finite()) {
            grid.entry(cell(p)).or_default().push(i as u32);
        }
    }
    let r2 = radius * radius;
    let mut pairs: Vec<(u32, u32)> = positions
        .par_iter()
        .enumerate()
        .flat_map_iter(|(i, &p)| {
            let mut near: Vec<(f32, u32)> = Vec::new();
            if p.iter().all(|x| x.is_finite()) {
                let c = cell(p);
                for dx in -1..=1 {
                    for dy in -1..=1 {
                        for dz in -1..=1 {
                            let key = [c[0] + dx, c[1] + dy, c[2] + dz];
                            for &j in grid.get(&key).map(Vec::as_slice).unwrap_or(&[]) {
                                let q = positions[j as usize];
                                let d2 = (0..3).map(|a| (p[a] - q[a]).powi(2)).sum::<f32>();
                                if j as usize != i && d2 <= r2 {
                                    near.push((d2, j));
                                }
                            }
                        }
                    }
                }
            }
            // Ties broken by index so the graph does not depend on hash order.
            near.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            near.truncate(k);
            near.into_iter()
                .map(move |(_, j)| (i.min(j as usize) as u32, i.max(j as usize) as u32))
        })
        .collect();
    pairs.par_sort_unstable();
    pairs.dedup();
    pairs
}

/// Contrast-sensitive Potts weights (eq. of Boykov–Jolly, GrabCut) for each pair:
/// w_ij = λ · exp(−‖Δp‖² / (2 r²)) · exp(−(1 − max(n_i·n_j, 0)) / σ_n) · exp(−β ‖Δc‖²),
/// with β = 1 / (2 ⟨‖Δc‖²⟩) over all pairs, so the colour term adapts to the scene's contrast.
pub fn potts_weights(
    points: &SurfelPoints,
    pairs: &[(u32, u32)],
    params: &SegmentParams,
) -> Vec<(u32, u32, f64)> {
    let dc2 = |i: usize, j: usize| -> f64 {
        (0..3)
            .map(|a| (points.color[i][a] as f64 - points.color[j][a] as f64).powi(2))
            .sum()
    };
    let mean_dc2 = if pairs.is_empty() {
        0.0
    } else {
        pairs
            .iter()
            .map(|&(i, j)| dc2(i as usize, j as usize))
            .sum::<f64>()
            / pairs.len() as f64
    };
    let beta = if mean_dc2 > 0.0 { 0.5 / mean_dc2 } else { 0.0 };
    let r2 = (params.radius as f64).powi(2);
    pairs
        .par_iter()
        .map(|&(i, j)| {
            let (a, b) = (i as usize, j as usize);
            let dp2: f64 = (0..3)
                .map(|k| (points.position[a][k] as f64 - points.position[b][k] as f64).powi(2))
                .sum();
            let cos: f64 = (0..3)
                .map(|k| points.normal[a][k] as f64 * points.normal[b][k] as f64)
                .sum();
            let w = params.smoothness as f64
                * (-dp2 / (2.0 * r2)).exp()
                * (-(1.0 - cos.clamp(0.0, 1.0)) / params.normal_sigma as f64).exp()
                * (-beta * dc2(a, b)).exp();
            (i, j, w)
        })
        .collect()
}

/// A multi-label Potts energy E(l) = Σ_i U_i(l_i) + Σ_(i,j) w_ij [l_i ≠ l_j].
#[derive(Clone, Debug, PartialEq)]
pub struct Potts {
    pub n_labels: usize,
    /// U_i(l), `n × n_labels`, surfel-major.
    pub unary: Vec<f64>,
    /// (i, j, w_ij ≥ 0).
    pub edges: Vec<(u32, u32, f64)>,
}

impl Potts {
    pub fn node_count(&self) -> usize {
        self.unary.len() / self.n_labels.max(1)
    }

    pub fn energy(&self, labels: &[u8]) -> f64 {
        let l = self.n_labels;
        let data: f64 = labels
            .iter()
            .enumerate()
            .map(|(i, &x)| self.unary[i * l + x as usize])
            .sum();
        let smooth: f64 = self
            .edges
            .iter()
            .filter(|&&(i, j, _)| labels[i as usize] != labels[j as usize])
            .map(|e| e.2)
            .sum();
        data + smooth
    }

    /// Per node the label of least unary cost (ties: the lowest label).
    pub fn unary_argmin(&self) -> Vec<u8> {
        self.unary
            .chunks(self.n_labels)
            .map(|row| {
                let mut best = 0;
                for (l, &u) in row.iter().enumerate() {
                    if u < row[best] {
                        best = l;
                    }
                }
                best as u8
            })
            .collect()
    }

    /// α-expansion from `labels`: for each α, the binary move "keep l_i or switch to α" is
    /// solved exactly by a minimum cut (Potts is a metric, so every move energy is submodular;
    /// Kolmogorov–Zabih construction). A move is taken only when it lowers the energy, so the
    /// energy never increases. Stops after a sweep with no relative gain above 1e-9 or after
    /// `max_sweeps`. Returns the labels and the sweeps run.
    pub fn alpha_expansion(&self, mut labels: Vec<u8>, max_sweeps: usize) -> (Vec<u8>, usize) {
        let n = self.node_count();
        assert_eq!(labels.len(), n, "one label per node");
        let mut energy = self.energy(&labels);
        let mut graph = MaxFlow::new(n + 2);
        let mut coef = vec![0.0f64; n];
        let mut sweeps = 0;
        while sweeps < max_sweeps {
            sweeps += 1;
            let start = energy;
            for alpha in 0..self.n_labels as u8 {
                let proposal = self.expansion_move(&labels, alpha, &mut graph, &mut coef);
                let e = self.energy(&proposal);
                if e < energy {
                    energy = e;
                    labels = proposal;
                }
            }
            if start - energy <= 1e-9 * start.abs().max(1.0) {
                break;
            }
        }
        (labels, sweeps)
    }

    /// The optimal α-expansion of `labels` (the labelling of least energy among those where
    /// each node keeps its label or takes α; of several, the one changing fewest), by one minimum cut in `graph` (reused between
    /// calls; `coef` is scratch of one entry per node). Binary x_i = 1 ⇔ node i takes α ⇔ i
    /// ends on the sink side. Pair term with A = E(0,0), B = E(0,1), C = E(1,0), D = E(1,1):
    /// E = A + (C − A) x_i + (D − C) x_j + (B + C − A − D)(1 − x_i) x_j.
    pub fn expansion_move(
        &self,
        labels: &[u8],
        alpha: u8,
        graph: &mut MaxFlow,
        coef: &mut [f64],
    ) -> Vec<u8> {
        let n = labels.len();
        let l = self.n_labels;
        let (s, t) = (n, n + 1);
        graph.reset(n + 2);
        for (i, c) in coef.iter_mut().enumerate() {
            *c = self.unary[i * l + alpha as usize] - self.unary[i * l + labels[i] as usize];
        }
        for &(i, j, w) in &self.edges {
            let (li, lj) = (labels[i as usize], labels[j as usize]);
            let a = if li != lj { w } else { 0.0 };
            let b = if li != alpha { w } else { 0.0 };
            let c = if alpha != lj { w } else { 0.0 };
            coef[i as usize] += c - a;
            coef[j as usize] -= c;
            let pair = b + c - a;
            if pair > 0.0 {
                graph.add_edge(i as usize, j as usize, pair, 0.0);
            }
        }
        for (i, &c) in coef.iter().enumerate() {
            // c·x_i: paid when i is on the sink side (edge s → i cut); a negative c is
            // −c·(1 − x_i) plus a constant (edge i → t cut when i stays on the source side).
            if c > 0.0 {
                graph.add_edge(s, i, c, 0.0);
            } else if c < 0.0 {
                graph.add_edge(i, t, -c, 0.0);
            }
        }
        graph.solve(s, t);
        // Of all minimum cuts, the one that moves the fewest nodes to α: a node whose choice
        // costs nothing either way (e.g. seen by no view and cut off from every seen surfel)
        // keeps its label instead of drifting to whichever α comes last.
        let to_alpha = graph.sink_side(t);
        labels
            .iter()
            .zip(&to_alpha)
            .map(|(&li, &a)| if a { alpha } else { li })
            .collect()
    }
}
