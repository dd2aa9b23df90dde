//! Frequency response of the denoisers on a height-field patch: the analysis of the paper's §IV-B
//! (Figs. 11 and 12).
//!
//! # Method
//!
//! 1. [`height_patch`] builds a planar patch: a grid of `cells × cells` squares of side 1 whose
//!    interior vertices are jittered (so the vertex distribution is not homogeneous, as in the
//!    paper's Fig. 11a), split into triangles and lifted by a height field with low-frequency
//!    waves and a sharp-crested ridge (creases at its crest and feet).
//! 2. Noise along the clean normal, σ = level · L (the paper: 40 % of the mean edge), then every
//!    method denoises the noisy patch.
//! 3. [`resample`] reads each mesh as a height field z(x, y): every point of a regular N × N grid
//!    inside the patch (a margin of [`MARGIN`] cells, [`OVERSAMPLE`] grid points per cell) takes
//!    the linear interpolation of z over the triangle whose *current* x, y projection covers it.
//!    Points that no triangle covers (where denoising folded the mesh) are filled from their
//!    neighbours and counted.
//! 4. [`radial_spectrum`]: the 2D FFT (`rustfft`) of the Hann-windowed heights, minus one common
//!    offset (the windowed mean of the noisy field, so the DC term does not leak into the first
//!    rings), with the power summed over rings r = round(|k|) of the integer frequency vector k.
//! 5. [`gain`]: per ring, `√(Σ|F_denoised|² / Σ|F_noisy|²)`, the magnitude of the operator's
//!    transfer function as the ratio of ring RMS magnitudes. The same ratio for the clean surface,
//!    `|F_clean| / |F_noisy|`, is the gain an ideal denoiser would have: ≈ 1 where the shape
//!    dominates the spectrum, ≈ 0 where the noise does.
//! 6. The **error left** per ring: the same ratio for the error fields, `|F(denoised − clean)| /
//!    |F(noisy − clean)|`. A gain curve alone cannot tell restored shape from new artefacts (both
//!    add energy); the error left can: below 1 the method removed error at that frequency, above
//!    1 it added some.
//!
//! The paper plots the *difference* of magnitudes `|F_noisy| − |F_denoised|` (smoothed), which
//! is what the operator removes; the CSV carries it too (`*_diff`, ring mean, in units of L), but
//! the chart shows the gain, which does not depend on the amplitude of the shape.
//!
//! Frequencies are in cycles per L (the clean mean edge length); the curves stop at the vertex
//! Nyquist frequency (half a cycle per cell), above which the resampled spectrum only holds
//! interpolation artefacts.

use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rustfft::FftPlanner;
use rustfft::num_complex::Complex;

use super::metrics::{Metrics, Reference};
use super::noise::{NoiseModel, NoiseSpec, add_noise};
use super::plot::{Corner, LineChart, Series, colours};
use super::render::{RenderOptions, View, render};
use super::report::{label, method_colour};
use super::table::TableMethod;
use super::{EvalError, Mesh, check_faces};
use crate::denoise::denoise;
use crate::points::Faces;

/// Cells of the patch left out of the resampling grid on each side (boundary vertices have
/// one-sided neighbourhoods).
pub const MARGIN: usize = 3;
/// Grid points per cell along each axis.
pub const OVERSAMPLE: usize = 2;
/// Largest jitter of an interior vertex along x and y, in cells.
pub const JITTER: f64 = 0.2;
/// Rings where the clean surface's gain is at least this belong to the *shape* band.
pub const SHAPE_BAND: f64 = 0.9;
/// Rings where the clean surface's gain is at most this belong to the *noise* band.
pub const NOISE_BAND: f64 = 0.1;

/// What the frequency-response experiment runs on.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SpectrumSpec {
    /// Cells per side of the patch (`cells + 1` vertices per side).
    pub cells: usize,
    /// The noise (the paper: along the normal, 40 % of L).
    pub noise: NoiseSpec,
}

impl Default for SpectrumSpec {
    /// A 96 × 96-cell patch (9,409 vertices), normal noise at 40 % of L, seed 0.
    fn default() -> Self {
        SpectrumSpec {
            cells: 96,
            noise: NoiseSpec {
                model: NoiseModel::Normal,
                level: 0.4,
                seed: 0,
            },
        }
    }
}

impl SpectrumSpec {
    /// Checks the patch size and the noise.
    ///
    /// # Errors
    /// [`EvalError::Param`] naming the bad value.
    pub fn validate(&self) -> Result<(), EvalError> {
        if !(4 * MARGIN..=1024).contains(&self.cells) {
            return Err(EvalError::Param {
                name: "patch",
                detail: format!(
                    "cells per side must be in {}..=1024, got {}",
                    4 * MARGIN,
                    self.cells
                ),
            });
        }
        self.noise.validate()
    }

    /// The resampling grid of the patch.
    pub fn grid(&self) -> GridSpec {
        GridSpec {
            origin: DVec2::splat(MARGIN as f64),
            spacing: 1.0 / OVERSAMPLE as f64,
            n: OVERSAMPLE * (self.cells - 2 * MARGIN),
        }
    }

    /// The last ring of the curves: the vertex Nyquist frequency, half a cycle per cell.
    pub fn max_ring(&self) -> usize {
        (self.cells - 2 * MARGIN) / 2
    }
}

