//! `lightfuse evaluate`: the paper's experiment (§ Novel-State Relighting, Tables 1 and 2).
//!
//! For every test state of a dataset, its arrangement (the dataset's object poses, the target
//! transforms) is rendered from the state's cameras and compared with the Cycles frames:
//! - **relighting** (Table 1): under each environment no training state saw, the dataset's own
//!   file of it;
//! - **synthesis** (Table 2): under a training state's lighting (relight runs with
//!   `training_state`), rendered with that state's *recovered* environment, against Cycles under
//!   the true one.
//!
//! Rows, one image each per (run, view):
//! - **LightFuse**: the relightable scene (stage 3) placed in the test layout and path traced
//!   ([`Strategy::Full`]): shadows, highlights and inter-reflection re-traced for the layout;
//! - **Baked**: stage 1's splatting appearance moved to the layout (what methods that bake
//!   appearance can do; it cannot relight), over the run's environment where it is not opaque
//!   (any method shows the environment behind the scene);
//! - **No re-tracing**: the recovered materials lit by the run's environment without visibility
//!   or indirect light ([`Strategy::Unshadowed`], a ReCap-like row).
//!
//! The traced rows share each view's primary records ([`Primaries`]): geometry and layout
//! decide them, so every environment and both traced rows reuse one trace per view.
//!
//! Metrics per image: PSNR and SSIM (3DGS's: 11×11 Gaussian, σ 1.5) on 8-bit sRGB, and PSNR on
//! scene-linear HDR with the reference's peak ([`crate::eval::metrics`]). Each traced row is
//! also measured after the per-channel median albedo rescale (TensoIR/IRGS's convention): one
//! ratio per scene, the median over the test views' surface pixels of true / recovered base
//! colour ([`compare_albedo`]), every record's base colour multiplied by it (clamped to 1) and
//! the same paths re-evaluated ([`Primaries::shade`]). Baked has no base colour to rescale.
//! A row's figure is the mean over its images.
//!
//! Denoising ([`Options::denoise`], on by default): the paper's evaluation denoised its 32-spp
//! renders with OptiX's HDR denoiser and albedo + normal guides; we use Intel Open Image
//! Denoise's `RT` filter in HDR mode with the same two guides ([`crate::shade::denoise`]; OptiX
//! needs an NVIDIA GPU, OIDN is its CPU counterpart and Blender's own). Each traced image is
//! denoised on its own (both rows, raw and rescaled), with guides from the view's pixel-centre
//! records, pixels that saw only the environment kept as rendered ([`denoise_render`]).
//! Baked is splatted, noise-free, and is not denoised. `--no-denoise` compares the images as
//! rendered (the report's `denoise` says which).

use crate::error::{Error, Result};
use crate::eval::html;
use crate::eval::lighting::{
    compare_albedo, compare_environments, irradiance_sphere, luminous_power,
};
use crate::eval::report::comparison_strip;
use crate::eval::tables::{
    markdown, mean_rows, Metrics, Report, RowFigures, RunFigures, Selection, StateEnvironment,
    ViewFigures, ViewUniformity, DENOISER, FORMAT,
};
use crate::io::dataset::{Dataset, Frame};
use crate::io::file_stem;
use crate::io::work::{read_stage_scene, WorkDir};
use crate::scene::{Environment, Layout, Scene, State};
use crate::shade::denoise::denoise_render;
use crate::shade::estimator::{self_hit_epsilon, Estimator, PixelFilter, Strategy};
use crate::shade::render::{environment_image, Aovs, Primaries};
use crate::shade::replay::{check_bounces, MAX_BOUNCES};
use crate::shade::EnvMap;
use crate::trace::TraceScene;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Samples per pixel of the traced rows (the paper's 32; `--spp`).
pub const DEFAULT_SPP: u32 = 32;

#[derive(Clone)]
pub struct Options {
    pub dataset: PathBuf,
    pub work: WorkDir,
    /// Samples per pixel of the traced rows (the paper: 32).
    pub spp: u32,
    /// Indirect bounces of the traced rows ([`Estimator::bounces`]; the paper: 1). None: the
    /// ones stage 3 trained with ([`trained_bounces`]), so a scene is relit by the estimator
    /// that fitted its materials.
    pub bounces: Option<u32>,
    pub seed: u32,
    /// Write a comparison strip per (run, view) into `<work>/eval/images/`.
    pub images: bool,
    /// Denoise the traced rows with Open Image Denoise (needs the `denoise` build feature).
    pub denoise: bool,
    /// Which baseline rows and which tables' runs to render (default: everything).
    pub selection: Selection,
    pub quiet: bool,
}

/// One run to evaluate: a test state's frames under one environment.
struct Run<'d> {
    state: usize,
    environment: &'d str,
    training_state: Option<&'d str>,
    frames: &'d [Frame],
}

