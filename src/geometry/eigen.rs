//! Closed-form eigen decomposition of symmetric 3×3 matrices in f64.
//!
//! Hand-rolled on purpose: it runs once per point (PCA) and once per vertex (robust solve), and a
//! closed form is about 3× faster than nalgebra's iterative `SymmetricEigen` on this machine
//! (see `benches/kernels.rs`, group `eigen`).
//!
//! The eigenvalues come from the trigonometric solution of the characteristic cubic (after scaling
//! by the largest entry and shifting by the mean eigenvalue, which keeps the cubic well
//! conditioned), with `acos` and `cos` from the `libm` crate: plain Rust arithmetic, the same bits
//! on every platform, where the C library's last bit differs between glibc, musl and macOS.
//!
//! The eigenvectors follow the robust construction of D. Eberly ("A Robust Eigensolver for 3×3
//! Symmetric Matrices"): the vector of the best separated eigenvalue is the longest cross product
//! of two rows of A − λI; the second is the null vector of A − λI restricted to the plane
//! orthogonal to the first; the third is their cross product. The result is an orthonormal
//! right-handed basis even for repeated eigenvalues.

use glam::DVec3;

/// A symmetric 3×3 matrix stored as its six unique entries.
///
/// ```text
///  | xx xy xz |
///  | xy yy yz |     stored as [xx, xy, xz, yy, yz, zz]
///  | xz yz zz |
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SymMat3(pub [f64; 6]);

impl SymMat3 {
    /// The zero matrix.
    pub const ZERO: SymMat3 = SymMat3([0.0; 6]);

    /// The identity scaled by `s`.
    pub fn scaled_identity(s: f64) -> SymMat3 {
        SymMat3([s, 0.0, 0.0, s, 0.0, s])
    }

    /// The outer product `v vᵀ`.
    #[inline]
    pub fn outer(v: DVec3) -> SymMat3 {
        SymMat3([
            v.x * v.x,
            v.x * v.y,
            v.x * v.z,
            v.y * v.y,
            v.y * v.z,
            v.z * v.z,
        ])
    }

    /// Adds `w v vᵀ` in place.
    #[inline]
    pub fn add_outer(&mut self, v: DVec3, w: f64) {
        let m = &mut self.0;
        m[0] += w * v.x * v.x;
        m[1] += w * v.x * v.y;
        m[2] += w * v.x * v.z;
        m[3] += w * v.y * v.y;
        m[4] += w * v.y * v.z;
        m[5] += w * v.z * v.z;
    }

    /// Entry-wise sum.
    #[inline]
    pub fn add(&mut self, o: &SymMat3) {
        for (a, b) in self.0.iter_mut().zip(o.0) {
            *a += b;
        }
    }

    /// Matrix–vector product.
    #[inline]
    pub fn mul_vec(&self, v: DVec3) -> DVec3 {
        let m = &self.0;
        DVec3::new(
            m[0] * v.x + m[1] * v.y + m[2] * v.z,
            m[1] * v.x + m[3] * v.y + m[4] * v.z,
            m[2] * v.x + m[4] * v.y + m[5] * v.z,
        )
    }

    /// Trace.
    pub fn trace(&self) -> f64 {
        self.0[0] + self.0[3] + self.0[5]
    }

