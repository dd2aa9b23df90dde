//! Halo growth within the memory budget: a tile's owned points whose results are not yet exact
//! are redone in groups, each loading only the cells near its own points ([`Shell`]), never the
//! tile's whole grown halo.
//!
//! ```text
//!   first run: the tile's spill file (core + planned halo), or its points within a narrower
//!              halo for a pass that reaches less far (the globals' pre-pass)
//!        │  exact owned results are kept; the rest are *pending*
//!        ▼
//!   round r (halo hᵣ = 2hᵣ₋₁, from round 2 at least the plan's halo, capped at
//!            plan::sufficient_halo):
//!     pending = one group G
//!        ▼
//!     for each G: load every point of the cells within hᵣ of G's points (Shell) from the
//!                 spill files, side by side; over max_points, unless a half of G may fit
//!                 (by the lower bounds), the widest of hᵣ/2, hᵣ/4, … above hᵣ₋₁ that fits
//!                 (load_widest: its leftovers try the halos above it); else G is cut in two
//!                 at the median of its longest axis, and a group of at most LONE_GROUP
//!                 points is set aside as *lone*; lower bounds from the
//!                 occupancy grid and the block tables refuse a load that cannot fit before a
//!                 record is read
//!                 run the kernel with G owned; exact results are kept, the rest stay pending
//!     the lone points, together: load only the cells their dependencies reach (by_cells on
//!                 FineCells; one spill read per round serves them all), halved while over
//!                 max_points; one that still cannot fit tries its box at the halos since the
//!                 last round (lone_box), or is refused: TilingError::PointBudget
//! ```
//!
//! A result the kernel proves exact equals the whole-cloud result whatever else was loaded, so
//! results from the first run and from any group are the in-memory bytes: grouping changes only
//! what is loaded, never a value. Every kernel run holds at most [`TileBudget::max_points`]
//! points, so a growth costs no more memory than the first load. A narrowed tile's pending
//! points are a shell along its narrowed faces; the box of a shell is the whole tile, so loading
//! by cells, not by box, is what keeps a round from reloading the tile. See docs/DECISIONS.md
//! (issue 16).

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use glam::DVec3;
use rayon::prelude::*;

use super::fine::{self, FineCells};
use super::plan::{self, Plan};
use super::shell::{self, Shell};
use super::spill::{TilePoint, owned_within, read_owned_near};
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
    /// Of those, runs of a group at a narrower halo than its round's ([`load_widest`]).
    pub narrower: u32,
}

/// A pending owned point: global index and position.
type Pending = (u64, DVec3);

