//! The in-memory point path on a bare position array: what [`super::run`] does between reading a
//! cloud that fits the budget and writing it, without the file.
//!
//! # Brief overview
//!
//! [`denoise_points`] runs [`cloud::run_all`], the operator the file path's in-memory driver
//! runs (points failing [`in_range`] are not processed; the f64 origin, isolation and globals are
//! `run_all`'s), and the outlier threshold from exact sums over the processed points, as that
//! driver does: an array denoised here and the same points written to a file and run through
//! `qemd denoise` give the same positions bit for bit. The Python binding calls it.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use glam::DVec3;

use super::DenoiseSpec;
use super::assemble::threshold;
use super::memory::check_points;
use crate::denoise::cloud;
use crate::denoise::{DenoiseError, PhaseTiming, Stats};
use crate::geometry::ExactSum;
use crate::neighbours::with_cancel;
use crate::points::in_range;

/// What [`denoise_points`] computed.
#[derive(Debug, Clone)]
pub struct PointsOutput {
    /// Indices (into the input) of the processed points: those passing [`in_range`], ascending.
    pub kept: Vec<usize>,
    /// New position of each processed point (parallel to `kept`).
    pub positions: Vec<DVec3>,
    /// The outlier statistic of each processed point: its mean distance to its k-NN list.
    pub knn_mean: Vec<f64>,
    /// The outlier threshold: mean + α·σ of `knn_mean` with the spec's α.
    pub threshold: f64,
    /// Counts (`points` is the input length, `non_finite` the points not processed); no phases.
    pub stats: Stats,
    /// Wall and CPU time of the kernel's phases.
    pub phases: Vec<PhaseTiming>,
}

impl PointsOutput {
    /// True where processed point `j` (an index into `kept`) is a statistical outlier.
    pub fn is_outlier(&self, j: usize) -> bool {
        self.knn_mean[j] > self.threshold
    }
}

/// Denoises the point cloud `positions` as `spec` says (its `outliers` mode is left to the
/// caller: see [`PointsOutput::is_outlier`]); `cancel` stops the k-NN passes.
///
/// # Errors
/// Bad parameters, no usable point, all points identical, fewer points than k, cancellation
/// ([`crate::neighbours::NeighboursError::Cancelled`]).
pub fn denoise_points(
    positions: &[DVec3],
    spec: &DenoiseSpec,
    cancel: &Arc<AtomicBool>,
) -> Result<PointsOutput, DenoiseError> {
    spec.params.validate()?;
    if spec.classes.is_some() {
        return Err(DenoiseError::Param {
            name: "classes",
            detail: "needs a class per point, which an array of positions does not have; \
                     denoise a file (LAS, or PLY/PCD with a class field) instead"
                .into(),
        });
    }
    check_points(positions)?;
    let all = with_cancel(cancel, || cloud::run_all(positions, &spec.params))?;
    let kept: Vec<usize> = (0..positions.len())
        .filter(|&i| in_range(positions[i]))
        .collect();
    let moved: Vec<DVec3> = kept.iter().map(|&i| all.positions[i]).collect();
    let knn_mean: Vec<f64> = kept.iter().map(|&i| all.knn_mean[i]).collect();
    let (sum, sq): (ExactSum, ExactSum) = (
        knn_mean.iter().copied().collect(),
        knn_mean.iter().map(|m| m * m).collect(),
    );
    let mut stats = all.stats;
    let phases = std::mem::take(&mut stats.phases);
    Ok(PointsOutput {
        kept,
        threshold: threshold(&sum, &sq, spec.outlier_alpha),
        phases,
        positions: moved,
        knn_mean,
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::denoise::{self, Params};

    /// A noisy wavy sheet with a few far points and one NaN.
    fn sheet() -> Vec<DVec3> {
        let mut v = Vec::new();
        for i in 0..30 {
            for j in 0..30 {
                let (x, y) = (i as f64 * 0.1, j as f64 * 0.1);
                let noise = (((i * 31 + j * 17) % 13) as f64 - 6.0) * 0.002;
                v.push(DVec3::new(x + 1000.0, y, (x * 2.0).sin() * 0.1 + noise));
            }
        }
        v.push(DVec3::new(1010.0, 10.0, 5.0));
        v.push(DVec3::new(f64::NAN, 0.0, 0.0));
        v
    }

    #[test]
    fn points_equal_the_kernel_and_skip_what_is_out_of_range() {
        let pts = sheet();
        let spec = DenoiseSpec::default();
        let out = denoise_points(&pts, &spec, &Arc::new(AtomicBool::new(false))).unwrap();
        assert_eq!(out.kept.len(), pts.len() - 1);
        assert!(!out.kept.contains(&(pts.len() - 1)));
        assert_eq!(out.stats.non_finite, 1);
        let whole = denoise::denoise(&pts, None, &Params::default()).unwrap();
        for (j, &i) in out.kept.iter().enumerate() {
            assert_eq!(out.positions[j].to_array(), whole.positions[i].to_array());
        }
        // The far point is the one outlier at α = 2.
        let flagged: Vec<usize> = (0..out.kept.len())
            .filter(|&j| out.is_outlier(j))
            .map(|j| out.kept[j])
            .collect();
        assert_eq!(flagged, vec![900]);
    }

    #[test]
    fn errors_are_the_kernels() {
        let cancel = Arc::new(AtomicBool::new(false));
        let spec = DenoiseSpec::default();
        assert_eq!(
            denoise_points(&[DVec3::NAN], &spec, &cancel).unwrap_err(),
            DenoiseError::Empty
        );
        assert_eq!(
            denoise_points(&[DVec3::ONE; 20], &spec, &cancel).unwrap_err(),
            DenoiseError::AllIdentical(20)
        );
        let few: Vec<DVec3> = (0..5).map(|i| DVec3::splat(i as f64)).collect();
        assert!(matches!(
            denoise_points(&few, &spec, &cancel).unwrap_err(),
            DenoiseError::Neighbours(_)
        ));
        cancel.store(true, std::sync::atomic::Ordering::Relaxed);
        assert!(matches!(
            denoise_points(&sheet(), &spec, &cancel).unwrap_err(),
            DenoiseError::Neighbours(crate::neighbours::NeighboursError::Cancelled)
        ));
    }
}
