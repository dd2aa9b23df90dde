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

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::metrics::Metrics;
use super::noise::{NoiseSpec, add_noise_with_length};
use super::pairs::{Pair, PairsOutcome, benchmark_pairs, run_pairs};
use super::plot::{LineChart, Series, colours};
use super::render::{RenderOptions, render};
use super::spectrum::{FrequencyResponse, SpectrumSpec, frequency_response, write_file};
use super::table::{
    NOISY, Summary, Table, TableMethod, TableRow, TableSpec, run_table_with_progress,
};
use super::{EvalError, Mesh, scale_length};
use crate::denoise::{Method, Params, denoise};

/// Name of the faithful row (the paper's operator).
pub const FAITHFUL: &str = "faithful";
/// Name of the bilateral row.
pub const BILATERAL: &str = "bilateral";
/// Name of qemd's default row.
pub const DEFAULT: &str = "default";

/// The three denoisers of the report, in row order: `faithful` (the paper's Algorithm 1 with
/// area-weighted normals: the paper's Table I QEM column), `bilateral` (Fleishman et al. 2003,
/// 3 passes) and `default` (qemd's default operator).
pub fn report_methods() -> Vec<TableMethod> {
    vec![
        TableMethod::new(FAITHFUL, Params::paper()),
        TableMethod::new(
            BILATERAL,
            Params {
                method: Method::Bilateral,
                iterations: 3,
                ..Params::default()
            },
        ),
        TableMethod::new(DEFAULT, Params::default()),
    ]
}

/// The colour of a method in every chart of the report.
pub fn method_colour(name: &str) -> [u8; 3] {
    match name {
        NOISY => colours::NOISY,
        FAITHFUL => colours::FAITHFUL,
        BILATERAL => colours::BILATERAL,
        DEFAULT => colours::DEFAULT,
        _ => colours::OTHER,
    }
}

/// A readable label for a row name.
pub fn label(name: &str) -> &str {
    match name {
        NOISY => "noisy input",
        FAITHFUL => "faithful",
        BILATERAL => "bilateral",
        DEFAULT => "qemd default",
        other => other,
    }
}

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

fn pct(level: f64) -> String {
    format!("{:.0} %", level * 100.0)
}

fn num(v: Option<f64>, d: usize) -> String {
    v.map_or_else(|| "–".to_string(), |v| format!("{v:.d$}"))
}

