//! The parametric street scene (`--scene street`).
//!
//! # Brief overview
//!
//! ```text
//!   y ▲  yard ░ building ░ building    ░ ░ building      (fences and bushes in front yards)
//!     │  ═══════ sidewalk ══ pole ═ tree ═ object ══════  kerb (vertical face)
//!     │  ─ ─ ─ ─ road (crowned), parked cars ─ ─ ─ ─ ─ ─  wires between poles, some across
//!     │  ═══════ sidewalk ══════ tree ══ pole ══════════
//!     └──────────────────────────────────────────────▶ x   (z up, the street rises along x)
//! ```
//!
//! Everything varies with the scene seed (ChaCha8): the road and sidewalk widths, the kerb
//! height, the slope along the street, how many buildings of which widths, depths, heights and
//! roofs (flat, gabled along or across the street), setbacks, poles and their spacing, wire sag,
//! cars, trees (trunk and a crown of leaf triangles), bushes, fences (picket or solid) and where
//! the sculpted object stands. The length of the street is a parameter (`--length`, default
//! [`DEFAULT_LENGTH`] m); the scene is [`HALF_DEPTH`] m deep on each side of the axis.
//!
//! Sizes are those of a real residential street: lanes of 3.2–4 m, sidewalks of 2.5–4 m, kerbs
//! 12–18 cm, slope up to 3 %, a 2 % cross-fall from the crown to the gutters, houses 5–15 m to
//! the eaves, poles 7–9 m with 7–13 cm radius, wires of 8–15 mm radius sagging 0.3–1 m over a
//! span, cars 3.8–4.9 m long, tree crowns 1.6–2.8 m in radius holding about 120 leaves (8–12 cm)
//! per m³, bushes 350 leaves (6 cm) per m³.

use glam::{DVec2, DVec3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::LidarError;
use super::kinds::Kind;
use super::scene::{Scene, SceneBuilder};
use crate::eval::synth::Shape;
use crate::points::Faces;

/// Default length of the street (m).
pub const DEFAULT_LENGTH: f64 = 100.0;
/// The scene reaches this far (m) on each side of the street's axis.
pub const HALF_DEPTH: f64 = 28.0;
/// Leaves per m³ of a tree crown.
const TREE_LEAVES: f64 = 120.0;
/// Leaves per m³ of a bush.
const BUSH_LEAVES: f64 = 350.0;
/// Sides of a pole, trunk or wheel.
const ROUND_SIDES: usize = 16;
/// Sides of a wire.
const WIRE_SIDES: usize = 8;
/// Length of a wire segment (m).
const WIRE_SEGMENT: f64 = 0.5;

/// A mesh placed into the scene (`--mesh`).
#[derive(Debug, Clone)]
pub struct PlacedMesh {
    /// Its vertices, in its own frame.
    pub positions: Vec<DVec3>,
    /// Its faces.
    pub faces: Faces,
    /// Where the centre of its bounding box's bottom goes; `None`: on a sidewalk, by the seed.
    pub at: Option<DVec3>,
    /// Scale factor; `None`: the largest extent becomes 1.5 m.
    pub scale: Option<f64>,
    /// The mesh's up axis is y (most mesh files), turned to z.
    pub y_up: bool,
}

/// What the street is made of besides its seed.
#[derive(Debug, Clone)]
pub struct StreetSpec {
    /// Length along x (m).
    pub length: f64,
    /// The sculpted object on a sidewalk (`None`: none).
    pub object: Option<Shape>,
    /// A mesh file's mesh.
    pub mesh: Option<PlacedMesh>,
}

impl Default for StreetSpec {
    fn default() -> StreetSpec {
        StreetSpec {
            length: DEFAULT_LENGTH,
            object: Some(Shape::Torus),
            mesh: None,
        }
    }
}

/// Where the street's surfaces are, for placing sensors.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Layout {
    /// Length along x; the street runs from −length/2 to length/2.
    pub length: f64,
    /// The scene's half extent across (y).
    pub half_depth: f64,
    /// Half the road's width (kerb to kerb).
    pub road_half: f64,
    /// Sidewalk width.
    pub sidewalk: f64,
    /// Kerb height.
    pub kerb: f64,
    /// Rise per metre along x.
    pub slope: f64,
    /// Fall per metre from the crown (y = 0) to the gutters.
    pub crossfall: f64,
}

