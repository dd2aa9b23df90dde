//! The occupancy grid: how many points each coarse cell of space holds, counted in the
//! partition pass, so a tile can prove that a ball reaching past its region holds no point it
//! has not loaded.
//!
//! A tile's result is exact when every k-NN ball it depends on is complete. Inside the region
//! that is a box test; a ball that crosses the region's faces is still complete when every cell
//! it touches holds exactly as many points overall as the tile has loaded from it:
//!
//! ```text
//!   ┌───────┬───────┬───────┐     region face
//!   │ 0     │ 0     │ 0     │     ┆
//!   ├───────┼───────┼───────┤     ┆      ball of an isolated point p crossing the face:
//!   │ 0     │ 3 = 3 │ 0     │←────┆───   complete, every touched cell's global count
//!   ├───────┼───────┼───────┤     ┆      equals what the tile loaded from it
//!   │ 0     │ 0     │ 0     │     ┆
//!   └───────┴───────┴───────┘
//! ```
//!
//! This is what keeps far outliers and sparse stragglers from growing halos: their balls sit in
//! empty space. Cells start at a quarter of the isolation radius and double while there are more than
//! the cap the memory budget sets (at most [`MAX_CELLS`]), so the grid stays small for any input; coarser cells only make the test more
//! conservative. Only the speed depends on the grid, never a result.

use glam::DVec3;
use rustc_hash::{FxHashMap, FxHashSet};

use crate::geometry::floor_i64;

/// Most cells a grid keeps whatever the budget; beyond its cap ([`Occupancy::new`]) the cells
/// double in size.
pub const MAX_CELLS: usize = 1 << 20;

/// Fewest cells a cap allows (coarsening ends: keys shifted far enough are 0 or −1, eight cells).
pub const MIN_CELLS: usize = 4096;

/// Heap bytes a cell costs at the worst: a hash-map entry (a key of three `i64` and an `u64`
/// count, 32 bytes, and a control byte) in a table at most 7/8 full that doubles, so up to
/// 2 × 8/7 buckets a cell. The memory budget reserves this for each cell of the cap.
pub const BYTES_PER_CELL: u64 = 76;

/// Most cells one ball test visits; a larger ball is reported as not proven complete.
const MAX_VISITS: i64 = 1331;

/// Point counts per cell of a regular grid. A cell is `2^level` base cells along each axis, and a
/// point's key is its base-cell key shifted right by `level`, so coarsening merges counts exactly
/// and a point is always counted in the cell [`Occupancy::loaded`] puts it in.
#[derive(Debug, Clone, PartialEq)]
pub struct Occupancy {
    /// Base cell edge length.
    base: f64,
    /// Times the cells doubled.
    level: u32,
    /// Corner of cell (0, 0, 0).
    origin: DVec3,
    /// Points per non-empty cell.
    counts: FxHashMap<[i64; 3], u64>,
    /// Most cells kept: counting past it doubles the cells.
    most: usize,
}

/// Counts of the points one tile loaded, per cell of an [`Occupancy`] grid.
#[derive(Debug, Clone, Default)]
pub struct Loaded(FxHashMap<[i64; 3], u64>);

impl Occupancy {
    /// An empty grid of cells of `cell` (positive and finite) with a corner at `origin`, keeping
    /// at most `most` cells (within [`MIN_CELLS`] and [`MAX_CELLS`]): past it the cells double.
    pub fn new(cell: f64, origin: DVec3, most: usize) -> Occupancy {
        Occupancy {
            base: cell,
            level: 0,
            origin,
            counts: FxHashMap::default(),
            most: most.clamp(MIN_CELLS, MAX_CELLS),
        }
    }

    /// This grid keeping at most `most` cells from now on (coarsened until it does).
    pub fn capped(mut self, most: usize) -> Occupancy {
        self.most = most.clamp(MIN_CELLS, MAX_CELLS);
        while self.counts.len() > self.most {
            self.coarsen();
        }
        self
    }

