//! A [`FrequencyResponse`] as charts, CSV, a summary, a band table and text for the report, and
//! the files [`FrequencyResponse::write`] puts in a folder.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::analysis::{Bands, NOISE_BAND, SHAPE_BAND, band_rings};
use super::{FrequencyResponse, MethodResponse};
use crate::eval::methods::{label, method_colour};
use crate::eval::plot::{Corner, LineChart, Series, colours};
use crate::eval::render::{RenderOptions, render};
use crate::eval::{EvalError, write_file};

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
