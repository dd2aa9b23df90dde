//! The work directory of the tiled path: the one place that names its files and says which
//! phases of a run are committed there.
//!
//! # Brief overview
//!
//! ```text
//!  pid                  "<pid> <pid namespace> <boot id>": the owner (temporary directories)
//!  plan.json            the plan (pass 1); a different plan invalidates every other file
//!  part_<p>/            what partition task p wrote (records [p·n/P, (p+1)·n/P) of the input):
//!    tile_<t>.pts         spill file of tile t (pass 2, see super::spill)
//!    tile_<t>.blk         its block table: the box of each block of owned records
//!    occupancy.bin        its occupancy grid (when the plan has an isolation radius)
//!    part.json            the part is committed: its bytes (written in .part_<p>.tmp/, which
//!                         is renamed to part_<p>/ whole)
//!  occupancy.bin        the parts' occupancy grids merged (saved before the marker)
//!  spill.done           the partition is committed (holds the bytes spilled)
//!  globals.json         the global scalars (the pre-pass), when the method needs them
//!  tile_<t>.res         results of tile t (written atomically)
//!  tile_<t>.json        outcome of tile t, saved after its results: the tile is committed
//!  merge_<l>_<g>.res    intermediate merges of the stitch (beyond spill::MAX_OPEN tiles)
//! ```
//!
//! A run either owns a **temporary** directory (created in a base directory with the prefix
//! [`TEMP_PREFIX`], removed when the [`WorkDir`] drops) or uses a caller's **persistent** one (a
//! job's directory: an interrupted run resumes from what is committed there). A process killed
//! outright (SIGKILL, an OOM kill) cannot remove its temporary directory, so each records its
//! owner in a `pid` file, and creating a new one first removes those of the same base whose owner
//! is gone ([`remove_stale`]). Persistent directories are never removed.
//!
//! The queries ([`WorkDir::committed_partition`], [`WorkDir::committed_globals`],
//! [`WorkDir::committed_tile`]) are what resume logic asks; an unreadable checkpoint counts as
//! missing, so its phase is redone.

use std::path::{Path, PathBuf};

use super::TileOutcome;
use super::occupancy::Occupancy;
use super::plan::Plan;
use crate::denoise::cloud::Globals;
use crate::io::{AtomicFile, IoError};

/// Name prefix of a temporary work directory (the rest is random).
pub const TEMP_PREFIX: &str = "qemd-tiles-";
/// The file naming the process that owns a temporary work directory.
pub const PID_FILE: &str = "pid";
/// The plan of the run.
pub const PLAN_FILE: &str = "plan.json";
/// The marker of a committed partition (holds the bytes spilled).
pub const PARTITION_DONE: &str = "spill.done";
/// The occupancy grid of the partition pass.
pub const OCCUPANCY_FILE: &str = "occupancy.bin";
/// The global scalars of the pre-pass.
pub const GLOBALS_FILE: &str = "globals.json";

/// The marker of a committed part, in its directory.
pub const PART_DONE: &str = "part.json";

/// The directory of partition part `part` in `dir`.
pub fn part_dir(dir: &Path, part: u64) -> PathBuf {
    dir.join(format!("part_{part:04}"))
}

/// Where partition part `part` is written before it is committed (renamed to [`part_dir`]).
fn part_temp(dir: &Path, part: u64) -> PathBuf {
    dir.join(format!(".part_{part:04}.tmp"))
}

/// The spill file of tile `t` in the directory `part` of a partition part.
pub fn spill_path(part: &Path, t: usize) -> PathBuf {
    part.join(format!("tile_{t:05}.pts"))
}

/// The block table of tile `t`'s spill file in `part` (see [`super::spill`]).
pub fn blocks_path(part: &Path, t: usize) -> PathBuf {
    part.join(format!("tile_{t:05}.blk"))
}

/// A committed part's marker ([`PART_DONE`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PartDone {
    /// Bytes the part spilled.
    pub bytes: u64,
}

