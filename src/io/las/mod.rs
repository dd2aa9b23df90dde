//! ASPRS LAS backend (LAS 1.0–1.4, point data record formats 0–10), LASzip-compressed LAZ and
//! COPC input: a streaming, lossless reader and writer.
//!
//! # Brief overview
//!
//! ```text
//!  public header block (header size bytes)     LasMeta: raw bytes, patched on write
//!  VLRs + bytes up to the point data           LasMeta: raw records + padding, verbatim
//!  point records  (LAS: raw, LAZ: chunks)      PointBatch records, raw (decompressed) bytes
//!  [LAZ chunk table]                           rebuilt by the compressor
//!  [bytes, EVLRs, bytes] up to the end         LasTrailer: raw pieces, verbatim
//! ```
//!
//! * [`LasSource::open`] validates the header, the VLRs, the EVLRs and the size of the point data
//!   before the first point is read, so a truncated file, a header that claims more points than the
//!   file holds, a file that is not LAS and bad LAZ framing fail at once with a one-line
//!   [`IoError`] naming the file. The header is parsed with `las::raw::Header`; LAZ point data is
//!   decompressed with the `laz` crate (the engine of `las`) one batch at a time, so neither
//!   direction ever holds the whole file. For LAZ the point count is checked against the chunk
//!   table: exactly for variable-size chunks (COPC), to within the last chunk for fixed-size ones
//!   (a smaller excess is caught only if the compressed data runs out, as in LASzip itself). The
//!   LAZ codec runs under `catch_unwind` with the panic hook silenced: corrupt data that makes it
//!   panic is reported as a one-line error, with no panic message or backtrace on stderr. Framing the
//!   codec trusts is checked before it decodes (see `chunks`): layer sizes that do not fit in their
//!   chunk (they would size its buffers) and a compressor type that disagrees with the items.
//! * Positions are decoded in f64 with the file's own scale and offset: `x = X·scale + offset`.
//! * [`LasSink`] writes the points of a batch as raw records: every byte of a record travels through
//!   unchanged except X, Y and Z, which are quantised with the *file's* scale and offset,
//!   `X = round((x − offset)/scale)` (computed in f64; a coordinate that falls outside the 32-bit
//!   range, or is not finite, is an error). A position whose bits equal the decoded value of the
//!   record's X keeps X as it was, so an unchanged point is byte-identical whatever the scale.
//!   (This backend does not use `Schema::set_position`: it would store metres, not scaled
//!   integers.)
//!
//! # The record schema
//!
//! [`SourceInfo::schema`] describes the raw little-endian record. `x`, `y`, `z` are the *scaled
//! integers* X, Y, Z (`I32`); decoded positions come only in [`PointBatch::positions`]. Bit fields
//! keep their byte: PDRF 0–5 have `return_flags` (return number bits 0–2, number of returns 3–5,
//! scan direction 6, edge of flight line 7) and `classification` (class bits 0–4, synthetic 5,
//! key-point 6, withheld 7); PDRF 6–10 have `return_numbers` (return number bits 0–3, number of
//! returns 4–7), `classification_flags` (flags 0–3, scanner channel 4–5, scan direction 6, edge 7)
//! and a whole `classification` byte. Then `intensity`, `scan_angle_rank` (i8) or `scan_angle`
//! (i16), `user_data`, `point_source_id`, `gps_time`, `red`/`green`/`blue`, `nir` and the
//! waveform fields (`wave_packet_index`, `wave_offset`, `wave_size`, `wave_return_location`,
//! `wave_xt`/`yt`/`zt`) as the format has them. Extra bytes are named from the Extra Bytes VLR;
//! bytes it does not describe are `extra_<k>` (`u8`).
//!
//! # Writing like a LAS source
//!
//! When the output is LAS/LAZ and the source was too ([`Meta::Las`]), the output keeps the public
//! header byte for byte (version, point format, record length, scale, offset, system identifier,
//! generating software, dates, GUID, global encoding, header padding, …), every VLR and EVLR in
//! order and the bytes between them. Recomputed from what was written are only:
//!
//! * the point counts: legacy count and legacy per-return counts (returns 1–5) — filled when the
//!   source filled them (LAS < 1.4, or a non-zero legacy count) and the count fits 32 bits, zero
//!   otherwise — and the LAS 1.4 64-bit count and 15 per-return counts;
//! * the bounds, from the quantised coordinates;
//! * the offsets that follow the point data: start of the first EVLR, number of EVLRs, start of the
//!   waveform data packet record (it keeps pointing at the same EVLR);
//! * when compression changes (`.las` ↔ `.laz`): the compression bits (7 and 6) of the point
//!   format byte, the laszip VLR (added last, or removed), the VLR count and the offset to the
//!   point data.
//!
//! LAZ output reuses the source's laszip VLR unchanged when `laz` can compress with it (otherwise a
//! new one for the point format replaces it). `.laz` in the output path means compressed output,
//! `.las` uncompressed; any other extension follows the source (uncompressed without one).
//!
//! **COPC** (`*.copc.laz`) is read as the LAZ file it is: all points in file order (node by node).
//! An output path ending in `.copc.laz` is written as COPC 1.0 by [`CopcSink`] (octree rebuilt
//! from the written points; see its module). Any other output is plain LAZ or LAS, not COPC,
//! since moved points no longer match the octree and the chunk offsets change: the COPC info VLR
//! (`copc`/1) and the hierarchy EVLR (`copc`/1000) are dropped and the laszip VLR's variable chunk
//! size becomes fixed [`LAZ_CHUNK_SIZE`]-point chunks (only its chunk-size field changes). Every
//! other VLR and EVLR, the `copc`/10000 extents included, is kept verbatim; so is the rest of the
//! header (the VLR count and offset to the point data follow the dropped VLR).
//!
//! # Writing anything else as LAS
//!
//! A source of another format ([`Meta::None`], PLY, …) is written as **LAS 1.4, PDRF 6** (7 with
//! RGB, 8 with NIR), global encoding 0x10 (WKT; no CRS is known), system identifier `OTHER`,
//! generating software `qemd`, today's date, legacy counts zero. Fields of well-known names
//! (`intensity`, `classification`, `gps_time`, `red`/`green`/`blue`, …) whose type the LAS
//! dimension holds exactly become that dimension (table in `foreign`); every other non-xyz field
//! becomes an extra byte field of the same type, described by an Extra Bytes VLR, so nothing is
//! lost, under its own name unless a dimension or an earlier field has it (then `extra_<name>`):
//! no name occurs twice (issue 15).
//!
//! The sink only sees positions batch by batch, so the frame is chosen from the **first batch**:
//! with `E` the largest extent along an axis, the scale (common to x, y, z) is the power of ten
//! `10^(ceil(log10 E) − 6)` capped at 0.001 and floored at 1e-9 (0.001 when `E` is 0): 10⁵–10⁶
//! steps across the first batch, 1 mm for extents above a kilometre. Each offset is the axis
//! minimum rounded down to a multiple of `unit = scale·10⁶` (a power of ten ≥ `E`), so UTM
//! coordinates get offsets like 500 000 and keep full precision. Points up to 2147 units from the
//! offset fit (at least 2147 first-batch extents, or 2147 km under the 1 mm cap); a point beyond
//! is a write error.
//!
//! # Noise flag
//!
//! With [`SinkOptions::noise_flag`], points with [`FLAG_NOISE`] set get classification 7 (PDRF
//! 0–5: the low 5 bits of the classification byte, keeping the synthetic/key-point/withheld bits;
//! PDRF 6–10: the classification byte); other points keep theirs.
//!
//! # Normals
//!
//! With [`SinkOptions::normals`] every record carries the written normal, surface variation and
//! class as extra bytes `NormalX`, `NormalY`, `NormalZ`, `Curvature` (`float`, data type 9; the
//! names PDAL's `filters.normal` gives its dimensions) and `Structure` (`unsigned char`, 1):
//!
//! * an extra-bytes field that already holds one of them (by name: `NormalX`, `nx`, `normal_x`,
//!   …) is written in place, in its type, through its descriptor's scale and offset when it has
//!   them (a normal stored as a scaled `short`, say);
//! * the others are appended to the record: their descriptors go at the end of the Extra Bytes
//!   VLR (LASF_Spec, record 4; added when the file has none), after a `data_type 0` descriptor
//!   for any extra bytes the VLR did not describe, so each descriptor still names its bytes; the
//!   record length in the header grows, and LAZ output gets a LASzip VLR built for the new
//!   length instead of the source's;
//! * a foreign source's fields become extra bytes as above, and the five follow them.
//!
//! COPC output goes through the same sink, so it carries the same extra bytes.
//!
//! The sink writes through an [`AtomicFile`] (temporary file, renamed at [`Sink::finish`] after
//! the announced count is checked): nothing is left behind on error.
//!
//! [`SourceInfo::schema`]: crate::io::SourceInfo::schema
//! [`PointBatch::positions`]: crate::points::PointBatch::positions
//! [`Meta::Las`]: crate::io::Meta::Las
//! [`Meta::None`]: crate::io::Meta::None
//! [`SinkOptions::noise_flag`]: crate::io::SinkOptions::noise_flag
//! [`SinkOptions::normals`]: crate::io::SinkOptions::normals
//! [`FLAG_NOISE`]: crate::points::FLAG_NOISE
//! [`AtomicFile`]: crate::io::AtomicFile
//! [`Sink::finish`]: crate::io::Sink::finish

