//! Which field of a record holds its class, and how to read it.
//!
//! A point's class is the LAS classification (PDRF 6–10 keep the whole byte; PDRF 0–5 keep the
//! class in the low five bits, the top three being the synthetic, key-point and withheld flags),
//! or else a field named `class` or `label` (PLY, PCD — PCL's `PointXYZL` — and text columns of
//! that name, and LAS written from such a file). `qemd denoise --classes` moves only the points
//! of the classes it names, and `qemd harm` reports per class; both read classes through
//! [`ClassField`].

use crate::points::Schema;

/// The class field of a record layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClassField {
    /// Index of the field in the schema.
    index: usize,
    /// The field holds only a class (false: a LAS 1.0–1.3 byte whose top three bits are flags).
    whole: bool,
    /// LAS records: the field and bit of the withheld flag (bit 7 of the classification byte in
    /// formats 0–5, bit 2 of `classification_flags` in 6–10).
    withheld: Option<(usize, u32)>,
}

impl ClassField {
    /// The class field of `schema` (`las`: the records are LAS point records), `None` when it has
    /// none.
    pub fn of(schema: &Schema, las: bool) -> Option<ClassField> {
        if let Some(index) = schema.field_index("classification") {
            // LAS 1.4 formats 6–10 have a whole class byte beside `classification_flags`; the
            // older formats keep flags in the top three bits.
            let flags = schema.field_index("classification_flags");
            let whole = flags.is_some() || !las;
            let withheld = match flags {
                _ if !las => None,
                Some(f) => Some((f, 0x04)),
                None => Some((index, 0x80)),
            };
            return Some(ClassField {
                index,
                whole,
                withheld,
            });
        }
        schema
            .field_index("class")
            .or_else(|| schema.field_index("label"))
            .map(|index| ClassField {
                index,
                whole: true,
                withheld: None,
            })
    }

    /// True when `record` is a LAS point record whose withheld flag is set.
    pub fn withheld(&self, schema: &Schema, record: &[u8]) -> bool {
        self.withheld
            .is_some_and(|(f, bit)| schema.get_f64(record, f) as u32 & bit != 0)
    }

    /// True when the records are LAS point records (the field is their classification).
    pub fn is_las(&self) -> bool {
        self.withheld.is_some()
    }

    /// The class code of `record` (a negative or fractional value reads as its integer part,
    /// saturated at 0).
    pub fn code(&self, schema: &Schema, record: &[u8]) -> u32 {
        let v = schema.get_f64(record, self.index) as u32;
        if self.whole { v } else { v & 31 }
    }

    /// The name of the field.
    pub fn name<'a>(&self, schema: &'a Schema) -> &'a str {
        &schema.fields[self.index].name
    }
}

/// The ASPRS name of LAS classification `code` (LAS 1.4 R15, Table 17), `None` for a code the
/// specification reserves or leaves to users.
pub fn las_class_name(code: u32) -> Option<&'static str> {
    Some(match code {
        0 => "never classified",
        1 => "unclassified",
        2 => "ground",
        3 => "low vegetation",
        4 => "medium vegetation",
        5 => "high vegetation",
        6 => "building",
        7 => "noise",
        8 => "model key-point",
        9 => "water",
        10 => "rail",
        11 => "road surface",
        12 => "overlap",
        13 => "wire guard",
        14 => "wire conductor",
        15 => "transmission tower",
        16 => "wire connector",
        17 => "bridge deck",
        18 => "high noise",
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::points::{Endian, ScalarType};

    /// x, y, z as u8, then `names`, one byte each.
    fn schema(names: &[&str]) -> Schema {
        let mut fields = vec![
            ("x", ScalarType::U8),
            ("y", ScalarType::U8),
            ("z", ScalarType::U8),
        ];
        fields.extend(names.iter().map(|n| (*n, ScalarType::U8)));
        Schema::packed(&fields, Endian::Little).unwrap()
    }

    #[test]
    fn las_classes_drop_the_flag_bits_of_the_old_formats() {
        let old = schema(&["classification"]);
        let f = ClassField::of(&old, true).unwrap();
        // Class 6 with the withheld flag (bit 7).
        assert_eq!(f.code(&old, &[0, 0, 0, 0x80 | 6]), 6);
        assert!(f.withheld(&old, &[0, 0, 0, 0x80 | 6]));
        assert!(!f.withheld(&old, &[0, 0, 0, 0x40 | 6]));
        let new = schema(&["classification", "classification_flags"]);
        let f = ClassField::of(&new, true).unwrap();
        assert_eq!(f.code(&new, &[0, 0, 0, 0x86, 0]), 0x86);
        assert!(f.withheld(&new, &[0, 0, 0, 7, 0x04]));
        assert!(!f.withheld(&new, &[0, 0, 0, 0x86, 0x0b]));
        // Not LAS: the field is a plain number.
        assert_eq!(
            ClassField::of(&old, false)
                .unwrap()
                .code(&old, &[0, 0, 0, 0x86]),
            0x86
        );
    }

    #[test]
    fn class_or_label_fields_are_found_and_others_are_not() {
        let s = schema(&["intensity", "label"]);
        let f = ClassField::of(&s, false).unwrap();
        assert_eq!((f.code(&s, &[0, 0, 0, 9, 4]), f.name(&s)), (4, "label"));
        assert_eq!(ClassField::of(&schema(&["intensity"]), false), None);
    }
}
