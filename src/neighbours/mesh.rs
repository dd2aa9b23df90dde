//! Vertex adjacency of a polygon mesh and k-ring walks.
//!
//! A ring does not walk on through a **hub**, a vertex with more than [`HUB_VALENCE`] neighbours
//! (the apex of a triangle fan, the pole of a UV sphere with many segments): the hub joins the
//! ring, its neighbours do not come with it. Otherwise the 2-ring of each of a fan's N rim
//! vertices would hold every rim vertex, N² in all (issue 51: a 833 KB OFF fan took 120 s and
//! 2 GiB). A ring centred on a hub still holds the hub's neighbours. Meshes without hubs get the
//! rings they always had.

use super::NeighboursError;
use crate::points::Faces;

/// The most neighbours (or incident faces) a vertex may have and still lend them to the
/// neighbourhoods of others; the vertices of ordinary meshes have 3 to 20.
pub const HUB_VALENCE: usize = 64;

/// Vertex–vertex adjacency (unique, ascending) in CSR form, built from polygon edges.
#[derive(Debug, Clone, Default)]
pub struct MeshAdjacency {
    offsets: Vec<u32>,
    neighbours: Vec<u32>,
}

/// Per-thread scratch for [`MeshAdjacency::ring`]: a visit stamp per vertex.
#[derive(Debug, Clone)]
pub struct RingScratch {
    stamp: Vec<u32>,
    generation: u32,
}

impl RingScratch {
    /// Scratch for a mesh of `n` vertices.
    pub fn new(n: usize) -> RingScratch {
        RingScratch {
            stamp: vec![0; n],
            generation: 0,
        }
    }
}

