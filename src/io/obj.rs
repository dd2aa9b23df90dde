//! Wavefront OBJ meshes (`.obj`).
//!
//! # Brief overview
//!
//! OBJ is a mesh format whose faces may come before, between or after the vertices, so
//! [`ObjSource::open`] reads and parses the **whole file at open**; the points are then served in
//! batches from memory. The writer streams.
//!
//! * `v x y z [w]` and `v x y z r g b` lines become points: x, y, z and every further column are
//!   `F64` fields of the record (named `w`, or `r g b`, else `c3`, `c4`, …). When lines differ in
//!   their number of columns the record has the most, the missing values are NaN and a sink of
//!   the same file leaves them out again.
//! * `f` lines in all their forms (`v`, `v/vt`, `v/vt/vn`, `v//vn`, negative = relative indices,
//!   polygons) become [`Faces`] (0-based).
//! * Every other line (`vn`, `vt`, `g`, `o`, `s`, `usemtl`, `mtllib`, `l`, `p`, comments, blank
//!   lines) and the `f` lines themselves are kept byte for byte, in order:
//!
//! ```text
//!  # exported by …          ObjMeta::header        (lines before the first `v`)
//!  v 1 2 3                  point 0  ┐
//!  vn 0 0 1                 ObjRun { after: 1 }    (lines that follow point 0)
//!  v 4 5 6                  point 1  ┘
//!  f 1 2 3                  ObjRun { after: 2 }    (lines after the last point: the trailer)
//! ```
//!
//! A sink created like an OBJ source writes the header, then the `v` lines re-formatted (shortest
//! round-trip text, the file's own line terminator) with the runs put back between them, so an
//! unchanged write reproduces the file line for line. Runs that fall between vertices are known
//! only at [`Sink::finish`], so the vertex lines from the first such run on are held in memory
//! until then. A sink of any other layout writes `v x y z` lines and then `f` lines (1-based) from
//! [`Extras::faces`]. OBJ is a mesh format: [`create_with`](super::create_with) refuses
//! [`SinkOptions::noise_flag`](super::SinkOptions::noise_flag) ("outlier flags apply to point
//! clouds").

use std::io::Read;
use std::path::Path;

use glam::DVec3;

use super::lines::{
    LineEnding, LineSink, coord_types, default_names, extra_fields, f64_schema, parse_f64,
    push_value, show, split_eol, strip_comment, tokens,
};
use super::tally::{Tally, check_batch};
use super::{AtomicFile, Extras, Format, Input, IoError, Meta, Sink, Source, SourceInfo, Trailer};
use crate::points::{Faces, PointBatch, ScalarType, Schema};

/// OBJ header information a sink reproduces.
#[derive(Debug, Clone, Default)]
pub struct ObjMeta {
    /// Raw lines before the first `v` line, with their terminators.
    pub header: Vec<u8>,
    /// Number of `v` lines before the first non-vertex line that follows a vertex (all of them
    /// when the vertices form one block); a sink writes these directly.
    pub streamed: u64,
    /// Line terminator of the `v` lines.
    pub eol: LineEnding,
    /// The `v` lines differ in their number of columns.
    pub ragged: bool,
}

/// Consecutive non-vertex lines of an OBJ file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ObjRun {
    /// Number of `v` lines before the run.
    pub after: u64,
    /// The raw lines, with their terminators.
    pub text: Vec<u8>,
}

/// OBJ content besides the points: every line after the first `v` line that is not a `v` line.
#[derive(Debug, Clone, Default)]
pub struct ObjTrailer {
    /// The runs, in file order.
    pub runs: Vec<ObjRun>,
    /// The file ends with a `v` line that has no line terminator.
    pub unterminated: bool,
}

/// OBJ reader: parses the whole file at open, then serves the points in batches.
pub struct ObjSource {
    info: SourceInfo,
    positions: Vec<DVec3>,
    records: Vec<u8>,
    next: usize,
    extras: Extras,
}

