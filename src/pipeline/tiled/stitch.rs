//! Phase 6, **stitch**: the result files merge in global-index order while the input streams a
//! last time, so every attribute is copied from the input untouched; the output is assembled
//! by the same rules as in memory ([`crate::pipeline::assemble`]).

use super::outliers::Threshold;
use crate::io::{self, BATCH, SourceInfo};
use crate::pipeline::assemble::Assembler;
use crate::pipeline::normals::NormalsAction;
use crate::pipeline::stream::{sink_options, stream};
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::points::PointBatch;
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
    let mut merge =
        ResultMerge::open(work.path(), plan.tiles.len(), normals).map_err(tiling_err)?;
    let mut next: Option<TileResult> = merge.next_result().map_err(tiling_err)?;
    let mut out = PointBatch::with_capacity(info.schema.record_len, BATCH);
    let mut found = 0u64;
    let mut written = 0u64;
    let extras = stream(job, opts, |b| {
        out.clear(written);
        for i in 0..b.len() {
            let gi = b.start + i as u64;
            let (result, normal) = match next {
                Some(r) if r.index == gi => {
                    next = merge.next_result().map_err(tiling_err)?;
                    (Some((r.p, r.knn_mean)), r.normal)
                }
                _ => (None, None),
            };
            found += asm.push(b, i, result, normal, &mut out) as u64;
        }
        written += out.len() as u64;
        sink.write_batch(&out)?;
        Ok(())
    })?;
    sink.finish(&extras)?;
    Ok(Stitched {
        written,
        found,
        dropped,
        normals: asm.normals_action(),
    })
}
