//! The loop skeleton the stages share (docs/design.md §4): the `log.jsonl` appender,
//! checkpoints written atomically and read back for `--resume`, and the training loop itself
//! ([`StageLoop`], [`resume_or_start`]); progress is [`crate::progress`].

use crate::error::{Error, Result};
use crate::io::dataset::{split, Dataset, Observation};
use crate::io::work::{read_stage_scene, StageFiles};
use crate::io::AtomicFiles;
use crate::progress::{say, Progress};
use crate::scene::Scene;
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A stage's `log.jsonl`: one JSON object per line, each written through at once (a crashed or
/// interrupted run keeps every line it logged).
pub struct StageLog {
    path: PathBuf,
    file: std::fs::File,
}

impl StageLog {
    /// Opens `path` for appending, creating it if needed: a resumed run continues its log.
    pub fn append(path: &Path) -> Result<StageLog> {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(|e| Error::io(path, e))?;
        Ok(StageLog {
            path: path.to_path_buf(),
            file,
        })
    }

    /// Starts `path` afresh (`resume` false) or appends to it (`resume` true).
    pub fn create(path: &Path, resume: bool) -> Result<StageLog> {
        if resume {
            return Self::append(path);
        }
        let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
        Ok(StageLog {
            path: path.to_path_buf(),
            file,
        })
    }

    /// Appends `value` as one line.
    pub fn write(&mut self, value: &serde_json::Value) -> Result<()> {
        let line = format!("{value}\n");
        self.file
            .write_all(line.as_bytes())
            .and_then(|_| self.file.flush())
            .map_err(|e| Error::io(&self.path, e))
    }
}

/// Writes `value` as JSON to `path` atomically: a temporary sibling, then a rename, so an
/// interrupted write leaves the previous checkpoint in place.
///
/// The JSON is streamed to the file rather than built in memory first: stage 1's checkpoint on a
/// room is ~0.6 GB of text (kitchen preset, 0.7 M surfels), and as one `Vec` it grew by doubling
/// to ~1 GB beside the model, which made the end of training the stage's peak (1.95 GB against
/// 1.35 GB during training, `reconstruct data/kitchen --iterations 400`).
pub fn write_checkpoint<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let mut files = AtomicFiles::new();
    files.write_with(path, |w| {
        serde_json::to_writer(w, value).map_err(|e| {
            if e.is_io() {
                std::io::Error::from(e)
            } else {
                std::io::Error::other(format!("checkpoint: {e}"))
            }
        })
    })?;
    files.commit()
}

/// Reads a checkpoint written by [`write_checkpoint`]; errors name the file.
pub fn read_checkpoint<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_slice(&bytes).map_err(|e| {
        Error::invalid(
            path,
            "checkpoint",
            format!("expected a LightFuse checkpoint: {e}"),
        )
    })
}

/// The mean of a stage's per-iteration losses over the iterations since the last log line:
/// every numeric field of the losses' serde form, summed in f64.
#[derive(Default)]
pub struct LossWindow {
    sums: serde_json::Map<String, serde_json::Value>,
    n: u32,
}

impl LossWindow {
    /// Adds one iteration's losses (a struct of numbers; other fields are ignored).
    pub fn add<L: Serialize>(&mut self, losses: &L) {
        let Ok(serde_json::Value::Object(m)) = serde_json::to_value(losses) else {
            return;
        };
        for (k, v) in m {
            if let Some(x) = v.as_f64() {
                let acc = self.sums.entry(k).or_insert(0.0.into());
                *acc = (acc.as_f64().unwrap_or(0.0) + x).into();
            }
        }
        self.n += 1;
    }

    /// The means so far, and the window emptied.
    pub fn take(&mut self) -> serde_json::Map<String, serde_json::Value> {
        let k = self.n.max(1) as f64;
        let out = std::mem::take(&mut self.sums)
            .into_iter()
            .map(|(name, v)| (name, (v.as_f64().unwrap_or(0.0) / k).into()))
            .collect();
        self.n = 0;
        out
    }
}

