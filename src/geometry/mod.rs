//! Geometric kernels: quadrics, their minimisers, PCA normals and exact sums.
//!
//! # Brief overview
//!
//! * [`Quadric`] is Garland–Heckbert's error quadric, stored as its ten unique coefficients: the
//!   symmetric [`SymMat3`] `A`, the vector `b` and the scalar `c`, so that the error at `w` is
//!   `wᵀAw + 2bᵀw + c`. [`Quadric::plane`] builds the squared distance to a plane; quadrics add.
//! * [`Solve`] turns a summed quadric into a new position: the paper's `plain` minimiser, Lindstrom's
//!   `robust` truncated pseudo-inverse, or a `regularised` minimiser that bounds the step.
//! * [`pca_fit`] gives a neighbourhood's principal axes; [`pca_normal`] its plane (smallest
//!   eigenvector of the centred covariance). [`along_fit`] fits a neighbourhood along a known
//!   beam direction (LiDAR range noise); [`Quadric::along`] minimises a quadric on a beam.
//! * [`floor_i64`] keys a coordinate to its cell without a libm call; [`exp`] is `eˣ` without
//!   one, the same bits on every platform (the operators' Gaussian weights).
//! * [`ExactSum`] adds f64 values without rounding, so global means are the same bits whatever the
//!   order or grouping of the terms (tiles, threads).
//!
//! Kernels take positions *relative to the vertex being moved*: a quadric built from `u − v` and
//! minimised near the origin returns an offset from `v`. That keeps every intermediate small even on
//! UTM-sized coordinates, and makes the operator exactly translation invariant in exact arithmetic.

mod along;
mod cell;
mod eigen;
mod exp;
mod sum;

pub use along::{AlongFit, along_fit};
pub use cell::floor_i64;
pub use eigen::{Eigen, SymMat3, any_orthogonal};
pub use exp::exp;
pub use sum::ExactSum;

use glam::DVec3;
use thiserror::Error;

/// Errors of the geometric kernels: parameters out of range.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum GeometryError {
    /// A solver parameter is outside its valid range.
    #[error("{name} must be {expected}, got {value}")]
    Parameter {
        /// Parameter name.
        name: &'static str,
        /// Valid range.
        expected: &'static str,
        /// Given value.
        value: f64,
    },
}

/// An error quadric `Q(w) = wᵀAw + 2bᵀw + c` (ten coefficients).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Quadric {
    /// The quadratic part.
    pub a: SymMat3,
    /// The linear part.
    pub b: DVec3,
    /// The constant.
    pub c: f64,
}

impl Quadric {
    /// The zero quadric.
    pub const ZERO: Quadric = Quadric {
        a: SymMat3::ZERO,
        b: DVec3::ZERO,
        c: 0.0,
    };

    /// Squared distance to the plane through `p` with unit normal `n`: with `d = n·p`,
    /// `A = n nᵀ`, `b = −d n`, `c = d²`. A zero `n` gives the zero quadric.
    #[inline]
    pub fn plane(n: DVec3, p: DVec3) -> Quadric {
        let d = n.dot(p);
        Quadric {
            a: SymMat3::outer(n),
            b: -d * n,
            c: d * d,
        }
    }

    /// Adds `weight` times the plane quadric of (`n`, `p`) in place.
    #[inline]
    pub fn add_plane(&mut self, n: DVec3, p: DVec3, weight: f64) {
        let d = n.dot(p);
        self.a.add_outer(n, weight);
        self.b -= (weight * d) * n;
        self.c += weight * d * d;
    }

    /// The minimiser `t` of the quadric on the line `t·d` through the origin (the vertex):
    /// `t = −dᵀb / dᵀAd`, one division. `None` when the quadric barely varies along `d`
    /// (`dᵀAd ≤` [`SINGULAR_ALONG`] `· tr A`: planes that contain the line, which fix no point
    /// on it) or the result is not finite.
    #[inline]
    pub fn along(&self, d: DVec3) -> Option<f64> {
        let dad = d.dot(self.a.mul_vec(d));
        if dad.is_nan() || dad <= SINGULAR_ALONG * self.a.trace() {
            return None;
        }
        let t = -d.dot(self.b) / dad;
        t.is_finite().then_some(t)
    }

    /// Evaluates the quadric at `w`.
    pub fn eval(&self, w: DVec3) -> f64 {
        w.dot(self.a.mul_vec(w)) + 2.0 * self.b.dot(w) + self.c
    }

