//! Quality metrics of a denoised mesh or cloud against its clean original (`docs/EVALUATION.md`).
//!
//! # Brief overview
//!
//! [`Reference`] holds the clean input: its scale length L, its surface as a BVH for exact
//! point-to-triangle distances, its face normals and volume, and (built on first use) a k-d tree of
//! its points for the Chamfer distance. [`Reference::evaluate`] measures one result and returns
//! [`Metrics`]; every error is in % of L.
//!
//! * **Correspondence metrics**, when the result has the clean vertex count (and the clean faces,
//!   if it has faces), over the vertices the clean faces reference (all finite points for a clean
//!   cloud), with r = denoised − clean:
//!   `surf_std` / `surf_rms` (standard deviation / RMS of the signed distance from each denoised
//!   vertex to the clean surface), `std_xyz` (√ of the mean over the axes of var(r_axis)),
//!   `ang_deg` (mean angle between corresponding face normals) and `dvol_pct` (relative change of
//!   the enclosed volume, closed clean meshes only).
//!   For a clean cloud, [`Reference::with_surface`] adds the mesh it was sampled from, so that
//!   `surf_std` and `surf_rms` apply to clouds too.
//! * **Point-cloud metrics**, when the result has no faces or no correspondence, over its finite
//!   points: point-to-mesh distance (mean and RMS of the unsigned distance to the clean surface)
//!   and the symmetric Chamfer distance
//!   `½ (mean_{p∈D} min_{q∈C} |p − q| + mean_{q∈C} min_{p∈D} |q − p|)` to the clean points C.
//!
//! # Distances
//!
//! The signed distance is the exact Euclidean distance to the nearest clean triangle, signed by
//! that triangle's normal `(v1 − v0) × (v2 − v0)`. The nearest triangle comes from the BVH of
//! `parry3d-f64`'s `TriMesh` (a best-first descent with exact point–triangle projection). A BVH
//! over the triangles' boxes is exact whatever the triangle sizes; the alternative, a k-d tree of
//! triangle centroids searched within (distance + largest triangle radius), degrades to a linear
//! scan as soon as one long sliver triangle (common in CAD meshes) inflates that radius.
//! Coordinates are taken relative to a fixed origin inside the mesh's box, so georeferenced
//! meshes keep their precision. Sums are exact ([`ExactSum`]), so the numbers do not depend on
//! the thread count.

use std::fmt;
use std::sync::OnceLock;

use glam::DVec3;
use parry3d_f64::math::Vector;
use parry3d_f64::query::PointQueryWithLocation;
use parry3d_f64::shape::TriMesh;
use rayon::prelude::*;

use super::{EvalError, check_faces, is_closed, referenced, scale_length, signed_volume};
use crate::denoise::normals::face_cross;
use crate::denoise::origin_of;
use crate::geometry::ExactSum;
use crate::neighbours::KnnIndex;
use crate::points::Faces;

/// The quality of one denoised result; errors in % of L, `None` where a metric does not apply.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Metrics {
    /// The clean scale length L (mean unique-edge length, or mean nearest-neighbour distance).
    #[serde(rename = "L")]
    pub l: f64,
    /// True when the result corresponds to the clean input vertex by vertex.
    pub correspondence: bool,
    /// Vertices (correspondence) or points (otherwise) that were measured.
    pub vertices: usize,
    /// Standard deviation of the signed distance to the clean surface.
    pub surf_std: Option<f64>,
    /// RMS of the signed distance to the clean surface.
    pub surf_rms: Option<f64>,
    /// √ of the mean over x, y, z of the variance of the residual.
    pub std_xyz: Option<f64>,
    /// Mean angle between corresponding face normals, in degrees.
    pub ang_deg: Option<f64>,
    /// (denoised − clean volume) / |clean volume| · 100, closed clean meshes only.
    pub dvol_pct: Option<f64>,
    /// Mean unsigned distance from the result's points to the clean surface.
    pub point_to_mesh_mean: Option<f64>,
    /// RMS distance from the result's points to the clean surface.
    pub point_to_mesh_rms: Option<f64>,
    /// Symmetric Chamfer distance between the result's points and the clean points.
    pub chamfer: Option<f64>,
    /// Faces left out of `ang_deg` because they have zero area before or after.
    pub skipped_faces: usize,
    /// Non-finite points left out of the point-cloud metrics.
    pub skipped_points: usize,
}

