//! `lightfuse reconstruct`: stage 1 end to end, a plain function of files.
//!
//! 1. Read the dataset and every training observation (checked: [`Dataset::training_observations`]);
//!    every 8th view of each state (index ≡ 0 mod 8, the mip-NeRF 360 convention) is held out.
//! 2. Back-project the training views ([`init::backproject`]), estimate each object's pose in
//!    every state ([`poses::estimate`]: point-cloud registration, the rendered alignment, an ICP
//!    polish chosen by geometry, a turn the texture decides; [`poses::oracle`], the ground truth,
//!    only with `--oracle-poses`). Build the initial components ([`init::initial_components`]).
//! 3. Clean the labels with the graph cut ([`segment::segment`]) over the reference state.
//! 4. Train ([`super::train::Trainer`]); at a third of the iterations, seed surfels where the render lies
//!    behind the captured depth (eq. completion-mask). Then drop the object surfels grown
//!    beneath the surface their object stands on ([`support::beneath_support`]); a resumed
//!    finished run repeats only this step and the next.
//! 5. Write `scene.glb`, `report.json` (held-out PSNR, depth error, pose errors, label shares),
//!    `log.jsonl` (losses) and `checkpoint.json` (resumable with `--resume`); `poses.json`, the
//!    poses of step 2 before training ([`PoseSteps`]), is written when they are found, so the
//!    report can say where a pose error entered.

use super::poses;
use super::train::{render_state, Model, RawComponent, Settings, Trainer};
use super::{completion, init, segment, support};
use crate::error::{Error, Result};
use crate::eval::report::ObjectPoseError;
use crate::eval::stage1::{self, HeldOutView};
use crate::io::dataset::{split, Dataset, Observation, HOLDOUT};
use crate::io::work::{PoseSteps, WorkDir};
use crate::io::AtomicFiles;
use crate::progress::{say, Progress};
use crate::scene::{Component, Rigid, Scene, State};
use crate::stages::common::{
    check_resumed_settings, read_checkpoint, resume_or_start, StageLog, StageLoop,
};
use glam::Vec3;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Voxel pitch of the initial point thinning, metres (`--voxel`).
pub const DEFAULT_VOXEL: f32 = 0.01;
/// Depth-discrepancy threshold τ_D of eq. completion-mask, metres (`--tau-d`).
pub const DEFAULT_TAU_D: f32 = 0.05;

pub struct Options {
    pub dataset: PathBuf,
    pub work: WorkDir,
    pub settings: Settings,
    pub oracle_poses: bool,
    pub resume: bool,
    pub quiet: bool,
    /// Voxel pitch of the initialisation, metres.
    pub voxel: f32,
    /// Depth-discrepancy threshold τ_D of eq. completion-mask, metres.
    pub tau_d: f32,
}

#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub dataset: String,
    pub iterations: u32,
    pub surfels: usize,
    /// This process's wall time, reading to writing.
    pub seconds: f64,
    /// Wall time of the training iterations over every run a `--resume` continued
    /// ([`crate::stages::common::Resumable::training_seconds`]).
    pub training_seconds: f64,
    /// Held-out views: PSNR in sRGB over the pixels the capture saw a surface in.
    pub heldout_psnr_srgb: f64,
    pub heldout_views: usize,
    pub heldout: Vec<HeldOutView>,
    /// The same over the training views (how well the captures are fitted).
    pub train_psnr_srgb: f64,
    /// Median |D̂ − D*| over held-out pixels with reference depth, metres, and as a share of
    /// the scene's extent (diagonal of the training points' bounds).
    pub heldout_median_depth_error_m: f64,
    pub heldout_median_depth_error_rel: f64,
    pub pose_errors: Vec<ObjectPoseError>,
    /// Per object: share of its true surface points (masked reference depth) whose nearest
    /// surfel carries its label.
    pub label_share: Vec<(String, f64)>,
    /// Per object: share of its surfels whose nearest observed surface point (any label's,
    /// reference state) is its own ([`crate::eval::labels::label_purity`]).
    pub label_purity: Vec<(String, f64)>,
    /// Per object: surfels dropped after training as lying beneath the surface the object stands
    /// on ([`super::support`]).
    #[serde(default)]
    pub beneath_support_dropped: Vec<(String, usize)>,
    pub oracle_poses: bool,
}

