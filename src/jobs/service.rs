//! The [`Jobs`] handle: settings, shared state, the queue and the job operations (submit,
//! inspect, list, dismiss, results, shutdown). The worker loop is in `run.rs`, the synchronous
//! path in `sync.rs`, start-up recovery in `recovery.rs`, request types in `requests.rs`.
//!
//! Lifecycle of a job (statuses as OGC API – Processes names them):
//!
//! ```text
//!  submit ──▶ accepted ──(worker)──▶ running ──▶ successful
//!                │  ▲                   │    └──▶ failed
//!                │  └──(shutdown, or ───┤
//!                │     restart after a  │
//!                │     crash: resumes)  │
//!                └──────────────────────┴──(DELETE)──▶ dismissed (files removed)
//! ```
//!
//! Status changes are conditional updates (`… WHERE status = 'running'`), so a worker finishing
//! and a DELETE racing it cannot both win: whichever writes second sees that it lost and, if it is
//! the worker, removes the files it wrote.

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::{Notify, watch};
use tracing::{info, warn};

use super::ids::{new_id, now_ms, valid_id};
use super::metrics::Metrics;
use super::progress::{JobProgress, ProgressView};
use super::recovery::{clear_dir, remove_stale_files};
use super::requests::{JobInfo, JobRequest, ResultFile, spec_error, validate_output};
use super::slurm::SlurmSettings;
use super::store::{JobRow, JobSpec, Status, Store};
use super::{JobsError, bridge};
use crate::io::Format;
use crate::pipeline::scaleout::Executor;
use crate::pipeline::{self, OutlierMode};

/// The default of [`Settings::preview_points`]: most points on each side of a job's preview.
pub const PREVIEW_POINTS: u64 = 1_000_000;

/// What the service needs from the configuration.
#[derive(Debug, Clone)]
pub struct Settings {
    /// Database, uploads, results, checkpoints.
    pub data_dir: PathBuf,
    /// Jobs running at the same time.
    pub job_concurrency: usize,
    /// Accepted jobs waiting for a slot.
    pub queue_capacity: usize,
    /// Memory budget of each run.
    pub memory_budget: u64,
    /// Point clouds with more points run tiled, with tiles of about this many points.
    pub job_tile_points: u64,
    /// Default outlier threshold.
    pub outlier_alpha: f64,
    /// Largest upload in bytes.
    pub max_upload_size: u64,
    /// Synchronous requests running at the same time.
    pub sync_concurrency: usize,
    /// Most points on each side of a job's preview ([`super::preview`]).
    pub preview_points: u64,
    /// Wall-clock limit of one run of a job: beyond it the job is cancelled and ends `failed`.
    pub job_time_limit: Duration,
    /// Wall-clock limit of a synchronous request (waiting for a core included): beyond it the
    /// run is cancelled and the answer is 504.
    pub sync_time_limit: Duration,
    /// `executor = "slurm"`: point clouds of at least [`SlurmSettings::min_points`] points run
    /// as SLURM array jobs ([`super::slurm`]); `None`: every job runs here.
    pub slurm: Option<SlurmSettings>,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            data_dir: PathBuf::from("qemd-data"),
            job_concurrency: 1,
            queue_capacity: 16,
            memory_budget: pipeline::DEFAULT_MEMORY_BUDGET,
            job_tile_points: 250_000,
            outlier_alpha: crate::pipeline::DEFAULT_OUTLIER_ALPHA,
            max_upload_size: 16 << 30,
            sync_concurrency: 8,
            preview_points: PREVIEW_POINTS,
            job_time_limit: super::limit::JOB_TIME_LIMIT,
            sync_time_limit: super::limit::SYNC_TIME_LIMIT,
            slurm: None,
        }
    }
}

/// A running job, as the worker and a DELETE share it.
pub(super) struct Running {
    pub(super) cancel: Arc<AtomicBool>,
    pub(super) progress: Arc<JobProgress>,
    /// Set by a DELETE: the worker must not record the outcome and must remove its files.
    pub(super) dismissed: AtomicBool,
    /// Becomes true when the worker is done with the job's files.
    pub(super) done: watch::Sender<bool>,
    /// Wakes a SLURM job's monitor from its wait between polls (DELETE, shutdown).
    pub(super) wake: Notify,
}

#[derive(Default)]
pub(super) struct Queue {
    pub(super) ids: VecDeque<String>,
    /// Slots promised to submissions still being written to the store.
    pub(super) reserved: usize,
}

