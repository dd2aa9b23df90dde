//! The QEM operator (Algorithm 1 of Vieira et al.) on meshes and on point clouds.
//!
//! For each vertex `v`, the tangent-plane quadrics of its neighbourhood `N(v)` (which contains `v`)
//! are summed and `v` moves to the minimiser chosen by the [`Solve`]. The planes are expressed
//! relative to `v` (`Quadric::plane(n_u, u − v)`), so the solve returns an offset from `v`.

use glam::DVec3;
use rayon::prelude::*;

use super::common::{FaceTopology, check_cancel, mean_edge_length, merge_step, stay};
use super::filtered::{face_geometry, filter_normals};
use super::normals::vertex_normals;
use super::{DenoiseError, NormalWeighting, Output, Params, Planes, SolveKind, Stats, Timer};
use crate::geometry::Quadric;
use crate::neighbours::{MeshAdjacency, Neighbourhoods, RingScratch};
use crate::points::Faces;

/// The new position of `v` from the quadric `q` (relative to `v`), and why it stayed put, if it
/// did. `limit2` (squared) bounds the step: a minimiser farther than the neighbourhood reaches
/// is not trusted. The paper's plain solve has no bound (`f64::INFINITY`).
#[inline]
fn apply(v: DVec3, q: &Quadric, params: &Params, limit2: f64) -> (DVec3, u8) {
    match params.solver_for(q.a.trace()).offset(q) {
        Some(w) if w.length_squared() <= limit2 => (v + w, 0),
        Some(_) => (v, stay::FAR),
        None => (v, stay::SINGULAR),
    }
}

/// The step bound for a point-cloud neighbourhood reaching `reach2` (squared): none for the
/// paper's plain solve, the neighbourhood's reach for the others.
#[inline]
pub fn step_limit(params: &Params, reach2: f64) -> f64 {
    match params.solve {
        SolveKind::Plain => f64::INFINITY,
        _ => reach2,
    }
}

/// The summed quadric of `v` over `neighbourhood`, each member contributing the plane through its
/// position with its normal, relative to `v`.
#[inline]
pub fn summed_quadric(
    pos: &[DVec3],
    normals: &[DVec3],
    v: DVec3,
    neighbourhood: &[u32],
) -> Quadric {
    let mut q = Quadric::ZERO;
    for &u in neighbourhood {
        let n = normals[u as usize];
        if n != DVec3::ZERO {
            q.add_plane(n, pos[u as usize] - v, 1.0);
        }
    }
    q
}

/// One mesh pass: every vertex moves to the minimiser of the quadrics of its `rings`-ring.
/// Returns the new positions and, per vertex, why it stayed put (`common::stay` flags, 0 if it moved).
pub fn mesh_step(
    pos: &[DVec3],
    adjacency: &MeshAdjacency,
    normals: &[DVec3],
    params: &Params,
) -> Vec<(DVec3, u8)> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(512)
        .map_init(
            || (RingScratch::new(pos.len()), Vec::with_capacity(64)),
            |(scratch, ring), v| {
                adjacency.ring(v, params.rings, scratch, ring);
                let q = summed_quadric(pos, normals, pos[v], ring);
                // Mesh vertices are not bounded: ../shared/EVALUATION.md's robust operator lets a few
                // vertices step beyond their ring (the golden outputs have them), and a mesh has
                // no isolated points.
                apply(pos[v], &q, params, f64::INFINITY)
            },
        )
        .collect()
}

/// The QEM operator on a mesh with tangent planes (the paper's when `params` is
/// [`Params::paper`]): per cycle, vertex normals from the incident faces (their normals filtered
/// first when `filter` > 0, then fixed for the cycle; recomputed before every update otherwise),
/// then `updates` Jacobi passes over k-rings.
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
    timer.lap("neighbours", &mut stats);
    let s = params.schedule(true);
    let mut cur = pos.to_vec();
    let mut stayed = vec![0u8; pos.len()];
    let first = vertex_normals(pos, faces, params.normals);
    stats.zero_area_faces = first.zero_area_faces;
    stats.unreferenced = first.unreferenced;
    for _ in 0..s.cycles.max(1) {
        check_cancel()?;
        let filtered = (s.filter > 0).then(|| {
            let (n, c, a) = face_geometry(&cur, faces);
            let n = filter_normals(
                &topo,
                &n,
                &c,
                &a,
                sigma_s,
                params.sigma_r_floor(true),
                s.filter,
            )?;
            Ok::<_, DenoiseError>(weighted_vertex_normals(
                cur.len(),
                faces,
                &n,
                &a,
                params.normals,
            ))
        });
        let filtered = filtered.transpose()?;
        timer.lap("normals", &mut stats);
        for _ in 0..s.updates {
            check_cancel()?;
            let normals = match &filtered {
                Some(n) => n.clone(),
                None => vertex_normals(&cur, faces, params.normals).normals,
            };
            let step = mesh_step(&cur, &adjacency, &normals, params);
            cur = merge_step(step, &mut stayed);
        }
        timer.lap("solve", &mut stats);
    }
    stats.book_moves(pos, &cur, &stayed, |_| true);
    Ok(Output {
        positions: cur,
        stats,
    })
}

