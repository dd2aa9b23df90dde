//! The PLY payload: fixed-offset position codecs, ascii number parsing and printing, and the
//! streaming walker that reads non-vertex elements (keeping their raw bytes and collecting faces).

use std::fmt::Write as _;
use std::io::{BufRead, Read};
use std::path::Path;

use glam::DVec3;

use super::super::IoError;
use super::header::{PlyElement, PlyEncoding, PlyType};
use crate::points::{Endian, Faces, Rounding, ScalarType, Schema, read_scalar, stored_toward};

/// Largest piece read at once while following counts a file declares (a lying count then fails
/// with "truncated" instead of a huge allocation).
const CHUNK: usize = 1 << 20;

/// Position layouts with a dedicated fixed-offset loop.
#[derive(Debug, Clone, Copy)]
enum Layout {
    F32(Endian),
    F64(Endian),
    Other,
}

/// Decodes and encodes x, y and z at fixed offsets of a record slab.
///
/// Records whose x, y and z share one float type use a monomorphised loop with plain
/// `from_le_bytes`/`from_be_bytes` at fixed offsets; other layouts go through
/// [`Schema::position`] and [`Schema::set_position`].
#[derive(Debug, Clone, Copy)]
pub(super) struct PosCodec {
    layout: Layout,
    offs: [usize; 3],
    record_len: usize,
}

#[inline(always)]
fn take<const N: usize>(r: &[u8], o: usize) -> [u8; N] {
    let mut a = [0; N];
    a.copy_from_slice(&r[o..o + N]);
    a
}

#[inline(always)]
fn dec<const N: usize>(
    records: &[u8],
    rl: usize,
    o: [usize; 3],
    f: impl Fn([u8; N]) -> f64,
    out: &mut Vec<DVec3>,
) {
    out.extend(records.chunks_exact(rl).map(|r| {
        DVec3::new(
            f(take::<N>(r, o[0])),
            f(take::<N>(r, o[1])),
            f(take::<N>(r, o[2])),
        )
    }));
}

#[inline(always)]
fn enc<const N: usize>(
    records: &mut [u8],
    rl: usize,
    o: [usize; 3],
    f: impl Fn(f64) -> [u8; N],
    positions: &[DVec3],
) {
    for (r, p) in records.chunks_exact_mut(rl).zip(positions) {
        r[o[0]..o[0] + N].copy_from_slice(&f(p.x));
        r[o[1]..o[1] + N].copy_from_slice(&f(p.y));
        r[o[2]..o[2] + N].copy_from_slice(&f(p.z));
    }
}

/// [`enc`] for `f32` fields, the records holding the input's positions, rounded as `rounding`
/// says.
fn enc_f32(
    records: &mut [u8],
    (rl, o): (usize, [usize; 3]),
    endian: Endian,
    positions: &[DVec3],
    rounding: Rounding,
) {
    type Get = fn([u8; 4]) -> f32;
    type Put = fn(f32) -> [u8; 4];
    let (get, put): (Get, Put) = match endian {
        Endian::Little => (f32::from_le_bytes, f32::to_le_bytes),
        Endian::Big => (f32::from_be_bytes, f32::to_be_bytes),
    };
    for (r, p) in records.chunks_exact_mut(rl).zip(positions) {
        let from = o.map(|at| f64::from(get(r[at..at + 4].try_into().expect("four bytes"))));
        let stored = rounding.store(p.to_array(), from, [1.0; 3], |_, v, towards| {
            stored_toward(v, towards, ScalarType::F32)
        });
        for (at, v) in o.into_iter().zip(stored) {
            r[at..at + 4].copy_from_slice(&put(v as f32));
        }
    }
}

impl PosCodec {
    /// The codec for `schema`'s x, y and z fields.
    pub fn new(schema: &Schema) -> PosCodec {
        let f = schema.xyz.map(|i| &schema.fields[i]);
        let offs = f.map(|f| f.offset);
        let layout = if f.iter().all(|f| f.ty == ScalarType::F32) {
            Layout::F32(schema.endian)
        } else if f.iter().all(|f| f.ty == ScalarType::F64) {
            Layout::F64(schema.endian)
        } else {
            Layout::Other
        };
        PosCodec {
            layout,
            offs,
            record_len: schema.record_len,
        }
    }

