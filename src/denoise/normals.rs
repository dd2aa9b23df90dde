//! Normals: mesh face and vertex normals, PCA point normals.

use glam::DVec3;
use rayon::prelude::*;

use super::NormalWeighting;
use super::common::{Within, median};
use crate::geometry::{exp, pca_normal};
use crate::neighbours::Neighbourhoods;
use crate::points::Faces;

/// Unnormalised face normal: `(v1 − v0) × (v2 − v0)` for a triangle, the sum of the fan
/// triangles' cross products for a polygon (twice the area vector). Zero for zero-area faces.
#[inline]
pub fn face_cross(pos: &[DVec3], face: &[u32]) -> DVec3 {
    let mut n = DVec3::ZERO;
    if face.len() >= 3 {
        let p0 = pos[face[0] as usize];
        for i in 1..face.len() - 1 {
            n += (pos[face[i] as usize] - p0).cross(pos[face[i + 1] as usize] - p0);
        }
    }
    n
}

/// Unit face normals (zero for zero-area faces) and the number of zero-area faces.
pub fn face_normals(pos: &[DVec3], faces: &Faces) -> (Vec<DVec3>, u64) {
    let normals: Vec<DVec3> = (0..faces.len())
        .into_par_iter()
        .with_min_len(4096)
        .map(|f| face_cross(pos, faces.face(f)).normalize_or_zero())
        .collect();
    let zero = normals.iter().filter(|n| **n == DVec3::ZERO).count() as u64;
    (normals, zero)
}

/// Mesh vertex normals from the incident faces.
#[derive(Debug, Clone)]
pub struct VertexNormals {
    /// Unit normal per vertex; zero where the faces' normals cancel or there is no face.
    pub normals: Vec<DVec3>,
    /// Faces with zero area.
    pub zero_area_faces: u64,
    /// Vertices that no face references.
    pub unreferenced: u64,
}

/// Vertex normals as `weighting` says: the normalised sum of the incident faces' cross products
/// (`Area`) or of their unit normals (`Mean`). Faces are accumulated in face order, so the sums are
/// the same bits on every run.
pub fn vertex_normals(pos: &[DVec3], faces: &Faces, weighting: NormalWeighting) -> VertexNormals {
    let mut acc = vec![DVec3::ZERO; pos.len()];
    let mut referenced = vec![false; pos.len()];
    let mut zero_area = 0u64;
    for f in faces.iter() {
        let c = face_cross(pos, f);
        if c == DVec3::ZERO {
            zero_area += 1;
        }
        let n = match weighting {
            NormalWeighting::Area => c,
            NormalWeighting::Mean => c.normalize_or_zero(),
        };
        for &v in f {
            acc[v as usize] += n;
            referenced[v as usize] = true;
        }
    }
    let normals = acc.into_iter().map(DVec3::normalize_or_zero).collect();
    VertexNormals {
        normals,
        zero_area_faces: zero_area,
        unreferenced: referenced.iter().filter(|r| !**r).count() as u64,
    }
}

/// PCA normal of every point over its neighbour list (coordinates taken relative to the point).
/// Returns the unit normals (zero where the neighbourhood is coincident, collinear or has fewer than
/// three points) and the number of such degenerate neighbourhoods among finite points.
pub fn pca_normals(pos: &[DVec3], lists: &Neighbourhoods) -> (Vec<DVec3>, u64) {
    let normals: Vec<DVec3> = (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let v = pos[i];
            let list = lists.get(i);
            pca_normal(list.iter().map(|&u| pos[u as usize] - v)).map_or(DVec3::ZERO, |f| f.normal)
        })
        .collect();
    let degenerate = normals
        .iter()
        .zip(pos)
        .filter(|(n, p)| **n == DVec3::ZERO && p.is_finite())
        .count() as u64;
    (normals, degenerate)
}