    /// The same quadric expressed in coordinates centred at `origin` (`Q'(x) = Q(x + origin)`).
    pub fn recentred(&self, origin: DVec3) -> Quadric {
        let ao = self.a.mul_vec(origin);
        Quadric {
            a: self.a,
            b: self.b + ao,
            c: self.c + 2.0 * self.b.dot(origin) + origin.dot(ao),
        }
    }
}

impl std::ops::AddAssign<&Quadric> for Quadric {
    fn add_assign(&mut self, o: &Quadric) {
        self.a.add(&o.a);
        self.b += o.b;
        self.c += o.c;
    }
}

impl std::ops::Add for Quadric {
    type Output = Quadric;
    fn add(mut self, o: Quadric) -> Quadric {
        self += &o;
        self
    }
}

/// How the minimiser of a summed quadric is found.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase", tag = "kind")]
pub enum Solve {
    /// The paper's `w = −A⁻¹b`; a vertex whose `λmin ≤ 1e-12·λmax` stays put.
    Plain,
    /// Lindstrom's `w = v − A⁺(Av + b)`, dropping eigenvalues below `eps·λmax`.
    Robust {
        /// Relative eigenvalue cut-off, in (0, 1).
        eps: f64,
    },
    /// Minimises `Q(w) + λ‖w − v‖²`: `w = v − (A + λI)⁻¹(Av + b)`. `λ` is in the units of `A`
    /// (one unit per unit-normal plane summed), so it is scale-free.
    Regularised {
        /// Weight of the step penalty, > 0.
        lambda: f64,
    },
}

/// Relative threshold below which the plain solve treats `A` as singular.
pub const SINGULAR_RATIO: f64 = 1e-12;

/// Smallest `dᵀAd / tr A` of a quadric that [`Quadric::along`] minimises along `d`: below it the
/// summed planes all but contain the line (for one plane, `dᵀAd / tr A` is the squared sine of
/// the angle between the line and the plane: 1e-6 is 0.06°), so a step along it would divide the
/// planes' offset by a vanishing sine, and the point stays.
pub const SINGULAR_ALONG: f64 = 1e-6;

impl Solve {
    /// Checks the parameter ranges.
    ///
    /// # Errors
    /// [`GeometryError::Parameter`] naming the parameter.
    pub fn validate(&self) -> Result<(), GeometryError> {
        match *self {
            Solve::Plain => Ok(()),
            Solve::Robust { eps } if eps > 0.0 && eps < 1.0 => Ok(()),
            Solve::Robust { eps } => Err(GeometryError::Parameter {
                name: "eps",
                expected: "in (0, 1)",
                value: eps,
            }),
            Solve::Regularised { lambda } if lambda > 0.0 && lambda.is_finite() => Ok(()),
            Solve::Regularised { lambda } => Err(GeometryError::Parameter {
                name: "lambda",
                expected: "finite and > 0",
                value: lambda,
            }),
        }
    }

    /// The minimiser of `q`, a quadric in coordinates centred at the vertex, as an offset from the
    /// vertex. `None` when the vertex must stay where it is (zero or singular `A`, non-finite
    /// result).
    pub fn offset(&self, q: &Quadric) -> Option<DVec3> {
        // The regularised step of a quadric with a positive trace (every quadric of planes and
        // lines with positive weight, so its largest eigenvalue is positive) is one linear
        // solve; anything else (a zero, negative or non-finite trace, a solve that fails) takes
        // the eigendecomposition below and its checks.
        if let Solve::Regularised { lambda } = *self
            && q.a.trace() > 0.0
            && let Some(step) = q.a.solve_shifted(lambda, q.b)
        {
            return Some(-step);
        }
        let e = q.a.eigen();
        let lmax = e.values[2];
        if lmax.is_nan() || lmax <= 0.0 {
            return None;
        }
        // g = A·0 + b: the gradient / 2 at the vertex.
        let g = q.b;
        let mut step = DVec3::ZERO;
        match *self {
            Solve::Plain => {
                if e.values[0] <= SINGULAR_RATIO * lmax {
                    return None;
                }
                for i in 0..3 {
                    step += e.vectors[i] * (e.vectors[i].dot(g) / e.values[i]);
                }
            }
            Solve::Robust { eps } => {
                for i in 0..3 {
                    if e.values[i] >= eps * lmax {
                        step += e.vectors[i] * (e.vectors[i].dot(g) / e.values[i]);
                    }
                }
            }
            Solve::Regularised { lambda } => {
                for i in 0..3 {
                    step += e.vectors[i] * (e.vectors[i].dot(g) / (e.values[i] + lambda));
                }
            }
        }
        let w = -step;
        w.is_finite().then_some(w)
    }
}

