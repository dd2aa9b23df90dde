//! k-NN lists of the points a few hops from some seeds: what a run needs when only the seeds'
//! results are wanted and those depend on `hops` hops of the k-NN graph.
//!
//! ```text
//!   round 0: lists of the seeds
//!   round h: lists of the members of round h − 1's lists that have none yet   (h = 1 … hops)
//!   the rest: no list of their own (only themselves, radius 0), reported as not listed
//! ```
//!
//! A tile loads its core and a halo wide enough for its farthest outlier's ball, and the kernel
//! only needs exact results for the core; the hops of a surface reach a thin shell of that halo.
//! Every indexed point stays a candidate, so a listed point's list is the one
//! [`KnnIndex::knn_all`] gives it, bit for bit. Once the listed points are most of the cloud, one
//! last round lists all the rest (a round costs a pass over the grid's cells, whatever its
//! share; the grid's first level is built once for all rounds).

use rayon::prelude::*;

use super::{KnnIndex, Neighbourhoods, NeighboursError};

/// Once this share of the points is listed, the next round lists every point.
const ALL_SHARE: f64 = 0.5;

impl KnnIndex {
    /// k-NN lists of every point within `hops` hops of a seed (`seeds[i]`), as
    /// [`KnnIndex::knn_all`] gives them; a point that is not listed (third value false) has the
    /// list `[itself]` and radius 0, and whatever depends on it must be treated as unknown.
    ///
    /// # Errors
    /// As [`KnnIndex::knn_all`].
    pub fn knn_near(
        &self,
        k: usize,
        seeds: &[bool],
        hops: usize,
    ) -> Result<(Neighbourhoods, Vec<f64>, Vec<bool>), NeighboursError> {
        let n = seeds.len();
        let mut listed = vec![false; n];
        let mut ask: Vec<bool> = seeds.to_vec();
        // Each listed point's list (start and end in `found`) and radius, in the order found.
        let mut found: Vec<u32> = Vec::new();
        let mut entries: Vec<(u32, u32, f64)> = Vec::new();
        let mut slot = vec![u32::MAX; n];
        let mut count = 0usize;
        // One first grid level for every round: each round asks a few more lists of the same
        // points, and rebuilding the level (a sort of the whole run) was most of their cost.
        let base = self.base_level(k)?;
        for round in 0..=hops {
            let all = count as f64 >= ALL_SHARE * n as f64;
            if all {
                for (a, l) in ask.iter_mut().zip(&listed) {
                    *a = !*l;
                }
            }
            let (nb, radii, _) = self.knn_from(&base, k, Some(&ask))?;
            let mut next = vec![false; n];
            for i in (0..n).filter(|&i| ask[i]) {
                listed[i] = true;
                slot[i] = entries.len() as u32;
                count += 1;
                let list = nb.get(i);
                let start = found.len() as u32;
                found.extend_from_slice(list);
                entries.push((start, found.len() as u32, radii[i]));
                for &u in list {
                    next[u as usize] = true;
                }
            }
            drop((nb, radii));
            if all {
                break;
            }
            for (a, (nx, l)) in ask.iter_mut().zip(next.iter().zip(&listed)) {
                *a = *nx && !*l;
            }
            if round == hops || !ask.iter().any(|&a| a) {
                break;
            }
        }
        // One CSR of every round's lists.
        let mut offsets = Vec::with_capacity(n + 1);
        offsets.push(0u32);
        let mut indices = Vec::new();
        let mut radii = vec![0.0; n];
        for i in 0..n {
            match entries.get(slot[i] as usize) {
                Some(&(a, b, r)) => {
                    indices.extend_from_slice(&found[a as usize..b as usize]);
                    radii[i] = r;
                }
                None => indices.push(i as u32),
            }
            offsets.push(indices.len() as u32);
        }
        Ok((Neighbourhoods { offsets, indices }, radii, listed))
    }
}

