//! A run's k-NN graph in spatial order ([`Graph`]): listed in one grid pass, or round by round
//! from the wanted points of a tile ([`listing`], with [`Stays`] deciding as lists arrive which
//! points stay where they are), then capped at the isolation radius ([`capped`]).

use glam::DVec3;

use super::CloudRun;
use crate::denoise::DenoiseError;
use crate::denoise::frame::Frame;
use crate::denoise::isolation::{cap_one, is_isolated};
use crate::denoise::structure::{Beams, LocalFit, Structure, class_of, local_fit};
use crate::neighbours::{KnnIndex, Listed, Neighbourhoods, Prune, Seen, keep_near};

/// The k-NN graph of a run in spatial order, capped at the isolation radius.
pub(super) struct Graph {
    /// The run's points in spatial order.
    pub(super) frame: Frame,
    /// Lists in frame indices, capped at the run's isolation radius.
    pub(super) lists: Neighbourhoods,
    /// Squared radius of each list (the cap for a capped one).
    pub(super) radii: Vec<f64>,
    /// The index the lists come from.
    pub(super) index: KnnIndex,
    /// Which lists were capped (shorter than k).
    pub(super) capped: Vec<bool>,
    /// Which points are isolated: capped lists shorter than
    /// [`crate::denoise::isolation::least_list`].
    pub(super) isolated: Vec<bool>,
    /// Which points have their own list (empty: all): the others' results are not exact.
    pub(super) listed: Vec<bool>,
    /// Each point's beam ([`CloudRun::beams`]) in frame order, `None` without beams.
    pub(super) beams: Option<Vec<DVec3>>,
}

/// What round-by-round listing needs to stop at the points that stay ([`Stays`]): the hops
/// left ([`Prune::least`]) and the scan's noise along the beams (the classes read it).
#[derive(Debug, Clone, Copy)]
pub(super) struct Stops {
    /// Hops left, see [`Prune::least`].
    pub(super) least: usize,
    /// [`crate::denoise::cloud::Globals::noise`].
    pub(super) noise: f64,
}

/// [`CloudRun::wanted`] points are listed round by round (with what they depend on) only when
/// they are at most this share of the run: every further hop costs a grid pass over the whole
/// run. Above it every list is computed in one pass and those no wanted point depends on are
/// dropped ([`keep_near`]).
const WANTED_SHARE: f64 = 0.25;

/// Builds the k-NN graph of a run in spatial order; with [`CloudRun::wanted`] points, only the
/// lists within `hops` hops of them (the others' results are not exact, and cost nothing in the
/// passes that follow).
/// With `stops` (hops left, see [`Prune::least`]), round by round listing does not follow the
/// points that stay ([`Stays`]).
pub(super) fn graph(
    run: &CloudRun,
    k: usize,
    hops: usize,
    stops: Option<Stops>,
) -> Result<Graph, DenoiseError> {
    Ok(capped(run, k, listing(run, k, hops, stops)?))
}

/// A run's k-NN lists before the isolation cap ([`graph`]'s first half).
pub(super) struct Listing {
    pub(super) frame: Frame,
    pub(super) index: KnnIndex,
    pub(super) lists: Neighbourhoods,
    pub(super) radii: Vec<f64>,
    pub(super) listed: Vec<bool>,
    pub(super) beams: Option<Vec<DVec3>>,
}

/// The lists of [`graph`], not capped yet. Without [`CloudRun::wanted`] points the run's
/// isolation radius is not read.
pub(super) fn listing(
    run: &CloudRun,
    k: usize,
    hops: usize,
    stops: Option<Stops>,
) -> Result<Listing, DenoiseError> {
    let frame = Frame::new(run.positions, Some(run.ties));
    let beams = in_frame(&frame, run.beams);
    let index = KnnIndex::build_with_ties(&frame.positions, run.origin, frame.ties.clone())?;
    let seeds: Option<(Vec<bool>, bool)> = run.wanted.map(|w| {
        let n = w.iter().filter(|&&x| x).count();
        let few = n as f64 <= WANTED_SHARE * w.len() as f64;
        (frame.order.iter().map(|&i| w[i as usize]).collect(), few)
    });
    let (lists, radii, listed) = match seeds {
        Some((s, true)) => {
            let mut stays = Stays {
                pos: &frame.positions,
                beams: Beams {
                    dirs: beams.as_deref(),
                    noise: stops.map_or(0.0, |s| s.noise),
                },
                index: &index,
                cap2: run.isolation.map(|c| c * c),
                least: crate::denoise::isolation::least_list(k, run.short_lists),
                own: vec![None; s.len()],
                members: Vec::new(),
                buf: Vec::new(),
            };
            let mut seen = |x: u32, listed: &Listed, decide: bool| stays.seen(x, listed, decide);
            let prune = stops.map(|s| Prune {
                seen: &mut seen,
                least: s.least,
            });
            index.knn_near(k, &s, hops, prune)?
        }
        Some((s, false)) => {
            let (lists, radii) = index.knn_all(k)?;
            keep_near(lists, radii, &s, hops)
        }
        None => {
            let (lists, radii) = index.knn_all(k)?;
            (lists, radii, Vec::new())
        }
    };
    Ok(Listing {
        frame,
        index,
        lists,
        radii,
        listed,
        beams,
    })
}

