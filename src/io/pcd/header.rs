//! The PCD header: its field model, parsing the lines up to `DATA`, and writing them back.
//!
//! The raw lines are kept (terminators included) so that a sink reproduces them byte for byte;
//! only the lines whose value changes are rebuilt (`WIDTH`/`HEIGHT`/`POINTS` when the point count
//! changes, `FIELDS`/`SIZE`/`TYPE`/`COUNT` when a `noise` field is appended, `DATA` when the kind
//! changes). A rebuilt line keeps its keyword's spelling and its terminator.
//!
//! Accepted grammar (PCL's, slightly more lenient):
//!
//! ```text
//!  # comment                  full-line comments and blank lines anywhere before DATA
//!  VERSION 0.7                optional
//!  FIELDS x y z rgb           required (`COLUMNS` is PCL's old alias)
//!  SIZE 4 4 4 4               required: 1, 2, 4 or 8 bytes
//!  TYPE F F F U               required: I (signed), U (unsigned), F (float: SIZE 4 or 8)
//!  COUNT 1 1 1 1              optional, 1 each by default
//!  WIDTH 640                  WIDTH or POINTS required; WIDTH defaults to POINTS,
//!  HEIGHT 480                 HEIGHT to 1, POINTS to WIDTH × HEIGHT; WIDTH × HEIGHT = POINTS
//!  VIEWPOINT 0 0 0 1 0 0 0    optional (tx ty tz qw qx qy qz)
//!  POINTS 307200
//!  DATA binary_compressed     last header line: ascii | binary | binary_compressed
//! ```
//!
//! Keywords are matched case-insensitively. The first line that is neither blank nor a comment
//! must be a known keyword (otherwise the file is "not a PCD file"); so must every later line that
//! is not a comment: an unknown word (`POINTS0300`, stray text) is a header error naming the line
//! (issue 15; PCL skips such lines, and qemd used to copy them to the output).

use std::io::{BufRead, Read};
use std::path::Path;

use crate::io::IoError;
use crate::io::lines::{LineEnding, show, split_eol, tokens};
use crate::points::ScalarType;

/// Longest header line accepted (a safeguard against reading a large binary file as one line).
const MAX_LINE: u64 = 1 << 20;
/// Most schema fields (COUNT expanded) a record may have.
pub(super) const MAX_FIELDS: usize = 1 << 16;

/// The `DATA` kind of a PCD file: how the point records are stored after the header.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum PcdData {
    /// One line of whitespace-separated numbers per point.
    Ascii,
    /// Packed little-endian records, one after the other (row-major).
    #[default]
    Binary,
    /// One LZF-compressed block holding all values of field 1, then of field 2, … (column-major),
    /// preceded by its compressed and uncompressed sizes (`u32` little-endian each).
    BinaryCompressed,
}

impl PcdData {
    /// The keyword of the `DATA` line.
    pub fn keyword(self) -> &'static str {
        match self {
            PcdData::Ascii => "ascii",
            PcdData::Binary => "binary",
            PcdData::BinaryCompressed => "binary_compressed",
        }
    }

    /// Parses the keyword of a `DATA` line (case-insensitive).
    pub fn from_keyword(s: &str) -> Option<PcdData> {
        match s.to_ascii_lowercase().as_str() {
            "ascii" => Some(PcdData::Ascii),
            "binary" => Some(PcdData::Binary),
            "binary_compressed" => Some(PcdData::BinaryCompressed),
            _ => None,
        }
    }
}

/// One entry of the `FIELDS` line with its `SIZE`, `TYPE` and `COUNT`.
///
/// A field with `COUNT` k > 1 becomes k schema fields named `name[0]` … `name[k-1]` (see
/// [`PcdField::element_name`]); a field with `COUNT` 1 keeps its name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PcdField {
    /// Name as the `FIELDS` line spells it (`_` marks padding).
    pub name: String,
    /// Type of each element (from `SIZE` and `TYPE`).
    pub ty: ScalarType,
    /// Number of elements (`COUNT`), at least 1.
    pub count: usize,
}

