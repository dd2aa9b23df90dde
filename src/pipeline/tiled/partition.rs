//! Phase 2, **partition**: a second pass writes every processed point to its owner's spill file
//! and its halo copies to the other tiles', and counts the points per cell of the occupancy grid.
//! The pass is cut into parts, ranges of input records ([`crate::tiling::plan::Plan::part_range`]),
//! each written and committed on its own ([`write_part`]): side by side here, as tasks of a
//! scale-out job. A work directory holding the same plan keeps its committed parts, and a
//! committed partition is reused as it is.

use std::sync::atomic::{AtomicU64, Ordering};

use rayon::prelude::*;

use super::plan::Limits;
use crate::io::IoError;
use crate::pipeline::classes::Selection;
use crate::pipeline::stream::{stream, stream_range};
use crate::pipeline::{Job, PipelineError, RunOptions};
use crate::points::PointBatch;
use crate::points::in_range;
use crate::tiling::occupancy::Occupancy;
use crate::tiling::plan::Plan;
use crate::tiling::spill::{SpillWriter, TilePoint, spilled_points};
use crate::tiling::workdir::{PartDone, WorkDir};
use crate::tiling::{TileBudget, TilingError};

/// Occupancy cells per isolation radius: fine enough that a cell beside a dense region is often
/// empty, coarse enough that a ball of the radius visits at most 10³ cells.
const CELLS_PER_RADIUS: f64 = 4.0;

/// The spill buffers hold at most 1 / `SPILL_SHARE` of the memory budget: no kernel runs during
/// the partition, and each buffer is written as one sorted run of blocks, so longer buffers give
/// halo growth smaller blocks to read ([`crate::tiling::spill`]).
pub const SPILL_SHARE: u64 = 4;

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

/// Partitions `job`'s input by `plan` into `work` (or finds it committed there): its parts not
/// committed yet run side by side on the thread pool, then the partition is committed. Then
/// checks up front that every tile's first load (its spill files, exactly) fits `limits`, so a
/// run that cannot fit says so before any tile work.
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
            let todo: Vec<u64> = (0..plan.parts())
                .filter(|&p| work.committed_part(p).is_none())
                .collect();
            let side_by_side = todo.len().clamp(1, rayon::current_num_threads()) as u64;
            let memory = opts.memory_budget / SPILL_SHARE / side_by_side;
            let read = AtomicU64::new(0);
            todo.par_iter().try_for_each(|&part| {
                write_part(job, opts, plan, work, part, memory, &read).map(|_| ())
            })?;
            let bytes = work.commit_parts(plan)?.ok_or_else(|| {
                tiling_err(TilingError::Corrupt {
                    path: work.path().to_path_buf(),
                    detail: "a partition part vanished before the partition was committed".into(),
                })
            })?;
            Partition {
                bytes,
                occupancy: work.occupancy(),
                resumed: false,
            }
        }
    };
    let budget = partition.budget(limits);
    for t in 0..plan.tiles.len() {
        let points = spilled_points(work.path(), plan.parts(), t).map_err(tiling_err)?;
        budget
            .check_points(t, points, plan.tile_halo(t))
            .map_err(tiling_err)?;
    }
    Ok(partition)
}

/// Writes and commits part `part` of the partition (one task of the phase; the caller is the
/// part's only writer), with `memory` bytes of spill buffers; `read` counts the points read
/// by every part, for progress. Returns the bytes spilled.
///
/// # Errors
/// Read and spill failures, cancellation, an input that can no longer seek to the part.
pub fn write_part(
    job: &Job,
    opts: &RunOptions,
    plan: &Plan,
    work: &WorkDir,
    part: u64,
    memory: u64,
    read: &AtomicU64,
) -> Result<u64, PipelineError> {
    let tiling_err = |e| PipelineError::tiling(&job.input, e);
    let dir = work.begin_part(part)?;
    let selection = Selection::of(job, crate::io::open(&job.input, job.input_format)?.info())?;
    let mut spill =
        SpillWriter::create(&dir, plan.tiles.len(), &plan.bounds, memory).map_err(tiling_err)?;
    let mut near = Vec::new();
    let mut occupancy = plan
        .isolation
        .map(|r| Occupancy::new(r / CELLS_PER_RADIUS, plan.origin, plan.grid_cells));
    let each = |b: &PointBatch| {
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
        let n = b.len() as u64;
        opts.progress
            .advance(read.fetch_add(n, Ordering::Relaxed) + n);
        Ok(())
    };
    if plan.parts() == 1 {
        stream(job, opts, each)?;
    } else {
        let range = plan.part_range(part);
        if !stream_range(job, opts, range.clone(), each)? {
            return Err(PipelineError::from(IoError::invalid(
                &job.input,
                format!(
                    "cannot seek to record {}, where partition part {part} of the plan starts",
                    range.start
                ),
            )));
        }
    }
    let bytes = spill.finish().map_err(tiling_err)?;
    work.commit_part(part, PartDone { bytes }, occupancy.as_ref())?;
    Ok(bytes)
}
