//! Phase 4, **tiles**: each tile runs the operator with a halo large enough for every owned
//! result to be exact and commits its result file and outcome ([`crate::tiling::process_tile`]).
//! Tiles committed by an earlier, interrupted run are taken as they are. The next tile's spill
//! file is read on a helper thread while the current one computes.

use crate::denoise::Stats;
use crate::denoise::cloud::Globals;
use crate::geometry::ExactSum;
use crate::neighbours::with_cancel;
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::tiling::plan::Plan;
use crate::tiling::spill::TilePoint;
use crate::tiling::workdir::WorkDir;
use crate::tiling::{self, TileBudget, TileOutcome};

/// The tiles of a run, summed.
#[derive(Debug, Clone, Default)]
pub struct Tiles {
    /// Counters of all processed points (`points` and `non_finite` over the whole input).
    pub stats: Stats,
    /// The kernel's phase timings inside the tiles.
    pub kernel: Stats,
    /// Exact sums of the k-NN mean distance and its square (the outlier statistic).
    pub knn_mean: (ExactSum, ExactSum),
    /// Halo growths.
    pub halo_growths: u64,
    /// Kernel runs on the cells of lone points' dependencies.
    pub cell_runs: u64,
    /// Kernel runs of growth groups at a narrower halo than their round's.
    pub narrower_runs: u64,
    /// Tiles that owned no point.
    pub empty: u64,
    /// Tiles taken from an earlier run's checkpoints.
    pub resumed: u64,
    /// Bytes of the result files.
    pub result_bytes: u64,
}

impl Tiles {
    /// Adds one tile's outcome.
    fn book(&mut self, o: &TileOutcome) {
        self.stats.merge(&o.stats);
        self.knn_mean.0.merge(&o.knn_mean.0);
        self.knn_mean.1.merge(&o.knn_mean.1);
        self.halo_growths += o.halo_growths as u64;
        self.cell_runs += u64::from(o.cell_runs);
        self.narrower_runs += u64::from(o.narrower_runs);
        self.empty += (o.owned == 0) as u64;
        self.result_bytes += o.result_bytes;
    }
}

/// Processes and commits tile `t` (one task of the phase); `preloaded` is its spill file when
/// the caller read it ahead ([`tiling::load_tile`]).
///
/// # Errors
/// Spill read failures, operator errors, halo limit, cancellation, write failures.
pub fn tile(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    work: &WorkDir,
    (budget, globals): (&TileBudget, &Globals),
    t: usize,
    preloaded: Option<Vec<TilePoint>>,
) -> Result<TileOutcome, PipelineError> {
    let o = with_cancel(&opts.cancel, || {
        tiling::process_tile(
            work.path(),
            plan,
            budget,
            t,
            &job.spec.params,
            globals,
            preloaded,
        )
    })
    .map_err(|e| PipelineError::tiling(&job.input, e))?;
    // The outcome is saved after the result file: a tile counts as finished only with both.
    work.commit_tile(t, &o)?;
    Ok(o)
}

/// Processes every tile of `plan` in `work` not yet committed there, and sums all outcomes.
///
/// # Errors
/// As [`tile`].
pub fn tiles(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    work: &WorkDir,
    budget: &TileBudget,
    globals: &Globals,
) -> Result<Tiles, PipelineError> {
    let tiling_err = |e| PipelineError::tiling(&job.input, e);
    opts.progress.phase("tiles", plan.tiles.len() as u64);
    let mut sum = Tiles::default();
    let mut todo = Vec::new();
    for t in 0..plan.tiles.len() {
        match work.committed_tile(t) {
            Some(o) => {
                sum.resumed += 1;
                sum.book(&o);
            }
            None => todo.push(t),
        }
    }
    opts.progress.advance(sum.resumed);
    let mut ahead = match todo.first() {
        Some(&t) => Some(tiling::load_tile(work.path(), plan, t).map_err(tiling_err)?),
        None => None,
    };
    for (i, &t) in todo.iter().enumerate() {
        opts.check_cancel()?;
        let pts = ahead.take();
        let following = todo.get(i + 1).copied();
        let (o, next) = std::thread::scope(|s| {
            let path = work.path();
            let reader = following.map(|n| s.spawn(move || tiling::load_tile(path, plan, n)));
            let o = tile(job, opts, plan, work, (budget, globals), t, pts);
            let next = reader.map(|h| h.join().expect("the spill reader does not panic"));
            (o, next)
        });
        let o = o?;
        ahead = next.transpose().map_err(tiling_err)?;
        sum.book(&o);
        opts.progress.advance(sum.resumed + i as u64 + 1);
    }
    sum.stats.non_finite = plan.points - plan.finite;
    sum.stats.points = plan.points;
    sum.kernel.phases = std::mem::take(&mut sum.stats.phases);
    Ok(sum)
}
