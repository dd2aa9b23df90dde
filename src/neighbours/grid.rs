//! All-points k-NN on a uniform grid, with the k-d tree as the fallback.
//!
//! Hand-rolled on purpose: asking kiddo for the k nearest neighbours of every point costs about
//! 3 µs per point on this machine (k = 16, f64, queries in Morton order; `benches/kernels.rs`,
//! group `knn`), which alone is more than the whole operator's budget. Scans are dense and
//! locally uniform, so a grid whose cell is about one k-NN radius answers almost every query from
//! the 3 × 3 × 3 block around its cell, and all queries of a cell share one candidate list laid
//! out contiguously. Distances use the same formula as [`super::brute`], candidates are ranked by
//! (squared distance, tie key), and a query whose k-th distance is not provably inside the block
//! goes to the k-d tree, so the answer is exactly the brute-force one whatever the cell size.
//!
//! ```text
//!   cell size c ≈ 1.3 × median k-NN radius (from a sample)
//!   ┌───┬───┬───┐
//!   │   │   │   │   candidates of every query in the centre cell = the 27 cells around it;
//!   ├───┼───┼───┤   exact when the k-th distance < c + distance from the query to its own
//!   │   │ q │   │   cell's nearest face (nothing outside the block can be closer)
//!   ├───┼───┼───┤
//!   │   │   │   │
//!   └───┴───┴───┘
//! ```

use rustc_hash::FxHashMap;

use rayon::prelude::*;

/// Squared distance, coordinate by coordinate (the same formula as the oracle).
#[inline(always)]
pub(crate) fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

/// Packs signed cell coordinates into one key (21 bits each, offset to be non-negative).
#[inline]
fn key(c: [i64; 3]) -> u64 {
    const OFF: i64 = 1 << 20;
    ((c[0] + OFF) as u64) << 42 | ((c[1] + OFF) as u64) << 21 | (c[2] + OFF) as u64
}

/// Per-thread scratch: the candidate block of one cell in structure-of-arrays form.
#[derive(Default)]
struct Block {
    xs: Vec<f64>,
    ys: Vec<f64>,
    zs: Vec<f64>,
    ids: Vec<u32>,
    ties: Vec<u64>,
    d: Vec<f64>,
    sel: Vec<u32>,
    best: Vec<(u128, u32)>,
    /// The last answered query of this thread (any cell): its k-th distance bounds the next
    /// query's by the triangle inequality.
    prev: Option<([f64; 3], f64)>,
    /// Block positions of the last answered query's neighbours, while the block is unchanged:
    /// the farthest of them from the next query bounds its k-th distance tightly.
    prev_sel: Vec<u32>,
}

/// The answers of the grid pass for one cell: per point its index and k-th squared distance
/// (NaN when the k-d tree must answer instead) and, for answered points, k neighbours each in
/// `lists`, in the same order.
pub(crate) struct CellAnswers {
    /// (point index, k-th squared distance or NaN).
    pub(crate) points: Vec<(u32, f64)>,
    /// k neighbour indices per answered point, ascending by (distance, index).
    pub(crate) lists: Vec<u32>,
}

