//! Phase 6, **stitch**: the result files merge in global-index order while the input streams a
//! last time, so every attribute is copied from the input untouched; the output is assembled
//! by the same rules as in memory ([`crate::pipeline::assemble`]). With a plan in parts, the
//! parts' record ranges are stitched side by side into bodies that the output takes in order.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender};

use rayon::prelude::*;

use super::outliers::Threshold;
use crate::io::{
    self, AtomicFile, BATCH, BodyStats, Extras, Format, IoError, Sink, SinkOptions, Source,
    SourceInfo,
};
use crate::pipeline::assemble::Assembler;
use crate::pipeline::normals::NormalsAction;
use crate::pipeline::stream::{sink_options, stream, stream_range};
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::points::PointBatch;
use crate::tiling::TilingError;
use crate::tiling::plan::Plan;
use crate::tiling::spill::{ResultMerge, TileResult};
use crate::tiling::workdir::{WorkDir, body_path};

/// What the stitch wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stitched {
    /// Points written.
    pub written: u64,
    /// Points flagged or removed as outliers.
    pub found: u64,
    /// Unprocessed points dropped (0 for organized clouds, which keep them).
    pub dropped: u64,
    /// What happened to stored normals.
    pub normals: NormalsAction,
}

/// Results per chunk the merging thread hands over.
const CHUNK: usize = 1 << 14;
/// Chunks the merging thread may be ahead.
const AHEAD: usize = 4;

/// A chunk of merged results, or the merge's error; a chunk shorter than [`CHUNK`] is the last.
type Chunk = Result<Vec<TileResult>, TilingError>;

/// Sends `merge`'s results in chunks until they end, an error, or the receiver is gone.
fn merge_ahead(mut merge: ResultMerge, tx: &SyncSender<Chunk>) {
    loop {
        let mut chunk = Vec::with_capacity(CHUNK);
        let mut filled = || -> Result<(), TilingError> {
            while chunk.len() < CHUNK {
                match merge.next_result()? {
                    Some(r) => chunk.push(r),
                    None => break,
                }
            }
            Ok(())
        };
        let sent = match filled() {
            Ok(()) => {
                let last = chunk.len() < CHUNK;
                tx.send(Ok(chunk)).is_ok() && !last
            }
            Err(e) => {
                let _ = tx.send(Err(e));
                false
            }
        };
        if !sent {
            return;
        }
    }
}

/// The receiving end of [`merge_ahead`]: its results one by one.
struct Merged {
    rx: Receiver<Chunk>,
    chunk: std::vec::IntoIter<TileResult>,
    done: bool,
}

impl Merged {
    fn next(&mut self) -> Result<Option<TileResult>, TilingError> {
        loop {
            if let Some(r) = self.chunk.next() {
                return Ok(Some(r));
            }
            if self.done {
                return Ok(None);
            }
            let chunk = self.rx.recv().map_err(|_| TilingError::Corrupt {
                path: std::path::PathBuf::new(),
                detail: "the result merge stopped before its end".into(),
            })??;
            self.done = chunk.len() < CHUNK;
            self.chunk = chunk.into_iter();
        }
    }
}

/// What a stitch reads: the job, its input's description, the plan, the results in `work`,
/// and the outliers' threshold.
#[derive(Clone, Copy)]
pub struct Stitch<'a> {
    /// The job (its output is what the stitch writes).
    pub job: &'a Job,
    /// Progress and cancellation.
    pub opts: &'a RunOptions,
    /// The input's description.
    pub info: &'a SourceInfo,
    /// The plan.
    pub plan: &'a Plan,
    /// The work directory holding the tiles' results.
    pub work: &'a WorkDir,
    /// The outliers' threshold.
    pub threshold: &'a Threshold,
}

