//! The loop skeleton the stages share (DESIGN §4): a progress bar on a terminal or plain lines
//! in a log, the `log.jsonl` appender, and checkpoints written atomically and read back for
//! `--resume`.

use crate::error::{Error, Result};
use crate::io::AtomicFiles;
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A line on stderr unless `--quiet`.
pub fn say(quiet: bool, s: &str) {
    if !quiet {
        eprintln!("{s}");
    }
}

/// A stage's progress: an indicatif bar when stderr is a terminal; otherwise (a file or a pipe)
/// plain lines, so that a log of a long run still says what happened; nothing with `--quiet`.
pub struct Progress {
    bar: indicatif::ProgressBar,
    quiet: bool,
    message: String,
    total: u64,
    /// A plain line when the position is a multiple of this (bar not drawn).
    plain_every: u64,
    start: u64,
    started: Instant,
}

impl Progress {
    /// A bar of `total` steps labelled `message`, at position 0; plain lines about every tenth
    /// of the run unless [`Progress::plain_every`] says otherwise.
    pub fn new(quiet: bool, total: u64, message: &str) -> Progress {
        let bar = if quiet {
            indicatif::ProgressBar::hidden()
        } else {
            let bar = indicatif::ProgressBar::new(total);
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{msg:12} [{bar:30}] {pos}/{len} {elapsed} eta {eta} {prefix}",
                )
                .expect("valid template")
                .progress_chars("=> "),
            );
            bar.set_message(message.to_string());
            bar
        };
        Progress {
            bar,
            quiet,
            message: message.to_string(),
            total,
            plain_every: (total / 10).max(1),
            start: 0,
            started: Instant::now(),
        }
    }

    /// Plain lines (bar not drawn) at positions that are multiples of `every`.
    pub fn plain_every(mut self, every: u64) -> Progress {
        self.plain_every = every.max(1);
        self
    }

    /// Starts (or resumes) at `position`: the time left is estimated from the steps run since.
    pub fn start_at(&mut self, position: u64) {
        self.bar.set_position(position);
        self.start = position;
        self.started = Instant::now();
    }

    /// True when the bar is drawn (stderr is a terminal and not `--quiet`).
    pub fn is_drawn(&self) -> bool {
        !self.bar.is_hidden()
    }

    pub fn inc(&self, n: u64) {
        self.bar.inc(n);
    }

    pub fn set_message(&self, message: &str) {
        self.bar.set_message(message.to_string());
    }

    /// The status after the bar (losses, counts); without a bar, a plain line when the position
    /// falls on the plain-line grid.
    pub fn status(&self, status: &str) {
        let pos = self.bar.position();
        if !self.is_drawn() && pos % self.plain_every == 0 {
            let done = pos as f64 / self.total.max(1) as f64;
            let spent = self.started.elapsed().as_secs_f64();
            let ran = pos.saturating_sub(self.start).max(1) as f64;
            let left = spent / ran * self.total.saturating_sub(pos) as f64;
            say(
                self.quiet,
                &format!(
                    "{} {pos}/{} ({:.0} %) {status} · {spent:.0} s, ~{left:.0} s left",
                    self.message,
                    self.total,
                    100.0 * done
                ),
            );
        }
        self.bar.set_prefix(status.to_string());
    }

    /// A message above the bar, or a plain line when the bar is not drawn.
    pub fn println(&self, s: &str) {
        if self.bar.is_hidden() {
            say(self.quiet, s);
        } else {
            self.bar.println(s);
        }
    }

    /// Removes the bar.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

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
pub fn write_checkpoint<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let bytes = serde_json::to_vec(value).map_err(|e| Error::Usage(format!("checkpoint: {e}")))?;
    let mut files = AtomicFiles::new();
    files.write(path, &bytes)?;
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
