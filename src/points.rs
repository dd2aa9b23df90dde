//! The data model every other layer shares: positions plus opaque attribute records.
//!
//! # Brief overview
//!
//! * [`Schema`] describes one fixed-size binary point record: its [`Field`]s (name, [`ScalarType`],
//!   byte offset), its byte order and which three fields are x, y and z. Readers build a schema from
//!   the file's own header, so a writer can reproduce the input's layout and property types exactly.
//! * [`PointBatch`] is the unit that flows from an `io::Source` to an `io::Sink`: positions decoded to
//!   f64 plus the untouched record bytes of every point. Only x, y and z are ever rewritten; every
//!   other byte of the record travels through unchanged (colour, intensity, GPS time, normals, …).
//! * [`Faces`] holds polygon connectivity in CSR form; [`Aabb`] is an axis-aligned box.
//! * [`in_range`] is the one rule for which positions are processed: finite, and no coordinate
//!   beyond ±[`MAX_COORD`]. Every other point is left out of the neighbourhoods and written back
//!   unchanged (organized clouds) or dropped and counted, as a NaN point is.
//!
//! ```text
//!  PointBatch (n points, record_len = R)
//!  positions: [ p0 | p1 | p2 | … ]                 DVec3 (f64), decoded x/y/z
//!  records:   [ r0 (R bytes) | r1 | r2 | … ]       original encoding, attributes untouched
//!  start:     global index of p0 in the source
//!  flags:     [] or one byte per point (FLAG_NOISE)
//!  normals:   [] or one PointNormal per point (`--write-normals`)
//! ```

use glam::DVec3;
use thiserror::Error;

/// Errors of the data model: a schema that cannot describe a record.
#[derive(Debug, Error, PartialEq, Eq)]
#[non_exhaustive]
pub enum PointsError {
    /// A schema has no field with the given name.
    #[error("the point schema has no field named `{0}`")]
    MissingField(String),
    /// A field lies outside the record.
    #[error("field `{name}` at byte {offset} does not fit in a {record_len}-byte record")]
    FieldOutOfRecord {
        /// Field name.
        name: String,
        /// Byte offset of the field.
        offset: usize,
        /// Length of the record.
        record_len: usize,
    },
}

/// The scalar types found in point formats (PLY, PCD, LAS, raw binary).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum ScalarType {
    /// Signed 8-bit integer.
    I8,
    /// Unsigned 8-bit integer.
    U8,
    /// Signed 16-bit integer.
    I16,
    /// Unsigned 16-bit integer.
    U16,
    /// Signed 32-bit integer.
    I32,
    /// Unsigned 32-bit integer.
    U32,
    /// Signed 64-bit integer.
    I64,
    /// Unsigned 64-bit integer.
    U64,
    /// IEEE single precision.
    F32,
    /// IEEE double precision.
    F64,
}

impl ScalarType {
    /// Size of one value in bytes.
    pub const fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::I64 | ScalarType::U64 | ScalarType::F64 => 8,
        }
    }

    /// True for `F32` and `F64`.
    pub const fn is_float(self) -> bool {
        matches!(self, ScalarType::F32 | ScalarType::F64)
    }
}

/// Byte order of binary records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum Endian {
    /// Least significant byte first.
    Little,
    /// Most significant byte first.
    Big,
}

/// One named scalar inside a record.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Field {
    /// Name as the file spells it (`x`, `red`, `intensity`, …).
    pub name: String,
    /// Stored type.
    pub ty: ScalarType,
    /// Byte offset inside the record.
    pub offset: usize,
}

/// Layout of one fixed-size point record.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Schema {
    /// Fields in record order.
    pub fields: Vec<Field>,
    /// Bytes per record (may exceed the sum of field sizes when a format pads records).
    pub record_len: usize,
    /// Byte order of multi-byte fields.
    pub endian: Endian,
    /// Indices into `fields` of x, y and z.
    pub xyz: [usize; 3],
}

impl Schema {
    /// Builds a packed schema from `(name, type)` pairs; x, y and z must be among them.
    ///
    /// # Errors
    /// [`PointsError::MissingField`] when x, y or z is absent.
    pub fn packed(fields: &[(&str, ScalarType)], endian: Endian) -> Result<Schema, PointsError> {
        let mut offset = 0;
        let fields: Vec<Field> = fields
            .iter()
            .map(|&(name, ty)| {
                let f = Field {
                    name: name.to_string(),
                    ty,
                    offset,
                };
                offset += ty.size();
                f
            })
            .collect();
        Schema::new(fields, offset, endian)
    }

