//! Pass 1: bounds, counts, a deterministic sample, and the adaptive split into tiles.
//!
//! The planner sees every point once. It keeps the exact bounds of the finite points, the
//! counts, and a *bottom-k* sample: the points whose hashed global index is among the `S`
//! smallest, which is a uniform sample that does not depend on batch sizes or thread counts.
//! Tiles are then chosen by count, not by area: a k-d split of the sample, along the axis (of
//! those at least half as long as the longest) whose cut has the fewest sample points within the
//! halo of it, at the quantile that leaves the left side a whole number of full target-sized tiles, until
//! each leaf is expected to hold at most the target number of points. Every tile but one thus
//! holds the target for any cloud size.
//!
//! ```text
//!   split tree (axis, value)            leaves = tiles; ownership is half-open:
//!        x < 4.2 ?                      descend "p[axis] < value → left, else right",
//!       /         \                     so every point has exactly one owner
//!   y < 1.0 ?    tile 2
//!    /     \
//!  tile 0  tile 1
//! ```

use std::collections::BinaryHeap;

use glam::DVec3;
use smallvec::{SmallVec, smallvec};

use crate::points::Aabb;
use crate::tiling::{TilingError, occupancy};

/// Upper bound on the planning sample (the sample the isolation radius is drawn from).
pub const SAMPLE: usize = crate::denoise::isolation::SAMPLE;

/// A node of the split tree.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Node {
    /// Points with `p[axis] < value` go to `left`, the others to `right`.
    Split {
        /// 0, 1 or 2.
        axis: usize,
        /// The split coordinate.
        value: f64,
        /// Child node index.
        left: usize,
        /// Child node index.
        right: usize,
    },
    /// A tile.
    Leaf {
        /// Tile index.
        tile: usize,
    },
}

/// One tile: the box of space it owns.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Tile {
    /// Its index.
    pub id: usize,
    /// Its box (bounded by the cloud's bounds on the outside faces).
    pub core: Aabb,
    /// Points the sample predicts it owns.
    pub estimate: u64,
    /// Its first load's halo: the plan's, or narrower where that would load more points than the
    /// budget allows one run ([`Planner::finish_within`]); with `faces`, the narrowest of them.
    /// 0 in plans written before it existed, read as the plan's ([`Plan::tile_halo`]).
    #[serde(default)]
    pub halo: f64,
    /// The halo of each face (−x, +x, −y, +y, −z, +z) where they differ: only the faces whose
    /// halo holds too much are narrowed. `None`: every face has `halo`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub faces: Option<[f64; 6]>,
}

/// The result of planning.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Plan {
    /// Bounds of the finite points.
    pub bounds: Aabb,
    /// Origin of the relative coordinates every tile uses (`bounds.min`, as the in-memory path).
    pub origin: DVec3,
    /// All points read (finite or not).
    pub points: u64,
    /// Points processed (passing [`crate::points::in_range`]).
    pub finite: u64,
    /// The split tree; node 0 is the root.
    pub nodes: Vec<Node>,
    /// The tiles, by index.
    pub tiles: Vec<Tile>,
    /// Initial halo width (in coordinate units), the widest of any tile's ([`Tile::halo`]).
    pub halo: f64,
    /// The cloud's isolation radius ([`crate::denoise::isolation`]), drawn from the same sample
    /// as the in-memory path draws it; it bounds every list, hence the halo a tile can need.
    #[serde(default)]
    pub isolation: Option<f64>,
    /// True when `isolation` is the user's `--radius`, under which shorter lists still serve
    /// ([`crate::denoise::isolation::cap`]).
    #[serde(default)]
    pub short_lists: bool,
    /// Partition parts: ranges of input records partitioned side by side, each its own task
    /// ([`Plan::part_range`]); 1 for a format that cannot seek to a record. 0 in plans written
    /// before there were parts, which therefore never equal a plan of today.
    #[serde(default)]
    pub parts: u64,
    /// Most cells of the partition's occupancy grid: its share of the memory budget
    /// ([`crate::tiling::occupancy::BYTES_PER_CELL`] each). [`occupancy::MAX_CELLS`] in plans
    /// written before there was a cap.
    #[serde(default = "most_grid_cells")]
    pub grid_cells: usize,
}

/// The grid cap of plans written before there was one.
fn most_grid_cells() -> usize {
    occupancy::MAX_CELLS
}

impl Plan {
    /// Partition parts (at least 1).
    pub fn parts(&self) -> u64 {
        self.parts.max(1)
    }

    /// The input records part `part` of [`Plan::parts`] reads: equal shares of every record read
    /// (finite or not), in order.
    pub fn part_range(&self, part: u64) -> std::ops::Range<u64> {
        let (n, p) = (u128::from(self.points), u128::from(self.parts()));
        let at = |i: u64| u64::try_from(n * u128::from(i) / p).unwrap_or(self.points);
        at(part)..at(part + 1)
    }

    /// The tile that owns `p` (a finite point).
    pub fn owner(&self, p: DVec3) -> usize {
        let mut at = 0;
        loop {
            match self.nodes[at] {
                Node::Leaf { tile } => return tile,
                Node::Split {
                    axis,
                    value,
                    left,
                    right,
                } => at = if p[axis] < value { left } else { right },
            }
        }
    }

    /// The halo of tile `t`'s first load: its own ([`Tile::halo`]), or the plan's in plans
    /// written before tiles had one.
    pub fn tile_halo(&self, t: usize) -> f64 {
        let h = self.tiles[t].halo;
        if h > 0.0 { h } else { self.halo }
    }

