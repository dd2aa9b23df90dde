//! The point operator as a sequence of passes over per-point state ([`Program`], [`State`]).
//!
//! # Brief overview
//!
//! Once a point's k-NN list is known, everything the operator computes for it is a chain of
//! **passes**. A pass at point `i` is a function of `i`'s own list and of what earlier passes
//! computed at `i` and at the members of its list; nothing reads farther than one hop per pass:
//!
//! ```text
//!   guarded (default), per cycle c:
//!     Fit(c)        own list          the local fit (PCA) of the cycle's positions
//!     Class(c)      members' fits     class, noise scale, step bound; settled if it stays
//!     Filter(c, t)  members' t − 1    normal-filter iteration t (t = 1 also weights, range)
//!     Offsets(c, 0) members' normals, classes, noise, positions: the first update's offsets
//!     Gains(c)      members' offsets  the gains, and the first update's positions
//!     Offsets(c, u) members' positions of update u: update u + 1's positions (u ≥ 1)
//!   without the guard: Normals(c), Filter(c, t), Limits, Update(c, u), (WrittenFits, Written)
//!   bilateral: Normals(c), Bilateral(c)
//! ```
//!
//! A pass is **hop** when it reads what earlier passes computed at the members ([`Pass::hops`]);
//! the others read only the point's own list at positions already known. The in-memory run
//! executes each pass over every point before the next (Jacobi, as the operator is defined); a
//! streamed run executes a pass at a point as soon as the pass before is done at every member
//! ([`Program::waits`]). Both call the same per-point functions on the same state, so they
//! write the same bits.
//!
//! Every value a member's later pass reads is kept per cycle (fits, classes, noise scales,
//! filtered normals, first-update offsets, positions after each update): with lists that are not
//! symmetric, a point may run ahead of a point that lists it, so nothing read across a list is
//! overwritten. Values only the point itself reads (filter weights and ranges, gains, step
//! bounds) are shared by the cycles.

use glam::DVec3;
use rayon::prelude::*;

use super::Globals;
use crate::denoise::common::stay;
use crate::denoise::guarded::{self, Guard};
use crate::denoise::normals::{filter_range, filter_step, filter_weights};
use crate::denoise::structure::{Beams, LocalFit, Structure, class_in, local_fit, noise_of};
use crate::denoise::{Method, Params, bilateral, qem, written};
use crate::geometry::pca_normal;
use crate::neighbours::Neighbourhoods;
use crate::points::PointNormal;

/// Per-point flags of [`State::flags`].
pub(crate) mod flag {
    /// Fewer than the least list members within the isolation radius: keeps its position.
    pub const ISOLATED: u8 = 1;
    /// Its list was capped at the isolation radius.
    pub const CAPPED: u8 = 2;
    /// Keeps its position but serves as a neighbour (`--classes`).
    pub const HELD: u8 = 4;
    /// Duplicates a point of lower global index.
    pub const DUPLICATE: u8 = 8;
    /// No plane in the first cycle's neighbourhood.
    pub const DEGENERATE: u8 = 16;
    /// Its class in the last cycle does not move: every later pass gives it a fixed value and
    /// reads nothing of its members.
    pub const SETTLED: u8 = 32;
}

/// A point's k-NN lists, whatever stores them.
pub(crate) trait ListView: Sync {
    /// The list of point `i` (its members, the point itself included, by distance).
    fn list(&self, i: usize) -> &[u32];
}

impl ListView for Neighbourhoods {
    #[inline]
    fn list(&self, i: usize) -> &[u32] {
        self.get(i)
    }
}

