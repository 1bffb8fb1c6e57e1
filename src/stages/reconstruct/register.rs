//! Stage 1, object poses per state (eq. state-assembly): the rigid T_{k,o} = (R, t) that maps an
//! object's points seen in the reference state onto its points seen in state k. Estimated from
//! the observations only; the dataset's ground-truth poses are for evaluation.
//!
//! **Global search.** Objects may be moved anywhere and turned by any angle, and some are
//! symmetric in shape (a ball, a vase) so that only their texture fixes the rotation. Every
//! rotation of a grid over SO(3) (the object's up axis on a Fibonacci sphere, +Y exactly
//! included, times turns about it, both at `rotation_step_deg`) is tried: the translation starts
//! at the centroid difference and takes three trimmed-mean steps towards the nearest target
//! points, then the rotation is scored by a truncated mean of a geometry + normal + colour
//! residual (truncation keeps partial overlaps from being punished). The best
//! few distinct rotations go on to refinement.
//!
//! **Refinement.** Iteratively reweighted Gauss–Newton ICP, coarse then fine spacing.
//! Correspondences are nearest neighbours in a joint space (x, y, z, w·f) of position and colour
//! feature f, so texture pulls matches to the right place where geometry cannot (a sphere turned
//! about its centre); the residual is point-to-plane plus a lighter point-to-point term (the
//! point-to-plane term alone cannot see such a turn). The candidate with the lowest final score
//! wins.
//!
//! **Colour under changing light.** States are lit differently, so raw RGB does not match. The
//! feature is the log chromaticity, which a per-channel gain (exposure, the light's colour) and
//! shading do not change, and, with a small weight, the log luminance; both relative to the
//! cloud's median ([`colour_features`]).
//!
//! Everything is deterministic for a given seed (the seed picks the coarse sample of points).

use super::init::{voxel_thin, PointCloud};
use crate::scene::synthetic::SplitMix;
use crate::scene::Rigid;
use crate::spatial::KdTree;
use crate::stats::median;
use glam::{DQuat, DVec3, Quat, Vec3};
use rayon::prelude::*;

// ---------------------------------------------------------------------------------------------
// Registration

/// Options of a [`Pair`] (and of [`register`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RegisterOptions {
    /// Seed of the coarse point sample.
    pub seed: u64,
    /// Step of the rotation grid, degrees (up-axis spacing and turn spacing).
    pub rotation_step_deg: f32,
    /// Source points scored per rotation in the global search.
    pub coarse_samples: usize,
    /// Distinct rotations refined by ICP.
    pub candidates: usize,
    /// Fraction of residuals kept by the trimmed means (the rest is taken as non-overlap).
    pub trim: f32,
    /// Colour weight in the joint correspondence space: one unit of colour feature counts as
    /// this many point spacings.
    pub colour_weight: f32,
    /// Scale of a colour-feature residual in the score (one unit of score).
    pub colour_sigma: f32,
    /// Weight of the point-to-point term relative to the point-to-plane one.
    pub point_to_point: f32,
    /// Gauss–Newton iterations per refinement level.
    pub icp_iterations: usize,
    /// Point spacing of the coarse level as a fraction of the object's bounding-box diagonal.
    /// The fine level uses a third of it. Neither goes below the clouds' median footprint.
    pub coarse_spacing: f32,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        RegisterOptions {
            seed: 0,
            // 15°: the ICP basin on textured shapes is ~20° (tests/recon_register.rs), so the
            // nearest grid rotation (at most ~10° away) is inside it.
            rotation_step_deg: 15.0,
            coarse_samples: 400,
            candidates: 12,
            trim: 0.8,
            colour_weight: 2.0,
            colour_sigma: 0.15,
            point_to_point: 0.3,
            icp_iterations: 30,
            coarse_spacing: 1.0 / 25.0,
        }
    }
}

/// A pose estimate and how well it fits, so callers can warn about bad fits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Registration {
    /// Maps source (reference-state) points onto target (state-k) points.
    pub transform: Rigid,
    /// Fraction of source points with a target point within 2 fine spacings after alignment.
    pub fitness: f32,
    /// RMS point-to-plane distance of those inliers, metres.
    pub rmse: f32,
    /// RMS colour-feature difference of those inliers.
    pub colour_rmse: f32,
    /// The trimmed score that chose this candidate (lower is better).
    pub score: f32,
    /// Geometry alone, lighting-free: the mean over every source point of r²/τ², r its
    /// point-to-plane distance to the nearest target point within τ = 2 fine spacings, and 1
    /// where there is none. 0 is a perfect fit of clouds that overlap wholly; it compares
    /// poses of one pair of clouds ([`Pair::best_fit`]).
    pub geometric_cost: f32,
    /// The fine point spacing used, metres.
    pub spacing: f32,
}

/// Residuals of the log ratio beyond this (ln units: a factor 1.65) are a specular highlight
/// or a shadow that moved, not shading ([`Pair::shading_residual`]).
pub const SHADING_TRUNCATION: f32 = 0.5;

/// Fewer matched points than this leave the 27 shading coefficients of
/// [`Pair::shading_residual`] underdetermined.
pub const MIN_SHADING_POINTS: usize = 60;

/// The 9 real spherical harmonics to order 2 of a unit vector, unnormalised (constant factors
/// do not change a least-squares fit): 1, x, y, z, xy, yz, zx, x² − y², 3z² − 1.
fn sh2(n: Vec3) -> [f64; 9] {
    let (x, y, z) = (n.x as f64, n.y as f64, n.z as f64);
    [
        1.0,
        x,
        y,
        z,
        x * y,
        y * z,
        z * x,
        x * x - y * y,
        3.0 * z * z - 1.0,
    ]
}

