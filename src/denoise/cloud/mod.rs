//! Point-cloud operators on a set of points: the one entry point that both the in-memory path and
//! each tile of the out-of-core path run.
//!
//! # Brief overview
//!
//! A [`CloudRun`] is a set of finite points with their global indices (the tie keys of neighbour
//! ranking) and, for a tile, the box that holds every point the caller has (`region`). [`run`]
//! lays the points out in spatial order, builds the k-NN graph once, and runs the method's passes
//! over it. It returns every point's result together with whether that result is **exact**, i.e.
//! equal to what the whole cloud would give:
//!
//! ```text
//!   region (core + halo)                       tainted at hop 0: the k-NN ball leaves the region,
//!   ┌──────────────────────────┐               so the list may miss a point outside
//!   │ ·  ·  · ·  ·  ·  ·  · ·  │←─ hop 0       tainted at hop h+1: some list member is tainted
//!   │ · ┌──────────────────┐ · │←─ hop 1       at hop h (its value depends on the list)
//!   │ · │ core (owned)     │ · │               a result is exact when the point is untainted
//!   │ · │  all exact when  │ · │               after `reach(params)` hops
//!   │ · │  halo ≥ reach    │ · │
//!   │ · └──────────────────┘ · │
//!   └──────────────────────────┘
//! ```
//!
//! A method's reach ([`reach`]) is the number of hops the taint must spread for a result to be
//! exact: a QEM update reads the list members' normals, whose PCA reads *their* lists, so the
//! paper's one update is exact once no member's list is tainted (1 hop); a bilateral pass counts
//! 1 too. The caller grows the halo until every owned point is exact.
//! For the guarded default, a point whose class does not move (scatter, sparse) keeps its input
//! position and lends its neighbours nothing beyond its class: it is exact one hop in, and taint
//! does not spread through it ([`Taint::spread`]).
//!
//! Every list is capped at the cloud's isolation radius ([`super::isolation`]): a point with
//! fewer than k points that near is isolated, stays where it is and lends no plane to anyone,
//! so no result depends on anything farther than that radius per hop.
//!
//! Global scalars (the bilateral σc, the mean spacing, the guarded operator's noise) come from
//! exact sums that merge across tiles to the same bits as over the whole cloud.
//!
//! # Files
//!
//! - `mod.rs`: the run ([`CloudRun`], [`run`], [`run_all`]) and the method's passes;
//! - `globals.rs`: [`Globals`] and their mergeable partials;
//! - `graph.rs`: the k-NN graph of a run, listed whole or from the wanted points, then capped;
//! - `taint.rs`: which results are exact (the taint and how it spreads);
//! - `hops.rs`: how many hops from the wanted points each pass is needed.

mod globals;
mod graph;
mod hops;
mod program;
mod taint;

pub use globals::{
    Globals, GlobalsPartial, NOISE_SAMPLE, globals_partial, in_noise_sample, needs_globals,
};

use glam::DVec3;
use rayon::prelude::*;

use self::globals::{globals_k, partial_of};
use self::graph::{Graph, Listing, Stops, capped, graph, listing, typical_from_lists};
use self::hops::{graded, hop_depths, update_reach};
use self::taint::Taint;
use super::common::{Within, merge_step, stay};
use super::guarded::{self, Guard};
use super::normals::{filter_point_normals, filter_point_normals_within, pca_normals};
use super::qem::is_duplicate;
use super::structure::{
    Beams, Structure, classify_within, local_fits_within, noise_scale_within, planes,
};
use super::written::of_cycle;
use super::{DenoiseError, Method, Params, Stats, StructureCounts, Timer, bilateral, qem};
use crate::neighbours::NeighboursError;
use crate::points::{Aabb, PointNormal};

/// True when `params` run the guarded QEM operator.
pub(super) fn guarded_qem(params: &Params) -> bool {
    params.method == Method::Qem && params.guard
}

/// True when the points whose class does not move keep their input position whatever lies more
/// than a hop away (see `run_on`): the guarded operator in one cycle (with more, a later class
/// could move them) and without written normals (they read the filter's hops).
fn settles(params: &Params) -> bool {
    guarded_qem(params) && params.schedule(false).cycles == 1 && !params.write_normals
}

/// The hops left, out of [`reach`], within which a run computes the classes (so a point that
/// stays may stop the listing there, [`crate::neighbours::Prune::least`]); `None` when points do not settle.
fn stops(params: &Params) -> Option<usize> {
    settles(params).then(|| reach(params).saturating_sub(graded(&params.schedule(false)).classes))
}

/// Number of k-NN graph hops a result depends on (see the module overview).
pub fn reach(params: &Params) -> usize {
    let s = params.schedule(false);
    match params.method {
        // The guarded operator reads lists as far out as its last cycle computes local fits
        // (`graded`: the updates, the gains one hop past the first, the filter iterations, the
        // classes reading their members' fits), and each earlier cycle one hop past that (the
        // next cycle's fits read the members' moved positions). 7 for the default; it was
        // `cycles × (3 + filter + max(updates, 2))`, 8, until 2026-12-06 (DECISIONS "The paper
        // operator's reach is one hop").
        Method::Qem if params.guard => s.cycles * graded(&s).fits + s.cycles.saturating_sub(1),
        // Without the guard, a hop is counted where a pass reads what its members computed:
        // taint starts at the points whose own list may be wrong (hop 0), so a pass that reads a
        // point's own list, as the first cycle's PCA normals do, adds none. Each filter
        // iteration and each update reads the members' normals and positions (1 each); a later
        // cycle's normals read the members' moved positions (1). The paper's one update: 1 hop
        // (it was counted 3 until 2026-12-06, which grew cluttered tiles' halos for nothing;
        // DECISIONS "The paper operator's reach is one hop"). Written normals' classes read the
        // members' fits, one hop past the last cycle's normals.
        Method::Qem => {
            let (c, f, u) = (s.cycles, s.filter, s.updates);
            let positions = c * (f + u) + c.saturating_sub(1);
            let written = if params.write_normals {
                c.saturating_sub(1) * (f + u + 1) + f + 1
            } else {
                0
            };
            positions.max(written).max(1)
        }
        // The written classes of the last cycle read the members' fits: one hop past its
        // normals, which is past a bilateral pass's reach (the QEM cycles reach further anyway).
        Method::Bilateral if params.write_normals => s.cycles + 1,
        Method::Bilateral => s.cycles,
    }
}

