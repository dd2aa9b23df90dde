//! The PLY header: its element model, reading and writing.
//!
//! Reading is split in two. This module collects the raw header lines itself (up to and
//! including `end_header`), because a writer must reproduce them byte for byte (type spellings such
//! as `float` vs `float32`, the order of comments and `obj_info` lines, line terminators) and must
//! know exactly where the payload starts. The collected text is then handed to the `ply-rs-bw`
//! header parser ([`ply_rs_bw::parser::Parser::read_header`]), which validates the grammar and
//! yields the encoding, comments, `obj_info` lines, elements and property types. Only the
//! *positions* of the `element` lines are located here (to rewrite their counts), and duplicate
//! names — which the crate's name-keyed maps would merge silently — are rejected.

use std::io::BufRead;
use std::path::Path;

use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{self as rs, DefaultElement};

use super::super::IoError;
use crate::points::{Endian, ScalarType};

/// Longest header line accepted (a safeguard against reading a large binary file as one line).
const MAX_LINE: u64 = 1 << 16;
/// Largest header accepted, in bytes.
const MAX_HEADER: usize = 1 << 22;

/// Payload encoding of a PLY file (the `format` line).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum PlyEncoding {
    /// `format ascii 1.0`: whitespace-separated numbers, one element per line.
    Ascii,
    /// `format binary_little_endian 1.0`.
    #[default]
    BinaryLittleEndian,
    /// `format binary_big_endian 1.0`.
    BinaryBigEndian,
}

impl PlyEncoding {
    /// The keyword of the `format` line.
    pub fn keyword(self) -> &'static str {
        match self {
            PlyEncoding::Ascii => "ascii",
            PlyEncoding::BinaryLittleEndian => "binary_little_endian",
            PlyEncoding::BinaryBigEndian => "binary_big_endian",
        }
    }

    /// Byte order of the binary records a source delivers (ascii values are stored little-endian).
    pub fn record_endian(self) -> Endian {
        match self {
            PlyEncoding::BinaryBigEndian => Endian::Big,
            PlyEncoding::Ascii | PlyEncoding::BinaryLittleEndian => Endian::Little,
        }
    }

    /// True for the two binary encodings.
    pub fn is_binary(self) -> bool {
        self != PlyEncoding::Ascii
    }
}

/// Type of one PLY property.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PlyType {
    /// A single value.
    Scalar(ScalarType),
    /// A length of type `count` followed by that many values of type `item`.
    List {
        /// Integer type of the length prefix.
        count: ScalarType,
        /// Type of the items.
        item: ScalarType,
    },
}

/// One declared property of an element.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct PlyProperty {
    /// Property name.
    pub name: String,
    /// Property type.
    pub ty: PlyType,
}

/// One declared element: a name, an instance count and properties.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct PlyElement {
    /// Element name (`vertex`, `face`, `range_grid`, …).
    pub name: String,
    /// Number of instances.
    pub count: u64,
    /// Properties in declared order.
    pub properties: Vec<PlyProperty>,
}

impl PlyElement {
    /// Bytes per instance in a binary encoding; `None` when the element has list properties.
    pub fn record_len(&self) -> Option<usize> {
        self.properties.iter().try_fold(0, |acc, p| match p.ty {
            PlyType::Scalar(t) => Some(acc + t.size()),
            PlyType::List { .. } => None,
        })
    }

    /// Index of the face-index list (`vertex_indices` or `vertex_index`), if the element has one.
    pub fn face_list(&self) -> Option<usize> {
        self.properties.iter().position(|p| {
            matches!(p.ty, PlyType::List { .. })
                && (p.name == "vertex_indices" || p.name == "vertex_index")
        })
    }
}

/// The PLY type keyword for `ty` (classic spelling); `None` for 64-bit integers, which PLY lacks.
pub fn type_keyword(ty: ScalarType) -> Option<&'static str> {
    Some(match ty {
        ScalarType::I8 => "char",
        ScalarType::U8 => "uchar",
        ScalarType::I16 => "short",
        ScalarType::U16 => "ushort",
        ScalarType::I32 => "int",
        ScalarType::U32 => "uint",
        ScalarType::F32 => "float",
        ScalarType::F64 => "double",
        ScalarType::I64 | ScalarType::U64 => return None,
    })
}

fn scalar_from_rs(t: &rs::ScalarType) -> ScalarType {
    match t {
        rs::ScalarType::Char => ScalarType::I8,
        rs::ScalarType::UChar => ScalarType::U8,
        rs::ScalarType::Short => ScalarType::I16,
        rs::ScalarType::UShort => ScalarType::U16,
        rs::ScalarType::Int => ScalarType::I32,
        rs::ScalarType::UInt => ScalarType::U32,
        rs::ScalarType::Float => ScalarType::F32,
        rs::ScalarType::Double => ScalarType::F64,
    }
}

