//! The line toolkit of the text formats (XYZ/PTS, OBJ, OFF, the PCD header): line terminators
//! ([`LineEnding`]), splitting, comments and tokens, numbers parsed and printed at a field's
//! precision, `F64` schemas and records for text columns, and a line reader and an atomic line
//! writer that reproduce a file's terminators.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::{AtomicFile, Input, IoError};
use crate::points::{Endian, Field, ScalarType, Schema};

/// Line terminator of a text file.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum LineEnding {
    /// `\n` (Unix).
    #[default]
    Lf,
    /// `\r\n` (Windows).
    CrLf,
}

impl LineEnding {
    /// The terminator's bytes.
    pub fn bytes(self) -> &'static [u8] {
        match self {
            LineEnding::Lf => b"\n",
            LineEnding::CrLf => b"\r\n",
        }
    }

    /// The terminator of a raw line, `None` when the line has none (the file's last line).
    pub(crate) fn of(raw: &[u8]) -> Option<LineEnding> {
        if raw.ends_with(b"\r\n") {
            Some(LineEnding::CrLf)
        } else if raw.ends_with(b"\n") {
            Some(LineEnding::Lf)
        } else {
            None
        }
    }
}

/// Splits a raw line into its content and its terminator (`\n`, `\r\n` or nothing).
pub(crate) fn split_eol(raw: &[u8]) -> (&[u8], &[u8]) {
    let n = match LineEnding::of(raw) {
        Some(LineEnding::CrLf) => 2,
        Some(LineEnding::Lf) => 1,
        None => 0,
    };
    raw.split_at(raw.len() - n)
}

/// `b` without leading and trailing ASCII whitespace.
pub(crate) fn trim(b: &[u8]) -> &[u8] {
    b.trim_ascii()
}

/// `b` up to (excluding) the first `#`.
pub(crate) fn strip_comment(b: &[u8]) -> &[u8] {
    match b.iter().position(|&c| c == b'#') {
        Some(i) => &b[..i],
        None => b,
    }
}

/// True for a blank line or a comment line (`#` or `//`).
pub(crate) fn is_comment_or_blank(content: &[u8]) -> bool {
    let t = trim(content);
    t.is_empty() || t.starts_with(b"#") || t.starts_with(b"//")
}

/// The whitespace-separated tokens of `b`.
pub(crate) fn tokens(b: &[u8]) -> impl Iterator<Item = &[u8]> {
    b.split(|c| c.is_ascii_whitespace())
        .filter(|t| !t.is_empty())
}

/// Parses a decimal number (`nan` and `inf` included).
pub(crate) fn parse_f64(tok: &[u8]) -> Option<f64> {
    std::str::from_utf8(tok).ok()?.parse().ok()
}

/// Parses an unsigned integer.
pub(crate) fn parse_u64(tok: &[u8]) -> Option<u64> {
    std::str::from_utf8(tok).ok()?.parse().ok()
}

/// A token fit for a one-line error message: lossy UTF-8, escaped, at most 40 characters.
pub(crate) fn show(tok: &[u8]) -> String {
    let s = String::from_utf8_lossy(tok);
    let mut out: String = s
        .chars()
        .take(40)
        .collect::<String>()
        .escape_debug()
        .collect();
    if s.chars().count() > 40 {
        out.push('…');
    }
    out
}

/// Appends `v` in the shortest text that reads back as the same value of type `ty`: `f32` fields
/// print as `f32`, everything else as `f64` (integers print without a fraction).
pub(crate) fn push_value(out: &mut Vec<u8>, ty: ScalarType, v: f64) {
    // Writing into a Vec<u8> cannot fail.
    let _ = match ty {
        ScalarType::F32 => write!(out, "{}", v as f32),
        _ => write!(out, "{v}"),
    };
}

/// Type of each of x, y and z in `schema` (used to print coordinates at the field's precision).
pub(crate) fn coord_types(schema: &Schema) -> [ScalarType; 3] {
    schema.xyz.map(|i| schema.fields[i].ty)
}

/// Indices of the fields of `schema` other than x, y and z, in record order.
pub(crate) fn extra_fields(schema: &Schema) -> Vec<usize> {
    (0..schema.fields.len())
        .filter(|i| !schema.xyz.contains(i))
        .collect()
}

/// A packed little-endian `F64` schema for text columns; the first three names must be x, y, z.
pub(crate) fn f64_schema(path: &Path, names: &[String]) -> Result<Schema, IoError> {
    let fields = names
        .iter()
        .enumerate()
        .map(|(i, n)| Field {
            name: n.clone(),
            ty: ScalarType::F64,
            offset: 8 * i,
        })
        .collect();
    Schema::new(fields, 8 * names.len(), Endian::Little)
        .map_err(|e| IoError::header(path, e.to_string()))
}

/// Names `x`, `y`, `z`, then `fallback(i)` for the extra columns 3…n-1.
pub(crate) fn default_names(n: usize, extra: &[&str]) -> Vec<String> {
    let mut names: Vec<String> = ["x", "y", "z"].iter().map(|s| s.to_string()).collect();
    for i in 3..n {
        names.push(match extra.get(i - 3) {
            Some(s) if extra.len() == n - 3 => s.to_string(),
            _ => format!("c{i}"),
        });
    }
    names
}