/// Resolves one `f` vertex reference (`7`, `7/2`, `7/2/5`, `7//5`, `-1`) to a 0-based index.
fn face_index(path: &Path, line: u64, tok: &[u8], defined: usize) -> Result<i64, IoError> {
    let v = tok.split(|&c| c == b'/').next().unwrap_or_default();
    let i: i64 = std::str::from_utf8(v)
        .ok()
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| {
            IoError::invalid(
                path,
                format!("line {line}: bad vertex index `{}` in a face", show(tok)),
            )
        })?;
    match i {
        0 => Err(IoError::invalid(
            path,
            format!("line {line}: face index 0 (OBJ indices start at 1)"),
        )),
        i if i < 0 => {
            let k = defined as i64 + i;
            if k < 0 {
                return Err(IoError::invalid(
                    path,
                    format!(
                        "line {line}: relative face index {i} is out of range ({defined} vertices \
                         defined so far)"
                    ),
                ));
            }
            Ok(k)
        }
        i => Ok(i - 1),
    }
}

impl ObjSource {
    /// Reads and parses a whole OBJ file.
    ///
    /// # Errors
    /// Unreadable file, no vertex, a malformed number, a face index that is 0 or out of range.
    pub fn open(path: &Path) -> Result<ObjSource, IoError> {
        ObjSource::new(Input::from_path(path)?)
    }

    /// [`ObjSource::open`] on any [`Input`].
    ///
    /// # Errors
    /// As [`ObjSource::open`].
    pub fn new(mut input: Input) -> Result<ObjSource, IoError> {
        let owned = input.name().to_path_buf();
        let path = owned.as_path();
        let mut data = Vec::new();
        input
            .read_to_end(&mut data)
            .map_err(|e| IoError::io(path, e))?;
        let mut header = Vec::new();
        let mut runs: Vec<ObjRun> = Vec::new();
        let mut eol = None;
        let mut unterminated = false;
        // Vertex values, flat, and the number of columns of each vertex.
        let mut values: Vec<f64> = Vec::new();
        let mut cols: Vec<u8> = Vec::new();
        let mut faces = Faces::new();
        let mut has_faces = false;
        let mut face: Vec<u32> = Vec::new();
        // Largest forward face index and the line that uses it.
        let mut max_index: Option<(i64, u64)> = None;
        for (k, raw) in data.split_inclusive(|&c| c == b'\n').enumerate() {
            let line = k as u64 + 1;
            let (content, terminator) = split_eol(raw);
            let body = strip_comment(content);
            let mut toks = tokens(body);
            let keyword = toks.next().unwrap_or_default();
            if keyword == b"v" {
                let start = values.len();
                for tok in toks {
                    let v = parse_f64(tok).ok_or_else(|| {
                        IoError::invalid(
                            path,
                            format!("line {line}: bad number `{}` in a `v` line", show(tok)),
                        )
                    })?;
                    values.push(v);
                }
                let n = values.len() - start;
                if !(3..=u8::MAX as usize).contains(&n) {
                    return Err(IoError::invalid(
                        path,
                        format!("line {line}: a `v` line needs 3 to 255 numbers, found {n}"),
                    ));
                }
                cols.push(n as u8);
                if eol.is_none() {
                    eol = LineEnding::of(raw);
                }
                unterminated = terminator.is_empty();
                continue;
            }
            if keyword == b"f" {
                face.clear();
                for tok in toks {
                    let i = face_index(path, line, tok, cols.len())?;
                    let i = u32::try_from(i).map_err(|_| {
                        IoError::invalid(
                            path,
                            format!("line {line}: face index {} is too large", i + 1),
                        )
                    })?;
                    if max_index.is_none_or(|(m, _)| i as i64 > m) {
                        max_index = Some((i as i64, line));
                    }
                    face.push(i);
                }
                if face.is_empty() {
                    return Err(IoError::invalid(
                        path,
                        format!("line {line}: face without vertices"),
                    ));
                }
                faces.push(&face);
                has_faces = true;
            }
            let after = cols.len() as u64;
            if after == 0 {
                header.extend_from_slice(raw);
            } else {
                match runs.last_mut() {
                    Some(r) if r.after == after => r.text.extend_from_slice(raw),
                    _ => runs.push(ObjRun {
                        after,
                        text: raw.to_vec(),
                    }),
                }
            }
            unterminated = false;
        }
        let n = cols.len();
        if n == 0 {
            let what = if data.is_empty() {
                "empty file"
            } else {
                "no vertex (`v` line)"
            };
            return Err(IoError::invalid(path, what));
        }
        if let Some((m, line)) = max_index
            && m as usize >= n
        {
            return Err(IoError::invalid(
                path,
                format!(
                    "line {line}: face index {} is out of range ({n} vertices)",
                    m + 1
                ),
            ));
        }
        let ncols = cols.iter().copied().max().unwrap_or(3) as usize;
        let ragged = cols.iter().any(|&c| c as usize != ncols);
        let names = default_names(
            ncols,
            match ncols {
                4 => &["w"],
                6 => &["r", "g", "b"],
                _ => &[],
            },
        );
        let schema = f64_schema(path, &names)?;
        let mut positions = Vec::with_capacity(n);
        let mut records = Vec::with_capacity(n * schema.record_len);
        let mut at = 0;
        for &c in &cols {
            let v = &values[at..at + c as usize];
            at += c as usize;
            positions.push(DVec3::new(v[0], v[1], v[2]));
            for j in 0..ncols {
                let x = v.get(j).copied().unwrap_or(f64::NAN);
                records.extend_from_slice(&x.to_le_bytes());
            }
        }
        let streamed = runs.first().map_or(n as u64, |r| r.after);
        let meta = ObjMeta {
            header,
            streamed,
            eol: eol.unwrap_or_default(),
            ragged,
        };
        let nfaces = faces.len() as u64;
        Ok(ObjSource {
            info: SourceInfo {
                path: path.to_path_buf(),
                format: Format::Obj,
                schema,
                len: Some(n as u64),
                faces: has_faces.then_some(nfaces),
                meta: Meta::Obj(meta),
            },
            positions,
            records,
            next: 0,
            extras: Extras {
                faces: has_faces.then_some(faces),
                trailer: Trailer::Obj(ObjTrailer { runs, unterminated }),
            },
        })
    }
}