    /// A record of just x, y, z of one type.
    pub fn xyz_only(ty: ScalarType) -> Schema {
        Schema::packed(&[("x", ty), ("y", ty), ("z", ty)], Endian::Little)
            .expect("x, y and z are present by construction")
    }

    /// Builds a schema from explicit fields, locating x, y and z by name.
    ///
    /// # Errors
    /// [`PointsError::MissingField`] when x, y or z is absent, [`PointsError::FieldOutOfRecord`]
    /// when a field does not fit in `record_len`.
    pub fn new(
        fields: Vec<Field>,
        record_len: usize,
        endian: Endian,
    ) -> Result<Schema, PointsError> {
        for f in &fields {
            if f.offset + f.ty.size() > record_len {
                return Err(PointsError::FieldOutOfRecord {
                    name: f.name.clone(),
                    offset: f.offset,
                    record_len,
                });
            }
        }
        let find = |n: &str| {
            fields
                .iter()
                .position(|f| f.name == n)
                .ok_or_else(|| PointsError::MissingField(n.to_string()))
        };
        let xyz = [find("x")?, find("y")?, find("z")?];
        Ok(Schema {
            fields,
            record_len,
            endian,
            xyz,
        })
    }

    /// Index of the field called `name`.
    pub fn field_index(&self, name: &str) -> Option<usize> {
        self.fields.iter().position(|f| f.name == name)
    }

    /// Reads field `i` of `record` as f64 (integers convert exactly up to 2^53).
    pub fn get_f64(&self, record: &[u8], i: usize) -> f64 {
        let f = &self.fields[i];
        read_scalar(&record[f.offset..f.offset + f.ty.size()], f.ty, self.endian)
    }

    /// Writes `v` into field `i` of `record`, converting to the field's type (integers round to
    /// nearest and saturate).
    pub fn set_f64(&self, record: &mut [u8], i: usize, v: f64) {
        let f = &self.fields[i];
        write_scalar(
            &mut record[f.offset..f.offset + f.ty.size()],
            f.ty,
            self.endian,
            v,
        );
    }

    /// Decodes the position stored in `record`.
    pub fn position(&self, record: &[u8]) -> DVec3 {
        DVec3::new(
            self.get_f64(record, self.xyz[0]),
            self.get_f64(record, self.xyz[1]),
            self.get_f64(record, self.xyz[2]),
        )
    }

    /// Stores `p` into the x, y and z fields of `record`.
    pub fn set_position(&self, record: &mut [u8], p: DVec3) {
        self.set_f64(record, self.xyz[0], p.x);
        self.set_f64(record, self.xyz[1], p.y);
        self.set_f64(record, self.xyz[2], p.z);
    }

    /// Stores `p` into the x, y and z fields of `record`, which hold the point's input position,
    /// rounded as `rounding` says.
    pub fn move_position(&self, record: &mut [u8], p: DVec3, rounding: Rounding) {
        let from = self.position(record).to_array();
        let tys = self.xyz.map(|i| self.fields[i].ty);
        let stored = rounding.store(p.to_array(), from, [1.0; 3], |k, v, towards| {
            stored_toward(v, towards, tys[k])
        });
        for (k, v) in stored.into_iter().enumerate() {
            self.set_f64(record, self.xyz[k], v);
        }
    }
}

/// How a sink rounds a moved point's coordinates to the values its output stores.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Rounding {
    /// Each coordinate to the nearest stored value: what `qemd noise` and conversions write.
    #[default]
    Nearest,
    /// The stored move never longer than the computed one ([`store_move`]): what a denoising run
    /// writes, so that the bounds it put on every move hold in the file.
    NoLonger,
}

impl Rounding {
    /// What a point moved from `from` to `v` stores; `unit` and `round` as [`store_move`] takes
    /// them.
    pub fn store(
        self,
        v: [f64; 3],
        from: [f64; 3],
        unit: [f64; 3],
        round: impl Fn(usize, f64, f64) -> f64,
    ) -> [f64; 3] {
        match self {
            Rounding::Nearest => std::array::from_fn(|k| round(k, v[k], v[k])),
            Rounding::NoLonger => store_move(v, from, unit, round),
        }
    }
}

