//! The exclusive lock a single-task phase (or a partition part) holds on its work directory
//! while it runs, so that a duplicated task (an engine's retry racing the original) waits and then finds the work
//! committed instead of writing the same files at once. The operating system releases it when
//! the holder exits, however it exits (a SIGKILL included).

use std::fs::File;
use std::path::Path;

use super::Phase;
use super::layout::{lock_path, part_lock_path, range_lock_path};
use crate::io::IoError;

/// A held lock; released on drop.
#[derive(Debug)]
pub struct PhaseLock {
    file: File,
}

impl PhaseLock {
    /// Waits for and takes `phase`'s lock in `dir`.
    ///
    /// # Errors
    /// The lock file cannot be created or locked (a file system without locks).
    pub fn acquire(dir: &Path, phase: Phase) -> Result<PhaseLock, IoError> {
        PhaseLock::at(&lock_path(dir, phase))
    }
}

impl PhaseLock {
    /// Waits for and takes the lock of partition part `part` in `dir` (each part is written by
    /// one task at a time).
    ///
    /// # Errors
    /// As [`PhaseLock::acquire`].
    pub fn acquire_part(dir: &Path, part: u64) -> Result<PhaseLock, IoError> {
        PhaseLock::at(&part_lock_path(dir, part))
    }

    /// Waits for and takes the lock of stitch range `range` in `dir`.
    ///
    /// # Errors
    /// As [`PhaseLock::acquire`].
    pub fn acquire_range(dir: &Path, range: u64) -> Result<PhaseLock, IoError> {
        PhaseLock::at(&range_lock_path(dir, range))
    }

    fn at(path: &Path) -> Result<PhaseLock, IoError> {
        let file = File::options()
            .create(true)
            .truncate(false)
            .write(true)
            .open(path)
            .map_err(|e| IoError::io(path, e))?;
        file.lock().map_err(|e| IoError::io(path, e))?;
        Ok(PhaseLock { file })
    }
}

impl Drop for PhaseLock {
    fn drop(&mut self) {
        let _ = self.file.unlock();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_waits_for_the_first() {
        let d = tempfile::tempdir().unwrap();
        let first = PhaseLock::acquire(d.path(), Phase::Partition).unwrap();
        let other = File::open(lock_path(d.path(), Phase::Partition)).unwrap();
        assert!(other.try_lock().is_err(), "held");
        // Another phase's lock is independent.
        let _stitch = PhaseLock::acquire(d.path(), Phase::Stitch).unwrap();
        drop(first);
        assert!(other.try_lock().is_ok(), "released on drop");
    }
}
