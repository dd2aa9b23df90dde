//! The fine cells within a halo of a growth group's points: what a group loads, and the proof
//! that a k-NN ball holds nothing more than was loaded.
//!
//! A tile with a narrowed halo leaves the owned points near its narrowed faces pending, a shell
//! along those faces whose bounding box is the whole tile. Loading the box reloads the tile for
//! every round; loading the cells near the pending points loads the shell.
//!
//! ```text
//!   cell edge c = halo / DILATION
//!   loaded cells = every cell within DILATION cells (L∞) of a group point's cell
//!                ⊇ the cube of half-side `halo` around each group point
//!   a ball is complete when every cell its bounding box (clamped to the cloud's bounds) touches
//!   is loaded
//! ```
//!
//! Which cells are loaded decides only which results the kernel can prove exact, never a value,
//! so the bytes are those of the in-memory run whatever the cells (docs/DECISIONS.md, issue 16).

use glam::DVec3;
use rustc_hash::FxHashSet;

use crate::geometry::floor_i64;
use crate::points::Aabb;

/// Cells per halo: a group point's cell and `DILATION` cells on every side cover the cube of
/// half-side `halo` around it, and at most `halo × (1 + 1/DILATION)` past it.
const DILATION: i64 = 2;

/// Most cells a shell keeps (about 7 MB of keys): past it, the cells grow (one per halo, then
/// doubling), so the shell is coarser but still covers the halo.
const MAX_CELLS: usize = 1 << 18;

/// Points a kernel run may hold per cell a shell keeps: the cells are charged to the memory
/// budget at about 4 bytes per point, against the hundreds each point costs the kernel.
const POINTS_PER_CELL: u64 = 8;

/// Fewest cells a shell may keep whatever the budget (about 128 kB).
const MIN_CELLS: usize = 1 << 12;

/// Most cells a ball's bounding box may touch and still be proven.
const MAX_VISITS: i64 = 4096;

/// Most cells in the box of a shell's keys for its lookups to use a bitmap (2 MiB) instead of
/// the hash set: a growth load asks for the cell of every record it reads, and hashing was the
/// largest cost of a growth-heavy tile (`perf`: 11 % of the CPU of the 10 M cluttered scene at
/// 200 MiB; BENCHMARKS, issue 16).
const DENSE_BITS: u64 = 1 << 24;

/// Most cells a set of loaded cells may keep for kernel runs of at most `max_points` points:
/// one per `POINTS_PER_CELL` (8), between `MIN_CELLS` (2¹²) and `MAX_CELLS` (2¹⁸).
pub fn most_cells(max_points: Option<u64>) -> usize {
    max_points.map_or(MAX_CELLS, |m| {
        usize::try_from(m / POINTS_PER_CELL)
            .unwrap_or(MAX_CELLS)
            .clamp(MIN_CELLS, MAX_CELLS)
    })
}

/// Cells in the cube of `dilation` cells around one.
fn cube(dilation: i64) -> usize {
    let side = (2 * dilation + 1) as usize;
    side * side * side
}

/// The cells loaded for one group at one halo.
pub struct Shell {
    origin: DVec3,
    cell: f64,
    bounds: Aabb,
    cells: FxHashSet<[i64; 3]>,
    dense: Option<Dense>,
    span: Aabb,
}

/// The loaded cells as one bit per cell of the box their keys span.
struct Dense {
    lo: [i64; 3],
    dims: [u64; 3],
    bits: Vec<u64>,
}

impl Dense {
    /// The bitmap of `cells`, when their keys' box holds at most [`DENSE_BITS`] cells.
    fn of(cells: &FxHashSet<[i64; 3]>) -> Option<Dense> {
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        for c in cells {
            for a in 0..3 {
                lo[a] = lo[a].min(c[a]);
                hi[a] = hi[a].max(c[a]);
            }
        }
        let mut dims = [0u64; 3];
        let mut total = 1u64;
        for a in 0..3 {
            let d = u64::try_from(i128::from(hi[a]) - i128::from(lo[a]) + 1).ok()?;
            total = total.checked_mul(d).filter(|&t| t <= DENSE_BITS)?;
            dims[a] = d;
        }
        let mut dense = Dense {
            lo,
            dims,
            bits: vec![0; total.div_ceil(64) as usize],
        };
        for c in cells {
            let i = dense.bit(*c).expect("a cell lies in its own box");
            dense.bits[(i / 64) as usize] |= 1 << (i % 64);
        }
        Some(dense)
    }

