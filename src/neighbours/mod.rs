//! Neighbourhoods: k nearest neighbours, radius balls and mesh k-rings.
//!
//! # Brief overview
//!
//! * [`KnnIndex`] answers k-NN and radius queries over positions taken relative to a fixed f64
//!   origin: a hierarchy of uniform grids for the all-points k-NN pass (see `grid.rs`), a kiddo
//!   k-d tree for single queries and the grid's rare fallbacks. Only points whose relative
//!   coordinates are all within ±[`LOCAL_LIMIT`] are indexed (non-finite and absurdly far points
//!   never are), so no distance between indexed points can overflow. Answers are exact and
//!   deterministic:
//!   candidates are ranked by (squared distance, tie key) with this crate's own distance formula,
//!   where the tie key is the point's *global* index. Equal distances (duplicates, grids) always
//!   select the lowest global indices, so a tile, whatever order it stores its points in, picks
//!   exactly the neighbours the whole cloud would.
//! * The all-points pass has bounded work per point whatever the geometry (dense clusters, far
//!   outliers, duplicate stacks); [`KnnWork`] counts it. It checks the cancellation flag a caller
//!   installs with [`with_cancel`] and stops with [`NeighboursError::Cancelled`].
//! * [`spatial_order`] is the Morton (Z-curve) permutation kernels use to lay points out so that
//!   neighbours are close in memory.
//! * [`Neighbourhoods`] stores the lists in CSR form; k-NN lists are the special case of equal
//!   lengths.
//! * [`MeshAdjacency`] holds the vertex–vertex edges of a polygon mesh and walks k-rings.
//! * [`median_spacing`] is a cloud's median nearest-neighbour distance, duplicates skipped.
//! * [`brute`] holds the linear-scan oracles the tests compare against.
//!
//! ```text
//!  Neighbourhoods (CSR)
//!  offsets: [0, k, 2k, …]            point i: indices[offsets[i]..offsets[i+1]]
//!  indices: [i0 n1 n2 … | i1 …]      ascending (distance, index) for k-NN
//! ```

pub mod brute;
mod cancel;
mod closure;
pub use closure::{Listed, Prune, Seen, keep_near};
mod grid;
mod mesh;
mod spacing;

pub use cancel::{requested as cancel_requested, with_cancel};
pub use grid::Work as KnnWork;
pub use mesh::{HUB_VALENCE, MeshAdjacency, RingScratch};
pub use spacing::median_spacing;

use std::num::NonZeroUsize;
use std::sync::OnceLock;
use std::sync::atomic::Ordering;

use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use thiserror::Error;

/// Errors of neighbourhood construction.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum NeighboursError {
    /// k-NN asked for more neighbours than there are points.
    #[error("the cloud has {points} usable points, fewer than k = {k}")]
    TooFewPoints {
        /// Usable points.
        points: usize,
        /// Requested neighbourhood size.
        k: usize,
    },
    /// k must be at least 1.
    #[error("k must be at least 1")]
    ZeroK,
    /// More points than u32 indices can address.
    #[error("{0} points exceed the 4,294,967,295 an index can address")]
    TooManyPoints(usize),
    /// A face references a vertex that does not exist.
    #[error("face {face} references vertex {vertex}, but there are {vertices} vertices")]
    FaceIndex {
        /// Face number.
        face: usize,
        /// Offending index.
        vertex: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// The k-d tree could not be built.
    #[error("k-d tree construction failed: {0}")]
    Tree(String),
    /// The pass was cancelled through the flag installed with [`with_cancel`].
    #[error("cancelled")]
    Cancelled,
}

/// The largest relative coordinate magnitude (|p − origin| per axis) an indexed point may have:
/// 2⁴³ ≈ 8.8 · 10¹². It is more than twice [`crate::points::MAX_COORD`], so every point the
/// pipeline processes is indexed whatever origin inside the cloud's box is chosen, and squared
/// distances between indexed points stay below 3 · (2 · 2⁴³)² ≈ 10²⁷: never infinite.
pub const LOCAL_LIMIT: f64 = (1u64 << 43) as f64;

/// True when relative coordinates `p` are indexed (finite, within ±[`LOCAL_LIMIT`]).
#[inline]
pub fn indexable(p: [f64; 3]) -> bool {
    // Comparisons, so that NaN fails.
    p[0].abs() <= LOCAL_LIMIT && p[1].abs() <= LOCAL_LIMIT && p[2].abs() <= LOCAL_LIMIT
}

/// Neighbour lists in compressed-sparse-row form.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Neighbourhoods {
    /// `n + 1` offsets into `indices`.
    pub offsets: Vec<u32>,
    /// Concatenated neighbour indices.
    pub indices: Vec<u32>,
}

impl Neighbourhoods {
    /// Lists of one fixed length `k` given as a flat `n × k` array.
    pub fn fixed(k: usize, indices: Vec<u32>) -> Neighbourhoods {
        let n = indices.len().checked_div(k).unwrap_or(0);
        Neighbourhoods {
            offsets: (0..=n).map(|i| (i * k) as u32).collect(),
            indices,
        }
    }

    /// Number of lists.
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// True without lists.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The list of point `i`.
    #[inline]
    pub fn get(&self, i: usize) -> &[u32] {
        &self.indices[self.offsets[i] as usize..self.offsets[i + 1] as usize]
    }
}

type Tree = ImmutableKdTree<f64, 3>;

/// Exact k-NN and radius queries over a point set, with ties broken by a global key.
pub struct KnnIndex {
    /// Built on first use: the all-points pass rarely needs it.
    tree: OnceLock<Tree>,
    /// Positions relative to `origin`, as stored in the tree.
    local: Vec<[f64; 3]>,
    origin: DVec3,
    /// Number of indexed points (the tree holds a placeholder when this is 0).
    indexed: usize,
    /// Tie key of each point (its global index); `None` means the local index.
    ties: Option<Vec<u64>>,
    /// The grid's cell size for one k, chosen on first use ([`KnnIndex::base_level`]): the
    /// rounds of [`KnnIndex::knn_near`] ask it again on the same points, and in a tiled run with
    /// many halo-growth groups the estimate was a quarter of the CPU (issue 16).
    cell: OnceLock<(usize, f64)>,
}

