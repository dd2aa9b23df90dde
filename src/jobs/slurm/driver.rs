//! The async side of the SLURM executor: planning and submission in a worker slot, then a
//! monitor task per job (polling, progress, delivery, failure, `DELETE`, shutdown). Every
//! SLURM command and file operation runs on the blocking pool ([`bridge::blocking`]); every wait
//! is bounded (commands by [`super::client::COMMAND_TIMEOUT`], the monitor by the job's
//! `job_time_limit`, a dismissal's wait for its tasks by [`GONE_WAIT`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use tracing::{Instrument, error, info, warn};

use super::{
    ArrayJob, Client, MAX_RESUBMITS, SlurmError, SlurmRecord, SlurmSettings, Submit, Verdict,
    job_name, pending_phases, verdict,
};
use crate::io::Format;
use crate::jobs::limit::Deadline;
use crate::jobs::progress::JobProgress;
use crate::jobs::run::scrub;
use crate::jobs::service::{Inner, Jobs, Running};
use crate::jobs::store::{JobRow, Status as JobStatus};
use crate::jobs::{JobsError, bridge};
use crate::pipeline::PipelineError;
use crate::pipeline::scaleout::{self, Hooks, Phase, PlanRequest, ScaleoutError, Status, WorkUrl};

/// How long a dismissed job waits for its cancelled tasks to end before its files go again.
const GONE_WAIT: Duration = Duration::from_secs(30);
/// How long SLURM may stay unreachable (every poll failing) before a job fails.
const UNREACHABLE: Duration = Duration::from_secs(600);

/// A SLURM job's paths and formats.
#[derive(Debug, Clone)]
struct Ctx {
    id: String,
    /// The job's directory (absolute: the tasks get it on their command line).
    dir: PathBuf,
    /// The scale-out work directory, `dir/work`.
    work: PathBuf,
    /// The tasks' logs, `dir/logs`.
    logs: PathBuf,
    /// The result, `dir/result.<ext>`.
    output: PathBuf,
    /// The input (canonical when it exists: task errors name it so).
    input: PathBuf,
    /// The data directory (canonical likewise).
    data: PathBuf,
    output_format: Format,
    started: Instant,
}

impl Ctx {
    fn work_url(&self) -> WorkUrl {
        WorkUrl::Local(self.work.clone())
    }

    /// `msg` with the server's paths replaced ([`scrub`]).
    fn scrub(&self, msg: &str) -> String {
        scrub(msg, &self.input, &self.output, &self.data)
    }
}

/// How a SLURM job's run in this process ends.
enum End {
    /// The stitch is committed: deliver the result.
    Done,
    /// Failed with a one-line reason; its SLURM jobs are cancelled.
    Failed(String),
    /// Over `job_time_limit`; its SLURM jobs are cancelled.
    TimeLimit,
    /// `DELETE`d: its SLURM jobs are cancelled and its files removed.
    Dismissed,
    /// The server is shutting down: the SLURM jobs go on, the job goes back to `accepted` and
    /// re-attaches at the next start.
    Shutdown,
}

/// The last line of a task's log that says what went wrong (`qemd: error: …`, else the last
/// line), at most 240 characters.
fn log_tail(logs: &Path, phase: Phase, task: &str) -> Option<String> {
    let text = std::fs::read_to_string(logs.join(format!("{phase}-{task}.out"))).ok()?;
    let lines: Vec<&str> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect();
    let line = lines
        .iter()
        .rev()
        .find(|l| l.starts_with("qemd: error:"))
        .or(lines.last())?;
    Some(match line.char_indices().nth(240) {
        Some((i, _)) => format!("{}…", &line[..i]),
        None => (*line).to_string(),
    })
}

/// Sets `progress` from the committed checkpoints.
fn show(progress: &JobProgress, status: &Status) {
    let tiles = status
        .phases
        .iter()
        .find(|p| p.phase == Phase::Tiles)
        .map_or((0, 0), |p| (p.committed, p.units));
    let (phase, done, total) = match status
        .next
        .and_then(|n| status.phases.iter().find(|p| p.phase == n))
    {
        Some(p) => (p.phase, p.committed, p.units),
        None => (Phase::Stitch, 1, 1),
    };
    progress.committed(phase.name(), done, total, tiles);
}

