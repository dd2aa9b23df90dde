//! Runs a computation without the GIL, on a worker thread, while the calling thread watches for
//! Python signals: Ctrl-C sets the run's cancel flag (the kernels check it inside their k-NN
//! passes and the pipeline per batch and tile) and raises `KeyboardInterrupt` once the run stops.
//! `threads` runs it on a pool of that many threads (results are bit-identical for any count).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::Duration;

use pyo3::prelude::*;

/// How often the calling thread looks for a signal.
const POLL: Duration = Duration::from_millis(100);

/// Runs `f(cancel)` as described in the module overview. `Err` is raised as `error` says; a
/// signal's exception wins over the run's own result.
pub fn run<T, F>(py: Python<'_>, threads: Option<usize>, f: F) -> PyResult<T>
where
    T: Send,
    F: FnOnce(&Arc<AtomicBool>) -> T + Send,
{
    let pool = match threads {
        None => None,
        Some(0) => {
            return Err(crate::error("threads: must be at least 1, got 0"));
        }
        Some(n) => Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| crate::error(&format!("threads: {e}")))?,
        ),
    };
    let cancel = Arc::new(AtomicBool::new(false));
    // Set by the worker when it is done; the calling thread waits on it without the GIL.
    let done = (Mutex::new(false), Condvar::new());
    std::thread::scope(|s| {
        let flag = Arc::clone(&cancel);
        let finished = &done;
        let worker = s.spawn(move || {
            let out = match &pool {
                Some(p) => p.install(|| f(&flag)),
                None => f(&flag),
            };
            let (lock, cv) = finished;
            *lock.lock().unwrap_or_else(PoisonError::into_inner) = true;
            cv.notify_all();
            out
        });
        let mut interrupted = None;
        loop {
            let over = py.detach(|| {
                let (lock, cv) = &done;
                let guard = lock.lock().unwrap_or_else(PoisonError::into_inner);
                let (guard, _) = cv
                    .wait_timeout_while(guard, POLL, |over| !*over)
                    .unwrap_or_else(PoisonError::into_inner);
                *guard
            });
            // A worker that panicked never sets the flag.
            if over || worker.is_finished() {
                break;
            }
            if interrupted.is_none()
                && let Err(e) = py.check_signals()
            {
                cancel.store(true, Ordering::Relaxed);
                interrupted = Some(e);
            }
        }
        let out = py.detach(move || worker.join());
        let out = match out {
            Ok(v) => v,
            Err(panic) => std::panic::resume_unwind(panic),
        };
        match interrupted {
            Some(e) => Err(e),
            None => Ok(out),
        }
    })
}
