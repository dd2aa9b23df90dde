//! A job's run: the worker loop that takes queued jobs, runs the pipeline on the job pool and
//! records the outcome (successful, failed, back to accepted on shutdown, files removed when a
//! DELETE won the race).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use tokio::sync::watch;
use tracing::{Instrument, error, info, info_span};

use super::ids::{now_ms, sha256_file};
use super::limit::Deadline;
use super::progress::JobProgress;
use super::service::{Jobs, Running};
use super::store::{JobRow, Status, Upload};
use super::{JobsError, bridge};
use crate::io::Format;
use crate::pipeline::scaleout::Executor;
use crate::pipeline::{self, Job, PipelineError, Report, RunOptions};

/// Replaces server paths in a message: the input and output by `input` and `result`, the data
/// directory by `<data>`. Clients never see where the server keeps files.
pub(super) fn scrub(msg: &str, input: &Path, output: &Path, data_dir: &Path) -> String {
    let mut s = msg.to_string();
    for (p, label) in [(input, "input"), (output, "result"), (data_dir, "<data>")] {
        let text = p.display().to_string();
        if !text.is_empty() {
            s = s.replace(&text, label);
        }
    }
    s
}

impl Jobs {
    pub(super) async fn worker(self, mut shutdown: watch::Receiver<bool>) {
        loop {
            if *shutdown.borrow() {
                break;
            }
            let next = self.lock_queue().ids.pop_front();
            match next {
                Some(id) => {
                    self.update_gauges();
                    self.run_job(id).await;
                }
                None => {
                    tokio::select! {
                        _ = self.inner.wake.notified() => {}
                        changed = shutdown.changed() => if changed.is_err() { break },
                    }
                }
            }
        }
    }

    pub(super) async fn run_job(&self, id: String) {
        let i = id.clone();
        let row = match self.db(move |s| s.job(None, &i)).await {
            Ok(Some(r)) if r.status == Status::Accepted => r,
            Ok(_) => return,
            Err(e) => {
                error!(job = %id, error = %e, "cannot read a queued job");
                return;
            }
        };
        let span = info_span!("job", id = %row.id, tenant = %row.tenant);
        self.run_row(row).instrument(span).await;
    }

    pub(super) async fn run_row(&self, row: JobRow) {
        let id = row.id.clone();
        let u = row.upload.clone();
        let upload = self.db(move |s| s.upload(None, &u)).await;
        let running = Arc::new(Running {
            cancel: Arc::new(AtomicBool::new(false)),
            progress: Arc::new(JobProgress::default()),
            dismissed: AtomicBool::new(false),
            done: watch::channel(false).0,
            wake: tokio::sync::Notify::new(),
        });
        // Registered before the status changes, so that a DELETE seeing `running` finds it.
        let _ = self.lock_running().insert(id.clone(), running.clone());
        let started = now_ms();
        let i = id.clone();
        let marked = self
            .db(move |s| s.transition(&i, Status::Accepted, Status::Running, Some(started), None))
            .await;
        if !matches!(marked, Ok(true)) {
            let _ = self.lock_running().remove(&id);
            running.done.send_replace(true);
            return;
        }
        self.update_gauges();
        let input = match upload {
            Ok(Some(Upload {
                format: Some(ext),
                complete: true,
                id: uid,
                ..
            })) => (self.upload_path(&uid, ext), ext),
            other => {
                if let Err(e) = other {
                    error!(error = %e, "cannot read the job's upload");
                }
                self.finish_failed(&id, "the input upload no longer exists")
                    .await;
                let _ = self.lock_running().remove(&id);
                running.done.send_replace(true);
                self.update_gauges();
                return;
            }
        };
        if row.spec.executor == Executor::Slurm {
            // Planned and submitted here; a monitor task then follows it on the cluster and
            // records its outcome (this worker goes on to the next job).
            self.run_slurm(row, input, running).await;
            return;
        }
        let dir = self.job_dir(&id);
        let output = dir.join(format!("result.{}", row.spec.output_format));
        let deadline = Deadline::arm(
            self.inner.settings.job_time_limit,
            "job_time_limit",
            running.cancel.clone(),
        );
        let outcome = self.execute(&row, &input, &dir, &output, &running).await;
        deadline.disarm();
        let _ = self.lock_running().remove(&id);
        let dismissed = running.dismissed.load(Ordering::SeqCst);
        // A failed job's files are removed before its status says so: a client that sees
        // `failed` finds nothing of it left (the issue-15 test saw the directory once, in the
        // moment between the two).
        match outcome {
            _ if dismissed => {
                info!("stopped: dismissed");
                self.remove_job_files(&id).await;
            }
            Err(panicked) => {
                error!(error = %panicked, "the run panicked");
                self.remove_job_files(&id).await;
                self.finish_failed(&id, "internal error: the run panicked")
                    .await;
            }
            Ok(Ok(report)) => self.finish_success(&id, report, &dir, &output).await,
            Ok(Err(PipelineError::Cancelled)) if deadline.expired() => {
                // Over its limit: failed for good (a restart does not give it another run).
                let msg = deadline.error().to_string();
                info!(error = %msg, "failed");
                self.remove_job_files(&id).await;
                self.finish_failed(&id, &msg).await;
            }
            Ok(Err(PipelineError::Cancelled)) if self.shutting_down() => {
                // Back in the queue of the next start; the finished tiles stay as checkpoints.
                let i = id.clone();
                let _ = self
                    .db(move |s| s.transition(&i, Status::Running, Status::Accepted, None, None))
                    .await;
                info!("interrupted by shutdown; resumes at the next start");
            }
            Ok(Err(e)) => {
                let msg = scrub(&e.to_string(), &input.0, &output, self.data_dir());
                if e.is_input_fault() {
                    info!(error = %msg, "failed");
                } else {
                    error!(error = %e, "failed");
                }
                self.remove_job_files(&id).await;
                self.finish_failed(&id, &msg).await;
            }
        }
        running.done.send_replace(true);
        self.update_gauges();
    }