impl PcdField {
    /// A field of `count` elements of type `ty`.
    pub fn new(name: impl Into<String>, ty: ScalarType, count: usize) -> PcdField {
        PcdField {
            name: name.into(),
            ty,
            count,
        }
    }

    /// Bytes of one point's value (`SIZE × COUNT`).
    pub fn byte_len(&self) -> usize {
        self.ty.size() * self.count
    }

    /// True for PCL's padding field `_`, whose bytes PCL leaves out of `binary_compressed` data.
    pub fn is_padding(&self) -> bool {
        self.name == "_"
    }

    /// Name of schema field `i` of this PCD field: `name` when `COUNT` is 1, else `name[i]`.
    pub fn element_name(&self, i: usize) -> String {
        if self.count == 1 {
            self.name.clone()
        } else {
            format!("{}[{i}]", self.name)
        }
    }

    /// The `TYPE` letter of this field.
    pub fn type_letter(&self) -> char {
        type_letter(self.ty)
    }
}

/// The PCD `TYPE` letter of a scalar type.
pub(super) fn type_letter(ty: ScalarType) -> char {
    match ty {
        ScalarType::I8 | ScalarType::I16 | ScalarType::I32 | ScalarType::I64 => 'I',
        ScalarType::U8 | ScalarType::U16 | ScalarType::U32 | ScalarType::U64 => 'U',
        ScalarType::F32 | ScalarType::F64 => 'F',
    }
}

/// The scalar type of a `SIZE` / `TYPE` pair.
fn scalar_type(size: usize, letter: &str) -> Option<ScalarType> {
    Some(match (letter.to_ascii_uppercase().as_str(), size) {
        ("I", 1) => ScalarType::I8,
        ("I", 2) => ScalarType::I16,
        ("I", 4) => ScalarType::I32,
        ("I", 8) => ScalarType::I64,
        ("U", 1) => ScalarType::U8,
        ("U", 2) => ScalarType::U16,
        ("U", 4) => ScalarType::U32,
        ("U", 8) => ScalarType::U64,
        ("F", 4) => ScalarType::F32,
        ("F", 8) => ScalarType::F64,
        _ => return None,
    })
}

/// The header keywords.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Key {
    Version,
    Fields,
    Size,
    Type,
    Count,
    Width,
    Height,
    Viewpoint,
    Points,
    Data,
}

/// The header keywords, as [`Key::parse`] knows them.
const KEYWORDS: [&str; 11] = [
    "VERSION",
    "FIELDS",
    "COLUMNS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
    "DATA",
];

impl Key {
    fn parse(word: &str) -> Option<Key> {
        Some(match word.to_ascii_uppercase().as_str() {
            "VERSION" => Key::Version,
            "FIELDS" | "COLUMNS" => Key::Fields,
            "SIZE" => Key::Size,
            "TYPE" => Key::Type,
            "COUNT" => Key::Count,
            "WIDTH" => Key::Width,
            "HEIGHT" => Key::Height,
            "VIEWPOINT" => Key::Viewpoint,
            "POINTS" => Key::Points,
            "DATA" => Key::Data,
            _ => return None,
        })
    }

    fn upper(self) -> &'static str {
        match self {
            Key::Version => "VERSION",
            Key::Fields => "FIELDS",
            Key::Size => "SIZE",
            Key::Type => "TYPE",
            Key::Count => "COUNT",
            Key::Width => "WIDTH",
            Key::Height => "HEIGHT",
            Key::Viewpoint => "VIEWPOINT",
            Key::Points => "POINTS",
            Key::Data => "DATA",
        }
    }
}

/// One raw header line and the keyword it starts with (`None` for comments and blank lines).
#[derive(Debug, Clone)]
pub(super) struct Line {
    pub(super) raw: Vec<u8>,
    pub(super) key: Option<Key>,
}

/// A parsed PCD header.
#[derive(Debug, Clone, Default)]
pub(super) struct Header {
    /// Every line up to and including `DATA`, terminators included.
    pub(super) lines: Vec<Line>,
    pub(super) version: Option<String>,
    pub(super) fields: Vec<PcdField>,
    pub(super) width: u64,
    pub(super) height: u64,
    pub(super) viewpoint: [f64; 7],
    pub(super) points: u64,
    pub(super) data: PcdData,
}

