//! Out-of-core processing: plan, partition into tiles with a halo, process each tile exactly,
//! merge the results back in the original order.
//!
//! # Brief overview
//!
//! 1. **Plan** ([`plan::Planner`]): one streaming pass collects bounds, counts and a
//!    deterministic sample, and splits space into tiles by point count (a k-d split).
//! 2. **Partition** ([`spill::SpillWriter`]): a second pass writes every finite point, with its
//!    global index, to the spill file of the tile that owns it, and a halo copy to every other
//!    tile whose box grown by the halo contains it.
//! 3. **Process** ([`process_tile`]): each tile loads its points and runs
//!    [`crate::denoise::cloud::run`] on them with the tile's region. A result is kept only when
//!    it is provably the whole-cloud result (every k-NN ball it depends on lies inside the
//!    region, see [`crate::denoise::cloud`]); if any owned point is not, the halo doubles and the
//!    tile is redone from the neighbouring spill files. Finished tiles write a result file sorted
//!    by global index, atomically: these are the checkpoints a resumed job skips.
//! 4. **Stitch** ([`spill::ResultMerge`]): the result files merge in global-index order while
//!    the input streams a third time, so every attribute is copied from the input untouched.
//!
//! Every file of a run lives in its work directory ([`workdir`]), which names them and says
//! which phases are committed (what a resumed run skips).
//!
//! With ties broken by global index, sums in a fixed order and Jacobi passes, the tiled output is
//! bit-identical to the in-memory output for any tile size.

pub mod occupancy;
pub mod plan;
pub mod spill;
pub mod workdir;

use std::path::{Path, PathBuf};

use glam::DVec3;
use thiserror::Error;

use crate::denoise::cloud::{self, CloudRun, Globals, GlobalsPartial};
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
    /// Bytes of the result file.
    pub result_bytes: u64,
    /// Counters of the owned points and phase timings.
    pub stats: Stats,
    /// Exact sums of the owned points' k-NN mean distance and its square (outlier statistics).
    pub knn_mean: (ExactSum, ExactSum),
}

/// Largest halo tried, relative to the bounding-box diagonal, before giving up.
const MAX_HALO_FRACTION: f64 = 1.0;

/// Most halo doublings of one tile, whatever the plan says: the initial halo is at least 10⁻³ of
/// the diagonal, so 2 × the diagonal is reached in 11; this only bounds the loop if the plan's
/// numbers are degenerate.
const MAX_HALO_GROWTHS: u32 = 64;

/// What a tile may rely on and spend beyond its plan: the occupancy grid of the partition pass
/// (which proves balls complete and bounds what a halo loads) and the points one tile may hold.
#[derive(Debug, Clone, Copy, Default)]
pub struct TileBudget<'a> {
    /// The partition pass's grid, when there is one.
    pub occupancy: Option<&'a Occupancy>,
    /// Most points one tile's first load may hold; `None` for no limit. A grown halo is not held
    /// to it (it is what the plan cannot foresee; see docs/DECISIONS.md, issue 16).
    pub max_points: Option<u64>,
    /// Most points a halo load may read before they are counted (the grid's upper bound on a
    /// region; each read point costs far less than one the operator runs on).
    pub max_staged: Option<u64>,
}

impl TileBudget<'_> {
    /// [`TilingError::Budget`] when reading tile `t` with `halo` may take more points than
    /// [`TileBudget::max_staged`] (the grid's upper bound on the region).
    ///
    /// # Errors
    /// As said.
    pub fn check_load(&self, plan: &Plan, t: usize, halo: f64) -> Result<(), TilingError> {
        let (Some(o), Some(max)) = (self.occupancy, self.max_staged) else {
            return Ok(());
        };
        let points = o.points_in(&plan.region(t, halo));
        if points > max {
            return Err(TilingError::Budget {
                tile: t,
                points,
                max,
                halo,
            });
        }
        Ok(())
    }

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
    load(dir, plan, t, plan.halo)
}

/// Loads the points of tile `t` for `halo`: from its own spill file when `halo` is the plan's
/// (owned points plus halo copies), otherwise the owned points of every tile near the grown box.
fn load(dir: &Path, plan: &Plan, t: usize, halo: f64) -> Result<Vec<TilePoint>, TilingError> {
    let mut pts = Vec::new();
    if halo <= plan.halo {
        read_spill(dir, t, |_, _, _| true, &mut pts)?;
        return Ok(pts);
    }
    for other in 0..plan.tiles.len() {
        let core = plan.tiles[other].core;
        let mine = plan.tiles[t].core;
        let touches =
            (0..3).all(|a| core.min[a] <= mine.max[a] + halo && core.max[a] >= mine.min[a] - halo);
        if !touches {
            continue;
        }
        read_spill(
            dir,
            other,
            |_, p, is_halo| !is_halo && plan.in_region(t, halo, p),
            &mut pts,
        )?;
    }
    for p in &mut pts {
        p.owned = plan.owner(p.p) == t;
    }
    Ok(pts)
}