/// The scene the model stands for: components and one state per training state.
fn scene_of(model: &Model, dataset: &Dataset, train: &[usize]) -> Scene {
    let components = model.scene_components();
    let states = train
        .iter()
        .enumerate()
        .map(|(j, &k)| State {
            name: dataset.states[k].name.clone(),
            transforms: std::iter::once(Rigid::IDENTITY)
                .chain(model.poses[j].iter().copied())
                .collect(),
            environment: None,
        })
        .collect();
    Scene {
        components,
        states,
        reference_state: 0,
        environments: Vec::new(),
    }
}

/// Moves surfels between components to match the graph cut's labels (all components live in
/// the reference state's frame, so a move is a copy).
fn relabel(components: &mut [Component], labels: &[u8]) -> usize {
    let ids: Vec<u32> = components.iter().map(|c| c.id).collect();
    let mut moved = 0;
    let mut out: Vec<crate::scene::Surfels> = components
        .iter()
        .map(|c| crate::scene::Surfels::with_sh_degree(c.surfels.sh_degree))
        .collect();
    let mut i = 0;
    for (c, comp) in components.iter().enumerate() {
        let s = &comp.surfels;
        for k in 0..s.len() {
            let label = labels[i] as u32;
            i += 1;
            let to = ids.iter().position(|&id| id == label).unwrap_or(c);
            if to != c {
                moved += 1;
            }
            out[to].push(
                s.position[k],
                s.rotation[k],
                s.scale[k],
                s.opacity[k],
                s.sh_of(k),
                s.base_color[k],
                s.metallic[k],
                s.roughness[k],
            );
        }
    }
    for (comp, s) in components.iter_mut().zip(out) {
        comp.surfels = s;
    }
    moved
}

fn concat(components: &[Component]) -> crate::scene::Surfels {
    let mut all = crate::scene::Surfels::with_sh_degree(components[0].surfels.sh_degree);
    for c in components {
        all.extend(&c.surfels);
    }
    all
}

/// A checkpoint of this dataset's training states and objects, made with these `settings`, to go
/// on to their iterations (the position schedule keeps its original span).
///
/// `--refine-poses` starts moving poses a third of the way into `--iterations`, so a run
/// lengthened on resume asks for a later start than its checkpoint's: when both refine poses,
/// the checkpoint's start is kept (its poses may already have moved; holding them again until
/// the new third would not undo that, only stall it).
fn read_resumable(
    path: &Path,
    settings: &Settings,
    states: usize,
    objects: usize,
) -> Result<Trainer> {
    let mut t: Trainer = read_checkpoint(path)?;
    let mut settings = settings.clone();
    if settings.pose_from != u32::MAX && t.settings.pose_from != u32::MAX {
        settings.pose_from = t.settings.pose_from;
    }
    check_resumed_settings(
        path,
        &t.settings,
        &settings,
        |s| &mut s.iterations,
        "resume with the same preset, seed and switches, or start afresh without --resume",
    )?;
    t.adam.validate(path)?;
    if t.model.poses.len() != states
        || t.model.colour.len() != states
        || t.model.components.len() != objects + 1
        || t.model.components.iter().any(|c| c.sh.len() != states + 1)
    {
        return Err(Error::invalid(
            path,
            "model",
            "expected a checkpoint of this dataset's states and objects",
        ));
    }
    t.settings.iterations = settings.iterations;
    Ok(t)
}