/// One pass of a [`Program`] (see the module overview).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Pass {
    /// Guarded: the local fits of cycle `c`.
    Fit(usize),
    /// Guarded: classes, noise scales and step bounds of cycle `c`.
    Class(usize),
    /// Without the guard: the PCA normals of cycle `c`.
    Normals(usize),
    /// Normal-filter iteration `t` (from 1) of cycle `c`.
    Filter(usize, usize),
    /// Guarded: update `u` of cycle `c`: the offsets (`u` = 0) or the new positions.
    Offsets(usize, usize),
    /// Guarded: the gains of cycle `c` and its first update's positions.
    Gains(usize),
    /// QEM without the guard: each point's step bound, the largest list radius of its members.
    Limits,
    /// QEM without the guard: update `u` of cycle `c`.
    Update(usize, usize),
    /// Bilateral pass `c`.
    Bilateral(usize),
    /// Written normals without the guard: the last cycle's fits.
    WrittenFits,
    /// Written normals without the guard: the last cycle's classes and written values.
    Written,
}

impl Pass {
    /// True when the pass reads what earlier passes computed at the list's members.
    #[allow(dead_code)] // The streamed run's readiness (issue 48), next.
    pub(crate) fn hops(self) -> bool {
        match self {
            Pass::Fit(c) | Pass::Normals(c) => c > 0,
            Pass::WrittenFits => false,
            Pass::Class(_)
            | Pass::Filter(..)
            | Pass::Offsets(..)
            | Pass::Gains(_)
            | Pass::Limits
            | Pass::Update(..)
            | Pass::Bilateral(_)
            | Pass::Written => true,
        }
    }

    /// The report phase the pass's time is booked to.
    pub(crate) fn phase(self) -> &'static str {
        match self {
            Pass::Offsets(..)
            | Pass::Gains(_)
            | Pass::Limits
            | Pass::Update(..)
            | Pass::Bilateral(_) => "solve",
            _ => "normals",
        }
    }
}

/// The passes a run of `params` executes, in order, and what they need.
#[derive(Debug, Clone)]
pub(crate) struct Program {
    /// The passes.
    pub(crate) passes: Vec<Pass>,
    guard: bool,
    method: Method,
    cycles: usize,
    filter: usize,
    updates: usize,
    write: bool,
    k: usize,
}

impl Program {
    /// The passes of `params` on point clouds.
    pub(crate) fn new(params: &Params) -> Program {
        let s = params.schedule(false);
        let guard = super::guarded_qem(params);
        let filter = if params.method == Method::Qem {
            s.filter
        } else {
            0
        };
        let mut passes = Vec::new();
        if params.method == Method::Qem && !guard {
            passes.push(Pass::Limits);
        }
        for c in 0..s.cycles {
            let last = c + 1 == s.cycles;
            match params.method {
                Method::Qem if guard => {
                    passes.push(Pass::Fit(c));
                    passes.push(Pass::Class(c));
                    passes.extend((1..=filter).map(|t| Pass::Filter(c, t)));
                    passes.push(Pass::Offsets(c, 0));
                    passes.push(Pass::Gains(c));
                    passes.extend((1..s.updates).map(|u| Pass::Offsets(c, u)));
                }
                Method::Qem => {
                    passes.push(Pass::Normals(c));
                    passes.extend((1..=filter).map(|t| Pass::Filter(c, t)));
                    if last && params.write_normals {
                        passes.push(Pass::WrittenFits);
                        passes.push(Pass::Written);
                    }
                    passes.extend((0..s.updates).map(|u| Pass::Update(c, u)));
                }
                Method::Bilateral => {
                    passes.push(Pass::Normals(c));
                    if last && params.write_normals {
                        passes.push(Pass::WrittenFits);
                        passes.push(Pass::Written);
                    }
                    passes.push(Pass::Bilateral(c));
                }
            }
        }
        Program {
            passes,
            guard,
            method: params.method,
            cycles: s.cycles,
            filter,
            updates: s.updates,
            write: params.write_normals,
            k: params.k(),
        }
    }

    /// Position stages: the input, then one after each update (each bilateral pass).
    fn stages(&self) -> usize {
        1 + self.cycles
            * match self.method {
                Method::Qem => self.updates,
                Method::Bilateral => 1,
            }
    }

    /// The position stage a cycle starts from.
    fn start_stage(&self, c: usize) -> usize {
        match self.method {
            Method::Qem => c * self.updates,
            Method::Bilateral => c,
        }
    }

