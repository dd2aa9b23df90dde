//! Scalars a point operator reads over the whole cloud ([`Globals`]): the bilateral spacing and
//! the guarded operator's sensor noise, from partial sums that merge across tiles to the same
//! bits as over the whole cloud ([`GlobalsPartial`]).
//!
//! The in-memory run takes them from its own lists ([`partial_of`]); a tiled run sums each
//! tile's exact contributions in a pre-pass ([`globals_partial`]) and merges them.

use glam::DVec3;
use rayon::prelude::*;

use super::graph::{Graph, graph};
use super::taint::Taint;
use super::{CloudRun, guarded_qem};
use crate::denoise::{DenoiseError, Method, Params};
use crate::geometry::ExactSum;

/// Scalars computed over the whole cloud before the operator runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Globals {
    /// Mean distance from a point to its nearest other point (the point-cloud L); the bilateral
    /// σc. Zero when the method does not need it.
    pub spacing: f64,
    /// The sensor's noise: the median over all points of [`crate::denoise::structure::near_residual`]
    /// (the RMS residual of a point's nearest 8 about their own plane, or line where they lie on
    /// one, or along the beam where beams are known), read as the upper edge of its 2 % histogram
    /// bin. It caps every guarded step (one scan, one sensor, one noise level, so a
    /// coarse far-range neighbourhood cannot license a step of its own coarse scale). Zero when
    /// the method does not need it.
    #[serde(default)]
    pub noise: f64,
}

/// The mergeable parts behind [`Globals`]: partial sums over some points (a tile's owned ones).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GlobalsPartial {
    /// Nearest-other distances (bilateral).
    pub spacing: ExactSum,
    /// Small-scale residuals (the guarded operator).
    pub noise: crate::denoise::Displacements,
}

impl GlobalsPartial {
    /// Adds another partial.
    pub fn merge(&mut self, o: &GlobalsPartial) {
        self.spacing.merge(&o.spacing);
        self.noise.merge(&o.noise);
    }

    /// The global scalars.
    pub fn finish(&self) -> Globals {
        Globals {
            spacing: if self.spacing.count() > 0 {
                self.spacing.mean()
            } else {
                0.0
            },
            noise: self.noise.quantile(0.5),
        }
    }
}

/// The noise pre-pass reads every point of a cloud of up to twice this many finite points, and
/// a sample of about this many (at least) of a larger one ([`in_noise_sample`]).
pub const NOISE_SAMPLE: u64 = 1 << 16;

/// True when the point of global index `index`, in a cloud of `points` finite points, is one the
/// guarded operator's noise ([`Globals::noise`]) is the median over: every point of a cloud of
/// fewer than `2 × NOISE_SAMPLE`, otherwise one in `points / NOISE_SAMPLE` (by
/// [`crate::points::sample_key`], so the sample depends on nothing but the indices: every tile
/// and the in-memory path draw the same one). Why: the median of 65 536 residuals or more moves
/// by well under 1 % from the full one, and in a tiled run the pre-pass was a fifth of the CPU
/// time, a whole k-NN pass of its own (docs/DECISIONS.md, "The noise pre-pass on a sample").
/// The bilateral spacing, a mean, still reads every point.
pub fn in_noise_sample(index: u64, points: u64) -> bool {
    let stride = (points / NOISE_SAMPLE).max(1);
    crate::points::sample_key(index).is_multiple_of(stride)
}

/// True when `params` need [`Globals`] (a pre-pass over the whole cloud).
pub fn needs_globals(params: &Params) -> bool {
    params.method == Method::Bilateral || guarded_qem(params)
}

