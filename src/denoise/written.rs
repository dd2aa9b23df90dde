//! What `--write-normals` writes for each point: the oriented unit normal its neighbourhood gave
//! in the run, the neighbourhood's surface variation and its structure class.
//!
//! # Brief overview
//!
//! [`of_cycle`] turns one cycle of the point operator (its positions, k-NN lists, normals and,
//! for the guarded operator, its fits and classes) into one [`PointNormal`] per point. The
//! driver ([`super::cloud`]) calls it on the **last** cycle, the one whose positions are closest
//! to the output (the default runs one cycle on clouds, so there it is the input's
//! neighbourhood):
//!
//! ```text
//!  normal     guarded default: the filtered normal where the class takes planes (surface,
//!             edge); elsewhere the list's PCA normal where the list spans a plane (a line's or
//!             a scatter point's: the class says how far to trust it); else 0 0 0 (isolated,
//!             coincident or collinear lists)
//!             --no-guard, --paper, --method bilateral: the operator's own normal (PCA, filtered
//!             when the method filters), else the PCA normal as above, else 0 0 0
//!  sign       towards +z; a normal with z = 0 towards +y, then +x (PDAL's `always_up`, with
//!             ties broken so every normal has one sign)
//!  curvature  λ0 / (λ0 + λ1 + λ2) of the list's covariance (PCL's and PDAL's `curvature`);
//!             0 without a fit (isolated, fewer than three points, all coincident)
//!  structure  the class of the same cycle ([`Structure`] code); the methods without the guard
//!             classify with the same rules, for the output only
//! ```
//!
//! Every value is a pure function of a point's list and its members' fits, computed in `f64`
//! and rounded to `f32` once, here: the tiled path stores these bits in its result files and the
//! in-memory path hands them to the sink directly, so both write the same bytes. A point's
//! written values depend on at most as many hops as its position does for every method but
//! bilateral, whose classes read one hop further ([`super::cloud::reach`] accounts for it).

use glam::DVec3;
use rayon::prelude::*;

use super::structure::{LocalFit, Structure, classify, local_fits};
use crate::geometry::pca_fit;
use crate::neighbours::Neighbourhoods;
use crate::points::PointNormal;

/// `n` with the sign of the first non-zero of its z, y, x components made positive (zero stays
/// zero). A pure function of the vector, so tiles orient exactly as the whole cloud does.
pub fn orient(n: DVec3) -> DVec3 {
    let lead = if n.z != 0.0 {
        n.z
    } else if n.y != 0.0 {
        n.y
    } else {
        n.x
    };
    if lead < 0.0 { -n } else { n }
}

/// Surface variation `λ0 / (λ0 + λ1 + λ2)` of each point's list at `pos` (coordinates relative
/// to the point, as the fits take them); 0 for isolated points and lists without a fit.
pub fn curvatures(pos: &[DVec3], lists: &Neighbourhoods, isolated: &[bool]) -> Vec<f64> {
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            curvature_of(
                pos,
                lists.get(i),
                i,
                isolated.get(i).copied().unwrap_or(false),
            )
        })
        .collect()
}

/// [`curvatures`] of point `i` (list `list`; `isolated`: its list was capped short).
#[inline]
pub fn curvature_of(pos: &[DVec3], list: &[u32], i: usize, isolated: bool) -> f64 {
    let v = pos[i];
    if isolated || !v.is_finite() {
        return 0.0;
    }
    pca_fit(list.iter().map(|&u| pos[u as usize] - v)).map_or(0.0, |f| {
        let [l0, l1, l2] = f.values.map(|x| x.max(0.0));
        let sum = l0 + l1 + l2;
        if sum > 0.0 { l0 / sum } else { 0.0 }
    })
}

