//! The stage-2 loop (eq. geometry-objective): batches of pixel patches drawn across the training
//! views of every training state, each state assembled with stage 1's object poses
//! (eq. state-assembly), ray traced with the renderer's own hit and compositing rules
//! (eqs. gaussian-response, surface-record), compared with the captures' depth, normals and
//! coverage, and the shared geometry (centres, raw rotations, log scales, logit opacities of the
//! background and every object) updated by Adam through [`crate::trace::Placed::composite_backward`].
//! Object poses, appearance and materials are not touched.
//!
//! Per patch of `patch × patch` pixels (a patch, not scattered pixels, because the
//! depth-derived normal of L_DN^ray needs each pixel's four neighbours):
//! - L_α: |Σw − 𝟙\[D* > 0\]| (eq. alpha-coverage, extended as in stage 1 to push pixels that saw
//!   the environment to transparent: those are where a false occluder shows), the batch's
//!   surface pixels and its environment pixels each averaged and weighted one half;
//! - L_D: eq. reconstruction-depth on the traced depth z̄ = Σw t / Σw (rays with d·forward = 1,
//!   so t is planar depth), confidence = the capture's validity;
//! - L_N: 1 − n̂ · N*, n̂ the composited normal renormalised as the shader sees it (stage 1
//!   splats the plain sum Σw n, which also pulls coverage up wherever a surface was seen; here
//!   coverage is L_α's alone, so that discs are not pushed past silhouettes);
//! - L_DN^ray: 1 − N^D · N*, N^D the normals of the traced depth patch (central differences,
//!   [`crate::optim::depth_normal_loss`] with the reference normals);
//! - L_s: eq. scale-regularization over every surfel.
//!
//! Each term is averaged over the batch's patches; the switches of the paper's Table 3 drop
//! one each ([`Switches`]).

use crate::io::dataset::Observation;
use crate::optim::{self, sigmoid, Adam, Schedule};
use crate::scene::synthetic::SplitMix;
use crate::scene::{Camera, Component, Rigid, Surfels};
use crate::splat;
use crate::stages::reconstruct::train::RawComponent;
use crate::stages::reconstruct::{completion, init};
use crate::trace::{Placed, RecordGrad, SurfaceRecord, TraceRay, TraceScene, TraceSurfelGrads};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Which terms of eq. geometry-objective are on (the paper's Table 3 turns each off in turn).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Switches {
    pub coverage: bool,
    pub scale: bool,
    pub depth: bool,
    pub normal: bool,
}

impl Default for Switches {
    fn default() -> Self {
        Switches {
            coverage: true,
            scale: true,
            depth: true,
            normal: true,
        }
    }
}

/// Everything the loop's behaviour depends on; presets below. Saved in the checkpoint and the
/// report so a run can be repeated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Settings {
    pub iterations: u32,
    /// Side of a pixel patch.
    pub patch: u32,
    /// Patches per iteration (rays = patches × patch²).
    pub patches: u32,
    pub lr_position_init: f32,
    pub lr_position_final: f32,
    pub lr_rotation: f32,
    pub lr_scale: f32,
    pub lr_opacity: f32,
    pub lambda_alpha: f32,
    pub lambda_scale: f32,
    /// s_max of eq. scale-regularization, metres.
    pub s_max: f32,
    pub lambda_depth: f32,
    pub lambda_normal: f32,
    pub lambda_depth_normal: f32,
    /// Surfels whose opacity falls below this are removed every `prune_every` iterations: they
    /// cannot be seen (the tracer drops hits fainter than 1/255) but still cost traversal.
    pub prune_opacity: f32,
    pub prune_every: u32,
    /// Every `fill_every` iterations in [fill_every, fill_until], surface pixels of the training
    /// views that the traced surfels leave uncovered (Σw < ½) get new surfels back-projected
    /// from the captures' depth (stage 1's completion seeding, voxel-thinned at `fill_voxel`):
    /// a hole wider than a surfel's support gives no gradient to close it.
    pub fill_every: u32,
    pub fill_until: u32,
    pub fill_voxel: f32,
    pub switches: Switches,
    pub seed: u64,
}