    /// Every tile whose box, grown by its own halos ([`Plan::face_halos`]), contains `p`: the
    /// tiles whose first load holds `p`, appended to `out`.
    pub fn near_tiles(&self, p: DVec3, out: &mut Vec<usize>) {
        let from = out.len();
        self.near(p, self.halo, out);
        let mut keep = from;
        for i in from..out.len() {
            let t = out[i];
            if self.tile_halo(t) >= self.halo || self.in_first_load(t, p) {
                out[keep] = t;
                keep += 1;
            }
        }
        out.truncate(keep);
    }

    /// Every tile whose box, grown by `halo` in every direction, contains `p`, appended to `out`.
    pub fn near(&self, p: DVec3, halo: f64, out: &mut Vec<usize>) {
        // On the stack: the plan and the partition call this once per sample or input point.
        let mut stack: SmallVec<[usize; 32]> = smallvec![0];
        while let Some(at) = stack.pop() {
            match self.nodes[at] {
                Node::Leaf { tile } => out.push(tile),
                Node::Split {
                    axis,
                    value,
                    left,
                    right,
                } => {
                    if p[axis] - halo <= value {
                        stack.push(left);
                    }
                    if p[axis] + halo >= value {
                        stack.push(right);
                    }
                }
            }
        }
    }

    /// The halo of each face of tile `t`'s first load (−x, +x, −y, +y, −z, +z).
    pub fn face_halos(&self, t: usize) -> [f64; 6] {
        self.tiles[t].faces.unwrap_or([self.tile_halo(t); 6])
    }

    /// The region of tile `t`'s first load: its box grown by its face halos, with faces on the
    /// cloud's outer bounds pushed to infinity (no point lies beyond them, so a k-NN ball
    /// crossing them is still complete).
    pub fn first_region(&self, t: usize) -> Aabb {
        self.region_within(t, &self.face_halos(t))
    }

    /// The face halos of a first load of tile `t` narrowed to `halo`: each of
    /// [`Plan::face_halos`], at most `halo`. Such a load is a subset of the spill file's.
    pub fn narrowed_faces(&self, t: usize, halo: f64) -> [f64; 6] {
        self.face_halos(t).map(|h| h.min(halo))
    }

    /// The region of a load of tile `t` with face halos `faces` (at most its own), as
    /// [`Plan::first_region`].
    pub fn region_within(&self, t: usize, faces: &[f64; 6]) -> Aabb {
        let (h, core) = (faces, self.tiles[t].core);
        self.region_of(&Aabb {
            min: core.min - DVec3::new(h[0], h[2], h[4]),
            max: core.max + DVec3::new(h[1], h[3], h[5]),
        })
    }

    /// True when `p` lies within tile `t`'s box grown by `faces`.
    pub fn within_faces(&self, t: usize, faces: &[f64; 6], p: DVec3) -> bool {
        within(&self.tiles[t].core, faces, p)
    }

    /// True when tile `t`'s first load holds `p`: `p` lies within its box grown by its face halos.
    pub fn in_first_load(&self, t: usize, p: DVec3) -> bool {
        self.within_faces(t, &self.face_halos(t), p)
    }

    /// `bx` (a box holding every point of the cloud inside it) with faces at or beyond the cloud's
    /// bounds pushed to infinity, as [`Plan::region`].
    pub fn region_of(&self, bx: &Aabb) -> Aabb {
        let mut r = *bx;
        for a in 0..3 {
            if bx.min[a] <= self.bounds.min[a] {
                r.min[a] = f64::NEG_INFINITY;
            }
            if bx.max[a] >= self.bounds.max[a] {
                r.max[a] = f64::INFINITY;
            }
        }
        r
    }
}

/// True when `p` lies within `core` grown by `faces` (−x, +x, −y, +y, −z, +z).
fn within(core: &Aabb, faces: &[f64; 6], p: DVec3) -> bool {
    (0..3).all(|a| p[a] >= core.min[a] - faces[2 * a] && p[a] <= core.max[a] + faces[2 * a + 1])
}

/// Accumulates pass 1.
#[derive(Debug, Clone)]
pub struct Planner {
    bounds: Aabb,
    points: u64,
    finite: u64,
    capacity: usize,
    /// Max-heap on the hash: the `capacity` smallest hashes seen so far.
    sample: BinaryHeap<(u64, u64, [u64; 3])>,
}

impl Planner {
    /// A planner keeping a sample of at most `capacity` points.
    pub fn new(capacity: usize) -> Planner {
        Planner {
            bounds: Aabb::empty(),
            points: 0,
            finite: 0,
            capacity: capacity.max(1),
            sample: BinaryHeap::new(),
        }
    }

    /// Sees the point with global index `i`.
    pub fn add(&mut self, i: u64, p: DVec3) {
        self.points += 1;
        if !crate::points::in_range(p) {
            return;
        }
        self.finite += 1;
        self.bounds.grow(p);
        let h = crate::points::sample_key(i);
        if self.sample.len() < self.capacity {
            self.sample
                .push((h, i, [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()]));
        } else if let Some(top) = self.sample.peek()
            && h < top.0
        {
            self.sample.pop();
            self.sample
                .push((h, i, [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()]));
        }
    }

    /// All points seen.
    pub fn points(&self) -> u64 {
        self.points
    }

    /// Points seen that are processed (passing [`crate::points::in_range`]).
    pub fn finite(&self) -> u64 {
        self.finite
    }