/// The result file of tile `t` in `dir`.
pub fn result_path(dir: &Path, t: usize) -> PathBuf {
    dir.join(format!("tile_{t:05}.res"))
}

/// The outcome (checkpoint) of tile `t` in `dir`.
pub fn outcome_path(dir: &Path, t: usize) -> PathBuf {
    dir.join(format!("tile_{t:05}.json"))
}

/// Intermediate merge file `g` of merge level `level` in `dir`.
pub fn merge_path(dir: &Path, level: usize, g: usize) -> PathBuf {
    dir.join(format!("merge_{level}_{g:05}.res"))
}

/// An intermediate merge of the results of stitch range `range` ([`merge_path`] for one range).
pub fn range_merge_path(dir: &Path, range: u64, level: usize, g: usize) -> PathBuf {
    dir.join(format!("merge_r{range:05}_{level}_{g:05}.res"))
}

/// The body of stitch range `range`: its output records alone ([`crate::io::SinkOptions::body`]).
pub fn body_path(dir: &Path, range: u64) -> PathBuf {
    dir.join(format!("body_{range:05}.bin"))
}

/// What the body of stitch range `range` holds (JSON), committed after the body.
pub fn body_done_path(dir: &Path, range: u64) -> PathBuf {
    dir.join(format!("body_{range:05}.json"))
}

/// True for the name of a file a run writes to its work directory (other than [`PID_FILE`]).
fn is_run_file(name: &str) -> bool {
    name.starts_with("tile_")
        || name.starts_with("merge_")
        || name.starts_with("body_")
        || name.starts_with(".stitch.")
        || name.starts_with("part_")
        || name.starts_with(".part_")
        || [PLAN_FILE, PARTITION_DONE, OCCUPANCY_FILE, GLOBALS_FILE].contains(&name)
}

enum Kind {
    Temp(tempfile::TempDir),
    Persistent(PathBuf),
}

/// The directory a tiled run keeps its files in (see the module overview).
pub struct WorkDir {
    kind: Kind,
}

impl std::fmt::Debug for WorkDir {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkDir")
            .field("path", &self.path())
            .field("temporary", &self.is_temporary())
            .finish()
    }
}

impl WorkDir {
    /// A caller's persistent directory (created if missing); what is committed there is kept.
    ///
    /// # Errors
    /// The directory cannot be created.
    pub fn persistent(path: &Path) -> std::io::Result<WorkDir> {
        std::fs::create_dir_all(path)?;
        Ok(WorkDir {
            kind: Kind::Persistent(path.to_path_buf()),
        })
    }

    /// A fresh temporary directory in `base` ([`TEMP_PREFIX`], owned by this process), removed
    /// on drop. Stale ones in `base` are removed first ([`remove_stale`]).
    ///
    /// # Errors
    /// The directory or its `pid` file cannot be created.
    pub fn temporary_in(base: &Path) -> std::io::Result<WorkDir> {
        remove_stale(base);
        let dir = tempfile::Builder::new()
            .prefix(TEMP_PREFIX)
            .tempdir_in(base)?;
        std::fs::write(dir.path().join(PID_FILE), Owner::current().to_string())?;
        Ok(WorkDir {
            kind: Kind::Temp(dir),
        })
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        match &self.kind {
            Kind::Temp(d) => d.path(),
            Kind::Persistent(p) => p,
        }
    }

    /// True for a temporary directory (removed on drop).
    pub fn is_temporary(&self) -> bool {
        matches!(self.kind, Kind::Temp(_))
    }

    /// The directory of partition part `part`.
    pub fn part(&self, part: u64) -> PathBuf {
        part_dir(self.path(), part)
    }

    /// The marker of part `part`, when it is committed (an unreadable one counts as missing).
    pub fn committed_part(&self, part: u64) -> Option<PartDone> {
        load_json(&self.part(part).join(PART_DONE))
    }