    /// The cell edge length.
    pub fn cell(&self) -> f64 {
        self.base * f64::from(1u32 << self.level.min(31))
    }

    /// The cell of `p` (monotone in each coordinate).
    fn key(&self, p: DVec3) -> [i64; 3] {
        // Saturating float-to-int casts: positions are within ±1e12 and cells positive.
        let c = (p - self.origin) / self.base;
        [floor_i64(c.x), floor_i64(c.y), floor_i64(c.z)].map(|v| v >> self.level.min(63))
    }

    /// The key of `p` in the grid of cells `2^shift` times finer along each axis, with the same
    /// corner: its cell's key is this key shifted right by `shift` (exactly: the finer keys
    /// either shift the base keys less, or scale by a power of two, which rounds nothing).
    pub fn fine_key(&self, p: DVec3, shift: u32) -> [i64; 3] {
        let y = (p - self.origin) / self.base;
        if self.level >= shift {
            [floor_i64(y.x), floor_i64(y.y), floor_i64(y.z)]
                .map(|v| v >> (self.level - shift).min(63))
        } else {
            let c = y * f64::from(1u32 << (shift - self.level).min(31));
            [floor_i64(c.x), floor_i64(c.y), floor_i64(c.z)]
        }
    }

    /// The box of the fine cell `key` of [`Occupancy::fine_key`] (closed, padded as
    /// [`Occupancy::cell_box`]).
    pub fn fine_box(&self, key: [i64; 3], shift: u32) -> crate::points::Aabb {
        let cell = self.cell() / f64::from(1u32 << shift.min(31));
        let min = self.origin + DVec3::new(key[0] as f64, key[1] as f64, key[2] as f64) * cell;
        let pad = DVec3::splat(cell * 1e-9 + (min.abs().max_element() + cell) * 1e-15);
        crate::points::Aabb {
            min: min - pad,
            max: min + DVec3::splat(cell) + pad,
        }
    }

    /// The key of the cell holding `p`.
    pub fn cell_of(&self, p: DVec3) -> [i64; 3] {
        self.key(p)
    }

    /// The box of the cell `key` (closed; a point on a face may belong to the next cell).
    pub fn cell_box(&self, key: [i64; 3]) -> crate::points::Aabb {
        let cell = self.cell();
        let min = self.origin + DVec3::new(key[0] as f64, key[1] as f64, key[2] as f64) * cell;
        // A margin keeps the box a superset of the points keyed to the cell under rounding.
        let pad = DVec3::splat(cell * 1e-9 + (min.abs().max_element() + cell) * 1e-15);
        crate::points::Aabb {
            min: min - pad,
            max: min + DVec3::splat(cell) + pad,
        }
    }

    /// Points counted in cell `key`.
    pub fn count(&self, key: [i64; 3]) -> u64 {
        self.counts.get(&key).copied().unwrap_or(0)
    }

