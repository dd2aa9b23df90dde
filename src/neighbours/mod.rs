//! Neighbourhoods: k nearest neighbours, radius balls and mesh k-rings.
//!
//! # Brief overview
//!
//! * [`KnnIndex`] wraps a kiddo k-d tree over positions taken relative to a fixed f64 origin. Its
//!   answers are deterministic: candidates are ordered by (squared distance, index), and a tie at the
//!   k-th place is resolved by a radius query, so that equal distances (duplicate points, grids)
//!   always select the lowest indices. A tile whose points are numbered in global order therefore
//!   picks exactly the neighbours the whole cloud would.
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
mod mesh;

pub use mesh::{MeshAdjacency, RingScratch};

use std::num::NonZeroUsize;

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

/// A k-d tree over a point set, with deterministic tie-breaking by index.
pub struct KnnIndex {
    tree: Tree,
    /// Positions relative to `origin`, as stored in the tree.
    local: Vec<[f64; 3]>,
    origin: DVec3,
    /// Number of finite, indexed points (the tree holds a placeholder when this is 0).
    indexed: usize,
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
        let local: Vec<[f64; 3]> = points.iter().map(|&p| (p - origin).to_array()).collect();
        let entries: Vec<(u32, [f64; 3])> = local
            .iter()
            .enumerate()
            .filter(|(_, p)| p.iter().all(|c| c.is_finite()))
            .map(|(i, &p)| (i as u32, p))
            .collect();
        let tree = if entries.is_empty() {
            Tree::new_from_entries(&[(0, [0.0; 3])])
        } else {
            Tree::new_from_entries(&entries)
        }
        .map_err(|e| NeighboursError::Tree(e.to_string()))?;
        Ok(KnnIndex {
            tree,
            local,
            origin,
            indexed: entries.len(),
        })
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
        let (a, b) = (self.local[i], self.local[j]);
        let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    }

    /// The `k` nearest indexed points to indexed point `i`, itself included (it is at distance 0,
    /// after any lower-indexed duplicates), in ascending (distance, index) order, appended to
    /// `out`. Returns the squared distance of the k-th.
    pub fn knn_of(&self, i: usize, k: usize, out: &mut Vec<u32>) -> f64 {
        self.knn_at(self.local[i], k, out)
    }

    /// The `k` nearest indexed points to `q` (relative to the origin), ascending by
    /// (distance, index), appended to `out`; returns the squared distance of the k-th. Fewer than
    /// `k` are returned only when fewer are indexed.
    pub fn knn_at(&self, q: [f64; 3], k: usize, out: &mut Vec<u32>) -> f64 {
        let n = self.indexed;
        if k == 0 || n == 0 {
            return 0.0;
        }
        // One extra candidate tells whether the k-th place is tied.
        let want = (k + 1).min(n);
        let mut cand: Vec<(f64, u32)> = self
            .tree
            .query(&q)
            .nearest_n::<SquaredEuclidean<f64>>(NonZeroUsize::new(want).expect("want ≥ 1"))
            .execute()
            .into_iter()
            .map(|r| (r.distance, r.item))
            .collect();
        cand.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        if cand.len() > k && cand[k].0 == cand[k - 1].0 {
            // Tie at the boundary: gather every point at that distance and keep the lowest indices.
            let r = cand[k - 1].0;
            cand = self
                .tree
                .query(&q)
                .within::<SquaredEuclidean<f64>>(r)
                .execute()
                .into_iter()
                .map(|r| (r.distance, r.item))
                .collect();
            cand.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        }
        cand.truncate(k);
        out.extend(cand.iter().map(|c| c.1));
        cand.last().map_or(0.0, |c| c.0)
    }

    /// Every indexed point within squared distance `r2` of `q` (inclusive), ascending by index.
    pub fn within_at(&self, q: [f64; 3], r2: f64, out: &mut Vec<u32>) {
        if self.indexed == 0 {
            return;
        }
        let start = out.len();
        out.extend(
            self.tree
                .query(&q)
                .within::<SquaredEuclidean<f64>>(r2)
                .unsorted()
                .execute()
                .into_iter()
                .map(|r| r.item),
        );
        out[start..].sort_unstable();
    }

    /// Relative coordinates of indexed point `i`.
    #[inline]
    pub fn local(&self, i: usize) -> [f64; 3] {
        self.local[i]
    }

    /// k-NN lists of every point in `queries` (indices of indexed points), computed in parallel;
    /// also returns the squared radius of each list. Non-finite queries get empty lists.
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
        // Queries run in Morton order: consecutive queries touch the same leaves, which is worth
        // about 2× over input order on scanner-ordered or shuffled clouds.
        let order = morton_order(&self.local);
        let chunk = 4096;
        let in_order: Vec<(Vec<u32>, Vec<f64>)> = order
            .par_chunks(chunk)
            .map(|ids| {
                let mut lists = Vec::with_capacity(ids.len() * k);
                let mut radii = Vec::with_capacity(ids.len());
                for &i in ids {
                    let i = i as usize;
                    if self.local[i].iter().all(|c| c.is_finite()) {
                        let start = lists.len();
                        let r = self.knn_of(i, k, &mut lists);
                        debug_assert_eq!(lists.len() - start, k);
                        radii.push(r);
                    } else {
                        radii.push(f64::NAN);
                    }
                }
                (lists, radii)
            })
            .collect();
        // Scatter back to input order: finite points own k slots, non-finite ones none.
        let mut offsets = Vec::with_capacity(n + 1);
        offsets.push(0u32);
        let mut total = 0u32;
        for p in &self.local {
            if p.iter().all(|c| c.is_finite()) {
                total += k as u32;
            }
            offsets.push(total);
        }
        let mut indices = vec![0u32; total as usize];
        let mut radii = vec![0.0f64; n];
        for (ids, (lists, rs)) in order.chunks(chunk).zip(&in_order) {
            let mut at = 0;
            for (&i, &r) in ids.iter().zip(rs) {
                let i = i as usize;
                if !r.is_nan() {
                    let o = offsets[i] as usize;
                    indices[o..o + k].copy_from_slice(&lists[at..at + k]);
                    at += k;
                    radii[i] = r;
                }
            }
        }
        Ok((Neighbourhoods { offsets, indices }, radii))
    }
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

/// A permutation of the finite points' indices (non-finite ones last) sorted by 63-bit Morton code
/// over their bounding box, ties by index.
pub fn morton_order(local: &[[f64; 3]]) -> Vec<u32> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in local.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let scale: Vec<f64> = (0..3)
        .map(|a| {
            let e = hi[a] - lo[a];
            if e > 0.0 {
                ((1u64 << 21) - 1) as f64 / e
            } else {
                0.0
            }
        })
        .collect();
    let mut keyed: Vec<(u64, u32)> = local
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            if !p.iter().all(|c| c.is_finite()) {
                return (u64::MAX, i as u32);
            }
            let q = |a: usize| ((p[a] - lo[a]) * scale[a]) as u64;
            (
                spread3(q(0)) | spread3(q(1)) << 1 | spread3(q(2)) << 2,
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
