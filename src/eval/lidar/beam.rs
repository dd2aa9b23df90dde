//! What happens to one pulse: dropout, angular jitter, the footprint, echoes, mixed pixels, range
//! noise and intensity.
//!
//! # Brief overview
//!
//! For pulse `i` of a scan with seed `s`, every random number comes from ChaCha8 seeded with `s`
//! on stream `i`, drawn in a fixed order whatever happens to the pulse, so a pulse's return does
//! not depend on any other pulse, on the thread count, or on whether the clean or the noisy scan
//! is written.
//!
//! 1. **Dropout**: with probability `dropout` the pulse returns nothing.
//! 2. **Angular jitter**: the beam really leaves along `d`, the nominal direction `d₀` turned by
//!    two independent N(0, jitter²) angles; the sensor reports `d₀`.
//! 3. **Footprint**: `footprint_rays` sub-rays (1, 7 or 19) spread over the beam's cone of full
//!    angle `divergence` around `d` (centre, then rings at equal-area radii) are cast into the
//!    scene up to `max_range`. A thin wire is hit when any sub-ray meets it, as a real footprint
//!    (divergence × range wide) catches a wire narrower than itself.
//! 4. **Echoes**: the hits, by range, form echoes: an echo starts at its nearest hit and takes
//!    every hit within `mix_distance` (the pulse-mixing distance, about half the pulse length)
//!    of it. The first echo holding at least `detect` of the sub-rays is the return; a weaker
//!    first echo is missed (the pulse goes on). No echo: no return (sky, out of range).
//! 5. **Range**: if the echo holds hits of more than one object whose nearest hits are more
//!    than [`MIX_MIN`] apart, it is a **mixed pixel**: its range is the mean of the echo's hit
//!    ranges, between the foreground edge and the background, and its kind is `mixed`.
//!    Otherwise the range is the centre sub-ray's, when it is in the echo (the return lies on
//!    the surface), else that of the echo's sub-ray nearest the centre (an **off-centre**
//!    return: a wire or edge caught by the rim of the footprint, reported along the beam).
//! 6. **Noise**: the clean return is `o + d·r`; the noisy one `o + d₀·(r + ε)` with
//!    ε ~ N(0, σ²): range noise along the reported beam, plus the jitter's sideways error.
//! 7. **Intensity**: share of the footprint in the echo × the kind's reflectance × |cos| of the
//!    incidence angle, with 5 % multiplicative noise, as 16 bits.

use glam::DVec3;
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::LidarError;
use super::bvh::Bvh;
use super::kinds::Kind;
use super::scene::{Scene, perpendiculars};
use super::sensors::Pulse;

/// Objects in one echo closer than this (m) do not make a mixed pixel (a car's tyre on the road,
/// a wall's foot on the ground): the return stays on the surface.
pub const MIX_MIN: f64 = 0.05;

/// What a sensor measures with.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Physics {
    /// Range noise σ (m).
    pub sigma: f64,
    /// Angular jitter σ (degrees).
    pub jitter_deg: f64,
    /// Full beam divergence (mrad).
    pub divergence_mrad: f64,
    /// Sub-rays over the footprint (1, 7 or 19).
    pub footprint_rays: usize,
    /// Share of pulses dropped.
    pub dropout: f64,
    /// Largest range (m).
    pub max_range: f64,
    /// Pulse-mixing distance (m).
    pub mix_distance: f64,
    /// Smallest share of the footprint an echo needs.
    pub detect: f64,
}

impl Physics {
    /// Checks every value.
    ///
    /// # Errors
    /// [`LidarError::Param`] naming the flag.
    pub fn validate(&self) -> Result<(), LidarError> {
        let bad = |name: &'static str, detail: String| Err(LidarError::Param { name, detail });
        if !(self.sigma >= 0.0 && self.sigma <= 10.0) {
            return bad("sigma", format!("must be 0–10 m, got {}", self.sigma));
        }
        if !(self.jitter_deg >= 0.0 && self.jitter_deg <= 1.0) {
            return bad("jitter", format!("must be 0–1°, got {}", self.jitter_deg));
        }
        if !(self.divergence_mrad >= 0.0 && self.divergence_mrad <= 50.0) {
            return bad(
                "divergence",
                format!("must be 0–50 mrad, got {}", self.divergence_mrad),
            );
        }
        if ![1, 7, 19].contains(&self.footprint_rays) {
            return bad(
                "footprint-rays",
                format!("must be 1, 7 or 19, got {}", self.footprint_rays),
            );
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return bad(
                "dropout",
                format!("must be in [0, 1), got {}", self.dropout),
            );
        }
        if !(self.max_range > 0.0 && self.max_range <= 1e5) {
            return bad(
                "max-range",
                format!("must be in (0, 100000] m, got {}", self.max_range),
            );
        }
        if !(self.mix_distance >= 0.0 && self.mix_distance <= 100.0) {
            return bad(
                "mix-distance",
                format!("must be 0–100 m, got {}", self.mix_distance),
            );
        }
        if !(self.detect > 0.0 && self.detect <= 1.0) {
            return bad("detect", format!("must be in (0, 1], got {}", self.detect));
        }
        Ok(())
    }