    /// Appends the positions of every record in `records` to `out`.
    pub fn decode(&self, schema: &Schema, records: &[u8], out: &mut Vec<DVec3>) {
        let (rl, o) = (self.record_len, self.offs);
        if rl == 0 {
            return;
        }
        out.reserve(records.len() / rl);
        match self.layout {
            Layout::F32(Endian::Little) => {
                dec(records, rl, o, |b| f32::from_le_bytes(b) as f64, out)
            }
            Layout::F32(Endian::Big) => dec(records, rl, o, |b| f32::from_be_bytes(b) as f64, out),
            Layout::F64(Endian::Little) => dec(records, rl, o, f64::from_le_bytes, out),
            Layout::F64(Endian::Big) => dec(records, rl, o, f64::from_be_bytes, out),
            Layout::Other => out.extend(records.chunks_exact(rl).map(|r| schema.position(r))),
        }
    }

    /// Stores `positions` into the x, y and z fields of the records in `records`, which hold the
    /// input's, rounded as `rounding` says.
    pub fn encode(
        &self,
        schema: &Schema,
        records: &mut [u8],
        positions: &[DVec3],
        rounding: Rounding,
    ) {
        let (rl, o) = (self.record_len, self.offs);
        if rl == 0 {
            return;
        }
        match self.layout {
            Layout::F32(endian) => enc_f32(records, (rl, o), endian, positions, rounding),
            Layout::F64(Endian::Little) => enc(records, rl, o, f64::to_le_bytes, positions),
            Layout::F64(Endian::Big) => enc(records, rl, o, f64::to_be_bytes, positions),
            Layout::Other => {
                for (r, &p) in records.chunks_exact_mut(rl).zip(positions) {
                    schema.move_position(r, p, rounding);
                }
            }
        }
    }
}

/// PLY name of a scalar type, for messages.
pub(super) fn type_name(ty: ScalarType) -> &'static str {
    super::header::type_keyword(ty).unwrap_or(match ty {
        ScalarType::I64 => "int64",
        _ => "uint64",
    })
}

/// Parses an integer token; integral floats (`3.0`, `1e2`) are accepted too.
fn parse_int(tok: &str) -> Option<i64> {
    tok.parse::<i64>().ok().or_else(|| {
        let v: f64 = tok.parse().ok()?;
        (v.fract() == 0.0 && v.abs() < 9.2e18).then_some(v as i64)
    })
}

/// Parses `tok` as a value of type `ty` and stores it little-endian in `out[..ty.size()]`.
/// Returns `None` when the token is not a number or out of the type's range.
pub(super) fn parse_ascii(tok: &str, ty: ScalarType, out: &mut [u8]) -> Option<()> {
    macro_rules! int {
        ($t:ty) => {{
            let v = <$t>::try_from(parse_int(tok)?).ok()?;
            out[..ty.size()].copy_from_slice(&v.to_le_bytes());
        }};
    }
    match ty {
        ScalarType::I8 => int!(i8),
        ScalarType::U8 => int!(u8),
        ScalarType::I16 => int!(i16),
        ScalarType::U16 => int!(u16),
        ScalarType::I32 => int!(i32),
        ScalarType::U32 => int!(u32),
        ScalarType::I64 => int!(i64),
        ScalarType::U64 => {
            let v = tok
                .parse::<u64>()
                .ok()
                .or_else(|| u64::try_from(parse_int(tok)?).ok())?;
            out[..8].copy_from_slice(&v.to_le_bytes());
        }
        ScalarType::F32 => out[..4].copy_from_slice(&tok.parse::<f32>().ok()?.to_le_bytes()),
        ScalarType::F64 => out[..8].copy_from_slice(&tok.parse::<f64>().ok()?.to_le_bytes()),
    }
    Some(())
}