/// A parsed header plus the raw text needed to reproduce it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(super) struct Header {
    /// Payload encoding.
    pub encoding: PlyEncoding,
    /// Elements in declared order.
    pub elements: Vec<PlyElement>,
    /// `comment` lines (text after the keyword).
    pub comments: Vec<String>,
    /// `obj_info` lines (text after the keyword).
    pub obj_info: Vec<String>,
    /// Raw lines, each with its terminator (bytes: comments need not be UTF-8).
    pub lines: Vec<Vec<u8>>,
    /// For each element, the index into `lines` of its `element` line.
    pub element_lines: Vec<usize>,
    /// Line terminator of the `end_header` line (`\n` when the file ends right after it).
    pub newline: String,
}

impl Header {
    /// Length of the header in bytes.
    pub fn byte_len(&self) -> usize {
        self.lines.iter().map(Vec::len).sum()
    }

    /// The header bytes with the count of element `i` replaced by `c` for each `(i, c)` given.
    pub fn text_with_counts(&self, counts: &[(usize, u64)]) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.byte_len() + 16);
        for (l, line) in self.lines.iter().enumerate() {
            let new = self
                .element_lines
                .iter()
                .position(|&el| el == l)
                .and_then(|e| counts.iter().find(|(i, _)| *i == e))
                .map(|&(_, c)| c);
            match new {
                Some(c) => out.extend_from_slice(replace_count(line, c).as_bytes()),
                None => out.extend_from_slice(line),
            }
        }
        out
    }

    /// Declares a further scalar property `name` of type `ty` as the last property of element
    /// `e`: a `property` line goes right after the element's last `property` line (with that
    /// line's terminator), and the element model gets the property too.
    pub fn push_property(&mut self, e: usize, name: &str, ty: ScalarType) {
        let start = self.element_lines[e];
        let end = self
            .element_lines
            .get(e + 1)
            .copied()
            .unwrap_or(self.lines.len().saturating_sub(1));
        let after = (start + 1..end)
            .rev()
            .find(|&l| word(&self.lines[l], 0) == Some(b"property".as_slice()))
            .unwrap_or(start);
        let prev = &self.lines[after];
        let body = prev
            .iter()
            .rposition(|&c| c != b'\r' && c != b'\n')
            .map_or(0, |n| n + 1);
        let nl = match &prev[body..] {
            b"" => self.newline.as_bytes().to_vec(),
            t => t.to_vec(),
        };
        let kw = type_keyword(ty).unwrap_or("double");
        let mut line = format!("property {kw} {name}").into_bytes();
        line.extend_from_slice(&nl);
        let at = after + 1;
        self.lines.insert(at, line);
        for l in &mut self.element_lines {
            if *l >= at {
                *l += 1;
            }
        }
        self.elements[e].properties.push(PlyProperty {
            name: name.to_string(),
            ty: PlyType::Scalar(ty),
        });
    }
}

/// Replaces the last token (the count) of an `element` line, keeping spacing and terminator.
fn replace_count(line: &[u8], count: u64) -> String {
    // Element lines passed the grammar, so they are ASCII.
    let line = String::from_utf8_lossy(line);
    let line = line.as_ref();
    let body = line.trim_end_matches([' ', '\t', '\r', '\n']);
    let start = body.rfind([' ', '\t']).map_or(0, |i| i + 1);
    format!("{}{count}{}", &body[..start], &line[body.len()..])
}

/// Reads one line (terminator included) of at most [`MAX_LINE`] bytes; `Ok(false)` at end of file.
fn read_line(r: &mut impl BufRead, buf: &mut Vec<u8>, path: &Path) -> Result<bool, IoError> {
    buf.clear();
    let n = std::io::Read::take(&mut *r, MAX_LINE)
        .read_until(b'\n', buf)
        .map_err(|e| IoError::io(path, e))?;
    Ok(n > 0)
}

/// Reads and parses the header; on success `r` is positioned at the first payload byte.
pub(super) fn read_header(r: &mut impl BufRead, path: &Path) -> Result<Header, IoError> {
    let mut buf = Vec::new();
    if !read_line(r, &mut buf, path)? {
        return Err(IoError::header(path, "empty file, not a PLY file"));
    }
    let magic = buf.trim_ascii_end();
    if magic != b"ply" {
        return Err(IoError::header(
            path,
            "not a PLY file (the first line is not `ply`)",
        ));
    }
    let mut lines = vec![buf.clone()];
    let mut total = buf.len();
    loop {
        let lineno = lines.len() + 1;
        if !read_line(r, &mut buf, path)? {
            return Err(IoError::header(
                path,
                format!("the file ends at line {lineno} without an `end_header` line"),
            ));
        }
        total += buf.len();
        if (!buf.ends_with(b"\n") && buf.len() as u64 >= MAX_LINE) || total > MAX_HEADER {
            return Err(IoError::header(
                path,
                format!("line {lineno} is too long for a header line (no `end_header` found)"),
            ));
        }
        lines.push(buf.clone());
        if buf.trim_ascii() == b"end_header" {
            break;
        }
    }
    parse_lines(lines, path)
}

