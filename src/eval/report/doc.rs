//! The report's small document model: headings, paragraphs, code, lists, tables and figures,
//! printed as HTML ([`Doc::to_html`]) or Markdown ([`Doc::to_markdown`]) from one content.

use std::fmt::Write as _;

/// A document that prints as HTML or Markdown.
#[derive(Debug, Default)]
pub(super) struct Doc {
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
    pub(super) fn h(&mut self, level: usize, s: &str) {
        self.blocks.push(Block::Heading(level, s.into()));
    }
    pub(super) fn p(&mut self, s: &str) {
        self.blocks.push(Block::Para(s.into()));
    }
    pub(super) fn code(&mut self, s: &str) {
        self.blocks.push(Block::Code(s.into()));
    }
    pub(super) fn list(&mut self, items: &[String]) {
        self.blocks.push(Block::List(items.to_vec()));
    }
    pub(super) fn table(&mut self, head: Vec<String>, rows: Vec<Vec<String>>) {
        self.blocks.push(Block::Table(head, rows));
    }
    pub(super) fn svg(&mut self, file: &str, alt: &str) {
        self.blocks.push(Block::Svg(file.into(), alt.into()));
    }
    pub(super) fn images(&mut self, v: Vec<(String, String)>) {
        self.blocks.push(Block::Images(v));
    }

    pub(super) fn to_markdown(&self) -> String {
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
    pub(super) fn to_html(&self) -> String {
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

    #[test]
    fn inline_marks_become_html() {
        assert_eq!(
            inline("a `x<y` **b** & c"),
            "a <code>x&lt;y</code> <strong>b</strong> &amp; c"
        );
    }
}
