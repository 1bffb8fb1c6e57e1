//! Progress of long work: an indicatif bar when stderr is a terminal, plain lines with the time
//! left when it is a file or a pipe (so a log of a long run still says what happened), nothing
//! with `--quiet`. Every stage, `lightfuse evaluate` and the renderer's command report through
//! it.

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
    /// With [`Progress::step_costs`]: `work[i]`, the summed cost of the steps before position
    /// `i` (`total + 1` entries); without, every step costs one.
    work: Option<Vec<f64>>,
}

/// The time left after `spent` seconds took the run from work done `from` to `at`, of `all`:
/// the rate so far applied to the work left. 0 before any work was done (nothing to go by).
fn time_left(spent: f64, from: f64, at: f64, all: f64) -> f64 {
    let ran = at - from;
    if ran > 0.0 {
        spent / ran * (all - at).max(0.0)
    } else {
        0.0
    }
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
            work: None,
        }
    }

    /// Steps of unequal cost: `cost(i)` is step i's, in any unit (stage 3's samples per pixel,
    /// which its schedules raise 4x in the last fifth of a run). The time left is then the rate
    /// per unit so far times the units left, in the plain lines and, in place of indicatif's
    /// estimate (which counts steps alike), in the drawn bar's status. Without it, a run of the
    /// paper's stage 3 at iteration 3,000 of 15,000 said 5.5 hours were left, counting its
    /// later 16- and 32-spp iterations as 8-spp ones: weighed by their spp, the work left is
    /// 2.1 times that (204,000 spp-iterations, not 96,000).
    pub fn step_costs(mut self, cost: impl Fn(u64) -> f64) -> Progress {
        let mut work = Vec::with_capacity(self.total as usize + 1);
        let mut sum = 0.0;
        work.push(sum);
        for i in 0..self.total {
            sum += cost(i);
            work.push(sum);
        }
        self.work = Some(work);
        if !self.bar.is_hidden() {
            self.bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{msg:12} [{bar:30}] {pos}/{len} {elapsed} {prefix}",
                )
                .expect("valid template")
                .progress_chars("=> "),
            );
        }
        self
    }

    /// Work done by position `pos` (steps, or their summed costs).
    fn work(&self, pos: u64) -> f64 {
        let pos = pos.min(self.total);
        match &self.work {
            Some(w) => w[pos as usize],
            None => pos as f64,
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
        let spent = self.started.elapsed().as_secs_f64();
        let left = time_left(
            spent,
            self.work(self.start),
            self.work(pos),
            self.work(self.total),
        );
        if !self.is_drawn() && pos % self.plain_every == 0 {
            let done = pos as f64 / self.total.max(1) as f64;
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
        if self.work.is_some() {
            let left = std::time::Duration::try_from_secs_f64(left).unwrap_or_default();
            let eta = indicatif::HumanDuration(left);
            self.bar.set_prefix(format!("eta {eta} {status}"));
        } else {
            self.bar.set_prefix(status.to_string());
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_time_left_weighs_the_steps_left_by_their_cost() {
        let bar = Progress::new(true, 10, "test");
        assert_eq!(time_left(6.0, bar.work(0), bar.work(3), bar.work(10)), 14.0);
        assert_eq!(time_left(6.0, bar.work(3), bar.work(3), bar.work(10)), 0.0);
        let spp = |i: u64| match i {
            ..7_500 => 8.0,
            7_500..12_000 => 16.0,
            _ => 32.0,
        };
        let bar = Progress::new(true, 15_000, "test").step_costs(spp);
        assert_eq!(
            bar.work(15_000),
            7_500.0 * 8.0 + 4_500.0 * 16.0 + 3_000.0 * 32.0
        );
        let left = time_left(3_840.0, bar.work(1_000), bar.work(3_000), bar.work(15_000));
        // 2,000 steps of 8 in 3,840 s: 0.24 s per unit; left 4,500 x 8 + 4,500 x 16 + 3,000 x 32.
        assert!((left - 0.24 * 204_000.0).abs() < 1e-6, "{left}");
        // Past the end (a run resumed beyond a shortened total) nothing is left.
        assert_eq!(time_left(1.0, 0.0, 2.0, 1.0), 0.0);
    }
}