    /// The state of `n` points, with every array the program writes sized for them (`full`, as
    /// a streamed run's window needs), or empty until the pass that writes it (in memory, where
    /// each pass writes every point at once).
    pub(crate) fn state(&self, n: usize, full: bool) -> State {
        let cyc = self.cycles;
        let per_cycle = |on: bool| if on { cyc } else { 0 };
        let unguarded_written = !self.guard && self.write;
        let sized = |on: bool| if on && full { n } else { 0 };
        State {
            n,
            pos: (0..self.stages())
                .map(|s| vec![DVec3::ZERO; if s == 0 { n } else { sized(true) }])
                .collect(),
            ties: vec![0; n],
            radii: vec![0.0; n],
            flags: vec![0; n],
            knn_mean: vec![0.0; n],
            stayed: vec![0; n],
            fits: (0..per_cycle(self.guard) + usize::from(unguarded_written))
                .map(|_| vec![LocalFit::isolated(); sized(true)])
                .collect(),
            classes: (0..per_cycle(self.guard) + usize::from(unguarded_written))
                .map(|_| vec![Structure::Degenerate; sized(true)])
                .collect(),
            noise: (0..per_cycle(self.guard))
                .map(|_| vec![0.0; sized(true)])
                .collect(),
            bound: vec![0.0; sized(self.guard)],
            normals: (0..cyc)
                .map(|_| {
                    (0..=self.filter)
                        .map(|_| vec![DVec3::ZERO; sized(true)])
                        .collect()
                })
                .collect(),
            weights: vec![0.0; sized(self.filter > 0) * self.k],
            range: vec![0.0; sized(self.filter > 0)],
            offsets: (0..per_cycle(self.guard))
                .map(|_| vec![(None, 0); sized(true)])
                .collect(),
            gains: vec![0.0; sized(self.guard)],
            limits: vec![0.0; sized(self.method == Method::Qem && !self.guard)],
            written: vec![PointNormal::NONE; sized(self.write)],
            beams: Vec::new(),
        }
    }

    /// Frees what no pass after `p` reads, in a run that executes each pass at every point
    /// before the next (in memory): the filter's earlier iterations, weights and ranges, the
    /// first update's offsets, the positions of earlier updates, a finished cycle's fits, noise
    /// scales and normals. The first cycle's classes, the input positions and what the result
    /// reports are kept.
    pub(crate) fn release(&self, p: Pass, st: &mut State) {
        match p {
            Pass::Filter(c, t) => {
                free(&mut st.normals[c][t - 1]);
                if t == self.filter {
                    st.weights = Vec::new();
                    st.range = Vec::new();
                }
            }
            Pass::Gains(c) => free(&mut st.offsets[c]),
            _ => {}
        }
        // The positions an update read, once the next stage is written.
        let read = match p {
            Pass::Gains(c) => Some(self.start_stage(c)),
            Pass::Offsets(c, u) if u > 0 => Some(self.start_stage(c) + u),
            Pass::Update(c, u) => Some(self.start_stage(c) + u),
            Pass::Bilateral(c) => Some(c),
            _ => None,
        };
        if let Some(s) = read.filter(|&s| s > 0) {
            free(&mut st.pos[s]);
        }
        // A cycle's last update: what only that cycle read.
        let ends = match p {
            Pass::Gains(c) if self.updates == 1 => Some(c),
            Pass::Offsets(c, u) if u + 1 == self.updates && u > 0 => Some(c),
            _ => None,
        };
        if let Some(c) = ends {
            free(&mut st.fits[c]);
            free(&mut st.noise[c]);
            free(&mut st.normals[c][self.filter]);
            if c > 0 {
                free(&mut st.classes[c]);
            }
        }
    }

    /// True when pass `p` at point `i` must wait for the pass before it at every member: a hop
    /// pass, unless the point has settled (its later passes read nothing of its members) or is
    /// isolated under the guard (its class is sparse whatever its members are).
    #[allow(dead_code)] // The streamed run's readiness (issue 48), next.
    pub(crate) fn waits(&self, p: Pass, st: &State, i: usize) -> bool {
        if !p.hops() {
            return false;
        }
        match p {
            Pass::Class(_) => st.flags[i] & flag::ISOLATED == 0,
            Pass::Filter(..) | Pass::Offsets(..) | Pass::Gains(_) => {
                st.flags[i] & flag::SETTLED == 0
            }
            _ => true,
        }
    }

