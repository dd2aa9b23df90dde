//! Runs a denoising job end to end: source → (tiles) → sink, with progress, cancellation, a
//! memory budget and a report.
//!
//! # Brief overview
//!
//! [`run`] picks the path:
//!
//! * **Meshes** run in memory ([`crate::denoise::denoise`]): faces need the whole vertex set.
//! * **Point clouds that fit the memory budget** run in memory, as one region without a boundary.
//! * **Larger point clouds** (or any cloud with `tile_points` set) run in tiles: plan, partition,
//!   process, stitch (see [`crate::tiling`]). Both point paths run the same kernel on the same
//!   neighbourhoods, so they write the same bytes.
//!
//! The output is created *like* the input (same schema, property types, header, order) and
//! appears atomically (a stream — standard output, a device, a FIFO — is written directly; see
//! [`crate::io::output`]); the input is only ever opened for reading, and an output path naming
//! the input is refused. An input that is a stream (`-`, `/dev/stdin` from a pipe, a FIFO) is
//! first spooled to the temporary directory ([`crate::io::input`]), since the passes below read
//! it more than once. Stored normals are recomputed (meshes) or cleared (clouds), never written
//! stale (`normals`). Points of a point cloud that fail [`crate::points::in_range`] (a NaN or
//! infinite coordinate, or one beyond ±10¹², i.e. a corrupt record) are dropped and counted as
//! they are read (organized PCD clouds keep them, unprocessed and unchanged). Outliers are
//! flagged (keeping their input position) or removed as [`OutlierMode`] says.
//!
//! Cancellation (the [`RunOptions::cancel`] flag) is checked per batch while streaming, per tile,
//! per halo growth, and inside the k-NN passes (installed with
//! [`crate::neighbours::with_cancel`]), so a run stops soon after the flag is set.
//!
//! [`Report`] records what happened: counts, tiles, halo growths, bytes spilled, per-phase wall and
//! CPU time, peak RSS.

mod arrays;
mod normals;
mod progress;
mod spec;

pub use arrays::{PointsOutput, denoise_points};
pub use normals::NormalsAction;
pub use progress::{BarProgress, LogProgress, NoProgress, Progress};
pub use spec::{DEFAULT_OUTLIER_ALPHA, DenoiseSpec, SpecError, SpecOverlay, validate_alpha};

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use cpu_time::ProcessTime;
use glam::DVec3;
use thiserror::Error;

use crate::denoise::cloud::{self, Globals};
use crate::denoise::{self, DenoiseError, Method, Params, PhaseTiming, Stats, Timer};
use crate::geometry::ExactSum;
use crate::io::{self, BATCH, Cloud, Extras, Format, IoError, SinkOptions, Source, SourceInfo};
use crate::neighbours::{NeighboursError, with_cancel};
use crate::points::{FLAG_NOISE, PointBatch, Schema, in_range};
use crate::tiling::occupancy::Occupancy;
use crate::tiling::plan::{Plan, Planner, SAMPLE};
use crate::tiling::spill::{ResultMerge, SpillWriter, TileResult};
use crate::tiling::{self, TilingError};

/// Errors of a pipeline run; each names the file concerned.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// Reading or writing failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The denoiser refused the input or the parameters.
    #[error("{path}: {error}", path = .path.display())]
    Denoise {
        /// Input file.
        path: PathBuf,
        /// What the denoiser said.
        error: DenoiseError,
    },
    /// Parameters are invalid (checked before any I/O).
    #[error(transparent)]
    Params(SpecError),
    /// The output path names the input file.
    #[error("{path}: refusing to overwrite the input file", path = .path.display())]
    SameFile {
        /// The path given twice.
        path: PathBuf,
    },
    /// The temporary directory is unusable.
    #[error("{path}: temporary directory unusable: {detail}", path = .path.display())]
    TempDir {
        /// The directory.
        path: PathBuf,
        /// Why.
        detail: String,
    },
    /// The tiled path failed.
    #[error("{path}: {error}", path = .path.display())]
    Tiling {
        /// Input file.
        path: PathBuf,
        /// What failed.
        error: TilingError,
    },
    /// The run was cancelled (Ctrl-C, a job cancel).
    #[error("cancelled")]
    Cancelled,
    /// The report could not be written.
    #[error("{path}: cannot write report: {detail}", path = .path.display())]
    Report {
        /// Report path.
        path: PathBuf,
        /// What failed.
        detail: String,
    },
}

