//! Evaluation: synthetic shapes, noise, the quality metrics of `docs/EVALUATION.md`, the paper's Table I
//! protocol and a software renderer.
//!
//! # Brief overview
//!
//! * [`synth`]: [`Shape`]s (icosphere, cube, CAD-like part, torus, step) as closed, consistently
//!   oriented triangle [`Mesh`]es, and [`SurfaceSampler`], which streams seeded, area-uniform surface
//!   samples in batches so that any number of points can be written with bounded memory.
//! * [`noise`]: the `iso` and `normal` noise models with σ = level · L ([`add_noise`]).
//! * [`metrics`]: [`Reference`] holds a clean mesh or cloud with its spatial indices and measures a
//!   denoised result against it ([`Metrics`]: `surf_std`, `surf_rms`, `std_xyz`, `ang_deg`,
//!   `dvol_pct`, point-to-mesh and Chamfer errors, all in % of L).
//! * [`table`]: the Table I protocol (noise → denoise → metrics over levels, seeds and a list of
//!   named methods) with a Markdown formatter.
//! * [`render`](mod@render): z-buffered rasterisation of meshes and splatting of point clouds to PNG.
//! * [`plot`]: line charts as SVG (plotters) for the report.
//! * [`spectrum`]: the paper's frequency-response analysis on a height-field patch (2D FFT of
//!   resampled height fields, radially averaged gain).
//! * [`pairs`]: the real clean/noisy benchmark pairs, measured per method.
//! * [`pairing`]: which output point is which input point (by index, checked on the attributes
//!   both keep, or by those attributes when the output is reordered).
//! * [`scans`]: the real-scan protocol (`qemd harm`): displacement over r16 on the scan as it is,
//!   and noise removed from the scan plus known noise, per class.
//! * [`lidar`]: a LiDAR simulator with exact truth (a parametric street, spinning, mobile,
//!   airborne and terrestrial sensors, beam physics) and its scorer (`qemd synth lidar`,
//!   `qemd score`).
//! * [`report`](mod@report): the quality report (`qemd report`): Table I for four rows, charts,
//!   renderings, the pairs and the frequency response as HTML and Markdown.
//!
//! ```text
//!  Shape ──mesh()──▶ Mesh ──add_noise()──▶ noisy ──denoise()──▶ denoised
//!                      │                                          │
//!                      └──────────── Reference::new() ──evaluate()┘──▶ Metrics ──▶ Table
//! ```
//!
//! Everything here works on in-memory positions and [`Faces`]; reading and writing files is the
//! caller's business (except PNG output, which goes through [`crate::io::AtomicFile`]).

pub mod lidar;
pub(crate) mod methods;
pub mod metrics;
pub mod noise;
pub mod pairing;
pub mod pairs;
pub mod plot;
pub mod render;
pub mod report;
pub mod scans;
pub mod spectrum;
pub mod synth;
pub mod table;

pub use metrics::{Metrics, Reference, evaluate};
pub use noise::{NoiseModel, NoiseSpec, Noisy, add_noise, add_noise_with_length};
pub use render::{Image, PointShading, RenderOptions, Shading, View, render};
pub use report::{Report, ReportSpec, report_methods, write_report};
pub use spectrum::{FrequencyResponse, SpectrumSpec, frequency_response};
pub use synth::{Shape, SurfaceSampler};
pub use table::{Table, TableMethod, TableProgress, TableSpec, run_table, run_table_with_progress};

use glam::DVec3;
use thiserror::Error;

use crate::denoise::DenoiseError;
use crate::denoise::bilateral::mean_spacing;
use crate::denoise::common::mean_edge_length;
use crate::io::{Cloud, IoError};
use crate::neighbours::{KnnIndex, MeshAdjacency, NeighboursError};
use crate::points::{Faces, ScalarType};