    /// Runs pass `p` at the points `at` (their results written into `st`).
    pub(crate) fn run<L: ListView>(
        &self,
        p: Pass,
        st: &mut State,
        lists: &L,
        (params, globals): (&Params, &Globals),
        at: At,
    ) {
        let (k, n) = (self.k, st.n);
        match p {
            Pass::Fit(c) => {
                let s = self.start_stage(c);
                let beams = st.beams(globals);
                let out = at.map(|i| {
                    if st.flags[i] & flag::ISOLATED != 0 {
                        LocalFit::isolated()
                    } else {
                        local_fit(&st.pos[s], lists.list(i), i, beams)
                    }
                });
                at.put(&mut st.fits[c], n, out, LocalFit::isolated());
            }
            Pass::Class(c) => {
                let last = c + 1 == self.cycles;
                let g = guarded::GLOBAL * globals.noise;
                let out: Vec<(Structure, f64)> = at.map_init(Vec::new, |buf, i| {
                    let list = lists.list(i);
                    // An isolated point's own class is sparse, and a sparse point stays sparse:
                    // `class_in` gives the same without its members.
                    let class = if st.flags[i] & flag::ISOLATED != 0 {
                        Structure::Sparse
                    } else {
                        class_in(&st.fits[c], &st.radii, list, i, buf)
                    };
                    (class, noise_of(&st.fits[c], list, buf))
                });
                let planes = at.map_zip(&out, |i, &(class, _)| {
                    if class.takes_planes() {
                        st.fits[c][i].normal
                    } else {
                        DVec3::ZERO
                    }
                });
                at.each(&mut st.flags, |j, f| {
                    let class = out[j].0;
                    if c == 0 && class == Structure::Degenerate {
                        *f |= flag::DEGENERATE;
                    }
                    if last && !class.moves() {
                        *f |= flag::SETTLED;
                    }
                });
                let (classes, noise): (Vec<Structure>, Vec<f64>) = out.into_par_iter().unzip();
                let bound = noise.par_iter().map(|&x| x.min(g)).collect();
                at.put(&mut st.classes[c], n, classes, Structure::Degenerate);
                at.put(&mut st.noise[c], n, noise, 0.0);
                at.put(&mut st.bound, n, bound, 0.0);
                at.put(&mut st.normals[c][0], n, planes, DVec3::ZERO);
                if self.filter == 0 {
                    self.written_guarded(st, lists, c, at);
                }
            }
            Pass::Normals(c) => {
                let s = self.start_stage(c);
                let out = at.map(|i| {
                    let v = st.pos[s][i];
                    let list = lists.list(i);
                    pca_normal(list.iter().map(|&u| st.pos[s][u as usize] - v))
                        .map_or(DVec3::ZERO, |f| f.normal)
                });
                let pos0 = &st.pos[0];
                at.each(&mut st.flags, |j, f| {
                    if c == 0 && out[j] == DVec3::ZERO && pos0[at.slot(j)].is_finite() {
                        *f |= flag::DEGENERATE;
                    }
                });
                // An isolated point lends no plane.
                let out = at.map_zip(&out, |i, &nrm| {
                    if st.flags[i] & flag::ISOLATED != 0 {
                        DVec3::ZERO
                    } else {
                        nrm
                    }
                });
                at.put(&mut st.normals[c][0], n, out, DVec3::ZERO);
            }
            Pass::Filter(c, t) => {
                if t == 1 {
                    let s = self.start_stage(c);
                    let floor2 = params.sigma_r_floor(false).powi(2);
                    sized(&mut st.weights, n * k, 0.0);
                    sized(&mut st.range, n, 0.0);
                    let (n0, pos, radii) = (&st.normals[c][0], &st.pos[s], &st.radii);
                    at.each_chunk(&mut st.weights, k, &mut st.range, |i, w, r, diffs| {
                        if n0[i] == DVec3::ZERO {
                            return;
                        }
                        let list = lists.list(i);
                        filter_weights(pos, list, i, radii[i], &mut w[..list.len()]);
                        *r = filter_range(n0, list, i, floor2, diffs);
                    });
                }
                let out = {
                    let (prev, w, r) = (&st.normals[c][t - 1], &st.weights, &st.range);
                    at.map(|i| {
                        let list = lists.list(i);
                        filter_step(prev, list, &w[i * k..i * k + list.len()], r[i], i)
                    })
                };
                at.put(&mut st.normals[c][t], n, out, DVec3::ZERO);
                if t == self.filter && self.guard {
                    self.written_guarded(st, lists, c, at);
                }
            }
            Pass::Offsets(c, u) => {
                let s = self.start_stage(c) + u;
                let g = self.guard_of(st, c, (params, globals));
                if u == 0 {
                    let out =
                        at.map(|i| guarded::offset_of(&st.pos[s], lists.list(i), &g, params, i));
                    at.put(&mut st.offsets[c], n, out, (None, 0));
                } else {
                    let out = at.map(|i| {
                        let off = guarded::offset_of(&st.pos[s], lists.list(i), &g, params, i);
                        guarded::moved(st.pos[s][i], off, st.gains[i], &g, i)
                    });
                    self.store_positions(st, s + 1, at, out);
                }
            }
            Pass::Gains(c) => {
                let s = self.start_stage(c);
                let g = self.guard_of(st, c, (params, globals));
                let out: Vec<(f64, (DVec3, u8))> = at.map(|i| {
                    let gain = guarded::gain_of(lists.list(i), &g, &st.offsets[c], i);
                    let m = guarded::moved(st.pos[s][i], st.offsets[c][i], gain, &g, i);
                    (gain, m)
                });
                let (gains, moved): (Vec<f64>, Vec<(DVec3, u8)>) = out.into_par_iter().unzip();
                at.put(&mut st.gains, n, gains, 0.0);
                self.store_positions(st, s + 1, at, moved);
            }
            Pass::Limits => {
                let out = at.map(|i| {
                    lists
                        .list(i)
                        .iter()
                        .filter(|&&u| u as usize != i)
                        .map(|&u| st.radii[u as usize])
                        .fold(0.0, f64::max)
                });
                at.put(&mut st.limits, n, out, 0.0);
            }
            Pass::Update(c, u) => {
                let s = self.start_stage(c) + u;
                let normals = &st.normals[c][self.filter];
                let out = at.map(|i| {
                    qem::point_step(&st.pos[s], lists.list(i), st.limits[i], normals, params, i)
                });
                self.store_positions(st, s + 1, at, out);
            }
            Pass::Bilateral(c) => {
                let sigma_c = globals.spacing;
                let r2 = 4.0 * sigma_c * sigma_c;
                let out = at.map_init(Vec::new, |buf, i| {
                    let list = lists.list(i);
                    let normals = &st.normals[c][0];
                    bilateral::point_step(&st.pos[c], list, normals, sigma_c, r2, i, buf)
                });
                self.store_positions(st, c + 1, at, out);
            }
            Pass::WrittenFits => {
                let s = self.start_stage(self.cycles - 1);
                let out = at.map(|i| {
                    if st.flags[i] & flag::ISOLATED != 0 {
                        LocalFit::isolated()
                    } else {
                        local_fit(&st.pos[s], lists.list(i), i, Beams::NONE)
                    }
                });
                at.put(&mut st.fits[0], n, out, LocalFit::isolated());
            }
            Pass::Written => {
                let c = self.cycles - 1;
                let s = self.start_stage(c);
                let normals = &st.normals[c][self.filter];
                let out: Vec<(Structure, PointNormal)> = at.map_init(Vec::new, |buf, i| {
                    let list = lists.list(i);
                    let class = class_in(&st.fits[0], &st.radii, list, i, buf);
                    let isolated = st.flags[i] & flag::ISOLATED != 0;
                    let curvature = written::curvature_of(&st.pos[s], list, i, isolated);
                    let w = written::written_of(normals[i], &st.fits[0][i], class, curvature);
                    (class, w)
                });
                let (classes, written): (Vec<Structure>, Vec<PointNormal>) =
                    out.into_par_iter().unzip();
                at.put(&mut st.classes[0], n, classes, Structure::Degenerate);
                at.put(&mut st.written, n, written, PointNormal::NONE);
            }
        }
    }

