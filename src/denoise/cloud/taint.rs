//! Where a run's results may differ from the whole cloud's ([`Taint`]): seeded by the points
//! without a list of their own and those whose k-NN ball leaves the run's region, then spread
//! hop by hop along the lists.

use glam::DVec3;
use rayon::prelude::*;

use super::CloudRun;
use super::graph::Graph;
use crate::neighbours::Neighbourhoods;
use crate::points::Aabb;

/// True where the k-NN ball of a point lies strictly inside `region` (so its list is complete).
fn inside(region: &Aabb, p: DVec3, r2: f64) -> bool {
    let lo = p - region.min;
    let hi = region.max - p;
    let d = lo.min(hi).min_element();
    // A relative margin covers the rounding of the squared distances.
    d > 0.0 && d * d > r2 * (1.0 + 1e-9) + f64::MIN_POSITIVE
}

/// Where a run's results may differ from the whole cloud's: seeded by the points without a list
/// of their own and those whose k-NN ball leaves the region (and is not proven complete), then
/// spread hop by hop to every point whose list holds a tainted one ([`Taint::spread`]).
pub(super) struct Taint {
    /// Hop 0: the seeds.
    pub(super) seeds: Vec<bool>,
    /// Hop 1: what a point's class reads (its own list, its members' fits and radii).
    pub(super) class: Vec<bool>,
    /// False for a run without a region: only its unlisted points are unknown, and the lists
    /// of every point within the reach of a wanted one are computed, so nothing spreads.
    pub(super) spreads: bool,
}

impl Taint {
    pub(super) fn of(run: &CloudRun, g: &Graph) -> Taint {
        let (pos, lists, radii) = (&g.frame.positions, &g.lists, &g.radii);
        let unlisted = |i: usize| g.listed.get(i).is_some_and(|l| !l);
        let Some(region) = run.region.as_ref() else {
            let seeds: Vec<bool> = (0..pos.len()).map(unlisted).collect();
            return Taint {
                class: seeds.clone(),
                seeds,
                spreads: false,
            };
        };
        let seeds: Vec<bool> = (0..pos.len())
            .into_par_iter()
            .map(|i| {
                unlisted(i)
                    || (!inside(region, pos[i], radii[i])
                        && !run.complete.is_some_and(|c| c(pos[i], radii[i])))
            })
            .collect();
        let class = spread_once(lists, &seeds, None);
        Taint {
            seeds,
            class,
            spreads: true,
        }
    }

    /// The taint after `hops` hops, not spread through the `blocked` points: those whose
    /// contribution to the points listing them is exact whatever lies farther out.
    pub(super) fn spread(
        &self,
        lists: &Neighbourhoods,
        hops: usize,
        blocked: &[bool],
    ) -> Vec<bool> {
        let mut t = self.seeds.clone();
        if !self.spreads {
            return t;
        }
        for _ in 0..hops {
            let next = spread_once(lists, &t, Some(blocked));
            if next == t {
                break;
            }
            t = next;
        }
        t
    }
}

/// One hop of taint: `t` and every point whose list holds a tainted point that is not `blocked`.
fn spread_once(lists: &Neighbourhoods, t: &[bool], blocked: Option<&[bool]>) -> Vec<bool> {
    let passes = |u: u32| t[u as usize] && blocked.is_none_or(|b| !b[u as usize]);
    (0..t.len())
        .into_par_iter()
        .map(|i| t[i] || lists.get(i).iter().any(|&u| passes(u)))
        .collect()
}
