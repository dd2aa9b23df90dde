//! Wall-clock limits (issue 15): a job's run and a synchronous request end when their limit
//! (`job_time_limit`, `sync_time_limit`) is hit, whatever the input does.
//!
//! A [`Deadline`] is a timer on the runtime that sets the run's cancel flag once the limit has
//! passed; the pipeline then stops at its next check (per k-NN cell and query, between batches,
//! tiles and phases) and returns `Cancelled`, which the caller turns into the limit's error
//! because [`Deadline::expired`] says why the flag was set. A run that finishes in the same
//! instant keeps its result: only a run that stopped is reported as over its limit.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use super::JobsError;

/// Default `job_time_limit`: six hours, several times the longest job the default limits admit
/// (docs/DECISIONS.md, "Wall-clock limits").
pub const JOB_TIME_LIMIT: Duration = Duration::from_secs(6 * 3600);

/// Default `sync_time_limit`: one minute, the read timeout of common HTTP clients and proxies.
pub const SYNC_TIME_LIMIT: Duration = Duration::from_secs(60);

/// A limit running against one run; dropping it disarms the timer.
pub(super) struct Deadline {
    limit: Duration,
    at: tokio::time::Instant,
    key: &'static str,
    expired: Arc<AtomicBool>,
    timer: tokio::task::JoinHandle<()>,
}

impl Deadline {
    /// Starts the clock: after `limit`, `cancel` is set. `key` names the setting in messages.
    /// Needs a tokio runtime.
    pub(super) fn arm(limit: Duration, key: &'static str, cancel: Arc<AtomicBool>) -> Deadline {
        let expired = Arc::new(AtomicBool::new(false));
        let flag = expired.clone();
        let timer = tokio::spawn(async move {
            tokio::time::sleep(limit).await;
            flag.store(true, Ordering::SeqCst);
            cancel.store(true, Ordering::SeqCst);
        });
        Deadline {
            limit,
            at: tokio::time::Instant::now() + limit,
            key,
            expired,
            timer,
        }
    }

    /// Completes once the limit has passed.
    pub(super) async fn passed(&self) {
        tokio::time::sleep_until(self.at).await;
    }

    /// True once the limit has passed (and the cancel flag was set for it).
    pub(super) fn expired(&self) -> bool {
        self.expired.load(Ordering::SeqCst)
    }

    /// Stops the clock (the run is over); [`Deadline::expired`] keeps its answer.
    pub(super) fn disarm(&self) {
        self.timer.abort();
    }

    /// The error of a run stopped by this limit.
    pub(super) fn error(&self) -> JobsError {
        JobsError::TimeLimit {
            limit: self.limit,
            key: self.key,
        }
    }
}

impl Drop for Deadline {
    fn drop(&mut self) {
        self.timer.abort();
    }
}

/// `limit` as people write it: `6h`, `60s`, `1m 30s`, `250ms`.
pub fn format_limit(limit: Duration) -> String {
    humantime::format_duration(limit).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn sets_the_flag_after_the_limit_and_not_before() {
        let cancel = Arc::new(AtomicBool::new(false));
        let d = Deadline::arm(Duration::from_millis(50), "sync_time_limit", cancel.clone());
        assert!(!d.expired() && !cancel.load(Ordering::SeqCst));
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert!(d.expired() && cancel.load(Ordering::SeqCst));
        assert_eq!(
            d.error().to_string(),
            "exceeded the time limit of 50ms (sync_time_limit)"
        );

        // Dropped before the limit: the flag stays clear.
        let cancel = Arc::new(AtomicBool::new(false));
        drop(Deadline::arm(
            Duration::from_millis(50),
            "job_time_limit",
            cancel.clone(),
        ));
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert!(!cancel.load(Ordering::SeqCst));
        assert_eq!(format_limit(JOB_TIME_LIMIT), "6h");
    }
}
