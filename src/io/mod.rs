//! Streaming readers and writers for scan and mesh formats.
//!
//! # Brief overview
//!
//! * A [`Source`] describes its file in a [`SourceInfo`] (format, record [`Schema`], point count,
//!   face count, and the format's own header in [`Meta`]) and then fills reusable
//!   [`PointBatch`]es until the points run out. [`Source::finish`] returns the [`Extras`]: the faces
//!   and whatever else the file holds besides points (other PLY elements, OBJ texture coordinates…).
//! * A [`Sink`] is created *like* a source ([`create`]): it reproduces the source's header, property
//!   types and encoding, writes batches, and in [`Sink::finish`] writes the extras and atomically
//!   renames its temporary file onto the target. A sink that is dropped without `finish` leaves
//!   nothing behind. Every output goes through [`AtomicFile`] ([`output`]): only regular files
//!   (or missing paths) are renamed onto; `-`, devices and FIFOs are written directly.
//! * Inputs that are streams (`-`, pipes, FIFOs) are spooled to a temporary file first
//!   ([`input`]); [`open`] and [`Cloud::read`] do so by themselves.
//! * [`Cloud`] is the in-memory convenience built on the two: read everything, write everything.
//!
//! Sinks take positions from `batch.positions` and every other byte of a record from
//! `batch.records`; they never reorder points, except the COPC sink (`*.copc.laz`), whose format
//! stores points node by node in an octree. Sources deliver non-finite positions as they are
//! (the caller decides whether to drop them).
//!
//! # Noise flag
//!
//! A sink created by [`create_with`] with [`SinkOptions::noise_flag`] writes each point's
//! [`FLAG_NOISE`](crate::points::FLAG_NOISE) bit of [`PointBatch::flags`] (an empty `flags`
//! means no point is flagged):
//!
//! * **LAS/LAZ**: classification 7 (noise) on flagged points; other points keep their class.
//! * **PCD**: a last field `noise` (`SIZE 1`, `TYPE U`, `COUNT 1`) holding 0 or 1.
//! * **PLY**: a last vertex property `property uchar noise` holding 0 or 1, in the file's
//!   encoding (ascii or either binary one), for PLY and foreign sources alike.
//! * **XYZ/TXT, PTS**: a last column 0 or 1 after the file's separator; a header comment naming
//!   the columns (`//X Y Z …`, `# x y z …`) gets the name `noise`.
//! * **KITTI**: refused, a `.bin` record has no room for it (drop outliers, or pick another
//!   format).
//! * **E57**: an extension attribute `qemd:noise`, integer 0 or 1.
//! * **OBJ, OFF**: refused, outlier flags apply to point clouds.
//!
//! In PLY, PCD and text output a field, property or column already named [`NOISE_FIELD`] (a file
//! written by an earlier run) is overwritten in place instead of a second one being added. A
//! refused option fails in [`create_with`] with [`IoError::Unsupported`], before any file is
//! created.
//!
//! # Normals
//!
//! A sink created with [`SinkOptions::normals`] writes each point's [`PointNormal`] of
//! [`PointBatch::normals`] (an empty `normals` writes [`PointNormal::NONE`]): the unit normal
//! (`f32`), the surface variation `curvature` (`f32`) and the structure class (`u8`, the
//! [`crate::denoise::structure::Structure`] code), as five fields ([`NormalField`]):
//!
//! * **PLY**: vertex properties `float nx`, `float ny`, `float nz`, `float curvature`,
//!   `uchar structure` (after the existing ones, before an appended `noise`).
//! * **PCD**: fields `normal_x normal_y normal_z curvature` (`F 4`, PCL's `PointNormal` names)
//!   and `structure` (`U 1`).
//! * **XYZ/TXT, PTS**: columns `nx ny nz curvature structure`, named in the header comment as
//!   the noise column is.
//! * **LAS/LAZ, COPC**: extra bytes `NormalX`, `NormalY`, `NormalZ`, `Curvature` (`float`, PDAL
//!   `filters.normal`'s names) and `Structure` (`unsigned char`), described by the Extra Bytes
//!   VLR (LASF_Spec, record 4), which is added or extended; the record length, the point data
//!   offset and the LASzip VLR follow.
//! * **E57**: the E57 normals extension's `nor:normalX`, `nor:normalY`, `nor:normalZ` (single,
//!   −1 to 1, in the scan's own frame) and `qemd:curvature`, `qemd:structure`.
//! * **KITTI and raw `.bin`**: refused (no room in the record); **OBJ, OFF**: refused (meshes:
//!   their stored normals are recomputed from the faces).
//!
//! A field the output record already has under one of a value's names (`nx`, `normal_x` or
//! `NormalX`; `curvature` or `Curvature`; `structure` or `Structure`) is overwritten in place,
//! in its own type, instead of a second one being added: a re-run, or an input that stored
//! normals, keeps one set.
//!
//! # Writing another format's records
//!
//! When the output format differs from the source's, the PLY, PCD and text sinks lay their
//! records out from the source's [`Schema`] (the "foreign schema" path): every field keeps its
//! name (made valid for the format) and its type where the format has it, with one exception —
//! **x, y and z of an integer type are promoted to `f64`** (PLY `double`, PCD `F 8`; text prints
//! them as the shortest text that round-trips the `f64` position). LAS stores x, y, z as scaled
//! `I32` integers; writing those as integers would round the coordinates to whole units.
//! Positions always come from `batch.positions`, which LAS sources decode with the file's scale
//! and offset. Float x, y, z keep their type (`f32` stays `f32`). (LAS output chooses its own
//! scale and offset, KITTI stores `f32`, and OBJ/OFF print positions as the text sinks do.)
//!
//! One backend per format lives in its own module; this module only dispatches. [`trajectory`]
//! holds the sensor trajectory text format (GPS time, x, y, z per line).