impl fmt::Display for Metrics {
    /// One `name  value` line per metric that applies.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "L                   {:.6e}", self.l)?;
        writeln!(
            f,
            "vertices            {}{}",
            self.vertices,
            if self.correspondence {
                " (vertex correspondence)"
            } else {
                " (points)"
            }
        )?;
        let rows = [
            ("surf_std", self.surf_std, "% L"),
            ("surf_rms", self.surf_rms, "% L"),
            ("std_xyz", self.std_xyz, "% L"),
            ("ang_deg", self.ang_deg, "°"),
            ("dvol_pct", self.dvol_pct, "%"),
            ("point_to_mesh_mean", self.point_to_mesh_mean, "% L"),
            ("point_to_mesh_rms", self.point_to_mesh_rms, "% L"),
            ("chamfer", self.chamfer, "% L"),
        ];
        for (name, v, unit) in rows {
            if let Some(v) = v {
                writeln!(f, "{name:<20}{v:.4} {unit}")?;
            }
        }
        if self.skipped_faces > 0 {
            writeln!(f, "skipped_faces       {}", self.skipped_faces)?;
        }
        if self.skipped_points > 0 {
            writeln!(f, "skipped_points      {}", self.skipped_points)?;
        }
        Ok(())
    }
}

/// The clean surface as a BVH.
struct Surface {
    mesh: TriMesh,
    /// Subtracted from every query (and from the mesh's vertices).
    origin: DVec3,
    /// Unit normal of each BVH triangle.
    normals: Vec<DVec3>,
}

impl Surface {
    /// `None` when no face has area.
    fn build(pos: &[DVec3], faces: &Faces, origin: DVec3) -> Result<Option<Surface>, EvalError> {
        // Compact vertex buffer: only corners of triangles with area, relative to the origin.
        let mut map = vec![u32::MAX; pos.len()];
        let mut vertices = Vec::new();
        let mut indices = Vec::new();
        let mut normals = Vec::new();
        for t in faces.triangles() {
            let c = t.map(|v| pos[v as usize]);
            let n = (c[1] - c[0]).cross(c[2] - c[0]).normalize_or_zero();
            if n == DVec3::ZERO {
                continue;
            }
            indices.push(t.map(|v| {
                let slot = &mut map[v as usize];
                if *slot == u32::MAX {
                    let q = pos[v as usize] - origin;
                    vertices.push(Vector::new(q.x, q.y, q.z));
                    *slot = (vertices.len() - 1) as u32;
                }
                *slot
            }));
            normals.push(n);
        }
        if indices.is_empty() {
            return Ok(None);
        }
        let mesh = TriMesh::new(vertices, indices)
            .map_err(|e| EvalError::Degenerate(format!("clean surface: {e}")))?;
        Ok(Some(Surface {
            mesh,
            origin,
            normals,
        }))
    }

    /// Exact distance from `p` to the surface, signed by the nearest triangle's normal.
    fn signed_distance(&self, p: DVec3) -> f64 {
        let q = p - self.origin;
        let v = Vector::new(q.x, q.y, q.z);
        let (proj, (tri, _)) = self.mesh.project_local_point_and_get_location(v, false);
        let d = v - proj.point;
        let d = DVec3::new(d.x, d.y, d.z);
        let dist = d.length();
        if self.normals[tri as usize].dot(d) < 0.0 {
            -dist
        } else {
            dist
        }
    }
}

/// A k-d tree over a compacted point set.
struct Samples {
    points: Vec<DVec3>,
    index: KnnIndex,
}

impl Samples {
    fn build(points: Vec<DVec3>) -> Result<Samples, EvalError> {
        let index = KnnIndex::build(&points, origin_of(&points))?;
        Ok(Samples { points, index })
    }

    /// Mean distance from each of `queries` to its nearest sample, summed exactly.
    fn mean_nearest(&self, queries: &[DVec3]) -> f64 {
        let origin = self.index.origin();
        let sums: Vec<ExactSum> = queries
            .par_chunks(4096)
            .map(|chunk| {
                let mut out = Vec::with_capacity(1);
                let mut sum = ExactSum::new();
                for &q in chunk {
                    out.clear();
                    let d2 = self.index.knn_at((q - origin).to_array(), 1, &mut out);
                    sum.add(d2.sqrt());
                }
                sum
            })
            .collect();
        merged(&sums).mean()
    }
}