/// Fewer points than this on either side is not enough to register.
pub const MIN_POINTS: usize = 10;

/// Weight of the log luminance in the colour feature (see [`colour_features`]).
pub const LUMINANCE_WEIGHT: f32 = 0.15;

/// Radiance below this is noise; clamping keeps the logarithms finite.
const COLOUR_FLOOR: f32 = 1e-4;

/// Colour features of a cloud (see the module docs): per point, the log chromaticity
/// ln cᵢ − ⅓ Σⱼ ln cⱼ (×2, components r and g) and 0.15 ln luminance, each minus its median over
/// the cloud. A per-channel gain (exposure, white balance of the light) cancels exactly; shading
/// changes only the luminance component, hence its small weight: a shading ratio of 2.5 between
/// two lightings (ln 2.5 ≈ 0.9) then costs about one σ_f.
pub fn colour_features(rgb: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let raw: Vec<[f32; 3]> = rgb
        .iter()
        .map(|c| {
            let l = log_rgb(*c);
            let m = (l[0] + l[1] + l[2]) / 3.0;
            [2.0 * (l[0] - m), 2.0 * (l[1] - m), LUMINANCE_WEIGHT * m]
        })
        .collect();
    let med: [f32; 3] = std::array::from_fn(|d| {
        median(&mut raw.iter().map(|f| f[d]).collect::<Vec<_>>()).unwrap_or(0.0)
    });
    raw.iter()
        .map(|f| std::array::from_fn(|d| f[d] - med[d]))
        .collect()
}

/// ln of an observed RGB, floored at [`COLOUR_FLOOR`]: the one log colour of
/// [`colour_features`] and [`Pair::shading_residual`].
fn log_rgb(c: [f32; 3]) -> [f32; 3] {
    c.map(|x| x.max(COLOUR_FLOOR).ln())
}

/// One side of a registration at one spacing.
struct Side {
    pos: Vec<Vec3>,
    normal: Vec<Vec3>,
    feat: Vec<Vec3>,
    /// ln of the observed RGB ([`log_rgb`]), for [`Pair::shading_residual`].
    log_rgb: Vec<Vec3>,
}

impl Side {
    fn new(cloud: &PointCloud, spacing: f32) -> Side {
        let thin = voxel_thin(cloud, spacing);
        Side {
            pos: thin.position.iter().map(|p| Vec3::from_array(*p)).collect(),
            normal: thin.normal.iter().map(|n| Vec3::from_array(*n)).collect(),
            feat: colour_features(&thin.rgb)
                .into_iter()
                .map(Vec3::from_array)
                .collect(),
            log_rgb: thin
                .rgb
                .iter()
                .map(|&c| Vec3::from_array(log_rgb(c)))
                .collect(),
        }
    }

    fn centroid(&self) -> Vec3 {
        self.pos.iter().copied().sum::<Vec3>() / self.pos.len().max(1) as f32
    }

    fn geo_tree(&self) -> KdTree<3> {
        KdTree::new(&self.pos.iter().map(|p| p.to_array()).collect::<Vec<_>>())
    }

    fn joint(&self, i: usize, p: Vec3, w: f32) -> [f32; 6] {
        let f = self.feat[i] * w;
        [p.x, p.y, p.z, f.x, f.y, f.z]
    }
}

/// The rotation grid: up axes on a Fibonacci sphere (+Y first, exactly), each with turns about
/// it every `step` radians.
pub fn rotation_grid(step_deg: f32) -> Vec<Quat> {
    let step = step_deg.to_radians().max(1e-3);
    // A spherical cap of angular radius step/2 per axis: area ≈ π (step/2)² of 4π.
    let n_up = ((16.0 / (step * step)).ceil() as usize).max(1);
    let n_turn = ((std::f32::consts::TAU / step).ceil() as usize).max(1);
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let mut ups = vec![Vec3::Y];
    for i in 1..n_up {
        let y = 1.0 - 2.0 * i as f32 / (n_up - 1).max(1) as f32;
        let r = (1.0 - y * y).max(0.0).sqrt();
        let phi = golden * i as f32;
        ups.push(Vec3::new(r * phi.cos(), y, r * phi.sin()));
    }
    let mut out = Vec::with_capacity(ups.len() * n_turn);
    for up in ups {
        let tilt = Quat::from_rotation_arc(Vec3::Y, up.normalize());
        for j in 0..n_turn {
            let turn = Quat::from_rotation_y(j as f32 * std::f32::consts::TAU / n_turn as f32);
            out.push((tilt * turn).normalize());
        }
    }
    out
}

struct Scorer<'a> {
    src: &'a Side,
    tgt: &'a Side,
    tree: &'a KdTree<3>,
    sample: &'a [usize],
    spacing: f32,
    opts: &'a RegisterOptions,
}

