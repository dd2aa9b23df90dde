//! Inputs that are streams: standard input (`-`), `/dev/stdin`, FIFOs, character devices.
//!
//! # Brief overview
//!
//! The readers work on files: LAS seeks to its point data and EVLRs, and the pipeline reads its
//! input more than once (the header, then the points; the tiled path streams it three times). A
//! stream can be read only once, so [`InputFile::open`] first copies it, in 1 MiB pieces (memory
//! stays bounded whatever the size), to a **spool**: a temporary file in the temporary directory
//! (`--temp-dir`), removed when the [`InputFile`] is dropped. A spooled input needs as much free
//! disk as its size. Regular files (and `/dev/stdin` redirected from one) are read in place.
//!
//! The format of a stream comes from the format given, else from the path's extension (a FIFO
//! named `scan.las`), else from the content ([`sniff`]). Raw `.bin` scans (KITTI,
//! nuScenes) have no signature and need the format given.
//!
//! Errors about a spool name the input as the user gave it (`<stdin>` for `-`), never the
//! temporary path.

use std::io::Read;
use std::path::{Path, PathBuf};

use super::output::is_stdio;
use super::sniff::{SNIFF_LEN, sniff};
use super::{Format, IoError};

/// How the input is shown in messages when it is standard input.
pub const STDIN_NAME: &str = "<stdin>";

/// An input ready to be opened by path: the file itself, or a spool of a stream.
#[derive(Debug)]
pub struct InputFile {
    /// The path to read.
    read: PathBuf,
    /// The path as the user gave it (`<stdin>` for `-`).
    shown: PathBuf,
    /// The format, when it was given or told from the stream.
    format: Option<Format>,
    /// The spool, removed on drop.
    spool: Option<tempfile::TempPath>,
}

/// True when `path` is read as a stream: `-`, or an existing file that is not a regular one
/// (a pipe behind `/dev/stdin`, a FIFO, a character device).
pub fn is_stream_input(path: &Path) -> bool {
    is_stdio(path) || std::fs::metadata(path).is_ok_and(|m| !m.is_file() && !m.is_dir())
}

impl InputFile {
    /// Prepares `path` for reading; a stream is spooled into `temp_dir` (the system temporary
    /// directory when `None`). `format` is the format given by the user, if any.
    ///
    /// # Errors
    /// The stream cannot be read or the spool written; the format of a stream cannot be told.
    pub fn open(
        path: &Path,
        format: Option<Format>,
        temp_dir: Option<&Path>,
    ) -> Result<InputFile, IoError> {
        if !is_stream_input(path) {
            return Ok(InputFile {
                read: path.to_path_buf(),
                shown: path.to_path_buf(),
                format,
                spool: None,
            });
        }
        let shown = if is_stdio(path) {
            PathBuf::from(STDIN_NAME)
        } else {
            path.to_path_buf()
        };
        if is_stdio(path) && std::io::IsTerminal::is_terminal(&std::io::stdin()) {
            return Err(IoError::invalid(
                &shown,
                "standard input is a terminal; pipe or redirect a scan into it",
            ));
        }
        let dir = temp_dir.map_or_else(std::env::temp_dir, Path::to_path_buf);
        let mut tmp = tempfile::Builder::new()
            .prefix(".qemd-stdin.")
            .tempfile_in(&dir)
            .map_err(|e| IoError::io(&dir, e))?;
        let copied = if is_stdio(path) {
            copy_stream(&mut std::io::stdin().lock(), tmp.as_file_mut())
        } else {
            std::fs::File::open(path).and_then(|mut f| copy_stream(&mut f, tmp.as_file_mut()))
        };
        let bytes = copied.map_err(|e| IoError::io(&shown, e))?;
        if bytes == 0 {
            return Err(IoError::invalid(&shown, "empty input: nothing was read"));
        }
        let spool = tmp.into_temp_path();
        let format = match format.or_else(|| Format::from_path(path).ok()) {
            Some(f) => f,
            None => {
                let mut head = Vec::with_capacity(SNIFF_LEN);
                std::fs::File::open(&spool)
                    .and_then(|f| f.take(SNIFF_LEN as u64).read_to_end(&mut head))
                    .map_err(|e| IoError::io(&shown, e))?;
                sniff(&head).ok_or_else(|| {
                    IoError::invalid(
                        &shown,
                        "cannot tell the format from the content (raw .bin scans have no \
                         signature); give the input format (--input-format)",
                    )
                })?
            }
        };
        Ok(InputFile {
            read: spool.to_path_buf(),
            shown,
            format: Some(format),
            spool: Some(spool),
        })
    }

    /// The path to open (the spool for a stream).
    pub fn path(&self) -> &Path {
        &self.read
    }

    /// The input as the user named it.
    pub fn shown(&self) -> &Path {
        &self.shown
    }

    /// The format given, or told from a stream.
    pub fn format(&self) -> Option<Format> {
        self.format
    }

    /// True when the input was a stream copied to a spool.
    pub fn is_spooled(&self) -> bool {
        self.spool.is_some()
    }

    /// `e` with the spool's path replaced by the input's name.
    pub fn explain(&self, e: IoError) -> IoError {
        if self.is_spooled() {
            e.with_path(&self.read, &self.shown)
        } else {
            e
        }
    }
}

/// Copies `from` to `to` with a fixed buffer; returns the bytes copied.
fn copy_stream(from: &mut impl Read, to: &mut std::fs::File) -> std::io::Result<u64> {
    let mut buf = vec![0u8; 1 << 20];
    let mut total = 0u64;
    loop {
        let n = match from.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        std::io::Write::write_all(to, &buf[..n])?;
        total += n as u64;
    }
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regular_files_are_read_in_place() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.xyz");
        std::fs::write(&p, "0 0 0\n").unwrap();
        let i = InputFile::open(&p, None, None).unwrap();
        assert!(!i.is_spooled());
        assert_eq!(i.path(), p);
        assert_eq!(i.format(), None);
    }

    #[test]
    fn error_paths_name_the_stream() {
        let i = InputFile {
            read: "/tmp/.qemd-stdin.x".into(),
            shown: STDIN_NAME.into(),
            format: Some(Format::Ply),
            spool: Some(tempfile::NamedTempFile::new().unwrap().into_temp_path()),
        };
        let e = i.explain(IoError::header(Path::new("/tmp/.qemd-stdin.x"), "bad"));
        assert_eq!(e.to_string(), "<stdin>: bad header: bad");
    }
}
