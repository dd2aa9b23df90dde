//! The scene's triangles in a bounding-volume hierarchy: exact ray casts for the simulator and
//! exact closest points for the scorer.
//!
//! Both go through `parry3d-f64`'s `TriMesh` (its BVH, `RayCast` and point projection): a ray
//! cast returns the time of impact along a unit direction (so the range in metres), the triangle
//! hit and its normal; a projection returns the nearest point of the nearest triangle. Triangles
//! are hit from either side. Coordinates are used as they are: a scene's frame is local (the
//! street's, or a sensor's), never georeferenced.

use glam::DVec3;
use parry3d_f64::math::Vector;
use parry3d_f64::query::{PointQueryWithLocation, Ray, RayCast};
use parry3d_f64::shape::TriMesh;

use super::LidarError;

/// A ray's first hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) direction.
    pub range: f64,
    /// The triangle hit.
    pub triangle: u32,
    /// The triangle's unit normal (either side).
    pub normal: DVec3,
}

/// Triangles in a BVH.
pub struct Bvh {
    mesh: TriMesh,
}

fn vector(p: DVec3) -> Vector {
    Vector::new(p.x, p.y, p.z)
}

fn dvec(v: Vector) -> DVec3 {
    DVec3::new(v.x, v.y, v.z)
}

impl Bvh {
    /// The BVH of `triangles` over `positions`; triangle ids are indices into `triangles`.
    ///
    /// # Errors
    /// [`LidarError::Scene`] without triangles.
    pub fn new(positions: &[DVec3], triangles: &[[u32; 3]]) -> Result<Bvh, LidarError> {
        if triangles.is_empty() {
            return Err(LidarError::Scene("the scene has no triangles".into()));
        }
        let vertices = positions.iter().map(|&p| vector(p)).collect();
        let mesh = TriMesh::new(vertices, triangles.to_vec())
            .map_err(|e| LidarError::Scene(format!("cannot index the scene's triangles: {e}")))?;
        Ok(Bvh { mesh })
    }

    /// The first hit of the ray from `o` along the unit direction `d` within `max_range`.
    pub fn cast(&self, o: DVec3, d: DVec3, max_range: f64) -> Option<Hit> {
        let ray = Ray::new(vector(o), vector(d));
        let hit = self
            .mesh
            .cast_local_ray_and_get_normal(&ray, max_range, false)?;
        let n = dvec(hit.normal);
        Some(Hit {
            range: hit.time_of_impact,
            triangle: hit.subshape,
            normal: n.normalize_or_zero(),
        })
    }

    /// The distance from `p` to the nearest triangle, and that triangle.
    pub fn distance(&self, p: DVec3) -> (f64, u32) {
        let q = vector(p);
        let (proj, (tri, _)) = self.mesh.project_local_point_and_get_location(q, false);
        ((dvec(q) - dvec(proj.point)).length(), tri)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ray_to_a_known_plane_hits_it_within_1e_9() {
        // The plane n·p = c, tilted, as two large triangles.
        let n = DVec3::new(0.2, -0.3, 1.0).normalize();
        let c = 1.7;
        let (u, v) = super::super::scene::perpendiculars(n);
        let at = n * c;
        let corners = [
            at - u * 80.0 - v * 80.0,
            at + u * 80.0 - v * 80.0,
            at + u * 80.0 + v * 80.0,
            at - u * 80.0 + v * 80.0,
        ];
        let bvh = Bvh::new(&corners, &[[0, 1, 2], [0, 2, 3]]).unwrap();
        let o = DVec3::new(3.0, -2.0, 40.0);
        let mut worst: f64 = 0.0;
        for k in 0..1000 {
            let a = k as f64 * 0.37;
            let d = DVec3::new(libm::cos(a) * 0.4, libm::sin(a) * 0.5, -1.0).normalize();
            let h = bvh.cast(o, d, 1e3).expect("the plane is below");
            let p = o + d * h.range;
            worst = worst.max((n.dot(p) - c).abs());
            // The exact range of the analytic intersection.
            let t = (c - n.dot(o)) / n.dot(d);
            assert!((h.range - t).abs() < 1e-9, "{} vs {t}", h.range);
            assert!(h.normal.cross(n).length() < 1e-12);
        }
        assert!(worst < 1e-9, "{worst}");
        assert!(bvh.cast(o, DVec3::Z, 1e3).is_none());
        assert!(
            bvh.cast(o, DVec3::NEG_Z, 10.0).is_none(),
            "beyond the maximum range"
        );
        let (dist, _) = bvh.distance(at + u * 1.0 + v * 2.0 + n * 5.0);
        assert!((dist - 5.0).abs() < 1e-9);
    }
}
