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
//!   λ1 ≤ ELONGATED·λ2                   → Line    (wire, pole, one scan line or ring)
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
//! **Along beams.** Where the beam of each return is known ([`Beams`]: a sweep in its sensor
//! frame, a station, a trajectory), a list is fitted along the point's beam instead
//! ([`crate::geometry::along_fit`]): LiDAR noise lies along the beam, so a PCA of a noisy scan
//! line sees a flat plane through the beams (residual zero, the noise taken for shape), while the
//! spread across the beam is exact. There a list is
//!
//! ```text
//!   one line across the beam (one scan line, one ring, a wire) → Line
//!   two directions across it                                   → Surface
//!   either, with a residual along the beam > ROUGH × the scan's → Scatter (then Edge as above)
//! ```
//!
//! and its residual, the RMS error along the beam, is the range noise whatever the incidence.
//!
//! Every function here is a pure function of a point's list (and its beam), so tiles reproduce
//! it exactly.

use glam::DVec3;
use rayon::prelude::*;

use super::common::{Within, median};
use crate::geometry::{PcaFit, along_fit, pca_fit};
use crate::neighbours::Neighbourhoods;

/// Largest `λ1/λ2` of an elongated neighbourhood, a line too whatever its cross-section: a thick
/// wire or a pole (a round section), or one scan line whose returns are noisy along their beams
/// (a flat section: the noise lies in the plane of the line and the beams, so the PCA takes it
/// for a plane; projected onto that plane nothing moves). A list that is one line is smoothed
/// along it, never across to a parallel one.
pub const ELONGATED: f64 = 0.1;
/// Largest residual along the beam of a list that is still a surface or a line, in units of the
/// scan's noise ([`Beams::noise`]): a list fitted along its beam with a larger one is scatter
/// (vegetation, a depth edge, a mixed return). The fit's residual estimates the noise with
/// `count − 3` degrees of freedom (13 for 16 points), so a surface exceeds 3× its noise only by
/// its shape (a crease, a small cylinder), not by chance.
pub const ROUGH: f64 = 3.0;
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
    if l1 <= ELONGATED * l2 {
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

/// What the fits know of the beams: each point's beam direction and the scan's noise along them.
#[derive(Debug, Clone, Copy, Default)]
pub struct Beams<'a> {
    /// Unit direction from the sensor to each point (indexed as the positions; zero where the
    /// beam is unknown); `None`: no beams, every list is fitted by PCA.
    pub dirs: Option<&'a [DVec3]>,
    /// The scan's noise along the beams ([`crate::denoise::cloud::Globals::noise`]): a list fitted
    /// along its beam with a residual above [`ROUGH`] times it is scatter.
    pub noise: f64,
}

impl Beams<'_> {
    /// No beams: every list is fitted by PCA.
    pub const NONE: Beams<'static> = Beams {
        dirs: None,
        noise: 0.0,
    };

    /// The beam of point `i`, `None` where it is unknown.
    #[inline]
    pub fn at(&self, i: usize) -> Option<DVec3> {
        self.dirs.map(|d| d[i]).filter(|d| *d != DVec3::ZERO)
    }
}

/// The own fit of every point over its list (coordinates relative to the point), by PCA.
pub fn local_fits(pos: &[DVec3], lists: &Neighbourhoods) -> Vec<LocalFit> {
    local_fits_within(pos, lists, Within::All, Beams::NONE)
}

/// [`local_fits`] of the points `within` selects, along their beams where `beams` has them; the
/// others get the degenerate fit.
pub fn local_fits_within(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    within: Within,
    beams: Beams,
) -> Vec<LocalFit> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            if !within.has(i) {
                return fit_of(None);
            }
            local_fit(pos, lists.get(i), i, beams)
        })
        .collect()
}

/// The own fit of point `i` over its list `list` (see [`local_fits`]), along its beam where
/// `beams` has one (see the module overview).
pub fn local_fit(pos: &[DVec3], list: &[u32], i: usize, beams: Beams) -> LocalFit {
    let v = pos[i];
    if !v.is_finite() {
        return fit_of(None);
    }
    let rel = list.iter().map(|&u| pos[u as usize] - v);
    let pca = fit_of(pca_fit(rel.clone()));
    let Some(d) = beams.at(i).filter(|_| pca.own != Structure::Degenerate) else {
        return pca;
    };
    let Some(f) = along_fit(rel, d) else {
        return pca;
    };
    let rough = f.residual > ROUGH * beams.noise;
    if f.line {
        LocalFit {
            own: if rough {
                Structure::Scatter
            } else {
                Structure::Line
            },
            normal: pca.normal,
            axis: f.direction,
            residual: f.residual,
        }
    } else {
        LocalFit {
            own: if rough {
                Structure::Scatter
            } else {
                Structure::Surface
            },
            normal: f.direction,
            axis: pca.axis,
            residual: f.residual,
        }
    }
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

/// The small-scale residual of point `i`: the noise at the smallest scale, where real detail adds
/// least, from its nearest [`NEAR`] points (the first [`NEAR`] of its list, which is sorted by
/// distance and tie key; a longer list gives the same value as a list of exactly [`NEAR`]):
///
/// - along the beam `beam` when it is known: the residual of [`along_fit`], the range noise;
/// - else by PCA: their RMS distance to their own plane, or to their own line when they are
///   elongated (`λ1 ≤` [`ELONGATED`]` · λ2`): the nearest points of a return often lie on its own
///   scan line, and the plane through one noisy scan line holds its noise (a residual of zero:
///   the scan's noise was read as 0.04 mm on a sweep with 2 cm of range noise, and every step
///   was capped to nothing).
#[inline]
pub fn near_residual(pos: &[DVec3], list: &[u32], i: usize, beam: Option<DVec3>) -> f64 {
    let v = pos[i];
    let near = &list[..list.len().min(NEAR)];
    let rel = near.iter().map(|&u| pos[u as usize] - v);
    if let Some(f) = beam.and_then(|d| along_fit(rel.clone(), d)) {
        return f.residual;
    }
    pca_fit(rel).map_or(0.0, |f| {
        let [l0, l1, l2] = f.values.map(|x| x.max(0.0));
        let n = f.count as f64;
        if l1 <= ELONGATED * l2 {
            ((l0 + l1) / (n - 2.0).max(1.0)).sqrt()
        } else {
            (l0 / (n - 3.0).max(1.0)).sqrt()
        }
    })
}

/// [`near_residual`] of every finite point (0 for the others) from lists of at least [`NEAR`],
/// along the beams `beams` has.
pub fn near_residuals(pos: &[DVec3], lists: &Neighbourhoods, beams: Beams) -> Vec<f64> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            if pos[i].is_finite() {
                near_residual(pos, lists.get(i), i, beams.at(i))
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
