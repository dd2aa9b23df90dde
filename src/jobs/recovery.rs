//! Start-up recovery: what a crash or a kill left behind in the data directory.

use std::path::Path;

use super::JobsError;
use super::ids::valid_id;
use super::store::{Status, Store};

/// Removes every entry of `dir` (best effort).
pub(super) fn clear_dir(dir: &Path) {
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
pub(super) fn remove_stale_files(dir: &Path, store: &Store) -> Result<(), JobsError> {
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
