//! The service's SLURM executor (`executor = "slurm"`): a point cloud of at least
//! [`SlurmSettings::min_points`] points is planned by the service in the job's work directory
//! (the `qemd plan` code path, [`crate::pipeline::scaleout::plan`]) and each phase with tasks is
//! submitted as one SLURM array job, chained with `--dependency=afterok`; each task runs
//! `qemd worker --work DIR --phase P`. The service then polls: `squeue` for the tasks' states,
//! the work directory's committed checkpoints for progress (the code of `qemd status`), and
//! when the stitch is committed it runs `finish` into the job's result.
//!
//! ```text
//!  worker slot:  plan ──▶ sbatch partition ─▶ sbatch globals ─▶ sbatch tiles ─▶ sbatch stitch
//!                          (each id stored in the job's row before the next is submitted)
//!  monitor:      every slurm_poll_interval: squeue, then the committed checkpoints
//!                  stitch committed ─────────────▶ finish ─▶ successful
//!                  a task failed / never runnable ▶ scancel the rest ─▶ failed (the phase named)
//!                  tasks alive ──────────────────▶ progress from the checkpoints; wait
//!                  nothing alive, not committed ─▶ sacct (if kept) ─▶ resubmit what is not
//!                                                  committed (at most MAX_RESUBMITS times)
//! ```
//!
//! * [`client`]: the commands, blocking, bounded, parsed ([`SlurmError`] for anything else).
//! * [`verdict`]: what the states and checkpoints mean (pure, unit-tested).
//! * `driver.rs`: the async side (planning, submission, the monitor task, `DELETE`, restarts).
//!
//! A monitor holds no worker slot: a job on the cluster does not keep the next local job
//! waiting. A restarted service re-attaches to the SLURM jobs recorded in the job's row.

pub mod client;
mod driver;

use std::path::PathBuf;
use std::time::Duration;

use thiserror::Error;

pub use client::{Client, Submit, TaskState};

use crate::pipeline::scaleout::{Phase, Status};

/// How many times a job whose SLURM jobs vanished without committing its result is submitted
/// again before it fails.
pub const MAX_RESUBMITS: u32 = 2;

/// The SLURM executor's settings (`slurm_*` in the configuration).
#[derive(Debug, Clone)]
pub struct SlurmSettings {
    /// Point clouds with at least this many points go to SLURM.
    pub min_points: u64,
    /// The `qemd` binary the tasks run (`None`: the service's own executable).
    pub worker: Option<PathBuf>,
    /// `--partition`.
    pub partition: Option<String>,
    /// `--account`.
    pub account: Option<String>,
    /// `--cpus-per-task`, and each worker's `--threads`.
    pub cpus_per_task: u32,
    /// Most array tasks of one phase.
    pub max_tasks: u64,
    /// More `sbatch` options.
    pub sbatch_args: Vec<String>,
    /// How often a job's tasks and checkpoints are looked at.
    pub poll_interval: Duration,
    /// The client commands.
    pub client: Client,
}

impl Default for SlurmSettings {
    fn default() -> Self {
        SlurmSettings {
            min_points: 20_000_000,
            worker: None,
            partition: None,
            account: None,
            cpus_per_task: 4,
            max_tasks: 64,
            sbatch_args: Vec::new(),
            poll_interval: Duration::from_secs(5),
            client: Client::default(),
        }
    }
}

/// Errors of the SLURM client; each one line.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SlurmError {
    /// A command could not be started (not installed, not on `PATH`).
    #[error("{cmd}: cannot run: {source}")]
    Spawn {
        /// The command.
        cmd: &'static str,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A command did not answer in time (and was killed).
    #[error("{cmd}: no answer within {secs} s")]
    Timeout {
        /// The command.
        cmd: &'static str,
        /// The bound.
        secs: u64,
    },
    /// A command failed.
    #[error("{cmd} failed: {detail}")]
    Failed {
        /// The command.
        cmd: &'static str,
        /// Its error output, on one line.
        detail: String,
    },
    /// A command printed what it should not.
    #[error("{cmd}: {detail}")]
    Output {
        /// The command.
        cmd: &'static str,
        /// What was wrong.
        detail: String,
    },
    /// The cluster keeps no accounting database (`sacct` has nothing).
    #[error("sacct: {0}")]
    NoAccounting(String),
}

