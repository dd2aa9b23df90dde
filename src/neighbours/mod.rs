//! Neighbourhoods: k nearest neighbours, radius balls and mesh k-rings.
//!
//! # Brief overview
//!
//! * [`KnnIndex`] answers k-NN and radius queries over positions taken relative to a fixed f64
//!   origin: a uniform grid for the all-points k-NN pass (see `grid.rs`), a kiddo k-d tree for
//!   single queries and the grid's rare fallbacks. Answers are exact and deterministic:
//!   candidates are ranked by (squared distance, tie key) with this crate's own distance formula,
//!   where the tie key is the point's *global* index. Equal distances (duplicates, grids) always
//!   select the lowest global indices, so a tile, whatever order it stores its points in, picks
//!   exactly the neighbours the whole cloud would.
//! * [`spatial_order`] is the Morton (Z-curve) permutation kernels use to lay points out so that
//!   neighbours are close in memory.
//! * [`Neighbourhoods`] stores the lists in CSR form; k-NN lists are the special case of equal
//!   lengths.
//! * [`MeshAdjacency`] holds the vertex–vertex edges of a polygon mesh and walks k-rings.
//! * [`brute`] holds the linear-scan oracles the tests compare against.
//!
//! ```text
//!  Neighbourhoods (CSR)
//!  offsets: [0, k, 2k, …]            point i: indices[offsets[i]..offsets[i+1]]
//!  indices: [i0 n1 n2 … | i1 …]      ascending (distance, index) for k-NN
//! ```

pub mod brute;
mod grid;
mod mesh;

pub use mesh::{MeshAdjacency, RingScratch};

use std::num::NonZeroUsize;
use std::sync::OnceLock;

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
    /// Number of finite, indexed points (the tree holds a placeholder when this is 0).
    indexed: usize,
    /// Tie key of each point (its global index); `None` means the local index.
    ties: Option<Vec<u64>>,
}