impl Settings {
    /// Minutes on this 2-core machine for the demo dataset.
    pub fn fast() -> Settings {
        Settings {
            iterations: 600,
            patch: 8,
            patches: 64,
            // Stage 1 ends at 6.4e-6 m per step; stage 2 starts a little above it (the tracer's
            // gradients pull surfels that splatting left in the wrong place) and decays.
            lr_position_init: 1e-4,
            lr_position_final: 1e-6,
            lr_rotation: 1e-3,
            lr_scale: 5e-3,
            lr_opacity: 5e-2,
            lambda_alpha: 0.1,
            lambda_scale: 1.0,
            s_max: 0.05,
            lambda_depth: 0.1,
            lambda_normal: 0.05,
            lambda_depth_normal: 0.05,
            prune_opacity: 0.005,
            prune_every: 100,
            fill_every: 150,
            fill_until: 450,
            fill_voxel: 0.01,
            switches: Switches::default(),
            seed: 0,
        }
    }

    /// The paper's scale: 16,384 rays per iteration (as stage 3's batches) for 5,000 iterations.
    pub fn paper() -> Settings {
        Settings {
            iterations: 5000,
            patches: 256,
            fill_every: 500,
            fill_until: 3000,
            ..Settings::fast()
        }
    }
}

/// The losses of one iteration, weighted as they enter the objective.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct Losses {
    pub alpha: f32,
    pub scale: f32,
    pub depth: f32,
    pub normal: f32,
    pub depth_normal: f32,
    pub total: f32,
}

const GROUPS: [(&str, usize); 4] = [
    ("position", 3),
    ("rotation", 4),
    ("log_scale", 2),
    ("logit_opacity", 1),
];

fn group_of(c: &mut RawComponent, g: usize) -> &mut Vec<f32> {
    match g {
        0 => &mut c.position,
        1 => &mut c.rotation,
        2 => &mut c.log_scale,
        _ => &mut c.logit_opacity,
    }
}

/// One training state's views and the rigid transform of every component in it.
pub struct TrainState<'a> {
    pub views: Vec<&'a Observation>,
    pub transforms: Vec<Rigid>,
}

/// Steps between full BVH builds in [`Refiner::step`]; in between, the previous step's tree is
/// refitted to the moved surfels ([`TraceScene::refit`]), and it is built afresh whenever
/// surfels were added or removed. A step moves each surfel by a small fraction of its size, so a
/// hundred steps leave the tree's grouping still a good one while the build, which was most of
/// a step's time when made every step, is paid a few times a run. What a ray composites does not
/// depend on the tree beyond the order its hits are found in, i.e. rounding (`tests/trace.rs`).
/// The refine stage checkpoints at multiples of it, so a resumed run builds where an
/// uninterrupted one did and continues bit for bit.
pub const REBUILD_EVERY: u32 = 100;

/// The refinement: raw geometry of every component, Adam, and where the run stands.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Refiner {
    pub settings: Settings,
    pub components: Vec<RawComponent>,
    pub adam: Adam,
    pub iteration: u32,
    pub pruned: usize,
    pub filled: usize,
    rng: u64,
    /// The traced scene of the last step, to be refitted by the next ([`REBUILD_EVERY`]).
    #[serde(skip)]
    traced: TracedCache,
}

/// The scene [`Refiner::step`] keeps between steps: derived from the components, so neither
/// written to a checkpoint nor copied by a clone (a copy builds its own at its next step).
#[derive(Default)]
struct TracedCache(Option<TraceScene>);

impl Clone for TracedCache {
    fn clone(&self) -> Self {
        TracedCache(None)
    }
}

impl std::fmt::Debug for TracedCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.0.is_some() {
            "TracedCache(built)"
        } else {
            "TracedCache(empty)"
        })
    }
}

/// A patch's camera: the view's intrinsics shifted so that pixel (x0, y0) is its (0, 0).
fn patch_camera(cam: &Camera, x0: u32, y0: u32, side: u32) -> Camera {
    Camera {
        cx: cam.cx - x0 as f32,
        cy: cam.cy - y0 as f32,
        w: side,
        h: side,
        ..*cam
    }
}

/// One patch: which view, where, and its pixels' indices in the view.
struct Patch {
    state: usize,
    view: usize,
    x0: u32,
    y0: u32,
}