    /// An empty directory to write part `part` in (whatever an earlier attempt left there is
    /// removed: the caller is the part's only writer).
    ///
    /// # Errors
    /// The directory cannot be cleared or made.
    pub fn begin_part(&self, part: u64) -> Result<PathBuf, IoError> {
        let tmp = part_temp(self.path(), part);
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| IoError::io(&tmp, e))?;
        }
        std::fs::create_dir(&tmp).map_err(|e| IoError::io(&tmp, e))?;
        Ok(tmp)
    }

    /// Commits part `part` written in [`WorkDir::begin_part`]'s directory: its occupancy grid
    /// and its marker, then the directory renamed into place whole.
    ///
    /// # Errors
    /// Write failures; the part committed already (its directory exists).
    pub fn commit_part(
        &self,
        part: u64,
        done: PartDone,
        occupancy: Option<&Occupancy>,
    ) -> Result<(), IoError> {
        let tmp = part_temp(self.path(), part);
        if let Some(o) = occupancy {
            save_grid(&tmp.join(OCCUPANCY_FILE), o)?;
        }
        save_json(&tmp.join(PART_DONE), &done)?;
        let to = self.part(part);
        std::fs::rename(&tmp, &to).map_err(|e| IoError::io(&to, e))
    }

    /// Commits the partition of `plan` when all its parts are committed and here (with their
    /// occupancy grids, when the plan has an isolation radius): the grids merged, the plan, then
    /// the marker with the bytes spilled. Returns the bytes, or `None` while something is
    /// missing. Any number of callers may race: they write the same bytes.
    ///
    /// # Errors
    /// Write failures.
    pub fn commit_parts(&self, plan: &Plan) -> Result<Option<u64>, IoError> {
        // Every marker first: a task that commits one part of many reads no grid.
        let mut bytes = 0u64;
        for part in 0..plan.parts() {
            let Some(done) = self.committed_part(part) else {
                return Ok(None);
            };
            bytes += done.bytes;
        }
        let mut merged: Option<Occupancy> = None;
        for part in 0..plan.parts() {
            if plan.isolation.is_some() {
                let Some(o) = load_grid(&self.part(part).join(OCCUPANCY_FILE)) else {
                    return Ok(None);
                };
                match &mut merged {
                    Some(m) => m.merge(&o),
                    None => merged = Some(o.capped(plan.grid_cells)),
                }
            }
        }
        save_json(&self.path().join(PLAN_FILE), plan)?;
        self.commit_partition(bytes, merged.as_ref())?;
        Ok(Some(bytes))
    }

    /// The result file of tile `t`.
    pub fn result(&self, t: usize) -> PathBuf {
        result_path(self.path(), t)
    }

    /// The bytes spilled when `plan`'s partition is committed here (the same plan saved and the
    /// partition marker present; an unreadable count reads 0), else `None`.
    pub fn committed_partition(&self, plan: &Plan) -> Option<u64> {
        let dir = self.path();
        let same = load_json::<Plan>(&dir.join(PLAN_FILE)).is_some_and(|p| p == *plan);
        let marker = dir.join(PARTITION_DONE);
        (same && marker.exists()).then(|| load_json(&marker).unwrap_or(0))
    }

    /// Starts partitioning for `plan`: unless the plan saved here is the same (whose committed
    /// parts are then kept), removes every file of an earlier run (a plan that changed
    /// invalidates them all) and saves the plan.
    ///
    /// # Errors
    /// Files cannot be removed or written.
    pub fn begin_partition(&self, plan: &Plan) -> Result<(), IoError> {
        let dir = self.path();
        if load_json::<Plan>(&dir.join(PLAN_FILE)).is_some_and(|p| p == *plan) {
            return Ok(());
        }
        let entries = std::fs::read_dir(dir).map_err(|e| IoError::io(dir, e))?;
        for e in entries {
            let p = e.map_err(|e| IoError::io(dir, e))?.path();
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            if !is_run_file(&name) {
                continue;
            }
            let gone = if p.is_dir() {
                std::fs::remove_dir_all(&p)
            } else {
                std::fs::remove_file(&p)
            };
            gone.map_err(|e| IoError::io(&p, e))?;
        }
        save_json(&dir.join(PLAN_FILE), plan)
    }

    /// Commits the partition: the occupancy grid (when there is one), then the marker with the
    /// bytes spilled.
    fn commit_partition(&self, bytes: u64, occupancy: Option<&Occupancy>) -> Result<(), IoError> {
        if let Some(o) = occupancy {
            save_grid(&self.path().join(OCCUPANCY_FILE), o)?;
        }
        save_json(&self.path().join(PARTITION_DONE), &bytes)
    }

    /// The occupancy grid saved with the partition, if readable.
    pub fn occupancy(&self) -> Option<Occupancy> {
        load_grid(&self.path().join(OCCUPANCY_FILE))
    }

    /// The committed global scalars, if any.
    pub fn committed_globals(&self) -> Option<Globals> {
        load_json(&self.path().join(GLOBALS_FILE))
    }

    /// Commits the global scalars.
    ///
    /// # Errors
    /// Write failures.
    pub fn commit_globals(&self, globals: &Globals) -> Result<(), IoError> {
        save_json(&self.path().join(GLOBALS_FILE), globals)
    }

    /// Tile `t`'s outcome when the tile is committed (its result file and outcome both present).
    pub fn committed_tile(&self, t: usize) -> Option<TileOutcome> {
        self.result(t)
            .exists()
            .then(|| load_json(&outcome_path(self.path(), t)))
            .flatten()
    }

    /// Commits tile `t` (after its result file is written).
    ///
    /// # Errors
    /// Write failures.
    pub fn commit_tile(&self, t: usize, outcome: &TileOutcome) -> Result<(), IoError> {
        save_json(&outcome_path(self.path(), t), outcome)
    }
}