/// Runs `f` on tile `t`'s points, then on groups of its owned points not yet exact with ever
/// larger halos (see the module overview), and merges every value with `merge`. `f` sees at
/// least `min_points` points; the points it must produce values for are marked owned. Results
/// that depend on `hops` hops of capped lists are exact at [`plan::sufficient_halo`], so the
/// halo grows past it only for groups with fewer than `min_points` points loaded.
///
/// With `narrow`, the first run holds only the spill file's points within that halo of the
/// tile (where it is below the tile's own): for a pass whose results reach much less far than
/// the operator's, such as the globals' pre-pass, whose index over the whole first load was
/// most of its cost. The growth rounds start from it.
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
    (preloaded, narrow): (Option<Vec<TilePoint>>, Option<f64>),
    mut merge: impl FnMut(&mut V, V),
    mut f: impl FnMut(&[TilePoint], &CloudRun) -> Result<RunOutput<V>, TilingError>,
) -> Result<(V, Growth), TilingError> {
    check_cancel()?;
    let mut pts = match preloaded {
        Some(p) => p,
        None => super::load_tile(dir, plan, t)?,
    };
    let (first, region) = match narrow {
        Some(h) if h > 0.0 && h < plan.tile_halo(t) => {
            let faces = plan.narrowed_faces(t, h);
            pts.retain(|p| p.owned || plan.within_faces(t, &faces, p.p));
            (h, plan.region_within(t, &faces))
        }
        _ => (plan.tile_halo(t), plan.first_region(t)),
    };
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
        let (v, exact) = run_kernel(plan, budget, &pts, region, None, &mut f)?;
        merge(&mut value, v);
        pending_of(&pts, &exact)
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
        // Lone points whose cells do not fit, with the points their shell found.
        let mut lonely: Vec<(Pending, u64)> = Vec::new();
        // Each group with the halo its descents stay above (see `load_widest`).
        let mut stack = vec![(std::mem::take(&mut pending), before)];
        while let Some((mut group, floor)) = stack.pop() {
            check_cancel()?;
            let (shell, loaded, at) = match load_widest(dir, plan, budget, &group, (floor, halo))? {
                Ok(fit) => fit,
                Err(found) if group.len() <= LONE_GROUP => {
                    lonely.extend(group.into_iter().map(|g| (g, found)));
                    continue;
                }
                Err(_) => {
                    let (a, b) = halves(&mut group, |g| *g);
                    stack.push((b, floor));
                    stack.push((a, floor));
                    continue;
                }
            };
            growth.groups += 1;
            growth.narrower += u32::from(at < halo);
            growth.loaded = growth.loaded.max(loaded.len() as u64);
            if loaded.len() < min_points {
                if at < halo {
                    // Too few points at a narrower halo: the group tries the halos above it.
                    stack.push((group, at));
                } else {
                    next.extend(group);
                }
                continue;
            }
            let proof = |p: DVec3, r2: f64| shell.complete(p, r2);
            let (v, exact) =
                run_kernel(plan, budget, &loaded, Aabb::empty(), Some(&proof), &mut f)?;
            drop(shell);
            merge(&mut value, v);
            let still = pending_of(&loaded, &exact);
            if at < halo {
                // Proven at a narrower halo than the round's: the rest try the halos above it.
                if !still.is_empty() {
                    stack.push((still, at));
                }
            } else {
                only_few &= still.is_empty();
                next.extend(still);
            }
        }
        // The lone points load only the cells their dependencies reach, as many together as
        // fit: one read of the spill files serves them all (each alone read them a dozen times).
        let mut stack = if lonely.is_empty() {
            Vec::new()
        } else {
            vec![lonely]
        };
        while let Some(mut group) = stack.pop() {
            check_cancel()?;
            let points: Vec<Pending> = group.iter().map(|g| g.0).collect();
            let outcome = by_cells(dir, plan, budget, t, &points, (hops, min_points), &mut f)?;
            let (v, still, n) = match outcome {
                ByCells::Ran(v, still, n) => {
                    growth.cells += 1;
                    (v, still, n)
                }
                ByCells::Over(_) | ByCells::Unproven if group.len() > 1 => {
                    let (a, b) = halves(&mut group, |g| g.0);
                    stack.push(b);
                    stack.push(a);
                    continue;
                }
                outcome => {
                    // The shell is too large, and so are the cells. A lone point's box is
                    // smaller than its shell, and the rounds may have skipped the halo it needs
                    // (the plan's halo is their floor): its box at each halo from twice the
                    // last round's up to this one.
                    let (point, shell_found) = group[0];
                    let lone =
                        lone_box(dir, plan, budget, point, (before, halo), min_points, &mut f)?;
                    let Some(ran) = lone else {
                        let found = match outcome {
                            ByCells::Over(found) => found,
                            _ => shell_found,
                        };
                        return Err(TilingError::PointBudget {
                            tile: t,
                            index: point.0,
                            found,
                            max: budget.max_points.unwrap_or(0),
                            halo,
                        });
                    };
                    ran
                }
            };
            merge(&mut value, v);
            growth.groups += 1;
            growth.loaded = growth.loaded.max(n);
            only_few &= still.is_empty();
            next.extend(still);
        }
        pending = next;
    }
    Ok((value, growth))
}

