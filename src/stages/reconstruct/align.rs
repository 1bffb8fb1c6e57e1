//! Stage 1, object poses per state by analysis-by-synthesis (eq. state-assembly): the rigid
//! T_{k,o} that, applied to the object's surfels of the reference state and splatted with the
//! 2DGS kernel ([`crate::splat::forward`]), best reproduces what state k's cameras saw. An
//! alternative to point-cloud registration ([`super::register`]) for small, sparsely seen
//! objects, where a few hundred back-projected points do not pin the pose down.
//!
//! **Score** (lower is better), over every view of state k in which the object's mask has at
//! least [`MIN_VIEW_PIXELS`] pixels, each rendered on a crop around the object only:
//! `(1 − IoU) + w_z · mean_z + w_c · mean_c`, where
//! * IoU is the soft intersection-over-union of the rendered opacity A and the observed mask
//!   (mask == id), both summed over all views. A pixel where the observation shows something
//!   else *in front of* the rendered surface (observed depth below the rendered one by more
//!   than 2 σ_z) is occluded and counts for nothing;
//! * mean_z is the mean over pixels seen by both (mask == id there and at the 4 neighbours,
//!   so that edge pixels mixing the object with its background stay out, and A > ½) of
//!   min(((z_rendered − z_observed − m_v)/σ_z)², [`TRUNCATION`]), z_rendered the median depth
//!   and m_v the median of z_rendered − z_observed in view v: splatting surfels smaller than
//!   a pixel renders depth biased towards the camera (the nearest of several overlapping
//!   splats wins; ~1.5 cm at a 3 cm footprint in the tests), so only relative depth (shape)
//!   is compared and the other views' silhouettes fix the translation along each view axis;
//! * mean_c the same mean of min(|Δf|²/σ_c², [`TRUNCATION`]) for the log chromaticity f of the
//!   rendered colour (C/A) and of the observed RGB, each minus a median (of the reference
//!   surfels, and of state k's masked pixels): a per-channel gain and shading (the light of
//!   the state) cancel, the texture's hue pattern remains.
//!
//! **Parametrisation.** T(x) = R (x − c) + p with c the centroid of the reference surfels and
//! p the placed centroid, so turning the object does not move it. Poses whose p leaves the
//! ball of one object radius around state k's observed centroid are rejected (the crops are
//! sized to hold every pose inside it).
//!
//! **Search.** Every rotation of [`super::register::rotation_grid`] at `rotation_step_deg` is
//! scored with p at the centroid of state k's masked points; the best `candidates` rotations
//! farther apart than one grid step, plus the caller's candidates (e.g. from registration),
//! are refined by a deterministic pattern search over (ω, p) with halving steps; the lowest
//! refined score wins. Rotations and candidates are evaluated in parallel and collected in
//! order, ties broken by index, so the result does not depend on the thread count.

use super::init::{backproject, points_to_surfels, voxel_thin, BackprojectOptions, InitOptions};
use super::register::rotation_grid;
use crate::io::dataset::Observation;
use crate::scene::{Camera, Rigid, Surfels};
use crate::splat::{forward, Placement};
use crate::stats::median;
use glam::{Quat, Vec3};
use rayon::prelude::*;

/// A view takes part when the object covers at least this many pixels of it: fewer say more
/// about antialiasing than about the pose.
pub const MIN_VIEW_PIXELS: usize = 3;

/// Largest per-pixel depth or colour cost: a 2σ residual. Beyond it a pixel is an outlier
/// (a mixed edge pixel, a specular highlight) and should not dominate the mean.
pub const TRUNCATION: f32 = 4.0;

/// Options of [`object_poses_by_rendering`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlignOptions {
    /// Step of the global rotation grid, degrees.
    pub rotation_step_deg: f32,
    /// Grid rotations kept for refinement.
    pub candidates: usize,
    /// Depth residual scale σ_z as a fraction of the object radius.
    pub depth_sigma: f32,
    /// Weight of the depth term.
    pub depth_weight: f32,
    /// Colour residual scale σ_c in log-chromaticity units.
    pub colour_sigma: f32,
    /// Weight of the colour term.
    pub colour_weight: f32,
    /// First translation step of the refinement, fraction of the object radius.
    pub translation_step: f32,
    /// First rotation step of the refinement, degrees.
    pub rotation_step_refine_deg: f32,
    /// Halvings of both steps before the refinement stops.
    pub halvings: usize,
}

