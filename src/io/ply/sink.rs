//! The PLY writer: the source's header reproduced, or one built from the schema; vertices batch
//! by batch; the trailer verbatim or the faces encoded (see the [module overview](super)).

use std::io::Write;
use std::path::Path;

use super::READ_BUF;
use super::body::{self, PosCodec, faces_digest, format_ascii};
use super::header::{self, PlyElement, PlyEncoding, PlyProperty, PlyType};
use crate::io::{
    AtomicFile, BodyStats, Extras, IoError, Meta, NOISE_FIELD, NormalField, NormalNames, Sink,
    SinkOptions, SourceInfo, Trailer, foreign_field_type,
};
use crate::points::{FLAG_NOISE, Faces, PointBatch, Rounding, ScalarType, Schema, write_scalar};

/// Streaming PLY writer.
pub struct PlySink {
    out: AtomicFile,
    encoding: PlyEncoding,
    /// Vertex record layout in the output (ascii: little-endian values).
    target: Schema,
    codec: PosCodec,
    /// How moved coordinates round to what the output stores ([`SinkOptions::rounding`]).
    rounding: Rounding,
    /// Layout of the incoming records.
    source: Schema,
    /// For each target field, the source field it comes from; `None` when the layouts agree.
    map: Option<Vec<Option<usize>>>,
    /// Target field receiving the noise flag.
    noise: Option<usize>,
    /// Target fields receiving the written normals ([`SinkOptions::normals`]).
    normals: Vec<(usize, NormalField)>,
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
        PlySink::new(AtomicFile::create(path)?, like, count, options)
    }

    /// [`PlySink::create_with`] writing to `out` (a file, a stream or memory).
    ///
    /// # Errors
    /// As [`PlySink::create`].
    pub fn new(
        mut out: AtomicFile,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<PlySink, IoError> {
        let shown = out.target().to_path_buf();
        let path = shown.as_path();
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
                    if options.normals {
                        for f in NormalField::ALL {
                            let has = |n: &&str| {
                                h.elements[m.vertex]
                                    .properties
                                    .iter()
                                    .any(|p| p.name == *n && matches!(p.ty, PlyType::Scalar(_)))
                            };
                            if !f.aliases().iter().any(has) {
                                h.push_property(m.vertex, f.name(NormalNames::Ply), f.ty());
                            }
                        }
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
                    if options.normals {
                        for f in NormalField::ALL {
                            if !fields
                                .iter()
                                .any(|(n, _)| f.aliases().contains(&n.as_str()))
                            {
                                fields.push((f.name(NormalNames::Ply).to_string(), f.ty()));
                            }
                        }
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
        let normals = if options.normals {
            NormalField::ALL
                .iter()
                .filter_map(|&f| f.find(&target).map(|k| (k, f)))
                .collect()
        } else {
            Vec::new()
        };
        let face = post
            .iter()
            .position(|e| e.name == "face")
            .and_then(|i| post[i].face_list().map(|k| (i, k)));

        // A body holds the vertex records alone; its count is the sink's it is appended to.
        if !options.body {
            out.write_all(&header_text)
                .and_then(|_| out.write_all(&pre_vertex))
                .map_err(|e| out.err(e))?;
        }
        Ok(PlySink {
            out,
            encoding,
            codec: PosCodec::new(&target),
            rounding: options.rounding,
            target,
            source,
            map: (!same).then_some(map),
            noise,
            normals,
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
            .encode(&self.target, &mut self.buf, &batch.positions, self.rounding);
        if let Some(k) = self.noise {
            for (i, rec) in self.buf.chunks_exact_mut(trl).enumerate() {
                let flag = u8::from(batch.flag(i) & FLAG_NOISE != 0);
                self.target.set_f64(rec, k, f64::from(flag));
            }
        }
        if !self.normals.is_empty() {
            for (i, rec) in self.buf.chunks_exact_mut(trl).enumerate() {
                let n = batch.normal(i);
                for &(k, f) in &self.normals {
                    self.target.set_f64(rec, k, f.value(&n));
                }
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

    fn splittable(&self) -> bool {
        true
    }

    fn finish_body(self: Box<Self>) -> Result<BodyStats, IoError> {
        let points = self.written;
        self.out.commit_unsynced()?;
        Ok(BodyStats::count(points))
    }

    fn append_body(&mut self, path: &Path, stats: &BodyStats) -> Result<(), IoError> {
        if self.written + stats.points > self.count {
            return Err(self.invalid(format!("more points than the {} announced", self.count)));
        }
        self.out.append_file(path)?;
        self.written += stats.points;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