/// Result of fitting a plane to a neighbourhood.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaneFit {
    /// Unit normal (eigenvector of the smallest covariance eigenvalue); sign arbitrary.
    pub normal: DVec3,
    /// Covariance eigenvalues, ascending.
    pub values: [f64; 3],
    /// Mean of the neighbourhood, relative to the caller's origin.
    pub centroid: DVec3,
}

/// Relative threshold on the middle covariance eigenvalue below which a neighbourhood is a line or
/// a single point and has no plane.
pub const DEGENERATE_RATIO: f64 = 1e-12;

/// The principal axes of a neighbourhood: the centred covariance's eigen decomposition.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PcaFit {
    /// Number of points.
    pub count: usize,
    /// Eigenvalues of `Σ (q − q̄)(q − q̄)ᵀ`, ascending (sums, not means: divide by `count` for
    /// variances).
    pub values: [f64; 3],
    /// Unit eigenvectors, `vectors[i]` for `values[i]`: `vectors[0]` is the plane normal,
    /// `vectors[2]` the line direction.
    pub vectors: [DVec3; 3],
    /// Mean of the neighbourhood, relative to the caller's origin.
    pub centroid: DVec3,
}

impl PcaFit {
    /// True when the points span a plane (middle eigenvalue above [`DEGENERATE_RATIO`] of the
    /// largest): the normal is meaningful.
    pub fn has_plane(&self) -> bool {
        self.values[1] > DEGENERATE_RATIO * self.values[2]
    }

    /// True when the points are not all coincident: the line direction is meaningful.
    pub fn has_axis(&self) -> bool {
        self.values[2] > 0.0
    }
}

/// The principal axes of `pts` (already relative to some nearby origin). `None` for fewer than
/// three points or non-finite input; coincident points give a fit with all eigenvalues zero.
pub fn pca_fit(pts: impl Iterator<Item = DVec3> + Clone) -> Option<PcaFit> {
    let mut n = 0usize;
    let mut sum = DVec3::ZERO;
    for p in pts.clone() {
        sum += p;
        n += 1;
    }
    if n < 3 {
        return None;
    }
    let mean = sum / n as f64;
    // Centre before accumulating: the covariance of offsets from the mean is well conditioned.
    let mut cov = SymMat3::ZERO;
    for p in pts {
        cov.add_outer(p - mean, 1.0);
    }
    if !cov.0.iter().all(|x| x.is_finite()) {
        return None;
    }
    let e = cov.eigen();
    if e.values.iter().any(|v| v.is_nan()) {
        return None;
    }
    Some(PcaFit {
        count: n,
        values: e.values,
        vectors: e.vectors,
        centroid: mean,
    })
}