/// Validates `lines` with ply-rs-bw and builds the element model.
fn parse_lines(lines: Vec<Vec<u8>>, path: &Path) -> Result<Header, IoError> {
    // Non-UTF-8 bytes (a Latin-1 comment, say) become U+FFFD for the grammar; the raw bytes stay.
    let text = String::from_utf8_lossy(&lines.concat()).into_owned();
    let parser = Parser::<DefaultElement>::new();
    let parsed = parser
        .read_header(&mut Reader::new(text.as_bytes()))
        .map_err(|e| {
            let detail = match e
                .line()
                .and_then(|l| lines.get(l.wrapping_sub(1)).map(|s| (l, s)))
            {
                Some((l, s)) => format!(
                    "line {l}: cannot parse `{}`",
                    clip(&String::from_utf8_lossy(s.trim_ascii()))
                ),
                None => e
                    .to_string()
                    .lines()
                    .next()
                    .unwrap_or("malformed")
                    .to_string(),
            };
            IoError::header(path, detail)
        })?;

    let encoding = match parsed.encoding {
        rs::Encoding::Ascii => PlyEncoding::Ascii,
        rs::Encoding::BinaryLittleEndian => PlyEncoding::BinaryLittleEndian,
        rs::Encoding::BinaryBigEndian => PlyEncoding::BinaryBigEndian,
    };

    // Locate the element lines; the crate already validated their syntax.
    let element_lines: Vec<usize> = lines
        .iter()
        .enumerate()
        .filter(|(_, l)| word(l, 0) == Some(b"element".as_slice()))
        .map(|(i, _)| i)
        .collect();
    if element_lines.len() != parsed.elements.len() {
        let mut seen = std::collections::HashSet::new();
        let dup = element_lines
            .iter()
            .filter_map(|&i| word(&lines[i], 1))
            .find(|n| !seen.insert(*n))
            .map(String::from_utf8_lossy)
            .unwrap_or_default();
        return Err(IoError::header(
            path,
            format!("element `{dup}` is declared twice"),
        ));
    }

    let mut elements = Vec::with_capacity(parsed.elements.len());
    for (k, (name, def)) in parsed.elements.iter().enumerate() {
        let next = element_lines.get(k + 1).copied().unwrap_or(lines.len());
        let declared = lines[element_lines[k] + 1..next]
            .iter()
            .filter(|l| word(l, 0) == Some(b"property".as_slice()))
            .count();
        if declared != def.properties.len() {
            return Err(IoError::header(
                path,
                format!("element `{name}` declares a property name twice"),
            ));
        }
        let mut properties = Vec::with_capacity(def.properties.len());
        for (pname, p) in &def.properties {
            let ty = match &p.data_type {
                rs::PropertyType::Scalar(t) => PlyType::Scalar(scalar_from_rs(t)),
                rs::PropertyType::List(c, t) => {
                    let count = scalar_from_rs(c);
                    if count.is_float() {
                        return Err(IoError::header(
                            path,
                            format!(
                                "list property `{pname}` of element `{name}` has a \
                                 floating-point length type"
                            ),
                        ));
                    }
                    PlyType::List {
                        count,
                        item: scalar_from_rs(t),
                    }
                }
            };
            properties.push(PlyProperty {
                name: pname.clone(),
                ty,
            });
        }
        elements.push(PlyElement {
            name: name.clone(),
            count: def.count as u64,
            properties,
        });
    }

    let last = lines.last().map(Vec::as_slice).unwrap_or_default();
    let newline = match last.iter().rposition(|&c| c != b'\r' && c != b'\n') {
        Some(n) if n + 1 < last.len() => String::from_utf8_lossy(&last[n + 1..]).into_owned(),
        _ => "\n".to_string(),
    };
    Ok(Header {
        encoding,
        elements,
        comments: parsed.comments,
        obj_info: parsed.obj_infos,
        lines,
        element_lines,
        newline,
    })
}

/// Word `k` (0-based) of a line, split at ASCII whitespace.
fn word(line: &[u8], k: usize) -> Option<&[u8]> {
    line.split(|c| c.is_ascii_whitespace())
        .filter(|w| !w.is_empty())
        .nth(k)
}

/// Shortens a quoted line for an error message.
fn clip(s: &str) -> String {
    if s.chars().count() > 60 {
        format!("{}…", s.chars().take(60).collect::<String>())
    } else {
        s.to_string()
    }
}