/// Builds the report's content once, for both HTML and Markdown.
fn document(clean: &Mesh, spec: &ReportSpec, r: &Report) -> Doc {
    let t = &r.table;
    let mut d = Doc::default();
    d.h(1, &format!("qemd quality report: {}", spec.title));
    if let Some(c) = &spec.command {
        d.p("Regenerate this report with:");
        d.code(c);
    }
    d.p(&format!(
        "qemd {}. Clean mesh `{}`: {} vertices, {} faces, L (mean edge length) = {:.6e}. \
         Errors are in % of L, angles in degrees; protocol and metrics as in `EVALUATION.md`.",
        env!("CARGO_PKG_VERSION"),
        spec.title,
        clean.positions.len(),
        clean.faces.len(),
        t.l
    ));
    d.list(&[
        format!("**{}**: the noisy mesh as it is.", label(NOISY)),
        format!(
            "**{}**: the paper's Algorithm 1 exactly — one pass, tangent planes over 2-rings, \
             area-weighted vertex normals, w = −A⁻¹b (`Params::paper()`; the paper's Table I QEM column).",
            label(FAITHFUL)
        ),
        format!(
            "**{}**: Fleishman et al. 2003, 3 passes, the paper's comparator.",
            label(BILATERAL)
        ),
        format!(
            "**{}**: qemd's default operator (`Params::default()`): bilateral-filtered face \
             normals, repeated damped QEM updates on face planes, adaptive schedule, volume kept.",
            label(DEFAULT)
        ),
    ]);

    d.h(2, "Table I protocol");
    let seeds: Vec<String> = t.seeds.iter().map(u64::to_string).collect();
    d.p(&format!(
        "`{}` noise, σ = level · L, every metric averaged over seed{} {}. Headline: the residual \
         noise `surf_std` (standard deviation of the signed distance to the clean surface).",
        t.model,
        if t.seeds.len() == 1 { "" } else { "s" },
        seeds.join(", ")
    ));
    let mut head = vec!["method".to_string()];
    head.extend(t.levels.iter().map(|&l| pct(l)));
    let rows = t
        .rows
        .iter()
        .map(|row| {
            let mut v = vec![label(&row.method).to_string()];
            v.extend(row.cells.iter().map(|c| num(c.mean.surf_std, 2)));
            v
        })
        .collect();
    d.table(head, rows);
    d.p(&table_reading(t));
    if t.rows
        .iter()
        .flat_map(|r| &r.cells)
        .all(|c| c.mean.dvol_pct.is_none())
    {
        d.p(
            "`dvol_pct` shows – because the clean mesh is not closed: a volume change is only \
             defined for closed meshes.",
        );
    }
    for (li, &level) in t.levels.iter().enumerate() {
        d.h(3, &format!("All metrics at {} noise", pct(level)));
        let head = [
            "method", "surf_std", "surf_rms", "std_xyz", "ang_deg", "dvol_pct",
        ]
        .map(String::from)
        .to_vec();
        let rows = t
            .rows
            .iter()
            .filter_map(|row| {
                let m = &row.cells.get(li)?.mean;
                Some(vec![
                    label(&row.method).to_string(),
                    num(m.surf_std, 2),
                    num(m.surf_rms, 2),
                    num(m.std_xyz, 2),
                    num(m.ang_deg, 2),
                    num(m.dvol_pct, 3),
                ])
            })
            .collect();
        d.table(head, rows);
    }
    d.h(3, "Error against noise level");
    d.svg("surf_std.svg", "surf_std against noise level");
    d.svg("ang_deg.svg", "ang_deg against noise level");

    d.h(
        2,
        &format!("Before and after at {} noise", pct(spec.render_level)),
    );
    d.p(&format!(
        "Seed {}, view `{}`, flat shading (every facet visible), software renderer.",
        spec.seeds.first().copied().unwrap_or(0),
        spec.render.view
    ));
    d.images(
        r.renderings
            .iter()
            .map(|x| {
                let caption = match &x.metrics {
                    None => "clean".to_string(),
                    Some(m) => format!(
                        "{}: surf_std {}, ang_deg {}",
                        label(&x.name),
                        num(m.surf_std, 1),
                        num(m.ang_deg, 1)
                    ),
                };
                (x.file.clone(), caption)
            })
            .collect(),
    );

    d.h(2, "Real benchmark pairs");
    match &r.pairs {
        None => d.p("Not run (no pairs directory given)."),
        Some(p) => pairs_section(&mut d, p),
    }

    d.h(2, "Frequency response");
    match &r.spectrum {
        None => d.p("Not run."),
        Some(s) => spectrum_section(&mut d, s),
    }
    d
}

fn pairs_section(d: &mut Doc, p: &PairsOutcome) {
    d.p(&format!(
        "Published clean/noisy pairs with the same connectivity (`{}`). Each cell: `ang_deg` \
         (mean face-normal angle, degrees) / surface error `surf_std` (% of the clean mesh's L). \
         The last column holds the numbers the GCN-Denoiser paper (Shen et al. 2022, a learned \
         method) publishes for its two pairs, for scale: its angle is the same measure as \
         `ang_deg`, but its surface figure is that paper's own vertex-distance measure and scale, \
         not % of L, so only the angles compare directly.",
        p.dir.display()
    ));
    if !p.results.is_empty() {
        let methods: Vec<String> = p.results[0].rows.iter().map(|r| r.method.clone()).collect();
        let mut head = vec!["pair".to_string(), "vertices".to_string()];
        head.extend(methods.iter().map(|m| label(m).to_string()));
        head.push("GCN-Denoiser (published)".into());
        let rows = p
            .results
            .iter()
            .map(|res| {
                let mut v = vec![res.pair.name.clone(), res.vertices.to_string()];
                v.extend(res.rows.iter().map(|row| {
                    format!(
                        "{} / {}",
                        num(row.metrics.ang_deg, 2),
                        num(row.metrics.surf_std, 1)
                    )
                }));
                v.push(res.pair.published.as_ref().map_or("–".into(), |g| {
                    format!("{:.2} / {:.1}", g.ang_deg, g.surf_std)
                }));
                v
            })
            .collect();
        d.table(head, rows);
        d.p(&pairs_reading(p));
    }
    for s in &p.skipped {
        d.p(&format!("Note: {s}."));
    }
}

