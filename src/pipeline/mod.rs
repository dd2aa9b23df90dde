//! Runs a denoising job end to end: source → denoise → sink, with timing and a report.
//!
//! # Brief overview
//!
//! [`run`] reads the input through its `io::Source`, drops (and counts) non-finite points of point
//! clouds, runs [`crate::denoise::denoise`], and writes the result through an `io::Sink` created
//! *like* the source, so the output keeps the input's schema, property types, point order, faces
//! and every attribute. The output appears atomically (temp file + rename); the input is only
//! ever opened for reading, and an output path that names the input is refused.
//!
//! [`Report`] records what happened: counts, per-phase wall and CPU time, peak RSS.

use std::path::{Path, PathBuf};
use std::time::Instant;

use cpu_time::ProcessTime;
use glam::DVec3;
use thiserror::Error;

use crate::denoise::{self, DenoiseError, Params, PhaseTiming, Stats, Timer};
use crate::io::{self, Cloud, Format, IoError};

/// Errors of a pipeline run; each names the file concerned.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// Reading or writing failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The denoiser refused the input or the parameters.
    #[error("{path}: {source}", path = .path.display())]
    Denoise {
        /// Input file.
        path: PathBuf,
        /// What the denoiser said.
        source: DenoiseError,
    },
    /// Parameters are invalid (checked before any I/O).
    #[error(transparent)]
    Params(DenoiseError),
    /// The output path names the input file.
    #[error("{path}: refusing to overwrite the input file", path = .path.display())]
    SameFile {
        /// The path given twice.
        path: PathBuf,
    },
    /// The report could not be written.
    #[error("{path}: cannot write report: {detail}", path = .path.display())]
    Report {
        /// Report path.
        path: PathBuf,
        /// What failed.
        detail: String,
    },
}

/// Where a job reads and writes.
#[derive(Debug, Clone)]
pub struct Job {
    /// Input file.
    pub input: PathBuf,
    /// Output file.
    pub output: PathBuf,
    /// Input format (else from the extension).
    pub input_format: Option<Format>,
    /// Output format (else from the extension).
    pub output_format: Option<Format>,
    /// Denoising parameters.
    pub params: Params,
}

/// What a run did, written as JSON by `--report`.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Report {
    /// Input file.
    pub input: PathBuf,
    /// Output file.
    pub output: PathBuf,
    /// `mesh` or `points`.
    pub mode: String,
    /// The parameters used.
    pub params: Params,
    /// Points read.
    pub points_in: u64,
    /// Points written.
    pub points_out: u64,
    /// Faces carried through.
    pub faces: u64,
    /// Non-finite points dropped from a point cloud.
    pub dropped_non_finite: u64,
    /// Denoiser statistics.
    pub stats: Stats,
    /// Wall and CPU time per phase (read, neighbours, normals, solve, write).
    pub phases: Vec<PhaseTiming>,
    /// Total wall seconds.
    pub wall_s: f64,
    /// Total process CPU seconds.
    pub cpu_s: f64,
    /// Worker threads.
    pub threads: usize,
    /// Peak resident set size of the process in bytes (0 where unknown).
    pub peak_rss_bytes: u64,
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

/// True when `a` and `b` name the same existing file.
fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

/// Removes non-finite points (and their records) from a cloud without faces; returns how many.
fn drop_non_finite(cloud: &mut Cloud) -> u64 {
    let rl = cloud.info.schema.record_len;
    let before = cloud.positions.len();
    if cloud.positions.iter().all(|p| p.is_finite()) {
        return 0;
    }
    let mut positions: Vec<DVec3> = Vec::with_capacity(before);
    let mut records = Vec::with_capacity(cloud.records.len());
    for (i, p) in cloud.positions.iter().enumerate() {
        if p.is_finite() {
            positions.push(*p);
            records.extend_from_slice(&cloud.records[i * rl..(i + 1) * rl]);
        }
    }
    cloud.positions = positions;
    cloud.records = records;
    (before - cloud.positions.len()) as u64
}

/// Runs `job` in memory and returns its report.
///
/// # Errors
/// Bad parameters (before any I/O), unreadable or malformed input, too few points, write failures.
pub fn run(job: &Job) -> Result<Report, PipelineError> {
    job.params.validate().map_err(PipelineError::Params)?;
    if same_file(&job.input, &job.output) {
        return Err(PipelineError::SameFile {
            path: job.output.clone(),
        });
    }
    let wall = Instant::now();
    let cpu = ProcessTime::now();
    let mut phases = Stats::default();
    let mut timer = Timer::start();

    let mut cloud = Cloud::read(&job.input, job.input_format)?;
    let points_in = cloud.len() as u64;
    let mesh = job.params.mesh_mode(cloud.faces().is_some());
    let dropped = if cloud.faces().is_none() {
        drop_non_finite(&mut cloud)
    } else {
        0
    };
    timer.lap("read", &mut phases);

    let out = denoise::denoise(&cloud.positions, cloud.faces(), &job.params).map_err(|e| {
        PipelineError::Denoise {
            path: job.input.clone(),
            source: e,
        }
    })?;
    let mut stats = out.stats;
    stats.non_finite += dropped;
    let kernel_phases = std::mem::take(&mut stats.phases);
    cloud.positions = out.positions;
    timer = Timer::start();

    cloud.write(&job.output, job.output_format)?;
    timer.lap("write", &mut phases);

    let mut all = phases.phases;
    all.splice(1..1, kernel_phases);
    Ok(Report {
        input: job.input.clone(),
        output: job.output.clone(),
        mode: if mesh { "mesh" } else { "points" }.into(),
        params: job.params.clone(),
        points_in,
        points_out: cloud.len() as u64,
        faces: cloud.faces().map_or(0, |f| f.len() as u64),
        dropped_non_finite: dropped,
        stats,
        phases: all,
        wall_s: wall.elapsed().as_secs_f64(),
        cpu_s: cpu.elapsed().as_secs_f64(),
        threads: rayon::current_num_threads(),
        peak_rss_bytes: peak_rss_bytes(),
    })
}