/// The identity viewpoint PCL writes by default.
pub(super) const DEFAULT_VIEWPOINT: [f64; 7] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0];

impl Header {
    /// Bytes of the header (the offset of the point data).
    pub(super) fn byte_len(&self) -> u64 {
        self.lines.iter().map(|l| l.raw.len() as u64).sum()
    }

    /// The header as read.
    pub(super) fn bytes(&self) -> Vec<u8> {
        self.lines
            .iter()
            .flat_map(|l| l.raw.iter().copied())
            .collect()
    }

    /// Text of the comment lines (`#` and what follows, terminator excluded).
    pub(super) fn comments(&self) -> Vec<String> {
        self.lines
            .iter()
            .filter(|l| l.key.is_none())
            .map(|l| {
                String::from_utf8_lossy(split_eol(&l.raw).0)
                    .trim()
                    .to_string()
            })
            .filter(|t| t.starts_with('#'))
            .collect()
    }

    /// A fresh PCL-style v0.7 header for `count` unorganized points.
    pub(super) fn generated(
        fields: &[PcdField],
        count: u64,
        data: PcdData,
        viewpoint: [f64; 7],
    ) -> Header {
        let join =
            |f: &dyn Fn(&PcdField) -> String| fields.iter().map(f).collect::<Vec<_>>().join(" ");
        let vp: Vec<String> = viewpoint.iter().map(|v| v.to_string()).collect();
        let text = [
            (
                None,
                "# .PCD v0.7 - Point Cloud Data file format".to_string(),
            ),
            (Some(Key::Version), "VERSION 0.7".to_string()),
            (
                Some(Key::Fields),
                format!("FIELDS {}", join(&|f| f.name.clone())),
            ),
            (
                Some(Key::Size),
                format!("SIZE {}", join(&|f| f.ty.size().to_string())),
            ),
            (
                Some(Key::Type),
                format!("TYPE {}", join(&|f| f.type_letter().to_string())),
            ),
            (
                Some(Key::Count),
                format!("COUNT {}", join(&|f| f.count.to_string())),
            ),
            (Some(Key::Width), format!("WIDTH {count}")),
            (Some(Key::Height), "HEIGHT 1".to_string()),
            (Some(Key::Viewpoint), format!("VIEWPOINT {}", vp.join(" "))),
            (Some(Key::Points), format!("POINTS {count}")),
            (Some(Key::Data), format!("DATA {}", data.keyword())),
        ];
        Header {
            lines: text
                .into_iter()
                .map(|(key, t)| Line {
                    raw: format!("{t}\n").into_bytes(),
                    key,
                })
                .collect(),
            version: Some("0.7".into()),
            fields: fields.to_vec(),
            width: count,
            height: 1,
            viewpoint,
            points: count,
            data,
        }
    }