    /// Bounds of the finite points.
    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// Splits into tiles of about `target` points; `k` and `reach` size the initial halo.
    ///
    /// # Errors
    /// [`TilingError::Cancelled`] once the flag installed with
    /// [`crate::neighbours::with_cancel`] is set.
    pub fn finish(self, target: u64, k: usize, reach: usize) -> Result<Plan, TilingError> {
        self.finish_within(target, u64::MAX, k, reach)
    }

    /// As [`Planner::finish`], within a budget of `max_load` points per kernel run (owned plus
    /// halo, with a tenth of margin for the sample's estimate). The caller checks the exact loads
    /// after the partition. Two plans are weighed (issue 16):
    /// - **A**, the tiles of `target` with the halo of each tile that would load too much
    ///   narrowed to what fits (`Plan::fit_halos`); owned points near a narrowed face are
    ///   redone by halo growth;
    /// - **B**, smaller tiles with the whole halo, down to where shrinking stops removing load
    ///   (`shrink`), then narrowed the same way.
    ///
    /// A is returned when nothing had to be narrowed; otherwise B unless its halo copies make
    /// its summed loads more than `SHRINK_COST` times A's (a dense cluster inside the halo
    /// of every small tile near it).
    ///
    /// # Errors
    /// [`TilingError::Cancelled`] once the flag installed with
    /// [`crate::neighbours::with_cancel`] is set (checked before plan A and in every round of
    /// plan B's shrink).
    pub fn finish_within(
        self,
        target: u64,
        max_load: u64,
        k: usize,
        reach: usize,
    ) -> Result<Plan, TilingError> {
        let mut sample: Vec<(u64, DVec3)> = self
            .sample
            .into_iter()
            .map(|(_, i, b)| {
                (
                    i,
                    DVec3::new(
                        f64::from_bits(b[0]),
                        f64::from_bits(b[1]),
                        f64::from_bits(b[2]),
                    ),
                )
            })
            .collect();
        sample.sort_unstable_by_key(|s| s.0);
        let weight = if sample.is_empty() {
            0.0
        } else {
            self.finite as f64 / sample.len() as f64
        };
        let bounds = self.bounds;
        let origin = if bounds.is_empty() {
            DVec3::ZERO
        } else {
            bounds.min
        };
        let pts: Vec<DVec3> = sample.iter().map(|s| s.1).collect();
        // One typical radius for the halo and the isolation radius (a grid pass over the sample).
        let r_k = crate::denoise::isolation::typical_radius(&pts, origin, self.finite, k);
        let halo = halo_estimate(r_k, reach, &bounds);
        // The in-memory path draws the same radius from the same sample when the capacity is
        // [`SAMPLE`], as the pipeline's is.
        let isolation = crate::denoise::isolation::radius_of(r_k);
        let plan_at = |target: u64| {
            let mut nodes = Vec::new();
            let mut tiles = Vec::new();
            let mut idx: Vec<usize> = (0..pts.len()).collect();
            split(
                &pts,
                &mut idx,
                bounds,
                weight,
                target as f64,
                halo,
                &mut nodes,
                &mut tiles,
            );
            for tile in &mut tiles {
                tile.halo = halo;
            }
            Plan {
                bounds,
                origin,
                points: self.points,
                finite: self.finite,
                nodes,
                tiles,
                halo,
                isolation,
                short_lists: false,
                parts: 1,
                grid_cells: occupancy::MAX_CELLS,
            }
        };
        let target = target.max(1);
        // A tenth of margin: the sample's estimate is not the exact count.
        let accept = 0.9 * max_load as f64;
        if crate::neighbours::cancel_requested() {
            return Err(TilingError::Cancelled);
        }
        // Plan A: the budget's tiles, with the halos that would overload a run narrowed.
        let mut fitted = plan_at(target);
        let (fitted_max, fitted_total) = fitted.fit_halos(&pts, weight, accept);
        let narrowed = fitted.tiles.iter().any(|t| t.halo < halo);
        if fitted_max <= accept && !narrowed {
            return Ok(fitted);
        }
        // Plan B: smaller tiles with the whole halo, as far as shrinking helps, then narrowed.
        let (mut shrunk, accept_shrunk, stalled) =
            shrink(&plan_at, &pts, weight, target, max_load)?;
        let (shrunk_max, shrunk_total) = shrunk.fit_halos(&pts, weight, accept_shrunk);
        // A keeps the tiles and pays in halo growth for the owned points near narrowed faces; B
        // pays in halo copies (every copy is loaded, listed and spilled). B is taken unless its
        // copies make the loads more than `SHRINK_COST` times A's, or A is the one that fits. A
        // B whose shrinking stalled above the bound narrows like A, with more copies: it is
        // taken only where A does not fit.
        let take_shrunk = fitted_max > accept
            || (!stalled
                && shrunk_max <= accept_shrunk
                && shrunk_total <= SHRINK_COST * fitted_total);
        Ok(if take_shrunk { shrunk } else { fitted })
    }
}