impl Scorer<'_> {
    /// Translation for rotation `q` (centroids, then three trimmed steps), and its score.
    fn fit_translation(&self, q: Quat) -> (Vec3, f32) {
        let mut t = self.tgt.centroid() - q * self.src.centroid();
        let mut d = Vec::with_capacity(self.sample.len());
        for _ in 0..3 {
            d.clear();
            for &i in self.sample {
                let p = q * self.src.pos[i] + t;
                if let Some((j, d2)) = self.tree.nearest(&p.to_array()) {
                    d.push((d2, self.tgt.pos[j] - p));
                }
            }
            if d.is_empty() {
                break;
            }
            let keep = ((d.len() as f32 * self.opts.trim).ceil() as usize).clamp(1, d.len());
            d.select_nth_unstable_by(keep - 1, |a, b| a.0.total_cmp(&b.0));
            t += d[..keep].iter().map(|x| x.1).sum::<Vec3>() / keep as f32;
        }
        (t, self.score(q, t, self.sample))
    }

    /// Mean over `idx` of the truncated cost min(τ, |Δx|²/h² + 2 (1 − n·n') + |Δf|²/σ_f²) at
    /// the geometric nearest neighbour, τ = [`OUTLIER_COST`], or [`MISS_COST`] when no target
    /// point is within 3h. Truncation rather than trimming: with partial overlap a trimmed mean
    /// prefers a wrong pose that lays one observed cap onto the other over the true pose that
    /// leaves the unseen parts unmatched; and a point over unseen surface costs less than one
    /// over seen surface of the wrong colour, so a symmetric shape is not turned to overlap more.
    fn score(&self, q: Quat, t: Vec3, idx: &[usize]) -> f32 {
        let h2 = self.spacing * self.spacing;
        let s2 = self.opts.colour_sigma * self.opts.colour_sigma;
        let total: f32 = idx
            .iter()
            .map(|&i| {
                let p = q * self.src.pos[i] + t;
                let Some((j, d2)) = self.tree.nearest(&p.to_array()) else {
                    return MISS_COST;
                };
                if d2 > 9.0 * h2 {
                    return MISS_COST;
                }
                let n = q * self.src.normal[i];
                let df = self.src.feat[i] - self.tgt.feat[j];
                let e =
                    d2 / h2 + 2.0 * (1.0 - n.dot(self.tgt.normal[j])) + df.length_squared() / s2;
                e.min(OUTLIER_COST)
            })
            .sum();
        total / idx.len().max(1) as f32
    }
}

/// Largest cost of a source point over observed target surface: 16, a 4σ residual.
pub const OUTLIER_COST: f32 = 16.0;

/// Cost of a source point with no target surface near it (a part the state did not see): 4, a
/// 2σ residual, below [`OUTLIER_COST`].
pub const MISS_COST: f32 = 4.0;

/// One ICP level: Gauss–Newton on (ω, δt) with joint position–colour correspondences.
fn icp(level: &Level, mut q: DQuat, mut t: DVec3, opts: &RegisterOptions) -> (DQuat, DVec3) {
    let (src, tgt, spacing, tree) = (&level.src, &level.tgt, level.spacing, &level.joint);
    let w = level.colour_scale;
    // Matches farther than this are not the same surface.
    let gate = 4.0 * spacing;
    for _ in 0..opts.icp_iterations {
        let qf = q.as_quat();
        let tf = t.as_vec3();
        let matches: Vec<(usize, usize, f32)> = (0..src.pos.len())
            .into_par_iter()
            .filter_map(|i| {
                let p = qf * src.pos[i] + tf;
                let (j, _) = tree.nearest(&src.joint(i, p, w))?;
                let d2 = p.distance_squared(tgt.pos[j]);
                let facing = (qf * src.normal[i]).dot(tgt.normal[j]) > 0.0;
                (d2 < gate * gate && facing).then_some((i, j, d2))
            })
            .collect();
        if matches.len() < 6 {
            break;
        }
        let mut d: Vec<f32> = matches.iter().map(|m| m.2).collect();
        let keep = ((d.len() as f32 * opts.trim).ceil() as usize).clamp(1, d.len());
        let cut = *d.select_nth_unstable_by(keep - 1, f32::total_cmp).1;
        let beta = opts.point_to_point as f64;
        let (mut a, mut b) = ([[0.0f64; 6]; 6], [0.0f64; 6]);
        let mut add = |jrow: [f64; 6], r: f64, wt: f64| {
            for u in 0..6 {
                b[u] -= wt * jrow[u] * r;
                for v in 0..6 {
                    a[u][v] += wt * jrow[u] * jrow[v];
                }
            }
        };
        for &(i, j, d2) in &matches {
            if d2 > cut {
                continue;
            }
            let x = q * src.pos[i].as_dvec3() + t;
            let y = tgt.pos[j].as_dvec3();
            let n = tgt.normal[j].as_dvec3();
            let e = x - y;
            // x(ω, δt) = exp(ω) x + δt: ∂x/∂ω = −[x]×, so ∂(n·e)/∂ω = x × n.
            let c = x.cross(n);
            add([c.x, c.y, c.z, n.x, n.y, n.z], n.dot(e), 1.0);
            for (k, axis) in [DVec3::X, DVec3::Y, DVec3::Z].into_iter().enumerate() {
                let c = x.cross(axis);
                add([c.x, c.y, c.z, axis.x, axis.y, axis.z], e[k], beta);
            }
        }
        let Some(xi) = solve_spd(a, b) else { break };
        let omega = DVec3::new(xi[0], xi[1], xi[2]);
        let dt = DVec3::new(xi[3], xi[4], xi[5]);
        let dq = if omega.length() > 0.0 {
            DQuat::from_axis_angle(omega.normalize(), omega.length())
        } else {
            DQuat::IDENTITY
        };
        q = (dq * q).normalize();
        t = dq * t + dt;
        if omega.length() < 1e-6 && dt.length() < 1e-6 {
            break;
        }
    }
    (q, t)
}

