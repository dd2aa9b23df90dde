//! Point Cloud Library PCD backend (`.pcd`): a streaming, lossless reader and writer for the three
//! `DATA` kinds `ascii`, `binary` and `binary_compressed`.
//!
//! # Brief overview
//!
//! ```text
//!  # .PCD v0.7 …  VERSION  FIELDS  SIZE  TYPE  COUNT        PcdMeta (raw lines kept)
//!  WIDTH  HEIGHT  VIEWPOINT  POINTS  DATA <kind>
//!  point data (ascii lines | binary rows | LZF block)       PointBatch records
//!  [trailing bytes, e.g. PCL's zero padding]               PcdTrailer (raw)
//! ```
//!
//! * **Schema.** The record is the `FIELDS` in file order, packed, little-endian, each with the
//!   type of its `SIZE`/`TYPE` pair (`I`/`U` 1, 2, 4, 8 bytes, `F` 4 or 8). A field with
//!   `COUNT` k > 1 becomes k consecutive schema fields `name[0]` … `name[k-1]` (`normal[0]`,
//!   `fpfh[32]`); brackets cannot clash with PCD names, which never contain them in practice, and a
//!   sink regroups such runs into one `COUNT` k field again. x, y and z must be `COUNT` 1 fields
//!   (any type; usually `F` 4). Records pass through byte for byte; only x, y and z are rewritten,
//!   and only when the position differs from the record's (so NaN payloads survive).
//! * **Reading.** `ascii` and `binary` stream: one batch of lines or rows at a time.
//!   `binary_compressed` stores one LZF block of all values of field 1, then field 2, … (column
//!   major), so [`PcdSource::open`] reads the compressed block and decompresses it into memory:
//!   **memory cost = POINTS × record bytes** (the decompressed block; the compressed bytes are
//!   freed after decoding, and the block is freed once the last batch is delivered). The sizes in
//!   the block header are checked against the file length and against LZF's largest possible
//!   expansion before anything is allocated.
//! * **Writing.** [`PcdSink::create`] reproduces a PCD source's header byte for byte (same
//!   `DATA` kind, comments, `VERSION`, `VIEWPOINT`, `WIDTH`/`HEIGHT`). When the point count
//!   differs from the header's, the cloud can no longer be an image: it is written unorganized,
//!   `WIDTH count`, `HEIGHT 1`, `POINTS count`. For any other origin the sink writes a PCL-style
//!   v0.7 header with the schema's fields and `DATA binary` (fields converted to little-endian;
//!   integer x, y, z — LAS's scaled `I32` — become `F 8`, written from the decoded positions, so
//!   coordinates are not rounded to whole units).
//!   `ascii` and `binary` stream. `binary_compressed` needs the whole column-major block before it
//!   can compress it: the sink **buffers count × record bytes** (allocated up front, reported as an
//!   error when it cannot be), and at `finish` compresses it (the compressed copy takes at most
//!   about the same again). Everything goes to a temporary file renamed at `finish` ([`AtomicFile`]),
//!   after the point count has been checked. Faces cannot be stored; a sink ignores
//!   [`Extras::faces`].
//! * **Organized clouds** (`HEIGHT` > 1, e.g. a 640 × 480 stereo image): points keep their order
//!   and invalid points are delivered as NaN. [`SourceInfo::is_organized`] (or
//!   [`PcdMeta::is_organized`]) tells a caller to keep them in place instead of dropping them;
//!   sinks write NaN coordinates as given, so the image layout survives an unchanged count.
//! * **Noise flag.** With [`SinkOptions::noise_flag`] a field `noise` (`SIZE 1`, `TYPE U`,
//!   `COUNT 1`) is appended holding 1 where [`PointBatch::flags`] has [`FLAG_NOISE`], else 0. When
//!   the schema already has a field named `noise` (a re-run), that field is overwritten instead.
//! * **Normals.** With [`SinkOptions::normals`] the fields `normal_x normal_y normal_z curvature`
//!   (`F 4`, PCL's `PointNormal` names) and `structure` (`U 1`) are appended before `noise`; a
//!   field already holding one of them (`normal_x` or `nx`, …) is overwritten instead (see
//!   [the I/O overview](super#normals)).
//! * **Padding.** PCL's padding fields `_` are ordinary fields in `ascii` and `binary` data; in
//!   `binary_compressed` data PCL leaves them out of the block, so they read as zero bytes and are
//!   not written.
//!
//! Reading a file and writing it back unchanged yields a byte-identical file for `binary`, for
//! `ascii` whenever the file prints its numbers like PCL (C's `%.8g`, single spaces; floats that
//! need more digits get the shortest exact text, so ascii output is lossless), and for
//! `binary_compressed` written by this backend. PCL's own LZF encoder (a liblzf variant with a
//! different hash table) produces other, equally valid, compressed bytes than the `lzf` crate, so
//! a PCL-written `binary_compressed` file comes back with an identical header and identical
//! decompressed content, but different compressed bytes.
//!
//! # Why not `pcd-rs`
//!
//! `pcd-rs` 0.13 reads and writes `binary_compressed` with a dynamic schema, but it does not fit
//! the [`Source`]/[`Sink`] contract: its reader yields one `DynRecord` (a `Vec` of per-field
//! `Vec`s) per point instead of raw record bytes, it drops comments and the exact header lines,
//! its writer emits its own header and requires `Write + Seek` (an [`AtomicFile`] is not
//! seekable), it keeps both a column-major and a row-major copy of a compressed block, and it
//! allocates buffers of the sizes a file claims before checking them against the file. Its LZF
//! code is private. So this module parses and writes PCD itself and uses the maintained `lzf`
//! crate (a pure-Rust port of liblzf, compatible with PCL's decoder) for the compression.

