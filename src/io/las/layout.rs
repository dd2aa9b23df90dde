//! Byte layouts of the LAS public header, VLRs and point data records (PDRF 0–10), and the
//! [`Schema`] that describes a record, extra bytes included.

use std::collections::HashSet;

use crate::points::{Endian, Field, ScalarType, Schema};

/// Byte offsets of the public header fields this backend reads or rewrites.
pub(crate) mod at {
    /// Global encoding (u16).
    pub const GLOBAL_ENCODING: usize = 6;
    /// Version major (u8); minor follows.
    pub const VERSION: usize = 24;
    /// System identifier (32 bytes).
    pub const SYSTEM_ID: usize = 26;
    /// Generating software (32 bytes).
    pub const SOFTWARE: usize = 58;
    /// File creation day of year (u16); year (u16) follows.
    pub const DAY: usize = 90;
    /// Header size (u16).
    pub const HEADER_SIZE: usize = 94;
    /// Offset to point data (u32).
    pub const POINT_DATA: usize = 96;
    /// Number of VLRs (u32).
    pub const VLR_COUNT: usize = 100;
    /// Point data record format (u8).
    pub const FORMAT: usize = 104;
    /// Point data record length (u16).
    pub const RECORD_LEN: usize = 105;
    /// Legacy number of point records (u32).
    pub const LEGACY_COUNT: usize = 107;
    /// Legacy number of points by return (5 × u32).
    pub const LEGACY_BY_RETURN: usize = 111;
    /// X, Y, Z scale factors (3 × f64).
    pub const SCALE: usize = 131;
    /// X, Y, Z offsets (3 × f64).
    pub const OFFSET: usize = 155;
    /// Max X, min X, max Y, min Y, max Z, min Z (6 × f64).
    pub const BOUNDS: usize = 179;
    /// LAS 1.3+: start of the waveform data packet record (u64).
    pub const WAVEFORM: usize = 227;
    /// LAS 1.4: start of the first EVLR (u64).
    pub const FIRST_EVLR: usize = 235;
    /// LAS 1.4: number of EVLRs (u32).
    pub const EVLR_COUNT: usize = 243;
    /// LAS 1.4: number of point records (u64).
    pub const COUNT: usize = 247;
    /// LAS 1.4: number of points by return (15 × u64).
    pub const BY_RETURN: usize = 255;
}

/// Size of the public header every LAS 1.`minor` file must at least have.
pub(crate) fn min_header_size(minor: u8) -> usize {
    match minor {
        0..=2 => 227,
        3 => 235,
        _ => 375,
    }
}

/// Size of a VLR header.
pub(crate) const VLR_HEADER: usize = 54;
/// Size of an EVLR header.
pub(crate) const EVLR_HEADER: usize = 60;
/// Size of one Extra Bytes descriptor.
const EXTRA_BYTES_DESCRIPTOR: usize = 192;

/// Length of the standard part of each point data record format 0–10.
pub(crate) const BASE_LEN: [usize; 11] = [20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67];

/// True for the LAS 1.4 formats 6–10 (4-bit return numbers, classification byte of its own).
pub(crate) fn is_extended(format: u8) -> bool {
    format >= 6
}

/// Byte of the record that holds the return number (low 3 bits, or 4 bits for PDRF 6–10).
pub(crate) const RETURN_BYTE: usize = 14;

/// Byte of the record that holds the classification.
pub(crate) fn classification_byte(format: u8) -> usize {
    if is_extended(format) { 16 } else { 15 }
}

/// Return number (1-based; 0 when the record says 0) of a record of `format`.
pub(crate) fn return_number(format: u8, record: &[u8]) -> usize {
    let b = record[RETURN_BYTE];
    usize::from(if is_extended(format) {
        b & 0x0f
    } else {
        b & 0x07
    })
}

