//! The QEM operator (Algorithm 1 of Vieira et al.) on meshes and on point clouds.
//!
//! For each vertex `v`, the tangent-plane quadrics of its neighbourhood `N(v)` (which contains `v`)
//! are summed and `v` moves to the minimiser chosen by the [`Solve`]. The planes are expressed
//! relative to `v` (`Quadric::plane(n_u, u − v)`), so the solve returns an offset from `v`.

use glam::DVec3;
use rayon::prelude::*;

use super::normals::vertex_normals;
use super::{DenoiseError, Output, Params, Stats, Timer};
use crate::geometry::{Quadric, Solve};
use crate::neighbours::{MeshAdjacency, Neighbourhoods, RingScratch};
use crate::points::Faces;

/// Why a point stayed where it was in a pass (bit flags, or-ed over passes).
pub mod stay {
    /// The summed quadric was singular, or the solve not finite.
    pub const SINGULAR: u8 = 1;
    /// The minimiser lay farther than the point's neighbourhood reaches (isolated points and
    /// outliers, whose planes all belong to a distant surface).
    pub const FAR: u8 = 2;
}

/// The new position of `v` from the quadric `q` (relative to `v`), and why it stayed put, if it
/// did. `limit2` (squared) bounds the step: a minimiser farther than the neighbourhood reaches
/// is not trusted. The paper's plain solve has no bound (`f64::INFINITY`).
#[inline]
fn apply(v: DVec3, q: &Quadric, solve: Solve, limit2: f64) -> (DVec3, u8) {
    match solve.offset(q) {
        Some(w) if w.length_squared() <= limit2 => (v + w, 0),
        Some(_) => (v, stay::FAR),
        None => (v, stay::SINGULAR),
    }
}

/// The step bound of `solve` for a point-cloud neighbourhood reaching `reach2` (squared): none for
/// the paper's plain solve, the neighbourhood's reach for the others.
#[inline]
pub fn step_limit(solve: Solve, reach2: f64) -> f64 {
    match solve {
        Solve::Plain => f64::INFINITY,
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
/// Returns the new positions and, per vertex, why it stayed put ([`stay`] flags, 0 if it moved).
pub fn mesh_step(
    pos: &[DVec3],
    adjacency: &MeshAdjacency,
    normals: &[DVec3],
    rings: usize,
    solve: Solve,
) -> Vec<(DVec3, u8)> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(512)
        .map_init(
            || (RingScratch::new(pos.len()), Vec::with_capacity(64)),
            |(scratch, ring), v| {
                adjacency.ring(v, rings, scratch, ring);
                let q = summed_quadric(pos, normals, pos[v], ring);
                // Mesh vertices are not bounded: EVALUATION.md's robust operator lets a few
                // vertices step beyond their ring (the golden outputs have them), and a mesh has
                // no isolated points.
                apply(pos[v], &q, solve, f64::INFINITY)
            },
        )
        .collect()
}

/// The QEM operator on a mesh: `params.iterations` Jacobi passes over k-rings with face-based
/// vertex normals.
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
    timer.lap("neighbours", &mut stats);
    let solve = params.solver();
    let mut cur = pos.to_vec();
    let mut stayed = vec![0u8; pos.len()];
    for pass in 0..params.iterations {
        let vn = vertex_normals(&cur, faces, params.normals);
        if pass == 0 {
            stats.zero_area_faces = vn.zero_area_faces;
            stats.unreferenced = vn.unreferenced;
        }
        timer.lap("normals", &mut stats);
        let step = mesh_step(&cur, &adjacency, &vn.normals, params.rings, solve);
        cur = merge_step(step, &mut stayed);
        timer.lap("solve", &mut stats);
    }
    stats.book_moves(pos, &cur, &stayed, |_| true);
    Ok(Output {
        positions: cur,
        stats,
    })
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

/// One point pass: every finite point moves to the minimiser of the quadrics of its k-NN list,
/// unless the step exceeds [`step_limit`] of `reach2[i]` (a squared neighbourhood scale).
/// Non-finite points keep their value.
pub fn points_step(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    reach2: &[f64],
    normals: &[DVec3],
    solve: Solve,
) -> Vec<(DVec3, u8)> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let v = pos[i];
            if !v.is_finite() {
                return (v, 0);
            }
            let q = summed_quadric(pos, normals, v, lists.get(i));
            apply(v, &q, solve, step_limit(solve, reach2[i]))
        })
        .collect()
}

/// True when point `i`'s k-NN list starts with another point at distance zero with a lower tie
/// key, i.e. it duplicates an earlier point (lists are sorted by (distance, tie key)).
pub fn is_duplicate(pos: &[DVec3], lists: &Neighbourhoods, ties: &[u64], i: usize) -> bool {
    lists.get(i).first().is_some_and(|&j| {
        let j = j as usize;
        ties[j] < ties[i] && pos[j] == pos[i]
    })
}