/// The partials behind [`Globals`] over the points `counted` selects, and for each point whether
/// its contribution is exact (its k-NN ball inside the region). `counted(i, exact)` is asked
/// with that answer, so a tile sums only its exact contributions in the same pass (it used to
/// run the pass again once it knew which were exact: twice the cost of every tile with a
/// narrowed halo).
///
/// For the guarded operator only the points of the noise sample ([`in_noise_sample`], over a
/// cloud of `points` finite points) are listed and counted; the others are reported exact, as
/// nothing of theirs is summed.
///
/// # Errors
/// Fewer than two points.
pub fn globals_partial(
    run: &CloudRun,
    params: &Params,
    points: u64,
    counted: impl Fn(usize, bool) -> bool + Sync,
) -> Result<(GlobalsPartial, Vec<bool>), DenoiseError> {
    let kg = globals_k(params);
    let sampled: Option<Vec<bool>> = guarded_qem(params).then(|| {
        (0..run.positions.len())
            .map(|i| run.wanted.is_none_or(|w| w[i]) && in_noise_sample(run.ties[i], points))
            .collect()
    });
    let own = super::own_beams(run, params);
    let run = CloudRun {
        wanted: sampled.as_deref().or(run.wanted),
        ..super::with_beams(run, own.as_deref())
    };
    let g = graph(&run, kg, 0, None)?;
    let exact_f = Taint::of(&run, &g).seeds;
    let mut exact = vec![false; run.positions.len()];
    for (j, &i) in g.frame.order.iter().enumerate() {
        exact[i as usize] = !exact_f[j];
    }
    let part = partial_of(params, &g, kg, |i| {
        sampled.as_ref().is_none_or(|s| s[i]) && counted(i, exact[i])
    });
    if let Some(s) = &sampled {
        for (e, &s) in exact.iter_mut().zip(s) {
            *e |= !s;
        }
    }
    Ok((part, exact))
}

/// List length of the pre-pass behind [`Globals`]: the small-scale fit's [`NEAR`] for the
/// guarded operator, 2 (the point and its nearest other) for the bilateral spacing.
///
/// [`NEAR`]: crate::denoise::structure::NEAR
pub(super) fn globals_k(params: &Params) -> usize {
    if guarded_qem(params) {
        crate::denoise::structure::NEAR
    } else {
        2
    }
}

/// The partials behind [`Globals`] over the points `counted` selects (input indices), from a
/// graph whose lists hold the `kg` nearest or more.
///
/// The result is that of the `kg`-NN graph to the bit: lists are sorted by (squared distance, tie
/// key), a total order, so the first `kg` members of an exact longer list are the exact
/// `kg`-NN list; and a point is isolated at `kg` exactly when fewer than `kg` of its list lie
/// within the isolation radius (its `kg`-th nearest lies beyond it), which for a capped list is
/// its length.
pub(super) fn partial_of(
    params: &Params,
    g: &Graph,
    kg: usize,
    counted: impl Fn(usize) -> bool + Sync,
) -> GlobalsPartial {
    let (frame, lists) = (&g.frame, &g.lists);
    // An isolated point has no spacing or noise of its own: it is never smoothed.
    let take =
        |j: usize| counted(frame.order[j] as usize) && !(g.isolated[j] && lists.get(j).len() < kg);
    // Residuals of the counted points only (a sample of a large cloud), in parallel.
    let near: Vec<Option<f64>> = if guarded_qem(params) {
        (0..frame.positions.len())
            .into_par_iter()
            .with_min_len(1024)
            .map(|j| {
                take(j).then(|| {
                    let beam = g.beams.as_ref().map(|b| b[j]).filter(|d| *d != DVec3::ZERO);
                    crate::denoise::structure::near_residual(
                        &frame.positions,
                        lists.get(j),
                        j,
                        beam,
                    )
                })
            })
            .collect()
    } else {
        Vec::new()
    };
    let mut part = GlobalsPartial::default();
    for j in 0..frame.positions.len() {
        if !take(j) {
            continue;
        }
        let list = lists.get(j);
        if params.method == Method::Bilateral
            && let Some(&u) = list[..list.len().min(kg)]
                .iter()
                .find(|&&u| u as usize != j)
        {
            part.spacing.add(g.index.dist2(j, u as usize).sqrt());
        }
        if let Some(&Some(r)) = near.get(j) {
            part.noise.add(r);
        }
    }
    part.noise.refresh();
    part
}