    /// Runs the pipeline for `row` on a blocking thread.
    pub(super) async fn execute(
        &self,
        row: &JobRow,
        input: &(PathBuf, Format),
        dir: &Path,
        output: &Path,
        running: &Running,
    ) -> Result<Result<Report, PipelineError>, JobsError> {
        let spec = &row.spec;
        let job = Job {
            input: input.0.clone(),
            output: output.to_path_buf(),
            input_format: Some(input.1),
            output_format: Some(spec.output_format),
            spec: spec.denoise.clone(),
            trajectory: None,
        };
        let opts = RunOptions {
            memory_budget: spec.memory_budget,
            temp_dir: None,
            tile_points: spec.tile_points,
            part_points: None,
            progress: running.progress.clone(),
            cancel: running.cancel.clone(),
            work_dir: Some(dir.join("work")),
        };
        let dir = dir.to_path_buf();
        info!(input = %input.1, output = %spec.output_format, tile_points = ?spec.tile_points, "started");
        let span = tracing::Span::current();
        let inner = self.inner.clone();
        // The driver waits on a blocking thread; the run itself (its I/O and its kernels) happens
        // on the job pool's lower-priority threads.
        let run = bridge::blocking(move || {
            inner.job_pool.install(|| {
                span.in_scope(|| {
                    std::fs::create_dir_all(&dir).map_err(|e| PipelineError::TempDir {
                        path: dir.clone(),
                        detail: e.to_string(),
                    })?;
                    pipeline::run(&job, &opts)
                })
            })
        })
        .await;
        // The outer error is the bridge's: the run panicked (reported as that, not as a
        // pipeline error it is not).
        run
    }

    pub(super) async fn finish_success(
        &self,
        id: &str,
        mut report: Report,
        dir: &Path,
        output: &Path,
    ) {
        let out = output.to_path_buf();
        let work = dir.join("work");
        let hashed = bridge::blocking(move || {
            let _ = std::fs::remove_dir_all(&work);
            let size = std::fs::metadata(&out)
                .map_err(|e| JobsError::io("stat the result", e))?
                .len();
            Ok::<_, JobsError>((size, sha256_file(&out)?))
        })
        .await
        .and_then(|r| r);
        let (size, sha) = match hashed {
            Ok(x) => x,
            Err(e) => {
                error!(error = %e, "cannot hash the result");
                self.remove_job_files(id).await;
                self.finish_failed(id, "internal error while storing the result")
                    .await;
                return;
            }
        };
        report.input = PathBuf::from("input");
        report.output = PathBuf::from(format!(
            "result.{}",
            output
                .extension()
                .map(|e| e.to_string_lossy())
                .unwrap_or_default()
        ));
        self.inner.metrics.observe("job", &report);
        let i = id.to_string();
        let r = report.clone();
        let s = sha.clone();
        match self
            .db(move |st| st.finish_success(&i, now_ms(), &r, size, &s))
            .await
        {
            Ok(true) => info!(
                points = report.points_in,
                tiles = report.tiles,
                resumed = report.tiles_resumed,
                wall_s = report.wall_s,
                "successful"
            ),
            Ok(false) => self.remove_job_files(id).await,
            Err(e) => error!(error = %e, "cannot record a successful job"),
        }
    }

    pub(super) async fn finish_failed(&self, id: &str, msg: &str) {
        let (i, m) = (id.to_string(), msg.to_string());
        if let Err(e) = self.db(move |s| s.finish_failure(&i, now_ms(), &m)).await {
            error!(error = %e, "cannot record a failed job");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scrubbing_hides_server_paths() {
        let s = scrub(
            "/d/uploads/x.ply: bad header; /d/jobs/y/result.ply; /d/other",
            Path::new("/d/uploads/x.ply"),
            Path::new("/d/jobs/y/result.ply"),
            Path::new("/d"),
        );
        assert_eq!(s, "input: bad header; result; <data>/other");
    }
}