/// `beams` (input order) in `frame`'s order.
fn in_frame(frame: &Frame, beams: Option<&[DVec3]>) -> Option<Vec<DVec3>> {
    beams.map(|b| frame.order.iter().map(|&i| b[i as usize]).collect())
}

/// [`graph`] from its [`listing`]: the lists capped at the run's isolation radius.
pub(super) fn capped(run: &CloudRun, k: usize, listing: Listing) -> Graph {
    let Listing {
        frame,
        index,
        lists,
        radii,
        listed,
        beams,
    } = listing;
    // A listing made before the run had its beams (the in-memory run lists once for the
    // isolation radius) takes them now.
    let beams = beams.or_else(|| in_frame(&frame, run.beams));
    let (lists, radii, capped) =
        crate::denoise::isolation::cap_lists(lists, radii, run.isolation, |i, u| index.dist2(i, u));
    let least = crate::denoise::isolation::least_list(k, run.short_lists);
    let isolated = (0..lists.len())
        .map(|i| is_isolated(capped[i], lists.get(i).len(), least))
        .collect();
    Graph {
        frame,
        lists,
        radii,
        index,
        capped,
        isolated,
        listed,
        beams,
    }
}

/// [`crate::denoise::isolation::typical_radius`] of a whole cloud of `population` points from its own
/// uncapped lists of `k`, when the planner's sample is that cloud (at most
/// [`crate::denoise::isolation::SAMPLE`] points, the run's order being the global-index order): each
/// probe's distance to its `ks`-th sample neighbour is its list's entry `ks` (lists are sorted by
/// distance, the same distances to the bit). `None` when lists of `k` are too short for it.
pub(super) fn typical_from_lists(l: &Listing, population: u64, k: usize) -> Option<Option<f64>> {
    let n = l.frame.positions.len();
    let Some((probes, ks)) = crate::denoise::isolation::probes(n) else {
        return Some(None);
    };
    if ks >= k {
        return None;
    }
    let radii = probes
        .map(|i| {
            let j = l.frame.working(i);
            l.lists
                .get(j)
                .get(ks)
                .map_or(0.0, |&u| l.index.dist2(j, u as usize).sqrt())
        })
        .collect();
    Some(crate::denoise::isolation::typical_of(
        radii, n, population, k, ks,
    ))
}

/// Whether a listed point stays where it is whatever lies past its members' lists: its class,
/// from its capped list and its members' own classes and radii, does not move (the rule of
/// `run_on`'s `settled`, computed as the lists are found).
struct Stays<'a> {
    pos: &'a [DVec3],
    /// The beams in frame order and the scan's noise (the classes read them).
    beams: Beams<'a>,
    index: &'a KnnIndex,
    /// The isolation radius, squared.
    cap2: Option<f64>,
    /// Shortest list of a point that is not isolated.
    least: usize,
    /// Each listed point's own class, capped squared radius and members kept, once computed.
    own: Vec<Option<(Structure, f64, usize)>>,
    /// Scratch: the members of the point being decided, and their radii for the median.
    members: Vec<(u32, Structure, f64)>,
    buf: Vec<f64>,
}

impl Stays<'_> {
    /// Point `u`'s own class, capped squared radius and members kept (`None` before its list).
    fn own(&mut self, u: u32, listed: &Listed) -> Option<(Structure, f64, usize)> {
        if let Some(o) = self.own[u as usize] {
            return Some(o);
        }
        let (list, r2) = listed.get(u)?;
        let index = self.index;
        let (kept, r2, capped) = match self.cap2 {
            Some(c) => cap_one(list, r2, c, |w| index.dist2(u as usize, w as usize)),
            None => (list.len(), r2, false),
        };
        let class = if is_isolated(capped, kept, self.least) {
            LocalFit::isolated().own
        } else {
            local_fit(self.pos, &list[..kept], u as usize, self.beams).own
        };
        self.own[u as usize] = Some((class, r2, kept));
        Some((class, r2, kept))
    }

    fn seen(&mut self, x: u32, listed: &Listed, decide: bool) -> Seen {
        let Some((own, r2, kept)) = self.own(x, listed) else {
            return Seen {
                members: 0,
                stays: None,
            };
        };
        let undecided = Seen {
            members: kept,
            stays: None,
        };
        if !decide {
            return undecided;
        }
        let Some((list, _)) = listed.get(x) else {
            return undecided;
        };
        let mut members = std::mem::take(&mut self.members);
        members.clear();
        for &u in &list[..kept] {
            match self.own(u, listed) {
                Some((c, r, _)) => members.push((u, c, r)),
                None => {
                    self.members = members;
                    return undecided;
                }
            }
        }
        let class = class_of(
            x as usize,
            (own, r2),
            members.iter().copied(),
            &mut self.buf,
        );
        self.members = members;
        Seen {
            members: kept,
            stays: Some(!class.moves()),
        }
    }
}
