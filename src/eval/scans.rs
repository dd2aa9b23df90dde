//! The real-scan protocol (`qemd harm`): how far a method moves the points of a scan, and how much
//! of a known noise it removes, per class.
//!
//! # Brief overview
//!
//! * **Do no harm** ([`harm`]): the scan as it is goes in, a method's output comes out (same
//!   points, same order). Each point's displacement is measured in units of its own 16-NN radius
//!   `r16` in the input (the distance to the farthest of its 16 nearest points, itself counted):
//!   p50, p99 and max per class.
//! * **Known noise** ([`noise_removed`]): the scan is the clean reference, iso Gaussian noise of
//!   σ = 0.3 × its median nearest-neighbour spacing is added (`qemd noise --unit median-spacing`),
//!   the method denoises it. Per class, RMS |denoised − clean| over RMS |noisy − clean| (≤ 1 means
//!   never worse than doing nothing); for planar points (surface variation of the clean 16-NN
//!   ≤ 0.005) the RMS distance to the clean local plane, denoised over noisy.
//!
//! The output's points pair with the input's through [`pair`](super::pairing::pair): by index
//! when the attributes both files keep (GPS time, intensity, …) agree point by point, by those
//! attributes when the output is reordered (COPC) and they identify every point, and otherwise
//! the output is refused.
//!
//! Classes are the scan's own where it has them (LAS `classification`, or a `class`,
//! `classification` or `label` field), the guarded operator's structure classes of the clean scan
//! otherwise. Non-finite points are skipped.

use glam::DVec3;
use rayon::prelude::*;

use super::EvalError;
use super::pairing::{Pairing, pair};
use crate::denoise::structure::{Structure, classify, local_fits};
use crate::geometry::pca_fit;
use crate::io::Cloud;
use crate::io::classes::ClassField;
use crate::neighbours::KnnIndex;

/// Neighbourhood size of the protocol's radius and planes.
pub const K: usize = 16;
/// Largest surface variation of a planar point.
pub const PLANAR: f64 = 0.005;

/// Where a point's class comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ClassSource {
    /// The LAS classification (class bits only).
    Las,
    /// A `class`, `classification` or `label` field.
    Field,
    /// The structure classes of the clean scan.
    Structure,
}

/// Per-point class codes and their names.
#[derive(Debug, Clone)]
pub struct Classes {
    /// Where they come from.
    pub source: ClassSource,
    /// One code per point.
    pub codes: Vec<u32>,
}

impl Classes {
    /// The name of a class code.
    pub fn name(&self, code: u32) -> String {
        match self.source {
            ClassSource::Structure => Structure::ALL
                .get(code as usize)
                .map_or("?".to_string(), |s| s.name().to_string()),
            ClassSource::Las => match crate::io::classes::las_class_name(code) {
                Some(name) => format!("{code} {name}"),
                None => format!("{code}"),
            },
            ClassSource::Field => format!("{code}"),
        }
    }

    /// The distinct codes, ascending.
    pub fn distinct(&self) -> Vec<u32> {
        let mut c = self.codes.clone();
        c.sort_unstable();
        c.dedup();
        c
    }
}

/// The classes of `cloud`: its own, or the structure classes of its positions.
///
/// # Errors
/// Fewer than [`K`] finite points.
pub fn classes_of(cloud: &Cloud) -> Result<Classes, EvalError> {
    let schema = &cloud.info.schema;
    let las = cloud.info.format.is_las();
    if let Some(field) = ClassField::of(schema, las) {
        let codes = cloud
            .records
            .chunks_exact(schema.record_len)
            .map(|r| field.code(schema, r))
            .collect();
        let source = if las {
            ClassSource::Las
        } else {
            ClassSource::Field
        };
        return Ok(Classes { source, codes });
    }
    let (pts, map) = finite(&cloud.positions);
    let graph = Graph::new(&pts)?;
    let fits = local_fits(&pts, &graph.lists);
    let classes = classify(&fits, &graph.lists, &graph.radii2);
    let mut codes = vec![Structure::Degenerate as u32; cloud.positions.len()];
    for (j, &i) in map.iter().enumerate() {
        codes[i] = classes[j] as u32;
    }
    Ok(Classes {
        source: ClassSource::Structure,
        codes,
    })
}

/// The finite points and their indices in the input.
fn finite(p: &[DVec3]) -> (Vec<DVec3>, Vec<usize>) {
    let map: Vec<usize> = (0..p.len()).filter(|&i| p[i].is_finite()).collect();
    (map.iter().map(|&i| p[i]).collect(), map)
}

