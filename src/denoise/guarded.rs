//! The guarded quadric step of the default point operator: quadrics only where the
//! neighbourhood shows a surface or a line, robust weights on every neighbour's vote, and a step
//! bounded by the local noise.
//!
//! # Brief overview
//!
//! For a point `i` of class [`Structure::Surface`] or [`Structure::Edge`], each Surface or Edge
//! member `u` of its list votes with its (filtered, curvature-corrected) tangent plane; for a
//! [`Structure::Line`] point each Line member votes with its line (the quadric of the squared
//! distance to the line through `u` along its axis: `A = I − d dᵀ`). A vote is weighted by how
//! well the plane (line) agrees with `i`:
//!
//! ```text
//!   w_u = exp(−r² / (2 (AGREE · s_u)²)),   r = distance of i to u's plane (line),
//!                                          s_u = u's noise scale (structure::noise_scale)
//! ```
//!
//! so the planes of another surface (across a crease, behind a thin wall, of a distant surface
//! under an isolated point) lose their vote instead of dragging the point. The summed quadric is
//! minimised with the damped solve. Where the neighbourhood is rougher than the scan's noise
//! (`s_i > WIENER·g`, `g` the global noise of [`super::cloud::Globals`]) the step is scaled by the
//! Wiener gain `(WIENER·g / s_i)²`, the share of the local spread the noise explains; and where
//! the list's offsets are larger than the noise (`m_i`, their mean square per spanned direction,
//! above `g²`) by the shrinkage `g² / m_i`, the optimal share `σ²/(σ² + v)` of a step whose
//! plane estimate has error variance `v` ([`gains`]; computed in the first update of a cycle). The point's total
//! displacement from where the run found it is clamped to `STEP · min(s_i, g)` for surface
//! points and `STEP_FEATURE · min(s_i, g)` for edge and line points, to `REACH` times its own
//! k-NN radius in the input, and to `--max-move`: no point moves farther than the noise its
//! neighbourhood shows, nor out of the ball its neighbours were drawn from. Scatter, sparse and degenerate points do not move.
//!
//! **Along the beam.** Where the point's beam `d` is known ([`Beams`]), its error lies along `d`,
//! so the point moves only along it, to the minimiser of the summed quadric on that line,
//! `t* = −dᵀb / dᵀAd` ([`Quadric::along`]): no sideways drift, and a return keeps its beam. The
//! votes' agreement is then measured along the beam too (a plane's offset over the sine of the
//! angle between beam and plane), as is every noise scale ([`super::structure`]); a line point
//! (one scan line, whose list cannot fix a plane) steps as far as a surface point, since its
//! line is a surface sampled along one line.
//!
//! On a line the votes are lines through the members along their axes, each axis turned halfway
//! towards the point's own where the two are within 25° (as [`bent_normal`] does for planes): the
//! chord property of a circle, so a curved scan ring or a sagging wire is not pushed outwards.

use glam::DVec3;
use rayon::prelude::*;

use super::Params;
use super::common::stay;
use super::qem::{BEND_COS, bent_normal};
use super::structure::{Beams, LocalFit, Structure};
use crate::geometry::{Quadric, SymMat3, exp};
use crate::neighbours::Neighbourhoods;