impl KnnIndex {
    /// Builds the index over `points` (relative coordinates `p − origin`). Points failing
    /// [`indexable`] (non-finite, or beyond ±[`LOCAL_LIMIT`] from the origin) are not indexed and
    /// never returned.
    ///
    /// # Errors
    /// [`NeighboursError::TooManyPoints`] beyond u32 indices.
    pub fn build(points: &[DVec3], origin: DVec3) -> Result<KnnIndex, NeighboursError> {
        if points.len() > u32::MAX as usize {
            return Err(NeighboursError::TooManyPoints(points.len()));
        }
        let local: Vec<[f64; 3]> = points
            .par_iter()
            .map(|&p| (p - origin).to_array())
            .collect();
        let indexed = local.iter().filter(|p| indexable(**p)).count();
        Ok(KnnIndex {
            tree: OnceLock::new(),
            cell: OnceLock::new(),
            local,
            origin,
            indexed,
            ties: None,
        })
    }

    /// The k-d tree over the indexed points, built on first use.
    fn tree(&self) -> &Tree {
        self.tree.get_or_init(|| {
            let entries: Vec<(u32, [f64; 3])> = self
                .local
                .iter()
                .enumerate()
                .filter(|(_, p)| indexable(**p))
                .map(|(i, &p)| (i as u32, p))
                .collect();
            let entries = if entries.is_empty() {
                vec![(0, [0.0; 3])]
            } else {
                entries
            };
            // Construction from entries fails only on counts beyond u32, refused in `build`.
            Tree::new_from_entries(&entries).expect("k-d tree over at most u32::MAX points")
        })
    }

    /// Like [`KnnIndex::build`], with explicit tie keys (the points' global indices, which must
    /// be distinct): among equidistant candidates the lower key wins.
    ///
    /// # Errors
    /// As [`KnnIndex::build`].
    pub fn build_with_ties(
        points: &[DVec3],
        origin: DVec3,
        ties: Vec<u64>,
    ) -> Result<KnnIndex, NeighboursError> {
        debug_assert_eq!(points.len(), ties.len());
        let mut idx = KnnIndex::build(points, origin)?;
        idx.ties = Some(ties);
        Ok(idx)
    }

    /// The tie key of point `i`.
    #[inline]
    pub fn tie(&self, i: usize) -> u64 {
        self.ties.as_ref().map_or(i as u64, |t| t[i])
    }

    /// The tie keys, when they are not the local indices.
    pub fn ties(&self) -> Option<&[u64]> {
        self.ties.as_deref()
    }

    /// Number of indexed points.
    pub fn indexed(&self) -> usize {
        self.indexed
    }

    /// The origin the coordinates are relative to.
    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    /// The squared distance between indexed points `i` and `j`, as the index measures it.
    #[inline]
    pub fn dist2(&self, i: usize, j: usize) -> f64 {
        grid::dist2(self.local[i], self.local[j])
    }

    /// The `k` nearest indexed points to indexed point `i`, itself included (it is at distance 0,
    /// after any lower-indexed duplicates), in ascending (distance, index) order, appended to
    /// `out`. Returns the squared distance of the k-th.
    pub fn knn_of(&self, i: usize, k: usize, out: &mut Vec<u32>) -> f64 {
        self.knn_at(self.local[i], k, out)
    }

    /// The `k` nearest indexed points to `q` (relative to the origin), ascending by
    /// (distance, tie key), appended to `out`; returns the squared distance of the k-th. Fewer than
    /// `k` are returned only when fewer are indexed.
    ///
    /// Distances are this crate's own (`brute` computes them the same way), not kiddo's: the
    /// tree proposes a radius, every point inside a slightly larger radius is re-measured, and
    /// the k best by (distance, tie key) win. So the grid pass, this fallback and the oracle agree
    /// bit for bit, ties and rounding included.
    ///
    /// A query that is not itself [`indexable`] (beyond ±[`LOCAL_LIMIT`], where distances may
    /// overflow) is answered by a linear scan with the same ranking; a non-finite one gets no
    /// neighbours and NaN.
    pub fn knn_at(&self, q: [f64; 3], k: usize, out: &mut Vec<u32>) -> f64 {
        self.knn_at_counted(q, k, out).0
    }

    /// [`KnnIndex::knn_at`], also returning how many candidates were measured.
    fn knn_at_counted(&self, q: [f64; 3], k: usize, out: &mut Vec<u32>) -> (f64, usize) {
        if k == 0 || self.indexed == 0 {
            return (0.0, 0);
        }
        if !q.iter().all(|c| c.is_finite()) {
            return (f64::NAN, 0);
        }
        let want = k.min(self.indexed);
        if !indexable(q) {
            // Beyond the tree's reach: a scan ranks every point the same way.
            return self.knn_scan(q, k, out);
        }
        // One more than wanted: when that one lies beyond the inflated radius, every point the
        // radius query below would return is already here, and the second search is skipped
        // (most queries; the candidates are re-ranked by this crate's distance either way).
        let proposal = self
            .tree()
            .query(&q)
            .nearest_n::<SquaredEuclidean<f64>>(NonZeroUsize::new(want + 1).expect("want ≥ 1"))
            .execute();
        let r = proposal.get(want - 1).map_or(0.0, |c| c.distance);
        let items: Vec<u32> = match proposal.get(want) {
            Some(next) if next.distance <= inflate(r) => self.tree_within(q, inflate(r)).collect(),
            _ => proposal
                .iter()
                .filter(|c| c.distance <= inflate(r))
                .map(|c| c.item)
                .collect(),
        };
        let mut cand: Vec<(u128, u32)> = items
            .into_iter()
            .map(|item| {
                (
                    grid::rank(
                        grid::dist2(q, self.local[item as usize]),
                        self.tie(item as usize),
                    ),
                    item,
                )
            })
            .collect();
        let seen = cand.len();
        cand.sort_unstable();
        cand.truncate(want);
        out.extend(cand.iter().map(|c| c.1));
        (cand.last().map_or(0.0, |c| grid::rank_distance(c.0)), seen)
    }