/// The points of one run.
#[derive(Clone, Copy)]
pub struct CloudRun<'a> {
    /// Finite positions.
    pub positions: &'a [DVec3],
    /// Global index of each point (the tie key of neighbour ranking); distinct.
    pub ties: &'a [u64],
    /// Origin of the relative coordinates neighbour search uses; the same for every tile.
    pub origin: DVec3,
    /// The box holding every point the caller has, `None` for the whole cloud.
    pub region: Option<Aabb>,
    /// The cap on every list, the same for every tile: the cloud's isolation radius
    /// ([`super::isolation::radius`]), or the user's `--radius` where smaller
    /// ([`super::isolation::cap`]); `None` caps no list.
    pub isolation: Option<f64>,
    /// True when the cap is the user's `--radius`: a capped list still serves with
    /// [`super::isolation::MIN_LIST`] members or more ([`super::isolation::least_list`]).
    pub short_lists: bool,
    /// For a tile: the points whose results the caller keeps (its owned ones), `None` for all.
    /// When they are few, only the lists their results depend on are computed, and every other
    /// result is reported not exact.
    pub wanted: Option<&'a [bool]>,
    /// Points that keep their position but serve as neighbours (`--classes`), `None` for none.
    pub held: Option<&'a [bool]>,
    /// Each point's beam (unit direction from the sensor, zero where unknown), `None` for
    /// none; the guarded operator fits and moves along it ([`super::beams`]). A run of params
    /// with a [`super::SensorOrigin::At`] computes them from the positions when this is `None`.
    pub beams: Option<&'a [DVec3]>,
    /// For a tile: whether the ball (centre, squared radius) holds no point the caller does not
    /// have, for balls that leave `region` (the tiling's occupancy grid proves it). `None`: only
    /// balls inside `region` are complete.
    pub complete: Option<&'a (dyn Fn(DVec3, f64) -> bool + Sync)>,
}

/// Per-point results of a run, in the run's input order.
#[derive(Debug, Clone)]
pub struct CloudResult {
    /// New positions.
    pub positions: Vec<DVec3>,
    /// True where the result provably equals the whole-cloud result.
    pub exact: Vec<bool>,
    /// Mean distance to the other members of the point's k-NN list (the outlier statistic).
    pub knn_mean: Vec<f64>,
    /// True where the point duplicates one with a lower global index.
    pub duplicate: Vec<bool>,
    /// True where the point's neighbourhood had no plane (coincident or collinear) in pass 1.
    pub degenerate: Vec<bool>,
    /// Why a pass left the point in place (`common::stay` flags, or-ed over passes).
    pub stayed: Vec<u8>,
    /// The neighbourhood class of the first cycle (`Structure` code) for the guarded operator,
    /// `None` for the others.
    pub structure: Option<Vec<u8>>,
    /// With [`Params::write_normals`]: what the output writes per point, from the last cycle
    /// ([`super::written`]); exact wherever the position is.
    pub normals: Option<Vec<PointNormal>>,
    /// Phase timings.
    pub stats: Stats,
}

impl CloudResult {
    /// Adds the counters of the points `counted` selects to `stats` (owned points of a tile).
    pub fn book(&self, input: &[DVec3], counted: impl Fn(usize) -> bool, stats: &mut Stats) {
        let mut s = Stats::default();
        for i in (0..input.len()).filter(|&i| counted(i)) {
            s.points += 1;
            s.duplicates += self.duplicate[i] as u64;
            s.degenerate_neighbourhoods += self.degenerate[i] as u64;
        }
        if let Some(classes) = &self.structure {
            let mut c = [0u64; 6];
            for i in (0..input.len()).filter(|&i| counted(i)) {
                c[classes[i] as usize] += 1;
            }
            s.structure = StructureCounts::from_codes(c);
        }
        s.book_moves(input, &self.positions, &self.stayed, counted);
        stats.merge(&s);
    }
}

/// [`NeighboursError::Cancelled`] once the cancel flag installed on this thread
/// ([`crate::neighbours::with_cancel`]) is set: checked between the passes of [`run`], so a
/// cancelled run stops after the pass in flight.
fn check_cancel() -> Result<(), DenoiseError> {
    if crate::neighbours::cancel_requested() {
        Err(crate::neighbours::NeighboursError::Cancelled.into())
    } else {
        Ok(())
    }
}

/// Runs the point operator of `params` on `run`.
///
/// # Errors
/// Fewer points than k.
pub fn run(
    run: &CloudRun,
    params: &Params,
    globals: &Globals,
) -> Result<CloudResult, DenoiseError> {
    let timer = Timer::start();
    let own = own_beams(run, params);
    let run = &with_beams(run, own.as_deref());
    let stops = stops(params).map(|least| Stops {
        least,
        noise: globals.noise,
    });
    let g = graph(run, params.k(), reach(params), stops)?;
    run_on(run, params, globals, g, timer)
}

/// The beams of a run of the guarded operator whose params give one sensor position and whose
/// caller gave none ([`CloudRun::beams`]), from the positions; `None` otherwise.
pub(super) fn own_beams(run: &CloudRun, params: &Params) -> Option<Vec<DVec3>> {
    let o = params.sensor_origin.point()?;
    (guarded_qem(params) && run.beams.is_none())
        .then(|| super::beams::from_origin(run.positions, o))
}

/// `run` with `beams` where it has none.
pub(super) fn with_beams<'a>(run: &CloudRun<'a>, beams: Option<&'a [DVec3]>) -> CloudRun<'a> {
    CloudRun {
        beams: run.beams.or(beams),
        ..*run
    }
}