pub mod classes;
pub mod crs;
pub mod e57;
pub mod input;
pub mod las;
pub(crate) mod lines;
pub mod obj;
pub mod off;
pub mod output;
pub mod pcd;
pub mod ply;
pub mod raw;
pub mod reader;
pub mod resolution;
pub mod sniff;
pub(crate) mod tally;
pub mod text;
pub mod trajectory;

pub use input::{InputFile, is_stream_input};
pub use lines::LineEnding;
pub use output::{
    AtomicFile, MemoryOutput, OutputTarget, STDIO, is_stdio, is_stream_output, remove_stale_temps,
};
pub use reader::Input;

use std::fs::File;
use std::path::{Path, PathBuf};

use glam::DVec3;
use thiserror::Error;

pub use crate::points::Rounding;
use crate::points::{Faces, PointBatch, PointNormal, ScalarType, Schema};

/// Errors of the I/O layer. Each names the file it is about.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum IoError {
    /// The operating system refused an operation.
    #[error("{path}: {error}", path = .path.display())]
    Io {
        /// File concerned.
        path: PathBuf,
        /// Underlying error (part of the message, so not chained as a source).
        error: std::io::Error,
    },
    /// The file ends before the data its header announces.
    #[error("{path}: truncated: {detail}", path = .path.display())]
    Truncated {
        /// File concerned.
        path: PathBuf,
        /// What was expected.
        detail: String,
    },
    /// The header is malformed or inconsistent.
    #[error("{path}: bad header: {detail}", path = .path.display())]
    Header {
        /// File concerned.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// The body holds data the format does not allow (bad number, face index out of range…).
    #[error("{path}: {detail}", path = .path.display())]
    Invalid {
        /// File concerned.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// The format could not be told from the extension or content.
    #[error("{path}: unknown format (expected one of {known})", path = .path.display())]
    UnknownFormat {
        /// File concerned.
        path: PathBuf,
        /// The supported extensions.
        known: &'static str,
    },
    /// A feature of the file this build does not support.
    #[error("{path}: unsupported: {detail}", path = .path.display())]
    Unsupported {
        /// File concerned.
        path: PathBuf,
        /// What is unsupported.
        detail: String,
    },
}

impl IoError {
    /// Wraps an OS error with the path it concerns.
    pub fn io(path: &Path, source: std::io::Error) -> IoError {
        if source.kind() == std::io::ErrorKind::UnexpectedEof {
            return IoError::Truncated {
                path: path.to_path_buf(),
                detail: "unexpected end of file".into(),
            };
        }
        IoError::Io {
            path: path.to_path_buf(),
            error: source,
        }
    }

    /// A malformed or inconsistent header.
    pub fn header(path: &Path, detail: impl Into<String>) -> IoError {
        IoError::Header {
            path: path.to_path_buf(),
            detail: detail.into(),
        }
    }

    /// Data the format does not allow.
    pub fn invalid(path: &Path, detail: impl Into<String>) -> IoError {
        IoError::Invalid {
            path: path.to_path_buf(),
            detail: detail.into(),
        }
    }

    /// The same error naming `to` where it named `from` (a spooled stream shown by its name).
    pub fn with_path(self, from: &Path, to: &Path) -> IoError {
        let swap = |p: PathBuf| if p == from { to.to_path_buf() } else { p };
        match self {
            IoError::Io { path, error } => IoError::Io {
                path: swap(path),
                error,
            },
            IoError::Truncated { path, detail } => IoError::Truncated {
                path: swap(path),
                detail,
            },
            IoError::Header { path, detail } => IoError::Header {
                path: swap(path),
                detail,
            },
            IoError::Invalid { path, detail } => IoError::Invalid {
                path: swap(path),
                detail,
            },
            IoError::UnknownFormat { path, known } => IoError::UnknownFormat {
                path: swap(path),
                known,
            },
            IoError::Unsupported { path, detail } => IoError::Unsupported {
                path: swap(path),
                detail,
            },
        }
    }

    /// The file ends early.
    pub fn truncated(path: &Path, detail: impl Into<String>) -> IoError {
        IoError::Truncated {
            path: path.to_path_buf(),
            detail: detail.into(),
        }
    }
}

/// `s` with its control characters escaped (`\x1b`, `\x07`, `\n`…), for a terminal: a file's
/// name or header may hold ESC and BEL, which an error or `qemd info` would otherwise send to
/// the terminal as they are (issue 51). Everything else, Unicode included, stays.
pub fn printable(s: &str) -> std::borrow::Cow<'_, str> {
    if !s.chars().any(char::is_control) {
        return std::borrow::Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        match c {
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c.is_control() && (c as u32) < 0x100 => {
                out.push_str(&format!("\\x{:02x}", c as u32));
            }
            c if c.is_control() => out.push_str(&format!("\\u{{{:x}}}", c as u32)),
            c => out.push(c),
        }
    }
    std::borrow::Cow::Owned(out)
}

