//! Stanford PLY backend: a streaming, lossless reader and writer.
//!
//! # Brief overview
//!
//! * [`PlySource::open`] reads the header, requires a `vertex` element with scalar `x`, `y` and `z`,
//!   and describes the vertex record as a packed [`Schema`] in the file's own property types and
//!   byte order (ascii values are stored little-endian). The header text is collected here and
//!   validated by `ply-rs-bw`'s header parser; the raw lines are kept so that a writer can
//!   reproduce them byte for byte.
//!   Elements declared *before* `vertex` are read at once and kept in [`PlyMeta`].
//! * [`Source::read_batch`] delivers vertices. Binary files take a fast path: one `read_exact` of
//!   `n × record_len` bytes straight into the batch, then positions decoded at fixed offsets.
//!   Ascii lines are parsed token by token into the same binary records.
//! * [`Source::finish`] reads every element after `vertex`: the `face` element becomes [`Faces`]
//!   (indices checked against the vertex count), and every element's bytes — plus any bytes after
//!   the last element — are kept verbatim in [`PlyTrailer`].
//! * [`PlySink::create`] reproduces a PLY source's header byte for byte (only the vertex count, and
//!   the face count when it changed, are rewritten) or, for any other origin, writes a
//!   `binary_little_endian` header from the schema, with integer x, y, z (LAS's scaled `I32`)
//!   promoted to `double` so that coordinates are not rounded to whole units.
//!   [`Sink::write_batch`] copies the record slab and patches x, y, z in place; [`Sink::finish`]
//!   writes the trailer verbatim when it matches, or the faces generically, and only then moves
//!   the file into place.
//! * **Noise flag.** [`PlySink::create_with`] with [`SinkOptions::noise_flag`] declares one more
//!   vertex property, `property uchar noise`, after the vertex element's last property line (the
//!   rest of the header is kept, for PLY and foreign sources alike) and writes 1 for points whose
//!   [`PointBatch::flags`] have [`FLAG_NOISE`], else 0, in every encoding. A vertex element that
//!   already has a `noise` property (a re-run) keeps its header; that property is overwritten.
//!
//! ```text
//!  ply / format / comment / obj_info / element … / end_header      PlyMeta (raw lines)
//!  [elements before vertex]                                         PlyMeta (raw bytes)
//!  vertex 0 … vertex n-1                                            PointBatch records
//!  face 0 … , other elements …                                      PlyTrailer (raw) + Faces
//!  [trailing bytes]                                                 PlyTrailer (raw)
//! ```
//!
//! Reading a file and writing it back unchanged (without the noise flag) yields a byte-identical
//! file for the binary encodings. For ascii every value is identical, and so are the bytes
//! whenever the file prints its numbers in shortest `%g`-like form with one separator style (true
//! of the Stanford scans): floats are printed with the fewest digits that round-trip in their
//! declared type, line terminators and a trailing space on vertex lines follow the source, and
//! every other line (header, faces, other elements) is copied verbatim.

mod body;
mod header;

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

pub use header::{PlyElement, PlyEncoding, PlyProperty, PlyType};

use self::body::{FaceTarget, PosCodec, Walker, eof, faces_digest, format_ascii, parse_ascii};
use self::header::Header;
use super::{
    AtomicFile, Extras, IoError, Meta, NOISE_FIELD, Sink, SinkOptions, Source, SourceInfo, Trailer,
    foreign_field_type, open_file, regular_len,
};
use crate::points::{FLAG_NOISE, Faces, PointBatch, ScalarType, Schema, write_scalar};

/// Read buffer size; binary batches larger than this bypass the buffer.
const READ_BUF: usize = 1 << 16;

/// PLY header information a sink reproduces: the raw header, the element model and the raw bytes
/// of any element stored before `vertex`.
#[derive(Debug, Clone, Default)]
pub struct PlyMeta {
    header: Header,
    vertex: usize,
    pre_vertex: Vec<u8>,
    ascii_trailing_space: bool,
}

impl PlyMeta {
    /// Payload encoding.
    pub fn encoding(&self) -> PlyEncoding {
        self.header.encoding
    }

    /// All declared elements in file order (`vertex` included).
    pub fn elements(&self) -> &[PlyElement] {
        &self.header.elements
    }

    /// The `vertex` element (`None` only for a default-constructed meta).
    pub fn vertex_element(&self) -> Option<&PlyElement> {
        self.header
            .elements
            .get(self.vertex)
            .filter(|e| e.name == "vertex")
    }

    /// Text of the `comment` lines.
    pub fn comments(&self) -> &[String] {
        &self.header.comments
    }

    /// Text of the `obj_info` lines.
    pub fn obj_info(&self) -> &[String] {
        &self.header.obj_info
    }