/// What a point moved from `from` to `v` stores, given `round(axis, value, towards)` (the value
/// of the axis's storage next to `value` on `towards`' side, the nearest when `towards` is
/// `value`): every coordinate to nearest, unless that makes the stored move longer than the
/// computed one (`unit` turns each axis's storage units into lengths); then every coordinate
/// towards `from`. So the stored move is never longer than the computed one, and every bound the
/// operator put on a move (a quarter of the point's k-NN radius, the noise bound, `--max-move`)
/// holds in the file, on coarse storage too (float32 UTM coordinates are 0.5 m apart near
/// 5·10⁶ m; LAS scales of 1 cm), while a move that rounding does not lengthen keeps the nearest
/// value. Unmoved points store `from`.
pub fn store_move(
    v: [f64; 3],
    from: [f64; 3],
    unit: [f64; 3],
    round: impl Fn(usize, f64, f64) -> f64,
) -> [f64; 3] {
    let near: [f64; 3] = std::array::from_fn(|k| round(k, v[k], v[k]));
    let len2 = |p: &[f64; 3]| {
        (0..3)
            .map(|k| ((p[k] - from[k]) * unit[k]).powi(2))
            .sum::<f64>()
    };
    if len2(&near) <= len2(&v) {
        near
    } else {
        std::array::from_fn(|k| round(k, v[k], from[k]))
    }
}

/// Decodes one scalar of type `ty` from exactly `ty.size()` bytes.
pub fn read_scalar(b: &[u8], ty: ScalarType, endian: Endian) -> f64 {
    macro_rules! rd {
        ($t:ty) => {{
            let a = b.try_into().expect("slice length equals the scalar size");
            (match endian {
                Endian::Little => <$t>::from_le_bytes(a),
                Endian::Big => <$t>::from_be_bytes(a),
            }) as f64
        }};
    }
    match ty {
        ScalarType::I8 => b[0] as i8 as f64,
        ScalarType::U8 => b[0] as f64,
        ScalarType::I16 => rd!(i16),
        ScalarType::U16 => rd!(u16),
        ScalarType::I32 => rd!(i32),
        ScalarType::U32 => rd!(u32),
        ScalarType::I64 => rd!(i64),
        ScalarType::U64 => rd!(u64),
        ScalarType::F32 => rd!(f32),
        ScalarType::F64 => rd!(f64),
    }
}

/// Of the two values of type `ty` around `v`, the one on `from`'s side (`v` itself when `ty`
/// holds it; the nearest when `from` equals `v` or is NaN): a coordinate moved from `from` to
/// `v` stored this way moves no farther than computed ([`store_move`]). Integer types then
/// saturate as [`write_scalar`] does.
pub fn stored_toward(v: f64, from: f64, ty: ScalarType) -> f64 {
    match ty {
        ScalarType::F64 => v,
        ScalarType::F32 => {
            let q = v as f32;
            let qd = f64::from(q);
            if from < v && qd > v {
                f64::from(q.next_down())
            } else if from > v && qd < v {
                f64::from(q.next_up())
            } else {
                qd
            }
        }
        _ => integer_toward(v, from),
    }
}

/// The integer next to `v` on `from`'s side (nearest when `from` equals `v` or is NaN); see
/// [`stored_toward`]. Scaled-integer formats (LAS) apply it to `(v − offset) / scale`.
pub fn integer_toward(v: f64, from: f64) -> f64 {
    if from < v {
        v.floor()
    } else if from > v {
        v.ceil()
    } else {
        v.round()
    }
}