/// Fits a plane to `pts` (already relative to some nearby origin): the normal is the eigenvector of
/// the smallest eigenvalue of `Σ (q − q̄)(q − q̄)ᵀ`. `None` for fewer than three points, coincident
/// or collinear points (middle eigenvalue ≤ 1e-12·largest), or non-finite input.
pub fn pca_normal(pts: impl Iterator<Item = DVec3> + Clone) -> Option<PlaneFit> {
    let f = pca_fit(pts)?;
    f.has_plane().then_some(PlaneFit {
        normal: f.vectors[0],
        values: f.values,
        centroid: f.centroid,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn unit(v: (f64, f64, f64)) -> Option<DVec3> {
        let v = DVec3::new(v.0, v.1, v.2);
        (v.length() > 1e-3).then(|| v.normalize())
    }

    proptest! {
        /// A plane's quadric is zero on the plane and the squared distance elsewhere.
        #[test]
        fn plane_quadric_is_zero_on_the_plane(
            n in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            p in (-100.0f64..100.0, -100.0f64..100.0, -100.0f64..100.0),
            s in -50.0f64..50.0, t in -50.0f64..50.0, h in -5.0f64..5.0,
        ) {
            let Some(n) = unit(n) else { return Ok(()) };
            let p = DVec3::new(p.0, p.1, p.2);
            let q = Quadric::plane(n, p);
            let u = any_orthogonal(n);
            let v = n.cross(u);
            let on = p + u * s + v * t;
            let scale = 1.0 + p.length_squared() + on.length_squared();
            prop_assert!(q.eval(on).abs() < 1e-12 * scale);
            prop_assert!((q.eval(on + n * h) - h * h).abs() < 1e-11 * scale);
        }

        /// Quadrics are linear: the sum evaluates to the sum of evaluations.
        #[test]
        fn quadric_sum_is_linear(
            n1 in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            n2 in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            p1 in (-10.0f64..10.0, -10.0f64..10.0, -10.0f64..10.0),
            p2 in (-10.0f64..10.0, -10.0f64..10.0, -10.0f64..10.0),
            w in (-10.0f64..10.0, -10.0f64..10.0, -10.0f64..10.0),
        ) {
            let (Some(n1), Some(n2)) = (unit(n1), unit(n2)) else { return Ok(()) };
            let q1 = Quadric::plane(n1, DVec3::new(p1.0, p1.1, p1.2));
            let q2 = Quadric::plane(n2, DVec3::new(p2.0, p2.1, p2.2));
            let w = DVec3::new(w.0, w.1, w.2);
            prop_assert!(((q1 + q2).eval(w) - q1.eval(w) - q2.eval(w)).abs() < 1e-9);
            let o = DVec3::new(p1.2, p2.0, 3.0);
            prop_assert!(((q1 + q2).recentred(o).eval(w) - (q1 + q2).eval(w + o)).abs() < 1e-8);
        }

        /// The PCA normal of a noisy, rotated plane is within a small angle of the true normal.
        #[test]
        fn pca_normal_of_noisy_plane(
            n in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            seed in 0u64..1000,
        ) {
            let Some(n) = unit(n) else { return Ok(()) };
            let u = any_orthogonal(n);
            let v = n.cross(u);
            let mut x = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
            let mut rnd = move || {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (x >> 11) as f64 / (1u64 << 53) as f64 - 0.5
            };
            let pts: Vec<DVec3> = (0..64)
                .map(|_| u * rnd() + v * rnd() + n * (0.01 * rnd()))
                .collect();
            let fit = pca_normal(pts.iter().copied()).unwrap();
            prop_assert!(fit.normal.dot(n).abs() > (5f64).to_radians().cos());
        }
    }

    fn vec3(t: (f64, f64, f64)) -> DVec3 {
        DVec3::new(t.0, t.1, t.2)
    }

    proptest! {
        /// The regularised step by one linear solve is the eigendecomposition's
        /// `Σ vᵢ (vᵢ·b) / (λᵢ + λ)`, on quadrics of a few planes (rank 1 to 3, any scale).
        #[test]
        fn the_regularised_solve_matches_the_eigen_step(
            planes in proptest::collection::vec(
                ((-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0), (-5.0f64..5.0, -5.0f64..5.0, -5.0f64..5.0), 0.0f64..3.0),
                1..6,
            ),
            mu in 0.01f64..2.0,
        ) {
            let mut q = Quadric::ZERO;
            for (n, p, w) in planes {
                let Some(n) = unit(n) else { continue };
                q.add_plane(n, vec3(p), w);
            }
            let lambda = (mu * q.a.trace() / 3.0).max(f64::MIN_POSITIVE);
            let e = q.a.eigen();
            let mut want = DVec3::ZERO;
            for i in 0..3 {
                want -= e.vectors[i] * (e.vectors[i].dot(q.b) / (e.values[i] + lambda));
            }
            let got = Solve::Regularised { lambda }.offset(&q);
            if q.a.trace() > 0.0 {
                let got = got.unwrap();
                prop_assert!((got - want).length() <= 1e-9 * (1.0 + want.length()), "{got} {want}");
            } else {
                prop_assert_eq!(got, None);
            }
        }
    }

    proptest! {
        /// Points sampled on two planes: the robust minimiser lands exactly on their common edge,
        /// at the edge point closest to the vertex. On three planes the plain minimiser is the
        /// corner.
        #[test]
        fn samples_on_two_or_three_planes_move_onto_edge_or_corner(
            normals in proptest::collection::vec((-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0), 3),
            corner in (-50.0f64..50.0, -50.0f64..50.0, -50.0f64..50.0),
            v in (-5.0f64..5.0, -5.0f64..5.0, -5.0f64..5.0),
            samples in proptest::collection::vec((0usize..3, -3.0f64..3.0, -3.0f64..3.0), 6..40),
        ) {
            let ns: Vec<DVec3> = normals.into_iter().filter_map(unit).collect();
            prop_assume!(ns.len() == 3);
            let det = ns[0].dot(ns[1].cross(ns[2])).abs();
            prop_assume!(det > 0.3);
            let corner = vec3(corner);
            let v = corner + vec3(v);
            for planes in [2usize, 3] {
                let mut q = Quadric::ZERO;
                let mut used = [false; 3];
                for &(i, s, t) in &samples {
                    let i = i % planes;
                    used[i] = true;
                    let u = any_orthogonal(ns[i]);
                    let w = ns[i].cross(u);
                    let p = corner + u * s + w * t;
                    q.add_plane(ns[i], p - v, 1.0);
                }
                prop_assume!(used[..planes].iter().all(|&b| b));
                let solve = if planes == 2 { Solve::Robust { eps: 1e-3 } } else { Solve::Plain };
                let w = v + solve.offset(&q).unwrap();
                let scale = 1.0 + corner.length();
                for n in &ns[..planes] {
                    prop_assert!((n.dot(w - corner)).abs() < 1e-9 * scale, "off plane: {}", n.dot(w - corner));
                }
                if planes == 3 {
                    prop_assert!((w - corner).length() < 1e-9 * scale);
                } else {
                    // The closest edge point: the step is orthogonal to the edge direction.
                    let dir = ns[0].cross(ns[1]).normalize();
                    prop_assert!((w - v).dot(dir).abs() < 1e-9 * scale);
                }
            }
        }
    }

    #[test]
    fn degenerate_neighbourhoods_have_no_plane() {
        let p = DVec3::new(1.0, 2.0, 3.0);
        assert!(pca_normal([p; 5].into_iter()).is_none(), "coincident");
        let line = (0..5).map(|i| p + DVec3::new(1.0, 1.0, 0.0) * i as f64);
        assert!(pca_normal(line).is_none(), "collinear");
        assert!(pca_normal([p, p * 2.0].into_iter()).is_none(), "too few");
        let nan = [p, DVec3::new(f64::NAN, 0.0, 0.0), DVec3::Z, DVec3::X];
        assert!(pca_normal(nan.into_iter()).is_none(), "non-finite");
    }

    #[test]
    fn solves_on_two_and_three_planes() {
        // Vertex at the origin, planes x = 1, y = 2, z = 3: the corner (1, 2, 3).
        let mut q = Quadric::ZERO;
        q.add_plane(DVec3::X, DVec3::new(1.0, 5.0, 5.0), 1.0);
        q.add_plane(DVec3::Y, DVec3::new(0.0, 2.0, 0.0), 1.0);
        q.add_plane(DVec3::Z, DVec3::new(0.0, 0.0, 3.0), 1.0);
        let w = Solve::Plain.offset(&q).unwrap();
        assert!((w - DVec3::new(1.0, 2.0, 3.0)).length() < 1e-14);
        // Two planes: plain is singular, robust moves onto the edge by the shortest step.
        let mut q = Quadric::ZERO;
        q.add_plane(DVec3::X, DVec3::new(1.0, 0.0, 0.0), 1.0);
        q.add_plane(DVec3::Y, DVec3::new(0.0, 2.0, 0.0), 1.0);
        assert!(Solve::Plain.offset(&q).is_none());
        let w = Solve::Robust { eps: 1e-2 }.offset(&q).unwrap();
        assert!((w - DVec3::new(1.0, 2.0, 0.0)).length() < 1e-14);
        // Regularised: (A + λI) w = −b with A = diag(1, 1, 0), −b = (1, 2, 0).
        let w = Solve::Regularised { lambda: 1.0 }.offset(&q).unwrap();
        assert!((w - DVec3::new(0.5, 1.0, 0.0)).length() < 1e-14);
        assert!(Solve::Robust { eps: 0.0 }.validate().is_err());
        assert!(Solve::Regularised { lambda: -1.0 }.validate().is_err());
        assert!(Solve::Plain.offset(&Quadric::ZERO).is_none());
    }
}