/// A triangulated height field over `[0, cells]²`: vertex (i, j) sits at (i, j) plus, inside,
/// a seeded jitter of up to `jitter` cells along x and y, lifted to z = `height(x, y)`; each cell
/// is split along the same diagonal, faces oriented towards +z.
///
/// # Errors
/// [`EvalError::Param`] for fewer than one or more than 4096 cells, or a jitter outside
/// [0, 0.45]; [`EvalError::NonFinite`] when `height` is not finite at a vertex.
pub fn height_field_mesh(
    cells: usize,
    jitter: f64,
    seed: u64,
    height: impl Fn(f64, f64) -> f64,
) -> Result<Mesh, EvalError> {
    if !(1..=4096).contains(&cells) {
        return Err(EvalError::Param {
            name: "patch",
            detail: format!("cells per side must be in 1..=4096, got {cells}"),
        });
    }
    if !(0.0..=0.45).contains(&jitter) {
        return Err(EvalError::Param {
            name: "jitter",
            detail: format!("must be in [0, 0.45] cells, got {jitter}"),
        });
    }
    let side = cells + 1;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut positions = Vec::with_capacity(side * side);
    for j in 0..side {
        for i in 0..side {
            let (mut x, mut y) = (i as f64, j as f64);
            let inside = i > 0 && j > 0 && i < cells && j < cells;
            if inside && jitter > 0.0 {
                x += rng.random_range(-jitter..=jitter);
                y += rng.random_range(-jitter..=jitter);
            }
            let z = height(x, y);
            if !z.is_finite() {
                return Err(EvalError::NonFinite {
                    what: "height field",
                    index: positions.len(),
                });
            }
            positions.push(DVec3::new(x, y, z));
        }
    }
    let id = |i: usize, j: usize| (j * side + i) as u32;
    let mut tris = Vec::with_capacity(2 * cells * cells);
    for j in 0..cells {
        for i in 0..cells {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            tris.push([a, b, c]);
            tris.push([a, c, d]);
        }
    }
    Ok(Mesh {
        positions,
        faces: Faces::from_triangles(&tris),
    })
}

/// The height of the test patch at (x, y) for a patch of `cells` cells (all sizes relative to
/// the side w):
///
/// * low-frequency waves, 1.5 and 1 periods across, amplitude 0.04 w;
/// * a ridge through the centre at 30°, half-width 0.12 w, height 0.06 w: creases at its crest
///   and feet;
/// * a mesa (a truncated cone: plateau of radius 0.06 w, foot 0.14 w, height 0.05 w) and a conical
///   pit (radius 0.1 w, depth 0.04 w): circular creases and a point, so that sharp features of
///   every orientation are present.
pub fn patch_height(x: f64, y: f64, cells: usize) -> f64 {
    let w = cells as f64;
    let waves = 0.04 * w * (2.0 * PI * 1.5 * x / w).sin() * (2.0 * PI * y / w).cos();
    let (s, c) = (PI / 6.0).sin_cos();
    let d = (x - 0.5 * w) * s - (y - 0.5 * w) * c;
    let ridge = 0.06 * w * (1.0 - d.abs() / (0.12 * w)).max(0.0);
    let r = (x - 0.3 * w).hypot(y - 0.75 * w);
    let mesa = 0.05 * w * ((0.14 * w - r) / (0.08 * w)).clamp(0.0, 1.0);
    let q = (x - 0.72 * w).hypot(y - 0.28 * w);
    let pit = -0.04 * w * (1.0 - q / (0.1 * w)).max(0.0);
    waves + ridge + mesa + pit
}

