//! The quality report: one folder with an `index.html` and a `README.md` (plus the figures they
//! show) that puts qemd's default operator next to the paper's operator, the
//! bilateral baseline and the noisy input.
//!
//! [`write_report`] runs, on one clean mesh:
//!
//! * the Table I protocol ([`super::table`]): `iso` noise at 20, 40 and 80 % of L, metrics averaged
//!   over the seeds, for the three methods of [`report_methods`] and the noisy input, all metrics;
//! * two charts of `surf_std` and `ang_deg` against the noise level ([`super::plot`], SVG);
//! * renderings ([`super::render`]) of the clean mesh and of the noisy, faithful, bilateral and
//!   default results at 40 % noise, first seed, one view;
//! * the real benchmark pairs ([`super::pairs`]; skipped with a note where the files are absent);
//! * the frequency response ([`super::spectrum`]) with a paragraph on what the curves show.
//!
//! Both documents are built from one document model and link the figures (SVG charts, PNG renderings) as
//! files of the same folder, so the folder is the unit to keep or commit and no figure is stored
//! twice. Besides them the folder holds `table.json` (every run) and `pairs.json`. The output
//! depends only on the inputs and the spec: no dates or timings, so a regenerated report differs
//! only where results do.
//!
//! # Files
//!
//! The roster is `eval/methods.rs`; `sections` builds the content and `doc` prints it. This file
//! runs the experiments and writes the folder.

use std::path::{Path, PathBuf};

use super::metrics::Metrics;
use super::noise::{NoiseSpec, add_noise_with_length};
use super::pairs::{Pair, PairsOutcome, benchmark_pairs, run_pairs};
use super::plot::{LineChart, Series};
use super::render::{RenderOptions, render};
use super::spectrum::{FrequencyResponse, SpectrumSpec, frequency_response};
use super::table::{NOISY, Summary, Table, TableSpec, run_table_with_progress};
use super::{EvalError, Mesh, scale_length, write_file};
use crate::denoise::denoise;

mod doc;
mod sections;

pub use super::methods::{BILATERAL, DEFAULT, FAITHFUL, label, method_colour, report_methods};
use sections::document;

/// What the report covers.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportSpec {
    /// Name of the clean mesh (shown in the title).
    pub title: String,
    /// The command that regenerates the report, shown at the top.
    pub command: Option<String>,
    /// Noise seeds; the table averages over them, the renderings use the first.
    pub seeds: Vec<u64>,
    /// Noise levels of the table, fractions of L.
    pub levels: Vec<f64>,
    /// Noise level of the renderings.
    pub render_level: f64,
    /// Renderer settings (size, view).
    pub render: RenderOptions,
    /// Directory of the benchmark pairs; `None` leaves the section out with a note.
    pub pairs_dir: Option<PathBuf>,
    /// The pairs to look for there.
    pub pairs: Vec<Pair>,
    /// The frequency-response experiment; `None` leaves it out.
    pub spectrum: Option<SpectrumSpec>,
}

impl Default for ReportSpec {
    /// Levels 20/40/80 %, seed 0, renderings at 40 % (420 × 420, iso view), the pairs of
    /// [`super::pairs::DEFAULT_DIR`], the default frequency-response experiment.
    fn default() -> Self {
        ReportSpec {
            title: "mesh".into(),
            command: None,
            seeds: vec![0],
            levels: vec![0.2, 0.4, 0.8],
            render_level: 0.4,
            render: RenderOptions {
                width: 420,
                height: 420,
                ..RenderOptions::default()
            },
            pairs_dir: Some(PathBuf::from(super::pairs::DEFAULT_DIR)),
            pairs: benchmark_pairs(),
            spectrum: Some(SpectrumSpec::default()),
        }
    }
}

impl ReportSpec {
    /// The Table I spec of the report.
    pub fn table_spec(&self) -> TableSpec {
        TableSpec {
            levels: self.levels.clone(),
            seeds: self.seeds.clone(),
            methods: report_methods(),
            ..TableSpec::default()
        }
    }

    /// Checks everything before any work starts.
    ///
    /// # Errors
    /// [`EvalError::Param`] naming the bad value.
    pub fn validate(&self) -> Result<(), EvalError> {
        self.table_spec().validate()?;
        NoiseSpec {
            level: self.render_level,
            ..NoiseSpec::default()
        }
        .validate()?;
        self.render.validate()?;
        if let Some(s) = &self.spectrum {
            s.validate()?;
        }
        Ok(())
    }
}

