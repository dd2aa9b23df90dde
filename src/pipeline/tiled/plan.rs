//! Phase 1, **plan**: one streaming pass collects bounds, counts and a sample, and splits space
//! into tiles sized to the memory budget ([`crate::tiling::plan`]).

use glam::DVec3;

use crate::denoise::DenoiseError;
use crate::denoise::cloud;
use crate::io::SourceInfo;
use crate::neighbours::{NeighboursError, with_cancel};
use crate::pipeline::stream::stream;
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::tiling::plan::{Plan, Planner, SAMPLE};

/// What the memory budget allows one tile.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Points a tile targets (owned).
    pub target: u64,
    /// Most points (owned and halo) one kernel run may hold: a tile's first load, and each group
    /// of a grown halo ([`crate::tiling::growth`]).
    pub max_points: u64,
    /// Most cells of the occupancy grid ([`crate::tiling::plan::Plan::grid_cells`]).
    pub grid_cells: usize,
}

/// The share of the memory budget the occupancy grid may take (1/14: about a million cells at
/// 1 GiB, as many as the fixed cap allowed before).
const GRID_SHARE: u64 = 14;

impl Limits {
    /// The limits of `opts` at `per_point` working-set bytes per point
    /// ([`crate::pipeline::bytes_per_point`]). Everything the tiles phase holds at once is
    /// counted against the budget (the stated constant on top of it covers the binary, stacks
    /// and I/O buffers):
    ///
    /// ```text
    ///   budget ≥ grid cells × BYTES_PER_CELL                  the occupancy grid (≤ 1/14)
    ///          + target × size_of TileResult                  the tile's results so far
    ///          + max_points × (peak_per_point + size_of TilePoint)
    ///                                                         one kernel run, and the next
    ///                                                         tile's load read ahead
    /// ```
    ///
    /// A tile targets 40 % of the budget at `per_point` bytes, so a uniform cloud's first load
    /// (its core and a thin halo) fits a run.
    pub fn new(opts: &RunOptions, per_point: u64) -> Limits {
        use crate::tiling::occupancy::{BYTES_PER_CELL, MAX_CELLS, MIN_CELLS};
        use crate::tiling::spill::{TilePoint, TileResult};
        let budget = opts.memory_budget;
        let target = opts
            .tile_points
            .unwrap_or_else(|| (budget * 2 / (5 * per_point.max(1))).max(10_000));
        let grid_cells = usize::try_from(budget / GRID_SHARE / BYTES_PER_CELL)
            .unwrap_or(MAX_CELLS)
            .clamp(MIN_CELLS, MAX_CELLS);
        let grid = grid_cells as u64 * BYTES_PER_CELL;
        let results = target.saturating_mul(std::mem::size_of::<TileResult>() as u64);
        let run =
            crate::pipeline::peak_per_point(per_point) + std::mem::size_of::<TilePoint>() as u64;
        let max_points = budget.saturating_sub(grid).saturating_sub(results) / run.max(1);
        Limits {
            target,
            max_points,
            grid_cells,
        }
    }
}

/// Plans the tiles of `job`'s input within `limits`.
///
/// # Errors
/// Read failures, cancellation; no finite point, all points identical, fewer than k.
pub fn plan(
    job: &Job,
    opts: &RunOptions,
    info: &SourceInfo,
    limits: &Limits,
) -> Result<Plan, PipelineError> {
    opts.progress.phase("plan", info.len.unwrap_or(0));
    let mut planner = Planner::new(SAMPLE);
    stream(job, opts, |b| {
        for (j, p) in b.positions.iter().enumerate() {
            planner.add(b.start + j as u64, *p);
        }
        Ok(())
    })?;
    let refuse = |error| Err(PipelineError::denoise(&job.input, error));
    let finite = planner.finite();
    if finite == 0 {
        return refuse(DenoiseError::Empty);
    }
    if finite > 1 && planner.bounds().size() == DVec3::ZERO {
        return refuse(DenoiseError::AllIdentical(finite as usize));
    }
    let k = job.spec.params.k();
    if finite < k as u64 {
        return refuse(DenoiseError::Neighbours(NeighboursError::TooFewPoints {
            points: finite as usize,
            k,
        }));
    }
    let reach = cloud::reach(&job.spec.params);
    let mut plan = with_cancel(&opts.cancel, || {
        planner.finish_within(limits.target, limits.max_points, k, reach)
    })
    .map_err(|e| PipelineError::tiling(&job.input, e))?;
    // The in-memory run caps its lists the same way (`cloud::run_all`).
    (plan.isolation, plan.short_lists) =
        crate::denoise::isolation::cap(plan.isolation, job.spec.params.radius);
    plan.parts = parts(job, opts, &plan)?;
    plan.grid_cells = limits.grid_cells;
    Ok(plan)
}

/// Input records a partition part reads by default: a part under a second of reading would
/// cost more in files than it saves.
pub const PART_POINTS: u64 = 2_000_000;

/// Most spill files (parts × tiles) a partition makes: every tile read opens one per part.
const MAX_PART_FILES: u64 = 4096;

/// How many parts `plan`'s partition is cut into: [`RunOptions::part_points`] records each
/// (within [`MAX_PART_FILES`]), or one when the input cannot seek to a record.
///
/// # Errors
/// The input cannot be opened again.
fn parts(job: &Job, opts: &RunOptions, plan: &Plan) -> Result<u64, PipelineError> {
    let each = opts.part_points.unwrap_or(PART_POINTS).max(1);
    let most = (MAX_PART_FILES / plan.tiles.len().max(1) as u64).max(1);
    let parts = plan.points.div_ceil(each).clamp(1, most);
    if parts > 1 && !crate::io::open(&job.input, job.input_format)?.seek_point(0)? {
        return Ok(1);
    }
    Ok(parts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::denoise::Params;
    use crate::pipeline::{bytes_per_point, peak_per_point};
    use crate::tiling::occupancy::BYTES_PER_CELL;
    use crate::tiling::spill::{TilePoint, TileResult};

    /// Issue 16: what the tiles phase holds at once (the grid at its cap, a tile's results, one
    /// kernel run at its measured peak and the next tile read ahead) fits the budget, and a
    /// uniform cloud's first load (the target and a tenth of halo) fits a run, for both
    /// operators from 64 MiB to 16 GiB. Before, a `--paper` run could hold 60 % of the budget at
    /// the estimate, 87 % at its real peak, and the 100 M cluttered scene peaked at 1 203 MiB
    /// under 1 GiB.
    #[test]
    fn issue16_what_a_tile_holds_fits_the_budget() {
        for params in [Params::default(), Params::paper()] {
            for record in [12, 24, 34] {
                let per_point = bytes_per_point(&params, record);
                for mib in [64u64, 200, 1024, 16 << 10] {
                    let opts = RunOptions {
                        memory_budget: mib << 20,
                        ..RunOptions::default()
                    };
                    let l = Limits::new(&opts, per_point);
                    let held = l.grid_cells as u64 * BYTES_PER_CELL
                        + l.target * std::mem::size_of::<TileResult>() as u64
                        + l.max_points
                            * (peak_per_point(per_point) + std::mem::size_of::<TilePoint>() as u64);
                    assert!(held <= opts.memory_budget, "{mib} MiB: {held} B");
                    assert!(l.grid_cells as u64 * BYTES_PER_CELL <= opts.memory_budget / 14);
                    assert!(
                        l.max_points >= l.target * 11 / 10,
                        "{mib} MiB, {per_point} B a point: {l:?}"
                    );
                }
            }
        }
    }
}
