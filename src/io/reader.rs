//! What a [`super::Source`] reads from: [`Input`], a file or bytes already in memory.
//!
//! # Brief overview
//!
//! Every reader is written against [`Input`], which is `Read + Seek` and knows the name errors
//! use and, when it can be had, its length (the readers check the sizes a header declares
//! against it). [`Input::from_path`] opens a file; [`Input::from_bytes`] reads bytes the caller
//! holds (the service's synchronous path hands over the request body, so nothing is written to
//! disk). Some readers need a second, independent cursor on the same bytes (the E57 decoder
//! thread, the LAS trailer after a failed decode): [`Input::reopen`] gives one, opening the file
//! again or sharing the bytes.

use std::fs::File;
use std::io::{Cursor, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::IoError;

/// Bytes shared between the cursors of one in-memory input.
type Shared = Arc<dyn AsRef<[u8]> + Send + Sync>;

/// A cursor over shared bytes.
#[derive(Clone)]
struct SharedCursor(Cursor<SharedBytes>);

#[derive(Clone)]
struct SharedBytes(Shared);

impl AsRef<[u8]> for SharedBytes {
    fn as_ref(&self) -> &[u8] {
        (*self.0).as_ref()
    }
}

enum Bytes {
    File(File),
    Memory(SharedCursor),
}

/// The bytes of one input and the name its errors give (see the [module overview](self)).
pub struct Input {
    name: PathBuf,
    len: Option<u64>,
    bytes: Bytes,
}

impl std::fmt::Debug for Input {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Input")
            .field("name", &self.name)
            .field("len", &self.len)
            .field("in_memory", &matches!(self.bytes, Bytes::Memory(_)))
            .finish()
    }
}

impl Input {
    /// Opens the file at `path`.
    ///
    /// # Errors
    /// [`IoError::Io`] naming the path.
    pub fn from_path(path: &Path) -> Result<Input, IoError> {
        let file = File::open(path).map_err(|e| IoError::io(path, e))?;
        let len = file
            .metadata()
            .ok()
            .filter(std::fs::Metadata::is_file)
            .map(|m| m.len());
        Ok(Input {
            name: path.to_path_buf(),
            len,
            bytes: Bytes::File(file),
        })
    }

    /// Reads `bytes`, naming the input `name` in messages.
    pub fn from_bytes(
        name: impl Into<PathBuf>,
        bytes: impl AsRef<[u8]> + Send + Sync + 'static,
    ) -> Input {
        let shared: Shared = Arc::new(bytes);
        let len = (*shared).as_ref().len() as u64;
        Input {
            name: name.into(),
            len: Some(len),
            bytes: Bytes::Memory(SharedCursor(Cursor::new(SharedBytes(shared)))),
        }
    }

    /// The name errors give: the path, or the name given with the bytes.
    pub fn name(&self) -> &Path {
        &self.name
    }

    /// The length in bytes, when known (a regular file, bytes in memory; not a pipe).
    pub fn len(&self) -> Option<u64> {
        self.len
    }

    /// True for an input known to hold no bytes.
    pub fn is_empty(&self) -> bool {
        self.len == Some(0)
    }

    /// True when the bytes are in memory rather than in a file.
    pub fn in_memory(&self) -> bool {
        matches!(self.bytes, Bytes::Memory(_))
    }

    /// A second input on the same bytes, with its own position (at the start).
    ///
    /// # Errors
    /// The file cannot be opened again.
    pub fn reopen(&self) -> Result<Input, IoError> {
        self.reopener().open()
    }

    /// What opens this input again later, without holding a file open meanwhile.
    pub fn reopener(&self) -> Reopener {
        Reopener {
            name: self.name.clone(),
            shared: match &self.bytes {
                Bytes::File(_) => None,
                Bytes::Memory(c) => Some(c.0.get_ref().clone()),
            },
        }
    }

    /// Wraps an OS error with the input's name.
    pub fn err(&self, e: std::io::Error) -> IoError {
        IoError::io(&self.name, e)
    }
}

/// Opens an [`Input`] again: the file by its path, or the same bytes in memory.
#[derive(Clone)]
pub struct Reopener {
    name: PathBuf,
    shared: Option<SharedBytes>,
}

impl Reopener {
    /// A new input at byte 0.
    ///
    /// # Errors
    /// The file cannot be opened.
    pub fn open(&self) -> Result<Input, IoError> {
        match &self.shared {
            None => Input::from_path(&self.name),
            Some(b) => Ok(Input {
                name: self.name.clone(),
                len: Some(b.as_ref().len() as u64),
                bytes: Bytes::Memory(SharedCursor(Cursor::new(b.clone()))),
            }),
        }
    }
}

impl Read for Input {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match &mut self.bytes {
            Bytes::File(f) => f.read(buf),
            Bytes::Memory(c) => c.0.read(buf),
        }
    }
}

impl Seek for Input {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        match &mut self.bytes {
            Bytes::File(f) => f.seek(pos),
            Bytes::Memory(c) => c.0.seek(pos),
        }
    }
}

/// Moves `reader` to record `index` of the fixed `record_len`-byte records that start at byte
/// `start` of `path` (how [`super::Source::seek_point`] seeks in a fixed-record format).
///
/// # Errors
/// The seek fails.
pub(crate) fn seek_record(
    reader: &mut std::io::BufReader<Input>,
    path: &Path,
    (start, record_len): (u64, usize),
    index: u64,
) -> Result<(), IoError> {
    reader
        .seek(SeekFrom::Start(start + index * record_len as u64))
        .map(|_| ())
        .map_err(|e| IoError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_read_seek_and_reopen_independently() {
        let mut a = Input::from_bytes("<body>", b"hello world".to_vec());
        assert_eq!(a.len(), Some(11));
        assert!(a.in_memory());
        let mut five = [0u8; 5];
        a.read_exact(&mut five).unwrap();
        assert_eq!(&five, b"hello");
        let mut b = a.reopen().unwrap();
        let mut all = Vec::new();
        b.read_to_end(&mut all).unwrap();
        assert_eq!(all, b"hello world", "a reopened input starts at byte 0");
        a.seek(SeekFrom::Start(6)).unwrap();
        let mut rest = Vec::new();
        a.read_to_end(&mut rest).unwrap();
        assert_eq!(rest, b"world");
        assert_eq!(a.name(), Path::new("<body>"));
    }

    #[test]
    fn a_file_has_its_length_and_a_missing_one_names_its_path() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.xyz");
        std::fs::write(&p, b"1 2 3\n").unwrap();
        let f = Input::from_path(&p).unwrap();
        assert_eq!(f.len(), Some(6));
        assert!(!f.in_memory());
        let e = Input::from_path(&dir.path().join("missing.xyz")).unwrap_err();
        assert!(e.to_string().contains("missing.xyz"), "{e}");
    }
}
