//! qemd's mesh operator: bilateral filtering of face normals, then repeated damped QEM updates on
//! face planes, with an amount of smoothing chosen from the data, and the enclosed volume kept.
//!
//! # Brief overview
//!
//! * **Normals first.** The paper's operator lands at about half the noise because the tangent
//!   planes it sums are as noisy as the points (../shared/EVALUATION.md). Face normals are therefore
//!   smoothed by a bilateral filter over the faces sharing a vertex (Zheng et al. 2011): spatial
//!   width σs = the input's mean edge, range width σr = the median normal difference between such
//!   faces (at least `sigma_r`), recomputed every iteration, so the filter adapts to the noise it
//!   sees and stops smoothing across sharp edges.
//! * **Then the quadric step, repeated.** Each vertex moves to the minimiser of the area-weighted
//!   face planes (filtered normal through the face centroid) around it, with the damped solve
//!   `w = v − (A + μ·tr(A)/3·I)⁻¹(Av + b)`, which bounds tangential drift. A few such updates
//!   converge towards σ/√|N| instead of the single pass's σ/2.
//! * **How much.** A light cycle (3 filter iterations, 3 updates) runs first. Heavier cycles
//!   follow when the data says they help: when the input's median normal difference is that of
//!   strong noise (≥ 1.3), or when the light cycle removed most of it (what is left is below a
//!   share that grows from 42 % to 55 % with the noise): on a coarse mesh, where neighbouring
//!   faces differ because of the shape itself, the light cycle is all the smoothing the surface
//!   takes.
//! * **Volume.** On a closed mesh a final offset along the vertex normals restores the input's
//!   enclosed volume: independent noise leaves the expected volume unchanged, while plane
//!   projection through face centroids shrinks convex parts slightly.
//!
//! Meshes run in memory, so the global quantities (mean edge, medians, volume) need no
//! out-of-core counterpart.

use glam::DVec3;
use rayon::prelude::*;

use super::common::{FaceTopology, check_cancel, mean_edge_length, merge_step, stay};
use super::normals::{face_cross, vertex_normals};
use super::{DenoiseError, NormalWeighting, Output, Params, Stats, Timer};
use crate::geometry::{ExactSum, Quadric, exp};
use crate::neighbours::MeshAdjacency;
use crate::points::Faces;

/// Unit normals, centroids and areas of every face.
pub fn face_geometry(pos: &[DVec3], faces: &Faces) -> (Vec<DVec3>, Vec<DVec3>, Vec<f64>) {
    let per: Vec<(DVec3, DVec3, f64)> = (0..faces.len())
        .into_par_iter()
        .with_min_len(4096)
        .map(|fi| {
            let f = faces.face(fi);
            let c = face_cross(pos, f);
            let centroid =
                f.iter().map(|&v| pos[v as usize]).sum::<DVec3>() / f.len().max(1) as f64;
            (c.normalize_or_zero(), centroid, 0.5 * c.length())
        })
        .collect();
    let mut n = Vec::with_capacity(per.len());
    let mut c = Vec::with_capacity(per.len());
    let mut a = Vec::with_capacity(per.len());
    for (x, y, z) in per {
        n.push(x);
        c.push(y);
        a.push(z);
    }
    (n, c, a)
}

/// The median of `|n_f − n_g|` over pairs of faces sharing a vertex.
pub fn median_normal_difference(topo: &FaceTopology, normals: &[DVec3]) -> f64 {
    let mut d: Vec<f64> = (0..normals.len())
        .flat_map(|f| {
            topo.neighbours_of(f)
                .iter()
                .filter(move |&&g| g as usize > f)
                .map(move |&g| (normals[f] - normals[g as usize]).length())
        })
        .collect();
    if d.is_empty() {
        return 0.0;
    }
    let m = d.len() / 2;
    d.select_nth_unstable_by(m, f64::total_cmp);
    d[m]
}

