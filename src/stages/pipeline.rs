//! `lightfuse run`: stages 1–3 and the evaluation in order, on one work folder (docs/design.md §4).
//!
//! A step is skipped when its outputs exist and are newer than its inputs (the dataset's
//! `dataset.json` and the previous step's output), unless `<work>/run.json` records that another
//! preset made the folder; otherwise it runs with `resume`, so a killed run continues from the
//! step's checkpoint. A changed preset (or `--force`) runs every step afresh.

use crate::error::{Error, Result};
use crate::io::work::WorkDir;
use crate::progress::say;
use crate::stages::invert::train::Overrides;
use crate::stages::invert::Settings;
use crate::stages::Preset;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::SystemTime;

pub struct Options {
    pub dataset: PathBuf,
    pub work: WorkDir,
    /// "fast" or "paper", for every stage.
    pub preset: Preset,
    /// Run every step even when its outputs are up to date.
    pub force: bool,
    /// Denoise the evaluation's traced rows (see [`crate::eval::relight::Options::denoise`]);
    /// an `eval.json` made with the other setting is out of date.
    pub denoise: bool,
    /// Stage 3's options on top of the preset's ([`Overrides`]); a stage-3 output trained with
    /// other values for any of them is out of date.
    pub invert: Overrides,
    pub quiet: bool,
}

/// What a step did.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct StepOutcome {
    pub step: String,
    /// "ran" or "skipped (up to date)".
    pub outcome: String,
    pub seconds: f64,
}

/// `<work>/run.json`.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct RunRecord {
    pub format: String,
    pub preset: String,
    pub steps: Vec<StepOutcome>,
}

fn modified(path: &Path) -> Option<SystemTime> {
    std::fs::metadata(path).and_then(|m| m.modified()).ok()
}

/// True when every output exists and is at least as new as every input.
fn up_to_date(outputs: &[PathBuf], inputs: &[PathBuf]) -> bool {
    let newest_input = inputs.iter().filter_map(|p| modified(p)).max();
    outputs.iter().all(|o| match (modified(o), newest_input) {
        (Some(t), Some(i)) => t >= i,
        (Some(_), None) => true,
        (None, _) => false,
    })
}

/// False when an evaluation output was made with another denoising setting than `denoise`, or
/// rendered only some of the rows or tables (`lightfuse evaluate --rows/--tables`).
fn eval_settings_match(eval_json: &Path, denoise: bool) -> bool {
    let Some(v) = std::fs::read(eval_json)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
    else {
        return false;
    };
    let denoised = v
        .get("denoise")
        .and_then(|d| d.as_str())
        .map(|d| d != "none");
    // Reports written before the field rendered everything.
    let complete = v.get("selection").is_none_or(|s| {
        serde_json::from_value::<crate::eval::tables::Selection>(s.clone())
            .is_ok_and(|s| s == crate::eval::tables::Selection::ALL)
    });
    denoised == Some(denoise) && complete
}

/// False when stage 3's report was trained with other values than `options` give (the options
/// not given are not compared: an output `lightfuse invert` made with its own options counts
/// as it is, as stage 1's and 2's outputs do), or when it records no settings or cannot be read.
/// A report without one of the later fields was trained with its default, as serde reads it.
fn invert_settings_match(report_json: &Path, options: &Overrides) -> bool {
    std::fs::read(report_json)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| serde_json::from_value::<Settings>(v.get("settings")?.clone()).ok())
        .is_some_and(|recorded| {
            options
                .apply(recorded.clone())
                .is_ok_and(|asked| asked == recorded)
        })
}

