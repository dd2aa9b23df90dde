//! Out-of-core processing: plan, partition into tiles with a halo, process each tile exactly,
//! merge the results back in the original order.
//!
//! # Brief overview
//!
//! 1. **Plan** ([`plan::Planner`]): one streaming pass collects bounds, counts and a
//!    deterministic sample, and splits space into tiles by point count (a k-d split). Each tile
//!    gets a halo: the cloud's, or narrower where that would load more than the budget allows
//!    one run (a dense cluster next to the tile).
//! 2. **Partition** ([`spill::SpillWriter`]): a second pass writes every finite point, with its
//!    global index, to the spill file of the tile that owns it, and a halo copy to every other
//!    tile whose box grown by its halo contains it; each buffer of owned records goes out in
//!    Morton order, in blocks whose boxes a table beside the file keeps ([`spill`]).
//! 3. **Process** ([`process_tile`]): each tile loads its points and runs
//!    [`crate::denoise::cloud::run`] on them with the tile's region. A result is kept only when
//!    it is provably the whole-cloud result (every k-NN ball it depends on lies inside the
//!    region, see [`crate::denoise::cloud`]); the owned points that are not are redone in small
//!    groups with a doubled halo, each group loading only the cells near its own points from the
//!    blocks of the neighbouring spill files that meet them, and never more than the budget
//!    allows ([`growth`], [`shell`]).
//!    Finished tiles write a result file sorted by global index, atomically: these are the
//!    checkpoints a resumed job skips.
//! 4. **Stitch** ([`spill::ResultMerge`]): the result files merge in global-index order while
//!    the input streams a third time, so every attribute is copied from the input untouched.
//!
//! Every file of a run lives in its work directory ([`workdir`]), which names them and says
//! which phases are committed (what a resumed run skips).
//!
//! With ties broken by global index, sums in a fixed order and Jacobi passes, the tiled output is
//! bit-identical to the in-memory output for any tile size.

pub mod fine;
pub mod growth;
pub mod occupancy;
pub mod plan;
pub mod shell;
pub mod spill;
pub mod workdir;

use std::path::{Path, PathBuf};

use glam::DVec3;
use thiserror::Error;

use crate::denoise::cloud::{self, Globals, GlobalsPartial};
use crate::denoise::{DenoiseError, Params, Stats, structure};
use crate::geometry::ExactSum;
use crate::io::IoError;
use occupancy::Occupancy;
use plan::Plan;
use spill::{TilePoint, TileResult, read_spill, write_results};

/// Errors of the tiled path.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum TilingError {
    /// A temporary file could not be read or written.
    #[error("{path}: {error}", path = .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        error: std::io::Error,
    },
    /// A temporary file has an impossible length (disk trouble, or a foreign file).
    #[error("{path}: corrupt temporary file: {detail}", path = .path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// A result file could not be committed.
    #[error(transparent)]
    Result(Box<IoError>),
    /// The operator failed on a tile.
    #[error("tile {tile}: {error}")]
    Denoise {
        /// The tile.
        tile: usize,
        /// The operator's error.
        error: DenoiseError,
    },
    /// A tile's halo kept growing without making its results exact.
    #[error("tile {tile}: results still not exact with a halo of {halo} (cloud too sparse?)")]
    HaloLimit {
        /// The tile.
        tile: usize,
        /// The last halo tried.
        halo: f64,
    },
    /// Holding a tile exactly needs more points in memory than the budget allows.
    #[error(
        "tile {tile}: an exact result needs up to {points} points in memory (halo {halo:.4}), \
         more than the memory budget allows ({max}); raise --memory-budget"
    )]
    Budget {
        /// The tile.
        tile: usize,
        /// Points the tile would load (an upper bound from the occupancy grid).
        points: u64,
        /// Points the budget allows one tile.
        max: u64,
        /// The halo it would load them for.
        halo: f64,
    },
    /// One point's exact result needs more points in memory than the budget allows one run.
    #[error(
        "tile {tile}: the exact result of point {index} needs more than {max} points in memory \
         (halo {halo:.4}; {found} found), more than the memory budget allows; raise --memory-budget"
    )]
    PointBudget {
        /// The tile.
        tile: usize,
        /// The point's global index.
        index: u64,
        /// Points found in its box before the read stopped.
        found: u64,
        /// Points the budget allows one run.
        max: u64,
        /// The halo it needed.
        halo: f64,
    },
    /// The cancellation flag installed with [`crate::neighbours::with_cancel`] was set.
    #[error("cancelled")]
    Cancelled,
}