/// Encodes `v` as type `ty` into exactly `ty.size()` bytes. Integer types round to nearest and
/// saturate (Rust's `as` semantics; NaN becomes 0).
pub fn write_scalar(b: &mut [u8], ty: ScalarType, endian: Endian, v: f64) {
    macro_rules! wr {
        ($t:ty, $x:expr) => {{
            let x: $t = $x;
            b.copy_from_slice(&match endian {
                Endian::Little => x.to_le_bytes(),
                Endian::Big => x.to_be_bytes(),
            });
        }};
    }
    let r = v.round();
    match ty {
        ScalarType::I8 => b[0] = r as i8 as u8,
        ScalarType::U8 => b[0] = r as u8,
        ScalarType::I16 => wr!(i16, r as i16),
        ScalarType::U16 => wr!(u16, r as u16),
        ScalarType::I32 => wr!(i32, r as i32),
        ScalarType::U32 => wr!(u32, r as u32),
        ScalarType::I64 => wr!(i64, r as i64),
        ScalarType::U64 => wr!(u64, r as u64),
        ScalarType::F32 => wr!(f32, v as f32),
        ScalarType::F64 => wr!(f64, v),
    }
}

/// A run of consecutive points of one source: decoded positions plus the raw records.
///
/// Batches are reused: `clear` keeps the allocations, so a reader fills the same buffers again
/// and a streaming run allocates nothing per batch.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointBatch {
    /// Global index (position in the source) of the first point.
    pub start: u64,
    /// Decoded positions, one per point.
    pub positions: Vec<DVec3>,
    /// `record_len` bytes per point in the source's own encoding.
    pub records: Vec<u8>,
    /// Bytes per record.
    pub record_len: usize,
    /// Per-point flags: empty, or one byte per point ([`FLAG_NOISE`] marks an outlier). Sinks
    /// created with a noise flag write it (LAS class 7, or a `noise` property elsewhere).
    pub flags: Vec<u8>,
    /// Per-point normals: empty, or one per point. Sinks created with `normals` in their options
    /// write them as extra fields (an empty `normals` writes [`PointNormal::NONE`] everywhere).
    pub normals: Vec<PointNormal>,
}

/// What `--write-normals` writes for one point: the unit normal its neighbourhood gave in the
/// run (oriented, see [`crate::denoise::written`]), the surface variation and the structure
/// class. Stored in `f32` (`u8` for the class), the types every format writes them in, so the
/// in-memory and tiled paths hand sinks the same bits.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PointNormal {
    /// Unit normal, or 0 0 0 where the point has none.
    pub normal: [f32; 3],
    /// Surface variation `λ0 / (λ0 + λ1 + λ2)` of the neighbourhood (PCL's and PDAL's
    /// `curvature`), 0 where it has none.
    pub curvature: f32,
    /// The structure class code (`denoise::structure::Structure`: surface 0, edge 1, line 2,
    /// scatter 3, sparse 4, degenerate 5).
    pub structure: u8,
}

impl PointNormal {
    /// The values of a point without a neighbourhood (not processed): no normal, no curvature,
    /// degenerate (5).
    pub const NONE: PointNormal = PointNormal {
        normal: [0.0; 3],
        curvature: 0.0,
        structure: 5,
    };
}

/// [`PointBatch::flags`] bit: the point is a statistical outlier.
pub const FLAG_NOISE: u8 = 1;