fn merged(parts: &[ExactSum]) -> ExactSum {
    let mut s = ExactSum::new();
    for p in parts {
        s.merge(p);
    }
    s
}

/// Mean, population standard deviation and RMS of `v`, summed exactly.
fn moments(v: &[f64]) -> (f64, f64, f64) {
    let mean = v.iter().copied().collect::<ExactSum>().mean();
    let var = v
        .iter()
        .map(|x| (x - mean) * (x - mean))
        .collect::<ExactSum>()
        .mean();
    let ms = v.iter().map(|x| x * x).collect::<ExactSum>().mean();
    (mean, var.sqrt(), ms.sqrt())
}

/// The clean input, prepared for measuring any number of results against it.
pub struct Reference {
    positions: Vec<DVec3>,
    /// Non-empty faces, or `None` for a cloud.
    faces: Option<Faces>,
    /// The vertices the metrics run over: referenced by a face (mesh) or finite (cloud).
    active: Vec<bool>,
    l: f64,
    closed: bool,
    volume: f64,
    /// Unit clean face normals (zero for zero-area faces).
    face_normals: Vec<DVec3>,
    surface: Option<Surface>,
    /// The clean points as Chamfer samples, built on first use.
    samples: OnceLock<Result<Samples, String>>,
}

impl Reference {
    /// Prepares a clean mesh (`faces` given and non-empty) or cloud.
    ///
    /// # Errors
    /// No points, bad face indices, a referenced vertex that is not finite, L = 0.
    pub fn new(positions: Vec<DVec3>, faces: Option<Faces>) -> Result<Reference, EvalError> {
        let faces = faces.filter(|f| !f.is_empty());
        if positions.is_empty() {
            return Err(EvalError::Empty {
                what: "clean input",
                detail: "no vertices".into(),
            });
        }
        let active = match &faces {
            Some(f) => {
                check_faces(positions.len(), f)?;
                let r = referenced(positions.len(), f);
                if let Some(index) =
                    (0..positions.len()).find(|&i| r[i] && !positions[i].is_finite())
                {
                    return Err(EvalError::NonFinite {
                        what: "clean mesh",
                        index,
                    });
                }
                r
            }
            None => positions.iter().map(|p| p.is_finite()).collect(),
        };
        let l = scale_length(&positions, faces.as_ref())?;
        let (closed, volume, face_normals, surface) = match &faces {
            Some(f) => {
                let origin = origin_of(
                    &positions
                        .iter()
                        .zip(&active)
                        .filter(|(_, a)| **a)
                        .map(|(p, _)| *p)
                        .collect::<Vec<_>>(),
                );
                let normals = f
                    .iter()
                    .map(|face| face_cross(&positions, face).normalize_or_zero())
                    .collect();
                (
                    is_closed(f),
                    signed_volume(&positions, f),
                    normals,
                    Surface::build(&positions, f, origin)?,
                )
            }
            None => (false, 0.0, Vec::new(), None),
        };
        Ok(Reference {
            positions,
            faces,
            active,
            l,
            closed,
            volume,
            face_normals,
            surface,
            samples: OnceLock::new(),
        })
    }

    /// The scale length L.
    pub fn l(&self) -> f64 {
        self.l
    }

    /// Measures distances to the surface of another mesh from now on, typically the mesh a clean
    /// cloud was sampled from: `surf_std`, `surf_rms` and the point-to-mesh errors then apply to
    /// clouds too, while L and the Chamfer samples stay those of the clean input.
    ///
    /// # Errors
    /// Bad face indices, a referenced vertex that is not finite, no face with area.
    pub fn with_surface(
        mut self,
        positions: &[DVec3],
        faces: &Faces,
    ) -> Result<Reference, EvalError> {
        check_faces(positions.len(), faces)?;
        let used = referenced(positions.len(), faces);
        if let Some(index) = (0..positions.len()).find(|&i| used[i] && !positions[i].is_finite()) {
            return Err(EvalError::NonFinite {
                what: "surface mesh",
                index,
            });
        }
        let origin = origin_of(
            &positions
                .iter()
                .zip(&used)
                .filter(|(_, u)| **u)
                .map(|(p, _)| *p)
                .collect::<Vec<_>>(),
        );
        self.surface = Some(Surface::build(positions, faces, origin)?.ok_or_else(|| {
            EvalError::Degenerate("the surface mesh has no face with area".into())
        })?);
        Ok(self)
    }

