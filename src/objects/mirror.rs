//! A task's local mirror of an object-store work directory: a scratch directory that receives
//! the objects the task reads ([`Mirror::pull`]) and whose new files go back up
//! ([`Mirror::push`]) after the task, data before the files that commit them.
//!
//! The names are the work directory's own ([`crate::tiling::workdir`],
//! [`crate::pipeline::scaleout::layout`]), flat under the prefix, plus the job's copy of its input
//! under `input/`. Which objects a phase reads is [`wanted`].

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::ObjectsError;
use super::store::{Put, Store};
use crate::pipeline::scaleout::Phase;

/// The directory of the job's copy of its input inside the work directory.
pub const INPUT_DIR: &str = "input";

/// Files that commit what was written before them: uploaded last, each with [`Put::Create`].
fn is_marker(name: &str) -> bool {
    use crate::pipeline::scaleout::layout::{JOB_FILE, STITCH_DONE};
    use crate::tiling::workdir::{GLOBALS_FILE, PARTITION_DONE};
    [JOB_FILE, STITCH_DONE, PARTITION_DONE, GLOBALS_FILE].contains(&name)
        || (name.starts_with("tile_") && name.ends_with(".json"))
        || is_part_marker(name)
}

/// A partition part's file (`part_<p>/…`), by the name under the part's directory.
fn in_part(name: &str) -> Option<&str> {
    let (dir, file) = name.split_once('/')?;
    let p = dir.strip_prefix("part_")?;
    (!p.is_empty() && p.bytes().all(|b| b.is_ascii_digit())).then_some(file)
}

/// A committed part's marker (`part_<p>/part.json`).
fn is_part_marker(name: &str) -> bool {
    in_part(name) == Some(crate::tiling::workdir::PART_DONE)
}

/// A part's occupancy grid (`part_<p>/occupancy.bin`): read only to merge the partition's grid,
/// so not downloaded once the partition is committed (31 grids of 6.7 MB each at 100 M points).
pub fn is_part_grid(name: &str) -> bool {
    in_part(name) == Some(crate::tiling::workdir::OCCUPANCY_FILE)
}

/// Files that stay in the scratch directory: locks and the owner file (local coordination),
/// temporary files (names starting with `.`), the stitch's intermediate merges.
fn is_local(name: &str) -> bool {
    name.starts_with('.')
        || name.ends_with(".lock")
        || name.starts_with("merge_")
        || name == crate::tiling::workdir::PID_FILE
}

/// The small files every command reads: the frozen job, the plan, the partition's marker and
/// occupancy grid, the reduced global scalars.
pub fn is_base(name: &str) -> bool {
    use crate::pipeline::scaleout::layout::JOB_FILE;
    use crate::tiling::workdir::{GLOBALS_FILE, OCCUPANCY_FILE, PARTITION_DONE, PLAN_FILE};
    [
        JOB_FILE,
        PLAN_FILE,
        PARTITION_DONE,
        OCCUPANCY_FILE,
        GLOBALS_FILE,
    ]
    .contains(&name)
}

/// What a task of `phase` reads, by object name: the small files every phase reads, plus
/// - partition: the input, and the parts' markers (to skip committed parts);
/// - globals: every part's files, i.e. every spill file with its block table (halo growth
///   reads by block), the parts' occupancy grids and markers (a task that finds the partition
///   not committed but all its parts commits it; [`run_task`](super::run_task) skips the grids
///   once it is), and every tile's partial sums;
/// - tiles: the same, and the results and outcomes of the task's own tiles (`own`, to skip the
///   committed ones);
/// - stitch: every result and outcome, and the input (not the spill files). An object-store
///   job's stitch is one task ([`super::plan`]), which writes its ranges side by side.
pub fn wanted(phase: Phase, name: &str, own: &dyn Fn(usize) -> bool) -> bool {
    if is_base(name) {
        return true;
    }
    let input = name.starts_with(&format!("{INPUT_DIR}/"));
    let tile = |ext: &str| -> Option<usize> {
        name.strip_prefix("tile_")?.strip_suffix(ext)?.parse().ok()
    };
    let partial = name.starts_with("globals_") && name.ends_with(".json");
    let part = in_part(name).is_some();
    match phase {
        Phase::Partition => input || is_part_marker(name),
        Phase::Globals => part || partial,
        Phase::Tiles => {
            part || partial || tile(".res").is_some_and(own) || tile(".json").is_some_and(own)
        }
        Phase::Stitch => input || tile(".res").is_some() || tile(".json").is_some(),
    }
}