/// The standard fields of point data record format `format` (0–10), in record order.
pub(crate) fn standard_fields(format: u8) -> Vec<(&'static str, ScalarType, usize)> {
    use ScalarType::*;
    let mut f: Vec<(&'static str, ScalarType, usize)> = vec![
        ("x", I32, 0),
        ("y", I32, 4),
        ("z", I32, 8),
        ("intensity", U16, 12),
    ];
    let mut at;
    if is_extended(format) {
        f.extend([
            ("return_numbers", U8, 14),
            ("classification_flags", U8, 15),
            ("classification", U8, 16),
            ("user_data", U8, 17),
            ("scan_angle", I16, 18),
            ("point_source_id", U16, 20),
            ("gps_time", F64, 22),
        ]);
        at = 30;
        if matches!(format, 7 | 8 | 10) {
            f.extend([
                ("red", U16, at),
                ("green", U16, at + 2),
                ("blue", U16, at + 4),
            ]);
            at += 6;
        }
        if matches!(format, 8 | 10) {
            f.push(("nir", U16, at));
            at += 2;
        }
    } else {
        f.extend([
            ("return_flags", U8, 14),
            ("classification", U8, 15),
            ("scan_angle_rank", I8, 16),
            ("user_data", U8, 17),
            ("point_source_id", U16, 18),
        ]);
        at = 20;
        if matches!(format, 1 | 3 | 4 | 5) {
            f.push(("gps_time", F64, at));
            at += 8;
        }
        if matches!(format, 2 | 3 | 5) {
            f.extend([
                ("red", U16, at),
                ("green", U16, at + 2),
                ("blue", U16, at + 4),
            ]);
            at += 6;
        }
    }
    if matches!(format, 4 | 5 | 9 | 10) {
        f.extend([
            ("wave_packet_index", U8, at),
            ("wave_offset", U64, at + 1),
            ("wave_size", U32, at + 9),
            ("wave_return_location", F32, at + 13),
            ("wave_xt", F32, at + 17),
            ("wave_yt", F32, at + 21),
            ("wave_zt", F32, at + 25),
        ]);
        at += 29;
    }
    debug_assert_eq!(at, BASE_LEN[usize::from(format)]);
    f
}

/// Scalar type and count of the field an Extra Bytes descriptor `d` describes: `data_type` 0 is
/// `options` untyped bytes, 1–10 one value, 11–30 (deprecated) two or three; `None` for any
/// other code, which ends the walk.
fn extra_shape(d: &[u8]) -> Option<(ScalarType, usize)> {
    let code = d[2];
    Some(match code {
        0 => (ScalarType::U8, usize::from(d[3])),
        1..=10 => (extra_type(code)?, 1),
        11..=30 => (
            extra_type((code - 1) % 10 + 1)?,
            usize::from((code - 1) / 10 + 1),
        ),
        _ => return None,
    })
}

/// Scalar type of an Extra Bytes `data_type` 1–10.
fn extra_type(code: u8) -> Option<ScalarType> {
    use ScalarType::*;
    Some(match code {
        1 => U8,
        2 => I8,
        3 => U16,
        4 => I16,
        5 => U32,
        6 => I32,
        7 => U64,
        8 => I64,
        9 => F32,
        10 => F64,
        _ => return None,
    })
}

/// The Extra Bytes `data_type` of a scalar type.
pub(crate) fn extra_code(ty: ScalarType) -> u8 {
    use ScalarType::*;
    match ty {
        U8 => 1,
        I8 => 2,
        U16 => 3,
        I16 => 4,
        U32 => 5,
        I32 => 6,
        U64 => 7,
        I64 => 8,
        F32 => 9,
        F64 => 10,
    }
}

/// Text of a NUL-padded fixed-size ASCII field.
pub(crate) fn fixed_str(b: &[u8]) -> String {
    let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
    String::from_utf8_lossy(&b[..end]).into_owned()
}

