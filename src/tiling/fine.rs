//! The fine cells a lone point's dependencies reach: what [`super::growth`] loads for points
//! whose halo alone holds more than the budget, and the proof that a k-NN ball holds nothing
//! more than was loaded.
//!
//! The occupancy grid's cells are sized for the isolation radius, so beside a dense cluster one
//! cell can hold more points than a run may: a sparse point whose ball touches the cluster could
//! not load that cell, though its list needs a handful of the cluster's points. The fine grid
//! splits every occupancy cell into 2^[`FINE_SHIFT`] cells along each axis, keyed so that a fine
//! cell's occupancy cell is its key shifted right (the same arithmetic as
//! [`Occupancy::cell_of`]), which lets the proof skip every fine cell of an empty occupancy cell.
//! Occupancy cells with few points (`WHOLE_POINTS`, 1024) are loaded whole, one key for the 512 fine
//! ones (the wide balls of sparse points cross many of them):
//!
//! ```text
//!   occupancy cell (count from the partition pass)
//!   ┌───────────────┬───────────────┐
//!   │ 0             │ ▪▪▫▫ 1 200 000│   a ball is complete when every fine cell its bounding box
//!   │   (skipped)   │ ▪▪▫▫          │   touches is loaded (▪) or lies in an occupancy cell that
//!   │      ◯ ───────┼─▪▪            │   holds no point; a ball is loaded by adding those cells
//!   └───────────────┴───────────────┘
//! ```
//!
//! Which cells are loaded decides only which results the kernel can prove exact, never a value.

use glam::DVec3;
use rustc_hash::FxHashSet;

use super::occupancy::Occupancy;
use crate::points::Aabb;

/// Fine cells per occupancy cell along each axis: 2^3 = 8.
pub const FINE_SHIFT: u32 = 3;

/// Most fine cells one ball test or load visits (in non-empty occupancy cells).
const MAX_VISITS: usize = 1 << 16;

/// Most occupancy cells one ball test or load looks up.
const MAX_CELLS_VISITED: i64 = 4096;

/// Occupancy cells holding at most this many points are loaded whole (one key instead of up to
/// 512): the wide balls of sparse points cross many of them.
const WHOLE_POINTS: u64 = 1024;

/// The cells loaded for a group of lone points: whole occupancy cells where they hold few
/// points, fine cells within the others.
pub struct FineCells<'a> {
    grid: &'a Occupancy,
    whole: FxHashSet<[i64; 3]>,
    cells: FxHashSet<[i64; 3]>,
    span: Aabb,
    most: usize,
}

/// A ball that cannot be added: past the visits or cells allowed, or at coordinates whose keys
/// saturate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TooWide;

/// The fine keys of a ball's bounding box, `lo` and `hi`.
type Corners = ([i64; 3], [i64; 3]);

