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

pub mod beams;
pub mod bilateral;
pub mod cloud;
pub mod common;
pub(crate) mod filtered;
pub(crate) mod frame;
pub mod guarded;
pub mod isolation;
pub mod normals;
pub mod qem;
mod stats;
pub mod structure;
pub mod written;

pub use beams::SensorOrigin;
pub use stats::{Displacements, PhaseTiming, Stats, StructureCounts, Timer};

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
        /// Parameter name as the spec spells it (`sigma_r`; the CLI flag is `--sigma-r`).
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
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
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
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
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
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum SolveKind {
    /// `w = −A⁻¹b` (the paper).
    Plain,
    /// `w = v − A⁺(Av + b)`, eigenvalues below `eps·λmax` dropped.
    Robust,
    /// `w = v − (A + λI)⁻¹(Av + b)`.
    Regularised,
    /// `w = v − (A + μ·tr(A)/3·I)⁻¹(Av + b)`: the regularised solve with a penalty relative to
    /// the quadric's own weight, so it is the same for any neighbourhood size or weighting.
    #[default]
    Damped,
}

/// Which planes the quadrics are built from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Planes {
    /// Meshes: each face's plane (its — filtered — normal through its centroid), area-weighted,
    /// over the faces around the vertex. Point clouds: each neighbour's tangent plane, its normal
    /// bent halfway towards the point's own where the two are nearly parallel (which removes the
    /// outward bias of projecting onto the tangent planes of a curved surface).
    #[default]
    Face,
    /// The paper: each neighbour's tangent plane (its normal through itself), over the vertex's
    /// k-ring or the point's k nearest neighbours.
    Tangent,
}

/// Denoising parameters, named as the CLI flags.
///
/// The defaults are qemd's operator: normals smoothed by a bilateral filter (faces on meshes,
/// the k-NN graph on clouds), then repeated damped QEM updates on face (or curvature-corrected
/// tangent) planes, with an amount of smoothing chosen from the data on meshes. [`Params::paper`]
/// gives the paper's Algorithm 1 exactly.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Params {
    /// `--method`.
    pub method: Method,
    /// `--rings`: k-ring size of tangent planes in mesh mode (the vertex itself included).
    pub rings: usize,
    /// `--knn`: neighbourhood size in point mode (the point itself included); setting it forces
    /// point mode. `None` means mesh mode for meshes and 16 for point clouds.
    pub knn: Option<usize>,
    /// `--normals`: how vertex normals come from face normals (tangent planes on meshes).
    pub normals: NormalWeighting,
    /// `--planes`.
    pub planes: Planes,
    /// `--filter`: normal-filter iterations per cycle (0: raw normals, as the paper). `None`:
    /// 10 on meshes, 3 on point clouds.
    pub filter: Option<usize>,
    /// `--updates`: QEM updates per cycle. `None`: 5 on meshes, 2 on point clouds.
    pub updates: Option<usize>,
    /// `--iterations`: cycles (normal filter, then updates) for QEM, passes for bilateral.
    /// 0 chooses: on meshes from the noise the data shows (a light cycle, then two or three
    /// heavy ones unless the light one already left mostly shape); 1 on clouds; 3 for bilateral.
    pub iterations: usize,
    /// `--solve`.
    pub solve: SolveKind,
    /// `--eps`: relative eigenvalue cut-off of the robust solve.
    pub eps: f64,
    /// `--lambda`: step penalty of the regularised solve.
    pub lambda: f64,
    /// `--mu`: relative step penalty of the damped solve.
    pub mu: f64,
    /// `--sigma-r`: lower bound of the normal filter's range width. `None`: 0.35 on meshes, 0.2
    /// on point clouds.
    pub sigma_r: Option<f64>,
    /// `--volume`: keep the enclosed volume of closed meshes (a final offset along the normals;
    /// iso noise leaves the expected volume unchanged, so the input's is the target).
    pub volume: bool,
    /// `--no-guard` clears it: on point clouds, classify every neighbourhood ([`structure`]) and
    /// take the quadric step only where it shows a surface or a line, with robust plane weights
    /// and a step bounded by the local noise ([`guarded`]). The paper's operator has none.
    pub guard: bool,
    /// `--max-move`: a hard cap on any point's displacement, in the input's units (metres for
    /// LiDAR). `None`: no cap beyond the operator's own bounds.
    pub max_move: Option<f64>,
    /// `--radius`: point mode, the farthest a neighbour may be, in the input's units (metres for
    /// LiDAR): a list holds the k nearest points within it, and a point with fewer than
    /// [`isolation::MIN_LIST`] points that near keeps its position, as an isolated point does
    /// ([`isolation::cap`]). `None`: the cloud's isolation radius only.
    pub radius: Option<f64>,
    /// `--write-normals`: on point clouds, also compute what the output writes per point as
    /// extra fields (the oriented normal, the surface variation and the structure class of the
    /// last cycle's neighbourhood, [`written`]). Off by default: the output keeps the input's
    /// schema. Not serialised when off, so stored specs and reports keep their shape.
    #[serde(skip_serializing_if = "is_false")]
    pub write_normals: bool,
    /// `--sensor-origin`: on point clouds, where the beams come from ([`beams`]): the guarded
    /// operator fits each neighbourhood along each return's beam and moves the return only along
    /// it. `Auto`: the sensor's frame for the formats stored in it (KITTI, nuScenes), none
    /// elsewhere. Not serialised when `Auto`, so stored specs keep their shape.
    #[serde(skip_serializing_if = "is_auto")]
    pub sensor_origin: SensorOrigin,
}

