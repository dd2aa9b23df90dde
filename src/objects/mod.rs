//! Object-store work directories for scale-out (feature `s3`): `qemd plan`, `worker`, `finish`
//! and `status` on `s3://bucket/prefix` as on a shared directory, with the same bytes.
//!
//! # Brief overview
//!
//! The pipeline's scale-out commands ([`crate::pipeline::scaleout`]) run on a local directory.
//! For an S3 work directory each command here opens a [`mirror::Mirror`]: it lists the prefix,
//! downloads into a scratch directory the objects its phase reads ([`mirror::wanted`]), runs the
//! pipeline's command on the scratch directory, and uploads what the command wrote — data first,
//! then the files that commit it, each commit a conditional put (`If-None-Match: *`), so a
//! retried, duplicated or killed task never replaces or half-writes a checkpoint. Nothing a task
//! needs stays on a node beyond its scratch directory, which is removed when the task ends.
//!
//! ```text
//!  qemd plan IN --work s3://b/p    uploads IN as input/<name>, then job.json (the commit)
//!  qemd worker --phase P           pull what P reads → run the task → push what it wrote
//!  qemd finish -o OUT              pull → stitch if not committed → push → deliver OUT
//!  qemd status                     the committed objects, listed (results stand in by size)
//! ```
//!
//! A local work directory goes straight to the pipeline's commands. The tokio runtime that
//! `object_store` needs lives in [`store::Store`]; nothing below this layer knows it.
//!
//! Cost: a globals or tiles task downloads every spill file (a tile's halo growth may read any
//! of them), so N tasks move N times the spill; see docs/DECISIONS.md, "Object-store work
//! directories".

pub mod mirror;
pub mod store;

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;

use thiserror::Error;

use crate::io::{Format, IoError};
use crate::pipeline::scaleout::{
    self, FrozenJob, Hooks, Phase, PlanRequest, Planned, ScaleoutError, Status, TaskReport,
    WorkUrl, layout, worker,
};
use mirror::{INPUT_DIR, Mirror, is_base, wanted};
use store::Store;

/// Errors of the object-store layer.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ObjectsError {
    /// The scale-out command failed.
    #[error(transparent)]
    Scaleout(#[from] ScaleoutError),
    /// A local file could not be read or written.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The store refused or failed a request.
    #[error("{url}: {detail}")]
    Store {
        /// The object or prefix.
        url: String,
        /// What went wrong (one line).
        detail: String,
    },
    /// Ctrl-C or SIGTERM during a transfer.
    #[error("cancelled")]
    Cancelled,
}

impl ObjectsError {
    fn store(url: &str, detail: &str) -> ObjectsError {
        ObjectsError::Store {
            url: url.to_string(),
            detail: concise(detail),
        }
    }
}

/// One line of a client error: an S3 error document (`<Code>…</Code><Message>…</Message>`) as
/// `Code: Message (the client's text before the document)`, whitespace collapsed.
fn concise(detail: &str) -> String {
    let one_line = |s: &str| s.split_whitespace().collect::<Vec<_>>().join(" ");
    let tag = |name: &str| -> Option<&str> {
        let open = format!("<{name}>");
        let start = detail.find(&open)? + open.len();
        let len = detail[start..].find(&format!("</{name}>"))?;
        Some(&detail[start..start + len])
    };
    match (tag("Code"), tag("Message"), detail.find("<?xml")) {
        (Some(code), Some(message), Some(doc)) => {
            let before = one_line(&detail[..doc]);
            let before = before.trim_end_matches(':').trim_end();
            format!("{code}: {} ({before})", one_line(message))
        }
        _ => one_line(detail),
    }
}

/// The store and a fresh mirror of the S3 work directory `work` (`None` for a local one).
fn mirror_of(work: &WorkUrl) -> Result<Option<Mirror>, ObjectsError> {
    match work {
        WorkUrl::Local(_) => Ok(None),
        WorkUrl::S3 { bucket, prefix } => {
            let store = Store::open(bucket, prefix, &work.to_string())?;
            Mirror::open(store).map(Some)
        }
    }
}

