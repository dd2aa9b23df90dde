//! The scorer (`qemd score`): a denoised scan against the simulator's truth, per class.
//!
//! # Brief overview
//!
//! Point `i` of the scored file is return `i` of the truth. Before anything is measured the
//! pairing is checked, and a file that fails is refused in one line naming it:
//!
//! * the point count must be the truth's;
//! * every attribute the file stores that the truth knows must match point by point: `gps_time`,
//!   `time` (PCD: seconds since the first pulse, `f32`), `ring`, `intensity` (LAS 16 bits, KITTI
//!   and PCD reflectance, nuScenes 0–255), so a reordered LAS, PCD or KITTI file is caught
//!   exactly (GPS times are distinct);
//! * files without such attributes (a peer's XYZ output) are refused when more than
//!   [`FAR_SHARE`] of their points lie farther than [`far_bound`] (max(1 m, 20 σ)) from their
//!   truth position: far above any denoiser's move, far below what a reordering does.
//!
//! Then, per kind (the LAS class the truth gives each return), over the **surfaces** (ground,
//! building, car, object) and over **all**:
//!
//! * `dist`: mean distance from the point to the true surface (the scene mesh), for the scored
//!   file and for the input (`--noisy`), and their ratio (1 = nothing removed, lower is better);
//! * `rms`: RMS distance to the noise-free position, scored and input, and their ratio;
//! * with `--calm` (the scored file denoised the noise-free scan): each point's move from the
//!   input (`--noisy`, here the clean scan that went in; else the truth's position) over σ,
//!   p50, p99 and max.
//!
//! Distances are exact (BVH closest points, [`super::bvh`]); means are summed in point order, so
//! the numbers do not depend on the thread count. Non-finite points are counted and left out.

use std::path::Path;

use glam::DVec3;
use rayon::prelude::*;

use super::LidarError;
use super::bvh::Bvh;
use super::kinds::Kind;
use super::truth::Truth;
use super::writers::{kitti_reflectance, nuscenes_intensity, relative_time};
use crate::eval::scans::Spread;
use crate::io::{Cloud, Format};
use crate::points::ScalarType;

/// Largest share of points that may lie beyond [`far_bound`] of their truth.
pub const FAR_SHARE: f64 = 0.01;

/// The distance beyond which a point cannot be a denoised copy of its truth: max(1 m, 20 σ).
pub fn far_bound(sigma: f64) -> f64 {
    (20.0 * sigma).max(1.0)
}

/// How to score.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ScoreSpec {
    /// The scored file denoised the noise-free scan: report moves over σ.
    pub calm: bool,
    /// σ of the moves (default: the truth's).
    pub sigma: Option<f64>,
}

/// One row of the table.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ScoreRow {
    /// Kind name, `surfaces` or `all`.
    pub class: String,
    /// Points (finite in the scored file).
    pub points: usize,
    /// Mean distance to the true surface, scored file.
    pub dist: f64,
    /// Mean distance to the true surface, input.
    pub dist_input: Option<f64>,
    /// `dist / dist_input`.
    pub dist_ratio: Option<f64>,
    /// RMS distance to the noise-free position, scored file.
    pub rms: f64,
    /// The same for the input.
    pub rms_input: Option<f64>,
    /// `rms / rms_input`.
    pub rms_ratio: Option<f64>,
    /// `--calm`: moves from the input over σ.
    pub moves: Option<Spread>,
}

/// The scorer's result.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Score {
    /// The truth's sensor.
    pub sensor: String,
    /// σ used for the moves.
    pub sigma: f64,
    /// Points paired.
    pub points: usize,
    /// Attributes checked point by point.
    pub checked: Vec<String>,
    /// Points farther than [`far_bound`] from their truth (at most [`FAR_SHARE`]).
    pub far: usize,
    /// Non-finite points of the scored file (left out).
    pub nonfinite: usize,
    /// Per kind, then `surfaces`, then `all`.
    pub rows: Vec<ScoreRow>,
}

