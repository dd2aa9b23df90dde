//! Halo growth within the memory budget: a tile's owned points whose results are not yet exact
//! are redone in groups, each loading only the cells near its own points ([`Shell`]), never the
//! tile's whole grown halo.
//!
//! ```text
//!   first run: the tile's spill file (core + planned halo)
//!        │  exact owned results are kept; the rest are *pending*
//!        ▼
//!   round r (halo hᵣ = 2hᵣ₋₁, from round 2 at least the plan's halo, capped at
//!            plan::sufficient_halo):
//!     pending = one group G
//!        ▼
//!     for each G: load every point of the cells within hᵣ of G's points (Shell) from the
//!                 spill files (≤ max_points, else G is cut in two at the median of its longest
//!                 axis; one point that cannot fit tries its box at the halos since the last
//!                 round, lone_box, then the cells its dependencies reach, by_cells, or is
//!                 refused: TilingError::PointBudget)
//!                 run the kernel with G owned; exact results are kept, the rest stay pending
//! ```
//!
//! A result the kernel proves exact equals the whole-cloud result whatever else was loaded, so
//! results from the first run and from any group are the in-memory bytes: grouping changes only
//! what is loaded, never a value. Every kernel run holds at most [`TileBudget::max_points`]
//! points, so a growth costs no more memory than the first load. A narrowed tile's pending
//! points are a shell along its narrowed faces; the box of a shell is the whole tile, so loading
//! by cells, not by box, is what keeps a round from reloading the tile. See docs/DECISIONS.md
//! (issue 16).

use std::cell::Cell;
use std::collections::HashSet;
use std::path::Path;

use glam::DVec3;

use super::plan::{self, Plan};
use super::shell::Shell;
use super::spill::{TilePoint, read_spill};
use super::{TileBudget, TilingError};
use crate::denoise::DenoiseError;
use crate::denoise::cloud::CloudRun;
use crate::neighbours::KnnIndex;
use crate::points::Aabb;

/// Largest halo tried, relative to the bounding-box diagonal, before giving up.
const MAX_HALO_FRACTION: f64 = 1.0;

/// Most growth rounds of one tile, whatever the plan says: the halo doubles up to
/// [`plan::sufficient_halo`], a few times the plan's halo, so even a tile narrowed to 1/64 of it
/// ([`Plan::tile_halo`]) gets there in about 8 rounds; without an isolation radius it doubles
/// towards twice the diagonal. This only bounds the loop if the plan's numbers are degenerate.
const MAX_HALO_GROWTHS: u32 = 64;

/// What one kernel run gives the driver: a value over the owned points whose results are exact,
/// and for each loaded point whether its result is exact.
pub type RunOutput<V> = (V, Vec<bool>);

/// What the driver did for one tile.
#[derive(Debug, Clone, Copy, Default)]
pub struct Growth {
    /// Most points one kernel run held.
    pub loaded: u64,
    /// The largest halo a run used.
    pub halo: f64,
    /// Growth rounds (times the halo doubled).
    pub rounds: u32,
    /// Kernel runs on groups of pending points.
    pub groups: u32,
    /// Of those, runs on the cells a point's dependencies reach ([`by_cells`]).
    pub cells: u32,
}

/// A pending owned point: global index and position.
type Pending = (u64, DVec3);