fn runs(d: &Dataset, sel: Selection) -> Vec<Run<'_>> {
    let mut out = Vec::new();
    for (k, s) in d.states.iter().enumerate() {
        if s.split != "test" {
            continue;
        }
        if let (Some(env), false, true) = (&s.environment, s.frames.is_empty(), sel.relighting) {
            out.push(Run {
                state: k,
                environment: env,
                training_state: None,
                frames: &s.frames,
            });
        }
        for r in &s.relight {
            let wanted = match r.training_state {
                Some(_) => sel.synthesis,
                None => sel.relighting,
            };
            if wanted && !r.frames.is_empty() {
                out.push(Run {
                    state: k,
                    environment: &r.environment,
                    training_state: r.training_state.as_deref(),
                    frames: &r.frames,
                });
            }
        }
    }
    out
}

/// Refuses a dataset with nothing to evaluate against: no test state with frames.
pub fn check_dataset(d: &Dataset) -> Result<()> {
    if runs(d, Selection::ALL).is_empty() {
        return Err(Error::invalid(
            &d.file,
            "states",
            "expected a test state (split \"test\") with frames to compare against (blender/generate.py writes one with `relight` runs)",
        ));
    }
    Ok(())
}

/// The scene a stage wrote into the work folder, or a clear error naming the stage to run.
fn stage_scene(path: PathBuf, d: &Dataset, stage: &str) -> Result<(PathBuf, Scene)> {
    let scene = read_stage_scene(
        &path,
        d,
        &format!("run `{stage}` first (or `lightfuse run`)"),
    )?;
    Ok((path, scene))
}

/// The test state's arrangement in `scene`: the dataset's object poses (relative to the
/// reference state, where every scene component is defined).
fn test_state(scene: &Scene, d: &Dataset, k: usize) -> Result<State> {
    let mut layout = Layout::default();
    for o in &d.objects {
        layout
            .objects
            .insert(o.name.clone(), d.object_pose(k, &o.name)?);
    }
    scene.state_from_layout(&d.states[k].name, &layout, &d.file)
}

/// The environment a run is lit with, and what it is.
fn run_environment(
    run: &Run,
    d: &Dataset,
    scene: &Scene,
    scene_file: &Path,
) -> Result<(EnvMap, String)> {
    if let Some(t) = run.training_state {
        let state = scene.state_index(t).map(|i| &scene.states[i]);
        let Some(r) = state.and_then(|s| s.environment) else {
            return Err(Error::invalid(
                scene_file,
                "states",
                format!("expected training state {t:?} with its recovered environment (stage 3 writes one per training state)"),
            ));
        };
        let env = &scene.environments[r.index];
        return Ok((
            EnvMap::new(env, r.rotation_deg),
            format!("recovered: {}#{}", scene_file.display(), env.name),
        ));
    }
    let path = d.path(run.environment);
    let env = crate::io::exr::read_lighting(&path, Some(run.environment))?;
    Ok((
        EnvMap::new(&env, 0.0),
        format!("dataset: {}", run.environment),
    ))
}

/// Everything an evaluation reads, read and checked before anything is rendered or written.
struct Inputs<'d> {
    d: &'d Dataset,
    runs: Vec<Run<'d>>,
    /// Per run: the environment it is lit with, and what that is.
    envs: Vec<(EnvMap, String)>,
    relit_file: PathBuf,
    relit: Scene,
    baked_file: PathBuf,
    baked: Scene,
    /// The dataset's test states that have runs, and each one's arrangement in the relightable
    /// and in the baked scene.
    test_states: Vec<usize>,
    relit_states: Vec<State>,
    baked_states: Vec<State>,
}