/// What a stage's loop checkpoints: the trainer at some iteration, and the wall time the
/// training iterations took to reach it over every run a `--resume` continued. A run of the
/// paper presets spans sittings, and the time a single process measures is then only its own
/// share. The iterations a killed run had done after its last checkpoint are done, and counted,
/// again.
pub trait Resumable: Serialize {
    /// Training iterations done.
    fn iteration(&self) -> u32;
    /// Training wall time to reach them, seconds (0 in a fresh run's first state).
    fn training_seconds(&mut self) -> &mut f64;
}

/// The loop every stage runs (docs/design.md §4): steps until `total`, a `log.jsonl` line of the mean
/// losses every `log_every` iterations (and at the end), the progress bar's status at the same
/// time, and the checkpoint every `checkpoint_every` iterations (and at the end). It keeps the
/// state's training time ([`Resumable::training_seconds`]): what the state came with plus the
/// wall time since this loop started, as of the last step (the log lines and checkpoints
/// written between steps included), and writes it in every log line as `training_seconds`.
pub struct StageLoop<'a> {
    pub total: u32,
    pub log_every: u32,
    pub checkpoint_every: u32,
    pub checkpoint: &'a Path,
    pub log: &'a mut StageLog,
    pub bar: &'a Progress,
}

impl StageLoop<'_> {
    /// Runs `state` (the checkpointed value) from its iteration to `total`. `step` runs one
    /// iteration and returns its losses (it may print above the bar); `line` adds the stage's
    /// own fields to each log line (it holds the mean losses under their names, `iteration`
    /// and `training_seconds`) and returns the bar's status.
    pub fn run<C: Resumable, L: Serialize>(
        &mut self,
        state: &mut C,
        mut step: impl FnMut(&mut C, &Progress) -> Result<L>,
        mut line: impl FnMut(&C, &mut serde_json::Map<String, serde_json::Value>) -> String,
    ) -> Result<()> {
        let mut window = LossWindow::default();
        let (trained_before, started) = (*state.training_seconds(), Instant::now());
        while state.iteration() < self.total {
            let l = step(state, self.bar)?;
            *state.training_seconds() = trained_before + started.elapsed().as_secs_f64();
            window.add(&l);
            self.bar.inc(1);
            let it = state.iteration();
            let last = it >= self.total;
            if it % self.log_every.max(1) == 0 || last {
                let mut m = window.take();
                m.insert("iteration".into(), it.into());
                m.insert(
                    "training_seconds".into(),
                    (*state.training_seconds()).into(),
                );
                let status = line(state, &mut m);
                self.log.write(&serde_json::Value::Object(m))?;
                self.bar.status(&status);
            }
            if it % self.checkpoint_every.max(1) == 0 || last {
                write_checkpoint(self.checkpoint, state)?;
            }
        }
        Ok(())
    }
}

/// A resumed run may go on longer than its checkpoint's run meant to, but every other setting
/// must be the one it started with: else an error naming `path` and the field `settings`,
/// ending with what to do (`hint`). `iterations` picks the run's length out of the settings.
pub fn check_resumed_settings<S: Clone + PartialEq>(
    path: &Path,
    checkpoint: &S,
    run: &S,
    iterations: impl Fn(&mut S) -> &mut u32,
    hint: &str,
) -> Result<()> {
    let without_length = |s: &S| {
        let mut s = s.clone();
        *iterations(&mut s) = 0;
        s
    };
    if without_length(checkpoint) != without_length(run) {
        return Err(Error::invalid(
            path,
            "settings",
            format!("the checkpoint was made with other settings: {hint}"),
        ));
    }
    Ok(())
}

