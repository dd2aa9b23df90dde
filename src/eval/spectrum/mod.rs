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
//!
//! # Files
//!
//! `patch` synthesises the test patch, `analysis` resamples meshes as height fields and
//! measures their spectra, `present` turns a [`FrequencyResponse`] into charts, CSV and text;
//! this file holds the experiment itself.

use glam::{DVec2, DVec3};

use super::metrics::{Metrics, Reference};
use super::noise::{NoiseModel, NoiseSpec, add_noise};
use super::render::View;
use super::table::TableMethod;
use super::{EvalError, Mesh};
use crate::denoise::denoise;

mod analysis;
mod patch;
mod present;

pub use analysis::{
    Bands, GridSpec, HeightGrid, NOISE_BAND, RadialSpectrum, SHAPE_BAND, gain, radial_spectrum,
    resample, window_mean,
};
pub use patch::{JITTER, height_field_mesh, height_patch, patch_height};

/// Cells of the patch left out of the resampling grid on each side (boundary vertices have
/// one-sided neighbourhoods).
pub const MARGIN: usize = 3;
/// Grid points per cell along each axis.
pub const OVERSAMPLE: usize = 2;

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

/// The oblique view of the patch renderings: from above (+z), tilted towards −y.
pub fn patch_view() -> View {
    View::Angles {
        azimuth: 15.0,
        elevation: -60.0,
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use super::analysis::hann;
    use super::*;
    use crate::denoise::{Method, Params};
    use crate::points::Faces;

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