/// serde's `skip_serializing_if` for a sensor origin left to the input.
fn is_auto(o: &SensorOrigin) -> bool {
    *o == SensorOrigin::Auto
}

/// serde's `skip_serializing_if` for a flag that is off.
fn is_false(b: &bool) -> bool {
    !*b
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
            planes: Planes::Face,
            filter: None,
            updates: None,
            iterations: 0,
            solve: SolveKind::Damped,
            eps: 1e-2,
            lambda: 0.1,
            mu: 0.5,
            sigma_r: None,
            volume: true,
            guard: true,
            max_move: None,
            radius: None,
            write_normals: false,
            sensor_origin: SensorOrigin::Auto,
        }
    }
}

/// The schedule a run resolves to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Schedule {
    /// Normal-filter iterations per cycle.
    pub filter: usize,
    /// Updates per cycle.
    pub updates: usize,
    /// Cycles; 0 means adaptive (meshes only).
    pub cycles: usize,
}

impl Params {
    /// The paper's Algorithm 1: tangent planes over 2-rings (k-NN lists for clouds) with
    /// area-weighted vertex normals, raw normals, one update, the plain solve, no volume step.
    pub fn paper() -> Params {
        Params {
            planes: Planes::Tangent,
            filter: Some(0),
            updates: Some(1),
            iterations: 1,
            solve: SolveKind::Plain,
            volume: false,
            guard: false,
            ..Params::default()
        }
    }

    /// The geometric solver these parameters select, for a quadric whose `A` has trace `trace`.
    pub fn solver_for(&self, trace: f64) -> Solve {
        match self.solve {
            SolveKind::Plain => Solve::Plain,
            SolveKind::Robust => Solve::Robust { eps: self.eps },
            SolveKind::Regularised => Solve::Regularised {
                lambda: self.lambda,
            },
            SolveKind::Damped => Solve::Regularised {
                lambda: (self.mu * trace / 3.0).max(f64::MIN_POSITIVE),
            },
        }
    }

    /// The solver for unit-weight quadrics summed over `k` planes (trace `k`), for validation
    /// and reporting.
    pub fn solver(&self) -> Solve {
        self.solver_for(3.0)
    }

    /// Neighbourhood size for point mode.
    pub fn k(&self) -> usize {
        self.knn.unwrap_or(DEFAULT_KNN)
    }

    /// Filter iterations, updates and cycles for mesh (`mesh`) or point mode.
    pub fn schedule(&self, mesh: bool) -> Schedule {
        Schedule {
            filter: self.filter.unwrap_or(if mesh { 10 } else { 3 }),
            updates: self.updates.unwrap_or(if mesh { 5 } else { 2 }),
            cycles: match (self.iterations, self.method, mesh) {
                (0, Method::Bilateral, _) => 3,
                (0, Method::Qem, false) => 1,
                (n, _, _) => n,
            },
        }
    }

