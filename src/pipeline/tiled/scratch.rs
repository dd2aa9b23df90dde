//! The disk a tiled run needs, and its work directory (a persistent job directory, or a fresh
//! temporary one; see [`crate::tiling::workdir`]), checked before any work.

use std::path::PathBuf;

use bytesize::ByteSize;

use crate::pipeline::{PipelineError, RunOptions};
use crate::tiling::spill::{SPILL_RECORD, result_record};
use crate::tiling::workdir::WorkDir;

/// Disk bytes per point a tiled run needs in its scratch directory: one spill record per point
/// plus halo copies (counted as half as many again) and one result record.
pub const TILED_DISK_PER_POINT: u64 = disk_per_point(false);

/// [`TILED_DISK_PER_POINT`] of a run that writes normals (`normals`: longer result records) or
/// not.
pub const fn disk_per_point(normals: bool) -> u64 {
    (SPILL_RECORD as u64 * 3).div_ceil(2) + result_record(normals) as u64
}

/// Disk bytes per point of a tiled run whose input records are `record_len` bytes:
/// [`disk_per_point`], plus the stitch's bodies (written in ranges, the output's records stay in
/// the work directory until the output takes them; counted at the input's record length).
pub const fn run_disk_per_point(normals: bool, record_len: usize) -> u64 {
    disk_per_point(normals) + record_len as u64
}

/// A size for messages, with a binary unit that shows its value ("512 B", "1.5 MiB").
fn size(bytes: u64) -> String {
    ByteSize(bytes).display().iec().to_string()
}

/// Where the tiled path's work directory goes (a temporary one inside it, or it itself for a
/// job's `work_dir`).
fn base(opts: &RunOptions) -> PathBuf {
    opts.work_dir
        .clone()
        .or_else(|| opts.temp_dir.clone())
        .unwrap_or_else(std::env::temp_dir)
}

/// Refuses a tiled run of `points` points before any work when the scratch file system has
/// clearly too little room (`per_point` bytes a point: [`disk_per_point`]).
///
/// # Errors
/// [`PipelineError::TempDir`].
pub fn check_disk(opts: &RunOptions, points: u64, per_point: u64) -> Result<(), PipelineError> {
    let mut base = base(opts);
    // A job directory may not exist yet: measure the nearest existing ancestor.
    while !base.exists() {
        match base.parent() {
            Some(p) if !p.as_os_str().is_empty() => base = p.to_path_buf(),
            _ => return Ok(()),
        }
    }
    let need = points.saturating_mul(per_point);
    let free = fs4::available_space(&base).map_err(|e| PipelineError::TempDir {
        path: base.clone(),
        detail: e.to_string(),
    })?;
    if free < need {
        return Err(PipelineError::TempDir {
            path: base,
            detail: format!(
                "{} free, a tiled run of {points} points needs about {} \
                 ({per_point} bytes per point); free space or give --temp-dir",
                size(free),
                size(need)
            ),
        });
    }
    Ok(())
}

/// The run's work directory, checked to exist, be writable and have room for `need` bytes.
///
/// # Errors
/// [`PipelineError::TempDir`].
pub fn work_dir(opts: &RunOptions, need: u64) -> Result<WorkDir, PipelineError> {
    let base = base(opts);
    let bad = |detail: String| PipelineError::TempDir {
        path: base.clone(),
        detail,
    };
    let w = if opts.work_dir.is_some() {
        WorkDir::persistent(&base).map_err(|e| bad(format!("cannot create it: {e}")))?
    } else {
        if !base.is_dir() {
            return Err(bad("does not exist or is not a directory".into()));
        }
        WorkDir::temporary_in(&base)
            .map_err(|e| bad(format!("cannot create a directory in it: {e}")))?
    };
    let free = fs4::available_space(w.path()).map_err(|e| bad(e.to_string()))?;
    if free < need {
        return Err(bad(format!(
            "{} free, the tiled run needs about {}",
            size(free),
            size(need)
        )));
    }
    Ok(w)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue12_tiled_disk_is_checked_up_front() {
        let dir = tempfile::tempdir().unwrap();
        let opts = RunOptions {
            temp_dir: Some(dir.path().to_path_buf()),
            ..RunOptions::default()
        };
        assert_eq!(TILED_DISK_PER_POINT, 88);
        assert_eq!(disk_per_point(true), 112);
        check_disk(&opts, 1000, TILED_DISK_PER_POINT).unwrap();
        // 10^15 points need 88 PB: clearly more than any test machine has.
        let e = check_disk(&opts, 1_000_000_000_000_000, TILED_DISK_PER_POINT)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&dir.path().display().to_string()) && e.contains("needs about"),
            "{e}"
        );
        assert_eq!(e.lines().count(), 1);
    }

    #[test]
    fn issue10_sizes_show_their_value_at_any_scale() {
        assert_eq!(size(0), "0 B");
        assert_eq!(size(88_000), "85.9 KiB");
        assert_eq!(size(3 << 20), "3.0 MiB");
        assert_eq!(size(88_000_000_000_000_000), "78.2 PiB");
        // The message of a small run names a real figure, not "0.00 GiB".
        let dir = tempfile::tempdir().unwrap();
        let opts = RunOptions {
            temp_dir: Some(dir.path().to_path_buf()),
            ..RunOptions::default()
        };
        let e = work_dir(&opts, u64::MAX).unwrap_err().to_string();
        assert!(
            e.contains("free, the tiled run needs about 16.0 EiB"),
            "{e}"
        );
        assert!(!e.contains("0.00 GiB"), "{e}");
    }
}
