//! Synthetic noise with the models of `docs/EVALUATION.md`.
//!
//! σ = level · L, where L is the scale length of the *clean* input ([`super::scale_length`]: the
//! mean unique-edge length of a mesh, or the mean nearest-neighbour distance of a cloud).
//!
//! * [`NoiseModel::Iso`]: every coordinate gets an independent N(0, σ²) offset (3D RMS √3·σ).
//! * [`NoiseModel::Normal`]: one N(0, σ²) offset along the clean normal: the area-weighted vertex
//!   normal for a mesh, the PCA normal of the 16 nearest points for a cloud.
//!
//! Mesh vertices that no face references, and non-finite points of a cloud, keep their position
//! and draw no random numbers. The noised points draw from one `ChaCha8Rng` seeded with the
//! seed, in index order (three normal variates each for `iso`, one for `normal`), so a seed
//! always gives the same output.

use std::fmt;
use std::str::FromStr;

use glam::DVec3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::{EvalError, check_faces, referenced, scale_length};
use crate::denoise::normals::{pca_normals, vertex_normals};
use crate::denoise::{NormalWeighting, origin_of};
use crate::neighbours::KnnIndex;
use crate::points::Faces;

/// Neighbourhood size of the PCA normals of the `normal` model on point clouds.
pub const CLOUD_NORMAL_K: usize = 16;

/// How noise is drawn.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum NoiseModel {
    /// Every coordinate gets N(0, σ²): the model of the paper's Table I.
    #[default]
    Iso,
    /// One N(0, σ²) offset along the clean normal.
    Normal,
}

impl NoiseModel {
    /// The CLI name.
    pub fn name(self) -> &'static str {
        match self {
            NoiseModel::Iso => "iso",
            NoiseModel::Normal => "normal",
        }
    }
}

impl fmt::Display for NoiseModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for NoiseModel {
    type Err = EvalError;
    fn from_str(s: &str) -> Result<NoiseModel, EvalError> {
        match s.to_ascii_lowercase().as_str() {
            "iso" => Ok(NoiseModel::Iso),
            "normal" => Ok(NoiseModel::Normal),
            _ => Err(EvalError::Param {
                name: "model",
                detail: format!("unknown noise model `{s}` (iso, normal)"),
            }),
        }
    }
}

/// What noise to add.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NoiseSpec {
    /// `--model`.
    pub model: NoiseModel,
    /// `--level`: σ as a fraction of L (0.4 means σ = 0.4 L).
    pub level: f64,
    /// `--seed`.
    pub seed: u64,
}

impl Default for NoiseSpec {
    fn default() -> Self {
        NoiseSpec {
            model: NoiseModel::Iso,
            level: 0.4,
            seed: 0,
        }
    }
}

impl NoiseSpec {
    /// Checks the level.
    ///
    /// # Errors
    /// [`EvalError::Param`] for a negative or non-finite level.
    pub fn validate(&self) -> Result<(), EvalError> {
        if !(self.level >= 0.0 && self.level.is_finite()) {
            return Err(EvalError::Param {
                name: "level",
                detail: format!("must be finite and ≥ 0, got {}", self.level),
            });
        }
        Ok(())
    }
}

/// Noisy positions and the scale they were drawn at.
#[derive(Debug, Clone, PartialEq)]
pub struct Noisy {
    /// One position per input position.
    pub positions: Vec<DVec3>,
    /// The clean scale length L.
    pub l: f64,
    /// σ = level · L.
    pub sigma: f64,
    /// Number of points that received noise.
    pub displaced: usize,
}

/// Adds noise to a clean mesh (`faces` given and non-empty) or point cloud.
///
/// # Errors
/// Bad level, bad face indices, a referenced mesh vertex that is not finite, a cloud with fewer
/// than two finite points (or three for the `normal` model), L = 0.
pub fn add_noise(
    positions: &[DVec3],
    faces: Option<&Faces>,
    spec: &NoiseSpec,
) -> Result<Noisy, EvalError> {
    spec.validate()?;
    let faces = faces.filter(|f| !f.is_empty());
    if let Some(f) = faces {
        check_faces(positions.len(), f)?;
    }
    let l = scale_length(positions, faces)?;
    add_noise_with_length(positions, faces, spec, l)
}

/// [`add_noise`] with a known scale length `l` (σ = level · l), for callers that noise the same
/// clean input many times.
///
/// # Errors
/// As [`add_noise`], and [`EvalError::Param`] for `l` not finite and > 0.
pub fn add_noise_with_length(
    positions: &[DVec3],
    faces: Option<&Faces>,
    spec: &NoiseSpec,
    l: f64,
) -> Result<Noisy, EvalError> {
    spec.validate()?;
    if !(l > 0.0 && l.is_finite()) {
        return Err(EvalError::Param {
            name: "L",
            detail: format!("the scale length must be finite and > 0, got {l}"),
        });
    }
    let faces = faces.filter(|f| !f.is_empty());
    let active: Vec<bool> = match faces {
        Some(f) => {
            check_faces(positions.len(), f)?;
            let r = referenced(positions.len(), f);
            if let Some(index) = (0..positions.len()).find(|&i| r[i] && !positions[i].is_finite()) {
                return Err(EvalError::NonFinite {
                    what: "clean mesh",
                    index,
                });
            }
            r
        }
        None => positions.iter().map(|p| p.is_finite()).collect(),
    };
    let normals = match spec.model {
        NoiseModel::Iso => Vec::new(),
        NoiseModel::Normal => match faces {
            Some(f) => vertex_normals(positions, f, NormalWeighting::Area).normals,
            None => cloud_normals(positions)?,
        },
    };
    let sigma = spec.level * l;
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    let mut gauss = move || rng.sample::<f64, _>(StandardNormal);
    let mut out = positions.to_vec();
    let mut displaced = 0;
    for (i, p) in out.iter_mut().enumerate() {
        if !active[i] {
            continue;
        }
        displaced += 1;
        *p += match spec.model {
            NoiseModel::Iso => DVec3::new(gauss(), gauss(), gauss()) * sigma,
            NoiseModel::Normal => normals[i] * (gauss() * sigma),
        };
    }
    Ok(Noisy {
        positions: out,
        l,
        sigma,
        displaced,
    })
}