/// The 16-NN graph of a point set.
struct Graph {
    lists: crate::neighbours::Neighbourhoods,
    radii2: Vec<f64>,
}

impl Graph {
    fn new(pts: &[DVec3]) -> Result<Graph, EvalError> {
        if pts.len() < K {
            return Err(EvalError::Empty {
                what: "scan",
                detail: format!("{} finite points, the protocol needs {K}", pts.len()),
            });
        }
        let origin = crate::denoise::origin_of(pts);
        let index = KnnIndex::build(pts, origin)?;
        let (lists, radii2) = index.knn_all(K)?;
        Ok(Graph { lists, radii2 })
    }
}

/// p50, p99 and max of a sample.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Spread {
    /// Median.
    pub p50: f64,
    /// 99th percentile (nearest rank).
    pub p99: f64,
    /// Largest.
    pub max: f64,
}

impl Spread {
    /// p50, p99 and max of `xs` (zeros when empty).
    pub fn of(mut xs: Vec<f64>) -> Spread {
        if xs.is_empty() {
            return Spread::default();
        }
        xs.sort_unstable_by(f64::total_cmp);
        let at = |q: f64| xs[((q * xs.len() as f64).ceil() as usize).clamp(1, xs.len()) - 1];
        Spread {
            p50: at(0.5),
            p99: at(0.99),
            max: xs[xs.len() - 1],
        }
    }
}

/// Displacements of one class.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct HarmRow {
    /// Class code.
    pub class: u32,
    /// Class name.
    pub name: String,
    /// Points.
    pub count: usize,
    /// Displacement over r16.
    pub relative: Spread,
    /// Displacement in the input's units.
    pub absolute: Spread,
}

/// The do-no-harm table of a scan.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Harm {
    /// Where the classes come from.
    pub classes: ClassSource,
    /// How the output's points were paired with the input's.
    pub pairing: Pairing,
    /// One row per class, then `all`.
    pub rows: Vec<HarmRow>,
}

fn check_same(a: &Cloud, b: &Cloud, what: &'static str) -> Result<(), EvalError> {
    if a.len() != b.len() {
        return Err(EvalError::Empty {
            what,
            detail: format!(
                "has {} points where the reference has {}: the protocol needs the same points in the same order",
                b.len(),
                a.len()
            ),
        });
    }
    Ok(())
}

/// Displacement of each point of `output` from `input` over its r16 in `input`, per class.
///
/// # Errors
/// Different point counts, fewer than 16 finite points.
pub fn harm(input: &Cloud, output: &Cloud, classes: &Classes) -> Result<Harm, EvalError> {
    check_same(input, output, "output")?;
    let (order, pairing) = pair(input, output)?;
    let (pts, map) = finite(&input.positions);
    let graph = Graph::new(&pts)?;
    let d: Vec<(f64, f64)> = (0..pts.len())
        .into_par_iter()
        .map(|j| {
            let i = map[j];
            let q = output.positions[order[i]];
            let m = if q.is_finite() {
                (q - pts[j]).length()
            } else {
                f64::INFINITY
            };
            let r = graph.radii2[j].sqrt();
            (
                m,
                if r > 0.0 {
                    m / r
                } else if m == 0.0 {
                    0.0
                } else {
                    f64::INFINITY
                },
            )
        })
        .collect();
    let mut rows = Vec::new();
    let mut per = |code: Option<u32>, name: String| {
        let sel: Vec<usize> = (0..pts.len())
            .filter(|&j| code.is_none_or(|c| classes.codes[map[j]] == c))
            .collect();
        rows.push(HarmRow {
            class: code.unwrap_or(u32::MAX),
            name,
            count: sel.len(),
            relative: Spread::of(sel.iter().map(|&j| d[j].1).collect()),
            absolute: Spread::of(sel.iter().map(|&j| d[j].0).collect()),
        });
    };
    for c in classes.distinct() {
        per(Some(c), classes.name(c));
    }
    per(None, "all".into());
    Ok(Harm {
        classes: classes.source,
        pairing,
        rows,
    })
}

/// Noise removal in one class.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NoiseRow {
    /// Class code (`u32::MAX` for planar points and for all).
    pub class: u32,
    /// Class name, `planar` or `all`.
    pub name: String,
    /// Points.
    pub count: usize,
    /// RMS error of the noisy input.
    pub noisy: f64,
    /// RMS error of the denoised output.
    pub denoised: f64,
    /// denoised / noisy.
    pub ratio: f64,
}