/// Solves the 6×6 normal equations (Cholesky with a tiny ridge); `None` if singular.
/// Solves A x = b for a symmetric positive semi-definite A (normal equations) by Cholesky, with
/// a ridge of 1e-9 of the largest diagonal entry (a direction the data does not constrain then
/// gets a tiny, finite answer); `None` when A is zero, not finite or indefinite.
fn solve_spd<const N: usize>(mut a: [[f64; N]; N], b: [f64; N]) -> Option<[f64; N]> {
    let scale = (0..N).map(|i| a[i][i]).fold(0.0, f64::max);
    if scale <= 0.0 || !scale.is_finite() {
        return None;
    }
    for (i, row) in a.iter_mut().enumerate() {
        row[i] += 1e-9 * scale;
    }
    let mut l = [[0.0f64; N]; N];
    for i in 0..N {
        for j in 0..=i {
            let s: f64 = a[i][j] - (0..j).map(|k| l[i][k] * l[j][k]).sum::<f64>();
            if i == j {
                if s <= 0.0 {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    let mut y = [0.0; N];
    for i in 0..N {
        y[i] = (b[i] - (0..i).map(|k| l[i][k] * y[k]).sum::<f64>()) / l[i][i];
    }
    let mut x = [0.0; N];
    for i in (0..N).rev() {
        x[i] = (y[i] - (i + 1..N).map(|k| l[k][i] * x[k]).sum::<f64>()) / l[i][i];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

fn bbox_diagonal(c: &PointCloud) -> f32 {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for p in &c.position {
        lo = lo.min(Vec3::from_array(*p));
        hi = hi.max(Vec3::from_array(*p));
    }
    (hi - lo).length()
}

/// One level of a [`Pair`]: both clouds thinned at half its scale, and the target's two k-d
/// trees (positions for scores and fit quality; joint position–colour points for ICP), built
/// once for every pose asked of the pair.
struct Level {
    /// Geometric scale (scores, gates), metres.
    spacing: f32,
    /// Length of one unit of colour feature in the joint space: `colour_weight` spacings.
    colour_scale: f32,
    src: Side,
    tgt: Side,
    geo: KdTree<3>,
    joint: KdTree<6>,
}

impl Level {
    /// A [`Scorer`] of this level's clouds over the source points `sample`.
    fn scorer<'a>(&'a self, sample: &'a [usize], opts: &'a RegisterOptions) -> Scorer<'a> {
        Scorer {
            src: &self.src,
            tgt: &self.tgt,
            tree: &self.geo,
            sample,
            spacing: self.spacing,
            opts,
        }
    }

    fn new(source: &PointCloud, target: &PointCloud, spacing: f32, opts: &RegisterOptions) -> Self {
        let src = Side::new(source, spacing / 2.0);
        let tgt = Side::new(target, spacing / 2.0);
        let colour_scale = opts.colour_weight * spacing;
        let joint: Vec<[f32; 6]> = (0..tgt.pos.len())
            .map(|j| tgt.joint(j, tgt.pos[j], colour_scale))
            .collect();
        Level {
            spacing,
            colour_scale,
            geo: tgt.geo_tree(),
            joint: KdTree::new(&joint),
            src,
            tgt,
        }
    }
}

/// One object's points in two states (source: the reference state; target: state k), prepared
/// once for every question stage 1 asks of them: a global [`Pair::register`], the
/// [`Pair::polish`] of a pose found otherwise, the [`Pair::best_fit`] of several hypotheses,
/// the [`Pair::evaluate`] of any pose. Thinning both clouds at two levels and building the
/// target's trees is then done once per pair, not once per question (and per ICP run).
pub struct Pair {
    coarse: Level,
    fine: Level,
    /// The source cloud's centroid and bounding-box diagonal, metres ([`PolishLimits`]).
    centroid: Vec3,
    diagonal: f32,
    opts: RegisterOptions,
}

impl Pair {
    /// `None` when either cloud has fewer than [`MIN_POINTS`] points. The coarse scale is the
    /// larger of `coarse_spacing` × the bounding-box diagonal and the median pixel footprint
    /// (nearest neighbours are that far apart even when aligned); the fine scale is half of it.
    /// Clouds are thinned at half a level's scale, which keeps nearly every observed point at
    /// the fine level.
    pub fn new(source: &PointCloud, target: &PointCloud, opts: &RegisterOptions) -> Option<Pair> {
        if source.len() < MIN_POINTS || target.len() < MIN_POINTS {
            return None;
        }
        let diagonal = bbox_diagonal(source);
        let diag = diagonal.max(bbox_diagonal(target));
        let footprint = median(
            &mut source
                .footprint
                .iter()
                .chain(&target.footprint)
                .copied()
                .collect::<Vec<_>>(),
        )
        .unwrap_or(0.0);
        let coarse = (diag * opts.coarse_spacing).max(footprint).max(1e-6);
        let centroid = source
            .position
            .iter()
            .fold(Vec3::ZERO, |a, p| a + Vec3::from_array(*p))
            / source.len() as f32;
        Some(Pair {
            coarse: Level::new(source, target, coarse, opts),
            fine: Level::new(source, target, coarse / 2.0, opts),
            centroid,
            diagonal,
            opts: *opts,
        })
    }

    /// ICP at the coarse, then the fine level from (q, t), and the fit quality reached.
    fn refine(&self, q: DQuat, t: DVec3) -> Registration {
        let (q, t) = icp(&self.coarse, q, t, &self.opts);
        let (q, t) = icp(&self.fine, q, t, &self.opts);
        self.quality(q.as_quat(), t.as_vec3())
    }

    /// Score and fit quality of (q, t) on the fine level.
    fn quality(&self, q: Quat, t: Vec3) -> Registration {
        let lv = &self.fine;
        let all: Vec<usize> = (0..lv.src.pos.len()).collect();
        let score = lv.scorer(&all, &self.opts).score(q, t, &all);
        let inlier = 2.0 * lv.spacing;
        let mut n_in = 0usize;
        let (mut geo2, mut col2) = (0.0f64, 0.0f64);
        for i in 0..lv.src.pos.len() {
            let p = q * lv.src.pos[i] + t;
            if let Some((j, _)) = lv.geo.nearest_within(&p.to_array(), inlier * inlier) {
                n_in += 1;
                geo2 += (lv.tgt.normal[j].dot(p - lv.tgt.pos[j]) as f64).powi(2);
                col2 += (lv.src.feat[i] - lv.tgt.feat[j]).length_squared() as f64;
            }
        }
        let denom = n_in.max(1) as f64;
        let n = lv.src.pos.len().max(1) as f64;
        let geometric_cost =
            ((geo2 / (inlier as f64).powi(2) + (lv.src.pos.len() - n_in) as f64) / n) as f32;
        Registration {
            transform: Rigid {
                rotation: q.normalize().to_array(),
                translation: t.to_array(),
            },
            fitness: n_in as f32 / lv.src.pos.len().max(1) as f32,
            rmse: (geo2 / denom).sqrt() as f32,
            colour_rmse: (col2 / denom).sqrt() as f32,
            score,
            geometric_cost,
            spacing: lv.spacing,
        }
    }

    /// The fit quality of a given transform, as [`Pair::register`] reports it (for
    /// diagnostics and for comparing estimates).
    pub fn evaluate(&self, transform: &Rigid) -> Registration {
        self.quality(
            transform.quat().normalize(),
            Vec3::from_array(transform.translation),
        )
    }

    /// Estimates T mapping the source onto the target (see the module docs): the global search
    /// over the rotation grid, then ICP from the best few distinct rotations; the lowest fine
    /// score wins.
    pub fn register(&self) -> Registration {
        let (lv, opts) = (&self.coarse, &self.opts);
        let mut rng = SplitMix(opts.seed);
        let mut sample: Vec<usize> = (0..lv.src.pos.len()).collect();
        for i in (1..sample.len()).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            sample.swap(i, j);
        }
        sample.truncate(opts.coarse_samples.max(MIN_POINTS));
        sample.sort_unstable();
        let scorer = lv.scorer(&sample, opts);
        let grid = rotation_grid(opts.rotation_step_deg);
        let mut scored: Vec<(f32, usize, Vec3)> = grid
            .par_iter()
            .enumerate()
            .map(|(r, q)| {
                let (t, s) = scorer.fit_translation(*q);
                (s, r, t)
            })
            .collect();
        scored.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        // Distinct candidates: farther apart than one grid step in rotation.
        let min_sep = opts.rotation_step_deg.to_radians();
        let mut cands: Vec<(Quat, Vec3)> = Vec::new();
        for &(_, r, t) in &scored {
            if cands.len() >= opts.candidates.max(1) {
                break;
            }
            if cands
                .iter()
                .all(|(q, _)| q.angle_between(grid[r]) > min_sep)
            {
                cands.push((grid[r], t));
            }
        }
        // The grid is never empty (+Y with one turn at least), so neither are the candidates.
        cands
            .iter()
            .map(|&(q, t)| self.refine(q.as_dquat(), t.as_dvec3()))
            .min_by(|a, b| a.score.total_cmp(&b.score))
            .unwrap_or_else(|| self.evaluate(&Rigid::IDENTITY))
    }

    /// ICP (coarse, then fine level; no global search) from each of `starts`, for a pose
    /// another method found roughly: the rendered alignment of [`super::align`], whose score
    /// picks the right basin where point clouds cannot but is too blunt to place an object to
    /// the millimetre. `starts[0]` is that pose and decides the basin: a fixed point beyond
    /// `limits` of it, or fitting worse than it does, is dropped, and so is a further start
    /// (e.g. the registration's own estimate) lying beyond `limits` of it. Of what remains
    /// (each start's fixed point, and the further starts as they are), the lowest
    /// [`Registration::geometric_cost`] wins, as in [`Pair::best_fit`]: colour guides ICP's
    /// correspondences but does not vote here, since a reflection or a shadow that moved with
    /// the lighting can make the trimmed score prefer a pose turned the few degrees that lay
    /// it over its old place (the demo's steel pot, whose handles alone fix its turn: the
    /// score chose registration's estimate 5.6° off, the geometry a fixed point 1.6° off).
    /// Several starts matter where ICP can slide along a near-symmetry of the shape (a plain
    /// box or tin seen in part): the fixed point reached from a rough start may then fit no
    /// better than registration's estimate, which already lies at the bottom of the same
    /// basin and is kept. `None` when nothing remains (or there is no start): keep `starts[0]`
    /// then.
    pub fn polish(&self, starts: &[Rigid], limits: &PolishLimits) -> Option<Registration> {
        let first = starts.first()?;
        let q0 = first.quat().normalize();
        let start = self.evaluate(first);
        let reach = limits.translation * self.diagonal;
        let c = self.centroid.to_array();
        let near = |r: &Rigid| {
            let moved = (Vec3::from_array(r.transform_point(c))
                - Vec3::from_array(first.transform_point(c)))
            .length();
            r.quat().angle_between(q0).to_degrees() <= limits.rotation_deg && moved <= reach
        };
        starts
            .iter()
            .enumerate()
            .filter(|(_, s)| near(s))
            .flat_map(|(k, s)| {
                let polished = self.refine(
                    s.quat().normalize().as_dquat(),
                    Vec3::from_array(s.translation).as_dvec3(),
                );
                // A further start (registration's) is a fixed point of the fine level already,
                // which the coarse level can pull away from: it competes as it is too.
                let kept = (k > 0).then(|| self.evaluate(s));
                std::iter::once(polished).chain(kept)
            })
            .filter(|r| near(&r.transform) && r.fitness >= limits.fitness * start.fitness)
            .min_by(|a, b| a.geometric_cost.total_cmp(&b.geometric_cost))
    }

    /// How well `transform` carries the reference state's colours onto what state k saw, once
    /// the change of lighting is allowed for: the texture's verdict on a pose, where geometry
    /// cannot choose (a shape symmetric under a turn, told apart by its texture only).
    ///
    /// Model. A diffuse point of albedo a and normal n has radiance a·E(n) with E the
    /// irradiance of its state's lighting, a smooth function of the normal. For a source point
    /// i carried to its nearest target point j (fine level, within 2 spacings, normals within
    /// 60° of each other so that a thin panel's front does not pair with its back), the log
    /// ratio d_ij = ln c_j − ln c_i (per channel) is then ln E_k(n) − ln E_ref(n'), smooth in
    /// n when the pose is right; a wrong pose adds ln a(x) − ln a(S x), the texture against
    /// itself moved, which no smooth function of the normal explains. Per channel, d is fitted
    /// by least squares as a quadratic in the carried normal n = R n_i (the 9 functions of
    /// real spherical harmonics to order 2, in which irradiance is nearly exact: Ramamoorthi
    /// and Hanrahan 2001), refitted without the points whose residual exceeds
    /// [`SHADING_TRUNCATION`] (speculars, shadows that moved); the result is the root mean
    /// of min(r², τ²) over the matched points and channels, ln units (lower is better).
    /// Points darker than the colour floor carry no ratio and are skipped. `None` when fewer
    /// than [`MIN_SHADING_POINTS`] points pair up.
    pub fn shading_residual(&self, transform: &Rigid) -> Option<f32> {
        let lv = &self.fine;
        let q = transform.quat().normalize();
        let t = Vec3::from_array(transform.translation);
        let inlier = 2.0 * lv.spacing;
        let floor = COLOUR_FLOOR.ln() + 1e-3;
        let mut rows: Vec<([f64; 9], Vec3)> = Vec::new();
        for i in 0..lv.src.pos.len() {
            let p = q * lv.src.pos[i] + t;
            let n = q * lv.src.normal[i];
            let Some((j, _)) = lv.geo.nearest_within(&p.to_array(), inlier * inlier) else {
                continue;
            };
            if lv.tgt.normal[j].dot(n) < 0.5
                || lv.src.log_rgb[i].min_element() < floor
                || lv.tgt.log_rgb[j].min_element() < floor
            {
                continue;
            }
            rows.push((sh2(n), lv.tgt.log_rgb[j] - lv.src.log_rgb[i]));
        }
        if rows.len() < MIN_SHADING_POINTS {
            return None;
        }
        let tau = SHADING_TRUNCATION as f64;
        let fit = |keep: &dyn Fn(usize) -> bool| -> Option<[[f64; 9]; 3]> {
            let mut a = [[0.0f64; 9]; 9];
            let mut b = [[0.0f64; 9]; 3];
            for (k, (phi, d)) in rows.iter().enumerate() {
                if !keep(k) {
                    continue;
                }
                for r in 0..9 {
                    for c in 0..9 {
                        a[r][c] += phi[r] * phi[c];
                    }
                    for ch in 0..3 {
                        b[ch][r] += phi[r] * d[ch] as f64;
                    }
                }
            }
            Some([
                solve_spd(a, b[0])?,
                solve_spd(a, b[1])?,
                solve_spd(a, b[2])?,
            ])
        };
        let residual = |coef: &[[f64; 9]; 3], k: usize| -> [f64; 3] {
            let (phi, d) = &rows[k];
            std::array::from_fn(|ch| {
                d[ch] as f64 - (0..9).map(|r| coef[ch][r] * phi[r]).sum::<f64>()
            })
        };
        let first = fit(&|_| true)?;
        let inliers: Vec<bool> = (0..rows.len())
            .map(|k| residual(&first, k).iter().all(|r| r.abs() <= tau))
            .collect();
        let coef = if inliers.iter().filter(|&&k| k).count() >= MIN_SHADING_POINTS {
            fit(&|k| inliers[k])?
        } else {
            first
        };
        let sum: f64 = (0..rows.len())
            .map(|k| {
                residual(&coef, k)
                    .iter()
                    .map(|r| (r * r).min(tau * tau))
                    .sum::<f64>()
            })
            .sum();
        Some((sum / (3 * rows.len()) as f64).sqrt() as f32)
    }

    /// Of `hypotheses` (poses from different basins, each already polished in its own), the
    /// one whose geometry fits best: the lowest [`Registration::geometric_cost`], with its
    /// index. Colour does not vote: under another lighting a chrome object's reflections or a
    /// shadow move across its surface, and the trimmed score's colour term can then prefer a
    /// pose turned upside down. Where two hypotheses differ by a symmetry of the shape the
    /// costs tie and either is right for what follows (the translation is the same). `None`
    /// when there is no hypothesis.
    pub fn best_fit(&self, hypotheses: &[Rigid]) -> Option<(usize, Registration)> {
        hypotheses
            .iter()
            .map(|h| self.evaluate(h))
            .enumerate()
            .min_by(|a, b| a.1.geometric_cost.total_cmp(&b.1.geometric_cost))
    }
}

/// Options of [`Pair::choose_turn`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TurnOptions {
    /// Turns tried about the vertical, degrees apart (each then polished by ICP, whose basin
    /// is ~20° wide: [`RegisterOptions::rotation_step_deg`]).
    pub step_deg: f32,
    /// A turned pose ties with the best geometric fit when its cost is within
    /// max(`tie_relative` × the best cost, `tie_absolute`) of it.
    pub tie_relative: f32,
    pub tie_absolute: f32,
    /// A tie replaces the given pose only when its shading residual is lower by this share.
    pub shading_margin: f32,
    /// A given pose that is no tie but fits within this factor of the best cost stays when
    /// its shading residual is lower than the best tie's by `shading_margin`.
    pub veto_cost: f32,
}

impl Default for TurnOptions {
    fn default() -> Self {
        TurnOptions {
            step_deg: 15.0,
            // Measured on bedroom's 10 object-states (15° steps, polished): poses that differ
            // by a symmetry of the shape cost 0.0004-0.0058 (a plain lamp, a box cushion
            // four ways), a pose one ICP basin off 0.02-0.03 (the lamp turned 15°), a
            // different pose of an asymmetric shape 0.058 against 0.012 (the books turned
            // half way); twice the best cost or 0.01 separates them.
            tie_relative: 1.0,
            tie_absolute: 0.01,
            // Among the lamp's ties (its striped shade, the same after a half turn) the two
            // right turns scored 0.231 / 0.235 in one state and 0.276 / 0.258 in the other,
            // the wrong ones 0.31-0.34; the cushion's four (a noise texture of ~4 % contrast)
            // 0.175-0.185. So the residual's own scatter is up to ~7 %, and a wrong turn of a
            // texture that shows costs 25-35 % more: 15 % keeps noise from turning a pose.
            shading_margin: 0.15,
            // Study's thin sign: its half turn fit the points better (0.041 against 0.108:
            // front and back are 1.2 cm apart) and its stripes said no (0.40 against 0.33).
            // Kitchen's plain glossy mug, given 142° off: 0.057 against 0.001, a gap no
            // highlight should overrule (its wrong pose's residual was the lower, 0.17 / 0.20).
            veto_cost: 3.0,
        }
    }
}

/// What [`Pair::choose_turn`] decided.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TurnChoice {
    /// The chosen pose (the given one, polished turns of it, or the given one unchanged).
    pub transform: Rigid,
    /// The turn about the vertical it started from, degrees (0: the given pose).
    pub turn_deg: f32,
    /// Turns whose geometry tied with the best fit.
    pub ties: usize,
}

impl Pair {
    /// Several hypotheses kept until the texture decides between them: `pose` turned about the
    /// vertical `up` through the object (its source centroid carried by `pose`) by every
    /// multiple of `step_deg`, each polished by ICP ([`Pair::polish`]) in its own basin, and
    /// polished again from the turned rotation with the translation fitted afresh (the
    /// registration's trimmed steps from the centroids), the better fit of the two kept. The
    /// best geometric fit ([`Registration::geometric_cost`]) defines the ties (see
    /// [`TurnOptions`]): turns the shape cannot tell apart, as a solid of revolution or a box
    /// four ways. When the given pose is among them, it stays unless another tie carries the
    /// reference colours onto state k with a clearly lower [`Pair::shading_residual`] (a
    /// striped shade turned); when it is not (the geometry found a better basin: an object
    /// registration lost), the tie with the lowest shading residual is taken, the best fit
    /// when no tie has one, unless the given pose fits nearly as well
    /// ([`TurnOptions::veto_cost`]) and its own residual is clearly lower than that tie's: the
    /// texture vetoes the geometry. Objects in rooms are turned about the vertical when moved,
    /// which is why only those turns are tried: any other rotation stays as registration found
    /// it.
    /// Turns are evaluated in parallel and collected in order, so the choice does not depend
    /// on the thread count.
    pub fn choose_turn(
        &self,
        pose: &Rigid,
        up: Vec3,
        limits: &PolishLimits,
        opts: &TurnOptions,
    ) -> TurnChoice {
        let up = up.normalize_or(Vec3::Y);
        let centre = Vec3::from_array(pose.transform_point(self.centroid.to_array()));
        let n = ((360.0 / opts.step_deg.max(1.0)).round() as usize).max(1);
        let all: Vec<usize> = (0..self.coarse.src.pos.len()).collect();
        let scorer = self.coarse.scorer(&all, &self.opts);
        let fits: Vec<(f32, Registration)> = (0..n)
            .into_par_iter()
            .map(|s| {
                let deg = s as f32 * 360.0 / n as f32;
                if s == 0 {
                    return (0.0, self.evaluate(pose));
                }
                let q = Quat::from_axis_angle(up, deg.to_radians());
                let turned = Rigid {
                    rotation: q.to_array(),
                    translation: (centre - q * centre).to_array(),
                }
                .compose(pose);
                // Turned about its own centroid the object stays where `pose` put it; when
                // that place is wrong too (an object registration lost), the translation
                // fitted afresh to the turned rotation is a second start.
                let rotation = turned.quat().normalize();
                let refit = Rigid {
                    rotation: rotation.to_array(),
                    translation: scorer.fit_translation(rotation).0.to_array(),
                };
                let fit = [turned, refit]
                    .iter()
                    .map(|s| {
                        self.polish(&[*s], limits)
                            .unwrap_or_else(|| self.evaluate(s))
                    })
                    .min_by(|a, b| a.geometric_cost.total_cmp(&b.geometric_cost))
                    .unwrap_or_else(|| self.evaluate(&turned));
                (deg, fit)
            })
            .collect();
        let best = fits
            .iter()
            .map(|(_, r)| r.geometric_cost)
            .fold(f32::INFINITY, f32::min);
        let reach = best + (opts.tie_relative * best).max(opts.tie_absolute);
        let ties: Vec<usize> = (0..n)
            .filter(|&s| fits[s].1.geometric_cost <= reach)
            .collect();
        let shading: Vec<Option<f32>> = ties
            .par_iter()
            .map(|&s| self.shading_residual(&fits[s].1.transform))
            .collect();
        let lowest = (0..ties.len())
            .filter_map(|i| shading[i].map(|v| (i, v)))
            .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        let chosen = match (ties.first() == Some(&0), lowest) {
            // The given pose ties: another tie must be clearly better lit.
            (true, Some((i, v))) => match shading[0] {
                Some(given) if v < given * (1.0 - opts.shading_margin) => ties[i],
                _ => 0,
            },
            (true, None) => 0,
            // The geometry prefers another basin, unless the given pose is clearly better lit
            // than all of it: a thin panel's front and back are a few millimetres apart, and
            // the turned panel can fit the points better while its texture says otherwise.
            (false, Some((i, v))) => {
                let near = fits[0].1.geometric_cost <= opts.veto_cost * best;
                match near.then(|| self.shading_residual(pose)).flatten() {
                    Some(given) if given < v * (1.0 - opts.shading_margin) => 0,
                    _ => ties[i],
                }
            }
            (false, None) => (0..n)
                .min_by(|&a, &b| {
                    fits[a]
                        .1
                        .geometric_cost
                        .total_cmp(&fits[b].1.geometric_cost)
                })
                .unwrap_or(0),
        };
        TurnChoice {
            transform: fits[chosen].1.transform,
            turn_deg: fits[chosen].0,
            ties: ties.len(),
        }
    }
}

/// [`Pair::evaluate`] of a given transform. `None` when either cloud has fewer than
/// [`MIN_POINTS`] points.
pub fn evaluate(
    source: &PointCloud,
    target: &PointCloud,
    transform: &Rigid,
    opts: &RegisterOptions,
) -> Option<Registration> {
    Some(Pair::new(source, target, opts)?.evaluate(transform))
}

/// [`Pair::register`]: T mapping `source` onto `target`. `None` when either cloud has fewer
/// than [`MIN_POINTS`] points.
pub fn register(
    source: &PointCloud,
    target: &PointCloud,
    opts: &RegisterOptions,
) -> Option<Registration> {
    Some(Pair::new(source, target, opts)?.register())
}

/// How far [`Pair::polish`] may move a pose: a local refinement inside the ICP basin (~20° on
/// textured shapes, see [`RegisterOptions::rotation_step_deg`]), not a new search.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PolishLimits {
    /// Largest rotation change, degrees.
    pub rotation_deg: f32,
    /// Largest move of the source cloud's centroid, as a share of its bounding-box diagonal.
    pub translation: f32,
    /// The polished fit must keep at least this share of the starting pose's fitness.
    pub fitness: f32,
}

