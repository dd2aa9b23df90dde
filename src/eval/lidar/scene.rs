//! A scene: triangles that know which object they belong to, and the primitives scenes are built
//! from.
//!
//! # Brief overview
//!
//! ```text
//!  positions: Vec<DVec3>      triangles: Vec<[u32; 3]>     face_object: Vec<u32> (one per triangle)
//!                                                          objects: Vec<Kind>    (one per object id)
//! ```
//!
//! [`SceneBuilder`] appends primitives, each to the object it is told: boxes and prisms (walls,
//! roofs, cars, fence slats), closed cylinders (poles, trunks, wheels), tubes along a polyline
//! (wires), clouds of small randomly oriented triangles inside an ellipsoid (leaves: rays pass
//! between them or stop on one, as they do in a crown), and any triangle mesh under an affine map
//! (the sculpted object, `--mesh`). Primitives are oriented outwards where they are closed, but a
//! ray hits a triangle from either side: orientation only matters to a reader of the truth mesh.
//!
//! The scene's frame is local: x along the street, y across it, z up, metres; a sensor may write
//! its points in another frame (see [`super::Frame`]).

use glam::{DVec2, DVec3};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;

use super::kinds::Kind;
use crate::points::Faces;

/// A scene of triangles, each belonging to one object of one [`Kind`].
#[derive(Debug, Clone, Default)]
pub struct Scene {
    /// Vertex positions.
    pub positions: Vec<DVec3>,
    /// Triangles indexing `positions`.
    pub triangles: Vec<[u32; 3]>,
    /// The object of each triangle.
    pub face_object: Vec<u32>,
    /// The kind of each object (indexed by object id).
    pub objects: Vec<Kind>,
}

impl Scene {
    /// The kind of triangle `t`.
    pub fn kind_of_face(&self, t: usize) -> Kind {
        self.objects[self.face_object[t] as usize]
    }

    /// The triangles as [`Faces`].
    pub fn faces(&self) -> Faces {
        Faces::from_triangles(&self.triangles)
    }

    /// Triangles per kind, in [`Kind::ALL`] order (kinds without triangles left out).
    pub fn triangles_per_kind(&self) -> Vec<(Kind, usize)> {
        let mut n = [0usize; Kind::ALL.len()];
        for &o in &self.face_object {
            n[self.objects[o as usize] as usize] += 1;
        }
        Kind::ALL
            .into_iter()
            .zip(n)
            .filter(|&(_, c)| c > 0)
            .collect()
    }
}

/// Appends primitives to a [`Scene`].
#[derive(Debug, Default)]
pub struct SceneBuilder {
    scene: Scene,
}

impl SceneBuilder {
    /// A new object of `kind`; returns its id.
    pub fn object(&mut self, kind: Kind) -> u32 {
        self.scene.objects.push(kind);
        (self.scene.objects.len() - 1) as u32
    }

    /// The scene built so far.
    pub fn finish(self) -> Scene {
        self.scene
    }

    /// Triangles so far.
    pub fn triangle_count(&self) -> usize {
        self.scene.triangles.len()
    }

    fn vertex(&mut self, p: DVec3) -> u32 {
        self.scene.positions.push(p);
        (self.scene.positions.len() - 1) as u32
    }

    fn tri(&mut self, obj: u32, t: [u32; 3]) {
        self.scene.triangles.push(t);
        self.scene.face_object.push(obj);
    }

    /// A convex polygon, counter-clockwise seen from the side it faces, as a fan.
    pub fn polygon(&mut self, obj: u32, corners: &[DVec3]) {
        let v: Vec<u32> = corners.iter().map(|&p| self.vertex(p)).collect();
        for i in 1..v.len().saturating_sub(1) {
            self.tri(obj, [v[0], v[i], v[i + 1]]);
        }
    }