/// `iterations` bilateral filter passes over point normals on the k-NN graph. Each normal becomes
/// the normalised sum of its neighbours' normals (turned to agree with its own: PCA normals have
/// no sign) weighted by distance (σs = the point's own k-NN radius, `radii` squared) and by
/// normal difference (σr = the median difference over its list in the input normals, at least
/// `sigma_r_floor`: a local width, so no global statistic is needed and tiles reproduce it
/// exactly). Points without a normal keep none.
pub fn filter_point_normals(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    radii: &[f64],
    normals: &[DVec3],
    sigma_r_floor: f64,
    iterations: usize,
) -> Vec<DVec3> {
    filter_point_normals_within(
        pos,
        lists,
        radii,
        normals,
        (sigma_r_floor, iterations),
        Within::All,
    )
}

/// [`filter_point_normals`] where the output is read only at the points `within` selects: each
/// iteration reads the previous one's normals of the list members, so iteration `t` of `T`
/// (from 0) is computed `T − 1 − t` hops wider, and the weights as wide as the first. Elsewhere
/// a point keeps its input normal, which nothing that reads the selected points sees.
pub fn filter_point_normals_within(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    radii: &[f64],
    normals: &[DVec3],
    (sigma_r_floor, iterations): (f64, usize),
    within: Within,
) -> Vec<DVec3> {
    if iterations == 0 {
        return normals.to_vec();
    }
    let widest = within.wider(iterations - 1);
    // Positions are fixed while the normals are filtered: the spatial weights (one per list
    // entry) and the range width of each point (the median normal difference over its list in
    // the input normals, at least `sigma_r_floor`) are computed once, in one pass. A point
    // without a normal keeps none whatever its list holds, so its weights are never read and
    // not computed.
    let mut spatial = vec![0.0f64; lists.indices.len()];
    let mut range = vec![0.0f64; pos.len()];
    let floor2 = sigma_r_floor * sigma_r_floor;
    list_blocks(&lists.offsets, &mut spatial, &mut range)
        .into_par_iter()
        .for_each_init(Vec::new, |diffs, (start, ws, rs)| {
            let mut at = 0;
            for (i, r) in (start..).zip(rs.iter_mut()) {
                let list = lists.get(i);
                let w = &mut ws[at..at + list.len()];
                at += list.len();
                if normals[i] == DVec3::ZERO || !widest.has(i) {
                    continue;
                }
                filter_weights(pos, list, i, radii[i], w);
                *r = filter_range(normals, list, i, floor2, diffs);
            }
        });
    // Two buffers, swapped between iterations (each reads the previous one only).
    let mut n = normals.to_vec();
    let mut next = vec![DVec3::ZERO; n.len()];
    for t in 0..iterations {
        let here = within.wider(iterations - 1 - t);
        next.par_iter_mut()
            .enumerate()
            .with_min_len(1024)
            .for_each(|(i, out)| {
                if !here.has(i) {
                    *out = n[i];
                    return;
                }
                let (a, b) = (lists.offsets[i] as usize, lists.offsets[i + 1] as usize);
                *out = filter_step(&n, &lists.indices[a..b], &spatial[a..b], range[i], i);
            });
        std::mem::swap(&mut n, &mut next);
    }
    n
}

/// The spatial weights of point `i`'s list entries for the normal filter
/// ([`filter_point_normals`]), written to `out` (one per member): a Gaussian of the distance,
/// σs² = half the list's squared radius `radius2`.
#[inline]
pub fn filter_weights(pos: &[DVec3], list: &[u32], i: usize, radius2: f64, out: &mut [f64]) {
    let ss2 = 2.0 * radius2.max(f64::MIN_POSITIVE);
    for (w, &u) in out.iter_mut().zip(list) {
        *w = gauss(-(pos[i] - pos[u as usize]).length_squared() / ss2);
    }
}

/// The range width of point `i` for the normal filter: twice the median squared difference
/// between its normal and its members' (turned to agree with it), at least `floor2` (the
/// squared `sigma_r_floor`); `diffs` is scratch.
#[inline]
pub fn filter_range(
    normals: &[DVec3],
    list: &[u32],
    i: usize,
    floor2: f64,
    diffs: &mut Vec<f64>,
) -> f64 {
    let ni = normals[i];
    diffs.clear();
    diffs.extend(list.iter().map(|&u| {
        let nu = normals[u as usize];
        let nu = if nu.dot(ni) < 0.0 { -nu } else { nu };
        (ni - nu).length_squared()
    }));
    2.0 * median(diffs).max(floor2)
}

