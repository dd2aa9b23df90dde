//! [`Info`] as the text `qemd info` prints: one `name  value` line per fact, as `lasinfo` does.

use std::fmt;

use super::Info;
use crate::io::printable;

/// Shortest text that reads back as `v` (coordinates keep every digit they have).
fn num(v: f64) -> String {
    format!("{v}")
}

/// `v` rounded to `digits` significant digits, as the shortest text of that value (an extent
/// computed by subtraction, `199.97999999998137`, shows as `199.98`).
fn sig(v: f64, digits: usize) -> String {
    let rounded: f64 = format!("{:.*e}", digits.saturating_sub(1), v)
        .parse()
        .unwrap_or(v);
    format!("{rounded}")
}

impl fmt::Display for Info {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Names, comments and descriptions come from the file: control characters escaped.
        let row = |f: &mut fmt::Formatter<'_>, name: &str, value: &str| {
            writeln!(f, "  {name:<12} {}", printable(value))
        };
        writeln!(f, "{}", printable(&self.path.to_string_lossy()))?;
        row(f, "format", &format!("{} ({})", self.kind, self.format))?;
        let declared = match self.declared_points {
            Some(d) if d != self.points => format!(" (the header declares {d})"),
            _ => String::new(),
        };
        row(f, "points", &format!("{}{declared}", self.points))?;
        if let Some(n) = self.faces {
            row(f, "faces", &n.to_string())?;
        }
        if self.non_finite > 0 {
            row(f, "non-finite", &format!("{} points", self.non_finite))?;
        }
        match &self.bounds {
            Some(b) => {
                for (k, axis) in ["x", "y", "z"].iter().enumerate() {
                    let name = if k == 0 { "bounds" } else { "" };
                    row(
                        f,
                        name,
                        &format!(
                            "{axis} {} … {}  ({})",
                            self.coordinate(b.min[k]),
                            self.coordinate(b.max[k]),
                            self.extent(b.max[k] - b.min[k])
                        ),
                    )?;
                }
            }
            None => row(f, "bounds", "none (no finite point)")?,
        }
        if let (Some(s), Some(o)) = (self.scale, self.offset) {
            row(f, "scale", &s.map(num).join(" "))?;
            row(f, "offset", &o.map(num).join(" "))?;
        }
        row(
            f,
            "crs",
            &self
                .crs
                .as_ref()
                .map_or_else(|| "none declared".to_string(), |c| c.summary()),
        )?;
        let spacing = match &self.spacing {
            Some(s) => match s.sampled {
                Some(m) => format!(
                    "{} (median nearest-neighbour distance, from {m} sampled points)",
                    sig(s.median, 4)
                ),
                None => format!("{} (median nearest-neighbour distance)", sig(s.median, 4)),
            },
            None => "none (fewer than two distinct points)".to_string(),
        };
        row(f, "spacing", &spacing)?;
        if let Some(c) = &self.classes {
            let list: Vec<String> = c
                .counts
                .iter()
                .map(|(code, n)| match c.names.get(code) {
                    Some(name) => format!("{code} {name}: {n}"),
                    None => format!("{code}: {n}"),
                })
                .collect();
            row(f, "classes", &format!("{} ({})", list.join(", "), c.field))?;
        }
        let fields: Vec<String> = self
            .fields
            .iter()
            .map(|x| format!("{} {}", x.name, x.ty))
            .collect();
        row(
            f,
            "fields",
            &format!("{} ({} bytes)", fields.join(", "), self.record_length),
        )?;
        if !self.extra_fields.is_empty() {
            row(f, "extra", &self.extra_fields.join(", "))?;
        }
        self.format_header(f, row)
    }
}

impl Info {
    /// A stored coordinate as its storage has it: with the LAS scale's decimals, as the `f32`
    /// it is, or as the shortest text of the `f64`.
    fn coordinate(&self, v: f64) -> String {
        match self.decimals {
            Some(d) => format!("{v:.d$}"),
            None if self.float32 => format!("{}", v as f32),
            None => num(v),
        }
    }

    /// The difference of two stored coordinates, without the digits the subtraction invents.
    fn extent(&self, v: f64) -> String {
        match self.decimals {
            Some(d) => format!("{v:.d$}"),
            None if self.float32 => sig(v, 7),
            None => sig(v, 12),
        }
    }

    /// The format's own header lines (LAS software and VLRs, PLY elements and comments, PCD
    /// viewpoint, E57 scans).
    fn format_header(
        &self,
        f: &mut fmt::Formatter<'_>,
        row: impl Fn(&mut fmt::Formatter<'_>, &str, &str) -> fmt::Result,
    ) -> fmt::Result {
        let h = &self.header;
        let text = |v: &serde_json::Value| v.as_str().unwrap_or_default().to_string();
        if let Some(vlrs) = h["vlrs"].as_array() {
            for (name, key) in [
                ("software", "generating_software"),
                ("system", "system_identifier"),
            ] {
                if !text(&h[key]).is_empty() {
                    row(f, name, &text(&h[key]))?;
                }
            }
            if h["creation_year"].as_u64().unwrap_or(0) > 0 {
                row(
                    f,
                    "created",
                    &format!("day {} of {}", h["creation_day"], h["creation_year"]),
                )?;
            }
            for (i, v) in vlrs.iter().enumerate() {
                let kind = if v["extended"].as_bool() == Some(true) {
                    "evlr"
                } else {
                    "vlr"
                };
                row(
                    f,
                    if i == 0 { "records" } else { "" },
                    &format!(
                        "{kind} {} {} \"{}\" ({} bytes)",
                        text(&v["user_id"]),
                        v["record_id"],
                        text(&v["description"]),
                        v["length"]
                    ),
                )?;
            }
        }
        if let Some(elements) = h["elements"].as_array() {
            let list: Vec<String> = elements
                .iter()
                .map(|e| format!("{} {}", text(&e["name"]), e["count"]))
                .collect();
            row(f, "elements", &list.join(", "))?;
            for c in h["comments"].as_array().into_iter().flatten() {
                row(f, "comment", &text(c))?;
            }
        }
        if let Some(vp) = h["viewpoint"].as_array() {
            let v: Vec<String> = vp.iter().map(|x| x.to_string()).collect();
            row(f, "viewpoint", &v.join(" "))?;
        }
        if let Some(scans) = h["scans"].as_array() {
            for (i, s) in scans.iter().enumerate() {
                let name = s["name"].as_str().unwrap_or("(unnamed)");
                let pose = if s["posed"].as_bool() == Some(true) {
                    ", posed"
                } else {
                    ""
                };
                row(
                    f,
                    if i == 0 { "scans" } else { "" },
                    &format!("{name}: {} points{pose}", s["points"]),
                )?;
            }
        }
        Ok(())
    }
}
