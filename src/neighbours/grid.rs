//! All-points k-NN on a hierarchy of uniform grids, with the k-d tree as the fallback.
//!
//! Hand-rolled on purpose: asking kiddo for the k nearest neighbours of every point costs about
//! 3 µs per point on this machine (k = 16, f64, queries in Morton order; `benches/kernels.rs`,
//! group `knn`), which alone is more than the whole operator's budget. Scans are dense and
//! locally uniform, so a grid whose cell is about one k-NN radius answers almost every query from
//! the 3 × 3 × 3 block around its cell, and all queries of a cell share one candidate list laid
//! out contiguously. Distances use the same formula as [`super::brute`], candidates are ranked by
//! (squared distance, tie key), and a query whose k-th distance is not provably inside the block
//! goes to the k-d tree, so the answer is exactly the brute-force one whatever the cell size.
//!
//! ```text
//!   level 0: cell c₀ ≈ 1.5 × median k-NN radius (extrapolated from a sample, checked by a
//!            trial of 257 probes: measured when the sample was off, area-weighted when ≥ 1/8
//!            of the probes would go to the tree)
//!   ┌───┬───┬───┐
//!   │   │   │   │   candidates of every query in the centre cell = the 27 cells around it;
//!   ├───┼───┼───┤   exact when the k-th distance < c + distance from the query to its own
//!   │   │ q │   │   cell's nearest face (nothing outside the block can be closer)
//!   ├───┼───┼───┤
//!   │   │   │   │   a cell whose block holds more than DENSE_LOAD_PER_K · k candidates is
//!   └───┴───┴───┘   *dense*: its queries move to level 1, a finer grid over the points of
//!                   the dense cells' blocks only, and so on (at most MAX_LEVELS levels)
//! ```
//!
//! **Why levels.** One cell size cannot suit a scan whose density varies: in a dense cluster a
//! block holds thousands of candidates and every query scans them all (quadratic in the local
//! density), and one far outlier used to make the single grid coarse for everything. Each level
//! refines only where the block load is high, so every query is answered from a block of
//! bounded size (or by the tree), whatever the geometry; the work counters of [`Work`] show it.
//!
//! **Why a refined answer is still exact.** A query q of level l + 1 lies in a dense cell D of
//! level l, and level l + 1 holds every point of D's block, which contains every point within
//! `c_l + inner_l(q)` of q (`inner` = distance from q to the faces of its own cell). By induction
//! level l + 1 holds every point within `cap(q) = min over ancestors j of (c_j + inner_j(q))`, so
//! a block answer at level l + 1 is exact when its k-th distance is below
//! `min(ring · c + inner(q), cap(q))`. Cell geometry is computed relative to each level's own
//! corner, and an absolute allowance `slack` for its rounding is subtracted from every reach.
//!
//! **Duplicates.** Points at one position ask the same question, so they get the same answer:
//! consecutive queries at a bitwise-equal position copy the previous list (a stack of m copies
//! costs one block scan, not m). A cell that is one big stack is never refined.

use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use crate::geometry::floor_i64;

/// Squared distance, coordinate by coordinate (the same formula as the oracle).
#[inline(always)]
pub(crate) fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

/// Bits of one axis' cell coordinate in a cell key (coordinates relative to the level's corner).
const AXIS_BITS: u32 = 42;
/// Most cells a level spans along one axis: its cell size is floored to `span / MAX_SPAN`, so a
/// coordinate (plus the two cells a ring reaches beyond) always fits in [`AXIS_BITS`] bits.
const MAX_SPAN: f64 = (1u64 << 41) as f64;
/// A cell whose 3 × 3 × 3 block holds more than this many candidates per unit of k is dense.
/// A uniform cloud at the level-0 cell size has about 7 k (on a surface) to 20 k (in a volume)
/// on average, so only real density contrasts refine.
const DENSE_LOAD_PER_K: usize = 32;
/// The block load per unit of k a refined level aims at (its cell shrinks by the cube root of
/// the smallest dense load over this, at least by 2).
const TARGET_LOAD_PER_K: f64 = 8.0;
/// Ring 2 is tried only while the 5 × 5 × 5 block holds at most this many candidates per unit
/// of k; beyond it a k-d tree query is cheaper (and a dense cluster two cells from a sparse
/// point cannot make that point's query scan the cluster).
const RING2_LOAD_PER_K: usize = 96;
/// Most grid levels; deeper queries are answered at the last level (or by the tree).
pub(crate) const MAX_LEVELS: usize = 32;
/// Rounding allowance of cell geometry, relative to the level's largest coordinate: the cell of a
/// point and the faces of a cell are computed with a few roundings of relative size 2⁻⁵³.
const ROUNDING: f64 = 1.0 / (1u64 << 40) as f64;

/// Work counters of one all-points pass: what the k-NN cost is made of, independent of timing
/// and of the thread count.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Work {
    /// Points queried.
    pub queries: u64,
    /// Candidate distances the grid levels evaluated.
    pub candidates: u64,
    /// Cell look-ups of the grid levels (block gathering and load estimates).
    pub cells: u64,
    /// Queries the grid left to the k-d tree (a few of them to a scan, [`super::SCAN_QUERIES`]).
    pub tree_queries: u64,
    /// Candidates the k-d tree returned for re-measuring.
    pub tree_candidates: u64,
    /// Grid levels built (1 when no cell was dense).
    pub levels: u32,
    /// The largest block (candidates) any grid query scanned.
    pub max_block: u64,
}

impl Work {
    fn merge(&mut self, o: &Work) {
        self.queries += o.queries;
        self.candidates += o.candidates;
        self.cells += o.cells;
        self.tree_queries += o.tree_queries;
        self.tree_candidates += o.tree_candidates;
        self.levels = self.levels.max(o.levels);
        self.max_block = self.max_block.max(o.max_block);
    }
}

