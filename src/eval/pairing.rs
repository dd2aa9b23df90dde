//! Which output point is which input point: the pairing `qemd harm` measures moves over.
//!
//! A method's output is paired with its input point by point. Most writers keep the order, but
//! not all: COPC output stores points node by node in its octree. Pairing by position in the file
//! would then measure the distance between unrelated points (a "move" of 705 r16 where the true
//! largest was 0.25, issue 47). So the pairing is proven, not assumed:
//!
//! * The **shared attributes** are the fields both files have under one name and type, except
//!   x, y, z and what a denoiser writes (`classification`, which outliers turn to 7, the `noise`
//!   flag and the written normals): GPS time, intensity, return numbers, ring, time, colours….
//! * When every point's shared attributes equal those of the input point at the same index, the
//!   files pair **by index**.
//! * Otherwise the output is reordered and the files pair **by attributes**: every output point
//!   goes to the input point with the same shared attributes. Where several input points share
//!   them (real scans hold records alike but for x, y, z), the group's points pair by position,
//!   and only when that is unambiguous: each output point's nearest input point of its group is
//!   at most half as far as the second nearest (found through a k-d tree of the group), and the
//!   matching is one-to-one. (A denoiser moves a point by a fraction of its spacing; points alike
//!   in every attribute but position lie apart.)
//! * Otherwise the output is refused in one line: reordered, and not re-pairable.
//! * Files without shared attributes (plain XYZ) pair by index, unchecked, when at least a
//!   quarter of the output points lie nearest to the input point at their own index; otherwise
//!   the output is refused as reordered (nothing else could pair it).

use std::collections::HashMap;

use glam::DVec3;

use super::EvalError;
use crate::io::Cloud;
use crate::neighbours::KnnIndex;

/// Fields a denoiser may change, never used to pair.
const WRITTEN: &[&str] = &[
    "x",
    "y",
    "z",
    "classification",
    "noise",
    "nx",
    "ny",
    "nz",
    "normal_x",
    "normal_y",
    "normal_z",
    "NormalX",
    "NormalY",
    "NormalZ",
    "curvature",
    "Curvature",
    "structure",
    "Structure",
];

/// How the output pairs with the input.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case", tag = "by")]
pub enum Pairing {
    /// Point i is point i, checked on the shared attributes.
    Index {
        /// The attributes compared.
        checked: Vec<String>,
    },
    /// Point i is point i, unchecked (no shared attributes).
    Unchecked,
    /// The output is reordered; each point found by its attributes.
    Attributes {
        /// The attributes that identify the points.
        fields: Vec<String>,
        /// Points in groups alike in those attributes, paired by position.
        by_position: usize,
    },
}