/// How a tile went (saved beside its result file as part of the checkpoint).
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct TileOutcome {
    /// Points owned.
    pub owned: u64,
    /// Points loaded (owned + halo) in the final attempt.
    pub loaded: u64,
    /// Times the halo had to grow.
    pub halo_growths: u32,
    /// The halo that made every owned result exact.
    pub halo: f64,
    /// Kernel runs on the cells the dependencies of lone points reach (points whose halo
    /// alone would hold more than the budget).
    #[serde(default)]
    pub cell_runs: u32,
    /// Kernel runs of growth groups at a narrower halo than their round's (groups whose shell
    /// at the round's halo held more than the budget).
    #[serde(default)]
    pub narrower_runs: u32,
    /// Bytes of the result file.
    pub result_bytes: u64,
    /// Counters of the owned points and phase timings.
    pub stats: Stats,
    /// Exact sums of the owned points' k-NN mean distance and its square (outlier statistics).
    pub knn_mean: (ExactSum, ExactSum),
}

/// What a tile may rely on and spend beyond its plan: the occupancy grid of the partition pass
/// (which proves balls complete and bounds what a halo loads) and the points one tile may hold.
#[derive(Debug, Clone, Copy, Default)]
pub struct TileBudget<'a> {
    /// The partition pass's grid, when there is one.
    pub occupancy: Option<&'a Occupancy>,
    /// Most points one kernel run may hold (a tile's first load, and every group of a grown
    /// halo, [`growth`]); `None` for no limit.
    pub max_points: Option<u64>,
}

impl TileBudget<'_> {
    /// [`TilingError::Budget`] when tile `t`'s first load holds more than
    /// [`TileBudget::max_points`].
    ///
    /// # Errors
    /// As said.
    pub fn check_points(&self, t: usize, points: u64, halo: f64) -> Result<(), TilingError> {
        match self.max_points {
            Some(max) if points > max => Err(TilingError::Budget {
                tile: t,
                points,
                max,
                halo,
            }),
            _ => Ok(()),
        }
    }
}

/// Loads the points of tile `t` for the plan's halo: its spill file (owned points plus halo
/// copies). Callers may run this ahead of [`process_tile`] to overlap reading with computing.
///
/// # Errors
/// Spill read failures.
pub fn load_tile(dir: &Path, plan: &Plan, t: usize) -> Result<Vec<TilePoint>, TilingError> {
    let mut pts = Vec::new();
    read_spill(dir, plan.parts(), t, |_, _, _| true, &mut pts)?;
    Ok(pts)
}

/// The exact partials behind [`Globals`] over tile `t`'s owned points (the pre-pass), from a
/// first load narrowed to [`globals_halo`].
///
/// # Errors
/// Spill read failures, too few points, halo limit.
pub fn globals_of_tile(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    t: usize,
    params: &Params,
) -> Result<GlobalsPartial, TilingError> {
    globals_of_tile_from(dir, plan, budget, (t, globals_halo(plan)), params).map(|(sum, _)| sum)
}

/// [`globals_of_tile`] with the first load narrowed to `narrow` (the tile's own halo when
/// `None`), and how the halo grew.
///
/// # Errors
/// As [`globals_of_tile`].
pub fn globals_of_tile_from(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    (t, narrow): (usize, Option<f64>),
    params: &Params,
) -> Result<(GlobalsPartial, growth::Growth), TilingError> {
    growth::with_exact_halo(
        dir,
        plan,
        budget,
        t,
        (0, structure::NEAR),
        (None, narrow),
        |sum: &mut GlobalsPartial, part| sum.merge(&part),
        |pts, run| {
            // Only the exact owned contributions are summed: the others are redone with a larger
            // halo.
            cloud::globals_partial(run, params, plan.finite, |i, exact| pts[i].owned && exact)
                .map_err(|e| TilingError::Denoise { tile: t, error: e })
        },
    )
}