/// Width of the agreement weight in units of the voter's noise scale.
pub const AGREE: f64 = 2.0;
/// Largest total displacement of a surface point in units of its noise scale.
pub const STEP: f64 = 3.0;
/// Largest total displacement of an edge or line point in units of its noise scale. Where the
/// neighbourhood is not one plane, the quadric's minimiser is the least certain (two noisy planes
/// meeting at a shallow angle, an axis fitted to a few points, the visible arc of a pole taken for
/// a wire), and on the real scans the per-class harm came from such points moving 2–3 noise
/// scales: with 1 instead of 3 the summed excess of the worst classes over 1 fell from 2.13 to
/// 1.48 on the 21 real scans, at +0.1 % (sphere) and +0.6 % (cube) point-to-mesh RMS on the
/// synthetic shapes at 0.4 L (docs/DECISIONS.md).
pub const STEP_FEATURE: f64 = 1.0;
/// Largest total displacement of any point in units of its own k-NN radius in the input (the
/// distance to the farthest member of its list, itself counted: `r16` at the default k). The
/// noise bound above is a median over the scan and over the list: on a scan whose noise is a
/// good part of its spacing (dense mobile or photogrammetric clouds) `STEP` noise scales reach
/// past the next samples, and on a plane with noise 0.4–0.6 × its spacing the 99th percentile
/// of the surface points' moves was 0.34–0.36 `r16`, over the real-scan protocol's do-no-harm
/// goal (p99 ≤ 0.3, max ≤ 0.6 `r16`, on the scan as it is). A quarter keeps both goals on any
/// scan, with room for the rounding of the written coordinates. Measured: on the 21 real scans
/// no class's known-noise ratio rose and planar ratios rose by at most 0.01; on the synthetic
/// shapes the point-to-mesh RMS rose by at most 0.24 % at 0.4 L and 1.1 % at 0.8 L (mean error
/// 2.1 %; docs/DECISIONS.md).
pub const REACH: f64 = 0.25;
/// Smallest sine of the angle between a point's beam and a voting plane by which the plane's
/// offset is divided to measure it along the beam (3°): a plane the beam grazes more closely
/// counts as that far.
pub const GRAZING: f64 = 0.05;
/// Cap of a point's noise scale in units of the scan's global noise ([`super::cloud::Globals`]).
pub const GLOBAL: f64 = 1.0;
/// Local spread, in units of the capped noise scale, that the noise alone is taken to explain:
/// the global noise is a median, so about half of the points of a uniformly noisy surface have a
/// larger local residual; below `WIENER ×` it the step is not shrunk. 1.3 keeps the synthetic
/// sphere and cube within 9 % and 4 % of the unguarded operator (1.0: 41 % and 24 %), at
/// per-class ratios on the real scans a few hundredths higher (docs/DECISIONS.md).
pub const WIENER: f64 = 1.3;

/// What the guarded step reads, per point, besides positions.
#[derive(Debug, Clone, Copy)]
pub struct Guard<'a> {
    /// Positions where the run started (the clamp's centre).
    pub start: &'a [DVec3],
    /// Filtered unit normals (zero for points that take no plane).
    pub normals: &'a [DVec3],
    /// Own fits (the line axes).
    pub fits: &'a [LocalFit],
    /// Classes.
    pub classes: &'a [Structure],
    /// Noise scales.
    pub noise: &'a [f64],
    /// Noise scales of the step bound: the noise scale capped by the scan's.
    pub bound: &'a [f64],
    /// Squared k-NN radius of each point's list in the input ([`REACH`]).
    pub radii: &'a [f64],
    /// The user's hard cap on any displacement, if any.
    pub max_move: Option<f64>,
    /// Each point's beam, where known: the point moves only along it.
    pub beams: Beams<'a>,
}

/// Adds the quadric of the squared distance to the line through `p` along unit `d`.
#[inline]
fn add_line(q: &mut Quadric, d: DVec3, p: DVec3, weight: f64) {
    // A = I − d dᵀ; the distance² of w is (w − p)ᵀA(w − p).
    let mut a = SymMat3::scaled_identity(1.0);
    a.add_outer(d, -1.0);
    let ap = a.mul_vec(p);
    let mut wa = a;
    wa.0.iter_mut().for_each(|x| *x *= weight);
    q.a.add(&wa);
    q.b -= weight * ap;
    q.c += weight * p.dot(ap);
}

/// The agreement weight of a residual `r` against a voter of noise scale `s`.
#[inline]
fn agree(r: f64, s: f64) -> f64 {
    if s <= 0.0 {
        // A noise-free voter agrees only exactly.
        return if r == 0.0 { 1.0 } else { 0.0 };
    }
    if r == 0.0 {
        // exp(−0) is 1 exactly: the point's own plane (2 of 32 calls a point) skips the call.
        return 1.0;
    }
    let t = r / (AGREE * s);
    exp(-0.5 * t * t)
}

/// The axis `a` of a voting line turned halfway towards the point's own `own` (its sign first
/// matched) where the two are within 25°; `a` otherwise. On a circle the line through a member
/// along the bisector of the two tangents passes through the point itself.
#[inline]
fn bent_axis(own: DVec3, a: DVec3) -> DVec3 {
    let a = if a.dot(own) < 0.0 { -a } else { a };
    if own != DVec3::ZERO && a != DVec3::ZERO && own.dot(a) > BEND_COS {
        (own + a).normalize()
    } else {
        a
    }
}