fn spectrum_section(d: &mut Doc, s: &FrequencyResponse) {
    d.p(
        "The paper's §IV-B experiment: a planar patch with a height field, noise along the normal, \
         each method applied once; the noisy and denoised patches are resampled as height fields \
         on a regular grid and compared in the 2D Fourier domain, radially averaged. Plotted is the \
         gain |F_denoised| / |F_noisy| per frequency ring (log scale; 1 = unchanged), next to the \
         clean surface's |F_clean| / |F_noisy| (dashed), the gain an ideal denoiser would have. \
         The paper's Fig. 12 plots the difference of magnitudes |F_noisy| − |F_denoised| instead; \
         it is in `spectrum.csv` as `*_diff`.",
    );
    d.svg("spectrum.svg", "frequency response");
    d.p(
        "The gain alone cannot tell restored shape from new artefacts: both add energy. The second \
         chart measures the error of each result against the clean patch, frequency by frequency, \
         as a fraction of the noisy input's error (1 = no better than the input).",
    );
    d.svg("spectrum_error.svg", "error left per frequency");
    d.p(&s.intro());
    let (head, rows) = s.band_table();
    d.table(head, rows);
    d.list(&s.methods.iter().map(|m| s.describe(m)).collect::<Vec<_>>());
    d.p(&s.reading());
    let mut imgs = vec![
        ("patch_clean.png".to_string(), "clean patch".to_string()),
        ("patch_noisy.png".to_string(), "noisy patch".to_string()),
    ];
    for m in &s.methods {
        imgs.push((format!("patch_{}.png", m.name), label(&m.name).to_string()));
    }
    d.images(imgs);
    d.p("Curves: `spectrum.csv`; summary: `spectrum.md`.");
}

/// The mean of one metric of a row at level index `li`.
fn mean_of(row: &TableRow, li: usize, f: fn(&Summary) -> Option<f64>) -> Option<f64> {
    f(&row.cells.get(li)?.mean)
}