/// Groups of at most this many points whose cells do not fit go to [`by_cells`] with the lone
/// points, instead of halving on: halving reads the spill files once per half, down to single
/// points, and the cells a point's dependencies reach are far fewer than its halo's. Swept on
/// the 10 M cluttered scene at 200 MiB (same bytes each time; BENCHMARKS, issue 16): 32 →
/// 339 CPU-s, 256 → 221, 1024 → 218, 4096 → 235, 16 384 → 242, every group → 291.
const LONE_GROUP: usize = 1024;

/// Rounds of [`by_cells`] per hop of the results (each round adds the cells the incomplete balls
/// of the dependencies touch; a chain of `hops` hops needs about that many).
const CELL_ROUNDS_PER_HOP: usize = 3;

/// What [`by_cells`] did with a group.
enum ByCells<V> {
    /// The kernel ran: its value, the group's points still not exact, the points loaded.
    Ran(V, Vec<Pending>, u64),
    /// The cells the group depends on hold more points than the budget allows one run (this
    /// many were seen before the read stopped).
    Over(u64),
    /// The cells cannot prove the balls the group needs.
    Unproven,
}

/// Runs `f` on the fine cells ([`FineCells`]) that `group`'s results depend on, for lone points
/// whose halo holds more points than the budget allows (a sparse point beside a dense cluster):
/// starting from a small ball around each point (or, with too few points for a list, the ball
/// through the nearest occupancy cells holding more than k), it computes, among what is loaded,
/// the k-NN lists of the points within `hops` hops of the group (capped as the kernel caps
/// them; [`KnnIndex::knn_near`]), follows them `hops` hops from the group, and adds
/// the cells of every ball there not proven complete, until none is left; then the kernel runs
/// with the cells as its proof. Which cells are loaded decides only whether the kernel can prove
/// results exact, never a value. [`ByCells::Unproven`] when the cells cannot prove the needed
/// balls (no grid, balls wider than they visit, or too many rounds).
///
/// # Errors
/// Spill read failures, `f`'s errors, cancellation.
fn by_cells<V>(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    t: usize,
    group: &[Pending],
    (hops, k): (usize, usize),
    f: &mut impl FnMut(&[TilePoint], &CloudRun) -> Result<RunOutput<V>, TilingError>,
) -> Result<ByCells<V>, TilingError> {
    let Some(o) = budget.occupancy else {
        return Ok(ByCells::Unproven);
    };
    let max = budget.max_points.unwrap_or(u64::MAX);
    let mut cells = FineCells::new(o, shell::most_cells(budget.max_points));
    let edge = o.cell() / f64::from(1u32 << fine::FINE_SHIFT);
    for (_, p) in group {
        if cells.add_ball(*p, edge * edge).is_err() {
            return Ok(ByCells::Unproven);
        }
    }
    let denoise = |e| TilingError::Denoise {
        tile: t,
        error: DenoiseError::Neighbours(e),
    };
    for _ in 0..CELL_ROUNDS_PER_HOP * (hops + 2) {
        check_cancel()?;
        let span = cells.span();
        let pts = match load_where(
            dir,
            plan,
            (&span, |_| true),
            |p| cells.contains(p),
            group,
            Some(max),
        )? {
            Ok(p) => p,
            Err(found) => return Ok(ByCells::Over(found)),
        };
        if pts.len() <= k {
            // Too few points for a list: the ball through the nearest occupancy cells that hold
            // more than k points, across empty space.
            let mut added = false;
            for (_, p) in group {
                let reach = o
                    .nearest_cells(*p, k as u64 + 1)
                    .into_iter()
                    .map(|c| {
                        let b = o.cell_box(c);
                        (b.min - *p).abs().max((b.max - *p).abs()).length_squared()
                    })
                    .fold(0.0, f64::max);
                match cells.add_ball(*p, reach) {
                    Ok(a) => added |= a,
                    Err(_) => return Ok(ByCells::Unproven),
                }
            }
            if !added {
                return Ok(ByCells::Unproven);
            }
            continue;
        }
        let positions: Vec<DVec3> = pts.iter().map(|p| p.p).collect();
        let ties: Vec<u64> = pts.iter().map(|p| p.index).collect();
        let index = KnnIndex::build_with_ties(&positions, plan.origin, ties).map_err(denoise)?;
        // Only the lists the group's dependencies have (`hops` deep): the cells hold far more
        // points than those, and listing every point was most of this function's cost.
        let seeds: Vec<bool> = pts.iter().map(|p| p.owned).collect();
        let (lists, radii, _) = index.knn_near(k, &seeds, hops, None).map_err(denoise)?;
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
            let (p, r2) = (positions[i], radii[i]);
            if cells.complete(p, r2) || o.complete(&loaded, p, r2) {
                continue;
            }
            match cells.add_ball(p, r2) {
                Ok(a) => added |= a,
                Err(_) => return Ok(ByCells::Unproven),
            }
        }
        if added {
            continue;
        }
        drop((lists, radii, loaded));
        let proof = |p: DVec3, r2: f64| cells.complete(p, r2);
        let (v, exact) = run_kernel(plan, budget, &pts, Aabb::empty(), Some(&proof), f)?;
        let still = pending_of(&pts, &exact);
        return Ok(ByCells::Ran(v, still, pts.len() as u64));
    }
    Ok(ByCells::Unproven)
}