    /// A closed prism: the convex `profile` (counter-clockwise in the (`u`, `v`) plane, placed at
    /// `at`) swept along `along`. The side faces are quads.
    pub fn prism(
        &mut self,
        obj: u32,
        at: DVec3,
        u: DVec3,
        v: DVec3,
        profile: &[DVec2],
        along: DVec3,
    ) {
        let p0: Vec<DVec3> = profile.iter().map(|q| at + u * q.x + v * q.y).collect();
        let p1: Vec<DVec3> = p0.iter().map(|&p| p + along).collect();
        // The cap facing −along is the profile seen from behind when u × v points along `along`.
        let forward = u.cross(v).dot(along) > 0.0;
        let (back, front): (Vec<DVec3>, Vec<DVec3>) = if forward {
            (p0.iter().rev().copied().collect(), p1.clone())
        } else {
            (p0.clone(), p1.iter().rev().copied().collect())
        };
        self.polygon(obj, &back);
        self.polygon(obj, &front);
        let n = p0.len();
        for i in 0..n {
            let j = (i + 1) % n;
            let quad = if forward {
                [p0[i], p0[j], p1[j], p1[i]]
            } else {
                [p0[i], p1[i], p1[j], p0[j]]
            };
            self.polygon(obj, &quad);
        }
    }

    /// A box with centre `c`, half sizes `h` along the horizontal unit axis `x` (the box's own x),
    /// its perpendicular `z × x` and z.
    pub fn oriented_box(&mut self, obj: u32, c: DVec3, h: DVec3, x: DVec3) {
        let y = DVec3::Z.cross(x);
        let profile = [
            DVec2::new(-h.x, -h.z),
            DVec2::new(h.x, -h.z),
            DVec2::new(h.x, h.z),
            DVec2::new(-h.x, h.z),
        ];
        self.prism(obj, c - y * h.y, x, DVec3::Z, &profile, y * (2.0 * h.y));
    }

    /// An axis-aligned box from `lo` to `hi`.
    pub fn aabb(&mut self, obj: u32, lo: DVec3, hi: DVec3) {
        self.oriented_box(obj, (lo + hi) / 2.0, (hi - lo) / 2.0, DVec3::X);
    }

    /// A closed cylinder of `radius` from `base` to `base + axis`, with `sides` sides.
    pub fn cylinder(&mut self, obj: u32, base: DVec3, axis: DVec3, radius: f64, sides: usize) {
        let (u, v) = perpendiculars(axis);
        let profile: Vec<DVec2> = (0..sides)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / sides as f64;
                DVec2::new(libm::cos(a), libm::sin(a)) * radius
            })
            .collect();
        self.prism(obj, base, u, v, &profile, axis);
    }

    /// A tube of `radius` along the polyline `path` with `sides` sides, closed at both ends.
    pub fn tube(&mut self, obj: u32, path: &[DVec3], radius: f64, sides: usize) {
        if path.len() < 2 {
            return;
        }
        let axis = (path[path.len() - 1] - path[0]).normalize();
        let (u, v) = perpendiculars(axis);
        let mut rings: Vec<Vec<u32>> = Vec::with_capacity(path.len());
        for (i, &p) in path.iter().enumerate() {
            // The ring at a joint lies in the plane bisecting the two segments.
            let t = if i == 0 {
                path[1] - path[0]
            } else if i + 1 == path.len() {
                path[i] - path[i - 1]
            } else {
                (path[i] - path[i - 1]).normalize() + (path[i + 1] - path[i]).normalize()
            }
            .normalize();
            let ring = (0..sides)
                .map(|k| {
                    let a = std::f64::consts::TAU * k as f64 / sides as f64;
                    let r = u * libm::cos(a) + v * libm::sin(a);
                    // Project the ring direction onto the plane normal to the local tangent.
                    let r = (r - t * r.dot(t)).normalize();
                    self.vertex(p + r * radius)
                })
                .collect();
            rings.push(ring);
        }
        for w in rings.windows(2) {
            for k in 0..sides {
                let k1 = (k + 1) % sides;
                self.tri(obj, [w[0][k], w[0][k1], w[1][k1]]);
                self.tri(obj, [w[0][k], w[1][k1], w[1][k]]);
            }
        }
        let first = rings[0].clone();
        let last = rings[rings.len() - 1].clone();
        for k in 1..sides - 1 {
            self.tri(obj, [first[0], first[k + 1], first[k]]);
            self.tri(obj, [last[0], last[k], last[k + 1]]);
        }
    }

    /// `count` leaves: equilateral triangles of side `size`, randomly oriented, centred uniformly
    /// inside the ellipsoid of centre `c` and semi-axes `semi`.
    pub fn leaves(
        &mut self,
        obj: u32,
        c: DVec3,
        semi: DVec3,
        count: usize,
        size: f64,
        rng: &mut ChaCha8Rng,
    ) {
        let r = size / 3f64.sqrt();
        for _ in 0..count {
            let q = loop {
                let q = DVec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                if q.length_squared() <= 1.0 {
                    break q;
                }
            };
            let centre = c + q * semi;
            let n = unit_vector(rng);
            let (u, v) = perpendiculars(n);
            let spin = rng.random_range(0.0..std::f64::consts::TAU);
            let corners: Vec<DVec3> = (0..3)
                .map(|k| {
                    let a = spin + std::f64::consts::TAU * k as f64 / 3.0;
                    centre + (u * libm::cos(a) + v * libm::sin(a)) * r
                })
                .collect();
            self.polygon(obj, &corners);
        }
    }

    /// The triangles of a mesh, each vertex mapped by `map`.
    pub fn mesh(
        &mut self,
        obj: u32,
        positions: &[DVec3],
        faces: &Faces,
        map: impl Fn(DVec3) -> DVec3,
    ) {
        let base = self.scene.positions.len() as u32;
        self.scene
            .positions
            .extend(positions.iter().map(|&p| map(p)));
        for t in faces.triangles() {
            self.tri(obj, t.map(|v| base + v));
        }
    }
}

