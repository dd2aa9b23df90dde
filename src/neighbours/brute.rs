//! Linear-scan oracles for the k-d tree queries (tests and benches compare against them). They
//! see exactly the points the index does: those passing [`super::indexable`].

use glam::DVec3;

/// The `k` nearest indexable points of `pts` to `q`, ascending by (squared distance, index).
pub fn knn(pts: &[DVec3], q: DVec3, k: usize) -> Vec<u32> {
    let ties: Vec<u64> = (0..pts.len() as u64).collect();
    knn_with_ties(pts, &ties, q, k)
}

/// The `k` nearest indexable points of `pts` to `q`, ascending by (squared distance, `ties[i]`).
pub fn knn_with_ties(pts: &[DVec3], ties: &[u64], q: DVec3, k: usize) -> Vec<u32> {
    let mut all: Vec<(f64, u64, u32)> = pts
        .iter()
        .enumerate()
        .filter(|(_, p)| super::indexable(p.to_array()))
        .map(|(i, &p)| (sq(p, q), ties[i], i as u32))
        .collect();
    all.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    all.truncate(k);
    all.into_iter().map(|c| c.2).collect()
}

/// Indices of the indexable points within squared distance `r2` of `q` (inclusive), ascending.
pub fn within(pts: &[DVec3], q: DVec3, r2: f64) -> Vec<u32> {
    pts.iter()
        .enumerate()
        .filter(|(_, p)| super::indexable(p.to_array()) && sq(**p, q) <= r2)
        .map(|(i, _)| i as u32)
        .collect()
}

/// Squared distance computed coordinate by coordinate, in the same order as the index.
fn sq(a: DVec3, b: DVec3) -> f64 {
    let d = a - b;
    d.x * d.x + d.y * d.y + d.z * d.z
}