    /// The header exactly as read (`ply` to `end_header`, line terminators included).
    pub fn header_bytes(&self) -> Vec<u8> {
        self.header.lines.concat()
    }

    /// Raw bytes of the elements declared before `vertex` (usually empty).
    pub fn pre_vertex_bytes(&self) -> &[u8] {
        &self.pre_vertex
    }
}

/// The PLY content after the vertices, as raw bytes per element plus trailing bytes.
#[derive(Debug, Clone, Default)]
pub struct PlyTrailer {
    encoding: PlyEncoding,
    elements: Vec<PlyElement>,
    data: Vec<u8>,
    ends: Vec<usize>,
    faces_digest: Option<u64>,
}

impl PlyTrailer {
    /// Encoding of the bytes.
    pub fn encoding(&self) -> PlyEncoding {
        self.encoding
    }

    /// The elements after `vertex`, in file order.
    pub fn elements(&self) -> &[PlyElement] {
        &self.elements
    }

    /// Raw bytes of element `i` of [`PlyTrailer::elements`] (ascii: its lines); `None` when
    /// there is no such element.
    pub fn element_bytes(&self, i: usize) -> Option<&[u8]> {
        let end = *self.ends.get(i)?;
        let start = if i == 0 { 0 } else { self.ends[i - 1] };
        self.data.get(start..end)
    }

    /// Bytes after the last element (usually empty).
    pub fn trailing_bytes(&self) -> &[u8] {
        &self.data[self.ends.last().copied().unwrap_or(0)..]
    }
}

/// Streaming PLY reader (ascii, binary little- and big-endian).
pub struct PlySource {
    info: SourceInfo,
    reader: BufReader<File>,
    encoding: PlyEncoding,
    elements: Vec<PlyElement>,
    vertex: usize,
    /// The face element and its index-list property.
    face: Option<(usize, usize)>,
    count: u64,
    read: u64,
    /// Number of the next ascii line (1-based).
    line: u64,
    codec: PosCodec,
    text: Vec<u8>,
    /// Faces of a face element stored before `vertex`.
    early_faces: Option<Faces>,
}

