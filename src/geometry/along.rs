//! Fits along a known measuring direction: the regression of the coordinate along a LiDAR beam on
//! the coordinates across it.
//!
//! # Brief overview
//!
//! A LiDAR return is a range measured along a beam: its error lies along the beam, and its
//! position across the beam (the beam's direction) is exact. A fit that treats all three
//! coordinates alike (PCA, [`super::pca_fit`]) cannot tell that noise from shape: the returns of
//! one scan line, noisy along their beams, lie in the plane spanned by the line and the beam, and
//! their PCA plane fits that noise exactly (a zero residual, a normal across the beams). Here the
//! points are written in a frame `(x, y, z)` with `z` along the beam direction `d`, and `z` is
//! regressed on `(x, y)`:
//!
//! ```text
//!   across the beam, the points spread in two directions → plane   z = a + b·x + c·y
//!   across the beam, they lie on one line (μ1 ≤ LINE·μ2)  → line    z = a + b·s   (s along it)
//!                                     μ1 ≤ μ2: eigenvalues of the (x, y) spread
//! ```
//!
//! The residual is the RMS error along the beam (the range noise, whatever the incidence), the
//! plane's normal and the line's direction are those of the fitted model. A scan line is
//! recognised by its points' spread across the beam alone, which the noise does not touch.
//!
//! Sums are centred (two passes) and taken in the order given, so a fit is a pure function of its
//! points.

use glam::DVec3;

use super::eigen::any_orthogonal;

/// Largest ratio of the smaller to the larger spread across the beam (eigenvalues of the 2 × 2
/// covariance of the points' coordinates across it) of points on one line: one scan line, one
/// ring, a wire. Adjacent rings of a spinning sensor are 0.4°–2° apart and a list of 16 spans
/// 5–20 times the azimuth step along its ring, so a list that reaches a second ring has a ratio
/// of 0.02 or more once a few of its points lie there; a single ring has none, up to angular
/// jitter.
pub const LINE: f64 = 0.02;

/// A fit along a beam.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlongFit {
    /// Number of points.
    pub count: usize,
    /// True when the points lie on one line across the beam.
    pub line: bool,
    /// The fitted line's unit direction (a line), or the fitted plane's unit normal, turned to
    /// face the beam's origin (`normal · d < 0`) (a plane).
    pub direction: DVec3,
    /// RMS residual along the beam: the residual sum of squares over `count − 2` (a line: offset
    /// and slope) or `count − 3` (a plane), at least 1.
    pub residual: f64,
}