mod body;
mod header;

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

pub use header::{PcdData, PcdField};

use self::body::{Columns, parse_value, push_value};
use self::header::{DEFAULT_VIEWPOINT, Header};
use super::lines::{LineEnding, show, tokens};
use super::reader::seek_record;
use super::tally::{Tally, check_batch};
use super::{
    AtomicFile, BodyStats, Extras, Format, Input, IoError, Meta, NormalField, NormalNames, Sink,
    SinkOptions, Source, SourceInfo, Trailer, foreign_field_type,
};
use crate::points::{
    Endian, FLAG_NOISE, Field, PointBatch, Rounding, ScalarType, Schema, stored_toward,
};

/// Read buffer size.
const READ_BUF: usize = 1 << 16;

/// Name of the field a sink appends for [`SinkOptions::noise_flag`] (shared with PLY and text).
pub use super::NOISE_FIELD;

/// PCD header information a sink reproduces: the raw header lines and the field model.
#[derive(Debug, Clone, Default)]
pub struct PcdMeta {
    header: Header,
    /// The `DATA` kind a sink writes (the file's own unless changed with [`PcdMeta::set_data`]).
    data: PcdData,
}

impl PcdMeta {
    /// The `DATA` kind a sink created like this source writes: the file's own, unless changed
    /// with [`PcdMeta::set_data`].
    pub fn data(&self) -> PcdData {
        self.data
    }

    /// The `DATA` kind the file was read from.
    pub fn file_data(&self) -> PcdData {
        self.header.data
    }

    /// Makes sinks created like this source write `data` instead (to convert between kinds);
    /// the rest of the header is kept.
    pub fn set_data(&mut self, data: PcdData) {
        self.data = data;
    }

    /// The `VERSION` value (`None` when the header has no such line).
    pub fn version(&self) -> Option<&str> {
        self.header.version.as_deref()
    }

    /// The fields as declared (before `COUNT` expansion).
    pub fn fields(&self) -> &[PcdField] {
        &self.header.fields
    }

    /// `WIDTH`: points per row of an organized cloud, else the point count.
    pub fn width(&self) -> u64 {
        self.header.width
    }

    /// `HEIGHT`: rows of an organized cloud, 1 for an unorganized one.
    pub fn height(&self) -> u64 {
        self.header.height
    }

    /// `POINTS`.
    pub fn points(&self) -> u64 {
        self.header.points
    }

    /// True when `HEIGHT` > 1: the points form a `WIDTH` × `HEIGHT` image (row by row), and
    /// invalid points are NaN placeholders that must stay in place.
    pub fn is_organized(&self) -> bool {
        self.header.height > 1
    }

    /// `VIEWPOINT`: translation x, y, z and rotation quaternion w, x, y, z.
    pub fn viewpoint(&self) -> [f64; 7] {
        self.header.viewpoint
    }

    /// Text of the comment lines (`# …`).
    pub fn comments(&self) -> Vec<String> {
        self.header.comments()
    }

    /// The header exactly as read (up to and including the `DATA` line).
    pub fn header_bytes(&self) -> Vec<u8> {
        self.header.bytes()
    }
}

/// The bytes of a PCD file after its point data (PCL pads `binary_compressed` files with zeros;
/// ascii files may end in blank lines), reproduced by a sink that writes the same `DATA` kind.
#[derive(Debug, Clone, Default)]
pub struct PcdTrailer {
    data: PcdData,
    tail: Vec<u8>,
    unterminated: bool,
}

impl PcdTrailer {
    /// The `DATA` kind of the file the bytes come from.
    pub fn data(&self) -> PcdData {
        self.data
    }

    /// The bytes after the point data.
    pub fn tail_bytes(&self) -> &[u8] {
        &self.tail
    }

    /// Ascii only: the last point line ends the file without a line terminator.
    pub fn unterminated(&self) -> bool {
        self.unterminated
    }
}