/// Runs `f` on tile `t`'s points, then on groups of its owned points not yet exact with ever
/// larger halos (see the module overview), and merges every value with `merge`. `f` sees at
/// least `min_points` points; the points it must produce values for are marked owned. Results
/// that depend on `hops` hops of capped lists are exact at [`plan::sufficient_halo`], so the
/// halo grows past it only for groups with fewer than `min_points` points loaded.
///
/// # Errors
/// Spill read failures, `f`'s errors, cancellation, [`TilingError::HaloLimit`], and
/// [`TilingError::PointBudget`] when one point's box at the halo it needs holds more points than
/// the budget allows one run.
#[allow(clippy::too_many_arguments)]
pub fn with_exact_halo<V: Default>(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    t: usize,
    (hops, min_points): (usize, usize),
    preloaded: Option<Vec<TilePoint>>,
    mut merge: impl FnMut(&mut V, V),
    mut f: impl FnMut(&[TilePoint], &CloudRun) -> Result<RunOutput<V>, TilingError>,
) -> Result<(V, Growth), TilingError> {
    check_cancel()?;
    let pts = match preloaded {
        Some(p) => p,
        None => super::load_tile(dir, plan, t)?,
    };
    let first = plan.tile_halo(t);
    budget.check_points(t, pts.len() as u64, first)?;
    let mut value = V::default();
    let mut growth = Growth {
        loaded: pts.len() as u64,
        halo: first,
        ..Growth::default()
    };
    let owned = |p: &&TilePoint| p.owned;
    let first_few = pts.len() < min_points;
    let mut pending: Vec<Pending> = if first_few {
        // Isolated points may have fewer than k points within reach; the cloud has more.
        pts.iter().filter(owned).map(|p| (p.index, p.p)).collect()
    } else if pts.iter().any(|p| p.owned) {
        let (v, exact) = run_kernel(plan, budget, &pts, plan.first_region(t), None, &mut f)?;
        merge(&mut value, v);
        pts.iter()
            .zip(&exact)
            .filter(|(p, e)| p.owned && !**e)
            .map(|(p, _)| (p.index, p.p))
            .collect()
    } else {
        Vec::new()
    };
    drop(pts);

    // The limit is finite: the plan's bounds hold only points within ±MAX_COORD.
    let limit = MAX_HALO_FRACTION * plan.bounds.diagonal().max(f64::MIN_POSITIVE) * 2.0;
    let sufficient = plan::sufficient_halo(plan.isolation, hops);
    let mut halo = first;
    // Whether every pending point is pending only because too few points were loaded for it.
    let mut only_few = first_few;
    while !pending.is_empty() {
        // A narrowed tile's first round doubles its narrow halo (cheap, and it finishes most
        // points near the narrowed faces); later rounds start at the plan's halo, the reach the
        // sample predicts, instead of doubling up to it through rounds that finish nothing.
        let floor = if growth.rounds == 0 { 0.0 } else { plan.halo };
        let before = halo;
        halo = match sufficient {
            Some(s) if halo < s => (halo * 2.0).max(floor).min(s),
            // Cannot happen: at the sufficient halo every list and its members are loaded.
            Some(_) if !only_few => return Err(TilingError::HaloLimit { tile: t, halo }),
            _ => halo * 2.0,
        };
        growth.rounds += 1;
        if halo.is_nan() || halo > limit || growth.rounds > MAX_HALO_GROWTHS {
            return Err(TilingError::HaloLimit { tile: t, halo });
        }
        growth.halo = halo;
        only_few = true;
        let mut next = Vec::new();
        let mut stack = vec![std::mem::take(&mut pending)];
        while let Some(mut group) = stack.pop() {
            check_cancel()?;
            let points = group.iter().map(|g| g.1);
            let shell = Shell::around(plan.origin, plan.bounds, points, halo, budget.max_points);
            let loaded = match load_shell(dir, plan, &shell, &group, budget.max_points)? {
                Ok(loaded) => loaded,
                Err(found) if group.len() == 1 => {
                    // The shell is too large. A lone point's box is smaller than its shell, and
                    // the rounds may have skipped the halo it needs (the plan's halo is their
                    // floor): its box at each halo from twice the last round's up to this one.
                    let lone = lone_box(
                        dir,
                        plan,
                        budget,
                        group[0],
                        (before, halo),
                        min_points,
                        &mut f,
                    )?;
                    if let Some((v, still, n)) = lone {
                        merge(&mut value, v);
                        growth.groups += 1;
                        growth.loaded = growth.loaded.max(n);
                        only_few &= still.is_empty();
                        next.extend(still);
                        continue;
                    }
                    // Load only the cells its dependencies reach.
                    let by = by_cells(dir, plan, budget, t, &group, (hops, min_points), &mut f)?;
                    let Some((v, still, n)) = by else {
                        return Err(TilingError::PointBudget {
                            tile: t,
                            index: group[0].0,
                            found,
                            max: budget.max_points.unwrap_or(0),
                            halo,
                        });
                    };
                    merge(&mut value, v);
                    growth.groups += 1;
                    growth.cells += 1;
                    growth.loaded = growth.loaded.max(n);
                    only_few &= still.is_empty();
                    next.extend(still);
                    continue;
                }
                Err(_) => {
                    let (a, b) = halves(&mut group);
                    stack.push(b);
                    stack.push(a);
                    continue;
                }
            };
            growth.groups += 1;
            growth.loaded = growth.loaded.max(loaded.len() as u64);
            if loaded.len() < min_points {
                next.extend(group);
                continue;
            }
            let (v, exact) =
                run_kernel(plan, budget, &loaded, Aabb::empty(), Some(&shell), &mut f)?;
            drop(shell);
            merge(&mut value, v);
            let before = next.len();
            next.extend(
                loaded
                    .iter()
                    .zip(&exact)
                    .filter(|(p, e)| p.owned && !**e)
                    .map(|(p, _)| (p.index, p.p)),
            );
            only_few &= next.len() == before;
        }
        pending = next;
    }
    Ok((value, growth))
}