    /// `(self + λI)⁻¹ b` by the adjugate, or `None` when the shifted matrix's determinant is not
    /// positive and finite. For a positive semidefinite `self` and `λ ≥ tr/6` (the damped solve)
    /// the shifted matrix's condition number is at most 7, so this is as accurate as the
    /// eigendecomposition and an order of magnitude cheaper.
    pub fn solve_shifted(&self, lambda: f64, b: DVec3) -> Option<DVec3> {
        let [a00, a01, a02, a11, a12, a22] = self.0;
        let (m00, m11, m22) = (a00 + lambda, a11 + lambda, a22 + lambda);
        let c00 = m11 * m22 - a12 * a12;
        let c01 = a02 * a12 - a01 * m22;
        let c02 = a01 * a12 - a02 * m11;
        let c11 = m00 * m22 - a02 * a02;
        let c12 = a01 * a02 - m00 * a12;
        let c22 = m00 * m11 - a01 * a01;
        let det = m00 * c00 + a01 * c01 + a02 * c02;
        if !(det > 0.0 && det.is_finite()) {
            return None;
        }
        let x = DVec3::new(
            c00 * b.x + c01 * b.y + c02 * b.z,
            c01 * b.x + c11 * b.y + c12 * b.z,
            c02 * b.x + c12 * b.y + c22 * b.z,
        ) / det;
        x.is_finite().then_some(x)
    }

    /// Row `i` as a vector.
    fn row(&self, i: usize) -> DVec3 {
        let m = &self.0;
        match i {
            0 => DVec3::new(m[0], m[1], m[2]),
            1 => DVec3::new(m[1], m[3], m[4]),
            _ => DVec3::new(m[2], m[4], m[5]),
        }
    }

    /// Eigenvalues in ascending order with their unit eigenvectors.
    pub fn eigen(&self) -> Eigen {
        eigen(self)
    }
}

/// Eigenvalues (ascending) and matching orthonormal eigenvectors of a [`SymMat3`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Eigen {
    /// λ0 ≤ λ1 ≤ λ2.
    pub values: [f64; 3],
    /// Unit eigenvectors, `vectors[i]` for `values[i]`.
    pub vectors: [DVec3; 3],
}

fn eigen(a: &SymMat3) -> Eigen {
    let scale = a.0.iter().fold(0.0f64, |m, &x| m.max(x.abs()));
    if scale == 0.0 || !scale.is_finite() {
        return Eigen {
            values: [0.0; 3],
            vectors: [DVec3::X, DVec3::Y, DVec3::Z],
        };
    }
    let m = SymMat3(a.0.map(|x| x / scale));
    let [a00, a01, a02, a11, a12, a22] = m.0;
    let q = (a00 + a11 + a22) / 3.0;
    let b00 = a00 - q;
    let b11 = a11 - q;
    let b22 = a22 - q;
    let off = a01 * a01 + a02 * a02 + a12 * a12;
    let p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off;
    let p = (p2 / 6.0).sqrt();
    if p == 0.0 {
        // A multiple of the identity.
        return Eigen {
            values: [q * scale; 3],
            vectors: [DVec3::X, DVec3::Y, DVec3::Z],
        };
    }
    let c00 = b11 * b22 - a12 * a12;
    let c01 = a01 * b22 - a12 * a02;
    let c02 = a01 * a12 - b11 * a02;
    let det = (b00 * c00 - a01 * c01 + a02 * c02) / (p * p * p);
    let half_det = (0.5 * det).clamp(-1.0, 1.0);
    // `libm` (the pure-Rust port of musl's) rather than the platform's C library, whose last bit
    // differs between glibc, musl and macOS: the same bits on every machine a tile runs on.
    let angle = libm::acos(half_det) / 3.0;
    const TWO_THIRDS_PI: f64 = 2.094_395_102_393_195_5;
    let beta2 = libm::cos(angle) * 2.0;
    let beta0 = libm::cos(angle + TWO_THIRDS_PI) * 2.0;
    let beta1 = -(beta0 + beta2);
    let mut vals = [q + p * beta0, q + p * beta1, q + p * beta2];

    // Work with the eigenvalue farthest from the other two first.
    let mut vecs = [DVec3::ZERO; 3];
    if half_det >= 0.0 {
        vecs[2] = vector_of_separated(&m, vals[2]);
        vecs[1] = vector_in_complement(&m, vecs[2], vals[1]);
        vecs[0] = vecs[1].cross(vecs[2]);
    } else {
        vecs[0] = vector_of_separated(&m, vals[0]);
        vecs[1] = vector_in_complement(&m, vecs[0], vals[1]);
        vecs[2] = vecs[0].cross(vecs[1]);
    }
    // The trigonometric eigenvalues lose half their digits where two of them (nearly) coincide
    // (acos is not Lipschitz at ±1). The eigenvectors are still an accurate orthonormal basis of
    // the eigenspaces, so refine each eigenvalue as its Rayleigh quotient, which is accurate to
    // second order, and restore the ascending order.
    for i in 0..3 {
        vals[i] = vecs[i].dot(m.mul_vec(vecs[i]));
    }
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| vals[i].total_cmp(&vals[j]));
    let mut vectors = order.map(|i| vecs[i]);
    if vectors[0].cross(vectors[1]).dot(vectors[2]) < 0.0 {
        vectors[0] = -vectors[0];
    }
    Eigen {
        values: order.map(|i| vals[i] * scale),
        vectors,
    }
}