/// The record schema of `fields`: packed, little-endian, `COUNT` expanded to `name[i]`.
///
/// # Errors
/// [`crate::points::PointsError::MissingField`] when x, y or z is not a `COUNT` 1 field.
pub fn schema_of(fields: &[PcdField]) -> Result<Schema, crate::points::PointsError> {
    let mut out = Vec::with_capacity(fields.iter().map(|f| f.count).sum());
    let mut offset = 0;
    for f in fields {
        for i in 0..f.count {
            out.push(Field {
                name: f.element_name(i),
                ty: f.ty,
                offset,
            });
            offset += f.ty.size();
        }
    }
    Schema::new(out, offset, Endian::Little)
}

/// The PCD fields for records of `schema` (another format's layout): one `COUNT` 1 field per
/// schema field, except that runs named `base[0]`, `base[1]`, … of one type become one field
/// `base` with that `COUNT`. Whitespace in names becomes `_`.
pub fn fields_of(schema: &Schema) -> Vec<PcdField> {
    let clean = |s: &str| -> String {
        let t: String = s
            .chars()
            .map(|c| {
                if c.is_whitespace() || c.is_control() {
                    '_'
                } else {
                    c
                }
            })
            .collect();
        if t.is_empty() { "unnamed".into() } else { t }
    };
    let f = &schema.fields;
    let mut out = Vec::with_capacity(f.len());
    let mut i = 0;
    while i < f.len() {
        let name = clean(&f[i].name);
        if let Some(base) = name.strip_suffix("[0]").filter(|b| !b.is_empty()) {
            let mut k = 1;
            while i + k < f.len()
                && f[i + k].ty == f[i].ty
                && clean(&f[i + k].name) == format!("{base}[{k}]")
            {
                k += 1;
            }
            if k > 1 {
                out.push(PcdField::new(base, f[i].ty, k));
                i += k;
                continue;
            }
        }
        out.push(PcdField::new(name, f[i].ty, 1));
        i += 1;
    }
    out
}

/// `schema` with the types a PCD header gets for another format's records: integer x, y and z
/// become `F64` (see [`foreign_field_type`]). Only names and types are meaningful in the result
/// (offsets are not recomputed); it feeds [`fields_of`].
fn promoted(schema: &Schema) -> Schema {
    let mut s = schema.clone();
    for i in schema.xyz {
        s.fields[i].ty = foreign_field_type(schema, i);
    }
    s
}

// ---------------------------------------------------------------------------------------------
// Reader.

/// Streaming PCD reader (`ascii`, `binary`, `binary_compressed`).
pub struct PcdSource {
    info: SourceInfo,
    reader: BufReader<Input>,
    kind: PcdData,
    total: u64,
    read: u64,
    /// Ascii: number of the last line read (1-based, header lines included).
    line: u64,
    /// Ascii: longest point line accepted.
    max_line: u64,
    /// Ascii: the last point line had no terminator.
    unterminated: bool,
    text: Vec<u8>,
    /// Compressed: the decompressed column-major block and its layout.
    block: Vec<u8>,
    columns: Option<Columns>,
    /// Binary: where the point records start, when the input can seek.
    data_start: Option<u64>,
}

impl PcdSource {
    /// Opens `path` and reads its header; for `binary_compressed`, also reads and decompresses
    /// the point block (see the module overview for the memory cost).
    ///
    /// # Errors
    /// [`IoError::Invalid`] for an empty file or a corrupt LZF block, [`IoError::Header`] for a
    /// file that is not PCD, a malformed header or one without x, y or z,
    /// [`IoError::Truncated`] when the file is shorter than the points its header announces.
    pub fn open(path: &Path) -> Result<PcdSource, IoError> {
        PcdSource::new(Input::from_path(path)?)
    }