impl Default for AlignOptions {
    fn default() -> Self {
        AlignOptions {
            // 20°: the nearest grid rotation is at most ~12° away, inside the pattern search's
            // first step (12°), which can still walk to it.
            rotation_step_deg: 20.0,
            candidates: 6,
            // A tenth of the radius: on the demo (radius ~15 cm, pixel footprint ~3 cm) a
            // pixel's depth varies by about that across its footprint on a curved surface.
            depth_sigma: 0.1,
            depth_weight: 0.5,
            // 0.3 in log chromaticity: ~30 % hue-ratio change, well above the antialiasing
            // mix at edges but below the contrast of a painted pattern.
            colour_sigma: 0.3,
            colour_weight: 0.5,
            translation_step: 0.25,
            rotation_step_refine_deg: 12.0,
            // 12° / 2⁷ ≈ 0.1°, 0.25 r / 2⁷ ≈ 0.2 % of the radius: below what a pixel can tell.
            halvings: 7,
        }
    }
}

/// The object's reference surfels for [`object_poses_by_rendering`]: the masked pixels of
/// the reference observations back-projected and thinned at `voxel` (metres; half the median
/// pixel footprint, [`median_footprint`], is a good choice), each becoming a surfel of σ =
/// [`REFERENCE_SIGMA`] × `voxel` and opacity 0.9. Unlike the training initialisation the
/// footprint is *not* stretched for oblique pixels: those sit on the silhouette, and surfels
/// several pixels wide there would render a silhouette far larger than the mask.
pub fn reference_surfels(reference: &[Observation], object_ids: &[u8], voxel: f32) -> Vec<Surfels> {
    let bopts = BackprojectOptions::default();
    let mut cloud = super::init::PointCloud::default();
    for o in reference {
        cloud.extend(&backproject(
            &without_mixed_pixels(o, bopts.depth_jump),
            &bopts,
        ));
    }
    let iopts = InitOptions {
        voxel,
        opacity: 0.9,
        sigma_per_spacing: REFERENCE_SIGMA,
        ..Default::default()
    };
    object_ids
        .iter()
        .map(|&id| {
            let mut thin = voxel_thin(&cloud.with_mask(id), voxel);
            thin.footprint.iter_mut().for_each(|f| *f = voxel);
            points_to_surfels(&thin, &iopts)
        })
        .collect()
}

/// The observation with the mask cleared (set to 0, background) at object pixels that have
/// fewer than three 4-neighbours of the same id and a depth within `depth_jump` × z: on a
/// silhouette the depth mixes the object with what lies behind it, so such a pixel
/// back-projects to a point floating off the object, and the floater would render as extra
/// silhouette in other views. Straight edges (three such neighbours) are kept.
pub fn without_mixed_pixels(o: &Observation, depth_jump: f32) -> Observation {
    let (w, h) = (o.camera.w as usize, o.camera.h as usize);
    let mut out = o.clone();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (id, z) = (o.mask[i], o.depth[i]);
            if id == 0 {
                continue;
            }
            let mut n = 0;
            let mut check = |x2: usize, y2: usize| {
                let j = y2 * w + x2;
                if o.mask[j] == id && o.depth[j] > 0.0 && (o.depth[j] - z).abs() <= depth_jump * z {
                    n += 1;
                }
            };
            if x > 0 {
                check(x - 1, y);
            }
            if x + 1 < w {
                check(x + 1, y);
            }
            if y > 0 {
                check(x, y - 1);
            }
            if y + 1 < h {
                check(x, y + 1);
            }
            if n < 3 {
                out.mask[i] = 0;
            }
        }
    }
    out
}

/// σ of a reference surfel per unit of point spacing: two neighbours half a spacing from a
/// pixel each give α = 0.9 e^{−½ (0.5/0.7)²} ≈ 0.7 there, so a lattice renders nearly opaque
/// while the silhouette grows by well under a spacing.
pub const REFERENCE_SIGMA: f32 = 0.7;