/// [`TilingError::Cancelled`] once Ctrl-C or SIGTERM set the run's flag.
fn check_cancel() -> Result<(), TilingError> {
    if crate::neighbours::cancel_requested() {
        Err(TilingError::Cancelled)
    } else {
        Ok(())
    }
}

/// A proof that every point of the cloud in a ball (centre, squared radius) was loaded.
type Proof<'a> = &'a (dyn Fn(DVec3, f64) -> bool + Sync);

/// Runs `f` on `pts` with `region` the box holding every point of the cloud inside it, and
/// `cells`, when given, the proof of the cells loaded beside it ([`Shell`], [`FineCells`]).
fn run_kernel<V>(
    plan: &Plan,
    budget: &TileBudget,
    pts: &[TilePoint],
    region: Aabb,
    cells: Option<Proof>,
    f: &mut impl FnMut(&[TilePoint], &CloudRun) -> Result<RunOutput<V>, TilingError>,
) -> Result<RunOutput<V>, TilingError> {
    let occupancy = budget.occupancy;
    let positions: Vec<DVec3> = pts.iter().map(|p| p.p).collect();
    let ties: Vec<u64> = pts.iter().map(|p| p.index).collect();
    let owned: Vec<bool> = pts.iter().map(|p| p.owned).collect();
    let held: Vec<bool> = pts.iter().map(|p| p.held).collect();
    // Balls crossing the region are complete when the loaded cells hold them, or when the
    // occupancy cells they touch hold nothing more.
    let loaded = std::sync::OnceLock::new();
    let complete = |p: DVec3, r2: f64| {
        cells.is_some_and(|c| c(p, r2))
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
        complete: (occupancy.is_some() || cells.is_some())
            .then_some(&complete as &(dyn Fn(DVec3, f64) -> bool + Sync)),
        wanted: Some(&owned),
        held: held.iter().any(|&h| h).then_some(held.as_slice()),
        beams: None,
    };
    f(pts, &run)
}