impl<'d> Inputs<'d> {
    fn load(opts: &Options, d: &'d Dataset) -> Result<Inputs<'d>> {
        check_dataset(d)?;
        let runs = runs(d, opts.selection);
        if runs.is_empty() {
            return Err(Error::invalid(
                &d.file,
                "states.relight",
                "expected a test run of the requested --tables (Table 2's are relight runs with a training_state)",
            ));
        }
        let (relit_file, relit) = stage_scene(opts.work.relightable(), d, "lightfuse invert")?;
        let (baked_file, baked) = stage_scene(opts.work.scene(), d, "lightfuse reconstruct")?;
        let mut envs = Vec::with_capacity(runs.len());
        for run in &runs {
            envs.push(run_environment(run, d, &relit, &relit_file)?);
            for f in run.frames {
                let p = d.path(&f.file_path);
                if !p.is_file() {
                    return Err(Error::invalid(
                        &d.file,
                        "frames.file_path",
                        format!("expected the Cycles frame {} (missing)", p.display()),
                    ));
                }
            }
        }
        let test_states: Vec<usize> = {
            let mut v: Vec<usize> = runs.iter().map(|r| r.state).collect();
            v.dedup();
            v
        };
        let relit_states: Vec<State> = test_states
            .iter()
            .map(|&k| test_state(&relit, d, k))
            .collect::<Result<_>>()?;
        let baked_states: Vec<State> = test_states
            .iter()
            .map(|&k| test_state(&baked, d, k))
            .collect::<Result<_>>()?;
        Ok(Inputs {
            d,
            runs,
            envs,
            relit_file,
            relit,
            baked_file,
            baked,
            test_states,
            relit_states,
            baked_states,
        })
    }
}

/// What the evaluation writes besides the report: the PNGs beside it and the page's assets.
#[derive(Default)]
struct Pictures {
    strips: Vec<(PathBuf, image::RgbImage)>,
    assets: html::Assets,
}

/// The indirect bounces stage 3 trained with, from its report (`settings.bounces`): 1, the
/// paper's, when there is no report or it predates the setting; an error naming the report
/// when it cannot be read or holds a value no estimator takes. Read as plain JSON: the
/// report's type belongs to the stages, above this layer.
pub fn trained_bounces(report: &Path) -> Result<u32> {
    let bytes = match std::fs::read(report) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(1),
        Err(e) => return Err(Error::io(report, e)),
    };
    let v: serde_json::Value = serde_json::from_slice(&bytes).map_err(|e| {
        Error::invalid(
            report,
            "report",
            format!("expected stage 3's report (JSON): {e}"),
        )
    })?;
    match v.get("settings").and_then(|s| s.get("bounces")) {
        None => Ok(1),
        Some(b) => b
            .as_u64()
            .and_then(|b| u32::try_from(b).ok())
            .filter(|&b| check_bounces(b, "").is_ok())
            .ok_or_else(|| {
                Error::invalid(
                    report,
                    "settings.bounces",
                    format!("expected 1 to {MAX_BOUNCES} indirect bounces, found {b}"),
                )
            }),
    }
}

