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
//!
//! With a [`Prune`], the caller says of each listed point whether it *stays*: whether what it
//! lends the points listing it reads only its members' own lists (the guarded operator's
//! points that do not move). Its members are then listed but not followed, so a cone of hops
//! stops one hop past such points instead of crossing them.

use rayon::prelude::*;

use super::{KnnIndex, Neighbourhoods, NeighboursError};

/// Once this share of the points is listed, the next round lists every point.
const ALL_SHARE: f64 = 0.5;

/// A listed point as the pruning of [`KnnIndex::knn_near`] sees it.
#[derive(Debug, Clone, Copy)]
pub struct Seen {
    /// How many of its list's members count (a prefix: the list as the caller caps it).
    pub members: usize,
    /// `Some(true)` when what it lends the points listing it reads its members' own lists and no
    /// more (a point that does not move), `Some(false)` when not, `None` while undecided (some
    /// member has no list yet, or no verdict was asked for).
    pub stays: Option<bool>,
}

/// The lists [`KnnIndex::knn_near`] has found so far.
pub struct Listed<'a> {
    found: &'a [u32],
    entries: &'a [(u32, u32, f64)],
    slot: &'a [u32],
}

impl Listed<'_> {
    /// Point `i`'s list and squared radius, once listed.
    pub fn get(&self, i: u32) -> Option<(&[u32], f64)> {
        let &(a, b, r) = self.entries.get(*self.slot.get(i as usize)? as usize)?;
        Some((&self.found[a as usize..b as usize], r))
    }
}

/// How [`KnnIndex::knn_near`] may stop short of `hops` hops: `seen(x, listed, decide)` tells
/// which members of listed point `x` count and, when `decide`, whether `x` stays; the members of
/// a point that stays are listed but not followed further. Points with fewer than `least` hops
/// left are not asked for a verdict (the caller knows nothing of them that far out).
pub struct Prune<'a> {
    /// The verdict on a listed point.
    pub seen: &'a mut dyn FnMut(u32, &Listed, bool) -> Seen,
    /// Fewest hops left at which a verdict is asked.
    pub least: usize,
}

impl KnnIndex {
    /// k-NN lists of every point within `hops` hops of a seed (`seeds[i]`), as
    /// [`KnnIndex::knn_all`] gives them; a point that is not listed (third value false) has the
    /// list `[itself]` and radius 0, and whatever depends on it must be treated as unknown. With
    /// `prune`, a path is followed only through points that do not stay (see [`Prune`]), and
    /// only along the members that count.
    ///
    /// # Errors
    /// As [`KnnIndex::knn_all`].
    pub fn knn_near(
        &self,
        k: usize,
        seeds: &[bool],
        hops: usize,
        mut prune: Option<Prune>,
    ) -> Result<(Neighbourhoods, Vec<f64>, Vec<bool>), NeighboursError> {
        let n = seeds.len();
        let mut listed = vec![false; n];
        // Hops left to follow from each point (-1: not needed).
        let mut left = vec![-1i32; n];
        let mut ask: Vec<u32> = (0..n as u32).filter(|&i| seeds[i as usize]).collect();
        for &i in &ask {
            left[i as usize] = hops as i32;
        }
        // Each listed point's list (start and end in `found`) and radius, in the order found.
        let mut found: Vec<u32> = Vec::new();
        let mut entries: Vec<(u32, u32, f64)> = Vec::new();
        let mut slot = vec![u32::MAX; n];
        let mut count = 0usize;
        // Verdicts asked for and given (they never change: the lists are final).
        let mut verdict: Vec<Option<Seen>> = Vec::new();
        if prune.is_some() {
            verdict = vec![None; n];
        }
        // Points followed from, by hops left; points whose verdict waits for a member's list.
        let mut buckets: Vec<Vec<u32>> = vec![Vec::new(); hops + 1];
        let mut waiting: Vec<u32> = Vec::new();
        // One first grid level for every round: each round asks a few more lists of the same
        // points, and rebuilding the level (a sort of the whole run) was most of their cost.
        let base = self.base_level(k)?;
        // A round per hop, and one more per hop where a verdict waits: bounded, and past the
        // bound the rest is listed at once (listing more is never wrong).
        let rounds = 2 * hops + 3;
        for round in 0..=rounds {
            if ask.is_empty() {
                break;
            }
            let all = round == rounds || count as f64 >= ALL_SHARE * n as f64;
            let mut asked = vec![false; n];
            if all {
                for (a, l) in asked.iter_mut().zip(&listed) {
                    *a = !*l;
                }
            } else {
                for &i in &ask {
                    asked[i as usize] = true;
                }
            }
            let (nb, radii, _) = self.knn_from(&base, k, Some(&asked))?;
            for i in (0..n).filter(|&i| asked[i]) {
                listed[i] = true;
                slot[i] = entries.len() as u32;
                count += 1;
                let start = found.len() as u32;
                found.extend_from_slice(nb.get(i));
                entries.push((start, found.len() as u32, radii[i]));
                if left[i] >= 1 {
                    buckets[left[i] as usize].push(i as u32);
                }
            }
            drop((nb, radii));
            if all {
                break;
            }
            for i in waiting.drain(..) {
                buckets[left[i as usize] as usize].push(i);
            }
            let view = Listed {
                found: &found,
                entries: &entries,
                slot: &slot,
            };
            let mut next = Vec::new();
            // From the most hops left down: a member is left fewer hops than its point, so
            // every point is followed once, at its final count.
            for b in (1..=hops).rev() {
                while let Some(x) = buckets[b].pop() {
                    if left[x as usize] != b as i32 {
                        continue;
                    }
                    let list = view.get(x).map_or(&[][..], |(l, _)| l);
                    let (members, onward) = match prune.as_mut() {
                        None => (list.len(), b as i32 - 1),
                        Some(p) => {
                            let decide = b >= p.least;
                            let seen = match verdict[x as usize] {
                                Some(v) if v.stays.is_some() || !decide => v,
                                _ => (p.seen)(x, &view, decide),
                            };
                            verdict[x as usize] = Some(seen);
                            match seen.stays {
                                Some(true) if decide => (seen.members, 0),
                                None if decide => {
                                    waiting.push(x);
                                    (seen.members, 0)
                                }
                                _ => (seen.members, b as i32 - 1),
                            }
                        }
                    };
                    for &u in &list[..members.min(list.len())] {
                        let was = left[u as usize];
                        if onward > was {
                            left[u as usize] = onward;
                            if listed[u as usize] {
                                if onward >= 1 {
                                    buckets[onward as usize].push(u);
                                }
                            } else if was < 0 {
                                next.push(u);
                            }
                        }
                    }
                }
            }
            ask = next;
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
            let (nb, radii, listed) = index.knn_near(8, &seeds, hops, None).unwrap();
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
            let (nb, radii, listed) = index.knn_near(8, &seeds, hops, None).unwrap();
            let want = within_hops(&all, &seeds, hops);
            assert_eq!(listed, want, "hops {hops}");
            for i in (0..pts.len()).filter(|&i| listed[i]) {
                assert_eq!(nb.get(i), all.get(i), "point {i}, hops {hops}");
                assert_eq!(radii[i].to_bits(), all_r[i].to_bits());
            }
        }
    }