/// Runs stages 1–3 and the evaluation; returns what each step did.
pub fn run(opts: &Options) -> Result<Vec<StepOutcome>> {
    if opts.denoise {
        // Checked here too, so that the run fails before the stages rather than after them.
        crate::shade::denoise::require("or pass --no-denoise to evaluate undenoised")?;
    }
    // Checked before the stages too, so that a bad option fails before hours of stage 1.
    let invert_settings = invert_settings(opts)?;
    let dataset = crate::io::dataset::Dataset::read(&opts.dataset)?;
    crate::eval::relight::check_dataset(&dataset)?;
    let mut runner = Runner::new(opts)?;
    let (w, ds) = (&opts.work, &dataset.file);
    runner.step(
        "stage 1: reconstruct",
        vec![w.scene(), w.reconstruct().report()],
        vec![ds.clone()],
        &mut |resume| {
            use crate::stages::reconstruct::{run, train::Settings};
            run::reconstruct(&run::Options {
                dataset: ds.clone(),
                work: w.clone(),
                settings: opts.preset.pick(Settings::fast, Settings::paper),
                oracle_poses: false,
                resume,
                quiet: opts.quiet,
                voxel: run::DEFAULT_VOXEL,
                tau_d: run::DEFAULT_TAU_D,
            })
            .map(|_| ())
        },
    )?;
    runner.step(
        "stage 2: refine",
        vec![w.refined(), w.refine().report()],
        vec![ds.clone(), w.scene()],
        &mut |resume| {
            use crate::stages::refine::{self, Settings};
            refine::refine(&refine::Options {
                dataset: ds.clone(),
                work: w.clone(),
                scene: None,
                settings: opts.preset.pick(Settings::fast, Settings::paper),
                leaks: Default::default(),
                resume,
                quiet: opts.quiet,
            })
            .map(|_| ())
        },
    )?;
    runner.step(
        "stage 3: invert",
        vec![w.relightable(), w.invert().report()],
        vec![ds.clone(), w.refined()],
        &mut |resume| {
            use crate::stages::invert;
            invert::invert(&invert::Options {
                dataset: ds.clone(),
                work: w.clone(),
                scene: None,
                settings: invert_settings.clone(),
                eval_spp: invert::run::DEFAULT_EVAL_SPP,
                eval_stride: invert::run::DEFAULT_EVAL_STRIDE,
                resume,
                quiet: opts.quiet,
            })
            .map(|_| ())
        },
    )?;
    runner.step(
        "evaluate",
        vec![w.eval_json()],
        vec![ds.clone(), w.scene(), w.relightable()],
        &mut |_| {
            crate::eval::relight::evaluate(&crate::eval::relight::Options {
                dataset: ds.clone(),
                work: w.clone(),
                spp: crate::eval::relight::DEFAULT_SPP,
                bounces: None,
                seed: 0,
                images: true,
                denoise: opts.denoise,
                selection: crate::eval::tables::Selection::ALL,
                quiet: opts.quiet,
            })
            .map(|_| ())
        },
    )?;
    Ok(runner.steps)
}

/// Stage 3's settings for the run: the preset's, with the run's options.
fn invert_settings(opts: &Options) -> Result<Settings> {
    opts.invert
        .apply(opts.preset.pick(Settings::fast, Settings::paper))
}

/// Runs the steps of one `lightfuse run` in order, skipping those whose outputs are up to date
/// and made with the same settings, and records each in `run.json` as it ends.
struct Runner<'o> {
    opts: &'o Options,
    record_path: PathBuf,
    /// Every step runs afresh (`--force`, or another preset made the folder).
    fresh: bool,
    steps: Vec<StepOutcome>,
}