impl PointBatch {
    /// An empty batch for records of `record_len` bytes with room for `capacity` points.
    pub fn with_capacity(record_len: usize, capacity: usize) -> PointBatch {
        PointBatch {
            start: 0,
            positions: Vec::with_capacity(capacity),
            records: Vec::with_capacity(capacity * record_len),
            record_len,
            flags: Vec::new(),
            normals: Vec::new(),
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the batch holds no point.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Empties the batch and sets the global index of its next first point.
    pub fn clear(&mut self, start: u64) {
        self.start = start;
        self.positions.clear();
        self.records.clear();
        self.flags.clear();
        self.normals.clear();
    }

    /// Record bytes of point `i`.
    pub fn record(&self, i: usize) -> &[u8] {
        &self.records[i * self.record_len..(i + 1) * self.record_len]
    }

    /// Mutable record bytes of point `i`.
    pub fn record_mut(&mut self, i: usize) -> &mut [u8] {
        &mut self.records[i * self.record_len..(i + 1) * self.record_len]
    }

    /// The flags of point `i` (0 when the batch carries none).
    pub fn flag(&self, i: usize) -> u8 {
        self.flags.get(i).copied().unwrap_or(0)
    }

    /// The normal of point `i` ([`PointNormal::NONE`] when the batch carries none).
    pub fn normal(&self, i: usize) -> PointNormal {
        self.normals.get(i).copied().unwrap_or(PointNormal::NONE)
    }

    /// Appends one point.
    pub fn push(&mut self, position: DVec3, record: &[u8]) {
        debug_assert_eq!(record.len(), self.record_len);
        self.positions.push(position);
        self.records.extend_from_slice(record);
    }
}

/// Polygon connectivity in compressed-sparse-row form.
///
/// ```text
///  offsets: [0, 3, 6, 10]          face f = indices[offsets[f]..offsets[f+1]]
///  indices: [a b c | c b d | d e f g]
/// ```
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Faces {
    /// `len() + 1` offsets into `indices`; starts at 0.
    pub offsets: Vec<u32>,
    /// Vertex indices of all faces, concatenated.
    pub indices: Vec<u32>,
}

impl Faces {
    /// No faces.
    pub fn new() -> Faces {
        Faces {
            offsets: vec![0],
            indices: Vec::new(),
        }
    }

    /// Builds from triangles.
    pub fn from_triangles(tris: &[[u32; 3]]) -> Faces {
        let mut f = Faces::new();
        for t in tris {
            f.push(t);
        }
        f
    }

    /// Appends one polygon.
    pub fn push(&mut self, face: &[u32]) {
        if self.offsets.is_empty() {
            self.offsets.push(0);
        }
        self.indices.extend_from_slice(face);
        self.offsets.push(self.indices.len() as u32);
    }

    /// Number of faces.
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// True when there is no face.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Vertex indices of face `f`.
    pub fn face(&self, f: usize) -> &[u32] {
        &self.indices[self.offsets[f] as usize..self.offsets[f + 1] as usize]
    }

    /// Iterates over the faces.
    pub fn iter(&self) -> impl Iterator<Item = &[u32]> + '_ {
        (0..self.len()).map(move |f| self.face(f))
    }

    /// Largest vertex index referenced plus one (0 without faces).
    pub fn min_vertex_count(&self) -> usize {
        self.indices.iter().max().map_or(0, |&m| m as usize + 1)
    }

    /// Fan triangles `(f[0], f[i], f[i+1])` of every face, in face order.
    pub fn triangles(&self) -> impl Iterator<Item = [u32; 3]> + '_ {
        self.iter()
            .flat_map(|f| (1..f.len().saturating_sub(1)).map(move |i| [f[0], f[i], f[i + 1]]))
    }
}

/// The largest coordinate magnitude a processed point may have, in the file's own units.
///
/// Why 10¹², and absolute rather than relative to the cloud: no real scan comes near it. Earth-
/// centred or projected coordinates are below 10⁷ m, 10¹⁰ in millimetres; a LAS coordinate is a
/// 32-bit integer times its scale plus an offset. A coordinate beyond it is a corrupt record (a
/// flipped exponent bit, a garbage float), not geometry, and no relative rule can tell one far
/// point from a scene. The bound keeps every derived quantity finite: squared distances stay
/// below 3 · (2 · 10¹²)² ≈ 10²⁵, where 10¹⁵⁵ would already overflow, so k-NN radii, halo boxes
/// and quadrics never become infinite. At 10¹² an f64 still resolves 0.1 mm.
pub const MAX_COORD: f64 = 1e12;

/// True when `p` is processed: every coordinate finite and within ±[`MAX_COORD`].
///
/// Points failing it are treated exactly like non-finite ones: never a neighbour, never moved,
/// written back unchanged where the layout must be kept (organized clouds), otherwise dropped
/// and counted in the run's report.
#[inline]
pub fn in_range(p: DVec3) -> bool {
    // Written as comparisons so that NaN fails them.
    p.x.abs() <= MAX_COORD && p.y.abs() <= MAX_COORD && p.z.abs() <= MAX_COORD
}

/// The sampling key of global index `i`: a 64-bit mix (a bijection, so keys never tie). The
/// points with the smallest keys are a uniform sample that depends on nothing but the indices:
/// the tiling planner and the in-memory path draw the same one.
pub fn sample_key(i: u64) -> u64 {
    let mut z = i.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// An axis-aligned bounding box; empty boxes have `min > max`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Aabb {
    /// Lower corner.
    pub min: DVec3,
    /// Upper corner.
    pub max: DVec3,
}

impl Default for Aabb {
    fn default() -> Self {
        Aabb::empty()
    }
}

