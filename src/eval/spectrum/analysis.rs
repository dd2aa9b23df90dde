//! Meshes as height fields and their spectra: [`resample`] onto a regular grid, the
//! Hann-windowed radial spectrum ([`radial_spectrum`]), the [`gain`] per ring and its averages
//! over the shape and noise bands ([`Bands`]).

use std::f64::consts::PI;

use glam::{DVec2, DVec3};
use rustfft::FftPlanner;
use rustfft::num_complex::Complex;

use crate::eval::{EvalError, check_faces};
use crate::points::Faces;

/// Rings where the clean surface's gain is at least this belong to the *shape* band.
pub const SHAPE_BAND: f64 = 0.9;
/// Rings where the clean surface's gain is at most this belong to the *noise* band.
pub const NOISE_BAND: f64 = 0.1;

/// A regular square grid in the x, y plane: point (i, j) is `origin + (i, j) · spacing`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GridSpec {
    /// Position of point (0, 0).
    pub origin: DVec2,
    /// Distance between neighbouring points.
    pub spacing: f64,
    /// Points per side.
    pub n: usize,
}

impl GridSpec {
    /// Checks the spacing and size.
    ///
    /// # Errors
    /// [`EvalError::Param`] for a spacing that is not finite and > 0, fewer than 4 or more than
    /// 8192 points per side, or a non-finite origin.
    pub fn validate(&self) -> Result<(), EvalError> {
        if !(self.spacing > 0.0 && self.spacing.is_finite() && self.origin.is_finite()) {
            return Err(EvalError::Param {
                name: "grid",
                detail: format!(
                    "origin {} and spacing {} must be finite, spacing > 0",
                    self.origin, self.spacing
                ),
            });
        }
        if !(4..=8192).contains(&self.n) {
            return Err(EvalError::Param {
                name: "grid",
                detail: format!("points per side must be in 4..=8192, got {}", self.n),
            });
        }
        Ok(())
    }

    /// The position of point (i, j).
    pub fn point(&self, i: usize, j: usize) -> DVec2 {
        self.origin + DVec2::new(i as f64, j as f64) * self.spacing
    }
}

/// Heights sampled on a [`GridSpec`].
#[derive(Debug, Clone, PartialEq)]
pub struct HeightGrid {
    /// The grid.
    pub grid: GridSpec,
    /// Row-major heights: index `j · n + i` is point (i, j).
    pub heights: Vec<f64>,
    /// Points no triangle covered, filled from their neighbours.
    pub filled: usize,
}

impl HeightGrid {
    /// The height at point (i, j).
    pub fn at(&self, i: usize, j: usize) -> f64 {
        self.heights[j * self.grid.n + i]
    }
}

fn cross2(a: DVec2, b: DVec2) -> f64 {
    a.x * b.y - a.y * b.x
}

/// Resamples a mesh that is a height field over x, y on `grid`: each grid point takes z linearly
/// interpolated over the triangles whose x, y projection contains it (averaged where several do,
/// e.g. on shared edges or folds). Points no triangle covers are filled with the mean of their
/// already known 4-neighbours, sweep after sweep, and counted in [`HeightGrid::filled`].
///
/// # Errors
/// Bad grid or face indices, a non-finite vertex of some triangle, or no grid point covered.
pub fn resample(
    positions: &[DVec3],
    faces: &Faces,
    grid: &GridSpec,
) -> Result<HeightGrid, EvalError> {
    grid.validate()?;
    check_faces(positions.len(), faces)?;
    let n = grid.n;
    let mut sum = vec![0.0; n * n];
    let mut count = vec![0u32; n * n];
    let index = |v: f64, hi: usize| -> Option<usize> {
        // Grid coordinate v clamped to [0, hi]; None when entirely outside.
        if v < 0.0 {
            Some(0)
        } else if v > hi as f64 {
            None
        } else {
            Some(v as usize)
        }
    };
    for [a, b, c] in faces.triangles() {
        let p = [a, b, c].map(|v| positions[v as usize]);
        if let Some(k) = p.iter().position(|q| !q.is_finite()) {
            return Err(EvalError::NonFinite {
                what: "resampled mesh",
                index: [a, b, c][k] as usize,
            });
        }
        let q = p.map(|v| v.truncate());
        let (e1, e2) = (q[1] - q[0], q[2] - q[0]);
        let det = cross2(e1, e2);
        let scale = e1.length_squared().max(e2.length_squared());
        if det.abs() <= 1e-12 * scale || scale == 0.0 {
            continue; // zero area in x, y: covers nothing a neighbour does not
        }
        let lo = q[0].min(q[1]).min(q[2]);
        let hi = q[0].max(q[1]).max(q[2]);
        let g_lo = (lo - grid.origin) / grid.spacing;
        let g_hi = (hi - grid.origin) / grid.spacing;
        if g_hi.x < 0.0 || g_hi.y < 0.0 {
            continue;
        }
        let (Some(i0), Some(j0)) = (index(g_lo.x.ceil(), n - 1), index(g_lo.y.ceil(), n - 1))
        else {
            continue;
        };
        let i1 = (g_hi.x.floor() as usize).min(n - 1);
        let j1 = (g_hi.y.floor() as usize).min(n - 1);
        const TOL: f64 = 1e-9;
        for j in j0..=j1 {
            for i in i0..=i1 {
                let r = grid.point(i, j) - q[0];
                let s = cross2(r, e2) / det;
                let t = cross2(e1, r) / det;
                if s >= -TOL && t >= -TOL && s + t <= 1.0 + TOL {
                    let z = p[0].z + s * (p[1].z - p[0].z) + t * (p[2].z - p[0].z);
                    sum[j * n + i] += z;
                    count[j * n + i] += 1;
                }
            }
        }
    }
    let mut known: Vec<bool> = count.iter().map(|&c| c > 0).collect();
    if !known.iter().any(|&k| k) {
        return Err(EvalError::Degenerate(format!(
            "no triangle covers the {n}×{n} resampling grid at {} (spacing {})",
            grid.origin, grid.spacing
        )));
    }
    let mut heights: Vec<f64> = sum
        .iter()
        .zip(&count)
        .map(|(&s, &c)| if c > 0 { s / f64::from(c) } else { 0.0 })
        .collect();
    let filled = known.iter().filter(|&&k| !k).count();
    while known.iter().any(|&k| !k) {
        let mut next = Vec::new();
        for j in 0..n {
            for i in 0..n {
                if known[j * n + i] {
                    continue;
                }
                let mut s = 0.0;
                let mut c = 0;
                let nb = [
                    (i > 0).then(|| j * n + i - 1),
                    (i + 1 < n).then(|| j * n + i + 1),
                    (j > 0).then(|| (j - 1) * n + i),
                    (j + 1 < n).then(|| (j + 1) * n + i),
                ];
                for k in nb.into_iter().flatten() {
                    if known[k] {
                        s += heights[k];
                        c += 1;
                    }
                }
                if c > 0 {
                    next.push((j * n + i, s / f64::from(c)));
                }
            }
        }
        for (k, h) in next {
            heights[k] = h;
            known[k] = true;
        }
    }
    Ok(HeightGrid {
        grid: *grid,
        heights,
        filled,
    })
}