/// [`run`] on the run's k-NN graph `g`; `timer` started before the graph was built (its time is
/// booked to `neighbours`).
fn run_on(
    run: &CloudRun,
    params: &Params,
    globals: &Globals,
    g: Graph,
    mut timer: Timer,
) -> Result<CloudResult, DenoiseError> {
    let mut stats = Stats {
        noise_estimate: guarded_qem(params).then_some(globals.noise),
        ..Stats::default()
    };
    let k = params.k();
    let taint = Taint::of(run, &g);
    let Graph {
        frame,
        lists,
        radii,
        index,
        capped,
        isolated,
        listed: _,
        beams,
    } = g;
    let beams = Beams {
        dirs: beams.as_deref().filter(|_| guarded_qem(params)),
        noise: globals.noise,
    };
    let n = frame.positions.len();
    let duplicate: Vec<bool> = (0..n)
        .into_par_iter()
        .map(|j| is_duplicate(&frame.positions, &lists, &frame.ties, j))
        .collect();
    // The outlier statistic; a capped list counts each missing member at the cap (so a far
    // outlier scores the isolation radius, not its distance to the scene).
    let knn_mean: Vec<f64> = (0..n)
        .into_par_iter()
        .map(|j| {
            let dist2 = |u: u32| index.dist2(j, u as usize);
            program::knn_mean_of(lists.get(j), j, dist2, capped[j], (k, run.isolation))
        })
        .collect();
    drop(index);
    // The step bound of each point: the largest k-NN radius among its neighbours, i.e. the scale
    // at which the surface around it is sampled. An isolated point's own radius reaches the
    // distant surface it would be projected onto; its neighbours' radii do not. The guarded
    // operator bounds its steps by the noise instead and needs none.
    let guard = guarded_qem(params);
    let limits: Vec<f64> = (0..if guard { 0 } else { n })
        .into_par_iter()
        .map(|j| {
            lists
                .get(j)
                .iter()
                .filter(|&&u| u as usize != j)
                .map(|&u| radii[u as usize])
                .fold(0.0, f64::max)
        })
        .collect();
    timer.lap("neighbours", &mut stats);
    check_cancel()?;

    let sched = params.schedule(false);
    // Hops from the wanted points (frame order), up to the last cycle's reach (`graded`).
    let depth: Option<Vec<u8>> = run.wanted.filter(|_| guard).map(|w| {
        let seeds: Vec<bool> = frame.order.iter().map(|&i| w[i as usize]).collect();
        hop_depths(&lists, &seeds, graded(&sched).fits)
    });
    let mut cur = frame.positions.clone();
    let mut stayed = vec![0u8; n];
    let mut degenerate = vec![false; n];
    let mut structure = None;
    // Points that stay where they are whatever lies more than a hop away (see `settled`).
    let mut settled = vec![false; n];
    let held: Vec<bool> = match run.held {
        Some(h) => frame.order.iter().map(|&i| h[i as usize]).collect(),
        None => Vec::new(),
    };
    let mut written = None;
    // After every pass (Jacobi: the next pass reads these positions).
    let hold = |cur: &mut Vec<DVec3>, stayed: &mut [u8]| {
        for (j, _) in isolated.iter().enumerate().filter(|(_, i)| **i) {
            cur[j] = frame.positions[j];
            stayed[j] |= stay::ISOLATED;
        }
        for (j, _) in held.iter().enumerate().filter(|(_, h)| **h) {
            cur[j] = frame.positions[j];
            stayed[j] |= stay::HELD;
        }
    };
    for pass in 0..sched.cycles {
        if guard {
            // The last cycle's passes only as far as a wanted result reads them.
            let last = pass + 1 == sched.cycles;
            let near = graded(&sched);
            let within = |most| match (&depth, last) {
                (Some(d), true) => Within::Hops(d, most),
                _ => Within::All,
            };
            let mut fits = local_fits_within(&cur, &lists, within(near.fits), beams);
            for (f, _) in fits.iter_mut().zip(&isolated).filter(|(_, i)| **i) {
                *f = super::structure::LocalFit::isolated();
            }
            let classes = classify_within(&fits, &lists, &radii, within(near.classes));
            let noise = noise_scale_within(&fits, &lists, within(near.guard));
            let bound: Vec<f64> = noise
                .iter()
                .map(|&s| s.min(guarded::GLOBAL * globals.noise))
                .collect();
            if pass == 0 {
                for (d, c) in degenerate.iter_mut().zip(&classes) {
                    *d = *c == Structure::Degenerate;
                }
                structure = Some(classes.iter().map(|c| *c as u8).collect::<Vec<u8>>());
            }
            if last && settles(params) {
                let classed = within(near.classes);
                settled = (0..n)
                    .map(|j| classed.has(j) && !classes[j].moves())
                    .collect();
            }
            let planes = planes(&fits, &classes);
            let normals = filter_point_normals_within(
                &cur,
                &lists,
                &radii,
                &planes,
                (params.sigma_r_floor(false), sched.filter),
                within(near.guard),
            );
            if params.write_normals && last {
                let fc = Some((fits.as_slice(), classes.as_slice()));
                written = Some(of_cycle(&cur, &lists, &radii, &isolated, &normals, fc));
            }
            timer.lap("normals", &mut stats);
            check_cancel()?;
            let g = Guard {
                start: &frame.positions,
                normals: &normals,
                fits: &fits,
                classes: &classes,
                noise: &noise,
                bound: &bound,
                radii: &radii,
                max_move: params.max_move,
                beams,
            };
            let mut gain = None;
            for u in 0..sched.updates {
                // The last cycle's updates only where a wanted result depends on them.
                let active = match (&depth, last) {
                    (Some(d), true) => Some(update_reach(d, sched.updates, u)),
                    _ => None,
                };
                let step = guarded::step(&cur, &lists, &g, params, &mut gain, active.as_deref());
                cur = merge_step(step, &mut stayed);
                hold(&mut cur, &mut stayed);
                check_cancel()?;
            }
            timer.lap("solve", &mut stats);
            continue;
        }
        let (mut normals, _) = pca_normals(&cur, &lists);
        if pass == 0 {
            for (d, (nrm, p)) in degenerate.iter_mut().zip(normals.iter().zip(&cur)) {
                *d = *nrm == DVec3::ZERO && p.is_finite();
            }
        }
        // An isolated point lends no plane.
        for (nrm, _) in normals.iter_mut().zip(&isolated).filter(|(_, i)| **i) {
            *nrm = DVec3::ZERO;
        }
        let normals = match params.method {
            Method::Qem if sched.filter > 0 => filter_point_normals(
                &cur,
                &lists,
                &radii,
                &normals,
                params.sigma_r_floor(false),
                sched.filter,
            ),
            _ => normals,
        };
        if params.write_normals && pass + 1 == sched.cycles {
            written = Some(of_cycle(&cur, &lists, &radii, &isolated, &normals, None));
        }
        timer.lap("normals", &mut stats);
        check_cancel()?;
        match params.method {
            Method::Qem => {
                for _ in 0..sched.updates {
                    let step = qem::points_step(&cur, &lists, &limits, &normals, params);
                    cur = merge_step(step, &mut stayed);
                    hold(&mut cur, &mut stayed);
                    check_cancel()?;
                }
            }
            Method::Bilateral => {
                let step = bilateral::points_step(&cur, &lists, &normals, globals.spacing);
                cur = merge_step(step, &mut stayed);
                hold(&mut cur, &mut stayed);
            }
        }
        timer.lap("solve", &mut stats);
    }
    if let Some(m) = params.max_move {
        for ((c, &p0), st) in cur.iter_mut().zip(&frame.positions).zip(&mut stayed) {
            let (p, flag) = guarded::clamp(p0, *c, m);
            *c = p;
            *st |= flag;
        }
    }
    // A point whose class does not move keeps its input position (and its counters), lends no
    // plane, no line and no offset, so what it gives the points listing it, and its own result,
    // are exact once its class is: its own list and its members' fits and radii, one hop (with
    // more cycles a later class could move it; written normals read the filter's hops). Taint
    // does not spread through such a point.
    let blocked: Vec<bool> = (0..n).map(|j| settled[j] && !taint.class[j]).collect();
    let tainted = taint.spread(&lists, reach(params), &blocked);
    let exact: Vec<bool> = (0..n).map(|j| !tainted[j] || blocked[j]).collect();
    Ok(CloudResult {
        positions: frame.restore(&cur),
        exact: frame.restore(&exact),
        knn_mean: frame.restore(&knn_mean),
        duplicate: frame.restore(&duplicate),
        degenerate: frame.restore(&degenerate),
        stayed: frame.restore(&stayed),
        structure: structure.map(|c| frame.restore(&c)),
        normals: written.map(|w| frame.restore(&w)),
        stats,
    })
}