    /// [`KnnIndex::knn_at_counted`] for a finite `q` by one pass over every indexed point,
    /// keeping the `k` best ranks (squared distance, tie key) seen: the same list and radius,
    /// without the k-d tree. What the grid passes use for their few fallback queries
    /// ([`SCAN_QUERIES`]), and the answer for a query beyond the tree's reach.
    fn knn_scan(&self, q: [f64; 3], k: usize, out: &mut Vec<u32>) -> (f64, usize) {
        let want = k.min(self.indexed);
        if want == 0 {
            return (0.0, 0);
        }
        let mut best: Vec<(u128, u32)> = Vec::with_capacity(want + 1);
        // The worst kept squared distance once `want` are kept: farther points cannot enter.
        let mut worst = f64::INFINITY;
        let mut seen = 0;
        for (i, p) in self.local.iter().enumerate() {
            if !indexable(*p) {
                continue;
            }
            let d = grid::dist2(q, *p);
            if d > worst {
                continue;
            }
            seen += 1;
            let r = (grid::rank(d, self.tie(i)), i as u32);
            let at = best.partition_point(|b| b.0 < r.0);
            if at < want {
                best.insert(at, r);
                best.truncate(want);
                if best.len() == want {
                    worst = grid::rank_distance(best[want - 1].0);
                }
            }
        }
        out.extend(best.iter().map(|b| b.1));
        (best.last().map_or(0.0, |b| grid::rank_distance(b.0)), seen)
    }

