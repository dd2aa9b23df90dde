//! Isolated points: the one rule that bounds how far any neighbourhood reaches.
//!
//! A far outlier's k-NN ball spans the scene. Its list then reaches points that say nothing about
//! it, its result depends on everything inside that ball, and a tile that owns it must load the
//! whole scene to prove its result exact (issue 16: 60 halo doublings and 50× the in-memory time
//! on a cluttered scene). So every list is capped at the cloud's **isolation radius** `R`:
//!
//! ```text
//!   R = ISOLATION × r_k       r_k: the cloud's typical k-NN radius, estimated from a
//!                             deterministic sample of the points (bottom keys of the global
//!                             index, the same sample the tiling planner draws)
//!
//!   list(p) = the k nearest points to p that lie within R of it
//!   p is isolated  ⇔  fewer than k points lie within R of p
//! ```
//!
//! An isolated point keeps its input position, takes no part as a plane or line in anyone's
//! quadric, and is counted in the run's report (`isolated`). Its capped list is still exact once
//! the ball of radius `R` around it is loaded, so a result never depends on anything farther than
//! `R` per hop, and a tile is provably exact with a halo of `(hops + 1) · R`: halo growth is
//! bounded by the data, not by the farthest outlier. In memory and in tiles the rule is the same,
//! so tiled output stays byte-identical.
//!
//! `ISOLATION = 32` is measured, not tuned to a file: over the 21 real scans of
//! `docs/quality/real-scans.md` the largest ratio of a point's 16-NN radius to the estimate is 30
//! (far-range returns of a KITTI sweep); the far outliers of the cluttered scene sit at more than
//! 1000×. Real sparse surface is left as it was; only points no scan-line or surface explains are
//! cut off.

use glam::DVec3;

use crate::neighbours::{KnnIndex, Neighbourhoods};

/// Isolation radius over the typical k-NN radius.
pub const ISOLATION: f64 = 32.0;

/// Most points in the sample the typical radius is estimated on (the tiling planner's sample).
pub const SAMPLE: usize = 1 << 18;

/// Sample points whose neighbour distance is measured (an even stride through the sample).
const PROBES: usize = 4096;

/// The uniform sample of at most [`SAMPLE`] points: those whose global index (`ties`) has one of
/// the smallest [`crate::points::sample_key`]s, in global-index order.
pub fn sample(positions: &[DVec3], ties: &[u64]) -> Vec<DVec3> {
    let mut keyed: Vec<(u64, u64)> = ties
        .iter()
        .enumerate()
        .map(|(j, &t)| (crate::points::sample_key(t), j as u64))
        .collect();
    if keyed.len() > SAMPLE {
        keyed.select_nth_unstable(SAMPLE);
        keyed.truncate(SAMPLE);
    }
    let mut picked: Vec<usize> = keyed.iter().map(|&(_, j)| j as usize).collect();
    picked.sort_unstable_by_key(|&j| ties[j]);
    picked.into_iter().map(|j| positions[j]).collect()
}

/// The typical k-NN radius of a cloud of `population` points from `sample` (in global-index
/// order): the median distance of probed sample points to their 8th sample neighbour, scaled to
/// the full density as on a surface (radius ∝ 1/√density). Zero distances (duplicate stacks) are
/// left out of the median. `None` when there are too few points or no positive distance.
pub fn typical_radius(sample: &[DVec3], origin: DVec3, population: u64, k: usize) -> Option<f64> {
    let (probes, ks) = probes(sample.len())?;
    let index = KnnIndex::build(sample, origin).ok()?;
    // The probes' lists from one grid pass over the sample (parallel, and its O(n) part is a
    // sort into cells), not from a k-d tree built for them: the tree's serial construction was
    // 3.5 % of a 120 k-point run's instructions and about 30 ms of its wall time (callgrind,
    // docs/BENCHMARKS.md). Both give the same distances to the bit (`KnnIndex::knn_at`), so the
    // radius is unchanged. With fewer than `ks + 1` points indexed the tree answers with the
    // points there are.
    let mut asked = vec![false; sample.len()];
    probes.clone().for_each(|i| asked[i] = true);
    let radii: Vec<f64> = match index.knn_asked(ks + 1, Some(&asked)) {
        Ok((_, radii2, _)) => probes.map(|i| radii2[i].sqrt()).collect(),
        Err(_) => {
            let mut list = Vec::new();
            probes
                .map(|i| index.knn_of(i, ks + 1, &mut list).sqrt())
                .collect()
        }
    };
    typical_of(radii, sample.len(), population, k, ks)
}