/// [`run`] of a whole cloud (no region, no wanted points) on its k-NN graph `g`, as the passes
/// of a [`program::Program`] executed one after the other over every point; `timer` started
/// before the graph was built (its time is booked to `neighbours`).
fn run_whole(
    run: &CloudRun,
    params: &Params,
    globals: &Globals,
    g: Graph,
    mut timer: Timer,
) -> Result<CloudResult, DenoiseError> {
    use program::{Program, flag};
    let mut stats = Stats {
        noise_estimate: guarded_qem(params).then_some(globals.noise),
        ..Stats::default()
    };
    let k = params.k();
    let Graph {
        frame,
        lists,
        radii,
        index,
        capped,
        isolated,
        listed: _,
        beams,
    } = g;
    let n = frame.positions.len();
    let prog = Program::new(params);
    let mut st = prog.state(n, false);
    let held = |j: usize| run.held.is_some_and(|h| h[frame.order[j] as usize]);
    st.flags = (0..n)
        .into_par_iter()
        .map(|j| {
            let mut f = 0;
            if isolated[j] {
                f |= flag::ISOLATED;
            }
            if capped[j] {
                f |= flag::CAPPED;
            }
            if held(j) {
                f |= flag::HELD;
            }
            if is_duplicate(&frame.positions, &lists, &frame.ties, j) {
                f |= flag::DUPLICATE;
            }
            f
        })
        .collect();
    st.knn_mean = (0..n)
        .into_par_iter()
        .map(|j| {
            let dist2 = |u: u32| index.dist2(j, u as usize);
            program::knn_mean_of(lists.get(j), j, dist2, capped[j], (k, run.isolation))
        })
        .collect();
    drop(index);
    st.radii = radii;
    st.ties.clone_from(&frame.ties);
    st.pos[0].clone_from(&frame.positions);
    st.beams = beams.filter(|_| guarded_qem(params)).unwrap_or_default();
    timer.lap("neighbours", &mut stats);
    check_cancel()?;
    for &p in &prog.passes {
        prog.run(p, &mut st, &lists, (params, globals), program::At::All(n));
        prog.release(p, &mut st);
        timer.lap(p.phase(), &mut stats);
        check_cancel()?;
    }
    let positions: Vec<DVec3> = (0..n).map(|j| prog.finish(&mut st, params, j)).collect();
    let bit = |f: u8| -> Vec<bool> { st.flags.iter().map(|&x| x & f != 0).collect() };
    let guard = guarded_qem(params);
    Ok(CloudResult {
        positions: frame.restore(&positions),
        exact: vec![true; n],
        knn_mean: frame.restore(&st.knn_mean),
        duplicate: frame.restore(&bit(flag::DUPLICATE)),
        degenerate: frame.restore(&bit(flag::DEGENERATE)),
        stayed: frame.restore(&st.stayed),
        structure: guard.then(|| {
            let c: Vec<u8> = st.classes[0].iter().map(|&c| c as u8).collect();
            frame.restore(&c)
        }),
        normals: params.write_normals.then(|| frame.restore(&st.written)),
        stats,
    })
}

/// What [`run_all`] gives, one entry per input position.
#[derive(Debug, Clone)]
pub struct AllResult {
    /// New positions (points failing [`crate::points::in_range`] stay as they were).
    pub positions: Vec<DVec3>,
    /// Mean distance to the other members of the point's k-NN list (the outlier statistic);
    /// NaN for points not processed.
    pub knn_mean: Vec<f64>,
    /// The neighbourhood class of the first cycle (`Structure` code) for the guarded operator,
    /// [`Structure::Degenerate`] for points not processed; `None` for the other operators.
    pub structure: Option<Vec<u8>>,
    /// With [`Params::write_normals`]: what the output writes per point ([`super::written`]),
    /// [`PointNormal::NONE`] for points not processed; `None` otherwise.
    pub normals: Option<Vec<PointNormal>>,
    /// What happened.
    pub stats: Stats,
}

impl From<AllResult> for super::Output {
    fn from(r: AllResult) -> super::Output {
        super::Output {
            positions: r.positions,
            stats: r.stats,
        }
    }
}

/// Runs the point operator on a whole cloud in memory (global index = position in `positions`).
/// Points failing [`crate::points::in_range`] (non-finite or beyond ±10¹²) are left as they are
/// and counted.
///
/// # Errors
/// Fewer finite points than k.
pub fn run_all(positions: &[DVec3], params: &Params) -> Result<AllResult, DenoiseError> {
    run_all_with(positions, params, PerPoint::default())
}

/// What a caller knows of each point of a cloud beyond its position (one entry per position).
#[derive(Debug, Clone, Copy, Default)]
pub struct PerPoint<'a> {
    /// Points that keep their position but still serve as neighbours (`--classes`).
    pub held: Option<&'a [bool]>,
    /// Each point's beam ([`CloudRun::beams`]; from a trajectory), zero where unknown.
    pub beams: Option<&'a [DVec3]>,
}