impl Source for ObjSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        let rl = self.info.schema.record_len;
        batch.clear(self.next as u64);
        batch.record_len = rl;
        let end = self.next.saturating_add(max).min(self.positions.len());
        batch
            .positions
            .extend_from_slice(&self.positions[self.next..end]);
        batch
            .records
            .extend_from_slice(&self.records[self.next * rl..end * rl]);
        let n = end - self.next;
        self.next = end;
        Ok(n)
    }

    fn finish(self: Box<Self>) -> Result<Extras, IoError> {
        Ok(self.extras)
    }
}

/// Streaming OBJ writer (see the module documentation for what it reproduces).
pub struct ObjSink {
    out: LineSink,
    schema: Schema,
    coords: [ScalarType; 3],
    /// Fields written after x, y, z (those of an OBJ source; none for other layouts).
    fields: Vec<usize>,
    ragged: bool,
    /// Vertices written directly; later ones are held until `finish`.
    streamed: u64,
    held: Vec<u8>,
    held_ends: Vec<usize>,
    tally: Tally,
    line: Vec<u8>,
}

impl ObjSink {
    /// Creates a sink that writes `count` points laid out like `like`.
    ///
    /// # Errors
    /// The directory is not writable.
    pub fn create(path: &Path, like: &SourceInfo, count: u64) -> Result<ObjSink, IoError> {
        ObjSink::new(AtomicFile::create(path)?, like, count)
    }