/// One rendering of the report.
#[derive(Debug, Clone, PartialEq)]
pub struct Rendering {
    /// Row name (`clean`, `noisy` or a method).
    pub name: String,
    /// PNG file name in the report folder.
    pub file: String,
    /// Metrics of the rendered result (`None` for the clean mesh).
    pub metrics: Option<Metrics>,
}

/// What [`write_report`] produced.
#[derive(Debug, Clone)]
pub struct Report {
    /// The Table I results.
    pub table: Table,
    /// The renderings.
    pub renderings: Vec<Rendering>,
    /// The benchmark pairs (`None` when not asked for).
    pub pairs: Option<PairsOutcome>,
    /// The frequency response (`None` when not asked for).
    pub spectrum: Option<FrequencyResponse>,
    /// Every file written.
    pub files: Vec<PathBuf>,
}

/// Runs everything the spec asks for on `clean` and writes the report into `out` (created if
/// missing). `log` hears about progress, one line at a time.
///
/// # Errors
/// A bad spec, a mesh without faces, a denoiser failure, unreadable pair files, unwritable output.
pub fn write_report(
    clean: &Mesh,
    spec: &ReportSpec,
    out: &Path,
    log: &mut dyn FnMut(&str),
) -> Result<Report, EvalError> {
    spec.validate()?;
    if clean.faces.is_empty() {
        return Err(EvalError::Empty {
            what: "clean mesh",
            detail: "the report needs faces".into(),
        });
    }
    std::fs::create_dir_all(out).map_err(|e| crate::io::IoError::io(out, e))?;
    let mut files = Vec::new();

    log(&format!(
        "Table I: {} levels × {} seeds × {} rows",
        spec.levels.len(),
        spec.seeds.len(),
        report_methods().len() + 1
    ));
    let table = run_table_with_progress(
        &clean.positions,
        &clean.faces,
        &spec.table_spec(),
        &mut |p| {
            if p.method == DEFAULT {
                log(&format!(
                    "[{}/{}] level {:.0} % seed {} done",
                    p.done,
                    p.total,
                    p.level * 100.0,
                    p.seed
                ));
            }
        },
    )?;
    let json = serde_json::to_string_pretty(&table)?;
    let p = out.join("table.json");
    write_file(&p, json.as_bytes())?;
    files.push(p);

    for (file, chart) in [
        (
            "surf_std.svg",
            level_chart(&table, "surf_std", |m| m.surf_std),
        ),
        ("ang_deg.svg", level_chart(&table, "ang_deg", |m| m.ang_deg)),
    ] {
        let p = out.join(file);
        write_file(&p, chart.to_svg()?.as_bytes())?;
        files.push(p);
    }

    log(&format!(
        "renderings at {:.0} % noise",
        spec.render_level * 100.0
    ));
    let renderings = renderings(clean, spec, out, &mut files)?;

    let pairs = match &spec.pairs_dir {
        Some(dir) => {
            let p = run_pairs(dir, &spec.pairs, &report_methods(), log)?;
            for s in &p.skipped {
                log(s);
            }
            Some(p)
        }
        None => None,
    };

    let spectrum = match &spec.spectrum {
        Some(s) => {
            log("frequency response");
            let r = frequency_response(s, &report_methods())?;
            files.extend(r.write(out, Some(&patch_render_options(&spec.render)))?);
            Some(r)
        }
        None => None,
    };

    let report = Report {
        table,
        renderings,
        pairs,
        spectrum,
        files,
    };
    let doc = document(clean, spec, &report);
    let mut report = report;
    for (name, body) in [
        ("index.html", doc.to_html()),
        ("README.md", doc.to_markdown()),
    ] {
        let p = out.join(name);
        write_file(&p, body.as_bytes())?;
        report.files.push(p);
    }
    if let Some(p) = &report.pairs {
        let p = serde_json::to_string_pretty(p)?;
        let path = out.join("pairs.json");
        write_file(&path, p.as_bytes())?;
        report.files.push(path);
    }
    Ok(report)
}

/// The patch renderings: the report's size, the oblique patch view.
fn patch_render_options(o: &RenderOptions) -> RenderOptions {
    RenderOptions {
        view: super::spectrum::patch_view(),
        ..o.clone()
    }
}

