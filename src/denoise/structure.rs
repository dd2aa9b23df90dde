//! What a point's neighbourhood is: surface, edge, line, scatter or too sparse, from the k-NN
//! list's principal axes, and the local noise scale that bounds every step.
//!
//! # Brief overview
//!
//! Real scans are not dense manifold surfaces everywhere: vegetation is volumetric scatter, wires
//! and poles are lines, mobile LiDAR lists run along one scan ring, far-range returns are sparse.
//! The quadric step is only earned where the neighbourhood shows a surface (or a line), so each
//! point gets a [`Structure`] from the eigenvalues `λ0 ≤ λ1 ≤ λ2` of its list's covariance:
//!
//! ```text
//!   λ1 ≤ LINE·λ2, or λ1 ≤ ELONGATED·λ2
//!     with a round section λ0 > ROUND·λ1 → Line    (wire, pole edge, one scan ring)
//!   λ0 ≤ SURFACE·(λ0+λ1+λ2), λ0 ≤ FLAT·λ1 → Surface (plane-fit residual small against the spread
//!                                                  in both tangent directions)
//!   else, most list members Surface     → Edge     (a crease or corner between surfaces)
//!   else                                → Scatter  (vegetation, multipath, noise clouds)
//!   all points coincident or < 3 points → Degenerate
//! ```
//!
//! Before the eigenvalue tests, a point whose own k-NN radius is at least `SPARSE` times the
//! median radius of its list members is Sparse (isolated points, far stragglers).
//!
//! The noise scale `s` of a point is the distance of its neighbourhood to its own fitted plane
//! (`√(λ0/(n−3))`, the plane taking three degrees of freedom, so that lists of 8 and 16 estimate
//! the same σ), or the RMS distance to its own fitted line for lines (`√((λ0+λ1)/n)`);
//! [`noise_scale`] takes the median over the Surface and Line members of a point's list, so an
//! edge point borrows the noise level of the faces around it instead of its own (large) two-plane
//! residual.
//!
//! Every function here is a pure function of a point's list, so tiles reproduce it exactly.

use glam::DVec3;
use rayon::prelude::*;

use super::common::{Within, median};
use crate::geometry::{PcaFit, pca_fit};
use crate::neighbours::Neighbourhoods;

/// Largest `λ1/λ2` of a line.
pub const LINE: f64 = 0.02;
/// Largest `λ1/λ2` of an elongated neighbourhood whose round cross-section
/// (`λ0 > ROUND·λ1`) makes it a line too: a thick wire, a pole, a noisy scan ring.
pub const ELONGATED: f64 = 0.1;
/// Smallest `λ0/λ1` of a round cross-section.
pub const ROUND: f64 = 0.25;
/// Largest surface variation `λ0/(λ0+λ1+λ2)` of a surface.
pub const SURFACE: f64 = 0.06;
/// Largest `λ0/λ1` of a surface: the spread across the normal must be well below the spread in
/// the second tangent direction, or the normal is the noise's, not the surface's.
pub const FLAT: f64 = 0.25;
/// Smallest ratio of a point's own k-NN radius to the median radius of its list members for
/// which it counts as sparse (isolated from the surface its list lies on).
pub const SPARSE: f64 = 3.0;

/// The kind of neighbourhood around a point.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
#[repr(u8)]
pub enum Structure {
    /// A surface: the plane fit leaves a small residual.
    Surface = 0,
    /// A crease or corner: the list mostly holds surface points, the fit does not.
    Edge = 1,
    /// A line: wires, poles, one ring of a mobile scan.
    Line = 2,
    /// Volumetric scatter: vegetation, multipath, noise clouds; never moved.
    Scatter = 3,
    /// Isolated from its list: never moved.
    Sparse = 4,
    /// Coincident points or fewer than three: never moved.
    Degenerate = 5,
}

impl Structure {
    /// Every class, in code order.
    pub const ALL: [Structure; 6] = [
        Structure::Surface,
        Structure::Edge,
        Structure::Line,
        Structure::Scatter,
        Structure::Sparse,
        Structure::Degenerate,
    ];

