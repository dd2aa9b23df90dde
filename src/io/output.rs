//! The one way every output is written: [`AtomicFile`].
//!
//! # Brief overview
//!
//! What happens depends on what the target path names when the file is created
//! ([`OutputTarget::of`]):
//!
//! | target | how it is written |
//! |---|---|
//! | a missing path or a regular file | a temporary file in the target's directory, renamed onto it at [`AtomicFile::commit`] (readers never see a half-written file; a failed run leaves the old file) |
//! | a symbolic link to a regular file | the same, **next to the resolved file**: the link stays a link and its target gets the new content |
//! | `-` or `/dev/stdout` | written straight to the process's standard output |
//! | a character or block device, a FIFO, a socket, or a link to one (`/dev/null`, `mkfifo` pipes, `/dev/stderr`) | opened and written directly; never renamed over, never truncated |
//! | a directory, a dangling symbolic link | refused with a one-line error before anything is written |
//!
//! Streams cannot seek. A sink that must patch its header after the data (LAS/LAZ: the bounds
//! and the LASzip chunk table are known only at the end) creates its file with
//! [`AtomicFile::create_seekable`]: towards a stream it writes a *spool* (a temporary file in the
//! temporary directory, as large as the output) and copies it to the stream at commit; towards a
//! regular file it behaves like [`AtomicFile::create`].
//!
//! [`AtomicFile::memory`] writes into memory instead: the bytes are handed to its
//! [`MemoryOutput`] at commit (the service's synchronous path answers with them, with no file).
//!
//! Dropping an uncommitted `AtomicFile` removes its temporary file; bytes already written to a
//! stream cannot be taken back (a reader of a pipe sees a short stream and the run's non-zero
//! exit status).

use std::fs::File;
use std::io::{BufWriter, Cursor, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use super::IoError;

/// The path that means standard output (and, as an input, standard input).
pub const STDIO: &str = "-";

/// True when `path` is `-`, the conventional name of standard input or output.
pub fn is_stdio(path: &Path) -> bool {
    path.as_os_str() == STDIO
}

/// Buffer of every output.
const BUFFER: usize = 1 << 20;

/// What an output path names, decided once when the output is created.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum OutputTarget {
    /// The process's standard output (`-`, `/dev/stdout`).
    Stdout,
    /// An existing file that is not a regular one (device, FIFO, socket), written directly.
    Stream(PathBuf),
    /// A regular file or a missing path (symbolic links resolved): temporary file + rename.
    Replace(PathBuf),
}

impl OutputTarget {
    /// Classifies `path` (see the [module overview](self)).
    ///
    /// # Errors
    /// A directory, a dangling symbolic link, or metadata that cannot be read.
    pub fn of(path: &Path) -> Result<OutputTarget, IoError> {
        if is_stdio(path) || path == Path::new("/dev/stdout") {
            return Ok(OutputTarget::Stdout);
        }
        let refuse = |detail: &str| IoError::Invalid {
            path: path.to_path_buf(),
            detail: detail.to_string(),
        };
        let link = match std::fs::symlink_metadata(path) {
            Ok(m) => m,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(OutputTarget::Replace(path.to_path_buf()));
            }
            Err(e) => return Err(IoError::io(path, e)),
        };
        let meta = if link.file_type().is_symlink() {
            match std::fs::metadata(path) {
                Ok(m) => m,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    return Err(refuse(
                        "is a dangling symbolic link; not writing through it (remove it or \
                         create its target)",
                    ));
                }
                Err(e) => return Err(IoError::io(path, e)),
            }
        } else {
            link.clone()
        };
        if meta.is_dir() {
            return Err(refuse("is a directory, not an output file"));
        }
        if !meta.is_file() {
            return Ok(OutputTarget::Stream(path.to_path_buf()));
        }
        if link.file_type().is_symlink() {
            let resolved = path.canonicalize().map_err(|e| IoError::io(path, e))?;
            return Ok(OutputTarget::Replace(resolved));
        }
        Ok(OutputTarget::Replace(path.to_path_buf()))
    }

    /// True for standard output and other streams (nothing is renamed).
    pub fn is_stream(&self) -> bool {
        !matches!(self, OutputTarget::Replace(_))
    }
}

/// True when `path` is written as a stream (standard output, a device, a FIFO); false for
/// regular files, missing paths and paths that cannot be classified.
pub fn is_stream_output(path: &Path) -> bool {
    OutputTarget::of(path).is_ok_and(|t| t.is_stream())
}

