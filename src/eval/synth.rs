//! Synthetic test shapes and seeded surface sampling.
//!
//! # Brief overview
//!
//! * [`Shape::mesh`] builds a triangle [`Mesh`] whose faces are oriented outwards (normals from
//!   `(v1 − v0) × (v2 − v0)`). All shapes except [`Shape::Step`] are closed: every edge is shared by
//!   exactly two faces and there are no T-junctions.
//!
//!   | shape | geometry | `resolution` |
//!   |---|---|---|
//!   | `sphere` | unit icosphere | subdivision level (6 → 40,962 vertices) |
//!   | `cube` | cube `[-1, 1]³`, sharp edges and corners | segments per edge |
//!   | `csg` | block 2 × 2 × 1 with a vertical cylindrical through-hole of radius 0.5 | segments per 2-unit box edge |
//!   | `torus` | major radius 1, minor radius 0.4 | segments around the tube |
//!   | `step` | open height field over x, z ∈ `[-1, 1]` (y up, like the renderer) with a 0.5-high vertical step at x = 0 | segments across x |
//!
//!   Every mesh is built from structured grids whose quads are split along the shorter diagonal,
//!   except the caps of `csg` (a square with a circular hole), which are a constrained Delaunay
//!   triangulation refined for quality with `spade`; its boundary vertices are the ones of the
//!   walls, so the caps join the walls without T-junctions.
//! * [`SurfaceSampler`] draws area-uniform points on a mesh surface from a seeded ChaCha8 stream
//!   and hands them out in batches: memory depends on the mesh, never on the number of points,
//!   and the points do not depend on the batch size.

use std::collections::HashMap;
use std::fmt;
use std::str::FromStr;

use glam::{DVec2, DVec3};
use rand::distr::Distribution;
use rand::distr::weighted::WeightedIndex;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use spade::handles::FixedVertexHandle;
use spade::{
    AngleLimit, ConstrainedDelaunayTriangulation, Point2, RefinementParameters, Triangulation,
};

use super::{EvalError, Mesh, check_faces};
use crate::points::Faces;

/// Major radius of the torus.
pub const TORUS_MAJOR: f64 = 1.0;
/// Minor (tube) radius of the torus.
pub const TORUS_MINOR: f64 = 0.4;
/// Radius of the cylindrical hole of the `csg` part.
pub const CSG_HOLE_RADIUS: f64 = 0.5;
/// Half-height of the `csg` block (its x and y half-widths are 1).
pub const CSG_HALF_HEIGHT: f64 = 0.5;
/// Height of the step of the `step` sheet.
pub const STEP_HEIGHT: f64 = 0.5;

/// A synthetic test shape.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    /// Unit icosphere.
    Sphere,
    /// Cube `[-1, 1]³`.
    Cube,
    /// A CAD-like block with a cylindrical through-hole: straight and circular sharp edges.
    Csg,
    /// Torus with radii 1 and 0.4 around the z axis.
    Torus,
    /// An open height field (y up) with a sharp vertical step.
    Step,
}

impl Shape {
    /// Every shape, in CLI order.
    pub const ALL: [Shape; 5] = [
        Shape::Sphere,
        Shape::Cube,
        Shape::Csg,
        Shape::Torus,
        Shape::Step,
    ];