/// Checks that `cloud` (read from `path`) pairs with `truth` point by point; returns the
/// attributes it compared.
///
/// # Errors
/// [`LidarError::Mismatch`] naming the file.
pub fn check_pairing(truth: &Truth, cloud: &Cloud, path: &Path) -> Result<Vec<String>, LidarError> {
    let shown = path.display();
    let n = truth.returns.len();
    if cloud.len() != n {
        return Err(LidarError::Mismatch(format!(
            "{shown}: {} points where the truth has {n}: the scorer pairs points by index",
            cloud.len()
        )));
    }
    let schema = &cloud.info.schema;
    let format = cloud.info.format;
    type Expect = Box<dyn Fn(&super::truth::TruthReturn) -> f64>;
    let mut checks: Vec<(String, usize, Expect)> = Vec::new();
    let t0 = truth.meta.time_origin;
    for (i, f) in schema.fields.iter().enumerate() {
        let float32 = f.ty == ScalarType::F32;
        let expect: Option<Expect> = match f.name.as_str() {
            "gps_time" if float32 => Some(Box::new(|r| f64::from(r.time as f32))),
            "gps_time" => Some(Box::new(|r| r.time)),
            "time" if float32 => Some(Box::new(move |r| f64::from(relative_time(r.time, t0)))),
            "time" if f.ty == ScalarType::F64 => Some(Box::new(|r| r.time)),
            "ring" => Some(Box::new(|r| f64::from(r.ring))),
            "intensity" if f.ty == ScalarType::U16 => Some(Box::new(|r| f64::from(r.intensity))),
            "intensity" if float32 && format == Format::Nuscenes => {
                Some(Box::new(|r| f64::from(nuscenes_intensity(r.intensity))))
            }
            "intensity" if float32 && matches!(format, Format::Kitti | Format::Pcd) => {
                Some(Box::new(|r| f64::from(kitti_reflectance(r.intensity))))
            }
            _ => None,
        };
        if let Some(e) = expect {
            checks.push((f.name.clone(), i, e));
        }
    }
    let rl = schema.record_len;
    for (name, i, expect) in &checks {
        for (k, r) in truth.returns.iter().enumerate() {
            let got = schema.get_f64(&cloud.records[k * rl..(k + 1) * rl], *i);
            let want = expect(r);
            if got != want {
                return Err(LidarError::Mismatch(format!(
                    "{shown}: point {k} has {name} {got} where the truth has {want}: its points are \
                     not in the truth's order (or not from this truth)"
                )));
            }
        }
    }
    Ok(checks.into_iter().map(|c| c.0).collect())
}

/// Scores `output` (read from `path`) against `truth`; `input` is what went into the denoiser.
///
/// # Errors
/// A file that does not pair with the truth ([`check_pairing`], and the distance bound), a
/// truth without a scene.
pub fn score(
    truth: &Truth,
    output: &Cloud,
    path: &Path,
    input: Option<(&Cloud, &Path)>,
    spec: ScoreSpec,
) -> Result<Score, LidarError> {
    let checked = check_pairing(truth, output, path)?;
    if let Some((c, p)) = input {
        check_pairing(truth, c, p)?;
    }
    let sigma = spec.sigma.unwrap_or(truth.meta.sigma);
    if spec.calm && (sigma.is_nan() || sigma <= 0.0) {
        return Err(LidarError::Param {
            name: "sigma",
            detail: format!("the moves are measured over σ, which must be positive (got {sigma})"),
        });
    }
    let bound = far_bound(truth.meta.sigma);
    let too_far = |cloud: &Cloud, p: &Path| -> Result<usize, LidarError> {
        let far = truth
            .returns
            .iter()
            .zip(&cloud.positions)
            .filter(|(r, q)| q.is_finite() && (**q - r.position).length() > bound)
            .count();
        if far as f64 > FAR_SHARE * truth.returns.len() as f64 {
            return Err(LidarError::Mismatch(format!(
                "{}: {far} of {} points lie farther than {bound} m from their truth position: its \
                 points are not in the truth's order (or not from this truth)",
                p.display(),
                truth.returns.len()
            )));
        }
        Ok(far)
    };
    let far = too_far(output, path)?;
    if let Some((c, p)) = input {
        too_far(c, p)?;
    }
    let bvh = Bvh::new(&truth.positions, &truth.triangles)?;
    let dist = |pts: &[DVec3]| -> Vec<f64> {
        pts.par_iter()
            .map(|&q| {
                if q.is_finite() {
                    bvh.distance(q).0
                } else {
                    f64::NAN
                }
            })
            .collect()
    };
    let d_out = dist(&output.positions);
    let d_in = input.map(|(c, _)| dist(&c.positions));
    let err = |pts: &[DVec3]| -> Vec<f64> {
        pts.iter()
            .zip(&truth.returns)
            .map(|(q, r)| (*q - r.position).length())
            .collect()
    };
    let e_out = err(&output.positions);
    let e_in = input.map(|(c, _)| err(&c.positions));
    let moves: Option<Vec<f64>> = spec.calm.then(|| {
        output
            .positions
            .iter()
            .enumerate()
            .map(|(i, q)| {
                let from = input.map_or(truth.returns[i].position, |(c, _)| c.positions[i]);
                (*q - from).length() / sigma
            })
            .collect()
    });
    let finite: Vec<bool> = output.positions.iter().map(|q| q.is_finite()).collect();
    let nonfinite = finite.iter().filter(|f| !**f).count();
    let row = |class: String, select: &dyn Fn(usize) -> bool| -> ScoreRow {
        let sel: Vec<usize> = (0..finite.len())
            .filter(|&i| finite[i] && select(i))
            .collect();
        let mean = |v: &[f64]| sel.iter().map(|&i| v[i]).sum::<f64>() / sel.len().max(1) as f64;
        let rms = |v: &[f64]| {
            (sel.iter().map(|&i| v[i] * v[i]).sum::<f64>() / sel.len().max(1) as f64).sqrt()
        };
        let ratio = |a: f64, b: Option<f64>| b.map(|b| if b > 0.0 { a / b } else { f64::NAN });
        let dist = mean(&d_out);
        let dist_input = d_in.as_deref().map(mean);
        let r = rms(&e_out);
        let rms_input = e_in.as_deref().map(rms);
        ScoreRow {
            class,
            points: sel.len(),
            dist,
            dist_input,
            dist_ratio: ratio(dist, dist_input),
            rms: r,
            rms_input,
            rms_ratio: ratio(r, rms_input),
            moves: moves
                .as_ref()
                .map(|m| Spread::of(sel.iter().map(|&i| m[i]).collect())),
        }
    };
    let mut rows = Vec::new();
    for k in Kind::ALL {
        if truth.returns.iter().any(|r| r.kind == k) {
            rows.push(row(k.name().to_string(), &|i| truth.returns[i].kind == k));
        }
    }
    rows.push(row("surfaces".into(), &|i| {
        truth.returns[i].kind.is_surface()
    }));
    rows.push(row("all".into(), &|_| true));
    Ok(Score {
        sensor: truth.meta.sensor.clone(),
        sigma,
        points: truth.returns.len(),
        checked,
        far,
        nonfinite,
        rows,
    })
}