    /// The header for `count` points stored as `data`, with `append` added as a last field.
    ///
    /// Unchanged lines are copied byte for byte. When `count` differs from the header's point
    /// count, the cloud is written unorganized: `WIDTH count`, `HEIGHT 1`, `POINTS count`.
    pub(super) fn render(&self, count: u64, data: PcdData, append: &[PcdField]) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.byte_len() as usize + 64);
        let resized = count != self.points;
        for line in &self.lines {
            let (content, eol) = split_eol(&line.raw);
            let replace = |value: String, out: &mut Vec<u8>| {
                let word = tokens(content).next().unwrap_or(b"");
                out.extend_from_slice(word);
                out.push(b' ');
                out.extend_from_slice(value.as_bytes());
                out.extend_from_slice(eol);
            };
            let extend = |token: &dyn Fn(&PcdField) -> String, out: &mut Vec<u8>| {
                out.extend_from_slice(content.trim_ascii_end());
                for f in append {
                    out.push(b' ');
                    out.extend_from_slice(token(f).as_bytes());
                }
                out.extend_from_slice(eol);
            };
            let appended = !append.is_empty();
            match line.key {
                Some(Key::Fields) if appended => extend(&|f| f.name.clone(), &mut out),
                Some(Key::Size) if appended => extend(&|f| f.ty.size().to_string(), &mut out),
                Some(Key::Type) if appended => extend(&|f| f.type_letter().to_string(), &mut out),
                Some(Key::Count) if appended => extend(&|f| f.count.to_string(), &mut out),
                Some(Key::Width) if resized => replace(count.to_string(), &mut out),
                Some(Key::Height) if resized => replace("1".into(), &mut out),
                Some(Key::Points) if resized => replace(count.to_string(), &mut out),
                Some(Key::Data) if data != self.data => {
                    replace(data.keyword().to_string(), &mut out)
                }
                _ => out.extend_from_slice(&line.raw),
            }
        }
        // A header without a WIDTH line derives it from POINTS; a missing POINTS line is derived
        // from WIDTH × HEIGHT: both stay consistent after the rewrites above.
        if !out.ends_with(b"\n") {
            // A file that ends right after `DATA kind` (no terminator, so no points): the point
            // data written after the copied line would run into it, and the file could not be
            // read back (found by the pcd fuzz target, issue 15).
            out.extend_from_slice(self.eol().bytes());
        }
        out
    }

    /// The line terminator of the `DATA` line (used for ascii point lines).
    pub(super) fn eol(&self) -> LineEnding {
        self.lines
            .last()
            .and_then(|l| LineEnding::of(&l.raw))
            .unwrap_or_default()
    }
}

/// Reads one line of at most [`MAX_LINE`] bytes into `buf`; returns its length (0 at the end).
fn read_line(r: &mut impl BufRead, buf: &mut Vec<u8>) -> std::io::Result<usize> {
    buf.clear();
    r.by_ref().take(MAX_LINE).read_until(b'\n', buf)
}

/// Values of one header line, before validation.
#[derive(Default)]
struct Raw {
    version: Option<String>,
    fields: Option<Vec<String>>,
    size: Option<Vec<String>>,
    ty: Option<Vec<String>>,
    count: Option<Vec<String>>,
    width: Option<u64>,
    height: Option<u64>,
    viewpoint: Option<[f64; 7]>,
    points: Option<u64>,
    data: Option<PcdData>,
}

/// Reads the header from `r` (positioned at the start of the file), leaving `r` at the first
/// byte of the point data.
///
/// # Errors
/// [`IoError::Invalid`] for an empty file, [`IoError::Header`] for a file that is not PCD or a
/// malformed or inconsistent header, [`IoError::Unsupported`] for an unknown `DATA` kind.
pub(super) fn read_header(r: &mut impl BufRead, path: &Path) -> Result<Header, IoError> {
    let mut lines: Vec<Line> = Vec::new();
    let mut raw = Raw::default();
    let mut buf = Vec::new();
    let mut seen_keyword = false;
    loop {
        let n = read_line(r, &mut buf).map_err(|e| IoError::io(path, e))?;
        let number = lines.len() + 1;
        if n == 0 {
            if lines.is_empty() {
                return Err(IoError::invalid(path, "empty file: not a PCD file"));
            }
            return Err(if seen_keyword {
                IoError::header(path, "the header ends without a DATA line")
            } else {
                IoError::header(path, "not a PCD file: no header keyword found")
            });
        }
        let (content, _) = split_eol(&buf);
        let text = content.trim_ascii();
        if text.is_empty() || text.starts_with(b"#") {
            if buf.last() != Some(&b'\n') && n as u64 == MAX_LINE {
                return Err(IoError::header(
                    path,
                    format!("line {number} is longer than {MAX_LINE} bytes"),
                ));
            }
            lines.push(Line {
                raw: std::mem::take(&mut buf),
                key: None,
            });
            continue;
        }
        let mut words = tokens(text);
        let first = words.next().unwrap_or_default();
        let key = std::str::from_utf8(first).ok().and_then(Key::parse);
        if !seen_keyword && key.is_none() {
            return Err(IoError::header(
                path,
                format!(
                    "not a PCD file: line {number} starts with `{}`, not a PCD header keyword",
                    show(first)
                ),
            ));
        }
        if buf.last() != Some(&b'\n') && n as u64 == MAX_LINE {
            return Err(IoError::header(
                path,
                format!("line {number} is longer than {MAX_LINE} bytes"),
            ));
        }
        let Some(key) = key else {
            // After the first keyword every non-comment line must be one (issue 15: a line such
            // as `POINTS0300` or stray text was kept and copied to the output).
            let word = String::from_utf8_lossy(first);
            let glued = KEYWORDS
                .iter()
                .find(|k| word.len() > k.len() && word.starts_with(*k))
                .map(|k| format!(" (a space missing after {k}?)"))
                .unwrap_or_default();
            return Err(IoError::header(
                path,
                format!(
                    "line {number}: `{}` is not a PCD header keyword{glued}",
                    show(first)
                ),
            ));
        };
        seen_keyword = true;
        let values: Vec<String> = words
            .map(|w| String::from_utf8_lossy(w).into_owned())
            .collect();
        store(&mut raw, key, values, path, number)?;
        lines.push(Line {
            raw: std::mem::take(&mut buf),
            key: Some(key),
        });
        if key == Key::Data {
            break;
        }
    }
    validate(raw, lines, path)
}

