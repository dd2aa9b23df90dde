//! The quality report: one folder with a self-contained `index.html` and a `README.md` (plus the
//! figures they show) that puts qemd's default operator next to the paper's operator, the
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
//! The HTML embeds everything (SVG inline, PNG as data URIs), so the file can travel alone; the
//! Markdown links the same figures as files. The output depends only on the inputs and the
//! spec: no dates or timings, so a regenerated report differs only where results do.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::metrics::Metrics;
use super::noise::{NoiseSpec, add_noise_with_length};
use super::pairs::{Pair, PairsOutcome, benchmark_pairs, run_pairs};
use super::plot::{LineChart, Series};
use super::render::{RenderOptions, render};
use super::spectrum::{
    FrequencyResponse, SpectrumSpec, frequency_response, method_colour, write_file,
};
use super::table::{NOISY, Table, TableMethod, TableSpec, run_table_with_progress};
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

/// A readable label for a row name.
pub fn label(name: &str) -> &str {
    match name {
        NOISY => "noisy input",
        FAITHFUL => "faithful (paper, Algorithm 1)",
        BILATERAL => "bilateral (Fleishman 2003)",
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
    let json = serde_json::to_string_pretty(&table).map_err(|e| EvalError::Plot(e.to_string()))?;
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
        ("index.html", doc.to_html(out)?),
        ("README.md", doc.to_markdown()),
    ] {
        let p = out.join(name);
        write_file(&p, body.as_bytes())?;
        report.files.push(p);
    }
    if let Some(p) = &report.pairs {
        let p = serde_json::to_string_pretty(p).map_err(|e| EvalError::Plot(e.to_string()))?;
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
fn level_chart(table: &Table, metric: &str, f: fn(&Metrics) -> Option<f64>) -> LineChart {
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
            .filter_map(|c| {
                // The mean of the runs' metric, when every run has it.
                let v: Option<Vec<f64>> = c.runs.iter().map(f).collect();
                let v = v.filter(|v| !v.is_empty())?;
                Some((c.level * 100.0, v.iter().sum::<f64>() / v.len() as f64))
            })
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
         The last column holds the numbers the GCN-Denoiser paper publishes for its two pairs \
         (a learned method, for scale).",
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

    /// The HTML page; figures are read from `dir` and embedded.
    fn to_html(&self, dir: &Path) -> Result<String, EvalError> {
        let read = |f: &str| -> Result<Vec<u8>, EvalError> {
            let p = dir.join(f);
            std::fs::read(&p).map_err(|e| EvalError::Io(crate::io::IoError::io(&p, e)))
        };
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
                    let svg = String::from_utf8_lossy(&read(file)?).into_owned();
                    let _ = writeln!(
                        s,
                        "<figure class=\"chart\" title=\"{}\">\n{}\n</figure>",
                        escape(alt),
                        svg.trim()
                    );
                }
                Block::Images(v) => {
                    s.push_str("<div class=\"images\">\n");
                    for (file, caption) in v {
                        let data = base64(&read(file)?);
                        let _ = writeln!(
                            s,
                            "<figure><img src=\"data:image/png;base64,{data}\" alt=\"{c}\"><figcaption>{c}</figcaption></figure>",
                            c = escape(caption)
                        );
                    }
                    s.push_str("</div>\n");
                }
            }
        }
        s.push_str("</body>\n</html>\n");
        Ok(s)
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
figure.chart svg { max-width: 100%; height: auto; }
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

/// Standard base64 with padding.
fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut o = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let b = [c[0], *c.get(1).unwrap_or(&0), *c.get(2).unwrap_or(&0)];
        let n = u32::from(b[0]) << 16 | u32::from(b[1]) << 8 | u32::from(b[2]);
        for k in 0..4 {
            if k <= c.len() {
                o.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                o.push('=');
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
    fn base64_matches_the_standard_vectors() {
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    #[test]
    fn inline_marks_become_html() {
        assert_eq!(
            inline("a `x<y` **b** & c"),
            "a <code>x&lt;y</code> <strong>b</strong> &amp; c"
        );
    }

    #[test]
    fn small_report_has_every_section() {
        let m = Shape::Sphere.mesh(2).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let spec = ReportSpec {
            title: "sphere".into(),
            command: Some("qemd report sphere.ply".into()),
            levels: vec![0.2, 0.4],
            render: RenderOptions {
                width: 120,
                height: 120,
                ..RenderOptions::default()
            },
            pairs_dir: Some(dir.path().join("no-pairs-here")),
            spectrum: Some(SpectrumSpec {
                cells: 16,
                ..SpectrumSpec::default()
            }),
            ..ReportSpec::default()
        };
        let mut lines = 0;
        let r = write_report(&m, &spec, dir.path(), &mut |_| lines += 1).unwrap();
        assert!(lines > 3);
        assert_eq!(r.table.rows.len(), 4);
        assert_eq!(r.renderings.len(), 5);
        for f in &r.files {
            assert!(f.is_file(), "{}", f.display());
        }
        let html = std::fs::read_to_string(dir.path().join("index.html")).unwrap();
        for needle in [
            "noisy input",
            "faithful (paper, Algorithm 1)",
            "bilateral (Fleishman 2003)",
            "qemd default",
            "<svg",
            "data:image/png;base64,",
            "not a directory",
            "Frequency response",
            "qemd report sphere.ply",
        ] {
            assert!(html.contains(needle), "{needle}");
        }
        let md = std::fs::read_to_string(dir.path().join("README.md")).unwrap();
        assert!(md.contains("![surf_std against noise level](surf_std.svg)"));
        assert!(md.contains("| qemd default |"));
        let bad = ReportSpec {
            seeds: vec![],
            ..spec
        };
        assert!(write_report(&m, &bad, dir.path(), &mut |_| {}).is_err());
    }
}