/// A fresh start: the training views back-projected (item 2), each object's pose in every state
/// (item 4, written to `poses.json`), the initial components and the graph cut's labels
/// (item 3).
fn initialise(
    dataset: &Dataset,
    train_states: &[usize],
    train: &[Vec<Observation>],
    objects: &[init::ObjectRef],
    opts: &Options,
) -> Result<Trainer> {
    // Initialisation (item 2): every training view back-projected.
    let bopts = init::BackprojectOptions::default();
    let clouds: Vec<init::PointCloud> =
        train.iter().map(|v| init::state_cloud(v, &bopts)).collect();
    // Poses (item 4).
    let ids: Vec<u8> = objects.iter().map(|o| o.id).collect();
    let poses: Vec<Vec<Rigid>> = if opts.oracle_poses {
        poses::oracle(dataset, train_states, objects)?
    } else {
        let t = Instant::now();
        say(
            opts.quiet,
            &format!(
                "registering {} objects in {} states (point clouds, rendered views, ICP polish)",
                objects.len(),
                train.len()
            ),
        );
        let steps = poses::estimate(&clouds, train, &ids);
        say(
            opts.quiet,
            &format!(
                "registered {} objects in {} states in {:.1} s (point clouds, rendered views, ICP polish, turns)",
                objects.len(),
                train.len(),
                t.elapsed().as_secs_f64()
            ),
        );
        crate::stages::common::write_checkpoint(&opts.work.poses(), &steps)?;
        steps.turned
    };
    let iopts = init::InitOptions {
        voxel: opts.voxel,
        ..Default::default()
    };
    let mut components = init::initial_components(&clouds, objects, &poses, &iopts);
    // Decomposition (item 3) over the reference state.
    let all = concat(&components);
    let seg = segment::segment(
        &segment::SurfelPoints::from_surfels(&all),
        &train[0],
        &segment::SegmentParams::default(),
    )?;
    let moved = relabel(&mut components, &seg.labels);
    say(
        opts.quiet,
        &format!(
            "initialised {} surfels ({} relabelled by the graph cut, energy {:.1} -> {:.1})",
            all.len(),
            moved,
            seg.energy_before,
            seg.energy_after
        ),
    );
    let model = Model::new(
        components
            .iter()
            .map(|c| RawComponent::from_component(c, poses.len()))
            .collect(),
        poses,
    );
    Ok(Trainer::new(opts.settings.clone(), model))
}