impl PlySource {
    /// Opens `path` and reads its header (and any element stored before `vertex`).
    ///
    /// # Errors
    /// [`IoError::Header`] for a missing or malformed header, a missing `vertex` element or a
    /// missing `x`/`y`/`z`; [`IoError::Unsupported`] for list properties on vertices or non-integer
    /// face indices; [`IoError::Truncated`] when a binary file is shorter than its vertex data.
    pub fn open(path: &Path) -> Result<PlySource, IoError> {
        let file = open_file(path)?;
        let file_len = regular_len(&file);
        let mut reader = BufReader::with_capacity(READ_BUF, file);
        let header = header::read_header(&mut reader, path)?;
        let encoding = header.encoding;

        let names = || {
            let n: Vec<&str> = header.elements.iter().map(|e| e.name.as_str()).collect();
            n.join(", ")
        };
        let vertex = header
            .elements
            .iter()
            .position(|e| e.name == "vertex")
            .ok_or_else(|| {
                IoError::header(path, format!("no `vertex` element (elements: {})", names()))
            })?;
        let vel = &header.elements[vertex];
        let mut fields = Vec::with_capacity(vel.properties.len());
        for p in &vel.properties {
            match p.ty {
                PlyType::Scalar(t) => fields.push((p.name.as_str(), t)),
                PlyType::List { .. } => {
                    return Err(IoError::Unsupported {
                        path: path.to_path_buf(),
                        detail: format!(
                            "the vertex element has a list property `{}`; per-vertex lists are \
                             not supported",
                            p.name
                        ),
                    });
                }
            }
        }
        for axis in ["x", "y", "z"] {
            if !fields.iter().any(|f| f.0 == axis) {
                let have: Vec<&str> = fields.iter().map(|f| f.0).collect();
                return Err(IoError::header(
                    path,
                    format!(
                        "the vertex element has no property `{axis}` (it has: {})",
                        have.join(", ")
                    ),
                ));
            }
        }
        let schema = Schema::packed(&fields, encoding.record_endian())
            .map_err(|e| IoError::header(path, e.to_string()))?;

        let face = header
            .elements
            .iter()
            .position(|e| e.name == "face")
            .and_then(|i| header.elements[i].face_list().map(|k| (i, k)));
        if let Some((i, k)) = face
            && let PlyType::List { item, .. } = header.elements[i].properties[k].ty
            && item.is_float()
        {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: format!(
                    "face indices `{}` are of floating-point type {}",
                    header.elements[i].properties[k].name,
                    body::type_name(item)
                ),
            });
        }
        let count = vel.count;

        // Elements before `vertex`: read now, kept raw in the meta.
        let mut line = header.lines.len() as u64 + 1;
        let mut pre_vertex = Vec::new();
        let mut early_faces = None;
        for (i, el) in header.elements[..vertex].iter().enumerate() {
            let mut faces = Faces::new();
            let target = face.filter(|f| f.0 == i).map(|f| FaceTarget {
                list: f.1,
                vertices: count,
                faces: &mut faces,
            });
            let collect = target.is_some();
            Walker {
                r: &mut reader,
                path,
                encoding,
                line: &mut line,
            }
            .element(el, &mut pre_vertex, target)?;
            if collect {
                early_faces = Some(faces);
            }
        }

        // A header that lies about the vertex count is caught before any point is read.
        if let Some(len) = file_len {
            let avail = len.saturating_sub((header.byte_len() + pre_vertex.len()) as u64);
            let rl = schema.record_len as u64;
            if encoding.is_binary() {
                let need = count.saturating_mul(rl);
                if need > avail {
                    return Err(IoError::truncated(
                        path,
                        format!(
                            "header declares {count} vertices ({need} bytes) but only {avail} \
                             bytes follow the header"
                        ),
                    ));
                }
            } else if count > 0 {
                // Every value takes at least one character and one separator.
                let nprops = fields.len() as u64;
                let need = count.saturating_mul(2 * nprops).saturating_sub(1);
                if need > avail {
                    return Err(IoError::truncated(
                        path,
                        format!(
                            "header declares {count} vertices (at least {need} bytes as ascii) \
                             but only {avail} bytes follow the header"
                        ),
                    ));
                }
            }
        }

        // Ascii style: do vertex lines end with a space? (Peeked, not consumed.)
        let ascii_trailing_space = !encoding.is_binary()
            && count > 0
            && reader.fill_buf().is_ok_and(|b| {
                b.iter().position(|&c| c == b'\n').is_some_and(|nl| {
                    let l = b[..nl].strip_suffix(b"\r").unwrap_or(&b[..nl]);
                    l.last() == Some(&b' ')
                })
            });

        let codec = PosCodec::new(&schema);
        let elements = header.elements.clone();
        let info = SourceInfo {
            path: path.to_path_buf(),
            format: super::Format::Ply,
            schema,
            len: Some(count),
            faces: face.map(|(i, _)| elements[i].count),
            meta: Meta::Ply(PlyMeta {
                header,
                vertex,
                pre_vertex,
                ascii_trailing_space,
            }),
        };
        Ok(PlySource {
            info,
            reader,
            encoding,
            elements,
            vertex,
            face,
            count,
            read: 0,
            line,
            codec,
            text: Vec::new(),
            early_faces,
        })
    }

    /// Parses one ascii vertex line into `rec`.
    fn ascii_vertex(&mut self, rec: &mut [u8], index: u64) -> Result<(), IoError> {
        let path = &self.info.path;
        let line = self.line;
        self.text.clear();
        let got = self
            .reader
            .read_until(b'\n', &mut self.text)
            .map_err(|e| IoError::io(path, e))?;
        if got == 0 {
            return Err(IoError::truncated(
                path,
                format!(
                    "the file ends after {index} of {} vertices (line {line})",
                    self.count
                ),
            ));
        }
        self.line += 1;
        let text = std::str::from_utf8(&self.text)
            .map_err(|_| IoError::invalid(path, format!("line {line} is not text")))?;
        let mut toks = text.split_ascii_whitespace();
        let fields = &self.info.schema.fields;
        for (k, f) in fields.iter().enumerate() {
            let Some(tok) = toks.next() else {
                if !self.text.ends_with(b"\n") {
                    return Err(IoError::truncated(
                        path,
                        format!(
                            "the file ends inside vertex {index} of {} (line {line})",
                            self.count
                        ),
                    ));
                }
                return Err(IoError::invalid(
                    path,
                    format!(
                        "line {line}: vertex {index} has {k} values but the header declares {}",
                        fields.len()
                    ),
                ));
            };
            if parse_ascii(tok, f.ty, &mut rec[f.offset..]).is_none() {
                return Err(IoError::invalid(
                    path,
                    format!(
                        "line {line}: `{tok}` is not a valid {} (property `{}` of vertex {index})",
                        body::type_name(f.ty),
                        f.name
                    ),
                ));
            }
        }
        if let Some(extra) = toks.next() {
            return Err(IoError::invalid(
                path,
                format!(
                    "line {line}: unexpected value `{extra}` after the {} properties of vertex \
                     {index}",
                    fields.len()
                ),
            ));
        }
        Ok(())
    }

    /// Skips the vertices nobody read.
    fn skip_vertices(&mut self) -> Result<(), IoError> {
        let left = self.count - self.read;
        if left == 0 {
            return Ok(());
        }
        let path = self.info.path.clone();
        if self.encoding.is_binary() {
            let bytes = left.saturating_mul(self.info.schema.record_len as u64);
            let copied = std::io::copy(&mut (&mut self.reader).take(bytes), &mut std::io::sink())
                .map_err(|e| IoError::io(&path, e))?;
            if copied < bytes {
                return Err(IoError::truncated(
                    &path,
                    "the file ends inside the vertex data",
                ));
            }
        } else {
            for i in self.read..self.count {
                self.text.clear();
                let got = self
                    .reader
                    .read_until(b'\n', &mut self.text)
                    .map_err(|e| IoError::io(&path, e))?;
                if got == 0 {
                    return Err(IoError::truncated(
                        &path,
                        format!("the file ends after {i} of {} vertices", self.count),
                    ));
                }
                self.line += 1;
            }
        }
        self.read = self.count;
        Ok(())
    }
}

