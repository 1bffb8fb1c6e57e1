//! Stage 2 from files to files: `<work>/scene.glb` (stage 1) and the dataset's captures to
//! `<work>/refined.glb` and `<work>/refine/{report.json, log.jsonl, checkpoint.json}`.

use super::train::{Refiner, Settings, TrainState, REBUILD_EVERY};
use crate::error::{Error, Result};
use crate::eval::geometry::{tally_state, GeometryFigures, GeometryTally, LeakOptions};
use crate::io::dataset::Observation;
use crate::io::work::WorkDir;
use crate::io::AtomicFiles;
use crate::progress::{say, Progress};
use crate::scene::Scene;
use crate::stages::common::{
    check_resumed_settings, read_checkpoint, resume_or_start, Resumable, StageInputs, StageLog,
    StageLoop,
};
use crate::trace::TraceScene;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Checkpoints are written this often (iterations), and at the end: where the loop builds its
/// BVH afresh ([`REBUILD_EVERY`]), so that a run resumed from one continues bit for bit.
const CHECKPOINT_EVERY: u32 = REBUILD_EVERY;
/// log.jsonl gets the mean losses of each window of this many iterations.
const LOG_EVERY: u32 = 25;

pub struct Options {
    pub dataset: PathBuf,
    /// The work folder: stage 1's `scene.glb` is read from it unless `scene` says otherwise.
    pub work: WorkDir,
    pub scene: Option<PathBuf>,
    pub settings: Settings,
    pub leaks: LeakOptions,
    pub resume: bool,
    pub quiet: bool,
}

/// The five figures of one state before and after.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StateFigures {
    pub state: String,
    pub heldout_views: Vec<usize>,
    pub before: GeometryFigures,
    pub after: GeometryFigures,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Report {
    pub dataset: String,
    pub scene: String,
    pub settings: Settings,
    pub leak_options: LeakOptions,
    pub iterations: u32,
    /// This process's wall time, reading to writing.
    pub seconds: f64,
    /// Wall time of the training iterations over every run a `--resume` continued
    /// ([`Resumable::training_seconds`]).
    #[serde(default)]
    pub training_seconds: f64,
    pub surfels_before: usize,
    pub surfels_after: usize,
    pub pruned: usize,
    /// Surfels added where the traced surfels left captured surfaces uncovered.
    pub filled: usize,
    /// Over the held-out views of every training state, traced with the state's poses.
    pub before: GeometryFigures,
    pub after: GeometryFigures,
    pub states: Vec<StateFigures>,
}

fn extent(scene: &Scene) -> f32 {
    scene
        .states
        .iter()
        .filter_map(|s| scene.bounds_in_state(s))
        .map(|(lo, hi)| {
            let d: f32 = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum();
            d.sqrt()
        })
        .fold(0.0, f32::max)
}

/// The five figures per training state over its held-out views (every view of the state decides
/// what blocks a shadow ray).
fn measure(
    scene: &Scene,
    states: &[(String, usize, Vec<&Observation>, Vec<&Observation>)],
    leaks: &LeakOptions,
) -> (GeometryFigures, Vec<GeometryFigures>) {
    let traced = TraceScene::new(scene);
    let ext = extent(scene);
    let mut all = GeometryTally::default();
    let mut per = Vec::new();
    for (name, _, held, every) in states {
        let state = &scene.states[scene
            .state_index(name)
            .expect("checked by read_stage_scene")];
        let placed = traced.place_state(state);
        let t = tally_state(&placed, held, every, ext, leaks);
        per.push(t.figures());
        all.merge(t);
    }
    (all.figures(), per)
}

/// What a resumed run needs besides the scene: the refiner, and the figures measured before
/// the stage ran (so a resumed report still says "before").
#[derive(Serialize, Deserialize)]
struct Checkpoint {
    refiner: Refiner,
    before: GeometryFigures,
    before_states: Vec<GeometryFigures>,
    surfels_before: usize,
    /// [`Resumable::training_seconds`] (absent from a checkpoint written before it was kept).
    #[serde(default)]
    training_seconds: f64,
}

impl Resumable for Checkpoint {
    fn iteration(&self) -> u32 {
        self.refiner.iteration
    }
    fn training_seconds(&mut self) -> &mut f64 {
        &mut self.training_seconds
    }
}

fn read_resumable(path: &Path, settings: &Settings) -> Result<Checkpoint> {
    let mut c: Checkpoint = read_checkpoint(path)?;
    check_resumed_settings(
        path,
        &c.refiner.settings,
        settings,
        |s| &mut s.iterations,
        "resume with the same preset, seed and switches, or start afresh without --resume",
    )?;
    c.refiner.set_iterations(settings.iterations);
    Ok(c)
}