impl MeshAdjacency {
    /// Builds the adjacency of `n` vertices from the edges of `faces` (consecutive corners,
    /// wrapping around). Repeated corners (degenerate edges) are skipped.
    ///
    /// # Errors
    /// [`NeighboursError::FaceIndex`] for an index ≥ `n`.
    pub fn build(n: usize, faces: &Faces) -> Result<MeshAdjacency, NeighboursError> {
        for (fi, f) in faces.iter().enumerate() {
            if let Some(&bad) = f.iter().find(|&&a| a as usize >= n) {
                return Err(NeighboursError::FaceIndex {
                    face: fi,
                    vertex: bad,
                    vertices: n,
                });
            }
        }
        let mut degree = vec![0u32; n + 1];
        for f in faces.iter() {
            for (c, &a) in f.iter().enumerate() {
                let b = f[(c + 1) % f.len()];
                if a != b && f.len() > 1 {
                    degree[a as usize] += 1;
                    degree[b as usize] += 1;
                }
            }
        }
        // Prefix sums give each vertex its slot range; fill, then sort and deduplicate in place.
        let mut offsets = vec![0u32; n + 1];
        for v in 0..n {
            offsets[v + 1] = offsets[v] + degree[v];
        }
        let mut fill = offsets.clone();
        let mut slots = vec![0u32; offsets[n] as usize];
        for f in faces.iter() {
            for (c, &a) in f.iter().enumerate() {
                let b = f[(c + 1) % f.len()];
                if a != b && f.len() > 1 {
                    slots[fill[a as usize] as usize] = b;
                    fill[a as usize] += 1;
                    slots[fill[b as usize] as usize] = a;
                    fill[b as usize] += 1;
                }
            }
        }
        let mut out_offsets = Vec::with_capacity(n + 1);
        let mut neighbours = Vec::with_capacity(slots.len() / 2);
        out_offsets.push(0u32);
        for v in 0..n {
            let list = &mut slots[offsets[v] as usize..offsets[v + 1] as usize];
            list.sort_unstable();
            let mut last = None;
            for &u in list.iter() {
                if Some(u) != last {
                    neighbours.push(u);
                    last = Some(u);
                }
            }
            out_offsets.push(neighbours.len() as u32);
        }
        Ok(MeshAdjacency {
            offsets: out_offsets,
            neighbours,
        })
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// True without vertices.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The vertices sharing an edge with `v`, ascending.
    #[inline]
    pub fn neighbours(&self, v: usize) -> &[u32] {
        &self.neighbours[self.offsets[v] as usize..self.offsets[v + 1] as usize]
    }

    /// Unique undirected edges `(a, b)` with `a < b`, ascending.
    pub fn edges(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        (0..self.len()).flat_map(move |a| {
            self.neighbours(a)
                .iter()
                .filter(move |&&b| b as usize > a)
                .map(move |&b| (a as u32, b))
        })
    }

    /// The k-ring `N_k(v)`: `v` itself, then every vertex within `k` edges, in breadth-first order
    /// (ring by ring, each ring in the order its vertices are reached from ascending lists),
    /// walking on through no hub but `v` itself (the [module overview](self)). Replaces the
    /// contents of `out`.
    pub fn ring(&self, v: usize, k: usize, scratch: &mut RingScratch, out: &mut Vec<u32>) {
        if scratch.stamp.len() < self.len() {
            scratch.stamp.resize(self.len(), 0);
        }
        scratch.generation = scratch.generation.wrapping_add(1);
        if scratch.generation == 0 {
            scratch.stamp.fill(0);
            scratch.generation = 1;
        }
        let g = scratch.generation;
        out.clear();
        out.push(v as u32);
        scratch.stamp[v] = g;
        let mut begin = 0;
        for _ in 0..k {
            let end = out.len();
            for i in begin..end {
                let w = out[i] as usize;
                if i > 0 && self.neighbours(w).len() > HUB_VALENCE {
                    continue;
                }
                for &u in self.neighbours(w) {
                    if scratch.stamp[u as usize] != g {
                        scratch.stamp[u as usize] = g;
                        out.push(u);
                    }
                }
            }
            if out.len() == end {
                break;
            }
            begin = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A strip of quads split into triangles: vertices 0..2n on two rows.
    fn strip(n: u32) -> Faces {
        let mut f = Faces::new();
        for i in 0..n - 1 {
            f.push(&[i, i + 1, n + i]);
            f.push(&[i + 1, n + i + 1, n + i]);
        }
        f
    }

    #[test]
    fn adjacency_is_symmetric_unique_and_sorted() {
        let f = strip(5);
        let a = MeshAdjacency::build(10, &f).unwrap();
        for v in 0..10 {
            let l = a.neighbours(v);
            assert!(l.windows(2).all(|w| w[0] < w[1]));
            for &u in l {
                assert!(a.neighbours(u as usize).contains(&(v as u32)));
            }
        }
        assert_eq!(a.neighbours(0), &[1, 5]);
        // 4 top + 4 bottom + 5 rungs + 4 diagonals.
        assert_eq!(a.edges().count(), 17);
    }

    /// A fan: apex 0, rim 1..=n, triangles (0, i, i + 1).
    fn fan(n: u32) -> Faces {
        let mut f = Faces::new();
        for i in 1..n {
            f.push(&[0, i, i + 1]);
        }
        f
    }

    #[test]
    fn issue51_rings_do_not_walk_through_a_hub() {
        let n = 5000;
        let a = MeshAdjacency::build(n as usize + 1, &fan(n)).unwrap();
        let mut s = RingScratch::new(n as usize + 1);
        let mut out = Vec::new();
        // A rim vertex: the apex and its rim neighbours, not the whole rim.
        a.ring(100, 2, &mut s, &mut out);
        out.sort();
        assert_eq!(out, vec![0, 98, 99, 100, 101, 102]);
        // The apex's own ring holds its neighbours.
        a.ring(0, 1, &mut s, &mut out);
        assert_eq!(out.len(), n as usize + 1);
        // A vertex of ordinary valence lends its neighbours as before.
        let small = MeshAdjacency::build(11, &fan(10)).unwrap();
        small.ring(5, 2, &mut s, &mut out);
        assert_eq!(out.len(), 11);
    }

    #[test]
    fn rings_grow_breadth_first() {
        let a = MeshAdjacency::build(10, &strip(5)).unwrap();
        let mut s = RingScratch::new(10);
        let mut out = Vec::new();
        a.ring(0, 0, &mut s, &mut out);
        assert_eq!(out, vec![0]);
        a.ring(0, 1, &mut s, &mut out);
        assert_eq!(out, vec![0, 1, 5]);
        a.ring(0, 2, &mut s, &mut out);
        let mut sorted = out.clone();
        sorted.sort();
        assert_eq!(sorted, vec![0, 1, 2, 5, 6]);
        a.ring(0, 20, &mut s, &mut out);
        assert_eq!(out.len(), 10);
    }

    #[test]
    fn bad_index_and_degenerate_faces() {
        let mut f = Faces::new();
        f.push(&[0, 1, 7]);
        assert!(matches!(
            MeshAdjacency::build(3, &f),
            Err(NeighboursError::FaceIndex { vertex: 7, .. })
        ));
        let mut f = Faces::new();
        f.push(&[0, 0, 0]);
        f.push(&[1, 1, 2]);
        let a = MeshAdjacency::build(4, &f).unwrap();
        assert!(a.neighbours(0).is_empty());
        assert_eq!(a.neighbours(1), &[2]);
        assert!(a.neighbours(3).is_empty());
    }
}