impl Layout {
    /// Height of the road at (x, y), |y| ≤ `road_half`.
    pub fn road_z(&self, x: f64, y: f64) -> f64 {
        self.slope * x - self.crossfall * y.abs()
    }

    /// Height of the sidewalks and yards at x.
    pub fn sidewalk_z(&self, x: f64) -> f64 {
        self.slope * x - self.crossfall * self.road_half + self.kerb
    }

    /// Height of the ground at (x, y).
    pub fn ground_z(&self, x: f64, y: f64) -> f64 {
        if y.abs() <= self.road_half {
            self.road_z(x, y)
        } else {
            self.sidewalk_z(x)
        }
    }

    /// The middle of the right-hand lane (driving towards +x).
    pub fn lane_y(&self) -> f64 {
        -self.road_half / 2.0
    }

    /// The middle of the sidewalk on the side of `sign` (±1).
    pub fn sidewalk_y(&self, sign: f64) -> f64 {
        sign * (self.road_half + self.sidewalk / 2.0)
    }
}

/// A built street.
#[derive(Debug, Clone)]
pub struct Street {
    /// Its triangles.
    pub scene: Scene,
    /// Its layout.
    pub layout: Layout,
}

/// Builds the street of `seed`.
///
/// # Errors
/// A length outside 20–2000 m; a placed mesh without faces.
pub fn street(spec: &StreetSpec, seed: u64) -> Result<Street, LidarError> {
    if !(20.0..=2000.0).contains(&spec.length) {
        return Err(LidarError::Param {
            name: "length",
            detail: format!("the street's length must be 20–2000 m, got {}", spec.length),
        });
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(0x0057_4745_4554);
    let layout = Layout {
        length: spec.length,
        half_depth: HALF_DEPTH,
        road_half: rng.random_range(3.2..4.0),
        sidewalk: rng.random_range(2.5..4.0),
        kerb: rng.random_range(0.12..0.18),
        slope: rng.random_range(-0.03..0.03),
        crossfall: 0.02,
    };
    let mut s = Builder {
        b: SceneBuilder::default(),
        l: layout,
        rng,
        poles: Vec::new(),
        taken: Vec::new(),
    };
    s.ground();
    for sign in [-1.0, 1.0] {
        s.buildings(sign);
        s.poles(sign);
    }
    s.wires();
    for sign in [-1.0, 1.0] {
        s.cars(sign);
        s.trees(sign);
    }
    if let Some(shape) = spec.object {
        s.sculpture(shape)?;
    }
    if let Some(m) = &spec.mesh {
        s.placed(m)?;
    }
    Ok(Street {
        scene: s.b.finish(),
        layout,
    })
}

struct Builder {
    b: SceneBuilder,
    l: Layout,
    rng: ChaCha8Rng,
    /// (x, y, top z) of every pole.
    poles: Vec<DVec3>,
    /// (x, y, radius) of everything standing on a sidewalk (poles, trees, the object).
    taken: Vec<DVec3>,
}

impl Builder {
    fn u(&mut self, lo: f64, hi: f64) -> f64 {
        self.rng.random_range(lo..hi)
    }

    fn chance(&mut self, p: f64) -> bool {
        self.rng.random_bool(p)
    }

    fn half(&self) -> f64 {
        self.l.length / 2.0
    }

    /// Road (two planes meeting at the crown), then per side the kerb face and the sidewalk and
    /// yard plane.
    fn ground(&mut self) {
        let (x, l) = (self.half(), self.l);
        let road = self.b.object(Kind::Ground);
        let p = |x: f64, y: f64| DVec3::new(x, y, l.ground_z(x, y));
        let rh = l.road_half;
        self.b
            .polygon(road, &[p(-x, -rh), p(x, -rh), p(x, 0.0), p(-x, 0.0)]);
        self.b
            .polygon(road, &[p(-x, 0.0), p(x, 0.0), p(x, rh), p(-x, rh)]);
        for sign in [-1.0, 1.0] {
            let side = self.b.object(Kind::Ground);
            let y0 = sign * rh;
            let y1 = sign * l.half_depth;
            let low = |x: f64| DVec3::new(x, y0, l.road_z(x, y0));
            let high = |x: f64, y: f64| DVec3::new(x, y, l.sidewalk_z(x));
            let (kerb, top) = if sign > 0.0 {
                (
                    [low(-x), low(x), high(x, y0), high(-x, y0)],
                    [high(-x, y0), high(x, y0), high(x, y1), high(-x, y1)],
                )
            } else {
                (
                    [low(x), low(-x), high(-x, y0), high(x, y0)],
                    [high(-x, y1), high(x, y1), high(x, y0), high(-x, y0)],
                )
            };
            self.b.polygon(side, &kerb);
            self.b.polygon(side, &top);
        }
    }

    /// A row of buildings on one side, with their front yards' fences and bushes.
    fn buildings(&mut self, sign: f64) {
        let l = self.l;
        let end = self.half();
        let mut x0 = -end + self.u(0.0, 4.0);
        while x0 < end - 6.0 {
            let w = self.u(8.0, 20.0).min(end - x0);
            let setback = if self.chance(0.3) {
                0.0
            } else {
                self.u(0.5, 5.0)
            };
            let front = l.road_half + l.sidewalk + setback;
            let depth = self.u(8.0, 14.0).min(l.half_depth - 1.0 - front);
            let height = self.u(5.0, 15.0);
            let rise = self.u(1.5, 3.5);
            let roof = self.rng.random_range(0..20u32);
            let x1 = x0 + w;
            let base = l.sidewalk_z(x0).min(l.sidewalk_z(x1)) - 0.5;
            let eave = l.sidewalk_z((x0 + x1) / 2.0) + height;
            let id = self.b.object(Kind::Building);
            let (ya, yb) = (sign * front, sign * (front + depth));
            let (y0, y1) = (ya.min(yb), ya.max(yb));
            if roof < 8 {
                // Flat roof.
                let profile = [
                    DVec2::new(y0, base),
                    DVec2::new(y1, base),
                    DVec2::new(y1, eave),
                    DVec2::new(y0, eave),
                ];
                self.b.prism(
                    id,
                    DVec3::new(x0, 0.0, 0.0),
                    DVec3::Y,
                    DVec3::Z,
                    &profile,
                    DVec3::X * w,
                );
            } else if roof < 15 {
                // Gabled, ridge along the street.
                let profile = [
                    DVec2::new(y0, base),
                    DVec2::new(y1, base),
                    DVec2::new(y1, eave),
                    DVec2::new((y0 + y1) / 2.0, eave + rise),
                    DVec2::new(y0, eave),
                ];
                self.b.prism(
                    id,
                    DVec3::new(x0, 0.0, 0.0),
                    DVec3::Y,
                    DVec3::Z,
                    &profile,
                    DVec3::X * w,
                );
            } else {
                // Gabled, ridge across the street.
                let profile = [
                    DVec2::new(x0, base),
                    DVec2::new(x1, base),
                    DVec2::new(x1, eave),
                    DVec2::new((x0 + x1) / 2.0, eave + rise),
                    DVec2::new(x0, eave),
                ];
                self.b.prism(
                    id,
                    DVec3::new(0.0, y0, 0.0),
                    DVec3::X,
                    DVec3::Z,
                    &profile,
                    DVec3::Y * (y1 - y0),
                );
            }
            if setback >= 1.5 {
                self.yard(sign, x0, x1, setback);
            }
            x0 = x1
                + if self.chance(0.35) {
                    0.0
                } else {
                    self.u(1.0, 6.0)
                };
        }
    }

    /// A front yard between x0 and x1: maybe a fence along the sidewalk, and bushes.
    fn yard(&mut self, sign: f64, x0: f64, x1: f64, setback: f64) {
        let l = self.l;
        let edge = l.road_half + l.sidewalk;
        if self.chance(0.6) {
            let y = sign * (edge + 0.1);
            let gate = (x0 + x1) / 2.0;
            let picket = self.chance(0.7);
            let height = self.u(0.9, 1.3);
            for (a, b) in [(x0 + 0.3, gate - 0.6), (gate + 0.6, x1 - 0.3)] {
                if b - a > 1.0 {
                    self.fence(y, a, b, height, picket);
                }
            }
        }
        let bushes = self.rng.random_range(1..4u32);
        for _ in 0..bushes {
            let x = self.u(x0 + 1.0, x1 - 1.0);
            let semi = DVec3::new(self.u(0.4, 0.9), self.u(0.4, 0.9), self.u(0.35, 0.7));
            let semi = semi
                .min(DVec3::new(9.0, setback / 2.0 - 0.2, 9.0))
                .max(DVec3::splat(0.25));
            let y = sign * (edge + setback / 2.0);
            let c = DVec3::new(x, y, l.sidewalk_z(x) + semi.z * 0.85);
            let id = self.b.object(Kind::LowVegetation);
            let n = (BUSH_LEAVES * ellipsoid_volume(semi)).round() as usize;
            self.b.leaves(id, c, semi, n, 0.06, &mut self.rng);
        }
    }

    /// A fence along y from x = a to b: posts, two rails and slats, or one solid panel.
    fn fence(&mut self, y: f64, a: f64, b: f64, height: f64, picket: bool) {
        let l = self.l;
        let id = self.b.object(Kind::Fence);
        let z = |x: f64| l.sidewalk_z(x);
        if !picket {
            let c = DVec3::new((a + b) / 2.0, y, z((a + b) / 2.0) + height / 2.0 - 0.1);
            self.b.oriented_box(
                id,
                c,
                DVec3::new((b - a) / 2.0, 0.02, height / 2.0 + 0.1),
                DVec3::X,
            );
            return;
        }
        let posts = ((b - a) / 2.0).ceil().max(1.0) as usize;
        for k in 0..=posts {
            let x = a + (b - a) * k as f64 / posts as f64;
            let c = DVec3::new(x, y, z(x) + height / 2.0 - 0.05);
            self.b
                .oriented_box(id, c, DVec3::new(0.04, 0.04, height / 2.0 + 0.05), DVec3::X);
        }
        for rail in [0.25, height - 0.2] {
            let c = DVec3::new((a + b) / 2.0, y + 0.05, z((a + b) / 2.0) + rail);
            self.b
                .oriented_box(id, c, DVec3::new((b - a) / 2.0, 0.015, 0.04), DVec3::X);
        }
        let pitch = 0.14;
        let slats = ((b - a) / pitch).floor() as usize;
        for k in 0..slats {
            let x = a + pitch * (k as f64 + 0.5);
            let c = DVec3::new(x, y + 0.08, z(x) + height / 2.0 + 0.02);
            self.b.oriented_box(
                id,
                c,
                DVec3::new(0.045, 0.01, height / 2.0 - 0.04),
                DVec3::X,
            );
        }
    }

    /// Street-light poles along the kerb of one side.
    fn poles(&mut self, sign: f64) {
        let l = self.l;
        let end = self.half();
        let mut x = -end + self.u(3.0, 10.0);
        while x < end - 3.0 {
            let y = sign * (l.road_half + 0.5);
            let height = self.u(7.0, 9.0);
            let radius = self.u(0.07, 0.13);
            let base = l.sidewalk_z(x);
            let id = self.b.object(Kind::Pole);
            self.b.cylinder(
                id,
                DVec3::new(x, y, base - 0.2),
                DVec3::Z * (height + 0.2),
                radius,
                ROUND_SIDES,
            );
            self.poles.push(DVec3::new(x, y, base + height));
            self.taken.push(DVec3::new(x, y, radius + 0.5));
            x += self.u(22.0, 30.0);
        }
    }

    /// Two wires between consecutive poles of a side, and one or two across the street.
    fn wires(&mut self) {
        let poles = self.poles.clone();
        for sign in [-1.0, 1.0] {
            let side: Vec<DVec3> = poles.iter().copied().filter(|p| p.y * sign > 0.0).collect();
            for w in side.windows(2) {
                for drop in [0.3, 0.8] {
                    let sag = self.u(0.3, 1.0);
                    let radius = self.u(0.008, 0.015);
                    let a = w[0] - DVec3::Z * drop;
                    let b = w[1] - DVec3::Z * drop;
                    self.wire(a, b, sag, radius);
                }
            }
        }
        let (left, right): (Vec<DVec3>, Vec<DVec3>) = poles.iter().partition(|p| p.y < 0.0);
        let mut crossings = 0;
        for a in &left {
            if crossings == 2 {
                break;
            }
            if let Some(b) = right.iter().find(|b| (b.x - a.x).abs() < 15.0) {
                let sag = self.u(0.3, 0.8);
                let radius = self.u(0.008, 0.015);
                self.wire(*a - DVec3::Z * 0.5, *b - DVec3::Z * 0.5, sag, radius);
                crossings += 1;
            }
        }
    }

    /// A catenary from a to b sagging `sag` below the chord at mid-span.
    fn wire(&mut self, a: DVec3, b: DVec3, sag: f64, radius: f64) {
        let span = (b - a).truncate().length();
        let c = catenary_parameter(span, sag);
        let n = ((span / WIRE_SEGMENT).ceil() as usize).max(2);
        let path: Vec<DVec3> = (0..=n)
            .map(|k| {
                let t = k as f64 / n as f64;
                let s = span * t - span / 2.0;
                let below = c * (libm::cosh(span / (2.0 * c)) - libm::cosh(s / c));
                a.lerp(b, t) - DVec3::Z * below
            })
            .collect();
        let id = self.b.object(Kind::Wire);
        self.b.tube(id, &path, radius, WIRE_SIDES);
    }

    /// Cars parked along the kerb of one side, in the road.
    fn cars(&mut self, sign: f64) {
        let l = self.l;
        let end = self.half();
        let mut x = -end + self.u(2.0, 8.0);
        loop {
            let length = self.u(3.8, 4.9);
            if x + length > end - 2.0 {
                break;
            }
            if self.chance(0.75) {
                let width = self.u(1.7, 1.9);
                let y = sign * (l.road_half - 0.25 - width / 2.0);
                let c = DVec3::new(x + length / 2.0, y, 0.0);
                let heading = if self.chance(0.5) {
                    DVec3::X
                } else {
                    DVec3::NEG_X
                };
                let yaw = self.u(-0.03, 0.03);
                let axis = DVec3::new(heading.x * libm::cos(yaw), libm::sin(yaw), 0.0);
                let ground = l.road_z(c.x, c.y);
                self.car(c.truncate().extend(ground), axis, length, width);
            }
            x += length + self.u(1.0, 10.0);
        }
    }

    /// A car standing at `c` (on the ground), pointing along the unit horizontal `axis`.
    fn car(&mut self, c: DVec3, axis: DVec3, length: f64, width: f64) {
        let id = self.b.object(Kind::Car);
        let side = DVec3::Z.cross(axis);
        let body = (0.32, 0.95);
        self.b.oriented_box(
            id,
            c + DVec3::Z * ((body.0 + body.1) / 2.0),
            DVec3::new(length / 2.0, width / 2.0, (body.1 - body.0) / 2.0),
            axis,
        );
        // The cabin: a trapezoid (slanted windscreen and rear window) across the car's width.
        let cabin_width = width * 0.88;
        let (top, h) = (body.1 + 0.5, length);
        let profile = [
            DVec2::new(-0.32 * h, body.1),
            DVec2::new(0.22 * h, body.1),
            DVec2::new(0.05 * h, top),
            DVec2::new(-0.24 * h, top),
        ];
        self.b.prism(
            id,
            c - side * (cabin_width / 2.0),
            axis,
            DVec3::Z,
            &profile,
            side * cabin_width,
        );
        let r = 0.31;
        for along in [-0.32, 0.32] {
            for across in [-1.0, 1.0] {
                let hub = c
                    + axis * (along * length)
                    + side * (across * (width / 2.0 - 0.1))
                    + DVec3::Z * r;
                self.b
                    .cylinder(id, hub - side * 0.1, side * 0.2, r, ROUND_SIDES);
            }
        }
    }

    /// Trees on the sidewalk of one side, about half-way between poles.
    fn trees(&mut self, sign: f64) {
        let l = self.l;
        let poles: Vec<DVec3> = self
            .poles
            .iter()
            .copied()
            .filter(|p| p.y * sign > 0.0)
            .collect();
        let mut spots: Vec<f64> = poles.windows(2).map(|w| (w[0].x + w[1].x) / 2.0).collect();
        if let (Some(first), Some(last)) = (poles.first(), poles.last()) {
            spots.push(first.x - 12.0);
            spots.push(last.x + 12.0);
        }
        for x in spots {
            if x.abs() > self.half() - 3.0 || !self.chance(0.75) {
                continue;
            }
            let x = x + self.u(-3.0, 3.0);
            let y = sign * (l.road_half + l.sidewalk - 0.8);
            let trunk = self.u(0.12, 0.22);
            let crown_base = self.u(2.2, 3.2);
            let semi = DVec3::new(self.u(1.6, 2.8), 0.0, self.u(1.8, 3.0));
            let semi = DVec3::new(semi.x, semi.x, semi.z);
            let ground = l.sidewalk_z(x);
            let centre = DVec3::new(x, y, ground + crown_base + semi.z * 0.9);
            let id = self.b.object(Kind::HighVegetation);
            self.b.cylinder(
                id,
                DVec3::new(x, y, ground - 0.2),
                DVec3::Z * (centre.z - ground + 0.2),
                trunk,
                ROUND_SIDES,
            );
            let n = (TREE_LEAVES * ellipsoid_volume(semi)).round() as usize;
            let size = self.u(0.08, 0.12);
            self.b.leaves(id, centre, semi, n, size, &mut self.rng);
            self.taken.push(DVec3::new(x, y, trunk + 0.5));
        }
    }

    /// A free spot on a sidewalk at least `clear` from everything standing there.
    fn free_spot(&mut self, clear: f64) -> DVec3 {
        let l = self.l;
        let mut best = DVec3::ZERO;
        let mut best_gap = f64::NEG_INFINITY;
        for _ in 0..40 {
            let sign = if self.chance(0.5) { 1.0 } else { -1.0 };
            let x = self.u(-self.half() * 0.6, self.half() * 0.6);
            let y = l.sidewalk_y(sign);
            let gap = self
                .taken
                .iter()
                .map(|t| (t.truncate() - DVec2::new(x, y)).length() - t.z)
                .fold(f64::INFINITY, f64::min);
            if gap > best_gap {
                (best, best_gap) = (DVec3::new(x, y, l.sidewalk_z(x)), gap);
            }
            if gap >= clear {
                break;
            }
        }
        best
    }

    /// The sculpted shape on a pedestal, standing upright and facing the street.
    fn sculpture(&mut self, shape: Shape) -> Result<(), LidarError> {
        let mesh = shape
            .mesh(shape.default_resolution().min(64))
            .map_err(|e| LidarError::Scene(e.to_string()))?;
        let spot = self.free_spot(2.0);
        let id = self.b.object(Kind::Object);
        let pedestal = 0.4;
        self.b.aabb(
            id,
            spot + DVec3::new(-0.3, -0.25, -0.2),
            spot + DVec3::new(0.3, 0.25, pedestal),
        );
        // Upright: the shape's z axis turned to −y (the torus faces the street), scaled to about
        // 1.4 m across.
        let (lo, hi) = bounds(&mesh.positions);
        let scale = 1.4 / (hi - lo).max_element();
        let turned = |p: DVec3| DVec3::new(p.x, -p.z, p.y);
        let (tlo, _) = bounds(
            &mesh
                .positions
                .iter()
                .map(|&p| turned(p))
                .collect::<Vec<_>>(),
        );
        let lift = spot.z + pedestal - tlo.z * scale;
        self.b.mesh(id, &mesh.positions, &mesh.faces, |p| {
            let q = turned(p) * scale;
            DVec3::new(spot.x + q.x, spot.y + q.y, lift + q.z)
        });
        self.taken.push(DVec3::new(spot.x, spot.y, 1.0));
        Ok(())
    }

    /// A mesh file's mesh, scaled and placed.
    fn placed(&mut self, m: &PlacedMesh) -> Result<(), LidarError> {
        if m.faces.is_empty() {
            return Err(LidarError::Param {
                name: "mesh",
                detail: "the mesh file has no faces".into(),
            });
        }
        let turn = |p: DVec3| {
            if m.y_up {
                DVec3::new(p.x, -p.z, p.y)
            } else {
                p
            }
        };
        let turned: Vec<DVec3> = m.positions.iter().map(|&p| turn(p)).collect();
        let (lo, hi) = bounds(&turned);
        let extent = (hi - lo).max_element();
        let scale = match m.scale {
            Some(s) => s,
            None if extent > 0.0 => 1.5 / extent,
            None => 1.0,
        };
        let at = match m.at {
            Some(a) => a,
            None => self.free_spot(2.0),
        };
        let bottom = DVec3::new((lo.x + hi.x) / 2.0, (lo.y + hi.y) / 2.0, lo.z);
        let id = self.b.object(Kind::Object);
        self.b
            .mesh(id, &turned, &m.faces, |p| at + (p - bottom) * scale);
        Ok(())
    }
}

/// Volume of an ellipsoid of semi-axes `s`.
fn ellipsoid_volume(s: DVec3) -> f64 {
    4.0 / 3.0 * std::f64::consts::PI * s.x * s.y * s.z
}

/// The smallest and largest coordinates of `p`.
fn bounds(p: &[DVec3]) -> (DVec3, DVec3) {
    p.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), &q| (lo.min(q), hi.max(q)),
    )
}