/// Runs the grid pass over the finite points of `local` with cells of side `cell` (> 0).
pub(crate) fn all_knn(
    local: &[[f64; 3]],
    ties: Option<&[u64]>,
    k: usize,
    cell: f64,
) -> Vec<CellAnswers> {
    let tie = |i: u32| ties.map_or(i as u64, |t| t[i as usize]);
    let finite = |p: &[f64; 3]| p.iter().all(|c| c.is_finite());
    let coord = |p: &[f64; 3]| -> [i64; 3] {
        [
            (p[0] / cell).floor() as i64,
            (p[1] / cell).floor() as i64,
            (p[2] / cell).floor() as i64,
        ]
    };
    // Points sorted by cell key, then along a Z-curve inside the cell (so consecutive queries
    // are close and the previous answer bounds the next one tightly), ties by index: each cell is
    // a contiguous run.
    let sub = |p: &[f64; 3], c: [i64; 3]| -> u16 {
        let mut z = 0u16;
        for a in 0..3 {
            let f = ((p[a] / cell - c[a] as f64) * 8.0).clamp(0.0, 7.0) as u16;
            for bit in 0..3 {
                z |= ((f >> bit) & 1) << (3 * bit + a);
            }
        }
        z
    };
    let mut keyed: Vec<(u64, u16, u32)> = local
        .par_iter()
        .enumerate()
        .filter(|(_, p)| finite(p))
        .map(|(i, p)| {
            let c = coord(p);
            (key(c), sub(p, c), i as u32)
        })
        .collect();
    keyed.par_sort_unstable();
    let mut runs: Vec<(u64, u32, u32)> = Vec::new();
    for (pos, &(kk, _, _)) in keyed.iter().enumerate() {
        match runs.last_mut() {
            Some(r) if r.0 == kk => r.2 = pos as u32 + 1,
            _ => runs.push((kk, pos as u32, pos as u32 + 1)),
        }
    }
    let table: FxHashMap<u64, (u32, u32)> = runs.iter().map(|&(kk, a, b)| (kk, (a, b))).collect();
    let sorted: Vec<u32> = keyed.iter().map(|&(_, _, i)| i).collect();
    drop(keyed);
    // A cell-ordered copy of the coordinates: gathering a block then reads contiguous memory
    // instead of jumping through the input order (that jump was most of the cost).
    let ordered: Vec<[f64; 3]> = sorted.par_iter().map(|&i| local[i as usize]).collect();

    runs.par_iter()
        .with_min_len(64)
        .map_init(Block::default, |blk, &(_, a, b)| {
            let c = coord(&ordered[a as usize]);
            blk.xs.clear();
            blk.ys.clear();
            blk.zs.clear();
            blk.ids.clear();
            blk.ties.clear();
            let push_ring = |blk: &mut Block, ring: i64| {
                for dz in -ring..=ring {
                    for dy in -ring..=ring {
                        for dx in -ring..=ring {
                            if dx.abs().max(dy.abs()).max(dz.abs()) != ring {
                                continue;
                            }
                            let Some(&(lo, hi)) =
                                table.get(&key([c[0] + dx, c[1] + dy, c[2] + dz]))
                            else {
                                continue;
                            };
                            let (lo, hi) = (lo as usize, hi as usize);
                            blk.ids.extend_from_slice(&sorted[lo..hi]);
                            blk.ties.extend(sorted[lo..hi].iter().map(|&i| tie(i)));
                            for p in &ordered[lo..hi] {
                                blk.xs.push(p[0]);
                                blk.ys.push(p[1]);
                                blk.zs.push(p[2]);
                            }
                        }
                    }
                }
            };
            blk.prev_sel.clear();
            push_ring(blk, 0);
            push_ring(blk, 1);
            let lo = [c[0] as f64 * cell, c[1] as f64 * cell, c[2] as f64 * cell];
            let n = (b - a) as usize;
            let mut out = CellAnswers {
                points: Vec::with_capacity(n),
                lists: Vec::with_capacity(n * k),
            };
            let mut retry = Vec::new();
            for (&qi, &q) in sorted[a as usize..b as usize]
                .iter()
                .zip(&ordered[a as usize..b as usize])
            {
                let r = query(blk, q, k, lo, cell, 1, &mut out.lists);
                if r.is_nan() {
                    retry.push(out.points.len());
                } else {
                    blk.prev = Some((q, r));
                }
                out.points.push((qi, r));
            }
            if !retry.is_empty() {
                // A second ring around the cell answers most of what the first could not
                // (points near a sparse border); the rest go to the k-d tree. Answers are
                // appended in retry order, so reorder the lists to follow `points`.
                push_ring(blk, 2);
                blk.prev_sel.clear();
                let mut extra = Vec::new();
                for &slot in &retry {
                    let qi = out.points[slot].0;
                    let q = local[qi as usize];
                    let r = query(blk, q, k, lo, cell, 2, &mut extra);
                    out.points[slot].1 = r;
                }
                if extra.is_empty() {
                    return out;
                }
                let mut lists = Vec::with_capacity(out.lists.len() + extra.len());
                let (mut first, mut second) = (0, 0);
                let mut next_retry = retry.iter().peekable();
                for (slot, &(_, r)) in out.points.iter().enumerate() {
                    let retried = next_retry.peek() == Some(&&slot);
                    if retried {
                        next_retry.next();
                        if !r.is_nan() {
                            lists.extend_from_slice(&extra[second..second + k]);
                            second += k;
                        }
                    } else if !r.is_nan() {
                        lists.extend_from_slice(&out.lists[first..first + k]);
                        first += k;
                    }
                }
                out.lists = lists;
            }
            out
        })
        .collect()
}