pub(super) struct Inner {
    pub(super) settings: Settings,
    pub(super) store: Store,
    pub(super) metrics: Metrics,
    // std Mutexes below: short critical sections, never held across an await.
    pub(super) queue: Mutex<Queue>,
    pub(super) wake: Notify,
    pub(super) running: Mutex<HashMap<String, Arc<Running>>>,
    /// Uploads with a PATCH in progress (one at a time each).
    pub(super) patching: Mutex<std::collections::HashSet<String>>,
    pub(super) shutdown: watch::Sender<bool>,
    pub(super) workers: Mutex<Vec<tokio::task::JoinHandle<()>>>,
    /// The synchronous path's own rayon pool, so that robot requests do not queue behind the
    /// tiles of long jobs.
    pub(super) sync_pool: rayon::ThreadPool,
    /// The jobs' rayon pool, at a lower priority (see [`bridge::lower_priority`]).
    pub(super) job_pool: rayon::ThreadPool,
    pub(super) sync_slots: tokio::sync::Semaphore,
    /// Synchronous requests computing at once (one per core of the synchronous pool); the others
    /// wait here in arrival order. Handing rayon more top-level work than it has threads lets a
    /// thread waiting inside one request pick up a newer one, which buries the older request
    /// under it: measured, that made the p99 latency 50× the p50.
    pub(super) sync_running: tokio::sync::Semaphore,
}

/// The job service handle (cheap to clone). See the [module overview](super).
#[derive(Clone)]
pub struct Jobs {
    pub(super) inner: Arc<Inner>,
}

impl std::fmt::Debug for Jobs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Jobs")
            .field("settings", &self.inner.settings)
            .finish_non_exhaustive()
    }
}

