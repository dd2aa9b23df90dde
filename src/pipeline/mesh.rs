//! The mesh driver: a mesh runs in memory ([`crate::denoise::denoise`]), since faces need the
//! whole vertex set; stored normals are recomputed.

use super::{Job, PipelineError, Report, normals};
use crate::denoise::{self, Stats, Timer};
use crate::io::{Cloud, IoError};

/// Denoises the mesh `job` names.
///
/// # Errors
/// Read, operator and write failures.
pub(crate) fn run(job: &Job) -> Result<Report, PipelineError> {
    let timer = Timer::start();
    let cloud = Cloud::read(&job.input, job.input_format)?;
    run_cloud(job, cloud, timer, |c| {
        c.write(&job.output, job.output_format)
    })
}

/// Denoises the mesh `cloud`, read for `job` since `timer` started, and writes it with `write`.
///
/// # Errors
/// Operator and write failures.
pub(crate) fn run_cloud(
    job: &Job,
    mut cloud: Cloud,
    mut timer: Timer,
    write: impl FnOnce(&Cloud) -> Result<(), IoError>,
) -> Result<Report, PipelineError> {
    let mut phases = Stats::default();
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
    write(&cloud)?;
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