impl Refiner {
    pub fn new(settings: Settings, components: &[Component]) -> Refiner {
        let components: Vec<RawComponent> = components
            .iter()
            .map(|c| RawComponent::from_component(c, 0))
            .collect();
        let mut adam = Adam::new();
        for (c, comp) in components.iter().enumerate() {
            for (g, (name, width)) in GROUPS.iter().enumerate() {
                let schedule = match g {
                    0 => Schedule::Exponential {
                        lr_init: settings.lr_position_init,
                        lr_final: settings.lr_position_final,
                        steps: settings.iterations as u64,
                    },
                    1 => Schedule::Constant {
                        lr: settings.lr_rotation,
                    },
                    2 => Schedule::Constant {
                        lr: settings.lr_scale,
                    },
                    _ => Schedule::Constant {
                        lr: settings.lr_opacity,
                    },
                };
                adam.add_group(
                    &format!("c{c}.{name}"),
                    comp.len() * width,
                    *width,
                    schedule,
                );
            }
        }
        Refiner {
            rng: settings.seed ^ 0x2EF1_7E00_0000_0002,
            settings,
            components,
            adam,
            iteration: 0,
            pruned: 0,
            filled: 0,
            traced: TracedCache::default(),
        }
    }

    /// Sets the run's length (a resumed run may go further): the position rate's decay is
    /// stretched to the new end.
    pub fn set_iterations(&mut self, iterations: u32) {
        self.settings.iterations = iterations;
        for c in 0..self.components.len() {
            let gi = self
                .adam
                .group_index(&format!("c{c}.position"))
                .expect("every component has its groups");
            self.adam.set_schedule(
                gi,
                Schedule::Exponential {
                    lr_init: self.settings.lr_position_init,
                    lr_final: self.settings.lr_position_final,
                    steps: iterations as u64,
                },
            );
        }
    }

    /// The activated surfels of every component (SH, materials as they came in).
    pub fn surfels(&self) -> Vec<Surfels> {
        self.components.iter().map(|c| c.surfels(0)).collect()
    }

    pub fn surfel_count(&self) -> usize {
        self.components.iter().map(RawComponent::len).sum()
    }

    /// The refined components, named and numbered as they came in.
    pub fn scene_components(&self) -> Vec<Component> {
        self.components
            .iter()
            .map(RawComponent::component)
            .collect()
    }

    fn draw_patches(&mut self, states: &[TrainState]) -> Vec<Patch> {
        let total: usize = states.iter().map(|s| s.views.len()).sum();
        let side = self.settings.patch;
        let mut rng = SplitMix(self.rng);
        let mut out = Vec::with_capacity(self.settings.patches as usize);
        for _ in 0..self.settings.patches {
            let mut r = (rng.next_u64() % total as u64) as usize;
            let mut state = 0;
            while r >= states[state].views.len() {
                r -= states[state].views.len();
                state += 1;
            }
            let cam = &states[state].views[r].camera;
            let x0 = (rng.next_u64() % (cam.w.saturating_sub(side) + 1) as u64) as u32;
            let y0 = (rng.next_u64() % (cam.h.saturating_sub(side) + 1) as u64) as u32;
            out.push(Patch {
                state,
                view: r,
                x0,
                y0,
            });
        }
        self.rng = rng.next_u64();
        out
    }