    /// [`ObjSink::create`] writing to `file` (a file, a stream or memory).
    ///
    /// # Errors
    /// Write failures.
    pub fn new(file: AtomicFile, like: &SourceInfo, count: u64) -> Result<ObjSink, IoError> {
        let schema = like.schema.clone();
        let (meta, fields) = match &like.meta {
            Meta::Obj(m) => (Some(m), extra_fields(&schema)),
            _ => (None, Vec::new()),
        };
        let mut out = LineSink::new(file, meta.map_or(LineEnding::Lf, |m| m.eol));
        if let Some(m) = meta {
            out.raw(&m.header)?;
        }
        Ok(ObjSink {
            out,
            coords: coord_types(&schema),
            schema,
            fields,
            ragged: meta.is_some_and(|m| m.ragged),
            streamed: meta.map_or(u64::MAX, |m| m.streamed),
            held: Vec::new(),
            held_ends: Vec::new(),
            tally: Tally::new(count),
            line: Vec::new(),
        })
    }

    /// Formats the `v` line of one point into `self.line`.
    fn format_vertex(&mut self, p: DVec3, rec: &[u8]) {
        self.line.clear();
        self.line.push(b'v');
        for (k, v) in [p.x, p.y, p.z].into_iter().enumerate() {
            self.line.push(b' ');
            push_value(&mut self.line, self.coords[k], v);
        }
        let mut keep = self.fields.len();
        if self.ragged {
            // Columns the line did not have were read as NaN.
            while keep > 0 && self.schema.get_f64(rec, self.fields[keep - 1]).is_nan() {
                keep -= 1;
            }
        }
        for &f in &self.fields[..keep] {
            self.line.push(b' ');
            push_value(
                &mut self.line,
                self.schema.fields[f].ty,
                self.schema.get_f64(rec, f),
            );
        }
    }
}

impl Sink for ObjSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        check_batch(self.out.path(), &self.schema, batch)?;
        let first = self.tally.written();
        self.tally.add(self.out.path(), batch.len())?;
        for (i, &p) in batch.positions.iter().enumerate() {
            self.format_vertex(p, batch.record(i));
            if first + (i as u64) < self.streamed {
                self.out.line(&self.line)?;
            } else {
                self.held.extend_from_slice(&self.line);
                self.held_ends.push(self.held.len());
            }
        }
        Ok(())
    }

    fn finish(mut self: Box<Self>, extras: &Extras) -> Result<(), IoError> {
        self.tally.check(self.out.path())?;
        let no_runs = Vec::new();
        let (runs, unterminated) = match &extras.trailer {
            Trailer::Obj(t) => (&t.runs, t.unterminated),
            _ => (&no_runs, false),
        };
        let mut r = 0;
        let mut start = 0;
        for (k, &end) in self.held_ends.iter().enumerate() {
            let index = self.streamed + k as u64;
            while r < runs.len() && runs[r].after <= index {
                self.out.raw(&runs[r].text)?;
                r += 1;
            }
            self.out.line(&self.held[start..end])?;
            start = end;
        }
        for run in &runs[r..] {
            self.out.raw(&run.text)?;
        }
        if !matches!(extras.trailer, Trailer::Obj(_))
            && let Some(faces) = &extras.faces
        {
            let count = self.tally.written();
            if faces.min_vertex_count() as u64 > count {
                return Err(IoError::invalid(
                    self.out.path(),
                    format!(
                        "a face references vertex {} but only {count} are written",
                        faces.min_vertex_count() - 1
                    ),
                ));
            }
            for f in faces.iter() {
                self.line.clear();
                self.line.push(b'f');
                for &i in f {
                    self.line.push(b' ');
                    self.line
                        .extend_from_slice((i as u64 + 1).to_string().as_bytes());
                }
                self.out.line(&self.line)?;
            }
        }
        self.out.finish(unterminated)
    }
}

