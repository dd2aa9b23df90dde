//! `qemd status`: each phase's progress, read from the committed files of the work directory
//! alone (no task needs to be alive, and no engine is asked).

use std::path::PathBuf;

use serde::Serialize;

use super::frozen::FrozenJob;
use super::layout::{globals_partial_path, load_json};
use super::url::WorkUrl;
use super::worker::{committed_ranges, committed_stitch};
use super::{Phase, ScaleoutError};
use crate::tiling::workdir::{PART_DONE, WorkDir};

/// One phase's progress.
#[derive(Debug, Clone, Serialize)]
pub struct PhaseStatus {
    /// The phase.
    pub phase: Phase,
    /// Its task count (what an engine's array should have).
    pub tasks: u64,
    /// Units of work (parts for the partition, tiles for globals and tiles; for the stitch 1,
    /// or its ranges and the output assembled from them; 0 when the phase is not needed).
    pub units: u64,
    /// Units committed.
    pub committed: u64,
}

impl PhaseStatus {
    /// True when every unit is committed.
    pub fn complete(&self) -> bool {
        self.committed >= self.units
    }
}

/// A job's progress.
#[derive(Debug, Clone, Serialize)]
pub struct Status {
    /// The work directory.
    pub work: String,
    /// The input.
    pub input: PathBuf,
    /// Points in the input.
    pub points: u64,
    /// Tiles of the plan.
    pub tiles: u64,
    /// Each phase, in order.
    pub phases: Vec<PhaseStatus>,
    /// The first phase not complete (`None`: the output is ready for `qemd finish`).
    pub next: Option<Phase>,
}

/// The progress of the job in `work`.
///
/// # Errors
/// A work directory without a readable plan.
pub fn status(work: &WorkUrl) -> Result<Status, ScaleoutError> {
    let dir = work.local()?;
    let frozen = FrozenJob::load(dir)?;
    let w = WorkDir::persistent(dir).map_err(|e| crate::io::IoError::io(dir, e))?;
    let tiles = frozen.plan.tiles.len();
    let tasks = frozen.tasks();
    let parts = frozen.plan.parts();
    let partition = if w.committed_partition(&frozen.plan).is_some() {
        parts
    } else {
        // By the markers' presence: an object store's status stands in empty files for them.
        (0..parts)
            .filter(|&p| w.part(p).join(PART_DONE).exists())
            .count() as u64
    };
    let globals = if tasks[1] == 0 {
        0
    } else if w.committed_globals().is_some() {
        tiles as u64
    } else {
        (0..tiles)
            .filter(|&t| load_json::<serde_json::Value>(&globals_partial_path(dir, t)).is_some())
            .count() as u64
    };
    let done_tiles = (0..tiles)
        .filter(|&t| w.committed_tile(t).is_some())
        .count() as u64;
    let stitched = committed_stitch(dir, &frozen).is_some();
    let (stitch_units, stitch) = match tasks[3] {
        1 => (1, u64::from(stitched)),
        ranges if stitched => (ranges + 1, ranges + 1),
        ranges => (ranges + 1, committed_ranges(dir, ranges)),
    };
    let units = [parts, tasks[1], tiles as u64, stitch_units];
    let committed = [partition, globals, done_tiles, stitch];
    let phases: Vec<PhaseStatus> = Phase::ALL
        .iter()
        .enumerate()
        .map(|(i, &phase)| PhaseStatus {
            phase,
            tasks: tasks[i],
            units: units[i],
            committed: committed[i],
        })
        .collect();
    let next = phases.iter().find(|p| !p.complete()).map(|p| p.phase);
    Ok(Status {
        work: work.to_string(),
        input: frozen.input.clone(),
        points: frozen.plan.points,
        tiles: tiles as u64,
        phases,
        next,
    })
}
