//! What a run did ([`Report`], written as JSON by `--report`), and the process's peak memory.

use std::path::{Path, PathBuf};

use super::{Job, NormalsAction, OutlierMode, PipelineError};
use crate::denoise::{Params, PhaseTiming, Stats};
use crate::io;

/// What a run did, written as JSON by `--report`.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Report {
    /// Input file.
    pub input: PathBuf,
    /// Output file.
    pub output: PathBuf,
    /// `mesh`, `points` (in memory) or `tiled`.
    pub mode: String,
    /// The parameters in force: every default the run resolved is filled in (`knn` 16 on
    /// clouds, the mode's `filter`, `updates`, `sigma_r` and cycles), so the report says what ran;
    /// `knn` stays `null` in mesh mode (k-rings), and `iterations` 0 on meshes means the cycles
    /// were chosen from the data.
    pub params: Params,
    /// Outlier handling.
    pub outliers: OutlierMode,
    /// Points read.
    pub points_in: u64,
    /// Points written.
    pub points_out: u64,
    /// Faces carried through.
    pub faces: u64,
    /// Points dropped from a point cloud for a NaN, infinite or out-of-range coordinate (beyond
    /// ±[`crate::points::MAX_COORD`]).
    pub dropped_non_finite: u64,
    /// Points found to be outliers (flagged or removed).
    pub outliers_found: u64,
    /// Tiles (1 in memory).
    pub tiles: u64,
    /// Tiles that owned no point.
    pub empty_tiles: u64,
    /// Times a tile's halo had to grow.
    pub halo_growths: u64,
    /// Kernel runs on the cells the dependencies of lone points reach, where a point's halo
    /// alone would hold more than the memory budget.
    #[serde(default)]
    pub cell_runs: u64,
    /// Kernel runs of growth groups at a narrower halo than their round's, where the round's
    /// halo would have held more points than the memory budget.
    #[serde(default)]
    pub narrower_runs: u64,
    /// Tiles taken from an earlier, interrupted run's checkpoints.
    #[serde(default)]
    pub tiles_resumed: u64,
    /// Bytes written to spill and result files.
    pub bytes_spilled: u64,
    /// Denoiser statistics.
    pub stats: Stats,
    /// Wall and CPU time per phase.
    pub phases: Vec<PhaseTiming>,
    /// Total wall seconds.
    pub wall_s: f64,
    /// Total process CPU seconds.
    pub cpu_s: f64,
    /// Worker threads.
    pub threads: usize,
    /// Peak resident set size of the process in bytes (0 where unknown).
    pub peak_rss_bytes: u64,
    /// What happened to normals stored in the input: recomputed (meshes) or cleared (clouds).
    #[serde(default)]
    pub normals: NormalsAction,
}

impl Report {
    /// Writes the report as pretty JSON, atomically.
    ///
    /// # Errors
    /// [`PipelineError::Report`].
    pub fn write(&self, path: &Path) -> Result<(), PipelineError> {
        use std::io::Write;
        let err = |detail: String| PipelineError::Report {
            path: path.to_path_buf(),
            detail,
        };
        let mut f = io::AtomicFile::create(path).map_err(|e| err(e.to_string()))?;
        serde_json::to_writer_pretty(&mut f, self).map_err(|e| err(e.to_string()))?;
        f.write_all(b"\n").map_err(|e| err(e.to_string()))?;
        f.commit().map_err(|e| err(e.to_string()))
    }
}

/// `params` with the defaults a run in mesh mode (`mesh`) or point mode resolves filled in.
fn in_force(params: &Params, mesh: bool) -> Params {
    let s = params.schedule(mesh);
    Params {
        knn: (!mesh || params.knn.is_some()).then(|| params.k()),
        filter: Some(s.filter),
        updates: Some(s.updates),
        iterations: s.cycles,
        sigma_r: Some(params.sigma_r_floor(mesh)),
        ..params.clone()
    }
}

/// Peak resident set size of this process (VmHWM), in bytes; 0 where unavailable.
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

impl Report {
    /// The report of a run of `job` in `mode` before anything happened (one tile, this pool's
    /// threads).
    pub(crate) fn empty(job: &Job, mode: &str) -> Report {
        Report {
            input: job.input.clone(),
            output: job.output.clone(),
            mode: mode.into(),
            params: in_force(&job.spec.params, mode == "mesh"),
            outliers: job.spec.outliers,
            points_in: 0,
            points_out: 0,
            faces: 0,
            dropped_non_finite: 0,
            outliers_found: 0,
            tiles: 1,
            empty_tiles: 0,
            halo_growths: 0,
            cell_runs: 0,
            narrower_runs: 0,
            tiles_resumed: 0,
            bytes_spilled: 0,
            stats: Stats::default(),
            phases: Vec::new(),
            wall_s: 0.0,
            cpu_s: 0.0,
            threads: rayon::current_num_threads(),
            peak_rss_bytes: 0,
            normals: NormalsAction::None,
        }
    }
}