/// Opens a stage's checkpoint for `--resume` when asked and present (`read` validates it
/// against this run), otherwise starts afresh with `fresh`; says which. Returns the state and
/// whether it was resumed.
pub fn resume_or_start<C: Resumable>(
    checkpoint: &Path,
    resume: bool,
    quiet: bool,
    read: impl FnOnce(&Path) -> Result<C>,
    fresh: impl FnOnce() -> Result<C>,
) -> Result<(C, bool)> {
    if resume && checkpoint.is_file() {
        let mut c = read(checkpoint)?;
        say(
            quiet,
            &format!(
                "resuming from {} at iteration {} ({:.0} s of training so far)",
                checkpoint.display(),
                c.iteration(),
                c.training_seconds()
            ),
        );
        Ok((c, true))
    } else {
        Ok((fresh()?, false))
    }
}

/// What stages 2 and 3 start from: the dataset, the earlier stage's scene checked against it
/// ([`read_stage_scene`]; `missing` says how to make it), the stage's own folder (made), and
/// every training state's observations split into training and held-out views.
pub struct StageInputs {
    pub dataset: Dataset,
    pub scene: Scene,
    pub files: StageFiles,
    /// The dataset's training states, in order; `train[j]` and `held[j]` are state
    /// `train_states[j]`'s.
    pub train_states: Vec<usize>,
    pub train: Vec<Vec<Observation>>,
    pub held: Vec<Vec<Observation>>,
}