    /// One iteration of eq. geometry-objective: a batch of patches of every state traced, the
    /// losses of their records, the backward pass, Adam on the surfels (with eq.
    /// scale-regularization), then the schedule's pruning and hole filling.
    pub fn step(&mut self, states: &[TrainState]) -> Losses {
        let s = self.settings.clone();
        let surfels = self.surfels();
        let refs: Vec<&Surfels> = surfels.iter().collect();
        // Built for a few thousand rays a step, so the faster build; refitted in between.
        let scene = match self.traced.0.take() {
            Some(mut scene) if self.iteration % REBUILD_EVERY != 0 => {
                scene.refit(&refs);
                scene
            }
            _ => TraceScene::from_components_for_few_rays(&refs),
        };
        let patches = self.draw_patches(states);
        let side = s.patch.min(
            states
                .iter()
                .flat_map(|st| st.views.iter().map(|v| v.camera.w.min(v.camera.h)))
                .min()
                .unwrap_or(s.patch),
        );
        let per_patch = (side * side) as usize;
        let inv_p = 1.0 / patches.len().max(1) as f32;

        // Forward: every patch's pixels traced in its state's placement.
        let rays = patch_rays(states, &patches, side);
        let placed: Vec<_> = states
            .iter()
            .map(|st| scene.place(&st.transforms))
            .collect();
        let records: Vec<SurfaceRecord> = rays
            .par_iter()
            .enumerate()
            .with_min_len(64)
            .map(|(i, r)| {
                placed[patches[i / per_patch].state].composite(r.origin, r.dir, r.t_min, r.t_max)
            })
            .collect();

        // The losses and dL/d(record sums), patch by patch.
        let coverage_weights = coverage_weights(states, &patches, side);
        let per: Vec<(Losses, Vec<RecordGrad>)> = patches
            .par_iter()
            .enumerate()
            .map(|(k, p)| {
                let obs = states[p.state].views[p.view];
                let rec = &records[k * per_patch..(k + 1) * per_patch];
                patch_losses(&s, obs, p, side, rec, inv_p, coverage_weights)
            })
            .collect();
        let mut losses = Losses::default();
        let mut grads = Vec::with_capacity(rays.len());
        for (l, g) in per {
            losses.alpha += l.alpha;
            losses.depth += l.depth;
            losses.normal += l.normal;
            losses.depth_normal += l.depth_normal;
            grads.extend(g);
        }

        // Backward, then Adam.
        let g_surfels = backward(&placed, &refs, &rays, &grads, &patches, per_patch);
        drop(placed);
        self.traced.0 = Some(scene);
        losses.scale = self.update_surfels(&surfels, &g_surfels);
        losses.total =
            losses.alpha + losses.scale + losses.depth + losses.normal + losses.depth_normal;

        // The schedule: pruning and hole filling.
        self.iteration += 1;
        if s.prune_every > 0 && self.iteration % s.prune_every == 0 {
            self.prune();
        }
        if s.fill_every > 0 && self.iteration % s.fill_every == 0 && self.iteration <= s.fill_until
        {
            self.fill_holes(states);
        }
        losses
    }

    /// Adam on every component's surfels (`surfels`: their activated values this step,
    /// `g_surfels`: the traced backward pass's gradients), with eq. scale-regularization's
    /// gradient added (each component weighted by its share of the surfels); non-finite
    /// gradients are zeroed. Returns the scale term's value.
    fn update_surfels(&mut self, surfels: &[Surfels], g_surfels: &[TraceSurfelGrads]) -> f32 {
        let total = self.surfel_count().max(1) as f32;
        let s = &self.settings;
        let mut scale_loss = 0.0;
        for (c, comp) in self.components.iter_mut().enumerate() {
            let len = comp.len();
            if len == 0 || g_surfels.len() <= c {
                continue;
            }
            let act = &surfels[c];
            let sg = &g_surfels[c];
            // eq. scale-regularization over every surfel of the scene.
            let scale_reg = optim::scale_regularization(&act.scale, s.s_max);
            let lambda_s = if s.switches.scale {
                s.lambda_scale
            } else {
                0.0
            };
            let share = len as f32 / total;
            scale_loss += lambda_s * scale_reg.value * share;
            let finite = |v: f32| if v.is_finite() { v } else { 0.0 };
            let g_pos: Vec<f32> = sg.position.iter().flatten().map(|&v| finite(v)).collect();
            let g_rot: Vec<f32> = sg.rotation.iter().flatten().map(|&v| finite(v)).collect();
            let g_scale: Vec<f32> = (0..len)
                .flat_map(|i| {
                    [0, 1].map(|k| {
                        finite(splat::log_scale_grad(
                            act.scale[i][k],
                            sg.scale[i][k] + lambda_s * share * scale_reg.grad[i][k],
                        ))
                    })
                })
                .collect();
            let g_opacity: Vec<f32> = (0..len)
                .map(|i| finite(splat::logit_grad(act.opacity[i], sg.opacity[i])))
                .collect();
            for (g, gr) in [(0, &g_pos), (1, &g_rot), (2, &g_scale), (3, &g_opacity)] {
                let gi = self
                    .adam
                    .group_index(&format!("c{c}.{}", GROUPS[g].0))
                    .expect("every component has its groups");
                self.adam.step(gi, group_of(comp, g), gr);
            }
        }
        scale_loss
    }

