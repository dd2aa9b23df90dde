//! The [`Jobs`] handle: queue, workers, job lifecycle and the synchronous path.
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
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use sha2::{Digest, Sha256};
use tokio::sync::{Notify, watch};
use tracing::{Instrument, error, info, info_span, warn};

use super::metrics::Metrics;
use super::progress::{JobProgress, ProgressView};
use super::store::{JobRow, JobSpec, Status, Store, Upload};
use super::{JobsError, bridge};
use crate::denoise::{DenoiseError, Params};
use crate::io::{Format, IoError};
use crate::pipeline::{self, Job, NoProgress, OutlierMode, PipelineError, Report, RunOptions};

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
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            data_dir: PathBuf::from("qemd-data"),
            job_concurrency: 1,
            queue_capacity: 16,
            memory_budget: pipeline::DEFAULT_MEMORY_BUDGET,
            job_tile_points: 250_000,
            outlier_alpha: 2.0,
            max_upload_size: 16 << 30,
            sync_concurrency: 8,
            preview_points: super::preview::PREVIEW_POINTS,
        }
    }
}

/// How the client named the format of an upload.
#[derive(Debug, Clone, Default)]
pub struct FormatHint {
    /// `?format=` (a format name or extension).
    pub format: Option<String>,
    /// The client's file name (its extension is a hint too).
    pub filename: Option<String>,
}

/// A job submission, as the API received it (validated here).
#[derive(Debug, Clone)]
pub struct JobRequest {
    /// The input upload's id.
    pub input: String,
    /// Denoising parameters.
    pub params: Params,
    /// Outlier handling.
    pub outliers: OutlierMode,
    /// Outlier threshold (else the configured default).
    pub outlier_alpha: Option<f64>,
    /// Output format (else the input's).
    pub output_format: Option<String>,
}

/// A synchronous request.
#[derive(Debug, Clone)]
pub struct SyncRequest {
    /// Input format (canonical extension).
    pub format: String,
    /// Denoising parameters.
    pub params: Params,
    /// Outlier handling.
    pub outliers: OutlierMode,
    /// Outlier threshold (else the configured default).
    pub outlier_alpha: Option<f64>,
    /// Output format (else the input's).
    pub output_format: Option<String>,
}

/// The answer of a synchronous request.
#[derive(Debug, Clone)]
pub struct SyncOutput {
    /// The denoised file.
    pub bytes: Vec<u8>,
    /// Its format (extension).
    pub format: String,
    /// What the run did (paths replaced by `input` and `result`).
    pub report: Report,
}

/// A job with its live progress.
#[derive(Debug, Clone)]
pub struct JobInfo {
    /// The stored row.
    pub row: JobRow,
    /// Progress: live while running, complete when successful, `None` otherwise.
    pub progress: Option<ProgressView>,
}

/// A downloadable result.
#[derive(Debug, Clone)]
pub struct ResultFile {
    /// Where it is.
    pub path: PathBuf,
    /// Bytes.
    pub size: u64,
    /// SHA-256 (hex): the strong ETag.
    pub sha256: String,
    /// Format (extension).
    pub format: String,
    /// When the job finished, ms since the Unix epoch.
    pub finished_ms: i64,
}

/// The canonical extension for a format name (`kitti` → `bin`), `None` when unknown.
pub fn canonical_format(name: &str) -> Option<String> {
    let lower = name.trim().to_ascii_lowercase();
    let f = Format::from_name(&lower)?;
    Some(match f {
        Format::Kitti => "bin".to_string(),
        Format::Nuscenes => "pcd.bin".to_string(),
        _ => lower,
    })
}

/// The output extension of a job: the requested one, else the input's.
///
/// # Errors
/// [`JobsError::Invalid`] for an unknown format.
pub fn output_format_for(requested: Option<&str>, input: &str) -> Result<String, JobsError> {
    match requested {
        None => Ok(input.to_string()),
        Some(name) => canonical_format(name).ok_or_else(|| JobsError::Invalid {
            field: "output_format".into(),
            detail: format!(
                "unknown format `{name}` (expected ply, obj, off, xyz, txt, pts, bin, pcd, las or laz)"
            ),
        }),
    }
}

