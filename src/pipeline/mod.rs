//! Runs a denoising job end to end: source → (tiles) → sink, with progress, cancellation, a
//! memory budget and a report.
//!
//! # Brief overview
//!
//! [`run`] picks the path:
//!
//! * **Meshes** run in memory (`mesh`, [`crate::denoise::denoise`]): faces need the whole
//!   vertex set.
//! * **Point clouds that fit the memory budget** run in memory (`memory`), as one region
//!   without a boundary ([`crate::denoise::cloud::run_all`]).
//! * **Larger point clouds** (or any cloud with `tile_points` set) run in tiles ([`tiled`]) as
//!   named phases: plan, partition, globals, tiles, outlier threshold, stitch (see
//!   [`crate::tiling`]). Both point paths run the same kernel on the same neighbourhoods and
//!   assemble the output by the same rules (`assemble`), so they write the same bytes.
//!
//! The output is created *like* the input (same schema, property types, header, order) and
//! appears atomically (a stream — standard output, a device, a FIFO — is written directly; see
//! [`crate::io::output`]); the input is only ever opened for reading, and an output path naming
//! the input is refused. An input that is a stream (`-`, `/dev/stdin` from a pipe, a FIFO) is
//! first spooled to the temporary directory ([`crate::io::input`]), since the passes below read
//! it more than once. Stored normals are recomputed (meshes) or cleared (clouds), never written
//! stale (`normals`); with `write_normals` a cloud gets the run's own normals, curvature and
//! structure class as fields instead ([`crate::denoise::written`]), carried through the tiles'
//! result records so both point paths write the same bytes. Points of a point cloud that fail [`crate::points::in_range`] (a NaN or
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
mod assemble;
mod bytes;
pub mod classes;
mod error;
mod job;
mod memory;
mod mesh;
mod normals;
mod options;
mod progress;
mod report;
pub mod scaleout;
mod spec;
mod stream;
pub mod tiled;

pub use arrays::{PointsOutput, denoise_points};
pub use bytes::{BytesOutput, run_bytes};
pub use classes::ClassList;
pub use error::PipelineError;
pub use job::{Job, OutlierMode};
pub use normals::NormalsAction;
pub use options::{DEFAULT_MEMORY_BUDGET, RunOptions};
pub use progress::{BarProgress, LogProgress, NoProgress, Progress};
pub use report::{Report, peak_rss_bytes};
pub use spec::{DEFAULT_OUTLIER_ALPHA, DenoiseSpec, SpecError, SpecOverlay, validate_alpha};
pub use tiled::TILED_DISK_PER_POINT;

use std::path::Path;
use std::time::Instant;

use cpu_time::ProcessTime;

use crate::denoise::{Method, Params};
use crate::io;

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
    // Written normals: the kernel's values, restored to input order and carried to the sink
    // (`PointNormal`, 20 bytes, about three copies), and the last cycle's curvatures.
    let normals = if params.write_normals { 72 } else { 0 };
    (record_len + 4 * k + 240 + filter + normals) as u64
}

/// A kernel run's peak over [`bytes_per_point`]: the run's working set plus what the estimate
/// leaves out (in memory, the read cloud's buffers and decoders and the outlier pass; in a tile,
/// the round-by-round lists of a growth group; allocator slack in both). Measured at 1.25–1.45 ×
/// the estimate (issue 16, docs/BENCHMARKS.md: in memory, the 300 k cluttered scene 750 B a point
/// against 568 B, `lone-star.copc.laz` 742 against 580, `--paper` 443 against 328; a `--paper`
/// growth group of 1.9 M points on the 100 M cluttered scene 475 B against 328). 3/2 keeps a
/// run within the budget it was sized for.
pub const PEAK_FACTOR: (u64, u64) = (3, 2);

/// The peak bytes a point costs a kernel run at `per_point` ([`bytes_per_point`]): with
/// [`PEAK_FACTOR`].
pub fn peak_per_point(per_point: u64) -> u64 {
    let (num, den) = PEAK_FACTOR;
    per_point.saturating_mul(num) / den
}

/// True when a cloud of `points` points at `per_point` ([`bytes_per_point`]) runs in memory
/// within `budget`.
pub fn fits_in_memory(points: u64, per_point: u64, budget: u64) -> bool {
    let (num, den) = PEAK_FACTOR;
    points.saturating_mul(per_point).saturating_mul(num) / den <= budget
}

/// Runs `job`; see the module overview.
///
/// # Errors
/// Bad parameters (before any I/O), unreadable or malformed input, too few points, an unusable
/// temporary directory, cancellation, write failures.
pub fn run(job: &Job, opts: &RunOptions) -> Result<Report, PipelineError> {
    job.spec.validate()?;
    if job.trajectory.is_some() && job.spec.params.sensor_origin.point().is_some() {
        return Err(SpecError {
            field: "trajectory",
            detail: "and sensor_origin both give the beams; give one".into(),
        }
        .into());
    }
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
    refuse_normals_early(job)?;
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

/// Refuses a job with a trajectory (`--trajectory`) for `why`.
fn refuse_trajectory(job: &Job, why: &str) -> Result<(), PipelineError> {
    match &job.trajectory {
        Some(_) => Err(SpecError {
            field: "trajectory",
            detail: why.to_string(),
        }
        .into()),
        None => Ok(()),
    }
}

/// Refuses written normals towards an output format that cannot hold them, before any work, when
/// the format is known from the job or the output's extension (the sink refuses it otherwise).
fn refuse_normals_early(job: &Job) -> Result<(), PipelineError> {
    let format = job
        .output_format
        .or_else(|| io::Format::from_path(&job.output).ok());
    match format.and_then(io::refuse_normals) {
        Some(detail) if job.spec.params.write_normals => Err(io::IoError::Unsupported {
            path: job.output.clone(),
            detail: detail.into(),
        }
        .into()),
        _ => Ok(()),
    }
}

/// [`run`] on an input that is a file.
fn run_file(job: &Job, opts: &RunOptions) -> Result<Report, PipelineError> {
    let wall = Instant::now();
    let cpu = ProcessTime::now();
    let source = io::open(&job.input, job.input_format)?;
    let info = source.info().clone();
    drop(source);
    let job = &Job {
        spec: job.spec.for_format(info.format),
        ..job.clone()
    };
    let mut report = if job.spec.params.mesh_mode(info.has_faces()) {
        job.spec.check_mesh(true)?;
        refuse_trajectory(job, "applies to point clouds, not meshes")?;
        mesh::run(job, opts, &info)?
    } else {
        let per_point = bytes_per_point(&job.spec.params, info.schema.record_len);
        let fits = info
            .len
            .is_some_and(|n| fits_in_memory(n, per_point, opts.memory_budget));
        if opts.tile_points.is_none() && fits {
            memory::run(job, opts)?
        } else {
            refuse_trajectory(
                job,
                "needs the cloud in memory: it does not fit --memory-budget (or --tile-points \
                 asks for tiles), and a tiled run does not carry the points' times yet",
            )?;
            tiled::run(job, opts, &info, per_point)?
        }
    };
    report.wall_s = wall.elapsed().as_secs_f64();
    report.cpu_s = cpu.elapsed().as_secs_f64();
    report.peak_rss_bytes = peak_rss_bytes();
    Ok(report)
}
