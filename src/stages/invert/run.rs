//! Stage 3 from files to files: `<work>/refined.glb` (stage 2; stage 1's `scene.glb` with a
//! warning when stage 2 has not run) and the dataset's captures to `<work>/relightable.glb`,
//! `<work>/relightable.usda` and `<work>/invert/{report.json, log.jsonl, checkpoint.json}`.

use super::cache::TrainState;
use super::cache::{CacheFigures, PrimaryCache};
use super::hypotheses::SearchFigures;
use super::lightfit::FitFigures;
use super::train::{Inverter, Settings};
use crate::error::{Error, Result};
use crate::eval::lighting::{AlbedoFigures, MaterialFigures};
use crate::eval::stage3::StateReport;
use crate::io::work::WorkDir;
use crate::io::AtomicFiles;
use crate::progress::{say, Progress};
use crate::scene::{EnvRef, Surfels};
use crate::shade::estimator::self_hit_epsilon;
use crate::stages::common::{
    check_resumed_settings, read_checkpoint, resume_or_start, Resumable, StageInputs, StageLog,
    StageLoop,
};
use crate::trace::TraceScene;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Checkpoints are written this often (iterations), and at the end.
const CHECKPOINT_EVERY: u32 = 50;
/// log.jsonl gets the mean losses of each window of this many iterations.
const LOG_EVERY: u32 = 10;

/// Stage 3's own figures: samples per pixel, and every N-th pixel in x and y of each view
/// (`--eval-spp`, `--eval-stride`).
pub const DEFAULT_EVAL_SPP: u32 = 16;
pub const DEFAULT_EVAL_STRIDE: u32 = 2;