    /// With a pruning that says the points at x ≥ 20 of the plane stay: those are listed with
    /// their members (the members' lists are what a verdict reads) but not followed, so nothing
    /// past two lists' reach beyond x = 20 is listed, while without it 40 hops from x = 5 reach the
    /// far side; and every list is the all-points one.
    #[test]
    fn issue16_points_that_stay_are_listed_with_their_members_and_not_followed() {
        let pts = cloud();
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (all, all_r) = index.knn_all(8).unwrap();
        let seeds: Vec<bool> = (0..pts.len()).map(|i| i == 30 * 60 + 5).collect();
        let hops = 40;
        let (_, _, free) = index.knn_near(8, &seeds, hops, None).unwrap();
        assert!((0..pts.len()).any(|i| free[i] && pts[i].x > 30.0));
        let mut seen = |x: u32, listed: &Listed, decide: bool| {
            let (list, _) = listed.get(x).expect("asked of listed points only");
            // The verdict reads the members' lists.
            let ready = list.iter().all(|&u| listed.get(u).is_some());
            Seen {
                members: list.len(),
                stays: (decide && ready).then(|| pts[x as usize].x >= 20.0),
            }
        };
        let kept = index
            .knn_near(
                8,
                &seeds,
                hops,
                Some(Prune {
                    seen: &mut seen,
                    least: 1,
                }),
            )
            .unwrap();
        let listed = &kept.2;
        let reach = all_r.iter().fold(0.0f64, |m, &r| m.max(r.sqrt()));
        // A point left of x = 20 is followed, and lists members up to `reach` past it; those
        // stay, and list theirs.
        for i in (0..pts.len()).filter(|&i| listed[i]) {
            assert!(pts[i].x <= 20.0 + 2.0 * reach, "point {i} at {}", pts[i]);
        }
        // Every point of the plane left of x = 17 is within reach of the seed through points that
        // move, and listed.
        assert!((0..3600).all(|i| pts[i].x >= 17.0 || listed[i]));
        assert_kept(&kept, (&all, &all_r), "pruned");
    }

    #[test]
    fn past_half_the_points_every_point_is_listed() {
        let pts = cloud();
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (all, _) = index.knn_all(8).unwrap();
        let seeds: Vec<bool> = (0..pts.len()).map(|i| i % 3 != 0).collect();
        let (nb, _, listed) = index.knn_near(8, &seeds, 5, None).unwrap();
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
                    let (near, near_r, near_listed) =
                        index.knn_near(8, &seeds, hops, None).unwrap();
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