/// Runs the evaluation and writes `<work>/eval/{eval.json, eval.md, report.html}` (and the
/// images: [`crate::eval::html`]): the inputs loaded and checked, the median albedo ratio,
/// every (run, view) rendered and measured (`render_view`), the figures pooled into the
/// tables, and the files written last, so a failed evaluation leaves an earlier `eval/` as it
/// was.
pub fn evaluate(opts: &Options) -> Result<Report> {
    let t0 = Instant::now();
    let bounces = match opts.bounces {
        Some(b) => check_bounces(b, "--bounces")?,
        None => trained_bounces(&opts.work.invert().report())?,
    };
    if opts.spp == 0 || opts.spp > crate::shade::sobol::MAX_SAMPLES {
        return Err(Error::Usage(format!(
            "--spp: expected 1 ..= {}, found {}",
            crate::shade::sobol::MAX_SAMPLES,
            opts.spp
        )));
    }
    if opts.denoise {
        crate::shade::denoise::require("or pass --no-denoise to compare the images as rendered")?;
    }
    let d = Dataset::read(&opts.dataset)?;
    let input = Inputs::load(opts, &d)?;
    let filter = PixelFilter::new(crate::shade::estimator::DEFAULT_FILTER_WIDTH);
    let trace = TraceScene::new(&input.relit);
    let out_dir = opts.work.eval_dir();
    let measures = albedo_ratio(
        &input,
        &trace,
        &filter,
        opts.seed,
        opts.images.then_some(out_dir.as_path()),
    )?;
    let albedo = &measures.figures;
    let ratio = albedo
        .ratio
        .map(|r| if r.is_finite() { r as f32 } else { 1.0 });
    let scales = [[1.0; 3], ratio];

    let (runs, d) = (&input.runs, input.d);
    let total: u64 = runs.iter().map(|r| r.frames.len() as u64).sum();
    let bar = crate::progress::Progress::new(opts.quiet, total, "evaluate");
    let mut rays = 0u64;
    let mut figures: Vec<RunFigures> = runs
        .iter()
        .zip(&input.envs)
        .map(|(r, (_, lit_by))| RunFigures {
            state: d.states[r.state].name.clone(),
            environment: r.environment.to_string(),
            training_state: r.training_state.map(str::to_string),
            lit_by: lit_by.clone(),
            views: Vec::new(),
            mean: BTreeMap::new(),
        })
        .collect();
    let mut pictures = Pictures {
        strips: measures.strips,
        ..Default::default()
    };
    for (si, &k) in input.test_states.iter().enumerate() {
        let state = TestState {
            placed: trace.place_state(&input.relit_states[si]),
            eps: self_hit_epsilon(&input.relit, &input.relit_states[si]),
            placements: crate::splat::placements(&input.baked, &input.baked_states[si]),
        };
        let my_runs: Vec<usize> = (0..runs.len()).filter(|&r| runs[r].state == k).collect();
        let views = my_runs
            .iter()
            .map(|&r| runs[r].frames.len())
            .max()
            .unwrap_or(0);
        for v in 0..views {
            // One primary trace per distinct camera of this view index.
            let mut primaries: Option<(Primaries, Aovs)> = None;
            for &r in &my_runs {
                let Some(frame) = runs[r].frames.get(v) else {
                    continue;
                };
                let cam = &frame.camera;
                if primaries.as_ref().map(|(p, _)| &p.camera) != Some(cam) {
                    let p = Primaries::trace(&state.placed, &filter, cam, opts.spp, opts.seed);
                    rays += p.rays;
                    let aovs = p.aovs();
                    primaries = Some((p, aovs));
                }
                let (p, aovs) = primaries.as_ref().expect("traced above");
                if opts.images && v == 0 && r == my_runs[0] {
                    pictures.assets.materials.push(material_view(
                        d,
                        k,
                        frame,
                        aovs,
                        &out_dir,
                        &mut pictures.strips,
                    ));
                }
                let view = ViewToRender {
                    run: &runs[r],
                    env: &input.envs[r].0,
                    k,
                    v,
                    frame,
                    primaries: p,
                    aovs,
                };
                let (figure, n) = render_view(
                    opts,
                    bounces,
                    d,
                    &state,
                    &view,
                    &scales,
                    &out_dir,
                    &mut pictures,
                )?;
                rays += n;
                let status = format!(
                    "{} {} view {v}: LightFuse {:.1} dB",
                    d.states[k].name,
                    runs[r].training_state.unwrap_or(runs[r].environment),
                    figure.rows["lightfuse"].raw.psnr_srgb_db
                );
                figures[r].views.push(figure);
                bar.inc(1);
                // Without a terminal (a log), a plain line about every tenth of the frames.
                bar.status(&status);
            }
        }
    }
    bar.finish();
    let envs = recovered_environments(d, &input.relit)?;
    let environments: Vec<StateEnvironment> = envs
        .iter()
        .filter_map(|(state, rec, truth)| {
            truth.as_ref().map(|t| StateEnvironment {
                state: state.clone(),
                figures: compare_environments(rec, t),
            })
        })
        .collect();
    if opts.images {
        pictures.assets.environments =
            environment_pairs(&envs, &environments, &out_dir, &mut pictures.strips);
    }
    let report = Report {
        format: FORMAT.into(),
        dataset: d.file.display().to_string(),
        relightable: input.relit_file.display().to_string(),
        baked: input.baked_file.display().to_string(),
        spp: opts.spp,
        bounces,
        seed: opts.seed,
        denoise: if opts.denoise { DENOISER } else { "none" }.into(),
        selection: opts.selection,
        albedo_ratio: albedo.ratio,
        albedo_pixels: albedo.pixels,
        albedo_uniformity: albedo.uniformity.clone(),
        albedo_away_from_seams: measures.away_from_seams,
        shadow_ghosts: measures.ghosts,
        albedo_views: measures.per_view,
        environments,
        relighting: BTreeMap::new(),
        synthesis: BTreeMap::new(),
        runs: figures,
        rays,
        seconds: 0.0,
    };
    let report = Report {
        seconds: t0.elapsed().as_secs_f64(),
        ..pooled(report)
    };
    write(opts, &report, pictures)?;
    Ok(report)
}

