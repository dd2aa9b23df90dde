//! The grid a file stores its coordinates on, measured from its first points: the reason a
//! run can have nothing to move.
//!
//! A file's coordinates are quantised by how it stores them: a LAS scale (0.01), or the
//! spacing of `f32` values at the coordinates' magnitude (0.5 at a UTM northing of 4.9e6, as
//! libE57Format and pye57 write E57 by default). When that grid is coarser than the scan's
//! noise, nearby returns share their stored values exactly, the noise estimated from them is
//! (close to) zero, and every step bounded by it is zero. [`coordinate_resolution`] measures the
//! grid from the data, whatever the format: per axis, the smallest positive gap between the
//! distinct values of the first [`SAMPLE`] finite points. On coordinates stored with more
//! precision than the data needs (doubles of noisy data) that gap is tiny, so the measure only
//! ever speaks for a coarse grid.

use std::path::Path;

use super::{Format, IoError};
use crate::points::PointBatch;

/// Points read from the start of the file.
pub const SAMPLE: usize = 65_536;

/// Per axis (x, y, z), the smallest positive difference between two stored coordinate values
/// among the first [`SAMPLE`] finite points of `path` (0 for an axis with fewer than two
/// distinct values).
///
/// # Errors
/// The file cannot be opened or read.
pub fn coordinate_resolution(path: &Path, format: Option<Format>) -> Result<[f64; 3], IoError> {
    let mut source = super::open(path, format)?;
    let mut batch = PointBatch::with_capacity(source.info().schema.record_len, 8192);
    let mut axes: [Vec<f64>; 3] = Default::default();
    while axes[0].len() < SAMPLE {
        let n = source.read_batch(&mut batch, (SAMPLE - axes[0].len()).min(8192))?;
        if n == 0 {
            break;
        }
        for p in batch.positions.iter().filter(|p| p.is_finite()) {
            for (a, v) in axes.iter_mut().zip(p.to_array()) {
                a.push(v);
            }
        }
    }
    Ok(axes.map(|mut a| smallest_gap(&mut a)))
}

/// The smallest positive difference between two of `values` (reordered), or 0.
fn smallest_gap(values: &mut [f64]) -> f64 {
    values.sort_unstable_by(f64::total_cmp);
    values
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|&d| d > 0.0)
        .fold(0.0, |m: f64, d| if m == 0.0 { d } else { m.min(d) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_gap_is_the_grid_of_f32_values_at_utm_magnitude() {
        // f32 values near 4.9e6 are 0.5 apart.
        let mut v: Vec<f64> = (0..100)
            .map(|i| f64::from(4_918_340.0_f32 + (i as f32) * 0.013))
            .collect();
        assert_eq!(smallest_gap(&mut v), 0.5);
        let mut one = vec![3.0, 3.0];
        assert_eq!(smallest_gap(&mut one), 0.0);
        let mut fine = vec![0.0, 1e-9, 1.0];
        assert_eq!(smallest_gap(&mut fine), 1e-9);
    }
}