/// The supported file formats. Serialised as [`Format::name`] (a job's stored output format,
/// an upload's format); a [`Format::Bin`] layout does not travel that way (`bin` reads back as
/// KITTI), which the service never needs: it only takes named formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(into = "String", try_from = "String")]
#[non_exhaustive]
pub enum Format {
    /// Stanford PLY (ascii, binary little- and big-endian).
    Ply,
    /// Wavefront OBJ.
    Obj,
    /// Object File Format.
    Off,
    /// Text point cloud, one `x y z …` line per point (`.xyz`, `.txt`).
    Xyz,
    /// Leica-style text point cloud: the point count, then `x y z …` lines (`.pts`).
    Pts,
    /// KITTI Velodyne scan: little-endian `f32` x, y, z, intensity records (`.bin`).
    Kitti,
    /// nuScenes LiDAR sweep: little-endian `f32` x, y, z, intensity, ring records (`.pcd.bin`).
    Nuscenes,
    /// Raw little-endian `f32` records of another layout (`--bin-fields`).
    Bin(raw::BinLayout),
    /// Point Cloud Library PCD (ascii, binary, binary_compressed).
    Pcd,
    /// ASPRS LAS (`.las`), uncompressed.
    Las,
    /// LAZ (`.laz`): LAS compressed by LASzip.
    Laz,
    /// Cloud Optimized Point Cloud (`.copc.laz`): read as the LAZ file it is, written as COPC 1.0
    /// (points reordered into octree chunks; a regular file only).
    Copc,
    /// ASTM E57 (`.e57`): terrestrial scans, Cartesian or spherical, several per file.
    E57,
}

const KNOWN: &str =
    ".ply, .obj, .off, .xyz, .txt, .pts, .bin, .pcd.bin, .pcd, .las, .laz, .copc.laz, .e57";

impl Format {
    /// Tells the format from a file extension (case-insensitive).
    ///
    /// # Errors
    /// [`IoError::UnknownFormat`] for an unknown or missing extension.
    pub fn from_path(path: &Path) -> Result<Format, IoError> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if name.ends_with(".pcd.bin") {
            return Ok(Format::Nuscenes);
        }
        if name.ends_with(".copc.laz") {
            return Ok(Format::Copc);
        }
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        ext.as_deref()
            .and_then(Format::from_name)
            .ok_or_else(|| IoError::UnknownFormat {
                path: path.to_path_buf(),
                known: KNOWN,
            })
    }

    /// Parses a format name or extension (`ply`, `obj`, `off`, `xyz`, `txt`, `pts`, `bin`,
    /// `kitti`, `nuscenes`, `pcd`, `las`, `laz`, `copc`, `e57`; see [`Format::NAMES`]).
    pub fn from_name(name: &str) -> Option<Format> {
        match name.to_ascii_lowercase().as_str() {
            "ply" => Some(Format::Ply),
            "obj" => Some(Format::Obj),
            "off" => Some(Format::Off),
            "xyz" | "txt" => Some(Format::Xyz),
            "pts" => Some(Format::Pts),
            "bin" | "kitti" => Some(Format::Kitti),
            "nuscenes" | "pcd.bin" => Some(Format::Nuscenes),
            "pcd" => Some(Format::Pcd),
            "las" => Some(Format::Las),
            "laz" => Some(Format::Laz),
            "copc" | "copc.laz" => Some(Format::Copc),
            "e57" => Some(Format::E57),
            _ => None,
        }
    }

    /// Lower-case name, also the canonical extension.
    pub fn name(self) -> &'static str {
        match self {
            Format::Ply => "ply",
            Format::Obj => "obj",
            Format::Off => "off",
            Format::Xyz => "xyz",
            Format::Pts => "pts",
            Format::Kitti => "bin",
            Format::Nuscenes => "pcd.bin",
            Format::Bin(_) => "bin",
            Format::Pcd => "pcd",
            Format::Las => "las",
            Format::Laz => "laz",
            Format::Copc => "copc.laz",
            Format::E57 => "e57",
        }
    }

    /// The names [`Format::from_name`] accepts, for help texts.
    pub const NAMES: &'static [&'static str] = &[
        "ply", "obj", "off", "xyz", "txt", "pts", "pcd", "las", "laz", "copc", "kitti", "bin",
        "nuscenes", "e57",
    ];

    /// The message for a name [`Format::from_name`] does not know, listing those it does.
    pub fn unknown(name: &str) -> String {
        format!(
            "unknown format `{name}` (expected one of {})",
            Format::NAMES.join(", ")
        )
    }

    /// True for the formats that store a sweep in its sensor's frame, the sensor at the origin
    /// (KITTI Velodyne `.bin`, nuScenes `.pcd.bin`): every return's beam runs from `(0, 0, 0)`.
    /// A raw `.bin` of another layout makes no such promise, nor does PCD, whose `VIEWPOINT` is
    /// commonly left at its default on clouds that are not in a sensor's frame.
    pub fn sensor_frame(self) -> bool {
        matches!(self, Format::Kitti | Format::Nuscenes)
    }

    /// LAS, LAZ or COPC: one reader, one point model.
    pub fn is_las(self) -> bool {
        matches!(self, Format::Las | Format::Laz | Format::Copc)
    }

    /// The record layout of a raw `f32` format (KITTI, nuScenes, [`Format::Bin`]).
    pub fn bin_layout(self) -> Option<raw::BinLayout> {
        match self {
            Format::Kitti => Some(raw::BinLayout::KITTI),
            Format::Nuscenes => Some(raw::BinLayout::NUSCENES),
            Format::Bin(l) => Some(l),
            _ => None,
        }
    }
}

