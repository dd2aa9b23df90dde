//! How the fields of a foreign schema (PLY, PCD, text, …) become LAS 1.4 dimensions.
//!
//! # Brief overview
//!
//! ```text
//!  foreign field ──► well-known name and a type that fits? ──► core dimension of PDRF 6/7/8
//!                                      └─ otherwise ──────────► extra bytes (Extra Bytes VLR),
//!                                                              renamed if its name is taken
//! ```
//!
//! | names | core dimension | source types mapped (value kept exactly) |
//! |---|---|---|
//! | `intensity` | intensity (u16) | u8, u16 |
//! | `return_number`, `number_of_returns` | 4-bit return fields | u8 (a value above 15 is a write error) |
//! | `return_numbers`, `classification_flags` | the whole byte 14 / 15 (qemd's LAS names) | u8 |
//! | `classification`, `user_data` | their byte | u8 |
//! | `scan_angle` | scan angle (i16, 0.006° units) | i16 |
//! | `point_source_id` | point source ID (u16) | u8, u16 |
//! | `gps_time`, `time`, `timestamp` | GPS time (f64) | f32, f64, 8–32-bit integers |
//! | `red`/`green`/`blue` (or `r`/`g`/`b`, `diffuse_red`/…), all three | RGB (PDRF 7) | u16; u8 scaled by 257 (0–255 onto 0–65535, exactly invertible) |
//! | `nir` | NIR (PDRF 8) | u16 |
//! | PDRF 0–5's `return_flags`, `classification`, `scan_angle_rank` (a schema with `return_flags`: a LAS source's fields through another format) | return numbers, scan direction and edge; class and its synthetic, key-point and withheld flags; scan angle (the nearest 0.006° step to the whole degree) | u8, u8, i8 |
//!
//! The point format is 6, 7 when RGB is mapped, 8 when NIR is. A field of a well-known name but
//! another type (a float intensity, say) stays an extra-bytes field, and so does every other
//! field; an extra-bytes name that equals a dimension of the point format (as readers such as
//! laspy name them) or an earlier extra field (after the 32-byte limit of the Extra Bytes VLR)
//! gets the prefix `extra_` (and a number if still taken), so no name occurs twice in the file.

use crate::points::{ScalarType, Schema};

/// Where a mapped field goes in a PDRF 6–8 record, and how.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Slot {
    /// One byte.
    Byte(usize),
    /// A 4-bit field: the low (`false`) or high (`true`) nibble of a byte.
    Nibble(usize, bool),
    /// An unsigned 16-bit value.
    U16(usize),
    /// An unsigned 16-bit colour from an 8-bit one (×257).
    Colour8(usize),
    /// A signed 16-bit value.
    I16(usize),
    /// A double.
    F64(usize),
    /// PDRF 0–5's `return_flags` byte: return number and number of returns into byte 14's
    /// nibbles, scan direction and edge of flight line into bits 6 and 7 of byte 15.
    LegacyReturns,
    /// PDRF 0–5's `classification` byte: the class (bits 0–4) into byte 16, the synthetic,
    /// key-point and withheld flags (bits 5–7) into bits 0–2 of byte 15.
    LegacyClass,
    /// PDRF 0–5's `scan_angle_rank` (whole degrees) as the scan angle in 0.006° units (i16 at 18).
    AngleRank,
}

/// The plan for a foreign schema.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Mapping {
    /// Point data record format: 6, 7 or 8.
    pub format: u8,
    /// `(source field, slot)` per field mapped onto a core dimension.
    pub core: Vec<(usize, Slot)>,
    /// `(source field, name written)` per extra-bytes field, in record order.
    pub extras: Vec<(usize, String)>,
}

/// Dimension names of PDRF 6–8 as LAS readers (laspy, PDAL) spell them.
const CORE_NAMES: [&str; 22] = [
    "X",
    "Y",
    "Z",
    "x",
    "y",
    "z",
    "intensity",
    "return_number",
    "number_of_returns",
    "synthetic",
    "key_point",
    "withheld",
    "overlap",
    "scanner_channel",
    "scan_direction_flag",
    "edge_of_flight_line",
    "classification",
    "user_data",
    "scan_angle",
    "point_source_id",
    "gps_time",
    "classification_flags",
];