/// The pass was cancelled through its flag.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Cancelled;

/// Per-thread scratch: the candidate block of one cell in structure-of-arrays form.
#[derive(Default)]
struct Block {
    xs: Vec<f64>,
    ys: Vec<f64>,
    zs: Vec<f64>,
    ids: Vec<u32>,
    /// Per candidate: `tie << 32 | position in the block` when the pass's tie keys fit in 32 bits
    /// ([`Pass::packed`]), the tie key otherwise.
    keys: Vec<u64>,
    d: Vec<f64>,
    sel: Vec<u32>,
    best: Vec<(u128, u32)>,
    /// Packed ranks `distance bits << 64 | tie << 32 | position` of the candidates within the
    /// bound (only the first `kept` are meaningful; never shrunk, so no per-query fill).
    ranked: Vec<u128>,
    /// The last answered query of this thread (any cell, any level): its k-th distance bounds
    /// the next query's by the triangle inequality.
    prev: Option<([f64; 3], f64)>,
    /// Block positions of the last answered query's neighbours, while the block is unchanged:
    /// the farthest of them from the next query bounds its k-th distance tightly.
    prev_sel: Vec<u32>,
}

impl Block {
    fn clear(&mut self) {
        self.xs.clear();
        self.ys.clear();
        self.zs.clear();
        self.ids.clear();
        self.keys.clear();
        self.prev_sel.clear();
    }
}

/// The answers of the grid pass for one cell: per point its index and k-th squared distance
/// (NaN when the k-d tree must answer instead) and, for answered points, k neighbours each in
/// `lists`, in the same order.
#[derive(Default)]
pub(crate) struct CellAnswers {
    /// (point index, k-th squared distance or NaN).
    pub(crate) points: Vec<(u32, f64)>,
    /// k neighbour indices per answered point, ascending by (distance, index).
    pub(crate) lists: Vec<u32>,
    /// Work of this cell.
    work: Work,
}

/// One grid level over a subset of the points.
///
/// ```text
///   sorted:  [ ids of cell A (Z-order, id) | ids of cell B | … ]   runs: (key, start, end), by key
///   xs, ys, zs: [ their local coordinates, same order ]            columns: (x, y) → its runs
///   cell of p = ⌊(p − corner) / cell⌋, relative to the subset's own lower corner
///   key = x · 2⁸⁴ + y · 2⁴² + z: the cells of one (x, y) column are consecutive runs, by z,
///   so a 3 × 3 × 3 block costs 9 hash look-ups, not 27
/// ```
struct Level {
    /// Cell side.
    cell: f64,
    /// Lower corner of the subset (local coordinates): cell coordinates are relative to it, so
    /// they stay small and their rounding is relative to the subset's extent, not to the
    /// coordinates' magnitude.
    corner: [f64; 3],
    /// Absolute allowance for the rounding of cell geometry, subtracted from every reach.
    slack: f64,
    /// Point indices, sorted by (cell key, Z-order inside the cell, index).
    sorted: Vec<u32>,
    /// Their local coordinates, same order, one column per axis: gathering a block copies
    /// contiguous runs into the block's own columns.
    xs: Vec<f64>,
    ys: Vec<f64>,
    zs: Vec<f64>,
    /// Their tie keys, same order, when every key fits in 32 bits ([`packed`]; empty
    /// otherwise): gathering a block copies them too, instead of looking each candidate's key up
    /// in the index's order (a cache miss per candidate where the input is not in spatial order,
    /// a third of the block gathering's time on the cluttered scene).
    ties: Vec<u32>,
    /// One entry per occupied cell, ascending by key: (key, start, end) in `sorted`.
    runs: Runs,
    /// Column key (x, y) → its cells' range in `runs`.
    columns: FxHashMap<u128, (u32, u32)>,
}

/// The geometry of an earlier (coarser) level a query passed through: it bounds which points
/// the finer levels hold (see the module overview).
#[derive(Clone, Copy)]
struct Ancestor {
    cell: f64,
    corner: [f64; 3],
    slack: f64,
}

impl Ancestor {
    /// Distance from `q` to the faces of its cell, at least 0.
    fn inner(&self, q: [f64; 3]) -> f64 {
        let mut inner = f64::INFINITY;
        for (&qa, &ca) in q.iter().zip(&self.corner) {
            let u = qa - ca;
            let lo = (u / self.cell).floor() * self.cell;
            inner = inner.min(u - lo).min(lo + self.cell - u);
        }
        inner.max(0.0)
    }

    /// Radius around `q` within which every point of the level lies in the cells within `ring`
    /// of q's cell.
    fn reach(&self, q: [f64; 3], ring: i64) -> f64 {
        ring as f64 * self.cell + self.inner(q) - self.slack
    }
}

const Z_MASK: u128 = (1u128 << AXIS_BITS) - 1;