/// Appends `v` as the shortest digits that round-trip in its type (Rust's float formatting).
/// Like C's `%g` (the style of most PLY writers), a decimal exponent below -4 selects exponent
/// notation with a sign and at least two digits (`-3.70248e-05`); so does one of 21 or more (a
/// plain 1e300 would take 300 digits). Everything else prints plainly, as `{}` does (`0.0001`).
fn push_float<T>(v: T, out: &mut String)
where
    T: std::fmt::Display + std::fmt::LowerExp,
{
    let start = out.len();
    let _ = write!(out, "{v:e}");
    // The decimal exponent of the shortest digits (none for NaN and infinities).
    let exp = out[start..].find('e').map(|e| {
        (
            start + e + 1,
            out[start + e + 1..].parse::<i32>().unwrap_or(0),
        )
    });
    match exp {
        Some((at, x)) if !(-4..21).contains(&x) => {
            // Rust writes `1.5e-7` / `1e30`; C writes `1.5e-07` / `1e+30`.
            let fix = match (x < 0, x.unsigned_abs() < 10) {
                (true, true) => "-0",
                (true, false) => "-",
                (false, true) => "+0",
                (false, false) => "+",
            };
            out.replace_range(at..at + usize::from(x < 0), fix);
        }
        _ => {
            out.truncate(start);
            let _ = write!(out, "{v}");
        }
    }
}

/// Appends the ascii text of the value of type `ty` stored in `b` (integers as integers, floats
/// as the shortest text that parses back to the same value of their type).
pub(super) fn format_ascii(b: &[u8], ty: ScalarType, endian: Endian, out: &mut String) {
    macro_rules! int {
        ($t:ty) => {{
            let a = take::<{ std::mem::size_of::<$t>() }>(b, 0);
            let v = match endian {
                Endian::Little => <$t>::from_le_bytes(a),
                Endian::Big => <$t>::from_be_bytes(a),
            };
            let _ = write!(out, "{v}");
        }};
    }
    match ty {
        ScalarType::I8 => int!(i8),
        ScalarType::U8 => int!(u8),
        ScalarType::I16 => int!(i16),
        ScalarType::U16 => int!(u16),
        ScalarType::I32 => int!(i32),
        ScalarType::U32 => int!(u32),
        ScalarType::I64 => int!(i64),
        ScalarType::U64 => int!(u64),
        ScalarType::F32 => push_float(read_scalar(b, ty, endian) as f32, out),
        ScalarType::F64 => push_float(read_scalar(b, ty, endian), out),
    }
}

/// Reads an integer of type `ty` (floats are truncated; only integer types are passed).
pub(super) fn read_int(b: &[u8], ty: ScalarType, endian: Endian) -> i64 {
    macro_rules! rd {
        ($t:ty) => {{
            let a = take::<{ std::mem::size_of::<$t>() }>(b, 0);
            (match endian {
                Endian::Little => <$t>::from_le_bytes(a),
                Endian::Big => <$t>::from_be_bytes(a),
            }) as i64
        }};
    }
    match ty {
        ScalarType::I8 => b[0] as i8 as i64,
        ScalarType::U8 => b[0] as i64,
        ScalarType::I16 => rd!(i16),
        ScalarType::U16 => rd!(u16),
        ScalarType::I32 => rd!(i32),
        ScalarType::U32 => rd!(u32),
        ScalarType::I64 => rd!(i64),
        ScalarType::U64 => rd!(u64),
        ScalarType::F32 | ScalarType::F64 => read_scalar(b, ty, endian) as i64,
    }
}

/// A 64-bit FNV-1a digest of a face set, to notice faces changed since they were read.
pub(super) fn faces_digest(faces: &Faces) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &w in faces.offsets.iter().chain(&faces.indices) {
        h ^= u64::from(w);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h ^ faces.len() as u64
}

/// Maps end-of-file while following a declared count to `Truncated` with `what` as the detail.
pub(super) fn eof(
    path: &Path,
    what: impl FnOnce() -> String,
) -> impl FnOnce(std::io::Error) -> IoError {
    move |e| {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            IoError::truncated(path, what())
        } else {
            IoError::io(path, e)
        }
    }
}

/// Appends exactly `n` bytes from `r` to `raw`, in pieces of at most [`CHUNK`] bytes.
fn read_append(r: &mut impl Read, raw: &mut Vec<u8>, n: u64) -> std::io::Result<()> {
    let mut left = n;
    while left > 0 {
        let k = left.min(CHUNK as u64) as usize;
        let start = raw.len();
        raw.resize(start + k, 0);
        r.read_exact(&mut raw[start..])?;
        left -= k as u64;
    }
    Ok(())
}