    /// The points the k-d tree finds within squared distance `r2` of `q` by its own distance, in
    /// no order (callers widen `r2` with [`inflate`] and re-measure).
    fn tree_within(&self, q: [f64; 3], r2: f64) -> impl Iterator<Item = u32> + '_ {
        self.tree()
            .query(&q)
            .within::<SquaredEuclidean<f64>>(r2)
            .unsorted()
            .execute()
            .into_iter()
            .map(|c| c.item)
    }

    /// Every indexed point within squared distance `r2` of `q` (inclusive, by this crate's own
    /// distance), ascending by index. A query or radius the tree cannot take (not
    /// [`indexable`], infinite) is answered by a linear scan; a NaN one finds nothing.
    pub fn within_at(&self, q: [f64; 3], r2: f64, out: &mut Vec<u32>) {
        if self.indexed == 0 || r2.is_nan() || !q.iter().all(|c| c.is_finite()) {
            return;
        }
        let start = out.len();
        if !indexable(q) || !r2.is_finite() {
            out.extend(
                (0..self.local.len())
                    .filter(|&i| indexable(self.local[i]))
                    .filter(|&i| grid::dist2(q, self.local[i]) <= r2)
                    .map(|i| i as u32),
            );
            return;
        }
        out.extend(
            self.tree_within(q, inflate(r2))
                .filter(|&j| grid::dist2(q, self.local[j as usize]) <= r2),
        );
        out[start..].sort_unstable();
    }

    /// Relative coordinates of indexed point `i`.
    #[inline]
    pub fn local(&self, i: usize) -> [f64; 3] {
        self.local[i]
    }

    /// The level-0 grid cell sizes for [`KnnIndex::knn_all`] (plain, weighted): 1.5 × the median
    /// k-th neighbour distance of [`CELL_PROBES`] points, and 1.5 × the area-weighted median of
    /// the same distances ([`cell_radii`]), estimated on an evenly strided subsample of about
    /// [`CELL_SAMPLE`] points (for a stride `s`, a ball holding k − 1 neighbours holds about
    /// (k − 1)/s sample points; below 5, radii are scaled as on a surface, ∝ √count); 0 when it
    /// cannot be estimated (the grid then chooses). [`KnnIndex::base_level`] chooses between
    /// them. Only speed depends on it: the grid pass is exact for any cell size, and refines
    /// dense cells itself.
    fn estimate_cells(&self, k: usize) -> (f64, f64) {
        let stride = (self.indexed / CELL_SAMPLE).max(1);
        let sample: Vec<DVec3> = self
            .local
            .iter()
            .filter(|p| indexable(**p))
            .step_by(stride)
            .map(|&p| DVec3::from_array(p))
            .collect();
        // Lists include the point itself, so a list of k holds k − 1 neighbours.
        let ks = ((k - 1) as f64 / stride as f64).round().max(5.0) as usize + 1;
        let scale = ((k - 1) as f64 / ((ks - 1) * stride) as f64).sqrt();
        if sample.len() <= ks {
            return (0.0, 0.0);
        }
        let Ok(sub) = KnnIndex::build(&sample, DVec3::ZERO) else {
            return (0.0, 0.0);
        };
        let step = (sample.len() / CELL_PROBES).max(1);
        let mut radii: Vec<f64> = (0..sample.len())
            .step_by(step)
            .map(|i| {
                let mut v = Vec::with_capacity(ks);
                sub.knn_of(i, ks, &mut v).sqrt()
            })
            .collect();
        radii.sort_by(f64::total_cmp);
        let (plain, weighted) = cell_radii(&radii);
        (1.5 * plain * scale, 1.5 * weighted * scale)
    }

    /// k-NN lists of every indexed point (the point itself included), computed in parallel;
    /// also returns the squared radius of each list. Points that are not indexed get empty lists.
    ///
    /// # Errors
    /// [`NeighboursError::ZeroK`], [`NeighboursError::TooFewPoints`] when fewer than `k` points are
    /// indexed, [`NeighboursError::Cancelled`] when the flag installed with [`with_cancel`] on
    /// this thread is set during the pass.
    pub fn knn_all(&self, k: usize) -> Result<(Neighbourhoods, Vec<f64>), NeighboursError> {
        self.knn_all_counted(k)
            .map(|(lists, radii, _)| (lists, radii))
    }

    /// [`KnnIndex::knn_all`], also returning the work it did.
    ///
    /// # Errors
    /// As [`KnnIndex::knn_all`].
    pub fn knn_all_counted(
        &self,
        k: usize,
    ) -> Result<(Neighbourhoods, Vec<f64>, KnnWork), NeighboursError> {
        self.knn_asked(k, None)
    }

    /// [`KnnIndex::knn_all_counted`] for the indexed points `asked` selects (every one when
    /// `None`); the others get empty lists and radius 0. Every indexed point is a candidate, so an
    /// asked point's list and radius are [`KnnIndex::knn_all`]'s.
    ///
    /// # Errors
    /// As [`KnnIndex::knn_all`].
    pub(crate) fn knn_asked(
        &self,
        k: usize,
        asked: Option<&[bool]>,
    ) -> Result<(Neighbourhoods, Vec<f64>, KnnWork), NeighboursError> {
        let base = self.base_level(k)?;
        self.knn_from(&base, k, asked)
    }

    /// The first grid level of a pass with lists of `k` (every indexed point sorted into
    /// cells), to share between the passes of [`KnnIndex::knn_from`]. Its cell is chosen by a
    /// trial: the level is built with the plain cell of [`KnnIndex::estimate_cells`], and
    /// [`CELL_PROBES`] probes (evenly strided over the indexed points) are queried on it as a
    /// pass would ([`grid::BaseLevel::trial`]). The level is rebuilt
    /// - with the weighted cell, when it is over [`WEIGHTED_LARGER`] × the plain one and one
    ///   probe in [`TREE_SHARE`] or more would go to the k-d tree (a dense population beside a
    ///   sparse one: the sparse one's queries leave the grid);
    /// - otherwise with 1.5 × the probes' median k-th distance as measured, when that is over
    ///   [`GROW`] × the plain cell. The subsample's radii are scaled to full density as on a
    ///   surface (∝ √count); where the points fill space at the subsample's scale (noisy or
    ///   volumetric clutter) that comes out too small, and a block then holds about one query:
    ///   one gather per query instead of one per dozen.
    ///
    /// The choice is cached for the first `k` asked (the rounds of `knn_near` ask it again).
    ///
    /// # Errors
    /// [`NeighboursError::ZeroK`], [`NeighboursError::TooFewPoints`] when fewer than `k` points
    /// are indexed.
    pub(crate) fn base_level(&self, k: usize) -> Result<grid::BaseLevel, NeighboursError> {
        if k == 0 {
            return Err(NeighboursError::ZeroK);
        }
        if self.indexed < k {
            return Err(NeighboursError::TooFewPoints {
                points: self.indexed,
                k,
            });
        }
        let ids = || (0..self.local.len() as u32).filter(|&i| indexable(self.local[i as usize]));
        let build =
            |cell: f64| grid::BaseLevel::build(&self.local, ids().collect(), cell, self.ties());
        if let Some(&(at, cell)) = self.cell.get()
            && at == k
        {
            return Ok(build(cell));
        }
        let (plain, weighted) = self.estimate_cells(k);
        let base = build(plain);
        // Where the subsample is the whole index its radii are exact, and a cloud whose two
        // cells agree needs no tree-share trial.
        let extrapolated = self.indexed >= 2 * CELL_SAMPLE;
        let try_weighted = weighted > WEIGHTED_LARGER * plain;
        let mut cell = plain;
        if extrapolated || try_weighted {
            let step = (self.indexed / CELL_PROBES).max(1);
            let probes: Vec<u32> = ids().step_by(step).collect();
            let trial = base.trial(&self.local, &probes, k);
            let measured = 1.5 * trial.kth[trial.kth.len() / 2];
            if try_weighted && trial.tree * TREE_SHARE >= probes.len() {
                cell = weighted;
            } else if extrapolated && measured.is_finite() && measured > GROW * plain {
                cell = measured;
            }
        }
        // Cached for the first k asked (the rounds of `knn_near` ask it again).
        let _ = self.cell.set((k, cell));
        Ok(if cell == plain {
            base
        } else {
            drop(base);
            build(cell)
        })
    }

    /// [`KnnIndex::knn_asked`] from a first level `base` that [`KnnIndex::base_level`] built for
    /// this index and `k`.
    ///
    /// # Errors
    /// As [`KnnIndex::knn_all`].
    pub(crate) fn knn_from(
        &self,
        base: &grid::BaseLevel,
        k: usize,
        asked: Option<&[bool]>,
    ) -> Result<(Neighbourhoods, Vec<f64>, KnnWork), NeighboursError> {
        let flag = cancel::current();
        let cancel = flag.as_deref();
        let stop = || cancel.is_some_and(|c| c.load(Ordering::Relaxed));
        let n = self.local.len();
        let (cells, mut work) = grid::all_knn(&self.local, base, asked, self.ties(), k, cancel)
            .map_err(|_| NeighboursError::Cancelled)?;
        let asked = |i: usize| asked.is_none_or(|a| a[i]);
        let mut offsets = Vec::with_capacity(n + 1);
        offsets.push(0u32);
        let mut total = 0u32;
        let mut listed = Vec::with_capacity(n);
        for (i, p) in self.local.iter().enumerate() {
            if indexable(*p) && asked(i) {
                total += k as u32;
                listed.push(i as u32);
            }
            offsets.push(total);
        }
        // Where each point's answer is: (cell, offset into its lists), or (MAX, fallback group).
        const TREE: u32 = u32::MAX;
        let mut loc = vec![(TREE, 0u32); n];
        // Points the tree answers, grouped by position: a cell lists coincident points
        // consecutively, and they share one answer.
        let mut groups: Vec<u32> = Vec::new();
        for (ci, c) in cells.iter().enumerate() {
            let mut at = 0u32;
            let mut last: Option<[f64; 3]> = None;
            for &(i, r) in &c.points {
                if r.is_nan() {
                    let p = self.local[i as usize];
                    if last != Some(p) {
                        groups.push(i);
                        last = Some(p);
                    }
                    loc[i as usize] = (TREE, groups.len() as u32 - 1);
                } else {
                    loc[i as usize] = (ci as u32, at);
                    at += k as u32;
                    last = None;
                }
            }
        }
        // Sparse regions and outliers go to the tree, in parallel; a few of them to a scan of
        // every point, which costs less than building the tree (when it is not built yet).
        let scan = groups.len() <= SCAN_QUERIES && self.tree.get().is_none();
        let resolved: Vec<(Vec<u32>, f64, usize)> = groups
            .par_iter()
            .map(|&i| {
                let mut v = Vec::with_capacity(k);
                if stop() {
                    return (v, f64::NAN, 0);
                }
                let q = self.local[i as usize];
                let (r, seen) = if scan {
                    self.knn_scan(q, k, &mut v)
                } else {
                    self.knn_at_counted(q, k, &mut v)
                };
                (v, r, seen)
            })
            .collect();
        if stop() {
            return Err(NeighboursError::Cancelled);
        }
        work.tree_queries = cells
            .iter()
            .map(|c| c.points.iter().filter(|p| p.1.is_nan()).count() as u64)
            .sum();
        work.tree_candidates = resolved.iter().map(|r| r.2 as u64).sum();
        // Gather every list into CSR order, in parallel.
        let mut indices = vec![0u32; total as usize];
        indices
            .par_chunks_mut(k)
            .zip(listed.par_iter())
            .for_each(|(dst, &i)| {
                let (ci, at) = loc[i as usize];
                if ci == TREE {
                    dst.copy_from_slice(&resolved[at as usize].0);
                } else {
                    let at = at as usize;
                    dst.copy_from_slice(&cells[ci as usize].lists[at..at + k]);
                }
            });
        let mut radii = vec![0.0f64; n];
        for c in &cells {
            for &(i, r) in &c.points {
                if !r.is_nan() {
                    radii[i as usize] = r;
                }
            }
        }
        for (i, l) in loc.iter().enumerate() {
            if l.0 == TREE && indexable(self.local[i]) && asked(i) {
                radii[i] = resolved[l.1 as usize].1;
            }
        }
        Ok((Neighbourhoods { offsets, indices }, radii, work))
    }
}

