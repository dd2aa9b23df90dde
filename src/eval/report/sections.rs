//! The report's content: [`document`] builds every section (Table I, renderings, the real pairs,
//! the frequency response) into a [`Doc`], with the paragraphs that read the numbers.

use std::fmt::Write as _;

use super::doc::Doc;
use super::{Report, ReportSpec};
use crate::eval::methods::{BILATERAL, DEFAULT, FAITHFUL, label};
use crate::eval::pairs::PairsOutcome;
use crate::eval::spectrum::FrequencyResponse;
use crate::eval::table::{NOISY, Summary, Table, TableRow};
use crate::eval::{Mesh, Metrics};

fn pct(level: f64) -> String {
    format!("{:.0} %", level * 100.0)
}

fn num(v: Option<f64>, d: usize) -> String {
    v.map_or_else(|| "–".to_string(), |v| format!("{v:.d$}"))
}

/// Builds the report's content once, for both HTML and Markdown.
pub(super) fn document(clean: &Mesh, spec: &ReportSpec, r: &Report) -> Doc {
    let t = &r.table;
    let mut d = Doc::default();
    d.h(1, &format!("qemd quality report: {}", spec.title));
    if let Some(c) = &spec.command {
        d.p("Regenerate this report with:");
        d.code(c);
    }
    d.p(&format!(
        "qemd {}. Clean mesh `{}`: {} vertices, {} faces, L (mean edge length) = {:.6e}. \
         Errors are in % of L, angles in degrees; protocol and metrics as in `docs/EVALUATION.md`.",
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