/// Errors of the evaluation tools.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum EvalError {
    /// A parameter is out of range.
    #[error("invalid parameter {name}: {detail}")]
    Param {
        /// Parameter name as the CLI spells it.
        name: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// The input has nothing to work on.
    #[error("the {what} is empty: {detail}")]
    Empty {
        /// Which input (`clean mesh`, `denoised cloud`, …).
        what: &'static str,
        /// What is missing.
        detail: String,
    },
    /// A face references a vertex that does not exist.
    #[error("face {face} references vertex {vertex}, but there are only {vertices} vertices")]
    FaceIndex {
        /// Face index.
        face: usize,
        /// The bad vertex index.
        vertex: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// A vertex that takes part in the computation is NaN or infinite.
    #[error("{what} vertex {index} has a non-finite coordinate")]
    NonFinite {
        /// Which input.
        what: &'static str,
        /// Vertex index.
        index: usize,
    },
    /// Clean and denoised meshes do not correspond vertex by vertex.
    #[error("the meshes do not correspond: {0}")]
    Mismatch(String),
    /// A method's output does not pair with its input point by point.
    #[error("{0}")]
    Pairing(String),
    /// The geometry is degenerate for the requested operation (zero scale length, no area…).
    #[error("degenerate input: {0}")]
    Degenerate(String),
    /// A synthetic shape could not be built.
    #[error("cannot build the synthetic shape: {0}")]
    Synth(String),
    /// Denoising failed (Table I).
    #[error(transparent)]
    Denoise(#[from] DenoiseError),
    /// A neighbour search failed.
    #[error(transparent)]
    Neighbours(#[from] NeighboursError),
    /// Writing a file failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// PNG encoding failed.
    #[error("PNG encoding failed: {0}")]
    Png(#[from] png::EncodingError),
    /// Drawing a chart failed.
    #[error("cannot draw the chart: {0}")]
    Plot(String),
    /// Serialising results to JSON failed.
    #[error("cannot write the results as JSON: {0}")]
    Json(#[from] serde_json::Error),
}

/// A triangle (or polygon) mesh in memory.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<DVec3>,
    /// Faces indexing `positions`.
    pub faces: Faces,
}

impl Mesh {
    /// The mesh as a [`Cloud`] with a float64 x, y, z record, ready for [`Cloud::write`].
    pub fn into_cloud(self) -> Cloud {
        Cloud::generated(self.positions, Some(self.faces), ScalarType::F64)
    }

    /// Signed volume enclosed by the faces (positive for a closed mesh oriented outwards).
    pub fn signed_volume(&self) -> f64 {
        signed_volume(&self.positions, &self.faces)
    }

    /// True when every undirected edge is shared by exactly two faces.
    pub fn is_closed(&self) -> bool {
        is_closed(&self.faces)
    }

    /// True when no directed edge occurs twice, i.e. neighbouring faces agree on orientation.
    pub fn is_consistently_oriented(&self) -> bool {
        is_consistently_oriented(&self.faces)
    }
}

/// Checks that every face index is below `n`.
///
/// # Errors
/// [`EvalError::FaceIndex`] naming the first bad face.
pub fn check_faces(n: usize, faces: &Faces) -> Result<(), EvalError> {
    for (face, f) in faces.iter().enumerate() {
        if let Some(&vertex) = f.iter().find(|&&v| v as usize >= n) {
            return Err(EvalError::FaceIndex {
                face,
                vertex,
                vertices: n,
            });
        }
    }
    Ok(())
}

/// Which of `n` vertices at least one face references (indices must be valid).
pub fn referenced(n: usize, faces: &Faces) -> Vec<bool> {
    let mut r = vec![false; n];
    for &v in &faces.indices {
        if let Some(x) = r.get_mut(v as usize) {
            *x = true;
        }
    }
    r
}

/// The directed edges `(a, b)` of all faces, consecutive corners wrapping around; repeated corners
/// (degenerate edges) are left out.
fn directed_edges(faces: &Faces) -> Vec<(u32, u32)> {
    let mut e = Vec::with_capacity(faces.indices.len());
    for f in faces.iter() {
        for (c, &a) in f.iter().enumerate() {
            let b = f[(c + 1) % f.len()];
            if a != b {
                e.push((a, b));
            }
        }
    }
    e
}

/// True when the faces are non-empty and every undirected edge is shared by exactly two faces.
pub fn is_closed(faces: &Faces) -> bool {
    let mut e: Vec<(u32, u32)> = directed_edges(faces)
        .into_iter()
        .map(|(a, b)| (a.min(b), a.max(b)))
        .collect();
    if e.is_empty() {
        return false;
    }
    e.sort_unstable();
    e.chunk_by(|x, y| x == y).all(|run| run.len() == 2)
}

/// True when no directed edge occurs twice: adjacent faces traverse their shared edge in opposite
/// directions. (Together with [`is_closed`] this means a consistently oriented closed surface.)
pub fn is_consistently_oriented(faces: &Faces) -> bool {
    let mut e = directed_edges(faces);
    e.sort_unstable();
    e.windows(2).all(|w| w[0] != w[1])
}

/// Signed volume enclosed by `faces` (fan-triangulated), taken relative to the centroid of the
/// referenced vertices so that far-away meshes keep their precision. It is the enclosed volume only
/// for a closed mesh; positive when the faces are oriented outwards.
pub fn signed_volume(pos: &[DVec3], faces: &Faces) -> f64 {
    let mut c = DVec3::ZERO;
    let mut n = 0usize;
    for &v in &faces.indices {
        if let Some(p) = pos.get(v as usize) {
            c += *p;
            n += 1;
        }
    }
    if n == 0 {
        return 0.0;
    }
    c /= n as f64;
    let mut sum = 0.0;
    for [a, b, d] in faces.triangles() {
        let (Some(&pa), Some(&pb), Some(&pd)) = (
            pos.get(a as usize),
            pos.get(b as usize),
            pos.get(d as usize),
        ) else {
            continue;
        };
        sum += (pa - c).dot((pb - c).cross(pd - c));
    }
    sum / 6.0
}

/// The scale length L of `docs/EVALUATION.md`: the mean length of the unique undirected edges of the
/// faces, or for a cloud without faces the mean distance from each point to its nearest other
/// point.
///
/// # Errors
/// Bad face indices, fewer than two finite points, or L = 0.
pub fn scale_length(positions: &[DVec3], faces: Option<&Faces>) -> Result<f64, EvalError> {
    let l = match faces {
        Some(f) if !f.is_empty() => {
            check_faces(positions.len(), f)?;
            let adjacency = MeshAdjacency::build(positions.len(), f)?;
            mean_edge_length(positions, &adjacency)
        }
        _ => {
            let finite = positions.iter().filter(|p| p.is_finite()).count();
            if finite < 2 {
                return Err(EvalError::Empty {
                    what: "point cloud",
                    detail: format!("{finite} finite points; the point spacing needs two"),
                });
            }
            let index = KnnIndex::build(positions, crate::denoise::origin_of(positions))?;
            let (lists, _) = index.knn_all(2)?;
            mean_spacing(&index, &lists)
        }
    };
    if !(l > 0.0 && l.is_finite()) {
        return Err(EvalError::Degenerate(format!(
            "the scale length L is {l} (all edges or point distances are zero)"
        )));
    }
    Ok(l)
}

/// Writes `bytes` to `path` atomically.
pub(crate) fn write_file(path: &std::path::Path, bytes: &[u8]) -> Result<(), EvalError> {
    use std::io::Write as _;
    let mut f = crate::io::AtomicFile::create(path)?;
    f.write_all(bytes).map_err(|e| f.err(e))?;
    f.commit()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closedness_and_orientation_of_a_tetrahedron() {
        let pos = vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z];
        let faces = Faces::from_triangles(&[[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]);
        let m = Mesh {
            positions: pos.clone(),
            faces,
        };
        assert!(m.is_closed());
        assert!(m.is_consistently_oriented());
        assert!((m.signed_volume() - 1.0 / 6.0).abs() < 1e-15);
        let open = Faces::from_triangles(&[[0, 2, 1], [0, 1, 3], [1, 2, 3]]);
        assert!(!is_closed(&open));
        let flipped = Faces::from_triangles(&[[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 3, 2]]);
        assert!(is_closed(&flipped));
        assert!(!is_consistently_oriented(&flipped));
        assert!(!is_closed(&Faces::new()));
    }

    #[test]
    fn scale_length_of_mesh_and_cloud() {
        let pos = vec![DVec3::ZERO, DVec3::X, DVec3::Y];
        let faces = Faces::from_triangles(&[[0, 1, 2]]);
        let l = scale_length(&pos, Some(&faces)).unwrap();
        assert!((l - (2.0 + 2f64.sqrt()) / 3.0).abs() < 1e-15);
        let l = scale_length(&pos, None).unwrap();
        assert!((l - 1.0).abs() < 1e-15);
        assert!(matches!(
            scale_length(&pos[..1], None),
            Err(EvalError::Empty { .. })
        ));
        let bad = Faces::from_triangles(&[[0, 1, 7]]);
        assert!(matches!(
            scale_length(&pos, Some(&bad)),
            Err(EvalError::FaceIndex { vertex: 7, .. })
        ));
        let same = vec![DVec3::ONE; 3];
        assert!(matches!(
            scale_length(&same, Some(&faces)),
            Err(EvalError::Degenerate(_))
        ));
    }
}
