//! `--classes`: only the points of the named classes move; every point still serves as a
//! neighbour.
//!
//! A LiDAR user denoises ground and buildings (`--classes 2,6`) and leaves vegetation, wires
//! and water exactly as the classifier left them. The class is read per record through
//! [`ClassField`] (LAS classification, or a `class`/`label` field). A point of another class is
//! **held**: it keeps its input position, bit for bit, but its position, normal and plane still
//! take part in its neighbours' steps (a held ground point still flattens the unheld ground
//! around it). Both drivers mark held points from the same records — the in-memory run with a
//! mask, the tiled run with a bit in each spill record — so tiled output stays byte-identical.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use super::{Job, PipelineError};
use crate::io::SourceInfo;
use crate::io::classes::ClassField;
use crate::points::Schema;

/// A set of class codes, sorted and without repeats; never empty. Written `2,6` (in flags,
/// query strings and JSON strings); JSON may also give an array of integers.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct ClassList(Vec<u32>);

impl ClassList {
    /// True when `code` is one of the list's.
    pub fn contains(&self, code: u32) -> bool {
        self.0.binary_search(&code).is_ok()
    }

    /// The codes, ascending.
    pub fn codes(&self) -> &[u32] {
        &self.0
    }

    fn new(mut codes: Vec<u32>) -> Result<ClassList, String> {
        if codes.is_empty() {
            return Err("expected one or more class codes, such as 2,6".into());
        }
        codes.sort_unstable();
        codes.dedup();
        Ok(ClassList(codes))
    }
}

impl FromStr for ClassList {
    type Err = String;

    fn from_str(s: &str) -> Result<ClassList, String> {
        let codes = s
            .split(',')
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .map(|t| {
                t.parse::<u32>()
                    .map_err(|_| format!("`{t}` is not a class code (a whole number ≥ 0)"))
            })
            .collect::<Result<Vec<u32>, String>>()?;
        ClassList::new(codes)
    }
}

impl fmt::Display for ClassList {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, c) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            write!(f, "{c}")?;
        }
        Ok(())
    }
}

impl Serialize for ClassList {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for ClassList {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<ClassList, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = ClassList;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("class codes: a string such as \"2,6\" or an array of integers")
            }
            fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<ClassList, E> {
                s.parse().map_err(E::custom)
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<ClassList, E> {
                let c = u32::try_from(v).map_err(|_| E::custom("class code too large"))?;
                ClassList::new(vec![c]).map_err(E::custom)
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut a: A,
            ) -> Result<ClassList, A::Error> {
                let mut codes = Vec::new();
                while let Some(c) = a.next_element::<u32>()? {
                    codes.push(c);
                }
                ClassList::new(codes).map_err(serde::de::Error::custom)
            }
        }
        d.deserialize_any(V)
    }
}

/// Parses a `--classes` value.
///
/// # Errors
/// Text that is not a comma-separated list of class codes.
pub fn parse(s: &str) -> Result<ClassList, String> {
    s.parse()
}

/// Which points of an input `--classes` holds.
#[derive(Debug, Clone)]
pub(crate) struct Selection {
    schema: Schema,
    field: ClassField,
    moving: ClassList,
}

impl Selection {
    /// The selection `job` asks for on an input described by `info`; `None` without
    /// `--classes`.
    ///
    /// # Errors
    /// [`PipelineError::NoClassField`] when the input has no class field.
    pub(crate) fn of(job: &Job, info: &SourceInfo) -> Result<Option<Selection>, PipelineError> {
        let Some(moving) = job.spec.classes.clone() else {
            return Ok(None);
        };
        let field = ClassField::of(&info.schema, info.format.is_las()).ok_or_else(|| {
            PipelineError::NoClassField {
                path: job.input.clone(),
            }
        })?;
        Ok(Some(Selection {
            schema: info.schema.clone(),
            field,
            moving,
        }))
    }

    /// True when the point of `record` is held (its class is not one that moves).
    pub(crate) fn held(&self, record: &[u8]) -> bool {
        !self.moving.contains(self.field.code(&self.schema, record))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue9_class_lists_parse_sort_and_refuse_junk() {
        let l: ClassList = " 6, 2,6 ".parse().unwrap();
        assert_eq!(l.codes(), [2, 6]);
        assert_eq!(l.to_string(), "2,6");
        assert!(l.contains(6) && !l.contains(3));
        assert!("".parse::<ClassList>().is_err());
        assert!("2,x".parse::<ClassList>().unwrap_err().contains("`x`"));
        assert!("-1".parse::<ClassList>().is_err());
        let j: ClassList = serde_json::from_str("[6, 2]").unwrap();
        assert_eq!(j, l);
        let s: ClassList = serde_json::from_str("\"2,6\"").unwrap();
        assert_eq!(s, l);
        assert_eq!(serde_json::to_string(&l).unwrap(), "\"2,6\"");
        assert!(serde_json::from_str::<ClassList>("[]").is_err());
    }
}