/// `iterations` bilateral filter passes over the face normals (Zheng et al. 2011): each normal
/// becomes the normalised sum of its neighbours' normals weighted by area, distance (σs) and
/// normal difference (σr = max(median difference, `sigma_r_floor`), recomputed every pass).
///
/// # Errors
/// Cancellation ([`check_cancel`], before every pass).
pub fn filter_normals(
    topo: &FaceTopology,
    normals: &[DVec3],
    centroids: &[DVec3],
    areas: &[f64],
    sigma_s: f64,
    sigma_r_floor: f64,
    iterations: usize,
) -> Result<Vec<DVec3>, DenoiseError> {
    let mut n = normals.to_vec();
    let ss2 = 2.0 * sigma_s * sigma_s;
    for _ in 0..iterations {
        check_cancel()?;
        let sr = median_normal_difference(topo, &n).max(sigma_r_floor);
        let sr2 = 2.0 * sr * sr;
        n = (0..n.len())
            .into_par_iter()
            .with_min_len(1024)
            .map(|f| {
                let mut s = DVec3::ZERO;
                for &g in topo.neighbours_of(f) {
                    let g = g as usize;
                    let ws = exp(-(centroids[f] - centroids[g]).length_squared() / ss2);
                    let wr = exp(-(n[f] - n[g]).length_squared() / sr2);
                    s += n[g] * (areas[g] * ws * wr);
                }
                let s = s.normalize_or_zero();
                if s == DVec3::ZERO { n[f] } else { s }
            })
            .collect();
    }
    Ok(n)
}

/// One update: every vertex moves to the damped minimiser of the area-weighted planes of the
/// faces around it (`normals[f]` through the current centroid), unless the minimiser lies
/// farther than the farthest of those centroids (the vertex stays, counted as `far`).
pub fn face_plane_step(
    pos: &[DVec3],
    faces: &Faces,
    topo: &FaceTopology,
    normals: &[DVec3],
    params: &Params,
) -> Vec<(DVec3, u8)> {
    let (_, centroids, areas) = face_geometry(pos, faces);
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|v| {
            let p = pos[v];
            let mut q = Quadric::ZERO;
            // The farthest centroid of the planes summed: no step goes beyond what they span.
            let mut reach2 = 0.0f64;
            for &f in topo.faces_of(v) {
                let f = f as usize;
                if normals[f] != DVec3::ZERO && areas[f] > 0.0 {
                    q.add_plane(normals[f], centroids[f] - p, areas[f]);
                    reach2 = reach2.max((centroids[f] - p).length_squared());
                }
            }
            match params.solver_for(q.a.trace()).offset(&q) {
                // A minimiser beyond the faces around the vertex is a nearly flat direction's
                // drift, not the surface: the plain solve put a vertex of the noisy bunny 254
                // bounding-box diagonals away in one update (issue 51).
                Some(w) if w.length_squared() > reach2 => (p, stay::FAR),
                Some(w) => (p + w, 0),
                None => (p, stay::SINGULAR),
            }
        })
        .collect()
}

/// The state a cycle works on.
struct Run<'a> {
    faces: &'a Faces,
    topo: FaceTopology,
    sigma_s: f64,
    params: &'a Params,
    cur: Vec<DVec3>,
    stayed: Vec<u8>,
    timer: Timer,
    stats: Stats,
}

impl Run<'_> {
    /// One cycle: filter the current face normals, then run `updates` updates with them.
    ///
    /// # Errors
    /// Cancellation, checked before every filter pass and update.
    fn cycle(&mut self, filter: usize, updates: usize) -> Result<(), DenoiseError> {
        let (n, c, a) = face_geometry(&self.cur, self.faces);
        let floor = self.params.sigma_r_floor(true);
        let n = filter_normals(&self.topo, &n, &c, &a, self.sigma_s, floor, filter)?;
        self.timer.lap("normals", &mut self.stats);
        for _ in 0..updates {
            check_cancel()?;
            let step = face_plane_step(&self.cur, self.faces, &self.topo, &n, self.params);
            self.cur = merge_step(step, &mut self.stayed);
        }
        self.timer.lap("solve", &mut self.stats);
        Ok(())
    }

    fn normal_difference(&self) -> f64 {
        median_normal_difference(&self.topo, &face_geometry(&self.cur, self.faces).0)
    }
}

/// Closed: every undirected edge is shared by exactly two faces.
fn is_closed(faces: &Faces) -> bool {
    let mut count = std::collections::HashMap::new();
    for f in faces.iter() {
        for i in 0..f.len() {
            let (a, b) = (f[i], f[(i + 1) % f.len()]);
            if a != b {
                *count.entry((a.min(b), a.max(b))).or_insert(0u32) += 1;
            }
        }
    }
    !count.is_empty() && count.values().all(|&c| c == 2)
}

/// Signed volume of a closed mesh (fan triangles, relative to the first vertex), summed exactly.
fn volume(pos: &[DVec3], faces: &Faces) -> f64 {
    let o = pos.first().copied().unwrap_or(DVec3::ZERO);
    faces
        .triangles()
        .map(|t| {
            let (a, b, c) = (
                pos[t[0] as usize] - o,
                pos[t[1] as usize] - o,
                pos[t[2] as usize] - o,
            );
            a.dot(b.cross(c)) / 6.0
        })
        .collect::<ExactSum>()
        .value()
}