    /// The clean positions.
    pub fn positions(&self) -> &[DVec3] {
        &self.positions
    }

    /// The clean faces (`None` for a cloud).
    pub fn faces(&self) -> Option<&Faces> {
        self.faces.as_ref()
    }

    /// True for a mesh whose every edge is shared by exactly two faces.
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Exact distance from `p` to the clean surface, signed by the nearest triangle's normal;
    /// `None` for a cloud or a mesh without any face of non-zero area.
    pub fn signed_distance(&self, p: DVec3) -> Option<f64> {
        self.surface.as_ref().map(|s| s.signed_distance(p))
    }

    fn samples(&self) -> Result<&Samples, EvalError> {
        self.samples
            .get_or_init(|| {
                let pts: Vec<DVec3> = self
                    .positions
                    .iter()
                    .zip(&self.active)
                    .filter(|(_, a)| **a)
                    .map(|(p, _)| *p)
                    .collect();
                Samples::build(pts).map_err(|e| e.to_string())
            })
            .as_ref()
            .map_err(|e| EvalError::Degenerate(format!("clean samples: {e}")))
    }

    /// Measures `denoised` (with its faces, if any) against the clean input.
    ///
    /// # Errors
    /// An empty result, bad face indices, a non-finite vertex where vertices correspond.
    pub fn evaluate(
        &self,
        denoised: &[DVec3],
        faces: Option<&Faces>,
    ) -> Result<Metrics, EvalError> {
        let faces = faces.filter(|f| !f.is_empty());
        if denoised.is_empty() {
            return Err(EvalError::Empty {
                what: "denoised input",
                detail: "no vertices".into(),
            });
        }
        if let Some(f) = faces {
            check_faces(denoised.len(), f)?;
        }
        let correspondence = denoised.len() == self.positions.len()
            && match (faces, &self.faces) {
                (None, _) => true,
                (Some(d), Some(c)) => d == c,
                (Some(_), None) => false,
            };
        let scale = 100.0 / self.l;
        let mut m = Metrics {
            l: self.l,
            correspondence,
            vertices: 0,
            surf_std: None,
            surf_rms: None,
            std_xyz: None,
            ang_deg: None,
            dvol_pct: None,
            point_to_mesh_mean: None,
            point_to_mesh_rms: None,
            chamfer: None,
            skipped_faces: 0,
            skipped_points: 0,
        };
        if correspondence {
            self.correspondence_metrics(denoised, scale, &mut m)?;
        }
        if faces.is_none() || !correspondence {
            self.point_metrics(denoised, faces, scale, &mut m)?;
        }
        Ok(m)
    }

    fn correspondence_metrics(
        &self,
        denoised: &[DVec3],
        scale: f64,
        m: &mut Metrics,
    ) -> Result<(), EvalError> {
        let idx: Vec<usize> = (0..denoised.len()).filter(|&i| self.active[i]).collect();
        if let Some(&index) = idx.iter().find(|&&i| !denoised[i].is_finite()) {
            return Err(EvalError::NonFinite {
                what: "denoised",
                index,
            });
        }
        m.vertices = idx.len();
        // std_xyz: residual variance per axis.
        let var: f64 = (0..3)
            .map(|axis| {
                let r: Vec<f64> = idx
                    .iter()
                    .map(|&i| denoised[i][axis] - self.positions[i][axis])
                    .collect();
                moments(&r).1.powi(2)
            })
            .sum();
        m.std_xyz = Some((var / 3.0).sqrt() * scale);
        if let Some(surface) = &self.surface {
            let s: Vec<f64> = idx
                .par_iter()
                .with_min_len(1024)
                .map(|&i| surface.signed_distance(denoised[i]))
                .collect();
            let (_, std, rms) = moments(&s);
            m.surf_std = Some(std * scale);
            m.surf_rms = Some(rms * scale);
        }
        let Some(faces) = &self.faces else {
            return Ok(());
        };
        // ang_deg over faces with area before and after.
        let mut angles = ExactSum::new();
        for (face, nc) in faces.iter().zip(&self.face_normals) {
            let nd = face_cross(denoised, face).normalize_or_zero();
            if *nc == DVec3::ZERO || nd == DVec3::ZERO {
                m.skipped_faces += 1;
                continue;
            }
            angles.add(nc.cross(nd).length().atan2(nc.dot(nd)).to_degrees());
        }
        m.ang_deg = (angles.count() > 0).then(|| angles.mean());
        if self.closed && self.volume != 0.0 {
            let vd = signed_volume(denoised, faces);
            m.dvol_pct = Some((vd - self.volume) / self.volume.abs() * 100.0);
        }
        Ok(())
    }