/// The per-channel median albedo ratio (true / recovered base colour), from the pixel-centre
/// records of every test view that has an albedo pass ([`compare_albedo`]); and the same pairs'
/// ghost figures taken apart by where the training states' shadows fell
/// ([`crate::eval::shadows`]), when the dataset has the training states' environments and the
/// views' masks.
///
/// Also each view's ghost figures and, with `out_dir` (images asked for), its strip for the
/// report: the recovered base colour | the albedo pass | the ghost map ([`html::ghost_map`]),
/// each pixel against its surface's median over every view.
fn albedo_ratio(
    input: &Inputs,
    trace: &TraceScene,
    filter: &PixelFilter,
    seed: u32,
    out_dir: Option<&Path>,
) -> Result<AlbedoMeasures> {
    use crate::eval::lighting::{albedo_deviation, away_from_seams, uniformity_of};
    use crate::eval::shadows::{lit_share, shadow_ghosts, Shares};
    use rayon::prelude::*;
    // Each training state as stage 3 saw it (the relightable scene placed by its poses) and
    // the environment that truly lit it.
    let mut lights = Vec::new();
    for (k, st) in input.d.states.iter().enumerate() {
        if st.split != "train" {
            continue;
        }
        let (Some(i), Some(env)) = (input.relit.state_index(&st.name), input.d.environment(k)?)
        else {
            continue;
        };
        let state = &input.relit.states[i];
        lights.push((
            st.name.clone(),
            trace.place_state(state),
            EnvMap::new(&env, 0.0),
            self_hit_epsilon(&input.relit, state),
        ));
    }
    let mut pairs = Vec::new();
    let mut views = Vec::new();
    let mut away_from_seam = Vec::new();
    let mut shares: Vec<Option<Shares>> = Vec::new();
    let mut masks_everywhere = true;
    for (si, &k) in input.test_states.iter().enumerate() {
        let placed = trace.place_state(&input.relit_states[si]);
        let Some(run) = input.runs.iter().find(|r| r.state == k) else {
            continue;
        };
        for (v, f) in run.frames.iter().enumerate() {
            let Some(rel) = &f.albedo_file_path else {
                continue;
            };
            let truth = input.d.frame_rgb(rel, &f.camera)?;
            let mask = input.d.frame_mask(f)?;
            masks_everywhere &= mask.is_some();
            let p = Primaries::trace(&placed, filter, &f.camera, 1, seed);
            let aovs = p.aovs();
            let w = f.camera.w as usize;
            let kept: Vec<usize> = (0..truth.len())
                .filter(|&i| aovs.depth[i] > 0.0 && truth[i].iter().any(|&t| t > 0.0))
                .collect();
            let view_shares: Vec<Option<Shares>> = kept
                .par_iter()
                .map(|&i| {
                    if lights.is_empty() || mask.as_ref().is_none_or(|m| m[i] != 0) {
                        return None;
                    }
                    let (o, d) = f
                        .camera
                        .planar_ray((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
                    let x = glam::Vec3::from(o) + aovs.depth[i] * glam::Vec3::from(d);
                    let n = glam::Vec3::from(aovs.normal[i]);
                    // One generator stream per (view, pixel, state): fixed, and independent.
                    let id = ((k * 4096 + v) * truth.len() + i) as u64;
                    Some(
                        lights
                            .iter()
                            .enumerate()
                            .map(|(j, (_, pl, env, eps))| {
                                lit_share(pl, env, x, n, *eps, id * 8 + j as u64)
                            })
                            .collect(),
                    )
                })
                .collect();
            let first = pairs.len();
            let away = away_from_seams(&truth, w);
            for (&i, s) in kept.iter().zip(view_shares) {
                pairs.push((aovs.albedo[i], truth[i]));
                shares.push(s);
                away_from_seam.push(away[i]);
            }
            let (w, h) = (f.camera.w, f.camera.h);
            let strip = out_dir.map(|_| {
                let mut strip = image::RgbImage::new(3 * w, h);
                image::imageops::replace(&mut strip, &html::srgb_image(&aovs.albedo, w, h), 0, 0);
                image::imageops::replace(&mut strip, &html::srgb_image(&truth, w, h), w as i64, 0);
                strip
            });
            views.push(AlbedoView {
                state: input.d.states[k].name.clone(),
                frame: f.file_path.clone(),
                first,
                pixels: kept,
                size: (w, h),
                strip,
            });
        }
    }
    let names: Vec<String> = lights.iter().map(|l| l.0.clone()).collect();
    let ghosts = (!lights.is_empty() && masks_everywhere && !pairs.is_empty())
        .then(|| shadow_ghosts(&pairs, &shares, &names));
    let deviation = albedo_deviation(&pairs);
    let mut strips = Vec::new();
    let per_view = views
        .into_iter()
        .map(|v| {
            let range = v.first..v.first + v.pixels.len();
            let image = v.strip.zip(out_dir).map(|(mut strip, dir)| {
                let (w, h) = v.size;
                let mut map = vec![None; (w * h) as usize];
                for (&i, d) in v.pixels.iter().zip(&deviation[range.clone()]) {
                    map[i] = Some(d.map(|d| d.1));
                }
                image::imageops::replace(&mut strip, &html::ghost_map(&map, w, h), 2 * w as i64, 0);
                let stem = file_stem(&v.frame).unwrap_or_default();
                let rel = format!("materials/{}/{stem}-ghosts.png", v.state);
                strips.push((dir.join(&rel), strip));
                rel
            });
            ViewUniformity {
                figures: uniformity_of(&deviation, |i| range.contains(&i)),
                state: v.state,
                frame: v.frame,
                image,
            }
        })
        .collect();
    Ok(AlbedoMeasures {
        away_from_seams: uniformity_of(&deviation, |i| away_from_seam[i]),
        figures: compare_albedo(&pairs),
        ghosts,
        per_view,
        strips,
    })
}

/// What [`albedo_ratio`] measures: the base colour against the albedo pass over every test
/// view, the ghosts taken apart by where the training states' shadows fell, each view's ghost
/// figures, and the views' strips (path, image) when images were asked for.
struct AlbedoMeasures {
    figures: crate::eval::lighting::AlbedoFigures,
    ghosts: Option<crate::eval::shadows::ShadowGhosts>,
    away_from_seams: Option<crate::eval::lighting::UniformityFigures>,
    per_view: Vec<ViewUniformity>,
    strips: Vec<(PathBuf, image::RgbImage)>,
}

/// One test view's pixels among [`albedo_ratio`]'s pairs (from `first`, one per kept pixel),
/// with its strip's first two tiles drawn (the third, the ghost map, needs every view's
/// pairs for the surfaces' medians).
struct AlbedoView {
    state: String,
    frame: String,
    first: usize,
    pixels: Vec<usize>,
    size: (u32, u32),
    strip: Option<image::RgbImage>,
}

/// A test state's arrangement, ready to render: the relightable scene placed for tracing (with
/// its self-hit offset) and the baked scene placed for splatting.
struct TestState<'s> {
    placed: crate::trace::Placed<'s>,
    eps: f32,
    placements: Vec<crate::splat::Placement<'s>>,
}

/// One (run, view) to render: the run, its environment, the test state `k` and view index
/// `v`, the Cycles frame, and the view's primary records with their AOVs.
struct ViewToRender<'a> {
    run: &'a Run<'a>,
    env: &'a EnvMap,
    k: usize,
    v: usize,
    frame: &'a Frame,
    primaries: &'a Primaries,
    aovs: &'a Aovs,
}