impl Stitch<'_> {
    /// Writes the job's output from its input and the results.
    ///
    /// With a plan in several parts and an output that can take bodies ([`Sink::splittable`]),
    /// the parts' record ranges are written side by side on the pool, each into a body of its
    /// own ([`Stitch::write_body`], in a scratch directory inside the work directory), which the
    /// output then takes in order; the bytes are those of one pass.
    ///
    /// # Errors
    /// Read and write failures, cancellation.
    pub fn run(&self) -> Result<Stitched, PipelineError> {
        let (job, plan, work) = (self.job, self.plan, self.work);
        self.opts.progress.phase("stitch", plan.points);
        let mut out = self.output()?;
        if by_ranges(plan, out.sink.as_ref()) > 1 {
            let scratch = tempfile::Builder::new()
                .prefix(".stitch.")
                .tempdir_in(work.path())
                .map_err(|e| IoError::io(work.path(), e))?;
            let read = AtomicU64::new(0);
            let bodies = (0..plan.parts())
                .into_par_iter()
                .map(|r| {
                    let path = body_path(scratch.path(), r);
                    self.write_body(r, &path, &read).map(|b| (path, b))
                })
                .collect::<Result<Vec<_>, _>>()?;
            return self.append(out, &bodies);
        }
        let merge = ResultMerge::open(work.path(), plan.tiles.len(), job.spec.params.write_normals)
            .map_err(|e| PipelineError::tiling(&job.input, e))?;
        let (extras, found, written) =
            merge_into(job, self.info, &out.asm, merge, out.sink.as_mut(), |f| {
                stream(job, self.opts, f)
            })?;
        let stitched = out.stitched(found, written);
        out.sink.finish(&extras)?;
        Ok(stitched)
    }

    /// Writes the job's output from the `bodies` of its stitch ranges, in range order (written
    /// by [`Stitch::write_body`], perhaps by other tasks).
    ///
    /// # Errors
    /// Read and write failures, cancellation; an output that cannot take bodies.
    pub fn assemble(&self, bodies: &[(PathBuf, Body)]) -> Result<Stitched, PipelineError> {
        self.opts.progress.phase("stitch", self.plan.points);
        self.append(self.output()?, bodies)
    }

    /// The assembler of the job's output.
    fn assembler(&self) -> Assembler {
        Assembler::new(self.info, self.job.spec.outliers, self.threshold.value)
            .writing_normals(self.job.spec.params.write_normals)
    }

    /// Creates the whole output's sink.
    fn output(&self) -> Result<Output, PipelineError> {
        let (job, plan) = (self.job, self.plan);
        let asm = self.assembler();
        let (dropped, removed) = if asm.keep_non_finite {
            (0, 0)
        } else {
            (plan.points - plan.finite, self.threshold.removed)
        };
        let sink = io::create_with(
            &job.output,
            job.output_format,
            self.info,
            plan.points - dropped - removed,
            &sink_options(job, self.opts),
        )?;
        Ok(Output { sink, asm, dropped })
    }

    /// Appends `bodies` to `out` in order, then what follows the input's points, and finishes.
    fn append(
        &self,
        mut out: Output,
        bodies: &[(PathBuf, Body)],
    ) -> Result<Stitched, PipelineError> {
        let (mut found, mut written) = (0, 0);
        for (path, b) in bodies {
            self.opts.check_cancel()?;
            out.sink.append_body(path, &b.stats)?;
            found += b.found;
            written += b.stats.points;
        }
        let stitched = out.stitched(found, written);
        out.sink.finish(&trailer(self.job, self.plan)?)?;
        Ok(stitched)
    }

    /// Writes the body of stitch range `r` (the records of [`Plan::part_range`]`(r)`, as the
    /// output holds them) to `path`, atomically; read counts are added to `read` for progress.
    ///
    /// # Errors
    /// Read and write failures, cancellation, an input that cannot seek to the range.
    pub fn write_body(&self, r: u64, path: &Path, read: &AtomicU64) -> Result<Body, PipelineError> {
        let (job, opts, info) = (self.job, self.opts, self.info);
        let asm = self.assembler();
        let range = self.plan.part_range(r);
        let merge = ResultMerge::open_range(
            self.work.path(),
            self.plan.tiles.len(),
            job.spec.params.write_normals,
            r,
            range.clone(),
        )
        .map_err(|e| PipelineError::tiling(&job.input, e))?;
        // The format the whole output's sink resolved (its extension, else the input's).
        let format = job
            .output_format
            .or_else(|| Format::from_path(&job.output).ok())
            .unwrap_or(info.format);
        let options = SinkOptions {
            body: true,
            ..sink_options(job, opts)
        };
        let mut sink = io::create_in(AtomicFile::create(path)?, format, info, 0, &options)?;
        let ((), found, _) = merge_into(job, info, &asm, merge, sink.as_mut(), |f| {
            let seeked = stream_range(job, opts, range.clone(), |b| {
                f(b)?;
                let n = b.len() as u64;
                opts.progress
                    .advance(read.fetch_add(n, Ordering::Relaxed) + n);
                Ok(())
            })?;
            if seeked {
                Ok(())
            } else {
                Err(PipelineError::from(IoError::invalid(
                    &job.input,
                    format!(
                        "cannot seek to record {}, where stitch range {r} starts",
                        range.start
                    ),
                )))
            }
        })?;
        let stats = sink.finish_body()?;
        Ok(Body { stats, found })
    }
}