    /// The CLI name.
    pub fn name(self) -> &'static str {
        match self {
            Shape::Sphere => "sphere",
            Shape::Cube => "cube",
            Shape::Csg => "csg",
            Shape::Torus => "torus",
            Shape::Step => "step",
        }
    }

    /// A sensible resolution: level 6 for the sphere (the 40,962-vertex icosphere of the Table I
    /// runs, docs/quality/meshes.md), tens of thousands of vertices for the others.
    pub fn default_resolution(self) -> u32 {
        match self {
            Shape::Sphere => 6,
            Shape::Cube => 64,
            Shape::Csg => 96,
            Shape::Torus => 64,
            Shape::Step => 128,
        }
    }

    /// The accepted resolutions (see the module table for their meaning).
    pub fn resolution_range(self) -> std::ops::RangeInclusive<u32> {
        match self {
            // Up to a few million vertices; dense point sets come from `SurfaceSampler`.
            Shape::Sphere => 0..=9,
            Shape::Cube => 1..=1000,
            Shape::Csg => 4..=1000,
            Shape::Torus => 3..=1000,
            Shape::Step => 2..=2000,
        }
    }

    /// The volume of the ideal (smooth) closed shape; `None` for the open step.
    pub fn volume(self) -> Option<f64> {
        use std::f64::consts::PI;
        match self {
            Shape::Sphere => Some(4.0 / 3.0 * PI),
            Shape::Cube => Some(8.0),
            Shape::Csg => Some(
                4.0 * 2.0 * CSG_HALF_HEIGHT
                    - PI * CSG_HOLE_RADIUS * CSG_HOLE_RADIUS * 2.0 * CSG_HALF_HEIGHT,
            ),
            Shape::Torus => Some(2.0 * PI * PI * TORUS_MAJOR * TORUS_MINOR * TORUS_MINOR),
            Shape::Step => None,
        }
    }

    /// Builds the mesh at `resolution`.
    ///
    /// # Errors
    /// [`EvalError::Param`] when `resolution` is outside [`Shape::resolution_range`],
    /// [`EvalError::Synth`] if the cap triangulation of `csg` fails.
    pub fn mesh(self, resolution: u32) -> Result<Mesh, EvalError> {
        let range = self.resolution_range();
        if !range.contains(&resolution) {
            return Err(EvalError::Param {
                name: "resolution",
                detail: format!(
                    "{} needs a resolution in {}..={}, got {resolution}",
                    self.name(),
                    range.start(),
                    range.end()
                ),
            });
        }
        let n = resolution as usize;
        Ok(match self {
            Shape::Sphere => icosphere(n),
            Shape::Cube => cube(n),
            Shape::Csg => csg(n)?,
            Shape::Torus => torus(n),
            Shape::Step => step(n),
        })
    }

    /// A sampler of `count` seeded, area-uniform points on the shape's mesh at `resolution` (the
    /// tessellated surface, so choose a fine resolution for curved shapes).
    ///
    /// # Errors
    /// As [`Shape::mesh`].
    pub fn sampler(
        self,
        resolution: u32,
        count: u64,
        seed: u64,
    ) -> Result<SurfaceSampler, EvalError> {
        let m = self.mesh(resolution)?;
        SurfaceSampler::new(&m.positions, &m.faces, count, seed)
    }
}

impl fmt::Display for Shape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Shape {
    type Err = EvalError;
    fn from_str(s: &str) -> Result<Shape, EvalError> {
        Shape::ALL
            .into_iter()
            .find(|sh| sh.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| EvalError::Param {
                name: "shape",
                detail: format!("unknown shape `{s}` (sphere, cube, csg, torus, step)"),
            })
    }
}

/// Collects vertices and triangles.
#[derive(Default)]
struct Builder {
    pos: Vec<DVec3>,
    tris: Vec<[u32; 3]>,
}

impl Builder {
    fn vertex(&mut self, p: DVec3) -> u32 {
        self.pos.push(p);
        (self.pos.len() - 1) as u32
    }

    fn tri(&mut self, a: u32, b: u32, c: u32) {
        self.tris.push([a, b, c]);
    }

    /// A quad `a → b → c → d` (counter-clockwise seen from outside), split along its shorter
    /// diagonal; ties (up to rounding) take `a–c`, so regular grids split uniformly.
    fn quad(&mut self, a: u32, b: u32, c: u32, d: u32) {
        let p = |i: u32| self.pos[i as usize];
        let ac = (p(a) - p(c)).length_squared();
        let bd = (p(b) - p(d)).length_squared();
        if bd < ac * (1.0 - 1e-9) {
            self.tri(a, b, d);
            self.tri(b, c, d);
        } else {
            self.tri(a, b, c);
            self.tri(a, c, d);
        }
    }

    /// Quads between consecutive rows of vertex indices (all rows equally long). The outward side
    /// is the one where (along a row) × (towards the next row) points.
    fn grid(&mut self, rows: &[Vec<u32>], wrap_cols: bool, wrap_rows: bool) {
        let nr = rows.len();
        let nc = rows.first().map_or(0, Vec::len);
        let row_pairs = if wrap_rows { nr } else { nr.saturating_sub(1) };
        let col_pairs = if wrap_cols { nc } else { nc.saturating_sub(1) };
        for i in 0..row_pairs {
            let (r0, r1) = (&rows[i], &rows[(i + 1) % nr]);
            for j in 0..col_pairs {
                let j1 = (j + 1) % nc;
                self.quad(r0[j], r0[j1], r1[j1], r1[j]);
            }
        }
    }