/// PCA normals of a cloud over its [`CLOUD_NORMAL_K`] nearest points (fewer for tiny clouds).
fn cloud_normals(positions: &[DVec3]) -> Result<Vec<DVec3>, EvalError> {
    let finite = positions.iter().filter(|p| p.is_finite()).count();
    if finite < 3 {
        return Err(EvalError::Empty {
            what: "point cloud",
            detail: format!("{finite} finite points; a normal needs three"),
        });
    }
    let index = KnnIndex::build(positions, origin_of(positions))?;
    let (lists, _) = index.knn_all(CLOUD_NORMAL_K.min(finite))?;
    Ok(pca_normals(positions, &lists).0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::Shape;

    fn spec(model: NoiseModel, level: f64, seed: u64) -> NoiseSpec {
        NoiseSpec { model, level, seed }
    }

    #[test]
    fn iso_noise_is_seeded_and_has_the_right_sigma() {
        let m = Shape::Sphere.mesh(3).unwrap();
        let mut pos = m.positions.clone();
        // One vertex that no face references: it must not move.
        pos.push(DVec3::new(5.0, 5.0, 5.0));
        let s = spec(NoiseModel::Iso, 0.4, 3);
        let a = add_noise(&pos, Some(&m.faces), &s).unwrap();
        let b = add_noise(&pos, Some(&m.faces), &s).unwrap();
        assert_eq!(a, b);
        let c = add_noise(&pos, Some(&m.faces), &spec(NoiseModel::Iso, 0.4, 4)).unwrap();
        assert_ne!(a.positions, c.positions);
        assert_eq!(a.positions.last(), pos.last());
        assert_eq!(a.displaced, pos.len() - 1);
        let l = scale_length(&m.positions, Some(&m.faces)).unwrap();
        assert_eq!(a.l, l);
        assert!((a.sigma - 0.4 * l).abs() < 1e-15);
        // Sample standard deviation of all 3·642 coordinates of the displacement.
        let d: Vec<f64> = a
            .positions
            .iter()
            .zip(&pos)
            .take(m.positions.len())
            .flat_map(|(q, p)| (*q - *p).to_array())
            .collect();
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        let sd = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
        assert!((sd / a.sigma - 1.0).abs() < 0.05, "{sd} vs {}", a.sigma);
        assert!(mean.abs() < 0.1 * a.sigma);
    }

    #[test]
    fn normal_noise_moves_along_the_normals() {
        let m = Shape::Sphere.mesh(3).unwrap();
        let n = add_noise(
            &m.positions,
            Some(&m.faces),
            &spec(NoiseModel::Normal, 0.2, 1),
        )
        .unwrap();
        let normals = vertex_normals(&m.positions, &m.faces, NormalWeighting::Area).normals;
        let mut sq = 0.0;
        for ((q, p), nv) in n.positions.iter().zip(&m.positions).zip(&normals) {
            let d = *q - *p;
            assert!(d.cross(*nv).length() < 1e-12);
            sq += d.length_squared();
        }
        let rms = (sq / m.positions.len() as f64).sqrt();
        assert!((rms / n.sigma - 1.0).abs() < 0.1, "{rms} vs {}", n.sigma);
    }

    #[test]
    fn cloud_noise_uses_point_spacing_and_skips_nan() {
        let mut pts: Vec<DVec3> = (0..10)
            .flat_map(|i| (0..10).map(move |j| DVec3::new(i as f64, j as f64, 0.0) * 0.5))
            .collect();
        pts.push(DVec3::NAN);
        let n = add_noise(&pts, None, &spec(NoiseModel::Normal, 0.5, 0)).unwrap();
        assert!((n.l - 0.5).abs() < 1e-15);
        assert!(n.positions.last().unwrap().is_nan());
        assert_eq!(n.displaced, 100);
        // The PCA normal of a plane is ±z: only z changes.
        for (q, p) in n.positions.iter().zip(&pts).take(100) {
            assert_eq!((q.x, q.y), (p.x, p.y));
        }
        let zero = add_noise(&pts, None, &spec(NoiseModel::Iso, 0.0, 0)).unwrap();
        assert_eq!(zero.positions[..100], pts[..100]);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let m = Shape::Cube.mesh(1).unwrap();
        assert!(matches!(
            add_noise(
                &m.positions,
                Some(&m.faces),
                &spec(NoiseModel::Iso, -1.0, 0)
            ),
            Err(EvalError::Param { name: "level", .. })
        ));
        let mut pos = m.positions.clone();
        pos[0] = DVec3::NAN;
        assert!(matches!(
            add_noise(&pos, Some(&m.faces), &NoiseSpec::default()),
            Err(EvalError::NonFinite { index: 0, .. })
        ));
        assert!(add_noise(&[], None, &NoiseSpec::default()).is_err());
        assert_eq!("Normal".parse::<NoiseModel>().unwrap(), NoiseModel::Normal);
        assert!("pink".parse::<NoiseModel>().is_err());
    }
}