/// The written values of one cycle: `normals` is the operator's normal of each point (zero where
/// it has none), `guarded` the fits and classes of the guarded operator (`None`: computed here
/// with the same rules). `radii` are the lists' squared radii, `isolated` the points whose lists
/// were capped (they lend no plane and get none).
pub fn of_cycle(
    pos: &[DVec3],
    lists: &Neighbourhoods,
    radii: &[f64],
    isolated: &[bool],
    normals: &[DVec3],
    guarded: Option<(&[LocalFit], &[Structure])>,
) -> Vec<PointNormal> {
    let own;
    let (fits, classes) = match guarded {
        Some(g) => g,
        None => {
            let mut fits = local_fits(pos, lists);
            for (f, _) in fits.iter_mut().zip(isolated).filter(|(_, i)| **i) {
                *f = LocalFit::isolated();
            }
            let classes = classify(&fits, lists, radii);
            own = (fits, classes);
            (own.0.as_slice(), own.1.as_slice())
        }
    };
    let curvature = curvatures(pos, lists, isolated);
    (0..pos.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| written_of(normals[i], &fits[i], classes[i], curvature[i]))
        .collect()
}

/// What the output writes for one point: its operator `normal` (its fit's where that is zero),
/// oriented ([`orient`]), its `curvature` and its class.
#[inline]
pub fn written_of(normal: DVec3, fit: &LocalFit, class: Structure, curvature: f64) -> PointNormal {
    let n = match normal.normalize_or_zero() {
        DVec3::ZERO => fit.normal.normalize_or_zero(),
        n => n,
    };
    let n = orient(n);
    PointNormal {
        normal: [n.x as f32, n.y as f32, n.z as f32],
        curvature: curvature as f32,
        structure: class as u8,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::neighbours::KnnIndex;

    #[test]
    fn orientation_is_up_then_y_then_x() {
        assert_eq!(
            orient(DVec3::new(0.3, 0.0, -0.5)),
            DVec3::new(-0.3, 0.0, 0.5)
        );
        assert_eq!(
            orient(DVec3::new(0.3, -1.0, 0.0)),
            DVec3::new(-0.3, 1.0, 0.0)
        );
        assert_eq!(orient(DVec3::new(-1.0, 0.0, 0.0)), DVec3::X);
        assert_eq!(orient(DVec3::new(0.0, 0.0, 1.0)), DVec3::Z);
        assert_eq!(orient(DVec3::ZERO), DVec3::ZERO);
        // -0.0 is no sign: the next component decides.
        assert_eq!(
            orient(DVec3::new(0.0, -1.0, -0.0)),
            DVec3::new(-0.0, 1.0, 0.0)
        );
    }

    #[test]
    fn a_tilted_plane_and_a_line_and_a_lone_point() {
        // A plane z = 0.5 x (normal ∝ (-0.5, 0, 1)), a line far away, a pair of coincident points.
        let mut pts = Vec::new();
        for i in 0..20 {
            for j in 0..20 {
                let (x, y) = (i as f64, j as f64);
                pts.push(DVec3::new(x, y, 0.5 * x));
            }
        }
        let plane = pts.len();
        for i in 0..40 {
            pts.push(DVec3::new(1000.0 + i as f64, 0.0, 0.0));
        }
        let index = KnnIndex::build(&pts, DVec3::ZERO).unwrap();
        let (lists, radii) = index.knn_all(8).unwrap();
        let isolated = vec![false; pts.len()];
        let zero = vec![DVec3::ZERO; pts.len()];
        let w = of_cycle(&pts, &lists, &radii, &isolated, &zero, None);
        let want = DVec3::new(-0.5, 0.0, 1.0).normalize();
        for p in &w[..plane] {
            let n = DVec3::new(
                f64::from(p.normal[0]),
                f64::from(p.normal[1]),
                f64::from(p.normal[2]),
            );
            assert!((n - want).length() < 1e-6, "{n}");
            assert!(p.curvature < 1e-6, "{}", p.curvature);
            assert_eq!(p.structure, Structure::Surface as u8);
        }
        for p in &w[plane..] {
            assert_eq!(p.structure, Structure::Line as u8);
            // A perfect line spans no plane: no normal, no variation across it.
            assert_eq!(p.normal, [0.0; 3]);
            assert!(p.curvature.abs() < 1e-9, "{}", p.curvature);
        }
        // An isolated point gets nothing but its class.
        let mut iso = isolated.clone();
        iso[0] = true;
        let w = of_cycle(&pts, &lists, &radii, &iso, &zero, None);
        assert_eq!(w[0].normal, [0.0; 3]);
        assert_eq!(w[0].curvature, 0.0);
        assert_eq!(w[0].structure, Structure::Sparse as u8);
    }
}