/// The pipeline's format for an extension the service produced (always known).
pub(super) fn format_of(ext: &str) -> Result<Format, JobsError> {
    Format::from_name(ext).ok_or_else(|| JobsError::Internal(format!("unknown extension {ext}")))
}

/// Milliseconds since the Unix epoch.
pub(super) fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// A fresh random id.
pub(super) fn new_id() -> String {
    uuid::Uuid::new_v4().to_string()
}

/// True for a well-formed id (anything else cannot exist, and never reaches the file system).
pub(super) fn valid_id(id: &str) -> bool {
    uuid::Uuid::parse_str(id).is_ok_and(|u| u.hyphenated().to_string() == id)
}

/// Lower-case hex.
pub(super) fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

/// SHA-256 of a file, streamed.
pub(super) fn sha256_file(path: &Path) -> Result<String, JobsError> {
    let mut f = std::fs::File::open(path)
        .map_err(|e| JobsError::io(format!("open {}", path.display()), e))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f
            .read(&mut buf)
            .map_err(|e| JobsError::io(format!("read {}", path.display()), e))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(hex(&h.finalize()))
}

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

/// Is a pipeline failure the input's or the request's fault (as opposed to the server's)?
fn client_fault(e: &PipelineError) -> bool {
    match e {
        PipelineError::Io(io) => !matches!(io, IoError::Io { .. }),
        PipelineError::Denoise { .. } | PipelineError::Params(_) => true,
        _ => false,
    }
}

/// Maps a parameter error to the request field it names.
pub(super) fn param_error(e: DenoiseError) -> JobsError {
    match e {
        DenoiseError::Param { name, detail } => JobsError::Invalid {
            field: match name {
                "outlier-alpha" => "outlier_alpha".into(),
                "outliers" => "outliers".into(),
                // CLI flags are kebab-case, JSON fields snake_case.
                n => format!("params.{}", n.replace('-', "_")),
            },
            detail,
        },
        other => JobsError::Invalid {
            field: "params".into(),
            detail: other.to_string(),
        },
    }
}

/// Checks what can be checked without the input file.
fn validate_params(params: &Params, alpha: f64) -> Result<(), JobsError> {
    params.validate().map_err(param_error)?;
    if !(alpha.is_finite() && alpha >= 0.0) {
        return Err(JobsError::Invalid {
            field: "outlier_alpha".into(),
            detail: format!("must be finite and ≥ 0, got {alpha}"),
        });
    }
    Ok(())
}

/// Refuses output options a sink would refuse later (noise flags in KITTI, OBJ, OFF).
fn validate_output(outliers: OutlierMode, output: &str) -> Result<(), JobsError> {
    let f = format_of(output)?;
    if outliers == OutlierMode::Classify
        && matches!(
            f,
            Format::Kitti | Format::Nuscenes | Format::Bin(_) | Format::Obj | Format::Off
        )
    {
        return Err(JobsError::Invalid {
            field: "outliers".into(),
            detail: format!(
                "`classify` needs an output format with room for a flag; {output} has none \
                 (use remove, or another output_format)"
            ),
        });
    }
    Ok(())
}

/// A running job, as the worker and a DELETE share it.
struct Running {
    cancel: Arc<AtomicBool>,
    progress: Arc<JobProgress>,
    /// Set by a DELETE: the worker must not record the outcome and must remove its files.
    dismissed: AtomicBool,
    /// Becomes true when the worker is done with the job's files.
    done: watch::Sender<bool>,
}

#[derive(Default)]
struct Queue {
    ids: VecDeque<String>,
    /// Slots promised to submissions still being written to the store.
    reserved: usize,
}