    fn point_metrics(
        &self,
        denoised: &[DVec3],
        faces: Option<&Faces>,
        scale: f64,
        m: &mut Metrics,
    ) -> Result<(), EvalError> {
        // A different mesh contributes the vertices its faces reference.
        let used = faces.map(|f| referenced(denoised.len(), f));
        let candidates = || {
            denoised
                .iter()
                .enumerate()
                .filter(|(i, _)| used.as_ref().is_none_or(|u| u[*i]))
                .map(|(_, p)| *p)
        };
        let pts: Vec<DVec3> = candidates().filter(|p| p.is_finite()).collect();
        m.skipped_points = candidates().count() - pts.len();
        if pts.is_empty() {
            return Err(EvalError::Empty {
                what: "denoised input",
                detail: "no finite points".into(),
            });
        }
        if !m.correspondence {
            m.vertices = pts.len();
        }
        if let Some(surface) = &self.surface {
            let d: Vec<f64> = pts
                .par_iter()
                .with_min_len(1024)
                .map(|&p| surface.signed_distance(p).abs())
                .collect();
            let (mean, _, rms) = moments(&d);
            m.point_to_mesh_mean = Some(mean * scale);
            m.point_to_mesh_rms = Some(rms * scale);
        }
        let clean = self.samples()?;
        let forward = clean.mean_nearest(&pts);
        let back = Samples::build(pts)?.mean_nearest(&clean.points);
        m.chamfer = Some(0.5 * (forward + back) * scale);
        Ok(())
    }
}

