//! Object File Format meshes (`.off`): `OFF`, `COFF`, `NOFF`, `CNOFF`, `STOFF` and combinations.
//!
//! # Brief overview
//!
//! ```text
//!  # comment              OffMeta::before_keyword
//!  COFF                   keyword (the counts may follow on this line: `OFF 8 6 12`)
//!  # comment              OffMeta::before_counts
//!  8 6 12                 vertex, face and edge counts (the edge count is kept as written)
//!                         OffMeta::before_vertices
//!  1 2 3 255 0 0 255      vertex: x y z, then the optional columns
//!  …
//!  4 0 1 2 3 255 0 0      face: n, n vertex indices (0-based), optional colour
//!  …                      everything after the last vertex: OffTrailer::raw, kept byte for byte
//! ```
//!
//! Vertices stream: [`OffSource::open`] reads the header and the first vertex line, each
//! [`Source::read_batch`] reads the next vertex lines, and [`Source::finish`] reads the rest of
//! the file and parses the faces. Columns after x, y, z are `F64` fields named after the keyword
//! prefixes (`nx ny nz` for `N`, `r g b [a]` for `C`, `s t` for `ST`), else `c3`, `c4`, …; every
//! vertex line must have as many columns as the first. Comment and blank lines between two
//! vertex lines are dropped. `4OFF`, `nOFF` and binary OFF are not supported.
//!
//! A sink created like an OFF source writes the same header with the new vertex count, the
//! vertex lines re-formatted (shortest round-trip text, the file's line terminator) and the
//! trailer unchanged. A sink of any other layout writes `OFF`, the counts, `x y z` vertex lines
//! and the faces of [`Extras::faces`]. OFF is a mesh format: [`create_with`](super::create_with)
//! refuses [`SinkOptions::noise_flag`](super::SinkOptions::noise_flag) ("outlier flags apply to
//! point clouds").

use std::path::Path;

use super::lines::{
    LineEnding, LineReader, LineSink, coord_types, default_names, encode_f64_record, extra_fields,
    f64_schema, is_comment_or_blank, parse_f64, parse_u64, push_value, show, split_eol,
    strip_comment, tokens,
};
use super::tally::{Tally, check_batch};
use super::{AtomicFile, Extras, Format, Input, IoError, Meta, Sink, Source, SourceInfo, Trailer};
use crate::points::{Faces, PointBatch, ScalarType, Schema};

/// OFF header information a sink reproduces.
#[derive(Debug, Clone, Default)]
pub struct OffMeta {
    /// Raw comment and blank lines before the keyword line.
    pub before_keyword: Vec<u8>,
    /// The keyword as written (`OFF`, `COFF`, `NOFF`, `CNOFF`, …).
    pub keyword: String,
    /// The counts stand on the keyword line.
    pub inline_counts: bool,
    /// Raw comment and blank lines between the keyword line and the counts line.
    pub before_counts: Vec<u8>,
    /// The edge count as written (most writers put 0), if the counts line has one.
    pub edges: Option<String>,
    /// Raw comment and blank lines between the counts and the first vertex.
    pub before_vertices: Vec<u8>,
    /// Line terminator of the header and vertex lines.
    pub eol: LineEnding,
}

/// OFF content besides the points.
#[derive(Debug, Clone, Default)]
pub struct OffTrailer {
    /// Everything after the last vertex line (the face lines and what follows), byte for byte.
    pub raw: Vec<u8>,
    /// Number of faces `raw` holds.
    pub faces: u64,
    /// The file ends with a vertex line that has no line terminator.
    pub unterminated: bool,
}

/// Column names after x, y, z for a keyword's prefixes and `extra` further columns.
fn column_names(keyword: &str, extra: usize) -> Vec<String> {
    let prefix = &keyword[..keyword.len() - 3];
    let st = prefix.starts_with("ST");
    let rest = prefix.trim_start_matches("ST");
    let colour = rest.contains('C');
    let normal = rest.contains('N');
    let mut names: Vec<&str> = Vec::new();
    if normal {
        names.extend(["nx", "ny", "nz"]);
    }
    let fixed = names.len() + if st { 2 } else { 0 };
    let ncolour = extra.saturating_sub(fixed);
    if colour && (ncolour == 3 || ncolour == 4) {
        names.extend(&["r", "g", "b", "a"][..ncolour]);
    }
    if st {
        names.extend(["s", "t"]);
    }
    default_names(3 + extra, &names)
}

