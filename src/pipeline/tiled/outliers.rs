//! Phase 5, **outlier threshold**: `mean + alpha·σ` of the k-NN mean distance over the whole
//! cloud, from the tiles' exact sums; when outliers are removed, also how many, so the stitch
//! can declare the output's point count before writing it.

use crate::geometry::ExactSum;
use crate::pipeline::assemble::threshold as mean_plus_alpha_sigma;
use crate::pipeline::{Job, OutlierMode, PipelineError};
use crate::tiling::plan::Plan;
use crate::tiling::spill::for_each_result;
use crate::tiling::workdir::WorkDir;

/// The outlier threshold of a run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Threshold {
    /// A point whose k-NN mean distance is above it is an outlier.
    pub value: f64,
    /// Points above it, counted only when they are removed ([`OutlierMode::Remove`]).
    pub removed: u64,
}

/// The threshold of `job` from the sums of the statistic and its square (the tiles phase's
/// [`super::tiles::Tiles::knn_mean`]), counting the outliers in `work`'s result files when they
/// are removed.
///
/// # Errors
/// Result read failures.
pub fn threshold(
    job: &Job,
    plan: &Plan,
    work: &WorkDir,
    (sum, sq): &(ExactSum, ExactSum),
) -> Result<Threshold, PipelineError> {
    let tiling_err = |e| PipelineError::tiling(&job.input, e);
    let value = mean_plus_alpha_sigma(sum, sq, job.spec.outlier_alpha);
    let mut removed = 0u64;
    if job.spec.outliers == OutlierMode::Remove {
        let normals = job.spec.params.write_normals;
        for_each_result(work.path(), plan.tiles.len(), normals, |r| {
            removed += u64::from(r.knn_mean > value);
        })
        .map_err(tiling_err)?;
    }
    Ok(Threshold { value, removed })
}
