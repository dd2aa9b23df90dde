//! The fine cells a lone point's dependencies reach: what [`super::growth`] loads for points
//! whose halo alone holds more than the budget, and the proof that a k-NN ball holds nothing
//! more than was loaded.
//!
//! The occupancy grid's cells are sized for the isolation radius, so beside a dense cluster one
//! cell can hold more points than a run may: a sparse point whose ball touches the cluster could
//! not load that cell, though its list needs a handful of the cluster's points. The fine grid
//! splits every occupancy cell into 2^[`FINE_SHIFT`] cells along each axis, keyed so that a fine
//! cell's occupancy cell is its key shifted right (the same arithmetic as
//! [`Occupancy::cell_of`]), which lets the proof skip every fine cell of an empty occupancy cell:
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

/// The fine cells loaded for a group of lone points.
pub struct FineCells<'a> {
    grid: &'a Occupancy,
    cells: FxHashSet<[i64; 3]>,
    span: Aabb,
    most: usize,
}

/// A ball or cell that cannot be added: past the visits or cells allowed, or at coordinates
/// whose keys saturate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TooWide;

impl<'a> FineCells<'a> {
    /// No cells, over `grid`, keeping at most `most` cells.
    pub fn new(grid: &'a Occupancy, most: usize) -> FineCells<'a> {
        FineCells {
            grid,
            cells: FxHashSet::default(),
            span: Aabb::empty(),
            most,
        }
    }

    /// Fine cells loaded.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// True when no cell is loaded.
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// A box holding every loaded cell (what decides which spill files are read).
    pub fn span(&self) -> Aabb {
        self.span
    }

    /// True when `p` lies in a loaded cell.
    pub fn contains(&self, p: DVec3) -> bool {
        let span = &self.span;
        (0..3).all(|a| p[a] >= span.min[a] && p[a] <= span.max[a])
            && self.cells.contains(&self.grid.fine_key(p, FINE_SHIFT))
    }

    /// Visits the fine cells of non-empty occupancy cells that the bounding box of the ball
    /// (`p`, √`r2`) touches, until `f` says stop (false); `Err` past [`MAX_VISITS`] or for a
    /// ball that cannot be keyed.
    fn visit(
        &self,
        p: DVec3,
        r2: f64,
        mut f: impl FnMut([i64; 3]) -> bool,
    ) -> Result<bool, TooWide> {
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
        let mut visits = 0usize;
        for cx in lo[0] >> s..=hi[0] >> s {
            for cy in lo[1] >> s..=hi[1] >> s {
                for cz in lo[2] >> s..=hi[2] >> s {
                    if self.grid.count([cx, cy, cz]) == 0 {
                        continue;
                    }
                    // The fine cells of this occupancy cell inside [lo, hi].
                    let range =
                        |c: i64, a: usize| (lo[a].max(c << s), hi[a].min(((c + 1) << s) - 1));
                    let ((x0, x1), (y0, y1), (z0, z1)) = (range(cx, 0), range(cy, 1), range(cz, 2));
                    let n = ((x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1)) as usize;
                    visits += n;
                    if visits > MAX_VISITS {
                        return Err(TooWide);
                    }
                    for x in x0..=x1 {
                        for y in y0..=y1 {
                            for z in z0..=z1 {
                                if !f([x, y, z]) {
                                    return Ok(false);
                                }
                            }
                        }
                    }
                }
            }
        }
        Ok(true)
    }

    /// True when every point of the cloud within √`r2` of `p` lies in a loaded cell.
    pub fn complete(&self, p: DVec3, r2: f64) -> bool {
        self.visit(p, r2, |c| self.cells.contains(&c)) == Ok(true)
    }

    /// Loads the ball (`p`, √`r2`): every fine cell of a non-empty occupancy cell its bounding
    /// box touches. Returns whether a cell was added.
    ///
    /// # Errors
    /// [`TooWide`] for a ball past the visits allowed, or when the cells would pass the most
    /// kept (nothing is added then).
    pub fn add_ball(&mut self, p: DVec3, r2: f64) -> Result<bool, TooWide> {
        let mut new = Vec::new();
        self.visit(p, r2, |c| {
            if !self.cells.contains(&c) {
                new.push(c);
            }
            true
        })?;
        self.add(new)
    }

    /// Loads every fine cell of the occupancy cell `c`. Returns whether a cell was added.
    ///
    /// # Errors
    /// [`TooWide`] when the cells would pass the most kept (nothing is added then).
    pub fn add_cell(&mut self, c: [i64; 3]) -> Result<bool, TooWide> {
        let s = FINE_SHIFT;
        let side = 1i64 << s;
        let mut new = Vec::new();
        for x in 0..side {
            for y in 0..side {
                for z in 0..side {
                    let f = [(c[0] << s) + x, (c[1] << s) + y, (c[2] << s) + z];
                    if !self.cells.contains(&f) {
                        new.push(f);
                    }
                }
            }
        }
        self.add(new)
    }

    fn add(&mut self, new: Vec<[i64; 3]>) -> Result<bool, TooWide> {
        if self.cells.len() + new.len() > self.most {
            return Err(TooWide);
        }
        let added = !new.is_empty();
        for c in new {
            self.span.union(&self.grid.fine_box(c, FINE_SHIFT));
            self.cells.insert(c);
        }
        Ok(added)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grid with a dense cluster in one cell and a lone point two cells away.
    fn grid() -> (Occupancy, Vec<DVec3>, DVec3) {
        let mut g = Occupancy::new(1.0, DVec3::ZERO);
        let cluster: Vec<DVec3> = (0..1000)
            .map(|i| DVec3::new(2.1 + 0.0007 * i as f64, 0.5, 0.5))
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
        // Only part of the cluster's cell: its far end is not loaded, and a ball reaching it is
        // not complete.
        assert!(!cells.contains(cluster[999]));
        assert!(!cells.complete(lone, (cluster[999] - lone).length_squared()));
        // The empty cell between them was skipped: at most two occupancy cells' fine cells.
        assert!(cells.len() <= 2 * 512, "{}", cells.len());
        // A whole cell.
        assert!(cells.add_cell(g.cell_of(cluster[999])).unwrap());
        assert!(cells.contains(cluster[999]));
        // Past the cells kept, nothing is added.
        let mut few = FineCells::new(&g, 10);
        assert_eq!(few.add_cell(g.cell_of(lone)), Err(TooWide));
        assert!(few.is_empty());
        // A ball too wide to visit, or not finite, is never proven.
        assert!(!cells.complete(lone, 1e12));
        assert!(!cells.complete(lone, f64::INFINITY));
    }
}