/// Where face indices go while an element is walked.
pub(super) struct FaceTarget<'a> {
    /// Index of the index-list property.
    pub list: usize,
    /// Number of vertices the file declares (indices must be below it).
    pub vertices: u64,
    /// Output.
    pub faces: &'a mut Faces,
}

impl FaceTarget<'_> {
    fn push_index(&mut self, path: &Path, face: u64, v: i64) -> Result<(), IoError> {
        if v < 0 || v as u64 >= self.vertices {
            return Err(IoError::invalid(
                path,
                format!(
                    "face {face} references vertex {v} but the file has {} vertices",
                    self.vertices
                ),
            ));
        }
        self.faces.indices.push(v as u32);
        Ok(())
    }

    fn end_face(&mut self, path: &Path) -> Result<(), IoError> {
        let n = u32::try_from(self.faces.indices.len())
            .map_err(|_| IoError::invalid(path, "more than 2^32 face indices in total"))?;
        self.faces.offsets.push(n);
        Ok(())
    }
}

/// Reads the instances of non-vertex elements from a stream, keeping their raw bytes.
pub(super) struct Walker<'a, R> {
    /// The stream, positioned at the element's first byte.
    pub r: &'a mut R,
    /// File name for errors.
    pub path: &'a Path,
    /// Payload encoding.
    pub encoding: PlyEncoding,
    /// Number of the next ascii line (1-based, counting header lines).
    pub line: &'a mut u64,
}