/// An opened stream: standard output or a file opened for writing.
type Stream = Box<dyn Write + Send + Sync>;

enum Dest {
    /// A temporary file renamed onto `target` at commit.
    Rename {
        target: PathBuf,
        tmp: BufWriter<tempfile::NamedTempFile>,
    },
    /// Straight to a stream.
    Direct(BufWriter<Stream>),
    /// A seekable temporary file copied to the stream at commit.
    Spool {
        tmp: BufWriter<tempfile::NamedTempFile>,
        stream: Stream,
    },
    /// In memory, handed to `slot` at commit.
    Memory {
        buf: Cursor<Vec<u8>>,
        slot: MemoryOutput,
    },
}

/// Where the bytes of an [`AtomicFile::memory`] output arrive when it is committed.
#[derive(Debug, Clone, Default)]
pub struct MemoryOutput(Arc<Mutex<Option<Vec<u8>>>>);

impl MemoryOutput {
    /// The committed bytes (once); `None` before the commit or after a failed run.
    pub fn take(&self) -> Option<Vec<u8>> {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take()
    }
}

/// A buffered output that appears at its target path only when committed, or is written straight
/// to a stream (see the [module overview](self)).
pub struct AtomicFile {
    /// The path as given (for messages).
    target: PathBuf,
    dest: Dest,
}

impl AtomicFile {
    /// Starts writing towards `target`.
    ///
    /// # Errors
    /// The target is a directory or a dangling link; the target's directory does not exist or is
    /// not writable; a stream cannot be opened.
    pub fn create(target: &Path) -> Result<AtomicFile, IoError> {
        let dest = match OutputTarget::of(target)? {
            OutputTarget::Replace(resolved) => {
                // What killed writers of this target left (issue 51: a `kill -9` during the
                // stitch left `.o.ply.XXXXXX.tmp` for good); a live writer's file stays. A
                // directory that cannot be listed fails below, where the temporary file goes.
                let _ = remove_temps(&resolved, STALE_AFTER);
                Dest::Rename {
                    tmp: BufWriter::with_capacity(BUFFER, temp_next_to(&resolved, target)?),
                    target: resolved,
                }
            }
            t => Dest::Direct(BufWriter::with_capacity(BUFFER, open_stream(&t, target)?)),
        };
        Ok(AtomicFile {
            target: target.to_path_buf(),
            dest,
        })
    }

    /// Like [`AtomicFile::create`], for writers that seek: a stream target is spooled to a
    /// temporary file in `spool_dir` (the system temporary directory when `None`) and copied to
    /// the stream at commit.
    ///
    /// # Errors
    /// As [`AtomicFile::create`]; the spool cannot be created.
    pub fn create_seekable(target: &Path, spool_dir: Option<&Path>) -> Result<AtomicFile, IoError> {
        let t = OutputTarget::of(target)?;
        if !t.is_stream() {
            return AtomicFile::create(target);
        }
        let dir = spool_dir.map_or_else(std::env::temp_dir, Path::to_path_buf);
        let tmp = tempfile::Builder::new()
            .prefix(".qemd-spool.")
            .tempfile_in(&dir)
            .map_err(|e| IoError::io(&dir, e))?;
        Ok(AtomicFile {
            target: target.to_path_buf(),
            dest: Dest::Spool {
                tmp: BufWriter::with_capacity(BUFFER, tmp),
                stream: open_stream(&t, target)?,
            },
        })
    }

    /// An output in memory, named `name` in messages; the bytes reach the returned
    /// [`MemoryOutput`] at commit, and nothing if it is dropped uncommitted.
    pub fn memory(name: impl Into<PathBuf>) -> (AtomicFile, MemoryOutput) {
        let slot = MemoryOutput::default();
        let file = AtomicFile {
            target: name.into(),
            dest: Dest::Memory {
                buf: Cursor::new(Vec::new()),
                slot: slot.clone(),
            },
        };
        (file, slot)
    }

    /// True for an output in memory ([`AtomicFile::memory`]).
    pub fn in_memory(&self) -> bool {
        matches!(self.dest, Dest::Memory { .. })
    }