/// A scratch directory mirroring part of a [`Store`] (removed on drop).
pub struct Mirror {
    store: Store,
    scratch: tempfile::TempDir,
    /// What is under the prefix: name → size (listed at [`Mirror::open`]).
    remote: BTreeMap<String, u64>,
    /// What this mirror downloaded (or uploaded): name → the local file's stamp then.
    pulled: BTreeMap<String, Stamp>,
}

impl Mirror {
    /// Lists `store` and makes the scratch directory (in `QEMD_SCRATCH`, else the system's
    /// temporary directory).
    ///
    /// # Errors
    /// The listing fails, the scratch directory cannot be made.
    pub fn open(store: Store) -> Result<Mirror, ObjectsError> {
        let base = std::env::var_os("QEMD_SCRATCH")
            .map(PathBuf::from)
            .unwrap_or_else(std::env::temp_dir);
        std::fs::create_dir_all(&base).map_err(|e| crate::io::IoError::io(&base, e))?;
        let scratch = tempfile::Builder::new()
            .prefix("qemd-mirror-")
            .tempdir_in(&base)
            .map_err(|e| crate::io::IoError::io(&base, e))?;
        let remote = store.list()?;
        Ok(Mirror {
            store,
            scratch,
            remote,
            pulled: BTreeMap::new(),
        })
    }

    /// The scratch directory (the work directory the pipeline is handed).
    pub fn dir(&self) -> &Path {
        self.scratch.path()
    }

    /// The store's URL.
    pub fn url(&self) -> &str {
        self.store.url()
    }

    /// The size of object `name`, if it is under the prefix.
    pub fn remote(&self, name: &str) -> Option<u64> {
        self.remote.get(name).copied()
    }

    /// The names under the prefix.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.remote.keys().map(String::as_str)
    }

    /// Downloads every object `pick` selects that is not here yet.
    ///
    /// # Errors
    /// A failed download, cancellation.
    pub fn pull(
        &mut self,
        pick: impl Fn(&str) -> bool,
        cancelled: &(dyn Fn() -> bool + Sync),
    ) -> Result<(), ObjectsError> {
        let items: Vec<(String, PathBuf)> = self
            .remote
            .keys()
            .filter(|n| !self.pulled.contains_key(*n) && !is_local(n) && pick(n))
            .map(|n| (n.clone(), self.scratch.path().join(n)))
            .collect();
        self.store.get_all(&items, cancelled)?;
        for (n, p) in items {
            self.pulled.insert(n, stamp(&p)?);
        }
        Ok(())
    }

    /// Makes an empty file of each selected object's size (sparse; never read), for a reader
    /// that only asks whether a file is there and how long it is (`qemd status`).
    ///
    /// # Errors
    /// A file cannot be made.
    pub fn stand_ins(&mut self, pick: impl Fn(&str) -> bool) -> Result<(), ObjectsError> {
        for (n, &size) in &self.remote {
            if self.pulled.contains_key(n) || is_local(n) || !pick(n) {
                continue;
            }
            let p = self.scratch.path().join(n);
            let f = std::fs::File::create(&p).map_err(|e| crate::io::IoError::io(&p, e))?;
            f.set_len(size).map_err(|e| crate::io::IoError::io(&p, e))?;
            self.pulled.insert(n.clone(), stamp(&p)?);
        }
        Ok(())
    }

    /// Uploads `from` as object `name` (the job's input copy, before its plan is pushed).
    ///
    /// # Errors
    /// A failed upload.
    pub fn put_file(
        &mut self,
        name: &str,
        from: &Path,
        cancelled: &(dyn Fn() -> bool + Sync),
    ) -> Result<(), ObjectsError> {
        self.store.put(name, from, Put::Create, cancelled)?;
        let len = std::fs::metadata(from)
            .map_err(|e| crate::io::IoError::io(from, e))?
            .len();
        self.remote.insert(name.to_string(), len);
        self.pulled.insert(name.to_string(), stamp(from)?);
        Ok(())
    }

    /// Uploads every file the task wrote in the scratch directory: new ones, and pulled ones
    /// it rewrote (length or modification time changed: the partition rewrites the plan file). Data first, then the files
    /// that commit it ([`is_marker`]), so a task killed while uploading leaves nothing that reads
    /// as committed. Returns the number of objects written.
    ///
    /// # Errors
    /// A failed upload, cancellation.
    pub fn push(&mut self, cancelled: &(dyn Fn() -> bool + Sync)) -> Result<usize, ObjectsError> {
        let mut files = Vec::new();
        collect(self.scratch.path(), self.scratch.path(), &mut files)?;
        let mut todo: Vec<(String, PathBuf, u64)> = files
            .into_iter()
            .filter(|(n, p, _)| {
                !is_local(n) && self.pulled.get(n).is_none_or(|s| stamp(p).ok() != Some(*s))
            })
            .collect();
        // Markers last; otherwise by name, for a deterministic order.
        todo.sort_by(|a, b| (is_marker(&a.0), &a.0).cmp(&(is_marker(&b.0), &b.0)));
        let mut written = 0;
        for (name, path, len) in todo {
            if cancelled() {
                return Err(ObjectsError::Cancelled);
            }
            let mode = if name == crate::tiling::workdir::PLAN_FILE {
                Put::Overwrite
            } else {
                Put::Create
            };
            if self.store.put(&name, &path, mode, cancelled)? {
                written += 1;
            }
            self.remote.insert(name.clone(), len);
            self.pulled.insert(name, stamp(&path)?);
        }
        Ok(written)
    }
}