/// Vertex normals from given face normals: area-weighted or plain mean, normalised.
fn weighted_vertex_normals(
    n: usize,
    faces: &Faces,
    face_normals: &[DVec3],
    areas: &[f64],
    weighting: NormalWeighting,
) -> Vec<DVec3> {
    let mut acc = vec![DVec3::ZERO; n];
    for (fi, f) in faces.iter().enumerate() {
        let w = match weighting {
            NormalWeighting::Area => areas[fi],
            NormalWeighting::Mean => 1.0,
        };
        for &v in f {
            acc[v as usize] += face_normals[fi] * w;
        }
    }
    acc.into_iter().map(DVec3::normalize_or_zero).collect()
}

/// One point pass: every finite point moves to the minimiser of the quadrics of its k-NN list,
/// unless the step exceeds [`step_limit`] of `reach2[i]` (a squared neighbourhood scale).
/// With [`Planes::Face`], a neighbour's normal is bent halfway towards the point's own where the
/// two are within 25° (normals must then be consistently oriented within a neighbourhood).
/// Non-finite points keep their value.
pub fn points_step(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    reach2: &[f64],
    normals: &[DVec3],
    params: &Params,
) -> Vec<(DVec3, u8)> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| point_step(pos, lists.get(i), reach2[i], normals, params, i))
        .collect()
}

/// [`points_step`] at point `i` (list `list`, squared neighbourhood scale `reach2`).
#[inline]
pub fn point_step(
    pos: &[DVec3],
    list: &[u32],
    reach2: f64,
    normals: &[DVec3],
    params: &Params,
    i: usize,
) -> (DVec3, u8) {
    let v = pos[i];
    if !v.is_finite() {
        return (v, 0);
    }
    let q = match params.planes {
        Planes::Tangent => summed_quadric(pos, normals, v, list),
        Planes::Face => bent_quadric(pos, normals, i, list),
    };
    apply(v, &q, params, step_limit(params, reach2))
}

/// Cosine of the largest angle between a point's normal and a neighbour's for which the
/// neighbour's plane uses the bisecting normal (25°).
pub(crate) const BEND_COS: f64 = 0.906_307_787_036_649_9;

/// The curvature-corrected normal of neighbour normal `nu` seen from a point of normal `ni`:
/// `nu` turned to agree with `ni` (PCA normals have no sign), then the bisector of the two where
/// they are within 25°. Zero when `nu` is zero.
#[inline]
pub fn bent_normal(ni: DVec3, nu: DVec3) -> DVec3 {
    let nu = if nu.dot(ni) < 0.0 { -nu } else { nu };
    if nu != DVec3::ZERO && ni != DVec3::ZERO && ni.dot(nu) > BEND_COS {
        (ni + nu).normalize()
    } else {
        nu
    }
}

/// The summed quadric of point `i` over `neighbourhood` with curvature-corrected planes: a
/// neighbour `u` nearly parallel to `i` contributes the plane through `u` whose normal bisects
/// `n_i` and `n_u` ([`bent_normal`]). On a sphere that plane passes through `i` exactly, so
/// repeated projection no longer pushes convex surfaces outward; across a sharp edge (larger
/// angles) the neighbour's own plane is kept so the edge stays sharp.
#[inline]
pub fn bent_quadric(pos: &[DVec3], normals: &[DVec3], i: usize, neighbourhood: &[u32]) -> Quadric {
    let v = pos[i];
    let ni = normals[i];
    let mut q = Quadric::ZERO;
    for &u in neighbourhood {
        let nu = normals[u as usize];
        if nu == DVec3::ZERO {
            continue;
        }
        q.add_plane(bent_normal(ni, nu), pos[u as usize] - v, 1.0);
    }
    q
}

/// True when point `i`'s k-NN list starts with another point at distance zero with a lower tie
/// key, i.e. it duplicates an earlier point (lists are sorted by (distance, tie key)).
pub fn is_duplicate(pos: &[DVec3], lists: &Neighbourhoods, ties: &[u64], i: usize) -> bool {
    duplicates(pos, lists.get(i), ties, i)
}

/// [`is_duplicate`] of point `i` with list `list`.
#[inline]
pub fn duplicates(pos: &[DVec3], list: &[u32], ties: &[u64], i: usize) -> bool {
    list.first().is_some_and(|&j| {
        let j = j as usize;
        ties[j] < ties[i] && pos[j] == pos[i]
    })
}
