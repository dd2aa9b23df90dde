//! Cancellation of the long neighbourhood passes, without an async runtime.
//!
//! The k-NN passes run deep below the pipeline (pipeline → tiling → denoise → neighbours), and
//! the layers in between have no cancellation parameter. So the caller that owns a cancel flag
//! installs it for the duration of a closure with [`with_cancel`], on its own thread; the
//! all-points pass ([`super::KnnIndex::knn_all`]) reads it once on entry, hands it to its rayon
//! workers, checks it per grid cell and per fallback query, and returns
//! [`super::NeighboursError::Cancelled`] once it is set. Nothing here knows about tokio or
//! signals: the flag is a plain [`AtomicBool`] that a Ctrl-C handler or a job service sets.
//!
//! ```text
//!   pipeline thread                       rayon workers
//!   with_cancel(&flag, || {               knn_all: for each cell / fallback query:
//!       cloud::run(..)  ── knn_all ──▶        if flag.load() { stop, Err(Cancelled) }
//!   })                                    (one cell's work is bounded, so the stop is prompt)
//! ```

use std::cell::RefCell;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

thread_local! {
    /// The flag installed by the innermost [`with_cancel`] on this thread.
    static CURRENT: RefCell<Option<Arc<AtomicBool>>> = const { RefCell::new(None) };
}

/// Runs `f` with `flag` as this thread's cancellation flag: k-NN passes started by `f` on this
/// thread stop with [`super::NeighboursError::Cancelled`] soon after `flag` is set. The previous
/// flag (if any) is restored afterwards, also when `f` panics.
pub fn with_cancel<R>(flag: &Arc<AtomicBool>, f: impl FnOnce() -> R) -> R {
    struct Restore(Option<Arc<AtomicBool>>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let prev = self.0.take();
            CURRENT.with(|c| *c.borrow_mut() = prev);
        }
    }
    let prev = CURRENT.with(|c| c.borrow_mut().replace(flag.clone()));
    let _restore = Restore(prev);
    f()
}

/// The flag installed on this thread, if any.
pub(crate) fn current() -> Option<Arc<AtomicBool>> {
    CURRENT.with(|c| c.borrow().clone())
}

/// True when the flag installed on this thread is set.
pub fn requested() -> bool {
    CURRENT.with(|c| {
        c.borrow()
            .as_ref()
            .is_some_and(|f| f.load(Ordering::Relaxed))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scopes_nest_and_restore() {
        let a = Arc::new(AtomicBool::new(true));
        let b = Arc::new(AtomicBool::new(false));
        assert!(!requested());
        with_cancel(&a, || {
            assert!(requested());
            with_cancel(&b, || assert!(!requested()));
            assert!(requested());
        });
        assert!(!requested());
        assert!(current().is_none());
    }
}
