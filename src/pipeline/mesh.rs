//! The mesh driver: a mesh runs in memory ([`crate::denoise::denoise`]), since faces need the
//! whole vertex set; stored normals are recomputed.

use super::{Job, PipelineError, Report, normals};
use crate::denoise::{self, Stats, Timer};
use crate::io::Cloud;

/// Denoises the mesh `job` names.
///
/// # Errors
/// Read, operator and write failures.
pub(crate) fn run(job: &Job) -> Result<Report, PipelineError> {
    let mut phases = Stats::default();
    let mut timer = Timer::start();
    let mut cloud = Cloud::read(&job.input, job.input_format)?;
    timer.lap("read", &mut phases);
    let out = denoise::denoise(&cloud.positions, cloud.faces(), &job.spec.params)
        .map_err(|e| PipelineError::denoise(&job.input, e))?;
    let mut stats = out.stats;
    phases.merge(&Stats {
        phases: std::mem::take(&mut stats.phases),
        ..Stats::default()
    });
    cloud.positions = out.positions;
    let normals = normals::recompute_mesh(&mut cloud);
    timer = Timer::start();
    cloud.write(&job.output, job.output_format)?;
    timer.lap("write", &mut phases);
    let mut r = Report::empty(job, "mesh");
    r.points_in = cloud.len() as u64;
    r.points_out = cloud.len() as u64;
    r.faces = cloud.faces().map_or(0, |f| f.len() as u64);
    r.normals = normals;
    r.stats = stats;
    r.phases = phases.phases;
    Ok(r)
}