/// Colour names, the nir name and format-specific names that are taken only in PDRF 7/8.
const COLOUR_NAMES: [&str; 4] = ["red", "green", "blue", "nir"];

/// The slot of a field named `name` of type `ty`, if it maps (colours aside); `legacy`: the
/// schema has PDRF 0–5's `return_flags`, so its `classification` byte holds flags too.
fn slot_of(name: &str, ty: ScalarType, legacy: bool) -> Option<Slot> {
    use ScalarType::*;
    let small_int = matches!(ty, I8 | U8 | I16 | U16 | I32 | U32);
    Some(match (name, ty) {
        ("return_flags", U8) => Slot::LegacyReturns,
        ("classification", U8) if legacy => Slot::LegacyClass,
        ("scan_angle_rank", I8) => Slot::AngleRank,
        ("intensity", U8 | U16) => Slot::U16(12),
        ("return_number", U8) => Slot::Nibble(14, false),
        ("number_of_returns", U8) => Slot::Nibble(14, true),
        ("return_numbers", U8) => Slot::Byte(14),
        ("classification_flags", U8) => Slot::Byte(15),
        ("classification", U8) => Slot::Byte(16),
        ("user_data", U8) => Slot::Byte(17),
        ("scan_angle", I16) => Slot::I16(18),
        ("point_source_id", U8 | U16) => Slot::U16(20),
        ("gps_time" | "time" | "timestamp", _) if ty.is_float() || small_int => Slot::F64(22),
        _ => return None,
    })
}

/// The colour channel (0, 1, 2) a name stands for.
fn channel(name: &str) -> Option<usize> {
    match name {
        "red" | "r" | "diffuse_red" => Some(0),
        "green" | "g" | "diffuse_green" => Some(1),
        "blue" | "b" | "diffuse_blue" => Some(2),
        _ => None,
    }
}

/// The longest prefix of `s` of at most `max` bytes that ends on a character boundary.
fn fit(s: &str, max: usize) -> String {
    let mut end = s.len().min(max);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    s[..end].to_string()
}