    /// The bit of cell `c`, `None` outside the box.
    #[inline]
    fn bit(&self, c: [i64; 3]) -> Option<u64> {
        let mut i = 0u64;
        for ((&c, &lo), &dim) in c.iter().zip(&self.lo).zip(&self.dims) {
            let o = i128::from(c) - i128::from(lo);
            if !(0..i128::from(dim)).contains(&o) {
                return None;
            }
            i = i * dim + o as u64;
        }
        Some(i)
    }

    #[inline]
    fn contains(&self, c: [i64; 3]) -> bool {
        self.bit(c)
            .is_some_and(|i| self.bits[(i / 64) as usize] >> (i % 64) & 1 == 1)
    }
}

impl Shell {
    /// The cells within `halo` (L∞, rounded outward to whole cells) of the points in `group`,
    /// keyed from `origin`, for a cloud whose points all lie in the closed box `bounds`, for
    /// kernel runs of at most `max_points` points (which bounds the cells kept).
    pub fn around(
        origin: DVec3,
        bounds: Aabb,
        group: impl Iterator<Item = DVec3> + Clone,
        halo: f64,
        max_points: Option<u64>,
    ) -> Shell {
        let most = most_cells(max_points);
        let mut shell = Shell {
            origin,
            cell: halo / DILATION as f64,
            bounds,
            cells: FxHashSet::default(),
            dense: None,
            span: Aabb::empty(),
        };
        let mut seeds = shell.seeds(group.clone());
        let mut dilation = DILATION;
        while seeds.len().saturating_mul(cube(dilation)) > most && seeds.len() > 1 {
            if dilation > 1 {
                dilation = 1;
                shell.cell = halo;
            } else {
                shell.cell *= 2.0;
            }
            seeds = shell.seeds(group.clone());
        }
        for s in seeds {
            for x in -dilation..=dilation {
                for y in -dilation..=dilation {
                    for z in -dilation..=dilation {
                        shell.cells.insert([
                            s[0].saturating_add(x),
                            s[1].saturating_add(y),
                            s[2].saturating_add(z),
                        ]);
                    }
                }
            }
        }
        for &c in &shell.cells {
            shell.span.union(&shell.cell_box(c));
        }
        shell.dense = Dense::of(&shell.cells);
        shell
    }

    /// True when cell `key` is loaded.
    #[inline]
    fn has(&self, key: [i64; 3]) -> bool {
        match &self.dense {
            Some(d) => d.contains(key),
            None => self.cells.contains(&key),
        }
    }

    /// The distinct cells holding the points of `group`.
    fn seeds(&self, group: impl Iterator<Item = DVec3>) -> FxHashSet<[i64; 3]> {
        group.map(|p| self.key(p)).collect()
    }

    /// The cell of `p` (monotone in each coordinate; saturating casts: positions are finite and
    /// within ±1e12 of the origin, and the cell is positive).
    fn key(&self, p: DVec3) -> [i64; 3] {
        let c = (p - self.origin) / self.cell;
        [floor_i64(c.x), floor_i64(c.y), floor_i64(c.z)]
    }

    /// The closed box of cell `key`, padded so it holds every point keyed to the cell.
    fn cell_box(&self, key: [i64; 3]) -> Aabb {
        let min = self.origin + DVec3::new(key[0] as f64, key[1] as f64, key[2] as f64) * self.cell;
        let pad = DVec3::splat(self.cell * 1e-9 + (min.abs().max_element() + self.cell) * 1e-15);
        Aabb {
            min: min - pad,
            max: min + DVec3::splat(self.cell) + pad,
        }
    }

    /// A box holding every loaded cell (what decides which spill files are read).
    pub fn span(&self) -> Aabb {
        self.span
    }