    /// [`PcdSource::open`] on any [`Input`].
    ///
    /// # Errors
    /// As [`PcdSource::open`].
    pub fn new(input: Input) -> Result<PcdSource, IoError> {
        let owned = input.name().to_path_buf();
        let path = owned.as_path();
        let file_len = input.len();
        let mut reader = BufReader::with_capacity(READ_BUF, input);
        let header = header::read_header(&mut reader, path)?;
        for axis in ["x", "y", "z"] {
            if !header.fields.iter().any(|f| f.name == axis && f.count == 1) {
                let have: Vec<&str> = header.fields.iter().map(|f| f.name.as_str()).collect();
                return Err(IoError::header(
                    path,
                    format!(
                        "no field `{axis}` of COUNT 1 (FIELDS: {}); a point cloud needs x, y and z",
                        have.join(" ")
                    ),
                ));
            }
        }
        let schema = schema_of(&header.fields).map_err(|e| IoError::header(path, e.to_string()))?;
        let rl = schema.record_len as u64;
        let points = header.points;
        let kind = header.data;
        let avail = file_len.map(|len| len.saturating_sub(header.byte_len()));
        let mut block = Vec::new();
        let mut columns = None;
        match kind {
            PcdData::Binary => {
                // An ascii body under `DATA binary` read as records is a garbage cloud (issue 51).
                let head = reader.fill_buf().map_err(|e| IoError::io(path, e))?;
                if looks_like_ascii_rows(head) {
                    return Err(IoError::header(
                        path,
                        "DATA binary, but the point data is text (ascii rows); the header should \
                         say DATA ascii",
                    ));
                }
                let need = points.saturating_mul(rl);
                if let Some(avail) = avail
                    && need > avail
                {
                    return Err(IoError::truncated(
                        path,
                        format!(
                            "header announces {points} points ({need} bytes) but only {avail} \
                             bytes of point data follow"
                        ),
                    ));
                }
            }
            PcdData::Ascii => {
                // Every value takes at least one character and one separator.
                let values = schema.fields.len() as u64;
                let need = points.saturating_mul(2 * values).saturating_sub(1);
                if let Some(avail) = avail
                    && need > avail
                {
                    return Err(IoError::truncated(
                        path,
                        format!(
                            "header announces {points} points (at least {need} bytes as ascii) \
                             but only {avail} bytes follow the header"
                        ),
                    ));
                }
            }
            PcdData::BinaryCompressed => {
                let layout = Columns::new(&header.fields, points).ok_or_else(|| {
                    IoError::header(path, format!("{points} points do not fit in memory"))
                })?;
                block = read_block(&mut reader, path, &layout, points, avail)?;
                columns = Some(layout);
            }
        }
        let line = header.lines.len() as u64;
        let max_line = (schema.fields.len() as u64 * 64).max(1 << 20);
        let info = SourceInfo {
            path: path.to_path_buf(),
            format: Format::Pcd,
            schema,
            len: Some(points),
            faces: None,
            meta: Meta::Pcd(PcdMeta { header, data: kind }),
        };
        let data_start = match kind {
            PcdData::Binary => std::io::Seek::stream_position(&mut reader).ok(),
            PcdData::Ascii | PcdData::BinaryCompressed => None,
        };
        Ok(PcdSource {
            info,
            reader,
            kind,
            total: points,
            read: 0,
            line,
            max_line,
            unterminated: false,
            text: Vec::new(),
            block,
            columns,
            data_start,
        })
    }

    /// Reads `n` ascii point lines into `records` (zeroed, `n` records).
    fn read_ascii(&mut self, records: &mut [u8], n: usize) -> Result<(), IoError> {
        let path = &self.info.path;
        let schema = &self.info.schema;
        let rl = schema.record_len;
        for (k, rec) in records.chunks_exact_mut(rl).take(n).enumerate() {
            loop {
                self.text.clear();
                let got = self
                    .reader
                    .by_ref()
                    .take(self.max_line)
                    .read_until(b'\n', &mut self.text)
                    .map_err(|e| IoError::io(path, e))?;
                if got == 0 {
                    return Err(IoError::truncated(
                        path,
                        format!(
                            "header announces {} points but the data ends after {}",
                            self.total,
                            self.read + k as u64
                        ),
                    ));
                }
                self.line += 1;
                if got as u64 == self.max_line && self.text.last() != Some(&b'\n') {
                    return Err(IoError::invalid(
                        path,
                        format!("line {}: longer than {} bytes", self.line, self.max_line),
                    ));
                }
                if !self.text.trim_ascii().is_empty() {
                    break;
                }
            }
            self.unterminated = self.text.last() != Some(&b'\n');
            let line = self.line;
            let mut toks = tokens(&self.text);
            let count_err = |text: &[u8]| {
                IoError::invalid(
                    path,
                    format!(
                        "line {line}: {} values, expected {} (one per field element)",
                        tokens(text).count(),
                        schema.fields.len()
                    ),
                )
            };
            for f in &schema.fields {
                let tok = toks.next().ok_or_else(|| count_err(&self.text))?;
                let dst = &mut rec[f.offset..f.offset + f.ty.size()];
                if !parse_value(tok, f.ty, dst) {
                    return Err(IoError::invalid(
                        path,
                        format!(
                            "line {line}: bad number `{}` for field `{}` ({:?})",
                            show(tok),
                            f.name,
                            f.ty
                        ),
                    ));
                }
            }
            if toks.next().is_some() {
                return Err(count_err(&self.text));
            }
        }
        Ok(())
    }
}