impl Level {
    /// Sorts `ids` into cells of side `want` (floored so the level spans at most [`MAX_SPAN`]
    /// cells per axis; any positive size when the points coincide); `ties` are the pass's tie
    /// keys (`None`: the indices).
    fn build(local: &[[f64; 3]], ids: Vec<u32>, want: f64, ties: Option<&[u64]>) -> Level {
        let (lo, hi) = bounds(local, &ids);
        let corner = if ids.is_empty() { [0.0; 3] } else { lo };
        let span = (0..3)
            .map(|a| hi[a] - corner[a])
            .fold(0.0f64, |m, s| if s.is_finite() { m.max(s) } else { m });
        let floor = span / MAX_SPAN;
        let cell = if want.is_finite() && want > floor {
            want
        } else if floor > 0.0 {
            floor
        } else {
            1.0
        };
        let mut level = Level {
            cell,
            corner,
            slack: ROUNDING * (span + cell),
            sorted: Vec::new(),
            xs: Vec::new(),
            ys: Vec::new(),
            zs: Vec::new(),
            ties: Vec::new(),
            runs: Vec::new(),
            columns: FxHashMap::default(),
        };
        // Sorted by (cell key, Z-order inside the cell, index): each cell is a contiguous run, and
        // consecutive queries are close, so the previous answer bounds the next one tightly.
        let (runs, sorted) = sort_into_cells(&level, local, ids, span);
        level.runs = runs;
        for (r, &(key, _, _)) in level.runs.iter().enumerate() {
            let col = key >> AXIS_BITS;
            let e = level.columns.entry(col).or_insert((r as u32, r as u32));
            e.1 = r as u32 + 1;
        }
        level.sorted = sorted;
        // Cell-ordered copies of the coordinates: gathering a block then copies contiguous
        // memory instead of jumping through the input order. One read of each point for all
        // three.
        let n = level.sorted.len();
        let (mut xs, mut ys, mut zs) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        xs.par_iter_mut()
            .zip(ys.par_iter_mut())
            .zip(zs.par_iter_mut())
            .zip(level.sorted.par_iter())
            .for_each(|(((x, y), z), &i)| {
                [*x, *y, *z] = local[i as usize];
            });
        (level.xs, level.ys, level.zs) = (xs, ys, zs);
        if packed(ties, local.len()) {
            level.ties = level
                .sorted
                .par_iter()
                .map(|&i| ties.map_or(i, |t| t[i as usize] as u32))
                .collect();
        }
        level
    }

    /// Local coordinates of the point at position `j` of `sorted`.
    #[inline]
    fn point(&self, j: usize) -> [f64; 3] {
        [self.xs[j], self.ys[j], self.zs[j]]
    }

    fn ancestor(&self) -> Ancestor {
        Ancestor {
            cell: self.cell,
            corner: self.corner,
            slack: self.slack,
        }
    }

    /// Cell coordinates of `p` (non-negative for the level's own points).
    #[inline]
    fn coord(&self, p: [f64; 3]) -> [i64; 3] {
        let c = |a: usize| floor_i64((p[a] - self.corner[a]) / self.cell);
        [c(0), c(1), c(2)]
    }

    /// The key of cell `c`, or `None` outside the range keys can hold (no point lies there).
    #[inline]
    fn key(&self, c: [i64; 3]) -> Option<u128> {
        let limit = 1i64 << AXIS_BITS;
        if c.iter().any(|&v| !(0..limit).contains(&v)) {
            return None;
        }
        Some((c[0] as u128) << (2 * AXIS_BITS) | (c[1] as u128) << AXIS_BITS | c[2] as u128)
    }

    /// The 9-bit Z-order position of `p` inside its cell `c` (8 steps per axis).
    fn sub(&self, p: [f64; 3], c: [i64; 3]) -> u16 {
        let mut z = 0u16;
        for a in 0..3 {
            let u = (p[a] - self.corner[a]) / self.cell - c[a] as f64;
            let f = (u * 8.0).clamp(0.0, 7.0) as u16;
            for bit in 0..3 {
                z |= ((f >> bit) & 1) << (3 * bit + a);
            }
        }
        z
    }

    /// Calls `f(start, end)` (a range of `sorted`) for every occupied cell at Chebyshev distance
    /// `lo..=hi` from cell `c`, column by column, until `f` returns false; returns false then.
    fn for_cells(
        &self,
        c: [i64; 3],
        lo: i64,
        hi: i64,
        lookups: &mut u64,
        mut f: impl FnMut(usize, usize) -> bool,
    ) -> bool {
        let limit = 1i64 << AXIS_BITS;
        for dy in -hi..=hi {
            for dx in -hi..=hi {
                let (x, y) = (c[0] + dx, c[1] + dy);
                if !(0..limit).contains(&x) || !(0..limit).contains(&y) {
                    continue;
                }
                *lookups += 1;
                let Some(&(r0, r1)) = self.columns.get(&((x as u128) << AXIS_BITS | y as u128))
                else {
                    continue;
                };
                let runs = &self.runs[r0 as usize..r1 as usize];
                let plane = dx.abs().max(dy.abs());
                let first = runs.partition_point(|r| ((r.0 & Z_MASK) as i64) < c[2] - hi);
                for &(key, a, b) in &runs[first..] {
                    let dz = (key & Z_MASK) as i64 - c[2];
                    if dz > hi {
                        break;
                    }
                    if plane.max(dz.abs()) >= lo && !f(a as usize, b as usize) {
                        return false;
                    }
                }
            }
        }
        true
    }

    /// Appends the cells at Chebyshev distance `lo..=hi` from cell `c` to the block, unless that
    /// would make it hold more than `cap` candidates; returns false then (the block is then
    /// incomplete and must not be used for this ring).
    fn push_cells(
        &self,
        blk: &mut Block,
        c: [i64; 3],
        (lo, hi): (i64, i64),
        cap: usize,
        pass: &Pass,
        lookups: &mut u64,
    ) -> bool {
        let sorted = &self.sorted;
        self.for_cells(c, lo, hi, lookups, |a, b| {
            if blk.ids.len() + (b - a) > cap {
                return false;
            }
            blk.ids.extend_from_slice(&sorted[a..b]);
            if pass.packed {
                let at = blk.keys.len() as u64;
                blk.keys.extend(
                    self.ties[a..b]
                        .iter()
                        .zip(at..)
                        .map(|(&t, j)| (t as u64) << 32 | j),
                );
            } else {
                blk.keys.extend(sorted[a..b].iter().map(|&i| pass.tie(i)));
            }
            blk.xs.extend_from_slice(&self.xs[a..b]);
            blk.ys.extend_from_slice(&self.ys[a..b]);
            blk.zs.extend_from_slice(&self.zs[a..b]);
            true
        })
    }
}