/// The 1D Hann window of `n` samples, `sin²(π (i + ½) / n)`.
pub(super) fn hann(n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| (PI * (i as f64 + 0.5) / n as f64).sin().powi(2))
        .collect()
}

/// The Hann-window-weighted mean height of a grid (the offset [`radial_spectrum`] subtracts).
pub fn window_mean(grid: &HeightGrid) -> f64 {
    let n = grid.grid.n;
    let w = hann(n);
    let mut s = 0.0;
    let mut ws = 0.0;
    for j in 0..n {
        for i in 0..n {
            let wij = w[i] * w[j];
            s += wij * grid.at(i, j);
            ws += wij;
        }
    }
    s / ws
}

/// A radially averaged 2D spectrum.
#[derive(Debug, Clone, PartialEq)]
pub struct RadialSpectrum {
    /// Grid points per side.
    pub n: usize,
    /// Grid spacing.
    pub spacing: f64,
    /// Per ring r = 0..=n/2: the summed power Σ|F|² of the DFT terms with round(|k|) = r.
    pub power: Vec<f64>,
    /// Per ring: the mean magnitude |F| of its terms.
    pub magnitude: Vec<f64>,
    /// Per ring: its number of DFT terms.
    pub count: Vec<usize>,
}

impl RadialSpectrum {
    /// The frequency of ring `r` in cycles per unit length.
    pub fn frequency(&self, r: usize) -> f64 {
        r as f64 / (self.n as f64 * self.spacing)
    }

    /// The ring with the most power, ring 0 (the mean) left out; `None` for an all-zero
    /// spectrum.
    pub fn peak(&self) -> Option<usize> {
        (1..self.power.len())
            .filter(|&r| self.power[r] > 0.0)
            .max_by(|&a, &b| self.power[a].total_cmp(&self.power[b]))
    }
}