/// For each input point, the index of its output point, and how that was established.
///
/// # Errors
/// [`EvalError::Pairing`] for different point counts, a reordered output whose points the
/// shared attributes do not identify exactly, or one without shared attributes whose points are
/// not in the input's order.
pub fn pair(input: &Cloud, output: &Cloud) -> Result<(Vec<usize>, Pairing), EvalError> {
    let n = input.len();
    if output.len() != n {
        return Err(EvalError::Pairing(format!(
            "the output has {} points where the input has {n}: the protocol needs the same points",
            output.len()
        )));
    }
    let (si, so) = (&input.info.schema, &output.info.schema);
    // (offset in input record, offset in output record, size, name) of each shared field.
    let shared: Vec<(usize, usize, usize, String)> = si
        .fields
        .iter()
        .filter(|f| !WRITTEN.contains(&f.name.as_str()))
        .filter_map(|f| {
            let g = so
                .fields
                .iter()
                .find(|g| g.name == f.name && g.ty == f.ty)?;
            Some((f.offset, g.offset, f.ty.size(), f.name.clone()))
        })
        .collect();
    let names: Vec<String> = shared.iter().map(|s| s.3.clone()).collect();
    if shared.is_empty() || si.endian != so.endian {
        in_place(input, output)?;
        return Ok(((0..n).collect(), Pairing::Unchecked));
    }
    let key = |c: &Cloud, i: usize, input_side: bool| -> Vec<u8> {
        let rl = c.info.schema.record_len;
        let rec = &c.records[i * rl..(i + 1) * rl];
        let mut k = Vec::with_capacity(shared.iter().map(|s| s.2).sum());
        for (a, b, size, _) in &shared {
            let at = if input_side { *a } else { *b };
            k.extend_from_slice(&rec[at..at + size]);
        }
        k
    };
    if (0..n).all(|i| key(input, i, true) == key(output, i, false)) {
        return Ok(((0..n).collect(), Pairing::Index { checked: names }));
    }
    let refuse = |why: String| {
        EvalError::Pairing(format!(
            "its points are not in the input's order and cannot be paired exactly: {why}"
        ))
    };
    let mut groups: HashMap<Vec<u8>, (Vec<usize>, Vec<usize>)> = HashMap::with_capacity(n);
    for i in 0..n {
        groups.entry(key(input, i, true)).or_default().0.push(i);
    }
    for o in 0..n {
        let Some(g) = groups.get_mut(&key(output, o, false)) else {
            return Err(refuse(format!(
                "output point {o} matches no input point on {}",
                names.join(", ")
            )));
        };
        g.1.push(o);
    }
    let mut order = vec![usize::MAX; n];
    let mut by_position = 0;
    // In input order, so the first refusal named is the same on every run.
    let mut keyed: Vec<&(Vec<usize>, Vec<usize>)> = groups.values().collect();
    keyed.sort_unstable_by_key(|g| g.0[0]);
    for (ins, outs) in keyed {
        if ins.len() != outs.len() {
            return Err(refuse(format!(
                "{} input and {} output points share the {} of input point {}",
                ins.len(),
                outs.len(),
                names.join(", "),
                ins[0]
            )));
        }
        if ins.len() == 1 {
            order[ins[0]] = outs[0];
            continue;
        }
        // Input points at one position are interchangeable (same record, same place): the
        // group's distinct positions are indexed, each with its points in input order.
        let mut at: HashMap<[u64; 3], usize> = HashMap::new();
        let mut pts: Vec<DVec3> = Vec::new();
        let mut slots: Vec<std::collections::VecDeque<usize>> = Vec::new();
        for &i in ins {
            let p = input.positions[i];
            let k = *at.entry(p.to_array().map(f64::to_bits)).or_insert_with(|| {
                pts.push(p);
                slots.push(Default::default());
                pts.len() - 1
            });
            slots[k].push_back(i);
        }
        let origin = crate::denoise::origin_of(&pts);
        let index = KnnIndex::build(&pts, origin)?;
        let mut near = Vec::with_capacity(2);
        for &o in outs {
            let q = output.positions[o];
            near.clear();
            index.knn_at((q - origin).to_array(), 2, &mut near);
            let d: Vec<(f64, usize)> = near
                .iter()
                .map(|&k| ((pts[k as usize] - q).length(), k as usize))
                .collect();
            let (d1, k) = d.first().copied().unwrap_or((f64::NAN, 0));
            let d2 = d.get(1).map_or(f64::INFINITY, |x| x.0);
            let slot = (d1 <= 0.5 * d2).then(|| slots[k].pop_front()).flatten();
            let Some(i) = slot else {
                let other = d.get(1).map_or(k, |x| x.1);
                return Err(refuse(format!(
                    "input points {} and {} share the same {} and output point {o} lies about as \
                     near to both",
                    slots[k].front().copied().unwrap_or(ins[0]),
                    slots[other].front().copied().unwrap_or(ins[0]),
                    names.join(", ")
                )));
            };
            order[i] = o;
        }
        by_position += ins.len();
    }
    Ok((
        order,
        Pairing::Attributes {
            fields: names,
            by_position,
        },
    ))
}