/// The first load of the globals' pre-pass: [`GLOBALS_HALO`] typical k-NN radii (the plan's
/// isolation radius over [`crate::denoise::isolation::ISOLATION`]) instead of the operator's
/// halo of about 12, as its lists of [`structure::NEAR`] reach about 0.7 of one on a surface.
/// Points whose list reaches past it are redone by the growth rounds, and the result does not
/// depend on it. `None` (the tile's own halo) under the user's `--radius`, which says nothing of
/// the typical radius.
pub fn globals_halo(plan: &Plan) -> Option<f64> {
    plan.isolation
        .filter(|_| !plan.short_lists)
        .map(|r| GLOBALS_HALO * r / crate::denoise::isolation::ISOLATION)
}

/// Typical k-NN radii of the globals' first load ([`globals_halo`]).
const GLOBALS_HALO: f64 = 3.0;

/// Processes tile `t`: runs the operator with a halo large enough for every owned result to be
/// exact and writes the owned results to the tile's result file. `preloaded` is the tile's
/// [`load_tile`] result when the caller read it ahead.
///
/// # Errors
/// Spill read failures, operator errors, halo limit, result write failures.
pub fn process_tile(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    t: usize,
    params: &Params,
    globals: &Globals,
    preloaded: Option<Vec<TilePoint>>,
) -> Result<TileOutcome, TilingError> {
    let hops = cloud::reach(params);
    let ((parts, stats, knn_mean), growth) = growth::with_exact_halo(
        dir,
        plan,
        budget,
        t,
        (hops, params.k()),
        (preloaded, None),
        |sum: &mut Owned, part: Owned| {
            // A vector per run: one growing vector would hold up to twice its length in
            // capacity while the next kernel runs.
            sum.0.extend(part.0);
            sum.1.merge(&part.1);
            sum.2.0.merge(&part.2.0);
            sum.2.1.merge(&part.2.1);
        },
        |pts, run| {
            let r = cloud::run(run, params, globals)
                .map_err(|e| TilingError::Denoise { tile: t, error: e })?;
            let keep = |i: usize| pts[i].owned && r.exact[i];
            let mut part = Owned::default();
            let mut kept = Vec::with_capacity((0..pts.len()).filter(|&i| keep(i)).count());
            let input: Vec<DVec3> = pts.iter().map(|p| p.p).collect();
            r.book(&input, keep, &mut part.1);
            part.1.merge(&Stats {
                phases: r.stats.phases.clone(),
                ..Stats::default()
            });
            for (i, p) in pts.iter().enumerate().filter(|&(i, _)| keep(i)) {
                let m = r.knn_mean[i];
                part.2.0.add(m);
                part.2.1.add(m * m);
                kept.push(TileResult {
                    index: p.index,
                    p: r.positions[i],
                    knn_mean: m,
                    normal: r.normals.as_ref().map(|n| n[i]),
                });
            }
            part.0.push(kept);
            Ok((part, r.exact))
        },
    )?;
    // No kernel runs any more: the parts become one vector of their exact length.
    let mut results: Vec<TileResult> = Vec::with_capacity(parts.iter().map(Vec::len).sum());
    for p in parts {
        results.extend(p);
    }
    let mut outcome = TileOutcome {
        halo: growth.halo,
        halo_growths: growth.rounds,
        cell_runs: growth.cells,
        narrower_runs: growth.narrower,
        loaded: growth.loaded,
        stats,
        knn_mean,
        owned: results.len() as u64,
        ..TileOutcome::default()
    };
    outcome.result_bytes = write_results(dir, t, &mut results)?;
    Ok(outcome)
}

/// The owned exact results of some kernel runs: the result records of each run, their counters
/// and the sums of their outlier statistic and its square.
type Owned = (Vec<Vec<TileResult>>, Stats, (ExactSum, ExactSum));