/// Submits `phases` as array jobs chained with `afterok`, recording each id in the job's row
/// before the next is submitted. Stops early (the record then stays incomplete) when the job
/// is dismissed or the server shuts down.
fn submit_chain(
    inner: &Inner,
    ctx: &Ctx,
    settings: &SlurmSettings,
    phases: &[(Phase, u64)],
    record: &mut SlurmRecord,
    running: &Running,
) -> Result<(), JobsError> {
    let worker = match &settings.worker {
        Some(w) => w.clone(),
        None => std::env::current_exe().map_err(|e| {
            JobsError::Internal(format!(
                "cannot tell this server's executable for the SLURM tasks ({e}); set slurm_worker"
            ))
        })?,
    };
    std::fs::create_dir_all(&ctx.logs)
        .map_err(|e| JobsError::io(format!("create {}", ctx.logs.display()), e))?;
    record.complete = false;
    record.cpus_per_task = settings.cpus_per_task;
    let threads = settings.cpus_per_task.to_string();
    let mut after: Vec<String> = Vec::new();
    for &(phase, tasks) in phases {
        if running.dismissed.load(Ordering::SeqCst) || *inner.shutdown.borrow() {
            return Ok(());
        }
        let n = tasks.min(settings.max_tasks).max(1);
        let s = Submit {
            name: job_name(&ctx.id),
            tasks: n,
            after: after.clone(),
            chdir: ctx.dir.clone(),
            output: ctx.logs.join(format!("{phase}-%A_%a.out")),
            cpus_per_task: settings.cpus_per_task,
            partition: settings.partition.clone(),
            account: settings.account.clone(),
            extra: settings.sbatch_args.clone(),
            command: vec![
                worker.display().to_string(),
                "worker".into(),
                "--work".into(),
                ctx.work.display().to_string(),
                "--phase".into(),
                phase.name().into(),
                "--threads".into(),
                threads.clone(),
                "--json".into(),
            ],
        };
        let id = settings.client.submit(&s)?;
        info!(phase = %phase, slurm_job = %id, tasks = n, "submitted to SLURM");
        record.jobs.push(ArrayJob {
            phase,
            id: id.clone(),
            tasks: n,
        });
        inner.store.set_slurm(&ctx.id, record)?;
        after = vec![id];
    }
    record.complete = true;
    inner.store.set_slurm(&ctx.id, record)
}

/// Waits (at most `bound`) until no task of `ids` is pending or running.
fn wait_gone(client: &Client, ids: &[String], bound: Duration) {
    let start = Instant::now();
    while start.elapsed() < bound {
        match client.states(ids) {
            Ok(st)
                if st
                    .iter()
                    .all(|s| super::client::TERMINAL.contains(&s.state.as_str())) =>
            {
                return;
            }
            Err(_) => return,
            Ok(_) => std::thread::sleep(Duration::from_millis(250)),
        }
    }
}

impl Jobs {
    /// The SLURM settings in force, or the defaults (a server no longer configured for SLURM
    /// still follows and cancels the jobs it submitted; it cannot submit new ones).
    fn slurm_settings(&self) -> (SlurmSettings, bool) {
        match &self.inner.settings.slurm {
            Some(s) => (s.clone(), true),
            None => (SlurmSettings::default(), false),
        }
    }

    /// Cancels every SLURM job of job `id` (`scancel`, on the blocking pool); failures are
    /// logged.
    pub(in crate::jobs) async fn cancel_slurm(&self, id: &str, record: &SlurmRecord) {
        let client = self.slurm_settings().0.client;
        let ids = record.all_ids();
        let name = job_name(id);
        let r = bridge::blocking(move || client.cancel(&ids, Some(&name))).await;
        match r {
            Ok(Ok(())) => info!(job = id, slurm_jobs = ?record.all_ids(), "SLURM jobs cancelled"),
            Ok(Err(e)) => warn!(job = id, error = %e, "cannot cancel the job's SLURM jobs"),
            Err(e) => warn!(job = id, error = %e, "cannot cancel the job's SLURM jobs"),
        }
    }

