//! How far from a tile's wanted points each pass is needed, in k-NN hops: every point's hop depth
//! ([`hop_depths`]), the points each update moves ([`update_reach`]) and the depths of a guarded
//! cycle's passes ([`graded`]).

use crate::denoise::Schedule;
use crate::neighbours::Neighbourhoods;

/// Each point's number of hops from a seed along `lists` (a point `u` in the list of a point at
/// depth `d` is at most at depth `d + 1`), counted up to `most`; `u8::MAX` beyond.
pub(super) fn hop_depths(lists: &Neighbourhoods, seeds: &[bool], most: usize) -> Vec<u8> {
    let mut depth: Vec<u8> = seeds.iter().map(|&s| if s { 0 } else { u8::MAX }).collect();
    let mut frontier: Vec<u32> = (0..seeds.len() as u32)
        .filter(|&i| seeds[i as usize])
        .collect();
    for d in 1..=most.min(u8::MAX as usize - 1) {
        let mut next = Vec::new();
        for &i in &frontier {
            for &u in lists.get(i as usize) {
                if depth[u as usize] == u8::MAX {
                    depth[u as usize] = d as u8;
                    next.push(u);
                }
            }
        }
        frontier = next;
    }
    depth
}

/// The points update `u` (of `updates`, from 0) of the last cycle must move for the wanted points'
/// results: the update after it reads the positions of its list members, one hop further, so
/// update `u` is needed within `updates − 1 − u` hops; the first update's offsets also give the
/// gains, which read the offsets of the list (one hop more). Elsewhere nothing reads the result.
pub(super) fn update_reach(depth: &[u8], updates: usize, u: usize) -> Vec<bool> {
    let reach = updates - 1 - u + usize::from(u == 0);
    depth.iter().map(|&d| (d as usize) <= reach).collect()
}

/// How many hops from the wanted points each pass of a guarded cycle is needed (see
/// [`graded`]).
pub(super) struct Graded {
    /// What the updates read of a point and its list members: the noise scales and the filtered
    /// normals.
    pub(super) guard: usize,
    /// The classes (and so the planes the normal filter starts from).
    pub(super) classes: usize,
    /// The local fits.
    pub(super) fits: usize,
}

/// The passes of a guarded cycle graded by hops from the wanted points (the points whose
/// updates' results are kept). Update `u` of `U` moves the points within `U − 1 − u` hops (one
/// more for the first, whose offsets give the gains, [`update_reach`]), so the farthest update
/// reads a point `U` hops out and its list members, `U + 1` hops out: that is where the noise
/// scales and the filtered normals are needed. Each of the `F` filter iterations reads its input
/// one hop further, so the planes it starts from (the fits' normals where the class takes
/// planes) are needed `U + 1 + F` hops out; a class reads its list members' fits, one hop more.
/// Farther out a pass gives a placeholder that no kept result reads.
pub(super) fn graded(sched: &Schedule) -> Graded {
    let guard = sched.updates + 1;
    let classes = guard + sched.filter;
    Graded {
        guard,
        classes,
        fits: classes + 1,
    }
}