/// The `vn` normals of an OBJ file: their values in file order, and for every face corner (in
/// the order of [`Extras::faces`]) the `vn` it references, if any.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ObjNormals {
    /// One value per `vn` line.
    pub normals: Vec<DVec3>,
    /// Per face corner, the 0-based `vn` index (`v//vn`, `v/vt/vn`), or `None`.
    pub corners: Vec<Option<usize>>,
}

/// Lines of `text`, each with its terminator.
fn lines_of(text: &[u8]) -> impl Iterator<Item = &[u8]> {
    text.split_inclusive(|&b| b == b'\n')
}

/// The keyword of an OBJ line and its remaining tokens.
fn keyword_of(line: &[u8]) -> (&[u8], impl Iterator<Item = &[u8]>) {
    let (content, _) = split_eol(line);
    let mut toks = tokens(strip_comment(content));
    let kw = toks.next().unwrap_or_default();
    (kw, toks)
}

/// Reads the `vn` lines and the corners' `vn` references of an OBJ file (its header and runs,
/// in file order). Malformed `vn` values read as NaN.
pub fn obj_normals(meta: &ObjMeta, trailer: &ObjTrailer) -> ObjNormals {
    let mut out = ObjNormals::default();
    let texts = std::iter::once(meta.header.as_slice())
        .chain(trailer.runs.iter().map(|r| r.text.as_slice()));
    for text in texts {
        for line in lines_of(text) {
            let (kw, toks) = keyword_of(line);
            match kw {
                b"vn" => {
                    let v: Vec<f64> = toks
                        .take(3)
                        .map(|t| parse_f64(t).unwrap_or(f64::NAN))
                        .collect();
                    let g = |i: usize| v.get(i).copied().unwrap_or(f64::NAN);
                    out.normals.push(DVec3::new(g(0), g(1), g(2)));
                }
                b"f" => {
                    for tok in toks {
                        let vn = tok
                            .split(|&c| c == b'/')
                            .nth(2)
                            .and_then(|t| std::str::from_utf8(t).ok())
                            .and_then(|t| t.parse::<i64>().ok())
                            .and_then(|i| {
                                let n = out.normals.len() as i64;
                                let k = if i < 0 { n + i } else { i - 1 };
                                usize::try_from(k).ok()
                            });
                        out.corners.push(vn);
                    }
                }
                _ => {}
            }
        }
    }
    out
}