impl<'a> FineCells<'a> {
    /// No cells, over `grid`, keeping at most `most` cells (whole or fine).
    pub fn new(grid: &'a Occupancy, most: usize) -> FineCells<'a> {
        FineCells {
            grid,
            whole: FxHashSet::default(),
            cells: FxHashSet::default(),
            span: Aabb::empty(),
            most,
        }
    }

    /// Cells loaded (whole and fine).
    pub fn len(&self) -> usize {
        self.whole.len() + self.cells.len()
    }

    /// True when no cell is loaded.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A box holding every loaded cell (what decides which spill files are read).
    pub fn span(&self) -> Aabb {
        self.span
    }

    /// True when `p` lies in a loaded cell.
    pub fn contains(&self, p: DVec3) -> bool {
        let span = &self.span;
        (0..3).all(|a| p[a] >= span.min[a] && p[a] <= span.max[a])
            && (self.whole.contains(&self.grid.cell_of(p))
                || self.cells.contains(&self.grid.fine_key(p, FINE_SHIFT)))
    }

    /// The fine keys of the bounding box of the ball (`p`, √`r2`); `Err` for a ball that cannot
    /// be keyed or whose box touches more than [`MAX_CELLS_VISITED`] occupancy cells.
    fn corners(&self, p: DVec3, r2: f64) -> Result<Corners, TooWide> {
        // The margins cover the rounding of the squared distances, as `cloud::inside` does.
        let r = r2.max(0.0).sqrt() * (1.0 + 1e-9) + (p.abs().max_element() + 1.0) * 1e-15;
        if !r.is_finite() {
            return Err(TooWide);
        }
        let lo = self.grid.fine_key(p - DVec3::splat(r), FINE_SHIFT);
        let hi = self.grid.fine_key(p + DVec3::splat(r), FINE_SHIFT);
        // A saturated key may stand for far more space than its cell.
        if lo
            .iter()
            .chain(&hi)
            .any(|&k| k == i64::MIN || k == i64::MAX)
        {
            return Err(TooWide);
        }
        let s = FINE_SHIFT;
        let span = |a: usize| ((hi[a] >> s) - (lo[a] >> s)).saturating_add(1);
        if span(0).saturating_mul(span(1)).saturating_mul(span(2)) > MAX_CELLS_VISITED {
            return Err(TooWide);
        }
        Ok((lo, hi))
    }

    /// Calls `f` with each non-empty occupancy cell the box `(lo, hi)` touches that is not
    /// loaded whole, and the fine keys of the box inside it; stops when `f` says so (false).
    fn each_cell(&self, (lo, hi): Corners, mut f: impl FnMut([i64; 3], Corners) -> bool) -> bool {
        let s = FINE_SHIFT;
        for cx in lo[0] >> s..=hi[0] >> s {
            for cy in lo[1] >> s..=hi[1] >> s {
                for cz in lo[2] >> s..=hi[2] >> s {
                    let c = [cx, cy, cz];
                    if self.grid.count(c) == 0 || self.whole.contains(&c) {
                        continue;
                    }
                    let range = |a: usize| (lo[a].max(c[a] << s), hi[a].min(((c[a] + 1) << s) - 1));
                    let (x, y, z) = (range(0), range(1), range(2));
                    if !f(c, ([x.0, y.0, z.0], [x.1, y.1, z.1])) {
                        return false;
                    }
                }
            }
        }
        true
    }

    /// True when every point of the cloud within √`r2` of `p` lies in a loaded cell.
    pub fn complete(&self, p: DVec3, r2: f64) -> bool {
        let Ok(corners) = self.corners(p, r2) else {
            return false;
        };
        let mut visits = 0usize;
        self.each_cell(corners, |_, (a, b)| {
            visits += fine_count(a, b);
            visits <= MAX_VISITS
                && (a[0]..=b[0]).all(|x| {
                    (a[1]..=b[1]).all(|y| (a[2]..=b[2]).all(|z| self.cells.contains(&[x, y, z])))
                })
        })
    }

    /// Loads the ball (`p`, √`r2`): every occupancy cell its bounding box touches, whole where
    /// it holds at most `WHOLE_POINTS` points, else the fine cells of the box within it.
    /// Returns whether a cell was added.
    ///
    /// # Errors
    /// [`TooWide`] for a ball past the visits allowed, or when the cells would pass the most
    /// kept (nothing is added then).
    pub fn add_ball(&mut self, p: DVec3, r2: f64) -> Result<bool, TooWide> {
        let corners = self.corners(p, r2)?;
        let (mut whole, mut fine) = (Vec::new(), Vec::new());
        let mut visits = 0usize;
        let fits = self.each_cell(corners, |c, (a, b)| {
            if self.grid.count(c) <= WHOLE_POINTS {
                whole.push(c);
                return true;
            }
            visits += fine_count(a, b);
            if visits > MAX_VISITS {
                return false;
            }
            for x in a[0]..=b[0] {
                for y in a[1]..=b[1] {
                    for z in a[2]..=b[2] {
                        if !self.cells.contains(&[x, y, z]) {
                            fine.push([x, y, z]);
                        }
                    }
                }
            }
            true
        });
        if !fits || self.len() + whole.len() + fine.len() > self.most {
            return Err(TooWide);
        }
        let added = !whole.is_empty() || !fine.is_empty();
        for c in whole {
            self.span.union(&self.grid.cell_box(c));
            self.whole.insert(c);
        }
        for c in fine {
            self.span.union(&self.grid.fine_box(c, FINE_SHIFT));
            self.cells.insert(c);
        }
        Ok(added)
    }
}

/// Fine cells in the box of keys `a..=b`.
fn fine_count(a: [i64; 3], b: [i64; 3]) -> usize {
    (0..3).map(|i| (b[i] - a[i] + 1).max(0) as usize).product()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grid with a dense cluster in one cell and a lone point two cells away.
    fn grid() -> (Occupancy, Vec<DVec3>, DVec3) {
        let mut g = Occupancy::new(1.0, DVec3::ZERO, crate::tiling::occupancy::MAX_CELLS);
        let cluster: Vec<DVec3> = (0..2000)
            .map(|i| DVec3::new(2.1 + 0.00035 * i as f64, 0.5, 0.5))
            .collect();
        let lone = DVec3::new(0.2, 0.5, 0.5);
        for p in cluster.iter().chain([&lone]) {
            g.add(*p);
        }
        (g, cluster, lone)
    }

    #[test]
    fn issue16_fine_keys_nest_in_the_occupancy_cells() {
        let (mut g, ..) = grid();
        for level in 0..5 {
            for i in 0..2000 {
                let p = DVec3::new(
                    -7.3 + 0.0123 * i as f64,
                    3.1 - 0.007 * i as f64,
                    1e6 + 0.011 * i as f64,
                );
                let f = g.fine_key(p, FINE_SHIFT);
                assert_eq!(f.map(|k| k >> FINE_SHIFT), g.cell_of(p), "level {level}");
                let b = g.fine_box(f, FINE_SHIFT);
                assert!((0..3).all(|a| p[a] >= b.min[a] && p[a] <= b.max[a]));
            }
            g.coarsen();
        }
    }

    #[test]
    fn issue16_a_loaded_ball_is_complete_and_skips_empty_cells() {
        let (g, cluster, lone) = grid();
        let mut cells = FineCells::new(&g, 1 << 16);
        // The lone point's ball reaching the near end of the cluster.
        let r2 = (cluster[0] - lone).length_squared() * 1.01;
        assert!(!cells.complete(lone, r2));
        assert!(cells.add_ball(lone, r2).unwrap());
        assert!(cells.complete(lone, r2));
        assert!(!cells.add_ball(lone, r2).unwrap());
        assert!(cells.contains(lone) && cells.contains(cluster[0]));
        // The lone point's cell (one point) is loaded whole; only part of the cluster's cell
        // (2000 points) is: its far end is not loaded, and a ball reaching it is not complete.
        assert!(cells.whole.contains(&g.cell_of(lone)));
        assert!(!cells.whole.contains(&g.cell_of(cluster[0])));
        assert!(!cells.contains(cluster[999]));
        assert!(!cells.complete(lone, (cluster[999] - lone).length_squared()));
        // The empty cell between them was skipped: one whole cell and at most one cell's fine
        // cells.
        assert!(cells.len() <= 1 + 512, "{}", cells.len());
        // Past the cells kept, nothing is added.
        let mut few = FineCells::new(&g, 10);
        assert_eq!(few.add_ball(cluster[500], 0.25), Err(TooWide));
        assert!(few.is_empty());
        // A ball too wide to visit, or not finite, is never proven.
        assert!(!cells.complete(lone, 1e12));
        assert!(!cells.complete(lone, f64::INFINITY));
    }
}
