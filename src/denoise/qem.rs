//! The QEM operator (Algorithm 1 of Vieira et al.) on meshes and on point clouds.
//!
//! For each vertex `v`, the tangent-plane quadrics of its neighbourhood `N(v)` (which contains `v`)
//! are summed and `v` moves to the minimiser chosen by the [`Solve`]. The planes are expressed
//! relative to `v` (`Quadric::plane(n_u, u − v)`), so the solve returns an offset from `v`.

use glam::DVec3;
use rayon::prelude::*;

use super::frame::Frame;
use super::normals::{pca_normals, vertex_normals};
use super::{DenoiseError, Output, Params, Stats, Timer};
use crate::geometry::{Quadric, Solve};
use crate::neighbours::{KnnIndex, MeshAdjacency, Neighbourhoods, RingScratch};
use crate::points::Faces;

/// Outcome of one Jacobi pass.
#[derive(Debug, Clone, Copy, Default)]
pub struct StepCounts {
    /// Points that moved.
    pub moved: u64,
    /// Points that stayed: singular quadric or non-finite solve.
    pub singular: u64,
    /// Largest displacement.
    pub max_step: f64,
}

impl StepCounts {
    fn merge(self, o: StepCounts) -> StepCounts {
        StepCounts {
            moved: self.moved + o.moved,
            singular: self.singular + o.singular,
            max_step: self.max_step.max(o.max_step),
        }
    }

    /// Adds these counts to `stats`.
    pub fn book(&self, stats: &mut Stats) {
        stats.moved += self.moved;
        stats.singular += self.singular;
        stats.max_step = stats.max_step.max(self.max_step);
    }
}

/// The new position of `v` from the quadric `q` (relative to `v`), and how it went.
#[inline]
fn apply(v: DVec3, q: &Quadric, solve: Solve) -> (DVec3, StepCounts) {
    match solve.offset(q) {
        Some(w) => (
            v + w,
            StepCounts {
                moved: 1,
                singular: 0,
                max_step: w.length(),
            },
        ),
        None => (
            v,
            StepCounts {
                moved: 0,
                singular: 1,
                max_step: 0.0,
            },
        ),
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
pub fn mesh_step(
    pos: &[DVec3],
    adjacency: &MeshAdjacency,
    normals: &[DVec3],
    rings: usize,
    solve: Solve,
) -> (Vec<DVec3>, StepCounts) {
    let results: Vec<(DVec3, StepCounts)> = (0..pos.len())
        .into_par_iter()
        .with_min_len(512)
        .map_init(
            || (RingScratch::new(pos.len()), Vec::with_capacity(64)),
            |(scratch, ring), v| {
                adjacency.ring(v, rings, scratch, ring);
                let q = summed_quadric(pos, normals, pos[v], ring);
                apply(pos[v], &q, solve)
            },
        )
        .collect();
    split(results)
}

fn split(results: Vec<(DVec3, StepCounts)>) -> (Vec<DVec3>, StepCounts) {
    let counts = results
        .iter()
        .fold(StepCounts::default(), |a, r| a.merge(r.1));
    (results.into_iter().map(|r| r.0).collect(), counts)
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
    for pass in 0..params.iterations {
        let vn = vertex_normals(&cur, faces, params.normals);
        if pass == 0 {
            stats.zero_area_faces = vn.zero_area_faces;
            stats.unreferenced = vn.unreferenced;
        }
        timer.lap("normals", &mut stats);
        let (next, counts) = mesh_step(&cur, &adjacency, &vn.normals, params.rings, solve);
        counts.book(&mut stats);
        cur = next;
        timer.lap("solve", &mut stats);
    }
    Ok(Output {
        positions: cur,
        stats,
    })
}

/// One point pass: every finite point moves to the minimiser of the quadrics of its k-NN list.
/// Non-finite points keep their value and are not counted.
pub fn points_step(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    normals: &[DVec3],
    solve: Solve,
) -> (Vec<DVec3>, StepCounts) {
    let results: Vec<(DVec3, StepCounts)> = (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let v = pos[i];
            if !v.is_finite() {
                return (v, StepCounts::default());
            }
            let q = summed_quadric(pos, normals, v, lists.get(i));
            apply(v, &q, solve)
        })
        .collect();
    split(results)
}

/// Number of points whose k-NN list starts with another point at distance zero with a lower tie
/// key, i.e. duplicates of an earlier point (lists are sorted by (distance, tie key)).
pub fn count_duplicates(pos: &[DVec3], lists: &Neighbourhoods, ties: &[u64]) -> u64 {
    (0..pos.len())
        .filter(|&i| {
            lists.get(i).first().is_some_and(|&j| {
                let j = j as usize;
                ties[j] < ties[i] && pos[j] == pos[i]
            })
        })
        .count() as u64
}

/// The QEM operator on a point cloud: k nearest neighbours (the point included) relative to
/// `origin`, PCA normals, `params.iterations` Jacobi passes.
///
/// The k-NN graph is built once, on the input positions, and every pass reuses it (normals and
/// quadrics are re-evaluated on the updated positions). A fixed graph keeps the reach of `n`
/// passes at `2n` graph hops, which is what lets the tiled path reproduce this result exactly.
///
/// # Errors
/// Fewer finite points than k.
pub fn points(pos: &[DVec3], origin: DVec3, params: &Params) -> Result<Output, DenoiseError> {
    let mut timer = Timer::start();
    let mut stats = Stats {
        points: pos.len() as u64,
        non_finite: pos.iter().filter(|p| !p.is_finite()).count() as u64,
        ..Stats::default()
    };
    let frame = Frame::new(pos, None);
    let index = KnnIndex::build_with_ties(&frame.positions, origin, frame.ties.clone())?;
    let (lists, _) = index.knn_all(params.k())?;
    drop(index);
    stats.duplicates = count_duplicates(&frame.positions, &lists, &frame.ties);
    timer.lap("neighbours", &mut stats);
    let out = points_passes(&frame.positions, &lists, params, &mut stats, &mut timer);
    Ok(Output {
        positions: frame.restore(&out),
        stats,
    })
}

/// `params.iterations` QEM passes over a fixed neighbour graph.
pub fn points_passes(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    params: &Params,
    stats: &mut Stats,
    timer: &mut Timer,
) -> Vec<DVec3> {
    let solve = params.solver();
    let mut cur = pos.to_vec();
    for pass in 0..params.iterations {
        let (normals, degenerate) = pca_normals(&cur, lists);
        if pass == 0 {
            stats.degenerate_neighbourhoods = degenerate;
        }
        timer.lap("normals", stats);
        let (next, counts) = points_step(&cur, lists, &normals, solve);
        counts.book(stats);
        cur = next;
        timer.lap("solve", stats);
    }
    cur
}