impl From<Format> for String {
    fn from(f: Format) -> String {
        f.name().to_string()
    }
}

impl TryFrom<String> for Format {
    type Error = String;
    fn try_from(name: String) -> Result<Format, String> {
        Format::from_name(&name).ok_or_else(|| Format::unknown(&name))
    }
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Format-specific header information a sink needs to reproduce its source.
#[derive(Debug, Clone, Default)]
#[non_exhaustive]
pub enum Meta {
    /// No format header: a cloud built in memory, written with the sink format's defaults.
    #[default]
    None,
    /// PLY header (elements, comments, encoding).
    Ply(ply::PlyMeta),
    /// OBJ specifics.
    Obj(obj::ObjMeta),
    /// OFF specifics.
    Off(off::OffMeta),
    /// XYZ and PTS header lines and separator.
    Text(text::TextMeta),
    /// PCD header (raw lines, fields, organization, DATA kind).
    Pcd(pcd::PcdMeta),
    /// LAS public header and VLRs.
    Las(las::LasMeta),
    /// E57 scans (descriptors, poses, prototypes) and extensions.
    E57(e57::E57Meta),
}

/// What a source says about its file before any point is read.
#[derive(Debug, Clone)]
pub struct SourceInfo {
    /// The file (empty for clouds built in memory).
    pub path: PathBuf,
    /// Its format.
    pub format: Format,
    /// Layout of the records the source delivers.
    pub schema: Schema,
    /// Number of points, when the header declares it.
    pub len: Option<u64>,
    /// Number of faces the file declares (`None` for a point cloud). Sinks whose header states
    /// the face count (PLY, OFF) write this number and check it against the faces they get.
    pub faces: Option<u64>,
    /// The format's own header.
    pub meta: Meta,
}

impl SourceInfo {
    /// Info for data generated in memory: a packed x, y, z record of type `ty`.
    pub fn generated(format: Format, ty: ScalarType, len: u64, faces: Option<u64>) -> SourceInfo {
        SourceInfo {
            path: PathBuf::new(),
            format,
            schema: Schema::xyz_only(ty),
            len: Some(len),
            faces,
            meta: Meta::None,
        }
    }

    /// True when the file declares faces (a mesh).
    pub fn has_faces(&self) -> bool {
        self.faces.is_some()
    }

    /// True for an organized cloud (a PCD file with `HEIGHT` > 1): its points form a
    /// `WIDTH` × `HEIGHT` image and invalid points are NaN placeholders. A caller must keep such
    /// points in place (leave them unprocessed) rather than drop them; sinks write NaN
    /// coordinates as given, so an unchanged point count keeps the image layout.
    pub fn is_organized(&self) -> bool {
        matches!(&self.meta, Meta::Pcd(m) if m.is_organized())
    }
}

/// Format-specific content besides the points that a sink writes back unchanged.
#[derive(Debug, Clone, Default)]
#[non_exhaustive]
pub enum Trailer {
    /// Nothing besides points and faces.
    #[default]
    None,
    /// PLY elements other than `vertex`, as raw bytes.
    Ply(ply::PlyTrailer),
    /// OBJ lines other than vertex positions.
    Obj(obj::ObjTrailer),
    /// OFF face lines.
    Off(off::OffTrailer),
    /// XYZ and PTS comment lines after the points.
    Text(text::TextTrailer),
    /// PCD bytes after the point data.
    Pcd(pcd::PcdTrailer),
    /// LAS EVLRs after the points.
    Las(las::LasTrailer),
}

/// Everything a file holds besides its points.
#[derive(Debug, Clone, Default)]
pub struct Extras {
    /// Polygon faces, when the file has any.
    pub faces: Option<Faces>,
    /// Other content, reproduced by a sink of the same format.
    pub trailer: Trailer,
}

impl Extras {
    /// Extras holding only faces (for meshes built in memory).
    pub fn with_faces(faces: Faces) -> Extras {
        Extras {
            faces: Some(faces),
            trailer: Trailer::None,
        }
    }
}

/// A reader that streams points in batches.
pub trait Source: Send {
    /// What the file declares.
    fn info(&self) -> &SourceInfo;

    /// Clears `batch` (keeping its allocations), then appends up to `max` further points and sets
    /// `batch.start`. Returns how many points were read; 0 means the points are exhausted.
    ///
    /// # Errors
    /// Truncated or malformed data.
    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError>;

    /// Moves to point `index` (at most the count), so that the next batch starts there, when
    /// the format can without reading the points before it (fixed-size records: LAS, binary PLY
    /// and PCD, raw `.bin`; a LAZ chunk table of fixed-size chunks). Returns false, having moved nothing, when it cannot: the
    /// caller reads from the start. A range read this way is a task of a parallel partition.
    ///
    /// # Errors
    /// Seek failures, bad LAZ data.
    fn seek_point(&mut self, index: u64) -> Result<bool, IoError> {
        let _ = index;
        Ok(false)
    }

    /// Reads what follows the points and returns it; call after the last batch.
    ///
    /// # Errors
    /// Truncated or malformed data, face indices out of range.
    fn finish(self: Box<Self>) -> Result<Extras, IoError>;
}

/// What a sink's header needs of the points of a body written apart ([`SinkOptions::body`]):
/// their count, and for LAS the points per return and the stored bounds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct BodyStats {
    /// Points in the body.
    pub points: u64,
    /// LAS: points per return number 1–15 (zeros for other formats).
    pub by_return: [u64; 15],
    /// LAS: the smallest and largest stored (scaled integer) x, y, z; `None` for other formats
    /// and for a body without points.
    pub bounds: Option<([i32; 3], [i32; 3])>,
}