/// What the Table I numbers show, in words: per level the best method for `surf_std` and
/// `ang_deg`, then the rows that do worse than the noisy input on `std_xyz` (tangential drift)
/// or `ang_deg`.
fn table_reading(t: &Table) -> String {
    let Some(noisy) = t.row(NOISY) else {
        return String::new();
    };
    let methods: Vec<&TableRow> = t.rows.iter().filter(|r| r.method != NOISY).collect();
    let best = |li: usize, f: fn(&Summary) -> Option<f64>| {
        methods
            .iter()
            .filter_map(|r| Some((label(&r.method), mean_of(r, li, f)?)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
    };
    let mut parts = Vec::new();
    for (li, &level) in t.levels.iter().enumerate() {
        let mut p = format!("At {} noise", pct(level));
        if let Some((name, v)) = best(li, |m| m.surf_std) {
            let _ = write!(p, " the lowest `surf_std` is {name}'s ({v:.2} % of L");
            if let Some(n) = mean_of(noisy, li, |m| m.surf_std) {
                let _ = write!(p, ", {:.0} % of the input's", 100.0 * v / n);
            }
            p.push(')');
        }
        if let Some((name, v)) = best(li, |m| m.ang_deg) {
            let _ = write!(p, " and the lowest `ang_deg` {name}'s ({v:.2}°)");
        }
        parts.push(format!("{p}."));
    }
    for (f, what) in [
        (
            (|m: &Summary| m.std_xyz) as fn(&Summary) -> Option<f64>,
            "`std_xyz` above the noisy input's (vertices slide along the surface: tangential \
             drift, which `surf_std` does not see)",
        ),
        (
            |m: &Summary| m.ang_deg,
            "`ang_deg` above the noisy input's (face normals made worse)",
        ),
    ] {
        let who: Vec<String> = methods
            .iter()
            .filter_map(|r| {
                let levels: Vec<String> = t
                    .levels
                    .iter()
                    .enumerate()
                    .filter(|&(li, _)| {
                        matches!(
                            (mean_of(r, li, f), mean_of(noisy, li, f)),
                            (Some(a), Some(b)) if a > b
                        )
                    })
                    .map(|(_, &l)| pct(l))
                    .collect();
                (!levels.is_empty())
                    .then(|| format!("{} at {}", label(&r.method), levels.join(", ")))
            })
            .collect();
        if !who.is_empty() {
            parts.push(format!("With {what}: {}.", who.join("; ")));
        }
    }
    parts.join(" ")
}

/// What the pair results show, in words: how often each method is best, where one does worse
/// than its input, and our best angle next to the published one.
fn pairs_reading(p: &PairsOutcome) -> String {
    let Some(first) = p.results.first() else {
        return String::new();
    };
    // Every result has the noisy row first, then the methods in the same order.
    let names: Vec<&str> = first.rows[1..].iter().map(|r| r.method.as_str()).collect();
    let (mut ang_best, mut surf_best, mut ang_worse) = (
        vec![0; names.len()],
        vec![0; names.len()],
        vec![0; names.len()],
    );
    let mut published = Vec::new();
    for res in &p.results {
        let Some((noisy, rows)) = res.rows.split_first() else {
            continue;
        };
        let best = |f: fn(&Metrics) -> Option<f64>| {
            rows.iter()
                .enumerate()
                .filter_map(|(k, r)| Some((k, f(&r.metrics)?)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
        };
        if let Some((k, _)) = best(|m| m.surf_std) {
            surf_best[k] += 1;
        }
        let ang = best(|m| m.ang_deg);
        if let Some((k, v)) = ang {
            ang_best[k] += 1;
            if let Some(g) = &res.pair.published {
                published.push(format!(
                    "On {} our best angle is {}'s {v:.2}° against GCN-Denoiser's {:.2}° (input: \
                     {}°).",
                    res.pair.name,
                    label(&rows[k].method),
                    g.ang_deg,
                    num(noisy.metrics.ang_deg, 2)
                ));
            }
        }
        for (k, r) in rows.iter().enumerate() {
            if let (Some(x), Some(y)) = (r.metrics.ang_deg, noisy.metrics.ang_deg) {
                ang_worse[k] += usize::from(x > y);
            }
        }
    }
    let total = p.results.len();
    let tally = |counts: &[usize]| -> Option<String> {
        let v: Vec<String> = names
            .iter()
            .zip(counts)
            .filter(|&(_, &c)| c > 0)
            .map(|(n, c)| format!("{} on {c}", label(n)))
            .collect();
        (!v.is_empty()).then(|| format!("{} of the {total} pairs", v.join(", ")))
    };
    let mut claims = Vec::new();
    if let Some(t) = tally(&ang_best) {
        claims.push(format!("Lowest `ang_deg`: {t}"));
    }
    if let Some(t) = tally(&surf_best) {
        claims.push(format!("lowest surface error: {t}"));
    }
    if let Some(t) = tally(&ang_worse) {
        claims.push(format!("face normals worse than the noisy input's: {t}"));
    }
    let mut out = if claims.is_empty() {
        String::new()
    } else {
        format!("{}.", claims.join("; "))
    };
    for p in published {
        out.push(' ');
        out.push_str(&p);
    }
    out.trim_start().to_string()
}

/// A document that prints as HTML or Markdown.
#[derive(Debug, Default)]
struct Doc {
    blocks: Vec<Block>,
}

#[derive(Debug)]
enum Block {
    Heading(usize, String),
    Para(String),
    Code(String),
    List(Vec<String>),
    Table(Vec<String>, Vec<Vec<String>>),
    /// An SVG file of the report folder.
    Svg(String, String),
    /// PNG files of the report folder with captions.
    Images(Vec<(String, String)>),
}

impl Doc {
    fn h(&mut self, level: usize, s: &str) {
        self.blocks.push(Block::Heading(level, s.into()));
    }
    fn p(&mut self, s: &str) {
        self.blocks.push(Block::Para(s.into()));
    }
    fn code(&mut self, s: &str) {
        self.blocks.push(Block::Code(s.into()));
    }
    fn list(&mut self, items: &[String]) {
        self.blocks.push(Block::List(items.to_vec()));
    }
    fn table(&mut self, head: Vec<String>, rows: Vec<Vec<String>>) {
        self.blocks.push(Block::Table(head, rows));
    }
    fn svg(&mut self, file: &str, alt: &str) {
        self.blocks.push(Block::Svg(file.into(), alt.into()));
    }
    fn images(&mut self, v: Vec<(String, String)>) {
        self.blocks.push(Block::Images(v));
    }

    fn to_markdown(&self) -> String {
        let mut s = String::new();
        let cell = |c: &str| c.replace('|', "\\|");
        for b in &self.blocks {
            match b {
                Block::Heading(l, t) => {
                    let _ = writeln!(s, "{} {t}\n", "#".repeat(*l));
                }
                Block::Para(t) => {
                    let _ = writeln!(s, "{t}\n");
                }
                Block::Code(t) => {
                    let _ = writeln!(s, "```sh\n{t}\n```\n");
                }
                Block::List(items) => {
                    for i in items {
                        let _ = writeln!(s, "* {i}");
                    }
                    s.push('\n');
                }
                Block::Table(head, rows) => {
                    let h: Vec<String> = head.iter().map(|c| cell(c)).collect();
                    let _ = writeln!(s, "| {} |", h.join(" | "));
                    let _ = write!(s, "|---|");
                    for _ in 1..head.len() {
                        let _ = write!(s, "---:|");
                    }
                    s.push('\n');
                    for r in rows {
                        let r: Vec<String> = r.iter().map(|c| cell(c)).collect();
                        let _ = writeln!(s, "| {} |", r.join(" | "));
                    }
                    s.push('\n');
                }
                Block::Svg(file, alt) => {
                    let _ = writeln!(s, "![{alt}]({file})\n");
                }
                Block::Images(v) => {
                    let h: Vec<String> = v.iter().map(|(_, c)| cell(c)).collect();
                    let _ = writeln!(s, "| {} |", h.join(" | "));
                    let _ = writeln!(s, "|{}", ":---:|".repeat(v.len()));
                    let i: Vec<String> = v
                        .iter()
                        .map(|(f, c)| format!("![{}]({f})", cell(c)))
                        .collect();
                    let _ = writeln!(s, "| {} |\n", i.join(" | "));
                }
            }
        }
        s
    }

    /// The HTML page; it shows the figures of its folder by relative links.
    fn to_html(&self) -> String {
        let mut s =
            String::from("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n");
        let title = self
            .blocks
            .iter()
            .find_map(|b| match b {
                Block::Heading(1, t) => Some(t.as_str()),
                _ => None,
            })
            .unwrap_or("qemd report");
        let _ = writeln!(s, "<title>{}</title>", escape(title));
        s.push_str(STYLE);
        s.push_str("</head>\n<body>\n");
        for b in &self.blocks {
            match b {
                Block::Heading(l, t) => {
                    let _ = writeln!(s, "<h{l}>{}</h{l}>", inline(t));
                }
                Block::Para(t) => {
                    let _ = writeln!(s, "<p>{}</p>", inline(t));
                }
                Block::Code(t) => {
                    let _ = writeln!(s, "<pre><code>{}</code></pre>", escape(t));
                }
                Block::List(items) => {
                    s.push_str("<ul>\n");
                    for i in items {
                        let _ = writeln!(s, "<li>{}</li>", inline(i));
                    }
                    s.push_str("</ul>\n");
                }
                Block::Table(head, rows) => {
                    s.push_str("<table>\n<thead><tr>");
                    for h in head {
                        let _ = write!(s, "<th>{}</th>", inline(h));
                    }
                    s.push_str("</tr></thead>\n<tbody>\n");
                    for r in rows {
                        s.push_str("<tr>");
                        for c in r {
                            let _ = write!(s, "<td>{}</td>", inline(c));
                        }
                        s.push_str("</tr>\n");
                    }
                    s.push_str("</tbody>\n</table>\n");
                }
                Block::Svg(file, alt) => {
                    let _ = writeln!(
                        s,
                        "<figure class=\"chart\"><img src=\"{}\" alt=\"{}\"></figure>",
                        escape(file),
                        escape(alt)
                    );
                }
                Block::Images(v) => {
                    s.push_str("<div class=\"images\">\n");
                    for (file, caption) in v {
                        let _ = writeln!(
                            s,
                            "<figure><img src=\"{}\" alt=\"{c}\"><figcaption>{c}</figcaption></figure>",
                            escape(file),
                            c = escape(caption)
                        );
                    }
                    s.push_str("</div>\n");
                }
            }
        }
        s.push_str("</body>\n</html>\n");
        s
    }
}

const STYLE: &str = "<style>
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; padding: 0 1em; color: #222; }
table { border-collapse: collapse; margin: 1em 0; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
thead { background: #f2f2f2; }
pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; }
code { font-size: 0.95em; }
.images { display: flex; flex-wrap: wrap; gap: 0.8em; }
.images figure { margin: 0; width: 210px; }
.images img { width: 210px; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; }
figure.chart { margin: 1em 0; }
figure.chart img { max-width: 100%; height: auto; }
</style>
";

/// Escapes text for HTML.
fn escape(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            c => o.push(c),
        }
    }
    o
}

/// Escapes text and turns the Markdown inline marks it uses (`code`, **bold**) into HTML.
fn inline(s: &str) -> String {
    let mut o = String::new();
    for (k, part) in escape(s).split('`').enumerate() {
        if k % 2 == 1 {
            let _ = write!(o, "<code>{part}</code>");
        } else {
            for (b, q) in part.split("**").enumerate() {
                if b % 2 == 1 {
                    let _ = write!(o, "<strong>{q}</strong>");
                } else {
                    o.push_str(q);
                }
            }
        }
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::synth::Shape;

    #[test]
    fn inline_marks_become_html() {
        assert_eq!(
            inline("a `x<y` **b** & c"),
            "a <code>x&lt;y</code> <strong>b</strong> &amp; c"
        );
    }

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