/// Median pixel footprint z / √(f_x f_y) (not stretched for obliquity) of the masked pixels
/// of `object_ids` in `observations`, metres: a voxel size for [`reference_surfels`]; `None`
/// without masked pixels.
pub fn median_footprint(observations: &[Observation], object_ids: &[u8]) -> Option<f32> {
    let mut fp = Vec::new();
    for o in observations {
        let f = (o.camera.fl_x * o.camera.fl_y).sqrt();
        for (m, z) in o.mask.iter().zip(&o.depth) {
            if *z > 0.0 && object_ids.contains(m) {
                fp.push(z / f);
            }
        }
    }
    if fp.is_empty() {
        return None;
    }
    median(&mut fp)
}

/// Log chromaticity (2 components): ln c_i − ⅓ Σ ln c_j for i = r, g.
fn chroma(c: [f32; 3]) -> [f32; 2] {
    const FLOOR: f32 = 1e-4;
    let l = c.map(|x| x.max(FLOOR).ln());
    let m = (l[0] + l[1] + l[2]) / 3.0;
    [l[0] - m, l[1] - m]
}

fn median2(v: &[[f32; 2]]) -> [f32; 2] {
    std::array::from_fn(|d| median(&mut v.iter().map(|c| c[d]).collect::<Vec<_>>()).unwrap_or(0.0))
}

/// The parts of the score of a pose (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScoreTerms {
    /// Soft IoU of rendered opacity and observed mask over all views.
    pub iou: f32,
    /// Mean truncated squared depth residual (in σ_z²) where both see the object.
    pub depth: f32,
    /// Mean truncated squared log-chromaticity residual (in σ_c²) there.
    pub colour: f32,
    /// (1 − IoU) + w_z depth + w_c colour; infinite outside the allowed ball.
    pub total: f32,
}

/// One view cropped to the object's neighbourhood.
struct CropView {
    camera: Camera,
    /// Mask == id.
    mask: Vec<bool>,
    /// Mask == id here and at the 4 neighbours: depth and colour of edge pixels mix the
    /// object with what is behind it, so only these enter the depth and colour terms.
    interior: Vec<bool>,
    depth: Vec<f32>,
    /// Observed log chromaticity minus the state's median.
    chroma: Vec<[f32; 2]>,
}

/// Everything needed to score poses of one object in one state.
struct Problem<'a> {
    surfels: &'a Surfels,
    /// Reference centroid c.
    centre: Vec3,
    /// Object radius (largest surfel distance from c), metres.
    radius: f32,
    /// State k's centroid of the masked points.
    target: Vec3,
    views: Vec<CropView>,
    /// Median log chromaticity of the reference surfels.
    ref_chroma: [f32; 2],
    opts: AlignOptions,
}