/// Rounds of [`by_cells`] per hop of the results (each round adds the cells the incomplete balls
/// of the dependencies touch; a chain of `hops` hops needs about that many).
const CELL_ROUNDS_PER_HOP: usize = 3;

/// Runs `f` on the cells of the occupancy grid that `group`'s results depend on, for a group whose
/// box holds more points than the budget allows (a sparse point above a dense surface): starting
/// from the cells around the group, it computes the k-NN lists of what is loaded (capped as the
/// kernel caps them), follows them `hops` hops from the group, and adds every cell the ball of an
/// incomplete list there touches, until none is left; then the kernel runs with no region (every
/// ball proven by the grid). Which cells are loaded decides only whether the kernel can prove
/// results exact, never a value. Returns the value, the group's points still not exact and the
/// points loaded; `None` when the grid cannot prove the needed balls (no grid, balls wider than
/// it visits, or too many rounds).
///
/// # Errors
/// Spill read failures, `f`'s errors, cancellation, [`TilingError::PointBudget`] when the needed
/// cells hold more points than the budget allows one run.
fn by_cells<V>(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    t: usize,
    group: &[Pending],
    (hops, k): (usize, usize),
    f: &mut impl FnMut(&[TilePoint], &CloudRun) -> Result<RunOutput<V>, TilingError>,
) -> Result<Option<(V, Vec<Pending>, u64)>, TilingError> {
    let Some(o) = budget.occupancy else {
        return Ok(None);
    };
    let max = budget.max_points.unwrap_or(u64::MAX);
    let mut cells = HashSet::new();
    let ring = |cells: &mut HashSet<[i64; 3]>, c: [i64; 3]| {
        for x in -1..=1 {
            for y in -1..=1 {
                for z in -1..=1 {
                    let n = [c[0] + x, c[1] + y, c[2] + z];
                    if o.count(n) > 0 {
                        cells.insert(n);
                    }
                }
            }
        }
    };
    for (_, p) in group {
        ring(&mut cells, o.cell_of(*p));
    }
    let denoise = |e| TilingError::Denoise {
        tile: t,
        error: DenoiseError::Neighbours(e),
    };
    for _ in 0..CELL_ROUNDS_PER_HOP * (hops + 2) {
        check_cancel()?;
        let pts = match load_cells(dir, plan, o, &cells, group, max)? {
            Ok(p) => p,
            Err(found) => {
                return Err(TilingError::PointBudget {
                    tile: t,
                    index: group[0].0,
                    found,
                    max,
                    halo: f64::NAN,
                });
            }
        };
        if pts.len() <= k {
            // Too few points for a list: widen by a ring of cells.
            let now: Vec<[i64; 3]> = cells.iter().copied().collect();
            for c in now {
                ring(&mut cells, c);
            }
            continue;
        }
        let positions: Vec<DVec3> = pts.iter().map(|p| p.p).collect();
        let ties: Vec<u64> = pts.iter().map(|p| p.index).collect();
        let index = KnnIndex::build_with_ties(&positions, plan.origin, ties).map_err(denoise)?;
        let (lists, radii) = index.knn_all(k).map_err(denoise)?;
        let (lists, radii, _) =
            crate::denoise::isolation::cap_lists(lists, radii, plan.isolation, |i, u| {
                index.dist2(i, u)
            });
        drop(index);
        let loaded = o.loaded(positions.iter().copied());
        // The dependencies of the group, `hops` deep.
        let mut seen = vec![false; pts.len()];
        let mut frontier: Vec<usize> = (0..pts.len()).filter(|&i| pts[i].owned).collect();
        for &i in &frontier {
            seen[i] = true;
        }
        let mut deps = frontier.clone();
        for _ in 0..hops {
            let mut next = Vec::new();
            for &i in &frontier {
                for &u in lists.get(i) {
                    let u = u as usize;
                    if !seen[u] {
                        seen[u] = true;
                        next.push(u);
                    }
                }
            }
            deps.extend_from_slice(&next);
            frontier = next;
        }
        let mut added = false;
        for &i in &deps {
            if o.complete(&loaded, positions[i], radii[i]) {
                continue;
            }
            let Some(touched) = o.ball_cells(positions[i], radii[i]) else {
                return Ok(None);
            };
            for c in touched {
                if o.count(c) > 0 {
                    added |= cells.insert(c);
                }
            }
        }
        if added {
            continue;
        }
        drop((lists, radii, loaded));
        let (v, exact) = run_kernel(plan, budget, &pts, Aabb::empty(), None, f)?;
        let still = pts
            .iter()
            .zip(&exact)
            .filter(|(p, e)| p.owned && !**e)
            .map(|(p, _)| (p.index, p.p))
            .collect();
        return Ok(Some((v, still, pts.len() as u64)));
    }
    Ok(None)
}