/// Builds a header for a generated cloud; `elements` are written in order.
pub(super) fn generated_header(encoding: PlyEncoding, elements: Vec<PlyElement>) -> Header {
    let mut lines = vec![
        b"ply\n".to_vec(),
        format!("format {} 1.0\n", encoding.keyword()).into_bytes(),
    ];
    let mut element_lines = Vec::new();
    for e in &elements {
        element_lines.push(lines.len());
        lines.push(format!("element {} {}\n", e.name, e.count).into_bytes());
        for p in &e.properties {
            let kw = |t| type_keyword(t).unwrap_or("double");
            let line = match p.ty {
                PlyType::Scalar(t) => format!("property {} {}\n", kw(t), p.name),
                PlyType::List { count, item } => {
                    format!("property list {} {} {}\n", kw(count), kw(item), p.name)
                }
            };
            lines.push(line.into_bytes());
        }
    }
    lines.push(b"end_header\n".to_vec());
    Header {
        encoding,
        elements,
        comments: Vec::new(),
        obj_info: Vec::new(),
        lines,
        element_lines,
        newline: "\n".to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Header, IoError> {
        read_header(&mut text.as_bytes(), Path::new("t.ply"))
    }

    #[test]
    fn both_type_spellings_and_lists() {
        let h = parse(
            "ply\r\nformat binary_big_endian 1.0\r\ncomment a b\r\nobj_info o\r\n\
             element vertex 2\r\nproperty int8 x\r\nproperty uchar y\r\nproperty int16 z\r\n\
             property ushort a\r\nproperty int32 b\r\nproperty uint c\r\nproperty float32 d\r\n\
             property double e\r\nelement face 1\r\nproperty list uint16 uint vertex_index\r\n\
             end_header\r\nrest",
        )
        .unwrap();
        assert_eq!(h.encoding, PlyEncoding::BinaryBigEndian);
        assert_eq!(h.comments, vec!["a b"]);
        assert_eq!(h.obj_info, vec!["o"]);
        let v = &h.elements[0];
        let tys: Vec<_> = v.properties.iter().map(|p| p.ty).collect();
        use ScalarType::*;
        let want = [I8, U8, I16, U16, I32, U32, F32, F64].map(PlyType::Scalar);
        assert_eq!(tys, want);
        assert_eq!(v.record_len(), Some(1 + 1 + 2 + 2 + 4 + 4 + 4 + 8));
        assert_eq!(
            h.elements[1].properties[0].ty,
            PlyType::List {
                count: U16,
                item: U32
            }
        );
        assert_eq!(h.elements[1].face_list(), Some(0));
        assert_eq!(h.newline, "\r\n");
        assert_eq!(h.lines.concat().len(), h.byte_len());
        assert!(h.text_with_counts(&[]).ends_with(b"end_header\r\n"));
        let text = String::from_utf8(h.text_with_counts(&[(0, 17)])).unwrap();
        assert!(text.contains("element vertex 17\r\nproperty int8 x"));
    }

    #[test]
    fn errors_are_one_line_and_name_the_problem() {
        let e = parse("").unwrap_err().to_string();
        assert!(e.contains("empty file"), "{e}");
        let e = parse("hello\nworld\n").unwrap_err().to_string();
        assert!(e.contains("not a PLY"), "{e}");
        let e = parse("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("end_header"), "{e}");
        let e = parse("ply\nformat ascii 1.0\nelement vertex 1\nproperty flot x\nend_header\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 4") && e.contains("flot"), "{e}");
        assert!(!e.contains('\n'), "{e}");
        let e = parse("ply\nformat ascii 1.0\nelement a 1\nelement a 2\nend_header\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("twice"), "{e}");
        let e =
            parse("ply\nformat ascii 1.0\nelement a 1\nproperty list float int l\nend_header\n")
                .unwrap_err()
                .to_string();
        assert!(e.contains("floating-point length"), "{e}");
        let e = parse("ply\nelement a 1\nend_header\n")
            .unwrap_err()
            .to_string();
        assert!(!e.contains('\n'), "{e}");
    }

    #[test]
    fn non_utf8_comments_are_kept_byte_for_byte() {
        let text = b"ply\nformat ascii 1.0\ncomment cr\xe9\xe9 par\nelement vertex 0\n\
                     property float x\nend_header\n";
        let h = read_header(&mut text.as_slice(), Path::new("t.ply")).unwrap();
        assert_eq!(h.text_with_counts(&[]), text);
        assert_eq!(h.elements[0].name, "vertex");
    }

    #[test]
    fn count_replacement_keeps_spacing() {
        assert_eq!(
            replace_count(b"element  vertex   12 \r\n", 7),
            "element  vertex   7 \r\n"
        );
        assert_eq!(replace_count(b"element vertex 12", 0), "element vertex 0");
    }
}