    /// True when `p` lies in a loaded cell.
    pub fn contains(&self, p: DVec3) -> bool {
        // Most records a group reads lie outside the span: compare before hashing.
        let span = &self.span;
        (0..3).all(|a| p[a] >= span.min[a] && p[a] <= span.max[a]) && self.has(self.key(p))
    }

    /// False only when no point in the closed box `b` lies in a loaded cell: keys are monotone in
    /// each coordinate, so such a point's key lies between those of the box's corners. True as
    /// well for a box over more than [`MAX_VISITS`] cells. What picks the spill blocks a load
    /// reads: the span of a shell along a tile's faces is the whole tile.
    pub fn meets(&self, b: &Aabb) -> bool {
        let (mut lo, mut hi) = (self.key(b.min), self.key(b.max));
        if let Some(d) = &self.dense {
            // Outside the bitmap's box no cell is loaded.
            for a in 0..3 {
                let top = d.lo[a].saturating_add(i64::try_from(d.dims[a]).unwrap_or(i64::MAX) - 1);
                lo[a] = lo[a].max(d.lo[a]);
                hi[a] = hi[a].min(top);
            }
        }
        keys_between(lo, hi).is_none_or(|mut keys| keys.any(|k| self.has(k)))
    }

    /// True when a load keeps every point in the closed box `b`: the box lies in the span and
    /// every cell it touches is loaded (at most [`MAX_VISITS`] cells are looked at). False for an
    /// empty box.
    pub fn covers(&self, b: &Aabb) -> bool {
        if (0..3).any(|a| !(b.min[a] >= self.span.min[a] && b.max[a] <= self.span.max[a])) {
            return false;
        }
        let (lo, hi) = (self.key(b.min), self.key(b.max));
        if (0..3).any(|a| lo[a] > hi[a]) {
            return false;
        }
        keys_between(lo, hi).is_some_and(|mut keys| keys.all(|k| self.has(k)))
    }

    /// True when every point of the cloud in the ball (`p`, √`r2`) lies in a loaded cell.
    pub fn complete(&self, p: DVec3, r2: f64) -> bool {
        // The margins cover the rounding of the squared distances, as `cloud::inside` does.
        let r = r2.max(0.0).sqrt() * (1.0 + 1e-9) + (p.abs().max_element() + 1.0) * 1e-15;
        if !r.is_finite() {
            return false;
        }
        // Every point lies in the closed bounds, so the ball's part outside them holds none.
        let lo = (p - DVec3::splat(r)).max(self.bounds.min);
        let hi = (p + DVec3::splat(r)).min(self.bounds.max);
        if (0..3).any(|a| lo[a] > hi[a]) {
            return true;
        }
        // Every loaded point lies in the span as well as in a loaded cell (`contains`); a ball
        // reaching past the span is not proven, whatever its keys (they saturate for a degenerate
        // cell edge).
        self.covers(&Aabb { min: lo, max: hi })
    }
}