    /// What the guarded updates of cycle `c` read.
    fn guard_of<'a>(
        &self,
        st: &'a State,
        c: usize,
        (params, globals): (&Params, &Globals),
    ) -> Guard<'a> {
        Guard {
            start: &st.pos[0],
            normals: &st.normals[c][self.filter],
            fits: &st.fits[c],
            classes: &st.classes[c],
            noise: &st.noise[c],
            bound: &st.bound,
            radii: &st.radii,
            max_move: params.max_move,
            beams: st.beams(globals),
        }
    }

    /// The guarded operator's written values of the last cycle `c`, once its filtered normals
    /// are known (the point's own list and its own values).
    fn written_guarded<L: ListView>(&self, st: &mut State, lists: &L, c: usize, at: At) {
        if !self.write || c + 1 != self.cycles {
            return;
        }
        let s = self.start_stage(c);
        let out = at.map(|i| {
            let isolated = st.flags[i] & flag::ISOLATED != 0;
            let curvature = written::curvature_of(&st.pos[s], lists.list(i), i, isolated);
            written::written_of(
                st.normals[c][self.filter][i],
                &st.fits[c][i],
                st.classes[c][i],
                curvature,
            )
        });
        at.put(&mut st.written, st.n, out, PointNormal::NONE);
    }

    /// Stores the positions of stage `s` (with their [`stay`] flags) for the points `at`: an
    /// isolated or held point is put back where it started.
    fn store_positions(&self, st: &mut State, s: usize, at: At, moved: Vec<(DVec3, u8)>) {
        let (pos0, flags) = (&st.pos[0], &st.flags);
        let out: Vec<(DVec3, u8)> = at.map_zip(&moved, |i, &(p, f)| {
            let (mut p, mut f) = (p, f);
            if flags[i] & flag::ISOLATED != 0 {
                p = pos0[i];
                f |= stay::ISOLATED;
            }
            if flags[i] & flag::HELD != 0 {
                p = pos0[i];
                f |= stay::HELD;
            }
            (p, f)
        });
        at.each(&mut st.stayed, |j, x| *x |= out[j].1);
        let positions = out.into_par_iter().map(|(p, _)| p).collect();
        at.put(&mut st.pos[s], st.n, positions, DVec3::ZERO);
    }

    /// The final position of point `i`: the last stage's, within `--max-move` of its input.
    pub(crate) fn finish(&self, st: &mut State, params: &Params, i: usize) -> DVec3 {
        let last = &st.pos[self.stages() - 1];
        let mut p = last[i];
        if let Some(m) = params.max_move {
            let (q, f) = guarded::clamp(st.pos[0][i], p, m);
            p = q;
            st.stayed[i] |= f;
        }
        p
    }
}