/// The test patch of the frequency-response experiment ([`patch_height`] on a jittered grid).
///
/// # Errors
/// As [`height_field_mesh`].
pub fn height_patch(cells: usize, seed: u64) -> Result<Mesh, EvalError> {
    height_field_mesh(cells, JITTER, seed, |x, y| patch_height(x, y, cells))
}

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
fn hann(n: usize) -> Vec<f64> {
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
fn band_rings(clean: &[f64]) -> (usize, usize) {
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

/// One method's response.
#[derive(Debug, Clone, PartialEq)]
pub struct MethodResponse {
    /// Method name.
    pub name: String,
    /// Gain per ring (rings 1 to [`SpectrumSpec::max_ring`]).
    pub gain: Vec<f64>,
    /// `mean|F_noisy| − mean|F_denoised|` per ring, in units of L (the paper's Fig. 12 quantity).
    pub diff: Vec<f64>,
    /// Band averages of the gain.
    pub bands: Bands,
    /// The error left per ring: `|F(denoised − clean)| / |F(noisy − clean)|`.
    pub error: Vec<f64>,
    /// Band averages of the error left (bands of the clean gain, as for [`Self::bands`]).
    pub error_bands: Bands,
    /// The denoised patch measured against the clean one.
    pub metrics: Metrics,
    /// The denoised positions.
    pub positions: Vec<DVec3>,
    /// Grid points its resampling had to fill.
    pub filled: usize,
}

/// The result of [`frequency_response`].
#[derive(Debug, Clone, PartialEq)]
pub struct FrequencyResponse {
    /// What was run.
    pub spec: SpectrumSpec,
    /// The clean patch.
    pub patch: Mesh,
    /// The noisy positions.
    pub noisy: Vec<DVec3>,
    /// Clean scale length L (mean edge length).
    pub l: f64,
    /// The resampling grid.
    pub grid: GridSpec,
    /// Frequency of each ring of the curves, in cycles per L.
    pub frequency: Vec<f64>,
    /// The clean surface's gain |F_clean| / |F_noisy| per ring: the ideal response.
    pub clean: Vec<f64>,
    /// The noisy patch measured against the clean one.
    pub noisy_metrics: Metrics,
    /// One entry per method, in the order given.
    pub methods: Vec<MethodResponse>,
}

/// The noisy patch and its spectrum, against which any result on the same patch is measured.
struct Experiment {
    patch: Mesh,
    noisy: Vec<DVec3>,
    l: f64,
    grid: GridSpec,
    reference: Reference,
    /// The offset every spectrum subtracts (the windowed mean of the noisy field).
    offset: f64,
    noisy_spectrum: RadialSpectrum,
    /// Rings 1 to [`SpectrumSpec::max_ring`].
    rings: std::ops::RangeInclusive<usize>,
    frequency: Vec<f64>,
    clean: Vec<f64>,
    /// The clean heights, subtracted from a result's for its error field.
    clean_grid: HeightGrid,
    /// The spectrum of the noisy error field (no offset: a shift of the whole surface is an
    /// error of the lowest rings, not something to take out).
    noisy_error: RadialSpectrum,
}

/// `a − b` point by point (same grid).
fn difference(a: &HeightGrid, b: &HeightGrid) -> HeightGrid {
    HeightGrid {
        grid: a.grid,
        heights: a
            .heights
            .iter()
            .zip(&b.heights)
            .map(|(x, y)| x - y)
            .collect(),
        filled: a.filled,
    }
}

impl Experiment {
    fn new(spec: &SpectrumSpec) -> Result<Experiment, EvalError> {
        spec.validate()?;
        let patch = height_patch(spec.cells, spec.noise.seed)?;
        let noisy = add_noise(&patch.positions, Some(&patch.faces), &spec.noise)?;
        let grid = spec.grid();
        let reference = Reference::new(patch.positions.clone(), Some(patch.faces.clone()))?;
        let noisy_grid = resample(&noisy.positions, &patch.faces, &grid)?;
        let offset = window_mean(&noisy_grid);
        let noisy_spectrum = radial_spectrum(&noisy_grid, offset)?;
        let rings = 1..=spec.max_ring();
        let frequency: Vec<f64> = rings
            .clone()
            .map(|r| noisy_spectrum.frequency(r) * noisy.l)
            .collect();
        let clean_grid = resample(&patch.positions, &patch.faces, &grid)?;
        let clean_spectrum = radial_spectrum(&clean_grid, offset)?;
        let clean = gain(&noisy_spectrum, &clean_spectrum)[rings.clone()].to_vec();
        let noisy_error = radial_spectrum(&difference(&noisy_grid, &clean_grid), 0.0)?;
        Ok(Experiment {
            clean_grid,
            noisy_error,
            l: noisy.l,
            noisy: noisy.positions,
            patch,
            grid,
            reference,
            offset,
            noisy_spectrum,
            rings,
            frequency,
            clean,
        })
    }

    /// The response of whatever turned the noisy patch into `positions`.
    fn measure(&self, name: &str, positions: Vec<DVec3>) -> Result<MethodResponse, EvalError> {
        let g = resample(&positions, &self.patch.faces, &self.grid)?;
        let s = radial_spectrum(&g, self.offset)?;
        let gains = gain(&self.noisy_spectrum, &s)[self.rings.clone()].to_vec();
        let e = radial_spectrum(&difference(&g, &self.clean_grid), 0.0)?;
        let error = gain(&self.noisy_error, &e)[self.rings.clone()].to_vec();
        let diff = self
            .rings
            .clone()
            .map(|r| (self.noisy_spectrum.magnitude[r] - s.magnitude[r]) / self.l)
            .collect();
        Ok(MethodResponse {
            name: name.to_string(),
            bands: Bands::of(&gains, &self.clean, &self.frequency),
            gain: gains,
            error_bands: Bands::of(&error, &self.clean, &self.frequency),
            error,
            diff,
            metrics: self
                .reference
                .evaluate(&positions, Some(&self.patch.faces))?,
            positions,
            filled: g.filled,
        })
    }
}

/// Runs the experiment: builds the patch, adds the noise, denoises it with every method and
/// measures the response.
///
/// # Errors
/// A bad spec, a method's bad parameters or failure.
pub fn frequency_response(
    spec: &SpectrumSpec,
    methods: &[TableMethod],
) -> Result<FrequencyResponse, EvalError> {
    let e = Experiment::new(spec)?;
    let mut out = Vec::with_capacity(methods.len());
    for m in methods {
        let denoised = denoise(&e.noisy, Some(&e.patch.faces), &m.params)?;
        out.push(e.measure(&m.name, denoised.positions)?);
    }
    Ok(FrequencyResponse {
        spec: *spec,
        noisy_metrics: e.reference.evaluate(&e.noisy, Some(&e.patch.faces))?,
        patch: e.patch,
        noisy: e.noisy,
        l: e.l,
        grid: e.grid,
        frequency: e.frequency,
        clean: e.clean,
        methods: out,
    })
}

/// A half-amplitude cut-off (cycles per L) as a wavelength.
fn half(f: Option<f64>) -> String {
    f.map_or_else(|| "–".to_string(), |f| format!("{:.1} L", 1.0 / f))
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or_else(|| "–".to_string(), |v| format!("{v:.2}"))
}

impl FrequencyResponse {
    /// The clean surface's bands: where the shape and the noise dominate.
    pub fn clean_bands(&self) -> Bands {
        Bands::of(&self.clean, &self.clean, &self.frequency)
    }

    /// The band edges in cycles per L: the last frequency of the shape band and the first of the
    /// noise band (`None` where a band is empty).
    pub fn band_edges(&self) -> (Option<f64>, Option<f64>) {
        let (shape_end, noise_start) = band_rings(&self.clean);
        (
            shape_end
                .checked_sub(1)
                .and_then(|k| self.frequency.get(k).copied()),
            self.frequency.get(noise_start).copied(),
        )
    }

    /// The curves as CSV: ring, frequency (cycles per L), wavelength (L), the clean surface's
    /// gain, then `<method>_gain`, `<method>_diff` and `<method>_error` per method. Undefined
    /// values are empty.
    pub fn to_csv(&self) -> String {
        let mut s = String::from("ring,frequency_per_L,wavelength_L,clean_gain");
        for m in &self.methods {
            let _ = write!(s, ",{0}_gain,{0}_diff,{0}_error", m.name);
        }
        s.push('\n');
        let num = |v: f64| {
            if v.is_finite() {
                format!("{v:.6}")
            } else {
                String::new()
            }
        };
        for (k, &f) in self.frequency.iter().enumerate() {
            let _ = write!(
                s,
                "{},{},{},{}",
                k + 1,
                num(f),
                num(1.0 / f),
                num(self.clean[k])
            );
            for m in &self.methods {
                let _ = write!(
                    s,
                    ",{},{},{}",
                    num(m.gain[k]),
                    num(m.diff[k]),
                    num(m.error[k])
                );
            }
            s.push('\n');
        }
        s
    }

    /// The gain chart (log y): one line per method and the clean surface's gain dashed.
    pub fn chart(&self) -> LineChart {
        let mut c = LineChart::new(
            format!(
                "Frequency response ({} noise, σ = {:.0} % of L)",
                self.spec.noise.model,
                self.spec.noise.level * 100.0
            ),
            "radial frequency (cycles per L)",
            "gain |F_denoised| / |F_noisy|",
        );
        c.log_y = true;
        c.legend = Corner::LowerLeft;
        c.h_lines.push(1.0);
        let line = |g: &[f64]| -> Vec<(f64, f64)> {
            self.frequency
                .iter()
                .copied()
                .zip(g.iter().copied())
                .collect()
        };
        c.series.push(Series {
            dashed: true,
            ..Series::new("clean (ideal gain)", line(&self.clean), colours::REFERENCE)
        });
        for m in &self.methods {
            c.series.push(Series::new(
                label(&m.name),
                line(&m.gain),
                method_colour(&m.name),
            ));
        }
        let lo = self
            .clean
            .iter()
            .chain(self.methods.iter().flat_map(|m| m.gain.iter()))
            .copied()
            .filter(|g| g.is_finite() && *g > 0.0)
            .fold(f64::INFINITY, f64::min);
        let hi = self
            .methods
            .iter()
            .flat_map(|m| m.gain.iter())
            .copied()
            .filter(|g| g.is_finite())
            .fold(1.0, f64::max);
        if lo.is_finite() {
            c.y_range = Some(((lo / 1.5).max(1e-4), hi * 1.6));
        }
        c
    }

    /// The error-left chart (log y): per method, the error of the result over the noise, ring by
    /// ring; 1 (grey) is the noisy input.
    pub fn error_chart(&self) -> LineChart {
        let mut c = LineChart::new(
            "Error left per frequency (|F(denoised − clean)| / |F(noisy − clean)|)",
            "radial frequency (cycles per L)",
            "error left (1 = the input's noise)",
        );
        c.log_y = true;
        c.legend = Corner::LowerRight;
        c.h_lines.push(1.0);
        for m in &self.methods {
            let pts = self.frequency.iter().copied().zip(m.error.iter().copied());
            c.series.push(Series::new(
                label(&m.name),
                pts.collect(),
                method_colour(&m.name),
            ));
        }
        c
    }

    /// A short text saying what the curves show: [`FrequencyResponse::intro`], the band table,
    /// one sentence per method and [`FrequencyResponse::reading`], as Markdown.
    pub fn summary(&self) -> String {
        let mut s = format!("{}\n\n", self.intro());
        let (head, rows) = self.band_table();
        let _ = writeln!(s, "| {} |", head.join(" | "));
        let _ = writeln!(s, "|---|{}", "---:|".repeat(head.len() - 1));
        for r in rows {
            let _ = writeln!(s, "| {} |", r.join(" | "));
        }
        s.push('\n');
        for m in &self.methods {
            let _ = writeln!(s, "* {}", self.describe(m));
        }
        let _ = writeln!(s, "\n{}", self.reading());
        s
    }

    /// What was measured, and where the clean surface puts the shape and noise bands.
    pub fn intro(&self) -> String {
        let (shape_end, noise_start) = self.band_edges();
        let wl = |f: Option<f64>| f.map_or_else(|| "–".to_string(), |f| format!("{:.1}", 1.0 / f));
        format!(
            "Patch of {v}×{v} vertices (L = {l:.3} cells), {model} noise σ = {lvl:.0} % of L, \
             seed {seed}; resampled on a {n}×{n} grid with a Hann window; rings up to the vertex \
             Nyquist frequency ({fmax:.2} cycles per L). The clean surface's gain is ≥ {SHAPE_BAND} \
             (the shape dominates: the **shape band**) for wavelengths above {a} L and ≤ \
             {NOISE_BAND} (the noise dominates: the **noise band**) below {b} L; between them lies \
             the transition band.",
            v = self.spec.cells + 1,
            l = self.l,
            model = self.spec.noise.model,
            lvl = self.spec.noise.level * 100.0,
            seed = self.spec.noise.seed,
            n = self.grid.n,
            fmax = self.frequency.last().copied().unwrap_or(f64::NAN),
            a = wl(shape_end),
            b = wl(noise_start),
        )
    }

    /// Per row (clean, noisy, each method): surf_std and ang_deg on the patch, the mean gain in
    /// the three bands and the largest gain outside the shape band.
    pub fn band_table(&self) -> (Vec<String>, Vec<Vec<String>>) {
        let head = [
            "method",
            "surf_std",
            "ang_deg",
            "gain, shape band",
            "gain, transition",
            "gain, noise band",
            "half-amplitude λ",
            "max gain outside the shape band",
            "error left, shape band",
            "error left, transition",
        ]
        .map(String::from)
        .to_vec();
        let c = self.clean_bands();
        let mut rows = vec![
            vec![
                "clean (ideal)".into(),
                "0.00".into(),
                "0.00".into(),
                fmt_opt(c.shape),
                fmt_opt(c.transition),
                fmt_opt(c.noise),
                half(c.half),
                "–".into(),
                "0.00".into(),
                "0.00".into(),
            ],
            vec![
                "noisy".into(),
                fmt_opt(self.noisy_metrics.surf_std),
                fmt_opt(self.noisy_metrics.ang_deg),
                "1.00".into(),
                "1.00".into(),
                "1.00".into(),
                "–".into(),
                "1.00".into(),
                "1.00".into(),
                "1.00".into(),
            ],
        ];
        for m in &self.methods {
            let b = &m.bands;
            rows.push(vec![
                label(&m.name).to_string(),
                fmt_opt(m.metrics.surf_std),
                fmt_opt(m.metrics.ang_deg),
                fmt_opt(b.shape),
                fmt_opt(b.transition),
                fmt_opt(b.noise),
                half(b.half),
                if b.peak_outside_shape_frequency.is_finite() {
                    format!(
                        "{:.2} at λ = {:.1} L",
                        b.peak_outside_shape,
                        1.0 / b.peak_outside_shape_frequency
                    )
                } else {
                    "–".into()
                },
                fmt_opt(m.error_bands.shape),
                fmt_opt(m.error_bands.transition),
            ]);
        }
        (head, rows)
    }

    /// How the curves compare with the paper's reading of its Fig. 12.
    pub fn reading(&self) -> String {
        let boosting: Vec<&str> = self
            .methods
            .iter()
            .filter(|m| m.bands.peak_outside_shape > 1.05)
            .map(|m| label(&m.name))
            .collect();
        let best = self
            .methods
            .iter()
            .filter_map(|m| Some((label(&m.name), m.bands.noise?)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let mut s = String::from(
            "How to read it: a gain near 1 at low frequencies means the shape is kept; a gain far \
             below 1 at high frequencies means the noise is removed; a gain above 1 means the \
             operator adds energy at that frequency, which is how sharpened features (and new \
             artefacts) show; the error-left chart tells the two apart. The paper reads its \
             Fig. 12 as a band-pass with gains in the middle frequencies that would explain its \
             feature enhancement.",
        );
        if boosting.is_empty() {
            s.push_str(" Here no method has a gain above 1.05 outside the shape band.");
        } else {
            let _ = write!(
                s,
                " Here {} gain{} above 1.05 outside the shape band.",
                boosting.join(" and "),
                if boosting.len() == 1 { "s" } else { "" }
            );
        }
        if let Some((name, g)) = best {
            let _ = write!(
                s,
                " The strongest noise suppression is {name}'s ({:.0} % of the noise amplitude left \
                 in the noise band).",
                g * 100.0
            );
        }
        let least = |f: fn(&Bands) -> Option<f64>| {
            self.methods
                .iter()
                .filter_map(|m| Some((label(&m.name), f(&m.error_bands)?)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
        };
        if let (Some((a, x)), Some((b, y))) = (least(|b| b.shape), least(|b| b.transition)) {
            let _ = write!(
                s,
                " The least error where the shape dominates is {a}'s ({:.0} % of the input's), \
                 in the transition band {b}'s ({:.0} %).",
                x * 100.0,
                y * 100.0
            );
        }
        s
    }

    /// One sentence on one method's curve.
    pub fn describe(&self, m: &MethodResponse) -> String {
        let b = &m.bands;
        let mut parts = Vec::new();
        match b.shape {
            Some(g) if (g - 1.0).abs() <= 0.05 => parts.push(format!(
                "keeps the shape (gain {g:.2} where the shape dominates)"
            )),
            Some(g) if g < 1.0 => parts.push(format!(
                "attenuates the shape itself (gain {g:.2} where the shape dominates)"
            )),
            Some(g) => parts.push(format!(
                "amplifies the shape (gain {g:.2} where the shape dominates)"
            )),
            None => {}
        }
        match (b.half, self.clean_bands().half) {
            (Some(f), Some(c)) => parts.push(format!(
                "drops below half amplitude at wavelengths under {:.1} L (the clean surface: {:.1} L)",
                1.0 / f,
                1.0 / c
            )),
            (Some(f), None) => parts.push(format!(
                "drops below half amplitude at wavelengths under {:.1} L",
                1.0 / f
            )),
            (None, _) => parts.push("never drops below half amplitude".into()),
        }
        if let Some(g) = b.noise {
            parts.push(format!(
                "keeps {:.0} % of the noise amplitude where the noise dominates{}",
                g * 100.0,
                if g < 0.1 {
                    " (a strong low-pass)"
                } else if g < 0.5 {
                    ""
                } else {
                    " (little noise removed)"
                }
            ));
        }
        let e = &m.error_bands;
        if let (Some(a), Some(t)) = (e.shape, e.transition) {
            parts.push(format!(
                "leaves {:.0} % of the input's error where the shape dominates and {:.0} % in the \
                 transition band",
                a * 100.0,
                t * 100.0
            ));
        }
        if b.peak_outside_shape > 1.05 {
            let at = self
                .frequency
                .iter()
                .position(|&f| f == b.peak_outside_shape_frequency)
                .and_then(|k| m.error.get(k).copied())
                .unwrap_or(f64::NAN);
            let verdict = if at < 1.0 {
                "the energy it adds there moves the surface towards the clean one (restored \
                 shape, the feature sharpening the paper reads into its Fig. 12)"
            } else {
                "the energy it adds there is new error, not restored shape"
            };
            parts.push(format!(
                "and boosts mid frequencies (gain up to {:.2} at a wavelength of {:.1} L), where \
                 its error is {:.0} % of the input's: {verdict}",
                b.peak_outside_shape,
                1.0 / b.peak_outside_shape_frequency,
                at * 100.0
            ));
        } else if let Some(t) = b.transition {
            parts.push(format!(
                "and rolls off smoothly through the transition band (mean gain {t:.2}, no gain above 1)"
            ));
        }
        format!("**{}** {}.", label(&m.name), parts.join(", "))
    }

    /// Writes `spectrum.svg` and `spectrum_error.svg` (the charts), `spectrum.csv`, `spectrum.md`
    /// (the summary) and, with `render`, `patch_clean.png`, `patch_noisy.png` and
    /// `patch_<method>.png` into `dir` (created if missing); returns the paths written.
    ///
    /// # Errors
    /// Unwritable directory or files, chart or rendering failures.
    pub fn write(
        &self,
        dir: &Path,
        render_options: Option<&RenderOptions>,
    ) -> Result<Vec<PathBuf>, EvalError> {
        std::fs::create_dir_all(dir).map_err(|e| crate::io::IoError::io(dir, e))?;
        let mut files = Vec::new();
        let mut text = |name: &str, body: &str| -> Result<(), EvalError> {
            let p = dir.join(name);
            write_file(&p, body.as_bytes())?;
            files.push(p);
            Ok(())
        };
        text("spectrum.svg", &self.chart().to_svg()?)?;
        text("spectrum_error.svg", &self.error_chart().to_svg()?)?;
        text("spectrum.csv", &self.to_csv())?;
        text("spectrum.md", &self.summary())?;
        if let Some(o) = render_options {
            let mut shapes: Vec<(String, &[DVec3])> = vec![
                ("clean".into(), &self.patch.positions),
                ("noisy".into(), &self.noisy),
            ];
            for m in &self.methods {
                shapes.push((m.name.clone(), &m.positions));
            }
            for (name, pos) in shapes {
                let p = dir.join(format!("patch_{name}.png"));
                render(pos, Some(&self.patch.faces), o)?.save(&p)?;
                files.push(p);
            }
        }
        Ok(files)
    }
}

/// The oblique view of the patch renderings: from above (+z), tilted towards −y.
pub fn patch_view() -> View {
    View::Angles {
        azimuth: 15.0,
        elevation: -60.0,
    }
}

/// Writes `bytes` to `path` atomically.
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<(), EvalError> {
    use std::io::Write as _;
    let mut f = crate::io::AtomicFile::create(path)?;
    f.write_all(bytes).map_err(|e| f.err(e))?;
    f.commit()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::denoise::{Method, Params};

    fn grid_of(n: usize, f: impl Fn(usize, usize) -> f64) -> HeightGrid {
        HeightGrid {
            grid: GridSpec {
                origin: DVec2::ZERO,
                spacing: 1.0,
                n,
            },
            heights: (0..n * n).map(|k| f(k % n, k / n)).collect(),
            filled: 0,
        }
    }

    #[test]
    fn a_sinusoid_peaks_at_its_frequency() {
        let n = 64;
        for (kx, ky) in [(8usize, 0usize), (0, 5), (6, 8)] {
            let g = grid_of(n, |i, j| {
                2.0 + 0.7
                    * (2.0 * PI * (kx as f64 * i as f64 + ky as f64 * j as f64) / n as f64).sin()
            });
            let s = radial_spectrum(&g, window_mean(&g)).unwrap();
            let r = ((kx * kx + ky * ky) as f64).sqrt().round() as usize;
            assert_eq!(s.peak(), Some(r), "k = ({kx}, {ky})");
            // Two conjugate terms of magnitude a/2 = 0.35 and the window's ±1-bin side lobes
            // (half as large) carry the power: 2 · 0.35² · (1 + 4 · ¼ + 4 · 1/16) … at most.
            let total: f64 = s.power.iter().sum();
            assert!(s.power[r] > 0.4 * total, "{:?}", s.power);
            assert!((s.frequency(r) - r as f64 / 64.0).abs() < 1e-15);
        }
        // A constant has no power outside ring 0 once its mean is removed.
        let flat = grid_of(16, |_, _| 3.0);
        let s = radial_spectrum(&flat, window_mean(&flat)).unwrap();
        assert!(s.power.iter().all(|&p| p < 1e-24), "{:?}", s.power);
        let zero = grid_of(16, |_, _| 0.0);
        assert_eq!(radial_spectrum(&zero, 0.0).unwrap().peak(), None);
    }

    #[test]
    fn radial_binning_puts_every_term_in_its_ring_once() {
        // A single spike: after the window its DFT has the same magnitude m in every term, so each
        // ring's power is its term count times m² and its mean magnitude is m.
        let n = 8;
        let g = grid_of(n, |i, j| if (i, j) == (3, 4) { 1.0 } else { 0.0 });
        let s = radial_spectrum(&g, 0.0).unwrap();
        // Integer vectors k with components in −3..=4 by round(|k|), counted by hand:
        // ring 1: (±1, 0), (0, ±1), (±1, ±1); ring 2: (±2, 0), (0, ±2), (±2, ±1), (±1, ±2); ring 3:
        // (±3, 0), (0, ±3), (±3, ±1), (±1, ±3), (±2, ±2); ring 4: (4, 0..=±2), (0..=±2, 4), (±3, ±2),
        // (±2, ±3), (±3, ±3). The 5 left (|k| ≥ 4.5) lie beyond the last ring.
        assert_eq!(s.count, [1, 8, 12, 16, 22]);
        let w = hann(n);
        let norm: f64 = w.iter().sum::<f64>().powi(2);
        let m = w[3] * w[4] / norm;
        for r in 0..s.count.len() {
            assert!((s.magnitude[r] - m).abs() < 1e-15 * m.max(1.0), "ring {r}");
            let p = s.count[r] as f64 * m * m;
            assert!((s.power[r] - p).abs() < 1e-12 * p, "ring {r}");
        }
        // Parseval over the terms the rings hold: Σ power = (59 / 64) · n² · Σ|windowed field|².
        let total: f64 = s.power.iter().sum();
        let field = (w[3] * w[4] / norm).powi(2) * (n * n) as f64;
        assert!((total - field * 59.0 / 64.0).abs() < 1e-12 * total);
    }

    #[test]
    fn the_identity_operator_has_gain_one_and_the_clean_surface_the_ideal_gain() {
        let spec = SpectrumSpec {
            cells: 24,
            ..SpectrumSpec::default()
        };
        let e = Experiment::new(&spec).unwrap();
        let id = e.measure("identity", e.noisy.clone()).unwrap();
        assert_eq!(id.gain.len(), spec.max_ring());
        for (r, g) in id.gain.iter().enumerate() {
            assert!((g - 1.0).abs() < 1e-12, "ring {}: {g}", r + 1);
        }
        assert!(id.diff.iter().all(|d| d.abs() < 1e-12), "{:?}", id.diff);
        assert!(
            id.error.iter().all(|x| (x - 1.0).abs() < 1e-12),
            "{:?}",
            id.error
        );
        assert_eq!(id.bands.half, None);
        assert!((id.bands.peak - 1.0).abs() < 1e-12);
        assert_eq!(id.filled, 0);
        // Handing in the clean patch reproduces the reference curve: gain = |F_clean| / |F_noisy|.
        let clean = e.measure("clean", e.patch.positions.clone()).unwrap();
        assert_eq!(clean.gain, e.clean);
        assert!(clean.error.iter().all(|&x| x == 0.0), "{:?}", clean.error);
        assert_eq!(clean.metrics.surf_std, Some(0.0));
        // And the clean curve starts near 1 (the shape) and ends well below (the noise).
        assert!(
            e.clean[0] > 0.9 && *e.clean.last().unwrap() < 0.5,
            "{:?}",
            e.clean
        );
    }

    #[test]
    fn an_unchanged_field_has_gain_one_everywhere() {
        let g = grid_of(32, |i, j| {
            ((i * 7 + j * 13) % 11) as f64 * 0.1 + (i as f64 * 0.3).sin()
        });
        let off = window_mean(&g);
        let a = radial_spectrum(&g, off).unwrap();
        let b = radial_spectrum(&g.clone(), off).unwrap();
        for (r, x) in gain(&a, &b).into_iter().enumerate() {
            assert!((x - 1.0).abs() < 1e-12, "ring {r}: {x}");
        }
        // Scaling the field (about the offset) scales the gain.
        let half = grid_of(32, |i, j| off + 0.5 * (g.at(i, j) - off));
        let c = radial_spectrum(&half, off).unwrap();
        for x in &gain(&a, &c)[1..] {
            assert!((x - 0.5).abs() < 1e-9, "{x}");
        }
    }

    #[test]
    fn resampling_a_plane_gives_the_plane() {
        let plane = |x: f64, y: f64| 0.3 * x - 0.2 * y + 1.0;
        let m = height_field_mesh(12, 0.3, 5, plane).unwrap();
        let grid = GridSpec {
            origin: DVec2::splat(0.0),
            spacing: 12.0 / 37.0,
            n: 38,
        };
        let g = resample(&m.positions, &m.faces, &grid).unwrap();
        assert_eq!(g.filled, 0);
        for j in 0..grid.n {
            for i in 0..grid.n {
                let p = grid.point(i, j);
                assert!((g.at(i, j) - plane(p.x, p.y)).abs() < 1e-12, "({i}, {j})");
            }
        }
        // Outside the mesh nothing is covered.
        let away = GridSpec {
            origin: DVec2::splat(100.0),
            ..grid
        };
        assert!(matches!(
            resample(&m.positions, &m.faces, &away),
            Err(EvalError::Degenerate(_))
        ));
    }

    #[test]
    fn holes_are_filled_and_counted() {
        let m = height_field_mesh(8, 0.0, 0, |_, _| 2.0).unwrap();
        // Drop the two triangles of interior cell (3, 3): the 9 grid points strictly inside it
        // are not covered.
        let tris: Vec<[u32; 3]> = m
            .faces
            .triangles()
            .enumerate()
            .filter(|(k, _)| k / 2 != 3 * 8 + 3)
            .map(|(_, t)| t)
            .collect();
        let faces = Faces::from_triangles(&tris);
        let grid = GridSpec {
            origin: DVec2::ZERO,
            spacing: 0.25,
            n: 33,
        };
        let g = resample(&m.positions, &faces, &grid).unwrap();
        assert_eq!(g.filled, 9);
        assert!(g.heights.iter().all(|&h| (h - 2.0).abs() < 1e-12));
    }

    #[test]
    fn a_sinusoidal_mesh_peaks_at_its_frequency_after_resampling() {
        let spec = SpectrumSpec {
            cells: 38,
            ..SpectrumSpec::default()
        };
        let width = (spec.cells - 2 * MARGIN) as f64;
        let k = 4.0;
        let m = height_field_mesh(spec.cells, JITTER, 1, |x, y| {
            0.5 * (2.0 * PI * k * (x - MARGIN as f64) / width).cos() + 0.01 * y
        })
        .unwrap();
        let g = resample(&m.positions, &m.faces, &spec.grid()).unwrap();
        let s = radial_spectrum(&g, window_mean(&g)).unwrap();
        assert_eq!(s.peak(), Some(4));
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(height_field_mesh(0, 0.1, 0, |_, _| 0.0).is_err());
        assert!(height_field_mesh(4, 0.5, 0, |_, _| 0.0).is_err());
        assert!(matches!(
            height_field_mesh(4, 0.1, 0, |_, _| f64::NAN),
            Err(EvalError::NonFinite { .. })
        ));
        let spec = SpectrumSpec {
            cells: 3,
            ..SpectrumSpec::default()
        };
        assert!(matches!(
            frequency_response(&spec, &[]),
            Err(EvalError::Param { name: "patch", .. })
        ));
        let g = grid_of(8, |_, _| 0.0);
        let short = HeightGrid {
            heights: vec![0.0; 3],
            ..g.clone()
        };
        assert!(radial_spectrum(&short, 0.0).is_err());
        let nan = HeightGrid {
            heights: vec![f64::NAN; 64],
            ..g
        };
        assert!(radial_spectrum(&nan, 0.0).is_err());
        let m = height_field_mesh(4, 0.0, 0, |_, _| 0.0).unwrap();
        let bad = GridSpec {
            origin: DVec2::ZERO,
            spacing: 0.0,
            n: 8,
        };
        assert!(resample(&m.positions, &m.faces, &bad).is_err());
    }

    #[test]
    fn small_experiment_separates_shape_and_noise() {
        let spec = SpectrumSpec {
            cells: 40,
            ..SpectrumSpec::default()
        };
        let methods = [
            TableMethod::new("identity-ish", {
                // Bilateral with one pass is the lightest filter available: it must keep the
                // shape band and remove some of the noise.
                Params {
                    method: Method::Bilateral,
                    iterations: 1,
                    ..Params::default()
                }
            }),
            TableMethod::new("default", Params::default()),
        ];
        let r = frequency_response(&spec, &methods).unwrap();
        assert_eq!(r.frequency.len(), spec.max_ring());
        assert!(r.clean[0] > 0.9, "{:?}", r.clean);
        assert!(*r.clean.last().unwrap() < 0.5, "{:?}", r.clean);
        for m in &r.methods {
            let b = m.bands;
            assert!(b.shape.is_some_and(|g| (g - 1.0).abs() < 0.1), "{b:?}");
            let last = *m.gain.last().unwrap();
            assert!(last < 0.9, "{}: {last}", m.name);
        }
        let csv = r.to_csv();
        assert_eq!(csv.lines().count(), spec.max_ring() + 1);
        assert!(csv.starts_with("ring,frequency_per_L,wavelength_L,clean_gain,identity-ish_gain"));
        assert!(r.summary().contains("| qemd default |"));
        assert!(r.chart().to_svg().unwrap().contains("clean (ideal gain)"));
    }
}