/// Unit null vector of `m − λI` for a simple, well separated eigenvalue `λ`: the longest cross
/// product of two of its rows.
fn vector_of_separated(m: &SymMat3, lambda: f64) -> DVec3 {
    let r0 = m.row(0) - DVec3::X * lambda;
    let r1 = m.row(1) - DVec3::Y * lambda;
    let r2 = m.row(2) - DVec3::Z * lambda;
    let c = [r0.cross(r1), r0.cross(r2), r1.cross(r2)];
    let d = c.map(|v| v.length_squared());
    let i = if d[0] >= d[1] && d[0] >= d[2] {
        0
    } else if d[1] >= d[2] {
        1
    } else {
        2
    };
    if d[i] > 0.0 {
        c[i] / d[i].sqrt()
    } else {
        // All rows parallel or zero: any vector orthogonal to the non-zero row will do.
        any_orthogonal(if r0 != DVec3::ZERO {
            r0
        } else if r1 != DVec3::ZERO {
            r1
        } else {
            r2
        })
    }
}

/// Unit eigenvector for `lambda` orthogonal to the unit eigenvector `e`.
fn vector_in_complement(m: &SymMat3, e: DVec3, lambda: f64) -> DVec3 {
    let u = any_orthogonal(e);
    let v = e.cross(u);
    // The 2×2 matrix of m − λI restricted to span{u, v}.
    let mu = m.mul_vec(u) - u * lambda;
    let mv = m.mul_vec(v) - v * lambda;
    let m00 = u.dot(mu);
    let m01 = u.dot(mv);
    let m11 = v.dot(mv);
    let (a00, a01, a11) = (m00.abs(), m01.abs(), m11.abs());
    if a00 >= a11 {
        let max = a00.max(a01);
        if max > 0.0 {
            if a00 >= a01 {
                let t = -m01 / m00;
                let s = 1.0 / (1.0 + t * t).sqrt();
                return (u * t + v) * s;
            }
            let t = -m00 / m01;
            let s = 1.0 / (1.0 + t * t).sqrt();
            return u * s + v * (t * s);
        }
        u
    } else {
        let max = a11.max(a01);
        if max > 0.0 {
            if a11 >= a01 {
                let t = -m01 / m11;
                let s = 1.0 / (1.0 + t * t).sqrt();
                return u * s + v * (t * s);
            }
            let t = -m11 / m01;
            let s = 1.0 / (1.0 + t * t).sqrt();
            return u * (t * s) + v * s;
        }
        u
    }
}