    /// The lowercase name used in reports and written fields.
    pub fn name(self) -> &'static str {
        match self {
            Structure::Surface => "surface",
            Structure::Edge => "edge",
            Structure::Line => "line",
            Structure::Scatter => "scatter",
            Structure::Sparse => "sparse",
            Structure::Degenerate => "degenerate",
        }
    }

    /// True for the classes that take a plane step (surfaces and edges).
    pub fn takes_planes(self) -> bool {
        matches!(self, Structure::Surface | Structure::Edge)
    }

    /// True for the classes that move at all.
    pub fn moves(self) -> bool {
        matches!(self, Structure::Surface | Structure::Edge | Structure::Line)
    }
}

/// A point's fit: its class before the edge test, its plane normal, line direction and noise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalFit {
    /// Class from the point's own fit ([`Structure::Edge`] is decided later by [`classify`]).
    pub own: Structure,
    /// Unit plane normal (zero without a plane).
    pub normal: DVec3,
    /// Unit line direction (zero without one).
    pub axis: DVec3,
    /// RMS distance of the list to the fitted plane (to the line for lines).
    pub residual: f64,
}

impl LocalFit {
    /// The fit of an isolated point ([`crate::denoise::isolation`]): sparse, no plane, no line,
    /// no residual.
    pub fn isolated() -> LocalFit {
        LocalFit {
            own: Structure::Sparse,
            normal: DVec3::ZERO,
            axis: DVec3::ZERO,
            residual: 0.0,
        }
    }
}

/// Points of the small-scale fit behind [`near_residuals`], the point itself included.
pub const NEAR: usize = 8;

/// The fit of one list from its PCA.
fn fit_of(f: Option<PcaFit>) -> LocalFit {
    let none = LocalFit {
        own: Structure::Degenerate,
        normal: DVec3::ZERO,
        axis: DVec3::ZERO,
        residual: 0.0,
    };
    let Some(f) = f else { return none };
    if !f.has_axis() {
        return none;
    }
    let [l0, l1, l2] = f.values.map(|v| v.max(0.0));
    let n = f.count as f64;
    let normal = if f.has_plane() {
        f.vectors[0]
    } else {
        DVec3::ZERO
    };
    if l1 <= LINE * l2 || (l1 <= ELONGATED * l2 && l0 > ROUND * l1) {
        return LocalFit {
            own: Structure::Line,
            normal,
            axis: f.vectors[2],
            residual: ((l0 + l1) / n).sqrt(),
        };
    }
    let own = if l0 <= SURFACE * (l0 + l1 + l2) && l0 <= FLAT * l1 {
        Structure::Surface
    } else {
        Structure::Scatter
    };
    LocalFit {
        own,
        normal,
        axis: f.vectors[2],
        residual: (l0 / (n - 3.0).max(1.0)).sqrt(),
    }
}

/// The own fit of every point over its list (coordinates relative to the point).
pub fn local_fits(pos: &[DVec3], lists: &Neighbourhoods) -> Vec<LocalFit> {
    local_fits_within(pos, lists, Within::All)
}

/// [`local_fits`] of the points `within` selects; the others get the degenerate fit.
pub fn local_fits_within(pos: &[DVec3], lists: &Neighbourhoods, within: Within) -> Vec<LocalFit> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            if !within.has(i) {
                return fit_of(None);
            }
            local_fit(pos, lists.get(i), i)
        })
        .collect()
}

/// The own fit of point `i` over its list `list` (see [`local_fits`]).
pub fn local_fit(pos: &[DVec3], list: &[u32], i: usize) -> LocalFit {
    let v = pos[i];
    if !v.is_finite() {
        return fit_of(None);
    }
    fit_of(pca_fit(list.iter().map(|&u| pos[u as usize] - v)))
}

/// The plane each point offers the normal filter: its fit's normal where its class takes planes
/// ([`Structure::takes_planes`]), zero (no plane) otherwise.
pub fn planes(fits: &[LocalFit], classes: &[Structure]) -> Vec<DVec3> {
    fits.iter()
        .zip(classes)
        .map(|(f, c)| {
            if c.takes_planes() {
                f.normal
            } else {
                DVec3::ZERO
            }
        })
        .collect()
}