/// Stage 2: refines stage 1's geometry for ray tracing (eq. geometry-objective).
pub fn refine(opts: &Options) -> Result<Report> {
    let t0 = Instant::now();
    let scene_path = opts.scene.clone().unwrap_or_else(|| opts.work.scene());
    let StageInputs {
        dataset,
        scene,
        files: stage_files,
        train_states,
        train,
        held,
    } = StageInputs::read(
        &opts.dataset,
        &scene_path,
        "run `lightfuse reconstruct <dataset> -o <work>` first (or pass --scene)",
        opts.work.refine(),
        opts.quiet,
    )?;
    // (name, dataset index, held-out views, every view) per training state.
    let every: Vec<Vec<&Observation>> = train
        .iter()
        .zip(&held)
        .map(|(t, h)| t.iter().chain(h.iter()).collect())
        .collect();
    let eval_states: Vec<(String, usize, Vec<&Observation>, Vec<&Observation>)> = train_states
        .iter()
        .enumerate()
        .map(|(j, &k)| {
            (
                dataset.states[k].name.clone(),
                k,
                held[j].iter().collect(),
                every[j].clone(),
            )
        })
        .collect();
    let loop_states: Vec<TrainState> = train_states
        .iter()
        .enumerate()
        .filter(|(j, _)| !train[*j].is_empty())
        .map(|(j, &k)| {
            let s = scene
                .state_index(&dataset.states[k].name)
                .expect("checked by read_stage_scene");
            TrainState {
                views: train[j].iter().collect(),
                transforms: scene.states[s].transforms.clone(),
            }
        })
        .collect();
    if loop_states.is_empty() {
        return Err(Error::invalid(
            &dataset.file,
            "states",
            "expected training views to refine on (view 0 of every 8 is held out)",
        ));
    }

    let ckpt = stage_files.checkpoint();
    let log_path = stage_files.log();
    let (mut c, resumed) = resume_or_start(
        &ckpt,
        opts.resume,
        opts.quiet,
        |p| read_resumable(p, &opts.settings),
        || {
            say(
                opts.quiet,
                "measuring stage 1's geometry by ray tracing the held-out views",
            );
            let (before, before_states) = measure(&scene, &eval_states, &opts.leaks);
            Ok(Checkpoint {
                refiner: Refiner::new(opts.settings.clone(), &scene.components),
                before,
                before_states,
                surfels_before: scene.surfel_count(),
                training_seconds: 0.0,
            })
        },
    )?;
    let mut log = StageLog::create(&log_path, resumed)?;

    let total = opts.settings.iterations;
    let mut bar = Progress::new(opts.quiet, total as u64, "refining");
    bar.start_at(c.refiner.iteration as u64);
    StageLoop {
        total,
        log_every: LOG_EVERY,
        checkpoint_every: CHECKPOINT_EVERY,
        checkpoint: &ckpt,
        log: &mut log,
        bar: &bar,
    }
    .run(
        &mut c,
        |c, _| Ok(c.refiner.step(&loop_states)),
        |c, m| {
            let surfels = c.refiner.surfel_count();
            m.insert("surfels".into(), surfels.into());
            m.insert("seconds".into(), t0.elapsed().as_secs_f64().into());
            let total = m.get("total").and_then(|v| v.as_f64()).unwrap_or(0.0);
            format!("loss {total:.4} · {surfels} surfels")
        },
    )?;
    bar.finish();

    let mut refined = scene.clone();
    refined.components = c.refiner.scene_components();
    let refined_path = opts.work.refined();
    crate::io::write_scene(&refined, &refined_path)?;
    say(
        opts.quiet,
        "measuring the refined geometry by ray tracing the held-out views",
    );
    let (after, after_states) = measure(&refined, &eval_states, &opts.leaks);
    let report = Report {
        dataset: dataset.file.display().to_string(),
        scene: scene_path.display().to_string(),
        settings: opts.settings.clone(),
        leak_options: opts.leaks,
        iterations: c.refiner.iteration,
        seconds: t0.elapsed().as_secs_f64(),
        training_seconds: c.training_seconds,
        surfels_before: c.surfels_before,
        surfels_after: c.refiner.surfel_count(),
        pruned: c.refiner.pruned,
        filled: c.refiner.filled,
        before: c.before.clone(),
        after,
        states: eval_states
            .iter()
            .zip(c.before_states.iter().zip(after_states))
            .map(|((name, _, held, _), (b, a))| StateFigures {
                state: name.clone(),
                heldout_views: held.iter().map(|o| o.view).collect(),
                before: b.clone(),
                after: a,
            })
            .collect(),
    };
    let mut files = AtomicFiles::new();
    files.write(
        &stage_files.report(),
        &serde_json::to_vec_pretty(&report).expect("report serialises"),
    )?;
    files.commit()?;
    Ok(report)
}