/// Records the values of one keyword line.
fn store(
    raw: &mut Raw,
    key: Key,
    values: Vec<String>,
    path: &Path,
    number: usize,
) -> Result<(), IoError> {
    let bad = |what: &str| IoError::header(path, format!("line {number}: {} {what}", key.upper()));
    let one = |values: &[String]| -> Result<u64, IoError> {
        match values {
            [v] => v
                .parse::<u64>()
                .map_err(|_| bad(&format!("value `{}` is not a count", show(v.as_bytes())))),
            _ => Err(bad(&format!("needs one value, found {}", values.len()))),
        }
    };
    let duplicate = match key {
        Key::Version => raw.version.is_some(),
        Key::Fields => raw.fields.is_some(),
        Key::Size => raw.size.is_some(),
        Key::Type => raw.ty.is_some(),
        Key::Count => raw.count.is_some(),
        Key::Width => raw.width.is_some(),
        Key::Height => raw.height.is_some(),
        Key::Viewpoint => raw.viewpoint.is_some(),
        Key::Points => raw.points.is_some(),
        Key::Data => false,
    };
    if duplicate {
        return Err(bad("appears twice"));
    }
    if matches!(key, Key::Fields | Key::Size | Key::Type | Key::Count) && values.is_empty() {
        return Err(bad("has no value"));
    }
    match key {
        Key::Version => raw.version = Some(values.join(" ")),
        Key::Fields => raw.fields = Some(values),
        Key::Size => raw.size = Some(values),
        Key::Type => raw.ty = Some(values),
        Key::Count => raw.count = Some(values),
        Key::Width => raw.width = Some(one(&values)?),
        Key::Height => raw.height = Some(one(&values)?),
        Key::Points => raw.points = Some(one(&values)?),
        Key::Viewpoint => {
            let nums: Option<Vec<f64>> = values.iter().map(|v| v.parse().ok()).collect();
            match nums.as_deref() {
                Some(&[a, b, c, d, e, f, g]) => raw.viewpoint = Some([a, b, c, d, e, f, g]),
                _ => return Err(bad("needs 7 numbers (tx ty tz qw qx qy qz)")),
            }
        }
        Key::Data => {
            let word = match values.as_slice() {
                [w] => w,
                _ => return Err(bad(&format!("needs one value, found {}", values.len()))),
            };
            raw.data = Some(
                PcdData::from_keyword(word).ok_or_else(|| IoError::Unsupported {
                    path: path.to_path_buf(),
                    detail: format!(
                        "DATA `{}` (expected ascii, binary or binary_compressed)",
                        show(word.as_bytes())
                    ),
                })?,
            );
        }
    }
    Ok(())
}

