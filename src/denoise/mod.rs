//! Denoising operators: the QEM operator of Vieira et al. on meshes and point clouds, and the
//! bilateral filter of Fleishman et al. (2003) as the classical baseline.
//!
//! # Brief overview
//!
//! * [`Params`] holds every knob with the CLI's names; [`Params::validate`] rejects bad values
//!   before any work starts.
//! * [`denoise`] picks the mode: **mesh** when faces are given and `knn` is not set (k-rings and
//!   face normals), **points** otherwise (k nearest neighbours and PCA normals).
//! * Every pass is a Jacobi pass: all new positions are computed from the old ones, each by a pure
//!   function of its neighbourhood summed in a fixed order, so the output is bit-identical for any
//!   number of threads.
//! * [`Stats`] counts what happened: points that stayed because `A` was singular, vertices no face
//!   references, zero-area faces, degenerate (coincident or collinear) neighbourhoods, duplicates.
//!   Points never become NaN: a non-finite solve leaves the point where it is.
//!
//! The kernels are in [`qem`], [`bilateral`] and [`normals`]; [`cloud`] runs them on a set of
//! points, which is what the in-memory path and every tile of the out-of-core path do.

pub mod bilateral;
pub mod cloud;
pub mod frame;
pub mod normals;
pub mod qem;
mod stats;

pub use stats::{PhaseTiming, Stats, Timer};

use glam::DVec3;
use thiserror::Error;

use crate::geometry::{GeometryError, Solve};
use crate::neighbours::NeighboursError;
use crate::points::{Aabb, Faces};

/// Errors of the denoisers.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum DenoiseError {
    /// A parameter is out of range.
    #[error("invalid parameter {name}: {detail}")]
    Param {
        /// Parameter name as the CLI spells it.
        name: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// Neighbourhoods could not be built (too few points, bad face index…).
    #[error(transparent)]
    Neighbours(#[from] NeighboursError),
    /// A mesh vertex is NaN or infinite; mesh vertices cannot be dropped.
    #[error("mesh vertex {index} has a non-finite coordinate")]
    NonFiniteVertex {
        /// Vertex index.
        index: usize,
    },
    /// Nothing to denoise.
    #[error("the input has no usable points")]
    Empty,
    /// Every usable point sits at the same position: there is no surface.
    #[error("all {0} points are identical; there is no surface to denoise")]
    AllIdentical(usize),
}

impl From<GeometryError> for DenoiseError {
    fn from(e: GeometryError) -> Self {
        match e {
            GeometryError::Parameter {
                name,
                expected,
                value,
            } => DenoiseError::Param {
                name,
                detail: format!("must be {expected}, got {value}"),
            },
        }
    }
}

/// The denoising method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Quadric Error Metric operator (Vieira et al., Algorithm 1).
    #[default]
    Qem,
    /// Bilateral mesh denoising (Fleishman et al. 2003).
    Bilateral,
}

/// How mesh vertex normals are formed from the incident faces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum NormalWeighting {
    /// Sum of the unnormalised face cross products (area-weighted), normalised.
    #[default]
    Area,
    /// Sum of the unit face normals (plain mean), normalised.
    Mean,
}

/// The solver as the CLI names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum SolveKind {
    /// `w = −A⁻¹b` (the paper).
    Plain,
    /// `w = v − A⁺(Av + b)`, eigenvalues below `eps·λmax` dropped.
    #[default]
    Robust,
    /// `w = v − (A + λI)⁻¹(Av + b)`.
    Regularised,
}

/// Denoising parameters, named as the CLI flags.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Params {
    /// `--method`.
    pub method: Method,
    /// `--rings`: k-ring size in mesh mode (the vertex itself included).
    pub rings: usize,
    /// `--knn`: neighbourhood size in point mode (the point itself included); setting it forces
    /// point mode. `None` means mesh mode for meshes and 16 for point clouds.
    pub knn: Option<usize>,
    /// `--normals`: mesh vertex normals.
    pub normals: NormalWeighting,
    /// `--solve`.
    pub solve: SolveKind,
    /// `--eps`: relative eigenvalue cut-off of the robust solve.
    pub eps: f64,
    /// `--lambda`: step penalty of the regularised solve.
    pub lambda: f64,
    /// `--iterations`: number of Jacobi passes.
    pub iterations: usize,
}

/// Default point-mode neighbourhood size.
pub const DEFAULT_KNN: usize = 16;

impl Default for Params {
    fn default() -> Self {
        Params {
            method: Method::Qem,
            rings: 2,
            knn: None,
            normals: NormalWeighting::Area,
            solve: SolveKind::Robust,
            eps: 1e-2,
            lambda: 0.1,
            iterations: 1,
        }
    }
}

impl Params {
    /// The geometric solver these parameters select.
    pub fn solver(&self) -> Solve {
        match self.solve {
            SolveKind::Plain => Solve::Plain,
            SolveKind::Robust => Solve::Robust { eps: self.eps },
            SolveKind::Regularised => Solve::Regularised {
                lambda: self.lambda,
            },
        }
    }