/// The scratch directory as a work URL.
fn local(m: &Mirror) -> WorkUrl {
    WorkUrl::Local(m.dir().to_path_buf())
}

/// The frozen job of a mirror (after `job.json` is pulled).
fn frozen(m: &Mirror) -> Result<FrozenJob, ObjectsError> {
    FrozenJob::load(m.dir()).map_err(|e| match e {
        ScaleoutError::WorkDir { detail, .. } => ObjectsError::store(m.url(), &detail),
        e => e.into(),
    })
}

/// [`scaleout::plan`] into `work`. For S3 the input is uploaded into the work directory as
/// `input/<file name>` and the job reads that copy, so tasks need nothing but the store.
///
/// # Errors
/// The plan's errors, a failed transfer, a prefix that holds another job.
pub fn plan(work: &WorkUrl, req: &PlanRequest, hooks: &Hooks) -> Result<Planned, ObjectsError> {
    let Some(mut m) = mirror_of(work)? else {
        return Ok(scaleout::plan(
            work,
            req,
            hooks.progress.clone(),
            hooks.cancel.clone(),
        )?);
    };
    let cancelled = || hooks.cancel.load(Ordering::Relaxed);
    let name = req
        .input
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "input".into());
    let stored = format!("{INPUT_DIR}/{name}");
    m.pull(|n| n == layout::JOB_FILE, &cancelled)?;
    // One stitch task: a range task would download every whole result file (the mirror
    // fetches objects, not byte ranges); the one task still writes the ranges side by side.
    let req = PlanRequest {
        stored_as: Some(PathBuf::from(&stored)),
        stitch_tasks: false,
        ..req.clone()
    };
    let planned = scaleout::plan(
        &local(&m),
        &req,
        hooks.progress.clone(),
        hooks.cancel.clone(),
    )
    .map_err(|e| match e {
        ScaleoutError::WorkDir { detail, .. } => ObjectsError::store(m.url(), &detail),
        e => e.into(),
    })?;
    if !planned.existing {
        // The input before the job that names it: a job.json in the store has its input there.
        if m.remote(&stored) != Some(planned.job.input_id.len) {
            m.put_file(&stored, &req.input, &cancelled)?;
        }
        m.push(&cancelled)?;
    }
    Ok(planned)
}

/// [`scaleout::run_task`] on `work`.
///
/// # Errors
/// The task's errors, a failed transfer.
pub fn run_task(
    work: &WorkUrl,
    phase: Phase,
    index: (Option<u64>, Option<u64>),
    env: impl Fn(&str) -> Option<String>,
    hooks: &Hooks,
) -> Result<TaskReport, ObjectsError> {
    let Some(mut m) = mirror_of(work)? else {
        return Ok(scaleout::run_task(work, phase, index, env, hooks)?);
    };
    let cancelled = || hooks.cancel.load(Ordering::Relaxed);
    m.pull(|n| n == layout::JOB_FILE, &cancelled)?;
    let job = frozen(&m)?;
    let task = scaleout::resolve_index(index.0, index.1, job.tasks_of(phase), &env)?;
    let tiles = job.plan.tiles.len();
    let own: Vec<bool> = {
        let mut v = vec![false; tiles];
        for t in worker::assigned(task.index, task.of, tiles) {
            v[t] = true;
        }
        v
    };
    let committed = match phase {
        Phase::Partition => m.remote(crate::tiling::workdir::PARTITION_DONE).is_some(),
        Phase::Stitch => m.remote(layout::STITCH_DONE).is_some(),
        Phase::Globals | Phase::Tiles => false,
    };
    let mine = match phase {
        Phase::Partition => {
            worker::assigned(task.index, task.of, job.plan.parts() as usize).count()
        }
        Phase::Stitch => {
            worker::assigned(task.index, task.of, job.tasks_of(phase) as usize).count()
        }
        _ => usize::from(task.index == 0),
    } as u64;
    if committed && mine > 0 {
        // A phase already committed in the store: nothing to download.
        return Ok(TaskReport {
            phase,
            task,
            assigned: mine,
            done: 0,
            skipped: mine,
            wall_s: 0.0,
        });
    }
    let start = std::time::Instant::now();
    let partitioned = m.remote(crate::tiling::workdir::PARTITION_DONE).is_some();
    m.pull(
        |n| {
            wanted(phase, n, &|t| own.get(t).copied().unwrap_or(false))
                && !(partitioned && mirror::is_part_grid(n))
        },
        &cancelled,
    )?;
    let r = scaleout::run_task(&local(&m), phase, index, env, hooks)?;
    m.push(&cancelled)?;
    Ok(TaskReport {
        wall_s: start.elapsed().as_secs_f64(),
        ..r
    })
}

