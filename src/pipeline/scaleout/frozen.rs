//! The frozen job (`job.json`): everything a task needs, written once by the plan step, so that
//! workers take no parameters and every task of a job computes with the same ones. It holds the
//! resolved [`DenoiseSpec`] (defaults and the configuration's α applied), the run options that
//! shape the plan (memory budget, tile size), the formats, the input's absolute path with its
//! length and modification time (a task refuses an input that changed), and the plan itself
//! (the partition rewrites `plan.json`, so the frozen copy is the one tasks trust).

use std::path::{Path, PathBuf};
use std::time::UNIX_EPOCH;

use serde::{Deserialize, Serialize};

use super::ScaleoutError;
use super::layout::{JOB_FILE, commit_json, load_json, output_path};
use crate::denoise::cloud;
use crate::io::raw::BinLayout;
use crate::io::{Format, IoError};
use crate::pipeline::{DenoiseSpec, Job, RunOptions};
use crate::tiling::plan::Plan;

/// Version of the `job.json` layout and of the work directory's; a work directory of another
/// version is refused. 2: the partition is written in parts (`part_<p>/`).
pub const VERSION: u32 = 2;

/// A format as stored: its name, and the layout of a raw `.bin` format (which the name alone
/// reads back as KITTI).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StoredFormat {
    /// [`Format::name`].
    pub name: Format,
    /// The layout of [`Format::Bin`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bin: Option<BinLayout>,
}

impl From<Format> for StoredFormat {
    fn from(f: Format) -> StoredFormat {
        StoredFormat {
            name: f,
            bin: match f {
                Format::Bin(l) => Some(l),
                _ => None,
            },
        }
    }
}

impl StoredFormat {
    /// The format.
    pub fn format(self) -> Format {
        self.bin.map_or(self.name, Format::Bin)
    }
}

/// What identifies the input file between planning and the tasks that read it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputId {
    /// Length in bytes.
    pub len: u64,
    /// Modification time, nanoseconds since the Unix epoch (0 when the file system has none).
    pub modified_ns: u64,
}

impl InputId {
    /// The identity of the file at `path`.
    ///
    /// # Errors
    /// Its metadata cannot be read.
    pub fn of(path: &Path) -> Result<InputId, IoError> {
        let m = std::fs::metadata(path).map_err(|e| IoError::io(path, e))?;
        let modified_ns = m
            .modified()
            .ok()
            .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
            .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
        Ok(InputId {
            len: m.len(),
            modified_ns,
        })
    }
}

/// The frozen job (see the module overview).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrozenJob {
    /// [`VERSION`].
    pub version: u32,
    /// The input: absolute, or relative to the work directory when the job carries a copy of its
    /// input (an object-store job, see [`FrozenJob::input_path`]).
    pub input: PathBuf,
    /// Its identity when planned (for a copy in the work directory, its length alone).
    pub input_id: InputId,
    /// The input format when given (else told from the extension, as `qemd denoise` does).
    pub input_format: Option<StoredFormat>,
    /// The format of the stitched output.
    pub output_format: StoredFormat,
    /// What the run computes.
    pub spec: DenoiseSpec,
    /// The memory budget the plan was made for (it sizes the tiles and bounds each task).
    pub memory_budget: u64,
    /// The forced tile size, if any.
    pub tile_points: Option<u64>,
    /// The kernel's working set per point ([`crate::pipeline::bytes_per_point`] of the spec and
    /// the input's record length), so tasks that never read the input size their limits alike.
    pub bytes_per_point: u64,
    /// The plan.
    pub plan: Plan,
    /// Stitch tasks: the plan's parts when the output can be written in ranges
    /// ([`crate::pipeline::tiled::stitch::ranges`]), else 1 (as in jobs planned before ranges).
    #[serde(default = "one")]
    pub stitch_ranges: u64,
}

/// One stitch range.
fn one() -> u64 {
    1
}