/// The known-noise table of a scan.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NoiseRemoved {
    /// Where the classes come from.
    pub classes: ClassSource,
    /// Per class, then `all`: RMS |p − clean|.
    pub rows: Vec<NoiseRow>,
    /// Planar points: RMS distance to the clean local plane.
    pub planar: NoiseRow,
}

fn rms(xs: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = xs.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    if n == 0 { 0.0 } else { (s / n as f64).sqrt() }
}

/// The known-noise measures of `denoised` against `clean` and `noisy`.
///
/// # Errors
/// Different point counts, fewer than 16 finite points.
pub fn noise_removed(
    clean: &Cloud,
    noisy: &Cloud,
    denoised: &Cloud,
    classes: &Classes,
) -> Result<NoiseRemoved, EvalError> {
    check_same(clean, noisy, "noisy input")?;
    check_same(clean, denoised, "denoised output")?;
    // The noisy scan pairs with the clean one; the denoised with the noisy.
    let (to_noisy, _) = pair(clean, noisy)?;
    let (to_denoised, _) = pair(noisy, denoised)?;
    // Both in the clean scan's order.
    let noisy: Vec<DVec3> = to_noisy.iter().map(|&k| noisy.positions[k]).collect();
    let denoised: Vec<DVec3> = to_noisy
        .iter()
        .map(|&k| denoised.positions[to_denoised[k]])
        .collect();
    let (pts, map) = finite(&clean.positions);
    let graph = Graph::new(&pts)?;
    // The clean local plane of every point: PCA of its clean 16-NN.
    let planes: Vec<Option<(DVec3, DVec3)>> = (0..pts.len())
        .into_par_iter()
        .map(|j| {
            let v = pts[j];
            let f = pca_fit(graph.lists.get(j).iter().map(|&u| pts[u as usize] - v))?;
            let total: f64 = f.values.iter().sum();
            (f.has_plane() && f.values[0] <= PLANAR * total).then(|| (f.vectors[0], v + f.centroid))
        })
        .collect();
    let err = |c: &[DVec3], j: usize| {
        let q = c[map[j]];
        if q.is_finite() {
            (q - pts[j]).length()
        } else {
            f64::INFINITY
        }
    };
    let row = |code: u32, name: String, sel: &[usize], f: &dyn Fn(&[DVec3], usize) -> f64| {
        let noisy_rms = rms(sel.iter().map(|&j| f(&noisy, j)));
        let den_rms = rms(sel.iter().map(|&j| f(&denoised, j)));
        NoiseRow {
            class: code,
            name,
            count: sel.len(),
            noisy: noisy_rms,
            denoised: den_rms,
            ratio: if noisy_rms > 0.0 {
                den_rms / noisy_rms
            } else {
                0.0
            },
        }
    };
    let mut rows = Vec::new();
    for c in classes.distinct() {
        let sel: Vec<usize> = (0..pts.len())
            .filter(|&j| classes.codes[map[j]] == c)
            .collect();
        rows.push(row(c, classes.name(c), &sel, &err));
    }
    let all: Vec<usize> = (0..pts.len()).collect();
    rows.push(row(u32::MAX, "all".into(), &all, &err));
    let planar_sel: Vec<usize> = (0..pts.len()).filter(|&j| planes[j].is_some()).collect();
    let to_plane = |c: &[DVec3], j: usize| {
        let (n, p) = planes[j].expect("planar points only");
        let q = c[map[j]];
        if q.is_finite() {
            n.dot(q - p).abs()
        } else {
            f64::INFINITY
        }
    };
    let planar = row(u32::MAX, "planar".into(), &planar_sel, &to_plane);
    Ok(NoiseRemoved {
        classes: classes.source,
        rows,
        planar,
    })
}