/// The k-th neighbour distances the first grid level's cell may be sized from, given the
/// probes' distances `radii` (ascending): their median, and their median with each probe
/// weighted by the area it stands for, r² (capped at [`WEIGHT_CAP`] × the median, so that a few
/// far outliers do not decide). Where the points are two populations, a dense one that has most
/// of the points and a sparse one that has most of the space (a tile that is mostly one dense
/// cluster, with the surfaces around it), the plain median suits the cluster and leaves the
/// surfaces' queries to the k-d tree; the weighted one suits the surfaces, and the cluster
/// refines into finer levels, as the grid does for any dense cell. [`KnnIndex::base_level`]
/// chooses by trial. Only speed depends on it: the grid pass is exact for any cell size.
fn cell_radii(radii: &[f64]) -> (f64, f64) {
    let Some(&median) = radii.get(radii.len() / 2) else {
        return (0.0, 0.0);
    };
    let weight = |r: f64| r.min(WEIGHT_CAP * median).powi(2);
    let half = 0.5 * radii.iter().map(|&r| weight(r)).sum::<f64>();
    let mut acc = 0.0;
    let weighted = radii
        .iter()
        .copied()
        .find(|&r| {
            acc += weight(r);
            acc >= half
        })
        .unwrap_or(median);
    (median, weighted)
}

/// See [`KnnIndex::base_level`]: the cell grows to 1.5 × the probes' median k-th distance,
/// measured on the plain level, when that is over this many times the extrapolated one. On the
/// real scans of `../shared` the two agree within 0.93–1.03 × and on the torus 0.92 ×; on the
/// cluttered scene's tiles the measured one is 1.3–1.5 × (the grid then gathered a block per
/// query or so, and growing took a quarter of those tiles' time off).
const GROW: f64 = 1.2;
/// See [`KnnIndex::base_level`]: the weighted cell is tried only when it is this much larger
/// than the plain one (on a locally uniform cloud the two differ by a few per cent).
const WEIGHTED_LARGER: f64 = 1.25;
/// See [`KnnIndex::base_level`]: the weighted cell is taken when one probe in this many or more
/// would go to the k-d tree on the plain cell. The real scans of `../shared` leave at most 7 %
/// of their queries to the tree (`room_scan1.pcd`, `kitti_000008.bin`), where the weighted cell
/// costs 13–19 % more k-NN instructions; the cluttered scenes' slow tiles 22–41 %, where it
/// saves a third of the tile's time.
const TREE_SHARE: usize = 8;
/// See [`cell_radii`].
const WEIGHT_CAP: f64 = 8.0;

/// Points of the subsample [`KnnIndex::estimate_cells`] estimates the grid's cells from (at
/// most about this many), and of its points whose k-th neighbour distance it measures (also
/// the probes of [`KnnIndex::base_level`]'s trial). Only speed depends on them. The estimate
/// builds a k-d tree over the subsample once per index, and a tiled run on a real scan under a
/// small budget builds hundreds of indexes (halo growth): at 16 384 and 1024 the estimates were
/// 9 % of `lone-star.copc.laz`'s CPU at 32 MiB (perf), and 4096 and 256 made that run 14 %
/// faster with the same bytes and no slower k-NN in memory (BENCHMARKS "Issue 16 — graded
/// passes, …").
const CELL_SAMPLE: usize = 4096;
/// See [`CELL_SAMPLE`].
const CELL_PROBES: usize = 256;

/// Fallback queries of a grid pass answered by [`KnnIndex::knn_scan`] instead of the k-d tree,
/// when the tree is not built yet: building it costs about 480 instructions a point (callgrind,
/// the 300 k cluttered scene at 20 000 points a tile: 59 builds, 5.3 % of the run), a scan about
/// 10, so up to a few dozen scans cost less than one build.
const SCAN_QUERIES: usize = 32;

/// Widens a squared radius by a few ulps' worth so that a kiddo range query cannot miss a point
/// this crate measures as inside (the two may round the last bit differently).
fn inflate(r2: f64) -> f64 {
    r2 * (1.0 + 1e-12) + f64::MIN_POSITIVE
}

/// Interleaves the low 21 bits of `v` with two zero bits between each.
fn spread3(mut v: u64) -> u64 {
    v &= 0x1f_ffff;
    v = (v | v << 32) & 0x1f00000000ffff;
    v = (v | v << 16) & 0x1f0000ff0000ff;
    v = (v | v << 8) & 0x100f00f00f00f00f;
    v = (v | v << 4) & 0x10c30c30c30c30c3;
    v = (v | v << 2) & 0x1249249249249249;
    v
}

/// Morton (Z-curve) codes on a grid of 2²¹ steps per axis over a box: 63-bit keys whose order
/// keeps points that are near in space near in the order.
#[derive(Debug, Clone, Copy)]
pub struct MortonGrid {
    min: DVec3,
    scale: DVec3,
}

impl MortonGrid {
    /// The grid over `bounds` (an empty or flat axis maps to step 0).
    pub fn new(bounds: &crate::points::Aabb) -> MortonGrid {
        let size = bounds.size();
        let scale = |e: f64| {
            if e > 0.0 && e.is_finite() {
                ((1u64 << 21) - 1) as f64 / e
            } else {
                0.0
            }
        };
        MortonGrid {
            min: bounds.min,
            scale: DVec3::new(scale(size.x), scale(size.y), scale(size.z)),
        }
    }

    /// The code of `p` (coordinates outside the box are clamped into it).
    pub fn key(&self, p: DVec3) -> u64 {
        let d = (p - self.min) * self.scale;
        // `as` saturates (below the box, and NaN, give step 0); `min` clamps above the box, which
        // `spread3` would otherwise wrap.
        let q = |v: f64| (v as u64).min((1 << 21) - 1);
        spread3(q(d.x)) | spread3(q(d.y)) << 1 | spread3(q(d.z)) << 2
    }
}

