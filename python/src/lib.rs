//! `qemd`: the Quadric Error Metric denoiser of `qem-denoise` for Python.
//!
//! # Brief overview
//!
//! * [`denoise`]: an `(N, 3)` float64 or float32 array (a point cloud, or mesh vertices with
//!   `faces`) to the denoised array; the keywords are the fields of the parameter spec the CLI
//!   and the HTTP API use ([`qem_denoise::pipeline::SpecOverlay`]), with the same defaults and
//!   messages. Point clouds run through [`qem_denoise::pipeline::denoise_points`], the function
//!   the file path's in-memory branch calls, so the result is the CLI's bit for bit.
//! * [`denoise_file`]: [`qem_denoise::pipeline::run`] on files, streaming and tiled out of core as
//!   the CLI; returns the run report as a dict.
//! * [`normals`], [`knn`]: PCA normals and exact k-NN lists, the pieces people reach for.
//!
//! Every call checks its input first and raises `qemd.Error` (a `ValueError`) with a one-line
//! message; the GIL is released while computing ([`compute`]); Ctrl-C stops a run.

mod array;
mod compute;
mod spec;

use std::path::PathBuf;
use std::sync::Arc;

use glam::DVec3;
use numpy::PyArray2;
use numpy::ndarray::Array2;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use qem_denoise::denoise::normals::pca_normals;
use qem_denoise::denoise::{DenoiseError, origin_of};
use qem_denoise::io::Format;
use qem_denoise::neighbours::{KnnIndex, NeighboursError};
use qem_denoise::pipeline::{self, Job, OutlierMode, PipelineError, RunOptions, SpecError};

use array::{points_array, read_faces, read_points};

pyo3::create_exception!(
    qemd,
    Error,
    pyo3::exceptions::PyValueError,
    "A refused input or parameter, or a failed run; the message is one line, as the CLI's."
);

/// The module's exception with `msg`.
fn error(msg: &str) -> PyErr {
    Error::new_err(msg.to_string())
}

/// A kernel error as the exception, or `KeyboardInterrupt` for a cancelled run.
fn denoise_err(e: DenoiseError) -> PyErr {
    match e {
        DenoiseError::Neighbours(NeighboursError::Cancelled) => {
            pyo3::exceptions::PyKeyboardInterrupt::new_err("cancelled")
        }
        e => error(&e.to_string()),
    }
}