impl<'a> Problem<'a> {
    fn new(
        surfels: &'a Surfels,
        id: u8,
        state: &[Observation],
        opts: &AlignOptions,
    ) -> Option<Self> {
        if surfels.is_empty() {
            return None;
        }
        let centre = surfels
            .position
            .iter()
            .map(|p| Vec3::from_array(*p))
            .sum::<Vec3>()
            / surfels.len() as f32;
        let radius = surfels
            .position
            .iter()
            .map(|p| Vec3::from_array(*p).distance(centre))
            .fold(0.0f32, f32::max)
            .max(1e-4);
        // Target centroid: the state's masked points, thinned so that views seeing the object
        // larger do not weigh more.
        let bopts = BackprojectOptions::default();
        let mut cloud = super::init::PointCloud::default();
        let mut visible = Vec::new();
        for o in state {
            let n = o.mask.iter().filter(|&&m| m == id).count();
            if n >= MIN_VIEW_PIXELS {
                cloud.extend(&backproject(o, &bopts).with_mask(id));
                visible.push(o);
            }
        }
        if cloud.is_empty() {
            return None;
        }
        let spacing = {
            let mut fp = cloud.footprint.clone();
            let m = fp.len() / 2;
            *fp.select_nth_unstable_by(m, f32::total_cmp).1
        };
        let thin = voxel_thin(&cloud, spacing.max(1e-4));
        let target = thin
            .position
            .iter()
            .map(|p| Vec3::from_array(*p))
            .sum::<Vec3>()
            / thin.len() as f32;

        let mut all_chroma = Vec::new();
        let mut views = Vec::new();
        for o in visible {
            let cam = &o.camera;
            let (w, h) = (cam.w as i64, cam.h as i64);
            // Mask bounding box ∪ the projection of the ball of 2 radii around the target
            // (every accepted pose keeps the object inside it).
            let (mut x0, mut y0, mut x1, mut y1) = (w, h, -1i64, -1i64);
            for y in 0..h {
                for x in 0..w {
                    let i = (y * w + x) as usize;
                    if o.mask[i] == id {
                        x0 = x0.min(x);
                        y0 = y0.min(y);
                        x1 = x1.max(x);
                        y1 = y1.max(y);
                        all_chroma.push(chroma(o.rgb[i]));
                    }
                }
            }
            // A target that is not a number has no projection either way: the whole image.
            match cam.project(target.to_array()) {
                Some(([u, v], z)) if z > 2.0 * radius => {
                    let r = (cam.fl_x.max(cam.fl_y) * 2.0 * radius / (z - 2.0 * radius)).ceil();
                    x0 = x0.min((u - r).floor() as i64);
                    y0 = y0.min((v - r).floor() as i64);
                    x1 = x1.max((u + r).ceil() as i64);
                    y1 = y1.max((v + r).ceil() as i64);
                }
                _ => {
                    // Too close to bound: the whole image.
                    (x0, y0, x1, y1) = (0, 0, w - 1, h - 1);
                }
            }
            let (x0, y0) = (x0.clamp(0, w - 1), y0.clamp(0, h - 1));
            let (x1, y1) = (x1.clamp(x0, w - 1), y1.clamp(y0, h - 1));
            let (cw, ch) = ((x1 - x0 + 1) as usize, (y1 - y0 + 1) as usize);
            let mut camera = *cam;
            camera.cx -= x0 as f32;
            camera.cy -= y0 as f32;
            camera.w = cw as u32;
            camera.h = ch as u32;
            let mut mask = Vec::with_capacity(cw * ch);
            let mut interior = Vec::with_capacity(cw * ch);
            let is = |x: i64, y: i64| {
                x >= 0 && y >= 0 && x < w && y < h && o.mask[(y * w + x) as usize] == id
            };
            let mut depth = Vec::with_capacity(cw * ch);
            let mut chr = Vec::with_capacity(cw * ch);
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let i = (y * w + x) as usize;
                    mask.push(o.mask[i] == id);
                    interior.push(
                        is(x, y) && is(x - 1, y) && is(x + 1, y) && is(x, y - 1) && is(x, y + 1),
                    );
                    depth.push(o.depth[i]);
                    chr.push(chroma(o.rgb[i]));
                }
            }
            views.push(CropView {
                camera,
                mask,
                interior,
                depth,
                chroma: chr,
            });
        }
        let med = median2(&all_chroma);
        for v in &mut views {
            for c in &mut v.chroma {
                *c = [c[0] - med[0], c[1] - med[1]];
            }
        }
        let ref_rgb: Vec<[f32; 2]> = surfels.base_color.iter().map(|c| chroma(*c)).collect();
        Some(Problem {
            surfels,
            centre,
            radius,
            target,
            views,
            ref_chroma: median2(&ref_rgb),
            opts: *opts,
        })
    }

    /// The rigid transform of (R, p): x ↦ R (x − c) + p.
    fn rigid(&self, q: Quat, p: Vec3) -> Rigid {
        Rigid {
            rotation: q.normalize().to_array(),
            translation: (p - q * self.centre).to_array(),
        }
    }

    /// (R, p) of a rigid transform.
    fn params(&self, t: &Rigid) -> (Quat, Vec3) {
        let q = t.quat().normalize();
        (q, q * self.centre + Vec3::from_array(t.translation))
    }

    /// The score of the module docs (lower is better); infinite outside the allowed ball.
    fn score(&self, q: Quat, p: Vec3) -> f32 {
        self.terms(q, p).total
    }

    fn terms(&self, q: Quat, p: Vec3) -> ScoreTerms {
        if p.distance(self.target) > self.radius {
            return ScoreTerms {
                iou: 0.0,
                depth: TRUNCATION,
                colour: TRUNCATION,
                total: f32::INFINITY,
            };
        }
        let t = self.rigid(q, p);
        let sigma_z = self.opts.depth_sigma * self.radius;
        let occ = 2.0 * sigma_z;
        let s2c = self.opts.colour_sigma * self.opts.colour_sigma;
        let (mut inter, mut union) = (0.0f64, 0.0f64);
        let (mut zc, mut cc, mut both) = (0.0f64, 0.0f64, 0usize);
        for v in &self.views {
            let img = forward(
                &[Placement {
                    surfels: self.surfels,
                    transform: t,
                }],
                &v.camera,
            )
            .image;
            let mut dz = Vec::new();
            for i in 0..v.mask.len() {
                let a = img.alpha[i].clamp(0.0, 1.0);
                let m = v.mask[i];
                let zo = v.depth[i];
                // The median depth is the surface the ray enters, not a blend with the
                // object's far side.
                let zr = img.median_depth[i];
                if !m && a > 0.0 && zo > 0.0 && zr > 0.0 && zo < zr - occ {
                    continue; // something else in front
                }
                let mf = if m { 1.0 } else { 0.0 };
                inter += (a * mf) as f64;
                union += (a + mf - a * mf) as f64;
                if v.interior[i] && a > 0.5 {
                    both += 1;
                    if zo > 0.0 && zr > 0.0 {
                        dz.push(zr - zo);
                    } else {
                        zc += TRUNCATION as f64;
                    }
                    let c = img.color[i].map(|x| x / a);
                    let f = chroma(c);
                    let df = [
                        f[0] - self.ref_chroma[0] - v.chroma[i][0],
                        f[1] - self.ref_chroma[1] - v.chroma[i][1],
                    ];
                    cc += ((df[0] * df[0] + df[1] * df[1]) / s2c).min(TRUNCATION) as f64;
                }
            }
            // Residuals about the view's median: splatting sub-pixel surfels biases rendered
            // depth towards the camera by a sizeable part of a pixel footprint (the nearest
            // of several overlapping splats wins), the same in every view, so only the
            // relative depth (the shape) is compared; silhouettes in the other views pin the
            // translation along this view's axis.
            let med = median(&mut dz.clone()).unwrap_or(0.0);
            for d in dz {
                let r = (d - med) / sigma_z;
                zc += (r * r).min(TRUNCATION) as f64;
            }
        }
        let iou = if union > 0.0 { inter / union } else { 0.0 };
        let (mz, mc) = if both > 0 {
            (zc / both as f64, cc / both as f64)
        } else {
            (TRUNCATION as f64, TRUNCATION as f64)
        };
        ScoreTerms {
            iou: iou as f32,
            depth: mz as f32,
            colour: mc as f32,
            total: (1.0 - iou
                + self.opts.depth_weight as f64 * mz
                + self.opts.colour_weight as f64 * mc) as f32,
        }
    }

    /// Deterministic pattern search over (ω, p): each of the six axes is tried both ways with
    /// the current steps, the first improvement taken; a full sweep without one halves both.
    fn refine(&self, mut q: Quat, mut p: Vec3) -> (Quat, Vec3, f32) {
        let mut best = self.score(q, p);
        let mut rs = self.opts.rotation_step_refine_deg.to_radians();
        let mut ts = self.opts.translation_step * self.radius;
        let axes = [Vec3::X, Vec3::Y, Vec3::Z];
        let mut halvings = 0;
        // Bound on sweeps per step size: a walk longer than this is drifting, not converging.
        const MAX_SWEEPS: usize = 12;
        while halvings <= self.opts.halvings {
            for _ in 0..MAX_SWEEPS {
                let mut improved = false;
                for axis in axes {
                    for sign in [1.0f32, -1.0] {
                        let qn = (Quat::from_scaled_axis(axis * (sign * rs)) * q).normalize();
                        let s = self.score(qn, p);
                        if s < best {
                            (best, q, improved) = (s, qn, true);
                            break;
                        }
                    }
                    for sign in [1.0f32, -1.0] {
                        let pn = p + axis * (sign * ts);
                        let s = self.score(q, pn);
                        if s < best {
                            (best, p, improved) = (s, pn, true);
                            break;
                        }
                    }
                }
                if !improved {
                    break;
                }
            }
            rs *= 0.5;
            ts *= 0.5;
            halvings += 1;
        }
        (q, p, best)
    }

    fn solve(&self, initial: &[Rigid]) -> (Rigid, f32) {
        let grid = rotation_grid(self.opts.rotation_step_deg);
        let mut scored: Vec<(f32, usize)> = grid
            .par_iter()
            .enumerate()
            .map(|(r, q)| (self.score(*q, self.target), r))
            .collect();
        scored.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let min_sep = self.opts.rotation_step_deg.to_radians();
        let mut starts: Vec<(Quat, Vec3)> = Vec::new();
        for &(_, r) in &scored {
            if starts.len() >= self.opts.candidates.max(1) {
                break;
            }
            if starts
                .iter()
                .all(|(q, _)| q.angle_between(grid[r]) > min_sep)
            {
                starts.push((grid[r], self.target));
            }
        }
        for t in initial {
            let (q, mut p) = self.params(t);
            // A candidate outside the allowed ball starts from its nearest point in it.
            let d = p - self.target;
            if d.length() > self.radius {
                p = self.target + d * (0.99 * self.radius / d.length());
            }
            starts.push((q, p));
        }
        let refined: Vec<(Quat, Vec3, f32)> =
            starts.par_iter().map(|&(q, p)| self.refine(q, p)).collect();
        let mut best = 0;
        for (i, r) in refined.iter().enumerate() {
            if r.2 < refined[best].2 {
                best = i;
            }
        }
        let (q, p, s) = refined[best];
        (self.rigid(q, p), s)
    }
}