/// Runs `f` on tile `t`'s points with the smallest halo (starting at the plan's, doubling) for
/// which `f` reports every owned point exact. Results that depend on `hops` hops of capped lists
/// are exact at [`plan::sufficient_halo`], so the halo grows past it only while fewer than
/// `min_points` points (one list) are loaded. `f` sees at least `min_points` points, or none.
fn with_exact_halo<T>(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    t: usize,
    (hops, min_points): (usize, usize),
    mut preloaded: Option<Vec<TilePoint>>,
    mut f: impl FnMut(&[TilePoint], &CloudRun) -> Result<(T, bool), TilingError>,
) -> Result<(T, Vec<TilePoint>, f64, u32), TilingError> {
    let mut halo = plan.halo;
    let mut growths = 0;
    // The limit is finite: the plan's bounds hold only points within ±MAX_COORD.
    let limit = MAX_HALO_FRACTION * plan.bounds.diagonal().max(f64::MIN_POSITIVE) * 2.0;
    let sufficient = plan::sufficient_halo(plan.isolation, hops);
    loop {
        if crate::neighbours::cancel_requested() {
            return Err(TilingError::Cancelled);
        }
        let pts = match preloaded.take() {
            Some(p) => p,
            None => {
                budget.check_load(plan, t, halo)?;
                load(dir, plan, t, halo)?
            }
        };
        let occupancy = budget.occupancy;
        let positions: Vec<DVec3> = pts.iter().map(|p| p.p).collect();
        let ties: Vec<u64> = pts.iter().map(|p| p.index).collect();
        // Balls crossing the region are complete when the cells they touch hold nothing more.
        let loaded = std::sync::OnceLock::new();
        let complete = |p: DVec3, r2: f64| {
            occupancy.is_some_and(|o| {
                o.complete(
                    loaded.get_or_init(|| o.loaded(positions.iter().copied())),
                    p,
                    r2,
                )
            })
        };
        let run = CloudRun {
            positions: &positions,
            ties: &ties,
            origin: plan.origin,
            region: Some(plan.region(t, halo)),
            isolation: plan.isolation,
            complete: occupancy.map(|_| &complete as &(dyn Fn(DVec3, f64) -> bool + Sync)),
        };
        let owned = pts.iter().filter(|p| p.owned).count();
        if owned == 0 {
            return f(
                &[],
                &CloudRun {
                    positions: &[],
                    ties: &[],
                    ..run
                },
            )
            .map(|(v, _)| (v, pts, halo, growths));
        }
        let few = pts.len() < min_points;
        if !few {
            if growths == 0 {
                budget.check_points(t, pts.len() as u64, halo)?;
            }
            let (value, exact) = f(&pts, &run)?;
            if exact {
                return Ok((value, pts, halo, growths));
            }
        }
        growths += 1;
        if few {
            // Isolated points may have fewer than k points within reach; the cloud has more.
            halo *= 2.0;
        } else if sufficient.is_some_and(|s| halo >= s) {
            // Cannot happen: at the sufficient halo every list and its members are loaded.
            return Err(TilingError::HaloLimit { tile: t, halo });
        } else {
            halo = sufficient.map_or(halo * 2.0, |s| (halo * 2.0).min(s));
        }
        if halo.is_nan() || halo > limit || growths > MAX_HALO_GROWTHS {
            return Err(TilingError::HaloLimit { tile: t, halo });
        }
    }
}

/// The exact partials behind [`Globals`] over tile `t`'s owned points (the pre-pass).
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
    let (sum, _, _, _) = with_exact_halo(
        dir,
        plan,
        budget,
        t,
        (0, structure::NEAR),
        None,
        |pts, run| {
            if pts.is_empty() {
                return Ok((GlobalsPartial::default(), true));
            }
            let (sum, exact) = cloud::globals_partial(run, params, |i| pts[i].owned)
                .map_err(|e| TilingError::Denoise { tile: t, error: e })?;
            let ok = pts.iter().zip(&exact).all(|(p, e)| !p.owned || *e);
            Ok((sum, ok))
        },
    )?;
    Ok(sum)
}

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
    let (result, pts, halo, growths) = with_exact_halo(
        dir,
        plan,
        budget,
        t,
        (hops, params.k()),
        preloaded,
        |pts, run| {
            if pts.is_empty() {
                return Ok((None, true));
            }
            let r = cloud::run(run, params, globals)
                .map_err(|e| TilingError::Denoise { tile: t, error: e })?;
            let ok = pts.iter().zip(&r.exact).all(|(p, e)| !p.owned || *e);
            Ok((Some(r), ok))
        },
    )?;
    let mut outcome = TileOutcome {
        halo,
        halo_growths: growths,
        loaded: pts.len() as u64,
        ..TileOutcome::default()
    };
    let mut results = Vec::new();
    if let Some(r) = result {
        let input: Vec<DVec3> = pts.iter().map(|p| p.p).collect();
        r.book(&input, |i| pts[i].owned, &mut outcome.stats);
        outcome.stats.merge(&Stats {
            phases: r.stats.phases.clone(),
            ..Stats::default()
        });
        for (i, p) in pts.iter().enumerate().filter(|(_, p)| p.owned) {
            let m = r.knn_mean[i];
            outcome.knn_mean.0.add(m);
            outcome.knn_mean.1.add(m * m);
            results.push(TileResult {
                index: p.index,
                p: r.positions[i],
                knn_mean: m,
            });
        }
    }
    outcome.owned = results.len() as u64;
    outcome.result_bytes = write_results(dir, t, &mut results)?;
    Ok(outcome)
}