/// Final classes: [`Structure::Sparse`] for points whose own k-NN radius (`radii` squared) is at
/// least [`SPARSE`] times the median of their list members', [`Structure::Edge`] for non-surface
/// points whose list is mostly surface, the own class otherwise.
pub fn classify(fits: &[LocalFit], lists: &Neighbourhoods, radii: &[f64]) -> Vec<Structure> {
    classify_within(fits, lists, radii, Within::All)
}

/// [`classify`] of the points `within` selects; the others are [`Structure::Degenerate`]. Reads
/// the fits of the selected points' list members.
pub fn classify_within(
    fits: &[LocalFit],
    lists: &Neighbourhoods,
    radii: &[f64],
    within: Within,
) -> Vec<Structure> {
    (0..fits.len())
        .into_par_iter()
        .with_min_len(1024)
        .map_init(Vec::new, |buf: &mut Vec<f64>, i| {
            if !within.has(i) {
                return Structure::Degenerate;
            }
            class_in(fits, radii, lists.get(i), i, buf)
        })
        .collect()
}

/// [`class_of`] point `i` with list `list`, from the fits and squared radii of every point;
/// `buf` is scratch.
#[inline]
pub fn class_in(
    fits: &[LocalFit],
    radii: &[f64],
    list: &[u32],
    i: usize,
    buf: &mut Vec<f64>,
) -> Structure {
    let members = list
        .iter()
        .map(|&u| (u, fits[u as usize].own, radii[u as usize]));
    class_of(i, (fits[i].own, radii[i]), members, buf)
}

/// The final class of point `i` (see [`classify`]) from its own class and squared radius, and
/// those of its list's members (`(index, own class, squared radius)`, itself included or not).
pub fn class_of(
    i: usize,
    (own, radius2): (Structure, f64),
    members: impl Iterator<Item = (u32, Structure, f64)> + Clone,
    buf: &mut Vec<f64>,
) -> Structure {
    if own == Structure::Degenerate {
        return Structure::Degenerate;
    }
    let others = members.filter(|&(u, _, _)| u as usize != i);
    buf.clear();
    buf.extend(others.clone().map(|(_, _, r)| r));
    // Squared radii: compare with the square of the ratio.
    if radius2 >= SPARSE * SPARSE * median(buf) && radius2 > 0.0 {
        return Structure::Sparse;
    }
    if own != Structure::Scatter {
        return own;
    }
    let surface = others
        .clone()
        .filter(|&(_, c, _)| c == Structure::Surface)
        .count();
    let count = others.count();
    if count > 0 && 2 * surface > count {
        Structure::Edge
    } else {
        Structure::Scatter
    }
}

/// The noise scale of every point: the median residual of the Surface and Line members of its
/// list (the point itself included); 0 when it has none (such a point does not move).
pub fn noise_scale(fits: &[LocalFit], lists: &Neighbourhoods) -> Vec<f64> {
    noise_scale_within(fits, lists, Within::All)
}

/// [`noise_scale`] of the points `within` selects; the others get 0. Reads the fits of the
/// selected points' list members.
pub fn noise_scale_within(fits: &[LocalFit], lists: &Neighbourhoods, within: Within) -> Vec<f64> {
    (0..fits.len())
        .into_par_iter()
        .with_min_len(1024)
        .map_init(Vec::new, |buf: &mut Vec<f64>, i| {
            if !within.has(i) {
                return 0.0;
            }
            noise_of(fits, lists.get(i), buf)
        })
        .collect()
}

/// The noise scale of one point (see [`noise_scale`]) from its list `list` and the fits of its
/// members; `buf` is scratch.
#[inline]
pub fn noise_of(fits: &[LocalFit], list: &[u32], buf: &mut Vec<f64>) -> f64 {
    buf.clear();
    buf.extend(
        list.iter()
            .map(|&u| &fits[u as usize])
            .filter(|f| matches!(f.own, Structure::Surface | Structure::Line))
            .map(|f| f.residual),
    );
    median(buf)
}

