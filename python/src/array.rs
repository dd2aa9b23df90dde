//! NumPy arrays in and out: `(N, 3)` float64 or float32 points (any strides, so C and Fortran
//! order alike), `(M, 3)` integer faces, and results in the caller's float type.
//!
//! Everything is checked before any work, with a one-line message naming the argument: not an
//! array, wrong shape, wrong dtype, no rows, a NaN, infinite or out-of-range coordinate (beyond
//! ±10¹², which the file path treats as a corrupt record), a face index out of range.

use glam::DVec3;
use numpy::ndarray::Array2;
use numpy::prelude::*;
use numpy::{PyArray2, PyUntypedArray};
use pyo3::prelude::*;
use qem_denoise::points::{Faces, MAX_COORD, in_range};

/// The float type of a points array; results come back in it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Float {
    F64,
    F32,
}

/// `points` as f64 positions (float32 widened exactly), checked.
pub fn read_points(points: &Bound<'_, PyAny>) -> Result<(Vec<DVec3>, Float), String> {
    let arr = points.cast::<PyUntypedArray>().map_err(|_| {
        format!(
            "points: expected a numpy array of shape (N, 3), got {}",
            type_name(points)
        )
    })?;
    let shape = arr.shape();
    if shape.len() != 2 || shape[1] != 3 {
        return Err(format!(
            "points: expected shape (N, 3), got {}",
            shape_text(shape)
        ));
    }
    if shape[0] == 0 {
        return Err("points: the array has no points".into());
    }
    let (pts, float): (Vec<DVec3>, Float) = if let Ok(a) = points.cast::<PyArray2<f64>>() {
        let ro = a.readonly();
        let v = ro.as_array();
        let pts = v
            .rows()
            .into_iter()
            .map(|r| DVec3::new(r[0], r[1], r[2]))
            .collect();
        (pts, Float::F64)
    } else if let Ok(a) = points.cast::<PyArray2<f32>>() {
        let ro = a.readonly();
        let v = ro.as_array();
        let pts = v
            .rows()
            .into_iter()
            .map(|r| DVec3::new(r[0] as f64, r[1] as f64, r[2] as f64))
            .collect();
        (pts, Float::F32)
    } else {
        return Err(format!(
            "points: expected dtype float64 or float32, got {}",
            dtype_text(arr)
        ));
    };
    if let Some(i) = pts.iter().position(|&p| !in_range(p)) {
        return Err(format!(
            "points: row {i} has a NaN, infinite or out-of-range coordinate (|x| > {MAX_COORD:e})"
        ));
    }
    Ok((pts, float))
}

/// `faces` as triangles over `n` vertices, checked.
pub fn read_faces(faces: &Bound<'_, PyAny>, n: usize) -> Result<Faces, String> {
    let arr = faces.cast::<PyUntypedArray>().map_err(|_| {
        format!(
            "faces: expected a numpy integer array of shape (M, 3), got {}",
            type_name(faces)
        )
    })?;
    let shape = arr.shape();
    if shape.len() != 2 || shape[1] != 3 {
        return Err(format!(
            "faces: expected shape (M, 3), got {}",
            shape_text(shape)
        ));
    }
    if shape[0] == 0 {
        return Err("faces: the array has no faces".into());
    }
    let flat: Vec<i64> = if let Ok(a) = faces.cast::<PyArray2<i64>>() {
        a.readonly().as_array().iter().copied().collect()
    } else if let Ok(a) = faces.cast::<PyArray2<i32>>() {
        a.readonly().as_array().iter().map(|&i| i as i64).collect()
    } else if let Ok(a) = faces.cast::<PyArray2<u32>>() {
        a.readonly().as_array().iter().map(|&i| i as i64).collect()
    } else if let Ok(a) = faces.cast::<PyArray2<u64>>() {
        let v = a.readonly();
        v.as_array()
            .iter()
            .map(|&i| i64::try_from(i).unwrap_or(i64::MAX))
            .collect()
    } else {
        return Err(format!(
            "faces: expected dtype int32, int64, uint32 or uint64, got {}",
            dtype_text(arr)
        ));
    };
    if let Some(j) = flat.iter().position(|&i| i < 0 || i as u64 >= n as u64) {
        return Err(format!(
            "faces: row {} refers to vertex {}, but there are {n} points",
            j / 3,
            flat[j]
        ));
    }
    let m = flat.len() / 3;
    Ok(Faces {
        offsets: (0..=m).map(|f| (3 * f) as u32).collect(),
        indices: flat.into_iter().map(|i| i as u32).collect(),
    })
}

/// Positions as an `(N, 3)` array of `float`.
pub fn points_array<'py>(py: Python<'py>, pts: &[DVec3], float: Float) -> Bound<'py, PyAny> {
    match float {
        Float::F64 => {
            let flat: Vec<f64> = pts.iter().flat_map(|p| p.to_array()).collect();
            let a = Array2::from_shape_vec((pts.len(), 3), flat).expect("3 values per point");
            PyArray2::from_owned_array(py, a).into_any()
        }
        Float::F32 => {
            let flat: Vec<f32> = pts
                .iter()
                .flat_map(|p| p.to_array().map(|c| c as f32))
                .collect();
            let a = Array2::from_shape_vec((pts.len(), 3), flat).expect("3 values per point");
            PyArray2::from_owned_array(py, a).into_any()
        }
    }
}

fn type_name(v: &Bound<'_, PyAny>) -> String {
    v.get_type()
        .name()
        .map_or_else(|_| "an object".to_string(), |n| n.to_string())
}

fn shape_text(shape: &[usize]) -> String {
    match shape {
        [n] => format!("({n},)"),
        s => format!(
            "({})",
            s.iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

fn dtype_text(arr: &Bound<'_, PyUntypedArray>) -> String {
    arr.dtype()
        .str()
        .map_or_else(|_| "another dtype".to_string(), |s| s.to_string())
}