/// [`scaleout::finish`] on `work`: for S3 the stitch (when not committed) runs here and its
/// output is uploaded and committed like a stitch task's.
///
/// # Errors
/// The stitch's errors, a failed transfer, an output that cannot be written.
pub fn finish(
    work: &WorkUrl,
    output: &Path,
    format: Option<Format>,
    hooks: &Hooks,
) -> Result<scaleout::Finished, ObjectsError> {
    let Some(mut m) = mirror_of(work)? else {
        return Ok(scaleout::finish(work, output, format, hooks)?);
    };
    let cancelled = || hooks.cancel.load(Ordering::Relaxed);
    m.pull(|n| n == layout::JOB_FILE, &cancelled)?;
    let job = frozen(&m)?;
    let job_format = job.output_format.format();
    let out_name = layout::output_path(Path::new(""), job_format)
        .to_string_lossy()
        .into_owned();
    let stitched = m.remote(layout::STITCH_DONE).is_some() && m.remote(&out_name).is_some();
    let same_format =
        format.map_or_else(|| Format::from_path(output).ok(), Some) == Some(job_format);
    if stitched && same_format {
        // Committed: the output is all it delivers.
        let done = [layout::STITCH_DONE, out_name.as_str()];
        m.pull(|n| is_base(n) || done.contains(&n), &cancelled)?;
    } else {
        m.pull(|n| wanted(Phase::Stitch, n, &|_| true), &cancelled)?;
    }
    let f = scaleout::finish(&local(&m), output, format, hooks)?;
    m.push(&cancelled)?;
    Ok(f)
}

/// The frozen job of `work` (S3: `job.json` alone is downloaded).
///
/// # Errors
/// No plan in the work directory, a failed transfer.
pub fn job(work: &WorkUrl) -> Result<FrozenJob, ObjectsError> {
    let Some(mut m) = mirror_of(work)? else {
        return Ok(FrozenJob::load(work.local()?)?);
    };
    m.pull(|n| n == layout::JOB_FILE, &|| false)?;
    frozen(&m)
}

/// [`scaleout::status`] of `work`, from the committed objects (S3: listed, the small ones read).
///
/// # Errors
/// No plan in the work directory, a failed listing.
pub fn status(work: &WorkUrl) -> Result<Status, ObjectsError> {
    let Some(mut m) = mirror_of(work)? else {
        return Ok(scaleout::status(work)?);
    };
    let never = || false;
    m.pull(
        |n| {
            (n.ends_with(".json") && !n.ends_with(crate::tiling::workdir::OCCUPANCY_FILE))
                || n == crate::tiling::workdir::PARTITION_DONE
        },
        &never,
    )?;
    m.stand_ins(|n| n.ends_with(".res") || n.starts_with("output."))?;
    frozen(&m)?;
    let s = scaleout::status(&local(&m))?;
    Ok(Status {
        work: work.to_string(),
        ..s
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn an_s3_error_document_reads_as_code_and_message() {
        let raw = "Error performing GET http://h/b in 2ms - Server returned non-2xx status code: \
                   404 Not Found: <?xml version=\"1.0\"?> <Error><Code>NoSuchBucket</Code>\
                   <Message>The specified bucket\n does not exist</Message></Error>";
        assert_eq!(
            super::concise(raw),
            "NoSuchBucket: The specified bucket does not exist (Error performing GET http://h/b \
             in 2ms - Server returned non-2xx status code: 404 Not Found)"
        );
        assert_eq!(super::concise("refused\n  twice"), "refused twice");
    }
}