    /// Runs job `row` (already `running`) on SLURM: plans it and submits its phases (or takes
    /// the SLURM jobs its row records, after a restart), then hands it to a monitor task.
    pub(in crate::jobs) async fn run_slurm(
        &self,
        row: JobRow,
        input: (PathBuf, Format),
        running: Arc<Running>,
    ) {
        let id = row.id.clone();
        let deadline = Deadline::arm(
            self.inner.settings.job_time_limit,
            "job_time_limit",
            running.cancel.clone(),
        );
        let dir = self.job_dir(&id);
        let (data, upload) = (self.data_dir().to_path_buf(), input.0.clone());
        let made = bridge::blocking(move || {
            let dir = std::fs::create_dir_all(&dir)
                .and_then(|()| std::fs::canonicalize(&dir))
                .map_err(|e| JobsError::io("create the job directory", e))?;
            let data = std::fs::canonicalize(&data).unwrap_or(data);
            let upload = std::fs::canonicalize(&upload).unwrap_or(upload);
            Ok::<_, JobsError>((dir, data, upload))
        })
        .await
        .and_then(|r| r);
        let (dir, data, canonical_input) = match made {
            Ok(d) => d,
            Err(e) => {
                error!(error = %e, "cannot prepare a SLURM job");
                let ctx = self.bare_ctx(&row, input.0);
                let end = End::Failed("internal error while preparing the job".into());
                self.end_slurm(&ctx, end, None, &running, &deadline).await;
                return;
            }
        };
        let ctx = Ctx {
            id: id.clone(),
            work: dir.join("work"),
            logs: dir.join("logs"),
            output: dir.join(format!("result.{}", row.spec.output_format)),
            dir,
            input: canonical_input,
            data,
            output_format: row.spec.output_format,
            started: Instant::now(),
        };
        let record = match row.slurm.clone() {
            Some(r) if r.complete => {
                info!(slurm_jobs = ?r.ids(), "re-attaching to the job's SLURM jobs");
                r
            }
            earlier => match self
                .plan_and_submit(&ctx, &row, input, earlier, &running)
                .await
            {
                Ok(r) => r,
                Err((end, r)) => {
                    self.end_slurm(&ctx, end, r.as_ref(), &running, &deadline)
                        .await;
                    return;
                }
            },
        };
        let me = self.clone();
        let span = tracing::Span::current();
        let handle = tokio::spawn(
            async move { me.monitor(ctx, record, running, deadline).await }.instrument(span),
        );
        self.inner
            .workers
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(handle);
    }

    fn bare_ctx(&self, row: &JobRow, input: PathBuf) -> Ctx {
        let dir = self.job_dir(&row.id);
        Ctx {
            id: row.id.clone(),
            work: dir.join("work"),
            logs: dir.join("logs"),
            output: dir.join(format!("result.{}", row.spec.output_format)),
            dir,
            input,
            data: self.data_dir().to_path_buf(),
            output_format: row.spec.output_format,
            started: Instant::now(),
        }
    }

