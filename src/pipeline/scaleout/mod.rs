//! Scale-out: a tiled run as **indexed tasks** that any engine handing out an index can run (a
//! SLURM array job, a Kubernetes Indexed Job, an AWS Batch array job), with the same bytes as
//! `qemd denoise` on one node.
//!
//! # Brief overview
//!
//! A job is a **work directory** ([`WorkUrl`]; a local path or `file://` URL for now). Planning
//! ([`plan::plan`]) freezes everything a task needs in it ([`frozen::FrozenJob`]: the input, the
//! formats, the resolved spec, the memory budget, the tile size and the plan), so workers take no
//! parameters. Then the phases of the tiled driver ([`crate::pipeline::tiled`]) run as tasks:
//!
//! ```text
//!  phase       tasks          task I of N does                     commits
//!  partition   parts          part p's records, p ≡ I mod N        part_<p>/ (spill files, part.json),
//!                                                                   then spill.done
//!  globals     tiles or 0     tile t's partial sums, t ≡ I mod N   globals_<t>.json
//!  tiles       tiles          tile t, t ≡ I mod N                  tile_<t>.res, tile_<t>.json
//!  stitch      ranges or 1    range r's body, r ≡ I mod N; the     body_<r>.bin, body_<r>.json,
//!                             output once all are (one range: I=0) output.<ext>, stitch.json
//!  finish      (a command)    stitch if needed, deliver to -o      the output file
//! ```
//!
//! Each task is **idempotent**: it skips what is committed and commits each result atomically
//! (temp + rename), so a duplicated, retried or killed task changes nothing. The stitch holds an
//! exclusive lock on the work directory's `stitch.lock`, and each partition part on
//! `partition_<p>.lock`, so a duplicate waits and then finds the work done. The task that
//! commits the last part commits the partition (`spill.done`); when none saw every part (an
//! object store lists once per task), the first globals or tiles task does. A task's index comes from its flags or its engine ([`index`]).
//! Progress is read from the committed files alone ([`status`]).
//!
//! The partition has one task per part ([`crate::tiling::plan::Plan::part_range`]: ranges of
//! input records, for formats that can seek to a record; one part otherwise). The stitch has one
//! task per part too when the output can take its points as bodies ([`crate::io::Sink`]'s
//! bodies; [`FrozenJob::stitch_ranges`]), else one: each range's body is committed on its own,
//! and the task that finds them all committed assembles the output (else `finish` does).

pub mod finish;
pub mod frozen;
pub mod index;
pub mod layout;
pub mod lock;
pub mod plan;
pub mod status;
pub mod url;
pub mod worker;

use std::path::PathBuf;

use thiserror::Error;

use super::PipelineError;
use crate::io::IoError;

pub use finish::{Finished, finish, summary};
pub use frozen::FrozenJob;
pub use index::{TaskIndex, resolve_index};
pub use plan::{PlanRequest, Planned, plan};
pub use status::{PhaseStatus, Status, status};
pub use url::WorkUrl;
pub use worker::{Hooks, TaskReport, run_task};

/// Where a service job runs (the `executor` key of `qemd serve`'s configuration, and each job's
/// choice, frozen at submission): on the service's own node, or as SLURM array jobs of the
/// phases below (`crate::jobs`, feature `service`).
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Executor {
    /// In the service's process.
    #[default]
    Local,
    /// As SLURM array jobs, one per phase.
    Slurm,
}

impl Executor {
    /// The name, as configured and reported.
    pub fn name(self) -> &'static str {
        match self {
            Executor::Local => "local",
            Executor::Slurm => "slurm",
        }
    }
}

/// A phase that runs as tasks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Phase {
    /// The spill pass over the input.
    Partition,
    /// The global scalars' partial sums per tile (methods that need them).
    Globals,
    /// The operator on each tile.
    Tiles,
    /// The output, from the input and the tiles' results.
    Stitch,
}

impl Phase {
    /// The phases in the order they run.
    pub const ALL: [Phase; 4] = [
        Phase::Partition,
        Phase::Globals,
        Phase::Tiles,
        Phase::Stitch,
    ];

    /// The lower-case name (as on the command line).
    pub fn name(self) -> &'static str {
        match self {
            Phase::Partition => "partition",
            Phase::Globals => "globals",
            Phase::Tiles => "tiles",
            Phase::Stitch => "stitch",
        }
    }
}

impl std::fmt::Display for Phase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Errors of the scale-out commands.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ScaleoutError {
    /// A phase of the run failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// A file of the work directory could not be read or written.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The work directory's URL cannot be used.
    #[error("{url}: {detail}")]
    Url {
        /// The URL as given.
        url: String,
        /// What is wrong.
        detail: String,
    },
    /// The work directory holds no plan, another job, or a plan of another version.
    #[error("{path}: {detail}", path = .path.display())]
    WorkDir {
        /// The work directory.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// The input is not the file the job was planned on.
    #[error("{path}: {detail}", path = .path.display())]
    InputChanged {
        /// The input.
        path: PathBuf,
        /// What changed.
        detail: String,
    },
    /// A phase ran before the one it needs was complete.
    #[error("{path}: the {phase} phase needs {detail}", path = .path.display())]
    NotReady {
        /// The work directory.
        path: PathBuf,
        /// The phase asked for.
        phase: Phase,
        /// What is missing.
        detail: String,
    },
    /// A task's index cannot be told or is out of range.
    #[error("task index: {0}")]
    Index(String),
    /// The request cannot run as scale-out tasks.
    #[error("{path}: {detail}", path = .path.display())]
    Unsupported {
        /// The input.
        path: PathBuf,
        /// Why.
        detail: String,
    },
}
