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
//!
//! On LAS input a run holds, without being asked, the withheld points and the noise classes 7
//! and 18 ([`LAS_NOISE`]; `--classes` naming them moves them, `--classes 0-255` moves every
//! class): docs/DECISIONS.md, "LAS noise and withheld points stay".

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use super::{Job, PipelineError};
use crate::io::SourceInfo;
use crate::io::classes::ClassField;
use crate::points::Schema;

/// A set of class codes, as sorted, disjoint and non-adjacent inclusive ranges; never empty.
/// Written `2,6` or `1-6,9` (in flags, query strings and JSON strings; `0-255` is every LAS
/// class); JSON may also give an array of integers.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct ClassList(Vec<(u32, u32)>);

impl ClassList {
    /// True when `code` is one of the list's.
    pub fn contains(&self, code: u32) -> bool {
        let i = self.0.partition_point(|&(_, hi)| hi < code);
        self.0.get(i).is_some_and(|&(lo, _)| lo <= code)
    }

    /// The ranges, ascending, inclusive.
    pub fn ranges(&self) -> &[(u32, u32)] {
        &self.0
    }

    fn new(mut ranges: Vec<(u32, u32)>) -> Result<ClassList, String> {
        if ranges.is_empty() {
            return Err("expected one or more class codes, such as 2,6 or 1-6".into());
        }
        ranges.sort_unstable();
        let mut merged: Vec<(u32, u32)> = Vec::with_capacity(ranges.len());
        for (lo, hi) in ranges {
            match merged.last_mut() {
                Some(last) if lo <= last.1.saturating_add(1) => last.1 = last.1.max(hi),
                _ => merged.push((lo, hi)),
            }
        }
        Ok(ClassList(merged))
    }
}

impl FromStr for ClassList {
    type Err = String;

    fn from_str(s: &str) -> Result<ClassList, String> {
        let code = |t: &str| {
            let t = t.trim();
            t.parse::<u32>()
                .map_err(|_| format!("`{t}` is not a class code (a whole number ≥ 0)"))
        };
        let ranges = s
            .split(',')
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .map(|t| match t.split_once('-') {
                Some((a, b)) => {
                    let (lo, hi) = (code(a)?, code(b)?);
                    if lo > hi {
                        Err(format!("`{t}`: the range ends below its start"))
                    } else {
                        Ok((lo, hi))
                    }
                }
                None => code(t).map(|c| (c, c)),
            })
            .collect::<Result<Vec<(u32, u32)>, String>>()?;
        ClassList::new(ranges)
    }
}

impl fmt::Display for ClassList {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, &(lo, hi)) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            match hi - lo {
                0 => write!(f, "{lo}")?,
                1 => write!(f, "{lo},{hi}")?,
                _ => write!(f, "{lo}-{hi}")?,
            }
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
                f.write_str(
                    "class codes: a string such as \"2,6\" or \"1-6\", or an array of integers",
                )
            }
            fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<ClassList, E> {
                s.parse().map_err(E::custom)
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<ClassList, E> {
                let c = u32::try_from(v).map_err(|_| E::custom("class code too large"))?;
                ClassList::new(vec![(c, c)]).map_err(E::custom)
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut a: A,
            ) -> Result<ClassList, A::Error> {
                let mut codes = Vec::new();
                while let Some(c) = a.next_element::<u32>()? {
                    codes.push((c, c));
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

/// The LAS classes a run holds unless `--classes` names them: 7 (low point, noise) and 18 (high
/// noise). A classifier has already said these returns lie on no surface; pulled onto one, they
/// would look like ground or roof points while still labelled noise.
pub const LAS_NOISE: [u32; 2] = [7, 18];

/// Which points of an input are held: on LAS records, every withheld point and the points of
/// [`LAS_NOISE`] unless `--classes` names them; with `--classes`, every point of a class it does
/// not name.
#[derive(Debug, Clone)]
pub(crate) struct Selection {
    schema: Schema,
    field: ClassField,
    /// `--classes`; `None`: every class but [`LAS_NOISE`] moves.
    moving: Option<ClassList>,
}

impl Selection {
    /// The selection `job` asks for on an input described by `info`; `None` when every point
    /// moves (no `--classes`, and the input is not LAS).
    ///
    /// # Errors
    /// [`PipelineError::NoClassField`] when `--classes` is given and the input has no class
    /// field.
    pub(crate) fn of(job: &Job, info: &SourceInfo) -> Result<Option<Selection>, PipelineError> {
        let field = ClassField::of(&info.schema, info.format.is_las());
        let moving = job.spec.classes.clone();
        let field = match (field, &moving) {
            (Some(f), Some(_)) => f,
            (Some(f), None) if f.is_las() => f,
            (_, None) => return Ok(None),
            (None, Some(_)) => {
                return Err(PipelineError::NoClassField {
                    path: job.input.clone(),
                });
            }
        };
        Ok(Some(Selection {
            schema: info.schema.clone(),
            field,
            moving,
        }))
    }

    /// True when the point of `record` is held.
    pub(crate) fn held(&self, record: &[u8]) -> bool {
        let code = self.field.code(&self.schema, record);
        self.field.withheld(&self.schema, record)
            || match &self.moving {
                Some(m) => !m.contains(code),
                None => LAS_NOISE.contains(&code),
            }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue9_class_lists_parse_sort_and_refuse_junk() {
        let l: ClassList = " 6, 2,6 ".parse().unwrap();
        assert_eq!(l.ranges(), [(2, 2), (6, 6)]);
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

    #[test]
    fn issue9_class_ranges_merge_and_print_back() {
        let l: ClassList = "9,1-6,3-4,7".parse().unwrap();
        assert_eq!(l.ranges(), [(1, 7), (9, 9)]);
        assert_eq!(l.to_string(), "1-7,9");
        for (c, want) in [
            (0, false),
            (1, true),
            (7, true),
            (8, false),
            (9, true),
            (10, false),
        ] {
            assert_eq!(l.contains(c), want, "{c}");
        }
        let all: ClassList = "0-255".parse().unwrap();
        assert!(all.contains(0) && all.contains(255) && !all.contains(256));
        assert_eq!(
            "0-4294967295".parse::<ClassList>().unwrap().ranges().len(),
            1
        );
        assert!(
            "6-2"
                .parse::<ClassList>()
                .unwrap_err()
                .contains("below its start")
        );
        assert!("2-".parse::<ClassList>().is_err());
        assert_eq!("5,6".parse::<ClassList>().unwrap().to_string(), "5,6");
        let s: ClassList = serde_json::from_str("\"0-31\"").unwrap();
        assert_eq!(s.ranges(), [(0, 31)]);
    }
}