/// A cell's runs: (cell key, start, end) of each occupied cell, by key.
type Runs = Vec<(u128, u32, u32)>;

/// `ids` sorted by (cell key, Z-order inside the cell, index), and the runs of each cell in that
/// order: [`sort_packed`] where the level's cells fit its keys, else [`sort_tuples`] (the same
/// order).
fn sort_into_cells(
    level: &Level,
    local: &[[f64; 3]],
    ids: Vec<u32>,
    span: f64,
) -> (Runs, Vec<u32>) {
    match sort_packed(level, local, &ids, span) {
        Some(sorted) => sorted,
        None => sort_tuples(level, local, ids),
    }
}

/// Appends position `pos` of the sorted points, in cell `key`, to the runs.
fn extend_runs(runs: &mut Runs, pos: usize, key: u128) {
    match runs.last_mut() {
        Some(r) if r.0 == key => r.2 = pos as u32 + 1,
        _ => runs.push((key, pos as u32, pos as u32 + 1)),
    }
}

/// Bits of one cell coordinate in a [`sort_packed`] entry.
const PACKED_AXIS: u32 = 29;

/// [`sort_into_cells`] with each point one `u128`: cell coordinates in [`PACKED_AXIS`] bits each,
/// the Z-order's 9 bits, the index; sorted with single comparisons, where the tuples of
/// [`sort_tuples`] compare field by field (a 1.35 M-point tile's first level built in
/// 0.15–0.21 s instead of 0.24–0.28 s; docs/DECISIONS.md, issue 16). `None` when the level
/// spans more cells per axis than the bits hold (a far outlier beside a fine cell).
fn sort_packed(
    level: &Level,
    local: &[[f64; 3]],
    ids: &[u32],
    span: f64,
) -> Option<(Runs, Vec<u32>)> {
    const A: u32 = PACKED_AXIS;
    let cells = span / level.cell;
    if !(cells.is_finite() && cells < (1u64 << A) as f64 - 4.0) {
        return None;
    }
    let limit = 1i64 << A;
    let mut packed: Vec<u128> = ids
        .par_iter()
        .map(|&i| {
            let p = local[i as usize];
            let c = level.coord(p);
            if c.iter().all(|v| (0..limit).contains(v)) {
                let cell = (c[0] as u128) << (2 * A) | (c[1] as u128) << A | c[2] as u128;
                cell << 41 | u128::from(level.sub(p, c)) << 32 | u128::from(i)
            } else {
                u128::MAX
            }
        })
        .collect();
    if packed.contains(&u128::MAX) {
        return None;
    }
    packed.par_sort_unstable();
    let mask = (1u128 << A) - 1;
    let mut runs = Vec::new();
    for (pos, &e) in packed.iter().enumerate() {
        let cell = e >> 41;
        let c = [cell >> (2 * A), (cell >> A) & mask, cell & mask].map(|v| v as i64);
        // The level's own key of the cell (every coordinate fits: 29 bits < AXIS_BITS).
        extend_runs(&mut runs, pos, level.key(c).unwrap_or(u128::MAX));
    }
    let sorted = packed.par_iter().map(|&e| e as u32).collect();
    Some((runs, sorted))
}

/// [`sort_into_cells`] with (key split into two u64, Z-order, index) tuples: any level.
fn sort_tuples(level: &Level, local: &[[f64; 3]], ids: Vec<u32>) -> (Runs, Vec<u32>) {
    let mut keyed: Vec<(u64, u64, u16, u32)> = ids
        .par_iter()
        .map(|&i| {
            let p = local[i as usize];
            let c = level.coord(p);
            let key = level.key(c).unwrap_or(u128::MAX);
            ((key >> 64) as u64, key as u64, level.sub(p, c), i)
        })
        .collect();
    drop(ids);
    keyed.par_sort_unstable();
    let mut runs = Vec::new();
    for (pos, &(h, l, _, _)) in keyed.iter().enumerate() {
        extend_runs(&mut runs, pos, (h as u128) << 64 | l as u128);
    }
    let sorted = keyed.par_iter().map(|&(_, _, _, i)| i).collect();
    (runs, sorted)
}

/// Lower and upper corner of the points `ids`.
fn bounds(local: &[[f64; 3]], ids: &[u32]) -> ([f64; 3], [f64; 3]) {
    let empty = || ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    ids.par_iter()
        .fold(empty, |(mut lo, mut hi), &i| {
            let p = local[i as usize];
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
            (lo, hi)
        })
        .reduce(empty, |(l1, h1), (l2, h2)| {
            (
                [l1[0].min(l2[0]), l1[1].min(l2[1]), l1[2].min(l2[2])],
                [h1[0].max(h2[0]), h1[1].max(h2[1]), h1[2].max(h2[2])],
            )
        })
}

/// A set of point indices as bits.
struct Bits(Vec<u64>);

impl Bits {
    fn new(n: usize) -> Bits {
        Bits(vec![0; n.div_ceil(64)])
    }
    #[inline]
    fn get(&self, i: u32) -> bool {
        self.0[(i / 64) as usize] >> (i % 64) & 1 == 1
    }
    fn set(&mut self, i: u32) {
        self.0[(i / 64) as usize] |= 1 << (i % 64);
    }
}