/// Stage 1 from the dataset to `scene.glb` and `report.json` in `opts.work`.
pub fn reconstruct(opts: &Options) -> Result<Report> {
    let t0 = Instant::now();
    let dataset = Dataset::read(&opts.dataset)?;
    let train_states = dataset.train_states();
    say(
        opts.quiet,
        &format!("reading {} training states", train_states.len()),
    );
    let (train, held) = split(dataset.training_observations()?);
    for (j, t) in train.iter().enumerate() {
        if t.is_empty() {
            return Err(Error::invalid(
                &dataset.file,
                format!("states[{}].frames", train_states[j]),
                format!("expected at least 2 frames: view 0 of every {HOLDOUT} is held out"),
            ));
        }
    }
    let stage_files = opts.work.reconstruct();
    std::fs::create_dir_all(&stage_files.dir).map_err(|e| Error::io(&stage_files.dir, e))?;
    let objects: Vec<init::ObjectRef> = dataset
        .objects
        .iter()
        .map(|o| init::ObjectRef {
            id: o.id as u8,
            name: o.name.clone(),
        })
        .collect();

    let (mut trainer, _) = resume_or_start(
        &stage_files.checkpoint(),
        opts.resume,
        opts.quiet,
        |path| read_resumable(path, &opts.settings, train.len(), objects.len()),
        || initialise(&dataset, &train_states, &train, &objects, opts),
    )?;

    // Training (item 6) with completion (item 5).
    let views: Vec<Vec<&Observation>> = train.iter().map(|v| v.iter().collect()).collect();
    let total = trainer.settings.iterations;
    // Without a terminal the bar is not drawn: a plain line about every tenth of the run, on the
    // log's 50-iteration grid.
    let plain_every = (total / 10 / 50).max(1) * 50;
    let mut bar =
        Progress::new(opts.quiet, total as u64, "training").plain_every(plain_every as u64);
    // A fresh run in a used directory appends too (as a resumed one does).
    let mut log = StageLog::append(&stage_files.log())?;
    let completion_at = total / 3;
    bar.start_at(trainer.iteration as u64);
    StageLoop {
        total,
        log_every: 50,
        checkpoint_every: 500,
        checkpoint: &stage_files.checkpoint(),
        log: &mut log,
        bar: &bar,
    }
    .run(
        &mut trainer,
        |t, bar| {
            if t.iteration == completion_at && completion_at > 0 {
                let added = complete(t, &train, opts)?;
                bar.println(&format!(
                    "completion: {added} surfels seeded (eq. completion-mask, τ_D = {} m)",
                    opts.tau_d
                ));
            }
            Ok(t.step(&views))
        },
        |t, m| {
            let surfels = t.model.surfel_count();
            m.insert("surfels".into(), surfels.into());
            let total = m.get("total").and_then(|v| v.as_f64()).unwrap_or(0.0);
            format!("loss {total:.4} · {surfels} surfels")
        },
    )?;
    bar.finish();

    // Object surfels grown under the floor or table their object stands on (its mirror image
    // in a glossy support) are dropped before the scene is written ([`support`]). Only the
    // reference state's training views are consulted, in whose frame the objects' surfels lie.
    let reference = init::state_cloud(&train[0], &init::BackprojectOptions::default());
    let mut beneath = Vec::new();
    for c in 0..trainer.model.components.len() {
        let comp = &trainer.model.components[c];
        if comp.id == 0 {
            continue;
        }
        let positions: Vec<[f32; 3]> = comp
            .position
            .chunks_exact(3)
            .map(|p| [p[0], p[1], p[2]])
            .collect();
        let flags = support::beneath_support(&reference, &positions);
        let keep: Vec<usize> = (0..positions.len()).filter(|&i| !flags[i]).collect();
        beneath.push((comp.name.clone(), positions.len() - keep.len()));
        trainer.keep_surfels(c, &keep);
    }
    say(
        opts.quiet,
        &format!(
            "dropped object surfels beneath their supports: {}",
            beneath
                .iter()
                .map(|(n, k)| format!("{n} {k}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    );

    let scene = scene_of(&trainer.model, &dataset, &train_states);
    crate::io::write_scene(&scene, &opts.work.scene())?;
    let report = evaluate(
        &trainer.model,
        &dataset,
        &train_states,
        &train,
        &held,
        opts,
        t0,
    )?;
    let report = Report {
        beneath_support_dropped: beneath,
        training_seconds: trainer.training_seconds,
        ..report
    };
    let mut files = AtomicFiles::new();
    files.write(
        &opts.work.reconstruct().report(),
        &serde_json::to_vec_pretty(&report).expect("report serialises"),
    )?;
    files.commit()?;
    Ok(report)
}

/// Seeds surfels where every training view's render lies behind the capture by more than τ_D
/// (eq. completion-mask), each into the component its mask names, in that component's frame.
fn complete(trainer: &mut Trainer, train: &[Vec<Observation>], opts: &Options) -> Result<usize> {
    let iopts = init::InitOptions {
        voxel: opts.voxel,
        ..Default::default()
    };
    let ids: Vec<u32> = trainer.model.components.iter().map(|c| c.id).collect();
    let mut per_component: Vec<init::PointCloud> = vec![init::PointCloud::default(); ids.len()];
    for (j, views) in train.iter().enumerate() {
        let transforms: Vec<Rigid> = std::iter::once(Rigid::IDENTITY)
            .chain(trainer.model.poses[j].iter().copied())
            .collect();
        for o in views {
            let img = render_state(&trainer.model, j, &o.camera);
            let mask = completion::completion_mask(&img.depth, &o.depth, opts.tau_d)?;
            let seeds = completion::seed_points(o, &mask)?;
            seeds.add_to_components(&ids, &transforms, j as u32, &mut per_component);
        }
    }
    let mut added = 0;
    for (c, cloud) in per_component.iter().enumerate() {
        if cloud.is_empty() {
            continue;
        }
        let s = init::points_to_surfels(&init::voxel_thin(cloud, opts.voxel), &iopts);
        added += s.len();
        trainer.add_surfels(c, &s);
    }
    Ok(added)
}

fn evaluate(
    model: &Model,
    dataset: &Dataset,
    train_states: &[usize],
    train: &[Vec<Observation>],
    held: &[Vec<Observation>],
    opts: &Options,
    t0: Instant,
) -> Result<Report> {
    let figures = stage1::view_figures(
        &|j, camera| render_state(model, j, camera),
        dataset,
        train_states,
        train,
        held,
        &opts.work,
    )?;
    // Also of the poses before training, when step 2 recorded them (not with oracle poses).
    let steps = (!opts.oracle_poses)
        .then(|| PoseSteps::read(&opts.work, train_states.len(), dataset.objects.len()))
        .flatten();
    // Where a dataset gives no object frame, an object's errors are measured at its surfels'
    // centroid.
    let centroid = |o: usize| {
        let p = &model.components[o + 1].position;
        let n = (p.len() / 3).max(1) as f32;
        p.chunks(3).fold(Vec3::ZERO, |a, q| a + Vec3::from_slice(q)) / n
    };
    let pose_errors = stage1::pose_errors(
        dataset,
        train_states,
        &model.poses,
        &centroid,
        steps.as_ref(),
    )?;
    // Label shares: true surface points of each object (masked depth, reference state, all its
    // views) against the nearest surfel of the assembled reference state; and the purity of
    // each object's surfels against the nearest observed point.
    let views: Vec<&Observation> = train[0].iter().chain(&held[0]).collect();
    let objects: Vec<(String, u32)> = dataset
        .objects
        .iter()
        .map(|o| (o.name.clone(), o.id))
        .collect();
    let components = model.scene_components();
    let label_share = crate::eval::labels::label_shares(&components, &views, &objects);
    let label_purity = crate::eval::labels::label_purity(&components, &views, &objects);
    Ok(Report {
        dataset: dataset.file.display().to_string(),
        iterations: opts.settings.iterations,
        surfels: model.surfel_count(),
        seconds: t0.elapsed().as_secs_f64(),
        training_seconds: 0.0,
        heldout_psnr_srgb: figures.heldout_psnr_srgb,
        heldout_views: figures.heldout.len(),
        train_psnr_srgb: figures.train_psnr_srgb,
        heldout_median_depth_error_rel: figures.median_depth_error_m / figures.extent_m.max(1e-9),
        heldout_median_depth_error_m: figures.median_depth_error_m,
        heldout: figures.heldout,
        pose_errors,
        label_share,
        label_purity,
        beneath_support_dropped: Vec::new(),
        oracle_poses: opts.oracle_poses,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::common::write_checkpoint;

    fn component(id: u32) -> Component {
        let mut surfels = crate::scene::Surfels::with_sh_degree(0);
        let q = [0.0, 0.0, 0.0, 1.0];
        surfels.push(
            [0.0; 3],
            q,
            [0.1, 0.1],
            0.9,
            &[[0.0; 3]],
            [0.5; 3],
            0.0,
            0.5,
        );
        Component {
            name: format!("c{id}"),
            id,
            surfels,
        }
    }

    #[test]
    fn a_checkpoint_resumes_only_on_the_settings_states_and_objects_it_was_made_of() {
        let dir = tempfile::tempdir().expect("a temporary directory");
        let path = WorkDir::new(dir.path()).reconstruct().checkpoint();
        // Two training states, one object.
        let model = Model::new(
            [component(0), component(1)]
                .iter()
                .map(|c| RawComponent::from_component(c, 2))
                .collect(),
            vec![vec![Rigid::IDENTITY], vec![Rigid::IDENTITY]],
        );
        let mut trainer = Trainer::new(Settings::fast(), model);
        trainer.iteration = 40;
        write_checkpoint(&path, &trainer).expect("written");
        let settings = Settings {
            iterations: 90,
            ..Settings::fast()
        };
        // The same shape resumes where it was, to go on to the run's new length.
        let back = read_resumable(&path, &settings, 2, 1).expect("the same states and objects");
        assert_eq!((back.iteration, back.settings.iterations), (40, 90));
        // A run refining poses, lengthened on resume, keeps the start its checkpoint had
        // (`--refine-poses` derives it from `--iterations`).
        let refining = Settings {
            pose_from: 30,
            ..Settings::fast()
        };
        let mut refined = trainer.clone();
        refined.settings = refining.clone();
        write_checkpoint(&path, &refined).expect("written");
        let longer = Settings {
            iterations: 900,
            pose_from: 300,
            ..refining.clone()
        };
        let back = read_resumable(&path, &longer, 2, 1).expect("a longer run refining poses");
        assert_eq!(
            (back.settings.pose_from, back.settings.iterations),
            (30, 900)
        );
        // Not refining poses where the checkpoint did is another switch.
        assert!(read_resumable(&path, &settings, 2, 1).is_err());
        write_checkpoint(&path, &trainer).expect("written");
        // Another dataset's states or objects are a clear error naming the file and the field.
        for (states, objects) in [(3, 1), (1, 1), (2, 2), (2, 0)] {
            let err = read_resumable(&path, &settings, states, objects)
                .err()
                .unwrap_or_else(|| panic!("{states} states, {objects} objects resumed"));
            let msg = err.to_string();
            assert!(
                msg.contains("checkpoint.json") && msg.contains("model"),
                "{msg}"
            );
        }
        // Another preset, or one switch or the seed changed, is an error naming the settings:
        // the run would otherwise go on with the checkpoint's, silently.
        let others = [
            Settings::paper(),
            Settings {
                seed: settings.seed + 1,
                ..settings.clone()
            },
            Settings {
                pose_from: 30,
                ..settings.clone()
            },
        ];
        for other in others {
            let err = read_resumable(&path, &other, 2, 1)
                .err()
                .unwrap_or_else(|| panic!("resumed with {other:?}"));
            let msg = err.to_string();
            assert!(
                msg.contains("checkpoint.json") && msg.contains("settings"),
                "{msg}"
            );
        }
    }
}