impl<'o> Runner<'o> {
    fn new(opts: &'o Options) -> Result<Runner<'o>> {
        let record_path = opts.work.run_record();
        // Outputs of the single-stage commands (no run.json) count as they are; a recorded
        // other preset does not.
        let other_preset = std::fs::read(&record_path)
            .ok()
            .and_then(|b| serde_json::from_slice::<RunRecord>(&b).ok())
            .is_some_and(|r| r.preset != opts.preset.name());
        if other_preset {
            say(
                opts.quiet,
                &format!(
                    "{}: another preset made this work folder; every step runs again",
                    record_path.display()
                ),
            );
        }
        let root = opts.work.root();
        std::fs::create_dir_all(root).map_err(|e| Error::io(root, e))?;
        Ok(Runner {
            opts,
            record_path,
            fresh: opts.force || other_preset,
            steps: Vec::new(),
        })
    }

    /// Whether the outputs of step `name` were made with this run's settings (stage 3's options,
    /// the evaluation's denoising; the other steps' settings are the preset's).
    fn settings_match(&self, name: &str, outputs: &[PathBuf]) -> bool {
        match name {
            "evaluate" => eval_settings_match(&outputs[0], self.opts.denoise),
            "stage 3: invert" => invert_settings_match(&outputs[1], &self.opts.invert),
            _ => true,
        }
    }

    /// Runs step `name` (`f(resume)`) unless its `outputs` are newer than its `inputs` and
    /// were made with the same settings.
    fn step(
        &mut self,
        name: &str,
        outputs: Vec<PathBuf>,
        inputs: Vec<PathBuf>,
        f: &mut dyn FnMut(bool) -> Result<()>,
    ) -> Result<()> {
        let (opts, fresh) = (self.opts, self.fresh);
        let t = std::time::Instant::now();
        let same_settings = self.settings_match(name, &outputs);
        if !fresh && up_to_date(&outputs, &inputs) && same_settings {
            say(
                opts.quiet,
                &format!("== {name}: up to date ({}), skipped", outputs[0].display()),
            );
            self.steps.push(StepOutcome {
                step: name.into(),
                outcome: "skipped (up to date)".into(),
                seconds: 0.0,
            });
            return Ok(());
        }
        say(opts.quiet, &format!("== {name}"));
        // Outputs made with other settings: their checkpoint cannot be resumed either.
        f(!fresh && (same_settings || !outputs[0].exists()))?;
        self.steps.push(StepOutcome {
            step: name.into(),
            outcome: "ran".into(),
            seconds: t.elapsed().as_secs_f64(),
        });
        let record = RunRecord {
            format: "lightfuse-run/1".into(),
            preset: opts.preset.name().into(),
            steps: self.steps.clone(),
        };
        crate::stages::common::write_checkpoint(&self.record_path, &record)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_step_is_up_to_date_only_when_its_outputs_are_newer_than_its_inputs() {
        let dir = std::env::temp_dir().join(format!("lf-pipeline-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (input, output) = (dir.join("in"), dir.join("out"));
        std::fs::write(&input, b"1").unwrap();
        assert!(
            !up_to_date(std::slice::from_ref(&output), std::slice::from_ref(&input)),
            "missing output"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
        std::fs::write(&output, b"2").unwrap();
        assert!(up_to_date(
            std::slice::from_ref(&output),
            std::slice::from_ref(&input)
        ));
        // A missing input (e.g. an optional earlier output) does not make a step stale.
        assert!(up_to_date(
            std::slice::from_ref(&output),
            &[input.clone(), dir.join("none")]
        ));
        std::thread::sleep(std::time::Duration::from_millis(20));
        std::fs::write(&input, b"3").unwrap();
        assert!(
            !up_to_date(std::slice::from_ref(&output), std::slice::from_ref(&input)),
            "input changed"
        );
        assert!(
            !up_to_date(&[output, dir.join("none")], &[input]),
            "one output missing"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn outputs_made_with_other_settings_are_out_of_date() {
        use crate::stages::invert::train::Loss;
        let dir = std::env::temp_dir().join(format!("lf-pipeline-settings-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("report.json");
        let write = |v: serde_json::Value| std::fs::write(&f, v.to_string()).unwrap();
        // Evaluation: the denoising setting, and every row and table rendered.
        write(serde_json::json!({"denoise": "Open Image Denoise"}));
        assert!(eval_settings_match(&f, true) && !eval_settings_match(&f, false));
        let all = serde_json::to_value(crate::eval::tables::Selection::ALL).unwrap();
        write(serde_json::json!({"denoise": "none", "selection": all}));
        assert!(eval_settings_match(&f, false));
        let mut part = crate::eval::tables::Selection::ALL;
        part.baked = false;
        write(serde_json::json!({"denoise": "none", "selection": part}));
        assert!(
            !eval_settings_match(&f, false),
            "an ablation's partial evaluation"
        );
        // Stage 3: the options given; a report written before a field was trained with its
        // default (the paper's L1, one bounce, no light fit, no material search), and with
        // the rates decaying to a tenth, the fast preset's until 0.3.
        let fast = Settings {
            lr_decay: 0.1,
            ..Settings::fast()
        };
        let mut old = serde_json::to_value(&fast).unwrap();
        for later in [
            "loss",
            "bounces",
            "light_fit",
            "light_fit_texture",
            "light_fit_tie",
            "material_search",
        ] {
            old.as_object_mut().unwrap().remove(later).unwrap();
        }
        write(serde_json::json!({ "settings": old }));
        let none = Overrides::default();
        assert!(invert_settings_match(&f, &none));
        let l1 = Overrides {
            loss: Some(Loss::L1),
            bounces: Some(1),
            ..Default::default()
        };
        assert!(
            invert_settings_match(&f, &l1),
            "the defaults of the later fields"
        );
        let papers = Overrides {
            papers_method: true,
            ..Default::default()
        };
        assert!(
            invert_settings_match(&f, &papers),
            "an old report is the paper's method"
        );
        let others = [
            Overrides {
                loss: Some(Loss::WeightedL2),
                ..Default::default()
            },
            Overrides {
                bounces: Some(4),
                ..Default::default()
            },
            Overrides {
                light_fit: Some(true),
                ..Default::default()
            },
            Overrides {
                seed: Some(1),
                ..Default::default()
            },
            Overrides {
                lr_decay: Some(0.3),
                ..Default::default()
            },
        ];
        for other in &others {
            assert!(!invert_settings_match(&f, other), "{other:?}");
        }
        // An output made with other options (by `invert`, or an earlier `run`) counts as it
        // is when this run gives none, and is out of date when it gives other values.
        let made = Overrides {
            bounces: Some(4),
            light_fit: Some(true),
            iterations: Some(4),
            ..Default::default()
        };
        write(serde_json::json!({ "settings": made.apply(Settings::fast()).unwrap() }));
        assert!(invert_settings_match(&f, &none));
        assert!(invert_settings_match(&f, &made));
        assert!(invert_settings_match(
            &f,
            &Overrides {
                bounces: Some(4),
                ..Default::default()
            }
        ));
        assert!(!invert_settings_match(
            &f,
            &Overrides {
                bounces: Some(2),
                ..Default::default()
            }
        ));
        assert!(!invert_settings_match(
            &f,
            &Overrides {
                iterations: Some(2000),
                ..Default::default()
            }
        ));
        assert!(
            !invert_settings_match(
                &f,
                &Overrides {
                    bounces: Some(9),
                    ..Default::default()
                }
            ),
            "unusable"
        );
        write(serde_json::json!({"seconds": 3}));
        assert!(
            !invert_settings_match(&f, &none),
            "a report without settings"
        );
        assert!(!invert_settings_match(&dir.join("none.json"), &none));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