/// True when every tie key of a pass over `n` points (`ties`, or the indices when `None`) fits in
/// 32 bits ([`Pass::packed`], [`Level::ties`]).
fn packed(ties: Option<&[u64]>, n: usize) -> bool {
    match ties {
        Some(t) => t.iter().all(|&x| x <= u32::MAX as u64),
        None => n <= u32::MAX as usize + 1,
    }
}

/// The fixed inputs of one pass.
struct Pass<'a> {
    local: &'a [[f64; 3]],
    ties: Option<&'a [u64]>,
    k: usize,
    cancel: Option<&'a AtomicBool>,
    /// Every tie key fits in 32 bits: a candidate's rank (distance, tie) and its block position
    /// pack into one `u128`, which sorts in half the memory of a `(u128, u32)` pair with one
    /// comparison (the ranking is the same: tie keys are distinct).
    packed: bool,
}

impl Pass<'_> {
    #[inline]
    fn tie(&self, i: u32) -> u64 {
        self.ties.map_or(i as u64, |t| t[i as usize])
    }

    fn cancelled(&self) -> bool {
        self.cancel.is_some_and(|c| c.load(Ordering::Relaxed))
    }
}

/// Level 0 of [`all_knn`]: every indexed point sorted into cells of one size. Built once by the
/// caller, it serves every pass over the same points with the same k: the rounds of
/// [`super::KnnIndex::knn_near`] each ask for a few more lists, and rebuilding it (a sort of
/// the whole run) for each was most of a halo-growth group's k-NN time (issue 16).
pub(crate) struct BaseLevel(Level);

impl BaseLevel {
    /// Sorts `ids` (indices into `local`) into cells of side `cell` (see [`Level::build`]);
    /// `ties` must be those of the passes it will serve.
    pub(crate) fn build(
        local: &[[f64; 3]],
        ids: Vec<u32>,
        cell: f64,
        ties: Option<&[u64]>,
    ) -> BaseLevel {
        BaseLevel(Level::build(local, ids, cell, ties))
    }

    /// What a pass with lists of `k` would do with the `probes` (indices into `local`, points of
    /// this level) at this level: a probe is answered when the 3 × 3 × 3 block proves its k-th
    /// distance, or the 5 × 5 × 5 block does (skipped, as in the pass, when it holds more than
    /// [`RING2_LOAD_PER_K`] · k candidates); otherwise it goes to the k-d tree. A probe in a dense
    /// cell counts as answered (a finer level takes it). Only k-th distances are measured, so
    /// ties do not matter.
    pub(crate) fn trial(&self, local: &[[f64; 3]], probes: &[u32], k: usize) -> Trial {
        let level = &self.0;
        let me = level.ancestor();
        let mut d: Vec<f64> = Vec::new();
        let mut lookups = 0;
        let add = |d: &mut Vec<f64>, q: [f64; 3], a: usize, b: usize| {
            d.extend((a..b).map(|j| dist2(q, level.point(j))));
        };
        // The k-th distance when the block proves it.
        let proved = |d: &mut Vec<f64>, q: [f64; 3], ring: i64| {
            if d.len() < k {
                return None;
            }
            let (_, &mut dk, _) = d.select_nth_unstable_by(k - 1, f64::total_cmp);
            let reach = me.reach(q, ring);
            (reach > 0.0 && dk < reach * reach).then(|| dk.sqrt())
        };
        let mut out = Trial::default();
        for &i in probes {
            let q = local[i as usize];
            let c = level.coord(q);
            d.clear();
            let ring1 = level.for_cells(c, 0, 1, &mut lookups, |a, b| {
                add(&mut d, q, a, b);
                d.len() <= DENSE_LOAD_PER_K * k
            });
            let kth = if !ring1 {
                Some(0.0)
            } else {
                proved(&mut d, q, 1).or_else(|| {
                    let ring2 = level.for_cells(c, 2, 2, &mut lookups, |a, b| {
                        add(&mut d, q, a, b);
                        d.len() <= RING2_LOAD_PER_K * k
                    });
                    if ring2 { proved(&mut d, q, 2) } else { None }
                })
            };
            out.tree += usize::from(kth.is_none());
            out.kth.push(kth.unwrap_or(f64::INFINITY));
        }
        out.kth.sort_by(f64::total_cmp);
        out
    }
}

/// What [`BaseLevel::trial`] found.
#[derive(Debug, Clone, Default)]
pub(crate) struct Trial {
    /// Probes the pass would leave to the k-d tree.
    pub tree: usize,
    /// Each probe's k-th neighbour distance, ascending: exact where the level proves it, 0 in a
    /// dense cell (below the level's scale), infinite where the probe goes to the tree.
    pub kth: Vec<f64>,
}

