//! The in-memory point path on a bare position array: what [`super::run`] does between reading a
//! cloud that fits the budget and writing it, without the file.
//!
//! # Brief overview
//!
//! [`denoise_points`] keeps the points that pass [`in_range`] (the others are not processed),
//! takes the f64 origin of those points ([`origin_of`]), caps isolated points' lists, computes the
//! method's global scalars when it needs them, runs [`cloud::run`] and the outlier threshold from
//! exact sums. The file path's in-memory branch calls it, so an array denoised here and the same
//! points written to a file and run through `qemd denoise` give the same positions bit for bit.
//! The Python binding calls it too.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use glam::DVec3;

use super::{DenoiseSpec, threshold};
use crate::denoise::cloud::{self, CloudRun, Globals};
use crate::denoise::{DenoiseError, PhaseTiming, Stats, origin_of};
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
    let kept: Vec<usize> = (0..positions.len())
        .filter(|&i| in_range(positions[i]))
        .collect();
    let pts: Vec<DVec3> = kept.iter().map(|&i| positions[i]).collect();
    let ties: Vec<u64> = kept.iter().map(|&i| i as u64).collect();
    if pts.is_empty() {
        return Err(DenoiseError::Empty);
    }
    if pts.len() > 1 && pts.iter().all(|p| *p == pts[0]) {
        return Err(DenoiseError::AllIdentical(pts.len()));
    }
    let params = &spec.params;
    let origin = origin_of(&pts);
    let run = CloudRun {
        positions: &pts,
        ties: &ties,
        origin,
        region: None,
        isolation: crate::denoise::isolation::of_cloud(&pts, &ties, origin, params.k()),
        complete: None,
    };
    let globals = if cloud::needs_globals(params) {
        with_cancel(cancel, || cloud::globals_partial(&run, params, |_| true))?
            .0
            .finish()
    } else {
        Globals::default()
    };
    let result = with_cancel(cancel, || cloud::run(&run, params, &globals))?;
    let mut stats = Stats::default();
    result.book(&pts, |_| true, &mut stats);
    stats.points = positions.len() as u64;
    stats.non_finite = (positions.len() - pts.len()) as u64;
    let (sum, sq): (ExactSum, ExactSum) = (
        result.knn_mean.iter().copied().collect(),
        result.knn_mean.iter().map(|m| m * m).collect(),
    );
    Ok(PointsOutput {
        kept,
        threshold: threshold(&sum, &sq, spec.outlier_alpha),
        phases: result.stats.phases.clone(),
        positions: result.positions,
        knn_mean: result.knn_mean,
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