/// Reads the `binary_compressed` size header and LZF block that follow the header, checks them
/// against the layout and the file length, and decompresses the block.
fn read_block(
    reader: &mut BufReader<Input>,
    path: &Path,
    layout: &Columns,
    points: u64,
    avail: Option<u64>,
) -> Result<Vec<u8>, IoError> {
    let mut sizes = Vec::with_capacity(8);
    reader
        .by_ref()
        .take(8)
        .read_to_end(&mut sizes)
        .map_err(|e| IoError::io(path, e))?;
    if sizes.is_empty() && points == 0 {
        return Ok(Vec::new());
    }
    let word = |i: usize| sizes.get(i..i + 4).and_then(|b| b.try_into().ok());
    let (Some(c), Some(u)) = (word(0), word(4)) else {
        return Err(IoError::truncated(
            path,
            "the binary_compressed data ends inside its 8-byte size header",
        ));
    };
    let (c, u) = (u32::from_le_bytes(c) as u64, u32::from_le_bytes(u) as u64);
    let expected = layout.block_len() as u64;
    if u != expected {
        return Err(IoError::invalid(
            path,
            format!(
                "header announces {points} points ({expected} bytes uncompressed) but the \
                 binary_compressed block holds {u} bytes"
            ),
        ));
    }
    if let Some(rest) = avail.map(|a| a.saturating_sub(8))
        && c > rest
    {
        return Err(IoError::truncated(
            path,
            format!("the LZF block has {c} bytes but only {rest} bytes follow"),
        ));
    }
    if !body::plausible_sizes(c, u) {
        return Err(IoError::invalid(
            path,
            format!("corrupt binary_compressed block: {c} LZF bytes cannot decode to {u} bytes"),
        ));
    }
    let mut packed = Vec::new();
    reader
        .by_ref()
        .take(c)
        .read_to_end(&mut packed)
        .map_err(|e| IoError::io(path, e))?;
    if (packed.len() as u64) < c {
        return Err(IoError::truncated(
            path,
            format!(
                "the LZF block has {c} bytes but only {} follow",
                packed.len()
            ),
        ));
    }
    body::decompress(&packed, u as usize)
        .map_err(|e| IoError::invalid(path, format!("corrupt binary_compressed (LZF) block: {e}")))
}

impl Source for PcdSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn seek_point(&mut self, index: u64) -> Result<bool, IoError> {
        let Some(start) = self.data_start.filter(|_| index <= self.total) else {
            return Ok(false);
        };
        let records = (start, self.info.schema.record_len);
        seek_record(&mut self.reader, &self.info.path, records, index)?;
        self.read = index;
        Ok(true)
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        batch.clear(self.read);
        let rl = self.info.schema.record_len;
        batch.record_len = rl;
        let n = (self.total - self.read).min(max as u64) as usize;
        if n == 0 {
            return Ok(0);
        }
        batch.records.resize(n * rl, 0);
        match self.kind {
            PcdData::Binary => {
                self.reader
                    .read_exact(&mut batch.records)
                    .map_err(|e| match e.kind() {
                        std::io::ErrorKind::UnexpectedEof => IoError::truncated(
                            &self.info.path,
                            format!(
                                "header announces {} points but the data ends within point {}",
                                self.total,
                                self.read + 1
                            ),
                        ),
                        _ => IoError::io(&self.info.path, e),
                    })?
            }
            PcdData::Ascii => self.read_ascii(&mut batch.records, n)?,
            PcdData::BinaryCompressed => {
                if let Some(c) = &self.columns {
                    c.gather(&self.block, self.read as usize, rl, &mut batch.records);
                }
            }
        }
        let schema = &self.info.schema;
        batch
            .positions
            .extend(batch.records.chunks_exact(rl).map(|r| schema.position(r)));
        self.read += n as u64;
        if self.read == self.total {
            // The decompressed block is no longer needed.
            self.block = Vec::new();
        }
        Ok(n)
    }

    fn finish(mut self: Box<Self>) -> Result<Extras, IoError> {
        // Points not read yet are skipped (and checked) so the trailer starts after them.
        let mut scratch = PointBatch::default();
        while self.read_batch(&mut scratch, 1 << 12)? > 0 {}
        let mut tail = Vec::new();
        self.reader
            .read_to_end(&mut tail)
            .map_err(|e| IoError::io(&self.info.path, e))?;
        // What follows the points of an ascii body may be blank lines and comments; a row is a
        // point the header does not count (issue 51: it was kept aside, never denoised).
        if self.kind == PcdData::Ascii
            && let Some(row) = tail
                .split(|&b| b == b'\n')
                .map(|l| l.trim_ascii())
                .find(|l| !l.is_empty() && !l.starts_with(b"#"))
        {
            let row = String::from_utf8_lossy(&row[..row.len().min(60)]).into_owned();
            return Err(IoError::header(
                &self.info.path,
                format!(
                    "POINTS says {}, but more rows follow (`{row}`); fix POINTS (and WIDTH)",
                    self.total
                ),
            ));
        }
        Ok(Extras {
            faces: None,
            trailer: Trailer::Pcd(PcdTrailer {
                data: self.kind,
                tail,
                unterminated: self.kind == PcdData::Ascii && self.unterminated,
            }),
        })
    }
}

/// True when `head`, the start of a body announced as binary, reads as ascii PCD rows: at least
/// 32 bytes, all of them digits, signs, dots, exponents, spaces and line ends, with a space and a
/// line end among them (records of floats are never all of that).
fn looks_like_ascii_rows(head: &[u8]) -> bool {
    head.len() >= 32
        && head.contains(&b'\n')
        && head.contains(&b' ')
        && head.iter().all(|&b| {
            b.is_ascii_digit()
                || matches!(
                    b,
                    b' ' | b'\t' | b'\r' | b'\n' | b'.' | b'-' | b'+' | b'e' | b'E'
                )
        })
}