    /// The keys of the cells the bounding box of the ball (`p`, √`r2`) touches, as
    /// [`Occupancy::complete`] visits them; `None` for a ball it would not prove.
    pub fn ball_cells(&self, p: DVec3, r2: f64) -> Option<Vec<[i64; 3]>> {
        let r = r2.max(0.0).sqrt() * (1.0 + 1e-9) + (p.abs().max_element() + 1.0) * 1e-15;
        if !r.is_finite() {
            return None;
        }
        let lo = self.key(p - DVec3::splat(r));
        let hi = self.key(p + DVec3::splat(r));
        let span = |a: usize| hi[a].saturating_sub(lo[a]).saturating_add(1);
        if span(0).saturating_mul(span(1)).saturating_mul(span(2)) > MAX_VISITS {
            return None;
        }
        let mut out = Vec::new();
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    out.push([x, y, z]);
                }
            }
        }
        Some(out)
    }

    /// The non-empty cells nearest `p` (by the distance from `p` to the cell, then by key), as
    /// few as hold at least `want` points together (every non-empty cell when the grid holds
    /// fewer). One pass over the map keeping the `want` nearest cells (every cell holds a
    /// point, so no more are needed): for a point whose surroundings are empty, where widening
    /// by neighbouring cells would never reach anything.
    pub fn nearest_cells(&self, p: DVec3, want: u64) -> Vec<[i64; 3]> {
        let keep = usize::try_from(want).unwrap_or(usize::MAX);
        // A max-heap of the nearest cells so far; distances are non-negative, so their bits
        // order as they do.
        let mut near: std::collections::BinaryHeap<(u64, [i64; 3], u64)> =
            std::collections::BinaryHeap::new();
        for (&k, &n) in &self.counts {
            let b = self.cell_box(k);
            let d = (b.min - p).max(p - b.max).max(DVec3::ZERO).length_squared();
            near.push((d.to_bits(), k, n));
            if near.len() > keep {
                near.pop();
            }
        }
        let mut sum = 0u64;
        let mut out = Vec::new();
        for (_, k, n) in near.into_sorted_vec() {
            if sum >= want {
                break;
            }
            sum += n;
            out.push(k);
        }
        out
    }

    /// Counts `p` (a processed position).
    pub fn add(&mut self, p: DVec3) {
        *self.counts.entry(self.key(p)).or_insert(0) += 1;
        while self.counts.len() > self.most {
            self.coarsen();
        }
    }

    /// Adds the counts of `other` (a grid of the same base cells and corner, counted over other
    /// points, with the same cap): the grid one pass over both sets of points would have
    /// counted, because a pass ends at the finest level at which its points fit the cap, and a
    /// subset never needs a coarser level than the whole.
    pub fn merge(&mut self, other: &Occupancy) {
        debug_assert!(self.base == other.base && self.origin == other.origin);
        while self.level < other.level {
            self.coarsen();
        }
        let shift = self.level - other.level;
        for (k, &n) in &other.counts {
            *self.counts.entry(k.map(|c| c >> shift)).or_insert(0) += n;
        }
        while self.counts.len() > self.most {
            self.coarsen();
        }
    }

    /// Doubles the cell size, merging counts exactly (a cell's parent is its key shifted right
    /// by one, as [`Occupancy::key`] computes it).
    pub(crate) fn coarsen(&mut self) {
        self.level += 1;
        let old = std::mem::take(&mut self.counts);
        for (k, n) in old {
            *self.counts.entry(k.map(|c| c >> 1)).or_insert(0) += n;
        }
    }

    /// Non-empty cells.
    pub fn len(&self) -> usize {
        self.counts.len()
    }

    /// True when no point was counted.
    pub fn is_empty(&self) -> bool {
        self.counts.is_empty()
    }

    /// The per-cell counts of `points` (what a tile loaded).
    pub fn loaded(&self, points: impl Iterator<Item = DVec3>) -> Loaded {
        let mut m = FxHashMap::default();
        for p in points {
            *m.entry(self.key(p)).or_insert(0u64) += 1;
        }
        Loaded(m)
    }

    /// An upper bound on the points inside `region`: the counts of every cell it touches.
    pub fn points_in(&self, region: &crate::points::Aabb) -> u64 {
        let cell = self.cell();
        // A cell touches the region unless it lies wholly beyond one of its faces; the margin
        // keeps the bound an upper one under rounding.
        let lo = (region.min - self.origin) / cell - DVec3::splat(1e-9);
        let hi = (region.max - self.origin) / cell + DVec3::splat(1e-9);
        let touches =
            |k: &[i64; 3]| (0..3).all(|a| (k[a] as f64) + 1.0 >= lo[a] && (k[a] as f64) <= hi[a]);
        // A small region visits its cells; a large one (or one with infinite faces) the map.
        let first = (lo - DVec3::ONE).ceil();
        let last = hi.floor();
        let span = (last - first + DVec3::ONE).max(DVec3::ZERO);
        let visits = span.x * span.y * span.z;
        if visits.is_finite() && visits <= self.counts.len() as f64 {
            let mut sum = 0;
            for x in first.x as i64..=last.x as i64 {
                for y in first.y as i64..=last.y as i64 {
                    for z in first.z as i64..=last.z as i64 {
                        let k = [x, y, z];
                        if touches(&k) {
                            sum += self.counts.get(&k).copied().unwrap_or(0);
                        }
                    }
                }
            }
            return sum;
        }
        self.counts
            .iter()
            .filter(|(k, _)| touches(k))
            .map(|(_, n)| n)
            .sum()
    }

    /// A lower bound on the points of the cloud in the union of the cubes of half-side `half`
    /// around `centres`: the counts of distinct cells lying wholly inside one of the cubes
    /// (with a margin for rounding). Visits at most `visits` cells and stops once the bound
    /// passes `stop`; any subset of those cells still bounds from below. What lets a growth group
    /// that cannot fit its run be split without reading the spill files first.
    pub fn points_within_cubes(
        &self,
        centres: impl Iterator<Item = DVec3>,
        half: f64,
        visits: usize,
        stop: u64,
    ) -> u64 {
        // `cell()` stops doubling at level 31 while keys shift on: no bound past it.
        if self.level > 31 {
            return 0;
        }
        let cell = self.cell();
        let mut seen = FxHashSet::default();
        let (mut sum, mut left) = (0u64, visits);
        for c in centres {
            // Cells k with k ≥ lo and k + 1 ≤ hi lie inside the cube; the margins keep them
            // inside under the rounding of keys and of these quotients.
            let lo = (c - DVec3::splat(half) - self.origin) / cell + DVec3::splat(1e-6);
            let hi = (c + DVec3::splat(half) - self.origin) / cell - DVec3::splat(1e-6);
            if !(lo.is_finite() && hi.is_finite()) {
                continue;
            }
            let first = lo.ceil();
            let last = hi.floor() - DVec3::ONE;
            if (0..3).any(|a| first[a] > last[a]) {
                continue;
            }
            let span = last - first + DVec3::ONE;
            if span.x * span.y * span.z > left as f64 {
                return sum;
            }
            left -= (span.x * span.y * span.z) as usize;
            for x in first.x as i64..=last.x as i64 {
                for y in first.y as i64..=last.y as i64 {
                    for z in first.z as i64..=last.z as i64 {
                        let k = [x, y, z];
                        if let Some(&n) = self.counts.get(&k)
                            && seen.insert(k)
                        {
                            sum += n;
                            if sum > stop {
                                return sum;
                            }
                        }
                    }
                }
            }
        }
        sum
    }

    /// True when every point within √`r2` of `p` is among the loaded ones: every cell the ball's
    /// bounding box touches holds no more points overall than were loaded from it.
    pub fn complete(&self, loaded: &Loaded, p: DVec3, r2: f64) -> bool {
        // Margins cover the rounding of the squared radius and of `p ± r`.
        let r = r2.max(0.0).sqrt() * (1.0 + 1e-9) + (p.abs().max_element() + 1.0) * 1e-15;
        if !r.is_finite() {
            return false;
        }
        let lo = self.key(p - DVec3::splat(r));
        let hi = self.key(p + DVec3::splat(r));
        let span = |a: usize| hi[a].saturating_sub(lo[a]).saturating_add(1);
        if span(0).saturating_mul(span(1)).saturating_mul(span(2)) > MAX_VISITS {
            return false;
        }
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    let k = [x, y, z];
                    let all = self.counts.get(&k).copied().unwrap_or(0);
                    if all > loaded.0.get(&k).copied().unwrap_or(0) {
                        return false;
                    }
                }
            }
        }
        true
    }
}