/// One array job the service submitted.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ArrayJob {
    /// The phase its tasks run.
    pub phase: Phase,
    /// SLURM's job id.
    pub id: String,
    /// Its array tasks.
    pub tasks: u64,
}

/// What a job has on the cluster (stored in its row, as JSON, after every `sbatch`).
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct SlurmRecord {
    /// The array jobs of the current submission, in phase order.
    pub jobs: Vec<ArrayJob>,
    /// True once every phase of the current submission is submitted.
    pub complete: bool,
    /// Array jobs of earlier submissions (ended or cancelled).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub earlier: Vec<ArrayJob>,
    /// Times the job was submitted again after its SLURM jobs vanished.
    #[serde(default)]
    pub resubmits: u32,
    /// `--cpus-per-task` of the tasks.
    #[serde(default)]
    pub cpus_per_task: u32,
}

impl SlurmRecord {
    /// The ids of the current submission.
    pub fn ids(&self) -> Vec<String> {
        self.jobs.iter().map(|j| j.id.clone()).collect()
    }

    /// Every id ever submitted for the job.
    pub fn all_ids(&self) -> Vec<String> {
        self.earlier
            .iter()
            .chain(&self.jobs)
            .map(|j| j.id.clone())
            .collect()
    }
}

/// The SLURM job name of every array job of service job `id` (`scancel --name` finds them all,
/// also one submitted just before a crash left it unrecorded).
pub fn job_name(id: &str) -> String {
    format!("qemd-{id}")
}

/// What a poll found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// The stitch is committed: the result can be delivered.
    Done,
    /// Tasks are pending or running.
    Wait,
    /// A task failed or can never run.
    Failed {
        /// The phase.
        phase: Phase,
        /// The task (`<array>_<index>`).
        task: String,
        /// One line: what happened.
        reason: String,
    },
    /// No task is alive and the stitch is not committed: the jobs vanished (purged, a cluster
    /// reset) or ended without committing.
    Idle,
}

/// Reads the tasks' `states` (taken before `status`: a task commits before it ends, so what is
/// not committed after every task ended never will be) against the job's `record`.
pub fn verdict(record: &SlurmRecord, states: &[TaskState], status: &Status) -> Verdict {
    if status.next.is_none() {
        return Verdict::Done;
    }
    let mut alive = false;
    for job in &record.jobs {
        for s in states.iter().filter(|s| s.array == job.id) {
            let never = s.reason == "DependencyNeverSatisfied";
            if client::failed(&s.state) || never {
                let reason = if never {
                    format!(
                        "the {} phase never ran on SLURM: task {} is {} because an earlier \
                         phase failed (DependencyNeverSatisfied)",
                        job.phase,
                        s.id(),
                        s.state
                    )
                } else {
                    format!(
                        "the {} phase failed on SLURM: task {} {}",
                        job.phase,
                        s.id(),
                        s.state
                    )
                };
                return Verdict::Failed {
                    phase: job.phase,
                    task: s.id(),
                    reason,
                };
            }
            alive |= !client::TERMINAL.contains(&s.state.as_str());
        }
    }
    if alive { Verdict::Wait } else { Verdict::Idle }
}