// ---------------------------------------------------------------------------------------------
// Writer.

/// One field copied from a foreign record into a PCD row.
#[derive(Debug, Clone, Copy)]
struct FieldCopy {
    src: usize,
    dst: usize,
    len: usize,
    /// The source is big-endian: reverse the bytes.
    swap: bool,
}

/// How a sink turns incoming records into PCD rows.
enum Conv {
    /// The incoming record is already a PCD row (prefix of the output row).
    Same,
    /// Field by field, converted to little-endian.
    Fields(Vec<FieldCopy>),
}

/// Streaming PCD writer.
pub struct PcdSink {
    out: AtomicFile,
    like: Schema,
    /// Layout of the rows written (little-endian, packed; the noise field included).
    schema: Schema,
    conv: Conv,
    /// x, y, z whose output type differs from the incoming one (integers written as `F64`).
    promoted: [bool; 3],
    /// How moved coordinates round to what the output stores ([`SinkOptions::rounding`]).
    rounding: Rounding,
    /// Output field receiving the noise flag.
    noise: Option<usize>,
    /// Output fields receiving the written normals ([`SinkOptions::normals`]).
    normals: Vec<(usize, NormalField)>,
    kind: PcdData,
    tally: Tally,
    rows: Vec<u8>,
    text: Vec<u8>,
    eol: LineEnding,
    pending_eol: bool,
    /// `binary_compressed`: the column-major block being filled, and its layout.
    block: Vec<u8>,
    columns: Option<Columns>,
    /// The `DATA` kind of the PCD source whose header is reproduced (its trailer is written
    /// back when it has this kind).
    reproduce: Option<PcdData>,
}

