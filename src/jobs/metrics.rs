//! Prometheus metrics of the service (the `prometheus` crate, text exposition).
//!
//! | metric | kind | labels |
//! |---|---|---|
//! | `qemd_jobs` | gauge, set at scrape time from the store | `state` |
//! | `qemd_queue_depth` | gauge: accepted jobs waiting for a slot | |
//! | `qemd_jobs_running` | gauge | |
//! | `qemd_points_processed_total` | counter: points read by finished runs | `path` = job, sync |
//! | `qemd_phase_duration_seconds` | histogram of pipeline phase wall times | `phase` |
//! | `qemd_run_duration_seconds` | histogram of whole runs | `path` |
//! | `qemd_sync_requests_total` | counter | `outcome` = ok, rejected, error, timeout |
//! | `qemd_sync_spooled_total` | counter: synchronous runs that needed a temporary file (a body above the memory budget, E57 or COPC output) | |
//! | `qemd_uploads_total`, `qemd_upload_bytes_total` | counters of completed uploads | |

use prometheus::{
    Encoder, HistogramOpts, HistogramVec, IntCounter, IntCounterVec, IntGauge, IntGaugeVec, Opts,
    Registry, TextEncoder,
};

use super::JobsError;
use super::store::Status;
use crate::pipeline::Report;

/// The service's metrics in their own registry.
#[derive(Clone)]
pub struct Metrics {
    registry: Registry,
    /// Jobs by state.
    pub jobs: IntGaugeVec,
    /// Accepted jobs waiting for a slot.
    pub queue_depth: IntGauge,
    /// Jobs running now.
    pub running: IntGauge,
    /// Points read by finished runs.
    pub points: IntCounterVec,
    /// Wall seconds per pipeline phase.
    pub phases: HistogramVec,
    /// Wall seconds per run.
    pub runs: HistogramVec,
    /// Synchronous requests by outcome.
    pub sync_requests: IntCounterVec,
    /// Synchronous runs that needed a temporary file.
    pub sync_spooled: IntCounter,
    /// Completed uploads.
    pub uploads: IntCounter,
    /// Bytes of completed uploads.
    pub upload_bytes: IntCounter,
}

impl std::fmt::Debug for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Metrics").finish_non_exhaustive()
    }
}

fn internal(e: prometheus::Error) -> JobsError {
    JobsError::Internal(format!("metrics: {e}"))
}

impl Metrics {
    /// Creates and registers every metric.
    ///
    /// # Errors
    /// Registration failures (a programming error: duplicate names).
    pub fn new() -> Result<Metrics, JobsError> {
        let registry = Registry::new();
        let buckets = prometheus::exponential_buckets(0.005, 2.0, 18).map_err(internal)?;
        let m = Metrics {
            jobs: IntGaugeVec::new(Opts::new("qemd_jobs", "Jobs by state"), &["state"])
                .map_err(internal)?,
            queue_depth: IntGauge::new("qemd_queue_depth", "Accepted jobs waiting for a slot")
                .map_err(internal)?,
            running: IntGauge::new("qemd_jobs_running", "Jobs running now").map_err(internal)?,
            points: IntCounterVec::new(
                Opts::new(
                    "qemd_points_processed_total",
                    "Points read by finished runs",
                ),
                &["path"],
            )
            .map_err(internal)?,
            phases: HistogramVec::new(
                HistogramOpts::new(
                    "qemd_phase_duration_seconds",
                    "Wall time of pipeline phases",
                )
                .buckets(buckets.clone()),
                &["phase"],
            )
            .map_err(internal)?,
            runs: HistogramVec::new(
                HistogramOpts::new("qemd_run_duration_seconds", "Wall time of whole runs")
                    .buckets(buckets),
                &["path"],
            )
            .map_err(internal)?,
            sync_requests: IntCounterVec::new(
                Opts::new(
                    "qemd_sync_requests_total",
                    "Synchronous denoise requests by outcome",
                ),
                &["outcome"],
            )
            .map_err(internal)?,
            sync_spooled: IntCounter::new(
                "qemd_sync_spooled_total",
                "Synchronous runs that needed a temporary file",
            )
            .map_err(internal)?,
            uploads: IntCounter::new("qemd_uploads_total", "Completed uploads")
                .map_err(internal)?,
            upload_bytes: IntCounter::new("qemd_upload_bytes_total", "Bytes of completed uploads")
                .map_err(internal)?,
            registry,
        };
        let r = &m.registry;
        r.register(Box::new(m.jobs.clone())).map_err(internal)?;
        r.register(Box::new(m.queue_depth.clone()))
            .map_err(internal)?;
        r.register(Box::new(m.running.clone())).map_err(internal)?;
        r.register(Box::new(m.points.clone())).map_err(internal)?;
        r.register(Box::new(m.phases.clone())).map_err(internal)?;
        r.register(Box::new(m.runs.clone())).map_err(internal)?;
        r.register(Box::new(m.sync_requests.clone()))
            .map_err(internal)?;
        r.register(Box::new(m.sync_spooled.clone()))
            .map_err(internal)?;
        r.register(Box::new(m.uploads.clone())).map_err(internal)?;
        r.register(Box::new(m.upload_bytes.clone()))
            .map_err(internal)?;
        for s in Status::ALL {
            m.jobs.with_label_values(&[s.as_str()]).set(0);
        }
        for p in ["job", "sync"] {
            m.points.with_label_values(&[p]).inc_by(0);
        }
        for o in ["ok", "rejected", "error", "timeout"] {
            m.sync_requests.with_label_values(&[o]).inc_by(0);
        }
        Ok(m)
    }

    /// Books a finished run: points, phase and run durations.
    pub fn observe(&self, path: &str, report: &Report) {
        self.points
            .with_label_values(&[path])
            .inc_by(report.points_in);
        for p in &report.phases {
            self.phases
                .with_label_values(&[p.name.as_str()])
                .observe(p.wall_s);
        }
        self.runs.with_label_values(&[path]).observe(report.wall_s);
    }

    /// The text exposition of every metric.
    ///
    /// # Errors
    /// Encoding failures.
    pub fn render(&self) -> Result<String, JobsError> {
        let mut buf = Vec::new();
        TextEncoder::new()
            .encode(&self.registry.gather(), &mut buf)
            .map_err(internal)?;
        String::from_utf8(buf).map_err(|e| JobsError::Internal(format!("metrics: {e}")))
    }
}