/// Runs the grid levels over the points of `base` (indices into `local`), starting with `base`
/// itself. Every point of `base` that `asked` selects (all of them when `None`) appears in
/// exactly one returned [`CellAnswers`], answered or marked for the tree (NaN); every point of
/// `base` is a candidate. A cell without asked points costs nothing beyond its place in the grid.
/// `base` must have been built over `local`.
///
/// # Errors
/// [`Cancelled`] once `cancel` is set (checked per cell and per query).
pub(crate) fn all_knn(
    local: &[[f64; 3]],
    base: &BaseLevel,
    asked: Option<&[bool]>,
    ties: Option<&[u64]>,
    k: usize,
    cancel: Option<&AtomicBool>,
) -> Result<(Vec<CellAnswers>, Work), Cancelled> {
    let pass = Pass {
        local,
        ties,
        k,
        cancel,
        packed: packed(ties, local.len()),
    };
    let ids = &base.0.sorted;
    let mut queries: Option<Bits> = asked.map(|a| {
        let mut b = Bits::new(local.len());
        for &i in ids.iter().filter(|&&i| a[i as usize]) {
            b.set(i);
        }
        b
    });
    let mut work = Work {
        queries: match &queries {
            Some(q) => ids.iter().filter(|&&i| q.get(i)).count() as u64,
            None => ids.len() as u64,
        },
        ..Work::default()
    };
    let mut out: Vec<CellAnswers> = Vec::new();
    let mut ancestors: Vec<Ancestor> = Vec::new();
    // The points of the next level (level 0 is the caller's) and its cell size.
    let mut subset = Vec::new();
    let mut want = 0.0;
    for depth in 0..MAX_LEVELS {
        if ids.is_empty() || (depth > 0 && subset.is_empty()) {
            break;
        }
        work.levels = depth as u32 + 1;
        let built;
        let level = if depth == 0 {
            &base.0
        } else {
            built = Level::build(local, std::mem::take(&mut subset), want, ties);
            &built
        };
        let is_query = |i: u32| queries.as_ref().is_none_or(|q| q.get(i));
        let may_defer = depth + 1 < MAX_LEVELS;
        let run_cell = |blk: &mut Block, r: usize, defer: bool| -> (CellAnswers, usize) {
            let (_, a, b) = level.runs[r];
            if pass.cancelled() {
                return (CellAnswers::default(), 0);
            }
            answer_cell(
                &pass,
                level,
                &ancestors,
                blk,
                (a as usize, b as usize),
                &is_query,
                defer,
            )
        };
        // Every cell holding queries is answered from its block, or, when the block is dense,
        // deferred to the next level (its load returned).
        let mut answers: Vec<(CellAnswers, usize)> = (0..level.runs.len())
            .into_par_iter()
            .with_min_len(64)
            .map_init(Block::default, |blk, r| run_cell(blk, r, may_defer))
            .collect();
        if pass.cancelled() {
            return Err(Cancelled);
        }
        let mut dense: Vec<usize> = (0..answers.len()).filter(|&r| answers[r].1 > 0).collect();
        let mut next = Vec::new();
        let mut next_want = 0.0;
        if !dense.is_empty() {
            // The next level holds every point of the dense cells' blocks.
            let mut ranges: Vec<(u32, u32)> = Vec::new();
            for &r in &dense {
                let c = level.coord(level.point(level.runs[r].1 as usize));
                let mut lookups = 0;
                level.for_cells(c, 0, 1, &mut lookups, |a, b| {
                    ranges.push((a as u32, b as u32));
                    true
                });
                work.cells += lookups;
            }
            ranges.par_sort_unstable();
            ranges.dedup();
            for (a, b) in ranges {
                next.extend_from_slice(&level.sorted[a as usize..b as usize]);
            }
            let least = dense.iter().map(|&r| answers[r].1).min().unwrap_or(0);
            let shrink = libm::cbrt(least as f64 / (TARGET_LOAD_PER_K * k as f64)).clamp(2.0, 1e6);
            next_want = level.cell / shrink;
            // A level that cannot be finer than this one (its span floors the cell size) would
            // make no progress: answer everything here instead.
            let (lo, hi) = bounds(local, &next);
            let span = (0..3).map(|a| hi[a] - lo[a]).fold(0.0f64, f64::max);
            if span / MAX_SPAN >= level.cell / 1.5 {
                let forced: Vec<(CellAnswers, usize)> = dense
                    .par_iter()
                    .map_init(Block::default, |blk, &r| run_cell(blk, r, false))
                    .collect();
                if pass.cancelled() {
                    return Err(Cancelled);
                }
                for (&r, f) in dense.iter().zip(forced) {
                    answers[r] = f;
                }
                dense.clear();
                next.clear();
            }
        }
        let mut bits = (!dense.is_empty()).then(|| Bits::new(local.len()));
        for (r, (a, _)) in answers.into_iter().enumerate() {
            work.merge(&a.work);
            if !a.points.is_empty() {
                out.push(CellAnswers {
                    work: Work::default(),
                    ..a
                });
            }
            if let Some(bits) = bits.as_mut()
                && dense.binary_search(&r).is_ok()
            {
                let (_, a, b) = level.runs[r];
                for &i in &level.sorted[a as usize..b as usize] {
                    if is_query(i) {
                        bits.set(i);
                    }
                }
            }
        }
        let Some(bits) = bits else {
            break;
        };
        ancestors.push(level.ancestor());
        queries = Some(bits);
        subset = next;
        want = next_want;
    }
    Ok((out, work))
}