    /// The sub-rays' offsets in units of the footprint radius: the centre first, then rings of
    /// 6 (and 12) at the radii that give every sub-ray an equal share of the disc.
    fn pattern(&self) -> Vec<(f64, f64)> {
        let ring = |n: usize, r: f64, turn: f64| {
            (0..n).map(move |k| {
                let a = std::f64::consts::TAU * (k as f64 + turn) / n as f64;
                (r * libm::cos(a), r * libm::sin(a))
            })
        };
        let mut p = vec![(0.0, 0.0)];
        match self.footprint_rays {
            7 => p.extend(ring(6, 0.70, 0.0)),
            19 => {
                p.extend(ring(6, 0.44, 0.0));
                p.extend(ring(12, 0.82, 0.5));
            }
            _ => {}
        }
        p
    }
}

/// One return.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Return {
    /// The pulse's index.
    pub pulse: u32,
    /// The noise-free return `o + d·r` (on the surface, unless mixed or off-centre).
    pub clean: DVec3,
    /// The measured return `o + d₀·(r + ε)`.
    pub noisy: DVec3,
    /// What it belongs to (`Mixed` for a mixed pixel).
    pub kind: Kind,
    /// The object hit (for a mixed pixel, the nearest one).
    pub object: u32,
    /// A mixed pixel.
    pub mixed: bool,
    /// Off-centre: caught by the rim of the footprint.
    pub offcentre: bool,
    /// Intensity (16 bits).
    pub intensity: u16,
}

/// Fires every pulse (in parallel; the result does not depend on the thread count).
pub fn fire_all(
    physics: &Physics,
    pulses: &[Pulse],
    seed: u64,
    scene: &Scene,
    bvh: &Bvh,
) -> Vec<Return> {
    use rayon::prelude::*;
    let pattern = physics.pattern();
    pulses
        .par_iter()
        .enumerate()
        .filter_map(|(i, p)| fire(physics, &pattern, p, i as u32, seed, scene, bvh))
        .collect()
}

/// One hit of a sub-ray.
#[derive(Debug, Clone, Copy)]
struct SubHit {
    range: f64,
    ray: usize,
    triangle: u32,
    normal: DVec3,
}

fn fire(
    physics: &Physics,
    pattern: &[(f64, f64)],
    pulse: &Pulse,
    index: u32,
    seed: u64,
    scene: &Scene,
    bvh: &Bvh,
) -> Option<Return> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(u64::from(index));
    // Every draw, in a fixed order, whatever happens to the pulse.
    let drop = rng.random::<f64>();
    let jitter = (gauss(&mut rng), gauss(&mut rng));
    let eps = gauss(&mut rng);
    let speckle = gauss(&mut rng);
    if drop < physics.dropout {
        return None;
    }
    let d0 = pulse.dir;
    let (u, v) = perpendiculars(d0);
    let j = physics.jitter_deg.to_radians();
    let d = (d0 + (u * jitter.0 + v * jitter.1) * j).normalize();
    let (u, v) = perpendiculars(d);
    let spread = libm::tan(physics.divergence_mrad * 1e-3 / 2.0);
    let mut hits: Vec<SubHit> = pattern
        .iter()
        .enumerate()
        .filter_map(|(k, &(a, b))| {
            let dk = if k == 0 {
                d
            } else {
                (d + (u * a + v * b) * spread).normalize()
            };
            bvh.cast(pulse.origin, dk, physics.max_range)
                .map(|h| SubHit {
                    range: h.range,
                    ray: k,
                    triangle: h.triangle,
                    normal: h.normal,
                })
        })
        .collect();
    hits.sort_by(|a, b| a.range.total_cmp(&b.range).then(a.ray.cmp(&b.ray)));
    let n = pattern.len() as f64;
    let mut start = 0;
    let echo = loop {
        let first = hits.get(start)?;
        let end = hits[start..]
            .iter()
            .position(|h| h.range - first.range > physics.mix_distance)
            .map_or(hits.len(), |k| start + k);
        if (end - start) as f64 / n >= physics.detect - 1e-12 {
            break &hits[start..end];
        }
        start = end;
    };
    let object = |h: &SubHit| scene.face_object[h.triangle as usize];
    // The nearest hit of each object in the echo: more than one object far enough apart mix.
    let nearest = echo[0];
    let far = echo
        .iter()
        .filter(|h| object(h) != object(&nearest))
        .map(|h| h.range)
        .fold(f64::NEG_INFINITY, f64::max);
    let mixed = far - nearest.range > MIX_MIN;
    let (range, hit, offcentre) = if mixed {
        let mean = echo.iter().map(|h| h.range).sum::<f64>() / echo.len() as f64;
        (mean, nearest, false)
    } else {
        // The centre sub-ray if it is in the echo, else the one nearest the centre (pattern
        // order is by distance from the centre).
        let h = *echo.iter().min_by_key(|h| h.ray).expect("an echo has hits");
        (h.range, h, h.ray != 0)
    };
    let kind = if mixed {
        Kind::Mixed
    } else {
        scene.kind_of_face(hit.triangle as usize)
    };
    let share = echo.len() as f64 / n;
    let cos = hit.normal.dot(d).abs();
    let value = share
        * scene.kind_of_face(hit.triangle as usize).reflectance()
        * cos
        * (1.0 + 0.05 * speckle).max(0.0);
    let intensity = (value * 65535.0).round().clamp(1.0, 65535.0) as u16;
    Some(Return {
        pulse: index,
        clean: pulse.origin + d * range,
        noisy: pulse.origin + d0 * (range + physics.sigma * eps),
        kind,
        object: object(&hit),
        mixed,
        offcentre,
        intensity,
    })
}

fn gauss(rng: &mut impl Rng) -> f64 {
    rng.sample::<f64, _>(StandardNormal)
}