/// Checks an OFF keyword; `Ok(())` for the supported `[ST][C][N]OFF` forms.
fn check_keyword(path: &Path, line: u64, kw: &str) -> Result<(), IoError> {
    let Some(prefix) = kw.strip_suffix("OFF") else {
        return Err(IoError::header(
            path,
            format!(
                "line {line}: expected the `OFF` keyword, found `{}`",
                show(kw.as_bytes())
            ),
        ));
    };
    if prefix.contains('4') || prefix.contains('n') {
        return Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: format!("line {line}: `{kw}` (OFF with other than 3 dimensions)"),
        });
    }
    let rest = prefix.strip_prefix("ST").unwrap_or(prefix);
    if !matches!(rest, "" | "C" | "N" | "CN" | "NC") {
        return Err(IoError::header(
            path,
            format!("line {line}: unknown OFF keyword `{}`", show(kw.as_bytes())),
        ));
    }
    Ok(())
}

/// Parses `nv nf [ne]`.
fn parse_counts(
    path: &Path,
    line: u64,
    toks: &[&[u8]],
) -> Result<(u64, u64, Option<String>), IoError> {
    let bad = || {
        let text: Vec<String> = toks.iter().map(|t| show(t)).collect();
        IoError::header(
            path,
            format!(
                "line {line}: expected the counts `vertices faces edges`, found `{}`",
                text.join(" ")
            ),
        )
    };
    if !(2..=3).contains(&toks.len()) {
        return Err(bad());
    }
    let nv = parse_u64(toks[0]).ok_or_else(bad)?;
    let nf = parse_u64(toks[1]).ok_or_else(bad)?;
    let ne = match toks.get(2) {
        Some(t) => {
            parse_u64(t).ok_or_else(bad)?;
            Some(String::from_utf8_lossy(t).into_owned())
        }
        None => None,
    };
    Ok((nv, nf, ne))
}

/// Streaming OFF reader.
pub struct OffSource {
    info: SourceInfo,
    lines: LineReader,
    ncols: usize,
    vertices: u64,
    faces: u64,
    /// Vertices read so far.
    read: u64,
    /// The first vertex, parsed at open.
    first: Option<Vec<f64>>,
    unterminated: bool,
    values: Vec<f64>,
    record: Vec<u8>,
}

/// Parses a vertex line of `ncols` numbers into `values`.
fn parse_vertex(
    path: &Path,
    line: u64,
    content: &[u8],
    ncols: usize,
    values: &mut Vec<f64>,
) -> Result<(), IoError> {
    values.clear();
    for tok in tokens(strip_comment(content)) {
        let v = parse_f64(tok).ok_or_else(|| {
            IoError::invalid(
                path,
                format!("line {line}: bad number `{}` in a vertex", show(tok)),
            )
        })?;
        values.push(v);
    }
    if values.len() != ncols {
        return Err(IoError::invalid(
            path,
            format!(
                "line {line}: a vertex with {} numbers, expected {ncols} like the first",
                values.len()
            ),
        ));
    }
    Ok(())
}

impl OffSource {
    /// Opens an OFF file and reads its header and first vertex.
    ///
    /// # Errors
    /// Unreadable or empty file, a missing or unsupported keyword, bad counts, a bad first vertex.
    pub fn open(path: &Path) -> Result<OffSource, IoError> {
        OffSource::new(Input::from_path(path)?)
    }

