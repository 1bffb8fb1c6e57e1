//! How fit a surfel scene is for ray tracing, measured by ray tracing it (not by splatting): what
//! stage 2 (`lightfuse refine`) reports before and after it runs. The definitions are in
//! `docs/geometry-metrics.md`; in short, over the evaluated views of a state placed with its
//! object poses:
//!
//! - **depth**: |z̄ − D*| over *surface pixels* (the capture saw a surface, D* > 0) that the
//!   traced ray covers (Σw ≥ ½); its median.
//! - **normal**: the angle between the renormalised composited normal and the capture's normal
//!   over the same pixels; its mean, degrees.
//! - **holes**: the share of surface pixels whose composited alpha Σw is below ½.
//! - **false occlusion**: the share of *environment pixels* (D* = 0: the capture saw the sky)
//!   whose composited alpha exceeds ½.
//! - **light leaks**: shadow rays from observed surface points (a grid of the evaluated views'
//!   surface pixels, back-projected with the capture's depth and lifted along its normal) in
//!   cosine-distributed directions about the captured normal. A ray is *blocked* by the
//!   reference geometry where, between two steps of a march along it, some capture of the state
//!   sees it go from in front of its captured surface to behind it (on the same surface: the
//!   captured depth does not jump) while no capture sees through the point. A blocked ray
//!   *leaks* when the surfels let more than half its light through up to a little past that
//!   point (`reference_blocker`).
//!
//! Captures decide what is blocked, so the figure needs no mesh: it works on any dataset with
//! depth, and it only asks the surfels to block where the captured surfaces are.

use crate::io::dataset::Observation;
use crate::scene::synthetic::SplitMix;
use crate::scene::Camera;
use crate::trace::Placed;
use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A pixel's traced alpha must reach this to count as covered (and below it, as a hole).
pub const COVERED: f32 = 0.5;

/// How the shadow rays of the light-leak figure are cast and judged.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LeakOptions {
    /// Every `stride`-th pixel in x and y of an evaluated view's surface pixels casts rays.
    pub stride: usize,
    /// Shadow rays per surface point.
    pub directions: u32,
    /// The ray starts this far above the captured surface along its normal, metres: clear of
    /// the surface's own surfels (stage 1 places them within a few millimetres of it).
    pub lift: f32,
    /// A capture judges a point to lie on its surface within this depth, metres.
    pub surface_margin: f32,
    /// March step along the ray, metres (below `surface_margin`, so no surface is stepped over
    /// unless the ray grazes it).
    pub step: f32,
    /// The ray is not judged before this distance: the surface it starts from is not a blocker.
    pub min_distance: f32,
    /// The surfels may block up to this far past the point where the captures put the ray
    /// behind the surface, metres.
    pub slack: f32,
    /// Seed of the direction sequence.
    pub seed: u64,
}

impl Default for LeakOptions {
    fn default() -> Self {
        LeakOptions {
            stride: 4,
            directions: 8,
            lift: 0.01,
            surface_margin: 0.02,
            step: 0.01,
            min_distance: 0.03,
            slack: 0.02,
            seed: 7,
        }
    }
}

/// The five figures with the counts behind them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GeometryFigures {
    /// Median |z̄ − D*| over covered surface pixels, metres.
    pub depth_median_m: f64,
    /// Mean normal angle error over covered surface pixels, degrees.
    pub normal_mean_deg: f64,
    /// Share of surface pixels with Σw < ½.
    pub holes: f64,
    /// Share of environment pixels with Σw > ½.
    pub false_occlusion: f64,
    /// Share of blocked shadow rays that the surfels let through.
    pub light_leaks: f64,
    pub surface_pixels: usize,
    pub environment_pixels: usize,
    pub blocked_rays: usize,
    pub leaking_rays: usize,
}

/// What tracing one view gives per pixel: planar depth z̄ (0 without a hit), Σw, and the
/// renormalised composited normal (0 without a hit).
pub struct TracedView {
    pub alpha: Vec<f32>,
    pub depth: Vec<f32>,
    pub normal: Vec<[f32; 3]>,
}

/// Traces every pixel centre of the camera through the placed scene.
pub fn trace_view(placed: &Placed, camera: &Camera) -> TracedView {
    let (w, h) = (camera.w as usize, camera.h as usize);
    let records: Vec<_> = (0..w * h)
        .into_par_iter()
        .with_min_len(64)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let (o, d) = camera.planar_ray(x as f32 + 0.5, y as f32 + 0.5);
            placed.composite(o, d, 0.0, f32::INFINITY)
        })
        .collect();
    TracedView {
        alpha: records.iter().map(|r| r.alpha).collect(),
        depth: records.iter().map(|r| r.mean_depth()).collect(),
        normal: records.iter().map(|r| r.unit_normal()).collect(),
    }
}

