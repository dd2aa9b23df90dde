//! Phase 2, **partition**: a second pass writes every processed point to its owner's spill file
//! and its halo copies to the other tiles', and counts the points per cell of the occupancy grid.
//! A work directory holding the same plan and a committed partition is reused as it is.

use super::plan::Limits;
use crate::pipeline::classes::Selection;
use crate::pipeline::stream::stream;
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::points::in_range;
use crate::tiling::TileBudget;
use crate::tiling::occupancy::Occupancy;
use crate::tiling::plan::Plan;
use crate::tiling::spill::{SpillWriter, TilePoint, spilled_points};
use crate::tiling::workdir::WorkDir;

/// Occupancy cells per isolation radius: fine enough that a cell beside a dense region is often
/// empty, coarse enough that a ball of the radius visits at most 10³ cells.
const CELLS_PER_RADIUS: f64 = 4.0;

/// The spill buffers hold at most 1 / `SPILL_SHARE` of the memory budget: no kernel runs during
/// the partition, and each buffer is written as one sorted run of blocks, so longer buffers give
/// halo growth smaller blocks to read ([`crate::tiling::spill`]).
const SPILL_SHARE: u64 = 4;

/// A committed partition.
#[derive(Debug, Clone)]
pub struct Partition {
    /// Bytes written to the spill files.
    pub bytes: u64,
    /// The occupancy grid (with an isolation radius; only the speed depends on it).
    pub occupancy: Option<Occupancy>,
    /// True when an earlier run's partition was reused.
    pub resumed: bool,
}

impl Partition {
    /// What a tile of this partition may rely on and spend.
    pub fn budget(&self, limits: &Limits) -> TileBudget<'_> {
        TileBudget {
            occupancy: self.occupancy.as_ref(),
            max_points: Some(limits.max_points),
        }
    }
}

/// Partitions `job`'s input by `plan` into `work` (or finds it committed there), then checks up
/// front that every tile's first load (its spill file, exactly) fits `limits`, so a run that
/// cannot fit says so before any tile work.
///
/// # Errors
/// Read and spill failures, cancellation, a tile over the budget.
pub fn partition(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    limits: &Limits,
    work: &WorkDir,
) -> Result<Partition, PipelineError> {
    let tiling_err = |e| PipelineError::tiling(&job.input, e);
    let partition = match work.committed_partition(plan) {
        Some(bytes) => Partition {
            bytes,
            // A missing grid proves nothing and costs halo growth.
            occupancy: work.occupancy(),
            resumed: true,
        },
        None => {
            work.begin_partition(plan)?;
            opts.progress.phase("partition", plan.points);
            let (bytes, occupancy) = spill(job, opts, plan, work)?;
            work.commit_partition(bytes, occupancy.as_ref())?;
            Partition {
                bytes,
                occupancy,
                resumed: false,
            }
        }
    };
    let budget = partition.budget(limits);
    for t in 0..plan.tiles.len() {
        let points = spilled_points(work.path(), t).map_err(tiling_err)?;
        budget
            .check_points(t, points, plan.tile_halo(t))
            .map_err(tiling_err)?;
    }
    Ok(partition)
}

/// The spill pass: returns the bytes spilled and the occupancy grid.
fn spill(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    work: &WorkDir,
) -> Result<(u64, Option<Occupancy>), PipelineError> {
    let tiling_err = |e| PipelineError::tiling(&job.input, e);
    let selection = Selection::of(job, crate::io::open(&job.input, job.input_format)?.info())?;
    let mut spill = SpillWriter::create(
        work.path(),
        plan.tiles.len(),
        &plan.bounds,
        opts.memory_budget / SPILL_SHARE,
    )
    .map_err(tiling_err)?;
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
            let mut point = TilePoint {
                index: b.start + j as u64,
                p,
                owned: true,
                held: selection.as_ref().is_some_and(|s| s.held(b.record(j))),
            };
            let owner = plan.owner(p);
            spill.push(owner, &point).map_err(tiling_err)?;
            point.owned = false;
            near.clear();
            plan.near_tiles(p, &mut near);
            for &t in near.iter().filter(|&&t| t != owner) {
                spill.push(t, &point).map_err(tiling_err)?;
            }
        }
        Ok(())
    })?;
    Ok((spill.finish().map_err(tiling_err)?, occupancy))
}