/// The stitch ranges of `plan` for a sink like `sink`: its parts when the output can take
/// bodies, else one.
fn by_ranges(plan: &Plan, sink: &dyn Sink) -> u64 {
    if plan.parts() > 1 && sink.splittable() {
        plan.parts()
    } else {
        1
    }
}

/// The stitch ranges of `plan` for `job`'s output in `format` ([`Stitch::run`]'s choice, made
/// without writing anything): what a scale-out job plans as stitch tasks.
///
/// # Errors
/// An output that cannot be created like the input (an option its format cannot carry).
pub fn ranges(
    job: &Job,
    opts: &RunOptions,
    info: &SourceInfo,
    plan: &Plan,
    format: Format,
) -> Result<u64, PipelineError> {
    if plan.parts() <= 1 {
        return Ok(1);
    }
    let (probe, _) = AtomicFile::memory(&job.input);
    Ok(
        match io::create_in(probe, format, info, 0, &sink_options(job, opts)) {
            Ok(sink) => by_ranges(plan, sink.as_ref()),
            // E57 and COPC write a file of their own: one range.
            Err(IoError::Unsupported { .. }) => 1,
            Err(e) => return Err(e.into()),
        },
    )
}

/// The whole output's sink and what it is written with.
struct Output {
    sink: Box<dyn Sink>,
    asm: Assembler,
    dropped: u64,
}

impl Output {
    fn stitched(&self, found: u64, written: u64) -> Stitched {
        Stitched {
            written,
            found,
            dropped: self.dropped,
            normals: self.asm.normals_action(),
        }
    }
}

/// What a stitch range's body holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Body {
    /// Its points, and what the output's header needs of them.
    pub stats: BodyStats,
    /// Points of the range flagged or removed as outliers.
    pub found: u64,
}

/// What follows the input's points ([`Source::finish`] after its last record), for the output's
/// trailer when the points were read in ranges.
fn trailer(job: &Job, plan: &Plan) -> Result<Extras, PipelineError> {
    let mut src: Box<dyn Source> = io::open(&job.input, job.input_format)?;
    if !src.seek_point(plan.points)? {
        return Err(PipelineError::from(IoError::invalid(
            &job.input,
            "cannot seek past its last record to read what follows the points",
        )));
    }
    Ok(src.finish()?)
}

/// Feeds `sink` the points `feed` streams (it calls its argument on each input batch), each with
/// its result from `merge` (on a thread of its own, a chunk ahead), assembled by `asm` (records
/// of `info`). Returns
/// what `feed` returned, the outliers found and the points written.
fn merge_into<T>(
    job: &Job,
    info: &SourceInfo,
    asm: &Assembler,
    merge: ResultMerge,
    sink: &mut dyn Sink,
    feed: impl FnOnce(
        &mut dyn FnMut(&PointBatch) -> Result<(), PipelineError>,
    ) -> Result<T, PipelineError>,
) -> Result<(T, u64, u64), PipelineError> {
    let tiling_err = |e| PipelineError::tiling(&job.input, e);
    let mut out = PointBatch::with_capacity(info.schema.record_len, BATCH);
    let mut found = 0u64;
    let mut written = 0u64;
    // The merge runs on a thread of its own, a chunk ahead: it was half of the stitch, which is
    // serial in a scale-out job (docs/BENCHMARKS.md, issue 11).
    let fed = std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::sync_channel(AHEAD);
        scope.spawn(move || merge_ahead(merge, &tx));
        let mut results = Merged {
            rx,
            chunk: Vec::new().into_iter(),
            done: false,
        };
        let mut next: Option<TileResult> = results.next().map_err(tiling_err)?;
        feed(&mut |b: &PointBatch| {
            out.clear(written);
            for i in 0..b.len() {
                let gi = b.start + i as u64;
                let (result, normal) = match next {
                    Some(r) if r.index == gi => {
                        next = results.next().map_err(tiling_err)?;
                        (Some((r.p, r.knn_mean)), r.normal)
                    }
                    _ => (None, None),
                };
                found += asm.push(b, i, result, normal, &mut out) as u64;
            }
            written += out.len() as u64;
            sink.write_batch(&out)?;
            Ok(())
        })
        // `results` (the receiver) drops here, so a merge still sending stops.
    })?;
    Ok((fed, found, written))
}