pub struct Options {
    pub dataset: PathBuf,
    /// The work folder: stage 2's `refined.glb` is read from it unless `scene` says otherwise.
    pub work: WorkDir,
    pub scene: Option<PathBuf>,
    pub settings: Settings,
    /// Evaluation: samples per pixel, and every `eval_stride`-th pixel in x and y.
    pub eval_spp: u32,
    pub eval_stride: u32,
    pub resume: bool,
    pub quiet: bool,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Report {
    pub dataset: String,
    pub scene: String,
    pub settings: Settings,
    pub eval_spp: u32,
    pub eval_stride: u32,
    pub iterations: u32,
    /// This process's wall time, reading to writing.
    pub seconds: f64,
    /// Wall time of the training iterations over every run a `--resume` continued (the
    /// iterations each checkpoint kept; those a killed run had done after its last checkpoint
    /// are done and counted again). Equals the training share of `seconds` without a resume.
    #[serde(default)]
    pub training_seconds: f64,
    pub surfels: usize,
    /// The training pixels' primary records, traced once ([`PrimaryCache`]): its size and
    /// cost (absent when a resumed run had nothing left to train).
    pub primary_cache: Option<CacheFigures>,
    pub states: Vec<StateReport>,
    /// Base colour at the pixel centres of the evaluated training views against the dataset's
    /// albedo pass, on pixels both call surface ([`crate::eval::lighting::compare_albedo`]).
    pub albedo: Option<AlbedoFigures>,
    /// Per object, the mean metallic and roughness its pixels see, and the generator's values
    /// when the dataset records them.
    pub materials: Vec<MaterialFigures>,
    /// What the linear lighting fit found and cost (`--light-fit`; [`super::lightfit`]).
    #[serde(default)]
    pub light_fit: Option<FitFigures>,
    /// Each object's material hypotheses and the one it started from (`--material-search`;
    /// [`super::hypotheses`]).
    #[serde(default)]
    pub material_search: Option<SearchFigures>,
}

/// What a resumed run needs: the inverter (parameters, Adam, iteration, generator), and the
/// training time spent to reach it (for the report of a run resumed over several sittings).
#[derive(Serialize, Deserialize)]
struct Checkpoint {
    inverter: Inverter,
    #[serde(default)]
    training_seconds: f64,
    /// [`super::lightfit`]'s figures when the run started from it.
    #[serde(default)]
    light_fit: Option<FitFigures>,
    /// [`super::hypotheses`]' figures when the run started from its choices.
    #[serde(default)]
    material_search: Option<SearchFigures>,
}

impl Resumable for Checkpoint {
    fn iteration(&self) -> u32 {
        self.inverter.iteration
    }
    fn training_seconds(&mut self) -> &mut f64 {
        &mut self.training_seconds
    }
}

fn read_resumable(path: &Path, settings: &Settings, surfels: &[Surfels]) -> Result<Checkpoint> {
    let mut c: Checkpoint = read_checkpoint(path)?;
    check_resumed_settings(
        path,
        &c.inverter.settings,
        settings,
        |s| &mut s.iterations,
        "resume with the same preset, schedule and seed, or start afresh without --resume",
    )?;
    let counts: Vec<usize> = c
        .inverter
        .materials
        .iter()
        .map(|m| m.metallic.len())
        .collect();
    let want: Vec<usize> = surfels.iter().map(|s| s.len()).collect();
    if counts != want {
        return Err(Error::invalid(
            path,
            "inverter.materials",
            format!("expected materials for {want:?} surfels per component (the scene's), found {counts:?}: the checkpoint belongs to another scene"),
        ));
    }
    c.inverter.adam.validate(path)?;
    c.inverter.check_environments(path)?;
    c.inverter.set_iterations(settings.iterations);
    Ok(c)
}

/// The scene stage 3 starts from: `--scene`, else `<work>/refined.glb`, else stage 1's
/// `<work>/scene.glb` with a warning.
fn scene_path(opts: &Options) -> Result<PathBuf> {
    if let Some(p) = &opts.scene {
        return Ok(p.clone());
    }
    let refined = opts.work.refined();
    if refined.is_file() {
        return Ok(refined);
    }
    let stage1 = opts.work.scene();
    if stage1.is_file() {
        eprintln!(
            "warning: {} is missing (stage 2 has not run): inverting stage 1's {} instead; its geometry was fitted for splatting, not for ray tracing",
            refined.display(),
            stage1.display()
        );
        return Ok(stage1);
    }
    Err(Error::invalid(
        &refined,
        "scene",
        "expected stage 2's refined scene here: run `lightfuse reconstruct <dataset> -o <work>` and `lightfuse refine <dataset> <work>` first (or pass --scene)",
    ))
}

/// Stage 3: inverse rendering of materials and per-state environments (eq. training-objectives).
pub fn invert(opts: &Options) -> Result<Report> {
    let t0 = Instant::now();
    opts.settings.check()?;
    let scene_file = scene_path(opts)?;
    let StageInputs {
        dataset,
        scene,
        files: stage_files,
        train_states,
        train,
        held,
    } = StageInputs::read(
        &opts.dataset,
        &scene_file,
        "run `lightfuse reconstruct` and `lightfuse refine` first (or pass --scene)",
        opts.work.invert(),
        opts.quiet,
    )?;
    let mut loop_states: Vec<TrainState> = Vec::new();
    let mut names = Vec::new();
    for (j, &k) in train_states.iter().enumerate() {
        let name = &dataset.states[k].name;
        let s = scene
            .state_index(name)
            .expect("checked by read_stage_scene");
        loop_states.push(TrainState {
            views: train[j].iter().collect(),
            transforms: scene.states[s].transforms.clone(),
            eps: self_hit_epsilon(&scene, &scene.states[s]),
        });
        names.push(name.clone());
    }
    if loop_states.iter().all(|s| s.views.is_empty()) {
        return Err(Error::invalid(
            &dataset.file,
            "states",
            "expected training views to invert (view 0 of every 8 is held out)",
        ));
    }

    let mut surfels: Vec<Surfels> = scene.components.iter().map(|c| c.surfels.clone()).collect();
    let mut trace = TraceScene::from_components(&surfels.iter().collect::<Vec<_>>());
    let ckpt = stage_files.checkpoint();
    let log_path = stage_files.log();
    let (mut c, resumed) = resume_or_start(
        &ckpt,
        opts.resume,
        opts.quiet,
        |p| read_resumable(p, &opts.settings, &surfels),
        || {
            say(
                opts.quiet,
                if opts.settings.light_fit {
                    "fitting each state's lighting to the shadows (linear, 32x16 texels)"
                } else {
                    "initialising each state's environment from the pixels its views see it in"
                },
            );
            let refs: Vec<&Surfels> = surfels.iter().collect();
            let (mut inverter, light_fit) =
                Inverter::start(opts.settings.clone(), &trace, &loop_states, &refs);
            if let Some(f) = &light_fit {
                say(
                    opts.quiet,
                    &format!(
                        "lighting fit: {} rows, {} sky texels, residual {:.3} -> {:.3}, the surroundings' light {:.0} %, suns {} % of each map's power ({} clusters taken out by the backward test), {:.1} s",
                        f.rows,
                        f.sky_texels,
                        f.residual[0],
                        f.residual[1],
                        100.0 * f.bounce_share,
                        f.sun_share
                            .iter()
                            .map(|v| format!("{:.0}", 100.0 * v))
                            .collect::<Vec<_>>()
                            .join(" / "),
                        f.suns_pruned
                            .iter()
                            .map(|v| v.to_string())
                            .collect::<Vec<_>>()
                            .join(" / "),
                        f.seconds
                    ),
                );
            }
            let material_search = opts.settings.material_search.then(|| {
                let mut scratch = surfels.clone();
                let component_names: Vec<String> =
                    scene.components.iter().map(|c| c.name.clone()).collect();
                let f = super::hypotheses::search(
                    &mut inverter,
                    &mut trace,
                    &mut scratch,
                    &loop_states,
                    &component_names,
                );
                for o in &f.objects {
                    say(
                        opts.quiet,
                        &format!(
                            "material search: {} starts {} ({})",
                            o.object,
                            o.chosen,
                            o.hypotheses
                                .iter()
                                .map(|h| format!("{} {:.3}", h.name, h.residual))
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    );
                }
                f
            });
            Ok(Checkpoint {
                inverter,
                training_seconds: 0.0,
                light_fit,
                material_search,
            })
        },
    )?;
    let mut log = StageLog::create(&log_path, resumed)?;

    let total = opts.settings.iterations;
    // An iteration's cost is about proportional to its samples per pixel.
    let mut bar = Progress::new(opts.quiet, total as u64, "inverting")
        .step_costs(|i| opts.settings.spp_at(i as u32) as f64);
    bar.start_at(c.inverter.iteration as u64);
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
        |c, _| Ok(c.inverter.step(&mut trace, &mut surfels, &loop_states)),
        |c, m| {
            // The samples per pixel the last iteration drew, not their window mean.
            let spp = c
                .inverter
                .settings
                .spp_at(c.inverter.iteration.saturating_sub(1));
            m.insert("spp".into(), spp.into());
            m.insert("seconds".into(), t0.elapsed().as_secs_f64().into());
            let l1 = m.get("l1").and_then(|v| v.as_f64()).unwrap_or(0.0);
            format!("L1 {l1:.4} · {spp} spp")
        },
    )?;
    bar.finish();

    // The relightable scene: materials in the surfels, each training state lit by its
    // recovered environment (world frame: rotation 0).
    c.inverter.write_materials(&mut surfels);
    let mut out = scene.clone();
    for (comp, s) in out.components.iter_mut().zip(&surfels) {
        comp.surfels = s.clone();
    }
    out.environments.clear();
    for (j, name) in names.iter().enumerate() {
        let env = c.inverter.environment(j, &format!("{name}-recovered"));
        out.environments.push(env);
        let s = out.state_index(name).expect("checked");
        out.states[s].environment = Some(EnvRef {
            index: out.environments.len() - 1,
            rotation_deg: 0.0,
        });
    }
    crate::io::write_scene(&out, &opts.work.relightable())?;
    crate::io::write_scene(&out, &opts.work.relightable_usda())?;

    say(
        opts.quiet,
        "measuring: rendering the training and held-out views",
    );
    let report = Report {
        dataset: dataset.file.display().to_string(),
        scene: scene_file.display().to_string(),
        settings: opts.settings.clone(),
        eval_spp: opts.eval_spp,
        eval_stride: opts.eval_stride,
        iterations: c.inverter.iteration,
        seconds: t0.elapsed().as_secs_f64(),
        training_seconds: c.training_seconds,
        surfels: out.surfel_count(),
        primary_cache: c.inverter.cache().map(PrimaryCache::figures),
        states: Vec::new(),
        albedo: None,
        materials: Vec::new(),
        light_fit: c.light_fit.clone(),
        material_search: c.material_search.clone(),
    };
    let figures = crate::eval::stage3::measure(
        &out,
        &dataset,
        &train_states,
        &names,
        &train,
        &held,
        opts.eval_spp,
        opts.eval_stride,
        opts.settings.bounces,
    )?;
    let report = Report {
        states: figures.states,
        albedo: figures.albedo,
        materials: figures.materials,
        ..report
    };
    let mut files = AtomicFiles::new();
    files.write(
        &stage_files.report(),
        &serde_json::to_vec_pretty(&report).expect("report serialises"),
    )?;
    files.commit()?;
    Ok(report)
}