impl KnnIndex {
    /// Builds the index over `points` (relative coordinates `p − origin`). Non-finite points are
    /// not indexed and never returned.
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
        let indexed = local
            .iter()
            .filter(|p| p.iter().all(|c| c.is_finite()))
            .count();
        Ok(KnnIndex {
            tree: OnceLock::new(),
            local,
            origin,
            indexed,
            ties: None,
        })
    }

    /// The k-d tree over the finite points, built on first use.
    fn tree(&self) -> &Tree {
        self.tree.get_or_init(|| {
            let entries: Vec<(u32, [f64; 3])> = self
                .local
                .iter()
                .enumerate()
                .filter(|(_, p)| p.iter().all(|c| c.is_finite()))
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

    /// Number of finite points in the index.
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
    pub fn knn_at(&self, q: [f64; 3], k: usize, out: &mut Vec<u32>) -> f64 {
        if k == 0 || self.indexed == 0 {
            return 0.0;
        }
        let want = k.min(self.indexed);
        let proposal = self
            .tree()
            .query(&q)
            .nearest_n::<SquaredEuclidean<f64>>(NonZeroUsize::new(want).expect("want ≥ 1"))
            .execute();
        let r = proposal.last().map_or(0.0, |c| c.distance);
        let mut cand: Vec<(u128, u32)> = self
            .tree()
            .query(&q)
            .within::<SquaredEuclidean<f64>>(inflate(r))
            .unsorted()
            .execute()
            .into_iter()
            .map(|c| {
                (
                    grid::rank(
                        grid::dist2(q, self.local[c.item as usize]),
                        self.tie(c.item as usize),
                    ),
                    c.item,
                )
            })
            .collect();
        cand.sort_unstable();
        cand.truncate(want);
        out.extend(cand.iter().map(|c| c.1));
        cand.last().map_or(0.0, |c| grid::rank_distance(c.0))
    }

    /// Every indexed point within squared distance `r2` of `q` (inclusive, by this crate's own
    /// distance), ascending by index.
    pub fn within_at(&self, q: [f64; 3], r2: f64, out: &mut Vec<u32>) {
        if self.indexed == 0 {
            return;
        }
        let start = out.len();
        out.extend(
            self.tree()
                .query(&q)
                .within::<SquaredEuclidean<f64>>(inflate(r2))
                .unsorted()
                .execute()
                .into_iter()
                .map(|r| r.item)
                .filter(|&j| grid::dist2(q, self.local[j as usize]) <= r2),
        );
        out[start..].sort_unstable();
    }

    /// Relative coordinates of indexed point `i`.
    #[inline]
    pub fn local(&self, i: usize) -> [f64; 3] {
        self.local[i]
    }

    /// A grid cell size for [`KnnIndex::knn_all`]: 1.3 × the median k-th neighbour distance,
    /// estimated on an evenly strided subsample of at most 16 384 points (for a stride `s`, a
    /// ball holding k − 1 neighbours holds about (k − 1)/s sample points; below 5, radii are
    /// scaled as on a surface, ∝ √count), and bounded so the grid has at most 2^19 cells per axis. Only speed
    /// depends on it: the grid pass is exact for any cell size.
    fn cell_size(&self, k: usize) -> f64 {
        let finite: Vec<DVec3> = self
            .local
            .iter()
            .filter(|p| p.iter().all(|c| c.is_finite()))
            .map(|&p| DVec3::from_array(p))
            .collect();
        let stride = (finite.len() / 16_384).max(1);
        let sample: Vec<DVec3> = finite.iter().step_by(stride).copied().collect();
        // Lists include the point itself, so a list of k holds k − 1 neighbours.
        let ks = ((k - 1) as f64 / stride as f64).round().max(5.0) as usize + 1;
        let scale = ((k - 1) as f64 / ((ks - 1) * stride) as f64).sqrt();
        let extent = finite
            .iter()
            .fold(0.0f64, |m, p| m.max(p.abs().max_element()));
        let floor = extent / (1u64 << 19) as f64;
        if sample.len() <= ks {
            return floor;
        }
        let Ok(sub) = KnnIndex::build(&sample, DVec3::ZERO) else {
            return floor;
        };
        let step = (sample.len() / 1024).max(1);
        let mut radii: Vec<f64> = (0..sample.len())
            .step_by(step)
            .map(|i| {
                let mut v = Vec::with_capacity(ks);
                sub.knn_of(i, ks, &mut v).sqrt()
            })
            .collect();
        radii.sort_by(f64::total_cmp);
        let median = radii.get(radii.len() / 2).copied().unwrap_or(0.0);
        (1.3 * median * scale).max(floor)
    }

    /// k-NN lists of every indexed point (the point itself included), computed in parallel;
    /// also returns the squared radius of each list. Non-finite points get empty lists.
    ///
    /// # Errors
    /// [`NeighboursError::ZeroK`], [`NeighboursError::TooFewPoints`] when fewer than `k` points are
    /// indexed.
    pub fn knn_all(&self, k: usize) -> Result<(Neighbourhoods, Vec<f64>), NeighboursError> {
        if k == 0 {
            return Err(NeighboursError::ZeroK);
        }
        if self.indexed < k {
            return Err(NeighboursError::TooFewPoints {
                points: self.indexed,
                k,
            });
        }
        let n = self.local.len();
        let cell = self.cell_size(k);
        let cells = if cell > 0.0 && cell.is_finite() {
            grid::all_knn(&self.local, self.ties(), k, cell)
        } else {
            // Every sampled point has k coincident neighbours: let the tree answer all.
            vec![grid::CellAnswers {
                points: (0..n)
                    .filter(|&i| self.local[i].iter().all(|c| c.is_finite()))
                    .map(|i| (i as u32, f64::NAN))
                    .collect(),
                lists: Vec::new(),
            }]
        };
        let mut offsets = Vec::with_capacity(n + 1);
        offsets.push(0u32);
        let mut total = 0u32;
        let mut listed = Vec::with_capacity(n);
        for (i, p) in self.local.iter().enumerate() {
            if p.iter().all(|c| c.is_finite()) {
                total += k as u32;
                listed.push(i as u32);
            }
            offsets.push(total);
        }
        // Where each point's answer is: (cell, offset into its lists), or (MAX, fallback slot).
        const TREE: u32 = u32::MAX;
        let mut loc = vec![(TREE, 0u32); n];
        let mut fallback = Vec::new();
        for (ci, c) in cells.iter().enumerate() {
            let mut at = 0u32;
            for &(i, r) in &c.points {
                if r.is_nan() {
                    loc[i as usize] = (TREE, fallback.len() as u32);
                    fallback.push(i);
                } else {
                    loc[i as usize] = (ci as u32, at);
                    at += k as u32;
                }
            }
        }
        // Sparse regions and outliers go to the tree, in parallel.
        let resolved: Vec<(Vec<u32>, f64)> = fallback
            .par_iter()
            .map(|&i| {
                let mut v = Vec::with_capacity(k);
                let r = self.knn_of(i as usize, k, &mut v);
                (v, r)
            })
            .collect();
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
        for (&i, (_, r)) in fallback.iter().zip(&resolved) {
            radii[i as usize] = *r;
        }
        Ok((Neighbourhoods { offsets, indices }, radii))
    }
}

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

/// The indices of `points` in Morton (Z-curve) order over their bounding box (63-bit codes, ties by
/// index), non-finite points last. Kernels that visit points in this order touch neighbouring
/// data in neighbouring memory; on shuffled input that halves the time of the normal and solve
/// passes.
pub fn spatial_order(points: &[DVec3]) -> Vec<u32> {
    let bounds = crate::points::Aabb::from_points(points);
    let size = bounds.size();
    let scale = |e: f64| {
        if e > 0.0 {
            ((1u64 << 21) - 1) as f64 / e
        } else {
            0.0
        }
    };
    let s = [scale(size.x), scale(size.y), scale(size.z)];
    let mut keyed: Vec<(u64, u32)> = points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            if !p.is_finite() {
                return (u64::MAX, i as u32);
            }
            let d = *p - bounds.min;
            let q = |v: f64, s: f64| (v * s) as u64;
            (
                spread3(q(d.x, s[0])) | spread3(q(d.y, s[1])) << 1 | spread3(q(d.z, s[2])) << 2,
                i as u32,
            )
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
        fn knn_with_ties_matches_brute_force(seed in 0u64..10_000, n in 20usize..300,
                                             k in 1usize..20) {
            let pts = cloud(seed, n, true);
            let mut ties: Vec<u64> = (0..n as u64).map(|i| i * 7919 % 100_003).collect();
            ties.reverse();
            let index = KnnIndex::build_with_ties(&pts, DVec3::ZERO, ties.clone()).unwrap();
            let (nb, _) = index.knn_all(k.min(n)).unwrap();
            for i in 0..n {
                let want = brute::knn_with_ties(&pts, &ties, pts[i], k.min(n));
                prop_assert_eq!(nb.get(i), &want[..], "point {}", i);
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
}