    /// Neighbourhood size for point mode.
    pub fn k(&self) -> usize {
        self.knn.unwrap_or(DEFAULT_KNN)
    }

    /// Checks every range; call before any I/O.
    ///
    /// # Errors
    /// [`DenoiseError::Param`] naming the first bad parameter.
    pub fn validate(&self) -> Result<(), DenoiseError> {
        let bad = |name, detail: &str| {
            Err(DenoiseError::Param {
                name,
                detail: detail.to_string(),
            })
        };
        if !(1..=64).contains(&self.rings) {
            return bad("rings", "must be between 1 and 64");
        }
        if let Some(k) = self.knn
            && !(3..=1024).contains(&k)
        {
            return bad(
                "knn",
                "must be between 3 and 1024 (a plane needs three points)",
            );
        }
        if !(1..=1000).contains(&self.iterations) {
            return bad("iterations", "must be between 1 and 1000");
        }
        if self.eps.is_nan() || self.eps <= 0.0 || self.eps >= 1.0 {
            return bad("eps", "must be in (0, 1)");
        }
        if !self.lambda.is_finite() || self.lambda <= 0.0 {
            return bad("lambda", "must be finite and > 0");
        }
        self.solver().validate()?;
        Ok(())
    }

    /// True when these parameters run in mesh mode on an input with (`has_faces`) or without faces.
    pub fn mesh_mode(&self, has_faces: bool) -> bool {
        has_faces && self.knn.is_none()
    }
}

/// The result of a denoising run.
#[derive(Debug, Clone)]
pub struct Output {
    /// New positions, one per input position (non-finite inputs stay as they were).
    pub positions: Vec<DVec3>,
    /// What happened.
    pub stats: Stats,
}

/// A fixed origin for neighbour searches: the lower corner of the finite points' bounding box.
/// Relative coordinates keep k-d tree distances precise on georeferenced data, and the tiled path
/// derives the same origin from the same bounds.
pub fn origin_of(positions: &[DVec3]) -> DVec3 {
    let b = Aabb::from_points(positions);
    if b.is_empty() { DVec3::ZERO } else { b.min }
}

/// Denoises `positions` (with `faces` for a mesh) as `params` say.
///
/// # Errors
/// Bad parameters, too few points for k, face indices out of range, non-finite mesh vertices.
pub fn denoise(
    positions: &[DVec3],
    faces: Option<&Faces>,
    params: &Params,
) -> Result<Output, DenoiseError> {
    params.validate()?;
    let finite = positions.iter().filter(|p| p.is_finite()).count();
    if finite == 0 {
        return Err(DenoiseError::Empty);
    }
    if finite > 1 && Aabb::from_points(positions).size() == DVec3::ZERO {
        return Err(DenoiseError::AllIdentical(finite));
    }
    match faces {
        Some(f) if params.mesh_mode(true) => {
            if let Some(i) = positions.iter().position(|p| !p.is_finite()) {
                return Err(DenoiseError::NonFiniteVertex { index: i });
            }
            match params.method {
                Method::Qem => qem::mesh(positions, f, params),
                Method::Bilateral => bilateral::mesh(positions, f, params),
            }
        }
        _ => cloud::run_all(positions, params),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_validation_names_the_field() {
        let p = Params {
            rings: 0,
            ..Params::default()
        };
        assert!(matches!(
            p.validate(),
            Err(DenoiseError::Param { name: "rings", .. })
        ));
        let p = Params {
            knn: Some(2),
            ..Params::default()
        };
        assert!(matches!(
            p.validate(),
            Err(DenoiseError::Param { name: "knn", .. })
        ));
        let p = Params {
            eps: 1.5,
            ..Params::default()
        };
        assert!(matches!(
            p.validate(),
            Err(DenoiseError::Param { name: "eps", .. })
        ));
        let p = Params {
            lambda: f64::NAN,
            ..Params::default()
        };
        assert!(matches!(
            p.validate(),
            Err(DenoiseError::Param { name: "lambda", .. })
        ));
        assert!(Params::default().validate().is_ok());
        let json = serde_json::to_string(&Params::default()).unwrap();
        let back: Params = serde_json::from_str(&json).unwrap();
        assert_eq!(back, Params::default());
        assert!(serde_json::from_str::<Params>(r#"{"ringz": 2}"#).is_err());
    }

    #[test]
    fn empty_and_all_nan_inputs_are_errors() {
        assert_eq!(
            denoise(&[], None, &Params::default()).unwrap_err(),
            DenoiseError::Empty
        );
        let nan = vec![DVec3::NAN; 20];
        assert_eq!(
            denoise(&nan, None, &Params::default()).unwrap_err(),
            DenoiseError::Empty
        );
        let same = vec![DVec3::ONE; 40];
        assert_eq!(
            denoise(&same, None, &Params::default()).unwrap_err(),
            DenoiseError::AllIdentical(40)
        );
    }
}