/// Reads `threads` from the keyword options.
fn threads_of(options: &[(String, Bound<'_, PyAny>)]) -> PyResult<Option<usize>> {
    match options.iter().find(|(k, _)| k == "threads") {
        None => Ok(None),
        Some((_, v)) if v.is_none() => Ok(None),
        Some((_, v)) => v
            .extract::<usize>()
            .map(Some)
            .map_err(|_| error("threads: expected a positive integer or None")),
    }
}

/// Denoises a point cloud, or a triangle mesh given `faces`.
///
/// points: (N, 3) float64 or float32 array, C or Fortran order; float32 is computed in float64
///     and returned as float32.
/// faces: optional (M, 3) integer array of vertex indices: mesh mode (unless `knn` is given).
/// threads: worker threads (default: all cores); the result is the same for any count.
/// **params: the parameter spec's fields (knn, method, planes, filter, updates, mu, sigma_r,
///     volume, guard, max_move, radius, rings, normals, solve, eps, lambda, iterations, paper, outliers,
///     outlier_alpha, sensor_origin), as the CLI's flags and the API's JSON fields name them; write_normals
///     applies to files (denoise_file) and is refused here.
///
/// Returns the denoised (N, 3) array in the input's dtype. With outliers="remove" the outliers'
/// rows are left out; with outliers="classify" returns (points, noise), noise a bool (N,) array,
/// the flagged points keeping their input position (as the file path's class 7 / noise flag).
///
/// Raises qemd.Error (a ValueError) on a bad array or parameter, KeyboardInterrupt on Ctrl-C.
#[pyfunction]
#[pyo3(signature = (points, *, faces = None, **params))]
fn denoise<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    faces: Option<&Bound<'py, PyAny>>,
    params: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    let (params, options) = spec::split_kwargs(params, &["threads"]).map_err(|e| error(&e))?;
    let threads = threads_of(&options)?;
    let spec = spec::spec_of(&params).map_err(|e| error(&e))?;
    let (pts, float) = read_points(points).map_err(|e| error(&e))?;
    let faces = match faces {
        Some(f) if !f.is_none() => Some(read_faces(f, pts.len()).map_err(|e| error(&e))?),
        _ => None,
    };
    if spec.params.write_normals {
        // The normals are fields of an output file; an array has no fields to add.
        let e = SpecError {
            field: "write_normals",
            detail: "writes fields of an output file: use denoise_file() (qemd.normals() gives \
                     an array's PCA normals)"
                .into(),
        };
        return Err(error(&e.to_string()));
    }
    if spec.params.mesh_mode(faces.is_some()) {
        spec.check_mesh(true).map_err(|e| error(&e.to_string()))?;
        let out = compute::run(py, threads, |_| {
            qem_denoise::denoise::denoise(&pts, faces.as_ref(), &spec.params)
        })?
        .map_err(denoise_err)?;
        return Ok(points_array(py, &out.positions, float));
    }
    let out = compute::run(py, threads, |cancel| {
        pipeline::denoise_points(&pts, &spec, cancel)
    })?
    .map_err(denoise_err)?;
    // Every row passed `in_range`, so every point was processed: `kept` is 0..N.
    debug_assert_eq!(out.kept.len(), pts.len());
    let outlier: Vec<bool> = (0..pts.len()).map(|j| out.is_outlier(j)).collect();
    match spec.outliers {
        OutlierMode::Off => Ok(points_array(py, &out.positions, float)),
        OutlierMode::Remove => {
            let kept: Vec<DVec3> = (0..pts.len())
                .filter(|&j| !outlier[j])
                .map(|j| out.positions[j])
                .collect();
            Ok(points_array(py, &kept, float))
        }
        OutlierMode::Classify => {
            let moved: Vec<DVec3> = (0..pts.len())
                .map(|j| if outlier[j] { pts[j] } else { out.positions[j] })
                .collect();
            let noise = numpy::PyArray1::from_vec(py, outlier);
            let tuple = PyTuple::new(py, [points_array(py, &moved, float), noise.into_any()])?;
            Ok(tuple.into_any())
        }
    }
}

/// Denoises the file `src` into `dst`, as `qemd denoise SRC DST` does: streaming, tiled out of
/// core when the cloud does not fit `memory_budget`, atomic output, formats from the extensions.
///
/// Run options (keywords): memory_budget (bytes, default 1 GiB), tile_points (force tiling with
/// about this many points per tile), temp_dir, input_format, output_format (format names as the
/// CLI's --input-format), threads. Every other keyword is a parameter-spec field, as for denoise().
///
/// Returns the run report (the CLI's --report JSON) as a dict.
///
/// Raises qemd.Error naming the file on unreadable or malformed input, a bad parameter, a write
/// failure; KeyboardInterrupt on Ctrl-C (no output is left behind).
#[pyfunction]
#[pyo3(signature = (src, dst, **params))]
fn denoise_file<'py>(
    py: Python<'py>,
    src: PathBuf,
    dst: PathBuf,
    params: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    const OWN: &[&str] = &[
        "threads",
        "memory_budget",
        "tile_points",
        "temp_dir",
        "input_format",
        "output_format",
    ];
    let (params, options) = spec::split_kwargs(params, OWN).map_err(|e| error(&e))?;
    let threads = threads_of(&options)?;
    let spec = spec::spec_of(&params).map_err(|e| error(&e))?;
    let mut job = Job::new(src, dst);
    job.spec = spec;
    let mut opts = RunOptions::default();
    for (name, v) in &options {
        if v.is_none() {
            continue;
        }
        let bad = |what: &str| error(&format!("{name}: expected {what}"));
        match name.as_str() {
            "memory_budget" => {
                opts.memory_budget = v.extract().map_err(|_| bad("a number of bytes"))?;
                if opts.memory_budget == 0 {
                    return Err(bad("a positive number of bytes"));
                }
            }
            "tile_points" => {
                let n: u64 = v.extract().map_err(|_| bad("a positive integer"))?;
                if n == 0 {
                    return Err(bad("a positive integer"));
                }
                opts.tile_points = Some(n);
            }
            "temp_dir" => opts.temp_dir = Some(v.extract().map_err(|_| bad("a path"))?),
            "input_format" | "output_format" => {
                let s: String = v.extract().map_err(|_| bad("a format name"))?;
                let f = Format::from_name(&s).ok_or_else(|| error(&Format::unknown(&s)))?;
                if name == "input_format" {
                    job.input_format = Some(f);
                } else {
                    job.output_format = Some(f);
                }
            }
            _ => {}
        }
    }
    let report = compute::run(py, threads, |cancel| {
        let opts = RunOptions {
            cancel: Arc::clone(cancel),
            ..opts
        };
        pipeline::run(&job, &opts)
    })?;
    let report = match report {
        Ok(r) => r,
        Err(PipelineError::Cancelled) => {
            return Err(pyo3::exceptions::PyKeyboardInterrupt::new_err("cancelled"));
        }
        Err(e) => return Err(error(&e.to_string())),
    };
    let text = serde_json::to_string(&report).map_err(|e| error(&e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// Unit PCA normals over each point's k nearest neighbours (the point included), as the denoiser
/// estimates them. Unoriented (the sign is the PCA's); zero where the neighbourhood is
/// coincident or collinear.
///
/// points: (N, 3) float64 or float32 array; knn: neighbourhood size (≥ 3, ≤ N).
/// Returns an (N, 3) array in the input's dtype.
#[pyfunction]
#[pyo3(signature = (points, knn = 16, *, threads = None))]
fn normals<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    knn: usize,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    let (pts, float) = read_points(points).map_err(|e| error(&e))?;
    if knn < 3 {
        return Err(error(&format!("knn: must be at least 3, got {knn}")));
    }
    let n = compute::run(py, threads, |cancel| {
        qem_denoise::neighbours::with_cancel(cancel, || {
            let index = KnnIndex::build(&pts, origin_of(&pts))?;
            let (lists, _) = index.knn_all(knn)?;
            Ok::<_, NeighboursError>(pca_normals(&pts, &lists).0)
        })
    })?
    .map_err(|e| denoise_err(e.into()))?;
    Ok(points_array(py, &n, float))
}

/// The k nearest neighbours of every point, the point itself included (first, unless an
/// identical point has a lower index), in ascending (distance, index) order: exact, and the same
/// lists the denoiser uses.
///
/// points: (N, 3) float64 or float32 array; k: list length (1 ≤ k ≤ N).
/// Returns (indices, distances): an (N, k) int64 array and an (N, k) float64 array of Euclidean
/// distances.
#[pyfunction]
#[pyo3(signature = (points, k, *, threads = None))]
fn knn<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    k: usize,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyTuple>> {
    let (pts, _) = read_points(points).map_err(|e| error(&e))?;
    let (idx, dist) = compute::run(py, threads, |cancel| {
        qem_denoise::neighbours::with_cancel(cancel, || {
            let index = KnnIndex::build(&pts, origin_of(&pts))?;
            let (lists, _) = index.knn_all(k)?;
            let mut idx = Vec::with_capacity(pts.len() * k);
            let mut dist = Vec::with_capacity(pts.len() * k);
            for i in 0..pts.len() {
                for &j in lists.get(i) {
                    idx.push(j as i64);
                    dist.push(index.dist2(i, j as usize).sqrt());
                }
            }
            Ok::<_, NeighboursError>((idx, dist))
        })
    })?
    .map_err(|e| denoise_err(e.into()))?;
    let shape = (pts.len(), k);
    let idx = Array2::from_shape_vec(shape, idx).expect("k indices per point");
    let dist = Array2::from_shape_vec(shape, dist).expect("k distances per point");
    PyTuple::new(
        py,
        [
            PyArray2::from_owned_array(py, idx).into_any(),
            PyArray2::from_owned_array(py, dist).into_any(),
        ],
    )
}

/// The parameter spec's field names, in declaration order (the keywords denoise() accepts
/// besides faces and threads).
#[pyfunction]
fn spec_fields() -> Vec<&'static str> {
    pipeline::SpecOverlay::fields().to_vec()
}

#[pymodule]
fn qemd(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("Error", m.py().get_type::<Error>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(denoise, m)?)?;
    m.add_function(wrap_pyfunction!(denoise_file, m)?)?;
    m.add_function(wrap_pyfunction!(normals, m)?)?;
    m.add_function(wrap_pyfunction!(knn, m)?)?;
    m.add_function(wrap_pyfunction!(spec_fields, m)?)?;
    Ok(())
}
