//! `qemd finish`: delivers a job's output to `-o OUT`. When OUT's format is the job's output
//! format, the stitch task runs if it has not (in the work directory), and its committed output
//! is hard-linked onto OUT (copied when OUT is on another file system or a stream), atomically.
//! For another format the stitch writes straight to OUT.

use std::path::{Path, PathBuf};

use super::frozen::FrozenJob;
use super::lock::PhaseLock;
use super::url::WorkUrl;
use super::worker::{Hooks, committed_stitch, run_task, stitch_into};
use super::{Phase, ScaleoutError};
use crate::denoise::{PhaseTiming, Stats};
use crate::io::{self, AtomicFile, Format, IoError};
use crate::pipeline::{NormalsAction, PipelineError, Report};
use crate::tiling::workdir::WorkDir;

/// What `finish` delivered.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Finished {
    /// The output.
    pub output: PathBuf,
    /// Its format.
    pub format: Format,
    /// Points read.
    pub points_in: u64,
    /// Points written.
    pub written: u64,
    /// Points flagged or removed as outliers.
    pub found: u64,
    /// Unprocessed points dropped.
    pub dropped: u64,
    /// What happened to stored normals.
    pub normals: NormalsAction,
    /// Tiles of the plan.
    pub tiles: u64,
    /// How it got there: `linked`, `copied` (the work directory's output) or `stitched`.
    pub delivered: &'static str,
}

/// Delivers the output of the job in `work` to `output` (format `format`, else from its
/// extension, else the job's for a stream).
///
/// # Errors
/// An output naming the input, an unknown format, the stitch's errors, copy failures.
pub fn finish(
    work: &WorkUrl,
    output: &Path,
    format: Option<Format>,
    hooks: &Hooks,
) -> Result<Finished, ScaleoutError> {
    let dir = work.local()?;
    let frozen = FrozenJob::load(dir)?;
    if let (Ok(a), Ok(b)) = (frozen.input_path(dir).canonicalize(), output.canonicalize())
        && a == b
    {
        return Err(PipelineError::SameFile {
            path: output.to_path_buf(),
        }
        .into());
    }
    let job_format = frozen.output_format.format();
    let target = match format {
        Some(f) => f,
        None => match Format::from_path(output) {
            Ok(f) => f,
            Err(_) if io::is_stdio(output) || io::is_stream_output(output) => job_format,
            Err(e) => return Err(e.into()),
        },
    };
    let mut done = Finished {
        output: output.to_path_buf(),
        format: target,
        points_in: frozen.plan.points,
        written: 0,
        found: 0,
        dropped: 0,
        normals: NormalsAction::default(),
        tiles: frozen.plan.tiles.len() as u64,
        delivered: "stitched",
    };
    if target == job_format {
        run_task(work, Phase::Stitch, (Some(0), Some(1)), |_| None, hooks)?;
        let s = committed_stitch(dir, &frozen).ok_or_else(|| ScaleoutError::NotReady {
            path: dir.to_path_buf(),
            phase: Phase::Stitch,
            detail: "its output, which changed or vanished after the stitch".into(),
        })?;
        done.delivered = deliver(&frozen.job(dir).output, output)?;
        (done.written, done.found, done.dropped, done.normals) =
            (s.written, s.found, s.dropped, s.normals);
    } else {
        let _lock = PhaseLock::acquire(dir, Phase::Stitch)?;
        let job = crate::pipeline::Job {
            output: output.to_path_buf(),
            output_format: Some(target),
            ..frozen.job(dir)
        };
        let s = stitch_into(dir, &job, hooks)?;
        (done.written, done.found, done.dropped, done.normals) =
            (s.written, s.found, s.dropped, s.normals);
    }
    Ok(done)
}

/// Puts the file `src` at `out` atomically: a hard link renamed onto it, else a copy.
fn deliver(src: &Path, out: &Path) -> Result<&'static str, IoError> {
    if !io::is_stdio(out) && !io::is_stream_output(out) {
        let parent = match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let name = out
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = parent.join(format!(".{name}.qemd-link-{}", std::process::id()));
        let _ = std::fs::remove_file(&tmp);
        if std::fs::hard_link(src, &tmp).is_ok() {
            return match std::fs::rename(&tmp, out) {
                Ok(()) => Ok("linked"),
                Err(e) => {
                    let _ = std::fs::remove_file(&tmp);
                    Err(IoError::io(out, e))
                }
            };
        }
    }
    let mut from = std::fs::File::open(src).map_err(|e| IoError::io(src, e))?;
    let mut to = AtomicFile::create(out)?;
    std::io::copy(&mut from, &mut to).map_err(|e| IoError::io(out, e))?;
    to.commit()?;
    Ok("copied")
}

/// The report of a job whose stitch is committed in `work`, as [`crate::pipeline::run`] gives
/// for a tiled run: the counts of the stitch and every tile's committed outcome summed (in tile
/// order, so the same for any task count). Times and threads are the caller's to fill in: the
/// tasks ran elsewhere (`wall_s`, `cpu_s`, `peak_rss_bytes` are 0, `phases` the kernel's summed
/// over the tiles).
///
/// # Errors
/// A work directory without a plan, a stitch not committed, a tile not committed.
pub fn summary(work: &WorkUrl) -> Result<Report, ScaleoutError> {
    let dir = work.local()?;
    let frozen = FrozenJob::load(dir)?;
    let s = committed_stitch(dir, &frozen).ok_or_else(|| ScaleoutError::NotReady {
        path: dir.to_path_buf(),
        phase: Phase::Stitch,
        detail: "a committed stitch for its report".into(),
    })?;
    let w = WorkDir::persistent(dir).map_err(|e| IoError::io(dir, e))?;
    let plan = &frozen.plan;
    let mut stats = Stats::default();
    let (mut growths, mut cell_runs, mut empty, mut result_bytes) = (0u64, 0u64, 0u64, 0u64);
    let mut narrower_runs = 0u64;
    for t in 0..plan.tiles.len() {
        let o = w.committed_tile(t).ok_or_else(|| ScaleoutError::NotReady {
            path: dir.to_path_buf(),
            phase: Phase::Stitch,
            detail: format!("tile {t} committed for its report"),
        })?;
        stats.merge(&o.stats);
        growths += u64::from(o.halo_growths);
        cell_runs += u64::from(o.cell_runs);
        narrower_runs += u64::from(o.narrower_runs);
        empty += u64::from(o.owned == 0);
        result_bytes += o.result_bytes;
    }
    stats.non_finite = plan.points - plan.finite;
    stats.points = plan.points;
    let kernel = std::mem::take(&mut stats.phases);
    let spill = w.committed_partition(plan).unwrap_or(0);
    let mut r = Report::empty(&frozen.job(dir), "tiled");
    r.normals = s.normals;
    r.points_in = plan.points;
    r.points_out = s.written;
    r.dropped_non_finite = s.dropped;
    r.outliers_found = s.found;
    r.tiles = plan.tiles.len() as u64;
    r.empty_tiles = empty;
    r.halo_growths = growths;
    r.cell_runs = cell_runs;
    r.narrower_runs = narrower_runs;
    r.bytes_spilled = spill + result_bytes;
    r.stats = stats;
    r.phases = kernel
        .into_iter()
        .map(|p| PhaseTiming {
            name: format!("tiles.{}", p.name),
            ..p
        })
        .collect();
    r.threads = 0;
    Ok(r)
}