    /// Seeds surfels where the captures saw a surface that the traced surfels do not cover
    /// (see [`Settings::fill_every`]), each into the component its mask names, in that
    /// component's frame. Returns how many were added.
    pub fn fill_holes(&mut self, states: &[TrainState]) -> usize {
        let surfels = self.surfels();
        let refs: Vec<&Surfels> = surfels.iter().collect();
        let scene = TraceScene::from_components(&refs);
        let ids: Vec<u32> = self.components.iter().map(|c| c.id).collect();
        let mut clouds = vec![init::PointCloud::default(); ids.len()];
        for (j, st) in states.iter().enumerate() {
            let placed = scene.place(&st.transforms);
            for obs in &st.views {
                let traced = crate::eval::geometry::trace_view(&placed, &obs.camera);
                let holes: Vec<bool> = obs
                    .depth
                    .iter()
                    .zip(&traced.alpha)
                    .map(|(&d, &a)| d > 0.0 && a < crate::eval::geometry::COVERED)
                    .collect();
                let Ok(seeds) = completion::seed_points(obs, &holes) else {
                    continue;
                };
                seeds.add_to_components(&ids, &st.transforms, j as u32, &mut clouds);
            }
        }
        let mut added = 0;
        for (c, cloud) in clouds.iter().enumerate() {
            if cloud.is_empty() {
                continue;
            }
            let opts = init::InitOptions {
                voxel: self.settings.fill_voxel,
                sh_degree: self.components[c].sh_degree,
                ..Default::default()
            };
            let new = init::points_to_surfels(&init::voxel_thin(cloud, opts.voxel), &opts);
            let n = self.components[c].append(&new);
            for (name, _) in GROUPS {
                let gi = self
                    .adam
                    .group_index(&format!("c{c}.{name}"))
                    .expect("every component has its groups");
                self.adam.append_points(gi, n);
            }
            added += n;
        }
        self.filled += added;
        if added > 0 {
            self.traced.0 = None;
        }
        added
    }

    /// Removes surfels fainter than `prune_opacity` (their Adam moments with them).
    pub fn prune(&mut self) {
        let min = self.settings.prune_opacity;
        for (c, comp) in self.components.iter_mut().enumerate() {
            let keep: Vec<usize> = (0..comp.len())
                .filter(|&i| sigmoid(comp.logit_opacity[i]) >= min)
                .collect();
            if keep.len() == comp.len() {
                continue;
            }
            self.pruned += comp.len() - keep.len();
            self.traced.0 = None;
            comp.gather(&keep);
            for (name, _) in GROUPS {
                let gi = self
                    .adam
                    .group_index(&format!("c{c}.{name}"))
                    .expect("every component has its groups");
                self.adam.keep_points(gi, &keep);
            }
        }
    }
}

/// The camera rays of every patch's pixels, patch-major (planar rays: depth along them is the
/// captures' planar depth).
fn patch_rays(states: &[TrainState], patches: &[Patch], side: u32) -> Vec<TraceRay> {
    let per_patch = (side * side) as usize;
    patches
        .iter()
        .flat_map(|p| {
            let cam = &states[p.state].views[p.view].camera;
            (0..per_patch).map(move |i| {
                let (x, y) = (p.x0 + i as u32 % side, p.y0 + i as u32 / side);
                let (origin, dir) = cam.planar_ray(x as f32 + 0.5, y as f32 + 0.5);
                TraceRay {
                    origin,
                    dir,
                    t_min: 0.0,
                    t_max: f32::INFINITY,
                }
            })
        })
        .collect()
}

/// L_α's weights of a surface pixel and an environment pixel of the batch: the two kinds as two
/// halves. A view sees far more surface than sky, and a plain mean lets discs grow past
/// silhouettes (more surface covered, a little sky occluded) until false occlusion sets in.
fn coverage_weights(states: &[TrainState], patches: &[Patch], side: u32) -> (f32, f32) {
    let per_patch = (side * side) as usize;
    let (mut surface, mut environment) = (0usize, 0usize);
    for p in patches {
        let obs = states[p.state].views[p.view];
        let w = obs.camera.w as usize;
        for i in 0..per_patch {
            let (x, y) = (
                p.x0 as usize + i % side as usize,
                p.y0 as usize + i / side as usize,
            );
            if obs.depth[y * w + x] > 0.0 {
                surface += 1;
            } else {
                environment += 1;
            }
        }
    }
    let half = |n: usize| if n > 0 { 0.5 / n as f32 } else { 0.0 };
    (half(surface), half(environment))
}