impl BodyStats {
    /// The stats of a body of `points` points in a format whose header needs only the count.
    pub fn count(points: u64) -> BodyStats {
        BodyStats {
            points,
            ..BodyStats::default()
        }
    }
}

/// A writer that streams points in batches into a temporary file and renames it at the end.
///
/// # Bodies
/// A sink created with [`SinkOptions::body`] writes the records alone (no header, no trailer, no
/// check of the announced count) and ends with [`Sink::finish_body`]; the sink of the whole
/// output, created with the same layout, takes such bodies in order with [`Sink::append_body`]
/// instead of their points, and writes byte for byte what it would have written from the points
/// (the stitch of a tiled run writes its output in ranges this way). Only the sinks whose
/// [`Sink::splittable`] is true can: fixed or line records without compression (PLY, PCD
/// `ascii`/`binary`, XYZ/PTS, raw `.bin`, LAS with a known scale and offset).
pub trait Sink {
    /// Writes the points of `batch`, positions from `batch.positions`.
    ///
    /// # Errors
    /// Write failures; more points than announced.
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError>;

    /// Writes the extras, flushes and moves the file into place.
    ///
    /// # Errors
    /// Write failures; fewer points than announced.
    fn finish(self: Box<Self>, extras: &Extras) -> Result<(), IoError>;

    /// True when this sink writes its points the same way in bodies ([`Sink::append_body`]).
    fn splittable(&self) -> bool {
        false
    }

    /// Ends a body sink ([`SinkOptions::body`]): flushes and moves its file into place (without a
    /// sync: bodies are scratch) and returns what the whole output's header needs of its points.
    ///
    /// # Errors
    /// Write failures; [`IoError::Unsupported`] for a sink that is not [`Sink::splittable`].
    fn finish_body(self: Box<Self>) -> Result<BodyStats, IoError> {
        Err(not_splittable(Path::new("")))
    }

    /// Appends the body at `path`, written by a body sink of this sink's layout, whose
    /// [`Sink::finish_body`] gave `stats`, as if its points had been written here.
    ///
    /// # Errors
    /// Read and write failures; more points than announced; [`IoError::Unsupported`] for a sink
    /// that is not [`Sink::splittable`].
    fn append_body(&mut self, path: &Path, stats: &BodyStats) -> Result<(), IoError> {
        let _ = stats;
        Err(not_splittable(path))
    }
}

/// The error of a body asked of a sink that cannot write bodies.
fn not_splittable(path: &Path) -> IoError {
    IoError::Unsupported {
        path: path.to_path_buf(),
        detail: "this output cannot be written in separate bodies".into(),
    }
}

/// Opens `path` for streaming; the format comes from `format` or else from the extension.
///
/// # Errors
/// Unknown format, unreadable file, malformed header.
pub fn open(path: &Path, format: Option<Format>) -> Result<Box<dyn Source>, IoError> {
    if input::is_stream_input(path) {
        return Spooled::open(path, format);
    }
    let format = match format {
        Some(f) => f,
        None => Format::from_path(path)?,
    };
    open_input(Input::from_path(path)?, format)
}

/// Opens `input` (a file or bytes in memory) as `format` for streaming.
///
/// # Errors
/// Malformed header; a format that needs a known size (LAS, raw scans) on an input without one.
pub fn open_input(input: Input, format: Format) -> Result<Box<dyn Source>, IoError> {
    Ok(match format {
        Format::Ply => Box::new(ply::PlySource::new(input)?),
        Format::Obj => Box::new(obj::ObjSource::new(input)?),
        Format::Off => Box::new(off::OffSource::new(input)?),
        Format::Xyz => Box::new(text::TextSource::new(input, text::TextFlavor::Xyz)?),
        Format::Pts => Box::new(text::TextSource::new(input, text::TextFlavor::Pts)?),
        Format::Kitti | Format::Nuscenes | Format::Bin(_) => {
            Box::new(raw::RawSource::new(input, format)?)
        }
        Format::Pcd => Box::new(pcd::PcdSource::new(input)?),
        Format::Las | Format::Laz | Format::Copc => Box::new(las::LasSource::new(input)?),
        Format::E57 => Box::new(e57::E57Source::new(input)?),
    })
}

/// A source reading the spool of a stream ([`input::InputFile`]), which it owns; its info and
/// errors name the stream.
struct Spooled {
    inner: Box<dyn Source>,
    info: SourceInfo,
    input: input::InputFile,
}

impl Spooled {
    fn open(path: &Path, format: Option<Format>) -> Result<Box<dyn Source>, IoError> {
        let input = input::InputFile::open(path, format, None)?;
        let inner = open(input.path(), input.format()).map_err(|e| input.explain(e))?;
        let mut info = inner.info().clone();
        info.path = input.shown().to_path_buf();
        Ok(Box::new(Spooled { inner, info, input }))
    }
}

impl Source for Spooled {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        self.inner
            .read_batch(batch, max)
            .map_err(|e| self.input.explain(e))
    }

    fn finish(self: Box<Self>) -> Result<Extras, IoError> {
        let Spooled { inner, input, .. } = *self;
        inner.finish().map_err(|e| input.explain(e))
    }
}