mod chunks;
mod copc;
mod foreign;
mod layout;
mod sink;
mod source;

use std::cell::Cell;
use std::io::{Read, Seek, SeekFrom};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;
use std::sync::Once;

use glam::DVec3;

pub use self::copc::CopcSink;
pub use self::sink::LasSink;
pub use self::source::LasSource;

use self::layout::{BASE_LEN, EVLR_HEADER, VLR_HEADER, fixed_str, get_u16};
use super::IoError;

/// Points per chunk of LAZ output whose source used variable-size chunks (COPC).
pub const LAZ_CHUNK_SIZE: u32 = 50_000;

/// User id of the LASzip VLR.
const LASZIP_USER: &str = "laszip encoded";
/// Record id of the LASzip VLR.
const LASZIP_RECORD: u16 = 22204;

/// One VLR (54-byte header) or EVLR (60-byte header), kept as raw bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LasVlr {
    raw: Vec<u8>,
    extended: bool,
}

impl LasVlr {
    /// Size of the record header.
    fn header_len(&self) -> usize {
        if self.extended {
            EVLR_HEADER
        } else {
            VLR_HEADER
        }
    }

    /// User id (NUL padding removed).
    pub fn user_id(&self) -> String {
        fixed_str(&self.raw[2..18])
    }