/// The parameter c of the catenary c·cosh(s/c) that sags `sag` over `span` (bisection on
/// c·(cosh(span/2c) − 1) = sag, which falls monotonically in c).
fn catenary_parameter(span: f64, sag: f64) -> f64 {
    let f = |c: f64| c * (libm::cosh(span / (2.0 * c)) - 1.0) - sag;
    let (mut lo, mut hi) = (span / 100.0, span * 1e4);
    for _ in 0..200 {
        let mid = (lo * hi).sqrt();
        if f(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    (lo * hi).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn catenary_sags_as_asked() {
        let c = catenary_parameter(25.0, 0.7);
        assert!((c * (libm::cosh(12.5 / c) - 1.0) - 0.7).abs() < 1e-9);
    }

    #[test]
    fn streets_differ_by_seed_and_hold_every_kind() {
        let a = street(&StreetSpec::default(), 1).unwrap();
        let b = street(&StreetSpec::default(), 2).unwrap();
        let again = street(&StreetSpec::default(), 1).unwrap();
        assert_eq!(a.scene.positions, again.scene.positions);
        assert_ne!(a.scene.positions.len(), b.scene.positions.len());
        let kinds: Vec<Kind> = a.scene.triangles_per_kind().iter().map(|k| k.0).collect();
        for k in Kind::ALL {
            if k != Kind::Mixed {
                assert!(kinds.contains(&k), "{k} missing");
            }
        }
        assert!(
            street(
                &StreetSpec {
                    length: 5.0,
                    ..StreetSpec::default()
                },
                0
            )
            .is_err()
        );
    }
}