impl Source for PlySource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        let rl = self.info.schema.record_len;
        batch.clear(self.read);
        batch.record_len = rl;
        let n = (self.count - self.read).min(max as u64) as usize;
        if n == 0 {
            return Ok(0);
        }
        batch.records.resize(n * rl, 0);
        if self.encoding.is_binary() {
            let (start, count) = (self.read, self.count);
            self.reader
                .read_exact(&mut batch.records)
                .map_err(eof(&self.info.path, || {
                    format!(
                        "the file ends inside vertices {start}..{} (the header declares {count})",
                        start + n as u64
                    )
                }))?;
        } else {
            let mut records = std::mem::take(&mut batch.records);
            let res = records
                .chunks_exact_mut(rl)
                .enumerate()
                .try_for_each(|(i, rec)| self.ascii_vertex(rec, self.read + i as u64));
            batch.records = records;
            res?;
        }
        self.codec
            .decode(&self.info.schema, &batch.records, &mut batch.positions);
        self.read += n as u64;
        Ok(n)
    }

    fn finish(self: Box<Self>) -> Result<Extras, IoError> {
        let mut s = *self;
        s.skip_vertices()?;
        let path = s.info.path.clone();
        let mut data = Vec::new();
        let mut ends = Vec::new();
        let mut faces = s.early_faces.take();
        let mut digest = None;
        for (i, el) in s.elements.iter().enumerate().skip(s.vertex + 1) {
            let mut f = Faces::new();
            let target = s.face.filter(|f| f.0 == i).map(|(_, list)| FaceTarget {
                list,
                vertices: s.count,
                faces: &mut f,
            });
            let collect = target.is_some();
            Walker {
                r: &mut s.reader,
                path: &path,
                encoding: s.encoding,
                line: &mut s.line,
            }
            .element(el, &mut data, target)?;
            ends.push(data.len());
            if collect {
                digest = Some(faces_digest(&f));
                faces = Some(f);
            }
        }
        let start = data.len();
        s.reader
            .read_to_end(&mut data)
            .map_err(|e| IoError::io(&path, e))?;
        if s.vertex + 1 == s.elements.len() {
            more_vertices(&path, &s.elements[s.vertex], s.encoding, &data[start..])?;
        }
        Ok(Extras {
            faces,
            trailer: Trailer::Ply(PlyTrailer {
                encoding: s.encoding,
                elements: s.elements[s.vertex + 1..].to_vec(),
                data,
                ends,
                faces_digest: digest,
            }),
        })
    }
}

/// Refuses bytes after the last element, the vertex one, that hold more vertices: whole ascii
/// lines of as many numbers as a vertex has properties, or binary bytes that are a whole number
/// of vertex records (issue 15: a header declaring 290 vertices of a file holding 300 dropped 10
/// without a word). Other trailing bytes (a comment, padding) are kept verbatim.
fn more_vertices(
    path: &Path,
    vertex: &PlyElement,
    encoding: PlyEncoding,
    trailing: &[u8],
) -> Result<(), IoError> {
    let extra = if encoding.is_binary() {
        match vertex.record_len() {
            Some(rl) if rl > 0 && !trailing.is_empty() && trailing.len().is_multiple_of(rl) => {
                trailing.len() / rl
            }
            _ => 0,
        }
    } else {
        let width = vertex.properties.len();
        let lines: Vec<&[u8]> = trailing
            .split(|&b| b == b'\n')
            .map(<[u8]>::trim_ascii)
            .filter(|l| !l.is_empty())
            .collect();
        let vertex_like = |l: &&[u8]| {
            let words: Vec<&[u8]> = l
                .split(u8::is_ascii_whitespace)
                .filter(|w| !w.is_empty())
                .collect();
            words.len() == width
                && words
                    .iter()
                    .all(|w| std::str::from_utf8(w).is_ok_and(|t| t.parse::<f64>().is_ok()))
        };
        if !lines.is_empty() && lines.iter().all(vertex_like) {
            lines.len()
        } else {
            0
        }
    };
    if extra == 0 {
        return Ok(());
    }
    Err(IoError::header(
        path,
        format!(
            "the header declares {} vertices but the file holds {} ({extra} more after them)",
            vertex.count,
            vertex.count + extra as u64
        ),
    ))
}

