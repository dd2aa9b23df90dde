//! The files scale-out adds to a work directory (the tiled run's own are named by
//! [`crate::tiling::workdir`]), and how they are committed:
//!
//! ```text
//!  job.json            the frozen job (plan step): input, formats, spec, budget, plan
//!  globals_<t>.json    tile t's partial sums of the global scalars (globals phase)
//!  output.<ext>        the stitched output (stitch phase), then
//!  stitch.json         its counts: the stitch is committed
//!  body_<r>.bin        stitch range r's output records (a stitch in ranges), then
//!  body_<r>.json       what they hold: the range is committed
//!  partition_<p>.lock  held by the task writing partition part p (an empty file)
//!  stitch_<r>.lock     held by the task writing stitch range r
//!  stitch.lock         held by the stitch (or finish) while it runs or assembles the bodies
//! ```
//!
//! Every file is written to a temporary name beside it and renamed into place, so a reader sees
//! it whole or not at all; an unreadable file counts as missing.

use std::path::{Path, PathBuf};

use crate::io::{AtomicFile, Format, IoError};

/// The frozen job.
pub const JOB_FILE: &str = "job.json";
/// The stitch's counts, written after the output: the stitch is committed.
pub const STITCH_DONE: &str = "stitch.json";

/// Tile `t`'s partial sums of the global scalars.
pub fn globals_partial_path(dir: &Path, t: usize) -> PathBuf {
    dir.join(format!("globals_{t:05}.json"))
}

/// The stitched output of a job whose output format is `format`.
pub fn output_path(dir: &Path, format: Format) -> PathBuf {
    dir.join(format!("output.{}", format.name()))
}

/// The lock file of the single-task phase `phase` (the stitch).
pub fn lock_path(dir: &Path, phase: super::Phase) -> PathBuf {
    dir.join(format!("{}.lock", phase.name()))
}

/// The lock file of partition part `part`.
pub fn part_lock_path(dir: &Path, part: u64) -> PathBuf {
    dir.join(format!("partition_{part:04}.lock"))
}

/// The lock file of stitch range `range`.
pub fn range_lock_path(dir: &Path, range: u64) -> PathBuf {
    dir.join(format!("stitch_{range:05}.lock"))
}

/// Writes `value` as JSON to `path` atomically; `sync` also syncs it to disk (the frozen job).
///
/// # Errors
/// Write failures.
pub fn commit_json<T: serde::Serialize>(path: &Path, value: &T, sync: bool) -> Result<(), IoError> {
    use std::io::Write;
    let mut f = AtomicFile::create(path)?;
    let text = serde_json::to_vec_pretty(value).map_err(|e| f.err(std::io::Error::other(e)))?;
    f.write_all(&text).map_err(|e| IoError::io(path, e))?;
    if sync {
        f.commit()
    } else {
        f.commit_unsynced()
    }
}

/// Reads JSON written by [`commit_json`]; `None` when missing or unreadable.
pub fn load_json<T: serde::de::DeserializeOwned>(path: &Path) -> Option<T> {
    serde_json::from_slice(&std::fs::read(path).ok()?).ok()
}