/// [`run_all`] with the points `per.held` marks kept in place (they still serve as
/// neighbours), and the beams `per.beams` gives.
///
/// # Errors
/// Fewer finite points than k.
pub fn run_all_with(
    positions: &[DVec3],
    params: &Params,
    per: PerPoint,
) -> Result<AllResult, DenoiseError> {
    let held = per.held;
    // The isolation radius (the typical radius's probes) is neighbour work: booked to
    // `neighbours` with the graph.
    let timer = Timer::start();
    let finite: Vec<usize> = (0..positions.len())
        .filter(|&i| crate::points::in_range(positions[i]))
        .collect();
    let pts: Vec<DVec3> = finite.iter().map(|&i| positions[i]).collect();
    let ties: Vec<u64> = finite.iter().map(|&i| i as u64).collect();
    let held: Option<Vec<bool>> = held.map(|h| finite.iter().map(|&i| h[i]).collect());
    let beams: Option<Vec<DVec3>> = per.beams.map(|b| finite.iter().map(|&i| b[i]).collect());
    let origin = super::origin_of(&pts);
    let k = params.k();
    let kg = globals_k(params);
    let listed_run = CloudRun {
        positions: &pts,
        ties: &ties,
        origin,
        region: None,
        isolation: None,
        short_lists: false,
        complete: None,
        wanted: None,
        held: None,
        beams: None,
    };
    // Where the planner's sample is the whole cloud, the isolation radius is read from the run's
    // own lists (one k-NN pass, not two: the probes' pass was about 10 % of a 120 k-point run's
    // wall time); elsewhere it comes from the sample, as the tiling planner computes it. A
    // listing that fails (too few indexable points, a cancel) takes the other path, which fails
    // the same way, with the errors it always gave.
    let own = (pts.len() <= super::isolation::SAMPLE
        && pts.len() >= k.max(kg)
        && (k >= kg || !needs_globals(params)))
    .then(|| listing(&listed_run, k, 0, None).ok())
    .flatten()
    .and_then(|l| typical_from_lists(&l, pts.len() as u64, k).map(|r_k| (l, r_k)));
    let (listed, isolation) = match own {
        Some((l, r_k)) => (Some(l), super::isolation::radius_of(r_k)),
        None => (None, super::isolation::of_cloud(&pts, &ties, origin, k)),
    };
    let (isolation, short_lists) = super::isolation::cap(isolation, params.radius);
    // The run's graph: from the lists above, or one pass now.
    let graph_of = |r: &CloudRun, listed: Option<Listing>| match listed {
        Some(l) => Ok(capped(r, k, l)),
        None => graph(r, k, 0, None),
    };
    let r = CloudRun {
        positions: &pts,
        ties: &ties,
        origin,
        region: None,
        isolation,
        short_lists,
        complete: None,
        wanted: None,
        held: held.as_deref(),
        beams: beams.as_deref(),
    };
    let own = own_beams(&r, params);
    let r = with_beams(&r, own.as_deref());
    let result = if !needs_globals(params) {
        run_whole(
            &r,
            params,
            &Globals::default(),
            graph_of(&r, listed)?,
            timer,
        )?
    } else if k >= kg {
        // One k-NN pass serves both: the pre-pass reads the first kg members of each list,
        // which are its kg-NN list to the bit (see `partial_of`).
        let g = graph_of(&r, listed).map_err(|e| match e {
            // As the separate pre-pass would fail first, on its kg.
            DenoiseError::Neighbours(NeighboursError::TooFewPoints { points, .. })
                if points < kg =>
            {
                NeighboursError::TooFewPoints { points, k: kg }.into()
            }
            e => e,
        })?;
        let n = pts.len() as u64;
        let sample = |i: usize| !guarded_qem(params) || in_noise_sample(ties[i], n);
        let globals = partial_of(params, &g, kg, sample).finish();
        run_whole(&r, params, &globals, g, timer)?
    } else {
        let globals = globals_partial(&r, params, pts.len() as u64, |_, _| true)?
            .0
            .finish();
        run_whole(&r, params, &globals, graph(&r, k, 0, None)?, timer)?
    };
    let mut stats = Stats::default();
    stats.merge(&result.stats);
    result.book(&pts, |_| true, &mut stats);
    stats.points = positions.len() as u64;
    stats.non_finite = (positions.len() - pts.len()) as u64;
    let mut out = positions.to_vec();
    let mut knn_mean = vec![f64::NAN; positions.len()];
    let mut structure = result
        .structure
        .as_ref()
        .map(|_| vec![Structure::Degenerate as u8; positions.len()]);
    let mut normals = result
        .normals
        .as_ref()
        .map(|_| vec![PointNormal::NONE; positions.len()]);
    for (j, &i) in finite.iter().enumerate() {
        out[i] = result.positions[j];
        knn_mean[i] = result.knn_mean[j];
        if let (Some(s), Some(r)) = (structure.as_mut(), result.structure.as_ref()) {
            s[i] = r[j];
        }
        if let (Some(n), Some(r)) = (normals.as_mut(), result.normals.as_ref()) {
            n[i] = r[j];
        }
    }
    Ok(AllResult {
        positions: out,
        knn_mean,
        structure,
        normals,
        stats,
    })
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::sync::atomic::AtomicBool;

    use super::*;

    /// A noisy grid plane, exact duplicates, a far cluster of 10 points (8 or more but fewer
    /// than 16 within the isolation radius: isolated at k = 16, not at k = 8) and far singles.
    fn issue9_cloud() -> Vec<DVec3> {
        let mut pts = Vec::new();
        for i in 0..60 {
            for j in 0..60 {
                let h = ((i * 7919 + j * 104_729) % 1000) as f64 / 1000.0;
                pts.push(DVec3::new(i as f64, j as f64, 0.05 * h));
            }
        }
        for i in 0..40 {
            pts.push(pts[i * 37]);
        }
        for i in 0..10 {
            pts.push(DVec3::new(5000.0 + i as f64, 3.0, 0.1 * (i % 3) as f64));
        }
        pts.push(DVec3::new(-9000.0, 0.0, 0.0));
        pts.push(DVec3::new(0.0, 9000.0, 1.0));
        pts
    }

    #[test]
    fn the_isolation_radius_from_the_runs_lists_is_the_samples() {
        // Duplicates, a far cluster and far singles; with and without strided probes.
        let mut big = issue9_cloud();
        for i in 0..6000 {
            big.push(DVec3::new(100.0 + (i % 80) as f64, (i / 80) as f64, 0.0));
        }
        for pts in [issue9_cloud(), big] {
            let ties: Vec<u64> = (0..pts.len() as u64).collect();
            let run = whole_run(&pts, &ties);
            for k in [9, 12, 16, 24] {
                let l = listing(&run, k, 0, None).unwrap();
                let own = typical_from_lists(&l, pts.len() as u64, k).unwrap();
                let sample = crate::denoise::isolation::sample(&pts, &ties);
                let want = crate::denoise::isolation::typical_radius(
                    &sample,
                    run.origin,
                    pts.len() as u64,
                    k,
                );
                assert!(want.is_some());
                assert_eq!(own, want, "k = {k}");
            }
            // Lists too short for the probes' neighbour: the sample's pass is needed.
            let l = listing(&run, 8, 0, None).unwrap();
            assert_eq!(typical_from_lists(&l, pts.len() as u64, 8), None);
        }
    }

    /// The whole cloud `pts` as one run, lists capped at its isolation radius for k = 16.
    fn whole_run<'a>(pts: &'a [DVec3], ties: &'a [u64]) -> CloudRun<'a> {
        let origin = crate::denoise::origin_of(pts);
        CloudRun {
            positions: pts,
            ties,
            origin,
            region: None,
            isolation: crate::denoise::isolation::of_cloud(pts, ties, origin, 16),
            short_lists: false,
            complete: None,
            wanted: None,
            held: None,
            beams: None,
        }
    }

    /// A deterministic jitter in [−0.5, 0.5) for grid point (i, j) of the test surfaces.
    fn jitter(i: usize, j: usize) -> f64 {
        ((i * 7919 + j * 104_729) % 1000) as f64 / 1000.0 - 0.5
    }

    /// A tile of `pts` (with `ties`): the points with x below `face`, their indices in `pts`,
    /// and the region holding every point of the cloud inside it.
    fn tile_below(
        pts: &[DVec3],
        ties: &[u64],
        face: f64,
    ) -> (Vec<usize>, Vec<DVec3>, Vec<u64>, Aabb) {
        let tile: Vec<usize> = (0..pts.len()).filter(|&i| pts[i].x < face).collect();
        let tile_pts = tile.iter().map(|&i| pts[i]).collect();
        let tile_ties = tile.iter().map(|&i| ties[i]).collect();
        let region = Aabb {
            min: DVec3::splat(-100.0),
            max: DVec3::new(face, 100.0, 100.0),
        };
        (tile, tile_pts, tile_ties, region)
    }

    #[test]
    fn issue9_globals_from_the_k_lists_equal_the_separate_pre_pass() {
        let pts = issue9_cloud();
        let ties: Vec<u64> = (0..pts.len() as u64).map(|i| 3 * i + 1).collect();
        let run = whole_run(&pts, &ties);
        let guarded = Params::default();
        let bilateral = Params {
            method: Method::Bilateral,
            ..Params::default()
        };
        for params in [guarded, bilateral] {
            let kg = globals_k(&params);
            let g = graph(&run, params.k(), 0, None).unwrap();
            // The far cluster is isolated in the k-list graph but not in the kg one.
            let capped = (0..pts.len())
                .filter(|&j| g.isolated[j] && g.lists.get(j).len() >= kg)
                .count();
            assert_eq!(capped, 10, "{:?}", params.method);
            let counted = |i: usize| !i.is_multiple_of(5);
            let n = pts.len() as u64;
            let separate = globals_partial(&run, &params, n, |i, _| counted(i))
                .unwrap()
                .0;
            let shared = partial_of(&params, &g, kg, counted);
            assert_eq!(shared, separate, "{:?}", params.method);
            assert!(separate.noise.count > 0 || separate.spacing.count() > 0);
        }
    }

    #[test]
    fn issue16_the_noise_of_a_large_cloud_is_the_median_over_its_sample_whichever_pass_lists_it() {
        let pts = issue9_cloud();
        let ties: Vec<u64> = (0..pts.len() as u64).collect();
        let run = whole_run(&pts, &ties);
        let params = Params::default();
        // As if the cloud had 4 × NOISE_SAMPLE points: one in four is sampled.
        let n = 4 * NOISE_SAMPLE;
        let sampled = |i: usize| in_noise_sample(ties[i], n);
        let share = (0..pts.len()).filter(|&i| sampled(i)).count() as f64 / pts.len() as f64;
        assert!((0.2..0.3).contains(&share), "{share}");
        // The in-memory path: the operator's 16-NN lists, the sample counted.
        let g = graph(&run, params.k(), 0, None).unwrap();
        let shared = partial_of(&params, &g, crate::denoise::structure::NEAR, sampled);
        // The pre-pass of a tile: only the sampled points listed (at their 8 nearest).
        let (separate, exact) = globals_partial(&run, &params, n, |_, _| true).unwrap();
        assert_eq!(shared, separate);
        let in_sample = (0..pts.len()).filter(|&i| sampled(i)).count() as u64;
        assert!(separate.noise.count <= in_sample && 2 * separate.noise.count > in_sample);
        assert!(
            exact.iter().all(|&e| e),
            "points out of the sample are done"
        );
        // A small cloud is read whole.
        let whole = globals_partial(&run, &params, pts.len() as u64, |_, _| true)
            .unwrap()
            .0;
        assert!(whole.noise.count > 3 * in_sample);
    }

    #[test]
    fn issue16_few_wanted_points_keep_their_results_and_the_rest_are_not_exact() {
        let pts = issue9_cloud();
        let ties: Vec<u64> = (0..pts.len() as u64).map(|i| 3 * i + 1).collect();
        let origin = crate::denoise::origin_of(&pts);
        let bb = Aabb::from_points(&pts);
        let whole = CloudRun {
            positions: &pts,
            ties: &ties,
            origin,
            // Holds every point with room: every result of the whole run is exact.
            region: Some(Aabb {
                min: bb.min - DVec3::splat(bb.diagonal()),
                max: bb.max + DVec3::splat(bb.diagonal()),
            }),
            isolation: crate::denoise::isolation::of_cloud(&pts, &ties, origin, 16),
            short_lists: false,
            complete: None,
            wanted: None,
            held: None,
            beams: None,
        };
        // A 12 × 12 corner of the 60 × 60 plane: 4 % of the points, so lists are computed
        // only within reach of it.
        let wanted: Vec<bool> = (0..pts.len())
            .map(|i| i < 3600 && i / 60 < 12 && i % 60 < 12)
            .collect();
        let few = CloudRun {
            wanted: Some(&wanted),
            ..whole
        };
        let params = Params::default();
        let all = run(&whole, &params, &Globals::default()).unwrap();
        assert!(all.exact.iter().all(|&e| e));
        let part = run(&few, &params, &Globals::default()).unwrap();
        // Unlisted points, and what depends on them, are not exact; the rest equal the whole run.
        let exact = part.exact.iter().filter(|&&e| e).count();
        assert!(exact < pts.len() / 2, "{exact} of {} exact", pts.len());
        assert!(
            (0..pts.len()).any(|i| wanted[i] && part.exact[i]),
            "no wanted point exact"
        );
        for i in (0..pts.len()).filter(|&i| part.exact[i]) {
            assert_eq!(part.positions[i], all.positions[i], "point {i}");
        }
    }

    /// A wanted block's results equal the whole run's, bit for bit, though the fits, classes,
    /// noise scales and filter iterations of its run stop where no wanted result reads them
    /// ([`graded`]): a wavy surface with a crease and noise, so every class and the noise bound
    /// are at work; a small block (lists round by round) and a large one (all lists, then
    /// [`keep_near`]).
    #[test]
    fn issue16_graded_passes_give_the_wanted_points_the_whole_runs_bits() {
        let mut pts = Vec::new();
        for i in 0..80 {
            for j in 0..80 {
                let h = jitter(i, j);
                let crease = 0.6 * (i as f64 - 40.0).max(0.0);
                let wave = 2.0 * (0.2 * i as f64).sin() * (0.15 * j as f64).cos();
                pts.push(DVec3::new(i as f64, j as f64, wave + crease + 0.3 * h));
            }
        }
        // Scatter above the surface (vegetation): scatter and edge classes.
        for i in 0..400 {
            let h = |m: usize| ((i * m) % 1000) as f64 / 1000.0;
            pts.push(DVec3::new(
                80.0 * h(7919),
                80.0 * h(104_729),
                1.0 + 2.0 * h(1_299_709),
            ));
        }
        let ties: Vec<u64> = (0..pts.len() as u64).map(|i| 5 * i + 2).collect();
        let bb = Aabb::from_points(&pts);
        let whole = CloudRun {
            region: Some(Aabb {
                min: bb.min - DVec3::splat(bb.diagonal()),
                max: bb.max + DVec3::splat(bb.diagonal()),
            }),
            ..whole_run(&pts, &ties)
        };
        let params = Params::default();
        let n = pts.len() as u64;
        let globals = globals_partial(&whole, &params, n, |_, e| e)
            .unwrap()
            .0
            .finish();
        assert!(globals.noise > 0.0);
        let all = run(&whole, &params, &globals).unwrap();
        for (lo, hi) in [(30, 46), (15, 65)] {
            let wanted: Vec<bool> = (0..pts.len())
                .map(|i| i < 6400 && (lo..hi).contains(&(i / 80)) && (lo..hi).contains(&(i % 80)))
                .collect();
            let part = CloudRun {
                wanted: Some(&wanted),
                ..whole
            };
            let part = run(&part, &params, &globals).unwrap();
            let mut moved = 0;
            for i in (0..pts.len()).filter(|&i| wanted[i]) {
                assert!(part.exact[i], "block {lo}..{hi}: point {i} not exact");
                assert_eq!(
                    part.positions[i], all.positions[i],
                    "block {lo}..{hi}: point {i}"
                );
                moved += usize::from(part.positions[i] != pts[i]);
            }
            assert!(moved > 0, "block {lo}..{hi}: nothing moved");
        }
    }

    /// A run over part of a cluttered cloud (a noisy plane under volumetric scatter, as
    /// vegetation over ground): the points that do not move (scatter) are exact once their
    /// class is, and taint does not spread through them, so more results are exact than with
    /// written normals (which read the filter's hops and keep the plain rule), and every exact
    /// result, of either kind, equals the whole cloud's bit for bit — also where the lists,
    /// computed round by round for a few wanted points, stop one hop past the points that stay.
    #[test]
    fn issue16_points_that_stay_are_exact_one_hop_in_and_stop_the_taint() {
        let mut pts = Vec::new();
        for i in 0..120 {
            for j in 0..80 {
                let h = jitter(i, j);
                pts.push(DVec3::new(0.5 * i as f64, 0.5 * j as f64, 0.1 * h));
            }
        }
        // Uniform in a box (splitmix64): a multiplicative lattice would lie on planes.
        let mut state = 7u64;
        let mut unit = move || {
            state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            (z ^ (z >> 31)) as f64 / u64::MAX as f64
        };
        for _ in 0..3000 {
            let (x, y, z) = (unit(), unit(), unit());
            pts.push(DVec3::new(60.0 * x, 40.0 * y, 3.0 + 6.0 * z));
        }
        let ties: Vec<u64> = (0..pts.len() as u64).map(|i| 3 * i + 1).collect();
        let whole = whole_run(&pts, &ties);
        let n = pts.len() as u64;
        let params = Params::default();
        let globals = globals_partial(&whole, &params, n, |_, e| e)
            .unwrap()
            .0
            .finish();
        let all = run(&whole, &params, &globals).unwrap();
        let moved = (0..pts.len())
            .filter(|&i| all.positions[i] != pts[i])
            .count();
        let classes = all.structure.as_ref().unwrap();
        let scatter = classes
            .iter()
            .filter(|&&c| c == Structure::Scatter as u8)
            .count();
        assert!(
            moved > 5000 && scatter > 1500,
            "{moved} moved, {scatter} scatter"
        );
        // A tile: the points with x < 36. Wanted: those with x < 30 (most of the tile: every
        // list, then `keep_near`), or with 26 ≤ x < 30 (a few: lists round by round, which stop
        // one hop past the points that stay).
        let (tile, tile_pts, tile_ties, region) = tile_below(&pts, &ties, 36.0);
        for (from, gain) in [(0.0, 400), (26.0, 100)] {
            let wanted: Vec<bool> = tile_pts
                .iter()
                .map(|p| (from..30.0).contains(&p.x))
                .collect();
            let part = CloudRun {
                positions: &tile_pts,
                ties: &tile_ties,
                region: Some(region),
                wanted: Some(&wanted),
                ..whole
            };
            let exact_of = |params: &Params| {
                let r = run(&part, params, &globals).unwrap();
                // Only the wanted points' passes run to the end (`graded`).
                let kept = |&(j, _): &(usize, &usize)| wanted[j] && r.exact[j];
                for (j, &i) in tile.iter().enumerate().filter(kept) {
                    assert_eq!(r.positions[j], all.positions[i], "from {from}: point {i}");
                }
                (0..tile.len()).filter(|&j| wanted[j] && r.exact[j]).count()
            };
            let plain = exact_of(&Params {
                write_normals: true,
                ..params.clone()
            });
            let settled = exact_of(&params);
            assert!(
                settled > plain + gain,
                "from {from}: {settled} exact with the rule, {plain} without, of {} wanted",
                wanted.iter().filter(|&&w| w).count()
            );
        }
    }

    /// Issue 16: the QEM operator without the guard reads one hop of lists per filter iteration
    /// and per update, plus one per later cycle (`reach`): a tile's exact results equal the
    /// whole cloud's bit for bit — the paper's one update, a schedule of two cycles with a
    /// filter iteration and two updates, and written normals — and the paper's results are
    /// exact two list radii closer to the tile's face than the reach of 3 it had allowed.
    #[test]
    fn issue16_the_paper_operator_reads_one_hop_of_lists() {
        let mut pts = Vec::new();
        for i in 0..120 {
            for j in 0..60 {
                let h = jitter(i, j);
                let (x, y) = (0.5 * i as f64, 0.5 * j as f64);
                pts.push(DVec3::new(x, y, 2.0 * (x / 3.0).sin() + 0.1 * h));
            }
        }
        for i in 0..1500u64 {
            let u = |m: u64| ((i * m + 17) % 1009) as f64 / 1009.0;
            pts.push(DVec3::new(60.0 * u(389), 30.0 * u(577), 3.0 + 6.0 * u(811)));
        }
        let ties: Vec<u64> = (0..pts.len() as u64).map(|i| 5 * i + 2).collect();
        let whole = whole_run(&pts, &ties);
        let (tile, tile_pts, tile_ties, region) = tile_below(&pts, &ties, 36.0);
        let part = CloudRun {
            positions: &tile_pts,
            ties: &tile_ties,
            region: Some(region),
            ..whole
        };
        let paper = Params::paper();
        let cycles = Params {
            iterations: 2,
            filter: Some(1),
            updates: Some(2),
            ..Params::paper()
        };
        let written = Params {
            write_normals: true,
            ..Params::paper()
        };
        assert_eq!([reach(&paper), reach(&cycles), reach(&written)], [1, 7, 1]);
        for params in [&paper, &cycles, &written] {
            let globals = Globals::default();
            let all = run(&whole, params, &globals).unwrap();
            let r = run(&part, params, &globals).unwrap();
            let mut band = 0;
            for (j, &i) in tile.iter().enumerate().filter(|&(j, _)| r.exact[j]) {
                assert_eq!(r.positions[j], all.positions[i], "{params:?}: point {i}");
                if let (Some(a), Some(b)) = (&r.normals, &all.normals) {
                    assert_eq!(a[j], b[i], "{params:?}: normal of point {i}");
                }
                band += usize::from((32.5..33.5).contains(&pts[i].x) && pts[i].z < 2.5);
            }
            assert!(
                params != &paper || band >= 100,
                "{band} surface points exact 2.5 to 3.5 from the face"
            );
        }
    }

    /// Issue 9: `--radius` in the input's units. Below the grid's spacing every list is capped
    /// and nothing moves; far above the isolation radius the result is the default's; at 1.5
    /// grid steps the lists hold 9 points, and the points move.
    #[test]
    fn issue9_radius_caps_lists_in_the_inputs_units() {
        let pts = issue9_cloud();
        let tight = Params {
            radius: Some(0.9),
            ..Params::default()
        };
        let r = run_all(&pts, &tight).unwrap();
        assert_eq!(r.positions, pts);
        assert_eq!(r.stats.isolated, pts.len() as u64);
        let wide = Params {
            radius: Some(1e9),
            ..Params::default()
        };
        let (a, b) = (
            run_all(&pts, &wide).unwrap(),
            run_all(&pts, &Params::default()).unwrap(),
        );
        assert_eq!(a.positions, b.positions);
        assert!(b.stats.moved > 3000);
        // Two grid steps: the grid's lists are whole, the far cluster of 10 is isolated.
        let two = run_all(
            &pts,
            &Params {
                radius: Some(2.5),
                ..Params::default()
            },
        )
        .unwrap();
        assert!(two.stats.moved > 3000);
        assert!(two.stats.isolated >= 12, "{}", two.stats.isolated);
        let short = run_all(
            &pts,
            &Params {
                radius: Some(1.5),
                ..Params::default()
            },
        )
        .unwrap();
        assert!(short.stats.moved > 3000, "{}", short.stats.moved);
        assert_ne!(short.positions, two.positions);
    }

    /// Issue 9, do no harm on a scan as it is: on a plane whose noise is half its spacing (the
    /// noise bound alone let the 99th percentile of the moves reach 0.36 × r16 there), no point
    /// moves more than [`guarded::REACH`] times its own 16-NN radius in the input (brute force),
    /// and the cap is what holds the largest moves.
    #[test]
    #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
    fn issue9_no_point_moves_past_a_quarter_of_its_own_r16() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut gauss = move || {
            let (u, v) = (1.0 - rng.random::<f64>(), rng.random::<f64>());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let mut pts = Vec::new();
        for i in 0..60 {
            for j in 0..60 {
                let (dx, dy, dz) = (0.2 * gauss(), 0.2 * gauss(), 0.5 * gauss());
                pts.push(DVec3::new(i as f64 + dx, j as f64 + dy, dz));
            }
        }
        let r = run_all(&pts, &Params::default()).unwrap();
        let (mut moved, mut at_cap, mut worst) = (0, 0, 0.0f64);
        for (p, q) in pts.iter().zip(&r.positions) {
            let list = crate::neighbours::brute::knn(&pts, *p, 16);
            let r16 = (pts[*list.last().unwrap() as usize] - *p).length();
            let d = (*q - *p).length() / r16;
            worst = worst.max(d);
            moved += usize::from(d > 0.0);
            at_cap += usize::from(d > 0.999 * guarded::REACH);
        }
        assert!(
            worst <= guarded::REACH * (1.0 + 1e-12),
            "a point moved {worst} × r16"
        );
        assert!(moved > 1000, "{moved} points moved");
        assert!(at_cap > 20, "{at_cap} points at the cap");
    }

    /// Issue 9: `--classes`. Held points keep their input position bit for bit, and still serve
    /// as neighbours: the free points' results differ from a run without the held ones.
    #[test]
    fn issue9_held_points_stay_and_still_serve_as_neighbours() {
        let pts = issue9_cloud();
        // Every other row of the grid is held.
        let held: Vec<bool> = (0..pts.len())
            .map(|i| i < 3600 && (i / 60) % 2 == 0)
            .collect();
        let params = Params::default();
        let r = run_all_with(
            &pts,
            &params,
            PerPoint {
                held: Some(&held),
                beams: None,
            },
        )
        .unwrap();
        let free = run_all(&pts, &params).unwrap();
        for i in 0..pts.len() {
            if held[i] {
                assert_eq!(r.positions[i], pts[i], "held point {i} moved");
            }
        }
        assert_eq!(r.stats.held, 1800);
        let moved = (0..pts.len()).filter(|&i| r.positions[i] != pts[i]).count();
        assert!(moved > 1000, "{moved}");
        // Unheld points read their held neighbours' planes: not the result of a cloud without
        // them, and not the all-free result either (the held neighbours did not move).
        let alone: Vec<DVec3> = (0..pts.len())
            .filter(|&i| !held[i])
            .map(|i| pts[i])
            .collect();
        let a = run_all(&alone, &params).unwrap();
        let unheld: Vec<usize> = (0..pts.len()).filter(|&i| !held[i]).collect();
        assert!(
            unheld
                .iter()
                .zip(&a.positions)
                .any(|(&i, p)| r.positions[i] != *p)
        );
        assert!(unheld.iter().any(|&i| r.positions[i] != free.positions[i]));
        // Nothing held: the plain run.
        let none = run_all_with(
            &pts,
            &params,
            PerPoint {
                held: Some(&vec![false; pts.len()]),
                beams: None,
            },
        )
        .unwrap();
        assert_eq!(none.positions, free.positions);
    }

    #[test]
    fn a_set_cancel_flag_stops_between_passes() {
        assert!(check_cancel().is_ok());
        let flag = Arc::new(AtomicBool::new(true));
        let e = crate::neighbours::with_cancel(&flag, check_cancel).unwrap_err();
        assert_eq!(
            e,
            DenoiseError::Neighbours(crate::neighbours::NeighboursError::Cancelled)
        );
        let flag = Arc::new(AtomicBool::new(false));
        assert!(crate::neighbours::with_cancel(&flag, check_cancel).is_ok());
    }
}