impl FrozenJob {
    /// The frozen job of the work directory `dir`.
    ///
    /// # Errors
    /// [`ScaleoutError::WorkDir`] when there is none (not planned), it is unreadable or of
    /// another version.
    pub fn load(dir: &Path) -> Result<FrozenJob, ScaleoutError> {
        let path = dir.join(JOB_FILE);
        let bad = |detail: String| ScaleoutError::WorkDir {
            path: dir.to_path_buf(),
            detail,
        };
        let text = match std::fs::read(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(bad(format!(
                    "no {JOB_FILE}: not a planned work directory (run `qemd plan` first)"
                )));
            }
            Err(e) => return Err(bad(format!("cannot read {JOB_FILE}: {e}"))),
        };
        let version = serde_json::from_slice::<serde_json::Value>(&text)
            .ok()
            .and_then(|v| v.get("version")?.as_u64());
        if version != Some(u64::from(VERSION)) {
            return Err(bad(format!(
                "{JOB_FILE} is of version {}, this qemd reads version {VERSION}",
                version.map_or_else(|| "unknown".to_string(), |v| v.to_string())
            )));
        }
        serde_json::from_slice(&text).map_err(|e| bad(format!("{JOB_FILE} is corrupt: {e}")))
    }

    /// The frozen job of `dir`, if there is a readable one.
    pub fn find(dir: &Path) -> Option<FrozenJob> {
        load_json(&dir.join(JOB_FILE))
    }

    /// Saves it in `dir` (atomically, synced).
    ///
    /// # Errors
    /// Write failures.
    pub fn save(&self, dir: &Path) -> Result<(), IoError> {
        commit_json(&dir.join(JOB_FILE), self, true)
    }

    /// Where a task in the work directory `dir` reads the input: the absolute path, or the copy
    /// the job carries in `dir`.
    pub fn input_path(&self, dir: &Path) -> PathBuf {
        if self.input.is_absolute() {
            self.input.clone()
        } else {
            dir.join(&self.input)
        }
    }

    /// The job a task runs: the frozen input and spec, the output into the work directory.
    pub fn job(&self, dir: &Path) -> Job {
        let out = self.output_format.format();
        Job {
            input: self.input_path(dir),
            output: output_path(dir, out),
            input_format: self.input_format.map(StoredFormat::format),
            output_format: Some(out),
            spec: self.spec.clone(),
            trajectory: None,
        }
    }

    /// The run options of a task in `dir`.
    pub fn options(&self, dir: &Path) -> RunOptions {
        RunOptions {
            memory_budget: self.memory_budget,
            tile_points: self.tile_points,
            work_dir: Some(dir.to_path_buf()),
            ..RunOptions::default()
        }
    }

    /// The limits every tile of the plan was made for.
    pub fn limits(&self, dir: &Path) -> crate::pipeline::tiled::plan::Limits {
        crate::pipeline::tiled::plan::Limits::new(&self.options(dir), self.bytes_per_point)
    }

    /// Tasks of each phase, in [`super::Phase::ALL`] order.
    pub fn tasks(&self) -> [u64; 4] {
        let tiles = self.plan.tiles.len() as u64;
        let globals = if cloud::needs_globals(&self.spec.params) {
            tiles
        } else {
            0
        };
        [self.plan.parts(), globals, tiles, self.stitch_ranges.max(1)]
    }

    /// Tasks of `phase`.
    pub fn tasks_of(&self, phase: super::Phase) -> u64 {
        let i = super::Phase::ALL
            .iter()
            .position(|&p| p == phase)
            .expect("every phase is listed");
        self.tasks()[i]
    }

    /// [`ScaleoutError::InputChanged`] unless the input is still the file that was planned.
    ///
    /// # Errors
    /// As said, and an input that cannot be read.
    pub fn check_input(&self, dir: &Path) -> Result<(), ScaleoutError> {
        let path = self.input_path(dir);
        let mut now = InputId::of(&path)?;
        if !self.input.is_absolute() {
            // A copy in the work directory (downloaded anew by each task) has no stable time.
            now.modified_ns = 0;
        }
        if now != self.input_id {
            return Err(ScaleoutError::InputChanged {
                path,
                detail: format!(
                    "changed since it was planned ({} bytes then, {} now, or a new modification \
                     time); plan the job again in a new work directory",
                    self.input_id.len, now.len
                ),
            });
        }
        Ok(())
    }
}