/// Plan B of [`Planner::finish_within`]: shrinks the tile target (down to [`MIN_TARGET`])
/// until the sample predicts every first load with the whole halo within the bound, and returns
/// that plan and the bound it met.
///
/// Shrinking stops at what no tile size removes: before the first shrink the smallest tiles'
/// load `f` is estimated (a dense cluster inside a halo sized by the cloud's typical spacing
/// loads whole, whatever the tile; a 30 M cluttered scene went to 30 339 tiles and 18 GB of
/// spill, docs/BENCHMARKS.md):
/// - `f` over the budget: shrinking cannot help; the first plan is kept.
/// - `f` within the budget but above the margin: the first tiles whose load is within 5 % of `f`
///   (and of the budget) are kept.
/// - A round whose largest load is not at least [`SHRINK_GAIN`] below the round before's ends
///   it: the round before's plan is returned, marked as stalled (the third value), and
///   [`Planner::finish_within`] takes it only where plan A does not fit. Cuts placed where the
///   cloud is thin ([`thinnest_cut`]) bring the largest load down towards `f` only slowly, one
///   cluster-avoiding cut at a time; a 3 M cluttered scene at 150 MiB went through 18 rounds
///   to 2447 tiles (a third of its plan phase) for a plan B that was not taken.
///
/// Each round checks the cancel flag (issue 15: a small budget can take dozens of rounds over
/// the whole sample, seconds after the read has ended).
fn shrink(
    plan_at: &impl Fn(u64) -> Plan,
    pts: &[DVec3],
    weight: f64,
    mut target: u64,
    max_load: u64,
) -> Result<(Plan, f64, bool), TilingError> {
    let mut accept = 0.9 * max_load as f64;
    let mut floor_probed = false;
    // The round before's plan and its largest load.
    let mut before: Option<(Plan, f64)> = None;
    // Each round shrinks the target by at least 10 %: the loop ends.
    loop {
        if crate::neighbours::cancel_requested() {
            return Err(TilingError::Cancelled);
        }
        let plan = plan_at(target);
        let load = plan.largest_load(pts, weight);
        if load <= accept || target <= MIN_TARGET {
            return Ok((plan, accept, false));
        }
        if let Some((last, was)) = before.take()
            && load > (1.0 - SHRINK_GAIN) * was
        {
            // Fewer tiles for (about) the same load.
            return Ok((last, accept, true));
        }
        if !floor_probed {
            floor_probed = true;
            let f = plan_at(MIN_TARGET).largest_load(pts, weight);
            if f > max_load as f64 {
                return Ok((plan, accept, false));
            }
            accept = accept.max((1.05 * f).min(max_load as f64));
            if load <= accept {
                return Ok((plan, accept, false));
            }
        }
        let shrunk = (target as f64 * (0.9 * max_load as f64 / load) * 0.95) as u64;
        target = shrunk.min(target * 9 / 10).max(MIN_TARGET);
        before = Some((plan, load));
    }
}

/// How many times plan A's summed first loads plan B's may reach and still be taken
/// ([`Planner::finish_within`]), both as the sample predicts them. Measured (docs/BENCHMARKS.md,
/// issue 16, 2026-12-04): at a predicted 1.6 × (`lone-star.copc.laz` at 128 MiB) B ran 1.26 ×
/// faster; at 1.9 × (a 200 k cluttered scene at 64 MiB) both ran alike; at 3–5 × (the same scene
/// at 48 MiB, `lone-star` at 64 MiB, a 30 M cluttered scene at 1 GiB) A ran 1.3–2.8 × faster.
const SHRINK_COST: f64 = 1.75;

/// The least share by which a round of [`shrink`] must lower the largest load for the next
/// round to be tried.
const SHRINK_GAIN: f64 = 0.05;

/// The smallest tile target [`Planner::finish_within`] shrinks to.
pub const MIN_TARGET: u64 = 1000;

/// The narrowest halo [`Plan::fit_halos`] gives a tile, as a share of the plan's: six halvings.
const MIN_HALO_SHARE: f64 = 1.0 / 64.0;

/// Bisection steps of [`Plan::fit_halos`] (the halo to 2⁻¹⁶ of the plan's).
const FIT_STEPS: usize = 16;

impl Plan {
    /// The most points one tile's first load (owned plus halo copies) holds, estimated from the
    /// sample (`weight` points per sample point).
    fn largest_load(&self, sample: &[DVec3], weight: f64) -> f64 {
        self.loads(sample).into_iter().max().unwrap_or(0) as f64 * weight
    }

    /// Sample points in each tile's first load.
    fn loads(&self, sample: &[DVec3]) -> Vec<u64> {
        let mut counts = vec![0u64; self.tiles.len()];
        let mut near = Vec::new();
        for &p in sample {
            near.clear();
            self.near_tiles(p, &mut near);
            for &t in &near {
                counts[t] += 1;
            }
        }
        counts
    }

    /// Narrows the halos of every tile whose first load the sample predicts over `accept` points
    /// to the widest that fit ([`Plan::fit_faces`], not below [`MIN_HALO_SHARE`] of the plan's),
    /// and returns the largest and the summed first loads left. A tile next to a dense cluster, or a dense tile
    /// in a cloud whose typical spacing is wide, then loads what the budget allows instead of
    /// making every tile smaller (issue 16: a 30 M-point cluttered scene went to 747 tiles and
    /// 588 halo growths that way).
    /// The owned points whose lists the narrower halo does not hold are redone by
    /// [`crate::tiling::growth`] within the same budget; the halo decides only what is loaded,
    /// never a value.
    fn fit_halos(&mut self, sample: &[DVec3], weight: f64, accept: f64) -> (f64, f64) {
        let mut counts = self.loads(sample);
        let bound = if weight > 0.0 {
            accept / weight
        } else {
            f64::INFINITY
        };
        let over: Vec<usize> = (0..counts.len())
            .filter(|&t| counts[t] as f64 > bound)
            .collect();
        let mut slot = vec![usize::MAX; self.tiles.len()];
        for (i, &t) in over.iter().enumerate() {
            slot[t] = i;
        }
        let mut held: Vec<Vec<DVec3>> = vec![Vec::new(); over.len()];
        let mut near = Vec::new();
        for &p in sample {
            near.clear();
            self.near(p, self.halo, &mut near);
            for &t in &near {
                if slot[t] != usize::MAX {
                    held[slot[t]].push(p);
                }
            }
        }
        for (&t, held) in over.iter().zip(&held) {
            let (faces, load) = self.fit_faces(t, held, bound);
            let narrowest = faces.iter().copied().fold(f64::INFINITY, f64::min);
            self.tiles[t].halo = narrowest;
            self.tiles[t].faces = faces.iter().any(|&h| h != narrowest).then_some(faces);
            counts[t] = load;
        }
        let largest = counts.iter().max().copied().unwrap_or(0);
        let total: u64 = counts.iter().sum();
        (largest as f64 * weight, total as f64 * weight)
    }