/// The fit of `pts` (relative to some nearby origin) along the unit beam direction `d`. `None`
/// for fewer than three points, a zero or non-finite `d`, non-finite points, or points that all
/// lie on one beam (no spread across it).
pub fn along_fit(pts: impl Iterator<Item = DVec3> + Clone, d: DVec3) -> Option<AlongFit> {
    if !d.is_finite() || d == DVec3::ZERO {
        return None;
    }
    let e1 = any_orthogonal(d);
    let e2 = d.cross(e1);
    let (mut n, mut sum) = (0usize, DVec3::ZERO);
    for p in pts.clone() {
        sum += p;
        n += 1;
    }
    if n < 3 || !sum.is_finite() {
        return None;
    }
    let mean = sum / n as f64;
    // Covariance of (x, y, z) = (e1, e2, d) coordinates, centred.
    let (mut xx, mut xy, mut yy, mut xz, mut yz, mut zz) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for p in pts {
        let q = p - mean;
        let (x, y, z) = (q.dot(e1), q.dot(e2), q.dot(d));
        xx += x * x;
        xy += x * y;
        yy += y * y;
        xz += x * z;
        yz += y * z;
        zz += z * z;
    }
    // Eigenvalues μ1 ≤ μ2 of [[xx, xy], [xy, yy]].
    let half = 0.5 * (xx + yy);
    let gap = (0.25 * (xx - yy) * (xx - yy) + xy * xy).sqrt();
    let (m1, m2) = (half - gap, half + gap);
    if m2.is_nan() || m2 <= 0.0 || !m2.is_finite() {
        return None;
    }
    let nf = n as f64;
    if m1 <= LINE * m2 {
        // The eigenvector of μ2, from the better-conditioned row.
        let (c, s) = if xy == 0.0 {
            if xx >= yy { (1.0, 0.0) } else { (0.0, 1.0) }
        } else if xx >= yy {
            (m2 - yy, xy)
        } else {
            (xy, m2 - xx)
        };
        let len = (c * c + s * s).sqrt();
        let (c, s) = (c / len, s / len);
        let e = e1 * c + e2 * s;
        // Along the line: s = (x, y)·(c, s); its variance is μ2.
        let sz = c * xz + s * yz;
        let slope = sz / m2;
        let rss = (zz - slope * sz).max(0.0);
        return Some(AlongFit {
            count: n,
            line: true,
            direction: (e + d * slope).normalize(),
            residual: (rss / (nf - 2.0).max(1.0)).sqrt(),
        });
    }
    let det = xx * yy - xy * xy;
    let b = (xz * yy - yz * xy) / det;
    let c = (yz * xx - xz * xy) / det;
    let rss = (zz - b * xz - c * yz).max(0.0);
    // z − b·x − c·y = const: the gradient (−b, −c, 1) is the normal; turned towards the origin.
    let normal = (e1 * b + e2 * c - d).normalize();
    Some(AlongFit {
        count: n,
        line: false,
        direction: normal,
        residual: (rss / (nf - 3.0).max(1.0)).sqrt(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic value in [−1, 1) for index `i` and salt `s`.
    fn jitter(i: usize, s: u64) -> f64 {
        let h = (i as u64 ^ s).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        ((h >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    #[test]
    fn a_plane_seen_along_noisy_beams_is_fitted_with_the_noise_along_them() {
        // A plane z = 0.2 x − 0.1 y + 5 hit by beams from the origin; range noise along each beam.
        let n = DVec3::new(-0.2, 0.1, 1.0).normalize();
        let mut pts = Vec::new();
        let mut sq = 0.0;
        for i in 0..40 {
            let (x, y) = ((i % 8) as f64 * 0.1, (i / 8) as f64 * 0.1);
            let on = DVec3::new(x, y, 0.2 * x - 0.1 * y + 5.0);
            let e = 0.01 * jitter(i, 7);
            sq += e * e;
            pts.push(on + on.normalize() * e);
        }
        let v = pts[17];
        let d = v.normalize();
        let f = along_fit(pts.iter().map(|p| *p - v), d).unwrap();
        assert!(!f.line);
        assert!(f.direction.dot(d) < 0.0);
        assert!(f.direction.dot(n).abs() > 0.999, "{:?}", f.direction);
        // The residual along the beam is of the order of the range noise (beams differ slightly).
        let rms = (sq / 40.0).sqrt();
        assert!(
            f.residual > 0.5 * rms && f.residual < 1.5 * rms,
            "{} {}",
            f.residual,
            rms
        );
    }

    #[test]
    fn one_scan_line_is_a_line_whatever_its_noise_along_the_beams() {
        // One ring of a sensor at the origin, on the ground 1.7 m below, noise 2 cm along the beams.
        let el = (-1.7f64 / 8.0).atan();
        let mut pts = Vec::new();
        for i in 0..16 {
            let az = 0.003 * i as f64;
            let d = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            let range = -1.7 / d.z + 0.02 * jitter(i, 3);
            pts.push(d * range);
        }
        let v = pts[8];
        let f = along_fit(pts.iter().map(|p| *p - v), v.normalize()).unwrap();
        assert!(f.line);
        // The line runs along the ring (across the beam), and the residual sees the noise.
        assert!(f.direction.dot(v.normalize()).abs() < 0.2);
        assert!(f.residual > 0.005, "{}", f.residual);
    }

    #[test]
    fn points_on_one_beam_or_too_few_have_no_fit() {
        let d = DVec3::X;
        let on_beam = [DVec3::X, DVec3::X * 2.0, DVec3::X * 3.0];
        assert_eq!(along_fit(on_beam.into_iter(), d), None);
        assert_eq!(along_fit([DVec3::Y, DVec3::Z].into_iter(), d), None);
        assert_eq!(
            along_fit([DVec3::Y, DVec3::Z, DVec3::ONE].into_iter(), DVec3::ZERO),
            None
        );
    }
}