    fn finish(self) -> Mesh {
        Mesh {
            positions: self.pos,
            faces: Faces::from_triangles(&self.tris),
        }
    }
}

/// Icosphere: a unit icosahedron subdivided `level` times (each triangle into four, new vertices
/// projected onto the sphere): `10·4^level + 2` vertices.
fn icosphere(level: usize) -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut pos: Vec<DVec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
    .collect();
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::with_capacity(tris.len() * 3 / 2);
        let mut midpoint = |a: u32, b: u32, pos: &mut Vec<DVec3>| -> u32 {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                pos.push((pos[a as usize] + pos[b as usize]).normalize());
                (pos.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(tris.len() * 4);
        for &[a, b, c] in &tris {
            let ab = midpoint(a, b, &mut pos);
            let bc = midpoint(b, c, &mut pos);
            let ca = midpoint(c, a, &mut pos);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        tris = next;
    }
    Mesh {
        positions: pos,
        faces: Faces::from_triangles(&tris),
    }
}

/// Cube `[-1, 1]³` with `n × n` quads per face; vertices on shared edges are welded through their
/// integer lattice coordinates.
fn cube(n: usize) -> Mesh {
    let mut b = Builder::default();
    let mut lattice: HashMap<[usize; 3], u32> = HashMap::new();
    let coord = |i: usize| -1.0 + 2.0 * i as f64 / n as f64;
    for axis in 0..3 {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        for side in [0, n] {
            // Rows run along u and advance along v: (e_u × e_v) = +e_axis, outward on the far side.
            let mut rows: Vec<Vec<u32>> = (0..=n)
                .map(|j| {
                    (0..=n)
                        .map(|i| {
                            let mut key = [0; 3];
                            key[axis] = side;
                            key[u] = i;
                            key[v] = j;
                            *lattice.entry(key).or_insert_with(|| {
                                b.vertex(DVec3::new(coord(key[0]), coord(key[1]), coord(key[2])))
                            })
                        })
                        .collect()
                })
                .collect();
            if side == 0 {
                rows.reverse();
            }
            b.grid(&rows, false, false);
        }
    }
    b.finish()
}

/// Torus around the z axis: `m` segments around the tube and about `m·R/r` around the axis, so
/// the quads are close to square.
fn torus(m: usize) -> Mesh {
    use std::f64::consts::TAU;
    let (big, small) = (TORUS_MAJOR, TORUS_MINOR);
    let major = ((m as f64 * big / small).round() as usize).max(3);
    let mut b = Builder::default();
    // Rows run along the major angle θ and advance along the tube angle φ; ∂θ × ∂φ points out.
    let rows: Vec<Vec<u32>> = (0..m)
        .map(|j| {
            let phi = TAU * j as f64 / m as f64;
            (0..major)
                .map(|i| {
                    let theta = TAU * i as f64 / major as f64;
                    let rho = big + small * phi.cos();
                    b.vertex(DVec3::new(
                        rho * theta.cos(),
                        rho * theta.sin(),
                        small * phi.sin(),
                    ))
                })
                .collect()
        })
        .collect();
    b.grid(&rows, true, true);
    b.finish()
}

/// An open height field y(x, z) over `[-1, 1]²` with a vertical wall of height [`STEP_HEIGHT`] at
/// x = 0: a profile polyline in (x, y) extruded along z. Height is y, the renderer's up axis.
fn step(n: usize) -> Mesh {
    let half = (n / 2).max(1);
    let d = 1.0 / half as f64;
    let wall = ((STEP_HEIGHT / d).round() as usize).max(1);
    let mut profile: Vec<DVec2> = (0..=half)
        .map(|k| DVec2::new(-1.0 + k as f64 * d, 0.0))
        .collect();
    profile.extend((1..=wall).map(|l| DVec2::new(0.0, STEP_HEIGHT * l as f64 / wall as f64)));
    profile.extend((1..=half).map(|k| DVec2::new(k as f64 * d, STEP_HEIGHT)));
    let ny = 2 * half;
    let mut b = Builder::default();
    // Rows run along the profile and advance along −z: (+x) × (−z) = +y on the plateaus and
    // (+y) × (−z) = −x on the wall, which faces the lower side.
    let rows: Vec<Vec<u32>> = (0..=ny)
        .map(|j| {
            let z = 1.0 - 2.0 * j as f64 / ny as f64;
            profile
                .iter()
                .map(|q| b.vertex(DVec3::new(q.x, q.y, z)))
                .collect()
        })
        .collect();
    b.grid(&rows, false, false);
    b.finish()
}

/// The CAD-like part: block `[-1, 1]² × [-h, h]` with a vertical cylindrical hole of radius r.
/// Walls are grids; both caps share one quality triangulation of the square with the circular
/// hole, whose boundary vertices are the walls' top and bottom rings.
fn csg(n: usize) -> Result<Mesh, EvalError> {
    use std::f64::consts::TAU;
    let (a, h, r) = (1.0, CSG_HALF_HEIGHT, CSG_HOLE_RADIUS);
    let d = 2.0 * a / n as f64;
    let around = ((TAU * r / d).round() as usize).max(8);
    let levels = ((2.0 * h / d).round() as usize).max(1);
    // The square counter-clockwise from (−a, −a), n samples per side, corners included.
    let square: Vec<DVec2> = (0..4 * n)
        .map(|k| {
            let t = 2.0 * a * (k % n) as f64 / n as f64;
            match k / n {
                0 => DVec2::new(-a + t, -a),
                1 => DVec2::new(a, -a + t),
                2 => DVec2::new(a - t, a),
                _ => DVec2::new(-a, a - t),
            }
        })
        .collect();
    let circle: Vec<DVec2> = (0..around)
        .map(|j| {
            let phi = TAU * j as f64 / around as f64;
            DVec2::new(r * phi.cos(), r * phi.sin())
        })
        .collect();
    let mut b = Builder::default();
    let z = |l: usize| -h + 2.0 * h * l as f64 / levels as f64;
    let ring = |pts: &[DVec2], l: usize, b: &mut Builder| -> Vec<u32> {
        pts.iter()
            .map(|p| b.vertex(DVec3::new(p.x, p.y, z(l))))
            .collect()
    };
    let outer: Vec<Vec<u32>> = (0..=levels).map(|l| ring(&square, l, &mut b)).collect();
    let inner: Vec<Vec<u32>> = (0..=levels).map(|l| ring(&circle, l, &mut b)).collect();
    // Outer walls: rows counter-clockwise, advancing upwards: tangent × z points outwards.
    b.grid(&outer, true, false);
    // Hole wall: advancing downwards, so the faces look into the hole.
    let down: Vec<Vec<u32>> = inner.iter().rev().cloned().collect();
    b.grid(&down, true, false);
    let (steiner, tris) = holed_square(&square, &circle, d)?;
    for (l, cap_z, flip) in [(levels, h, false), (0, -h, true)] {
        let mut map: Vec<u32> = outer[l].clone();
        map.extend_from_slice(&inner[l]);
        for p in &steiner {
            map.push(b.vertex(DVec3::new(p.x, p.y, cap_z)));
        }
        for t in &tris {
            let [i, j, k] = t.map(|x| map[x]);
            if flip {
                b.tri(i, k, j);
            } else {
                b.tri(i, j, k);
            }
        }
    }
    Ok(b.finish())
}

/// Triangulates the region between the closed loops `outer` (counter-clockwise) and `hole` with
/// target edge length `d`. Returns the added interior points and counter-clockwise triangles whose
/// indices count `outer`, then `hole`, then the interior points. The boundary edges are kept
/// exactly (no point is inserted on them), so walls sharing the loops join without T-junctions.
fn holed_square(
    outer: &[DVec2],
    hole: &[DVec2],
    d: f64,
) -> Result<(Vec<DVec2>, Vec<[usize; 3]>), EvalError> {
    let fail = |what: &str| EvalError::Synth(format!("cap triangulation: {what}"));
    let mut cdt = ConstrainedDelaunayTriangulation::<Point2<f64>>::new();
    let insert = |cdt: &mut ConstrainedDelaunayTriangulation<Point2<f64>>, p: DVec2| {
        cdt.insert(Point2::new(p.x, p.y))
            .map_err(|e| fail(&format!("{e:?}")))
    };
    // A frame well outside the square: refinement may split convex-hull edges even when
    // constraint edges are kept, so the square's edges must not lie on the hull.
    let extent = outer
        .iter()
        .fold(0.0f64, |m, p| m.max(p.abs().max_element()));
    let mut frame = Vec::new();
    for (x, y) in [(-3.0, -3.0), (3.0, -3.0), (3.0, 3.0), (-3.0, 3.0)] {
        frame.push(insert(&mut cdt, DVec2::new(x, y) * extent)?);
    }
    let mut loops: Vec<Vec<FixedVertexHandle>> = Vec::new();
    for pts in [outer, hole] {
        loops.push(
            pts.iter()
                .map(|&p| insert(&mut cdt, p))
                .collect::<Result<_, _>>()?,
        );
    }
    for lp in &loops {
        for i in 0..lp.len() {
            if cdt.try_add_constraint(lp[i], lp[(i + 1) % lp.len()]).len() != 1 {
                return Err(fail("a boundary edge could not be constrained"));
            }
        }
    }
    // Equilateral triangles of edge d have area √3/4·d² ≈ 0.43 d²; refining up to that bound
    // with a 28° angle limit gives edges close to d.
    let area: f64 = 0.5 * polygon_area(outer).abs() - 0.5 * polygon_area(hole).abs();
    let budget = (4.0 * area / (d * d)) as usize + 10 * (outer.len() + hole.len()) + 1000;
    let result = cdt.refine(
        RefinementParameters::<f64>::new()
            .exclude_outer_faces(true)
            .keep_constraint_edges()
            .with_angle_limit(AngleLimit::from_deg(28.0))
            .with_max_allowed_area(0.45 * d * d)
            .with_max_additional_vertices(budget),
    );
    if !result.refinement_complete {
        return Err(fail("refinement did not converge"));
    }
    for lp in &loops {
        for i in 0..lp.len() {
            if !cdt.exists_constraint(lp[i], lp[(i + 1) % lp.len()]) {
                return Err(fail("a boundary edge was split"));
            }
        }
    }
    const FRAME: usize = usize::MAX - 1;
    const UNSEEN: usize = usize::MAX;
    let mut local = vec![UNSEEN; cdt.num_vertices()];
    for f in &frame {
        local[f.index()] = FRAME;
    }
    for (i, hnd) in loops.iter().flatten().enumerate() {
        local[hnd.index()] = i;
    }
    let excluded: std::collections::HashSet<_> = result.excluded_faces.into_iter().collect();
    let mut steiner = Vec::new();
    let mut tris = Vec::new();
    let first_steiner = outer.len() + hole.len();
    for face in cdt.inner_faces() {
        if excluded.contains(&face.fix()) {
            continue;
        }
        let mut t = [0usize; 3];
        let mut p = [DVec2::ZERO; 3];
        for (c, v) in face.vertices().iter().enumerate() {
            let slot = &mut local[v.fix().index()];
            if *slot == FRAME {
                return Err(fail("an inner face touches the outer frame"));
            }
            if *slot == UNSEEN {
                *slot = first_steiner + steiner.len();
                steiner.push(DVec2::new(v.position().x, v.position().y));
            }
            t[c] = *slot;
            p[c] = DVec2::new(v.position().x, v.position().y);
        }
        if (p[1] - p[0]).perp_dot(p[2] - p[0]) < 0.0 {
            t.swap(1, 2);
        }
        tris.push(t);
    }
    Ok((steiner, tris))
}

/// Signed area of a closed polygon (positive when counter-clockwise).
fn polygon_area(p: &[DVec2]) -> f64 {
    (0..p.len())
        .map(|i| p[i].perp_dot(p[(i + 1) % p.len()]))
        .sum::<f64>()
        / 2.0
}

/// Seeded, area-uniform random points on a mesh surface, produced in batches.
///
/// Each point picks a triangle with probability proportional to its area (`WeightedIndex`,
/// a binary search over cumulative areas), then a uniform point in it. Points come from one
/// ChaCha8 stream in a fixed order, so the i-th point is the same for every batch size. Memory is
/// one corner triple and one weight per triangle.
pub struct SurfaceSampler {
    tris: Vec<[DVec3; 3]>,
    pick: WeightedIndex<f64>,
    rng: ChaCha8Rng,
    remaining: u64,
    area: f64,
}

impl SurfaceSampler {
    /// A sampler that will produce `count` points on the faces (fan-triangulated) of the mesh.
    /// Zero-area triangles are never picked.
    ///
    /// # Errors
    /// Bad face indices, a face corner that is not finite, or a surface of zero area.
    pub fn new(
        positions: &[DVec3],
        faces: &Faces,
        count: u64,
        seed: u64,
    ) -> Result<SurfaceSampler, EvalError> {
        check_faces(positions.len(), faces)?;
        let mut tris = Vec::new();
        let mut weights = Vec::new();
        for t in faces.triangles() {
            let c = t.map(|v| positions[v as usize]);
            if let Some(i) = t.iter().find(|&&v| !positions[v as usize].is_finite()) {
                return Err(EvalError::NonFinite {
                    what: "mesh",
                    index: *i as usize,
                });
            }
            let w = 0.5 * (c[1] - c[0]).cross(c[2] - c[0]).length();
            if w > 0.0 {
                tris.push(c);
                weights.push(w);
            }
        }
        let area: f64 = weights.iter().sum();
        if tris.is_empty() || !(area > 0.0 && area.is_finite()) {
            return Err(EvalError::Degenerate(
                "the surface has no area to sample".into(),
            ));
        }
        let pick = WeightedIndex::new(&weights)
            .map_err(|e| EvalError::Degenerate(format!("triangle areas: {e}")))?;
        Ok(SurfaceSampler {
            tris,
            pick,
            rng: ChaCha8Rng::seed_from_u64(seed),
            remaining: count,
            area,
        })
    }

    /// Points still to come.
    pub fn remaining(&self) -> u64 {
        self.remaining
    }

    /// Total area of the sampled surface.
    pub fn area(&self) -> f64 {
        self.area
    }

    /// Clears `out` (keeping its allocation) and fills it with the next points, at most `max`.
    /// Returns how many were produced; 0 means the sampler is exhausted.
    pub fn fill(&mut self, out: &mut Vec<DVec3>, max: usize) -> usize {
        out.clear();
        let k = self.remaining.min(max as u64) as usize;
        out.reserve(k);
        for _ in 0..k {
            let [a, b, c] = self.tris[self.pick.sample(&mut self.rng)];
            let s = self.rng.random::<f64>().sqrt();
            let t = self.rng.random::<f64>();
            out.push(a * (1.0 - s) + b * (s * (1.0 - t)) + c * (s * t));
        }
        self.remaining -= k as u64;
        k
    }
}

impl Iterator for SurfaceSampler {
    type Item = Vec<DVec3>;

    /// The next batch of up to [`crate::io::BATCH`] points, in a new vector.
    fn next(&mut self) -> Option<Vec<DVec3>> {
        let mut v = Vec::new();
        (self.fill(&mut v, crate::io::BATCH) > 0).then_some(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::{is_closed, is_consistently_oriented};

    fn check_closed(m: &Mesh) {
        assert!(is_closed(&m.faces), "not closed");
        assert!(
            is_consistently_oriented(&m.faces),
            "inconsistent orientation"
        );
        check_faces(m.positions.len(), &m.faces).unwrap();
        // No zero-area triangles and no unreferenced vertices.
        for t in m.faces.triangles() {
            let c = t.map(|v| m.positions[v as usize]);
            assert!((c[1] - c[0]).cross(c[2] - c[0]).length() > 1e-12);
        }
        assert!(
            crate::eval::referenced(m.positions.len(), &m.faces)
                .iter()
                .all(|&r| r)
        );
    }

    #[test]
    fn icosphere_counts_and_volume() {
        for level in 0..=3 {
            let m = Shape::Sphere.mesh(level).unwrap();
            let n = 10 * 4usize.pow(level) + 2;
            assert_eq!(m.positions.len(), n);
            assert_eq!(m.faces.len(), 20 * 4usize.pow(level));
            check_closed(&m);
            for p in &m.positions {
                assert!((p.length() - 1.0).abs() < 1e-14);
            }
        }
        let m = Shape::Sphere.mesh(3).unwrap();
        let v = m.signed_volume();
        let ideal = Shape::Sphere.volume().unwrap();
        assert!(
            v > 0.0 && (v - ideal).abs() / ideal < 0.03,
            "{v} vs {ideal}"
        );
        assert!(Shape::Sphere.mesh(10).is_err());
    }

    #[test]
    fn icosphere_level_6_has_40962_vertices() {
        // Counting only: 40,962 is the icosphere of the Table I runs (docs/quality/meshes.md).
        let m = Shape::Sphere.mesh(6).unwrap();
        assert_eq!(m.positions.len(), 40_962);
        assert_eq!(m.faces.len(), 81_920);
    }

    #[test]
    fn cube_is_closed_with_exact_volume_and_sharp_edges() {
        let n = 5;
        let m = Shape::Cube.mesh(n).unwrap();
        let n = n as usize;
        assert_eq!(m.positions.len(), 6 * n * n + 2);
        assert_eq!(m.faces.len(), 12 * n * n);
        check_closed(&m);
        assert!((m.signed_volume() - 8.0).abs() < 1e-12);
        // Right isosceles triangles: all edges are 2/n or 2√2/n.
        for t in m.faces.triangles() {
            for i in 0..3 {
                let e = (m.positions[t[i] as usize] - m.positions[t[(i + 1) % 3] as usize])
                    .length()
                    * n as f64
                    / 2.0;
                assert!((e - 1.0).abs() < 1e-12 || (e - 2f64.sqrt()).abs() < 1e-12);
            }
        }
        assert_eq!(max_dihedral_deg(&m).round(), 90.0);
    }

    #[test]
    fn torus_is_closed_with_close_volume() {
        let m = Shape::Torus.mesh(12).unwrap();
        check_closed(&m);
        assert_eq!(m.positions.len(), 12 * 30);
        // Inscribed polygons: the volume grows towards the ideal one as the mesh refines.
        let v = m.signed_volume();
        let finer = Shape::Torus.mesh(24).unwrap();
        check_closed(&finer);
        let v2 = finer.signed_volume();
        let ideal = Shape::Torus.volume().unwrap();
        assert!(0.0 < v && v < v2 && v2 < ideal, "{v} {v2} {ideal}");
        assert!((ideal - v2) / ideal < 0.015, "{v2} vs {ideal}");
    }

    #[test]
    fn step_is_an_open_upward_sheet_with_a_sharp_step() {
        let m = Shape::Step.mesh(8).unwrap();
        assert!(!is_closed(&m.faces));
        assert!(is_consistently_oriented(&m.faces));
        // Profile: 5 points up to x = 0, 2 up the wall, 4 on the plateau; 9 rows.
        assert_eq!(m.positions.len(), 11 * 9);
        let mut up = 0.0;
        for t in m.faces.triangles() {
            let c = t.map(|v| m.positions[v as usize]);
            let n = (c[1] - c[0]).cross(c[2] - c[0]);
            assert!(
                n.y >= 0.0 && (n.y > 0.0 || n.x < 0.0),
                "faces point up or at −x"
            );
            up += n.y / 2.0;
        }
        // Projected area of the sheet: 2 × 2.
        assert!((up - 4.0).abs() < 1e-12);
        assert_eq!(max_dihedral_deg(&m).round(), 90.0);
    }

    /// Largest angle between the normals of two faces sharing an edge.
    fn max_dihedral_deg(m: &Mesh) -> f64 {
        let mut by_edge: HashMap<(u32, u32), Vec<DVec3>> = HashMap::new();
        for t in m.faces.triangles() {
            let c = t.map(|v| m.positions[v as usize]);
            let n = (c[1] - c[0]).cross(c[2] - c[0]).normalize();
            for i in 0..3 {
                let (a, b) = (t[i], t[(i + 1) % 3]);
                by_edge.entry((a.min(b), a.max(b))).or_default().push(n);
            }
        }
        by_edge
            .values()
            .filter(|v| v.len() == 2)
            .map(|v| v[0].angle_between(v[1]).to_degrees())
            .fold(0.0, f64::max)
    }

    #[test]
    fn csg_is_watertight_with_straight_and_circular_sharp_edges() {
        let m = Shape::Csg.mesh(12).unwrap();
        check_closed(&m);
        let v = m.signed_volume();
        // The hole is a polygon with `around` sides inscribed in the circle.
        let around = ((std::f64::consts::TAU * 0.5 / (2.0 / 12.0)).round()).max(8.0);
        let hole = around / 2.0 * 0.25 * (std::f64::consts::TAU / around).sin();
        assert!((v - (4.0 - hole)).abs() < 1e-9, "{v}");
        assert!((v - Shape::Csg.volume().unwrap()).abs() / v < 0.02);
        // Classify the sharp edges: edges where the normals differ by ~90°. Straight ones lie on
        // the box (|x| = 1 or |y| = 1), circular ones on the hole rim (x² + y² = r²).
        let mut by_edge: HashMap<(u32, u32), Vec<DVec3>> = HashMap::new();
        let mut worst_angle = 180.0f64;
        for t in m.faces.triangles() {
            let c = t.map(|v| m.positions[v as usize]);
            let n = (c[1] - c[0]).cross(c[2] - c[0]).normalize();
            for i in 0..3 {
                let (a, b) = (t[i], t[(i + 1) % 3]);
                by_edge.entry((a.min(b), a.max(b))).or_default().push(n);
                let (e1, e2) = (c[(i + 1) % 3] - c[i], c[(i + 2) % 3] - c[i]);
                worst_angle = worst_angle.min(e1.angle_between(e2).to_degrees());
            }
        }
        let (mut straight, mut circular) = (0, 0);
        for (&(a, b), ns) in &by_edge {
            let angle = ns[0].angle_between(ns[1]).to_degrees();
            if angle > 45.0 {
                assert!((angle - 90.0).abs() < 1e-6, "dihedral {angle}");
                let (p, q) = (m.positions[a as usize], m.positions[b as usize]);
                let mid = (p + q) / 2.0;
                if (mid.x.abs() - 1.0).abs() < 1e-12 || (mid.y.abs() - 1.0).abs() < 1e-12 {
                    straight += 1;
                } else {
                    assert!((p.truncate().length() - 0.5).abs() < 1e-12);
                    circular += 1;
                }
            }
        }
        // 4 vertical box edges (6 segments each) + 2 × 4 × 12 rim segments; 2 × `around` hole rims.
        assert_eq!(straight, 4 * 6 + 2 * 4 * 12);
        assert_eq!(circular, 2 * around as usize);
        // Quality: no sliver triangles.
        assert!(worst_angle > 20.0, "smallest angle {worst_angle}°");
    }

    #[test]
    fn shape_names_parse() {
        for s in Shape::ALL {
            assert_eq!(s.name().parse::<Shape>().unwrap(), s);
            assert!(s.resolution_range().contains(&s.default_resolution()));
        }
        assert!("blob".parse::<Shape>().is_err());
        assert!(Shape::Cube.mesh(0).is_err());
    }

    #[test]
    fn sampler_is_seeded_uniform_and_batch_independent() {
        let m = Shape::Cube.mesh(2).unwrap();
        let n = 20_000u64;
        let mut all = Vec::new();
        let mut s = SurfaceSampler::new(&m.positions, &m.faces, n, 7).unwrap();
        assert!((s.area() - 24.0).abs() < 1e-12);
        let mut buf = Vec::new();
        while s.fill(&mut buf, 999) > 0 {
            all.extend_from_slice(&buf);
        }
        assert_eq!(all.len() as u64, n);
        assert_eq!(s.remaining(), 0);
        let one: Vec<DVec3> = Shape::Cube.sampler(2, n, 7).unwrap().flatten().collect();
        assert_eq!(one, all);
        let other: Vec<DVec3> = SurfaceSampler::new(&m.positions, &m.faces, 10, 8)
            .unwrap()
            .flatten()
            .collect();
        assert_ne!(other[..], all[..10]);
        // On the surface, and about one sixth on each face.
        let mut per_face = [0usize; 6];
        for p in &all {
            let a = p.abs();
            let axis = if a.x >= a.y && a.x >= a.z {
                0
            } else if a.y >= a.z {
                1
            } else {
                2
            };
            assert!((a.max_element() - 1.0).abs() < 1e-12);
            per_face[2 * axis + usize::from(p[axis] > 0.0)] += 1;
        }
        for c in per_face {
            let expected = n as f64 / 6.0;
            assert!((c as f64 - expected).abs() < 5.0 * expected.sqrt(), "{c}");
        }
        let degenerate = Faces::from_triangles(&[[0, 0, 1]]);
        assert!(SurfaceSampler::new(&m.positions, &degenerate, 1, 0).is_err());
    }
}