/// Answers the queries among the points `level.sorted[a..b]` (one cell) from its block: ring 1
/// first, ring 2 for those ring 1 cannot prove; the rest are marked for the tree. With `defer`,
/// a dense block is not scanned: the load is returned instead (second value, 0 otherwise).
fn answer_cell(
    pass: &Pass,
    level: &Level,
    ancestors: &[Ancestor],
    blk: &mut Block,
    (a, b): (usize, usize),
    is_query: &impl Fn(u32) -> bool,
    defer: bool,
) -> (CellAnswers, usize) {
    let k = pass.k;
    if !level.sorted[a..b].iter().any(|&i| is_query(i)) {
        return (CellAnswers::default(), 0);
    }
    let c = level.coord(level.point(a));
    let me = level.ancestor();
    let cap = |q: [f64; 3]| {
        ancestors
            .iter()
            .map(|an| an.reach(q, 1))
            .fold(f64::INFINITY, f64::min)
    };
    let mut out = CellAnswers::default();
    let dense_load = DENSE_LOAD_PER_K * k;
    blk.clear();
    let limit = if defer { dense_load } else { usize::MAX };
    if !level.push_cells(blk, c, (0, 1), limit, pass, &mut out.work.cells) {
        // Dense: measure the load without copying the rest of the block (copying it only to
        // measure it was a large share of a cluttered cloud's k-NN time).
        let mut load = 0;
        level.for_cells(c, 0, 1, &mut out.work.cells, |s, e| {
            load += e - s;
            true
        });
        // A stack of coincident points that makes up much of the load cannot be split: answered
        // here, deduplicated (one block scan for the whole stack).
        let stack = b - a > dense_load / 4 && (a..b).all(|j| level.point(j) == level.point(a));
        if !stack {
            return (out, load);
        }
        blk.clear();
        level.push_cells(blk, c, (0, 1), usize::MAX, pass, &mut out.work.cells);
    }
    out.points.reserve(b - a);
    out.lists.reserve((b - a) * k);
    let mut retry = Vec::new();
    // The last query of this cell and where its answer is (`None` when it failed).
    let mut last: Option<([f64; 3], Option<usize>)> = None;
    for (j, &qi) in (a..b).zip(&level.sorted[a..b]) {
        let q = level.point(j);
        if !is_query(qi) {
            continue;
        }
        if pass.cancelled() {
            return (CellAnswers::default(), 0);
        }
        if let Some((pq, at)) = last
            && pq == q
        {
            // The same position asks the same question: the same answer.
            match at {
                Some(at) => {
                    let r = out.points[out.points.len() - 1].1;
                    out.lists.extend_from_within(at..at + k);
                    out.points.push((qi, r));
                }
                None => {
                    retry.push(out.points.len());
                    out.points.push((qi, f64::NAN));
                }
            }
            continue;
        }
        let reach = me.reach(q, 1).min(cap(q));
        let at = out.lists.len();
        let r = query(blk, q, k, reach, pass.packed, &mut out.lists, &mut out.work);
        if r.is_nan() {
            retry.push(out.points.len());
            last = Some((q, None));
        } else {
            blk.prev = Some((q, r));
            last = Some((q, Some(at)));
        }
        out.points.push((qi, r));
    }
    if retry.is_empty() {
        return (out, 0);
    }
    // A second ring around the cell answers most of what the first could not (points near a
    // sparse border), unless it is heavy; the rest go to the k-d tree. Answers are appended in
    // retry order, so reorder the lists to follow `points`.
    blk.prev_sel.clear();
    let cap2 = RING2_LOAD_PER_K * k;
    if !level.push_cells(blk, c, (2, 2), cap2, pass, &mut out.work.cells) {
        return (out, 0);
    }
    let mut extra = Vec::new();
    let mut last: Option<([f64; 3], f64, Option<usize>)> = None;
    for &slot in &retry {
        if pass.cancelled() {
            return (CellAnswers::default(), 0);
        }
        let qi = out.points[slot].0;
        let q = pass.local[qi as usize];
        let r = match last {
            Some((pq, r, at)) if pq == q => {
                if let Some(at) = at {
                    extra.extend_from_within(at..at + k);
                }
                r
            }
            _ => {
                let reach = me.reach(q, 2).min(cap(q));
                let at = extra.len();
                let r = query(blk, q, k, reach, pass.packed, &mut extra, &mut out.work);
                last = Some((q, r, (!r.is_nan()).then_some(at)));
                r
            }
        };
        out.points[slot].1 = r;
    }
    if extra.is_empty() {
        return (out, 0);
    }
    let mut lists = Vec::with_capacity(out.lists.len() + extra.len());
    let (mut first, mut second) = (0, 0);
    let mut next_retry = retry.iter().peekable();
    for (slot, &(_, r)) in out.points.iter().enumerate() {
        let retried = next_retry.peek() == Some(&&slot);
        if retried {
            next_retry.next();
            if !r.is_nan() {
                lists.extend_from_slice(&extra[second..second + k]);
                second += k;
            }
        } else if !r.is_nan() {
            lists.extend_from_slice(&out.lists[first..first + k]);
            first += k;
        }
    }
    out.lists = lists;
    (out, 0)
}

#[inline(always)]
pub(crate) fn rank(d: f64, tie: u64) -> u128 {
    (d.to_bits() as u128) << 64 | tie as u128
}

/// The squared distance inside a [`rank`].
#[inline(always)]
pub(crate) fn rank_distance(r: u128) -> f64 {
    f64::from_bits((r >> 64) as u64)
}

/// Appends the k nearest candidates of `q` in the block to `lists` and returns the k-th squared
/// distance, or returns NaN (appending nothing) when the block cannot prove the answer complete:
/// every point outside the block is known to be at least `reach` away from `q`.
///
/// `blk.prev` is an earlier answered query: by the triangle inequality its k neighbours lie within
/// `√d_prev + |q − q_prev|` of `q`, which bounds this query's k-th distance and lets all but a
/// few candidates be discarded with one comparison.
fn query(
    blk: &mut Block,
    q: [f64; 3],
    k: usize,
    reach: f64,
    packed: bool,
    lists: &mut Vec<u32>,
    work: &mut Work,
) -> f64 {
    let m = blk.ids.len();
    work.candidates += m as u64;
    work.max_block = work.max_block.max(m as u64);
    if m < k || reach.is_nan() || reach <= 0.0 {
        return f64::NAN;
    }
    // Zipped columns, no indexing: the loop vectorises.
    blk.d.clear();
    blk.d.extend(
        blk.xs
            .iter()
            .zip(&blk.ys)
            .zip(&blk.zs)
            .map(|((&x, &y), &z)| dist2(q, [x, y, z])),
    );
    let t = if blk.prev_sel.len() == k {
        // k block members lie within the farthest of them: an exact bound, same formula.
        blk.prev_sel
            .iter()
            .map(|&j| blk.d[j as usize])
            .fold(0.0, f64::max)
    } else {
        match blk.prev {
            Some((pq, pr)) => {
                let bound = pr.sqrt() + dist2(q, pq).sqrt();
                // Widened so rounding in either distance cannot drop a true member.
                bound * bound * (1.0 + 1e-9) + f64::MIN_POSITIVE
            }
            None => f64::INFINITY,
        }
    };
    // A tighter guess from the previous answer's k-th distance, kept when it provably holds k
    // candidates (a vectorised count): fewer candidates to rank.
    let t = match blk.prev {
        Some((_, pr)) if pr * GUESS < t => {
            let g = pr * GUESS;
            let n = blk.d.iter().filter(|&&d| d <= g).count();
            if n >= k { g } else { t }
        }
        _ => t,
    };
    let dk = if packed {
        select_packed(blk, k, t)
    } else {
        select_wide(blk, k, t)
    };
    // Strict, with a relative margin for the rounding of `dist2`.
    if dk < reach * reach * (1.0 - 1e-9) {
        lists.extend(blk.prev_sel.iter().map(|&j| blk.ids[j as usize]));
        dk
    } else {
        f64::NAN
    }
}

