//! Pieces the mesh and point operators share: why a point stayed put ([`stay`]), merging a
//! pass's results ([`merge_step`]), the faces around each vertex ([`FaceTopology`]), the mean
//! edge length of a mesh ([`mean_edge_length`]), the median of a k-NN list's values
//! ([`median`]) and which points a pass computes ([`Within`]). `qem`, `filtered`, `bilateral`, `guarded` and
//! `cloud` use them; nothing here uses those files.

use glam::DVec3;
use rayon::prelude::*;

use crate::geometry::ExactSum;
use crate::neighbours::{HUB_VALENCE, MeshAdjacency};
use crate::points::Faces;

/// Why a point stayed where it was in a pass (bit flags, or-ed over passes).
pub mod stay {
    /// The summed quadric was singular, or the solve not finite.
    pub const SINGULAR: u8 = 1;
    /// The minimiser lay farther than the point's neighbourhood reaches (isolated points and
    /// outliers, whose planes all belong to a distant surface).
    pub const FAR: u8 = 2;
    /// The guarded step's total displacement was clamped to the bound of the local noise (or to
    /// `--max-move`).
    pub const BOUNDED: u8 = 4;
    /// Fewer than k points lie within the isolation radius: the point keeps its input position
    /// ([`crate::denoise::isolation`]).
    pub const ISOLATED: u8 = 8;
    /// Not of a class `--classes` names: the point keeps its input position and still serves as
    /// a neighbour.
    pub const HELD: u8 = 16;
}

/// Which points a per-point pass computes: all of them, or (a tile's run, where only the wanted
/// points' results are kept) those within some hops of a wanted point. A pass whose result a
/// wanted point reads through `h` more hops is computed where the hop count is at most `h`; the
/// others get a placeholder that nothing wanted reads (docs/DECISIONS.md, "A tile computes only
/// what its owned results depend on").
#[derive(Debug, Clone, Copy)]
pub enum Within<'a> {
    /// Every point.
    All,
    /// The points whose hop count from a wanted point (`u8::MAX`: farther than counted) is at
    /// most the second value.
    Hops(&'a [u8], usize),
}

impl Within<'_> {
    /// True when point `i` is computed.
    #[inline]
    pub fn has(&self, i: usize) -> bool {
        match self {
            Within::All => true,
            Within::Hops(depth, most) => (depth[i] as usize) <= *most,
        }
    }

    /// The points within `by` hops more: what a pass must compute for one that reads its list
    /// members' results to be computed here.
    pub fn wider(self, by: usize) -> Self {
        match self {
            Within::All => Within::All,
            Within::Hops(depth, most) => Within::Hops(depth, most + by),
        }
    }
}

/// [`NeighboursError::Cancelled`] once the cancel flag installed on this thread
/// ([`crate::neighbours::with_cancel`]) is set: the mesh operators check it between passes (each
/// pass's work is bounded by the mesh's size: no neighbourhood is larger than a hub allows).
///
/// # Errors
/// The cancellation.
pub fn check_cancel() -> Result<(), super::DenoiseError> {
    if crate::neighbours::cancel_requested() {
        Err(crate::neighbours::NeighboursError::Cancelled.into())
    } else {
        Ok(())
    }
}

/// Splits a pass's results into positions, or-ing its [`stay`] flags into `stayed`.
pub fn merge_step(step: Vec<(DVec3, u8)>, stayed: &mut [u8]) -> Vec<DVec3> {
    step.into_iter()
        .zip(stayed.iter_mut())
        .map(|((p, s), acc)| {
            *acc |= s;
            p
        })
        .collect()
}

/// Faces around each vertex and faces sharing a vertex with each face, in CSR form. A face's
/// list holds at most 1 + 3 × [`HUB_VALENCE`] faces, whatever the mesh.
#[derive(Debug, Clone)]
pub struct FaceTopology {
    vertex_offsets: Vec<u32>,
    vertex_faces: Vec<u32>,
    face_offsets: Vec<u32>,
    face_neighbours: Vec<u32>,
}