/// Fills `record` (F64 little endian, `values.len()` fields) and returns the position.
pub(crate) fn encode_f64_record(values: &[f64], record: &mut Vec<u8>) -> DVec3 {
    record.clear();
    for v in values {
        record.extend_from_slice(&v.to_le_bytes());
    }
    DVec3::new(values[0], values[1], values[2])
}

/// Reads a file line by line, counting lines from 1.
pub(crate) struct LineReader {
    path: PathBuf,
    inner: BufReader<Input>,
    buf: Vec<u8>,
    line: u64,
}

impl LineReader {
    pub(crate) fn new(input: Input) -> LineReader {
        LineReader {
            path: input.name().to_path_buf(),
            inner: BufReader::with_capacity(1 << 16, input),
            buf: Vec::new(),
            line: 0,
        }
    }

    /// Reads the next raw line (terminator included); false at the end of the file.
    pub(crate) fn next_line(&mut self) -> Result<bool, IoError> {
        self.buf.clear();
        let n = self
            .inner
            .read_until(b'\n', &mut self.buf)
            .map_err(|e| IoError::io(&self.path, e))?;
        if n == 0 {
            return Ok(false);
        }
        self.line += 1;
        Ok(true)
    }

    /// The current raw line.
    pub(crate) fn raw(&self) -> &[u8] {
        &self.buf
    }

    /// Number of the current line (1-based).
    pub(crate) fn line(&self) -> u64 {
        self.line
    }

    /// Appends the rest of the file to `out`.
    pub(crate) fn read_rest(&mut self, out: &mut Vec<u8>) -> Result<(), IoError> {
        self.inner
            .read_to_end(out)
            .map_err(|e| IoError::io(&self.path, e))?;
        Ok(())
    }
}

/// Writes lines through an [`AtomicFile`]. The terminator of a formatted line is held back until
/// something follows it, so a file whose last line had no terminator can be reproduced.
pub(crate) struct LineSink {
    file: AtomicFile,
    eol: LineEnding,
    pending: bool,
}

impl LineSink {
    pub(crate) fn new(file: AtomicFile, eol: LineEnding) -> LineSink {
        LineSink {
            file,
            eol,
            pending: false,
        }
    }

    pub(crate) fn path(&self) -> &Path {
        self.file.target()
    }

    fn put(&mut self, bytes: &[u8]) -> Result<(), IoError> {
        if self.pending {
            self.pending = false;
            let eol = self.eol.bytes();
            self.file.write_all(eol).map_err(|e| self.file.err(e))?;
        }
        self.file.write_all(bytes).map_err(|e| self.file.err(e))
    }

    /// Writes raw bytes that carry their own terminators (nothing for an empty slice).
    pub(crate) fn raw(&mut self, bytes: &[u8]) -> Result<(), IoError> {
        if bytes.is_empty() {
            return Ok(());
        }
        self.put(bytes)
    }

    /// Writes one line; its terminator follows with the next write or at `finish`.
    pub(crate) fn line(&mut self, content: &[u8]) -> Result<(), IoError> {
        self.put(content)?;
        self.pending = true;
        Ok(())
    }

    /// Appends the lines of a body ([`LineSink::finish_body`]) at `path`; `lines` tells whether it
    /// holds any (whose last terminator then follows with the next write or at `finish`).
    pub(crate) fn append_lines(&mut self, path: &Path, lines: bool) -> Result<(), IoError> {
        if !lines {
            return Ok(());
        }
        self.put(&[])?;
        self.file.append_file(path)?;
        self.pending = true;
        Ok(())
    }

    /// Moves the file into place, its last line unterminated (a body: the terminator is the
    /// writer's it is appended to), without a sync.
    pub(crate) fn finish_body(self) -> Result<(), IoError> {
        self.file.commit_unsynced()
    }

    /// Terminates the last line unless `unterminated`, then moves the file into place.
    pub(crate) fn finish(mut self, unterminated: bool) -> Result<(), IoError> {
        if self.pending && !unterminated {
            let eol = self.eol.bytes();
            self.file.write_all(eol).map_err(|e| self.file.err(e))?;
        }
        self.file.commit()
    }
}

/// Refuses counts a text file of `file_len` bytes cannot hold (when its length is known):
/// `points` lines (`noun` in the message) of at least `values` numbers (one character and a separator each) and `faces`
/// face lines of at least 8 bytes (`3 0 1 2` and its line end). A header that lies about a huge
/// count fails here, naming the file, before anything is sized from it.
///
/// # Errors
/// [`IoError::Truncated`] naming `path`.
pub(crate) fn check_text_count(
    path: &std::path::Path,
    (points, noun): (u64, &str),
    values: u64,
    faces: u64,
    file_len: Option<u64>,
) -> Result<(), IoError> {
    let need = points
        .saturating_mul(2 * values)
        .saturating_add(faces.saturating_mul(8))
        .saturating_sub(1);
    match file_len {
        Some(len) if need > len => Err(IoError::truncated(
            path,
            format!(
                "the header declares {points} {noun}{} (at least {need} bytes as text), but the \
                 file holds {len} bytes",
                if faces > 0 {
                    format!(" and {faces} faces")
                } else {
                    String::new()
                }
            ),
        )),
        _ => Ok(()),
    }
}
