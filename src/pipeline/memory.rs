//! The in-memory driver: a point cloud whose working set fits the memory budget is read whole,
//! denoised as one region without a boundary ([`crate::denoise::cloud::run_all`], the kernel the
//! tiled path runs per tile), and written batch by batch.
//!
//! The input's records are held once: the read cloud's buffers become the assembler's input and
//! the output is assembled into one reused batch of [`BATCH`] points, so the working set is what
//! [`super::bytes_per_point`] counts (one record per point).

use glam::DVec3;

use super::assemble::{Assembler, threshold};
use super::classes::Selection;
use super::stream::sink_options;
use super::{Job, PipelineError, Report, RunOptions};
use crate::denoise::cloud;
use crate::denoise::{DenoiseError, Stats, Timer};
use crate::geometry::ExactSum;
use crate::io::{self, BATCH, Cloud, IoError, Sink, SinkOptions, SourceInfo};
use crate::neighbours::with_cancel;
use crate::points::{PointBatch, in_range};

/// [`DenoiseError::Empty`] without a point to process, [`DenoiseError::AllIdentical`] when every
/// one is at the same position (as the tiled path's plan refuses them).
pub(super) fn check_points(positions: &[DVec3]) -> Result<(), DenoiseError> {
    let mut finite = positions.iter().filter(|p| in_range(**p));
    let Some(first) = finite.next() else {
        return Err(DenoiseError::Empty);
    };
    let (mut n, mut same) = (1usize, true);
    for p in finite {
        n += 1;
        same &= p == first;
    }
    if n > 1 && same {
        return Err(DenoiseError::AllIdentical(n));
    }
    Ok(())
}

/// The beam of every point from the trajectory at `path`, matched by each record's time
/// ([`io::trajectory`]); zero for a point outside the trajectory's time span.
///
/// # Errors
/// An unreadable or malformed trajectory; an input without a time field.
fn trajectory_beams(
    job: &Job,
    path: &std::path::Path,
    info: &SourceInfo,
    positions: &[DVec3],
    records: &[u8],
) -> Result<Vec<DVec3>, PipelineError> {
    let trajectory = io::trajectory::Trajectory::read(path)?;
    let schema = &info.schema;
    let field = io::trajectory::TimeField::of(schema)
        .ok_or_else(|| io::trajectory::no_time_field(&job.input))?;
    let len = schema.record_len.max(1);
    Ok(positions
        .iter()
        .zip(records.chunks_exact(len))
        .map(|(&p, r)| {
            trajectory
                .position_at(field.get(schema, r))
                .map_or(DVec3::ZERO, |o| crate::denoise::beams::direction(p, o))
        })
        .collect())
}

/// Denoises the point cloud `job` names in memory.
///
/// # Errors
/// Read, operator and write failures, cancellation.
pub(crate) fn run(job: &Job, opts: &RunOptions) -> Result<Report, PipelineError> {
    let timer = Timer::start();
    opts.progress.phase("read", 0);
    let cloud = Cloud::read(&job.input, job.input_format)?;
    run_cloud(job, opts, cloud, timer, |info, count, options| {
        io::create_with(&job.output, job.output_format, info, count, options)
    })
}

/// Denoises `cloud`, read for `job` since `timer` started, and writes it to the sink `create`
/// makes (from the input's layout, the number of points to write and the sink options).
///
/// # Errors
/// Operator and write failures, cancellation.
pub(crate) fn run_cloud(
    job: &Job,
    opts: &RunOptions,
    cloud: Cloud,
    mut timer: Timer,
    create: impl FnOnce(&SourceInfo, u64, &SinkOptions) -> Result<Box<dyn Sink>, IoError>,
) -> Result<Report, PipelineError> {
    let mut phases = Stats::default();
    let Cloud {
        info,
        positions,
        records,
        extras,
    } = cloud;
    timer.lap("read", &mut phases);
    opts.check_cancel()?;
    let denoise_err = |e| PipelineError::denoise(&job.input, e);
    check_points(&positions).map_err(denoise_err)?;
    opts.progress.phase("denoise", 1);
    let held: Option<Vec<bool>> = Selection::of(job, &info)?.map(|s| {
        records
            .chunks_exact(info.schema.record_len.max(1))
            .map(|r| s.held(r))
            .collect()
    });
    let beams = match &job.trajectory {
        Some(path) => Some(trajectory_beams(job, path, &info, &positions, &records)?),
        None => None,
    };
    let result = with_cancel(&opts.cancel, || {
        let per = cloud::PerPoint {
            held: held.as_deref(),
            beams: beams.as_deref(),
        };
        cloud::run_all_with(&positions, &job.spec.params, per)
    })
    .map_err(denoise_err)?;
    drop(held);
    let mut stats = result.stats;
    phases.merge(&Stats {
        phases: std::mem::take(&mut stats.phases),
        ..Stats::default()
    });
    opts.progress.advance(1);
    opts.check_cancel()?;
    timer = Timer::start();

    let n = positions.len();
    let input = PointBatch {
        start: 0,
        positions,
        records,
        record_len: info.schema.record_len,
        flags: Vec::new(),
        normals: Vec::new(),
    };
    let finite = |i: usize| in_range(input.positions[i]);
    let (mut sum, mut sq) = (ExactSum::new(), ExactSum::new());
    for m in (0..n).filter(|&i| finite(i)).map(|i| result.knn_mean[i]) {
        sum.add(m);
        sq.add(m * m);
    }
    let asm = Assembler::new(
        &info,
        job.spec.outliers,
        threshold(&sum, &sq, job.spec.outlier_alpha),
    )
    .writing_normals(job.spec.params.write_normals);
    let normal = |i: usize| result.normals.as_ref().map(|n| n[i]);
    let outcome = |i: usize| finite(i).then(|| (result.positions[i], result.knn_mean[i]));
    let count = (0..n)
        .filter(|&i| asm.writes(outcome(i).map(|(_, m)| m)))
        .count() as u64;
    opts.progress.phase("write", count);
    let mut sink = create(&info, count, &sink_options(job, opts))?;
    let mut out = PointBatch::with_capacity(input.record_len, BATCH.min(n));
    let (mut found, mut written) = (0u64, 0u64);
    for i in 0..n {
        found += asm.push(&input, i, outcome(i), normal(i), &mut out) as u64;
        if out.len() == BATCH {
            sink.write_batch(&out)?;
            written += out.len() as u64;
            out.clear(written);
        }
    }
    if !out.is_empty() {
        sink.write_batch(&out)?;
        written += out.len() as u64;
    }
    sink.finish(&extras)?;
    timer.lap("write", &mut phases);

    let mut r = Report::empty(job, "points");
    r.normals = asm.normals_action();
    r.points_in = n as u64;
    r.points_out = written;
    r.dropped_non_finite = if asm.keep_non_finite {
        0
    } else {
        stats.non_finite
    };
    r.outliers_found = found;
    r.stats = stats;
    r.phases = phases.phases;
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_to_process_and_one_position_are_refused() {
        let nan = DVec3::splat(f64::NAN);
        assert_eq!(check_points(&[]), Err(DenoiseError::Empty));
        assert_eq!(check_points(&[nan, nan]), Err(DenoiseError::Empty));
        assert_eq!(
            check_points(&[DVec3::ONE, nan, DVec3::ONE]),
            Err(DenoiseError::AllIdentical(2))
        );
        assert_eq!(check_points(&[DVec3::ONE]), Ok(()));
        assert_eq!(check_points(&[DVec3::ONE, DVec3::X]), Ok(()));
    }
}