    /// The path as given.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// A second handle on the temporary file, for writers that need to read back what they wrote
    /// (E57 updates its page checksums). Write through one handle only: the buffer of this one
    /// is flushed first, and nothing should be written through it afterwards. A direct stream has
    /// no file: create such outputs with [`AtomicFile::create_seekable`].
    ///
    /// # Errors
    /// Flush or duplication failures; a direct stream.
    pub fn try_clone_file(&mut self) -> std::io::Result<std::fs::File> {
        match &mut self.dest {
            Dest::Rename { tmp, .. } | Dest::Spool { tmp, .. } => {
                tmp.flush()?;
                tmp.get_ref().as_file().try_clone()
            }
            Dest::Direct(_) => Err(std::io::Error::new(
                std::io::ErrorKind::Unsupported,
                "the output is a stream and cannot be read back",
            )),
            Dest::Memory { .. } => Err(std::io::Error::new(
                std::io::ErrorKind::Unsupported,
                "the output is in memory and has no file",
            )),
        }
    }

    /// Appends the bytes of the file `src`; returns how many. Between files the kernel copies
    /// (`copy_file_range` under Linux), without a pass through user space.
    ///
    /// # Errors
    /// `src` cannot be read; write failures.
    pub fn append_file(&mut self, src: &Path) -> Result<u64, IoError> {
        let mut from = File::open(src).map_err(|e| IoError::io(src, e))?;
        let copied = match &mut self.dest {
            Dest::Rename { tmp, .. } | Dest::Spool { tmp, .. } => tmp
                .flush()
                .and_then(|()| std::io::copy(&mut from, tmp.get_mut().as_file_mut())),
            Dest::Direct(out) => std::io::copy(&mut from, out),
            Dest::Memory { buf, .. } => std::io::copy(&mut from, buf),
        };
        copied.map_err(|e| self.err(e))
    }

    /// True when the output goes to a stream (standard output, a device, a FIFO).
    pub fn is_stream(&self) -> bool {
        matches!(self.dest, Dest::Direct(_) | Dest::Spool { .. })
    }

    /// Flushes, syncs to disk and renames onto the target, replacing any regular file there; a
    /// stream is flushed (a spool copied to it first).
    ///
    /// # Errors
    /// Flush, copy or rename failures.
    pub fn commit(self) -> Result<(), IoError> {
        self.finish(true)
    }

    /// Like [`AtomicFile::commit`] without the sync: the file still appears only complete to
    /// every reader and survives the process being killed, but not a power loss. For scratch
    /// files (tile results), where a sync per tile would dominate the run.
    ///
    /// # Errors
    /// Flush or rename failures.
    pub fn commit_unsynced(self) -> Result<(), IoError> {
        self.finish(false)
    }

    fn finish(self, sync: bool) -> Result<(), IoError> {
        let shown = self.target;
        let io = |e| IoError::io(&shown, e);
        match self.dest {
            Dest::Rename { target, tmp } => {
                let tmp = tmp.into_inner().map_err(|e| io(e.into_error()))?;
                if sync {
                    tmp.as_file().sync_data().map_err(io)?;
                }
                fix_permissions(tmp.as_file(), &target).map_err(io)?;
                tmp.persist(&target).map_err(|e| io(e.error))?;
            }
            Dest::Direct(mut out) => out.flush().map_err(io)?,
            Dest::Spool { tmp, mut stream } => {
                let tmp = tmp.into_inner().map_err(|e| io(e.into_error()))?;
                let mut file = tmp.reopen().map_err(io)?;
                file.seek(SeekFrom::Start(0)).map_err(io)?;
                let _ = std::io::copy(&mut file, &mut stream).map_err(io)?;
                stream.flush().map_err(io)?;
            }
            Dest::Memory { buf, slot } => {
                *slot
                    .0
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(buf.into_inner());
            }
        }
        Ok(())
    }

    /// Wraps an OS error with the target path.
    pub fn err(&self, e: std::io::Error) -> IoError {
        IoError::io(&self.target, e)
    }
}

/// The temporary file a rename-mode output writes, in `resolved`'s directory (so the rename
/// stays on one file system).
fn temp_next_to(resolved: &Path, shown: &Path) -> Result<tempfile::NamedTempFile, IoError> {
    let dir = match resolved.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let name = resolved
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = tempfile::Builder::new()
        .prefix(&format!(".{name}."))
        .suffix(".tmp")
        .tempfile_in(dir)
        .map_err(|e| IoError::io(shown, e))?;
    // Held while the file lives (the process's end releases it, however it ends): it tells
    // [`remove_stale_temps`] that a writer is alive. A file system without locks leaves the
    // file unlocked, and then no other writer ever removes it.
    let _ = tmp.as_file().try_lock();
    Ok(tmp)
}