/// The sample points [`typical_radius`] probes (an even stride through the sample) and the
/// neighbour it measures each one's distance to (`ks`, lists of `ks + 1` holding the point
/// itself); `None` when the sample is too small.
pub fn probes(len: usize) -> Option<(std::iter::StepBy<std::ops::Range<usize>>, usize)> {
    let ks = 8.min(len.saturating_sub(1));
    (ks >= 2).then(|| ((0..len).step_by((len / PROBES).max(1)), ks))
}

/// [`typical_radius`] from the probes' distances to their `ks`-th sample neighbour (`radii`, in
/// probe order; zero and NaN distances are left out), for a sample of `len` of `population`
/// points and lists of `k`.
pub fn typical_of(
    mut radii: Vec<f64>,
    len: usize,
    population: u64,
    k: usize,
    ks: usize,
) -> Option<f64> {
    radii.retain(|&r| r > 0.0);
    if radii.is_empty() {
        return None;
    }
    radii.sort_by(f64::total_cmp);
    let fraction = len as f64 / population.max(1) as f64;
    let r_k = radii[radii.len() / 2] * (k as f64 * fraction / ks as f64).sqrt();
    (r_k > 0.0 && r_k.is_finite()).then_some(r_k)
}

/// The isolation radius `ISOLATION × r_k` for lists of `k` (see [`typical_radius`]).
pub fn radius(sample: &[DVec3], origin: DVec3, population: u64, k: usize) -> Option<f64> {
    radius_of(typical_radius(sample, origin, population, k))
}

/// The isolation radius for the typical radius `r_k` ([`typical_radius`]).
pub fn radius_of(r_k: Option<f64>) -> Option<f64> {
    r_k.map(|r| r * ISOLATION).filter(|r| r.is_finite())
}

/// The isolation radius of a whole cloud held in memory (`ties`: global indices), drawn from the
/// same sample the tiling planner draws.
pub fn of_cloud(positions: &[DVec3], ties: &[u64], origin: DVec3, k: usize) -> Option<f64> {
    radius(&sample(positions, ties), origin, positions.len() as u64, k)
}

/// Fewest list members a point keeps under the user's `--radius` before it counts as isolated
/// (a plane fit needs three; eight make the small-scale fit of [`super::structure::NEAR`]).
pub const MIN_LIST: usize = 8;

/// The cap on every list and whether it is the user's: the isolation radius, or the user's
/// `--radius` ([`super::Params::radius`]) where that is smaller. Both the in-memory run and the
/// tiling plan take it from here.
///
/// Under the isolation radius a point with fewer than k points within it is isolated (the rule
/// above). Under the user's radius the lists are those of PCL's and Open3D's hybrid search, the
/// k nearest within the radius, and a point is isolated only with fewer than [`MIN_LIST`] (so
/// `--radius` below the scan's k-NN radius still smooths, on shorter lists).
pub fn cap(isolation: Option<f64>, user: Option<f64>) -> (Option<f64>, bool) {
    match (isolation, user) {
        (Some(a), Some(b)) if b < a => (Some(b), true),
        (None, Some(b)) => (Some(b), true),
        (a, _) => (a, false),
    }
}

/// True when a point is isolated: its list was `capped` and kept fewer than `least`
/// ([`least_list`]) members.
pub fn is_isolated(capped: bool, len: usize, least: usize) -> bool {
    capped && len < least
}

/// The list length below which a capped list makes its point isolated, for lists of `k`:
/// `k` under the isolation radius, `min(k, MIN_LIST)` under the user's radius (`short`).
pub fn least_list(k: usize, short: bool) -> usize {
    if short { k.min(MIN_LIST) } else { k }
}