#[inline(always)]
pub(crate) fn rank(d: f64, tie: u64) -> u128 {
    (d.to_bits() as u128) << 64 | tie as u128
}

/// The squared distance inside a [`rank`].
#[inline(always)]
pub(crate) fn rank_distance(r: u128) -> f64 {
    f64::from_bits((r >> 64) as u64)
}

/// Appends the k nearest candidates of `q` in the block (the cells within `ring` of its own,
/// whose lower corner is `lo`) to `lists` and returns the k-th squared distance, or returns NaN
/// (appending nothing) when the block cannot prove the answer complete.
///
/// `blk.prev` is an earlier answered query: by the triangle inequality its k neighbours lie within
/// `√d_prev + |q − q_prev|` of `q`, which bounds this query's k-th distance and lets all but a
/// few candidates be discarded with one comparison.
fn query(
    blk: &mut Block,
    q: [f64; 3],
    k: usize,
    lo: [f64; 3],
    cell: f64,
    ring: i64,
    lists: &mut Vec<u32>,
) -> f64 {
    let m = blk.ids.len();
    if m < k {
        return f64::NAN;
    }
    blk.d.clear();
    blk.d
        .extend((0..m).map(|j| dist2(q, [blk.xs[j], blk.ys[j], blk.zs[j]])));
    let t = if blk.prev_sel.len() == k {
        // k block members lie within the farthest of them: an exact bound, same formula.
        blk.prev_sel
            .iter()
            .map(|&j| blk.d[j as usize])
            .fold(0.0, f64::max)
    } else {
        match blk.prev {
            Some((pq, pr)) => {
                let bound = pr.sqrt() + dist2(q, pq).sqrt();
                // Widened so rounding in either distance cannot drop a true member.
                bound * bound * (1.0 + 1e-9) + f64::MIN_POSITIVE
            }
            None => f64::INFINITY,
        }
    };
    // Branchless compaction of the candidates within the bound.
    let sel = &mut blk.sel;
    sel.clear();
    sel.resize(m, 0);
    let mut kept = 0;
    for j in 0..m {
        sel[kept] = j as u32;
        kept += (blk.d[j] <= t) as usize;
    }
    if kept < k {
        for (j, s) in sel.iter_mut().enumerate() {
            *s = j as u32;
        }
        kept = m;
    }
    let best = &mut blk.best;
    best.clear();
    best.extend(sel[..kept].iter().map(|&j| {
        let ju = j as usize;
        (rank(blk.d[ju], blk.ties[ju]), j)
    }));
    if kept > 2 * k {
        best.select_nth_unstable(k - 1);
        best.truncate(k);
    }
    best.sort_unstable();
    let dk = rank_distance(best[k - 1].0);
    // Any point outside the block is at least `reach` away.
    let mut inner = f64::INFINITY;
    for a in 0..3 {
        inner = inner.min(q[a] - lo[a]).min(lo[a] + cell - q[a]);
    }
    let reach = ring as f64 * cell + inner.max(0.0);
    // Strict, with a relative margin for the rounding of `dist2`.
    blk.prev_sel.clear();
    blk.prev_sel.extend(best[..k].iter().map(|e| e.1));
    if dk < reach * reach * (1.0 - 1e-9) {
        lists.extend(best[..k].iter().map(|e| blk.ids[e.1 as usize]));
        dk
    } else {
        f64::NAN
    }
}
