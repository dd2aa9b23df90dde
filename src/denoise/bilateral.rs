//! Bilateral denoising (Fleishman, Drori and Cohen-Or 2003), the paper's comparator.
//!
//! Each pass moves every vertex along its normal `n` by `Σ w h / Σ w` over its neighbours `q`,
//! with `t = |q − v|`, `h = n·(q − v)`, `w = exp(−t²/2σc²)·exp(−h²/2σs²)`. `σc` is the mean edge
//! length of the *input* (fixed for all passes); the neighbours are all points within `2σc`
//! (`v` excluded); `σs²` is the population variance of `h` over the neighbours (at least
//! `1e-12·σc²`). Meshes use area-weighted vertex normals of the current positions; point clouds
//! use PCA normals over the k nearest neighbours, their neighbours are those k nearest that lie
//! within `2σc`, and `σc` is the mean distance from a point to its nearest other point.

use glam::DVec3;
use rayon::prelude::*;

use super::common::{check_cancel, mean_edge_length, merge_step};
use super::normals::vertex_normals;
use super::{DenoiseError, NormalWeighting, Output, Params, Stats, Timer, origin_of};
use crate::geometry::{ExactSum, exp};
use crate::neighbours::{HUB_VALENCE, KnnIndex, MeshAdjacency, Neighbourhoods};
use crate::points::Faces;

/// Mean distance from each finite point to its nearest other point, summed exactly, read off
/// k-NN lists that include the point itself (k ≥ 2).
pub fn mean_spacing(index: &KnnIndex, lists: &Neighbourhoods) -> f64 {
    let mut sum = ExactSum::new();
    for i in 0..lists.len() {
        if let Some(&j) = lists.get(i).iter().find(|&&j| j as usize != i) {
            sum.add(index.dist2(i, j as usize).sqrt());
        }
    }
    sum.mean()
}

/// The bilateral offset of `v` along unit normal `n` from its neighbours' positions.
fn offset(
    v: DVec3,
    n: DVec3,
    nbrs: impl Iterator<Item = DVec3>,
    sigma_c: f64,
    buf: &mut Vec<(f64, f64)>,
) -> f64 {
    buf.clear();
    for q in nbrs {
        let d = q - v;
        buf.push((d.length_squared(), n.dot(d)));
    }
    if buf.is_empty() || n == DVec3::ZERO {
        return 0.0;
    }
    let m = buf.len() as f64;
    let mean = buf.iter().map(|x| x.1).sum::<f64>() / m;
    let var = buf.iter().map(|x| (x.1 - mean) * (x.1 - mean)).sum::<f64>() / m;
    let sc2 = sigma_c * sigma_c;
    let ss2 = var.max(1e-12 * sc2);
    let (mut sw, mut swh) = (0.0, 0.0);
    for &(t2, h) in buf.iter() {
        let w = exp(-t2 / (2.0 * sc2)) * exp(-h * h / (2.0 * ss2));
        sw += w;
        swh += w * h;
    }
    if sw > 0.0 { swh / sw } else { 0.0 }
}

fn finish(v: DVec3, n: DVec3, h: f64) -> (DVec3, u8) {
    let w = n * h;
    if w.is_finite() { (v + w, 0) } else { (v, 0) }
}

/// Bilateral mesh denoising, `params.iterations` passes.
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
    let sigma_c = mean_edge_length(pos, &adjacency);
    let origin = origin_of(pos);
    let mut cur = pos.to_vec();
    let mut stayed = vec![0u8; pos.len()];
    for pass in 0..params.schedule(true).cycles {
        check_cancel()?;
        let vn = vertex_normals(&cur, faces, NormalWeighting::Area);
        if pass == 0 {
            stats.zero_area_faces = vn.zero_area_faces;
            stats.unreferenced = vn.unreferenced;
        }
        timer.lap("normals", &mut stats);
        let index = KnnIndex::build(&cur, origin)?;
        let r2 = 4.0 * sigma_c * sigma_c;
        timer.lap("neighbours", &mut stats);
        let step: Vec<(DVec3, u8)> = (0..cur.len())
            .into_par_iter()
            .with_min_len(512)
            .map_init(
                || (Vec::new(), Vec::new()),
                |(list, buf), v| {
                    // The ball of 2σc, at most the HUB_VALENCE + 1 nearest (the vertex itself
                    // among them): near the apex of a fan it holds most of the rim (issue 51).
                    // Smaller balls are the whole ball, ascending by index as always.
                    list.clear();
                    index.knn_of(v, HUB_VALENCE + 1, list);
                    list.retain(|&u| index.dist2(v, u as usize) <= r2);
                    list.sort_unstable();
                    let nbrs = list
                        .iter()
                        .filter(|&&u| u as usize != v)
                        .map(|&u| cur[u as usize]);
                    let h = offset(cur[v], vn.normals[v], nbrs, sigma_c, buf);
                    finish(cur[v], vn.normals[v], h)
                },
            )
            .collect();
        cur = merge_step(step, &mut stayed);
        timer.lap("solve", &mut stats);
    }
    stats.book_moves(pos, &cur, &stayed, |_| true);
    Ok(Output {
        positions: cur,
        stats,
    })
}

/// One bilateral pass over a point cloud: each point moves along its PCA normal, weighing the
/// k-NN neighbours (itself excluded) that lie within `2σc`.
pub fn points_step(
    cur: &[DVec3],
    lists: &Neighbourhoods,
    normals: &[DVec3],
    sigma_c: f64,
) -> Vec<(DVec3, u8)> {
    let r2 = 4.0 * sigma_c * sigma_c;
    (0..cur.len())
        .into_par_iter()
        .with_min_len(1024)
        .map_init(Vec::new, |buf, i| {
            point_step(cur, lists.get(i), normals, sigma_c, r2, i, buf)
        })
        .collect()
}

/// [`points_step`] at point `i` (list `list`), with `r2 = 4σc²`; `buf` is scratch.
#[inline]
pub fn point_step(
    cur: &[DVec3],
    list: &[u32],
    normals: &[DVec3],
    sigma_c: f64,
    r2: f64,
    i: usize,
    buf: &mut Vec<(f64, f64)>,
) -> (DVec3, u8) {
    let v = cur[i];
    if !v.is_finite() {
        return (v, 0);
    }
    let nbrs = list
        .iter()
        .filter(|&&u| u as usize != i)
        .map(|&u| cur[u as usize])
        .filter(|q| (*q - v).length_squared() <= r2);
    let h = offset(v, normals[i], nbrs, sigma_c, buf);
    finish(v, normals[i], h)
}