/// Lists capped at `cap`: every member farther than `cap` from its point (`dist2`, squared) is
/// dropped. Returns the capped lists, their squared radii (`cap²` for a capped list: the ball its
/// exactness needs) and which lists were capped. `lists` must be sorted by distance.
pub fn cap_lists(
    lists: Neighbourhoods,
    radii: Vec<f64>,
    cap: Option<f64>,
    dist2: impl Fn(usize, usize) -> f64,
) -> (Neighbourhoods, Vec<f64>, Vec<bool>) {
    let n = lists.len();
    let Some(cap) = cap else {
        return (lists, radii, vec![false; n]);
    };
    let cap2 = cap * cap;
    if radii.iter().all(|&r| r <= cap2) {
        return (lists, radii, vec![false; n]);
    }
    let mut offsets = Vec::with_capacity(n + 1);
    offsets.push(0u32);
    let mut indices = Vec::with_capacity(lists.indices.len());
    let mut capped = vec![false; n];
    let mut out_radii = radii;
    for (i, c) in capped.iter_mut().enumerate() {
        let list = lists.get(i);
        let (kept, r2, was) = cap_one(list, out_radii[i], cap2, |u| dist2(i, u as usize));
        *c = was;
        out_radii[i] = r2;
        indices.extend_from_slice(&list[..kept]);
        offsets.push(indices.len() as u32);
    }
    (Neighbourhoods { offsets, indices }, out_radii, capped)
}