/// The robust quadric of point `i` (relative to its position).
fn quadric(pos: &[DVec3], g: &Guard, list: &[u32], i: usize) -> Quadric {
    let v = pos[i];
    let mut q = Quadric::ZERO;
    let beam = g.beams.at(i);
    match g.classes[i] {
        Structure::Line => {
            let own = g.fits[i].axis;
            for &u in list {
                let u = u as usize;
                if g.classes[u] != Structure::Line {
                    continue;
                }
                let d = bent_axis(own, g.fits[u].axis);
                let p = pos[u] - v;
                let r = (p - d * d.dot(p)).length();
                let w = agree(r, g.noise[u]);
                if w > 0.0 {
                    add_line(&mut q, d, p, w);
                }
            }
        }
        _ => {
            let ni = g.normals[i];
            for &u in list {
                let u = u as usize;
                let nu = g.normals[u];
                if nu == DVec3::ZERO || !g.classes[u].takes_planes() {
                    continue;
                }
                let n = bent_normal(ni, nu);
                let p = pos[u] - v;
                let mut r = n.dot(p).abs();
                if let Some(d) = beam {
                    r /= n.dot(d).abs().max(GRAZING);
                }
                let w = agree(r, g.noise[u]);
                if w > 0.0 {
                    q.add_plane(n, p, w);
                }
            }
        }
    }
    q
}

/// The quadric offset of every point that moves (`None` for those that stay), with its
/// [`stay`] flag.
fn offsets(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    g: &Guard,
    params: &Params,
    active: Option<&[bool]>,
) -> Vec<(Option<DVec3>, u8)> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            if active.is_some_and(|a| !a[i]) {
                return (None, 0);
            }
            offset_of(pos, lists.get(i), g, params, i)
        })
        .collect()
}

/// The quadric offset of point `i` (list `list`), `None` when it stays, with its [`stay`]
/// flag (see [`step`]).
#[inline]
pub fn offset_of(
    pos: &[DVec3],
    list: &[u32],
    g: &Guard,
    params: &Params,
    i: usize,
) -> (Option<DVec3>, u8) {
    let v = pos[i];
    if !v.is_finite() || !g.classes[i].moves() || g.bound[i] <= 0.0 {
        return (None, 0);
    }
    if g.max_move.is_some_and(|m| m <= 0.0) {
        return (None, 0);
    }
    let q = quadric(pos, g, list, i);
    if let Some(d) = g.beams.at(i) {
        return match q.along(d) {
            Some(t) => (Some(d * t), 0),
            None => (None, stay::SINGULAR),
        };
    }
    match params.solver_for(q.a.trace()).offset(&q) {
        Some(w) => (Some(w), 0),
        None => (None, stay::SINGULAR),
    }
}

/// Directions a point's offset spans: one (along a plane normal, or along the beam) for
/// surfaces, edges and points with a beam, two (across the axis) for lines without one.
#[inline]
fn dims(s: Structure, beam: bool) -> f64 {
    if s == Structure::Line && !beam {
        2.0
    } else {
        1.0
    }
}

/// The gain of every point that moves, from the offsets `offs` of the first update.
///
/// Two shrinkage factors, both the share of a spread that the noise explains:
/// - Wiener: the neighbourhood's plane-fit spread `s_i` against the capped noise `b_i`,
///   `min(1, (WIENER·b_i / s_i)²)`;
/// - shrinkage: the mean squared offset of the list's moving points per spanned direction,
///   `m_i`, against `b_i²`, `min(1, b_i² / m_i)`. For a point at noise σ along the normal and a
///   plane estimate with error variance `v` (bias included), the offset's expected square is
///   `σ² + v` and the step minimising the expected error is `σ²/(σ² + v)` of it: where the planes
///   disagree with the points (edges, vegetation, scan lines) the offsets exceed the noise and
///   the step is damped towards zero.
pub fn gains(lists: &Neighbourhoods, g: &Guard, offs: &[(Option<DVec3>, u8)]) -> Vec<f64> {
    (0..offs.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| gain_of(lists.get(i), g, offs, i))
        .collect()
}