/// The owned points of a kernel run whose results it did not prove exact (`exact[i]` for
/// `pts[i]`).
fn pending_of(pts: &[TilePoint], exact: &[bool]) -> Vec<Pending> {
    pts.iter()
        .zip(exact)
        .filter(|(p, e)| p.owned && !**e)
        .map(|(p, _)| (p.index, p.p))
        .collect()
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

/// Splits `group` (of items at the pending point `at` gives) at the median of its longest axis
/// (ties by global index), so the cut is the same on every run.
fn halves<T>(group: &mut Vec<T>, at: impl Fn(&T) -> Pending) -> (Vec<T>, Vec<T>) {
    let points: Vec<Pending> = group.iter().map(&at).collect();
    let size = grown(&points, 0.0).size();
    let axis = if size.x >= size.y && size.x >= size.z {
        0
    } else if size.y >= size.z {
        1
    } else {
        2
    };
    group.sort_unstable_by(|a, b| {
        let (a, b) = (at(a), at(b));
        a.1[axis].total_cmp(&b.1[axis]).then(a.0.cmp(&b.0))
    });
    let right = group.split_off(group.len() / 2);
    (std::mem::take(group), right)
}

/// The (tile, part) spill files holding the owned records of the tiles whose core touches
/// `span`, in the order a load appends them.
fn reads_of(plan: &Plan, span: &Aabb) -> Vec<(usize, u64)> {
    touching(plan, span)
        .flat_map(|t| (0..plan.parts()).map(move |part| (t, part)))
        .collect()
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
                    let still = pending_of(&loaded, &exact);
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
    load_where(dir, plan, (bx, |_| true), inside, group, max)
}

/// A group's shell that fits, its points, and the halo it was built for.
type Fit = (Shell, Vec<TilePoint>, f64);

/// Most halvings of the round's halo a group that does not fit tries ([`load_widest`]).
const MAX_DESCENT: usize = 8;

/// The shell of `group` at `halo` and its points, or, when that holds more points than a run
/// may and no half of a group larger than [`LONE_GROUP`] passes the lower bounds at `halo`
/// ([`a_half_may_fit`]: then it is halved instead), at the widest of `halo / 2`, `halo / 4`, …
/// above `floor` whose shell fits (at most [`MAX_DESCENT`] of them); with the halo it was loaded
/// at. `Err(found)` when none fits, with what the load at `halo` found.
///
/// Why: the second round jumps from twice a narrowed tile's halo to the plan's halo, and beside
/// a dense cluster the shell at the plan's halo holds more than the budget, while the points'
/// k-NN balls are far smaller: their results are proven at a halo in between, which the jump
/// skipped. Without this, such groups were halved down to the lone path ([`by_cells`]), which
/// took about half the tiles phase of the 10 M cluttered scene at 200 MiB (DECISIONS, issue 16).
/// A refused halo costs the lower bounds of [`load_shell`], not a read.
fn load_widest(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    group: &[Pending],
    (floor, halo): (f64, f64),
) -> Result<Result<Fit, u64>, TilingError> {
    let mut found = None;
    let mut h = halo;
    for _ in 0..=MAX_DESCENT {
        check_cancel()?;
        let points = group.iter().map(|g| g.1);
        let shell = Shell::around(plan.origin, plan.bounds, points, h, budget.max_points);
        match load_shell(dir, plan, budget, (&shell, h), group)? {
            Ok(loaded) => return Ok(Ok((shell, loaded, h))),
            Err(n) => {
                found.get_or_insert(n);
            }
        }
        if h == halo && group.len() > LONE_GROUP && a_half_may_fit(dir, plan, budget, group, halo)?
        {
            // Halving may make it fit at the round's halo, which proves more than a narrower one.
            break;
        }
        h *= 0.5;
        if h <= floor {
            break;
        }
    }
    Ok(Err(found.unwrap_or(0)))
}

/// Whether one of the halves `group` would be cut into passes the lower bounds of
/// [`refusal`] at `halo`.
fn a_half_may_fit(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    group: &[Pending],
    halo: f64,
) -> Result<bool, TilingError> {
    let mut g = group.to_vec();
    let (a, b) = halves(&mut g, |p| *p);
    for half in [a, b] {
        let points = half.iter().map(|g| g.1);
        let shell = Shell::around(plan.origin, plan.bounds, points, halo, budget.max_points);
        if refusal(dir, plan, budget, (&shell, halo), &half)?.is_none() {
            return Ok(true);
        }
    }
    Ok(false)
}

/// Cells the occupancy grid's lower bound on a group's points may visit (a few milliseconds).
const BOUND_VISITS: usize = 1 << 16;

/// Every point of the cloud in `shell`'s cells (from the owned records of the tiles its span
/// touches), the points of `group` marked owned; `Err(found)` when there are more than the
/// budget allows one run (at least `found`: a lower bound, or what a read counted). Two lower
/// bounds come first ([`refusal`]), the occupancy grid's cells inside the group's halo cubes
/// (which the shell covers) and the spill blocks the shell covers (from the block tables alone):
/// past the budget, the group is refused without reading a record. In the 10 M cluttered scene
/// at 200 MiB nine loads in ten used to fail, each after reading about 300 000 records
/// (DECISIONS, issue 16). The bounds come from the plan's files, the same on every run, so the
/// same loads happen.
fn load_shell(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    (shell, halo): (&Shell, f64),
    group: &[Pending],
) -> Result<Result<Vec<TilePoint>, u64>, TilingError> {
    if let Some(found) = refusal(dir, plan, budget, (shell, halo), group)? {
        return Ok(Err(found));
    }
    let span = shell.span();
    let near = |b: &Aabb| shell.meets(b);
    load_where(
        dir,
        plan,
        (&span, near),
        |p| shell.contains(p),
        group,
        budget.max_points,
    )
}

/// The lower bound on the points of `shell` (built for `group` at `halo`) that proves it holds
/// more than the budget allows one run, or `None` when neither bound does (see [`load_shell`]).
fn refusal(
    dir: &Path,
    plan: &Plan,
    budget: &TileBudget,
    (shell, halo): (&Shell, f64),
    group: &[Pending],
) -> Result<Option<u64>, TilingError> {
    let Some(m) = budget.max_points else {
        return Ok(None);
    };
    if let Some(o) = budget.occupancy {
        // The cube of half-side `halo` around each group point lies in the shell's cells.
        let inside = o.points_within_cubes(
            group.iter().map(|g| g.1),
            halo * (1.0 - 1e-6),
            BOUND_VISITS,
            m,
        );
        if inside > m {
            return Ok(Some(inside));
        }
    }
    // The spill blocks whose box the shell covers are kept whole by the load.
    let span = shell.span();
    let reads = reads_of(plan, &span);
    let within = reads
        .par_iter()
        .map(|&(t, part)| owned_within(dir, part..part + 1, t, |b| shell.covers(b)))
        .try_reduce(|| 0, |a, b| Ok(a.saturating_add(b)))?;
    Ok((within > m).then_some(within))
}

/// Every point of the cloud in `span` for which `keep` holds (from the owned records of the
/// tiles `span` touches, in the blocks `near` passes: see [`read_owned_near`]), the points of
/// `group` marked owned; `Err(found)` when there are more than `max`. The spill files of each
/// (tile, part) are read side by side on the pool and appended in (tile, part) order, so the
/// list is the one a serial read gives; a shared count stops every read once past `max`
/// (`found` is then at least `max + 1`, how far past depends on the threads).
fn load_where(
    dir: &Path,
    plan: &Plan,
    (span, near): (&Aabb, impl Fn(&Aabb) -> bool + Sync),
    keep: impl Fn(DVec3) -> bool + Sync,
    group: &[Pending],
    max: Option<u64>,
) -> Result<Result<Vec<TilePoint>, u64>, TilingError> {
    let mut mine: Vec<u64> = group.iter().map(|g| g.0).collect();
    mine.sort_unstable();
    let max = max.unwrap_or(u64::MAX);
    let count = AtomicU64::new(0);
    let reads = reads_of(plan, span);
    let runs = reads
        .par_iter()
        .map(|&(t, part)| {
            let mut pts = Vec::new();
            if count.load(Ordering::Relaxed) > max {
                return Ok(pts);
            }
            read_owned_near(
                dir,
                part..part + 1,
                t,
                (span, &near),
                |p| {
                    // Past the limit the points are counted, not kept.
                    keep(p) && count.fetch_add(1, Ordering::Relaxed) < max
                },
                &mut pts,
            )?;
            Ok(pts)
        })
        .collect::<Result<Vec<Vec<TilePoint>>, TilingError>>()?;
    let found = count.into_inner();
    if found > max {
        return Ok(Err(found));
    }
    let mut pts = Vec::with_capacity(runs.iter().map(Vec::len).sum());
    for run in runs {
        pts.extend(run);
    }
    for p in &mut pts {
        p.owned = mine.binary_search(&p.index).is_ok();
    }
    Ok(Ok(pts))
}