impl StageInputs {
    pub fn read(
        dataset: &Path,
        scene: &Path,
        missing: &str,
        files: StageFiles,
        quiet: bool,
    ) -> Result<StageInputs> {
        let dataset = Dataset::read(dataset)?;
        let scene = read_stage_scene(scene, &dataset, missing)?;
        std::fs::create_dir_all(&files.dir).map_err(|e| Error::io(&files.dir, e))?;
        say(quiet, "reading the training captures");
        let train_states = dataset.train_states();
        let (train, held) = split(dataset.training_observations()?);
        Ok(StageInputs {
            dataset,
            scene,
            files,
            train_states,
            train,
            held,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checkpoints_round_trip_and_bad_ones_name_the_file() {
        let dir = tempfile::tempdir().expect("a temporary directory");
        let path = dir.path().join("checkpoint.json");
        write_checkpoint(&path, &vec![1u32, 2, 3]).expect("written");
        let back: Vec<u32> = read_checkpoint(&path).expect("read back");
        assert_eq!(back, [1, 2, 3]);
        std::fs::write(&path, b"{not json").expect("written");
        let err = read_checkpoint::<Vec<u32>>(&path).expect_err("not a checkpoint");
        assert!(err.to_string().contains("checkpoint.json"), "{err}");
    }

    #[test]
    fn a_checkpoint_that_fails_midway_names_the_file_and_leaves_the_last_one() {
        // The checkpoint is streamed, so a value that fails to serialise after part of it is
        // written (here a map whose keys JSON cannot hold, after a field that is written) must
        // leave neither a torn file nor a temporary one behind.
        #[derive(Serialize)]
        struct Bad {
            iteration: u32,
            table: std::collections::BTreeMap<(u8, u8), u8>,
        }
        let dir = tempfile::tempdir().expect("a temporary directory");
        let path = dir.path().join("checkpoint.json");
        write_checkpoint(&path, &vec![1u32, 2, 3]).expect("written");
        let bad = Bad {
            iteration: 7,
            table: [((1, 2), 3)].into_iter().collect(),
        };
        let err = write_checkpoint(&path, &bad).expect_err("tuple keys are not JSON");
        let msg = err.to_string();
        assert!(
            msg.contains("checkpoint.json") && msg.contains("key"),
            "{msg}"
        );
        let back: Vec<u32> = read_checkpoint(&path).expect("the last checkpoint is intact");
        assert_eq!(back, [1, 2, 3]);
        let files: Vec<_> = std::fs::read_dir(dir.path())
            .expect("listed")
            .map(|e| e.expect("an entry").file_name())
            .collect();
        assert_eq!(files, [std::ffi::OsString::from("checkpoint.json")]);
    }

    #[test]
    fn the_loop_logs_window_means_and_checkpoints_on_its_grid() {
        #[derive(Serialize)]
        struct L {
            loss: f32,
            label: &'static str,
        }
        let dir = tempfile::tempdir().expect("a temporary directory");
        let (ckpt, log_path) = (dir.path().join("c.json"), dir.path().join("log.jsonl"));
        let mut log = StageLog::create(&log_path, false).expect("created");
        let bar = Progress::new(true, 5, "test");
        // As if resumed from a run that had trained for a day.
        let mut state = Counter {
            n: 0,
            training_seconds: 86400.0,
        };
        StageLoop {
            total: 5,
            log_every: 2,
            checkpoint_every: 4,
            checkpoint: &ckpt,
            log: &mut log,
            bar: &bar,
        }
        .run(
            &mut state,
            |s, _| {
                s.n += 1;
                // Each step takes a measurable time, so the clock must move.
                std::thread::sleep(std::time::Duration::from_millis(2));
                Ok(L {
                    loss: s.n as f32,
                    label: "x",
                })
            },
            |s, m| {
                m.insert("twice".into(), (2 * s.n).into());
                String::new()
            },
        )
        .expect("ran");
        let text = std::fs::read_to_string(&log_path).expect("read");
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).expect("json"))
            .collect();
        // Means of (1, 2), (3, 4) and the last (5): the end always logs and checkpoints.
        let got: Vec<(u64, f64, u64)> = lines
            .iter()
            .map(|v| {
                (
                    v["iteration"].as_u64().unwrap(),
                    v["loss"].as_f64().unwrap(),
                    v["twice"].as_u64().unwrap(),
                )
            })
            .collect();
        assert_eq!(got, [(2, 1.5, 4), (4, 3.5, 8), (5, 5.0, 10)]);
        assert!(lines.iter().all(|v| v.get("label").is_none()));
        // The training time goes on from what the state came with (five steps of at least
        // 2 ms each), grows line by line, and the last checkpoint keeps the last line's.
        let trained: Vec<f64> = lines
            .iter()
            .map(|v| v["training_seconds"].as_f64().unwrap())
            .collect();
        assert!(
            trained[0] >= 86400.0039 && trained[2] >= 86400.0099,
            "{trained:?}"
        );
        assert!(trained.windows(2).all(|w| w[0] < w[1]), "{trained:?}");
        let back: Counter = read_checkpoint(&ckpt).expect("checkpointed");
        assert_eq!((back.n, back.training_seconds), (5, trained[2]));
    }

    #[derive(Serialize, serde::Deserialize)]
    struct Counter {
        n: u32,
        training_seconds: f64,
    }

    impl Resumable for Counter {
        fn iteration(&self) -> u32 {
            self.n
        }
        fn training_seconds(&mut self) -> &mut f64 {
            &mut self.training_seconds
        }
    }

    /// The time left is the rate so far times the work left: with equal steps, the steps
    /// left; with costs, their sum (here the paper's stage 3 at 8, 16 and 32 samples per pixel,
    /// 3,000 iterations done in 3,840 s since a resume at 1,000).

    #[test]
    fn the_log_appends_one_object_per_line() {
        let dir = tempfile::tempdir().expect("a temporary directory");
        let path = dir.path().join("log.jsonl");
        let mut log = StageLog::create(&path, false).expect("created");
        log.write(&serde_json::json!({"iteration": 1}))
            .expect("written");
        drop(log);
        let mut log = StageLog::create(&path, true).expect("reopened");
        log.write(&serde_json::json!({"iteration": 2}))
            .expect("written");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text, "{\"iteration\":1}\n{\"iteration\":2}\n");
    }
}