/// How old a temporary file must be before [`AtomicFile::create`] removes it: its writer locks
/// it right after creating it, and must not lose it in between.
const STALE_AFTER: std::time::Duration = std::time::Duration::from_secs(1);

/// Removes the temporary files that writers of `target` ([`AtomicFile::create`]) left behind
/// when they were killed; returns how many. A live writer holds a lock on its file, which is
/// then kept (as is one whose lock cannot be tested). [`AtomicFile::create`] does this itself,
/// for files older than a second.
///
/// # Errors
/// The directory cannot be listed or a file removed.
pub fn remove_stale_temps(target: &Path) -> Result<usize, IoError> {
    remove_temps(target, std::time::Duration::ZERO)
}

/// [`remove_stale_temps`] for files at least `min_age` old.
fn remove_temps(target: &Path, min_age: std::time::Duration) -> Result<usize, IoError> {
    let dir = match target.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let Some(name) = target.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return Ok(0);
    };
    let prefix = format!(".{name}.");
    let mut removed = 0;
    for entry in std::fs::read_dir(dir).map_err(|e| IoError::io(dir, e))? {
        let entry = entry.map_err(|e| IoError::io(dir, e))?;
        let n = entry.file_name().to_string_lossy().into_owned();
        if n.starts_with(&prefix)
            && n.ends_with(".tmp")
            && entry.path().is_file()
            && stale(&entry, min_age)
        {
            std::fs::remove_file(entry.path()).map_err(|e| IoError::io(&entry.path(), e))?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// True when no live writer holds the temporary file `entry`: it is at least `min_age` old and
/// its lock can be taken.
fn stale(entry: &std::fs::DirEntry, min_age: std::time::Duration) -> bool {
    let old = min_age.is_zero()
        || entry
            .metadata()
            .and_then(|m| m.modified())
            .is_ok_and(|t| t.elapsed().is_ok_and(|age| age >= min_age));
    old && std::fs::File::open(entry.path()).is_ok_and(|f| f.try_lock().is_ok())
}

/// Opens a stream target for writing (never creating, truncating or renaming anything).
fn open_stream(t: &OutputTarget, shown: &Path) -> Result<Stream, IoError> {
    Ok(match t {
        OutputTarget::Stdout => Box::new(std::io::stdout()),
        OutputTarget::Stream(p) => Box::new(
            std::fs::OpenOptions::new()
                .write(true)
                .open(p)
                .map_err(|e| IoError::io(shown, e))?,
        ),
        OutputTarget::Replace(_) => unreachable!("a regular file is not a stream"),
    })
}

/// Seeking flushes the buffer first; backends that patch a header after the data (LAS) use it
/// and create their file with [`AtomicFile::create_seekable`]. A direct stream cannot seek.
impl Seek for AtomicFile {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        match &mut self.dest {
            Dest::Rename { tmp, .. } | Dest::Spool { tmp, .. } => tmp.seek(pos),
            Dest::Memory { buf, .. } => buf.seek(pos),
            Dest::Direct(_) => Err(std::io::Error::new(
                std::io::ErrorKind::Unsupported,
                "the output is a stream and cannot seek",
            )),
        }
    }
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match &mut self.dest {
            Dest::Rename { tmp, .. } | Dest::Spool { tmp, .. } => tmp.write(buf),
            Dest::Direct(out) => out.write(buf),
            Dest::Memory { buf: b, .. } => b.write(buf),
        }
    }
    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        match &mut self.dest {
            Dest::Rename { tmp, .. } | Dest::Spool { tmp, .. } => tmp.write_all(buf),
            Dest::Direct(out) => out.write_all(buf),
            Dest::Memory { buf: b, .. } => b.write_all(buf),
        }
    }
    fn flush(&mut self) -> std::io::Result<()> {
        match &mut self.dest {
            Dest::Rename { tmp, .. } | Dest::Spool { tmp, .. } => tmp.flush(),
            Dest::Direct(out) => out.flush(),
            Dest::Memory { .. } => Ok(()),
        }
    }
}

/// The temporary file is created owner-only; give the result the permissions of the file it
/// replaces, or the usual rw-r--r-- of a new file.
#[cfg(unix)]
fn fix_permissions(file: &File, target: &Path) -> std::io::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    let perms = std::fs::metadata(target)
        .map(|m| m.permissions())
        .unwrap_or_else(|_| std::fs::Permissions::from_mode(0o644));
    file.set_permissions(perms)
}