/// What a sink adds to its source's layout.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SinkOptions {
    /// Write each point's noise flag ([`crate::points::FLAG_NOISE`] in `PointBatch::flags`):
    /// classification 7 in LAS, an extra `noise` value (0/1) in the formats that can carry one
    /// (PCD: a `noise` field, `SIZE 1`, `TYPE U`; PLY: a vertex property `uchar noise`; XYZ and
    /// PTS: a last column). KITTI, OBJ and OFF refuse it (see the [module overview](self)).
    pub noise_flag: bool,
    /// Write each point's normal, surface variation and structure class
    /// ([`PointBatch::normals`]) as the fields of the [module overview](self#normals). KITTI,
    /// raw `.bin`, OBJ and OFF refuse it.
    pub normals: bool,
    /// Where a sink that must seek (LAS/LAZ) spools its output when the target is a stream
    /// (standard output, a FIFO); the system temporary directory when `None`.
    pub temp_dir: Option<PathBuf>,
    /// Write a body: the records alone, for [`Sink::append_body`] (see [`Sink`]'s bodies).
    pub body: bool,
    /// How a moved point's coordinates round to the values the output stores: to nearest by
    /// default; a denoising run asks [`Rounding::NoLonger`], so that no stored move is longer
    /// than the computed one (E57 stores coordinates as doubles, OBJ and OFF as text of the
    /// full value: nothing to round).
    pub rounding: Rounding,
}

/// Creates a sink at `path` that writes `count` points laid out like `like`. The format comes from
/// `format`, else from the extension. When it equals the source's format, the output keeps the
/// source's header, encoding and property types.
///
/// # Errors
/// Unknown format, the directory is not writable.
pub fn create(
    path: &Path,
    format: Option<Format>,
    like: &SourceInfo,
    count: u64,
) -> Result<Box<dyn Sink>, IoError> {
    create_with(path, format, like, count, &SinkOptions::default())
}

/// [`create`] with options (a noise flag).
///
/// # Errors
/// As [`create`], and [`IoError::Unsupported`] for an option the format cannot carry: the noise
/// flag in KITTI (no room in a `.bin` record), OBJ or OFF (meshes) output. Nothing is created then.
pub fn create_with(
    path: &Path,
    format: Option<Format>,
    like: &SourceInfo,
    count: u64,
    options: &SinkOptions,
) -> Result<Box<dyn Sink>, IoError> {
    // A directory or a dangling link is refused before anything else is looked at.
    let target = OutputTarget::of(path)?;
    let format = match format {
        Some(f) => f,
        None => Format::from_path(path).or_else(|e| {
            // A stream (standard output, a FIFO) without an extension gets the input's format;
            // COPC, which reorganises a file it can reopen, goes to a stream as the LAZ it is.
            if target.is_stream() {
                Ok(match like.format {
                    Format::Copc => Format::Laz,
                    f => f,
                })
            } else {
                Err(e)
            }
        })?,
    };
    let out = match format {
        // Formats that patch their header after the data seek; towards a stream they spool.
        Format::Las | Format::Laz => {
            AtomicFile::create_seekable(path, options.temp_dir.as_deref())?
        }
        // E57 and COPC read back and reorganise what they wrote: they need a path of their own.
        Format::E57 | Format::Copc => return create_file_only(path, format, like, count, options),
        _ => AtomicFile::create(path)?,
    };
    create_in(out, format, like, count, options)
}

/// [`create_with`] writing to `out`: a file, a stream, or memory ([`AtomicFile::memory`]).
///
/// # Errors
/// As [`create_with`]; [`IoError::Unsupported`] for E57 and COPC, which need a regular file.
pub fn create_in(
    out: AtomicFile,
    format: Format,
    like: &SourceInfo,
    count: u64,
    options: &SinkOptions,
) -> Result<Box<dyn Sink>, IoError> {
    refuse_options(out.target(), format, options)?;
    // A body announces nothing: the sink it is appended to counts its points.
    let count = if options.body { u64::MAX } else { count };
    Ok(match format {
        Format::Ply => Box::new(ply::PlySink::new(out, like, count, options)?),
        Format::Obj => Box::new(obj::ObjSink::new(out, like, count)?),
        Format::Off => Box::new(off::OffSink::new(out, like, count)?),
        Format::Xyz => Box::new(text::TextSink::new(
            out,
            text::TextFlavor::Xyz,
            like,
            count,
            options,
        )?),
        Format::Pts => Box::new(text::TextSink::new(
            out,
            text::TextFlavor::Pts,
            like,
            count,
            options,
        )?),
        Format::Kitti | Format::Nuscenes | Format::Bin(_) => Box::new(raw::RawSink::new(
            out,
            format,
            like,
            count,
            options.rounding,
        )?),
        Format::Pcd => Box::new(pcd::PcdSink::new(out, like, count, options)?),
        Format::Las => Box::new(las::LasSink::new(out, like, count, options, false)?),
        Format::Laz => Box::new(las::LasSink::new(out, like, count, options, true)?),
        Format::E57 | Format::Copc => {
            return Err(IoError::Unsupported {
                path: out.target().to_path_buf(),
                detail: format!("{format} output needs a regular file"),
            });
        }
    })
}

/// The sinks that write a path of their own (E57, COPC).
fn create_file_only(
    path: &Path,
    format: Format,
    like: &SourceInfo,
    count: u64,
    options: &SinkOptions,
) -> Result<Box<dyn Sink>, IoError> {
    refuse_options(path, format, options)?;
    Ok(match format {
        Format::Copc => Box::new(las::CopcSink::create(path, like, count, options)?),
        _ => Box::new(e57::E57Sink::create(path, like, count, options)?),
    })
}