/// Renders one (run, view) in every selected row (LightFuse and No re-tracing traced from the
/// shared primaries, raw and rescaled, denoised if asked; Baked splatted over the environment),
/// measures each against the Cycles frame, and adds its comparison strip to `pictures`.
/// Returns the view's figures and the rays traced.
#[allow(clippy::too_many_arguments)]
fn render_view(
    opts: &Options,
    bounces: u32,
    d: &Dataset,
    state: &TestState,
    view: &ViewToRender,
    scales: &[[f32; 3]; 2],
    out_dir: &Path,
    pictures: &mut Pictures,
) -> Result<(ViewFigures, u64)> {
    let (frame, p, aovs) = (view.frame, view.primaries, view.aovs);
    let cam = &frame.camera;
    let (w, h) = (cam.w, cam.h);
    let mut rays = 0u64;
    let truth = d.frame_rgb(&frame.file_path, cam)?;
    let bg = environment_image(view.env, cam);
    let mut traced = Vec::new();
    let strategies: &[Strategy] = if opts.selection.no_retracing {
        &[Strategy::Full, Strategy::Unshadowed]
    } else {
        &[Strategy::Full]
    };
    for &strategy in strategies {
        let est = Estimator::new(&state.placed, view.env, state.eps)
            .with_strategy(strategy)
            .with_bounces(bounces);
        let (mut images, n) = p.shade(&est, scales);
        rays += n;
        if opts.denoise {
            for (img, s) in images.iter_mut().zip(scales) {
                *img = denoise_render(img, aovs, &bg, s, w as usize, h as usize)?;
            }
        }
        traced.push(images);
    }
    let baked_img: Option<Vec<[f32; 3]>> = opts.selection.baked.then(|| {
        let splat = crate::splat::forward(&state.placements, cam).image;
        (0..splat.color.len())
            .map(|i| {
                let t = 1.0 - splat.alpha[i].clamp(0.0, 1.0);
                [0, 1, 2].map(|c| splat.color[i][c] + t * bg[i][c])
            })
            .collect()
    });
    let row = |images: &[Vec<[f32; 3]>]| RowFigures {
        raw: Metrics::of(&images[0], &truth, w, h),
        rescaled: Some(Metrics::of(&images[1], &truth, w, h)),
    };
    let mut rows = BTreeMap::new();
    rows.insert("lightfuse".to_string(), row(&traced[0]));
    if let Some(img) = &baked_img {
        rows.insert(
            "baked".to_string(),
            RowFigures {
                raw: Metrics::of(img, &truth, w, h),
                rescaled: None,
            },
        );
    }
    if let Some(images) = traced.get(1) {
        rows.insert("no_retracing".to_string(), row(images));
    }
    let image = if opts.images {
        let run_name = file_stem(view.run.environment).unwrap_or_default();
        let stem = file_stem(&frame.file_path).unwrap_or_else(|| format!("{:03}", view.v));
        let rel = format!(
            "images/{}/{}/{stem}.png",
            d.states[view.k].name,
            view.run.training_state.unwrap_or(&run_name)
        );
        pictures.strips.push((
            out_dir.join(&rel),
            comparison_strip(
                &truth,
                &traced[0][0],
                &[baked_img.as_deref(), traced.get(1).map(|t| &t[0][..])],
                None,
                w,
                h,
            ),
        ));
        Some(rel)
    } else {
        None
    };
    Ok((
        ViewFigures {
            frame: frame.file_path.clone(),
            image,
            rows,
        },
        rays,
    ))
}