/// The gain of point `i` (list `list`) from the offsets `offs` of the first update (see
/// [`gains`]); 0 for a point without an offset.
#[inline]
pub fn gain_of(list: &[u32], g: &Guard, offs: &[(Option<DVec3>, u8)], i: usize) -> f64 {
    if offs[i].0.is_none() {
        return 0.0;
    }
    let explained = WIENER * g.bound[i];
    let wiener = if g.noise[i] > explained {
        (explained / g.noise[i]).powi(2)
    } else {
        1.0
    };
    let (mut sum, mut n) = (0.0, 0usize);
    for &u in list {
        let u = u as usize;
        if let Some(w) = offs[u].0 {
            sum += w.length_squared() / dims(g.classes[u], g.beams.at(u).is_some());
            n += 1;
        }
    }
    // n ≥ 1: the list holds the point itself, which has an offset.
    let sigma2 = g.bound[i] * g.bound[i];
    let mean = sum / n as f64;
    let shrink = if mean > sigma2 { sigma2 / mean } else { 1.0 };
    shrink * wiener
}

/// One guarded update of every point (of the `active` ones; the others stay where they are):
/// the new position and why it stayed or was clamped ([`stay`] flags). The first update of a
/// cycle (`gain` is `None`) computes the gains from its offsets and stores them; later updates
/// reuse them, since their offsets no longer carry the scan's noise.
pub fn step(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    g: &Guard,
    params: &Params,
    gain: &mut Option<Vec<f64>>,
    active: Option<&[bool]>,
) -> Vec<(DVec3, u8)> {
    let offs = offsets(pos, lists, g, params, active);
    let gs: &[f64] = gain.get_or_insert_with(|| gains(lists, g, &offs));
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| moved(pos[i], offs[i], gs[i], g, i))
        .collect()
}

/// Where point `i` (now at `v`) goes with its offset `off` scaled by its gain `gain`, clamped
/// to its bound around where the run started, with its [`stay`] flag (see [`step`]).
#[inline]
pub fn moved(v: DVec3, off: (Option<DVec3>, u8), gain: f64, g: &Guard, i: usize) -> (DVec3, u8) {
    let (Some(w), _) = off else {
        return (v, off.1);
    };
    let step = match g.classes[i] {
        Structure::Surface => STEP,
        Structure::Line if g.beams.at(i).is_some() => STEP,
        _ => STEP_FEATURE,
    };
    let mut bound = (step * g.bound[i]).min(REACH * g.radii[i].sqrt());
    if let Some(m) = g.max_move {
        bound = bound.min(m);
    }
    clamp(g.start[i], v + w * gain, bound)
}

/// `p` pulled back into the ball of radius `bound` around `centre`, with [`stay::BOUNDED`] when
/// it had to be.
#[inline]
pub fn clamp(centre: DVec3, p: DVec3, bound: f64) -> (DVec3, u8) {
    let d = p - centre;
    let len = d.length();
    if len <= bound {
        (p, 0)
    } else {
        (centre + d * (bound / len), stay::BOUNDED)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_quadric_is_the_squared_distance_to_the_line() {
        let mut q = Quadric::ZERO;
        let d = DVec3::new(1.0, 1.0, 0.0).normalize();
        let p = DVec3::new(0.0, 0.0, 1.0);
        add_line(&mut q, d, p, 2.0);
        for w in [DVec3::ZERO, DVec3::new(3.0, -1.0, 2.0), p + 5.0 * d] {
            let r = (w - p) - d * d.dot(w - p);
            assert!((q.eval(w) - 2.0 * r.length_squared()).abs() < 1e-12);
        }
    }

    #[test]
    fn clamping_keeps_the_direction_and_the_bound() {
        let (p, f) = clamp(DVec3::ZERO, DVec3::new(3.0, 4.0, 0.0), 1.0);
        assert!((p - DVec3::new(0.6, 0.8, 0.0)).length() < 1e-15);
        assert_eq!(f, stay::BOUNDED);
        assert_eq!(clamp(DVec3::ZERO, DVec3::X, 2.0), (DVec3::X, 0));
    }
}