/// The outlier statistic of point `i` with list `list`: the mean distance to the other
/// members (`dist2`: squared distance to a member); a capped list counts each missing member
/// at the cap, the isolation radius (so a far outlier scores that radius, not its distance to
/// the scene). Lists of `k`.
pub(crate) fn knn_mean_of(
    list: &[u32],
    i: usize,
    dist2: impl Fn(u32) -> f64,
    capped: bool,
    (k, isolation): (usize, Option<f64>),
) -> f64 {
    let others = list.iter().filter(|&&u| u as usize != i);
    let (mut sum, mut count) =
        others.fold((0.0, 0usize), |(s, c), &u| (s + dist2(u).sqrt(), c + 1));
    if capped {
        let missing = (k - 1).saturating_sub(count);
        sum += missing as f64 * isolation.unwrap_or(0.0);
        count += missing;
    }
    if count == 0 { 0.0 } else { sum / count as f64 }
}

/// Per-point state of a run, indexed by the run's slots (in memory: every point in spatial
/// order). Which arrays are filled depends on the [`Program`].
#[derive(Debug, Default)]
pub(crate) struct State {
    /// Points (slots).
    pub(crate) n: usize,
    /// Positions by stage: the input (`pos[0]`), then after each update.
    pub(crate) pos: Vec<Vec<DVec3>>,
    /// Global indices (the k-NN tie keys).
    pub(crate) ties: Vec<u64>,
    /// Squared radius of each (capped) list.
    pub(crate) radii: Vec<f64>,
    /// [`flag`]s.
    pub(crate) flags: Vec<u8>,
    /// The outlier statistic.
    pub(crate) knn_mean: Vec<f64>,
    /// Why passes left the point in place ([`stay`] flags, or-ed).
    pub(crate) stayed: Vec<u8>,
    /// Local fits per cycle (guarded), or the last cycle's for written normals (unguarded).
    pub(crate) fits: Vec<Vec<LocalFit>>,
    /// Classes per cycle (guarded), or the last cycle's for written normals (unguarded).
    pub(crate) classes: Vec<Vec<Structure>>,
    /// Noise scales per cycle.
    pub(crate) noise: Vec<Vec<f64>>,
    /// Step bounds (the noise scale capped by the scan's).
    pub(crate) bound: Vec<f64>,
    /// Normals per cycle: the planes or PCA normals (`[c][0]`), then after each filter iteration.
    pub(crate) normals: Vec<Vec<Vec<DVec3>>>,
    /// Filter weights, `k` per point.
    pub(crate) weights: Vec<f64>,
    /// Filter range widths.
    pub(crate) range: Vec<f64>,
    /// The first update's offsets per cycle.
    pub(crate) offsets: Vec<Vec<(Option<DVec3>, u8)>>,
    /// Gains.
    pub(crate) gains: Vec<f64>,
    /// Step bounds of QEM without the guard.
    pub(crate) limits: Vec<f64>,
    /// Written normals.
    pub(crate) written: Vec<PointNormal>,
    /// Each point's beam (zero where unknown), empty without beams: the guarded operator's fits
    /// and steps follow it ([`Beams`]).
    pub(crate) beams: Vec<DVec3>,
}