    /// [`OffSource::open`] on any [`Input`].
    ///
    /// # Errors
    /// As [`OffSource::open`].
    pub fn new(input: Input) -> Result<OffSource, IoError> {
        let file_len = input.len();
        let owned = input.name().to_path_buf();
        let path = owned.as_path();
        let mut lines = LineReader::new(input);
        let mut meta = OffMeta::default();
        // The keyword line.
        let mut counts = None;
        loop {
            if !lines.next_line()? {
                return Err(IoError::header(
                    path,
                    if lines.line() == 0 {
                        "empty file: expected the `OFF` keyword"
                    } else {
                        "no `OFF` keyword"
                    },
                ));
            }
            let raw = lines.raw();
            let (content, _) = split_eol(raw);
            if is_comment_or_blank(content) {
                meta.before_keyword.extend_from_slice(raw);
                continue;
            }
            let line = lines.line();
            let toks: Vec<&[u8]> = tokens(strip_comment(content)).collect();
            let kw =
                String::from_utf8_lossy(toks.first().copied().unwrap_or_default()).into_owned();
            check_keyword(path, line, &kw)?;
            meta.eol = LineEnding::of(raw).unwrap_or_default();
            if toks.get(1) == Some(&&b"BINARY"[..]) {
                return Err(IoError::Unsupported {
                    path: path.to_path_buf(),
                    detail: "binary OFF".into(),
                });
            }
            if toks.len() > 1 {
                counts = Some(parse_counts(path, line, &toks[1..])?);
                meta.inline_counts = true;
            }
            meta.keyword = kw;
            break;
        }
        // The counts line.
        let (nv, nf, edges) = match counts {
            Some(c) => c,
            None => loop {
                if !lines.next_line()? {
                    return Err(IoError::truncated(
                        path,
                        "the file ends before the counts line",
                    ));
                }
                let raw = lines.raw();
                let (content, _) = split_eol(raw);
                if is_comment_or_blank(content) {
                    meta.before_counts.extend_from_slice(raw);
                    continue;
                }
                let toks: Vec<&[u8]> = tokens(strip_comment(content)).collect();
                break parse_counts(path, lines.line(), &toks)?;
            },
        };
        meta.edges = edges;
        // Counts no file of this size can hold are refused here, naming the file (issue 51).
        crate::io::lines::check_text_count(path, (nv, "vertices"), 3, nf, file_len)?;
        if nf > 0 && nv > u64::from(u32::MAX) + 1 {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: format!("{nv} vertices: face indices are limited to 32 bits"),
            });
        }
        // The first vertex fixes the number of columns.
        let mut first = None;
        let mut values = Vec::new();
        let mut unterminated = false;
        if nv > 0 {
            loop {
                if !lines.next_line()? {
                    return Err(IoError::truncated(
                        path,
                        format!("the header declares {nv} vertices but the file holds 0"),
                    ));
                }
                let raw = lines.raw();
                let (content, _) = split_eol(raw);
                if is_comment_or_blank(content) {
                    meta.before_vertices.extend_from_slice(raw);
                    continue;
                }
                let n = tokens(strip_comment(content)).count();
                if n < 3 {
                    return Err(IoError::invalid(
                        path,
                        format!(
                            "line {}: a vertex needs x y z, found {n} numbers",
                            lines.line()
                        ),
                    ));
                }
                parse_vertex(path, lines.line(), content, n, &mut values)?;
                unterminated = LineEnding::of(raw).is_none();
                first = Some(values.clone());
                break;
            }
        }
        let ncols = first.as_ref().map_or(3, Vec::len);
        let names = column_names(&meta.keyword, ncols - 3);
        let schema = f64_schema(path, &names)?;
        Ok(OffSource {
            info: SourceInfo {
                path: path.to_path_buf(),
                format: Format::Off,
                schema,
                len: Some(nv),
                faces: (nf > 0).then_some(nf),
                meta: Meta::Off(meta),
            },
            lines,
            ncols,
            vertices: nv,
            faces: nf,
            read: 0,
            first,
            unterminated,
            values,
            record: Vec::new(),
        })
    }

    /// Parses the next vertex into `self.values`; false after the declared count.
    fn next_vertex(&mut self) -> Result<bool, IoError> {
        if self.read == self.vertices {
            return Ok(false);
        }
        if let Some(v) = self.first.take() {
            self.values = v;
            return Ok(true);
        }
        let path = &self.info.path;
        while self.lines.next_line()? {
            let raw = self.lines.raw();
            let (content, _) = split_eol(raw);
            if is_comment_or_blank(content) {
                continue;
            }
            self.unterminated = LineEnding::of(raw).is_none();
            parse_vertex(
                path,
                self.lines.line(),
                content,
                self.ncols,
                &mut self.values,
            )?;
            return Ok(true);
        }
        Err(IoError::truncated(
            path,
            format!(
                "the header declares {} vertices but the file holds {}",
                self.vertices, self.read
            ),
        ))
    }
}