    /// Plans the job in its work directory (the `qemd plan` code, on the job pool) and submits
    /// every phase with tasks. A record left incomplete by an earlier run (a crash between two
    /// `sbatch`) is cancelled first: the phases are submitted anew.
    async fn plan_and_submit(
        &self,
        ctx: &Ctx,
        row: &JobRow,
        input: (PathBuf, Format),
        earlier: Option<SlurmRecord>,
        running: &Arc<Running>,
    ) -> Result<SlurmRecord, (End, Option<SlurmRecord>)> {
        let (settings, configured) = self.slurm_settings();
        let mut record = earlier.unwrap_or_default();
        if !record.jobs.is_empty() {
            self.cancel_slurm(&ctx.id, &record).await;
            let old = std::mem::take(&mut record.jobs);
            record.earlier.extend(old);
        }
        if !configured {
            return Err((
                End::Failed(
                    "the job was accepted for SLURM, but this server's executor is now local"
                        .into(),
                ),
                Some(record),
            ));
        }
        let req = PlanRequest {
            input: input.0,
            input_format: Some(input.1),
            output_format: Some(row.spec.output_format),
            spec: row.spec.denoise.clone(),
            memory_budget: row.spec.memory_budget,
            tile_points: row.spec.tile_points,
            part_points: None,
            stored_as: None,
            stitch_tasks: true,
        };
        let work = ctx.work_url();
        let hooks = Hooks {
            progress: running.progress.clone(),
            cancel: running.cancel.clone(),
        };
        let inner = self.inner.clone();
        let span = tracing::Span::current();
        info!(input = %row.spec.output_format, tile_points = ?row.spec.tile_points, "planning for SLURM");
        let planned = bridge::blocking(move || {
            inner.job_pool.install(|| {
                span.in_scope(|| {
                    scaleout::plan(&work, &req, hooks.progress, hooks.cancel)
                        .and_then(|_| scaleout::status(&work))
                })
            })
        })
        .await;
        let status = match planned {
            Ok(Ok(s)) => s,
            Ok(Err(e)) => return Err((self.stopped_or(ctx, e, running), Some(record))),
            Err(e) => {
                error!(error = %e, "the plan panicked");
                return Err((
                    End::Failed("internal error: the run panicked".into()),
                    Some(record),
                ));
            }
        };
        show(&running.progress, &status);
        let phases = pending_phases(&status);
        let inner = self.inner.clone();
        let c = ctx.clone();
        let r = running.clone();
        let submitted = bridge::blocking(move || {
            let res = submit_chain(&inner, &c, &settings, &phases, &mut record, &r);
            (res, record)
        })
        .await;
        match submitted {
            Ok((Ok(()), record)) if record.complete => Ok(record),
            Ok((Ok(()), record)) => Err((self.stop_reason(running), Some(record))),
            Ok((Err(e), record)) => {
                let msg = ctx.scrub(&e.to_string());
                warn!(error = %msg, "cannot submit to SLURM");
                Err((
                    End::Failed(format!("cannot submit to SLURM: {msg}")),
                    Some(record),
                ))
            }
            Err(e) => Err((End::Failed(format!("internal error: {e}")), None)),
        }
    }

    /// Why a run that stopped stopped: dismissed, over its limit or shutting down.
    fn stop_reason(&self, running: &Running) -> End {
        if running.dismissed.load(Ordering::SeqCst) {
            End::Dismissed
        } else if self.shutting_down() {
            End::Shutdown
        } else {
            End::TimeLimit
        }
    }

    /// The end of a run whose plan failed with `e`.
    fn stopped_or(&self, ctx: &Ctx, e: ScaleoutError, running: &Running) -> End {
        if matches!(e, ScaleoutError::Pipeline(PipelineError::Cancelled)) {
            return self.stop_reason(running);
        }
        let msg = ctx.scrub(&e.to_string());
        End::Failed(msg)
    }

    /// Follows the job's SLURM jobs until they deliver, fail, vanish for good, or the job is
    /// dismissed, over its limit or the server stops.
    async fn monitor(
        self,
        ctx: Ctx,
        mut record: SlurmRecord,
        running: Arc<Running>,
        deadline: Deadline,
    ) {
        let (settings, _) = self.slurm_settings();
        let mut shutdown = self.inner.shutdown.subscribe();
        let mut unreachable_since: Option<Instant> = None;
        let end = loop {
            let wake = running.wake.notified();
            tokio::pin!(wake);
            wake.as_mut().enable();
            if running.dismissed.load(Ordering::SeqCst) {
                break End::Dismissed;
            }
            if deadline.expired() {
                break End::TimeLimit;
            }
            if self.shutting_down() {
                break End::Shutdown;
            }
            let client = settings.client.clone();
            let ids = record.ids();
            let work = ctx.work_url();
            // States first, then checkpoints (see `verdict`).
            let polled = bridge::blocking(move || {
                let states = client.states(&ids);
                (states, scaleout::status(&work))
            })
            .await;
            match polled {
                Ok((Ok(states), Ok(status))) => {
                    unreachable_since = None;
                    show(&running.progress, &status);
                    match verdict(&record, &states, &status) {
                        Verdict::Done => break End::Done,
                        Verdict::Wait => {}
                        Verdict::Failed {
                            phase,
                            task,
                            reason,
                        } => break End::Failed(self.with_log(&ctx, phase, &task, reason)),
                        Verdict::Idle => {
                            if let Err(reason) =
                                self.idle(&ctx, &mut record, &status, &running).await
                            {
                                break End::Failed(reason);
                            }
                        }
                    }
                }
                Ok((_, Err(e))) => {
                    let msg = ctx.scrub(&e.to_string());
                    break End::Failed(msg);
                }
                Ok((Err(e), _)) => {
                    let since = *unreachable_since.get_or_insert_with(Instant::now);
                    warn!(error = %e, "cannot read the job's SLURM state; trying again");
                    if since.elapsed() > UNREACHABLE {
                        break End::Failed(format!(
                            "SLURM did not answer for {} s: {e}",
                            UNREACHABLE.as_secs()
                        ));
                    }
                }
                Err(e) => {
                    error!(error = %e, "a poll panicked");
                    break End::Failed("internal error: the poll panicked".into());
                }
            }
            tokio::select! {
                _ = tokio::time::sleep(settings.poll_interval) => {}
                _ = &mut wake => {}
                _ = shutdown.changed() => {}
            }
        };
        self.end_slurm(&ctx, end, Some(&record), &running, &deadline)
            .await;
    }