impl PipelineError {
    /// The same error naming the stream `input` where it named its spool.
    fn with_input(self, input: &io::InputFile) -> PipelineError {
        let (from, to) = (input.path(), input.shown());
        let swap = |p: PathBuf| if p == from { to.to_path_buf() } else { p };
        match self {
            PipelineError::Io(e) => PipelineError::Io(input.explain(e)),
            PipelineError::Denoise { path, error } => PipelineError::Denoise {
                path: swap(path),
                error,
            },
            PipelineError::Tiling { path, error } => PipelineError::Tiling {
                path: swap(path),
                error,
            },
            other => other,
        }
    }
}

/// What to do with statistical outliers: points whose mean distance to their k-NN list is above
/// `mean + alpha·σ` of that statistic over the whole cloud.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum OutlierMode {
    /// Leave them.
    #[default]
    Off,
    /// Flag them: LAS class 7, or a `noise` property.
    Classify,
    /// Drop them from the output.
    Remove,
}

/// Where a job reads and writes, and what it does.
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
    /// What the run computes.
    pub spec: DenoiseSpec,
}

impl Job {
    /// A job with the default spec (no outlier handling).
    pub fn new(input: impl Into<PathBuf>, output: impl Into<PathBuf>) -> Job {
        Job {
            input: input.into(),
            output: output.into(),
            input_format: None,
            output_format: None,
            spec: DenoiseSpec::default(),
        }
    }
}

/// How a job runs (not what it computes).
#[derive(Clone)]
pub struct RunOptions {
    /// Clouds whose working set fits run in memory; larger ones run in tiles sized to it.
    pub memory_budget: u64,
    /// Where spill files go (the system temp directory when `None`).
    pub temp_dir: Option<PathBuf>,
    /// Forces tiling with about this many points per tile.
    pub tile_points: Option<u64>,
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
            .field("work_dir", &self.work_dir)
            .finish()
    }
}

/// What a run did, written as JSON by `--report`.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Report {
    /// Input file.
    pub input: PathBuf,
    /// Output file.
    pub output: PathBuf,
    /// `mesh`, `points` (in memory) or `tiled`.
    pub mode: String,
    /// The parameters used.
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

/// Working-set bytes per point of the point kernel (positions in three layouts, the k-NN lists,
/// the grid pass's sort keys, per-point results; with a normal filter, its spatial weights and
/// normal copies). Measured peak RSS per tile point (10 M-point runs, docs/BENCHMARKS.md):
/// about 430 B with `--paper`, 670 B with the default; the tile target leaves the rest of the
/// budget as headroom.
pub fn bytes_per_point(params: &Params, record_len: usize) -> u64 {
    let k = params.k();
    let filter = match params.method {
        Method::Qem if params.schedule(false).filter > 0 => 8 * k + 112,
        _ => 0,
    };
    (record_len + 4 * k + 240 + filter) as u64
}

/// Outlier threshold from exact sums of the statistic and its square.
fn threshold(sum: &ExactSum, sq: &ExactSum, alpha: f64) -> f64 {
    let n = sum.count().max(1) as f64;
    let mean = sum.value() / n;
    let var = (sq.value() / n - mean * mean).max(0.0);
    mean + alpha * var.sqrt()
}

/// Runs `job`; see the module overview.
///
/// # Errors
/// Bad parameters (before any I/O), unreadable or malformed input, too few points, an unusable
/// temporary directory, cancellation, write failures.
pub fn run(job: &Job, opts: &RunOptions) -> Result<Report, PipelineError> {
    job.spec.validate().map_err(PipelineError::Params)?;
    if let Some(t) = &opts.temp_dir
        && !t.is_dir()
    {
        return Err(PipelineError::TempDir {
            path: t.clone(),
            detail: "does not exist or is not a directory".into(),
        });
    }
    if same_file(&job.input, &job.output) {
        return Err(PipelineError::SameFile {
            path: job.output.clone(),
        });
    }
    // A stream (standard input, a pipe, a FIFO) is read more than once below: spool it first.
    let input = io::InputFile::open(&job.input, job.input_format, opts.temp_dir.as_deref())?;
    if input.is_spooled() {
        let spooled = Job {
            input: input.path().to_path_buf(),
            input_format: input.format(),
            ..job.clone()
        };
        let mut report = run_file(&spooled, opts).map_err(|e| e.with_input(&input))?;
        report.input = job.input.clone();
        return Ok(report);
    }
    run_file(job, opts)
}