/// Serialises the cells as a sorted list (JSON keys must be strings, and sorted output is
/// reproducible).
/// The first bytes of a grid file ([`Occupancy::to_bytes`]), with the format's version.
const MAGIC: &[u8; 8] = b"QEMDOCC1";
/// Bytes before the cells: magic, base, level, origin, cell count, key and count widths.
const HEAD: usize = 8 + 8 + 4 + 24 + 8 + 2;

impl Occupancy {
    /// The grid as bytes: [`MAGIC`], the base cell edge, the level, the origin, the cell count,
    /// the widths of a key coordinate and of a count (4 bytes when every value fits, else 8),
    /// then each cell's key (3 coordinates) and count in key order, little-endian: 16 bytes a
    /// cell at most sizes. A binary grid: JSON grids took most of the partition's last task,
    /// which merges one per part (docs/BENCHMARKS.md, issue 11).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut cells: Vec<([i64; 3], u64)> = self.counts.iter().map(|(k, n)| (*k, *n)).collect();
        cells.sort_unstable();
        let narrow_keys = cells
            .iter()
            .all(|(k, _)| k.iter().all(|&v| i32::try_from(v).is_ok()));
        let narrow_counts = cells.iter().all(|&(_, n)| u32::try_from(n).is_ok());
        let (kw, cw) = (
            if narrow_keys { 4 } else { 8 },
            if narrow_counts { 4 } else { 8 },
        );
        let mut b = Vec::with_capacity(HEAD + (3 * kw + cw) * cells.len());
        b.extend_from_slice(MAGIC);
        b.extend_from_slice(&self.base.to_le_bytes());
        b.extend_from_slice(&self.level.to_le_bytes());
        for v in self.origin.to_array() {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&(cells.len() as u64).to_le_bytes());
        b.extend_from_slice(&[kw as u8, cw as u8]);
        for (k, n) in cells {
            for v in k {
                b.extend_from_slice(&v.to_le_bytes()[..kw]);
            }
            b.extend_from_slice(&n.to_le_bytes()[..cw]);
        }
        b
    }

    /// The grid of [`Occupancy::to_bytes`]; `None` for bytes of another format, truncated or
    /// with a base cell that is not positive and finite.
    pub fn from_bytes(b: &[u8]) -> Option<Occupancy> {
        let f64_at = |at: usize| Some(f64::from_le_bytes(b.get(at..at + 8)?.try_into().ok()?));
        if b.get(..8)? != MAGIC {
            return None;
        }
        let base = f64_at(8)?;
        let level = u32::from_le_bytes(b.get(16..20)?.try_into().ok()?);
        let origin = DVec3::new(f64_at(20)?, f64_at(28)?, f64_at(36)?);
        let n = usize::try_from(u64::from_le_bytes(b.get(44..52)?.try_into().ok()?)).ok()?;
        let (kw, cw) = (usize::from(*b.get(52)?), usize::from(*b.get(53)?));
        let cell = 3 * kw + cw;
        let whole = b.len() == HEAD.checked_add(n.checked_mul(cell)?)?;
        let widths = [4, 8].contains(&kw) && [4, 8].contains(&cw);
        if !(base.is_finite() && base > 0.0 && widths && whole) {
            return None;
        }
        // Fixed-size reads (the chunks are `cell` bytes, so every slice is whole).
        let key = |c: &[u8], i: usize| -> i64 {
            if kw == 4 {
                i64::from(i32::from_le_bytes(
                    c[4 * i..4 * i + 4].try_into().unwrap_or_default(),
                ))
            } else {
                i64::from_le_bytes(c[8 * i..8 * i + 8].try_into().unwrap_or_default())
            }
        };
        let count = |c: &[u8]| -> u64 {
            let at = 3 * kw;
            if cw == 4 {
                u64::from(u32::from_le_bytes(
                    c[at..at + 4].try_into().unwrap_or_default(),
                ))
            } else {
                u64::from_le_bytes(c[at..at + 8].try_into().unwrap_or_default())
            }
        };
        let mut counts = FxHashMap::default();
        counts.reserve(n);
        for c in b[HEAD..].chunks_exact(cell) {
            counts.insert([key(c, 0), key(c, 1), key(c, 2)], count(c));
        }
        Some(Occupancy {
            base,
            level,
            origin,
            counts,
            most: MAX_CELLS,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue11_a_grid_round_trips_through_its_bytes_and_other_bytes_are_refused() {
        let mut g = Occupancy::new(0.5, DVec3::new(-3.0, 2.0, 1e6), MAX_CELLS);
        for i in 0..200 {
            g.add(DVec3::new(
                f64::from(i) * 0.37 - 3.0,
                2.0 + f64::from(i % 7),
                1e6 - f64::from(i),
            ));
        }
        g.merge(&g.clone());
        let b = g.to_bytes();
        assert_eq!(Occupancy::from_bytes(&b), Some(g.clone()));
        // The same grid gives the same bytes (cells in key order).
        assert_eq!(Occupancy::from_bytes(&b).unwrap().to_bytes(), b);
        assert_eq!(Occupancy::from_bytes(&b[..b.len() - 1]), None);
        assert_eq!(Occupancy::from_bytes(b"{\"base\": 1.0}"), None);
        let mut bad = b.clone();
        bad[8..16].copy_from_slice(&f64::NAN.to_le_bytes());
        assert_eq!(Occupancy::from_bytes(&bad), None);
        // Keys beyond 32 bits and counts beyond 32 bits take 8 bytes each.
        let mut wide = Occupancy::new(1e-3, DVec3::ZERO, MAX_CELLS);
        wide.add(DVec3::new(-3e9, 5.0, 1.0));
        wide.counts.insert([1, 2, 3], u64::from(u32::MAX) + 7);
        let w = wide.to_bytes();
        assert_eq!(w[52..54], [8, 8]);
        assert_eq!(Occupancy::from_bytes(&w), Some(wide));
        assert_eq!(b[52..54], [4, 4]);
    }

    #[test]
    fn a_ball_in_empty_space_is_complete_and_one_over_unloaded_points_is_not() {
        let mut g = Occupancy::new(1.0, DVec3::ZERO, MAX_CELLS);
        let inside = [DVec3::new(0.5, 0.5, 0.5), DVec3::new(0.6, 0.5, 0.5)];
        let outside = DVec3::new(3.2, 0.5, 0.5);
        for p in inside.iter().chain([&outside]) {
            g.add(*p);
        }
        let loaded = g.loaded(inside.iter().copied());
        assert!(g.complete(&loaded, inside[0], 0.25));
        // A ball reaching the cell of the point not loaded.
        assert!(!g.complete(&loaded, inside[0], 9.0));
        // Everything loaded: complete whatever the radius (within the visit bound).
        let all = g.loaded(inside.iter().chain([&outside]).copied());
        assert!(g.complete(&all, inside[0], 9.0));
        assert!(!g.complete(&all, inside[0], 1e6));
        assert!(!g.complete(&all, inside[0], f64::INFINITY));
    }

    #[test]
    fn issue16_points_within_cubes_bounds_the_count_from_below() {
        // Points on a jittered lattice at three levels (coarse grids: the cells have levels).
        let pts: Vec<DVec3> = (0..4000u64)
            .map(|i| {
                let k = crate::points::sample_key(i);
                let j = |s: u64| ((k >> s) % 1000) as f64 / 1000.0;
                DVec3::new(j(0) * 7.0, j(10) * 5.0 - 2.0, j(20) * 3.0 + 1e5)
            })
            .collect();
        for (cell, level_up) in [(0.4, 0), (0.1, 3)] {
            let mut g = Occupancy::new(cell, DVec3::new(-1.0, -3.0, 1e5 - 2.0), MAX_CELLS);
            g.level = level_up;
            for p in &pts {
                g.add(*p);
            }
            for (centres, half) in [
                (vec![DVec3::new(3.0, 0.0, 1e5 + 1.5)], 1.0),
                (
                    vec![
                        DVec3::new(3.0, 0.0, 1e5 + 1.5),
                        DVec3::new(4.0, 1.0, 1e5 + 2.0),
                    ],
                    1.3,
                ),
                (vec![DVec3::new(1.0, -1.0, 1e5)], 0.1),
                (pts[..50].to_vec(), 0.6),
            ] {
                let exact = pts
                    .iter()
                    .filter(|p| {
                        centres
                            .iter()
                            .any(|c| (0..3).all(|a| (p[a] - c[a]).abs() <= half))
                    })
                    .count() as u64;
                let bound = g.points_within_cubes(centres.iter().copied(), half, 1 << 16, u64::MAX);
                assert!(bound <= exact, "{cell} {half}: {bound} > {exact}");
                if half >= 1.0 && level_up == 0 {
                    assert!(bound * 4 >= exact, "{cell} {half}: {bound} of {exact}");
                }
                // Stopping early or visiting fewer cells still bounds from below.
                assert!(
                    g.points_within_cubes(centres.iter().copied(), half, 10, u64::MAX) <= bound
                );
                let stopped = g.points_within_cubes(centres.iter().copied(), half, 1 << 16, 5);
                assert!(stopped <= bound && (stopped > 5 || stopped == bound));
            }
        }
    }

    #[test]
    fn points_in_bounds_the_count_from_above() {
        let mut g = Occupancy::new(1.0, DVec3::ZERO, MAX_CELLS);
        let pts: Vec<DVec3> = (0..1000)
            .map(|i| {
                DVec3::new(
                    (i % 10) as f64 + 0.5,
                    (i / 10 % 10) as f64 + 0.5,
                    (i / 100) as f64,
                )
            })
            .collect();
        for p in &pts {
            g.add(*p);
        }
        for (lo, hi) in [(0.0, 10.0), (2.2, 3.7), (-5.0, -1.0), (4.0, 4.0)] {
            let region = crate::points::Aabb {
                min: DVec3::splat(lo),
                max: DVec3::splat(hi),
            };
            let exact = pts
                .iter()
                .filter(|p| (0..3).all(|a| p[a] >= lo && p[a] <= hi))
                .count() as u64;
            let bound = g.points_in(&region);
            assert!(bound >= exact, "{lo}..{hi}: {bound} < {exact}");
            // At most one cell of slack on each side.
            let cells = ((hi - lo).max(0.0) + 3.0).powi(3) as u64;
            assert!(bound <= cells, "{lo}..{hi}: {bound}");
        }
        let all = crate::points::Aabb {
            min: DVec3::splat(f64::NEG_INFINITY),
            max: DVec3::splat(f64::INFINITY),
        };
        assert_eq!(g.points_in(&all), 1000);
    }

    #[test]
    fn issue16_points_in_visits_small_regions_to_the_same_count_as_the_map() {
        let mut g = Occupancy::new(0.5, DVec3::splat(-1.0), MAX_CELLS);
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut f = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..20_000 {
            g.add(DVec3::new(f() * 40.0, f() * 40.0, f() * 2.0));
        }
        for _ in 0..200 {
            let c = DVec3::new(f() * 44.0 - 2.0, f() * 44.0 - 2.0, f() * 3.0 - 0.5);
            let h = DVec3::new(f() * 3.0, f() * 3.0, f() * 3.0);
            let region = crate::points::Aabb {
                min: c - h,
                max: c + h,
            };
            let cell = g.cell();
            let lo = (region.min - g.origin) / cell - DVec3::splat(1e-9);
            let hi = (region.max - g.origin) / cell + DVec3::splat(1e-9);
            let by_map: u64 = g
                .counts
                .iter()
                .filter(|(k, _)| {
                    (0..3).all(|a| (k[a] as f64) + 1.0 >= lo[a] && (k[a] as f64) <= hi[a])
                })
                .map(|(_, n)| n)
                .sum();
            assert_eq!(g.points_in(&region), by_map, "{region:?}");
        }
    }

    #[test]
    fn issue16_nearest_cells_reach_the_wanted_count_across_empty_space() {
        let mut g = Occupancy::new(1.0, DVec3::ZERO, MAX_CELLS);
        let lone = DVec3::new(0.5, 0.5, 0.5);
        g.add(lone);
        // Nothing in the 26 cells around the lone point; a cluster 10 cells away, a farther one.
        for i in 0..5 {
            g.add(DVec3::new(10.5, 0.5 + 0.1 * i as f64, 0.5));
        }
        for i in 0..50 {
            g.add(DVec3::new(-20.5, 0.5, 0.5 + 0.01 * i as f64));
        }
        assert_eq!(g.nearest_cells(lone, 1), vec![[0, 0, 0]]);
        assert_eq!(g.nearest_cells(lone, 3), vec![[0, 0, 0], [10, 0, 0]]);
        assert_eq!(
            g.nearest_cells(lone, 7),
            vec![[0, 0, 0], [10, 0, 0], [-21, 0, 0]]
        );
        // More than the grid holds: every cell.
        assert_eq!(g.nearest_cells(lone, 1000).len(), 3);
        assert!(g.nearest_cells(lone, 0).is_empty());
    }

    #[test]
    fn coarsening_keeps_the_total_and_bounds_the_cells() {
        let mut g = Occupancy::new(1e-3, DVec3::ZERO, MAX_CELLS);
        let n = MAX_CELLS as u64 + 10;
        for i in 0..n {
            g.add(DVec3::new(i as f64 * 1e-3 + 5e-4, -0.25, 0.0));
        }
        assert!(g.len() <= MAX_CELLS);
        assert!(g.cell() > 1e-3);
        // Every point is found in the cell the merged counts put it in.
        let all = g.loaded((0..n).map(|i| DVec3::new(i as f64 * 1e-3 + 5e-4, -0.25, 0.0)));
        assert_eq!(all.0, g.counts);
        assert_eq!(g.counts.values().sum::<u64>(), n);
    }

    /// Issue 16: the memory budget caps the grid; parts counted under the cap merge to the grid
    /// one pass under it counts, and so does a finer grid capped afterwards.
    #[test]
    fn issue16_a_cap_bounds_the_cells_and_parts_merge_to_one_pass() {
        let p = |i: u64| DVec3::new((i % 97) as f64 * 0.1, (i / 97) as f64 * 0.1, 0.05);
        let n = 20_000u64;
        let mut one = Occupancy::new(0.1, DVec3::ZERO, MIN_CELLS);
        (0..n).for_each(|i| one.add(p(i)));
        assert!(one.len() <= MIN_CELLS && one.level > 0, "{}", one.len());
        let mut a = Occupancy::new(0.1, DVec3::ZERO, MIN_CELLS);
        let mut b = Occupancy::new(0.1, DVec3::ZERO, MIN_CELLS);
        (0..n / 3).for_each(|i| a.add(p(i)));
        (n / 3..n).for_each(|i| b.add(p(i)));
        a.merge(&b);
        assert_eq!(a, one);
        let mut fine = Occupancy::new(0.1, DVec3::ZERO, MAX_CELLS);
        (0..n).for_each(|i| fine.add(p(i)));
        assert_eq!(fine.level, 0);
        assert_eq!(fine.capped(MIN_CELLS), one);
        // A cap below the least is the least (coarsening always ends).
        assert_eq!(Occupancy::new(0.1, DVec3::ZERO, 1).most, MIN_CELLS);
    }
}
