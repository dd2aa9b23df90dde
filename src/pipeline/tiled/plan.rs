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
}

impl Limits {
    /// The limits of `opts` at `per_point` working-set bytes per point
    /// ([`crate::pipeline::bytes_per_point`]).
    pub fn new(opts: &RunOptions, per_point: u64) -> Limits {
        let budget = opts.memory_budget;
        // A tile's working set plus the next tile read ahead, the planning sample and I/O
        // buffers must fit the budget: a tile targets 40 % of it.
        let target = opts
            .tile_points
            .unwrap_or_else(|| (budget * 2 / (5 * per_point)).max(10_000));
        // One tile may run on as many points (owned and halo) as 60 % of the budget holds at
        // `per_point` bytes (the rest holds allocator slack and transient copies, the read-ahead
        // tile, the occupancy grid, the sample and I/O buffers); the tile target is 40 %, so a
        // uniform cloud's halo fits.
        let max_points = budget / 5 * 3 / per_point.max(1);
        Limits { target, max_points }
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