/// Maps the non-xyz fields of `schema` onto PDRF 6–8.
pub(super) fn map(schema: &Schema) -> Mapping {
    let fields: Vec<(usize, &str, ScalarType)> = schema
        .fields
        .iter()
        .enumerate()
        .filter(|(i, _)| !schema.xyz.contains(i))
        .map(|(i, f)| (i, f.name.as_str(), f.ty))
        .collect();
    let mut core: Vec<(usize, Slot)> = Vec::new();
    // The bytes (and of byte 15, the bits) a slot writes.
    let bytes = |s: Slot| -> Vec<(usize, u8)> {
        match s {
            Slot::Byte(at) => vec![(at, 0xff)],
            Slot::Nibble(at, high) => vec![(at, if high { 0xf0 } else { 0x0f })],
            Slot::U16(at) | Slot::Colour8(at) | Slot::I16(at) => vec![(at, 0xff), (at + 1, 0xff)],
            Slot::F64(at) => (at..at + 8).map(|b| (b, 0xff)).collect(),
            Slot::LegacyReturns => vec![(14, 0xff), (15, 0xc0)],
            Slot::LegacyClass => vec![(16, 0xff), (15, 0x07)],
            Slot::AngleRank => vec![(18, 0xff), (19, 0xff)],
        }
    };
    let taken = |core: &[(usize, Slot)], s: Slot| {
        let want = bytes(s);
        core.iter().any(|&(_, t)| {
            bytes(t)
                .iter()
                .any(|&(a, m)| want.iter().any(|&(b, n)| a == b && m & n != 0))
        })
    };
    let legacy = fields
        .iter()
        .any(|&(_, name, ty)| name == "return_flags" && ty == ScalarType::U8);
    // RGB only when all three channels are there with one mappable type.
    let mut rgb = [None; 3];
    for &(i, name, ty) in &fields {
        if let Some(c) = channel(name)
            && rgb[c].is_none()
            && matches!(ty, ScalarType::U8 | ScalarType::U16)
        {
            rgb[c] = Some((i, ty));
        }
    }
    let mut format = 6;
    if rgb.iter().all(Option::is_some) {
        format = 7;
        for (c, v) in rgb.iter().enumerate() {
            let (i, ty) = v.expect("all three");
            let at = 30 + 2 * c;
            let slot = if ty == ScalarType::U8 {
                Slot::Colour8(at)
            } else {
                Slot::U16(at)
            };
            core.push((i, slot));
        }
    }
    for &(i, name, ty) in &fields {
        if name == "nir" && ty == ScalarType::U16 && !taken(&core, Slot::U16(36)) {
            format = 8;
            core.push((i, Slot::U16(36)));
        }
    }
    for &(i, name, ty) in &fields {
        if let Some(s) = slot_of(name, ty, legacy)
            && !taken(&core, s)
        {
            core.push((i, s));
        }
    }
    core.sort_by_key(|&(i, _)| i);
    // Everything else is extra bytes, under a name no other dimension has.
    let mut used: Vec<String> = CORE_NAMES.iter().map(|s| (*s).to_string()).collect();
    if format >= 7 {
        used.extend(COLOUR_NAMES[..3].iter().map(|s| (*s).to_string()));
    }
    if format == 8 {
        used.push(COLOUR_NAMES[3].to_string());
    }
    let mut extras = Vec::new();
    for &(i, name, _) in &fields {
        if core.iter().any(|&(j, _)| j == i) {
            continue;
        }
        let mut out = fit(name, 32);
        if used.contains(&out) {
            out = fit(&format!("extra_{name}"), 32);
        }
        let base = out.clone();
        let mut k = 2;
        while used.contains(&out) {
            let tail = format!("_{k}");
            out = fit(&base, 32 - tail.len()) + &tail;
            k += 1;
        }
        used.push(out.clone());
        extras.push((i, out));
    }
    Mapping {
        format,
        core,
        extras,
    }
}