    /// Record id.
    pub fn record_id(&self) -> u16 {
        get_u16(&self.raw, 18)
    }

    /// Description (NUL padding removed).
    pub fn description(&self) -> String {
        let h = self.header_len();
        fixed_str(&self.raw[h - 32..h])
    }

    /// The payload after the record header.
    pub fn data(&self) -> &[u8] {
        &self.raw[self.header_len()..]
    }

    /// The whole record as stored: header and payload.
    pub fn bytes(&self) -> &[u8] {
        &self.raw
    }

    /// True for an EVLR (stored after the points).
    pub fn is_extended(&self) -> bool {
        self.extended
    }

    /// True when user id and record id are `user` and `record`.
    fn is(&self, user: &str, record: u16) -> bool {
        self.record_id() == record && self.user_id() == user
    }

    /// True for the LASzip VLR.
    fn is_laszip(&self) -> bool {
        self.is(LASZIP_USER, LASZIP_RECORD)
    }

    /// True for the records that describe a COPC layout (info VLR, hierarchy EVLR).
    fn is_copc_layout(&self) -> bool {
        self.is("copc", 1) || self.is("copc", 1000)
    }
}

/// The LAS header information a sink reproduces: the public header block and the VLRs, as raw
/// bytes, plus the decoded fields the backend needs.
#[derive(Debug, Clone)]
pub struct LasMeta {
    header: Vec<u8>,
    vlrs: Vec<LasVlr>,
    vlr_padding: Vec<u8>,
    version: (u8, u8),
    format: u8,
    record_len: usize,
    compressed: bool,
    scale: [f64; 3],
    offset: [f64; 3],
    count: u64,
}

impl LasMeta {
    /// LAS version (major, minor).
    pub fn version(&self) -> (u8, u8) {
        self.version
    }

    /// Point data record format, 0–10 (compression bits removed).
    pub fn point_format(&self) -> u8 {
        self.format
    }

    /// Bytes per point record (standard fields plus extra bytes).
    pub fn record_len(&self) -> usize {
        self.record_len
    }

    /// Bytes of the point format's standard fields (the record without its extra bytes).
    pub fn base_record_len(&self) -> usize {
        BASE_LEN[usize::from(self.format)]
    }

    /// The system identifier of the public header (NUL padding removed).
    pub fn system_identifier(&self) -> String {
        self.header.get(26..58).map(fixed_str).unwrap_or_default()
    }

    /// The generating software of the public header (NUL padding removed).
    pub fn generating_software(&self) -> String {
        self.header.get(58..90).map(fixed_str).unwrap_or_default()
    }

    /// The file creation day of year and year of the public header.
    pub fn creation(&self) -> (u16, u16) {
        (get_u16(&self.header, 90), get_u16(&self.header, 92))
    }

    /// The bounds the header states, as (min, max) x, y, z.
    pub fn header_bounds(&self) -> (DVec3, DVec3) {
        let f = |at: usize| {
            self.header.get(at..at + 8).map_or(f64::NAN, |b| {
                f64::from_le_bytes(b.try_into().expect("eight bytes"))
            })
        };
        // Max X, Min X, Max Y, Min Y, Max Z, Min Z from byte 179.
        (
            DVec3::new(f(187), f(203), f(219)),
            DVec3::new(f(179), f(195), f(211)),
        )
    }

    /// Number of extra bytes per record.
    pub fn extra_bytes(&self) -> usize {
        self.record_len - BASE_LEN[usize::from(self.format)]
    }

    /// True for LAZ (LASzip-compressed point data).
    pub fn is_compressed(&self) -> bool {
        self.compressed
    }