/// The cell keys from `lo` to `hi` (inclusive along each axis; none when `lo` exceeds `hi`
/// along one), or `None` when they are more than [`MAX_VISITS`].
fn keys_between(lo: [i64; 3], hi: [i64; 3]) -> Option<impl Iterator<Item = [i64; 3]>> {
    let span = |a: usize| hi[a].saturating_sub(lo[a]).saturating_add(1).max(0);
    if span(0).saturating_mul(span(1)).saturating_mul(span(2)) > MAX_VISITS {
        return None;
    }
    Some((lo[0]..=hi[0]).flat_map(move |x| {
        (lo[1]..=hi[1]).flat_map(move |y| (lo[2]..=hi[2]).map(move |z| [x, y, z]))
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bounds() -> Aabb {
        Aabb {
            min: DVec3::splat(-10.0),
            max: DVec3::splat(10.0),
        }
    }

    #[test]
    fn the_cells_cover_the_halo_cube_of_every_group_point() {
        let group = [DVec3::new(0.3, -1.7, 2.05), DVec3::new(4.0, 4.0, 4.0)];
        let halo = 0.25;
        let shell = Shell::around(
            DVec3::new(0.1, 0.2, 0.3),
            bounds(),
            group.iter().copied(),
            halo,
            None,
        );
        for g in group {
            for i in 0..=8 {
                for j in 0..=8 {
                    for k in 0..=8 {
                        let d = DVec3::new(i as f64, j as f64, k as f64) / 4.0 - 1.0;
                        assert!(shell.contains(g + d * halo), "{g} {d}");
                    }
                }
            }
            // At most halo × (1 + 1/DILATION) past the point.
            assert!(!shell.contains(g + DVec3::X * halo * 1.51));
            let span = shell.span();
            assert!(span.min.cmple(g - halo).all() && span.max.cmpge(g + halo).all());
        }
        assert!(!shell.contains(DVec3::new(2.0, 1.0, 3.0)));
    }

    #[test]
    fn a_group_of_many_cells_coarsens_the_cells_to_the_budget_and_still_covers_its_halo() {
        let group: Vec<DVec3> = (0..40_000)
            .map(|i| {
                let k = crate::points::sample_key(i);
                DVec3::new((k % 1000) as f64, ((k / 1000) % 1000) as f64, 0.0) * 0.009
            })
            .collect();
        let halo = 0.01;
        // Unbounded, then charged to a budget of 80 000 points a run (10 000 cells).
        for (max_points, most) in [(None, MAX_CELLS), (Some(80_000), 10_000)] {
            let points = group.iter().copied();
            let shell = Shell::around(DVec3::ZERO, bounds(), points, halo, max_points);
            assert!(shell.cells.len() <= most, "{}", shell.cells.len());
            assert!(shell.cell > halo / DILATION as f64);
            for g in group.iter().step_by(97) {
                for d in [DVec3::X, -DVec3::Y, DVec3::Z, DVec3::ONE, -DVec3::ONE] {
                    assert!(shell.contains(*g + d * halo));
                }
            }
        }
    }

    #[test]
    fn the_bitmap_and_the_hash_set_hold_the_same_cells() {
        let group = [DVec3::new(0.3, -1.7, 2.05), DVec3::new(4.0, 4.0, 4.0)];
        let mut shell = Shell::around(DVec3::ZERO, bounds(), group.iter().copied(), 0.25, None);
        assert!(shell.dense.is_some());
        let probes: Vec<DVec3> = (0..20_000)
            .map(|i| {
                let k = crate::points::sample_key(i);
                let c = |s: u64| ((k >> s) % 1000) as f64 / 1000.0 * 9.0 - 2.5;
                DVec3::new(c(0), c(10), c(20))
            })
            .chain(group.iter().flat_map(|g| {
                (0..125).map(move |i| {
                    *g + DVec3::new((i % 5) as f64, ((i / 5) % 5) as f64, (i / 25) as f64) * 0.15
                        - 0.3
                })
            }))
            .collect();
        let with: Vec<(bool, bool)> = probes
            .iter()
            .map(|&p| (shell.contains(p), shell.complete(p, 0.01)))
            .collect();
        assert!(with.iter().any(|w| w.0) && with.iter().any(|w| !w.0));
        shell.dense = None;
        let without: Vec<(bool, bool)> = probes
            .iter()
            .map(|&p| (shell.contains(p), shell.complete(p, 0.01)))
            .collect();
        assert_eq!(with, without);
    }

    #[test]
    fn issue16_a_block_holding_a_loaded_point_meets_the_shell() {
        let group = [DVec3::new(0.3, -1.7, 2.05), DVec3::new(4.0, 4.0, 4.0)];
        let shell = Shell::around(DVec3::ZERO, bounds(), group.iter().copied(), 0.25, None);
        let mut sparse = Shell::around(DVec3::ZERO, bounds(), group.iter().copied(), 0.25, None);
        sparse.dense = None;
        let (mut met, mut missed) = (0, 0);
        for i in 0..5_000u64 {
            // A "block": the box of a few points near each other.
            let k = crate::points::sample_key(i);
            let j = |s: u64| ((k >> s) % 1000) as f64 / 1000.0;
            let c = group[(i % 2) as usize] + DVec3::new(j(0), j(10), j(20)) * 1.6 - 0.8;
            let size = j(30) * 0.3;
            let pts: Vec<DVec3> = (0..4)
                .map(|q| c + DVec3::new(j(40 + q), j(44 + q), j(48 + q)) * size)
                .collect();
            let mut b = Aabb::empty();
            for p in &pts {
                b.union(&Aabb { min: *p, max: *p });
            }
            let holds = pts.iter().any(|p| shell.contains(*p));
            for sh in [&shell, &sparse] {
                assert!(!holds || sh.meets(&b), "{b:?}");
            }
            assert_eq!(shell.meets(&b), sparse.meets(&b));
            if shell.meets(&b) {
                met += 1
            } else {
                missed += 1
            }
        }
        // The test is not vacuous: many of these boxes lie away from the cells.
        assert!(met > 300 && missed > 1000, "{met} {missed}");
        assert!(!shell.meets(&Aabb::empty()));
        assert!(!shell.covers(&Aabb::empty()));
    }

    #[test]
    fn issue16_a_covered_box_holds_only_points_a_load_keeps() {
        let group = [DVec3::new(0.3, -1.7, 2.05), DVec3::new(4.0, 4.0, 4.0)];
        let shell = Shell::around(DVec3::ZERO, bounds(), group.iter().copied(), 0.25, None);
        let mut covered = 0;
        for i in 0..5_000u64 {
            let k = crate::points::sample_key(i);
            let j = |s: u64| ((k >> s) % 1000) as f64 / 1000.0;
            let c = group[(i % 2) as usize] + DVec3::new(j(0), j(10), j(20)) * 1.0 - 0.5;
            let size = j(30) * 0.2;
            let b = Aabb {
                min: c,
                max: c + DVec3::new(j(40), j(44), j(48)) * size,
            };
            if !shell.covers(&b) {
                continue;
            }
            covered += 1;
            for q in 0..27 {
                let f = DVec3::new((q % 3) as f64, (q / 3 % 3) as f64, (q / 9) as f64) / 2.0;
                assert!(shell.contains(b.min + (b.max - b.min) * f), "{b:?}");
            }
        }
        assert!(covered > 500, "{covered}");
    }

    #[test]
    fn a_ball_is_complete_only_when_its_cells_are_loaded() {
        let g = DVec3::new(1.0, 1.0, 1.0);
        let shell = Shell::around(DVec3::ZERO, bounds(), std::iter::once(g), 0.5, None);
        assert!(shell.complete(g, 0.49 * 0.49));
        assert!(shell.complete(g + DVec3::X * 0.2, 0.29 * 0.29));
        assert!(!shell.complete(g, 1.0));
        assert!(!shell.complete(g + DVec3::X * 0.8, 0.1));
        assert!(!shell.complete(g, f64::INFINITY));
    }

    #[test]
    fn a_degenerate_halo_proves_nothing_and_does_not_panic() {
        let g = DVec3::new(1.0, 2.0, 3.0);
        for halo in [0.0, f64::MIN_POSITIVE, 1e-300] {
            let shell = Shell::around(DVec3::ZERO, bounds(), std::iter::once(g), halo, None);
            assert!(!shell.complete(g, 1e-6), "{halo}");
            assert!(!shell.contains(g + DVec3::X), "{halo}");
        }
    }

    #[test]
    fn the_part_of_a_ball_outside_the_cloud_bounds_needs_no_cells() {
        let corner = DVec3::splat(10.0);
        let shell = Shell::around(DVec3::ZERO, bounds(), std::iter::once(corner), 0.5, None);
        // The loaded cells end 0.75 past the corner; this ball reaches 0.75 + 0.05 past it,
        // where no point can be.
        let out = corner + DVec3::splat(0.35);
        assert!(shell.complete(out, 0.45 * 0.45));
        assert!(!shell.contains(corner + DVec3::splat(0.78)));
        assert!(!shell.complete(corner, 0.6 * 0.6));
        // A ball wholly outside the bounds holds nothing.
        assert!(shell.complete(DVec3::splat(30.0), 1.0));
    }
}