/// Two unit vectors perpendicular to `axis` and to each other, (u, v, axis) right-handed.
pub fn perpendiculars(axis: DVec3) -> (DVec3, DVec3) {
    let a = axis.normalize();
    let helper = if a.z.abs() < 0.9 { DVec3::Z } else { DVec3::X };
    let u = helper.cross(a).normalize();
    (u, a.cross(u))
}

/// A uniformly distributed unit vector.
pub fn unit_vector(rng: &mut ChaCha8Rng) -> DVec3 {
    loop {
        let q = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let l = q.length_squared();
        if l > 1e-6 && l <= 1.0 {
            return q / l.sqrt();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::{is_closed, signed_volume};

    #[test]
    fn boxes_and_cylinders_are_closed_and_outward() {
        let mut b = SceneBuilder::default();
        let o = b.object(Kind::Building);
        b.aabb(o, DVec3::ZERO, DVec3::new(2.0, 3.0, 4.0));
        let s = b.finish();
        let f = s.faces();
        assert_eq!(s.triangles.len(), 12);
        assert!((signed_volume(&s.positions, &f) - 24.0).abs() < 1e-12);

        let mut b = SceneBuilder::default();
        let o = b.object(Kind::Pole);
        b.cylinder(o, DVec3::ZERO, DVec3::new(0.0, 0.0, 2.0), 1.0, 64);
        let s = b.finish();
        let v = signed_volume(&s.positions, &s.faces());
        let ideal = std::f64::consts::PI * 2.0;
        assert!(v > 0.0 && (v - ideal).abs() / ideal < 0.01, "{v}");

        let mut b = SceneBuilder::default();
        let o = b.object(Kind::Wire);
        let path: Vec<DVec3> = (0..5)
            .map(|i| DVec3::new(i as f64, 0.0, 0.1 * (i * i) as f64))
            .collect();
        b.tube(o, &path, 0.1, 8);
        let s = b.finish();
        // Welded by position, the tube is closed.
        let mut ids = std::collections::HashMap::new();
        let tris: Vec<[u32; 3]> = s
            .triangles
            .iter()
            .map(|t| {
                t.map(|v| {
                    let p = s.positions[v as usize];
                    let key = [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
                    let n = ids.len() as u32;
                    *ids.entry(key).or_insert(n)
                })
            })
            .collect();
        assert!(is_closed(&Faces::from_triangles(&tris)));
        assert!(signed_volume(&s.positions, &s.faces()) > 0.0);
    }
}