/// The median distance from a point to its nearest other point (the protocol's noise unit), where
/// exact duplicates are skipped: a point's spacing is the distance to its nearest point at a
/// non-zero distance among its 8 nearest (some scans store every point twice).
///
/// # Errors
/// Fewer than two distinct finite points.
pub fn median_spacing(positions: &[DVec3]) -> Result<f64, EvalError> {
    let (pts, _) = finite(positions);
    if pts.len() < 2 {
        return Err(EvalError::Empty {
            what: "cloud",
            detail: "fewer than two finite points".into(),
        });
    }
    let index = KnnIndex::build(&pts, crate::denoise::origin_of(&pts))?;
    crate::neighbours::median_spacing(&index)?.ok_or_else(|| EvalError::Empty {
        what: "cloud",
        detail: "every point duplicates another".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::points::ScalarType;

    fn grid(n: usize) -> Vec<DVec3> {
        (0..n * n)
            .map(|i| DVec3::new((i % n) as f64, (i / n) as f64, 0.0))
            .collect()
    }

    #[test]
    fn harm_measures_displacement_over_the_16nn_radius() {
        let clean = Cloud::generated(grid(10), None, ScalarType::F64);
        let mut moved = clean.clone();
        moved.positions[55].z += 1.0;
        let classes = classes_of(&clean).unwrap();
        assert_eq!(classes.source, ClassSource::Structure);
        let h = harm(&clean, &moved, &classes).unwrap();
        let all = h.rows.last().unwrap();
        assert_eq!(all.count, 100);
        assert_eq!(all.absolute.max, 1.0);
        // The 16-NN radius of an interior grid point is √5 (itself, 4 at 1, 4 at √2, 4 at 2, then
        // 8 at √5).
        assert!(
            (all.relative.max - 1.0 / 5f64.sqrt()).abs() < 1e-12,
            "{}",
            all.relative.max
        );
        assert_eq!(all.relative.p50, 0.0);
        assert!(
            harm(
                &clean,
                &Cloud::generated(grid(9), None, ScalarType::F64),
                &classes
            )
            .is_err()
        );
    }

    #[test]
    fn issue47_harm_pairs_a_reordered_output_by_gps_time() {
        use crate::eval::pairing::timed_at;
        // A 10 × 10 grid with a GPS time per point; the output moves point 55 by 1 and is
        // written in reverse order (as an octree writer reorders).
        let with_times = |pos: Vec<DVec3>, times: Vec<f64>| timed_at(&pos, &times, 0);
        let pos = grid(10);
        let times: Vec<f64> = (0..100).map(|i| 1000.0 + i as f64 * 1e-3).collect();
        let input = with_times(pos.clone(), times.clone());
        let mut moved = pos.clone();
        moved[55].z += 1.0;
        let output = with_times(
            moved.iter().rev().copied().collect(),
            times.iter().rev().copied().collect(),
        );
        let classes = classes_of(&input).unwrap();
        let h = harm(&input, &output, &classes).unwrap();
        assert!(matches!(h.pairing, Pairing::Attributes { .. }));
        let all = h.rows.last().unwrap();
        assert_eq!(all.absolute.max, 1.0);
        assert_eq!(all.relative.p50, 0.0);
        // With a time repeated, the two points alike pair by position (they lie 1 apart).
        let mut dup = times.clone();
        dup[1] = dup[0];
        let input2 = with_times(pos.clone(), dup.clone());
        let output2 = with_times(
            moved.iter().rev().copied().collect(),
            dup.iter().rev().copied().collect(),
        );
        let h2 = harm(&input2, &output2, &classes).unwrap();
        assert_eq!(h2.rows, h.rows);
        assert!(matches!(
            h2.pairing,
            Pairing::Attributes { by_position: 2, .. }
        ));
        // The known-noise table pairs the same way.
        let n = noise_removed(&input, &input, &output, &classes).unwrap();
        assert!((n.rows.last().unwrap().denoised - 0.1).abs() < 1e-12);
    }

    #[test]
    fn noise_removed_is_one_for_the_identity_and_zero_for_the_clean() {
        let clean = Cloud::generated(grid(12), None, ScalarType::F64);
        let mut noisy = clean.clone();
        for (i, p) in noisy.positions.iter_mut().enumerate() {
            p.z += if i % 2 == 0 { 0.1 } else { -0.1 };
        }
        let classes = classes_of(&clean).unwrap();
        let same = noise_removed(&clean, &noisy, &noisy, &classes).unwrap();
        assert!((same.rows.last().unwrap().ratio - 1.0).abs() < 1e-12);
        assert!((same.planar.ratio - 1.0).abs() < 1e-12);
        assert_eq!(same.planar.count, 144);
        let perfect = noise_removed(&clean, &noisy, &clean, &classes).unwrap();
        assert_eq!(perfect.planar.ratio, 0.0);
        assert!((median_spacing(&clean.positions).unwrap() - 1.0).abs() < 1e-12);
    }
}