impl<R: BufRead> Walker<'_, R> {
    /// Reads every instance of `el`, appending its bytes to `raw`; collects faces into `faces`.
    pub fn element(
        &mut self,
        el: &PlyElement,
        raw: &mut Vec<u8>,
        mut faces: Option<FaceTarget<'_>>,
    ) -> Result<(), IoError> {
        if let Some(f) = faces.as_mut() {
            f.faces.offsets.clear();
            f.faces.offsets.push(0);
            f.faces.indices.clear();
            f.faces.offsets.reserve(el.count.min(1 << 20) as usize);
        }
        if self.encoding.is_binary() {
            self.binary(el, raw, faces)
        } else {
            self.ascii(el, raw, faces)
        }
    }

    fn binary(
        &mut self,
        el: &PlyElement,
        raw: &mut Vec<u8>,
        mut faces: Option<FaceTarget<'_>>,
    ) -> Result<(), IoError> {
        let path = self.path;
        let endian = self.encoding.record_endian();
        let n = el.count;
        if let (Some(rl), None) = (el.record_len(), faces.as_ref()) {
            let bytes = n.saturating_mul(rl as u64);
            return read_append(self.r, raw, bytes).map_err(eof(path, || {
                format!(
                    "the file ends inside element `{}` ({n} × {rl} bytes declared)",
                    el.name
                )
            }));
        }
        for i in 0..n {
            let what = || {
                format!(
                    "the file ends inside element `{}` (instance {i} of {n})",
                    el.name
                )
            };
            for (k, p) in el.properties.iter().enumerate() {
                match p.ty {
                    PlyType::Scalar(t) => {
                        read_append(self.r, raw, t.size() as u64).map_err(eof(path, what))?
                    }
                    PlyType::List { count, item } => {
                        let at = raw.len();
                        read_append(self.r, raw, count.size() as u64).map_err(eof(path, what))?;
                        let len = read_int(&raw[at..], count, endian);
                        if len < 0 {
                            return Err(IoError::invalid(
                                path,
                                format!(
                                    "element `{}` {i}: negative list length {len} for `{}`",
                                    el.name, p.name
                                ),
                            ));
                        }
                        let at = raw.len();
                        let sz = item.size();
                        read_append(self.r, raw, len as u64 * sz as u64)
                            .map_err(eof(path, what))?;
                        if let Some(f) = faces.as_mut().filter(|f| f.list == k) {
                            for b in raw[at..].chunks_exact(sz) {
                                f.push_index(path, i, read_int(b, item, endian))?;
                            }
                        }
                    }
                }
            }
            if let Some(f) = faces.as_mut() {
                f.end_face(path)?;
            }
        }
        Ok(())
    }

    fn ascii(
        &mut self,
        el: &PlyElement,
        raw: &mut Vec<u8>,
        mut faces: Option<FaceTarget<'_>>,
    ) -> Result<(), IoError> {
        let path = self.path;
        let mut scratch = [0u8; 8];
        for i in 0..el.count {
            let line = *self.line;
            let start = raw.len();
            let got = self
                .r
                .read_until(b'\n', raw)
                .map_err(|e| IoError::io(path, e))?;
            if got == 0 {
                return Err(IoError::truncated(
                    path,
                    format!(
                        "the file ends after {i} of {} `{}` elements (line {line})",
                        el.count, el.name
                    ),
                ));
            }
            *self.line += 1;
            let text = std::str::from_utf8(&raw[start..])
                .map_err(|_| IoError::invalid(path, format!("line {line} is not text")))?;
            let complete = text.ends_with('\n');
            let mut toks = text.split_ascii_whitespace();
            // `role`: 0 a scalar property, 1 a list length, 2 a list item.
            let mut next = |prop: &str, role: u8, ty: ScalarType| -> Result<i64, IoError> {
                let what = || match role {
                    0 => format!("property `{prop}`"),
                    1 => format!("the length of `{prop}`"),
                    _ => format!("an item of `{prop}`"),
                };
                let tok = toks.next().ok_or_else(|| {
                    if complete {
                        IoError::invalid(
                            path,
                            format!(
                                "line {line}: missing value for {} of `{}` {i}",
                                what(),
                                el.name
                            ),
                        )
                    } else {
                        IoError::truncated(
                            path,
                            format!(
                                "the file ends inside `{}` {i} of {} (line {line})",
                                el.name, el.count
                            ),
                        )
                    }
                })?;
                if parse_ascii(tok, ty, &mut scratch).is_none() {
                    return Err(IoError::invalid(
                        path,
                        format!(
                            "line {line}: `{tok}` is not a valid {} ({} of `{}` {i})",
                            type_name(ty),
                            what(),
                            el.name
                        ),
                    ));
                }
                Ok(if ty.is_float() {
                    0
                } else {
                    read_int(&scratch, ty, Endian::Little)
                })
            };
            for (k, p) in el.properties.iter().enumerate() {
                match p.ty {
                    PlyType::Scalar(t) => {
                        next(&p.name, 0, t)?;
                    }
                    PlyType::List { count, item } => {
                        let len = next(&p.name, 1, count)?;
                        if len < 0 {
                            return Err(IoError::invalid(
                                path,
                                format!("line {line}: negative list length {len} for `{}`", p.name),
                            ));
                        }
                        let mut target = faces.as_mut().filter(|f| f.list == k);
                        for _ in 0..len {
                            let v = next(&p.name, 2, item)?;
                            if let Some(f) = target.as_mut() {
                                f.push_index(path, i, v)?;
                            }
                        }
                    }
                }
            }
            if let Some(extra) = toks.next() {
                return Err(IoError::invalid(
                    path,
                    format!(
                        "line {line}: unexpected value `{extra}` after the properties of `{}` {i}",
                        el.name
                    ),
                ));
            }
            if let Some(f) = faces.as_mut() {
                f.end_face(path)?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::points::Schema;

    #[test]
    fn ascii_numbers_parse_strictly_and_print_shortest() {
        let mut b = [0u8; 8];
        assert!(parse_ascii("255", ScalarType::U8, &mut b).is_some());
        assert!(parse_ascii("256", ScalarType::U8, &mut b).is_none());
        assert!(parse_ascii("-1", ScalarType::U16, &mut b).is_none());
        assert!(parse_ascii("3.0", ScalarType::I16, &mut b).is_some());
        assert!(parse_ascii("3.5", ScalarType::I16, &mut b).is_none());
        assert!(parse_ascii("1e3x", ScalarType::F32, &mut b).is_none());
        assert!(parse_ascii("-2.5e-3", ScalarType::F64, &mut b).is_some());
        let mut s = String::new();
        for (v, want) in [
            (0.1f32, "0.1"),
            (1e-7, "1e-07"),
            (-3.70248e-05, "-3.70248e-05"),
            (0.0001, "0.0001"),
            (-0.000814438, "-0.000814438"),
            (-0.0, "-0"),
            (1e30, "1e+30"),
            (3e-38, "3e-38"),
            (123456.5, "123456.5"),
            (f32::NAN, "NaN"),
            (f32::NEG_INFINITY, "-inf"),
        ] {
            s.clear();
            push_float(v, &mut s);
            assert_eq!(s, want);
            let back = s.parse::<f32>().unwrap();
            assert!(
                back.to_bits() == v.to_bits() || (v.is_nan() && back.is_nan()),
                "{s}"
            );
        }
        s.clear();
        format_ascii(&(-7i16).to_be_bytes(), ScalarType::I16, Endian::Big, &mut s);
        assert_eq!(s, "-7");
        s.clear();
        format_ascii(
            &0.1f64.to_le_bytes(),
            ScalarType::F64,
            Endian::Little,
            &mut s,
        );
        assert_eq!(s, "0.1");
    }

    #[test]
    fn codec_fast_paths_agree_with_schema() {
        use ScalarType::*;
        for endian in [Endian::Little, Endian::Big] {
            for tys in [[F32, F32, F32], [F64, F64, F64], [F32, I16, F64]] {
                let s = Schema::packed(
                    &[("a", U8), ("x", tys[0]), ("y", tys[1]), ("z", tys[2])],
                    endian,
                )
                .unwrap();
                let c = PosCodec::new(&s);
                let pts = [DVec3::new(1.5, -2.0, 3.25), DVec3::new(-0.5, 7.0, 1e3)];
                let mut recs = vec![9u8; 2 * s.record_len];
                c.encode(&s, &mut recs, &pts, Rounding::Nearest);
                assert_eq!(recs[0], 9);
                assert_eq!(recs[s.record_len], 9);
                let mut out = Vec::new();
                c.decode(&s, &recs, &mut out);
                assert_eq!(out, pts);
                let via_schema: Vec<_> = recs.chunks(s.record_len).map(|r| s.position(r)).collect();
                assert_eq!(out, via_schema);
            }
        }
    }

    #[test]
    fn walker_reads_lists_and_rejects_bad_indices() {
        let el = PlyElement {
            name: "face".into(),
            count: 2,
            properties: vec![super::super::header::PlyProperty {
                name: "vertex_indices".into(),
                ty: PlyType::List {
                    count: ScalarType::U8,
                    item: ScalarType::I32,
                },
            }],
        };
        let mut data = Vec::new();
        for f in [[0i32, 1, 2], [2, 1, 3]] {
            data.push(3u8);
            for v in f {
                data.extend_from_slice(&v.to_be_bytes());
            }
        }
        data.extend_from_slice(b"tail");
        let mut r = data.as_slice();
        let mut line = 1;
        let mut faces = Faces::new();
        let mut raw = Vec::new();
        let mut w = Walker {
            r: &mut r,
            path: Path::new("m.ply"),
            encoding: PlyEncoding::BinaryBigEndian,
            line: &mut line,
        };
        w.element(
            &el,
            &mut raw,
            Some(FaceTarget {
                list: 0,
                vertices: 4,
                faces: &mut faces,
            }),
        )
        .unwrap();
        assert_eq!(faces, Faces::from_triangles(&[[0, 1, 2], [2, 1, 3]]));
        assert_eq!(raw, data[..26]);
        assert_eq!(r, b"tail");

        let mut r = data.as_slice();
        let mut w = Walker {
            r: &mut r,
            path: Path::new("m.ply"),
            encoding: PlyEncoding::BinaryBigEndian,
            line: &mut line,
        };
        let e = w
            .element(
                &el,
                &mut Vec::new(),
                Some(FaceTarget {
                    list: 0,
                    vertices: 3,
                    faces: &mut faces,
                }),
            )
            .unwrap_err();
        assert!(matches!(e, IoError::Invalid { .. }));
        assert!(
            e.to_string()
                .contains("face 1 references vertex 3 but the file has 3 vertices"),
            "{e}"
        );
    }
}