/// Replaces the values of the `vn` lines (header and runs, in file order) by `normals`, one per
/// line; every other byte stays.
pub fn set_obj_normals(meta: &mut ObjMeta, trailer: &mut ObjTrailer, normals: &[DVec3]) {
    let mut next = normals.iter();
    let mut rewrite = |text: &mut Vec<u8>| {
        let mut out = Vec::with_capacity(text.len());
        for line in lines_of(text) {
            let (kw, _) = keyword_of(line);
            match (kw == b"vn").then(|| next.next()).flatten() {
                Some(n) => {
                    let (_, eol) = split_eol(line);
                    out.extend_from_slice(format!("vn {} {} {}", n.x, n.y, n.z).as_bytes());
                    out.extend_from_slice(eol);
                }
                None => out.extend_from_slice(line),
            }
        }
        *text = out;
    };
    rewrite(&mut meta.header);
    for r in &mut trailer.runs {
        rewrite(&mut r.text);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::Cloud;

    fn read_str(text: &str) -> Result<Cloud, IoError> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.obj");
        std::fs::write(&p, text).unwrap();
        Cloud::read(&p, None)
    }

    fn roundtrip(c: &Cloud) -> String {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("o.obj");
        c.write(&p, None).unwrap();
        std::fs::read_to_string(&p).unwrap()
    }

    #[test]
    fn face_forms_and_relative_indices() {
        let c = read_str(
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n\
             f 1 2 3\nf 1/1 2/2 3/3\nf 1/1/1 2/2/2 3/3/3\nf 1//1 2//2 3//3\nf -4 -3 -2 -1\n",
        )
        .unwrap();
        let f = c.faces().unwrap();
        assert_eq!(f.len(), 5);
        for i in 0..4 {
            assert_eq!(f.face(i), &[0, 1, 2]);
        }
        assert_eq!(f.face(4), &[0, 1, 2, 3]);
        assert_eq!(c.info.faces, Some(5));
    }

    #[test]
    fn interleaved_lines_roundtrip() {
        let text = "# head\nmtllib a.mtl\nv 1 2 3\nvn 0 0 1\nv 4 5 6\nvt 0.5 0.5\n\
                    v 7 8 9.5\ng part\nusemtl m\ns off\nf 1/1/1 2/1/1 3/1/1\nl 1 2\np 3\n\n# end";
        let c = read_str(text).unwrap();
        assert_eq!(c.len(), 3);
        assert_eq!(c.info.faces, Some(1));
        let Meta::Obj(m) = &c.info.meta else { panic!() };
        assert_eq!(m.streamed, 1);
        assert_eq!(roundtrip(&c), text);
    }

    #[test]
    fn colour_and_ragged_columns() {
        let text = "v 1 2 3 0.5 0.25 1\r\nv 4 5 6 1 0 0\r\nf 1 2 2\r\n";
        let c = read_str(text).unwrap();
        let names: Vec<_> = c.info.schema.fields.iter().map(|f| &f.name).collect();
        assert_eq!(names, ["x", "y", "z", "r", "g", "b"]);
        assert_eq!(roundtrip(&c), text);
        let text = "v 1 2 3\nv 4 5 6 0.5\nv 1 1 1\n";
        let c = read_str(text).unwrap();
        assert_eq!(c.info.schema.fields[3].name, "w");
        assert_eq!(roundtrip(&c), text);
    }

    #[test]
    fn moved_positions_change_only_coordinates() {
        let text = "# c\nv 1 2 3 1\nv 4 5 6 1\nv 7 8 9 1\nf 1 2 3\n";
        let mut c = read_str(text).unwrap();
        c.positions[1] = DVec3::new(0.1, -0.25, 1e-3);
        assert_eq!(
            roundtrip(&c),
            "# c\nv 1 2 3 1\nv 0.1 -0.25 0.001 1\nv 7 8 9 1\nf 1 2 3\n"
        );
    }

    #[test]
    fn bad_input() {
        let e = read_str("v 1 2 3\nv 1 2 3\nv 1 2 3\nf 1 2 4\n").unwrap_err();
        assert!(
            e.to_string()
                .contains("line 4: face index 4 is out of range"),
            "{e}"
        );
        let e = read_str("v 1 2 3\nf 0 1 1\n").unwrap_err();
        assert!(e.to_string().contains("line 2: face index 0"), "{e}");
        let e = read_str("v 1 2 3\nf -2 1 1\n").unwrap_err();
        assert!(e.to_string().contains("line 2"), "{e}");
        let e = read_str("v 1 2 3\nv 1 2e 3\n").unwrap_err();
        assert!(e.to_string().contains("line 2: bad number `2e`"), "{e}");
        let e = read_str("v 1 2 3\nf 1 a 1\n").unwrap_err();
        assert!(
            e.to_string().contains("line 2: bad vertex index `a`"),
            "{e}"
        );
        let e = read_str("v 1 2\n").unwrap_err();
        assert!(e.to_string().contains("line 1"), "{e}");
        assert!(matches!(read_str("").unwrap_err(), IoError::Invalid { .. }));
        assert!(read_str("# nothing\n").is_err());
    }

    #[test]
    fn generated_mesh_writes_v_then_f() {
        let c = Cloud::generated(
            vec![DVec3::ZERO, DVec3::X, DVec3::new(0.0, 0.5, 0.0)],
            Some(Faces::from_triangles(&[[0, 1, 2]])),
            ScalarType::F64,
        );
        assert_eq!(roundtrip(&c), "v 0 0 0\nv 1 0 0\nv 0 0.5 0\nf 1 2 3\n");
    }
}