/// Measures `denoised` against `clean` once; see [`Reference`] to measure many results against
/// the same clean input.
///
/// # Errors
/// As [`Reference::new`] and [`Reference::evaluate`].
pub fn evaluate(
    clean: &[DVec3],
    clean_faces: Option<&Faces>,
    denoised: &[DVec3],
    denoised_faces: Option<&Faces>,
) -> Result<Metrics, EvalError> {
    Reference::new(clean.to_vec(), clean_faces.cloned())?.evaluate(denoised, denoised_faces)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::denoise::NormalWeighting;
    use crate::denoise::normals::vertex_normals;
    use crate::eval::{Shape, SurfaceSampler};
    use glam::DQuat;

    fn sphere() -> (Vec<DVec3>, Faces) {
        let m = Shape::Sphere.mesh(3).unwrap();
        (m.positions, m.faces)
    }

    #[test]
    fn clean_against_clean_is_zero() {
        let (pos, faces) = sphere();
        let m = evaluate(&pos, Some(&faces), &pos, Some(&faces)).unwrap();
        assert!(m.correspondence);
        assert_eq!(m.vertices, pos.len());
        assert_eq!(m.surf_std, Some(0.0));
        assert_eq!(m.surf_rms, Some(0.0));
        assert_eq!(m.std_xyz, Some(0.0));
        assert_eq!(m.ang_deg, Some(0.0));
        assert_eq!(m.dvol_pct, Some(0.0));
        assert_eq!(m.chamfer, None);
        // As a point cloud: zero point-to-mesh and Chamfer distances.
        let p = evaluate(&pos, Some(&faces), &pos, None).unwrap();
        assert_eq!(p.point_to_mesh_mean, Some(0.0));
        assert_eq!(p.chamfer, Some(0.0));
        let json = serde_json::to_string(&m).unwrap();
        assert!(json.contains("\"L\":"));
        let back: Metrics = serde_json::from_str(&json).unwrap();
        assert_eq!(back.to_string(), m.to_string());
        assert!(m.to_string().contains("surf_std"));
    }

    #[test]
    fn offset_along_the_normal_shows_in_surf_rms() {
        let (pos, faces) = sphere();
        let r = Reference::new(pos.clone(), Some(faces.clone())).unwrap();
        let delta = 0.05 * r.l();
        let n = vertex_normals(&pos, &faces, NormalWeighting::Area).normals;
        let out: Vec<DVec3> = pos.iter().zip(&n).map(|(p, n)| *p + *n * delta).collect();
        let m = r.evaluate(&out, Some(&faces)).unwrap();
        let expect = delta / r.l() * 100.0;
        let rms = m.surf_rms.unwrap();
        assert!((rms - expect).abs() < 0.03 * expect, "{rms} vs {expect}");
        // Uniform offset: tiny spread, and a signed (outward, positive) distance.
        assert!(m.surf_std.unwrap() < 0.05 * expect);
        assert!(r.signed_distance(out[0]).unwrap() > 0.0);
        let inside: Vec<DVec3> = pos.iter().zip(&n).map(|(p, n)| *p - *n * delta).collect();
        assert!(r.signed_distance(inside[0]).unwrap() < 0.0);
    }

    #[test]
    fn tangential_drift_shows_in_std_xyz_not_surf_std() {
        let (pos, faces) = sphere();
        let r = Reference::new(pos.clone(), Some(faces.clone())).unwrap();
        // Rotate about z: every vertex slides along the sphere by up to ~0.5 L.
        let q = DQuat::from_rotation_z(0.5 * r.l());
        let out: Vec<DVec3> = pos.iter().map(|p| q * *p).collect();
        let m = r.evaluate(&out, Some(&faces)).unwrap();
        let (sx, ss) = (m.std_xyz.unwrap(), m.surf_std.unwrap());
        assert!(sx > 20.0, "std_xyz {sx}");
        assert!(ss < 0.1 * sx, "surf_std {ss} vs std_xyz {sx}");
        assert!(m.dvol_pct.unwrap().abs() < 1e-9);
    }

    #[test]
    fn rotated_face_gives_its_angle() {
        // Two separate triangles; the first one turns by 30° about its centroid.
        let pos = vec![
            DVec3::ZERO,
            DVec3::X,
            DVec3::Y,
            DVec3::new(5.0, 0.0, 0.0),
            DVec3::new(6.0, 0.0, 0.0),
            DVec3::new(5.0, 1.0, 0.0),
        ];
        let faces = Faces::from_triangles(&[[0, 1, 2], [3, 4, 5]]);
        let c = (pos[0] + pos[1] + pos[2]) / 3.0;
        let q = DQuat::from_rotation_x(30f64.to_radians());
        let mut out = pos.clone();
        for p in &mut out[..3] {
            *p = c + q * (*p - c);
        }
        let m = evaluate(&pos, Some(&faces), &out, Some(&faces)).unwrap();
        assert!((m.ang_deg.unwrap() - 15.0).abs() < 1e-9);
        assert_eq!(m.dvol_pct, None, "open mesh");
        // A collapsed face is left out of the angle and counted.
        let mut flat = pos.clone();
        flat[2] = flat[1];
        let m = evaluate(&pos, Some(&faces), &flat, Some(&faces)).unwrap();
        assert_eq!(m.skipped_faces, 1);
        assert_eq!(m.ang_deg, Some(0.0));
    }

    #[test]
    fn scaled_sphere_volume_change() {
        let (pos, faces) = sphere();
        let s: f64 = 1.02;
        let out: Vec<DVec3> = pos.iter().map(|p| *p * s).collect();
        let m = evaluate(&pos, Some(&faces), &out, Some(&faces)).unwrap();
        let expect = (s.powi(3) - 1.0) * 100.0;
        assert!((m.dvol_pct.unwrap() - expect).abs() < 1e-9);
    }

    #[test]
    fn point_cloud_metrics_against_samples() {
        let cube = Shape::Cube.mesh(4).unwrap();
        let clean: Vec<DVec3> = SurfaceSampler::new(&cube.positions, &cube.faces, 3000, 1)
            .unwrap()
            .flatten()
            .collect();
        // The clean cloud is its own reference: no faces, L from the point spacing.
        let r = Reference::new(clean.clone(), None).unwrap();
        let m = r.evaluate(&clean, None).unwrap();
        assert_eq!(m.chamfer, Some(0.0));
        assert_eq!(m.std_xyz, Some(0.0));
        assert_eq!(m.point_to_mesh_mean, None);
        // Against the mesh: points pushed out by δ along the face normal.
        let r = Reference::new(cube.positions.clone(), Some(cube.faces.clone())).unwrap();
        let delta = 0.1 * r.l();
        let pushed: Vec<DVec3> = clean
            .iter()
            .map(|p| {
                let a = p.abs();
                let axis = if a.x >= a.y && a.x >= a.z {
                    DVec3::X * p.x.signum()
                } else if a.y >= a.z {
                    DVec3::Y * p.y.signum()
                } else {
                    DVec3::Z * p.z.signum()
                };
                *p + axis * delta
            })
            .chain([DVec3::NAN])
            .collect();
        let m = r.evaluate(&pushed, None).unwrap();
        assert!(!m.correspondence);
        assert_eq!(m.skipped_points, 1);
        assert_eq!(m.vertices, 3000);
        let mean = m.point_to_mesh_mean.unwrap();
        assert!((mean - 10.0).abs() < 1e-6, "{mean}");
        assert!((m.point_to_mesh_rms.unwrap() - 10.0).abs() < 1e-6);
        // Chamfer against the 98 mesh vertices: positive, finite.
        assert!(m.chamfer.unwrap() > 0.0 && m.chamfer.unwrap().is_finite());
        assert_eq!(m.surf_std, None);
    }

    #[test]
    fn cloud_sampled_from_a_mesh_is_measured_against_that_surface() {
        let cube = Shape::Cube.mesh(4).unwrap();
        let clean: Vec<DVec3> = SurfaceSampler::new(&cube.positions, &cube.faces, 2000, 3)
            .unwrap()
            .flatten()
            .collect();
        let r = Reference::new(clean.clone(), None)
            .unwrap()
            .with_surface(&cube.positions, &cube.faces)
            .unwrap();
        let same = r.evaluate(&clean, None).unwrap();
        assert!(same.surf_rms.unwrap() < 1e-9);
        assert_eq!(same.chamfer, Some(0.0));
        // Every point 0.2 L outwards: surf_rms 20 %, no spread, Chamfer > 0.
        let delta = 0.2 * r.l();
        let out: Vec<DVec3> = clean
            .iter()
            .map(|p| {
                let a = p.abs();
                let n = if a.x >= a.y && a.x >= a.z {
                    DVec3::X * p.x.signum()
                } else if a.y >= a.z {
                    DVec3::Y * p.y.signum()
                } else {
                    DVec3::Z * p.z.signum()
                };
                *p + n * delta
            })
            .collect();
        let m = r.evaluate(&out, None).unwrap();
        assert!(m.correspondence);
        assert!((m.surf_rms.unwrap() - 20.0).abs() < 1e-6);
        assert!(m.surf_std.unwrap() < 1e-6);
        assert!((m.point_to_mesh_mean.unwrap() - 20.0).abs() < 1e-6);
        assert!(m.chamfer.unwrap() > 0.0);
        assert_eq!(m.ang_deg, None);
        assert!(
            Reference::new(clean, None)
                .unwrap()
                .with_surface(&cube.positions, &Faces::from_triangles(&[[0, 0, 1]]))
                .is_err()
        );
    }

    #[test]
    fn bad_inputs_are_errors() {
        let (pos, faces) = sphere();
        assert!(matches!(
            evaluate(&[], None, &pos, None),
            Err(EvalError::Empty { .. })
        ));
        assert!(matches!(
            evaluate(&pos, Some(&faces), &[], None),
            Err(EvalError::Empty { .. })
        ));
        let mut nan = pos.clone();
        nan[3] = DVec3::NAN;
        assert!(matches!(
            evaluate(&pos, Some(&faces), &nan, Some(&faces)),
            Err(EvalError::NonFinite { index: 3, .. })
        ));
        let degenerate = Faces::from_triangles(&[[0, 0, 1]]);
        let m = evaluate(&pos, Some(&degenerate), &pos, Some(&degenerate)).unwrap();
        assert_eq!(m.surf_std, None, "no surface without area");
        assert_eq!(m.std_xyz, Some(0.0));
        let bad = Faces::from_triangles(&[[0, 1, 99_999]]);
        assert!(matches!(
            evaluate(&pos, Some(&bad), &pos, None),
            Err(EvalError::FaceIndex { .. })
        ));
    }
}