/// qemd's mesh operator (see the module overview).
///
/// # Errors
/// Face indices out of range.
pub fn mesh(pos: &[DVec3], faces: &Faces, params: &Params) -> Result<Output, DenoiseError> {
    let mut timer = Timer::start();
    let mut stats = Stats {
        points: pos.len() as u64,
        ..Stats::default()
    };
    let adjacency = MeshAdjacency::build(pos.len(), faces)?;
    let topo = FaceTopology::build(pos.len(), faces);
    let sigma_s = mean_edge_length(pos, &adjacency);
    drop(adjacency);
    let vn = vertex_normals(pos, faces, NormalWeighting::Area);
    stats.zero_area_faces = vn.zero_area_faces;
    stats.unreferenced = vn.unreferenced;
    timer.lap("neighbours", &mut stats);

    let s = params.schedule(true);
    let mut run = Run {
        faces,
        topo,
        sigma_s,
        params,
        cur: pos.to_vec(),
        stayed: vec![0u8; pos.len()],
        timer,
        stats,
    };
    if s.cycles > 0 {
        for _ in 0..s.cycles {
            run.cycle(s.filter, s.updates)?;
        }
    } else {
        let m0 = run.normal_difference();
        run.cycle(3, 3)?;
        let m1 = run.normal_difference();
        let strong = m0 >= 1.3;
        // What the light cycle left is shape on a coarse mesh (neighbouring faces differ because
        // the surface turns) and noise on a fine one. The share that separates the two grows
        // with the noise: about 0.45 for light noise, 0.55 for medium (measured on the Table I
        // meshes: fine ≤ 0.36 / ≤ 0.47, coarse ≥ 0.45 / ≥ 0.6 at 20 % / 40 % noise).
        let share = 0.42 + 0.13 * ((m0 - 0.7) / 0.4).clamp(0.0, 1.0);
        if strong || m1 < share * m0 {
            for _ in 0..if strong { 3 } else { 2 } {
                run.cycle(s.filter, s.updates)?;
            }
        }
    }
    let Run {
        mut cur,
        stayed,
        mut timer,
        mut stats,
        ..
    } = run;
    if params.volume && is_closed(faces) {
        // An offset d along the normals changes the volume by about area·d; two Newton steps
        // take care of the curvature term.
        let target = volume(pos, faces);
        for _ in 0..2 {
            let lost = target - volume(&cur, faces);
            let (_, _, a) = face_geometry(&cur, faces);
            let area: f64 = a.iter().copied().collect::<ExactSum>().value();
            if !(area > 0.0 && lost.is_finite()) {
                break;
            }
            let d = lost / area;
            let normals = vertex_normals(&cur, faces, NormalWeighting::Area).normals;
            for (p, nv) in cur.iter_mut().zip(&normals) {
                *p += *nv * d;
            }
        }
        timer.lap("volume", &mut stats);
    }
    stats.book_moves(pos, &cur, &stayed, |_| true);
    Ok(Output {
        positions: cur,
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topology_of_a_strip() {
        let faces = Faces::from_triangles(&[[0, 1, 2], [1, 3, 2], [3, 4, 2]]);
        let t = FaceTopology::build(5, &faces);
        assert_eq!(t.faces_of(2), &[0, 1, 2]);
        assert_eq!(t.faces_of(0), &[0]);
        assert_eq!(t.neighbours_of(0), &[0, 1, 2]);
    }

    #[test]
    fn filter_keeps_a_flat_patch_flat() {
        let mut pos = Vec::new();
        for j in 0..5 {
            for i in 0..5 {
                pos.push(DVec3::new(i as f64, j as f64, 0.0));
            }
        }
        let mut tris = Vec::new();
        for j in 0..4u32 {
            for i in 0..4u32 {
                let a = j * 5 + i;
                tris.push([a, a + 1, a + 5]);
                tris.push([a + 1, a + 6, a + 5]);
            }
        }
        let faces = Faces::from_triangles(&tris);
        let (n, c, a) = face_geometry(&pos, &faces);
        let topo = FaceTopology::build(pos.len(), &faces);
        let f = filter_normals(&topo, &n, &c, &a, 1.0, 0.35, 10).unwrap();
        for v in &f {
            assert!((v.dot(DVec3::Z).abs() - 1.0).abs() < 1e-12);
        }
    }
}