/// Per-pixel contributions of one or more views, summed before the figures are taken.
#[derive(Clone, Debug, Default)]
pub struct GeometryTally {
    depth_errors: Vec<f32>,
    normal_angle_sum: f64,
    normal_count: usize,
    surface: usize,
    holes: usize,
    environment: usize,
    occluding: usize,
    blocked: usize,
    leaking: usize,
}

impl GeometryTally {
    pub fn merge(&mut self, other: GeometryTally) {
        self.depth_errors.extend(other.depth_errors);
        self.normal_angle_sum += other.normal_angle_sum;
        self.normal_count += other.normal_count;
        self.surface += other.surface;
        self.holes += other.holes;
        self.environment += other.environment;
        self.occluding += other.occluding;
        self.blocked += other.blocked;
        self.leaking += other.leaking;
    }

    pub fn figures(&self) -> GeometryFigures {
        let ratio = |a: usize, b: usize| if b > 0 { a as f64 / b as f64 } else { 0.0 };
        let mut e = self.depth_errors.clone();
        let depth_median_m = if e.is_empty() {
            0.0
        } else {
            let mid = e.len() / 2;
            *e.select_nth_unstable_by(mid, f32::total_cmp).1 as f64
        };
        GeometryFigures {
            depth_median_m,
            normal_mean_deg: if self.normal_count > 0 {
                self.normal_angle_sum / self.normal_count as f64
            } else {
                0.0
            },
            holes: ratio(self.holes, self.surface),
            false_occlusion: ratio(self.occluding, self.environment),
            light_leaks: ratio(self.leaking, self.blocked),
            surface_pixels: self.surface,
            environment_pixels: self.environment,
            blocked_rays: self.blocked,
            leaking_rays: self.leaking,
        }
    }
}

/// Depth, normal, holes and false occlusion of one traced view against its capture.
pub fn tally_view(traced: &TracedView, obs: &Observation) -> GeometryTally {
    let mut t = GeometryTally::default();
    for i in 0..obs.depth.len() {
        let a = traced.alpha[i];
        if obs.depth[i] > 0.0 {
            t.surface += 1;
            if a < COVERED {
                t.holes += 1;
                continue;
            }
            t.depth_errors.push((traced.depth[i] - obs.depth[i]).abs());
            let n = Vec3::from_array(traced.normal[i]);
            let r = Vec3::from_array(obs.normal[i]);
            if n.length_squared() > 0.0 && r.length_squared() > 0.0 {
                let c = n.normalize().dot(r.normalize()).clamp(-1.0, 1.0);
                t.normal_angle_sum += (c as f64).acos().to_degrees();
                t.normal_count += 1;
            }
        } else {
            t.environment += 1;
            if a > COVERED {
                t.occluding += 1;
            }
        }
    }
    t
}

/// Where a point is for one capture: `sd` = captured depth − the point's depth at the pixel it
/// projects to (positive in front of the captured surface), and that captured depth `d`; `None`
/// outside the image or behind the camera. `d = 0` (the capture saw the environment) gives
/// `sd = +∞`.
#[derive(Clone, Copy, Debug)]
struct Look {
    sd: f32,
    d: f32,
    /// The captured normal there.
    n: Vec3,
}

fn look(obs: &Observation, q: Vec3) -> Option<Look> {
    let cam = &obs.camera;
    let ([u, v], z) = cam.project(q.to_array())?;
    if !(u >= 0.0 && v >= 0.0 && u < cam.w as f32 && v < cam.h as f32) {
        return None;
    }
    let i = v as usize * cam.w as usize + u as usize;
    let d = obs.depth[i];
    Some(Look {
        sd: if d > 0.0 { d - z } else { f32::INFINITY },
        d,
        n: Vec3::from_array(obs.normal[i]),
    })
}

