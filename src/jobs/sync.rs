//! The synchronous path: a small scan denoised now, on the synchronous rayon pool, with nothing
//! written to the job store.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use super::limit::Deadline;
use super::requests::{SyncOutput, SyncRequest, spec_error, validate_output};
use super::service::Jobs;
use super::{JobsError, bridge};
use crate::pipeline::{self, Job, NoProgress, PipelineError, RunOptions};

/// A synchronous request's slot and core, given back when the run that holds them ends.
struct Held(Arc<super::service::Inner>);

impl Drop for Held {
    fn drop(&mut self) {
        self.0.sync_running.add_permits(1);
        self.0.sync_slots.add_permits(1);
    }
}

impl Jobs {
    /// Denoises `body` (a whole file in `req.format`) now and returns the result; the CPU work
    /// runs on the synchronous path's rayon pool. Dropping the future cancels the run.
    ///
    /// # Errors
    /// [`JobsError::Busy`] beyond `sync_concurrency` requests, [`JobsError::Invalid`] for bad
    /// parameters, [`JobsError::Run`] when the run fails (the readers or the denoiser refuse the
    /// input, or the environment fails), [`JobsError::TimeLimit`] past `sync_time_limit`.
    pub async fn denoise_now(
        &self,
        body: impl AsRef<[u8]> + Send + Sync + 'static,
        req: SyncRequest,
    ) -> Result<SyncOutput, JobsError> {
        if self.shutting_down() {
            return Err(JobsError::ShuttingDown);
        }
        let slot = self.inner.sync_slots.try_acquire().map_err(|_| {
            // A 429 is a rejected request too (issue 15: it was not counted).
            let m = &self.inner.metrics;
            m.sync_requests.with_label_values(&["rejected"]).inc();
            JobsError::Busy
        })?;
        let spec = req
            .spec
            .resolve(self.inner.settings.outlier_alpha)
            .map_err(spec_error)?;
        let input_format = req.format;
        let output_format = req.output_format.unwrap_or(input_format);
        validate_output(&spec, output_format)?;
        let cancel = Arc::new(AtomicBool::new(false));
        // Dropped when the client goes away before the answer: the run stops at its next check.
        struct CancelOnDrop(Arc<AtomicBool>);
        impl Drop for CancelOnDrop {
            fn drop(&mut self) {
                self.0.store(true, Ordering::Relaxed);
            }
        }
        let _guard = CancelOnDrop(cancel.clone());
        // The limit counts from here, waiting for a core included (issue 15).
        let limit = self.inner.settings.sync_time_limit;
        let deadline = Deadline::arm(limit, "sync_time_limit", cancel.clone());
        let tmp = self.data_dir().join("tmp");
        let budget = self.inner.settings.memory_budget;
        let running = self
            .inner
            .sync_running
            .acquire()
            .await
            .map_err(|_| JobsError::ShuttingDown)?;
        // The request's slot and core stay taken until the run itself ends, which may be after
        // the answer (a run past the limit stops at its next check): the worker gives them back.
        slot.forget();
        running.forget();
        let held = Held(self.inner.clone());
        let run = bridge::cpu(&self.inner.sync_pool, move || {
            let _held = held;
            // Errors and the report name the request's `input` and `result.<format>`.
            let job = Job {
                input: PathBuf::from("input"),
                output: PathBuf::from(format!("result.{output_format}")),
                input_format: Some(input_format),
                output_format: Some(output_format),
                spec,
                trajectory: None,
            };
            let opts = RunOptions {
                memory_budget: budget,
                // Only a body larger than the memory budget, or E57/COPC output, is spooled here.
                temp_dir: Some(tmp),
                tile_points: None,
                part_points: None,
                progress: Arc::new(NoProgress),
                cancel,
                work_dir: None,
            };
            match pipeline::run_bytes(body, &job, &opts) {
                Ok(out) => Ok(SyncOutput {
                    bytes: out.bytes,
                    format: output_format,
                    report: out.report,
                    spooled: out.spooled,
                }),
                Err(PipelineError::Params(e)) => Err(spec_error(e)),
                Err(e) => Err(JobsError::Run(e)),
            }
        });
        // The answer comes at the limit, not when the run gets to its next check (issue 51: a
        // 20 s limit answered after 71 s).
        let run = tokio::select! {
            r = run => r,
            () = deadline.passed() => Ok(Err(deadline.error())),
        };
        deadline.disarm();
        let run = match run {
            // Stopped by the limit (a cancelled run is not the client's fault, hence Internal).
            Ok(Err(JobsError::Run(PipelineError::Cancelled) | JobsError::Internal(_)))
                if deadline.expired() =>
            {
                Ok(Err(deadline.error()))
            }
            other => other,
        };
        let m = &self.inner.metrics;
        match &run {
            Ok(Err(JobsError::TimeLimit { .. })) => {
                m.sync_requests.with_label_values(&["timeout"]).inc();
            }
            Ok(Ok(out)) => {
                m.observe("sync", &out.report);
                if out.spooled {
                    m.sync_spooled.inc();
                }
                m.sync_requests.with_label_values(&["ok"]).inc();
            }
            Ok(Err(JobsError::Run(e))) if !e.is_input_fault() => {
                m.sync_requests.with_label_values(&["error"]).inc();
            }
            Ok(Err(JobsError::Internal(_))) | Err(_) => {
                m.sync_requests.with_label_values(&["error"]).inc();
            }
            Ok(Err(_)) => m.sync_requests.with_label_values(&["rejected"]).inc(),
        }
        run?
    }
}