/// The pose and score of one object in one state: see the module docs. `None` when the object
/// has no surfels or is seen in no view of the state by [`MIN_VIEW_PIXELS`] pixels.
pub fn align_object(
    reference: &Surfels,
    id: u8,
    state: &[Observation],
    initial: &[Rigid],
    opts: &AlignOptions,
) -> Option<(Rigid, f32)> {
    let problem = Problem::new(reference, id, state, opts)?;
    Some(problem.solve(initial))
}

/// The score of a given pose of one object in one state (lower is better; see the module
/// docs), for diagnostics; `None` as for [`align_object`].
pub fn score_pose(
    reference: &Surfels,
    id: u8,
    state: &[Observation],
    pose: &Rigid,
    opts: &AlignOptions,
) -> Option<ScoreTerms> {
    let problem = Problem::new(reference, id, state, opts)?;
    let (q, p) = problem.params(pose);
    Some(problem.terms(q, p))
}

/// Poses of every object in every state relative to `states[0]` (identity there), by
/// rendering (see the module docs). `reference_objects[o]` holds object `object_ids[o]`'s
/// surfels in the reference frame (e.g. [`reference_surfels`]); `states[j]` the training
/// observations of state j; `initial[j][o]` extra candidates (e.g. from registration; an
/// empty or short list is allowed). An object not seen in a state keeps the best initial
/// candidate, or identity.
pub fn object_poses_by_rendering(
    reference_objects: &[Surfels],
    object_ids: &[u8],
    states: &[Vec<Observation>],
    initial: &[Vec<Option<Rigid>>],
    opts: &AlignOptions,
) -> Vec<Vec<Rigid>> {
    assert_eq!(
        reference_objects.len(),
        object_ids.len(),
        "one surfel set per object id"
    );
    states
        .iter()
        .enumerate()
        .map(|(j, obs)| {
            object_ids
                .iter()
                .enumerate()
                .map(|(o, &id)| {
                    if j == 0 {
                        return Rigid::IDENTITY;
                    }
                    let cands: Vec<Rigid> = initial
                        .get(j)
                        .and_then(|row| row.get(o))
                        .and_then(|c| *c)
                        .into_iter()
                        .collect();
                    match align_object(&reference_objects[o], id, obs, &cands, opts) {
                        Some((t, _)) => t,
                        None => cands.first().copied().unwrap_or(Rigid::IDENTITY),
                    }
                })
                .collect()
        })
        .collect()
}