/// One filter iteration at point `i`: the normalised sum of its members' normals in `n` (the
/// iteration before), weighted by `weights` ([`filter_weights`]) and by their difference to its
/// own over `range` ([`filter_range`]). A point without a normal keeps none; one whose sum
/// vanishes keeps its own.
#[inline]
pub fn filter_step(n: &[DVec3], list: &[u32], weights: &[f64], range: f64, i: usize) -> DVec3 {
    let ni = n[i];
    if ni == DVec3::ZERO {
        return ni;
    }
    let mut s = DVec3::ZERO;
    for (&u, &w) in list.iter().zip(weights) {
        let nu = n[u as usize];
        let nu = if nu.dot(ni) < 0.0 { -nu } else { nu };
        if nu == DVec3::ZERO {
            continue;
        }
        let wr = gauss(-(ni - nu).length_squared() / range);
        s += nu * (w * wr);
    }
    let s = s.normalize_or_zero();
    if s == DVec3::ZERO { ni } else { s }
}

/// [`exp`]`(x)`, with `x = ±0` (a point against itself, equal normals) answered without the call:
/// `exp(±0) = 1` exactly, so the result is the same bits.
#[inline]
fn gauss(x: f64) -> f64 {
    if x == 0.0 { 1.0 } else { exp(x) }
}

/// Points per block of the parallel passes over lists.
const BLOCK: usize = 1024;