/// [`IoError::Unsupported`] when the noise flag or the normals are asked of a format that
/// cannot carry them.
fn refuse_options(path: &Path, format: Format, options: &SinkOptions) -> Result<(), IoError> {
    if let Some(detail) = options.normals.then(|| refuse_normals(format)).flatten() {
        return Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: detail.to_string(),
        });
    }
    if options.noise_flag {
        let refuse = match format {
            Format::Las
            | Format::Laz
            | Format::Copc
            | Format::Pcd
            | Format::Ply
            | Format::Xyz
            | Format::Pts
            | Format::E57 => None,
            Format::Kitti => Some(
                "a KITTI .bin record has no room for a noise flag; use --outliers remove or \
                 another output format",
            ),
            Format::Nuscenes | Format::Bin(_) => Some(
                "a raw .bin record has no room for a noise flag; use --outliers remove or \
                 another output format",
            ),
            Format::Obj | Format::Off => Some("outlier flags apply to point clouds"),
        };
        if let Some(detail) = refuse {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: detail.to_string(),
            });
        }
    }
    Ok(())
}

/// Why `format` cannot carry written normals, `None` when it can.
pub fn refuse_normals(format: Format) -> Option<&'static str> {
    match format {
        Format::Las
        | Format::Laz
        | Format::Copc
        | Format::Pcd
        | Format::Ply
        | Format::Xyz
        | Format::Pts
        | Format::E57 => None,
        Format::Kitti => Some(
            "a KITTI .bin record has no room for normals (--write-normals); write PLY, PCD, LAS \
             or text instead",
        ),
        Format::Nuscenes | Format::Bin(_) => Some(
            "a raw .bin record has no room for normals (--write-normals); write PLY, PCD, LAS \
             or text instead",
        ),
        Format::Obj | Format::Off => Some(
            "--write-normals applies to point clouds; a mesh's stored normals are recomputed \
             from its faces",
        ),
    }
}

/// Name of the per-point field that carries the noise flag in PLY, PCD and text output.
pub const NOISE_FIELD: &str = "noise";

/// One of the five values [`SinkOptions::normals`] writes per point (see the
/// [module overview](self#normals)).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NormalField {
    /// The normal's x.
    X,
    /// The normal's y.
    Y,
    /// The normal's z.
    Z,
    /// The surface variation.
    Curvature,
    /// The structure class code.
    Structure,
}

/// The naming convention of an output format's normal fields.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NormalNames {
    /// `nx ny nz curvature structure` (PLY, text).
    Ply,
    /// `normal_x normal_y normal_z curvature structure` (PCD, PCL's `PointNormal`).
    Pcd,
    /// `NormalX NormalY NormalZ Curvature Structure` (LAS extra bytes, PDAL's dimensions).
    Las,
}

impl NormalField {
    /// The five values, in the order they are appended.
    pub const ALL: [NormalField; 5] = [
        NormalField::X,
        NormalField::Y,
        NormalField::Z,
        NormalField::Curvature,
        NormalField::Structure,
    ];

    /// Every name under which an existing field holds this value (overwritten in place).
    pub fn aliases(self) -> &'static [&'static str] {
        match self {
            NormalField::X => &["nx", "normal_x", "NormalX"],
            NormalField::Y => &["ny", "normal_y", "NormalY"],
            NormalField::Z => &["nz", "normal_z", "NormalZ"],
            NormalField::Curvature => &["curvature", "Curvature"],
            NormalField::Structure => &["structure", "Structure"],
        }
    }

    /// The name a field added in `names`'s convention gets.
    pub fn name(self, names: NormalNames) -> &'static str {
        let i = match names {
            NormalNames::Ply => 0,
            NormalNames::Pcd => 1,
            NormalNames::Las => 2,
        };
        match self {
            NormalField::X | NormalField::Y | NormalField::Z => self.aliases()[i],
            _ => self.aliases()[usize::from(i == 2)],
        }
    }

    /// The type of an added field.
    pub fn ty(self) -> ScalarType {
        match self {
            NormalField::Structure => ScalarType::U8,
            _ => ScalarType::F32,
        }
    }

    /// This value of `n`.
    pub fn value(self, n: &PointNormal) -> f64 {
        match self {
            NormalField::X => f64::from(n.normal[0]),
            NormalField::Y => f64::from(n.normal[1]),
            NormalField::Z => f64::from(n.normal[2]),
            NormalField::Curvature => f64::from(n.curvature),
            NormalField::Structure => f64::from(n.structure),
        }
    }

    /// The field of `schema` that already holds this value (by [`NormalField::aliases`]).
    pub fn find(self, schema: &Schema) -> Option<usize> {
        self.aliases().iter().find_map(|n| schema.field_index(n))
    }
}

/// The type a sink gives field `i` of a record whose layout comes from *another* format: a field
/// keeps its type, except that x, y and z stored as integers (LAS keeps scaled `I32` coordinates)
/// become `F64`, so that decoded positions are not rounded to whole units.
pub(crate) fn foreign_field_type(schema: &Schema, i: usize) -> ScalarType {
    let ty = schema.fields[i].ty;
    if schema.xyz.contains(&i) && !ty.is_float() {
        ScalarType::F64
    } else {
        ty
    }
}

/// Points per batch for whole-file reads and writes.
pub const BATCH: usize = 1 << 16;