    /// `reason`, with what the failed task's log says.
    fn with_log(&self, ctx: &Ctx, phase: Phase, task: &str, reason: String) -> String {
        match log_tail(&ctx.logs, phase, task) {
            Some(line) => {
                let line = ctx.scrub(&line);
                format!("{reason}: {line}")
            }
            None => reason,
        }
    }

    /// No task alive and the stitch not committed: failed (by the accounting database's
    /// word), or submitted again for the phases not committed (at most [`MAX_RESUBMITS`]
    /// times), or failed with the reason.
    async fn idle(
        &self,
        ctx: &Ctx,
        record: &mut SlurmRecord,
        status: &Status,
        running: &Arc<Running>,
    ) -> Result<(), String> {
        let (settings, configured) = self.slurm_settings();
        let client = settings.client.clone();
        let ids = record.ids();
        let acct = bridge::blocking(move || client.accounting(&ids)).await;
        match acct {
            Ok(Ok(states)) => {
                if let Verdict::Failed {
                    phase,
                    task,
                    reason,
                } = verdict(record, &states, status)
                {
                    return Err(self.with_log(ctx, phase, &task, reason));
                }
            }
            Ok(Err(SlurmError::NoAccounting(_))) => {}
            Ok(Err(e)) => warn!(error = %e, "cannot read the accounting database"),
            Err(e) => warn!(error = %e, "cannot read the accounting database"),
        }
        let phase = status.next.unwrap_or(Phase::Stitch);
        if !configured {
            return Err(format!(
                "the {phase} phase is not committed and the job's SLURM jobs have ended; this \
                 server's executor is local, so it cannot submit them again"
            ));
        }
        if record.resubmits >= MAX_RESUBMITS {
            return Err(format!(
                "the {phase} phase is not committed and the job's SLURM jobs have ended or \
                 vanished (after {} submissions)",
                record.resubmits + 1
            ));
        }
        warn!(
            phase = %phase,
            slurm_jobs = ?record.ids(),
            "the job's SLURM jobs ended or vanished without committing; submitting the phases \
             not committed again"
        );
        record.resubmits += 1;
        let old = std::mem::take(&mut record.jobs);
        record.earlier.extend(old);
        let phases = pending_phases(status);
        let inner = self.inner.clone();
        let c = ctx.clone();
        let r = running.clone();
        let mut rec = record.clone();
        let submitted = bridge::blocking(move || {
            // Anything of this job still known to SLURM (an unrecorded submission) goes first.
            let _ = settings.client.cancel(&[], Some(&job_name(&c.id)));
            let res = submit_chain(&inner, &c, &settings, &phases, &mut rec, &r);
            (res, rec)
        })
        .await;
        match submitted {
            Ok((res, rec)) => {
                *record = rec;
                res.map_err(|e| {
                    let msg = ctx.scrub(&e.to_string());
                    format!("cannot submit to SLURM again: {msg}")
                })
            }
            Err(e) => Err(format!("internal error: {e}")),
        }
    }