    /// Face halos of tile `t` under which its first load holds at most `bound` of `held` (the
    /// sample points within the plan's halo of it), and that load. The faces are narrowed heaviest first (by the sample points in their slab at the plan's
    /// halo, ties by face): the heaviest alone to the widest common halo that fits, else the two
    /// heaviest, and so on; a face whose slab holds nothing is never narrowed unless nothing else
    /// fits, and then every face takes the narrowest halo ([`MIN_HALO_SHARE`]). A tile beside a
    /// dense cluster keeps its whole halo on the faces away from it, so only the owned points near
    /// the cluster's face are left to halo growth.
    fn fit_faces(&self, t: usize, held: &[DVec3], bound: f64) -> ([f64; 6], u64) {
        let core = self.tiles[t].core;
        let count =
            |faces: &[f64; 6]| held.iter().filter(|&&p| within(&core, faces, p)).count() as u64;
        let mut slabs = [0u64; 6];
        for &p in held {
            for a in 0..3 {
                slabs[2 * a] += u64::from(p[a] < core.min[a]);
                slabs[2 * a + 1] += u64::from(p[a] > core.max[a]);
            }
        }
        let mut order: Vec<usize> = (0..6).filter(|&f| slabs[f] > 0).collect();
        order.sort_by_key(|&f| (std::cmp::Reverse(slabs[f]), f));
        let narrowest = self.halo * MIN_HALO_SHARE;
        for j in 1..=order.len() {
            let at = |h: f64| {
                let mut faces = [self.halo; 6];
                for &f in &order[..j] {
                    faces[f] = h;
                }
                faces
            };
            let mut lo = narrowest;
            let mut load = count(&at(lo));
            if load as f64 > bound {
                continue;
            }
            let mut hi = self.halo;
            for _ in 0..FIT_STEPS {
                let mid = 0.5 * (lo + hi);
                let got = count(&at(mid));
                if got as f64 <= bound {
                    (lo, load) = (mid, got);
                } else {
                    hi = mid;
                }
            }
            return (at(lo), load);
        }
        let faces = [narrowest; 6];
        (faces, count(&faces))
    }
}

/// Recursive median split of the sample points `idx` inside `bx`; returns the node index.
#[allow(clippy::too_many_arguments)]
fn split(
    pts: &[DVec3],
    idx: &mut [usize],
    bx: Aabb,
    weight: f64,
    target: f64,
    halo: f64,
    nodes: &mut Vec<Node>,
    tiles: &mut Vec<Tile>,
) -> usize {
    let at = nodes.len();
    let estimate = idx.len() as f64 * weight;
    let size = bx.size();
    let axis = if size.x >= size.y && size.x >= size.z {
        0
    } else if size.y >= size.z {
        1
    } else {
        2
    };
    // Stop at the target, and where splitting cannot separate the points: a box whose sample
    // points all coincide (a stack of duplicates) stays one tile, whatever its count.
    let first = idx.first().map(|&i| pts[i]);
    let coincident = idx.iter().all(|&i| Some(pts[i]) == first);
    // Estimates move in steps of one sample point (`weight` points), and a cut cannot separate
    // equal coordinates: up to 2 % (or one step) over the target counts as the target, or a full
    // tile would be split once more into a full one and a sliver.
    let slack = weight.max(0.02 * target).min(0.5 * target);
    if estimate <= target + slack || idx.len() < 2 || size[axis] <= 0.0 || coincident {
        nodes.push(Node::Leaf { tile: tiles.len() });
        tiles.push(Tile {
            id: tiles.len(),
            core: bx,
            estimate: estimate.round() as u64,
            halo: 0.0,
            faces: None,
        });
        return at;
    }
    // Split where the left side holds a whole number of full target-sized tiles and the right
    // side the rest: every tile but the last one holds the target, whatever the cloud's size, so
    // the memory a tile needs (the peak RSS) does not depend on the size of the cloud.
    let count = ((estimate - slack) / target).ceil().max(2.0);
    let left = (count / 2.0).floor();
    let mid = ((left * target / weight).round() as usize).clamp(1, idx.len() - 1);
    let axis = thinnest_cut(pts, idx, mid, axis, &size, halo);
    let value = cut_at(pts, idx, mid, axis, &bx);
    // The points below the cut first.
    let mut cut = 0;
    for j in 0..idx.len() {
        if pts[idx[j]][axis] < value {
            idx.swap(cut, j);
            cut += 1;
        }
    }
    nodes.push(Node::Leaf { tile: usize::MAX });
    let (lo, hi) = idx.split_at_mut(cut);
    let mut lbox = bx;
    lbox.max[axis] = value;
    let mut rbox = bx;
    rbox.min[axis] = value;
    let left = split(pts, lo, lbox, weight, target, halo, nodes, tiles);
    let right = split(pts, hi, rbox, weight, target, halo, nodes, tiles);
    nodes[at] = Node::Split {
        axis,
        value,
        left,
        right,
    };
    at
}