impl Aabb {
    /// The empty box (grows to fit the first point).
    pub fn empty() -> Aabb {
        Aabb {
            min: DVec3::splat(f64::INFINITY),
            max: DVec3::splat(f64::NEG_INFINITY),
        }
    }

    /// Smallest box holding all finite points of `pts`.
    pub fn from_points(pts: &[DVec3]) -> Aabb {
        let mut b = Aabb::empty();
        for &p in pts {
            b.grow(p);
        }
        b
    }

    /// True when no point was added.
    pub fn is_empty(&self) -> bool {
        self.min.x > self.max.x
    }

    /// Grows to hold `p`; points that fail [`in_range`] (non-finite or beyond ±[`MAX_COORD`]) are
    /// ignored.
    pub fn grow(&mut self, p: DVec3) {
        if in_range(p) {
            self.min = self.min.min(p);
            self.max = self.max.max(p);
        }
    }

    /// Grows to hold `other`.
    pub fn union(&mut self, other: &Aabb) {
        if !other.is_empty() {
            self.min = self.min.min(other.min);
            self.max = self.max.max(other.max);
        }
    }

    /// Extent along each axis (zero for an empty box).
    pub fn size(&self) -> DVec3 {
        if self.is_empty() {
            DVec3::ZERO
        } else {
            self.max - self.min
        }
    }

    /// Length of the diagonal.
    pub fn diagonal(&self) -> f64 {
        self.size().length()
    }