    /// Records how the run ended and lets go of the job.
    async fn end_slurm(
        &self,
        ctx: &Ctx,
        end: End,
        record: Option<&SlurmRecord>,
        running: &Running,
        deadline: &Deadline,
    ) {
        deadline.disarm();
        let id = ctx.id.as_str();
        let cancel = |rec: Option<&SlurmRecord>| {
            let rec = rec.cloned().unwrap_or_default();
            async move { self.cancel_slurm(id, &rec).await }
        };
        match end {
            End::Done => self.deliver(ctx, record).await,
            End::Failed(msg) => {
                cancel(record).await;
                info!(error = %msg, "failed");
                self.finish_failed(id, &msg).await;
                self.remove_job_files(id).await;
            }
            End::TimeLimit => {
                cancel(record).await;
                let msg = deadline.error().to_string();
                info!(error = %msg, "failed");
                self.finish_failed(id, &msg).await;
                self.remove_job_files(id).await;
            }
            End::Dismissed => {
                cancel(record).await;
                // Cancelled tasks get SIGTERM, then SIGKILL after the cluster's KillWait: the
                // files go once they are gone (they went at the DELETE too).
                let client = self.slurm_settings().0.client;
                let ids = record.map(SlurmRecord::all_ids).unwrap_or_default();
                let _ = bridge::blocking(move || wait_gone(&client, &ids, GONE_WAIT)).await;
                info!("stopped: dismissed");
                self.remove_job_files(id).await;
            }
            End::Shutdown => {
                let i = id.to_string();
                let _ = self
                    .db(move |s| {
                        s.transition(&i, JobStatus::Running, JobStatus::Accepted, None, None)
                    })
                    .await;
                info!(
                    "server stopping; the SLURM jobs go on and the job re-attaches at the next start"
                );
            }
        }
        let _ = self.lock_running().remove(id);
        running.done.send_replace(true);
        self.update_gauges();
    }

    /// The stitch is committed: `finish` into the result (on the job pool), the report from
    /// the committed checkpoints, then the result is recorded as for a local job.
    async fn deliver(&self, ctx: &Ctx, record: Option<&SlurmRecord>) {
        let work = ctx.work_url();
        let output = ctx.output.clone();
        let format = ctx.output_format;
        let inner = self.inner.clone();
        let span = tracing::Span::current();
        let done = bridge::blocking(move || {
            inner.job_pool.install(|| {
                span.in_scope(|| {
                    scaleout::finish(&work, &output, Some(format), &Hooks::default())?;
                    scaleout::summary(&work)
                })
            })
        })
        .await;
        let mut report = match done {
            Ok(Ok(r)) => r,
            Ok(Err(e)) => {
                let msg = ctx.scrub(&e.to_string());
                error!(error = %msg, "cannot deliver the result");
                self.finish_failed(&ctx.id, &msg).await;
                self.remove_job_files(&ctx.id).await;
                return;
            }
            Err(e) => {
                error!(error = %e, "delivering the result panicked");
                self.finish_failed(&ctx.id, "internal error: the run panicked")
                    .await;
                self.remove_job_files(&ctx.id).await;
                return;
            }
        };
        report.wall_s = ctx.started.elapsed().as_secs_f64();
        report.threads = record.map_or(0, |r| r.cpus_per_task as usize);
        self.finish_success(&ctx.id, report, &ctx.dir, &ctx.output)
            .await;
        let logs = ctx.logs.clone();
        let _ = bridge::blocking(move || std::fs::remove_dir_all(logs)).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_log_line_that_says_what_went_wrong() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(
            d.path().join("tiles-12_1.out"),
            "starting\nqemd: error: /data/x: broken\n{\"phase\":\"tiles\"}\n\n",
        )
        .unwrap();
        assert_eq!(
            log_tail(d.path(), Phase::Tiles, "12_1").as_deref(),
            Some("qemd: error: /data/x: broken")
        );
        std::fs::write(d.path().join("stitch-13_0.out"), "a\nlast words\n").unwrap();
        assert_eq!(
            log_tail(d.path(), Phase::Stitch, "13_0").as_deref(),
            Some("last words")
        );
        assert_eq!(log_tail(d.path(), Phase::Stitch, "14_0"), None);
        std::fs::write(d.path().join("partition-1_0.out"), "x".repeat(500)).unwrap();
        let long = log_tail(d.path(), Phase::Partition, "1_0").unwrap();
        assert_eq!(long.chars().count(), 241);
    }
}