/// The k best candidates by (distance, tie) among those within `t` (all of them when fewer than
/// k are), into `blk.prev_sel` in ascending order; returns the k-th squared distance. Packed
/// ranks ([`Pass::packed`]): one branchless pass over the block builds the ranks of the
/// candidates within the bound.
const GUESS: f64 = 1.2;

fn select_packed(blk: &mut Block, k: usize, t: f64) -> f64 {
    let m = blk.ids.len();
    if blk.ranked.len() < m {
        blk.ranked.resize(m, 0);
    }
    let pack = |d: f64, key: u64| (d.to_bits() as u128) << 64 | key as u128;
    let ranked = &mut blk.ranked[..m];
    let mut kept = 0;
    for (&d, &key) in blk.d.iter().zip(&blk.keys) {
        ranked[kept] = pack(d, key);
        kept += (d <= t) as usize;
    }
    if kept < k {
        for ((r, &d), &key) in ranked.iter_mut().zip(&blk.d).zip(&blk.keys) {
            *r = pack(d, key);
        }
        kept = m;
    }
    let mut best = &mut ranked[..kept];
    if kept > 2 * k {
        best.select_nth_unstable(k - 1);
        best = &mut best[..k];
    }
    best.sort_unstable();
    blk.prev_sel.clear();
    blk.prev_sel.extend(best[..k].iter().map(|&r| r as u32));
    rank_distance(best[k - 1])
}

/// [`select_packed`] for tie keys beyond 32 bits: (rank, position) pairs.
fn select_wide(blk: &mut Block, k: usize, t: f64) -> f64 {
    let m = blk.ids.len();
    // Branchless compaction of the candidates within the bound.
    let sel = &mut blk.sel;
    sel.clear();
    sel.resize(m, 0);
    let mut kept = 0;
    for j in 0..m {
        sel[kept] = j as u32;
        kept += (blk.d[j] <= t) as usize;
    }
    if kept < k {
        for (j, s) in sel.iter_mut().enumerate() {
            *s = j as u32;
        }
        kept = m;
    }
    let best = &mut blk.best;
    best.clear();
    best.extend(sel[..kept].iter().map(|&j| {
        let ju = j as usize;
        (rank(blk.d[ju], blk.keys[ju]), j)
    }));
    if kept > 2 * k {
        best.select_nth_unstable(k - 1);
        best.truncate(k);
    }
    best.sort_unstable();
    blk.prev_sel.clear();
    blk.prev_sel.extend(best[..k].iter().map(|e| e.1));
    rank_distance(best[k - 1].0)
}

#[cfg(test)]
mod tests {
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    /// A noisy cluster, a sparse scatter and duplicate stacks, from a fixed seed.
    fn cloud(n: usize, far: f64) -> Vec<[f64; 3]> {
        let mut rng = ChaCha8Rng::seed_from_u64(16);
        let mut f = move || rng.random::<f64>();
        let mut pts: Vec<[f64; 3]> = (0..n)
            .map(|i| match i % 5 {
                0 => [f() * 10.0, f() * 10.0, f() * 10.0],
                1 => [3.0, 3.0, 3.0],
                _ => [5.0 + f() * 0.1, 5.0 + f() * 0.1, f() * 0.01],
            })
            .collect();
        pts.push([far, -far, far]);
        pts
    }

    #[test]
    fn packed_cell_order_equals_the_tuple_order() {
        for (far, cell) in [(20.0, 0.05), (1e3, 0.013), (1e3, 0.5)] {
            let local = cloud(20_000, far);
            let ids: Vec<u32> = (0..local.len() as u32).rev().collect();
            let level = Level::build(&local, ids.clone(), cell, None);
            let (lo, hi) = bounds(&local, &ids);
            let span = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
            let packed = sort_packed(&level, &local, &ids, span).expect("the level fits");
            let tuples = sort_tuples(&level, &local, ids);
            assert_eq!(packed, tuples);
            assert_eq!(packed.1, level.sorted);
            assert_eq!(packed.0, level.runs);
        }
    }

    #[test]
    fn a_level_wider_than_the_packed_keys_sorts_by_tuples() {
        let local = cloud(2_000, 1e9);
        let ids: Vec<u32> = (0..local.len() as u32).collect();
        let level = Level::build(&local, ids.clone(), 0.01, None);
        let (lo, hi) = bounds(&local, &ids);
        let span = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        assert!(sort_packed(&level, &local, &ids, span).is_none());
        let tuples = sort_tuples(&level, &local, ids);
        assert_eq!(tuples.1, level.sorted);
        assert_eq!(tuples.0, level.runs);
    }
}