/// The small-scale residual of point `i`: the RMS distance of its nearest [`NEAR`] points (the
/// first [`NEAR`] of its list, which is sorted by distance and tie key) to their own plane, the
/// noise at the smallest scale, where real detail adds least. A longer list gives the same value
/// as a list of exactly [`NEAR`]: its first [`NEAR`] members are that list.
#[inline]
pub fn near_residual(pos: &[DVec3], list: &[u32], i: usize) -> f64 {
    let v = pos[i];
    let near = &list[..list.len().min(NEAR)];
    pca_fit(near.iter().map(|&u| pos[u as usize] - v)).map_or(0.0, |f| {
        (f.values[0].max(0.0) / (f.count as f64 - 3.0).max(1.0)).sqrt()
    })
}

/// [`near_residual`] of every finite point (0 for the others) from lists of at least [`NEAR`].
pub fn near_residuals(pos: &[DVec3], lists: &Neighbourhoods) -> Vec<f64> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            if pos[i].is_finite() {
                near_residual(pos, lists.get(i), i)
            } else {
                0.0
            }
        })
        .collect()
}

/// Points per class, indexed by the class code.
pub fn counts(classes: &[Structure]) -> [u64; 6] {
    let mut c = [0u64; 6];
    for s in classes {
        c[*s as usize] += 1;
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::neighbours::KnnIndex;

    fn classes_of(pts: &[DVec3], k: usize) -> Vec<Structure> {
        let index = KnnIndex::build(pts, DVec3::ZERO).unwrap();
        let (lists, radii) = index.knn_all(k).unwrap();
        let fits = local_fits(pts, &lists);
        classify(&fits, &lists, &radii)
    }

    fn uniform(rng: &mut rand_chacha::ChaCha8Rng) -> f64 {
        use rand::RngExt;
        rng.random::<f64>()
    }

    #[test]
    fn a_plane_a_line_and_a_scatter_cloud_are_told_apart() {
        // A 30 × 30 grid plane, a line of 200 points, a uniform cube of 2000 points, far apart.
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut pts = Vec::new();
        for i in 0..30 {
            for j in 0..30 {
                pts.push(DVec3::new(i as f64, j as f64, 0.01 * uniform(&mut rng)));
            }
        }
        let plane = pts.len();
        for i in 0..200 {
            pts.push(DVec3::new(100.0 + 0.5 * i as f64, 0.0, 0.0));
        }
        let line = pts.len();
        for _ in 0..2000 {
            let (x, y, z) = (uniform(&mut rng), uniform(&mut rng), uniform(&mut rng));
            pts.push(DVec3::new(300.0 + 10.0 * x, 10.0 * y, 10.0 * z));
        }
        let c = classes_of(&pts, 16);
        let surface = c[..plane]
            .iter()
            .filter(|s| **s == Structure::Surface)
            .count();
        assert!(surface as f64 > 0.95 * plane as f64, "{surface} of {plane}");
        assert!(c[plane..line].iter().all(|s| *s == Structure::Line));
        let scatter = c[line..]
            .iter()
            .filter(|s| **s == Structure::Scatter)
            .count();
        assert!(
            scatter as f64 > 0.9 * 2000.0,
            "{scatter} of 2000: {:?}",
            counts(&c[line..])
        );
    }

    #[test]
    fn an_isolated_point_is_sparse_and_coincident_points_degenerate() {
        let mut pts = Vec::new();
        for i in 0..20 {
            for j in 0..20 {
                pts.push(DVec3::new(i as f64, j as f64, 0.0));
            }
        }
        pts.push(DVec3::new(10.0, 10.0, 50.0));
        let c = classes_of(&pts, 16);
        assert_eq!(c[400], Structure::Sparse);
        let same = vec![DVec3::ONE; 20];
        assert!(
            classes_of(&same, 8)
                .iter()
                .all(|s| *s == Structure::Degenerate)
        );
    }
}