/// Keeps, of the complete lists `lists` (and `radii`, as [`KnnIndex::knn_all`] gives them), those
/// of the points within `hops` hops of a seed: the lists and radii [`KnnIndex::knn_near`] gives
/// them, bit for bit, and which points are listed (empty when all are, or when fewer than
/// [`KEEP_ALL_BELOW`] of them would be dropped: then every list is kept). Where the seeds are many, one
/// grid pass over every point and a walk over the graph cost less than a pass per hop, and every
/// later pass of the operator skips the points no seed depends on (docs/DECISIONS.md, "A tile
/// computes only what its owned results depend on").
pub fn keep_near(
    lists: Neighbourhoods,
    radii: Vec<f64>,
    seeds: &[bool],
    hops: usize,
) -> (Neighbourhoods, Vec<f64>, Vec<bool>) {
    use std::sync::atomic::{AtomicBool, Ordering};
    let n = seeds.len();
    // The walk, a hop at a time over the frontier, in parallel: a point joins once (`swap`), so
    // the set reached does not depend on the threads.
    let reached: Vec<AtomicBool> = seeds.iter().map(|&s| AtomicBool::new(s)).collect();
    let mut frontier: Vec<u32> = (0..n as u32).filter(|&i| seeds[i as usize]).collect();
    for _ in 0..hops {
        let next: Vec<u32> = frontier
            .par_iter()
            .with_min_len(1024)
            .flat_map_iter(|&i| {
                lists
                    .get(i as usize)
                    .iter()
                    .copied()
                    .filter(|&u| !reached[u as usize].swap(true, Ordering::Relaxed))
                    .collect::<Vec<u32>>()
            })
            .collect();
        if next.is_empty() {
            break;
        }
        frontier = next;
    }
    let listed: Vec<bool> = reached.into_iter().map(AtomicBool::into_inner).collect();
    // Nearly everything reached: keep every list (listing more is never wrong) and skip the copy.
    let dropped = listed.iter().filter(|&&l| !l).count();
    if (dropped as f64) < KEEP_ALL_BELOW * n as f64 {
        return (lists, radii, Vec::new());
    }
    // The kept lists in CSR order, built a block of points at a time in parallel.
    const BLOCK: usize = 1 << 14;
    let blocks: Vec<(Vec<u32>, Vec<u32>)> = (0..n.div_ceil(BLOCK))
        .into_par_iter()
        .map(|b| {
            let (mut lens, mut idx) = (Vec::with_capacity(BLOCK), Vec::new());
            let start = b * BLOCK;
            for (i, &l) in listed.iter().enumerate().skip(start).take(BLOCK) {
                if l {
                    idx.extend_from_slice(lists.get(i));
                } else {
                    idx.push(i as u32);
                }
                lens.push(idx.len() as u32);
            }
            (lens, idx)
        })
        .collect();
    let mut offsets = Vec::with_capacity(n + 1);
    offsets.push(0u32);
    let mut indices = Vec::with_capacity(lists.indices.len());
    for (lens, idx) in blocks {
        let base = indices.len() as u32;
        offsets.extend(lens.iter().map(|&l| base + l));
        indices.extend_from_slice(&idx);
    }
    let radii = radii
        .into_iter()
        .zip(&listed)
        .map(|(r, &l)| if l { r } else { 0.0 })
        .collect();
    (Neighbourhoods { offsets, indices }, radii, listed)
}