/// Builds the schema of a record of `format` and `record_len` bytes. Bytes past the standard
/// fields are named from the Extra Bytes VLR payload `extra_vlr` when there is one (arrays as
/// `name_0`, `name_1`, …; undocumented runs as `name_0`…); bytes it does not describe become
/// `extra_<k>` (`u8`, `k` counted from the first extra byte). Duplicate names get a `_2`, `_3`…
/// suffix so that every field name is unique.
pub(crate) fn schema(format: u8, record_len: usize, extra_vlr: Option<&[u8]>) -> Schema {
    let mut fields: Vec<Field> = standard_fields(format)
        .into_iter()
        .map(|(n, ty, offset)| Field {
            name: n.to_string(),
            ty,
            offset,
        })
        .collect();
    let base = BASE_LEN[usize::from(format)];
    let mut names: HashSet<String> = fields.iter().map(|f| f.name.clone()).collect();
    let mut unique = |name: String| {
        let mut n = name.clone();
        let mut k = 2;
        while names.contains(&n) {
            n = format!("{name}_{k}");
            k += 1;
        }
        names.insert(n.clone());
        n
    };
    let mut at = base;
    for d in extra_vlr
        .unwrap_or(&[])
        .chunks_exact(EXTRA_BYTES_DESCRIPTOR)
    {
        let code = d[2];
        let name = fixed_str(&d[4..36]);
        let name = if name.is_empty() {
            format!("extra_{}", at - base)
        } else {
            name
        };
        let Some((ty, count)) = extra_shape(d) else {
            break;
        };
        if count == 0 || at + count * ty.size() > record_len {
            break;
        }
        for i in 0..count {
            let n = if count == 1 && code != 0 {
                name.clone()
            } else {
                format!("{name}_{i}")
            };
            fields.push(Field {
                name: unique(n),
                ty,
                offset: at,
            });
            at += ty.size();
        }
    }
    for k in at..record_len {
        fields.push(Field {
            name: unique(format!("extra_{}", k - base)),
            ty: ScalarType::U8,
            offset: k,
        });
    }
    Schema::new(fields, record_len, Endian::Little).expect("x, y, z fit in every LAS record")
}

/// What a sink that appends extra bytes to a record needs to know of the existing ones.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct ExtraLayout {
    /// The descriptors [`schema`] reads (those before the first it stops at), as raw bytes.
    pub descriptors: Vec<u8>,
    /// First byte after the bytes they describe (the base record length when there are none).
    pub end: usize,
    /// `(offset, scale, offset)` of every field whose descriptor sets a scale or an offset
    /// (options bits 3 and 4): its stored value is `(value − offset) / scale`.
    pub scaled: Vec<(usize, f64, f64)>,
}

/// The [`ExtraLayout`] of a record of `format` and `record_len` bytes described by the Extra
/// Bytes VLR payload `extra_vlr`: the same walk as [`schema`].
pub(crate) fn extra_layout(format: u8, record_len: usize, extra_vlr: Option<&[u8]>) -> ExtraLayout {
    let mut at = BASE_LEN[usize::from(format)];
    let mut out = ExtraLayout::default();
    for d in extra_vlr
        .unwrap_or(&[])
        .chunks_exact(EXTRA_BYTES_DESCRIPTOR)
    {
        let code = d[2];
        let Some((ty, count)) = extra_shape(d) else {
            break;
        };
        if count == 0 || at + count * ty.size() > record_len {
            break;
        }
        let options = d[3];
        for i in 0..count {
            if code != 0 && options & 0x18 != 0 {
                let scale = if options & 0x08 != 0 {
                    get_f64(d, 112 + 8 * i)
                } else {
                    1.0
                };
                let offset = if options & 0x10 != 0 {
                    get_f64(d, 136 + 8 * i)
                } else {
                    0.0
                };
                // A zero or non-finite scale stores nothing usable: take the value as it is.
                let scale = if scale.is_finite() && scale != 0.0 {
                    scale
                } else {
                    1.0
                };
                out.scaled.push((at, scale, offset));
            }
            at += ty.size();
        }
        out.descriptors.extend_from_slice(d);
    }
    out.end = at;
    out
}

/// An Extra Bytes descriptor of `n` (1–255) undocumented bytes (`data_type` 0).
pub(crate) fn undocumented_descriptor(n: u8) -> [u8; EXTRA_BYTES_DESCRIPTOR] {
    let mut d = [0u8; EXTRA_BYTES_DESCRIPTOR];
    d[3] = n;
    d
}

/// One Extra Bytes descriptor for a scalar field named `name`.
pub(crate) fn extra_descriptor(name: &str, ty: ScalarType) -> [u8; EXTRA_BYTES_DESCRIPTOR] {
    let mut d = [0u8; EXTRA_BYTES_DESCRIPTOR];
    d[2] = extra_code(ty);
    let n = name.as_bytes();
    let len = n.len().min(32);
    d[4..4 + len].copy_from_slice(&n[..len]);
    d
}