/// Writes `value` as JSON to `path` atomically (checkpoint metadata).
fn save_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), IoError> {
    use std::io::Write;
    let io_err = |e: std::io::Error| IoError::io(path, e);
    let mut f = AtomicFile::create(path)?;
    let text = serde_json::to_vec(value).map_err(|e| io_err(std::io::Error::other(e)))?;
    f.write_all(&text).map_err(io_err)?;
    f.commit_unsynced()
}

/// Writes an occupancy grid's bytes ([`Occupancy::to_bytes`]) to `path` atomically.
fn save_grid(path: &Path, grid: &Occupancy) -> Result<(), IoError> {
    use std::io::Write;
    let mut f = AtomicFile::create(path)?;
    f.write_all(&grid.to_bytes())
        .map_err(|e| IoError::io(path, e))?;
    f.commit_unsynced()
}

/// Reads a grid written by [`save_grid`]; `None` when missing or unreadable (then redone).
fn load_grid(path: &Path) -> Option<Occupancy> {
    Occupancy::from_bytes(&std::fs::read(path).ok()?)
}

/// Reads JSON written by [`save_json`]; `None` when missing or unreadable (then redone).
fn load_json<T: serde::de::DeserializeOwned>(path: &Path) -> Option<T> {
    serde_json::from_slice(&std::fs::read(path).ok()?).ok()
}

/// Who owns a temporary work directory: a process id, in a pid namespace, since a boot. A pid
/// means nothing outside its namespace (another container sharing the base) or after a reboot,
/// so only an owner of this namespace and boot can be found gone.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Owner {
    pid: u32,
    namespace: String,
    boot: String,
}

impl Owner {
    fn current() -> Owner {
        let read = |p: &str| {
            std::fs::read_link(p)
                .map(|l| l.to_string_lossy().into_owned())
                .or_else(|_| std::fs::read_to_string(p).map(|s| s.trim().to_string()))
                .unwrap_or_default()
        };
        Owner {
            pid: std::process::id(),
            namespace: read("/proc/self/ns/pid"),
            boot: read("/proc/sys/kernel/random/boot_id"),
        }
    }