/// The report with each run's mean and the tables' pooled means: Table 1 over every
/// relighting run's images, Table 2 over every synthesis run's.
fn pooled(mut report: Report) -> Report {
    for f in &mut report.runs {
        let rows: Vec<&BTreeMap<String, RowFigures>> = f.views.iter().map(|v| &v.rows).collect();
        f.mean = mean_rows(&rows);
    }
    let pool = |synthesis: bool| {
        let rows: Vec<&BTreeMap<String, RowFigures>> = report
            .runs
            .iter()
            .filter(|f| f.training_state.is_some() == synthesis)
            .flat_map(|f| f.views.iter().map(|v| &v.rows))
            .collect();
        mean_rows(&rows)
    };
    Report {
        relighting: pool(false),
        synthesis: pool(true),
        ..report
    }
}

/// Writes the strips, `eval.json`, `eval.md` and `report.html` (with the stages' loss curves
/// read from their logs) together: all or nothing.
fn write(opts: &Options, report: &Report, mut pictures: Pictures) -> Result<()> {
    pictures.assets.curves = [
        (
            "Stage 1: reconstruction (eq. reconstruction-objective)",
            opts.work.reconstruct().log(),
        ),
        (
            "Stage 2: refinement for ray tracing (eq. geometry-objective)",
            opts.work.refine().log(),
        ),
        ("Stage 3: inverse rendering", opts.work.invert().log()),
    ]
    .iter()
    .filter_map(|(title, log)| html::read_curve(title, log))
    .collect();
    let mut files = crate::io::AtomicFiles::new();
    for (path, img) in &pictures.strips {
        let mut bytes = Vec::new();
        img.write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|e| Error::io(path, std::io::Error::other(e)))?;
        files.write(path, &bytes)?;
    }
    files.write(
        &opts.work.eval_json(),
        serde_json::to_string_pretty(report)
            .expect("the report serialises")
            .as_bytes(),
    )?;
    files.write(&opts.work.eval_md(), markdown(report).as_bytes())?;
    files.write(
        &opts.work.report_html(),
        html::page(report, &pictures.assets).as_bytes(),
    )?;
    files.commit()
}

/// The report's material images of one view: roughness and metallic from the view's records,
/// and its base colour when the dataset has no albedo pass (with one, every view's base colour
/// is beside it, [`albedo_ratio`]'s strips).
fn material_view(
    d: &Dataset,
    k: usize,
    frame: &Frame,
    aovs: &Aovs,
    out_dir: &Path,
    pngs: &mut Vec<(PathBuf, image::RgbImage)>,
) -> html::MaterialView {
    let (w, h) = (frame.camera.w, frame.camera.h);
    let state = &d.states[k].name;
    let stem = frame.stem();
    let mut figures = Vec::new();
    let mut add = |name: &str, caption: &str, img: image::RgbImage| {
        let rel = format!("materials/{state}/{stem}-{name}.png");
        pngs.push((out_dir.join(&rel), img));
        figures.push(html::Figure {
            file: rel,
            caption: caption.into(),
        });
    };
    if frame.albedo_file_path.is_none() {
        add(
            "base_color",
            "base colour (recovered)",
            html::srgb_image(&aovs.albedo, w, h),
        );
    }
    add(
        "roughness",
        "roughness",
        html::grey_image(&aovs.roughness, w, h),
    );
    add(
        "metallic",
        "metallic",
        html::grey_image(&aovs.metallic, w, h),
    );
    html::MaterialView {
        state: state.clone(),
        frame: frame.file_path.clone(),
        figures,
    }
}