/// Axes shorter than this share of a box's longest are not cut ([`split`]): the tiles stay
/// within a bounded aspect ratio, so their halos stay a bounded share of their load.
const SPLIT_ASPECT: f64 = 0.5;

/// Sample points (evenly strided through the node's) on which [`thinnest_cut`] weighs the axes.
const SPLIT_PROBES: usize = 4096;

/// The axis [`split`] cuts: of the axes at least [`SPLIT_ASPECT`] as long as the longest
/// (`longest`), the one whose cut at the `mid`-th of the points `idx` has the fewest points
/// within `halo` of it, weighed on a strided subset of [`SPLIT_PROBES`] points. Those points are
/// the halo copies the cut makes, and a cut through a dense cluster overloads the halos of the
/// tiles on both sides (narrowed to the budget, their owned points near it redone by halo
/// growth: most of a cluttered scene's tiled cost). Ties go to the longest axis. The cut stays
/// at `mid`, so every tile but the last still holds the target. Only the speed depends on it.
fn thinnest_cut(
    pts: &[DVec3],
    idx: &[usize],
    mid: usize,
    longest: usize,
    size: &DVec3,
    halo: f64,
) -> usize {
    let step = idx.len().div_ceil(SPLIT_PROBES).max(1);
    let probes: Vec<DVec3> = idx.iter().step_by(step).map(|&i| pts[i]).collect();
    if probes.is_empty() {
        return longest;
    }
    let at = (mid * probes.len() / idx.len()).min(probes.len() - 1);
    let mut best = (longest, usize::MAX);
    let mut values: Vec<f64> = Vec::with_capacity(probes.len());
    for a in std::iter::once(longest).chain((0..3).filter(|&a| a != longest)) {
        if size[a] <= 0.0 || size[a] < SPLIT_ASPECT * size[longest] {
            continue;
        }
        values.clear();
        values.extend(probes.iter().map(|p| p[a]));
        let cut = *values.select_nth_unstable_by(at, f64::total_cmp).1;
        let slab = values.iter().filter(|&&v| (v - cut).abs() <= halo).count();
        if slab < best.1 {
            best = (a, slab);
        }
    }
    best.0
}

/// The value of the `mid`-th of the sample points `idx` along `axis` (ties by index: a total
/// order, so the same point a full sort puts there), found by selection (the order of `idx`
/// decides nothing in [`split`]); the middle of `bx` where that is on its boundary (many equal
/// coordinates).
fn cut_at(pts: &[DVec3], idx: &mut [usize], mid: usize, axis: usize, bx: &Aabb) -> f64 {
    idx.select_nth_unstable_by(mid, |&a, &b| {
        pts[a][axis].total_cmp(&pts[b][axis]).then(a.cmp(&b))
    });
    let value = pts[idx[mid]][axis];
    if value <= bx.min[axis] || value >= bx.max[axis] {
        0.5 * (bx.min[axis] + bx.max[axis])
    } else {
        value
    }
}

/// Initial halo: `(reach + 1)` typical k-NN radii `r_k`
/// ([`crate::denoise::isolation::typical_radius`]) times a safety factor of 1.5. Only the speed
/// depends on it: tiles whose halo proves too small are redone with a larger one.
fn halo_estimate(r_k: Option<f64>, reach: usize, bounds: &Aabb) -> f64 {
    let fallback = bounds.diagonal() * 1e-3;
    match r_k {
        Some(r_k) => {
            let h = (reach + 1) as f64 * r_k * 1.5;
            if h > 0.0 && h.is_finite() {
                h
            } else {
                fallback
            }
        }
        None => fallback,
    }
}