impl PcdSink {
    /// Creates a sink that writes `count` points laid out like `like` (see the module overview
    /// for the header rules and the memory used by `binary_compressed`).
    ///
    /// # Errors
    /// The directory is not writable; a `binary_compressed` block that exceeds the format's
    /// 4 GiB limit or cannot be allocated.
    pub fn create(
        path: &Path,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<PcdSink, IoError> {
        PcdSink::new(AtomicFile::create(path)?, like, count, options)
    }

    /// [`PcdSink::create`] writing to `out` (a file, a stream or memory).
    ///
    /// # Errors
    /// As [`PcdSink::create`].
    pub fn new(
        mut out: AtomicFile,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<PcdSink, IoError> {
        let shown = out.target().to_path_buf();
        let path = shown.as_path();
        let (header, kind, reproduce) = match &like.meta {
            Meta::Pcd(m) if schema_of(&m.header.fields).is_ok_and(|s| s == like.schema) => {
                (m.header.clone(), m.data, Some(m.header.data))
            }
            Meta::Pcd(m) => (
                Header::generated(&fields_of(&like.schema), count, m.data, m.viewpoint()),
                m.data,
                None,
            ),
            _ => (
                Header::generated(
                    &fields_of(&promoted(&like.schema)),
                    count,
                    PcdData::Binary,
                    DEFAULT_VIEWPOINT,
                ),
                PcdData::Binary,
                None,
            ),
        };
        let mut fields = header.fields.clone();
        // Fields appended after the incoming ones: the normals, then the noise flag. A value the
        // schema already holds is written into its field (output field i is incoming field i).
        let mut append = Vec::new();
        let mut slot = |name: &str, ty: ScalarType, existing: Option<usize>| match existing {
            Some(i) => i,
            None => {
                let f = PcdField::new(name, ty, 1);
                fields.push(f.clone());
                append.push(f);
                like.schema.fields.len() + append.len() - 1
            }
        };
        let normals: Vec<(usize, NormalField)> = if options.normals {
            NormalField::ALL
                .iter()
                .map(|&f| {
                    let i = slot(f.name(NormalNames::Pcd), f.ty(), f.find(&like.schema));
                    (i, f)
                })
                .collect()
        } else {
            Vec::new()
        };
        let noise = options.noise_flag.then(|| {
            slot(
                NOISE_FIELD,
                ScalarType::U8,
                like.schema.field_index(NOISE_FIELD),
            )
        });
        // The output layout: the incoming fields, packed little-endian, then the noise field.
        let mut out_fields = Vec::with_capacity(like.schema.fields.len() + 1);
        let mut offset = 0;
        for f in fields.iter() {
            for i in 0..f.count {
                out_fields.push(Field {
                    name: f.element_name(i),
                    ty: f.ty,
                    offset,
                });
                offset += f.ty.size();
            }
        }
        let schema = Schema {
            fields: out_fields,
            record_len: offset,
            endian: Endian::Little,
            xyz: like.schema.xyz,
        };
        let same = like.schema.endian == Endian::Little
            && like.schema.fields.len() <= schema.fields.len()
            && like.schema.record_len <= schema.record_len
            && like
                .schema
                .fields
                .iter()
                .zip(&schema.fields)
                .all(|(a, b)| a.ty == b.ty && a.offset == b.offset)
            && like
                .schema
                .fields
                .iter()
                .map(|f| f.ty.size())
                .sum::<usize>()
                == like.schema.record_len;
        // x, y, z promoted to `F64` are not copied but always written from the positions.
        let promoted = like
            .schema
            .xyz
            .map(|i| like.schema.fields[i].ty != schema.fields[i].ty);
        let conv = if same {
            Conv::Same
        } else {
            Conv::Fields(
                like.schema
                    .fields
                    .iter()
                    .zip(&schema.fields)
                    .filter(|(a, b)| a.ty == b.ty)
                    .map(|(a, b)| FieldCopy {
                        src: a.offset,
                        dst: b.offset,
                        len: a.ty.size(),
                        swap: like.schema.endian == Endian::Big && a.ty.size() > 1,
                    })
                    .collect(),
            )
        };

        let (block, columns) = if kind == PcdData::BinaryCompressed {
            let unsupported = |detail: String| IoError::Unsupported {
                path: path.to_path_buf(),
                detail,
            };
            let layout = Columns::new(&fields, count)
                .ok_or_else(|| unsupported(format!("{count} points do not fit in memory")))?;
            let len = layout.block_len();
            if u32::try_from(len).is_err() {
                return Err(unsupported(format!(
                    "binary_compressed data of {len} bytes exceeds the format's 4 GiB limit"
                )));
            }
            let mut block = Vec::new();
            block.try_reserve_exact(len).map_err(|_| {
                IoError::io(
                    path,
                    std::io::Error::new(
                        std::io::ErrorKind::OutOfMemory,
                        format!("cannot buffer {len} bytes of binary_compressed data"),
                    ),
                )
            })?;
            block.resize(len, 0);
            (block, Some(layout))
        } else {
            (Vec::new(), None)
        };

        // A body holds the point data alone.
        if !options.body {
            out.write_all(&header.render(count, kind, &append))
                .map_err(|e| out.err(e))?;
        }
        Ok(PcdSink {
            out,
            like: like.schema.clone(),
            schema,
            conv,
            promoted,
            rounding: options.rounding,
            noise,
            normals,
            kind,
            tally: Tally::new(count),
            rows: Vec::new(),
            text: Vec::new(),
            eol: header.eol(),
            pending_eol: false,
            block,
            columns,
            reproduce,
        })
    }

    /// Converts the records of `batch` into PCD rows in `self.rows`.
    fn convert(&mut self, batch: &PointBatch) {
        let ol = self.schema.record_len;
        self.rows.clear();
        self.rows.resize(batch.len() * ol, 0);
        for (i, row) in self.rows.chunks_exact_mut(ol.max(1)).enumerate() {
            let src = batch.record(i);
            match &self.conv {
                Conv::Same => row[..src.len()].copy_from_slice(src),
                Conv::Fields(copies) => {
                    for c in copies {
                        let dst = &mut row[c.dst..c.dst + c.len];
                        dst.copy_from_slice(&src[c.src..c.src + c.len]);
                        if c.swap {
                            dst.reverse();
                        }
                    }
                }
            }
            let old = self.like.position(src).to_array();
            let new = batch.positions[i].to_array();
            let tys = self.schema.xyz.map(|f| self.schema.fields[f].ty);
            let stored = self.rounding.store(new, old, [1.0; 3], |a, v, towards| {
                stored_toward(v, towards, tys[a])
            });
            for axis in 0..3 {
                if new[axis].to_bits() != old[axis].to_bits() || self.promoted[axis] {
                    self.schema
                        .set_f64(row, self.schema.xyz[axis], stored[axis]);
                }
            }
            if let Some(k) = self.noise {
                let flag = f64::from(u8::from(batch.flag(i) & FLAG_NOISE != 0));
                self.schema.set_f64(row, k, flag);
            }
            if !self.normals.is_empty() {
                let n = batch.normal(i);
                for &(k, f) in &self.normals {
                    self.schema.set_f64(row, k, f.value(&n));
                }
            }
        }
    }
}

impl Sink for PcdSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        check_batch(self.out.target(), &self.like, batch)?;
        let first = self.tally.written() as usize;
        self.tally.add(self.out.target(), batch.len())?;
        self.convert(batch);
        let ol = self.schema.record_len;
        match self.kind {
            PcdData::Binary => self.out.write_all(&self.rows).map_err(|e| self.out.err(e)),
            PcdData::Ascii => {
                self.text.clear();
                for row in self.rows.chunks_exact(ol.max(1)).take(batch.len()) {
                    if self.pending_eol {
                        self.text.extend_from_slice(self.eol.bytes());
                    }
                    for (k, f) in self.schema.fields.iter().enumerate() {
                        if k > 0 {
                            self.text.push(b' ');
                        }
                        push_value(&mut self.text, f.ty, &row[f.offset..f.offset + f.ty.size()]);
                    }
                    self.pending_eol = true;
                }
                self.out.write_all(&self.text).map_err(|e| self.out.err(e))
            }
            PcdData::BinaryCompressed => {
                if let Some(c) = &self.columns {
                    c.scatter(&self.rows, first, ol, &mut self.block);
                }
                Ok(())
            }
        }
    }