impl Jobs {
    /// Opens the data directory and the store, recovers after a restart (running jobs back to
    /// accepted, stale temporary files removed), queues the accepted jobs and starts the workers.
    /// Needs a tokio runtime.
    ///
    /// # Errors
    /// The data directory or the database cannot be opened.
    pub async fn open(settings: Settings) -> Result<Jobs, JobsError> {
        let dir = settings.data_dir.clone();
        let check = settings.slurm.as_ref().map(|s| s.client.clone());
        let (store, queued, attach) = bridge::blocking(move || -> Result<_, JobsError> {
            if let Some(client) = check {
                // A service configured for SLURM that cannot run sbatch says so at start.
                let version = client.check()?;
                info!(sbatch = %version, "executor: slurm");
            }
            for sub in ["uploads", "jobs", "tmp"] {
                let p = dir.join(sub);
                std::fs::create_dir_all(&p)
                    .map_err(|e| JobsError::io(format!("create {}", p.display()), e))?;
            }
            clear_dir(&dir.join("tmp"));
            let store = Store::open(&dir.join("qemd.sqlite"))?;
            let requeued = store.requeue_running()?;
            if requeued > 0 {
                info!(jobs = requeued, "re-queued jobs interrupted by a restart");
            }
            remove_stale_files(&dir, &store)?;
            // Jobs with SLURM jobs recorded re-attach at once; the others wait for a worker.
            let attach = store.accepted_on_slurm()?;
            let queued: Vec<String> = store
                .ids_with_status(Status::Accepted)?
                .into_iter()
                .filter(|id| !attach.contains(id))
                .collect();
            Ok((store, queued, attach))
        })
        .await??;
        let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
        let sync_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("qemd-sync-{i}"))
            .build()
            .map_err(|e| JobsError::Internal(format!("cannot start the sync pool: {e}")))?;
        let job_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("qemd-job-{i}"))
            .start_handler(|_| bridge::lower_priority())
            .build()
            .map_err(|e| JobsError::Internal(format!("cannot start the job pool: {e}")))?;
        let (shutdown, _) = watch::channel(false);
        let jobs = Jobs {
            inner: Arc::new(Inner {
                sync_slots: tokio::sync::Semaphore::new(settings.sync_concurrency),
                sync_running: tokio::sync::Semaphore::new(threads),
                settings,
                store,
                metrics: Metrics::new()?,
                queue: Mutex::new(Queue {
                    ids: queued.into(),
                    reserved: 0,
                }),
                wake: Notify::new(),
                running: Mutex::new(HashMap::new()),
                patching: Mutex::new(Default::default()),
                shutdown,
                workers: Mutex::new(Vec::new()),
                sync_pool,
                job_pool,
            }),
        };
        jobs.update_gauges();
        let mut handles = Vec::new();
        for _ in 0..jobs.inner.settings.job_concurrency {
            let me = jobs.clone();
            let rx = jobs.inner.shutdown.subscribe();
            handles.push(tokio::spawn(async move { me.worker(rx).await }));
        }
        if !attach.is_empty() {
            info!(jobs = attach.len(), "re-attaching to jobs on SLURM");
        }
        // Outside the worker slots (they hand the job to its monitor and return); joined at
        // shutdown like the workers.
        for id in attach {
            let me = jobs.clone();
            handles.push(tokio::spawn(async move { me.run_job(id).await }));
        }
        *jobs.inner.workers.lock().unwrap_or_else(|e| e.into_inner()) = handles;
        Ok(jobs)
    }

    /// The settings in force.
    pub fn settings(&self) -> &Settings {
        &self.inner.settings
    }

    /// The metrics (for the `/metrics` endpoint and the API's own counters).
    pub fn metrics(&self) -> &Metrics {
        &self.inner.metrics
    }

    /// Runs `f` on the store, on the blocking pool.
    pub(super) async fn db<T, F>(&self, f: F) -> Result<T, JobsError>
    where
        T: Send + 'static,
        F: FnOnce(&Store) -> Result<T, JobsError> + Send + 'static,
    {
        let inner = self.inner.clone();
        bridge::blocking(move || f(&inner.store)).await?
    }

    pub(super) fn data_dir(&self) -> &Path {
        &self.inner.settings.data_dir
    }

    pub(super) fn job_dir(&self, id: &str) -> PathBuf {
        self.data_dir().join("jobs").join(id)
    }

    pub(super) fn upload_path(&self, id: &str, format: Format) -> PathBuf {
        self.data_dir()
            .join("uploads")
            .join(format!("{id}.{}", format.name()))
    }

    pub(super) fn part_path(&self, id: &str) -> PathBuf {
        self.data_dir().join("uploads").join(format!("{id}.part"))
    }

    pub(super) fn shutting_down(&self) -> bool {
        *self.inner.shutdown.borrow()
    }

    pub(super) fn update_gauges(&self) {
        let depth = self.lock_queue().ids.len();
        let running = self.lock_running().len();
        let m = &self.inner.metrics;
        m.queue_depth.set(i64::try_from(depth).unwrap_or(i64::MAX));
        m.running.set(i64::try_from(running).unwrap_or(i64::MAX));
    }

    pub(super) fn lock_queue(&self) -> std::sync::MutexGuard<'_, Queue> {
        self.inner.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(super) fn lock_running(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<Running>>> {
        self.inner.running.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// True when the store answers and the server is not shutting down.
    pub async fn ready(&self) -> bool {
        !self.shutting_down() && self.db(|s| Ok(s.ping())).await.unwrap_or(false)
    }

    /// Accepted jobs waiting for a slot.
    pub fn queue_depth(&self) -> usize {
        self.lock_queue().ids.len()
    }

    /// The metrics text, with the job counts refreshed from the store.
    ///
    /// # Errors
    /// Store or encoding failures.
    pub async fn render_metrics(&self) -> Result<String, JobsError> {
        let counts = self.db(|s| s.count_by_status()).await?;
        for (status, n) in counts {
            self.inner
                .metrics
                .jobs
                .with_label_values(&[status.as_str()])
                .set(i64::try_from(n).unwrap_or(i64::MAX));
        }
        self.update_gauges();
        self.inner.metrics.render()
    }

    // ---------------------------------------------------------------------------------------
    // Jobs

    /// Validates `req` and queues a job for `tenant`.
    ///
    /// # Errors
    /// [`JobsError::Invalid`] naming the bad field (an unknown input is `input`),
    /// [`JobsError::WrongState`] when the upload is incomplete, [`JobsError::QueueFull`],
    /// [`JobsError::ShuttingDown`].
    pub async fn submit(&self, tenant: &str, req: JobRequest) -> Result<JobRow, JobsError> {
        if self.shutting_down() {
            return Err(JobsError::ShuttingDown);
        }
        let spec = req
            .spec
            .resolve(self.inner.settings.outlier_alpha)
            .map_err(spec_error)?;
        let upload = if valid_id(&req.input) {
            let (t, id) = (tenant.to_string(), req.input.clone());
            self.db(move |s| s.upload(Some(&t), &id)).await?
        } else {
            None
        };
        let Some(upload) = upload else {
            return Err(JobsError::Invalid {
                field: "input".into(),
                detail: format!("no upload with id `{}`", req.input),
            });
        };
        let Some(input_format) = upload.format.filter(|_| upload.complete) else {
            return Err(JobsError::WrongState {
                detail: format!(
                    "upload {} is incomplete ({} of {} bytes)",
                    upload.id,
                    upload.size,
                    upload.length.unwrap_or(0)
                ),
                offset: Some(upload.size),
            });
        };
        let output = req.output_format.unwrap_or(input_format);
        let mesh = spec.params.mesh_mode(upload.faces.is_some());
        if mesh && spec.outliers != OutlierMode::Off {
            return Err(JobsError::Invalid {
                field: "outliers".into(),
                detail: "applies to point clouds, not meshes (set params.knn for point mode)"
                    .into(),
            });
        }
        if mesh && spec.params.write_normals {
            return Err(JobsError::Invalid {
                field: "params.write_normals".into(),
                detail: "applies to point clouds, not meshes (set params.knn for point mode)"
                    .into(),
            });
        }
        validate_output(&spec, output)?;
        let settings = &self.inner.settings;
        // SLURM takes point clouds of a known size at or above its threshold (always tiled);
        // meshes, smaller clouds and clouds of unknown size run here.
        let executor = match (&settings.slurm, upload.points) {
            (Some(sl), Some(n)) if !mesh && n >= sl.min_points => Executor::Slurm,
            _ => Executor::Local,
        };
        let tile_points = (!mesh
            && (executor == Executor::Slurm
                || upload.points.is_none_or(|n| n > settings.job_tile_points)))
        .then_some(settings.job_tile_points);
        let row = JobRow {
            id: new_id(),
            tenant: tenant.to_string(),
            upload: upload.id.clone(),
            status: Status::Accepted,
            spec: JobSpec {
                denoise: spec,
                output_format: output,
                memory_budget: settings.memory_budget,
                tile_points,
                executor,
                input_filename: upload.filename.clone(),
            },
            created_ms: now_ms(),
            started_ms: None,
            finished_ms: None,
            report: None,
            error: None,
            result_size: None,
            result_sha256: None,
            slurm: None,
        };
        {
            let mut q = self.lock_queue();
            if q.ids.len() + q.reserved >= settings.queue_capacity {
                return Err(JobsError::QueueFull);
            }
            q.reserved += 1;
        }
        let stored = row.clone();
        let inserted = self.db(move |s| s.insert_job(&stored)).await;
        {
            let mut q = self.lock_queue();
            q.reserved -= 1;
            if inserted.is_ok() {
                q.ids.push_back(row.id.clone());
            }
        }
        inserted?;
        self.inner.wake.notify_one();
        self.update_gauges();
        info!(job = %row.id, tenant, upload = %row.upload, executor = executor.name(), "job accepted");
        Ok(row)
    }

    /// The job `id` of `tenant`, with live progress.
    ///
    /// # Errors
    /// [`JobsError::NoSuch`].
    pub async fn job(&self, tenant: &str, id: &str) -> Result<JobInfo, JobsError> {
        if !valid_id(id) {
            return Err(JobsError::NoSuch("job"));
        }
        let (t, i) = (tenant.to_string(), id.to_string());
        let row = self
            .db(move |s| s.job(Some(&t), &i))
            .await?
            .ok_or(JobsError::NoSuch("job"))?;
        Ok(self.with_progress(row))
    }

    pub(super) fn with_progress(&self, row: JobRow) -> JobInfo {
        let progress = match row.status {
            Status::Running => Some(
                self.lock_running()
                    .get(&row.id)
                    .map(|r| r.progress.snapshot())
                    .unwrap_or_default(),
            ),
            Status::Accepted => Some(ProgressView {
                phase: "queued".into(),
                ..ProgressView::default()
            }),
            Status::Successful => {
                let tiles = row.report.as_ref().map_or(0, |r| r.tiles);
                Some(ProgressView {
                    phase: "done".into(),
                    done: 1,
                    total: 1,
                    tiles_done: tiles,
                    tiles_total: tiles,
                    percent: 100.0,
                })
            }
            _ => None,
        };
        JobInfo { row, progress }
    }

    /// A page of `tenant`'s jobs (newest first) and the number matching.
    ///
    /// # Errors
    /// Store failures.
    pub async fn list(
        &self,
        tenant: &str,
        status: Option<Status>,
        limit: u64,
        offset: u64,
    ) -> Result<(Vec<JobInfo>, u64), JobsError> {
        let t = tenant.to_string();
        let (rows, total) = self
            .db(move |s| s.list_jobs(&t, status, limit, offset))
            .await?;
        Ok((
            rows.into_iter().map(|r| self.with_progress(r)).collect(),
            total,
        ))
    }

    /// A page of `tenant`'s uploads, newest first, and how many it has.
    ///
    /// # Errors
    /// Store failures.
    pub async fn list_uploads(
        &self,
        tenant: &str,
        limit: u64,
        offset: u64,
    ) -> Result<(Vec<super::Upload>, u64), JobsError> {
        let t = tenant.to_string();
        self.db(move |s| s.list_uploads(&t, limit, offset)).await
    }

    /// Dismisses job `id` of `tenant`: a queued job leaves the queue, a running one is cancelled
    /// (waiting up to a second for it to stop), and its files are removed.
    ///
    /// # Errors
    /// [`JobsError::NoSuch`].
    pub async fn dismiss(&self, tenant: &str, id: &str) -> Result<JobInfo, JobsError> {
        let info = self.job(tenant, id).await?;
        if info.row.status == Status::Dismissed {
            return Ok(info);
        }
        let i = id.to_string();
        let _ = self.db(move |s| s.dismiss(&i, now_ms())).await?;
        {
            let mut q = self.lock_queue();
            q.ids.retain(|x| x != id);
        }
        if let Some(rec) = &info.row.slurm {
            // Cancelled here too, not only by the job's monitor: an accepted job (queued after a
            // restart) has none.
            self.cancel_slurm(id, rec).await;
        }
        let running = self.lock_running().get(id).cloned();
        if let Some(r) = running {
            r.dismissed.store(true, Ordering::SeqCst);
            r.cancel.store(true, Ordering::SeqCst);
            r.wake.notify_waiters();
            let mut rx = r.done.subscribe();
            let stopped = tokio::time::timeout(Duration::from_secs(1), rx.wait_for(|d| *d))
                .await
                .is_ok();
            if !stopped {
                warn!(
                    job = id,
                    "still running 1 s after cancellation; files go when it stops"
                );
            }
        }
        self.remove_job_files(id).await;
        self.update_gauges();
        info!(job = id, tenant, "job dismissed");
        self.job(tenant, id).await
    }

    pub(super) async fn remove_job_files(&self, id: &str) {
        let dir = self.job_dir(id);
        let _ = bridge::blocking(move || match std::fs::remove_dir_all(&dir) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => warn!(dir = %dir.display(), error = %e, "cannot remove a job directory"),
        })
        .await;
    }

    /// The result of job `id` of `tenant`.
    ///
    /// # Errors
    /// [`JobsError::NoSuch`] (also for dismissed jobs), [`JobsError::WrongState`] while the job
    /// is not successful.
    pub async fn result(&self, tenant: &str, id: &str) -> Result<ResultFile, JobsError> {
        let info = self.job(tenant, id).await?;
        let row = info.row;
        match row.status {
            Status::Successful => {}
            Status::Dismissed => return Err(JobsError::NoSuch("job")),
            s => {
                return Err(JobsError::WrongState {
                    detail: format!("job {id} is {}; there is no result", s.as_str()),
                    offset: None,
                });
            }
        }
        let path = self
            .job_dir(id)
            .join(format!("result.{}", row.spec.output_format));
        match (row.result_size, row.result_sha256) {
            (Some(size), Some(sha256)) => Ok(ResultFile {
                path,
                size,
                sha256,
                format: row.spec.output_format,
                filename: row.spec.result_filename(id),
                finished_ms: row.finished_ms.unwrap_or(row.created_ms),
            }),
            _ => Err(JobsError::Internal(format!(
                "job {id} is successful but has no result record"
            ))),
        }
    }

    /// Stops taking work: running jobs are cancelled at their next batch or tile (finished tiles
    /// stay as checkpoints and the jobs go back to `accepted`), then waits up to `grace` for the
    /// workers to wind down.
    pub async fn shutdown(&self, grace: Duration) {
        self.begin_shutdown();
        let handles =
            std::mem::take(&mut *self.inner.workers.lock().unwrap_or_else(|e| e.into_inner()));
        let all = futures_util::future::join_all(handles);
        if tokio::time::timeout(grace, all).await.is_err() {
            warn!("jobs still running after the shutdown grace period");
        }
    }

    /// Marks the start of shutdown without waiting (readiness turns false, new jobs are refused,
    /// running jobs are cancelled).
    pub fn begin_shutdown(&self) {
        self.inner.shutdown.send_replace(true);
        for r in self.lock_running().values() {
            r.cancel.store(true, Ordering::SeqCst);
            r.wake.notify_waiters();
        }
    }
}