/// Streaming PLY writer.
pub struct PlySink {
    out: AtomicFile,
    encoding: PlyEncoding,
    /// Vertex record layout in the output (ascii: little-endian values).
    target: Schema,
    codec: PosCodec,
    /// Layout of the incoming records.
    source: Schema,
    /// For each target field, the source field it comes from; `None` when the layouts agree.
    map: Option<Vec<Option<usize>>>,
    /// Target field receiving the noise flag.
    noise: Option<usize>,
    count: u64,
    written: u64,
    /// Elements after `vertex`, as declared in the output header.
    post: Vec<PlyElement>,
    /// The face element (index into `post`) and its index-list property.
    face: Option<(usize, usize)>,
    trailing_space: bool,
    newline: String,
    buf: Vec<u8>,
    text: String,
}

/// Turns a field name into one the PLY grammar accepts, distinct from `taken`.
fn ply_name(name: &str, taken: &[String]) -> String {
    let mut s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if !s.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
        s.insert(0, '_');
    }
    let base = s.clone();
    let mut k = 2;
    while taken.contains(&s) {
        s = format!("{base}_{k}");
        k += 1;
    }
    s
}

/// Largest value an integer of type `ty` holds (floats: the largest exactly representable integer).
fn int_max(ty: ScalarType) -> u64 {
    match ty {
        ScalarType::I8 => i8::MAX as u64,
        ScalarType::U8 => u8::MAX as u64,
        ScalarType::I16 => i16::MAX as u64,
        ScalarType::U16 => u16::MAX as u64,
        ScalarType::I32 => i32::MAX as u64,
        ScalarType::U32 => u32::MAX as u64,
        ScalarType::I64 => i64::MAX as u64,
        ScalarType::U64 => u64::MAX,
        ScalarType::F32 => 1 << 24,
        ScalarType::F64 => 1 << 53,
    }
}

fn face_element(count: u64) -> PlyElement {
    PlyElement {
        name: "face".into(),
        count,
        properties: vec![PlyProperty {
            name: "vertex_indices".into(),
            ty: PlyType::List {
                count: ScalarType::U8,
                item: ScalarType::I32,
            },
        }],
    }
}

impl PlySink {
    /// Creates a sink at `path` for `count` points laid out like `like`.
    ///
    /// With a PLY source's meta the output keeps its header (encoding, comments, `obj_info`, every
    /// element and property type) with the vertex count set to `count` (and the face count to
    /// `like.faces`); record fields are matched by name, so a field the header lacks is dropped
    /// and a header property the records lack is written as 0. Otherwise a `binary_little_endian`
    /// header is built from `like.schema`, plus a `face` element (`list uchar int vertex_indices`)
    /// when `like.faces` is set; 64-bit integer fields, which PLY lacks, are written as `double`,
    /// so are integer x, y and z (LAS stores scaled `I32` coordinates; the positions written are
    /// the decoded ones, not rounded to whole units), and names are made valid PLY identifiers
    /// (`gps time` → `gps_time`).
    ///
    /// # Errors
    /// The directory is not writable; a face element stored before `vertex` would need a new count.
    pub fn create(path: &Path, like: &SourceInfo, count: u64) -> Result<PlySink, IoError> {
        PlySink::create_with(path, like, count, &SinkOptions::default())
    }