impl State {
    /// The beams the guarded passes read, with the scan's noise along them.
    fn beams<'a>(&'a self, globals: &Globals) -> Beams<'a> {
        Beams {
            dirs: (!self.beams.is_empty()).then_some(&self.beams[..]),
            noise: globals.noise,
        }
    }
}

/// The points a pass runs at: every point of the state, or some of its slots (ascending,
/// distinct).
#[derive(Clone, Copy)]
pub(crate) enum At<'a> {
    /// Every point `0..n`.
    All(usize),
    /// These slots.
    #[allow(dead_code)] // The streamed run's passes (issue 48), next.
    Slots(&'a [u32]),
}

impl At<'_> {
    /// Points.
    fn len(&self) -> usize {
        match self {
            At::All(n) => *n,
            At::Slots(s) => s.len(),
        }
    }

    /// The slot of the `j`-th point.
    #[inline]
    fn slot(&self, j: usize) -> usize {
        match self {
            At::All(_) => j,
            At::Slots(s) => s[j] as usize,
        }
    }

    /// `f` at every point, in parallel, in order.
    fn map<T: Send>(&self, f: impl Fn(usize) -> T + Sync + Send) -> Vec<T> {
        (0..self.len())
            .into_par_iter()
            .with_min_len(1024)
            .map(|j| f(self.slot(j)))
            .collect()
    }

    /// [`At::map`] with per-thread scratch made by `init`.
    fn map_init<T: Send, S>(
        &self,
        init: impl Fn() -> S + Sync + Send,
        f: impl Fn(&mut S, usize) -> T + Sync + Send,
    ) -> Vec<T> {
        (0..self.len())
            .into_par_iter()
            .with_min_len(1024)
            .map_init(init, |s, j| f(s, self.slot(j)))
            .collect()
    }

    /// `f` at every point with the value `values` holds for it.
    fn map_zip<T: Send, V: Sync>(
        &self,
        values: &[V],
        f: impl Fn(usize, &V) -> T + Sync + Send,
    ) -> Vec<T> {
        (0..self.len())
            .into_par_iter()
            .with_min_len(1024)
            .map(|j| f(self.slot(j), &values[j]))
            .collect()
    }

    /// `f(j, value)` on the value of `data` at each point's slot (`j`: the point's place here).
    fn each<T: Send>(&self, data: &mut [T], f: impl Fn(usize, &mut T) + Sync + Send) {
        match self {
            At::All(_) => data
                .par_iter_mut()
                .enumerate()
                .with_min_len(1024)
                .for_each(|(j, x)| f(j, x)),
            At::Slots(slots) => {
                let mut refs = Vec::with_capacity(slots.len());
                let mut rest = data;
                let mut base = 0;
                for &i in slots.iter() {
                    let (_, tail) = std::mem::take(&mut rest).split_at_mut(i as usize - base);
                    let (x, tail) = tail.split_first_mut().expect("a slot within the state");
                    refs.push(x);
                    rest = tail;
                    base = i as usize + 1;
                }
                refs.into_par_iter()
                    .enumerate()
                    .with_min_len(1024)
                    .for_each(|(j, x)| f(j, x));
            }
        }
    }

    /// `f(slot, chunk, value, scratch)` on each point's `width`-long chunk of `chunks` and its
    /// value in `values`.
    fn each_chunk<T: Send, V: Send>(
        &self,
        chunks: &mut [T],
        width: usize,
        values: &mut [V],
        f: impl Fn(usize, &mut [T], &mut V, &mut Vec<f64>) + Sync + Send,
    ) {
        match self {
            At::All(n) => chunks[..n * width]
                .par_chunks_mut(width)
                .zip(values.par_iter_mut())
                .enumerate()
                .with_min_len(1024)
                .for_each_init(Vec::new, |buf, (i, (c, v))| f(i, c, v, buf)),
            At::Slots(slots) => {
                let mut refs = Vec::with_capacity(slots.len());
                let (mut rest, mut rest_v) = (chunks, values);
                let mut base = 0;
                for &i in slots.iter() {
                    let skip = i as usize - base;
                    let (_, tail) = std::mem::take(&mut rest).split_at_mut(skip * width);
                    let (c, tail) = tail.split_at_mut(width);
                    let (_, tail_v) = std::mem::take(&mut rest_v).split_at_mut(skip);
                    let (v, tail_v) = tail_v.split_first_mut().expect("a slot within the state");
                    refs.push((i as usize, c, v));
                    rest = tail;
                    rest_v = tail_v;
                    base = i as usize + 1;
                }
                refs.into_par_iter()
                    .with_min_len(1024)
                    .for_each_init(Vec::new, |buf, (i, c, v)| f(i, c, v, buf));
            }
        }
    }

    /// Writes `values` (one per point, in order) into `out`, an array of `n` (taken as it is
    /// when every point is written; allocated with `fill` first when it is not sized yet).
    fn put<T: Clone + Send>(&self, out: &mut Vec<T>, n: usize, values: Vec<T>, fill: T) {
        if let At::All(_) = self {
            *out = values;
            return;
        }
        sized(out, n, fill);
        for (j, v) in values.into_iter().enumerate() {
            out[self.slot(j)] = v;
        }
    }
}

/// Drops `v`'s values and its memory.
fn free<T>(v: &mut Vec<T>) {
    *v = Vec::new();
}

/// `out` sized for `n` points (filled with `fill` when it is not yet).
fn sized<T: Clone>(out: &mut Vec<T>, n: usize, fill: T) -> &mut Vec<T> {
    if out.len() < n {
        out.resize(n, fill);
    }
    out
}
