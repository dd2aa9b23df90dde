//! Progress reporting: a small trait the pipeline calls, with a silent implementation, a plain
//! log-line implementation for non-terminals and an indicatif bar for terminals.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};

/// Receives the pipeline's progress. Implementations must be cheap: `advance` is called once per
/// batch or tile.
pub trait Progress: Send + Sync {
    /// A new phase starts with `total` units of work (points or tiles; 0 when unknown).
    fn phase(&self, name: &str, total: u64);
    /// `done` units of the current phase are finished.
    fn advance(&self, done: u64);
    /// The run is over.
    fn finish(&self) {}
}

/// Reports nothing (`--quiet`, tests, library use).
#[derive(Debug, Default, Clone, Copy)]
pub struct NoProgress;

impl Progress for NoProgress {
    fn phase(&self, _name: &str, _total: u64) {}
    fn advance(&self, _done: u64) {}
}

#[derive(Debug)]
struct LogState {
    name: String,
    total: u64,
    started: Instant,
    last: Instant,
}

/// Writes a plain progress line to stderr at most every `every` while a phase runs (for logs and
/// pipes, where a bar would be noise). Runs shorter than `every` print nothing.
#[derive(Debug)]
pub struct LogProgress {
    every: Duration,
    state: Mutex<Option<LogState>>,
}

impl LogProgress {
    /// Logs at most once per `every`.
    pub fn new(every: Duration) -> LogProgress {
        LogProgress {
            every,
            state: Mutex::new(None),
        }
    }
}

impl Progress for LogProgress {
    fn phase(&self, name: &str, total: u64) {
        let now = Instant::now();
        // std Mutex: held only to swap small state, never across I/O of the pipeline.
        *self.state.lock().unwrap_or_else(|e| e.into_inner()) = Some(LogState {
            name: name.to_string(),
            total,
            started: now,
            last: now,
        });
    }

    fn advance(&self, done: u64) {
        let mut guard = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let Some(s) = guard.as_mut() else { return };
        let now = Instant::now();
        if now.duration_since(s.last) < self.every {
            return;
        }
        s.last = now;
        let elapsed = now.duration_since(s.started).as_secs_f64();
        if s.total > 0 {
            let frac = done as f64 / s.total as f64;
            let eta = if frac > 0.0 {
                elapsed * (1.0 - frac) / frac
            } else {
                f64::NAN
            };
            eprintln!(
                "qemd: {}: {done}/{} ({:.1} %), {elapsed:.0} s elapsed, about {eta:.0} s left",
                s.name,
                s.total,
                frac * 100.0
            );
        } else {
            eprintln!("qemd: {}: {done} done, {elapsed:.0} s elapsed", s.name);
        }
    }
}

/// One indicatif bar per phase, with an ETA (for terminals).
#[derive(Debug)]
pub struct BarProgress {
    bar: Mutex<Option<ProgressBar>>,
}

impl Default for BarProgress {
    fn default() -> Self {
        BarProgress {
            bar: Mutex::new(None),
        }
    }
}

impl Progress for BarProgress {
    fn phase(&self, name: &str, total: u64) {
        let mut guard = self.bar.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(old) = guard.take() {
            old.finish();
        }
        let bar = if total > 0 {
            ProgressBar::new(total)
        } else {
            ProgressBar::new_spinner()
        };
        let style = ProgressStyle::with_template(
            "{prefix:>10} [{bar:40}] {percent:>3}% {human_pos}/{human_len} ETA {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ");
        bar.set_style(style);
        bar.set_prefix(name.to_string());
        *guard = Some(bar);
    }

    fn advance(&self, done: u64) {
        if let Some(b) = self.bar.lock().unwrap_or_else(|e| e.into_inner()).as_ref() {
            b.set_position(done);
        }
    }

    fn finish(&self) {
        if let Some(b) = self.bar.lock().unwrap_or_else(|e| e.into_inner()).take() {
            b.finish();
        }
    }
}