/// Each training state's recovered environment with the dataset's (None when the dataset has
/// no file of it), in the dataset's order. The dataset's files are stored as Cycles used them
/// (rotation applied), the world frame the recovered maps are in.
fn recovered_environments<'a>(
    d: &Dataset,
    relit: &'a Scene,
) -> Result<Vec<(String, &'a Environment, Option<Environment>)>> {
    let mut out = Vec::new();
    for (k, st) in d.states.iter().enumerate() {
        if st.split != "train" {
            continue;
        }
        let Some(env) = relit
            .state_index(&st.name)
            .and_then(|i| relit.states[i].environment)
            .map(|r| &relit.environments[r.index])
        else {
            continue;
        };
        out.push((st.name.clone(), env, d.environment(k)?));
    }
    Ok(out)
}

/// Side of each irradiance sphere in the report, pixels.
const SPHERE_SIZE: usize = 96;

/// The report's lighting images, per training state: the recovered map beside the dataset's at
/// one exposure, and the two maps' irradiance spheres ([`irradiance_sphere`]) at one exposure.
/// The recovered map is known up to a global scale (traded with the base colour), so it is
/// first brought to the truth's luminous power; the exposure is then the truth's own
/// ([`html::latlong_exposure`], [`html::median_exposure`]). Without a truth, the recovered map
/// alone at its own exposure.
fn environment_pairs(
    envs: &[(String, &Environment, Option<Environment>)],
    figures: &[StateEnvironment],
    out_dir: &Path,
    pngs: &mut Vec<(PathBuf, image::RgbImage)>,
) -> Vec<html::EnvironmentPair> {
    let mut pairs = Vec::new();
    for (state, rec, truth) in envs {
        let mut png = |name: &str, img: image::RgbImage| {
            let rel = format!("environments/{state}-{name}.png");
            pngs.push((out_dir.join(&rel), img));
            rel
        };
        let rec_sphere = irradiance_sphere(rec, SPHERE_SIZE);
        let (rec_map, rec_ball, truth_figs, spheres);
        match truth {
            Some(t) => {
                let p_rec = luminous_power(rec);
                let gain = if p_rec > 0.0 {
                    (luminous_power(t) / p_rec) as f32
                } else {
                    1.0
                };
                let (e_map, t_sphere) =
                    (html::latlong_exposure(t), irradiance_sphere(t, SPHERE_SIZE));
                let e_ball = html::median_exposure(t_sphere.iter().flatten());
                rec_map = html::tonemap_latlong_exposed(rec, gain * e_map);
                rec_ball = html::tonemap_sphere(&rec_sphere, 2 * SPHERE_SIZE, gain * e_ball);
                let truth_map = png("truth", html::tonemap_latlong_exposed(t, e_map));
                let truth_ball = png(
                    "truth-irradiance",
                    html::tonemap_sphere(&t_sphere, 2 * SPHERE_SIZE, e_ball),
                );
                truth_figs = Some((truth_map, truth_ball, t.width, t.height, gain));
            }
            None => {
                rec_map = html::tonemap_latlong(rec);
                rec_ball = html::tonemap_sphere(
                    &rec_sphere,
                    2 * SPHERE_SIZE,
                    html::median_exposure(rec_sphere.iter().flatten()),
                );
                truth_figs = None;
            }
        }
        let (rec_map, rec_ball) = (
            png("recovered", rec_map),
            png("recovered-irradiance", rec_ball),
        );
        let scaled = truth_figs.as_ref().map_or(String::new(), |f| {
            format!(", ×{:.3} to the truth's power", f.4)
        });
        let recovered = html::Figure {
            file: rec_map,
            caption: format!("recovered ({}×{}{scaled})", rec.width, rec.height),
        };
        let mut sphere_figs = vec![html::Figure {
            file: rec_ball,
            caption: format!("recovered: a white matte sphere from +X and −X{scaled}"),
        }];
        let truth = truth_figs.map(|(map, ball, w, h, _)| {
            sphere_figs.push(html::Figure {
                file: ball,
                caption: "truth: the same sphere".into(),
            });
            html::Figure {
                file: map,
                caption: format!("truth ({w}×{h})"),
            }
        });
        spheres = sphere_figs;
        pairs.push(html::EnvironmentPair {
            state: state.clone(),
            recovered,
            truth,
            spheres,
            figures: figures
                .iter()
                .find(|f| &f.state == state)
                .map(|f| f.figures.clone()),
        });
    }
    pairs
}