impl Source for OffSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        batch.clear(self.read);
        batch.record_len = self.info.schema.record_len;
        let mut n = 0;
        while n < max && self.next_vertex()? {
            let p = encode_f64_record(&self.values, &mut self.record);
            batch.push(p, &self.record);
            self.read += 1;
            n += 1;
        }
        Ok(n)
    }

    fn finish(mut self: Box<Self>) -> Result<Extras, IoError> {
        while self.next_vertex()? {
            self.read += 1;
        }
        let path = &self.info.path;
        let mut raw = Vec::new();
        let base = self.lines.line();
        self.lines.read_rest(&mut raw)?;
        let mut faces = Faces::new();
        let mut face = Vec::new();
        for (k, l) in raw.split_inclusive(|&c| c == b'\n').enumerate() {
            let line = base + k as u64 + 1;
            let (content, _) = split_eol(l);
            if is_comment_or_blank(content) {
                continue;
            }
            if faces.len() as u64 == self.faces {
                // A line past the faces the header counts: the header lies (issue 51: 0 faces
                // over 722 face lines ran as a point cloud). PLY refuses the same lie.
                return Err(IoError::header(
                    path,
                    format!(
                        "the header declares {} faces, but line {line} holds more data (`{}`); \
                         fix the counts line",
                        self.faces,
                        show(strip_comment(content))
                    ),
                ));
            }
            let mut toks = tokens(strip_comment(content));
            let head = toks.next().unwrap_or_default();
            let n = parse_u64(head).filter(|&n| n > 0).ok_or_else(|| {
                IoError::invalid(
                    path,
                    format!("line {line}: bad face vertex count `{}`", show(head)),
                )
            })?;
            face.clear();
            for tok in toks.by_ref().take(n.min(1 << 20) as usize) {
                let i = parse_u64(tok).ok_or_else(|| {
                    IoError::invalid(
                        path,
                        format!("line {line}: bad vertex index `{}` in a face", show(tok)),
                    )
                })?;
                if i >= self.vertices {
                    return Err(IoError::invalid(
                        path,
                        format!(
                            "line {line}: face index {i} is out of range ({} vertices)",
                            self.vertices
                        ),
                    ));
                }
                face.push(i as u32);
            }
            if face.len() as u64 != n {
                return Err(IoError::invalid(
                    path,
                    format!(
                        "line {line}: the face declares {n} vertices but lists {}",
                        face.len()
                    ),
                ));
            }
            // Remaining tokens are the face colour.
            faces.push(&face);
        }
        if (faces.len() as u64) < self.faces {
            return Err(IoError::truncated(
                path,
                format!(
                    "the header declares {} faces but the file holds {}",
                    self.faces,
                    faces.len()
                ),
            ));
        }
        let unterminated = self.unterminated && raw.is_empty();
        Ok(Extras {
            faces: (self.faces > 0).then_some(faces),
            trailer: Trailer::Off(OffTrailer {
                raw,
                faces: self.faces,
                unterminated,
            }),
        })
    }
}

/// Streaming OFF writer.
pub struct OffSink {
    out: LineSink,
    schema: Schema,
    coords: [ScalarType; 3],
    /// Fields written after x, y, z (those of an OFF source; none for other layouts).
    fields: Vec<usize>,
    /// Face count written in the header.
    faces: u64,
    tally: Tally,
    line: Vec<u8>,
}