/// A local file's length and modification time: what tells a rewritten file.
type Stamp = (u64, Option<std::time::SystemTime>);

fn stamp(p: &Path) -> Result<Stamp, ObjectsError> {
    let m = std::fs::metadata(p).map_err(|e| crate::io::IoError::io(p, e))?;
    Ok((m.len(), m.modified().ok()))
}

/// Regular files under `dir` (recursively): (name relative to `root` with `/`, path, length).
fn collect(
    root: &Path,
    dir: &Path,
    out: &mut Vec<(String, PathBuf, u64)>,
) -> Result<(), ObjectsError> {
    let io = |e| crate::io::IoError::io(dir, e);
    for e in std::fs::read_dir(dir).map_err(io)? {
        let e = e.map_err(io)?;
        let ty = e.file_type().map_err(io)?;
        let p = e.path();
        if ty.is_dir() {
            collect(root, &p, out)?;
        } else if ty.is_file() {
            let rel = p.strip_prefix(root).unwrap_or(&p);
            let name = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy())
                .collect::<Vec<_>>()
                .join("/");
            let len = e.metadata().map_err(io)?.len();
            out.push((name, p, len));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_phase_reads_what_it_needs_and_commits_go_last() {
        let own = |t: usize| t == 3;
        let base = ["job.json", "plan.json", "spill.done", "globals.json"];
        for p in Phase::ALL {
            for n in base {
                assert!(wanted(p, n, &own), "{p} {n}");
            }
            assert!(!wanted(p, "output.ply", &own));
            assert!(!wanted(p, "stitch.json", &own));
        }
        assert!(wanted(Phase::Partition, "input/a.las", &own));
        assert!(wanted(Phase::Partition, "part_0002/part.json", &own));
        assert!(!wanted(Phase::Partition, "part_0002/tile_00001.pts", &own));
        assert!(!wanted(Phase::Partition, "part_0002/occupancy.bin", &own));
        for n in [
            "part_0000/tile_00001.pts",
            "part_0011/tile_00001.blk",
            "part_0002/occupancy.bin",
            "part_0002/part.json",
        ] {
            assert!(wanted(Phase::Globals, n, &own), "{n}");
            assert!(wanted(Phase::Tiles, n, &own), "{n}");
            assert!(!wanted(Phase::Stitch, n, &own), "{n}");
        }
        assert!(!wanted(Phase::Tiles, "part_x/tile_00001.pts", &own));
        assert!(is_part_grid("part_0002/occupancy.bin"));
        assert!(!is_part_grid("occupancy.bin"));
        assert!(!is_part_grid("part_0002/part.json"));
        assert!(!wanted(Phase::Globals, "input/a.las", &own));
        assert!(wanted(Phase::Tiles, "tile_00003.res", &own));
        assert!(wanted(Phase::Tiles, "tile_00003.json", &own));
        assert!(!wanted(Phase::Tiles, "tile_00004.res", &own));
        assert!(wanted(Phase::Tiles, "globals_00004.json", &own));
        assert!(wanted(Phase::Stitch, "tile_00004.res", &own));
        assert!(!wanted(Phase::Stitch, "tile_00004.pts", &own));
        assert!(wanted(Phase::Stitch, "input/a.las", &own));
        for m in [
            "job.json",
            "stitch.json",
            "spill.done",
            "tile_00002.json",
            "part_0001/part.json",
        ] {
            assert!(is_marker(m), "{m}");
        }
        for d in [
            "tile_00002.res",
            "tile_00002.pts",
            "output.las",
            "globals_00001.json",
            "part_0001/occupancy.bin",
            "part_0001/tile_00002.pts",
        ] {
            assert!(!is_marker(d), "{d}");
        }
        for l in [
            "stitch.lock",
            "partition_0003.lock",
            ".tmpAbc",
            ".part_0003.tmp/tile_00001.pts",
            "merge_1_00002.res",
            "pid",
        ] {
            assert!(is_local(l), "{l}");
        }
    }
}
