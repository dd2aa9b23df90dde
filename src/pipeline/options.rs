//! How a job runs (not what it computes): the memory budget, temporary and work directories,
//! tile size, progress and cancellation.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use super::PipelineError;
use super::progress::{NoProgress, Progress};

/// How a job runs (not what it computes).
#[derive(Clone)]
pub struct RunOptions {
    /// Clouds whose working set fits run in memory; larger ones run in tiles sized to it.
    pub memory_budget: u64,
    /// Where spill files go (the system temp directory when `None`).
    pub temp_dir: Option<PathBuf>,
    /// Forces tiling with about this many points per tile.
    pub tile_points: Option<u64>,
    /// Input records per partition part of a tiled run (default
    /// [`crate::pipeline::tiled::plan::PART_POINTS`]); only the speed depends on it.
    pub part_points: Option<u64>,
    /// Receives phase and progress updates.
    pub progress: Arc<dyn Progress>,
    /// Set to stop the run at the next batch or tile.
    pub cancel: Arc<AtomicBool>,
    /// A persistent working directory for the tiled path (a job's): spill files, finished tiles
    /// and the plan stay there, so a run interrupted at any point resumes with only the
    /// unfinished tiles. `None`: a fresh temporary directory, removed at the end.
    pub work_dir: Option<PathBuf>,
}

/// The default memory budget: 1 GiB.
pub const DEFAULT_MEMORY_BUDGET: u64 = 1 << 30;

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            memory_budget: DEFAULT_MEMORY_BUDGET,
            temp_dir: None,
            tile_points: None,
            part_points: None,
            progress: Arc::new(NoProgress),
            cancel: Arc::new(AtomicBool::new(false)),
            work_dir: None,
        }
    }
}

impl std::fmt::Debug for RunOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RunOptions")
            .field("memory_budget", &self.memory_budget)
            .field("temp_dir", &self.temp_dir)
            .field("tile_points", &self.tile_points)
            .field("part_points", &self.part_points)
            .field("work_dir", &self.work_dir)
            .finish()
    }
}

impl RunOptions {
    /// [`PipelineError::Cancelled`] once the cancel flag is set.
    pub(crate) fn check_cancel(&self) -> Result<(), PipelineError> {
        if self.cancel.load(Ordering::Relaxed) {
            Err(PipelineError::Cancelled)
        } else {
            Ok(())
        }
    }
}