/// Elsewhere a fresh temporary file already has ordinary permissions.
#[cfg(not(unix))]
fn fix_permissions(_file: &File, _target: &Path) -> std::io::Result<()> {
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue11_stale_temps_of_a_target_go_and_nothing_else() {
        let d = tempfile::tempdir().unwrap();
        let target = d.path().join("body_00003.bin");
        for n in [
            ".body_00003.bin.a1B2.tmp",
            ".body_00003.bin.zz.tmp",
            ".body_00004.bin.q.tmp",
        ] {
            std::fs::write(d.path().join(n), b"x").unwrap();
        }
        std::fs::write(&target, b"committed").unwrap();
        assert_eq!(remove_stale_temps(&target).unwrap(), 2);
        let mut left: Vec<String> = std::fs::read_dir(d.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        assert_eq!(left, [".body_00004.bin.q.tmp", "body_00003.bin"]);
    }

    #[test]
    fn atomic_file_leaves_nothing_when_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.ply");
        {
            let mut f = AtomicFile::create(&target).unwrap();
            f.write_all(b"partial").unwrap();
        }
        assert!(!target.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        let mut f = AtomicFile::create(&target).unwrap();
        f.write_all(b"whole").unwrap();
        f.commit().unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"whole");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&target).unwrap().permissions().mode();
            assert_eq!(mode & 0o777, 0o644, "readable by others like any new file");
        }
    }

    #[test]
    fn issue10_memory_output_arrives_at_commit_only() {
        let (mut f, slot) = AtomicFile::memory("<response>");
        f.write_all(b"header later").unwrap();
        f.seek(SeekFrom::Start(0)).unwrap();
        f.write_all(b"HEADER").unwrap();
        assert!(f.in_memory() && !f.is_stream());
        assert_eq!(slot.take(), None, "nothing before the commit");
        f.commit().unwrap();
        assert_eq!(slot.take().unwrap(), b"HEADER later");
        let (mut g, slot) = AtomicFile::memory("<response>");
        g.write_all(b"partial").unwrap();
        drop(g);
        assert_eq!(slot.take(), None, "a dropped output hands over nothing");
    }

    #[test]
    fn issue12_targets_are_classified() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.ply");
        assert_eq!(
            OutputTarget::of(&file).unwrap(),
            OutputTarget::Replace(file.clone())
        );
        std::fs::write(&file, b"x").unwrap();
        assert_eq!(
            OutputTarget::of(&file).unwrap(),
            OutputTarget::Replace(file.clone())
        );
        assert_eq!(
            OutputTarget::of(Path::new("-")).unwrap(),
            OutputTarget::Stdout
        );
        assert_eq!(
            OutputTarget::of(Path::new("/dev/null")).unwrap(),
            OutputTarget::Stream("/dev/null".into())
        );
        let e = OutputTarget::of(dir.path()).unwrap_err().to_string();
        assert!(e.contains("is a directory"), "{e}");
        #[cfg(unix)]
        {
            let link = dir.path().join("link.ply");
            std::os::unix::fs::symlink(&file, &link).unwrap();
            assert_eq!(
                OutputTarget::of(&link).unwrap(),
                OutputTarget::Replace(file.canonicalize().unwrap())
            );
            let dangling = dir.path().join("dangling.ply");
            std::os::unix::fs::symlink(dir.path().join("missing.ply"), &dangling).unwrap();
            let e = OutputTarget::of(&dangling).unwrap_err().to_string();
            assert!(e.contains("dangling symbolic link"), "{e}");
        }
    }

    #[test]
    fn issue12_dev_null_is_written_not_replaced() {
        let mut f = AtomicFile::create(Path::new("/dev/null")).unwrap();
        assert!(f.is_stream());
        f.write_all(b"gone").unwrap();
        assert!(f.seek(SeekFrom::Start(0)).is_err(), "a stream cannot seek");
        f.commit().unwrap();
        let mut f = AtomicFile::create_seekable(Path::new("/dev/null"), None).unwrap();
        f.write_all(b"header later").unwrap();
        f.seek(SeekFrom::Start(0)).unwrap();
        f.write_all(b"HEADER").unwrap();
        f.commit().unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::FileTypeExt;
            let m = std::fs::symlink_metadata("/dev/null").unwrap();
            assert!(
                m.file_type().is_char_device(),
                "/dev/null is still a device"
            );
        }
    }
}