/// The halo with which every owned result of a tile is provably exact when lists reach at most
/// `isolation` and results depend on `hops` hops of them: a point farther than `(hops + 1) ·
/// isolation` inside the region's faces has an exact list, and so have its members, `hops` deep.
/// The small margin covers the rounding of [`crate::denoise::cloud`]'s inside test.
pub fn sufficient_halo(isolation: Option<f64>, hops: usize) -> Option<f64> {
    isolation.map(|r| (hops + 1) as f64 * r * (1.0 + 1e-6))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn planner(n: u64) -> Planner {
        let mut p = Planner::new(4096);
        for i in 0..n {
            let x = (crate::points::sample_key(i) % 1000) as f64;
            let y = (crate::points::sample_key(i + 7) % 1000) as f64;
            p.add(i, DVec3::new(x, y, (x * 0.01).sin()));
        }
        p.add(n, DVec3::NAN);
        p
    }

    #[test]
    fn every_point_has_exactly_one_owner_and_halos_cover() {
        let plan = planner(50_000).finish(5_000, 16, 2).unwrap();
        assert!(plan.tiles.len() >= 8, "{}", plan.tiles.len());
        assert_eq!((plan.points, plan.finite), (50_001, 50_000));
        for i in 0..2000u64 {
            let p = DVec3::new(
                (crate::points::sample_key(i * 3) % 1000) as f64,
                (crate::points::sample_key(i * 5) % 1000) as f64,
                0.3,
            );
            let t = plan.owner(p);
            let core = plan.tiles[t].core;
            assert!((0..3).all(|a| p[a] >= core.min[a] && p[a] <= core.max[a]));
            let owners = plan
                .tiles
                .iter()
                .filter(|tile| {
                    (0..3).all(|a| {
                        p[a] >= tile.core.min[a]
                            && (p[a] < tile.core.max[a] || tile.core.max[a] >= plan.bounds.max[a])
                    })
                })
                .count();
            assert_eq!(owners, 1, "{p}");
            let mut near = Vec::new();
            plan.near(p, 25.0, &mut near);
            for tile in &plan.tiles {
                assert_eq!(near.contains(&tile.id), within(&tile.core, &[25.0; 6], p));
            }
        }
    }

    #[test]
    fn every_tile_but_one_holds_the_target() {
        // The tile a run needs memory for is the target whatever the cloud's size: the count is
        // the least that fits, and only one tile holds the remainder.
        // (Coordinates without ties: a cut cannot separate equal coordinates, so clouds with
        // many of them get a sliver tile here and there.)
        for (n, target) in [(50_000u64, 7_000u64), (50_000, 5_000), (200_000, 9_000)] {
            let mut p = Planner::new(4096);
            for i in 0..n {
                let x = (crate::points::sample_key(i) % 1_000_000) as f64 * 1e-3;
                let y = (crate::points::sample_key(i + 7) % 1_000_000) as f64 * 1e-3;
                p.add(i, DVec3::new(x, y, (x * 0.01).sin()));
            }
            let plan = p.finish(target, 16, 2).unwrap();
            let sizes: Vec<u64> = plan.tiles.iter().map(|t| t.estimate).collect();
            assert_eq!(
                plan.tiles.len() as u64,
                n.div_ceil(target),
                "{n} / {target}: {sizes:?}"
            );
            let short = plan
                .tiles
                .iter()
                .filter(|t| (t.estimate as f64) < 0.97 * target as f64)
                .count();
            assert!(short <= 1, "{n} / {target}: {short} short tiles");
            let total: u64 = plan.tiles.iter().map(|t| t.estimate).sum();
            assert!(
                total.abs_diff(n) <= plan.tiles.len() as u64,
                "{total} vs {n}"
            );
        }
    }

    /// A plane of 20 000 points on a 1000-unit square and 5 000 points in a cluster far smaller
    /// than the halo: whatever the tile size, a tile near the cluster loads it whole. The
    /// planner's sample holds every point, so its load estimates are exact.
    fn plane_with_cluster() -> (Planner, Vec<DVec3>) {
        plane_with_cluster_of(1e-6)
    }

    /// As [`plane_with_cluster`], the cluster's points `step` apart along a diagonal.
    fn plane_with_cluster_of(step: f64) -> (Planner, Vec<DVec3>) {
        plane_and_cluster(0.01, |d| {
            DVec3::new(500.0 + d * step, 500.0 - d * step, d * step)
        })
    }

    /// 20 000 points on a plane 1000 long in x and `100 000 · y_unit` in y, then 5 000 cluster
    /// points `at(d)` for pseudo-random d in 0..1000, all seen by a planner whose sample holds
    /// every point.
    fn plane_and_cluster(y_unit: f64, at: impl Fn(f64) -> DVec3) -> (Planner, Vec<DVec3>) {
        let mut pts = Vec::new();
        for i in 0..20_000u64 {
            let x = (crate::points::sample_key(i) % 100_000) as f64 * 0.01;
            let y = (crate::points::sample_key(i + 7) % 100_000) as f64 * y_unit;
            pts.push(DVec3::new(x, y, 0.0));
        }
        for i in 20_000..25_000u64 {
            pts.push(at((crate::points::sample_key(i) % 1000) as f64));
        }
        let mut p = Planner::new(1 << 16);
        for (i, &v) in pts.iter().enumerate() {
            p.add(i as u64, v);
        }
        (p, pts)
    }

    #[test]
    fn issue16_shrinking_stops_where_the_halo_holds_the_load() {
        let (p, pts) = plane_with_cluster();
        let floor = p.finish(MIN_TARGET, 16, 2).unwrap();
        let f = floor.largest_load(&pts, 1.0);
        assert!(f > 5_000.0, "the cluster loads whole: {f}");
        // Over the budget even at the smallest tiles: the first plan is kept (the partition's
        // exact check refuses it), not dozens of 1000-point tiles.
        let refused = plane_with_cluster()
            .0
            .finish_within(20_000, (0.95 * f) as u64, 16, 2)
            .unwrap();
        assert!(refused.tiles.len() <= 2, "{} tiles", refused.tiles.len());
        // Within the budget only without the tenth of margin: the first tiles whose load is
        // within 5 % of the smallest tiles' are kept, fewer than the floor's.
        let kept = plane_with_cluster()
            .0
            .finish_within(20_000, (1.02 * f) as u64, 16, 2)
            .unwrap();
        assert!(kept.largest_load(&pts, 1.0) <= 1.02 * f);
        assert!(
            kept.tiles.len() < floor.tiles.len(),
            "{} tiles against the floor's {}",
            kept.tiles.len(),
            floor.tiles.len()
        );
        // Without the cluster the same budget is met by shrinking, as before.
        let mut plain = Planner::new(1 << 16);
        for i in 0..20_000u64 {
            let x = (crate::points::sample_key(i) % 100_000) as f64 * 0.01;
            let y = (crate::points::sample_key(i + 7) % 100_000) as f64 * 0.01;
            plain.add(i, DVec3::new(x, y, 0.0));
        }
        let plan = plain.finish_within(20_000, 3_000, 16, 2).unwrap();
        assert!(plan.tiles.len() >= 8, "{}", plan.tiles.len());
    }

    #[test]
    fn issue16_the_first_cut_misses_a_dense_cluster_the_median_of_the_longest_axis_hits() {
        // 20 000 points on a 1000 × 999 plane (x the longest axis) and a 5 000-point cluster at
        // x = 500, y = 200: the median in x runs through the cluster; the median in y (about
        // y = 375) is far from it.
        let (p, pts) = plane_and_cluster(0.00999, |d| {
            DVec3::new(500.0 + d * 1e-3, 200.0 - d * 1e-3, 0.0)
        });
        let plan = p.finish(12_500, 16, 2).unwrap();
        assert_eq!(plan.tiles.len(), 2);
        let Node::Split { axis, value, .. } = plan.nodes[0] else {
            panic!("one split");
        };
        assert_eq!(axis, 1, "cut at {value}");
        let near_cut = |q: &&DVec3| (q[axis] - value).abs() <= plan.halo;
        assert_eq!(pts[20_000..].iter().filter(near_cut).count(), 0);
        // The halo copies are the plane's strip (about 20 000 · 2 halo / 999), not the cluster
        // besides: a cut in x would load about 5 000 more.
        let strip = pts.iter().filter(near_cut).count() as u64;
        let loads = plan.loads(&pts);
        assert_eq!(loads.iter().sum::<u64>(), 25_000 + strip, "{loads:?}");
        assert!(strip < 5_000, "{strip}");
    }

    #[test]
    fn issue16_a_dense_cluster_narrows_the_halos_near_it_not_the_tiles() {
        // 20 000 plane points and a 5 000-point cluster far smaller than the halo (but wider
        // than the narrowest halo). At a budget the plane's tiles fit with their halo but the
        // tiles around the cluster do not, only the halos near the cluster narrow: the tiles
        // stay those of the unbounded plan.
        let step = 0.01;
        let (p, pts) = plane_with_cluster_of(step);
        let free = p.finish(4_000, 16, 2).unwrap();
        let f = free.largest_load(&pts, 1.0);
        assert!(f > 5_000.0, "the cluster loads whole: {f}");
        assert!(1000.0 * step < free.halo && 1000.0 * step > free.halo * MIN_HALO_SHARE);
        let max_load = 7_000;
        let plan = plane_with_cluster_of(step)
            .0
            .finish_within(4_000, max_load, 16, 2)
            .unwrap();
        assert_eq!(plan.tiles.len(), free.tiles.len());
        let loads = plan.loads(&pts);
        let full = free.loads(&pts);
        for (t, tile) in plan.tiles.iter().enumerate() {
            assert!(
                loads[t] as f64 <= 0.9 * max_load as f64,
                "tile {t}: {}",
                loads[t]
            );
            if full[t] as f64 <= 0.9 * max_load as f64 {
                assert_eq!(tile.halo, plan.halo, "tile {t} fitted: its halo stays");
            } else {
                assert!(tile.halo < plan.halo && tile.halo >= plan.halo * MIN_HALO_SHARE);
            }
        }
        assert!(plan.tiles.iter().any(|t| t.halo < plan.halo));
        // Only the faces towards the cluster narrow: each narrowed face has cluster points in
        // its slab at the plan's halo, and a narrowed tile keeps the whole halo on the others.
        let cluster = &pts[20_000..];
        for (t, tile) in plan.tiles.iter().enumerate() {
            let faces = plan.face_halos(t);
            for (f, &h) in faces.iter().enumerate() {
                if h >= plan.halo {
                    continue;
                }
                let (a, up) = (f / 2, f % 2 == 1);
                let beyond = cluster.iter().any(|q| {
                    within(&tile.core, &[plan.halo; 6], *q)
                        && if up {
                            q[a] > tile.core.max[a]
                        } else {
                            q[a] < tile.core.min[a]
                        }
                });
                assert!(
                    beyond,
                    "tile {t}: face {f} narrowed to {h}, no cluster beyond it"
                );
            }
            if tile.halo < plan.halo {
                assert!(tile.faces.is_some(), "tile {t}: every face narrowed");
            }
        }
        // `near_tiles` is what the partition copies by: the fitted loads to the point.
        let mut near = Vec::new();
        for (i, &q) in pts.iter().enumerate().step_by(97) {
            near.clear();
            plan.near_tiles(q, &mut near);
            for t in 0..plan.tiles.len() {
                let inside = plan.in_first_load(t, q);
                assert_eq!(near.contains(&t), inside, "point {i}, tile {t}");
            }
        }
    }

    #[test]
    fn issue15_planning_stops_when_cancelled() {
        let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
        let got = crate::neighbours::with_cancel(&flag, || planner(20_000).finish(1_000, 16, 2));
        assert!(matches!(got, Err(TilingError::Cancelled)), "{got:?}");
        flag.store(false, std::sync::atomic::Ordering::Relaxed);
        let got = crate::neighbours::with_cancel(&flag, || planner(20_000).finish(1_000, 16, 2));
        assert!(got.is_ok());
    }

    #[test]
    fn sample_does_not_depend_on_order() {
        let mut a = Planner::new(100);
        let mut b = Planner::new(100);
        for i in 0..10_000u64 {
            a.add(i, DVec3::splat(i as f64));
        }
        for i in (0..10_000u64).rev() {
            b.add(i, DVec3::splat(i as f64));
        }
        assert_eq!(
            a.finish(1000, 16, 2).unwrap(),
            b.finish(1000, 16, 2).unwrap()
        );
    }
}
