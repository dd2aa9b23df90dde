//! A run on bytes in memory: the service's synchronous path hands over the request body and gets
//! the result's bytes back.
//!
//! A cloud (or mesh) whose working set fits the memory budget is read from the bytes
//! ([`crate::io::Input::from_bytes`]), denoised by the in-memory drivers, and written into memory
//! ([`crate::io::AtomicFile::memory`]): **no file is created**. Two cases still need files, and
//! spool the bytes to a temporary directory and run the file path: a point cloud larger than the
//! budget (the tiled path spills to disk) and E57 or COPC output (their writers read back and
//! reorganise what they wrote). Errors name the job's `input` and `output` either way.

use std::time::Instant;

use cpu_time::ProcessTime;

use super::{Job, PipelineError, Report, RunOptions, SpecError};
use super::{bytes_per_point, memory, mesh, peak_rss_bytes, run_file};
use crate::denoise::Timer;
use crate::io::{self, AtomicFile, Cloud, Format, Input};

/// The result of [`run_bytes`].
#[derive(Debug)]
pub struct BytesOutput {
    /// The output file's bytes.
    pub bytes: Vec<u8>,
    /// What happened.
    pub report: Report,
    /// True when the run needed a temporary file (see the [module overview](self)).
    pub spooled: bool,
}

/// Denoises `body`, a whole file of `job.input_format`, into the bytes of a `job.output_format`
/// file. `job.input` and `job.output` are only the names errors and the report give; both
/// formats must be set.
///
/// # Errors
/// As [`super::run`]; a job without both formats.
pub fn run_bytes(
    body: impl AsRef<[u8]> + Send + Sync + 'static,
    job: &Job,
    opts: &RunOptions,
) -> Result<BytesOutput, PipelineError> {
    job.spec.validate()?;
    super::refuse_normals_early(job)?;
    let (Some(input_format), Some(output_format)) = (job.input_format, job.output_format) else {
        return Err(PipelineError::Params(SpecError {
            field: "format",
            detail: "a run on bytes needs both formats".into(),
        }));
    };
    let wall = Instant::now();
    let cpu = ProcessTime::now();
    let input = Input::from_bytes(&job.input, body);
    let again = input.reopener();
    let needs_file = matches!(output_format, Format::E57 | Format::Copc);
    if needs_file || opts.tile_points.is_some() {
        return spooled(input, job, opts);
    }
    // The body is in memory already and bounded by the caller, so the cloud is read before the
    // decision: text formats do not declare their point count.
    let timer = Timer::start();
    opts.progress.phase("read", 0);
    let cloud = Cloud::read_input(input, input_format)?;
    let job = &Job {
        spec: job.spec.for_format(cloud.info.format),
        ..job.clone()
    };
    let mesh = job.spec.params.mesh_mode(cloud.info.has_faces());
    let per_point = bytes_per_point(&job.spec.params, cloud.info.schema.record_len);
    let fits = (cloud.len() as u64).saturating_mul(per_point) <= opts.memory_budget;
    if !mesh && !fits {
        drop(cloud);
        return spooled(again.open()?, job, opts);
    }
    job.spec.check_mesh(mesh)?;
    let (out, slot) = AtomicFile::memory(&job.output);
    let mut out = Some(out);
    let mut take = || out.take().expect("the in-memory drivers create one sink");
    let mut report = if mesh {
        mesh::run_cloud(job, opts, cloud, timer, |c| {
            let sink = io::create_in(
                take(),
                output_format,
                &c.info,
                c.len() as u64,
                &Default::default(),
            )?;
            c.write_to(sink)
        })?
    } else {
        memory::run_cloud(job, opts, cloud, timer, |info, count, options| {
            io::create_in(take(), output_format, info, count, options)
        })?
    };
    report.wall_s = wall.elapsed().as_secs_f64();
    report.cpu_s = cpu.elapsed().as_secs_f64();
    report.peak_rss_bytes = peak_rss_bytes();
    let bytes = slot.take().ok_or_else(|| PipelineError::Report {
        path: job.output.clone(),
        detail: "the output was not committed".into(),
    })?;
    Ok(BytesOutput {
        bytes,
        report,
        spooled: false,
    })
}

/// The file path for bytes that need one: spooled into a temporary directory under
/// `opts.temp_dir`, run, read back; errors and the report name the job's input and output.
fn spooled(mut input: Input, job: &Job, opts: &RunOptions) -> Result<BytesOutput, PipelineError> {
    let base = opts.temp_dir.clone().unwrap_or_else(std::env::temp_dir);
    let temp_err = |e: std::io::Error| PipelineError::TempDir {
        path: base.clone(),
        detail: e.to_string(),
    };
    let dir = tempfile::Builder::new()
        .prefix("qemd-bytes-")
        .tempdir_in(&base)
        .map_err(temp_err)?;
    let ext = |f: Option<Format>| f.map_or("bin", Format::name);
    let in_path = dir.path().join(format!("input.{}", ext(job.input_format)));
    let out_path = dir
        .path()
        .join(format!("output.{}", ext(job.output_format)));
    let mut file = std::fs::File::create(&in_path).map_err(temp_err)?;
    std::io::copy(&mut input, &mut file).map_err(temp_err)?;
    drop(file);
    let on_disk = Job {
        input: in_path.clone(),
        output: out_path.clone(),
        ..job.clone()
    };
    let opts = RunOptions {
        temp_dir: Some(dir.path().to_path_buf()),
        ..opts.clone()
    };
    let rename = |e: PipelineError| {
        e.with_path(&in_path, &job.input)
            .with_path(&out_path, &job.output)
    };
    let mut report = run_file(&on_disk, &opts).map_err(rename)?;
    let bytes =
        std::fs::read(&out_path).map_err(|e| rename(io::IoError::io(&out_path, e).into()))?;
    report.input = job.input.clone();
    report.output = job.output.clone();
    Ok(BytesOutput {
        bytes,
        report,
        spooled: true,
    })
}