/// A VLR (`extended == false`, 54-byte header) or EVLR (60-byte header) as raw bytes.
pub(crate) fn vlr_bytes(
    user_id: &str,
    record_id: u16,
    description: &str,
    data: &[u8],
    extended: bool,
) -> Vec<u8> {
    let mut v = Vec::with_capacity(EVLR_HEADER + data.len());
    v.extend_from_slice(&[0, 0]);
    let mut uid = [0u8; 16];
    let n = user_id.len().min(16);
    uid[..n].copy_from_slice(&user_id.as_bytes()[..n]);
    v.extend_from_slice(&uid);
    v.extend_from_slice(&record_id.to_le_bytes());
    if extended {
        v.extend_from_slice(&(data.len() as u64).to_le_bytes());
    } else {
        v.extend_from_slice(&(data.len() as u16).to_le_bytes());
    }
    let mut desc = [0u8; 32];
    let n = description.len().min(32);
    desc[..n].copy_from_slice(&description.as_bytes()[..n]);
    v.extend_from_slice(&desc);
    v.extend_from_slice(data);
    v
}

/// Little-endian field accessors on a byte buffer.
pub(crate) fn get_u16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}

/// Reads a little-endian u32.
pub(crate) fn get_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

/// Reads a little-endian u64.
pub(crate) fn get_u64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

/// Reads a little-endian i32.
pub(crate) fn get_i32(b: &[u8], at: usize) -> i32 {
    i32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

/// Reads a little-endian f64.
pub(crate) fn get_f64(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

/// Writes `v` little-endian at `at`.
pub(crate) fn put(b: &mut [u8], at: usize, v: &[u8]) {
    b[at..at + v.len()].copy_from_slice(v);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn standard_layouts_have_the_spec_lengths() {
        for f in 0..=10u8 {
            let fields = standard_fields(f);
            let (_, ty, off) = fields.last().copied().unwrap();
            assert_eq!(off + ty.size(), BASE_LEN[usize::from(f)], "PDRF {f}");
        }
    }

    #[test]
    fn extra_bytes_are_named_from_the_vlr() {
        let mut vlr = Vec::new();
        vlr.extend_from_slice(&extra_descriptor("height", ScalarType::F32));
        vlr.extend_from_slice(&extra_descriptor("x", ScalarType::I16));
        let mut arr = extra_descriptor("v", ScalarType::U8);
        arr[2] = 21; // three u8
        vlr.extend_from_slice(&arr);
        let s = schema(0, 20 + 4 + 2 + 3 + 2, Some(&vlr));
        let names: Vec<&str> = s.fields.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(
            &names[names.len() - 7..],
            &["height", "x_2", "v_0", "v_1", "v_2", "extra_9", "extra_10"]
        );
        assert_eq!(s.xyz, [0, 1, 2]);
        let h = s.field_index("height").unwrap();
        assert_eq!((s.fields[h].ty, s.fields[h].offset), (ScalarType::F32, 20));
        // No VLR: every extra byte is a u8.
        let s = schema(6, 32, None);
        assert_eq!(s.fields.last().unwrap().name, "extra_1");
    }

    #[test]
    fn issue9_extra_layout_walks_as_the_schema_does() {
        let mut vlr = Vec::new();
        vlr.extend_from_slice(&extra_descriptor("height", ScalarType::F32));
        let mut scaled = extra_descriptor("NormalX", ScalarType::I16);
        scaled[3] = 0x18;
        put(&mut scaled, 112, &(1.0f64 / 32767.0).to_le_bytes());
        put(&mut scaled, 136, &0.5f64.to_le_bytes());
        vlr.extend_from_slice(&scaled);
        vlr.extend_from_slice(&undocumented_descriptor(3));
        // Describes 9 of the 11 extra bytes; a last descriptor that does not fit is dropped.
        vlr.extend_from_slice(&extra_descriptor("far", ScalarType::F64));
        let l = extra_layout(0, 20 + 11, Some(&vlr));
        assert_eq!(l.end, 20 + 9);
        assert_eq!(l.descriptors, vlr[..3 * EXTRA_BYTES_DESCRIPTOR]);
        assert_eq!(l.scaled, vec![(24, 1.0 / 32767.0, 0.5)]);
        let s = schema(0, 20 + 11, Some(&vlr));
        let first_unnamed = s.fields.iter().find(|f| f.name == "extra_9").unwrap();
        assert_eq!(first_unnamed.offset, l.end);
        assert_eq!(extra_layout(6, 30, None).end, 30);
    }
}
