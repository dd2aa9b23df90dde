//! Phase 3, **globals**: the scalars a method needs over the whole cloud (the bilateral σc, the
//! sensor noise), from exact partial sums over each tile's owned points, so they equal the
//! in-memory values bit for bit. Committed in the work directory.

use crate::denoise::cloud::{self, Globals, GlobalsPartial};
use crate::neighbours::with_cancel;
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::tiling::plan::Plan;
use crate::tiling::workdir::WorkDir;
use crate::tiling::{self, TileBudget};

/// The global scalars of `job` over the tiles of `plan` in `work` (zero when the method needs
/// none; the committed ones when there are).
///
/// # Errors
/// Spill read failures, halo limit, cancellation, write failures.
pub fn globals(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    work: &WorkDir,
    budget: &TileBudget,
) -> Result<Globals, PipelineError> {
    if !cloud::needs_globals(&job.spec.params) {
        return Ok(Globals::default());
    }
    if let Some(g) = work.committed_globals() {
        return Ok(g);
    }
    opts.progress.phase("globals", plan.tiles.len() as u64);
    let mut sum = GlobalsPartial::default();
    for t in 0..plan.tiles.len() {
        opts.check_cancel()?;
        sum.merge(&tile_partial(job, opts, plan, work, budget, t)?);
        opts.progress.advance(t as u64 + 1);
    }
    let g = sum.finish();
    work.commit_globals(&g)?;
    Ok(g)
}

/// The partial sums of tile `t` (one task of the phase).
///
/// # Errors
/// Spill read failures, halo limit, cancellation.
pub fn tile_partial(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    work: &WorkDir,
    budget: &TileBudget,
    t: usize,
) -> Result<GlobalsPartial, PipelineError> {
    with_cancel(&opts.cancel, || {
        tiling::globals_of_tile(work.path(), plan, budget, t, &job.spec.params)
    })
    .map_err(|e| PipelineError::tiling(&job.input, e))
}