/// A metric against the noise level (%), one line per row.
fn level_chart(table: &Table, metric: &str, f: fn(&Summary) -> Option<f64>) -> LineChart {
    let unit = if metric == "ang_deg" {
        "degrees"
    } else {
        "% of L"
    };
    let mut c = LineChart::new(
        format!(
            "{metric} against noise level ({} noise, mean over {} seed{})",
            table.model,
            table.seeds.len(),
            if table.seeds.len() == 1 { "" } else { "s" }
        ),
        "noise σ (% of L)",
        format!("{metric} ({unit})"),
    );
    for row in &table.rows {
        let pts = row
            .cells
            .iter()
            .filter_map(|c| Some((c.level * 100.0, f(&c.mean)?)))
            .collect();
        c.series.push(Series {
            markers: true,
            dashed: row.method == NOISY,
            ..Series::new(label(&row.method), pts, method_colour(&row.method))
        });
    }
    c
}

fn renderings(
    clean: &Mesh,
    spec: &ReportSpec,
    out: &Path,
    files: &mut Vec<PathBuf>,
) -> Result<Vec<Rendering>, EvalError> {
    let l = scale_length(&clean.positions, Some(&clean.faces))?;
    let noise = NoiseSpec {
        level: spec.render_level,
        seed: spec.seeds.first().copied().unwrap_or(0),
        ..NoiseSpec::default()
    };
    let noisy = add_noise_with_length(&clean.positions, Some(&clean.faces), &noise, l)?;
    let reference =
        super::metrics::Reference::new(clean.positions.clone(), Some(clean.faces.clone()))?;
    let mut shapes = vec![
        ("clean".to_string(), clean.positions.clone(), None),
        (
            NOISY.to_string(),
            noisy.positions.clone(),
            Some(reference.evaluate(&noisy.positions, Some(&clean.faces))?),
        ),
    ];
    for m in report_methods() {
        let d = denoise(&noisy.positions, Some(&clean.faces), &m.params)?;
        let metrics = reference.evaluate(&d.positions, Some(&clean.faces))?;
        shapes.push((m.name, d.positions, Some(metrics)));
    }
    let mut r = Vec::new();
    for (name, pos, metrics) in shapes {
        let file = format!("render_{name}.png");
        let p = out.join(&file);
        render(&pos, Some(&clean.faces), &spec.render)?.save(&p)?;
        files.push(p);
        r.push(Rendering {
            name,
            file,
            metrics,
        });
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::synth::Shape;

    /// The numeric cells of the Markdown table whose header line starts with `head`.
    fn table_numbers(md: &str, head: &str) -> Vec<(String, Vec<f64>)> {
        let mut lines = md.lines().skip_while(|l| !l.starts_with(head));
        assert!(lines.next().is_some(), "no table `{head}`");
        lines
            .skip(1)
            .take_while(|l| l.starts_with('|'))
            .map(|l| {
                let cells: Vec<&str> = l.trim_matches('|').split('|').map(str::trim).collect();
                let nums = cells[1..]
                    .iter()
                    .map(|c| c.parse::<f64>().unwrap_or_else(|_| panic!("`{c}` in {l}")))
                    .collect();
                (cells[0].to_string(), nums)
            })
            .collect()
    }

    #[test]
    fn small_report_has_every_section() {
        let m = Shape::Sphere.mesh(2).unwrap();
        let dir = tempfile::tempdir().unwrap();
        // One generated pair, with made-up published numbers.
        let pairs = dir.path().join("pairs");
        std::fs::create_dir(&pairs).unwrap();
        let noisy = super::super::noise::add_noise(
            &m.positions,
            Some(&m.faces),
            &NoiseSpec {
                level: 0.3,
                ..NoiseSpec::default()
            },
        )
        .unwrap();
        m.clone()
            .into_cloud()
            .write(&pairs.join("c.ply"), None)
            .unwrap();
        crate::io::Cloud::generated(
            noisy.positions,
            Some(m.faces.clone()),
            crate::points::ScalarType::F64,
        )
        .write(&pairs.join("n.ply"), None)
        .unwrap();
        let mut pair = Pair {
            name: "sphere_pair".into(),
            clean: "c.ply".into(),
            noisy: "n.ply".into(),
            published: None,
        };
        pair.published = Some(super::super::pairs::Published {
            source: "test".into(),
            ang_deg: 1.25,
            surf_std: 2.5,
        });
        let out = dir.path().join("report");
        let spec = ReportSpec {
            title: "sphere".into(),
            command: Some("qemd report sphere.ply".into()),
            seeds: vec![0, 1],
            levels: vec![0.2, 0.4],
            render: RenderOptions {
                width: 120,
                height: 120,
                ..RenderOptions::default()
            },
            pairs_dir: Some(pairs),
            pairs: vec![pair],
            spectrum: Some(SpectrumSpec {
                cells: 16,
                ..SpectrumSpec::default()
            }),
            ..ReportSpec::default()
        };
        let mut lines = 0;
        let r = write_report(&m, &spec, &out, &mut |_| lines += 1).unwrap();
        assert!(lines > 3);
        assert_eq!(r.table.rows.len(), 4);
        assert_eq!(r.renderings.len(), 5);
        for f in &r.files {
            assert!(f.is_file(), "{}", f.display());
        }
        for name in ["clean", "noisy", "faithful", "bilateral", "default"] {
            for file in [format!("render_{name}.png"), format!("patch_{name}.png")] {
                let bytes = std::fs::read(out.join(&file)).unwrap();
                assert!(bytes.starts_with(b"\x89PNG"), "{file}");
            }
        }
        for file in [
            "surf_std.svg",
            "ang_deg.svg",
            "spectrum.svg",
            "spectrum_error.svg",
        ] {
            let svg = std::fs::read_to_string(out.join(file)).unwrap();
            assert!(
                svg.starts_with("<svg") && svg.contains("qemd default"),
                "{file}"
            );
        }

        let md = std::fs::read_to_string(out.join("README.md")).unwrap();
        let head = table_numbers(&md, "| method | 20 % | 40 % |");
        let names: Vec<&str> = head.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(
            names,
            ["noisy input", "faithful", "bilateral", "qemd default"]
        );
        // The input's residual is the noise itself; every method lowers it.
        let noisy = &head[0].1;
        assert!(
            (noisy[0] - 20.0).abs() < 5.0 && (noisy[1] - 40.0).abs() < 10.0,
            "{noisy:?}"
        );
        for (name, v) in &head[1..] {
            assert!(v[0] < noisy[0] && v[1] < noisy[1], "{name}: {v:?}");
        }
        for (name, v) in table_numbers(&md, "| method | surf_std | surf_rms |") {
            assert_eq!(v.len(), 5, "{name}");
            assert!(v.iter().all(|x| x.is_finite()), "{name}");
        }
        assert!(md.contains("At 20 % noise the lowest `surf_std` is"));
        assert!(md.contains("![surf_std against noise level](surf_std.svg)"));
        // The pair: noisy, three methods, the published column.
        let pair_row = md
            .lines()
            .find(|l| l.starts_with("| sphere_pair |"))
            .unwrap();
        assert_eq!(pair_row.matches(" / ").count(), 5, "{pair_row}");
        assert!(pair_row.ends_with("| 1.25 / 2.5 |"), "{pair_row}");
        assert!(md.contains("against GCN-Denoiser's 1.25°"));
        assert!(md.contains("half-amplitude λ") && md.contains("* **qemd default** "));

        let html = std::fs::read_to_string(out.join("index.html")).unwrap();
        for needle in [
            "<title>qemd quality report: sphere</title>",
            "noisy input",
            "<td>qemd default</td>",
            "<img src=\"surf_std.svg\"",
            "<img src=\"render_default.png\"",
            "<img src=\"spectrum.svg\"",
            "Frequency response",
            "qemd report sphere.ply",
        ] {
            assert!(html.contains(needle), "{needle}");
        }

        // A missing pairs folder is a note, not an error; a bad spec fails before writing.
        let spec = ReportSpec {
            pairs_dir: Some(dir.path().join("no-pairs-here")),
            spectrum: None,
            seeds: vec![0],
            levels: vec![0.2],
            ..spec
        };
        let again = dir.path().join("again");
        write_report(&m, &spec, &again, &mut |_| {}).unwrap();
        let md = std::fs::read_to_string(again.join("README.md")).unwrap();
        assert!(md.contains("not a directory"));
        let bad = ReportSpec {
            seeds: vec![],
            ..spec
        };
        let never = dir.path().join("never");
        assert!(write_report(&m, &bad, &never, &mut |_| {}).is_err());
        assert!(!never.exists());
    }
}