/// Every point of the cloud in `cells`, the points of `group` marked owned; `Err(found)` when
/// there are more than `max`.
fn load_cells(
    dir: &Path,
    plan: &Plan,
    o: &super::occupancy::Occupancy,
    cells: &HashSet<[i64; 3]>,
    group: &[Pending],
    max: u64,
) -> Result<Result<Vec<TilePoint>, u64>, TilingError> {
    let mut bx = Aabb::empty();
    for &c in cells {
        bx.union(&o.cell_box(c));
    }
    let keep = |p| cells.contains(&o.cell_of(p));
    load_where(dir, plan, &bx, keep, group, Some(max))
}

/// [`TilingError::Cancelled`] once Ctrl-C or SIGTERM set the run's flag.
fn check_cancel() -> Result<(), TilingError> {
    if crate::neighbours::cancel_requested() {
        Err(TilingError::Cancelled)
    } else {
        Ok(())
    }
}

/// Runs `f` on `pts` with `region` the box holding every point of the cloud inside it, and
/// `shell`, when given, the cells holding every point of the cloud in them.
fn run_kernel<V>(
    plan: &Plan,
    budget: &TileBudget,
    pts: &[TilePoint],
    region: Aabb,
    shell: Option<&Shell>,
    f: &mut impl FnMut(&[TilePoint], &CloudRun) -> Result<RunOutput<V>, TilingError>,
) -> Result<RunOutput<V>, TilingError> {
    let occupancy = budget.occupancy;
    let positions: Vec<DVec3> = pts.iter().map(|p| p.p).collect();
    let ties: Vec<u64> = pts.iter().map(|p| p.index).collect();
    let owned: Vec<bool> = pts.iter().map(|p| p.owned).collect();
    let held: Vec<bool> = pts.iter().map(|p| p.held).collect();
    // Balls crossing the region are complete when the shell's cells hold them, or when the
    // occupancy cells they touch hold nothing more.
    let loaded = std::sync::OnceLock::new();
    let complete = |p: DVec3, r2: f64| {
        shell.is_some_and(|s| s.complete(p, r2))
            || occupancy.is_some_and(|o| {
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
        region: Some(region),
        isolation: plan.isolation,
        short_lists: plan.short_lists,
        complete: (occupancy.is_some() || shell.is_some())
            .then_some(&complete as &(dyn Fn(DVec3, f64) -> bool + Sync)),
        wanted: Some(&owned),
        held: held.iter().any(|&h| h).then_some(held.as_slice()),
    };
    f(pts, &run)
}

/// The bounding box of `group`'s points grown by `halo` (closed: every point of the cloud inside
/// it is loaded).
fn grown(group: &[Pending], halo: f64) -> Aabb {
    let mut b = Aabb::empty();
    for (_, p) in group {
        b.min = b.min.min(*p);
        b.max = b.max.max(*p);
    }
    b.min -= DVec3::splat(halo);
    b.max += DVec3::splat(halo);
    b
}

/// Splits `group` at the median of its longest axis (ties by global index), so the cut is the
/// same on every run.
fn halves(group: &mut Vec<Pending>) -> (Vec<Pending>, Vec<Pending>) {
    let b = grown(group, 0.0);
    let size = b.size();
    let axis = if size.x >= size.y && size.x >= size.z {
        0
    } else if size.y >= size.z {
        1
    } else {
        2
    };
    group.sort_unstable_by(|a, b| a.1[axis].total_cmp(&b.1[axis]).then(a.0.cmp(&b.0)));
    let right = group.split_off(group.len() / 2);
    (std::mem::take(group), right)
}

/// Tiles whose core touches `bx` (their owned records are the points in it).
fn touching(plan: &Plan, bx: &Aabb) -> impl Iterator<Item = usize> {
    plan.tiles
        .iter()
        .filter(|tile| {
            (0..3).all(|a| tile.core.min[a] <= bx.max[a] && tile.core.max[a] >= bx.min[a])
        })
        .map(|tile| tile.id)
}

/// Bisections of [`lone_box`] between a halo whose box fits and one whose box does not.
const LONE_BISECTIONS: usize = 6;

/// Runs `f` on the box of the lone pending `point` at the halos `2·from`, `4·from`, … up to
/// `halo`, until a run proves its result exact; where a box holds more points than the budget
/// allows, it bisects between that halo and the last that fit. Returns the value, the point when
/// it is still pending after the box at `halo`, and the points of the last load; `None` when no
/// box within the budget proved it and the box at `halo` does not fit.
///
/// # Errors
/// Spill read failures, `f`'s errors, cancellation.
fn lone_box<V: Default>(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    point: Pending,
    (from, halo): (f64, f64),
    min_points: usize,
    f: &mut impl FnMut(&[TilePoint], &CloudRun) -> Result<RunOutput<V>, TilingError>,
) -> Result<Option<(V, Vec<Pending>, u64)>, TilingError> {
    let group = [point];
    // The widest halo whose box fit without proving the point, the narrowest that did not fit.
    let (mut fit, mut over) = (from, None::<f64>);
    let mut h = (from * 2.0).min(halo);
    let mut bisections = 0;
    // Doubling towards `halo`, then bisecting: bounded by both counts.
    for _ in 0..MAX_HALO_GROWTHS as usize + LONE_BISECTIONS {
        check_cancel()?;
        let bx = grown(&group, h);
        match load_box(dir, plan, &bx, &group, budget.max_points)? {
            Err(_) => over = Some(h),
            Ok(loaded) => {
                let n = loaded.len() as u64;
                let (v, still) = if loaded.len() >= min_points {
                    let (v, exact) =
                        run_kernel(plan, budget, &loaded, plan.region_of(&bx), None, f)?;
                    let still: Vec<Pending> = loaded
                        .iter()
                        .zip(&exact)
                        .filter(|(p, e)| p.owned && !**e)
                        .map(|(p, _)| (p.index, p.p))
                        .collect();
                    (v, still)
                } else {
                    (V::default(), group.to_vec())
                };
                if still.is_empty() || (h >= halo && over.is_none()) {
                    return Ok(Some((v, still, n)));
                }
                fit = h;
            }
        }
        h = match over {
            None => (h * 2.0).min(halo),
            Some(_) if bisections >= LONE_BISECTIONS => return Ok(None),
            Some(o) => {
                bisections += 1;
                0.5 * (fit + o)
            }
        };
    }
    Ok(None)
}

/// Every point of the cloud inside `bx` (from the owned records of the tiles it touches), the
/// points of `group` marked owned; `Err(found)` when there are more than `max` (`found` of them
/// were seen before the read stopped).
fn load_box(
    dir: &Path,
    plan: &Plan,
    bx: &Aabb,
    group: &[Pending],
    max: Option<u64>,
) -> Result<Result<Vec<TilePoint>, u64>, TilingError> {
    let inside = |p: DVec3| (0..3).all(|a| p[a] >= bx.min[a] && p[a] <= bx.max[a]);
    load_where(dir, plan, bx, inside, group, max)
}

/// Every point of the cloud in `shell`'s cells (from the owned records of the tiles its span
/// touches), the points of `group` marked owned; `Err(found)` when there are more than `max`
/// (`found` of them were seen before the read stopped).
fn load_shell(
    dir: &Path,
    plan: &Plan,
    shell: &Shell,
    group: &[Pending],
    max: Option<u64>,
) -> Result<Result<Vec<TilePoint>, u64>, TilingError> {
    load_where(dir, plan, &shell.span(), |p| shell.contains(p), group, max)
}

/// Every point of the cloud in `span` for which `keep` holds (from the owned records of the
/// tiles `span` touches), the points of `group` marked owned; `Err(found)` when there are more
/// than `max`.
fn load_where(
    dir: &Path,
    plan: &Plan,
    span: &Aabb,
    keep: impl Fn(DVec3) -> bool,
    group: &[Pending],
    max: Option<u64>,
) -> Result<Result<Vec<TilePoint>, u64>, TilingError> {
    let mut mine: Vec<u64> = group.iter().map(|g| g.0).collect();
    mine.sort_unstable();
    let max = max.unwrap_or(u64::MAX);
    let count = Cell::new(0u64);
    let mut pts = Vec::new();
    for other in touching(plan, span) {
        read_spill(
            dir,
            other,
            |_, p, is_halo| {
                if is_halo || !keep(p) {
                    return false;
                }
                count.set(count.get() + 1);
                // Past the limit the points are counted, not kept.
                count.get() <= max
            },
            &mut pts,
        )?;
        if count.get() > max {
            return Ok(Err(count.get()));
        }
    }
    for p in &mut pts {
        p.owned = mine.binary_search(&p.index).is_ok();
    }
    Ok(Ok(pts))
}
