//! Jobs: the service's state and work, below the HTTP layer.
//!
//! # Brief overview
//!
//! * [`Jobs`] is the cheap, clonable handle the API holds: uploads (streamed to disk, hashed,
//!   sniffed and validated), job submission into a bounded queue, a fixed number of workers, job
//!   status and progress, cancellation, results, and the synchronous denoise path.
//! * [`store::Store`] keeps uploads and jobs in SQLite; files live under the data directory:
//!
//!   ```text
//!    data_dir/qemd.sqlite            uploads and jobs (WAL)
//!    data_dir/uploads/<id>.part      an upload still receiving bytes
//!    data_dir/uploads/<id>.<ext>     a complete upload (ext = its format: ply, laz, …)
//!    data_dir/jobs/<id>/work/        the pipeline's work_dir: plan, spill, tile checkpoints
//!    data_dir/jobs/<id>/result.<ext> the result
//!    data_dir/tmp/                   synchronous requests in flight (emptied at start)
//!   ```
//!
//! * [`bridge`] is the only place where async code hands work to other threads: rayon for the
//!   synchronous path, the blocking pool for SQLite, hashing and job drivers. Nothing below this
//!   module knows about tokio.
//! * A job's run is [`crate::pipeline::run`] with `work_dir` = its directory: tile results are
//!   checkpoints, so a job whose server died (even by SIGKILL) is re-queued at start-up and
//!   resumes with only its unfinished tiles, writing the same bytes. Point clouds larger than
//!   [`Settings::job_tile_points`] always run tiled, which bounds how long a cancellation takes
//!   (the pipeline checks its cancel flag between batches and tiles).
//! * [`preview`] builds the bounded, deterministic before/after previews the web page draws
//!   (`data_dir/jobs/<id>/preview-v1/`).
//! * [`slurm`] runs large jobs as SLURM array jobs when the service is configured with
//!   `executor = "slurm"`: planned here, each phase an array job, progress from the committed
//!   checkpoints, `DELETE` → `scancel`, re-attached after a restart.
//! * [`metrics::Metrics`] holds the Prometheus metrics; [`progress::ProgressView`] what a running
//!   job reports.
//!
//! Ids are random UUIDs (v4), and every lookup is scoped to a tenant: another tenant's upload or
//! job is indistinguishable from one that does not exist.

pub mod bridge;
mod ids;
mod limit;
pub mod metrics;
pub mod preview;
pub mod progress;
mod recovery;
mod requests;
mod run;
mod service;
pub mod slurm;
pub mod store;
mod sync;
mod uploads;

pub use limit::{JOB_TIME_LIMIT, SYNC_TIME_LIMIT, format_limit};
pub use requests::{
    FormatHint, JobInfo, JobRequest, ResultFile, SyncOutput, SyncRequest, canonical_format,
};
pub use service::{Jobs, Settings};
pub use store::{JobRow, JobSpec, Status, Upload};
pub use uploads::{DRAIN_MAX, check_hint, discard};

use thiserror::Error;

use crate::pipeline::PipelineError;

/// Errors of the job service; the API maps each to an HTTP status.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum JobsError {
    /// The database failed.
    #[error("database: {0}")]
    Db(#[from] rusqlite::Error),
    /// A file operation failed.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// No such upload or job (for this tenant).
    #[error("no such {0}")]
    NoSuch(&'static str),
    /// A request field is invalid.
    #[error("{field}: {detail}")]
    Invalid {
        /// The field, as the request spells it (`params.knn`, `output_format`, …).
        field: String,
        /// What is wrong.
        detail: String,
    },
    /// An upload's content is not a valid file of its format.
    #[error("{0}")]
    Rejected(String),
    /// A synchronous run failed; its paths are the request's names (`input`, `result.<format>`).
    /// [`PipelineError::is_input_fault`] tells the input's or the request's fault from the
    /// server's.
    #[error(transparent)]
    Run(PipelineError),
    /// The format is unknown or cannot be told from the content.
    #[error("{0}")]
    UnsupportedFormat(String),
    /// A body or upload is larger than allowed.
    #[error("larger than the limit of {limit} bytes")]
    OverLimit {
        /// The limit in bytes.
        limit: u64,
    },
    /// The resource is in a state that forbids the request.
    #[error("{detail}")]
    WrongState {
        /// What is in the way.
        detail: String,
        /// For a resumable upload, the offset the server has.
        offset: Option<u64>,
    },
    /// The job queue is full.
    #[error("the job queue is full")]
    QueueFull,
    /// Too many synchronous requests at once.
    #[error("too many synchronous requests at once")]
    Busy,
    /// The request body broke off or could not be read.
    #[error("{0}")]
    BodyRead(String),
    /// The server is shutting down.
    #[error("the server is shutting down")]
    ShuttingDown,
    /// A run hit its wall-clock limit and was stopped (issue 15).
    #[error("exceeded the time limit of {lim} ({key})", lim = crate::jobs::limit::format_limit(*.limit))]
    TimeLimit {
        /// The limit.
        limit: std::time::Duration,
        /// The setting that sets it (`job_time_limit`, `sync_time_limit`).
        key: &'static str,
    },
    /// A SLURM command failed (executor `slurm`).
    #[error(transparent)]
    Slurm(#[from] slurm::SlurmError),
    /// Anything else: a bug or an environment failure (never shown to clients).
    #[error("{0}")]
    Internal(String),
}

impl JobsError {
    /// A file operation failed.
    pub fn io(what: impl Into<String>, source: std::io::Error) -> JobsError {
        JobsError::Io {
            what: what.into(),
            source,
        }
    }
}