    /// Lower bound of the normal filter's range width.
    pub fn sigma_r_floor(&self, mesh: bool) -> f64 {
        self.sigma_r.unwrap_or(if mesh { 0.35 } else { 0.2 })
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
        if self.iterations > 1000 {
            return bad("iterations", "must be at most 1000 (0 chooses)");
        }
        if self.filter.is_some_and(|f| f > 1000) {
            return bad("filter", "must be at most 1000");
        }
        if self.updates.is_some_and(|u| !(1..=1000).contains(&u)) {
            return bad("updates", "must be between 1 and 1000");
        }
        if self.eps.is_nan() || self.eps <= 0.0 || self.eps >= 1.0 {
            return bad("eps", "must be in (0, 1)");
        }
        if !self.lambda.is_finite() || self.lambda <= 0.0 {
            return bad("lambda", "must be finite and > 0");
        }
        if !self.mu.is_finite() || self.mu <= 0.0 {
            return bad("mu", "must be finite and > 0");
        }
        if self
            .sigma_r
            .is_some_and(|s| !s.is_finite() || s <= 0.0 || s > 2.0)
        {
            return bad("sigma_r", "must be in (0, 2]");
        }
        if self.max_move.is_some_and(|m| !m.is_finite() || m < 0.0) {
            return bad("max_move", "must be finite and ≥ 0");
        }
        if self.radius.is_some_and(|r| !r.is_finite() || r <= 0.0) {
            return bad("radius", "must be finite and > 0");
        }
        if !self.sensor_origin.is_valid() {
            return bad("sensor_origin", "must be three finite coordinates");
        }
        self.solver().validate()?;
        Ok(())
    }

    /// Checks what [`Params::validate`] cannot know before the input is read: in mesh mode, the
    /// plain solve (no step bound) with more than one update in all, and no `--max-move`, is
    /// refused — repeated updates amplify its drift along nearly flat directions (the default
    /// schedule moved vertices of the shared bunny 1,523 L away; issue 15).
    ///
    /// # Errors
    /// [`DenoiseError::Param`] naming `solve`.
    pub fn check_mode(&self, mesh: bool) -> Result<(), DenoiseError> {
        let s = self.schedule(true);
        let single = s.updates == 1 && s.cycles == 1;
        if mesh
            && self.method == Method::Qem
            && self.solve == SolveKind::Plain
            && !single
            && self.max_move.is_none()
        {
            return Err(DenoiseError::Param {
                name: "solve",
                detail: format!(
                    "plain has no step bound and drifts over repeated updates on a mesh ({} \
                     updates × {} cycles asked); use it with --paper (or --updates 1 \
                     --iterations 1), bound it with --max-move, or keep the default damped solve",
                    s.updates,
                    if s.cycles == 0 {
                        "adaptive".to_string()
                    } else {
                        s.cycles.to_string()
                    }
                ),
            });
        }
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
            params.check_mode(true)?;
            if let Some(i) = positions.iter().position(|p| !p.is_finite()) {
                return Err(DenoiseError::NonFiniteVertex { index: i });
            }
            let mut out = match (params.method, params.planes) {
                (Method::Qem, Planes::Tangent) => qem::mesh(positions, f, params),
                (Method::Qem, Planes::Face) => filtered::mesh(positions, f, params),
                (Method::Bilateral, _) => bilateral::mesh(positions, f, params),
            }?;
            if let Some(m) = params.max_move {
                let mut moves = Displacements::default();
                for (p, &p0) in out.positions.iter_mut().zip(positions) {
                    let (q, flag) = guarded::clamp(p0, *p, m);
                    *p = q;
                    out.stats.bounded += u64::from(flag != 0);
                    moves.add((q - p0).length());
                }
                moves.refresh();
                out.stats.max_step = moves.max;
                out.stats.displacement = moves;
            }
            Ok(out)
        }
        _ => cloud::run_all(positions, params).map(Output::from),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 15, item 7: the plain solve on a mesh only with one update (the paper), or a cap.
    #[test]
    fn issue15_plain_solve_on_a_mesh_needs_one_update_or_a_cap() {
        let pos = [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::new(1.0, 1.0, 0.1)];
        let faces = Faces::from_triangles(&[[0, 1, 2], [1, 3, 2]]);
        let plain = Params {
            solve: SolveKind::Plain,
            ..Params::default()
        };
        let e = denoise(&pos, Some(&faces), &plain).unwrap_err();
        assert!(
            matches!(e, DenoiseError::Param { name: "solve", .. }),
            "{e}"
        );
        assert!(e.to_string().contains("--paper"), "{e}");
        // The paper, one update with the default planes, a cap, or point mode: accepted.
        for p in [
            Params::paper(),
            Params {
                updates: Some(1),
                iterations: 1,
                ..plain
            },
            Params {
                max_move: Some(0.1),
                ..plain
            },
        ] {
            assert!(p.check_mode(true).is_ok(), "{p:?}");
        }
        assert!(plain.check_mode(false).is_ok());
    }

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