/// Checks the header's consistency and builds the field model.
fn validate(raw: Raw, lines: Vec<Line>, path: &Path) -> Result<Header, IoError> {
    let err = |d: String| IoError::header(path, d);
    let names = raw.fields.ok_or_else(|| err("no FIELDS line".into()))?;
    let sizes = raw.size.ok_or_else(|| err("no SIZE line".into()))?;
    let types = raw.ty.ok_or_else(|| err("no TYPE line".into()))?;
    let n = names.len();
    let counts = raw.count.unwrap_or_else(|| vec!["1".into(); n]);
    for (what, len) in [
        ("SIZE", sizes.len()),
        ("TYPE", types.len()),
        ("COUNT", counts.len()),
    ] {
        if len != n {
            return Err(err(format!(
                "{what} has {len} values but FIELDS names {n} fields"
            )));
        }
    }
    let mut fields = Vec::with_capacity(n);
    let mut elements = 0usize;
    for i in 0..n {
        let name = &names[i];
        let size: usize = sizes[i].parse().map_err(|_| {
            err(format!(
                "field `{name}`: SIZE `{}` is not a number",
                show(sizes[i].as_bytes())
            ))
        })?;
        let ty = scalar_type(size, &types[i]).ok_or_else(|| {
            err(format!(
                "field `{name}`: SIZE {size} with TYPE `{}` is not a PCD type (I and U take 1, 2, \
                 4 or 8 bytes, F 4 or 8)",
                show(types[i].as_bytes())
            ))
        })?;
        let count: usize = counts[i].parse().ok().filter(|&c| c >= 1).ok_or_else(|| {
            err(format!(
                "field `{name}`: COUNT `{}` is not a positive number",
                show(counts[i].as_bytes())
            ))
        })?;
        elements = elements.saturating_add(count);
        if elements > MAX_FIELDS {
            return Err(err(format!(
                "more than {MAX_FIELDS} values per point (COUNT of `{name}` is {count})"
            )));
        }
        fields.push(PcdField::new(name.clone(), ty, count));
    }
    let data = raw.data.ok_or_else(|| err("no DATA line".into()))?;
    let height = raw.height.unwrap_or(1);
    let width = match (raw.width, raw.points) {
        (Some(w), _) => w,
        (None, Some(p)) => p.checked_div(height).unwrap_or(0),
        _ => return Err(err("neither WIDTH nor POINTS is given".into())),
    };
    let area = width.checked_mul(height);
    let points = match raw.points {
        Some(p) => p,
        None => area.ok_or_else(|| err(format!("WIDTH {width} × HEIGHT {height} overflows")))?,
    };
    if area != Some(points) {
        return Err(err(format!(
            "WIDTH {width} × HEIGHT {height} does not equal POINTS {points}"
        )));
    }
    Ok(Header {
        lines,
        version: raw.version,
        fields,
        width,
        height,
        viewpoint: raw.viewpoint.unwrap_or(DEFAULT_VIEWPOINT),
        points,
        data,
    })
}

#[cfg(test)]
mod io_pcd {
    use super::*;

    fn parse(text: &str) -> Result<Header, IoError> {
        read_header(&mut text.as_bytes(), Path::new("t.pcd"))
    }

    const HEAD: &str = "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z normal\nSIZE 4 4 4 4\n\
                        TYPE F F F F\nCOUNT 1 1 1 3\nWIDTH 2\nHEIGHT 2\n\
                        VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA ascii\n";

    #[test]
    fn parses_fields_counts_and_organization() {
        let h = parse(HEAD).unwrap();
        assert_eq!(h.fields.len(), 4);
        assert_eq!(h.fields[3], PcdField::new("normal", ScalarType::F32, 3));
        assert_eq!(h.fields[3].element_name(2), "normal[2]");
        assert_eq!((h.width, h.height, h.points), (2, 2, 4));
        assert_eq!(h.data, PcdData::Ascii);
        assert_eq!(h.bytes(), HEAD.as_bytes());
        assert_eq!(h.comments(), vec!["# .PCD v0.7".to_string()]);
    }