pub(super) struct Inner {
    pub(super) settings: Settings,
    pub(super) store: Store,
    pub(super) metrics: Metrics,
    // std Mutexes below: short critical sections, never held across an await.
    queue: Mutex<Queue>,
    wake: Notify,
    running: Mutex<HashMap<String, Arc<Running>>>,
    /// Uploads with a PATCH in progress (one at a time each).
    pub(super) patching: Mutex<std::collections::HashSet<String>>,
    shutdown: watch::Sender<bool>,
    workers: Mutex<Vec<tokio::task::JoinHandle<()>>>,
    /// The synchronous path's own rayon pool, so that robot requests do not queue behind the
    /// tiles of long jobs.
    sync_pool: rayon::ThreadPool,
    /// The jobs' rayon pool, at a lower priority (see [`bridge::lower_priority`]).
    job_pool: rayon::ThreadPool,
    sync_slots: tokio::sync::Semaphore,
    /// Synchronous requests computing at once (one per core of the synchronous pool); the others
    /// wait here in arrival order. Handing rayon more top-level work than it has threads lets a
    /// thread waiting inside one request pick up a newer one, which buries the older request
    /// under it: measured, that made the p99 latency 50× the p50.
    sync_running: tokio::sync::Semaphore,
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
        let (store, queued) = bridge::blocking(move || -> Result<_, JobsError> {
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
            let queued = store.ids_with_status(Status::Accepted)?;
            Ok((store, queued))
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

    pub(super) fn upload_path(&self, id: &str, ext: &str) -> PathBuf {
        self.data_dir().join("uploads").join(format!("{id}.{ext}"))
    }

    pub(super) fn part_path(&self, id: &str) -> PathBuf {
        self.data_dir().join("uploads").join(format!("{id}.part"))
    }

    fn shutting_down(&self) -> bool {
        *self.inner.shutdown.borrow()
    }

    fn update_gauges(&self) {
        let depth = self.lock_queue().ids.len();
        let running = self.lock_running().len();
        let m = &self.inner.metrics;
        m.queue_depth.set(i64::try_from(depth).unwrap_or(i64::MAX));
        m.running.set(i64::try_from(running).unwrap_or(i64::MAX));
    }

    fn lock_queue(&self) -> std::sync::MutexGuard<'_, Queue> {
        self.inner.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn lock_running(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<Running>>> {
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
    /// [`JobsError::Conflict`] when the upload is incomplete, [`JobsError::QueueFull`],
    /// [`JobsError::ShuttingDown`].
    pub async fn submit(&self, tenant: &str, req: JobRequest) -> Result<JobRow, JobsError> {
        if self.shutting_down() {
            return Err(JobsError::ShuttingDown);
        }
        let alpha = req
            .outlier_alpha
            .unwrap_or(self.inner.settings.outlier_alpha);
        validate_params(&req.params, alpha)?;
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
        let Some(input_format) = upload.format.clone().filter(|_| upload.complete) else {
            return Err(JobsError::Conflict {
                detail: format!(
                    "upload {} is incomplete ({} of {} bytes)",
                    upload.id,
                    upload.size,
                    upload.length.unwrap_or(0)
                ),
                offset: Some(upload.size),
            });
        };
        let output = output_format_for(req.output_format.as_deref(), &input_format)?;
        let mesh = req.params.mesh_mode(upload.faces.is_some());
        if mesh && req.outliers != OutlierMode::Off {
            return Err(JobsError::Invalid {
                field: "outliers".into(),
                detail: "applies to point clouds, not meshes (set params.knn for point mode)"
                    .into(),
            });
        }
        validate_output(req.outliers, &output)?;
        let settings = &self.inner.settings;
        let tile_points = (!mesh && upload.points.is_none_or(|n| n > settings.job_tile_points))
            .then_some(settings.job_tile_points);
        let row = JobRow {
            id: new_id(),
            tenant: tenant.to_string(),
            upload: upload.id.clone(),
            status: Status::Accepted,
            spec: JobSpec {
                params: req.params,
                outliers: req.outliers,
                outlier_alpha: alpha,
                output_format: output,
                memory_budget: settings.memory_budget,
                tile_points,
            },
            created_ms: now_ms(),
            started_ms: None,
            finished_ms: None,
            report: None,
            error: None,
            result_size: None,
            result_sha256: None,
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
        info!(job = %row.id, tenant, upload = %row.upload, "job accepted");
        Ok(row)
    }

    /// The job `id` of `tenant`, with live progress.
    ///
    /// # Errors
    /// [`JobsError::NotFound`].
    pub async fn job(&self, tenant: &str, id: &str) -> Result<JobInfo, JobsError> {
        if !valid_id(id) {
            return Err(JobsError::NotFound("job"));
        }
        let (t, i) = (tenant.to_string(), id.to_string());
        let row = self
            .db(move |s| s.job(Some(&t), &i))
            .await?
            .ok_or(JobsError::NotFound("job"))?;
        Ok(self.with_progress(row))
    }

    fn with_progress(&self, row: JobRow) -> JobInfo {
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

    /// Dismisses job `id` of `tenant`: a queued job leaves the queue, a running one is cancelled
    /// (waiting up to a second for it to stop), and its files are removed.
    ///
    /// # Errors
    /// [`JobsError::NotFound`].
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
        let running = self.lock_running().get(id).cloned();
        if let Some(r) = running {
            r.dismissed.store(true, Ordering::SeqCst);
            r.cancel.store(true, Ordering::SeqCst);
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

    async fn remove_job_files(&self, id: &str) {
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
    /// [`JobsError::NotFound`] (also for dismissed jobs), [`JobsError::Conflict`] while the job
    /// is not successful.
    pub async fn result(&self, tenant: &str, id: &str) -> Result<ResultFile, JobsError> {
        let info = self.job(tenant, id).await?;
        let row = info.row;
        match row.status {
            Status::Successful => {}
            Status::Dismissed => return Err(JobsError::NotFound("job")),
            s => {
                return Err(JobsError::Conflict {
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
                finished_ms: row.finished_ms.unwrap_or(row.created_ms),
            }),
            _ => Err(JobsError::Internal(format!(
                "job {id} is successful but has no result record"
            ))),
        }
    }

    async fn worker(self, mut shutdown: watch::Receiver<bool>) {
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

    async fn run_job(&self, id: String) {
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

    async fn run_row(&self, row: JobRow) {
        let id = row.id.clone();
        let u = row.upload.clone();
        let upload = self.db(move |s| s.upload(None, &u)).await;
        let running = Arc::new(Running {
            cancel: Arc::new(AtomicBool::new(false)),
            progress: Arc::new(JobProgress::default()),
            dismissed: AtomicBool::new(false),
            done: watch::channel(false).0,
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
            })) => (self.upload_path(&uid, &ext), ext),
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
        let dir = self.job_dir(&id);
        let output = dir.join(format!("result.{}", row.spec.output_format));
        let outcome = self.execute(&row, &input, &dir, &output, &running).await;
        let _ = self.lock_running().remove(&id);
        let dismissed = running.dismissed.load(Ordering::SeqCst);
        match outcome {
            _ if dismissed => {
                info!("stopped: dismissed");
                self.remove_job_files(&id).await;
            }
            Ok(report) => self.finish_success(&id, report, &dir, &output).await,
            Err(PipelineError::Cancelled) if self.shutting_down() => {
                // Back in the queue of the next start; the finished tiles stay as checkpoints.
                let i = id.clone();
                let _ = self
                    .db(move |s| s.transition(&i, Status::Running, Status::Accepted, None, None))
                    .await;
                info!("interrupted by shutdown; resumes at the next start");
            }
            Err(e) => {
                let msg = scrub(&e.to_string(), &input.0, &output, self.data_dir());
                if client_fault(&e) {
                    info!(error = %msg, "failed");
                } else {
                    error!(error = %e, "failed");
                }
                self.finish_failed(&id, &msg).await;
                self.remove_job_files(&id).await;
            }
        }
        running.done.send_replace(true);
        self.update_gauges();
    }

    /// Runs the pipeline for `row` on a blocking thread.
    async fn execute(
        &self,
        row: &JobRow,
        input: &(PathBuf, String),
        dir: &Path,
        output: &Path,
        running: &Running,
    ) -> Result<Report, PipelineError> {
        let spec = &row.spec;
        let job = Job {
            input: input.0.clone(),
            output: output.to_path_buf(),
            input_format: format_of(&input.1).ok(),
            output_format: format_of(&spec.output_format).ok(),
            params: spec.params.clone(),
            outliers: spec.outliers,
            outlier_alpha: spec.outlier_alpha,
        };
        let opts = RunOptions {
            memory_budget: spec.memory_budget,
            temp_dir: None,
            tile_points: spec.tile_points,
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
        match run {
            Ok(r) => r,
            Err(e) => Err(PipelineError::TempDir {
                path: PathBuf::from("worker"),
                detail: e.to_string(),
            }),
        }
    }

    async fn finish_success(&self, id: &str, mut report: Report, dir: &Path, output: &Path) {
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
                self.finish_failed(id, "internal error while storing the result")
                    .await;
                self.remove_job_files(id).await;
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

    async fn finish_failed(&self, id: &str, msg: &str) {
        let (i, m) = (id.to_string(), msg.to_string());
        if let Err(e) = self.db(move |s| s.finish_failure(&i, now_ms(), &m)).await {
            error!(error = %e, "cannot record a failed job");
        }
    }

    /// Stops taking work: running jobs are cancelled at their next batch or tile (finished tiles
    /// stay as checkpoints and the jobs go back to `accepted`), then waits up to `grace` for the
    /// workers to wind down.
    pub async fn shutdown(&self, grace: Duration) {
        self.inner.shutdown.send_replace(true);
        for r in self.lock_running().values() {
            r.cancel.store(true, Ordering::SeqCst);
        }
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
        }
    }

    // ---------------------------------------------------------------------------------------
    // Synchronous path

    /// Denoises `body` (a whole file in `req.format`) now and returns the result; the CPU work
    /// runs on the synchronous path's rayon pool. Dropping the future cancels the run.
    ///
    /// # Errors
    /// [`JobsError::Busy`] beyond `sync_concurrency` requests, [`JobsError::Invalid`] for bad
    /// parameters, [`JobsError::BadContent`] for input the readers or the denoiser refuse.
    pub async fn denoise_now(
        &self,
        body: impl AsRef<[u8]> + Send + 'static,
        req: SyncRequest,
    ) -> Result<SyncOutput, JobsError> {
        if self.shutting_down() {
            return Err(JobsError::ShuttingDown);
        }
        let _slot = self.inner.sync_slots.try_acquire().map_err(|_| {
            // A 429 is a rejected request too (issue 15: it was not counted).
            let m = &self.inner.metrics;
            m.sync_requests.with_label_values(&["rejected"]).inc();
            JobsError::Busy
        })?;
        let alpha = req
            .outlier_alpha
            .unwrap_or(self.inner.settings.outlier_alpha);
        validate_params(&req.params, alpha)?;
        let input_format = canonical_format(&req.format).ok_or_else(|| {
            JobsError::UnsupportedFormat(format!("unknown format `{}`", req.format))
        })?;
        let output_format = output_format_for(req.output_format.as_deref(), &input_format)?;
        validate_output(req.outliers, &output_format)?;
        let cancel = Arc::new(AtomicBool::new(false));
        // Dropped when the client goes away before the answer: the run stops at its next check.
        struct CancelOnDrop(Arc<AtomicBool>);
        impl Drop for CancelOnDrop {
            fn drop(&mut self) {
                self.0.store(true, Ordering::Relaxed);
            }
        }
        let _guard = CancelOnDrop(cancel.clone());
        let tmp = self.data_dir().join("tmp");
        let data_dir = self.data_dir().to_path_buf();
        let budget = self.inner.settings.memory_budget;
        let _running = self
            .inner
            .sync_running
            .acquire()
            .await
            .map_err(|_| JobsError::ShuttingDown)?;
        let run = bridge::cpu(&self.inner.sync_pool, move || {
            let dir = tempfile::Builder::new()
                .prefix("sync-")
                .tempdir_in(&tmp)
                .map_err(|e| JobsError::io("create a request directory", e))?;
            let input = dir.path().join(format!("in.{input_format}"));
            let output = dir.path().join(format!("out.{output_format}"));
            std::fs::write(&input, body.as_ref())
                .map_err(|e| JobsError::io("write the request body", e))?;
            let job = Job {
                input: input.clone(),
                output: output.clone(),
                input_format: format_of(&input_format).ok(),
                output_format: format_of(&output_format).ok(),
                params: req.params,
                outliers: req.outliers,
                outlier_alpha: alpha,
            };
            let opts = RunOptions {
                memory_budget: budget,
                temp_dir: Some(dir.path().to_path_buf()),
                tile_points: None,
                progress: Arc::new(NoProgress),
                cancel,
                work_dir: None,
            };
            match pipeline::run(&job, &opts) {
                Ok(mut report) => {
                    let bytes =
                        std::fs::read(&output).map_err(|e| JobsError::io("read the result", e))?;
                    report.input = PathBuf::from("input");
                    report.output = PathBuf::from(format!("result.{output_format}"));
                    Ok(SyncOutput {
                        bytes,
                        format: output_format,
                        report,
                    })
                }
                Err(PipelineError::Params(e)) => Err(param_error(e)),
                Err(e) if client_fault(&e) => Err(JobsError::BadContent(scrub(
                    &e.to_string(),
                    &input,
                    &output,
                    &data_dir,
                ))),
                Err(e) => Err(JobsError::Internal(e.to_string())),
            }
        })
        .await;
        let m = &self.inner.metrics;
        match &run {
            Ok(Ok(out)) => {
                m.observe("sync", &out.report);
                m.sync_requests.with_label_values(&["ok"]).inc();
            }
            Ok(Err(JobsError::Internal(_))) | Err(_) => {
                m.sync_requests.with_label_values(&["error"]).inc();
            }
            Ok(Err(_)) => m.sync_requests.with_label_values(&["rejected"]).inc(),
        }
        run?
    }
}

/// Removes every entry of `dir` (best effort).
fn clear_dir(dir: &Path) {
    if let Ok(entries) = std::fs::read_dir(dir) {
        for e in entries.flatten() {
            let p = e.path();
            let _ = if p.is_dir() {
                std::fs::remove_dir_all(&p)
            } else {
                std::fs::remove_file(&p)
            };
        }
    }
}

/// Start-up cleanup: job directories of dismissed or unknown jobs, `.part` files of uploads that
/// are not resumable ones (a one-shot upload cut off by a crash), temporary files.
fn remove_stale_files(dir: &Path, store: &Store) -> Result<(), JobsError> {
    if let Ok(entries) = std::fs::read_dir(dir.join("jobs")) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let keep = valid_id(&name)
                && store
                    .job(None, &name)?
                    .is_some_and(|j| j.status != Status::Dismissed);
            if !keep {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
    let partial = store.partial_uploads()?;
    if let Ok(entries) = std::fs::read_dir(dir.join("uploads")) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if let Some(id) = name.strip_suffix(".part")
                && !partial.iter().any(|p| p == id)
            {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_formats_and_scrubbing() {
        let id = new_id();
        assert!(valid_id(&id));
        assert!(!valid_id("../../etc/passwd"));
        assert!(!valid_id(&id.to_uppercase()));
        assert_eq!(canonical_format("KITTI").as_deref(), Some("bin"));
        assert_eq!(canonical_format("laz").as_deref(), Some("laz"));
        assert_eq!(canonical_format("doc"), None);
        assert_eq!(output_format_for(None, "laz").unwrap(), "laz");
        assert!(matches!(
            output_format_for(Some("doc"), "ply"),
            Err(JobsError::Invalid { field, .. }) if field == "output_format"
        ));
        let s = scrub(
            "/d/uploads/x.ply: bad header; /d/jobs/y/result.ply; /d/other",
            Path::new("/d/uploads/x.ply"),
            Path::new("/d/jobs/y/result.ply"),
            Path::new("/d"),
        );
        assert_eq!(s, "input: bad header; result; <data>/other");
        assert_eq!(hex(&[0, 15, 255]), "000fff");
    }

    #[test]
    fn parameter_errors_name_fields() {
        let p = Params {
            knn: Some(1),
            ..Params::default()
        };
        match validate_params(&p, 2.0) {
            Err(JobsError::Invalid { field, .. }) => assert_eq!(field, "params.knn"),
            other => panic!("{other:?}"),
        }
        match validate_params(&Params::default(), -1.0) {
            Err(JobsError::Invalid { field, .. }) => assert_eq!(field, "outlier_alpha"),
            other => panic!("{other:?}"),
        }
        assert!(validate_output(OutlierMode::Classify, "bin").is_err());
        assert!(validate_output(OutlierMode::Remove, "bin").is_ok());
    }
}