/// The phases of `status` with tasks that are not complete, in order, and their task counts.
pub fn pending_phases(status: &Status) -> Vec<(Phase, u64)> {
    status
        .phases
        .iter()
        .filter(|p| p.tasks > 0 && !p.complete())
        .map(|p| (p.phase, p.tasks))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::scaleout::PhaseStatus;

    fn status(committed: [u64; 4]) -> Status {
        let units = [1, 4, 4, 1];
        let phases: Vec<PhaseStatus> = Phase::ALL
            .iter()
            .zip(units.iter().zip(committed))
            .map(|(&phase, (&units, committed))| PhaseStatus {
                phase,
                tasks: units,
                units,
                committed,
            })
            .collect();
        let next = phases.iter().find(|p| !p.complete()).map(|p| p.phase);
        Status {
            work: "w".into(),
            input: "i".into(),
            points: 10,
            tiles: 4,
            phases,
            next,
        }
    }

    fn record() -> SlurmRecord {
        let jobs = Phase::ALL
            .iter()
            .enumerate()
            .map(|(i, &phase)| ArrayJob {
                phase,
                id: (10 + i).to_string(),
                tasks: if i % 3 == 0 { 1 } else { 2 },
            })
            .collect();
        SlurmRecord {
            jobs,
            complete: true,
            ..SlurmRecord::default()
        }
    }

    fn st(array: &str, task: &str, state: &str, reason: &str) -> TaskState {
        TaskState {
            array: array.into(),
            task: task.into(),
            state: state.into(),
            reason: reason.into(),
        }
    }

    #[test]
    fn verdicts() {
        let r = record();
        // Committed wins over whatever SLURM says.
        assert_eq!(verdict(&r, &[], &status([1, 4, 4, 1])), Verdict::Done);
        let running = [
            st("10", "0", "COMPLETED", "None"),
            st("11", "0", "RUNNING", "None"),
            st("11", "1", "COMPLETED", "None"),
            st("12", "0", "PENDING", "Dependency"),
            st("13", "0", "PENDING", "Dependency"),
        ];
        assert_eq!(verdict(&r, &running, &status([1, 3, 0, 0])), Verdict::Wait);
        // A failed tiles task names its phase; the stitch's cancellation after it does not
        // hide it.
        let failed = [
            st("12", "1", "FAILED", "NonZeroExitCode"),
            st("12", "0", "COMPLETED", "None"),
            st("13", "0", "CANCELLED", "DependencyNeverSatisfied"),
        ];
        match verdict(&r, &failed, &status([1, 4, 2, 0])) {
            Verdict::Failed {
                phase,
                task,
                reason,
            } => {
                assert_eq!((phase, task.as_str()), (Phase::Tiles, "12_1"));
                assert_eq!(reason, "the tiles phase failed on SLURM: task 12_1 FAILED");
            }
            v => panic!("{v:?}"),
        }
        // The failed task already purged: the stitch that can never run says why.
        let never = [st("13", "0", "PENDING", "DependencyNeverSatisfied")];
        match verdict(&r, &never, &status([1, 4, 2, 0])) {
            Verdict::Failed { phase, reason, .. } => {
                assert_eq!(phase, Phase::Stitch);
                assert!(reason.contains("never ran"), "{reason}");
            }
            v => panic!("{v:?}"),
        }
        // Everything ended (or vanished) without the stitch committed.
        let ended = [st("13", "0", "COMPLETED", "None")];
        assert_eq!(verdict(&r, &ended, &status([1, 4, 4, 0])), Verdict::Idle);
        assert_eq!(verdict(&r, &[], &status([1, 4, 1, 0])), Verdict::Idle);
        // States of other jobs (an earlier submission) are not this submission's.
        let other = [st("99", "0", "FAILED", "None")];
        assert_eq!(verdict(&r, &other, &status([1, 4, 1, 0])), Verdict::Idle);
    }

    #[test]
    fn pending_phases_skip_the_committed_and_the_empty() {
        let mut s = status([1, 4, 2, 0]);
        assert_eq!(
            pending_phases(&s),
            vec![(Phase::Tiles, 4), (Phase::Stitch, 1)]
        );
        s.phases[1].tasks = 0;
        s.phases[1].units = 0;
        s.phases[1].committed = 0;
        s = Status { ..s };
        assert_eq!(pending_phases(&status([0, 0, 0, 0])).len(), 4);
        assert!(!pending_phases(&s).iter().any(|p| p.0 == Phase::Globals));
    }

    #[test]
    fn records_round_trip() {
        let r = record();
        let text = serde_json::to_string(&r).unwrap();
        assert!(!text.contains("earlier"));
        assert_eq!(serde_json::from_str::<SlurmRecord>(&text).unwrap(), r);
        let mut r2 = r.clone();
        r2.earlier = r.jobs.clone();
        assert_eq!(r2.all_ids().len(), 8);
        assert_eq!(r2.ids(), vec!["10", "11", "12", "13"]);
    }
}