/// Writes `v` (the source value) into `rec` at `slot`, or says why it does not fit.
pub(super) fn store(rec: &mut [u8], slot: Slot, v: f64) -> Result<(), String> {
    match slot {
        Slot::Byte(at) => rec[at] = v as u8,
        Slot::Nibble(at, high) => {
            if !(0.0..=15.0).contains(&v) {
                return Err(format!("{v} does not fit the 4 bits of LAS point format 6"));
            }
            let n = v as u8;
            rec[at] = if high {
                (rec[at] & 0x0f) | (n << 4)
            } else {
                (rec[at] & 0xf0) | n
            };
        }
        Slot::U16(at) => rec[at..at + 2].copy_from_slice(&(v as u16).to_le_bytes()),
        Slot::Colour8(at) => rec[at..at + 2].copy_from_slice(&((v as u16) * 257).to_le_bytes()),
        Slot::I16(at) => rec[at..at + 2].copy_from_slice(&(v as i16).to_le_bytes()),
        Slot::F64(at) => rec[at..at + 8].copy_from_slice(&v.to_le_bytes()),
        Slot::LegacyReturns => {
            let b = v as u8;
            rec[14] = (b & 0x07) | (((b >> 3) & 0x07) << 4);
            rec[15] |= b & 0xc0;
        }
        Slot::LegacyClass => {
            let b = v as u8;
            rec[16] = b & 0x1f;
            rec[15] |= b >> 5;
        }
        Slot::AngleRank => {
            let units = (v / 0.006).round() as i16;
            rec[18..20].copy_from_slice(&units.to_le_bytes());
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::points::Endian;

    fn schema(fields: &[(&str, ScalarType)]) -> Schema {
        let mut all = vec![
            ("x", ScalarType::F32),
            ("y", ScalarType::F32),
            ("z", ScalarType::F32),
        ];
        all.extend_from_slice(fields);
        Schema::packed(&all, Endian::Little).unwrap()
    }

    #[test]
    fn well_known_names_become_core_dimensions() {
        use ScalarType::*;
        let m = map(&schema(&[
            ("intensity", U16),
            ("red", U8),
            ("green", U8),
            ("blue", U8),
            ("time", F64),
            ("classification", U8),
            ("confidence", F32),
        ]));
        assert_eq!(m.format, 7);
        assert_eq!(
            m.core,
            [
                (3, Slot::U16(12)),
                (4, Slot::Colour8(30)),
                (5, Slot::Colour8(32)),
                (6, Slot::Colour8(34)),
                (7, Slot::F64(22)),
                (8, Slot::Byte(16)),
            ]
        );
        assert_eq!(m.extras, [(9, "confidence".to_string())]);
    }

    #[test]
    fn no_name_occurs_twice() {
        use ScalarType::*;
        // A float intensity cannot be a u16 exactly: it stays extra, renamed; so do two
        // classifications, and a long name that equals another after 32 bytes.
        let long = "a_very_long_property_name_that_goes_on_1";
        let long2 = "a_very_long_property_name_that_goes_on_2";
        let m = map(&schema(&[
            ("intensity", F32),
            ("classification", U8),
            ("classification", U8),
            (long, F32),
            (long2, F32),
            ("red", F32),
        ]));
        assert_eq!(m.format, 6);
        let names: Vec<&str> = m.extras.iter().map(|(_, n)| n.as_str()).collect();
        assert_eq!(
            names,
            [
                "extra_intensity",
                "extra_classification",
                "a_very_long_property_name_that_g",
                "extra_a_very_long_property_name_",
                "red"
            ]
        );
        assert!(names.iter().all(|n| n.len() <= 32));
    }

    #[test]
    fn values_are_stored_exactly() {
        let mut rec = [0u8; 36];
        store(&mut rec, Slot::Nibble(14, false), 3.0).unwrap();
        store(&mut rec, Slot::Nibble(14, true), 5.0).unwrap();
        assert_eq!(rec[14], 0x53);
        assert!(store(&mut rec, Slot::Nibble(14, true), 16.0).is_err());
        store(&mut rec, Slot::Colour8(30), 255.0).unwrap();
        assert_eq!(&rec[30..32], &65535u16.to_le_bytes());
        store(&mut rec, Slot::I16(18), -300.0).unwrap();
        assert_eq!(&rec[18..20], &(-300i16).to_le_bytes());
    }

    /// Issue 51: PDRF 0–5's bytes (a LAS source through E57, PLY, …) become PDRF 6's fields, the
    /// class's flags into the flags byte, not into the class.
    #[test]
    fn issue51_legacy_las_fields_map_to_pdrf6() {
        use ScalarType::*;
        let m = map(&schema(&[
            ("return_flags", U8),
            ("classification", U8),
            ("scan_angle_rank", I8),
            ("return_numbers", U8),
        ]));
        assert_eq!(
            m.core,
            [
                (3, Slot::LegacyReturns),
                (4, Slot::LegacyClass),
                (5, Slot::AngleRank)
            ]
        );
        assert_eq!(m.extras, [(6, "return_numbers".to_string())]);
        // Without `return_flags`, `classification` is PDRF 6's whole byte.
        let plain = map(&schema(&[("classification", U8)]));
        assert_eq!(plain.core, [(3, Slot::Byte(16))]);
        let mut rec = [0u8; 30];
        // Return 2 of 3, scan direction, edge; class 2 (ground), synthetic and withheld.
        store(
            &mut rec,
            Slot::LegacyReturns,
            f64::from(2 | (3 << 3) | 0x40 | 0x80),
        )
        .unwrap();
        store(&mut rec, Slot::LegacyClass, f64::from(2 | 0x20 | 0x80)).unwrap();
        store(&mut rec, Slot::AngleRank, -12.0).unwrap();
        assert_eq!(rec[14], 2 | (3 << 4));
        assert_eq!(rec[15], 0x40 | 0x80 | 0x01 | 0x04);
        assert_eq!(rec[16], 2);
        assert_eq!(&rec[18..20], &(-2000i16).to_le_bytes());
    }
}