/// [`keep_near`] keeps every list when fewer than this share of the points would be dropped.
const KEEP_ALL_BELOW: f64 = 0.05;

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;

    /// A plane of 60 × 60 points with a dense blob on it, in a fixed order.
    fn cloud() -> Vec<DVec3> {
        let mut pts: Vec<DVec3> = (0..3600)
            .map(|i| DVec3::new((i % 60) as f64, (i / 60) as f64, 0.0))
            .collect();
        pts.extend((0..400).map(|i| {
            let a = i as f64 * 2.399;
            DVec3::new(
                30.0 + 0.3 * a.cos(),
                30.0 + 0.3 * a.sin(),
                0.01 * (i % 7) as f64,
            )
        }));
        pts
    }

    /// A listed point has its all-points list and radius, bit for bit; any other only itself and
    /// radius 0.
    fn assert_kept(
        (nb, radii, listed): &(Neighbourhoods, Vec<f64>, Vec<bool>),
        (all, all_r): (&Neighbourhoods, &[f64]),
        case: &str,
    ) {
        for (i, &l) in listed.iter().enumerate() {
            if l {
                assert_eq!(nb.get(i), all.get(i), "{case}, point {i}");
                assert_eq!(radii[i].to_bits(), all_r[i].to_bits(), "{case}, point {i}");
            } else {
                assert_eq!(nb.get(i), &[i as u32], "{case}, point {i}");
                assert_eq!(radii[i], 0.0, "{case}, point {i}");
            }
        }
    }

    /// The points within `hops` hops of a seed in the graph `all`.
    fn within_hops(all: &Neighbourhoods, seeds: &[bool], hops: usize) -> Vec<bool> {
        let mut want = seeds.to_vec();
        for _ in 0..hops {
            let mut next = want.clone();
            for i in (0..want.len()).filter(|&i| want[i]) {
                for &u in all.get(i) {
                    next[u as usize] = true;
                }
            }
            want = next;
        }
        want
    }

    #[test]
    fn listed_points_get_the_all_points_lists_and_the_rest_only_themselves() {
        let pts = cloud();
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (all, all_r) = index.knn_all(8).unwrap();
        // Seeds: a 4 × 4 patch in a corner, far from the blob.
        let seeds: Vec<bool> = (0..pts.len())
            .map(|i| i < 3600 && i % 60 < 4 && i / 60 < 4)
            .collect();
        for hops in 0..4 {
            let (nb, radii, listed) = index.knn_near(8, &seeds, hops).unwrap();
            // Exactly the points within `hops` hops of a seed are listed.
            let want = within_hops(&all, &seeds, hops);
            assert_eq!(listed, want, "hops {hops}");
            assert!(listed.iter().filter(|&&l| l).count() < 400, "hops {hops}");
            assert_kept(
                &(nb, radii, listed),
                (&all, &all_r),
                &format!("hops {hops}"),
            );
        }
    }

    /// Seeds inside the dense blob: its cells are refined into finer levels in every round, while
    /// the first level is shared by all rounds; lists and radii stay the all-points ones.
    #[test]
    fn issue16_rounds_through_a_refined_blob_share_the_first_level_and_keep_the_lists() {
        let pts = cloud();
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (all, all_r, work) = index.knn_all_counted(8).unwrap();
        assert!(work.levels > 1, "the blob must be refined: {work:?}");
        let seeds: Vec<bool> = (0..pts.len()).map(|i| i >= 3600 && i % 50 == 0).collect();
        for hops in 0..4 {
            let (nb, radii, listed) = index.knn_near(8, &seeds, hops).unwrap();
            let want = within_hops(&all, &seeds, hops);
            assert_eq!(listed, want, "hops {hops}");
            for i in (0..pts.len()).filter(|&i| listed[i]) {
                assert_eq!(nb.get(i), all.get(i), "point {i}, hops {hops}");
                assert_eq!(radii[i].to_bits(), all_r[i].to_bits());
            }
        }
    }

    #[test]
    fn past_half_the_points_every_point_is_listed() {
        let pts = cloud();
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (all, _) = index.knn_all(8).unwrap();
        let seeds: Vec<bool> = (0..pts.len()).map(|i| i % 3 != 0).collect();
        let (nb, _, listed) = index.knn_near(8, &seeds, 5).unwrap();
        assert!(listed.iter().all(|&l| l));
        assert_eq!(nb, all);
    }

    /// Dropping the lists no seed depends on from the all-points graph keeps exactly the points
    /// within `hops` hops of a seed, with their all-points lists and radii bit for bit (what the
    /// rounds give below half the points listed), or every list when nearly all are reached.
    #[test]
    fn issue16_kept_lists_of_the_whole_graph_are_those_within_the_hops() {
        let pts = cloud();
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (all, all_r) = index.knn_all(8).unwrap();
        let seeds_of: [&dyn Fn(usize) -> bool; 3] = [
            &|i| i < 3600 && i % 60 < 4 && i / 60 < 4,
            &|i| i >= 3600 && i % 50 == 0,
            &|i| i % 60 < 30,
        ];
        for (s, seeds_at) in seeds_of.iter().enumerate() {
            let seeds: Vec<bool> = (0..pts.len()).map(seeds_at).collect();
            for hops in 0..5 {
                let (nb, radii, listed) = keep_near(all.clone(), all_r.clone(), &seeds, hops);
                let want = within_hops(&all, &seeds, hops);
                let out = want.iter().filter(|&&w| !w).count() as f64;
                if out < KEEP_ALL_BELOW * pts.len() as f64 {
                    // Nearly all reached: every list kept.
                    assert!(listed.is_empty(), "seeds {s}, hops {hops}");
                    assert_eq!(nb, all);
                    continue;
                }
                let wrong = (0..pts.len()).filter(|&i| listed[i] != want[i]).count();
                assert_eq!(wrong, 0, "seeds {s}, hops {hops}");
                if s == 0 {
                    let (near, near_r, near_listed) = index.knn_near(8, &seeds, hops).unwrap();
                    assert_eq!(near_listed, listed);
                    assert_eq!(near, nb);
                    assert!(
                        near_r
                            .iter()
                            .zip(&radii)
                            .all(|(a, b)| a.to_bits() == b.to_bits())
                    );
                }
                let kept = (nb, radii, listed);
                assert_kept(&kept, (&all, &all_r), &format!("seeds {s}, hops {hops}"));
            }
        }
    }
}
