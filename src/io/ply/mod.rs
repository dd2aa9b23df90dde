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
//! * **Normals.** With [`SinkOptions::normals`] the vertex element gets `float nx`, `float ny`,
//!   `float nz`, `float curvature` and `uchar structure` (before an appended `noise`), holding
//!   [`PointBatch::normals`]; a property already holding one of them (`nx` or `normal_x`, …) is
//!   overwritten in its own type instead (see [the I/O overview](super#normals)).
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
mod sink;
mod source;

pub use header::{PlyElement, PlyEncoding, PlyProperty, PlyType};
pub use sink::PlySink;
pub use source::PlySource;

use self::header::Header;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{Cloud, Meta, Source};
    use crate::points::{Faces, ScalarType};

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
