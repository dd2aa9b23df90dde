//! Streaming the input batch by batch (the tiled path reads it once per pass), and the options
//! every sink of a run is created with.

use super::{Job, OutlierMode, PipelineError, RunOptions};
use crate::io::{self, BATCH, Extras, SinkOptions, Source};
use crate::points::{PointBatch, Rounding};

/// The sink options of `job`'s output.
pub(crate) fn sink_options(job: &Job, opts: &RunOptions) -> SinkOptions {
    SinkOptions {
        noise_flag: job.spec.outliers == OutlierMode::Classify,
        normals: job.spec.params.write_normals,
        temp_dir: opts.temp_dir.clone(),
        body: false,
        // The bounds the operator put on every move hold in the file.
        rounding: Rounding::NoLonger,
    }
}

/// Streams every batch of the job's input through `f`, with cancellation checks and progress.
pub(crate) fn stream(
    job: &Job,
    opts: &RunOptions,
    mut f: impl FnMut(&PointBatch) -> Result<(), PipelineError>,
) -> Result<Extras, PipelineError> {
    let mut src: Box<dyn Source> = io::open(&job.input, job.input_format)?;
    let mut batch = PointBatch::with_capacity(src.info().schema.record_len, BATCH);
    let mut done = 0u64;
    while src.read_batch(&mut batch, BATCH)? > 0 {
        opts.check_cancel()?;
        f(&batch)?;
        done += batch.len() as u64;
        opts.progress.advance(done);
    }
    Ok(src.finish()?)
}

/// Streams the points of `range` (record numbers) of the job's input through `f`, with
/// cancellation checks (progress is the caller's: ranges run side by side), for a format that
/// can seek ([`Source::seek_point`]); `Ok(false)` without reading when it cannot.
pub(crate) fn stream_range(
    job: &Job,
    opts: &RunOptions,
    range: std::ops::Range<u64>,
    mut f: impl FnMut(&PointBatch) -> Result<(), PipelineError>,
) -> Result<bool, PipelineError> {
    let mut src: Box<dyn Source> = io::open(&job.input, job.input_format)?;
    if !src.seek_point(range.start)? {
        return Ok(false);
    }
    let mut batch = PointBatch::with_capacity(src.info().schema.record_len, BATCH);
    let mut at = range.start;
    while at < range.end {
        let max = usize::try_from(range.end - at).map_or(BATCH, |left| left.min(BATCH));
        let n = src.read_batch(&mut batch, max)?;
        if n == 0 {
            break;
        }
        opts.check_cancel()?;
        f(&batch)?;
        at += n as u64;
    }
    Ok(true)
}