/// Without attributes to check, an output is taken in the input's order only when at least a
/// quarter of its points lie nearest to the input point at their own index (ties count as
/// nearest). A denoiser moves points by a fraction of their spacing, so nearly all do; in a
/// reordered file almost none do.
///
/// # Errors
/// [`EvalError::Pairing`] when fewer do.
fn in_place(input: &Cloud, output: &Cloud) -> Result<(), EvalError> {
    use rayon::prelude::*;
    let (pts, map): (Vec<DVec3>, Vec<usize>) = input
        .positions
        .iter()
        .enumerate()
        .filter(|(_, p)| p.is_finite())
        .map(|(i, p)| (*p, i))
        .unzip();
    if pts.is_empty() {
        return Ok(());
    }
    let origin = crate::denoise::origin_of(&pts);
    let index = KnnIndex::build(&pts, origin)?;
    let (own, total) = (0..pts.len())
        .into_par_iter()
        .map_init(Vec::new, |near, j| {
            let q = output.positions[map[j]];
            if !q.is_finite() {
                return (0, 0);
            }
            near.clear();
            index.knn_at((q - origin).to_array(), 1, near);
            let nearest = near
                .first()
                .map_or(f64::INFINITY, |&k| (pts[k as usize] - q).length());
            (usize::from((pts[j] - q).length() <= nearest), 1)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if 4 * own < total {
        return Err(EvalError::Pairing(format!(
            "its points are not in the input's order ({own} of {total} lie nearest to the input \
             point at their index) and it has no attribute in common with the input to pair them \
             by"
        )));
    }
    Ok(())
}

/// A cloud with x, y, z and gps_time (f64) and classification: point i at `positions[i]`, time
/// `times[i]`. For the tests of what pairs.
#[cfg(test)]
pub(crate) fn timed_at(positions: &[DVec3], times: &[f64], class: u8) -> Cloud {
    use crate::points::{Endian, ScalarType, Schema};
    let schema = Schema::packed(
        &[
            ("x", ScalarType::F64),
            ("y", ScalarType::F64),
            ("z", ScalarType::F64),
            ("gps_time", ScalarType::F64),
            ("classification", ScalarType::U8),
        ],
        Endian::Little,
    )
    .expect("a valid schema");
    let mut c = Cloud::generated(positions.to_vec(), None, ScalarType::F64);
    c.records = vec![0; positions.len() * schema.record_len];
    for (i, (p, t)) in positions.iter().zip(times).enumerate() {
        let rec = &mut c.records[i * schema.record_len..(i + 1) * schema.record_len];
        schema.set_position(rec, *p);
        schema.set_f64(rec, 3, *t);
        schema.set_f64(rec, 4, f64::from(class));
    }
    c.info.schema = schema;
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::points::ScalarType;

    /// Point i at (i, 0, 0), time `times[i]`, classification `class`.
    fn timed(times: &[f64], class: u8) -> Cloud {
        let pos: Vec<DVec3> = (0..times.len())
            .map(|i| DVec3::new(i as f64, 0.0, 0.0))
            .collect();
        timed_at(&pos, times, class)
    }

    #[test]
    fn issue47_pairs_by_index_by_attributes_or_refuses() {
        let a = timed(&[1.0, 2.0, 3.0], 2);
        // Same order, a class changed (outliers flagged): by index, checked on gps_time.
        let b = timed(&[1.0, 2.0, 3.0], 7);
        let (order, how) = pair(&a, &b).unwrap();
        assert_eq!(order, vec![0, 1, 2]);
        assert_eq!(
            how,
            Pairing::Index {
                checked: vec!["gps_time".into()]
            }
        );
        // Reordered: found by GPS time.
        let c = timed(&[3.0, 1.0, 2.0], 2);
        let (order, how) = pair(&a, &c).unwrap();
        assert_eq!(order, vec![1, 2, 0]);
        assert!(matches!(how, Pairing::Attributes { .. }));
        // Reordered with two equal times: the two pair by position (they are 1 apart).
        let d = timed(&[1.0, 1.0, 3.0], 2);
        let mut e = timed(&[3.0, 1.0, 1.0], 2);
        e.positions = vec![
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(1.1, 0.0, 0.0),
            DVec3::new(0.0, 0.0, 0.1),
        ];
        let (order, how) = pair(&d, &e).unwrap();
        assert_eq!(order, vec![2, 1, 0]);
        assert_eq!(
            how,
            Pairing::Attributes {
                fields: vec!["gps_time".into()],
                by_position: 2
            }
        );
        // … but not when an output point lies half-way between them.
        e.positions[1] = DVec3::new(0.5, 0.0, 0.0);
        let err = pair(&d, &e).unwrap_err().to_string();
        assert!(
            err.contains("cannot be paired exactly") && !err.contains('\n'),
            "{err}"
        );
        // Another point set: refused; no shared attributes: by index, unchecked.
        assert!(pair(&a, &timed(&[1.0, 2.0, 4.0], 2)).is_err());
        let plain = |pos: Vec<DVec3>| Cloud::generated(pos, None, ScalarType::F64);
        let moved: Vec<DVec3> = a.positions.iter().map(|p| *p + 0.3).collect();
        assert_eq!(pair(&a, &plain(moved)).unwrap().1, Pairing::Unchecked);
        // … unless its points are plainly elsewhere: a reversed line of 10 points is refused.
        let line = timed(&[0.0; 10], 2);
        let reversed: Vec<DVec3> = line.positions.iter().rev().copied().collect();
        let err = pair(&line, &plain(reversed)).unwrap_err().to_string();
        assert!(err.contains("0 of 10 lie nearest"), "{err}");
        assert!(pair(&a, &timed(&[1.0], 2)).is_err());
    }
}