impl FaceTopology {
    /// Builds the topology of `faces` over `n` vertices (indices already validated).
    pub fn build(n: usize, faces: &Faces) -> FaceTopology {
        let mut count = vec![0u32; n + 1];
        for f in faces.iter() {
            for &v in f {
                count[v as usize + 1] += 1;
            }
        }
        for v in 0..n {
            count[v + 1] += count[v];
        }
        let vertex_offsets = count.clone();
        let mut fill = count;
        let mut vertex_faces = vec![0u32; vertex_offsets[n] as usize];
        for (fi, f) in faces.iter().enumerate() {
            for &v in f {
                vertex_faces[fill[v as usize] as usize] = fi as u32;
                fill[v as usize] += 1;
            }
        }
        // A hub lends no faces (neighbours::HUB_VALENCE): through the apex of a fan every face
        // would share a vertex with every other, N² in all (issue 51).
        let around = |v: usize| {
            let fs = &vertex_faces[vertex_offsets[v] as usize..vertex_offsets[v + 1] as usize];
            if fs.len() > HUB_VALENCE { &[][..] } else { fs }
        };
        let lists: Vec<Vec<u32>> = (0..faces.len())
            .into_par_iter()
            .map(|fi| {
                let mut l: Vec<u32> = faces
                    .face(fi)
                    .iter()
                    .flat_map(|&v| around(v as usize).iter().copied())
                    .chain([fi as u32])
                    .collect();
                l.sort_unstable();
                l.dedup();
                l
            })
            .collect();
        let mut face_offsets = Vec::with_capacity(faces.len() + 1);
        face_offsets.push(0u32);
        let mut face_neighbours = Vec::new();
        for l in lists {
            face_neighbours.extend_from_slice(&l);
            face_offsets.push(face_neighbours.len() as u32);
        }
        FaceTopology {
            vertex_offsets,
            vertex_faces,
            face_offsets,
            face_neighbours,
        }
    }

    /// The faces around vertex `v`, ascending.
    #[inline]
    pub fn faces_of(&self, v: usize) -> &[u32] {
        &self.vertex_faces[self.vertex_offsets[v] as usize..self.vertex_offsets[v + 1] as usize]
    }

    /// The faces sharing a vertex with face `f` (itself included), ascending; a hub's faces
    /// (more than [`HUB_VALENCE`] around it) are not shared through it.
    #[inline]
    pub fn neighbours_of(&self, f: usize) -> &[u32] {
        &self.face_neighbours[self.face_offsets[f] as usize..self.face_offsets[f + 1] as usize]
    }
}

/// Mean length of the unique undirected edges, summed exactly.
pub fn mean_edge_length(pos: &[DVec3], adjacency: &MeshAdjacency) -> f64 {
    adjacency
        .edges()
        .map(|(a, b)| (pos[a as usize] - pos[b as usize]).length())
        .collect::<ExactSum>()
        .mean()
}

/// The median of `xs`: its `len / 2`-th smallest value by [`f64::total_cmp`] (the upper median
/// for even counts); 0 when empty. Reorders `xs`.
///
/// The same value as `*xs.select_nth_unstable_by(len / 2, f64::total_cmp).1`. For 9 to 16 values
/// (the default list, capped lists) it sorts their `total_cmp` keys with a fixed network of
/// compare-exchanges:
/// hand-rolled because std's selection is an insertion sort there whose branches mispredict on
/// every list (3 % of the default operator's time in the normal filter's range widths, perf on
/// 1 M points; `benches/kernels.rs`, group `median`).
pub fn median(xs: &mut [f64]) -> f64 {
    if (9..=16).contains(&xs.len()) {
        return median16(xs);
    }
    if xs.is_empty() {
        return 0.0;
    }
    let m = xs.len() / 2;
    *xs.select_nth_unstable_by(m, f64::total_cmp).1
}

/// The `total_cmp` key of `x`: its bits with the magnitude flipped for negative values, so keys
/// compare as signed integers exactly as `f64::total_cmp` compares the values (and map back).
#[inline(always)]
fn total_key(x: f64) -> i64 {
    let b = x.to_bits() as i64;
    b ^ (((b >> 63) as u64) >> 1) as i64
}