impl OffSink {
    /// Creates a sink that writes `count` points laid out like `like`, and writes the header; the
    /// face count is `like.faces` (0 without faces).
    ///
    /// # Errors
    /// The directory is not writable.
    pub fn create(path: &Path, like: &SourceInfo, count: u64) -> Result<OffSink, IoError> {
        OffSink::new(AtomicFile::create(path)?, like, count)
    }

    /// [`OffSink::create`] writing to `file` (a file, a stream or memory).
    ///
    /// # Errors
    /// Write failures.
    pub fn new(file: AtomicFile, like: &SourceInfo, count: u64) -> Result<OffSink, IoError> {
        let schema = like.schema.clone();
        let nf = like.faces.unwrap_or(0);
        let fields;
        let out = match &like.meta {
            Meta::Off(m) => {
                fields = extra_fields(&schema);
                let mut out = LineSink::new(file, m.eol);
                let mut counts = format!("{count} {nf}");
                if let Some(e) = &m.edges {
                    counts.push(' ');
                    counts.push_str(e);
                }
                out.raw(&m.before_keyword)?;
                if m.inline_counts {
                    out.line(format!("{} {counts}", m.keyword).as_bytes())?;
                } else {
                    out.line(m.keyword.as_bytes())?;
                }
                out.raw(&m.before_counts)?;
                if !m.inline_counts {
                    out.line(counts.as_bytes())?;
                }
                out.raw(&m.before_vertices)?;
                out
            }
            _ => {
                fields = Vec::new();
                let mut out = LineSink::new(file, LineEnding::Lf);
                out.line(b"OFF")?;
                out.line(format!("{count} {nf} 0").as_bytes())?;
                out
            }
        };
        Ok(OffSink {
            out,
            coords: coord_types(&schema),
            schema,
            fields,
            faces: nf,
            tally: Tally::new(count),
            line: Vec::new(),
        })
    }
}