/// The traced backward pass, state by state (each its own placement), the surfel gradients
/// summed per component.
fn backward(
    placed: &[Placed],
    refs: &[&Surfels],
    rays: &[TraceRay],
    grads: &[RecordGrad],
    patches: &[Patch],
    per_patch: usize,
) -> Vec<TraceSurfelGrads> {
    let mut g_surfels: Vec<TraceSurfelGrads> = Vec::new();
    for (j, pl) in placed.iter().enumerate() {
        let idx: Vec<usize> = (0..rays.len())
            .filter(|&i| patches[i / per_patch].state == j)
            .collect();
        if idx.is_empty() {
            continue;
        }
        let r: Vec<TraceRay> = idx.iter().map(|&i| rays[i]).collect();
        let g: Vec<RecordGrad> = idx.iter().map(|&i| grads[i]).collect();
        let out = pl.composite_backward(refs, &r, &g, false);
        if g_surfels.is_empty() {
            g_surfels = out.surfels;
        } else {
            for (acc, add) in g_surfels.iter_mut().zip(out.surfels) {
                acc.add(&add);
            }
        }
    }
    g_surfels
}

/// The losses of one patch (already divided by the batch's patch count) and dL/d(record sums)
/// of its pixels.
fn patch_losses(
    s: &Settings,
    obs: &Observation,
    p: &Patch,
    side: u32,
    rec: &[SurfaceRecord],
    inv_p: f32,
    (w_surface, w_environment): (f32, f32),
) -> (Losses, Vec<RecordGrad>) {
    let sw = s.switches;
    let n = rec.len();
    let w = obs.camera.w as usize;
    let pix =
        |i: usize| (p.y0 as usize + i / side as usize) * w + p.x0 as usize + i % side as usize;
    let ref_depth: Vec<f32> = (0..n).map(|i| obs.depth[pix(i)]).collect();
    let ref_normal: Vec<[f32; 3]> = (0..n).map(|i| obs.normal[pix(i)]).collect();
    let depth: Vec<f32> = rec.iter().map(SurfaceRecord::mean_depth).collect();
    let normal: Vec<[f32; 3]> = rec.iter().map(SurfaceRecord::unit_normal).collect();
    let mut l = Losses::default();
    let mut g_alpha = vec![0.0f32; n];
    let mut g_depth = vec![0.0f32; n];
    let mut g_normal = vec![[0.0f32; 3]; n];
    if sw.coverage {
        for i in 0..n {
            let (target, inv) = if ref_depth[i] > 0.0 {
                (1.0, w_surface)
            } else {
                (0.0, w_environment)
            };
            let d = rec[i].alpha - target;
            l.alpha += s.lambda_alpha * d.abs() * inv;
            if d != 0.0 {
                g_alpha[i] = s.lambda_alpha * inv * d.signum();
            }
        }
    }
    if sw.depth {
        let dl = optim::depth_l1(&depth, &ref_depth, None);
        l.depth = s.lambda_depth * dl.value * inv_p;
        for (g, d) in g_depth.iter_mut().zip(&dl.grad) {
            *g += s.lambda_depth * inv_p * d;
        }
    }
    if sw.normal {
        let nl = optim::normal_loss(&normal, &ref_normal, None);
        l.normal = s.lambda_normal * nl.value * inv_p;
        for (g, d) in g_normal.iter_mut().zip(&nl.grad) {
            for k in 0..3 {
                g[k] += s.lambda_normal * inv_p * d[k];
            }
        }
        // L_DN^ray: normals of the traced depth against the captured ones.
        let cam = patch_camera(&obs.camera, p.x0, p.y0, side);
        let dn = optim::depth_normal_loss(&depth, &cam, &ref_normal, None);
        l.depth_normal = s.lambda_depth_normal * dn.value * inv_p;
        for (g, d) in g_depth.iter_mut().zip(&dn.grad_depth) {
            *g += s.lambda_depth_normal * inv_p * d;
        }
    }
    let grads = (0..n)
        .map(|i| {
            let mut g = rec[i].mean_depth_grad(g_depth[i]);
            g.add(&rec[i].unit_normal_grad(g_normal[i]));
            g.alpha += g_alpha[i];
            g
        })
        .collect();
    (l, grads)
}