/// Distance along `o + s ω` at which the captures say the ray goes through a surface, if they
/// do: between two steps, some capture sees the point pass from in front of its captured
/// surface to behind it, on the same surface (its captured depth changes by less than the
/// margin: a point that passes behind a silhouette jumps from one surface to another and does
/// not count), and no capture sees the point more than the margin in front of what it saw
/// there. `o` lies `lift` above the surface it starts from, whose normal is `n`. Also returns
/// how far past that point the surfels may still block: the captures' depth is sampled per
/// pixel, so the crossing is known to within about a pixel's footprint along the surface,
/// which a grazing ray travels a long way through (`slack / |ω · n_surface|`, at most 5×).
fn reference_blocker(
    views: &[&Observation],
    o: Vec3,
    n: Vec3,
    w: Vec3,
    max: f32,
    opts: &LeakOptions,
) -> Option<(f32, f32)> {
    let m = opts.surface_margin;
    // Near the surface it starts from, a grazing ray is "on" that surface for every capture,
    // and that surface cannot block it. Judge it only once clear of it.
    let clear = (2.0 * m - opts.lift) / w.dot(n).max(1e-3);
    let mut s = opts.min_distance.max(clear);
    let mut prev: Vec<Option<Look>> = vec![None; views.len()];
    while s <= max {
        let q = o + s * w;
        let now: Vec<Option<Look>> = views.iter().map(|obs| look(obs, q)).collect();
        let free = now.iter().flatten().any(|l| l.sd > m);
        let crossed = now.iter().zip(&prev).find_map(|(a, b)| match (a, b) {
            (Some(a), Some(b)) if b.sd >= 0.0 && a.sd < 0.0 && (a.d - b.d).abs() < m => Some(a.n),
            _ => None,
        });
        if let (Some(ns), false) = (crossed, free) {
            return Some((s, opts.slack / w.dot(ns).abs().max(0.2)));
        }
        prev = now;
        s += opts.step;
    }
    None
}

/// A cosine-distributed direction about the unit normal `n`.
fn cosine_direction(n: Vec3, u1: f32, u2: f32) -> Vec3 {
    let r = u1.sqrt();
    let phi = std::f32::consts::TAU * u2;
    let (b1, b2) = n.any_orthonormal_pair();
    (b1 * (r * phi.cos()) + b2 * (r * phi.sin()) + n * (1.0 - u1).max(0.0).sqrt()).normalize()
}

/// Light leaks of the shadow rays cast from `obs`'s surface pixels; `state_views` are every
/// capture of the same state (they decide what is blocked) and `extent` bounds the march.
pub fn tally_leaks(
    placed: &Placed,
    obs: &Observation,
    state_views: &[&Observation],
    extent: f32,
    opts: &LeakOptions,
) -> GeometryTally {
    let cam = &obs.camera;
    let (w, h) = (cam.w as usize, cam.h as usize);
    let stride = opts.stride.max(1);
    let points: Vec<usize> = (0..h)
        .step_by(stride)
        .flat_map(|y| (0..w).step_by(stride).map(move |x| y * w + x))
        .filter(|&i| obs.depth[i] > 0.0 && Vec3::from_array(obs.normal[i]).length_squared() > 0.5)
        .collect();
    let counts: Vec<(usize, usize)> = points
        .par_iter()
        .map(|&i| {
            let (x, y) = (i % w, i / w);
            let (o, d) = cam.planar_ray(x as f32 + 0.5, y as f32 + 0.5);
            let p = Vec3::from_array(o) + obs.depth[i] * Vec3::from_array(d);
            let mut n = Vec3::from_array(obs.normal[i]).normalize();
            if n.dot(Vec3::from_array(d)) > 0.0 {
                n = -n;
            }
            let start = p + opts.lift * n;
            let mut rng = SplitMix(opts.seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            let (mut blocked, mut leaking) = (0, 0);
            for _ in 0..opts.directions {
                let dir = cosine_direction(n, rng.f32(), rng.f32());
                let Some((s, slack)) = reference_blocker(state_views, start, n, dir, extent, opts)
                else {
                    continue;
                };
                blocked += 1;
                let tr = placed.transmittance(start.to_array(), dir.to_array(), 0.0, s + slack);
                if tr > 1.0 - COVERED {
                    leaking += 1;
                }
            }
            (blocked, leaking)
        })
        .collect();
    GeometryTally {
        blocked: counts.iter().map(|c| c.0).sum(),
        leaking: counts.iter().map(|c| c.1).sum(),
        ..GeometryTally::default()
    }
}

/// All five figures over `evaluated` views of one placed state; `state_views` are every capture
/// of that state (for the light-leak test) and `extent` the scene's size, metres.
pub fn tally_state(
    placed: &Placed,
    evaluated: &[&Observation],
    state_views: &[&Observation],
    extent: f32,
    opts: &LeakOptions,
) -> GeometryTally {
    let mut t = GeometryTally::default();
    for obs in evaluated {
        let traced = trace_view(placed, &obs.camera);
        t.merge(tally_view(&traced, obs));
        t.merge(tally_leaks(placed, obs, state_views, extent, opts));
    }
    t
}