impl Default for PolishLimits {
    fn default() -> Self {
        // Half the basin in rotation; a quarter of the object in translation (a 20 cm object:
        // 5 cm). The alignment's errors this polishes were 0.6-5.7° and 0.6-2 cm on bedroom.
        PolishLimits {
            rotation_deg: 10.0,
            translation: 0.25,
            fitness: 0.95,
        }
    }
}

/// The [`Pair`] of every object in every state with the reference state `states[0]`:
/// `pairs[j][o]` maps object `object_ids[o]` from `states[0]` into `states[j]` (row 0 pairs the
/// reference state with itself); `None` when the object is too sparsely seen in state j or in
/// the reference state.
pub fn object_pairs(
    states: &[PointCloud],
    object_ids: &[u8],
    opts: &RegisterOptions,
) -> Vec<Vec<Option<Pair>>> {
    let Some(reference) = states.first() else {
        return Vec::new();
    };
    let refs: Vec<PointCloud> = object_ids
        .iter()
        .map(|&id| reference.with_mask(id))
        .collect();
    states
        .iter()
        .map(|cloud| {
            object_ids
                .iter()
                .zip(&refs)
                .map(|(&id, src)| Pair::new(src, &cloud.with_mask(id), opts))
                .collect()
        })
        .collect()
}

/// [`Pair::register`] of every pair of [`object_pairs`], but the reference state's own (row 0),
/// whose poses are identity with fitness 1.
pub fn registrations(pairs: &[Vec<Option<Pair>>]) -> Vec<Vec<Option<Registration>>> {
    pairs
        .iter()
        .enumerate()
        .map(|(j, row)| {
            row.iter()
                .map(|p| {
                    p.as_ref().map(|p| match j {
                        0 => Registration {
                            transform: Rigid::IDENTITY,
                            fitness: 1.0,
                            rmse: 0.0,
                            colour_rmse: 0.0,
                            score: 0.0,
                            geometric_cost: 0.0,
                            spacing: 0.0,
                        },
                        _ => p.register(),
                    })
                })
                .collect()
        })
        .collect()
}