    /// True for a COPC file (it has the `copc` info VLR).
    pub fn is_copc(&self) -> bool {
        self.vlrs.iter().any(|v| v.is("copc", 1))
    }

    /// Scale factors of X, Y, Z.
    pub fn scale(&self) -> DVec3 {
        DVec3::from_array(self.scale)
    }

    /// Offsets of X, Y, Z.
    pub fn offset(&self) -> DVec3 {
        DVec3::from_array(self.offset)
    }

    /// Number of points the header declares.
    pub fn point_count(&self) -> u64 {
        self.count
    }

    /// The public header block as read (header size bytes).
    pub fn header_bytes(&self) -> &[u8] {
        &self.header
    }

    /// The VLRs, in file order.
    pub fn vlrs(&self) -> &[LasVlr] {
        &self.vlrs
    }

    /// Bytes between the last VLR and the point data (usually none).
    pub fn vlr_padding(&self) -> &[u8] {
        &self.vlr_padding
    }
}

/// A piece of what follows the point data.
#[derive(Debug, Clone)]
enum Piece {
    /// Bytes that are not an EVLR.
    Bytes(Vec<u8>),
    /// One EVLR.
    Evlr(LasVlr),
}

impl Piece {
    fn len(&self) -> u64 {
        match self {
            Piece::Bytes(b) => b.len() as u64,
            Piece::Evlr(v) => v.raw.len() as u64,
        }
    }
}

/// What follows the point data: the EVLRs (and any bytes around them), verbatim. They are read
/// into memory by [`Source::finish`](crate::io::Source::finish) (EVLRs are metadata; an internal
/// waveform data packet record would be held too).
#[derive(Debug, Clone, Default)]
pub struct LasTrailer {
    /// File offset of the first piece in the source.
    start: u64,
    pieces: Vec<Piece>,
}

impl LasTrailer {
    /// The EVLRs, in file order (a LAS 1.3 waveform data packet record counts as one).
    pub fn evlrs(&self) -> impl Iterator<Item = &LasVlr> + '_ {
        self.pieces.iter().filter_map(|p| match p {
            Piece::Evlr(v) => Some(v),
            Piece::Bytes(_) => None,
        })
    }

    /// Bytes after the points that belong to no EVLR (usually none).
    pub fn other_bytes(&self) -> usize {
        self.pieces
            .iter()
            .map(|p| match p {
                Piece::Bytes(b) => b.len(),
                Piece::Evlr(_) => 0,
            })
            .sum()
    }
}

/// Maps a LASzip error to an [`IoError`].
fn laz_error(path: &Path, e: laz::LasZipError) -> IoError {
    match e {
        laz::LasZipError::IoError(e) => laz_io_error(path, e),
        e => IoError::invalid(path, format!("bad LAZ data: {e}")),
    }
}

/// Maps an I/O error of the LAZ codec to an [`IoError`].
fn laz_io_error(path: &Path, e: std::io::Error) -> IoError {
    if e.kind() == std::io::ErrorKind::UnexpectedEof {
        IoError::truncated(path, "the compressed point data ends early")
    } else if e.kind() == std::io::ErrorKind::InvalidData || e.kind() == std::io::ErrorKind::Other {
        IoError::invalid(path, format!("bad LAZ data: {e}"))
    } else {
        IoError::io(path, e)
    }
}

/// Runs LAZ code that may panic on corrupt input, turning a panic into an error.
fn guarded<T>(path: &Path, f: impl FnOnce() -> Result<T, IoError>) -> Result<T, IoError> {
    quietly(f).unwrap_or_else(|()| Err(IoError::invalid(path, "corrupt LAZ data")))
}

thread_local! {
    /// Set while [`quietly`] runs on this thread: its panics are caught, not reported.
    static QUIET: Cell<bool> = const { Cell::new(false) };
}

/// Runs `f`, catching a panic without the panic hook printing it (message and backtrace): the
/// caller turns it into a one-line error. Panics elsewhere, on other threads or outside `f`,
/// still reach the previous hook.
fn quietly<T>(f: impl FnOnce() -> T) -> Result<T, ()> {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(Cell::get) {
                previous(info);
            }
        }));
    });
    let was = QUIET.replace(true);
    let r = catch_unwind(AssertUnwindSafe(f));
    QUIET.set(was);
    r.map_err(|_| ())
}

/// Reads exactly `len` bytes at `offset`.
fn read_at(file: &mut impl ReadSeek, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
    file.seek(SeekFrom::Start(offset))?;
    let mut b = vec![0u8; len];
    file.read_exact(&mut b)?;
    Ok(b)
}

/// `Read + Seek`, for helpers that take either a file or a buffered file.
trait ReadSeek: Read + Seek {}
impl<T: Read + Seek> ReadSeek for T {}
