//! The one bridge between the async runtime (tokio) and blocking or CPU-bound work.
//!
//! * [`cpu`] runs a closure on a rayon pool and awaits its result through a oneshot channel: the
//!   synchronous denoise path, whose requests are short and CPU-bound.
//! * [`blocking`] runs a closure on tokio's blocking pool: SQLite statements, file hashing, and
//!   the drivers of long jobs, which alternate between file I/O and rayon-parallel kernels (the
//!   kernels still run on rayon's global pool; only the driver thread waits there).
//!
//! Neither ever runs work on a tokio worker thread, and a panic in the closure becomes an error
//! instead of taking the process down (rayon's default would abort).
//!
//! Jobs run on their own rayon pool whose threads call [`lower_priority`] (nice
//! [`JOB_NICE`] on Linux): background work yields the cores to synchronous requests, which are
//! latency-bound, instead of sharing them evenly.

use std::panic::{AssertUnwindSafe, catch_unwind};

use super::JobsError;

/// Nice value of the job pool's threads: the scheduler gives a nice-0 thread about ten times the
/// CPU share of a nice-10 one.
pub const JOB_NICE: i32 = 10;

/// Lowers the calling thread's scheduling priority to [`JOB_NICE`] (Linux; elsewhere, and when
/// the process already runs lower, nothing changes). Threads it spawns inherit it.
pub fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        let tid = rustix::thread::gettid();
        let lower = rustix::process::getpriority_process(Some(tid)).is_ok_and(|p| p < JOB_NICE);
        if lower {
            let _ = rustix::process::setpriority_process(Some(tid), JOB_NICE);
        }
    }
}

/// Runs `f` on `pool` and waits for it without blocking the runtime.
///
/// # Errors
/// [`JobsError::Internal`] when `f` panicked.
pub async fn cpu<T, F>(pool: &rayon::ThreadPool, f: F) -> Result<T, JobsError>
where
    T: Send + 'static,
    F: FnOnce() -> T + Send + 'static,
{
    let (tx, rx) = tokio::sync::oneshot::channel();
    pool.spawn(move || {
        let r = catch_unwind(AssertUnwindSafe(f));
        // The receiver is gone when the request was abandoned; the result is then dropped.
        let _ = tx.send(r);
    });
    match rx.await {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(_)) => Err(JobsError::Internal("a worker panicked".into())),
        Err(_) => Err(JobsError::Internal("a worker vanished".into())),
    }
}

/// Runs `f` on the blocking pool and waits for it without blocking the runtime.
///
/// # Errors
/// [`JobsError::Internal`] when `f` panicked.
pub async fn blocking<T, F>(f: F) -> Result<T, JobsError>
where
    T: Send + 'static,
    F: FnOnce() -> T + Send + 'static,
{
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| JobsError::Internal(format!("a blocking task failed: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn results_and_panics() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(cpu(&pool, || 6 * 7).await.unwrap(), 42);
        assert!(cpu(&pool, || -> u8 { panic!("boom") }).await.is_err());
        // The pool survives the panic.
        assert_eq!(cpu(&pool, || 1).await.unwrap(), 1);
        assert_eq!(blocking(|| "x").await.unwrap(), "x");
        assert!(blocking(|| -> u8 { panic!("boom") }).await.is_err());
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn job_threads_run_at_a_lower_priority() {
        let nice = std::thread::spawn(|| {
            lower_priority();
            rustix::process::getpriority_process(Some(rustix::thread::gettid())).unwrap()
        })
        .join()
        .unwrap();
        assert!(nice >= JOB_NICE);
        // Only that thread: this one keeps its priority.
        let mine = rustix::process::getpriority_process(Some(rustix::thread::gettid())).unwrap();
        assert!(mine < JOB_NICE || mine == nice);
    }
}