impl Sink for OffSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        check_batch(self.out.path(), &self.schema, batch)?;
        self.tally.add(self.out.path(), batch.len())?;
        for (i, p) in batch.positions.iter().enumerate() {
            let rec = batch.record(i);
            self.line.clear();
            for (k, v) in [p.x, p.y, p.z].into_iter().enumerate() {
                if k > 0 {
                    self.line.push(b' ');
                }
                push_value(&mut self.line, self.coords[k], v);
            }
            for &f in &self.fields {
                self.line.push(b' ');
                push_value(
                    &mut self.line,
                    self.schema.fields[f].ty,
                    self.schema.get_f64(rec, f),
                );
            }
            self.out.line(&self.line)?;
        }
        Ok(())
    }

    fn finish(mut self: Box<Self>, extras: &Extras) -> Result<(), IoError> {
        self.tally.check(self.out.path())?;
        let path = self.out.path().to_path_buf();
        let nf = self.faces;
        let mismatch = |got: u64| {
            IoError::invalid(
                &path,
                format!("the header announces {nf} faces but {got} were given"),
            )
        };
        if let Trailer::Off(t) = &extras.trailer {
            if t.faces != nf {
                return Err(mismatch(t.faces));
            }
            self.out.raw(&t.raw)?;
            return self.out.finish(t.unterminated);
        }
        let empty = Faces::new();
        let faces = extras.faces.as_ref().unwrap_or(&empty);
        if faces.len() as u64 != nf {
            return Err(mismatch(faces.len() as u64));
        }
        let count = self.tally.written();
        if faces.min_vertex_count() as u64 > count {
            return Err(IoError::invalid(
                &path,
                format!(
                    "a face references vertex {} but only {count} are written",
                    faces.min_vertex_count() - 1
                ),
            ));
        }
        for f in faces.iter() {
            self.line.clear();
            self.line.extend_from_slice(f.len().to_string().as_bytes());
            for &i in f {
                self.line.push(b' ');
                self.line.extend_from_slice(i.to_string().as_bytes());
            }
            self.out.line(&self.line)?;
        }
        self.out.finish(false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::Cloud;
    use glam::DVec3;

    fn read_str(text: &str) -> Result<Cloud, IoError> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.off");
        std::fs::write(&p, text).unwrap();
        Cloud::read(&p, None)
    }

    fn roundtrip(c: &Cloud) -> String {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("o.off");
        c.write(&p, None).unwrap();
        std::fs::read_to_string(&p).unwrap()
    }

    const QUAD: &str = "OFF\n# a quad\n4 2 5\n\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n\
                        3 0 1 2\n3  0 2 3   255 0 0\n# end\n";

    #[test]
    fn reads_and_roundtrips_with_comments() {
        let c = read_str(QUAD).unwrap();
        assert_eq!(c.len(), 4);
        let f = c.faces().unwrap();
        assert_eq!(f.len(), 2);
        assert_eq!(f.face(1), &[0, 2, 3]);
        assert_eq!(roundtrip(&c), QUAD);
    }

    #[test]
    fn coff_inline_counts_and_moved_positions() {
        let text = "COFF 3 1 0\r\n0 0 0 255 0 0 255\r\n1 0 0 0 255 0 255\r\n0 1 0 0 0 255 255\r\n3 0 1 2\r\n";
        let mut c = read_str(text).unwrap();
        let names: Vec<_> = c
            .info
            .schema
            .fields
            .iter()
            .map(|f| f.name.as_str())
            .collect();
        assert_eq!(names, ["x", "y", "z", "r", "g", "b", "a"]);
        assert_eq!(roundtrip(&c), text);
        c.positions[2] = DVec3::new(0.5, 1.25, -2.0);
        assert_eq!(
            roundtrip(&c),
            text.replace("0 1 0 0 0 255 255", "0.5 1.25 -2 0 0 255 255")
        );
        let c = read_str("NOFF\n1 0\n0 0 0 0 0 1").unwrap();
        assert_eq!(c.info.schema.fields[5].name, "nz");
        assert_eq!(roundtrip(&c), "NOFF\n1 0\n0 0 0 0 0 1");
    }

    #[test]
    fn truncated_vertices_and_faces() {
        let e = read_str("OFF\n3 1 0\n0 0 0\n1 0 0\n").unwrap_err();
        assert!(matches!(e, IoError::Truncated { .. }), "{e}");
        let e = read_str("OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n").unwrap_err();
        assert!(matches!(e, IoError::Truncated { .. }), "{e}");
        let e = read_str("OFF\n3\n").unwrap_err();
        assert!(matches!(e, IoError::Header { .. }), "{e}");
    }

    #[test]
    fn bad_faces_and_numbers() {
        let e = read_str("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n").unwrap_err();
        assert!(matches!(e, IoError::Invalid { .. }));
        assert!(
            e.to_string()
                .contains("line 6: face index 3 is out of range"),
            "{e}"
        );
        let e = read_str("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n4 0 1 2\n").unwrap_err();
        assert!(e.to_string().contains("line 6"), "{e}");
        let e = read_str("OFF\n3 1 0\n0 0 0\n1 z 0\n0 1 0\n3 0 1 2\n").unwrap_err();
        assert!(e.to_string().contains("line 4: bad number `z`"), "{e}");
        let e = read_str("").unwrap_err();
        assert!(matches!(e, IoError::Header { .. }), "{e}");
        assert!(matches!(
            read_str("4OFF\n1 0 0\n").unwrap_err(),
            IoError::Unsupported { .. }
        ));
        assert!(matches!(
            read_str("PLY\n1 0 0\n").unwrap_err(),
            IoError::Header { .. }
        ));
    }

    #[test]
    fn generated_mesh_and_face_count_check() {
        let mut c = Cloud::generated(
            vec![DVec3::ZERO, DVec3::X, DVec3::Y],
            Some(Faces::from_triangles(&[[0, 1, 2]])),
            ScalarType::F32,
        );
        assert_eq!(roundtrip(&c), "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
        c.extras.faces = None;
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.off");
        assert!(c.write(&p, None).is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