impl Score {
    /// The plain table `qemd score` prints.
    pub fn table(&self) -> String {
        let mut s = String::new();
        let input = self.rows.iter().any(|r| r.dist_input.is_some());
        let calm = self.rows.iter().any(|r| r.moves.is_some());
        s.push_str(&format!(
            "{:<16} {:>8} {:>10}",
            "class", "points", "dist mm"
        ));
        if input {
            s.push_str(&format!(" {:>10} {:>7}", "input mm", "ratio"));
        }
        s.push_str(&format!(" {:>10}", "rms mm"));
        if input {
            s.push_str(&format!(" {:>10} {:>7}", "input mm", "ratio"));
        }
        if calm {
            s.push_str(&format!(" {:>8} {:>8} {:>8}", "p50/σ", "p99/σ", "max/σ"));
        }
        s.push('\n');
        let opt = |v: Option<f64>, w: usize, p: usize| {
            v.map_or(format!("{:>w$}", "–"), |x| format!("{x:>w$.p$}"))
        };
        for r in &self.rows {
            s.push_str(&format!(
                "{:<16} {:>8} {:>10.2}",
                r.class,
                r.points,
                r.dist * 1e3
            ));
            if input {
                s.push_str(&format!(
                    " {} {}",
                    opt(r.dist_input.map(|x| x * 1e3), 10, 2),
                    opt(r.dist_ratio, 7, 3)
                ));
            }
            s.push_str(&format!(" {:>10.2}", r.rms * 1e3));
            if input {
                s.push_str(&format!(
                    " {} {}",
                    opt(r.rms_input.map(|x| x * 1e3), 10, 2),
                    opt(r.rms_ratio, 7, 3)
                ));
            }
            if let Some(m) = &r.moves {
                s.push_str(&format!(" {:>8.3} {:>8.3} {:>8.3}", m.p50, m.p99, m.max));
            }
            s.push('\n');
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::lidar::truth::{TruthMeta, TruthReturn};
    use crate::points::{Endian, Schema};

    /// The plane z = 0 (two triangles) and four returns on it.
    fn truth() -> Truth {
        let returns = (0..4)
            .map(|i| TruthReturn {
                position: DVec3::new(i as f64, 1.0, 0.0),
                origin: DVec3::new(0.0, 0.0, 10.0),
                time: 1000.0 + i as f64 * 1e-3,
                kind: if i < 3 { Kind::Ground } else { Kind::Pole },
                object: 0,
                flags: 0,
                ring: i as u16,
                intensity: 100,
            })
            .collect();
        Truth {
            meta: TruthMeta {
                sensor: "test".into(),
                sigma: 0.1,
                seed: 0,
                scene_seed: 0,
                frame: "street".into(),
                frame_origin: DVec3::ZERO,
                time_origin: 1000.0,
            },
            positions: vec![
                DVec3::new(-10.0, -10.0, 0.0),
                DVec3::new(10.0, -10.0, 0.0),
                DVec3::new(10.0, 10.0, 0.0),
                DVec3::new(-10.0, 10.0, 0.0),
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            face_kind: vec![Kind::Ground; 2],
            face_object: vec![0; 2],
            returns,
        }
    }

    /// A cloud with x y z gps_time at `positions`, the times of the truth's returns `order`.
    fn cloud(t: &Truth, positions: &[DVec3], order: &[usize]) -> Cloud {
        let schema = Schema::packed(
            &[
                ("x", ScalarType::F64),
                ("y", ScalarType::F64),
                ("z", ScalarType::F64),
                ("gps_time", ScalarType::F64),
            ],
            Endian::Little,
        )
        .unwrap();
        let mut c = Cloud::generated(positions.to_vec(), None, ScalarType::F64);
        c.records = vec![0; positions.len() * schema.record_len];
        for (i, (p, &k)) in positions.iter().zip(order).enumerate() {
            let rec = &mut c.records[i * schema.record_len..(i + 1) * schema.record_len];
            schema.set_position(rec, *p);
            schema.set_f64(rec, 3, t.returns[k].time);
        }
        c.info.schema = schema;
        c
    }

    #[test]
    fn issue47_scorer_on_a_hand_made_case() {
        let t = truth();
        let path = Path::new("out.ply");
        // Noisy: 0.3, −0.4, 0 and 0.2 above the plane (and along it for the third).
        let noisy: Vec<DVec3> = vec![
            DVec3::new(0.0, 1.0, 0.3),
            DVec3::new(1.0, 1.0, -0.4),
            DVec3::new(2.5, 1.0, 0.0),
            DVec3::new(3.0, 1.0, 0.2),
        ];
        // Denoised: half of every offset.
        let out: Vec<DVec3> = t
            .returns
            .iter()
            .zip(&noisy)
            .map(|(r, n)| r.position + (*n - r.position) / 2.0)
            .collect();
        let order = [0, 1, 2, 3];
        let (oc, nc) = (cloud(&t, &out, &order), cloud(&t, &noisy, &order));
        let s = score(
            &t,
            &oc,
            path,
            Some((&nc, Path::new("in.ply"))),
            ScoreSpec::default(),
        )
        .unwrap();
        assert_eq!(s.checked, vec!["gps_time".to_string()]);
        let ground = &s.rows[0];
        assert_eq!((ground.class.as_str(), ground.points), ("ground", 3));
        assert!((ground.dist_input.unwrap() - 0.7 / 3.0).abs() < 1e-12);
        assert!((ground.dist - 0.35 / 3.0).abs() < 1e-12);
        assert!((ground.dist_ratio.unwrap() - 0.5).abs() < 1e-12);
        let rms_in = ((0.09 + 0.16 + 0.25) / 3.0f64).sqrt();
        assert!((ground.rms_input.unwrap() - rms_in).abs() < 1e-12);
        assert!((ground.rms_ratio.unwrap() - 0.5).abs() < 1e-12);
        let pole = &s.rows[1];
        assert_eq!((pole.class.as_str(), pole.points), ("pole", 1));
        assert!((pole.dist - 0.1).abs() < 1e-12);
        assert_eq!(s.rows[2].class, "surfaces");
        assert_eq!(s.rows[2].points, 3);
        assert_eq!(s.rows[3].points, 4);
        // Calm: moves from the input over σ = 0.1.
        let calm = score(
            &t,
            &oc,
            path,
            Some((&nc, Path::new("in.ply"))),
            ScoreSpec {
                calm: true,
                sigma: None,
            },
        )
        .unwrap();
        let m = calm.rows[3].moves.unwrap();
        assert!((m.max - 2.5).abs() < 1e-9, "{m:?}");
        // Reordered (times of 1 and 0 swapped) and a missing point are refused, naming the file.
        let swapped = cloud(&t, &out, &[1, 0, 2, 3]);
        let e = score(&t, &swapped, path, None, ScoreSpec::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("out.ply: point 0 has gps_time") && !e.contains('\n'),
            "{e}"
        );
        let short = cloud(&t, &out[..3], &order[..3]);
        let e = score(&t, &short, path, None, ScoreSpec::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("out.ply: 3 points where the truth has 4"), "{e}");
        // Without attributes, a shuffled copy is caught by the distance bound.
        let plain = Cloud::generated(vec![out[3], out[2], out[1], out[0]], None, ScalarType::F64);
        let e = score(&t, &plain, path, None, ScoreSpec::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("farther than 2 m"), "{e}");
    }
}