/// The radially averaged spectrum of `grid` minus `offset`: the 2D DFT of
/// `w(i) w(j) (h(i, j) − offset)` with the Hann window `w`, magnitudes divided by Σ w(i) w(j) (so
/// a sinusoid of amplitude a on the grid's frequencies shows |F| = a/2 at its two terms).
///
/// # Errors
/// A bad grid, or a height count that does not match it.
pub fn radial_spectrum(grid: &HeightGrid, offset: f64) -> Result<RadialSpectrum, EvalError> {
    grid.grid.validate()?;
    let n = grid.grid.n;
    if grid.heights.len() != n * n {
        return Err(EvalError::Mismatch(format!(
            "{} heights for a {n}×{n} grid",
            grid.heights.len()
        )));
    }
    if let Some(index) = grid.heights.iter().position(|h| !h.is_finite()) {
        return Err(EvalError::NonFinite {
            what: "height grid",
            index,
        });
    }
    let w = hann(n);
    let norm: f64 = w.iter().sum::<f64>().powi(2);
    let mut buf: Vec<Complex<f64>> = (0..n * n)
        .map(|k| {
            let (i, j) = (k % n, k / n);
            Complex::new(w[i] * w[j] * (grid.heights[k] - offset), 0.0)
        })
        .collect();
    let fft = FftPlanner::new().plan_fft_forward(n);
    fft.process(&mut buf); // every row
    let mut t = vec![Complex::new(0.0, 0.0); n * n];
    for j in 0..n {
        for i in 0..n {
            t[i * n + j] = buf[j * n + i];
        }
    }
    fft.process(&mut t); // every column (now a row of the transpose)
    let rings = n / 2 + 1;
    let mut power = vec![0.0; rings];
    let mut magnitude = vec![0.0; rings];
    let mut count = vec![0usize; rings];
    let signed = |k: usize| -> f64 {
        if k <= n / 2 {
            k as f64
        } else {
            k as f64 - n as f64
        }
    };
    for a in 0..n {
        for b in 0..n {
            let r = signed(a).hypot(signed(b)).round() as usize;
            if r < rings {
                let m = t[a * n + b].norm() / norm;
                power[r] += m * m;
                magnitude[r] += m;
                count[r] += 1;
            }
        }
    }
    for (m, &c) in magnitude.iter_mut().zip(&count) {
        if c > 0 {
            *m /= c as f64;
        }
    }
    Ok(RadialSpectrum {
        n,
        spacing: grid.grid.spacing,
        power,
        magnitude,
        count,
    })
}

/// The gain per ring, `√(power_out / power_in)`; NaN where the input ring holds no power.
pub fn gain(input: &RadialSpectrum, output: &RadialSpectrum) -> Vec<f64> {
    input
        .power
        .iter()
        .zip(&output.power)
        .map(
            |(&pi, &po)| {
                if pi > 0.0 { (po / pi).sqrt() } else { f64::NAN }
            },
        )
        .collect()
}

/// Averages of a gain curve over the bands the clean surface's gain defines.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Bands {
    /// Mean gain over the shape band (clean gain ≥ [`SHAPE_BAND`]); `None` if empty.
    pub shape: Option<f64>,
    /// Mean gain over the transition band (between the two thresholds); `None` if empty.
    pub transition: Option<f64>,
    /// Mean gain over the noise band (clean gain ≤ [`NOISE_BAND`]); `None` if empty.
    pub noise: Option<f64>,
    /// The largest gain of any ring of the curve.
    pub peak: f64,
    /// Its frequency in cycles per L.
    pub peak_frequency: f64,
    /// The largest gain outside the shape band (0 if there is none).
    pub peak_outside_shape: f64,
    /// Its frequency in cycles per L.
    pub peak_outside_shape_frequency: f64,
    /// The first frequency (cycles per L) where the gain drops below ½: the half-amplitude
    /// cut-off of a low-pass; `None` if it never does.
    pub half: Option<f64>,
}

impl Bands {
    /// The band averages of `gain` (per ring, aligned with `clean` and `frequency`). The shape
    /// band runs from the first ring up to the first where the clean gain drops below
    /// [`SHAPE_BAND`]; the noise band from the ring after the last where it exceeds
    /// [`NOISE_BAND`] to the end; the transition band lies between.
    pub fn of(gain: &[f64], clean: &[f64], frequency: &[f64]) -> Bands {
        let (shape_end, noise_start) = band_rings(clean);
        let mut sums = [(0.0, 0usize); 3];
        let mut peak = (f64::NEG_INFINITY, f64::NAN);
        let mut outside = (0.0, f64::NAN);
        for (k, (&g, &f)) in gain.iter().zip(frequency).enumerate() {
            if !g.is_finite() {
                continue;
            }
            let band = if k < shape_end {
                0
            } else if k < noise_start {
                1
            } else {
                2
            };
            sums[band].0 += g;
            sums[band].1 += 1;
            if g > peak.0 {
                peak = (g, f);
            }
            if band > 0 && g > outside.0 {
                outside = (g, f);
            }
        }
        let mean = |(s, c): (f64, usize)| (c > 0).then(|| s / c as f64);
        Bands {
            shape: mean(sums[0]),
            transition: mean(sums[1]),
            noise: mean(sums[2]),
            peak: peak.0.max(0.0),
            peak_frequency: peak.1,
            peak_outside_shape: outside.0,
            peak_outside_shape_frequency: outside.1,
            half: gain
                .iter()
                .zip(frequency)
                .find(|(g, _)| **g < 0.5)
                .map(|(_, &f)| f),
        }
    }
}

/// The band edges as ring indices into `clean`: the shape band is `..shape_end`, the noise band
/// `noise_start..` (see [`Bands::of`]).
pub(super) fn band_rings(clean: &[f64]) -> (usize, usize) {
    let shape_end = clean
        .iter()
        .position(|&c| c.is_nan() || c < SHAPE_BAND)
        .unwrap_or(clean.len());
    let noise_start = clean
        .iter()
        .rposition(|&c| c.is_nan() || c > NOISE_BAND)
        .map_or(0, |k| k + 1)
        .max(shape_end);
    (shape_end, noise_start)
}