    #[test]
    fn render_keeps_unchanged_lines_and_rewrites_changed_ones() {
        let h = parse(HEAD).unwrap();
        assert_eq!(h.render(4, PcdData::Ascii, &[]), HEAD.as_bytes());
        let noise = PcdField::new("noise", ScalarType::U8, 1);
        let out = String::from_utf8(h.render(3, PcdData::Binary, &[noise])).unwrap();
        assert!(out.contains("FIELDS x y z normal noise\n"), "{out}");
        assert!(
            out.contains("SIZE 4 4 4 4 1\nTYPE F F F F U\nCOUNT 1 1 1 3 1\n"),
            "{out}"
        );
        assert!(out.contains("WIDTH 3\nHEIGHT 1\n"), "{out}");
        assert!(out.contains("POINTS 3\nDATA binary\n"), "{out}");
        let again = parse(&out).unwrap();
        assert_eq!(again.fields.len(), 5);
    }

    #[test]
    fn issue15_a_data_line_without_terminator_is_terminated_when_written() {
        let text = "FIELDS x y z\r\nSIZE 4 4 4\r\nTYPE F F F\r\nWIDTH 0\r\nDATA binary_compressed";
        let h = parse(text).unwrap();
        assert_eq!(h.points, 0);
        let out = h.render(0, PcdData::BinaryCompressed, &[]);
        assert!(out.ends_with(b"DATA binary_compressed\n"), "{out:?}");
        let mut written = out.clone();
        written.extend_from_slice(&[0u8; 8]);
        let mut r = written.as_slice();
        let again = read_header(&mut r, Path::new("t.pcd")).unwrap();
        assert_eq!(again.data, PcdData::BinaryCompressed);
        assert_eq!(r, &[0u8; 8]);
    }

    #[test]
    fn rejects_inconsistent_headers() {
        let cases = [
            (
                HEAD.replace("POINTS 4", "POINTS 5"),
                "does not equal POINTS",
            ),
            (
                HEAD.replace("SIZE 4 4 4 4", "SIZE 4 4 4"),
                "SIZE has 3 values",
            ),
            (
                HEAD.replace("TYPE F F F F", "TYPE F F F X"),
                "not a PCD type",
            ),
            (
                HEAD.replace("SIZE 4 4 4 4", "SIZE 4 4 4 2"),
                "not a PCD type",
            ),
            (
                HEAD.replace("COUNT 1 1 1 3", "COUNT 1 1 1 0"),
                "not a positive number",
            ),
            (HEAD.replace("DATA ascii\n", ""), "without a DATA line"),
            (
                HEAD.replace("VIEWPOINT 0 0 0 1 0 0 0", "VIEWPOINT 0 0"),
                "7 numbers",
            ),
            (HEAD.replace("WIDTH 2", "WIDTH two"), "not a count"),
            ("ply\nformat ascii 1.0\n".to_string(), "not a PCD file"),
            (
                HEAD.replace("COUNT 1 1 1 3", "COUNT 1 1 1 99999999"),
                "values per point",
            ),
        ];
        for (text, want) in cases {
            let e = parse(&text).unwrap_err().to_string();
            assert!(e.contains(want), "{e} (wanted {want})");
            assert!(e.starts_with("t.pcd: "), "{e}");
        }
        let e = parse(&HEAD.replace("DATA ascii", "DATA zip")).unwrap_err();
        assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
        assert!(parse("").unwrap_err().to_string().contains("empty file"));
    }

    #[test]
    fn defaults_for_optional_lines() {
        let h = parse("FIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nPOINTS 3\nDATA binary\n").unwrap();
        assert_eq!((h.width, h.height, h.points), (3, 1, 3));
        assert!(
            h.fields
                .iter()
                .all(|f| f.count == 1 && f.ty == ScalarType::F64)
        );
        assert_eq!(h.viewpoint, DEFAULT_VIEWPOINT);
        let h = parse("VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 5\nDATA binary\n")
            .unwrap();
        assert_eq!(h.points, 5);
    }
}