    /// Closed containment test.
    pub fn contains(&self, p: DVec3) -> bool {
        p.cmpge(self.min).all() && p.cmple(self.max).all()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scalar_roundtrip_every_type_and_endianness() {
        let types = [
            ScalarType::I8,
            ScalarType::U8,
            ScalarType::I16,
            ScalarType::U16,
            ScalarType::I32,
            ScalarType::U32,
            ScalarType::I64,
            ScalarType::U64,
            ScalarType::F32,
            ScalarType::F64,
        ];
        for ty in types {
            for endian in [Endian::Little, Endian::Big] {
                let mut b = vec![0u8; ty.size()];
                write_scalar(&mut b, ty, endian, 100.0);
                assert_eq!(read_scalar(&b, ty, endian), 100.0, "{ty:?} {endian:?}");
            }
        }
        let mut b = [0u8; 4];
        write_scalar(&mut b, ScalarType::F32, Endian::Big, 1.5);
        assert_eq!(b, 1.5f32.to_be_bytes());
    }

    #[test]
    fn in_range_is_finite_and_bounded() {
        assert!(in_range(DVec3::new(-MAX_COORD, MAX_COORD, 0.0)));
        for bad in [1e200, f64::MAX, f64::INFINITY, f64::NAN, -1.0000001e12] {
            assert!(!in_range(DVec3::new(0.0, bad, 0.0)), "{bad}");
        }
        let mut b = Aabb::empty();
        b.grow(DVec3::ONE);
        b.grow(DVec3::new(1e200, 0.0, 0.0));
        assert_eq!((b.min, b.max), (DVec3::ONE, DVec3::ONE));
    }

    #[test]
    fn schema_positions_and_padding() {
        let s = Schema::packed(
            &[
                ("x", ScalarType::F64),
                ("red", ScalarType::U8),
                ("y", ScalarType::F64),
                ("z", ScalarType::F32),
            ],
            Endian::Big,
        )
        .unwrap();
        assert_eq!(s.record_len, 21);
        let mut rec = vec![7u8; 21];
        s.set_position(&mut rec, DVec3::new(1.0, -2.0, 0.25));
        assert_eq!(s.position(&rec), DVec3::new(1.0, -2.0, 0.25));
        assert_eq!(rec[8], 7, "the attribute byte is untouched");
        assert!(matches!(
            Schema::packed(&[("x", ScalarType::F32)], Endian::Little),
            Err(PointsError::MissingField(_))
        ));
    }

    #[test]
    fn faces_csr_and_fan_triangles() {
        let mut f = Faces::new();
        f.push(&[0, 1, 2]);
        f.push(&[2, 1, 3, 4]);
        assert_eq!(f.len(), 2);
        assert_eq!(f.face(1), &[2, 1, 3, 4]);
        let t: Vec<_> = f.triangles().collect();
        assert_eq!(t, vec![[0, 1, 2], [2, 1, 3], [2, 3, 4]]);
        assert_eq!(f.min_vertex_count(), 5);
    }

    #[test]
    fn aabb_ignores_non_finite() {
        let b = Aabb::from_points(&[
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(f64::NAN, 0.0, 0.0),
            DVec3::new(-1.0, 5.0, 0.0),
        ]);
        assert_eq!(b.min, DVec3::new(-1.0, 2.0, 0.0));
        assert_eq!(b.max, DVec3::new(1.0, 5.0, 3.0));
        assert!(Aabb::empty().is_empty());
    }

    proptest::proptest! {
        /// Float32 storage: a stored move is never longer than the computed one, each stored
        /// coordinate is one of the two float32 values around the computed one, and to-nearest
        /// rounding is what `as f32` gives.
        #[test]
        fn no_longer_moves_in_float32(
            base in (-6e6f64..6e6, -6e6f64..6e6, -1e3f64..1e3),
            step in (-2.0f64..2.0, -2.0f64..2.0, -2.0f64..2.0),
        ) {
            let from = [base.0, base.1, base.2].map(|c| f64::from(c as f32));
            let v = [from[0] + step.0, from[1] + step.1, from[2] + step.2];
            let round = |_: usize, x: f64, t: f64| stored_toward(x, t, ScalarType::F32);
            let len = |p: [f64; 3]| (0..3).map(|k| (p[k] - from[k]).powi(2)).sum::<f64>();
            let stored = Rounding::NoLonger.store(v, from, [1.0; 3], round);
            proptest::prop_assert!(len(stored) <= len(v));
            for k in 0..3 {
                let q = stored[k] as f32;
                proptest::prop_assert_eq!(f64::from(q), stored[k]);
                proptest::prop_assert!(q.next_down() as f64 <= v[k] && v[k] <= q.next_up() as f64);
            }
            let near = Rounding::Nearest.store(v, from, [1.0; 3], round);
            proptest::prop_assert_eq!(near, v.map(|x| f64::from(x as f32)));
        }

        /// Scaled integers (LAS): the same, in metres through the scale.
        #[test]
        fn no_longer_moves_in_scaled_integers(
            from in (-1_000_000i32..1_000_000, -1_000_000i32..1_000_000, -1000i32..1000),
            step in (-50.0f64..50.0, -50.0f64..50.0, -50.0f64..50.0),
            scale in 0.0001f64..0.1,
        ) {
            let from = [from.0, from.1, from.2].map(f64::from);
            let v = [from[0] + step.0, from[1] + step.1, from[2] + step.2];
            let unit = [scale, scale, 2.0 * scale];
            let len = |p: [f64; 3]| (0..3).map(|k| ((p[k] - from[k]) * unit[k]).powi(2)).sum::<f64>();
            let stored = Rounding::NoLonger.store(v, from, unit, |_, x, t| integer_toward(x, t));
            proptest::prop_assert!(len(stored) <= len(v));
            for k in 0..3 {
                proptest::prop_assert_eq!(stored[k].fract(), 0.0);
                proptest::prop_assert!((stored[k] - v[k]).abs() < 1.0);
            }
        }
    }

    #[test]
    fn unmoved_and_special_values_store_as_they_were() {
        let from = [512_000.031_25, 5_123_000.5, 210.25];
        let round = |_: usize, x: f64, t: f64| stored_toward(x, t, ScalarType::F32);
        assert_eq!(Rounding::NoLonger.store(from, from, [1.0; 3], round), from);
        let nan = [f64::NAN; 3];
        assert!(
            Rounding::NoLonger
                .store(nan, nan, [1.0; 3], round)
                .iter()
                .all(|x| x.is_nan())
        );
        // Past float32's range: the largest float, never infinity, on the input's side.
        assert_eq!(
            stored_toward(1e39, 0.0, ScalarType::F32),
            f64::from(f32::MAX)
        );
        assert_eq!(integer_toward(2.5, 2.5), 3.0);
        assert_eq!(integer_toward(2.7, 0.0), 2.0);
        assert_eq!(integer_toward(-2.7, 0.0), -2.0);
        assert_eq!(stored_toward(-2.7, 0.0, ScalarType::I16), -2.0);
        assert_eq!(stored_toward(0.1, 0.0, ScalarType::F64), 0.1);
    }
}