/// Splits per-entry values (`entries`, laid out as the lists' `offsets` say) and per-point values
/// into blocks of [`BLOCK`] points: (first point, its entries, its points' values).
fn list_blocks<'a>(
    offsets: &[u32],
    mut entries: &'a mut [f64],
    mut points: &'a mut [f64],
) -> Vec<(usize, &'a mut [f64], &'a mut [f64])> {
    let n = points.len();
    let mut out = Vec::with_capacity(n.div_ceil(BLOCK));
    let mut start = 0;
    while start < n {
        let end = (start + BLOCK).min(n);
        let len = (offsets[end] - offsets[start]) as usize;
        let (e, rest_e) = std::mem::take(&mut entries).split_at_mut(len);
        let (p, rest_p) = std::mem::take(&mut points).split_at_mut(end - start);
        out.push((start, e, p));
        entries = rest_e;
        points = rest_p;
        start = end;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn area_and_mean_vertex_normals() {
        // Two triangles folded along the x axis: a large one in z = 0 and a small one in y = 0.
        let pos = vec![
            DVec3::ZERO,
            DVec3::X,
            DVec3::new(0.0, 10.0, 0.0),
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(5.0, 5.0, 5.0),
        ];
        let faces = Faces::from_triangles(&[[0, 1, 2], [0, 3, 1]]);
        let area = vertex_normals(&pos, &faces, NormalWeighting::Area);
        let mean = vertex_normals(&pos, &faces, NormalWeighting::Mean);
        // Face normals: (0, 0, 10) and (0, -1, 0) unnormalised.
        assert!((area.normals[0] - DVec3::new(0.0, -1.0, 10.0).normalize()).length() < 1e-15);
        assert!((mean.normals[0] - DVec3::new(0.0, -1.0, 1.0).normalize()).length() < 1e-15);
        assert_eq!(area.normals[4], DVec3::ZERO);
        assert_eq!(area.unreferenced, 1);
        assert_eq!(area.zero_area_faces, 0);
        let degenerate = Faces::from_triangles(&[[0, 1, 1]]);
        assert_eq!(
            vertex_normals(&pos, &degenerate, NormalWeighting::Area).zero_area_faces,
            1
        );
        let (fnorm, zero) = face_normals(&pos, &faces);
        assert_eq!((fnorm[0], zero), (DVec3::Z, 0));
    }
    /// The filter as first written (spatial weights collected per entry, a fresh buffer per
    /// iteration, every point's weights computed): the reference the faster one must match to
    /// the bit.
    fn filter_reference(
        pos: &[DVec3],
        lists: &Neighbourhoods,
        radii: &[f64],
        normals: &[DVec3],
        sigma_r_floor: f64,
        iterations: usize,
    ) -> Vec<DVec3> {
        let spatial: Vec<f64> = (0..pos.len())
            .flat_map(|i| {
                let ss2 = 2.0 * radii[i].max(f64::MIN_POSITIVE);
                lists
                    .get(i)
                    .iter()
                    .map(move |&u| exp(-(pos[i] - pos[u as usize]).length_squared() / ss2))
            })
            .collect();
        let range: Vec<f64> = (0..pos.len())
            .map(|i| {
                let ni = normals[i];
                let mut diffs: Vec<f64> = lists
                    .get(i)
                    .iter()
                    .map(|&u| {
                        let nu = normals[u as usize];
                        let nu = if nu.dot(ni) < 0.0 { -nu } else { nu };
                        (ni - nu).length_squared()
                    })
                    .collect();
                let m = diffs.len() / 2;
                let sr2 = if diffs.is_empty() {
                    0.0
                } else {
                    *diffs.select_nth_unstable_by(m, f64::total_cmp).1
                };
                2.0 * sr2.max(sigma_r_floor * sigma_r_floor)
            })
            .collect();
        let mut n = normals.to_vec();
        for _ in 0..iterations {
            n = (0..pos.len())
                .map(|i| {
                    let ni = n[i];
                    if ni == DVec3::ZERO {
                        return ni;
                    }
                    let ws = &spatial[lists.offsets[i] as usize..lists.offsets[i + 1] as usize];
                    let mut s = DVec3::ZERO;
                    for (&u, &w) in lists.get(i).iter().zip(ws) {
                        let nu = n[u as usize];
                        let nu = if nu.dot(ni) < 0.0 { -nu } else { nu };
                        if nu == DVec3::ZERO {
                            continue;
                        }
                        let wr = exp(-(ni - nu).length_squared() / range[i]);
                        s += nu * (w * wr);
                    }
                    let s = s.normalize_or_zero();
                    if s == DVec3::ZERO { ni } else { s }
                })
                .collect();
        }
        n
    }

    #[test]
    fn the_point_normal_filter_matches_its_reference_to_the_bit() {
        use crate::neighbours::KnnIndex;
        // A noisy wavy sheet of 3000 points with duplicates, PCA normals with some cleared, and
        // lists capped to uneven lengths (as isolation leaves them).
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut pos: Vec<DVec3> = (0..3000)
            .map(|_| {
                let (u, v) = (rnd() * 10.0, rnd() * 10.0);
                DVec3::new(u, v, (u * 0.7).sin() + 0.02 * rnd())
            })
            .collect();
        for i in 0..50 {
            pos[2000 + i] = pos[i * 7];
        }
        let index = KnnIndex::build(&pos, DVec3::ZERO).unwrap();
        let (full, radii) = index.knn_all(16).unwrap();
        let mut offsets = vec![0u32];
        let mut indices = Vec::new();
        for i in 0..pos.len() {
            let keep = if i % 11 == 0 { 5 + i % 9 } else { 16 };
            indices.extend_from_slice(&full.get(i)[..keep]);
            offsets.push(indices.len() as u32);
        }
        let capped = Neighbourhoods { offsets, indices };
        let (mut normals, _) = pca_normals(&pos, &full);
        for (i, n) in normals.iter_mut().enumerate() {
            if i % 13 == 0 {
                *n = DVec3::ZERO;
            } else if i % 5 == 0 {
                *n = -*n;
            }
        }
        for lists in [&full, &capped] {
            for (floor, iterations) in [(0.2, 3), (0.0, 1), (0.5, 2)] {
                let fast = filter_point_normals(&pos, lists, &radii, &normals, floor, iterations);
                let slow = filter_reference(&pos, lists, &radii, &normals, floor, iterations);
                let bits = |v: &[DVec3]| -> Vec<[u64; 3]> {
                    v.iter().map(|n| n.to_array().map(f64::to_bits)).collect()
                };
                assert_eq!(
                    bits(&fast),
                    bits(&slow),
                    "floor {floor}, {iterations} iterations"
                );
            }
        }
    }
}
