//! The plan step: reads the input once ([`crate::pipeline::tiled::plan`]) and freezes the job in
//! the work directory ([`super::frozen`]). Planning a work directory again with the same request
//! changes nothing; a directory that holds another job is refused, never cleared.

use std::path::{Path, PathBuf};

use super::ScaleoutError;
use super::frozen::{FrozenJob, InputId, StoredFormat, VERSION};
use super::url::WorkUrl;
use crate::io::{self, Format};
use crate::pipeline::tiled::{plan as plan_phase, scratch, stitch};
use crate::pipeline::{DenoiseSpec, Job, Progress, RunOptions, bytes_per_point};

/// What to plan.
#[derive(Debug, Clone)]
pub struct PlanRequest {
    /// The input file (a file every task can read; not a stream).
    pub input: PathBuf,
    /// Its format, when given.
    pub input_format: Option<Format>,
    /// The output format, when given (else the input's).
    pub output_format: Option<Format>,
    /// What the run computes (resolved).
    pub spec: DenoiseSpec,
    /// The memory budget each task may use.
    pub memory_budget: u64,
    /// Forced tile size.
    pub tile_points: Option<u64>,
    /// Input records per partition part ([`RunOptions::part_points`]).
    pub part_points: Option<u64>,
    /// Where tasks find the input when it is not `input` itself: a path relative to the work
    /// directory, for a job that carries a copy of its input (an object-store job uploads it
    /// there). `None`: tasks read `input`, which every task must be able to reach.
    pub stored_as: Option<PathBuf>,
    /// Stitch ranges as tasks of their own (a shared file system); `false`: one stitch task
    /// that writes the ranges side by side (an object store, where each range task would
    /// download every result file whole).
    pub stitch_tasks: bool,
}

/// The result of planning.
#[derive(Debug, Clone)]
pub struct Planned {
    /// The frozen job.
    pub job: FrozenJob,
    /// True when the work directory already held this job (nothing was read).
    pub existing: bool,
}

/// Plans `req` into the work directory `work` (created if missing).
///
/// # Errors
/// A bad spec, an input that is a stream, a mesh or unreadable, a work directory that holds
/// another job or cannot be written, the plan pass's errors.
pub fn plan(
    work: &WorkUrl,
    req: &PlanRequest,
    progress: std::sync::Arc<dyn Progress>,
    cancel: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> Result<Planned, ScaleoutError> {
    req.spec
        .validate()
        .map_err(crate::pipeline::PipelineError::from)?;
    let unsupported = |detail: &str| ScaleoutError::Unsupported {
        path: req.input.clone(),
        detail: detail.to_string(),
    };
    if io::is_stdio(&req.input) || io::is_stream_input(&req.input) {
        return Err(unsupported(
            "a scale-out job reads its input once per phase, on any node: give a file (not a \
             stream) every task can read",
        ));
    }
    let input = req
        .input
        .canonicalize()
        .map_err(|e| io::IoError::io(&req.input, e))?;
    let source = io::open(&input, req.input_format)?;
    let info = source.info().clone();
    drop(source);
    let spec = req.spec.for_format(info.format);
    if spec.params.mesh_mode(info.has_faces()) {
        return Err(unsupported(
            "a mesh runs in memory on one node (its k-rings need every face); use qemd denoise",
        ));
    }
    let dir = work.local()?;
    let mut input_id = InputId::of(&input)?;
    let stored = match &req.stored_as {
        Some(rel) if rel.is_absolute() || rel.as_os_str().is_empty() => {
            return Err(unsupported(
                "the input's copy is named relative to the work directory",
            ));
        }
        Some(rel) => {
            // Each task downloads its own copy: only the length identifies it.
            input_id.modified_ns = 0;
            rel.clone()
        }
        None => input.clone(),
    };
    let input_format = req.input_format.map(StoredFormat::from);
    let output_format = StoredFormat::from(req.output_format.unwrap_or(info.format));
    if let Some(e) = existing_job(dir)? {
        let same = e.input == stored
            && e.input_id == input_id
            && e.input_format == input_format
            && e.output_format == output_format
            && e.spec == spec
            && e.memory_budget == req.memory_budget
            && e.tile_points == req.tile_points;
        if same {
            return Ok(Planned {
                job: e,
                existing: true,
            });
        }
        return Err(ScaleoutError::WorkDir {
            path: dir.to_path_buf(),
            detail: "holds another job (another input, input file, format or parameters); plan \
                     into a new work directory, or remove this one"
                .into(),
        });
    }
    std::fs::create_dir_all(dir).map_err(|e| io::IoError::io(dir, e))?;
    let job = Job {
        input: input.clone(),
        output: PathBuf::new(),
        input_format: req.input_format,
        output_format: None,
        spec: spec.clone(),
        trajectory: None,
    };
    let opts = RunOptions {
        memory_budget: req.memory_budget,
        tile_points: req.tile_points,
        part_points: req.part_points,
        work_dir: Some(dir.to_path_buf()),
        progress,
        cancel,
        ..RunOptions::default()
    };
    if let Some(n) = info.len {
        scratch::check_disk(
            &opts,
            n,
            scratch::run_disk_per_point(spec.params.write_normals, info.schema.record_len),
        )?;
    }
    let per_point = bytes_per_point(&spec.params, info.schema.record_len);
    let limits = plan_phase::Limits::new(&opts, per_point);
    let plan = plan_phase::plan(&job, &opts, &info, &limits)?;
    let stitch_ranges = if req.stitch_tasks {
        stitch::ranges(&job, &opts, &info, &plan, output_format.format())?
    } else {
        1
    };
    let frozen = FrozenJob {
        version: VERSION,
        input: stored,
        input_id,
        input_format,
        output_format,
        spec: spec.clone(),
        memory_budget: req.memory_budget,
        tile_points: req.tile_points,
        bytes_per_point: per_point,
        plan,
        stitch_ranges,
    };
    frozen.save(dir)?;
    Ok(Planned {
        job: frozen,
        existing: false,
    })
}

/// The job already frozen in `dir`, if any (an unreadable one is an error: never overwritten).
fn existing_job(dir: &Path) -> Result<Option<FrozenJob>, ScaleoutError> {
    if !dir.join(super::layout::JOB_FILE).exists() {
        return Ok(None);
    }
    FrozenJob::load(dir).map(Some)
}
