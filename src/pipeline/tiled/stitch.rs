//! Phase 6, **stitch**: the result files merge in global-index order while the input streams a
//! last time, so every attribute is copied from the input untouched; the output is assembled
//! by the same rules as in memory ([`crate::pipeline::assemble`]).

use std::sync::mpsc::{Receiver, SyncSender};

use super::outliers::Threshold;
use crate::io::{self, BATCH, SourceInfo};
use crate::pipeline::assemble::Assembler;
use crate::pipeline::normals::NormalsAction;
use crate::pipeline::stream::{sink_options, stream};
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::points::PointBatch;
use crate::tiling::TilingError;
use crate::tiling::plan::Plan;
use crate::tiling::spill::{ResultMerge, TileResult};
use crate::tiling::workdir::WorkDir;

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

/// Writes `job`'s output from its input (described by `info`) and the results in `work`.
///
/// # Errors
/// Read and write failures, cancellation.
pub fn stitch(
    job: &Job,
    opts: &RunOptions,
    info: &SourceInfo,
    plan: &Plan,
    work: &WorkDir,
    threshold: &Threshold,
) -> Result<Stitched, PipelineError> {
    let tiling_err = |e| PipelineError::tiling(&job.input, e);
    let normals = job.spec.params.write_normals;
    let asm = Assembler::new(info, job.spec.outliers, threshold.value).writing_normals(normals);
    let (dropped, removed) = if asm.keep_non_finite {
        (0, 0)
    } else {
        (plan.points - plan.finite, threshold.removed)
    };
    let count = plan.points - dropped - removed;
    opts.progress.phase("stitch", plan.points);
    let mut sink = io::create_with(
        &job.output,
        job.output_format,
        info,
        count,
        &sink_options(job, opts),
    )?;
    let merge = ResultMerge::open(work.path(), plan.tiles.len(), normals).map_err(tiling_err)?;
    let mut out = PointBatch::with_capacity(info.schema.record_len, BATCH);
    let mut found = 0u64;
    let mut written = 0u64;
    // The merge runs on a thread of its own, a chunk ahead: it was half of the stitch, which is
    // serial in a scale-out job (docs/BENCHMARKS.md, issue 11).
    let extras = std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::sync_channel(AHEAD);
        scope.spawn(move || merge_ahead(merge, &tx));
        let mut results = Merged {
            rx,
            chunk: Vec::new().into_iter(),
            done: false,
        };
        let mut next: Option<TileResult> = results.next().map_err(tiling_err)?;
        stream(job, opts, |b| {
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
    sink.finish(&extras)?;
    Ok(Stitched {
        written,
        found,
        dropped,
        normals: asm.normals_action(),
    })
}