/// A unit vector orthogonal to the non-zero vector `e`.
pub fn any_orthogonal(e: DVec3) -> DVec3 {
    let o = if e.x.abs() > e.y.abs() {
        DVec3::new(-e.z, 0.0, e.x)
    } else {
        DVec3::new(0.0, e.z, -e.y)
    };
    let l = o.length();
    if l > 0.0 { o / l } else { DVec3::X }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn reconstruct(e: &Eigen) -> SymMat3 {
        let mut m = SymMat3::ZERO;
        for i in 0..3 {
            m.add_outer(e.vectors[i], e.values[i]);
        }
        m
    }

    fn check(a: SymMat3) {
        let e = a.eigen();
        let scale = a.0.iter().fold(0.0f64, |m, &x| m.max(x.abs())).max(1e-300);
        assert!(e.values[0] <= e.values[1] && e.values[1] <= e.values[2]);
        for i in 0..3 {
            assert!((e.vectors[i].length() - 1.0).abs() < 1e-12, "{a:?} {e:?}");
            let r = a.mul_vec(e.vectors[i]) - e.vectors[i] * e.values[i];
            assert!(r.length() < 1e-11 * scale, "residual {r:?} for {a:?}");
            for j in 0..i {
                assert!(e.vectors[i].dot(e.vectors[j]).abs() < 1e-11);
            }
        }
        let b = reconstruct(&e);
        for k in 0..6 {
            assert!((a.0[k] - b.0[k]).abs() < 1e-11 * scale);
        }
    }

    #[test]
    fn diagonal_repeated_and_zero() {
        check(SymMat3([1.0, 0.0, 0.0, 2.0, 0.0, 3.0]));
        check(SymMat3([2.0, 0.0, 0.0, 2.0, 0.0, 2.0]));
        check(SymMat3([1.0, 0.0, 0.0, 1.0, 0.0, 0.0]));
        check(SymMat3::outer(DVec3::new(1.0, 2.0, 3.0).normalize()));
        let z = SymMat3::ZERO.eigen();
        assert_eq!(z.values, [0.0; 3]);
    }

    /// The decomposition's bits are pinned: 4 000 seeded matrices (half of them plane-like
    /// covariances, as the PCA fits see) hash to one value. The platform's `acos` and `cos`
    /// differ from `libm`'s in the last bit for 7.6 % and 3 % of arguments on glibc (1 M random
    /// arguments, 2026-12-07), which changes this hash: it fails if the eigensolver goes back
    /// to the C library, on any platform, and on a platform whose outputs differ from this one's.
    #[test]
    fn eigen_bits_are_the_same_on_every_platform() {
        use rand::{RngExt, SeedableRng};
        use sha2::{Digest, Sha256};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut h = Sha256::new();
        for k in 0..4000 {
            let m = if k % 2 == 0 {
                SymMat3(std::array::from_fn(|_| rng.random_range(-1e3..1e3)))
            } else {
                // Sixteen points near a tilted plane: two large eigenvalues and a small one.
                let n = DVec3::new(rng.random(), rng.random(), 1.0).normalize();
                let (t, b) = (any_orthogonal(n), n.cross(any_orthogonal(n)));
                let mut a = SymMat3::ZERO;
                for _ in 0..16 {
                    let p = t * rng.random_range(-1.0..1.0)
                        + b * rng.random_range(-1.0..1.0)
                        + n * rng.random_range(-0.01..0.01);
                    a.add_outer(p, 1.0);
                }
                a
            };
            let e = m.eigen();
            for v in e
                .values
                .iter()
                .chain(e.vectors.iter().flat_map(|v| v.as_ref()))
            {
                h.update(v.to_bits().to_le_bytes());
            }
        }
        let hex: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(
            hex,
            "d72aa3790b69d0a5b1642411d6a2bf68db2a63816cb5d25da5dfc847599540e0"
        );
    }

    proptest! {
        #[test]
        fn random_symmetric(m in proptest::array::uniform6(-1e3f64..1e3)) {
            check(SymMat3(m));
        }

        #[test]
        fn sums_of_plane_outer_products(ns in proptest::collection::vec(
            (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0), 1..20)) {
            let mut a = SymMat3::ZERO;
            for (x, y, z) in ns {
                let n = DVec3::new(x, y, z);
                if n.length() > 1e-3 {
                    a.add_outer(n.normalize(), 1.0);
                }
            }
            check(a);
        }
    }
}