/// [`run`] on an input that is a file.
fn run_file(job: &Job, opts: &RunOptions) -> Result<Report, PipelineError> {
    let wall = Instant::now();
    let cpu = ProcessTime::now();
    let source = io::open(&job.input, job.input_format)?;
    let info = source.info().clone();
    drop(source);
    let mut report = if job.spec.params.mesh_mode(info.has_faces()) {
        if job.spec.outliers != OutlierMode::Off {
            return Err(PipelineError::Params(SpecError {
                field: "outliers",
                detail: "applies to point clouds, not meshes".into(),
            }));
        }
        run_mesh(job)?
    } else {
        let per_point = bytes_per_point(&job.spec.params, info.schema.record_len);
        let fits = info
            .len
            .is_some_and(|n| n.saturating_mul(per_point) <= opts.memory_budget);
        if opts.tile_points.is_none() && fits {
            run_points_in_memory(job, opts)?
        } else {
            run_tiled(job, opts, &info, per_point)?
        }
    };
    report.wall_s = wall.elapsed().as_secs_f64();
    report.cpu_s = cpu.elapsed().as_secs_f64();
    report.peak_rss_bytes = peak_rss_bytes();
    Ok(report)
}

fn empty_report(job: &Job, mode: &str) -> Report {
    Report {
        input: job.input.clone(),
        output: job.output.clone(),
        mode: mode.into(),
        params: job.spec.params.clone(),
        outliers: job.spec.outliers,
        points_in: 0,
        points_out: 0,
        faces: 0,
        dropped_non_finite: 0,
        outliers_found: 0,
        tiles: 1,
        empty_tiles: 0,
        halo_growths: 0,
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

fn run_mesh(job: &Job) -> Result<Report, PipelineError> {
    let mut phases = Stats::default();
    let mut timer = Timer::start();
    let mut cloud = Cloud::read(&job.input, job.input_format)?;
    timer.lap("read", &mut phases);
    let out = denoise::denoise(&cloud.positions, cloud.faces(), &job.spec.params)
        .map_err(|e| denoise_error(&job.input, e))?;
    let mut stats = out.stats;
    phases.merge(&Stats {
        phases: std::mem::take(&mut stats.phases),
        ..Stats::default()
    });
    cloud.positions = out.positions;
    let normals = normals::recompute_mesh(&mut cloud);
    timer = Timer::start();
    cloud.write(&job.output, job.output_format)?;
    timer.lap("write", &mut phases);
    let mut r = empty_report(job, "mesh");
    r.points_in = cloud.len() as u64;
    r.points_out = cloud.len() as u64;
    r.faces = cloud.faces().map_or(0, |f| f.len() as u64);
    r.normals = normals;
    r.stats = stats;
    r.phases = phases.phases;
    Ok(r)
}

/// True when `info`'s unprocessed points (failing [`in_range`]) must be written back unchanged
/// (organized clouds) rather than dropped.
fn keeps_non_finite(info: &SourceInfo) -> bool {
    info.is_organized()
}

/// The point-cloud rules that turn an input record plus its result into an output record.
struct Assembler {
    keep_non_finite: bool,
    mode: OutlierMode,
    threshold: f64,
    /// Stored normal fields to clear (they would be stale).
    normals: Option<(Schema, [usize; 3])>,
}

impl Assembler {
    fn new(info: &SourceInfo, mode: OutlierMode, threshold: f64) -> Assembler {
        Assembler {
            keep_non_finite: keeps_non_finite(info),
            mode,
            threshold,
            normals: normals::normal_fields(&info.schema).map(|f| (info.schema.clone(), f)),
        }
    }

    /// What the output does with stored normals.
    fn normals_action(&self) -> NormalsAction {
        if self.normals.is_some() {
            NormalsAction::Cleared
        } else {
            NormalsAction::None
        }
    }

    /// Appends a point to `out`, its stored normals cleared.
    fn put(&self, out: &mut PointBatch, p: DVec3, record: &[u8]) {
        out.push(p, record);
        if let Some((schema, f)) = &self.normals {
            let end = out.records.len();
            normals::clear_points(schema, *f, &mut out.records[end - schema.record_len..end]);
        }
    }

    /// Appends input point `i` of `batch` to `out` given its result (None for non-finite points);
    /// returns whether it was flagged or removed as an outlier.
    fn push(
        &self,
        batch: &PointBatch,
        i: usize,
        result: Option<(DVec3, f64)>,
        out: &mut PointBatch,
    ) -> bool {
        let (p, outlier) = match result {
            None if !self.keep_non_finite => return false,
            None => (batch.positions[i], false),
            // A flagged outlier keeps its input position: it is reported, not "denoised" onto
            // a surface it does not belong to.
            Some((_, m)) if self.mode != OutlierMode::Off && m > self.threshold => {
                (batch.positions[i], true)
            }
            Some((p, _)) => (p, false),
        };
        if outlier && self.mode == OutlierMode::Remove {
            if self.keep_non_finite {
                // An organized cloud keeps its image layout: a removed point becomes a NaN
                // placeholder, as its invalid points are.
                self.put(out, DVec3::NAN, batch.record(i));
            }
            return true;
        }
        self.put(out, p, batch.record(i));
        if self.mode == OutlierMode::Classify {
            out.flags.push(if outlier { FLAG_NOISE } else { 0 });
        }
        outlier
    }
}

fn sink_options(job: &Job, opts: &RunOptions) -> SinkOptions {
    SinkOptions {
        noise_flag: job.spec.outliers == OutlierMode::Classify,
        temp_dir: opts.temp_dir.clone(),
    }
}

/// The error of the denoiser on `path`; its cancellation is the run's.
fn denoise_error(path: &Path, error: DenoiseError) -> PipelineError {
    match error {
        DenoiseError::Neighbours(NeighboursError::Cancelled) => PipelineError::Cancelled,
        error => PipelineError::Denoise {
            path: path.to_path_buf(),
            error,
        },
    }
}

/// The error of the tiled path on `path`; its cancellation is the run's.
fn tiling_error(path: &Path, error: TilingError) -> PipelineError {
    match error {
        TilingError::Cancelled
        | TilingError::Denoise {
            error: DenoiseError::Neighbours(NeighboursError::Cancelled),
            ..
        } => PipelineError::Cancelled,
        error => PipelineError::Tiling {
            path: path.to_path_buf(),
            error,
        },
    }
}

fn cancelled(opts: &RunOptions) -> Result<(), PipelineError> {
    if opts.cancel.load(Ordering::Relaxed) {
        Err(PipelineError::Cancelled)
    } else {
        Ok(())
    }
}

fn run_points_in_memory(job: &Job, opts: &RunOptions) -> Result<Report, PipelineError> {
    let mut phases = Stats::default();
    let mut timer = Timer::start();
    opts.progress.phase("read", 0);
    let cloud = Cloud::read(&job.input, job.input_format)?;
    timer.lap("read", &mut phases);
    cancelled(opts)?;
    opts.progress.phase("denoise", 1);
    let result = denoise_points(&cloud.positions, &job.spec, &opts.cancel)
        .map_err(|e| denoise_error(&job.input, e))?;
    let stats = result.stats.clone();
    phases.merge(&Stats {
        phases: result.phases.clone(),
        ..Stats::default()
    });
    opts.progress.advance(1);
    cancelled(opts)?;
    timer = Timer::start();

    let asm = Assembler::new(&cloud.info, job.spec.outliers, result.threshold);
    let mut by_index: Vec<Option<(DVec3, f64)>> = vec![None; cloud.len()];
    for (j, &i) in result.kept.iter().enumerate() {
        by_index[i] = Some((result.positions[j], result.knn_mean[j]));
    }
    let input = PointBatch {
        start: 0,
        positions: cloud.positions.clone(),
        records: cloud.records.clone(),
        record_len: cloud.info.schema.record_len,
        flags: Vec::new(),
    };
    let mut out = PointBatch::with_capacity(input.record_len, cloud.len());
    let mut found = 0u64;
    for (i, r) in by_index.iter().enumerate() {
        found += asm.push(&input, i, *r, &mut out) as u64;
    }
    opts.progress.phase("write", out.len() as u64);
    let mut sink = io::create_with(
        &job.output,
        job.output_format,
        &cloud.info,
        out.len() as u64,
        &sink_options(job, opts),
    )?;
    write_chunked(sink.as_mut(), &out)?;
    sink.finish(&cloud.extras)?;
    timer.lap("write", &mut phases);

    let mut r = empty_report(job, "points");
    r.normals = asm.normals_action();
    r.points_in = cloud.len() as u64;
    r.points_out = out.len() as u64;
    r.dropped_non_finite = if asm.keep_non_finite {
        0
    } else {
        stats.non_finite
    };
    r.outliers_found = found;
    r.stats = stats;
    r.phases = phases.phases;
    Ok(r)
}

/// Writes `all` through `sink` in batches of [`BATCH`] points.
fn write_chunked(sink: &mut dyn io::Sink, all: &PointBatch) -> Result<(), PipelineError> {
    let rl = all.record_len;
    let mut b = PointBatch::with_capacity(rl, BATCH);
    for start in (0..all.len()).step_by(BATCH) {
        let end = (start + BATCH).min(all.len());
        b.clear(start as u64);
        b.positions.extend_from_slice(&all.positions[start..end]);
        b.records
            .extend_from_slice(&all.records[start * rl..end * rl]);
        if !all.flags.is_empty() {
            b.flags.extend_from_slice(&all.flags[start..end]);
        }
        sink.write_batch(&b)?;
    }
    Ok(())
}

/// Streams every batch of `path` through `f`, with cancellation checks and progress.
fn stream(
    job: &Job,
    opts: &RunOptions,
    mut f: impl FnMut(&PointBatch) -> Result<(), PipelineError>,
) -> Result<Extras, PipelineError> {
    let mut src: Box<dyn Source> = io::open(&job.input, job.input_format)?;
    let mut batch = PointBatch::with_capacity(src.info().schema.record_len, BATCH);
    let mut done = 0u64;
    while src.read_batch(&mut batch, BATCH)? > 0 {
        cancelled(opts)?;
        f(&batch)?;
        done += batch.len() as u64;
        opts.progress.advance(done);
    }
    Ok(src.finish()?)
}

/// Where the tiled path keeps its files: a temporary directory removed when dropped, or a
/// caller's persistent job directory.
enum Scratch {
    Temp(tempfile::TempDir),
    Persistent(PathBuf),
}

impl Scratch {
    fn path(&self) -> &Path {
        match self {
            Scratch::Temp(d) => d.path(),
            Scratch::Persistent(p) => p,
        }
    }
}

/// Disk bytes per point a tiled run needs in its scratch directory: one spill record per point
/// plus halo copies (counted as half as many again) and one result record.
pub const TILED_DISK_PER_POINT: u64 =
    (tiling::spill::SPILL_RECORD as u64 * 3).div_ceil(2) + tiling::spill::RESULT_RECORD as u64;

/// Where the tiled path's scratch directory goes.
fn scratch_base(opts: &RunOptions) -> PathBuf {
    opts.work_dir
        .clone()
        .or_else(|| opts.temp_dir.clone())
        .unwrap_or_else(std::env::temp_dir)
}

/// Refuses a tiled run of `points` points before any work when the scratch file system has
/// clearly too little room ([`TILED_DISK_PER_POINT`] per point).
fn check_disk(opts: &RunOptions, points: u64) -> Result<(), PipelineError> {
    let mut base = scratch_base(opts);
    // A job directory may not exist yet: measure the nearest existing ancestor.
    while !base.exists() {
        match base.parent() {
            Some(p) if !p.as_os_str().is_empty() => base = p.to_path_buf(),
            _ => return Ok(()),
        }
    }
    let need = points.saturating_mul(TILED_DISK_PER_POINT);
    let free = fs4::available_space(&base).map_err(|e| PipelineError::TempDir {
        path: base.clone(),
        detail: e.to_string(),
    })?;
    if free < need {
        return Err(PipelineError::TempDir {
            path: base,
            detail: format!(
                "{:.2} GiB free, a tiled run of {points} points needs about {:.2} GiB \
                 ({TILED_DISK_PER_POINT} bytes per point); free space or give --temp-dir",
                free as f64 / (1u64 << 30) as f64,
                need as f64 / (1u64 << 30) as f64
            ),
        });
    }
    Ok(())
}

/// The scratch directory, checked to exist, be writable and have room for `need` bytes.
fn scratch(opts: &RunOptions, need: u64) -> Result<Scratch, PipelineError> {
    let base = scratch_base(opts);
    let bad = |detail: String| PipelineError::TempDir {
        path: base.clone(),
        detail,
    };
    let s = if opts.work_dir.is_some() {
        std::fs::create_dir_all(&base).map_err(|e| bad(format!("cannot create it: {e}")))?;
        Scratch::Persistent(base.clone())
    } else {
        if !base.is_dir() {
            return Err(bad("does not exist or is not a directory".into()));
        }
        Scratch::Temp(
            tempfile::Builder::new()
                .prefix("qemd-")
                .tempdir_in(&base)
                .map_err(|e| bad(format!("cannot create a directory in it: {e}")))?,
        )
    };
    let free = fs4::available_space(s.path()).map_err(|e| bad(e.to_string()))?;
    if free < need {
        return Err(bad(format!(
            "{:.2} GiB free, the tiled run needs about {:.2} GiB",
            free as f64 / (1u64 << 30) as f64,
            need as f64 / (1u64 << 30) as f64
        )));
    }
    Ok(s)
}

/// Writes `value` as JSON to `path` atomically (checkpoint metadata).
fn save_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), PipelineError> {
    use std::io::Write;
    let io_err = |e: std::io::Error| PipelineError::Io(IoError::io(path, e));
    let mut f = io::AtomicFile::create(path)?;
    let text = serde_json::to_vec(value).map_err(|e| io_err(std::io::Error::other(e)))?;
    f.write_all(&text).map_err(io_err)?;
    f.commit_unsynced()?;
    Ok(())
}

/// Reads JSON written by [`save_json`]; `None` when missing or unreadable (then redone).
fn load_json<T: serde::de::DeserializeOwned>(path: &Path) -> Option<T> {
    serde_json::from_slice(&std::fs::read(path).ok()?).ok()
}

/// Removes every checkpoint file of an earlier run from `dir` (a plan that changed invalidates
/// them all).
fn clear_checkpoints(dir: &Path) -> Result<(), PipelineError> {
    let entries = std::fs::read_dir(dir).map_err(|e| IoError::io(dir, e))?;
    for e in entries {
        let p = e.map_err(|e| IoError::io(dir, e))?.path();
        let name = p
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let ours = name.starts_with("tile_")
            || name.starts_with("merge_")
            || ["plan.json", "spill.done", "globals.json"].contains(&name.as_str());
        if ours {
            std::fs::remove_file(&p).map_err(|e| IoError::io(&p, e))?;
        }
    }
    Ok(())
}

/// Pass 2: every finite point to its owner's spill file, halo copies to its neighbours'.
/// Occupancy cells per isolation radius: fine enough that a cell beside a dense region is often
/// empty, coarse enough that a ball of the radius visits at most 10³ cells.
const CELLS_PER_RADIUS: f64 = 4.0;

/// Pass 2: writes every processed point to its owner's spill file and its halo copies to the
/// others', and counts the points per cell of the occupancy grid (a quarter of the isolation radius).
fn partition(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    dir: &Path,
) -> Result<(u64, Option<Occupancy>), PipelineError> {
    let tiling_err = |e| tiling_error(&job.input, e);
    let mut spill = SpillWriter::create(dir, plan.tiles.len()).map_err(tiling_err)?;
    let mut near = Vec::new();
    let mut occupancy = plan
        .isolation
        .map(|r| Occupancy::new(r / CELLS_PER_RADIUS, plan.origin));
    stream(job, opts, |b| {
        for (j, &p) in b.positions.iter().enumerate() {
            if !in_range(p) {
                continue;
            }
            if let Some(o) = &mut occupancy {
                o.add(p);
            }
            let i = b.start + j as u64;
            let owner = plan.owner(p);
            spill.push(owner, i, p, false).map_err(tiling_err)?;
            near.clear();
            plan.near(p, plan.halo, &mut near);
            for &t in near.iter().filter(|&&t| t != owner) {
                spill.push(t, i, p, true).map_err(tiling_err)?;
            }
        }
        Ok(())
    })?;
    Ok((spill.finish().map_err(tiling_err)?, occupancy))
}

fn run_tiled(
    job: &Job,
    opts: &RunOptions,
    info: &SourceInfo,
    per_point: u64,
) -> Result<Report, PipelineError> {
    let tiling_err = |e| tiling_error(&job.input, e);
    let mut phases = Stats::default();
    let mut timer = Timer::start();

    // The disk the run needs, from the header's count, before the first pass.
    if let Some(n) = info.len {
        check_disk(opts, n)?;
    }
    // Pass 1: plan.
    opts.progress.phase("plan", info.len.unwrap_or(0));
    let mut planner = Planner::new(SAMPLE);
    stream(job, opts, |b| {
        for (j, p) in b.positions.iter().enumerate() {
            planner.add(b.start + j as u64, *p);
        }
        Ok(())
    })?;
    if planner.finite() == 0 {
        return Err(PipelineError::Denoise {
            path: job.input.clone(),
            error: DenoiseError::Empty,
        });
    }
    let b = planner.bounds();
    if planner.finite() > 1 && b.size() == DVec3::ZERO {
        return Err(PipelineError::Denoise {
            path: job.input.clone(),
            error: DenoiseError::AllIdentical(planner.finite() as usize),
        });
    }
    if planner.finite() < job.spec.params.k() as u64 {
        return Err(PipelineError::Denoise {
            path: job.input.clone(),
            error: DenoiseError::Neighbours(crate::neighbours::NeighboursError::TooFewPoints {
                points: planner.finite() as usize,
                k: job.spec.params.k(),
            }),
        });
    }
    // A tile's working set plus the next tile read ahead, the planning sample and I/O buffers
    // must fit the budget: a tile targets 40 % of it.
    let target = opts
        .tile_points
        .unwrap_or_else(|| (opts.memory_budget * 2 / (5 * per_point)).max(10_000));
    // One tile may run on as many points (owned and halo) as 60 % of the budget holds at
    // `per_point` bytes (the rest holds allocator slack and transient copies, the read-ahead
    // tile, the occupancy grid, the sample and I/O buffers); the tile target is 40 %, so a
    // uniform cloud's halo fits.
    let allowance = opts.memory_budget / 5 * 4;
    let max_points = opts.memory_budget / 5 * 3 / per_point.max(1);
    let plan = planner.finish_within(
        target,
        max_points,
        job.spec.params.k(),
        cloud::reach(&job.spec.params),
    );
    timer.lap("plan", &mut phases);

    // Pass 2: partition.
    let need = plan.finite * TILED_DISK_PER_POINT;
    let dir = scratch(opts, need)?;
    // A persistent directory holding the same plan and a finished partition is reused: only
    // tiles without a checkpoint are processed again.
    let plan_path = dir.path().join("plan.json");
    let spilled_marker = dir.path().join("spill.done");
    let resume = load_json::<tiling::plan::Plan>(&plan_path).is_some_and(|p| p == plan)
        && spilled_marker.exists();
    // The occupancy grid is saved before the marker, so a resumed run finds it.
    let occupancy_path = dir.path().join("occupancy.json");
    let mut bytes: u64 = if resume {
        load_json(&spilled_marker).unwrap_or(0)
    } else {
        0
    };
    let occupancy = if resume {
        // Only the speed depends on it: a missing grid proves nothing and costs halo growth.
        load_json::<Occupancy>(&occupancy_path)
    } else {
        clear_checkpoints(dir.path())?;
        save_json(&plan_path, &plan)?;
        opts.progress.phase("partition", plan.points);
        let (b, occupancy) = partition(job, opts, &plan, dir.path())?;
        bytes = b;
        if let Some(o) = &occupancy {
            save_json(&occupancy_path, o)?;
        }
        save_json(&spilled_marker, &bytes)?;
        occupancy
    };
    // A halo load may read as many points as the allowance holds at 80 bytes (a read point and
    // its position and index copies) before they are counted. A grown halo is otherwise not
    // refused (docs/DECISIONS.md, issue 16): refusing it failed real airborne scans at 64–128 MiB.
    let budget = tiling::TileBudget {
        occupancy: occupancy.as_ref(),
        max_points: Some(max_points),
        max_staged: Some(allowance / 80),
    };
    // Up front: every tile's first load (its spill file, exactly) fits, or the run says so
    // before any work.
    for t in 0..plan.tiles.len() {
        let points = tiling::spill::spilled_points(dir.path(), t).map_err(tiling_err)?;
        budget
            .check_points(t, points, plan.halo)
            .map_err(tiling_err)?;
    }
    timer.lap("partition", &mut phases);

    // Global scalars, when the method needs them: a pre-pass over the tiles.
    let globals_path = dir.path().join("globals.json");
    let globals = if !cloud::needs_globals(&job.spec.params) {
        Globals::default()
    } else if let Some(g) = resume
        .then(|| load_json::<Globals>(&globals_path))
        .flatten()
    {
        g
    } else {
        opts.progress.phase("globals", plan.tiles.len() as u64);
        let mut sum = cloud::GlobalsPartial::default();
        for t in 0..plan.tiles.len() {
            cancelled(opts)?;
            let partial = with_cancel(&opts.cancel, || {
                tiling::globals_of_tile(dir.path(), &plan, &budget, t, &job.spec.params)
            });
            sum.merge(&partial.map_err(tiling_err)?);
            opts.progress.advance(t as u64 + 1);
        }
        let g = sum.finish();
        save_json(&globals_path, &g)?;
        g
    };

    // Pass 3: tiles.
    opts.progress.phase("tiles", plan.tiles.len() as u64);
    let mut stats = Stats::default();
    let (mut sum, mut sq) = (ExactSum::new(), ExactSum::new());
    let mut growths = 0u64;
    let mut empty = 0u64;
    let mut resumed = 0u64;
    let outcome_path = |t: usize| dir.path().join(format!("tile_{t:05}.json"));
    // Tiles already finished by an interrupted run (result file and outcome both present).
    let finished: Vec<Option<tiling::TileOutcome>> = (0..plan.tiles.len())
        .map(|t| {
            (resume && tiling::spill::result_path(dir.path(), t).exists())
                .then(|| load_json(&outcome_path(t)))
                .flatten()
        })
        .collect();
    let todo: Vec<usize> = (0..plan.tiles.len())
        .filter(|&t| finished[t].is_none())
        .collect();
    let mut book = |o: &tiling::TileOutcome| {
        stats.merge(&o.stats);
        sum.merge(&o.knn_mean.0);
        sq.merge(&o.knn_mean.1);
        growths += o.halo_growths as u64;
        empty += (o.owned == 0) as u64;
        bytes += o.result_bytes;
    };
    for o in finished.iter().flatten() {
        resumed += 1;
        book(o);
    }
    opts.progress.advance(resumed);
    // The next tile's spill file is read on a helper thread while the current one computes.
    let mut ahead = match todo.first() {
        Some(&t) => Some(tiling::load_tile(dir.path(), &plan, t).map_err(tiling_err)?),
        None => None,
    };
    for (i, &t) in todo.iter().enumerate() {
        cancelled(opts)?;
        let pts = ahead.take();
        let following = todo.get(i + 1).copied();
        let (o, next) = std::thread::scope(|s| {
            let (path, plan) = (dir.path(), &plan);
            let reader = following.map(|n| s.spawn(move || tiling::load_tile(path, plan, n)));
            let o = with_cancel(&opts.cancel, || {
                tiling::process_tile(path, plan, &budget, t, &job.spec.params, &globals, pts)
            });
            let next = reader.map(|h| h.join().expect("the spill reader does not panic"));
            (o, next)
        });
        let o = o.map_err(tiling_err)?;
        ahead = next.transpose().map_err(tiling_err)?;
        // The outcome is saved after the result file: a tile counts as finished only with both.
        save_json(&outcome_path(t), &o)?;
        book(&o);
        opts.progress.advance(resumed + i as u64 + 1);
    }
    stats.non_finite = plan.points - plan.finite;
    stats.points = plan.points;
    timer.lap("tiles", &mut phases);
    // The kernel phases run inside the tiles; keep their totals too.
    let kernel = std::mem::take(&mut stats.phases);

    // Pass 4: stitch.
    let asm = Assembler::new(
        info,
        job.spec.outliers,
        threshold(&sum, &sq, job.spec.outlier_alpha),
    );
    let removed = if job.spec.outliers == OutlierMode::Remove {
        let mut merge = ResultMerge::open(dir.path(), plan.tiles.len()).map_err(tiling_err)?;
        let mut n = 0u64;
        while let Some(r) = merge.next_result().map_err(tiling_err)? {
            n += (r.knn_mean > asm.threshold) as u64;
        }
        n
    } else {
        0
    };
    let dropped = if asm.keep_non_finite {
        0
    } else {
        plan.points - plan.finite
    };
    let count = plan.points - dropped - if asm.keep_non_finite { 0 } else { removed };
    opts.progress.phase("stitch", plan.points);
    let mut sink = io::create_with(
        &job.output,
        job.output_format,
        info,
        count,
        &sink_options(job, opts),
    )?;
    let mut merge = ResultMerge::open(dir.path(), plan.tiles.len()).map_err(tiling_err)?;
    let mut next: Option<TileResult> = merge.next_result().map_err(tiling_err)?;
    let mut out = PointBatch::with_capacity(info.schema.record_len, BATCH);
    let mut found = 0u64;
    let mut written = 0u64;
    let extras = stream(job, opts, |b| {
        out.clear(written);
        for i in 0..b.len() {
            let gi = b.start + i as u64;
            let result = match next {
                Some(r) if r.index == gi => {
                    next = merge.next_result().map_err(tiling_err)?;
                    Some((r.p, r.knn_mean))
                }
                _ => None,
            };
            found += asm.push(b, i, result, &mut out) as u64;
        }
        written += out.len() as u64;
        sink.write_batch(&out)?;
        Ok(())
    })?;
    sink.finish(&extras)?;
    timer.lap("stitch", &mut phases);
    drop(dir);

    let mut r = empty_report(job, "tiled");
    r.normals = asm.normals_action();
    r.points_in = plan.points;
    r.points_out = written;
    r.dropped_non_finite = dropped;
    r.outliers_found = found;
    r.tiles = plan.tiles.len() as u64;
    r.empty_tiles = empty;
    r.halo_growths = growths;
    r.tiles_resumed = resumed;
    r.bytes_spilled = bytes;
    r.stats = stats;
    let mut all = phases.phases;
    all.extend(kernel.into_iter().map(|p| PhaseTiming {
        name: format!("tiles.{}", p.name),
        ..p
    }));
    r.phases = all;
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue12_tiled_disk_is_checked_up_front() {
        let dir = tempfile::tempdir().unwrap();
        let opts = RunOptions {
            temp_dir: Some(dir.path().to_path_buf()),
            ..RunOptions::default()
        };
        assert_eq!(TILED_DISK_PER_POINT, 88);
        check_disk(&opts, 1000).unwrap();
        // 10^15 points need 88 PB: clearly more than any test machine has.
        let e = check_disk(&opts, 1_000_000_000_000_000)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&dir.path().display().to_string()) && e.contains("needs about"),
            "{e}"
        );
        assert_eq!(e.lines().count(), 1);
    }
}
