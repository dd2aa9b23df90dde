//! The PLY reader: header, vertices batch by batch, then every element after `vertex` (see the
//! [module overview](super)).

use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use super::body::{self, FaceTarget, PosCodec, Walker, eof, faces_digest, parse_ascii};
use super::header::{self, PlyElement, PlyEncoding, PlyType};
use super::{PlyMeta, PlyTrailer, READ_BUF};
use crate::io::reader::seek_record;
use crate::io::{Extras, Input, IoError, Meta, Source, SourceInfo, Trailer};
use crate::points::{Faces, PointBatch, Schema};

/// Streaming PLY reader (ascii, binary little- and big-endian).
pub struct PlySource {
    info: SourceInfo,
    reader: BufReader<Input>,
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
    /// Where the vertex records start, for a binary file that can seek.
    vertex_start: Option<u64>,
}

impl PlySource {
    /// Opens `path` and reads its header (and any element stored before `vertex`).
    ///
    /// # Errors
    /// [`IoError::Header`] for a missing or malformed header, a missing `vertex` element or a
    /// missing `x`/`y`/`z`; [`IoError::Unsupported`] for list properties on vertices or non-integer
    /// face indices; [`IoError::Truncated`] when a binary file is shorter than its vertex data.
    pub fn open(path: &Path) -> Result<PlySource, IoError> {
        PlySource::new(Input::from_path(path)?)
    }

    /// [`PlySource::open`] on any [`Input`].
    ///
    /// # Errors
    /// As [`PlySource::open`].
    pub fn new(input: Input) -> Result<PlySource, IoError> {
        let owned = input.name().to_path_buf();
        let path = owned.as_path();
        let file_len = input.len();
        let mut reader = BufReader::with_capacity(READ_BUF, input);
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

        let vertex_start = if encoding.is_binary() {
            std::io::Seek::stream_position(&mut reader).ok()
        } else {
            None
        };
        let codec = PosCodec::new(&schema);
        let elements = header.elements.clone();
        let info = SourceInfo {
            path: path.to_path_buf(),
            format: crate::io::Format::Ply,
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
            vertex_start,
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

    fn seek_point(&mut self, index: u64) -> Result<bool, IoError> {
        let Some(start) = self.vertex_start.filter(|_| index <= self.count) else {
            return Ok(false);
        };
        let records = (start, self.info.schema.record_len);
        seek_record(&mut self.reader, &self.info.path, records, index)?;
        self.read = index;
        Ok(true)
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
