//! A running job's progress, fed by the pipeline through its [`Progress`] trait and read by
//! `GET /v1/jobs/{id}`.
//!
//! The pipeline names its phases (`plan`, `partition`, `globals`, `tiles`, `stitch` when tiled;
//! `read`, `denoise`, `write` in memory; meshes report none). Each phase covers a fixed share of
//! the overall percentage, so the percentage only grows within a run; tile counts are kept
//! separately because they are what a user of a long tiled run watches.

use std::sync::Mutex;

use crate::pipeline::Progress;

/// A snapshot for the API.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ProgressView {
    /// Current phase (`queued` before the run starts, `done` after it).
    pub phase: String,
    /// Units (points or tiles) of the current phase done.
    pub done: u64,
    /// Units of the current phase (0 when unknown).
    pub total: u64,
    /// Tiles finished (tiled runs).
    pub tiles_done: u64,
    /// Tiles planned (tiled runs; 0 before planning or in memory).
    pub tiles_total: u64,
    /// Overall estimate, 0–100.
    pub percent: f64,
}

#[derive(Debug, Default)]
struct State {
    phase: String,
    done: u64,
    total: u64,
    tiles_done: u64,
    tiles_total: u64,
    /// Highest percentage reported (a resumed run replays phases; never go backwards).
    high: f64,
}

/// Collects the pipeline's progress calls.
#[derive(Debug, Default)]
pub struct JobProgress {
    // std Mutex: a few word-sized updates per batch or tile, never held across I/O.
    state: Mutex<State>,
}

/// Share of the overall percentage: (start, width) of each named phase.
fn span_of(phase: &str) -> (f64, f64) {
    match phase {
        "plan" => (0.0, 10.0),
        "partition" => (10.0, 20.0),
        "globals" => (30.0, 5.0),
        "tiles" => (35.0, 55.0),
        "stitch" => (90.0, 10.0),
        "read" => (0.0, 20.0),
        "denoise" => (20.0, 60.0),
        "write" => (80.0, 20.0),
        _ => (0.0, 0.0),
    }
}

impl JobProgress {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The current state.
    pub fn snapshot(&self) -> ProgressView {
        let s = self.lock();
        let (start, width) = span_of(&s.phase);
        let frac = if s.total > 0 {
            (s.done as f64 / s.total as f64).min(1.0)
        } else {
            0.0
        };
        let percent = (start + width * frac).max(s.high).min(99.9);
        ProgressView {
            phase: if s.phase.is_empty() {
                "starting".into()
            } else {
                s.phase.clone()
            },
            done: s.done,
            total: s.total,
            tiles_done: s.tiles_done,
            tiles_total: s.tiles_total,
            percent: (percent * 10.0).round() / 10.0,
        }
    }
}

impl JobProgress {
    /// Sets the state from what is committed (a job on SLURM, whose tasks report elsewhere):
    /// `phase` with `done` of `total` units, and the tiles committed of all.
    pub fn committed(&self, phase: &str, done: u64, total: u64, tiles: (u64, u64)) {
        let mut s = self.lock();
        if s.phase != phase {
            let (start, width) = span_of(&s.phase);
            if s.total > 0 {
                let reached = start + width * (s.done as f64 / s.total as f64).min(1.0);
                s.high = s.high.max(reached);
            }
            // A later phase starts where it starts, at least.
            s.high = s.high.max(span_of(phase).0);
            s.phase = phase.to_string();
        }
        s.done = done;
        s.total = total;
        (s.tiles_done, s.tiles_total) = tiles;
    }
}

impl Progress for JobProgress {
    fn phase(&self, name: &str, total: u64) {
        let mut s = self.lock();
        let (start, width) = span_of(&s.phase);
        if s.total > 0 {
            let reached = start + width * (s.done as f64 / s.total as f64).min(1.0);
            s.high = s.high.max(reached);
        }
        s.phase = name.to_string();
        s.total = total;
        s.done = 0;
        if name == "tiles" {
            s.tiles_total = total;
            s.tiles_done = 0;
        }
    }

    fn advance(&self, done: u64) {
        let mut s = self.lock();
        s.done = done;
        if s.phase == "tiles" {
            s.tiles_done = done;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_and_percent() {
        let p = JobProgress::default();
        assert_eq!(p.snapshot().phase, "starting");
        p.phase("plan", 100);
        p.advance(50);
        assert_eq!(p.snapshot().percent, 5.0);
        p.phase("partition", 100);
        p.phase("tiles", 10);
        p.advance(4);
        let v = p.snapshot();
        assert_eq!((v.tiles_done, v.tiles_total), (4, 10));
        assert_eq!(v.percent, 35.0 + 22.0);
        p.phase("stitch", 100);
        let v = p.snapshot();
        assert_eq!(v.tiles_done, 4);
        assert!(v.percent >= 57.0);
    }

    #[test]
    fn committed_checkpoints_set_the_phase_and_tiles() {
        let p = JobProgress::default();
        p.committed("partition", 0, 1, (0, 8));
        assert_eq!(p.snapshot().percent, 10.0);
        p.committed("tiles", 2, 8, (2, 8));
        let v = p.snapshot();
        assert_eq!(
            (v.phase.as_str(), v.tiles_done, v.tiles_total),
            ("tiles", 2, 8)
        );
        // 35 + 55 × 2/8, to one decimal.
        assert_eq!(v.percent, 48.8);
        p.committed("stitch", 0, 1, (8, 8));
        assert_eq!(p.snapshot().percent, 90.0);
    }
}