/// A whole file in memory: positions, records and extras.
#[derive(Debug, Clone)]
pub struct Cloud {
    /// What the source declared.
    pub info: SourceInfo,
    /// Positions, one per point.
    pub positions: Vec<DVec3>,
    /// Raw records, `info.schema.record_len` bytes per point.
    pub records: Vec<u8>,
    /// Faces and other content.
    pub extras: Extras,
}

impl Cloud {
    /// Reads a whole file.
    ///
    /// # Errors
    /// Anything [`open`], [`Source::read_batch`] or [`Source::finish`] reports.
    pub fn read(path: &Path, format: Option<Format>) -> Result<Cloud, IoError> {
        let src = open(path, format)?;
        let file_len = std::fs::metadata(path).map_or(1 << 20, |m| m.len());
        Cloud::read_all(src, file_len)
    }

    /// Reads a whole [`Input`] (a file or bytes in memory) of `format`.
    ///
    /// # Errors
    /// As [`Cloud::read`].
    pub fn read_input(input: Input, format: Format) -> Result<Cloud, IoError> {
        let len = input.len().unwrap_or(1 << 20);
        Cloud::read_all(open_input(input, format)?, len)
    }

    /// Reads every point of `src`, whose input holds `file_len` bytes.
    fn read_all(mut src: Box<dyn Source>, file_len: u64) -> Result<Cloud, IoError> {
        let info = src.info().clone();
        // The declared length is untrusted (a LAZ header can claim billions of points in a few
        // bytes): the reservation is also held to one point per byte of the file; a cloud that
        // is really larger grows as it is read.
        let cap = info.len.unwrap_or(0).min(1 << 28).min(file_len) as usize;
        let rl = info.schema.record_len;
        let mut positions = Vec::with_capacity(cap);
        let mut records = Vec::with_capacity(cap * rl);
        let mut batch = PointBatch::with_capacity(rl, BATCH);
        while src.read_batch(&mut batch, BATCH)? > 0 {
            positions.extend_from_slice(&batch.positions);
            records.extend_from_slice(&batch.records);
        }
        let extras = src.finish()?;
        if let Some(f) = &extras.faces
            && f.min_vertex_count() > positions.len()
        {
            return Err(IoError::invalid(
                &info.path,
                format!(
                    "a face references vertex {} but the file has {} vertices",
                    f.min_vertex_count() - 1,
                    positions.len()
                ),
            ));
        }
        Ok(Cloud {
            info,
            positions,
            records,
            extras,
        })
    }

    /// A generated mesh or point set with an x, y, z record of type `ty`.
    pub fn generated(positions: Vec<DVec3>, faces: Option<Faces>, ty: ScalarType) -> Cloud {
        let info = SourceInfo::generated(
            Format::Ply,
            ty,
            positions.len() as u64,
            faces.as_ref().map(|f| f.len() as u64),
        );
        let mut records = vec![0u8; positions.len() * info.schema.record_len];
        for (rec, &p) in records
            .chunks_exact_mut(info.schema.record_len)
            .zip(&positions)
        {
            info.schema.set_position(rec, p);
        }
        Cloud {
            info,
            positions,
            records,
            extras: Extras {
                faces,
                trailer: Trailer::None,
            },
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True without points.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// The faces, if any.
    pub fn faces(&self) -> Option<&Faces> {
        self.extras.faces.as_ref()
    }

    /// Writes the cloud (current positions) to `path`, like its source.
    ///
    /// # Errors
    /// Anything [`create`] or the sink reports.
    pub fn write(&self, path: &Path, format: Option<Format>) -> Result<(), IoError> {
        self.write_to(create(
            path,
            format,
            &self.info,
            self.positions.len() as u64,
        )?)
    }

    /// Writes the cloud into `sink`, created for [`Cloud::len`] points like `self.info`.
    ///
    /// # Errors
    /// Anything the sink reports.
    pub fn write_to(&self, mut sink: Box<dyn Sink>) -> Result<(), IoError> {
        let rl = self.info.schema.record_len;
        let mut batch = PointBatch::with_capacity(rl, BATCH);
        for (c, (pos, rec)) in self
            .positions
            .chunks(BATCH)
            .zip(self.records.chunks(BATCH * rl.max(1)))
            .enumerate()
        {
            batch.clear((c * BATCH) as u64);
            batch.positions.extend_from_slice(pos);
            batch
                .records
                .extend_from_slice(if rl == 0 { &[] } else { rec });
            sink.write_batch(&batch)?;
        }
        sink.finish(&self.extras)
    }
}

/// Opens `path` for reading with a clear error.
///
/// # Errors
/// [`IoError::Io`] naming the path.
pub fn open_file(path: &Path) -> Result<File, IoError> {
    File::open(path).map_err(|e| IoError::io(path, e))
}

/// The length of `file` when it is a regular file (not a pipe or device), to check headers
/// against.
pub fn regular_len(file: &File) -> Option<u64> {
    file.metadata()
        .ok()
        .filter(|m| m.is_file())
        .map(|m| m.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_from_extension() {
        assert_eq!(
            Format::from_path(Path::new("a/b.PLY")).unwrap(),
            Format::Ply
        );
        assert_eq!(Format::from_path(Path::new("m.obj")).unwrap(), Format::Obj);
        assert!(matches!(
            Format::from_path(Path::new("m.xyzw")),
            Err(IoError::UnknownFormat { .. })
        ));
        assert!(Format::from_path(Path::new("noext")).is_err());
    }
}