    /// [`PlySink::create`] with options. With [`SinkOptions::noise_flag`] the vertex element gets
    /// a last property `uchar noise` holding 1 for points flagged [`FLAG_NOISE`], else 0; when it
    /// already has a property `noise` (a re-run), that property is overwritten instead (in its
    /// own type).
    ///
    /// # Errors
    /// As [`PlySink::create`].
    pub fn create_with(
        path: &Path,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<PlySink, IoError> {
        let (header_text, pre_vertex, encoding, target, post, trailing_space, newline, by_name) =
            match &like.meta {
                Meta::Ply(m) if m.vertex_element().is_some() => {
                    let mut h = m.header.clone();
                    let mut counts = vec![(m.vertex, count)];
                    h.elements[m.vertex].count = count;
                    let face_el = h
                        .elements
                        .iter()
                        .position(|e| e.name == "face" && e.face_list().is_some());
                    match (like.faces, face_el) {
                        (Some(n), Some(i)) if h.elements[i].count != n => {
                            if i < m.vertex {
                                return Err(IoError::Unsupported {
                                    path: path.to_path_buf(),
                                    detail: format!(
                                        "the face element precedes the vertex element; its count \
                                         cannot change from {} to {n}",
                                        h.elements[i].count
                                    ),
                                });
                            }
                            counts.push((i, n));
                            h.elements[i].count = n;
                        }
                        (Some(n), None) => {
                            // A mesh written like a PLY point cloud: append a face element.
                            let at = h.lines.len() - 1;
                            let nl = h.newline.clone();
                            h.lines.splice(
                                at..at,
                                [
                                    format!("element face {n}{nl}").into_bytes(),
                                    format!("property list uchar int vertex_indices{nl}")
                                        .into_bytes(),
                                ],
                            );
                            h.element_lines.push(at);
                            h.elements.push(face_element(n));
                        }
                        _ => {}
                    }
                    if options.noise_flag
                        && !h.elements[m.vertex]
                            .properties
                            .iter()
                            .any(|p| p.name == NOISE_FIELD)
                    {
                        h.push_property(m.vertex, NOISE_FIELD, ScalarType::U8);
                    }
                    let vel = &h.elements[m.vertex];
                    let fields: Vec<(&str, ScalarType)> = vel
                        .properties
                        .iter()
                        .filter_map(|p| match p.ty {
                            PlyType::Scalar(t) => Some((p.name.as_str(), t)),
                            PlyType::List { .. } => None,
                        })
                        .collect();
                    let target = Schema::packed(&fields, h.encoding.record_endian())
                        .map_err(|e| IoError::header(path, e.to_string()))?;
                    (
                        h.text_with_counts(&counts),
                        m.pre_vertex.clone(),
                        h.encoding,
                        target,
                        h.elements[m.vertex + 1..].to_vec(),
                        m.ascii_trailing_space,
                        h.newline.clone(),
                        true,
                    )
                }
                _ => {
                    let mut fields: Vec<(String, ScalarType)> = Vec::new();
                    for (i, f) in like.schema.fields.iter().enumerate() {
                        let taken: Vec<String> = fields.iter().map(|f| f.0.clone()).collect();
                        let ty = foreign_field_type(&like.schema, i);
                        let ty = if header::type_keyword(ty).is_some() {
                            ty
                        } else {
                            ScalarType::F64
                        };
                        fields.push((ply_name(&f.name, &taken), ty));
                    }
                    if options.noise_flag && !fields.iter().any(|f| f.0 == NOISE_FIELD) {
                        fields.push((NOISE_FIELD.to_string(), ScalarType::U8));
                    }
                    let refs: Vec<(&str, ScalarType)> =
                        fields.iter().map(|(n, t)| (n.as_str(), *t)).collect();
                    let target = Schema::packed(&refs, crate::points::Endian::Little)
                        .map_err(|e| IoError::header(path, e.to_string()))?;
                    let properties = fields
                        .iter()
                        .map(|(name, t)| PlyProperty {
                            name: name.clone(),
                            ty: PlyType::Scalar(*t),
                        })
                        .collect();
                    let mut elements = vec![PlyElement {
                        name: "vertex".into(),
                        count,
                        properties,
                    }];
                    if let Some(n) = like.faces {
                        elements.push(face_element(n));
                    }
                    let h = header::generated_header(PlyEncoding::BinaryLittleEndian, elements);
                    (
                        h.text_with_counts(&[]),
                        Vec::new(),
                        h.encoding,
                        target,
                        h.elements[1..].to_vec(),
                        false,
                        "\n".to_string(),
                        false,
                    )
                }
            };

        let source = like.schema.clone();
        let map: Vec<Option<usize>> = if by_name {
            target
                .fields
                .iter()
                .map(|f| source.field_index(&f.name))
                .collect()
        } else {
            // Target fields follow the source's one for one; an appended `noise` has no source.
            (0..target.fields.len())
                .map(|j| (j < source.fields.len()).then_some(j))
                .collect()
        };
        let same = source.endian == target.endian
            && source.record_len == target.record_len
            && map.iter().enumerate().all(|(j, s)| {
                s.is_some_and(|s| {
                    source.fields[s].ty == target.fields[j].ty
                        && source.fields[s].offset == target.fields[j].offset
                })
            });
        let noise = options
            .noise_flag
            .then(|| target.field_index(NOISE_FIELD))
            .flatten();
        let face = post
            .iter()
            .position(|e| e.name == "face")
            .and_then(|i| post[i].face_list().map(|k| (i, k)));

        let mut out = AtomicFile::create(path)?;
        out.write_all(&header_text)
            .and_then(|_| out.write_all(&pre_vertex))
            .map_err(|e| out.err(e))?;
        Ok(PlySink {
            out,
            encoding,
            codec: PosCodec::new(&target),
            target,
            source,
            map: (!same).then_some(map),
            noise,
            count,
            written: 0,
            post,
            face,
            trailing_space,
            newline,
            buf: Vec::new(),
            text: String::new(),
        })
    }

    fn invalid(&self, detail: impl Into<String>) -> IoError {
        IoError::invalid(self.out.target(), detail)
    }

    /// Encodes `faces` into element `el` (its only property is the index list `list`).
    fn write_faces(&mut self, el: &PlyElement, list: usize, faces: &Faces) -> Result<(), IoError> {
        if el.properties.len() != 1 {
            return Err(IoError::Unsupported {
                path: self.out.target().to_path_buf(),
                detail: format!(
                    "the faces changed but element `{}` has properties besides `{}`, which cannot \
                     be rewritten",
                    el.name, el.properties[list].name
                ),
            });
        }
        if faces.len() as u64 != el.count {
            return Err(self.invalid(format!(
                "the header declares {} faces but {} were given",
                el.count,
                faces.len()
            )));
        }
        let PlyType::List {
            count: ct,
            item: it,
        } = el.properties[list].ty
        else {
            return Err(self.invalid("the face index property is not a list"));
        };
        let endian = self.encoding.record_endian();
        let binary = self.encoding.is_binary();
        self.buf.clear();
        self.text.clear();
        for (f, face) in faces.iter().enumerate() {
            if face.len() as u64 > int_max(ct) {
                return Err(self.invalid(format!(
                    "face {f} has {} vertices, more than a `{}` length can count",
                    face.len(),
                    body::type_name(ct)
                )));
            }
            if let Some(&v) = face
                .iter()
                .find(|&&v| u64::from(v) >= self.count || u64::from(v) > int_max(it))
            {
                return Err(self.invalid(if u64::from(v) >= self.count {
                    format!(
                        "face {f} references vertex {v} but only {} vertices were written",
                        self.count
                    )
                } else {
                    format!(
                        "face {f}: vertex index {v} does not fit the `{}` index type",
                        body::type_name(it)
                    )
                }));
            }
            if binary {
                let mut put = |ty: ScalarType, v: f64| {
                    let at = self.buf.len();
                    self.buf.resize(at + ty.size(), 0);
                    write_scalar(&mut self.buf[at..], ty, endian, v);
                };
                put(ct, face.len() as f64);
                for &v in face {
                    put(it, f64::from(v));
                }
            } else {
                use std::fmt::Write as _;
                let _ = write!(self.text, "{}", face.len());
                for &v in face {
                    let _ = write!(self.text, " {v}");
                }
                self.text.push_str(&self.newline);
            }
            if self.buf.len() + self.text.len() >= READ_BUF {
                self.flush_bufs()?;
            }
        }
        self.flush_bufs()
    }

    fn flush_bufs(&mut self) -> Result<(), IoError> {
        self.out
            .write_all(&self.buf)
            .and_then(|_| self.out.write_all(self.text.as_bytes()))
            .map_err(|e| self.out.err(e))?;
        self.buf.clear();
        self.text.clear();
        Ok(())
    }
}

impl Sink for PlySink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        let n = batch.len();
        if n == 0 {
            return Ok(());
        }
        if self.written + n as u64 > self.count {
            return Err(self.invalid(format!("more points than the {} announced", self.count)));
        }
        let srl = self.source.record_len;
        if batch.records.len() != n * srl {
            return Err(self.invalid(format!(
                "a batch of {n} points holds {} record bytes, expected {} per point",
                batch.records.len(),
                srl
            )));
        }
        let trl = self.target.record_len;
        self.buf.clear();
        match &self.map {
            None => self.buf.extend_from_slice(&batch.records),
            Some(map) => {
                self.buf.resize(n * trl, 0);
                if srl > 0 {
                    for (dst, src) in self
                        .buf
                        .chunks_exact_mut(trl)
                        .zip(batch.records.chunks_exact(srl))
                    {
                        for (j, s) in map.iter().enumerate() {
                            if let Some(s) = *s {
                                self.target.set_f64(dst, j, self.source.get_f64(src, s));
                            }
                        }
                    }
                }
            }
        }
        self.codec
            .encode(&self.target, &mut self.buf, &batch.positions);
        if let Some(k) = self.noise {
            for (i, rec) in self.buf.chunks_exact_mut(trl).enumerate() {
                let flag = u8::from(batch.flag(i) & FLAG_NOISE != 0);
                self.target.set_f64(rec, k, f64::from(flag));
            }
        }
        if self.encoding.is_binary() {
            self.out.write_all(&self.buf).map_err(|e| self.out.err(e))?;
        } else {
            self.text.clear();
            let endian = self.target.endian;
            for rec in self.buf.chunks_exact(trl) {
                for (j, f) in self.target.fields.iter().enumerate() {
                    if j > 0 {
                        self.text.push(' ');
                    }
                    format_ascii(
                        &rec[f.offset..f.offset + f.ty.size()],
                        f.ty,
                        endian,
                        &mut self.text,
                    );
                }
                if self.trailing_space {
                    self.text.push(' ');
                }
                self.text.push_str(&self.newline);
            }
            self.out
                .write_all(self.text.as_bytes())
                .map_err(|e| self.out.err(e))?;
        }
        self.written += n as u64;
        Ok(())
    }

    fn finish(self: Box<Self>, extras: &Extras) -> Result<(), IoError> {
        let mut s = *self;
        if s.written != s.count {
            return Err(s.invalid(format!(
                "{} points were written but the header announces {}",
                s.written, s.count
            )));
        }
        let trailer = match &extras.trailer {
            Trailer::Ply(t) if t.encoding == s.encoding => Some(t),
            _ => None,
        };
        let post = std::mem::take(&mut s.post);
        for (i, el) in post.iter().enumerate() {
            let raw = trailer
                .filter(|t| t.elements.get(i) == Some(el))
                .and_then(|t| t.element_bytes(i));
            match s.face {
                Some((fi, list)) if fi == i => {
                    let unchanged = match (&extras.faces, trailer) {
                        (None, _) => true,
                        (Some(f), Some(t)) => t.faces_digest == Some(faces_digest(f)),
                        (Some(_), None) => false,
                    };
                    match (raw, &extras.faces) {
                        (Some(raw), _) if unchanged => {
                            s.out.write_all(raw).map_err(|e| s.out.err(e))?
                        }
                        (_, Some(f)) => s.write_faces(el, list, f)?,
                        (_, None) if el.count == 0 => {}
                        (_, None) => {
                            return Err(s.invalid(format!(
                                "the header declares {} faces but none were given",
                                el.count
                            )));
                        }
                    }
                }
                _ => match raw {
                    Some(raw) => s.out.write_all(raw).map_err(|e| s.out.err(e))?,
                    None if el.count == 0 => {}
                    None => {
                        return Err(s.invalid(format!(
                            "no data for element `{}` ({} declared in the header)",
                            el.name, el.count
                        )));
                    }
                },
            }
        }
        if let Some(t) = trailer.filter(|t| t.elements == post) {
            s.out
                .write_all(t.trailing_bytes())
                .map_err(|e| s.out.err(e))?;
        }
        s.out.commit()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::Cloud;

    #[test]
    fn names_become_ply_identifiers() {
        let taken = vec!["a".to_string(), "a_2".to_string()];
        assert_eq!(ply_name("x", &[]), "x");
        assert_eq!(ply_name("gps time", &[]), "gps_time");
        assert_eq!(ply_name("3d", &[]), "_3d");
        assert_eq!(ply_name("a", &taken), "a_3");
        assert_eq!(int_max(ScalarType::U8), 255);
        assert_eq!(int_max(ScalarType::I32), i32::MAX as u64);
    }

    #[test]
    fn default_meta_falls_back_to_the_generic_header() {
        assert!(PlyMeta::default().vertex_element().is_none());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.ply");
        let mut c = Cloud::generated(vec![glam::DVec3::ONE; 2], None, ScalarType::F32);
        c.info.meta = Meta::Ply(PlyMeta::default());
        c.write(&path, None).unwrap();
        let back = PlySource::open(&path).unwrap();
        let Meta::Ply(m) = &back.info().meta else {
            panic!("PLY meta expected")
        };
        assert_eq!(m.encoding(), PlyEncoding::BinaryLittleEndian);
        assert!(
            m.header_bytes()
                .starts_with(b"ply\nformat binary_little_endian 1.0\n")
        );
        assert_eq!(back.info().len, Some(2));
    }

    #[test]
    fn appends_a_face_element_to_a_ply_point_cloud() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.ply"), dir.path().join("b.ply"));
        std::fs::write(
            &a,
            "ply\r\nformat ascii 1.0\r\nelement vertex 3\r\nproperty float x\r\n\
             property float y\r\nproperty float z\r\nend_header\r\n0 0 0\r\n1 0 0\r\n0 1 0\r\n",
        )
        .unwrap();
        let mut c = Cloud::read(&a, None).unwrap();
        assert_eq!(c.info.faces, None);
        c.info.faces = Some(1);
        c.extras.faces = Some(Faces::from_triangles(&[[0, 1, 2]]));
        c.write(&b, None).unwrap();
        let text = std::fs::read_to_string(&b).unwrap();
        assert!(text.contains(
            "property float z\r\nelement face 1\r\nproperty list uchar int vertex_indices\r\n\
             end_header\r\n"
        ));
        assert!(text.ends_with("0 1 0\r\n3 0 1 2\r\n"), "{text}");
        let back = Cloud::read(&b, None).unwrap();
        assert_eq!(back.faces(), c.faces());
    }
}