/// Batcher's odd–even merge sort on `N` inputs as a list of compare-exchanges `(lo, hi)`:
/// `M` must be its length (63 for 16).
const fn odd_even_merge_network<const N: usize, const M: usize>() -> [(u8, u8); M] {
    let mut net = [(0u8, 0u8); M];
    let mut at = 0;
    let mut p = 1;
    while p < N {
        let mut k = p;
        while k >= 1 {
            let mut j = k % p;
            while j + k < N {
                let mut i = 0;
                while i < k && i + j + k < N {
                    if (i + j) / (2 * p) == (i + j + k) / (2 * p) {
                        net[at] = ((i + j) as u8, (i + j + k) as u8);
                        at += 1;
                    }
                    i += 1;
                }
                j += 2 * k;
            }
            k /= 2;
        }
        p *= 2;
    }
    assert!(at == M, "network length");
    net
}

const NETWORK16: [(u8, u8); 63] = odd_even_merge_network::<16, 63>();

/// [`median`] of 1 to 16 values: branch-free. Missing values are padded with the largest key,
/// which leaves every order statistic below `len` as it was.
fn median16(xs: &[f64]) -> f64 {
    let mut v = [i64::MAX; 16];
    for (k, &x) in v.iter_mut().zip(xs) {
        *k = total_key(x);
    }
    // Unrolled with constant indices, so the 16 keys live in registers: a loop over the table
    // indexes memory, and each compare-exchange waits on the previous one's store (about 1000
    // instructions a call against about 430; callgrind, 300 k default run).
    macro_rules! exchanges {
        ($($i:literal)*) => {$({
            const A: usize = NETWORK16[$i].0 as usize;
            const B: usize = NETWORK16[$i].1 as usize;
            let (x, y) = (v[A], v[B]);
            v[A] = x.min(y);
            v[B] = x.max(y);
        })*};
    }
    exchanges!(0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 23 24 25 26 27 28 29 30 31 32 33 34 35 36 37 38 39 40 41 42 43 44 45 46 47 48 49 50 51 52 53 54 55 56 57 58 59 60 61 62);
    // The key transform is an involution.
    f64::from_bits(total_key(f64::from_bits(v[xs.len() / 2] as u64)) as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue51_a_fans_faces_share_no_faces_through_its_apex() {
        // Apex 0, rim 1..=n, triangles (0, i, i + 1): every face touches the apex.
        let n = 4000u32;
        let mut faces = Faces::new();
        for i in 1..n {
            faces.push(&[0, i, i + 1]);
        }
        let t = FaceTopology::build(n as usize + 1, &faces);
        // Face i shares its rim vertices with faces i − 1 and i + 1 only.
        assert_eq!(t.neighbours_of(100), &[99, 100, 101]);
        assert_eq!(t.neighbours_of(0), &[0, 1]);
        let longest = (0..faces.len()).map(|f| t.neighbours_of(f).len()).max();
        assert_eq!(longest, Some(3));
        // The apex still has every face around it (the update sums their planes).
        assert_eq!(t.faces_of(0).len(), faces.len());
    }

    #[test]
    fn the_median_is_the_selected_value_for_every_length_and_value() {
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let specials = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            -f64::NAN,
            f64::MIN_POSITIVE,
            5e-324,
            // The largest key, which pads short lists.
            f64::from_bits(u64::MAX >> 1),
        ];
        for round in 0..20_000 {
            let len = if round % 2 == 0 {
                16
            } else {
                (next() % 20) as usize
            };
            let mut xs: Vec<f64> = (0..len)
                .map(|_| match next() % 4 {
                    0 => specials[(next() % specials.len() as u64) as usize],
                    // Few distinct values: ties.
                    1 => (next() % 4) as f64 * 0.25,
                    _ => f64::from_bits(next()),
                })
                .collect();
            let mut want = xs.clone();
            let expect = if want.is_empty() {
                0.0
            } else {
                let m = want.len() / 2;
                *want.select_nth_unstable_by(m, f64::total_cmp).1
            };
            assert_eq!(median(&mut xs).to_bits(), expect.to_bits(), "{want:?}");
        }
    }
}