/// The indices of `points` in Morton (Z-curve) order over their bounding box (63-bit codes, ties by
/// index), points failing [`crate::points::in_range`] (non-finite or absurdly far) last. Kernels that visit points in this order touch neighbouring
/// data in neighbouring memory; on shuffled input that halves the time of the normal and solve
/// passes.
pub fn spatial_order(points: &[DVec3]) -> Vec<u32> {
    let grid = MortonGrid::new(&crate::points::Aabb::from_points(points));
    let mut keyed: Vec<(u64, u32)> = points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            if !crate::points::in_range(*p) {
                return (u64::MAX, i as u32);
            }
            (grid.key(*p), i as u32)
        })
        .collect();
    keyed.par_sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn cloud(seed: u64, n: usize, grid: bool) -> Vec<DVec3> {
        let mut x = seed.wrapping_mul(0x9e3779b97f4a7c15) | 1;
        let mut rnd = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let p = DVec3::new(rnd(), rnd(), rnd()) * 10.0;
                if grid { p.floor() } else { p }
            })
            .collect()
    }

    proptest! {
        /// k-NN agrees exactly with the brute-force oracle, ties included (grid clouds are full of
        /// equal distances and duplicates).
        #[test]
        #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
        fn knn_matches_brute_force(seed in 0u64..10_000, n in 1usize..300, k in 1usize..20,
                                   grid in any::<bool>()) {
            let pts = cloud(seed, n, grid);
            let origin = DVec3::new(3.0, -2.0, 1.5);
            let index = KnnIndex::build(&pts, origin).unwrap();
            match index.knn_all(k) {
                Err(NeighboursError::TooFewPoints { .. }) => prop_assert!(n < k),
                Err(e) => prop_assert!(false, "{e}"),
                Ok((nb, _)) => {
                    let local: Vec<DVec3> = pts.iter().map(|&p| p - origin).collect();
                    for i in 0..n {
                        let want = brute::knn(&local, local[i], k);
                        prop_assert_eq!(nb.get(i), &want[..], "point {}", i);
                    }
                }
            }
        }

        /// Radius queries return exactly the points within the radius, inclusive.
        #[test]
        fn within_matches_brute_force(seed in 0u64..10_000, n in 1usize..300, r in 0.0f64..4.0,
                                      grid in any::<bool>()) {
            let pts = cloud(seed, n, grid);
            let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
            for i in (0..n).step_by(7) {
                let mut got = Vec::new();
                index.within_at(pts[i].to_array(), r * r, &mut got);
                prop_assert_eq!(got, brute::within(&pts, pts[i], r * r));
            }
        }
    }

    proptest! {
        /// With explicit tie keys (a shuffled global numbering), k-NN ranks equidistant points
        /// by key, exactly as the oracle does.
        #[test]
        #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
        fn knn_with_ties_matches_brute_force(seed in 0u64..10_000, n in 20usize..300,
                                             k in 1usize..20) {
            let pts = cloud(seed, n, true);
            let mut ties: Vec<u64> = (0..n as u64).map(|i| i * 7919 % 100_003).collect();
            ties.reverse();
            // Keys within 32 bits rank through packed ranks, wider ones through pairs.
            let wide: Vec<u64> = ties.iter().map(|&t| t * (1 << 20) + (1 << 33)).collect();
            for ties in [ties, wide] {
                let index = KnnIndex::build_with_ties(&pts, DVec3::ZERO, ties.clone()).unwrap();
                let (nb, _) = index.knn_all(k.min(n)).unwrap();
                for i in 0..n {
                    let want = brute::knn_with_ties(&pts, &ties, pts[i], k.min(n));
                    prop_assert_eq!(nb.get(i), &want[..], "point {}", i);
                }
            }
        }
    }

    proptest! {
        /// The k-d tree path (what the grid leaves to it) ranks exactly as the oracle does, at
        /// lattice points (ties at the k-th distance: its second search) and between them
        /// (mostly none: its first search alone).
        #[test]
        fn tree_knn_with_ties_matches_brute_force(seed in 0u64..10_000, n in 20usize..300,
                                                  k in 1usize..20) {
            let pts = cloud(seed, n, true);
            let ties: Vec<u64> = (0..n as u64).map(|i| (i * 7919 + 17) % 100_003).collect();
            let index = KnnIndex::build_with_ties(&pts, DVec3::ZERO, ties.clone()).unwrap();
            let k = k.min(n);
            let mut out = Vec::new();
            for (i, &p) in pts.iter().enumerate().step_by(5) {
                for q in [p, p + DVec3::new(0.31, 0.17, 0.05) * (i % 3) as f64] {
                    out.clear();
                    index.knn_at(q.to_array(), k, &mut out);
                    let want = brute::knn_with_ties(&pts, &ties, q, k);
                    prop_assert_eq!(&out, &want, "query {:?}", q);
                }
            }
        }
    }

    #[test]
    fn spatial_order_is_a_permutation_with_non_finite_last() {
        let mut pts = cloud(3, 500, false);
        pts[17] = DVec3::NAN;
        let order = spatial_order(&pts);
        let mut seen = order.clone();
        seen.sort_unstable();
        assert_eq!(seen, (0..500).collect::<Vec<u32>>());
        assert_eq!(*order.last().unwrap(), 17);
    }

    #[test]
    fn self_is_first_and_duplicates_break_by_index() {
        let pts = vec![DVec3::ONE; 6];
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let mut out = Vec::new();
        index.knn_of(4, 3, &mut out);
        assert_eq!(out, vec![0, 1, 2]);
        assert_eq!(
            index.knn_all(7).unwrap_err(),
            NeighboursError::TooFewPoints { points: 6, k: 7 }
        );
    }

    #[test]
    fn non_finite_points_are_never_neighbours() {
        let pts = vec![
            DVec3::ZERO,
            DVec3::new(f64::NAN, 0.0, 0.0),
            DVec3::X,
            DVec3::Y,
        ];
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (nb, _) = index.knn_all(3).unwrap();
        assert_eq!(nb.get(0), &[0, 2, 3]);
        assert!(nb.get(1).is_empty());
    }

    /// A deterministic generator for the scene tests.
    struct Rng(u64);
    impl Rng {
        fn f(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
        fn g(&mut self) -> f64 {
            let (u, v) = (self.f().max(1e-300), self.f());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        }
    }

    /// A wavy 10 × 10 surface of `n` points.
    fn surface(n: usize, seed: u64) -> Vec<DVec3> {
        let mut r = Rng(seed | 1);
        (0..n)
            .map(|_| {
                let (x, y) = (r.f() * 10.0, r.f() * 10.0);
                DVec3::new(x, y, (x * 0.8).sin() + 0.01 * r.g())
            })
            .collect()
    }

    /// The cluttered scene of the seam tests, small: a surface, dense Gaussian clusters, exact
    /// duplicates, a stack of coincident points and far outliers (up to `far`).
    fn cluttered(n: usize, far: f64, seed: u64) -> Vec<DVec3> {
        let mut r = Rng(seed | 1);
        let mut v = surface(n * 3 / 5, seed);
        let centres = [
            (DVec3::new(2.0, 2.0, 1.0), 0.003),
            (DVec3::new(7.0, 5.0, 0.5), 0.03),
        ];
        for i in 0..n * 2 / 5 {
            let (c, s) = centres[i % 2];
            v.push(c + DVec3::new(r.g(), r.g(), r.g()) * s);
        }
        for _ in 0..n / 100 {
            let p = v[(r.f() * v.len() as f64) as usize];
            v.push(p);
        }
        v.extend(std::iter::repeat_n(DVec3::new(5.0, 5.0, 3.0), 60));
        for _ in 0..n / 500 + 1 {
            let d = DVec3::new(r.g(), r.g(), r.g()).normalize_or(DVec3::X);
            v.push(d * (50.0 + r.f() * far));
        }
        v
    }

    /// Every `step`-th list of `nb` equals the brute-force oracle's.
    fn assert_oracle(pts: &[DVec3], origin: DVec3, nb: &Neighbourhoods, k: usize, step: usize) {
        let local: Vec<DVec3> = pts.iter().map(|&p| p - origin).collect();
        for i in (0..pts.len()).step_by(step) {
            if !indexable(local[i].to_array()) {
                assert!(nb.get(i).is_empty());
                continue;
            }
            assert_eq!(nb.get(i), &brute::knn(&local, local[i], k)[..], "point {i}");
        }
    }

    fn work_of(pts: &[DVec3], k: usize) -> (Neighbourhoods, KnnWork) {
        let origin = crate::denoise::origin_of(pts);
        let index = KnnIndex::build(pts, origin).unwrap();
        let (nb, _, work) = index.knn_all_counted(k).unwrap();
        assert_eq!(work.queries, pts.len() as u64);
        (nb, work)
    }

    /// Issue 15: one far point used to make the grid coarse for every point (20 k points with one
    /// point at 10⁶ took 40 µs per query instead of 1): the work per query must not depend on
    /// how far the outlier is, and the answer must stay the oracle's.
    #[test]
    #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
    fn issue15_far_outlier_knn_is_bounded() {
        let k = 16;
        let base = surface(20_000, 5);
        let (_, plain) = work_of(&base, k);
        for far in [1e3, 1e6, 1e11] {
            let mut pts = base.clone();
            pts.push(DVec3::new(far, 0.0, 0.0));
            let (nb, work) = work_of(&pts, k);
            let per_query = work.candidates as f64 / work.queries as f64;
            let plain_per_query = plain.candidates as f64 / plain.queries as f64;
            assert!(
                per_query <= 2.0 * plain_per_query,
                "far = {far}: {per_query:.0} candidates per query, {plain_per_query:.0} without it"
            );
            assert!(work.max_block <= 96 * k as u64, "{work:?}");
            assert!(work.tree_queries <= 20, "{work:?}");
            assert!(work.cells <= 4 * plain.cells, "{work:?} vs {plain:?}");
            assert_oracle(&pts, crate::denoise::origin_of(&pts), &nb, k, 97);
            let last = pts.len() - 1;
            assert_eq!(
                nb.get(last),
                &brute::knn(
                    &pts.iter()
                        .map(|&p| p - crate::denoise::origin_of(&pts))
                        .collect::<Vec<_>>(),
                    pts[last] - crate::denoise::origin_of(&pts),
                    k
                )[..]
            );
        }
    }

    /// Dense clusters, duplicates, a stack of 60 coincident points and far outliers: every grid
    /// query scans a bounded block, and the answer is the oracle's everywhere.
    #[test]
    #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
    fn cluttered_scene_is_exact_with_bounded_blocks() {
        for (seed, far) in [(1, 500.0), (2, 1e5), (3, 1e9)] {
            let pts = cluttered(4000, far, seed);
            for k in [1, 8, 16] {
                let (nb, work) = work_of(&pts, k);
                assert!(work.max_block <= 96 * k.max(4) as u64, "k = {k}: {work:?}");
                assert!(k < 16 || work.levels >= 2, "the clusters refine: {work:?}");
                assert!(
                    (work.candidates as f64) < 40.0 * k.max(4) as f64 * work.queries as f64,
                    "k = {k}: {work:?}"
                );
                assert_oracle(&pts, crate::denoise::origin_of(&pts), &nb, k, 3);
            }
            // Tie keys in another order than the storage order (a tile's global indices).
            let ties: Vec<u64> = (0..pts.len() as u64).map(|i| i * 7919 % 100_003).collect();
            let index = KnnIndex::build_with_ties(&pts, DVec3::ZERO, ties.clone()).unwrap();
            let (nb, _) = index.knn_all(16).unwrap();
            for i in (0..pts.len()).step_by(7) {
                let want = brute::knn_with_ties(&pts, &ties, pts[i], 16);
                assert_eq!(nb.get(i), &want[..], "point {i}");
            }
        }
    }

    /// Issue 16: a cloud that is mostly one dense cluster, with a surface beside it, had the
    /// grid's cells sized for the cluster and left the surface's queries to the k-d tree (41 % of
    /// the queries of a tile of the 30 M cluttered scene, the tile's largest cost): the cells now
    /// follow the space most points stand for, the cluster refines, and the answer stays the
    /// oracle's.
    #[test]
    #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
    fn issue16_a_dense_cluster_beside_a_surface_leaves_few_queries_to_the_tree() {
        let mut r = Rng(11);
        let mut pts = surface(12_000, 3);
        for _ in 0..24_000 {
            pts.push(DVec3::new(5.0, 5.0, 1.5) + DVec3::new(r.g(), r.g(), r.g()) * 0.02);
        }
        let (nb, work) = work_of(&pts, 16);
        assert!(work.tree_queries * 100 < work.queries, "{work:?}");
        assert!(work.levels >= 2, "the cluster refines: {work:?}");
        assert_oracle(&pts, crate::denoise::origin_of(&pts), &nb, 16, 3);
    }

    /// The trial that chooses the first level's cell predicts the pass: over every point of a
    /// one-level cloud with sparse scatter above a surface, the queries it leaves to the tree
    /// are exactly those the pass leaves.
    #[test]
    fn the_trial_counts_the_queries_the_pass_leaves_to_the_tree() {
        let mut r = Rng(5);
        let mut pts = surface(6000, 7);
        for _ in 0..400 {
            pts.push(DVec3::new(r.f() * 10.0, r.f() * 10.0, 2.0 + r.f() * 8.0));
        }
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let base = index.base_level(16).unwrap();
        let all: Vec<u32> = (0..pts.len() as u32).collect();
        let predicted = base.trial(&index.local, &all, 16).tree;
        let (nb, _, work) = index.knn_from(&base, 16, None).unwrap();
        assert_eq!(work.levels, 1, "{work:?}");
        assert!(work.tree_queries >= 300, "{work:?}");
        assert_eq!(predicted as u64, work.tree_queries);
        assert_oracle(&pts, DVec3::ZERO, &nb, 16, 13);
    }

    /// Issue 16: where the points fill space at the subsample's scale (a uniform cube of 100 000
    /// here), the cell extrapolated as on a surface is too small and a block holds about one
    /// query; the trial measures the k-th distances and grows the cell: far fewer cell look-ups,
    /// the same lists. On a surface (20 000 points) the extrapolation holds and the cell stays.
    #[test]
    #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
    fn issue16_the_first_cell_grows_to_the_measured_k_distance_in_a_volume() {
        let mut r = Rng(17);
        let cube: Vec<DVec3> = (0..100_000)
            .map(|_| DVec3::new(r.f(), r.f(), r.f()))
            .collect();
        let index = KnnIndex::build(&cube, DVec3::ZERO).unwrap();
        let (plain, _) = index.estimate_cells(16);
        let grown = index.base_level(16).unwrap();
        let chosen = index.cell.get().unwrap().1;
        assert!(chosen > GROW * plain, "{chosen} against {plain}");
        let ids: Vec<u32> = (0..cube.len() as u32).collect();
        let at_plain = grid::BaseLevel::build(&index.local, ids, plain, index.ties());
        let (a, _, wa) = index.knn_from(&grown, 16, None).unwrap();
        let (b, _, wb) = index.knn_from(&at_plain, 16, None).unwrap();
        assert!(wa.cells * 2 < wb.cells, "{wa:?} against {wb:?}");
        assert_eq!(a.indices, b.indices);
        assert_oracle(&cube, DVec3::ZERO, &a, 16, 1999);

        let flat = surface(20_000, 19);
        let index = KnnIndex::build(&flat, DVec3::ZERO).unwrap();
        let (plain, _) = index.estimate_cells(16);
        index.base_level(16).unwrap();
        assert_eq!(index.cell.get().unwrap().1, plain);
    }

    /// A stack of many coincident points costs one block scan, not one per copy; each copy's
    /// list is the k copies of lowest index.
    #[test]
    #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
    fn duplicate_stacks_are_answered_once() {
        let mut pts = surface(2000, 9);
        pts.extend(std::iter::repeat_n(DVec3::new(5.0, 5.0, 0.5), 20_000));
        let (nb, work) = work_of(&pts, 16);
        assert!(work.candidates < 2_000_000, "{work:?}");
        let first: Vec<u32> = (2000..2016).collect();
        assert_eq!(nb.get(2000), &first[..]);
        assert_eq!(nb.get(21_999), &first[..]);
        assert_oracle(&pts, crate::denoise::origin_of(&pts), &nb, 16, 37);
    }

    /// Issue 15: a coordinate whose square overflows (here 10²⁰⁰) is not indexed, never a
    /// neighbour, and the pass finishes; single queries there are answered by a linear scan.
    #[test]
    fn issue15_huge_coordinate_is_not_indexed() {
        let mut pts = surface(300, 4);
        pts.push(DVec3::new(1e200, 0.0, 0.0));
        pts.push(DVec3::new(f64::MAX, 0.0, 0.0));
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        assert_eq!(index.indexed(), 300);
        let (nb, radii) = index.knn_all(16).unwrap();
        assert!(nb.get(300).is_empty() && nb.get(301).is_empty());
        assert!(radii.iter().all(|r| r.is_finite()));
        assert!((0..300).all(|i| nb.get(i).iter().all(|&j| j < 300)));
        assert_oracle(&pts, DVec3::ZERO, &nb, 16, 1);
        let mut out = Vec::new();
        let r = index.knn_at([1e200, 0.0, 0.0], 4, &mut out);
        assert_eq!(out.len(), 4);
        assert_eq!(r, f64::INFINITY);
        out.clear();
        assert!(index.knn_at([f64::NAN, 0.0, 0.0], 4, &mut out).is_nan());
        assert!(out.is_empty());
        index.within_at([1e200, 0.0, 0.0], f64::INFINITY, &mut out);
        assert_eq!(out.len(), 300);
        out.clear();
        index.within_at([0.0; 3], f64::NAN, &mut out);
        assert!(out.is_empty());
    }

    /// A set flag stops the pass with `Cancelled`; without it the same index answers.
    #[test]
    fn knn_all_stops_when_cancelled() {
        let pts = surface(5000, 2);
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
        assert_eq!(
            with_cancel(&flag, || index.knn_all(16)).unwrap_err(),
            NeighboursError::Cancelled
        );
        flag.store(false, Ordering::Relaxed);
        assert!(with_cancel(&flag, || index.knn_all(16)).is_ok());
    }

    /// Results do not depend on the number of threads.
    #[test]
    fn knn_is_independent_of_the_thread_count() {
        let pts = cluttered(4000, 1e4, 7);
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| index.knn_all_counted(16).unwrap());
        let four = rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap()
            .install(|| index.knn_all_counted(16).unwrap());
        assert_eq!(one.0, four.0);
        assert_eq!(one.1, four.1);
    }
}