/// One list of [`cap_lists`]: how many of its members (sorted by distance, `dist2` squared) the
/// cap `cap2` (squared) keeps, the list's squared radius after it, and whether it was capped.
pub fn cap_one(
    list: &[u32],
    radius2: f64,
    cap2: f64,
    dist2: impl Fn(u32) -> f64,
) -> (usize, f64, bool) {
    if radius2 > cap2 {
        let kept = list.iter().take_while(|&&u| dist2(u) <= cap2).count();
        (kept, cap2, true)
    } else {
        (list.len(), radius2, false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize) -> Vec<DVec3> {
        (0..n * n)
            .map(|i| DVec3::new((i % n) as f64, (i / n) as f64, 0.0))
            .collect()
    }

    #[test]
    fn the_sample_is_the_planners_whatever_the_order() {
        let pts = grid(30);
        let ties: Vec<u64> = (0..pts.len() as u64).map(|i| i * 7 + 3).collect();
        let a = sample(&pts, &ties);
        // Reversed input, same global indices: same sample, same order.
        let rp: Vec<DVec3> = pts.iter().rev().copied().collect();
        let rt: Vec<u64> = ties.iter().rev().copied().collect();
        assert_eq!(a, sample(&rp, &rt));
        assert_eq!(a.len(), pts.len());
    }

    #[test]
    fn typical_radius_of_a_unit_grid_is_about_two() {
        let pts = grid(40);
        let r = typical_radius(&pts, DVec3::ZERO, pts.len() as u64, 16).unwrap();
        // 8th other neighbour on a unit grid: √2, at the √(16/8) scale of k = 16: 2.
        assert!((r - 2.0).abs() < 1e-9, "{r}");
        // A sample of a quarter of a denser cloud: the radius halves.
        let r4 = typical_radius(&pts, DVec3::ZERO, 4 * pts.len() as u64, 16).unwrap();
        assert!((r4 - r / 2.0).abs() < 1e-9);
    }

    #[test]
    fn duplicate_stacks_do_not_make_the_radius_zero() {
        // A third of the points stacked ten deep: most probed radii are zero.
        let mut pts = grid(30);
        let copies: Vec<DVec3> = pts.iter().step_by(3).flat_map(|&p| [p; 9]).collect();
        pts.extend(copies);
        let r = typical_radius(&pts, DVec3::ZERO, pts.len() as u64, 16);
        assert!(r.is_some_and(|r| r > 0.0), "{r:?}");
        // Every point stacked: there is no spacing to measure, and no cap.
        assert_eq!(typical_radius(&[DVec3::ONE; 50], DVec3::ZERO, 50, 16), None);
    }

    /// [`typical_radius`] by brute force: every probe's 9th distance (itself included) among the
    /// finite sample points, the median of the positive ones, scaled.
    fn typical_radius_brute(sample: &[DVec3], population: u64, k: usize) -> Option<f64> {
        let ks = 8.min(sample.len().saturating_sub(1));
        let finite: Vec<DVec3> = sample.iter().copied().filter(|p| p.is_finite()).collect();
        let mut radii: Vec<f64> = (0..sample.len())
            .step_by((sample.len() / PROBES).max(1))
            .filter(|&i| sample[i].is_finite())
            .map(|i| {
                let mut d: Vec<f64> = finite
                    .iter()
                    .map(|p| {
                        let e = *p - sample[i];
                        e.x * e.x + e.y * e.y + e.z * e.z
                    })
                    .collect();
                d.sort_by(f64::total_cmp);
                d[ks.min(d.len() - 1)].sqrt()
            })
            .filter(|&r| r > 0.0)
            .collect();
        if radii.is_empty() {
            return None;
        }
        radii.sort_by(f64::total_cmp);
        let fraction = sample.len() as f64 / population.max(1) as f64;
        Some(radii[radii.len() / 2] * (k as f64 * fraction / ks as f64).sqrt())
    }

    #[test]
    #[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
    fn typical_radius_equals_brute_force_with_duplicates_and_non_finite_points() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(16);
        let mut rnd = move || rng.random::<f64>();
        // 9000 points (so probes are strided), a dense clump, duplicates and non-finite points.
        let mut pts: Vec<DVec3> = (0..9000)
            .map(|i| {
                let s = if i % 5 == 0 { 0.01 } else { 1.0 };
                DVec3::new(rnd() * 30.0 * s, rnd() * 30.0 * s, rnd() * s)
            })
            .collect();
        for i in 0..200 {
            pts[3000 + i] = pts[i];
        }
        pts[17] = DVec3::new(f64::NAN, 0.0, 0.0);
        pts[4096] = DVec3::INFINITY;
        let origin = DVec3::new(1e5, -2e5, 3.0);
        let shifted: Vec<DVec3> = pts.iter().map(|p| *p + origin).collect();
        let got = typical_radius(&shifted, origin, 3 * pts.len() as u64, 16).unwrap();
        let want = typical_radius_brute(&pts, 3 * pts.len() as u64, 16).unwrap();
        // Coordinates relative to the origin round differently from the unshifted ones.
        assert!((got - want).abs() <= 1e-9 * want, "{got} against {want}");
        let exact = typical_radius(&pts, DVec3::ZERO, 3 * pts.len() as u64, 16).unwrap();
        assert_eq!(exact, want);
        // Fewer finite points than a list needs: the fallback answers with the points there are.
        let tiny = [
            DVec3::ZERO,
            DVec3::X,
            DVec3::Y,
            DVec3::new(f64::NAN, 0.0, 0.0),
            DVec3::Z,
            DVec3::INFINITY,
            DVec3::new(f64::NAN, 1.0, 1.0),
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(f64::NAN, 2.0, 1.0),
            DVec3::new(f64::NAN, 3.0, 1.0),
        ];
        assert_eq!(
            typical_radius(&tiny, DVec3::ZERO, 10, 16),
            typical_radius_brute(&tiny, 10, 16)
        );
    }

    #[test]
    fn capping_keeps_near_members_and_marks_only_capped_lists() {
        // Points 0..5 on a line at unit spacing, point 5 far away.
        let pts = [0.0, 1.0, 2.0, 3.0, 4.0, 100.0].map(|x| DVec3::new(x, 0.0, 0.0));
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (lists, radii) = index.knn_all(3).unwrap();
        let d2 = |i: usize, u: usize| pts[i].distance_squared(pts[u]);
        let (capped, r, iso) = cap_lists(lists.clone(), radii.clone(), Some(10.0), d2);
        assert_eq!(iso, [false, false, false, false, false, true]);
        assert_eq!(capped.get(5), [5]);
        assert_eq!(r[5], 100.0);
        for i in 0..5 {
            assert_eq!(capped.get(i), lists.get(i));
            assert_eq!(r[i], radii[i]);
        }
        let (same, _, none) = cap_lists(lists.clone(), radii, None, d2);
        assert_eq!(same, lists);
        assert!(none.iter().all(|c| !c));
    }
}