    fn finish(mut self: Box<Self>, extras: &Extras) -> Result<(), IoError> {
        self.tally.check(self.out.target())?;
        let trailer = match (&extras.trailer, self.reproduce) {
            (Trailer::Pcd(t), Some(kind)) if t.data == kind && kind == self.kind => Some(t),
            _ => None,
        };
        match self.kind {
            PcdData::Binary => {}
            PcdData::Ascii => {
                if self.pending_eol && !trailer.is_some_and(|t| t.unterminated) {
                    let eol = self.eol.bytes();
                    self.out.write_all(eol).map_err(|e| self.out.err(e))?;
                }
            }
            PcdData::BinaryCompressed => {
                let packed = body::compress(&self.block);
                let (Ok(c), Ok(u)) = (u32::try_from(packed.len()), u32::try_from(self.block.len()))
                else {
                    return Err(IoError::Unsupported {
                        path: self.out.target().to_path_buf(),
                        detail: "the compressed block exceeds the format's 4 GiB limit".into(),
                    });
                };
                let mut sizes = [0u8; 8];
                sizes[..4].copy_from_slice(&c.to_le_bytes());
                sizes[4..].copy_from_slice(&u.to_le_bytes());
                self.out.write_all(&sizes).map_err(|e| self.out.err(e))?;
                self.out.write_all(&packed).map_err(|e| self.out.err(e))?;
            }
        }
        if let Some(t) = trailer {
            self.out.write_all(&t.tail).map_err(|e| self.out.err(e))?;
        }
        self.out.commit()
    }

    /// `binary_compressed` compresses every point in one block: it cannot take bodies.
    fn splittable(&self) -> bool {
        self.kind != PcdData::BinaryCompressed
    }

    fn finish_body(self: Box<Self>) -> Result<BodyStats, IoError> {
        let points = self.tally.written();
        self.out.commit_unsynced()?;
        Ok(BodyStats::count(points))
    }

    fn append_body(&mut self, path: &Path, stats: &BodyStats) -> Result<(), IoError> {
        if !self.splittable() {
            return Err(IoError::Unsupported {
                path: self.out.target().to_path_buf(),
                detail: "binary_compressed PCD data cannot be written in separate bodies".into(),
            });
        }
        self.tally.add_body(self.out.target(), stats)?;
        if stats.points == 0 {
            return Ok(());
        }
        // Ascii rows are separated, not terminated: a body's first row needs the separator.
        if self.kind == PcdData::Ascii && self.pending_eol {
            let eol = self.eol.bytes();
            self.out.write_all(eol).map_err(|e| self.out.err(e))?;
        }
        self.out.append_file(path)?;
        self.pending_eol = true;
        Ok(())
    }
}

#[cfg(test)]
mod io_pcd {
    use super::*;

    #[test]
    fn count_fields_expand_and_regroup() {
        let fields = [
            PcdField::new("x", ScalarType::F32, 1),
            PcdField::new("y", ScalarType::F32, 1),
            PcdField::new("z", ScalarType::F32, 1),
            PcdField::new("fpfh", ScalarType::F32, 3),
            PcdField::new("label", ScalarType::U16, 1),
        ];
        let s = schema_of(&fields).unwrap();
        let names: Vec<&str> = s.fields.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(
            names,
            ["x", "y", "z", "fpfh[0]", "fpfh[1]", "fpfh[2]", "label"]
        );
        assert_eq!(s.record_len, 26);
        assert_eq!(s.fields[6].offset, 24);
        assert_eq!(fields_of(&s), fields);

        // A lone `a[0]`, a run broken by a type change, and a name with a space.
        let s = Schema::packed(
            &[
                ("x", ScalarType::F64),
                ("y", ScalarType::F64),
                ("z", ScalarType::F64),
                ("a[0]", ScalarType::U8),
                ("n[0]", ScalarType::F32),
                ("n[1]", ScalarType::F64),
                ("my field", ScalarType::I32),
            ],
            Endian::Big,
        )
        .unwrap();
        let got: Vec<(String, usize)> = fields_of(&s)
            .into_iter()
            .map(|f| (f.name, f.count))
            .collect();
        let want = [
            ("x", 1),
            ("y", 1),
            ("z", 1),
            ("a[0]", 1),
            ("n[0]", 1),
            ("n[1]", 1),
        ];
        assert_eq!(&got[..6], want.map(|(n, c)| (n.to_string(), c)));
        assert_eq!(got[6], ("my_field".to_string(), 1));
    }

    #[test]
    fn xyz_must_be_single_fields() {
        let fields = [
            PcdField::new("x", ScalarType::F32, 3),
            PcdField::new("y", ScalarType::F32, 1),
            PcdField::new("z", ScalarType::F32, 1),
        ];
        assert!(schema_of(&fields).is_err());
    }
}