    fn parse(text: &str) -> Option<Owner> {
        let mut f = text.split_whitespace();
        Some(Owner {
            pid: f.next()?.parse().ok()?,
            namespace: f.next()?.to_string(),
            boot: f.next()?.to_string(),
        })
    }

    /// True when this owner is provably gone: same namespace and boot as this process (both
    /// known), and no such process.
    fn gone(&self, me: &Owner) -> bool {
        cfg!(target_os = "linux")
            && !me.namespace.is_empty()
            && !me.boot.is_empty()
            && self.namespace == me.namespace
            && self.boot == me.boot
            && self.pid != me.pid
            && !Path::new("/proc").join(self.pid.to_string()).exists()
    }
}

impl std::fmt::Display for Owner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "{} {} {}", self.pid, self.namespace, self.boot)
    }
}

/// Removes the temporary work directories in `base` ([`TEMP_PREFIX`], a `pid` file) whose owner
/// process is gone (see [`Owner`]); returns how many. Best effort: a directory that cannot be
/// read or removed is left, and directories without a readable `pid` file (one being created,
/// or not ours) are never touched.
pub fn remove_stale(base: &Path) -> usize {
    let me = Owner::current();
    let Ok(entries) = std::fs::read_dir(base) else {
        return 0;
    };
    let mut removed = 0;
    for e in entries.flatten() {
        let name = e.file_name();
        let is_dir = e.file_type().is_ok_and(|t| t.is_dir());
        if !is_dir || !name.to_string_lossy().starts_with(TEMP_PREFIX) {
            continue;
        }
        let dir = e.path();
        let owner = std::fs::read_to_string(dir.join(PID_FILE))
            .ok()
            .and_then(|s| Owner::parse(&s));
        if owner.is_some_and(|o| o.gone(&me)) && std::fs::remove_dir_all(&dir).is_ok() {
            removed += 1;
        }
    }
    removed
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan() -> Plan {
        let mut p = crate::tiling::plan::Planner::new(64);
        for i in 0..200u64 {
            let x = i as f64;
            p.add(i, glam::DVec3::new(x, (x * 0.7).sin(), 0.0));
        }
        p.finish(50, 8, 2).unwrap()
    }

    #[test]
    fn phases_are_committed_in_order_and_a_new_plan_clears_them() {
        let d = tempfile::tempdir().unwrap();
        let w = WorkDir::persistent(&d.path().join("job")).unwrap();
        let p = plan();
        assert_eq!(w.committed_partition(&p), None);
        w.begin_partition(&p).unwrap();
        assert_eq!(w.committed_partition(&p), None, "no marker yet");
        w.commit_partition(96, None).unwrap();
        assert_eq!(w.committed_partition(&p), Some(96));
        assert!(w.occupancy().is_none());
        let g = Globals {
            spacing: 0.5,
            noise: 0.25,
        };
        w.commit_globals(&g).unwrap();
        assert_eq!(w.committed_globals(), Some(g));
        let o = TileOutcome {
            owned: 7,
            ..TileOutcome::default()
        };
        w.commit_tile(0, &o).unwrap();
        assert!(w.committed_tile(0).is_none(), "an outcome without results");
        std::fs::write(w.result(0), b"").unwrap();
        assert_eq!(w.committed_tile(0).map(|o| o.owned), Some(7));

        // Another plan: nothing of the first run survives its partition's start.
        let mut other = p.clone();
        other.halo *= 2.0;
        assert_eq!(w.committed_partition(&other), None);
        w.begin_partition(&other).unwrap();
        let left: Vec<String> = std::fs::read_dir(w.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(left, vec![PLAN_FILE.to_string()]);
        assert!(w.committed_globals().is_none() && w.committed_tile(0).is_none());
    }

    #[test]
    fn issue11_parts_commit_whole_and_the_partition_only_with_all_of_them() {
        let d = tempfile::tempdir().unwrap();
        let w = WorkDir::persistent(&d.path().join("job")).unwrap();
        let mut p = plan();
        p.parts = 3;
        p.isolation = Some(1.0);
        w.begin_partition(&p).unwrap();
        let pts: Vec<glam::DVec3> = (0..300)
            .map(|i| glam::DVec3::new(f64::from(i) * 0.37, f64::from(i % 7), 0.5))
            .collect();
        let mut all = Occupancy::new(0.25, glam::DVec3::ZERO, p.grid_cells);
        pts.iter().for_each(|&q| all.add(q));
        let grid = |part: usize| {
            let mut o = Occupancy::new(0.25, glam::DVec3::ZERO, p.grid_cells);
            pts[part * 100..(part + 1) * 100]
                .iter()
                .for_each(|&q| o.add(q));
            o
        };
        for part in [2u64, 0] {
            let tmp = w.begin_part(part).unwrap();
            std::fs::write(tmp.join("tile_00000.pts"), b"x").unwrap();
            // A retry starts the part afresh.
            let tmp = w.begin_part(part).unwrap();
            assert_eq!(std::fs::read_dir(&tmp).unwrap().count(), 0);
            assert!(w.committed_part(part).is_none(), "written, not committed");
            let done = PartDone { bytes: 32 * part };
            w.commit_part(part, done, Some(&grid(part as usize)))
                .unwrap();
            assert_eq!(w.committed_part(part), Some(done));
            assert!(!tmp.exists());
        }
        assert_eq!(w.commit_parts(&p).unwrap(), None, "part 1 is missing");
        assert_eq!(w.committed_partition(&p), None);
        w.begin_part(1).unwrap();
        w.commit_part(1, PartDone { bytes: 32 }, Some(&grid(1)))
            .unwrap();
        assert_eq!(w.commit_parts(&p).unwrap(), Some(96));
        assert_eq!(w.committed_partition(&p), Some(96));
        assert_eq!(w.occupancy(), Some(all), "the merged grid is one pass's");
        // The same plan again keeps the parts; another clears them.
        w.begin_partition(&p).unwrap();
        assert!(w.committed_part(1).is_some());
        let mut other = p.clone();
        other.parts = 2;
        w.begin_partition(&other).unwrap();
        assert!(w.committed_part(1).is_none() && !w.part(0).exists());
    }

    #[test]
    fn a_temporary_directory_records_its_owner_and_goes_on_drop() {
        let base = tempfile::tempdir().unwrap();
        let w = WorkDir::temporary_in(base.path()).unwrap();
        assert!(w.is_temporary());
        let name = w.path().file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with(TEMP_PREFIX), "{name}");
        let owner = Owner::parse(&std::fs::read_to_string(w.path().join(PID_FILE)).unwrap());
        assert_eq!(owner, Some(Owner::current()));
        // Its owner (this process) lives: not stale.
        assert_eq!(remove_stale(base.path()), 0);
        let path = w.path().to_path_buf();
        drop(w);
        assert!(!path.exists());
    }

    #[test]
    fn only_directories_of_a_gone_owner_here_are_stale() {
        let me = Owner::current();
        assert!(!me.gone(&me));
        let other_ns = Owner {
            pid: u32::MAX,
            namespace: "pid:[1]".into(),
            ..me.clone()
        };
        assert!(
            !other_ns.gone(&me),
            "another namespace's pid proves nothing"
        );
        let gone = Owner {
            pid: u32::MAX,
            ..me.clone()
        };
        assert_eq!(
            gone.gone(&me),
            cfg!(target_os = "linux") && !me.boot.is_empty()
        );
        assert_eq!(Owner::parse(&gone.to_string()), Some(gone));
        assert_eq!(Owner::parse("12"), None);
    }
}
