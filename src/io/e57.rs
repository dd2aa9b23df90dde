//! ASTM E57 (`.e57`) input and output through the `e57` crate (pure Rust): terrestrial scanner
//! exports (Leica, FARO, CloudCompare, …).
//!
//! # Brief overview
//!
//! ```text
//!  E57 file                              qemd cloud
//!  scan 0: pose₀, prototype, points  ─┐  positions: world frame (pose applied), f64
//!  scan 1: pose₁, prototype, points  ─┼► records:   one field per attribute + `scan`
//!  …                                 ─┘  E57Meta:   file GUID, extensions, scan descriptors
//! ```
//!
//! * **Scans are merged**: every scan of the file is read in file order into one cloud, each
//!   point moved into the file's common frame by its scan's pose (`p = R·p_local + t`, R from the
//!   unit quaternion). When the file has more than one scan, each record carries a `scan` field
//!   (`u32`, the scan's index), so neighbourhoods span scans (a denoiser wants the overlap) and a
//!   writer can split the points again.
//! * **Coordinates**: Cartesian scans are read as they are; spherical scans (range, azimuth,
//!   elevation) are converted, `x = r·cos(el)·cos(az)`, `y = r·cos(el)·sin(az)`, `z = r·sin(el)`,
//!   as E57 defines them, wherever a point's Cartesian coordinate is absent or marked invalid. A
//!   point with neither valid Cartesian nor valid spherical coordinates (state 1 or 2) has a NaN
//!   position: the pipeline leaves it out and counts it.
//! * **Every other attribute is a field**, raw (not normalised): `intensity`, `red`, `green`,
//!   `blue`, `row`, `column`, `return_index`, `return_count`, `time`, the invalid-state flags
//!   (`cartesian_invalid`, `spherical_invalid`, `intensity_invalid`, `color_invalid`,
//!   `time_invalid`) and extension attributes (`<namespace>_<name>`; qemd's own namespace reads
//!   back as the bare field name it was written from, `qemd:classification` → `classification`,
//!   unless that is a name listed above). Types: E57 single → `f32`,
//!   double and scaled integers → `f64` (the scaled value), integers → the smallest integer type
//!   that holds the declared range (`u8` for 0–255 colours), else `f64`. A field absent from a
//!   scan is 0 in its points.
//!
//! # Writing
//!
//! [`E57Sink`] streams: points go to a writer thread that owns the `e57` writer, one scan at a
//! time, and the file appears at [`Sink::finish`] (temporary file + rename).
//!
//! * **From an E57 source** the output has the source's scans in order, each with its name,
//!   description, pose, sensor and acquisition metadata, intensity and colour limits and its own
//!   attribute records (same types); points are stored in the scan's local frame
//!   (`p_local = Rᵀ·(p − t)`) and split by their `scan` field (each scan's points must be
//!   together, as the reader delivers them; a scan whose points were all dropped is written
//!   empty). A spherical scan is written spherical again, range, azimuth and elevation recomputed
//!   from the (denoised) position. Coordinates are always written as doubles: a moved point no
//!   longer sits on the source's scaled-integer grid. The invalid state of the written
//!   coordinates is recomputed (0, or 2 for a non-finite position); a scan without one stores a
//!   non-finite position as NaN doubles. The file's and the scans' GUIDs are derived from
//!   a SHA-256 of everything written (the same output gets the same GUIDs, so output stays
//!   deterministic); each scan lists its source GUID among its original GUIDs. Images and blobs are not copied.
//! * **From another format** the output is one Cartesian scan (identity pose): `intensity`,
//!   `red`/`green`/`blue` (all three), `row`, `column`, `return_index`, `return_count` and `time`
//!   become the E57 attributes of those names, with the field's type (integer types keep their
//!   range); every other field becomes an attribute of the `qemd` extension namespace, so nothing
//!   is lost.
//! * **Noise flag** ([`SinkOptions::noise_flag`]): an extension attribute `qemd:noise`, integer
//!   0–1.
//! * **Normals** ([`SinkOptions::normals`]): the E57 surface normals extension's
//!   `nor:normalX`, `nor:normalY`, `nor:normalZ` (single, −1 to 1, in the scan's own frame: the
//!   normal turned by the inverse of the scan's rotation, as its coordinates are), with the
//!   extension (`nor`, `http://www.libe57.org/E57_NOR_surface_normals.txt`) registered, and
//!   `qemd:curvature` (single) and `qemd:structure` (integer 0–5). Attributes already holding
//!   them (`nor:normal*`, or a field named `nx`, `normal_x`, `curvature`, `structure`, …) are
//!   replaced, not repeated.
//!
//! [`SinkOptions::noise_flag`]: super::SinkOptions::noise_flag
//! [`SinkOptions::normals`]: super::SinkOptions::normals

use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use e57::{
    E57Reader, E57Writer, Extension, PointCloud, Quaternion, Record, RecordDataType, RecordName,
    RecordValue, Transform, Translation,
};
use glam::{DQuat, DVec3};

use super::tally::{Tally, check_batch};
use super::{
    AtomicFile, BATCH, Extras, Format, IoError, Meta, NormalField, Sink, SinkOptions, Source,
    SourceInfo,
};
use crate::points::{Endian, FLAG_NOISE, Field, PointBatch, PointNormal, ScalarType, Schema};

/// The signature an E57 file starts with.
pub const SIGNATURE: &[u8; 8] = b"ASTM-E57";

/// Name of the field that holds a point's scan index (files with more than one scan).
pub const SCAN_FIELD: &str = "scan";

/// Namespace of the attributes qemd adds (fields without an E57 meaning, the noise flag).
pub const QEMD_NAMESPACE: &str = "qemd";

/// URL declared for the [`QEMD_NAMESPACE`] extension.
const QEMD_URL: &str = "https://github.com/qem-denoise/qemd/e57";

/// Namespace of the E57 surface normals extension (libE57Format's, CloudCompare's).
pub const NORMALS_NAMESPACE: &str = "nor";

/// URL of the E57 surface normals extension.
const NORMALS_URL: &str = "http://www.libe57.org/E57_NOR_surface_normals.txt";

/// What an E57 source says about its file, for a sink to reproduce it.
#[derive(Debug, Clone)]
pub struct E57Meta {
    guid: String,
    coordinate_metadata: Option<String>,
    extensions: Vec<Extension>,
    scans: Vec<PointCloud>,
}

impl E57Meta {
    /// GUID of the source file.
    pub fn guid(&self) -> &str {
        &self.guid
    }

    /// The scan descriptors (name, pose, prototype, …), in file order.
    pub fn scans(&self) -> &[PointCloud] {
        &self.scans
    }

    /// The file's coordinate metadata (the E57 root's `coordinateMetadata`: WKT or another
    /// description of the CRS), when it has one.
    pub fn coordinate_metadata(&self) -> Option<&str> {
        self.coordinate_metadata.as_deref()
    }
}

/// The field name of an E57 attribute.
fn field_name(name: &RecordName) -> String {
    match name {
        RecordName::CartesianX => "x".into(),
        RecordName::CartesianY => "y".into(),
        RecordName::CartesianZ => "z".into(),
        RecordName::CartesianInvalidState => "cartesian_invalid".into(),
        RecordName::SphericalRange => "range".into(),
        RecordName::SphericalAzimuth => "azimuth".into(),
        RecordName::SphericalElevation => "elevation".into(),
        RecordName::SphericalInvalidState => "spherical_invalid".into(),
        RecordName::Intensity => "intensity".into(),
        RecordName::IsIntensityInvalid => "intensity_invalid".into(),
        RecordName::ColorRed => "red".into(),
        RecordName::ColorGreen => "green".into(),
        RecordName::ColorBlue => "blue".into(),
        RecordName::IsColorInvalid => "color_invalid".into(),
        RecordName::RowIndex => "row".into(),
        RecordName::ColumnIndex => "column".into(),
        RecordName::ReturnCount => "return_count".into(),
        RecordName::ReturnIndex => "return_index".into(),
        RecordName::TimeStamp => "time".into(),
        RecordName::IsTimeStampInvalid => "time_invalid".into(),
        RecordName::Unknown { namespace, name } if namespace.is_empty() => name.clone(),
        // qemd's own attributes are the fields it wrote them from (issue 51: a LAS
        // `classification` came back as `qemd_classification`, and a LAS writer put it in extra
        // bytes), unless the name is one a standard attribute or the scan index reads as.
        RecordName::Unknown { namespace, name }
            if namespace == QEMD_NAMESPACE && !STANDARD_FIELDS.contains(&name.as_str()) =>
        {
            name.clone()
        }
        RecordName::Unknown { namespace, name } => format!("{namespace}_{name}"),
    }
}

/// The field names the standard E57 attributes (and the scan index) read as: a `qemd`
/// attribute of one of these names keeps its namespace prefix, so that it cannot merge with them.
const STANDARD_FIELDS: [&str; 21] = [
    "x",
    "y",
    "z",
    "cartesian_invalid",
    "range",
    "azimuth",
    "elevation",
    "spherical_invalid",
    "intensity",
    "intensity_invalid",
    "red",
    "green",
    "blue",
    "color_invalid",
    "row",
    "column",
    "return_count",
    "return_index",
    "time",
    "time_invalid",
    SCAN_FIELD,
];

/// True for the records that hold coordinates (they become positions, not fields).
fn is_coordinate(name: &RecordName) -> bool {
    matches!(
        name,
        RecordName::CartesianX
            | RecordName::CartesianY
            | RecordName::CartesianZ
            | RecordName::SphericalRange
            | RecordName::SphericalAzimuth
            | RecordName::SphericalElevation
    )
}

/// The field type of an E57 attribute type.
fn scalar_type(dt: &RecordDataType) -> ScalarType {
    match *dt {
        RecordDataType::Single { .. } => ScalarType::F32,
        RecordDataType::Double { .. } | RecordDataType::ScaledInteger { .. } => ScalarType::F64,
        RecordDataType::Integer { min, max } => {
            let fits = |lo: i64, hi: i64| min >= lo && max <= hi;
            if fits(0, 255) {
                ScalarType::U8
            } else if fits(-128, 127) {
                ScalarType::I8
            } else if fits(0, 65_535) {
                ScalarType::U16
            } else if fits(-32_768, 32_767) {
                ScalarType::I16
            } else if fits(0, i64::from(u32::MAX)) {
                ScalarType::U32
            } else if fits(i64::from(i32::MIN), i64::from(i32::MAX)) {
                ScalarType::I32
            } else {
                ScalarType::F64
            }
        }
    }
}

/// The record schema of a file with these scans (see the module docs).
fn schema_of(scans: &[PointCloud]) -> Schema {
    let mut fields: Vec<(String, ScalarType)> = vec![
        ("x".into(), ScalarType::F64),
        ("y".into(), ScalarType::F64),
        ("z".into(), ScalarType::F64),
    ];
    for r in scans.iter().flat_map(|s| &s.prototype) {
        if is_coordinate(&r.name) {
            continue;
        }
        let name = field_name(&r.name);
        let ty = scalar_type(&r.data_type);
        match fields.iter_mut().find(|(n, _)| *n == name) {
            Some((_, t)) if *t != ty => *t = ScalarType::F64,
            Some(_) => {}
            None => fields.push((name, ty)),
        }
    }
    if scans.len() > 1 && !fields.iter().any(|(n, _)| n == SCAN_FIELD) {
        fields.push((SCAN_FIELD.into(), ScalarType::U32));
    }
    let named: Vec<(&str, ScalarType)> = fields.iter().map(|(n, t)| (n.as_str(), *t)).collect();
    Schema::packed(&named, Endian::Little).expect("x, y and z are present by construction")
}

/// Maps an error of the `e57` crate to an [`IoError`] naming `path`.
fn e57_error(path: &Path, e: e57::Error) -> IoError {
    match e {
        e57::Error::Read { .. } | e57::Error::Write { .. } => {
            IoError::invalid(path, format!("E57: {e}"))
        }
        e => IoError::invalid(path, format!("bad E57 data: {e}")),
    }
}

/// Rotation and translation of a scan's pose (identity without one; a source refuses poses
/// that cannot be applied, [`E57Source::new`]).
fn pose(t: Option<&Transform>) -> (DQuat, DVec3) {
    let Some(t) = t else {
        return (DQuat::IDENTITY, DVec3::ZERO);
    };
    let q = &t.rotation;
    let q = DQuat::from_xyzw(q.x, q.y, q.z, q.w);
    let q = if q.length() > 0.0 && q.is_finite() {
        q.normalize()
    } else {
        DQuat::IDENTITY
    };
    let tr = &t.translation;
    (q, DVec3::new(tr.x, tr.y, tr.z))
}

/// How a scan's raw values map to a position and record fields.
struct ScanLayout {
    cartesian: Option<[usize; 3]>,
    cartesian_state: Option<usize>,
    spherical: Option<[usize; 3]>,
    spherical_state: Option<usize>,
    /// `(value index, field index)` of every non-coordinate attribute.
    fields: Vec<(usize, usize)>,
    rotation: DQuat,
    translation: DVec3,
}

impl ScanLayout {
    fn new(pc: &PointCloud, schema: &Schema) -> ScanLayout {
        let find = |n: RecordName| pc.prototype.iter().position(|r| r.name == n);
        let triple = |a, b, c| match (find(a), find(b), find(c)) {
            (Some(a), Some(b), Some(c)) => Some([a, b, c]),
            _ => None,
        };
        let fields = pc
            .prototype
            .iter()
            .enumerate()
            .filter(|(_, r)| !is_coordinate(&r.name))
            .filter_map(|(i, r)| schema.field_index(&field_name(&r.name)).map(|f| (i, f)))
            .collect();
        let (rotation, translation) = pose(pc.transform.as_ref());
        ScanLayout {
            cartesian: triple(
                RecordName::CartesianX,
                RecordName::CartesianY,
                RecordName::CartesianZ,
            ),
            cartesian_state: find(RecordName::CartesianInvalidState),
            spherical: triple(
                RecordName::SphericalRange,
                RecordName::SphericalAzimuth,
                RecordName::SphericalElevation,
            ),
            spherical_state: find(RecordName::SphericalInvalidState),
            fields,
            rotation,
            translation,
        }
    }

    /// The world position of a point (NaN without valid coordinates).
    fn position(&self, proto: &[Record], v: &[RecordValue]) -> Result<DVec3, e57::Error> {
        let get = |i: usize| v[i].to_f64(&proto[i].data_type);
        let state = |i: Option<usize>| -> Result<i64, e57::Error> {
            i.map_or(Ok(0), |i| v[i].to_i64(&proto[i].data_type))
        };
        let local = if let Some([x, y, z]) = self
            .cartesian
            .filter(|_| state(self.cartesian_state).is_ok_and(|s| s == 0))
        {
            DVec3::new(get(x)?, get(y)?, get(z)?)
        } else if let Some([r, a, e]) = self
            .spherical
            .filter(|_| state(self.spherical_state).is_ok_and(|s| s == 0))
        {
            let (r, az, el) = (get(r)?, get(a)?, get(e)?);
            // `libm`: the same Cartesian bits on every platform.
            DVec3::new(
                r * libm::cos(el) * libm::cos(az),
                r * libm::cos(el) * libm::sin(az),
                r * libm::sin(el),
            )
        } else {
            return Ok(DVec3::NAN);
        };
        Ok(self.rotation * local + self.translation)
    }
}

/// One message of the reader thread: a run of points, or the error that ended the reading.
type Chunk = Result<(Vec<DVec3>, Vec<u8>), IoError>;

/// Streaming E57 reader: a thread decodes the scans in file order and hands over runs of points.
pub struct E57Source {
    info: SourceInfo,
    rx: Receiver<Chunk>,
    thread: Option<JoinHandle<()>>,
    pending: (Vec<DVec3>, Vec<u8>),
    /// Points of `pending` already delivered.
    taken: usize,
    read: u64,
    total: u64,
}

impl E57Source {
    /// Opens an E57 file: reads its header and XML (scans, prototypes, poses) and starts decoding
    /// the points.
    ///
    /// # Errors
    /// An unreadable file, a file without the E57 signature, a malformed header or XML section,
    /// a scan without Cartesian or spherical coordinates.
    pub fn open(path: &Path) -> Result<E57Source, IoError> {
        E57Source::new(super::Input::from_path(path)?)
    }

    /// [`E57Source::open`] on any [`super::Input`].
    ///
    /// # Errors
    /// As [`E57Source::open`].
    pub fn new(mut file: super::Input) -> Result<E57Source, IoError> {
        let owned = file.name().to_path_buf();
        let path = owned.as_path();
        let again = file.reopener();
        let mut sig = [0u8; 8];
        let n = file.read(&mut sig).map_err(|e| IoError::io(path, e))?;
        if n < sig.len() || &sig != SIGNATURE {
            return Err(IoError::header(
                path,
                "not an E57 file (no `ASTM-E57` signature)",
            ));
        }
        file.rewind().map_err(|e| IoError::io(path, e))?;
        let reader = E57Reader::new(BufReader::new(file))
            .map_err(|e| IoError::header(path, format!("E57: {e}")))?;
        let scans = reader.pointclouds();
        for (k, s) in scans.iter().enumerate() {
            if !s.has_cartesian() && !s.has_spherical() {
                return Err(IoError::Unsupported {
                    path: path.to_path_buf(),
                    detail: format!("E57 scan {k} has neither Cartesian nor spherical coordinates"),
                });
            }
            // A pose that cannot be applied is refused, not read as no rotation (issue 51).
            if let Some(t) = &s.transform {
                let q = &t.rotation;
                let q = DQuat::from_xyzw(q.x, q.y, q.z, q.w);
                let tr = &t.translation;
                let bad = if !q.is_finite() {
                    Some("a non-finite rotation quaternion")
                } else if q.length() < 1e-6 {
                    Some("a zero rotation quaternion")
                } else if ![tr.x, tr.y, tr.z].iter().all(|v| v.is_finite()) {
                    Some("a non-finite translation")
                } else {
                    None
                };
                if let Some(bad) = bad {
                    return Err(IoError::invalid(
                        path,
                        format!(
                            "E57 scan {k}{}: its pose has {bad}",
                            s.name
                                .as_deref()
                                .map(|n| format!(" (`{n}`)"))
                                .unwrap_or_default()
                        ),
                    ));
                }
            }
        }
        let meta = E57Meta {
            guid: reader.guid().to_string(),
            coordinate_metadata: reader.coordinate_metadata().map(str::to_string),
            extensions: reader.extensions(),
            scans,
        };
        drop(reader);
        let schema = schema_of(&meta.scans);
        let total = meta.scans.iter().map(|s| s.records).sum();
        let (tx, rx) = sync_channel(2);
        let thread = {
            let owned = path.to_path_buf();
            let schema = schema.clone();
            let scans = meta.scans.clone();
            std::thread::Builder::new()
                .name("e57-reader".into())
                .spawn(move || {
                    if let Err(e) = decode(&owned, &again, &schema, &scans, &tx) {
                        let _ = tx.send(Err(e));
                    }
                })
                .map_err(|e| IoError::io(path, e))?
        };
        Ok(E57Source {
            info: SourceInfo {
                path: path.to_path_buf(),
                format: Format::E57,
                schema,
                len: Some(total),
                faces: None,
                meta: Meta::E57(meta),
            },
            rx,
            thread: Some(thread),
            pending: (Vec::new(), Vec::new()),
            taken: 0,
            read: 0,
            total,
        })
    }
}

/// The reader thread: decodes every scan and sends its points in runs of [`BATCH`].
fn decode(
    path: &Path,
    again: &super::reader::Reopener,
    schema: &Schema,
    scans: &[PointCloud],
    tx: &SyncSender<Chunk>,
) -> Result<(), IoError> {
    let file = again.open()?;
    let mut reader = E57Reader::new(BufReader::new(file)).map_err(|e| e57_error(path, e))?;
    let scan_field = (scans.len() > 1)
        .then(|| schema.field_index(SCAN_FIELD))
        .flatten();
    let rl = schema.record_len;
    for (k, pc) in scans.iter().enumerate() {
        let layout = ScanLayout::new(pc, schema);
        let proto = &pc.prototype;
        let mut positions = Vec::with_capacity(BATCH);
        let mut records = Vec::with_capacity(BATCH * rl);
        let mut read = 0u64;
        for values in reader.pointcloud_raw(pc).map_err(|e| e57_error(path, e))? {
            let values = values.map_err(|e| e57_error(path, e))?;
            read += 1;
            positions.push(
                layout
                    .position(proto, &values)
                    .map_err(|e| e57_error(path, e))?,
            );
            let at = records.len();
            records.resize(at + rl, 0);
            let rec = &mut records[at..];
            for &(vi, fi) in &layout.fields {
                let v = values[vi]
                    .to_f64(&proto[vi].data_type)
                    .map_err(|e| e57_error(path, e))?;
                schema.set_f64(rec, fi, v);
            }
            if let Some(fi) = scan_field {
                schema.set_f64(rec, fi, k as f64);
            }
            if positions.len() == BATCH {
                let run = (std::mem::take(&mut positions), std::mem::take(&mut records));
                if tx.send(Ok(run)).is_err() {
                    return Ok(()); // the source was dropped
                }
                positions.reserve(BATCH);
                records.reserve(BATCH * rl);
            }
        }
        if read != pc.records {
            return Err(IoError::truncated(
                path,
                format!(
                    "E57 scan {k} declares {} points, its data holds {read}",
                    pc.records
                ),
            ));
        }
        if !positions.is_empty() && tx.send(Ok((positions, records))).is_err() {
            return Ok(());
        }
    }
    Ok(())
}

impl Source for E57Source {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        let rl = self.info.schema.record_len;
        batch.clear(self.read);
        batch.record_len = rl;
        while batch.len() < max && self.read < self.total {
            if self.taken == self.pending.0.len() {
                match self.rx.recv() {
                    Ok(Ok(run)) => {
                        self.pending = run;
                        self.taken = 0;
                    }
                    Ok(Err(e)) => return Err(e),
                    Err(_) => {
                        return Err(IoError::truncated(
                            &self.info.path,
                            format!("the E57 points end after {} of {}", self.read, self.total),
                        ));
                    }
                }
                continue;
            }
            let n = (self.pending.0.len() - self.taken).min(max - batch.len());
            let (a, b) = (self.taken, self.taken + n);
            batch.positions.extend_from_slice(&self.pending.0[a..b]);
            batch
                .records
                .extend_from_slice(&self.pending.1[a * rl..b * rl]);
            self.taken = b;
            self.read += n as u64;
        }
        Ok(batch.len())
    }

    fn finish(mut self: Box<Self>) -> Result<Extras, IoError> {
        drop(std::mem::replace(&mut self.rx, sync_channel(0).1));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        Ok(Extras::default())
    }
}

/// How the writer thread turns one record into E57 values.
#[derive(Clone)]
enum Value {
    /// A coordinate record: x, y or z (`0..3`), or range, azimuth, elevation (`3..6`).
    Coordinate(usize),
    /// An invalid state: 0 for a finite position, else 2.
    State,
    /// A field of the record, converted to the record's type.
    Field(usize),
    /// The noise flag.
    Noise,
    /// A written normal's value (the normal in the scan's frame).
    Normal(NormalField),
    /// A record the source's scan has but the cloud has no field for: 0.
    Zero,
}

/// What the writer thread writes for one scan.
struct ScanPlan {
    /// Descriptor of the source scan (metadata, pose), if any.
    source: Option<PointCloud>,
    prototype: Vec<Record>,
    values: Vec<Value>,
    rotation: DQuat,
    translation: DVec3,
}

/// A message to the writer thread.
enum Msg {
    /// Points of the current scan: positions, records, flags, normals.
    Points(usize, Vec<DVec3>, Vec<u8>, Vec<u8>, Vec<PointNormal>),
}

/// The E57 record a written normal value goes to.
fn normal_record(f: NormalField) -> Record {
    let unit = RecordDataType::Single {
        min: Some(-1.0),
        max: Some(1.0),
    };
    let (namespace, name, data_type) = match f {
        NormalField::X => (NORMALS_NAMESPACE, "normalX", unit),
        NormalField::Y => (NORMALS_NAMESPACE, "normalY", unit),
        NormalField::Z => (NORMALS_NAMESPACE, "normalZ", unit),
        NormalField::Curvature => (
            QEMD_NAMESPACE,
            "curvature",
            RecordDataType::Single {
                min: None,
                max: None,
            },
        ),
        NormalField::Structure => (
            QEMD_NAMESPACE,
            "structure",
            RecordDataType::Integer { min: 0, max: 5 },
        ),
    };
    Record {
        name: RecordName::Unknown {
            namespace: namespace.into(),
            name: name.into(),
        },
        data_type,
    }
}

/// Streaming E57 writer.
pub struct E57Sink {
    target: PathBuf,
    like: Schema,
    tally: Tally,
    scan_field: Option<usize>,
    scans: usize,
    /// Scan of the last point written.
    current: usize,
    tx: Option<SyncSender<Msg>>,
    thread: Option<JoinHandle<Result<(), IoError>>>,
    file: Option<AtomicFile>,
    failed: bool,
}

/// The placeholder GUID of scan `k` (`None`: the file's), replaced in the XML by [`guid_from`].
fn placeholder(k: Option<usize>) -> String {
    match k {
        Some(k) => format!("{{qemd-scan-guid-{k}}}"),
        None => "{qemd-file-guid}".to_string(),
    }
}

/// A GUID (braced, UUID form) derived from the digest of everything written and a label: the same
/// output gives the same GUID (output stays deterministic), different outputs different ones.
fn guid_from(digest: &[u8], label: &str) -> String {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    h.update(digest);
    h.update(label.as_bytes());
    let bytes: [u8; 16] = h.finalize()[..16].try_into().expect("16 bytes");
    format!(
        "{{{}}}",
        uuid::Builder::from_random_bytes(bytes).into_uuid()
    )
}

/// An E57 record for field `f` of a non-E57 schema, by name and type.
fn record_for(f: &Field) -> Record {
    let name = match f.name.as_str() {
        "intensity" => RecordName::Intensity,
        "red" => RecordName::ColorRed,
        "green" => RecordName::ColorGreen,
        "blue" => RecordName::ColorBlue,
        "row" => RecordName::RowIndex,
        "column" => RecordName::ColumnIndex,
        "return_index" => RecordName::ReturnIndex,
        "return_count" => RecordName::ReturnCount,
        "time" => RecordName::TimeStamp,
        other => RecordName::Unknown {
            namespace: QEMD_NAMESPACE.into(),
            name: xml_name(other),
        },
    };
    Record {
        name,
        data_type: data_type(f.ty),
    }
}

/// An XML element name for a field name: letters, digits and `_`, not starting with a digit.
fn xml_name(name: &str) -> String {
    let mut s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if !s.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
        s.insert(0, '_');
    }
    s
}

/// The E57 type that holds a field of type `ty`.
fn data_type(ty: ScalarType) -> RecordDataType {
    let int = |min: i64, max: i64| RecordDataType::Integer { min, max };
    match ty {
        ScalarType::I8 => int(-128, 127),
        ScalarType::U8 => int(0, 255),
        ScalarType::I16 => int(-32_768, 32_767),
        ScalarType::U16 => int(0, 65_535),
        ScalarType::I32 => int(i64::from(i32::MIN), i64::from(i32::MAX)),
        ScalarType::U32 => int(0, i64::from(u32::MAX)),
        ScalarType::I64 => int(i64::MIN, i64::MAX),
        ScalarType::U64 | ScalarType::F64 => RecordDataType::Double {
            min: None,
            max: None,
        },
        ScalarType::F32 => RecordDataType::Single {
            min: None,
            max: None,
        },
    }
}

const DOUBLE: RecordDataType = RecordDataType::Double {
    min: None,
    max: None,
};

impl E57Sink {
    /// Creates a sink that writes `count` points laid out like `like` (see the module docs).
    ///
    /// # Errors
    /// The directory is not writable.
    pub fn create(
        path: &Path,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<E57Sink, IoError> {
        let schema = &like.schema;
        let noise = options.noise_flag;
        let (mut plans, extensions, coordinate_metadata) = match &like.meta {
            Meta::E57(m) if schema_of(&m.scans) == *schema => (
                m.scans
                    .iter()
                    .map(|pc| Self::like_scan(pc, schema, noise))
                    .collect(),
                m.extensions.clone(),
                m.coordinate_metadata.clone(),
            ),
            _ => (vec![Self::fresh(schema, noise)], Vec::new(), None),
        };
        if options.normals {
            for p in &mut plans {
                Self::add_normals(p, schema);
            }
        }
        let mut extensions = extensions;
        let uses_normals = plans.iter().any(|p: &ScanPlan| {
            p.prototype.iter().any(
                |r| matches!(&r.name, RecordName::Unknown { namespace, .. } if namespace == NORMALS_NAMESPACE),
            )
        });
        if uses_normals && !extensions.iter().any(|e| e.namespace == NORMALS_NAMESPACE) {
            extensions.push(Extension::new(NORMALS_NAMESPACE, NORMALS_URL));
        }
        let uses_qemd = plans.iter().any(|p: &ScanPlan| {
            p.prototype.iter().any(
                |r| matches!(&r.name, RecordName::Unknown { namespace, .. } if namespace == QEMD_NAMESPACE),
            )
        });
        if uses_qemd && !extensions.iter().any(|e| e.namespace == QEMD_NAMESPACE) {
            extensions.push(Extension::new(QEMD_NAMESPACE, QEMD_URL));
        }
        let scan_field = match &like.meta {
            Meta::E57(m) if plans.len() > 1 && schema_of(&m.scans) == *schema => {
                schema.field_index(SCAN_FIELD)
            }
            _ => None,
        };
        if super::output::is_stream_output(path) {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: "E57 output needs a regular file (its pages are read back and patched)"
                    .into(),
            });
        }
        let mut file = AtomicFile::create(path)?;
        let handle = file.try_clone_file().map_err(|e| file.err(e))?;
        let (tx, rx) = sync_channel::<Msg>(2);
        let scans = plans.len();
        let thread = {
            let owned = path.to_path_buf();
            let schema = schema.clone();
            std::thread::Builder::new()
                .name("e57-writer".into())
                .spawn(move || {
                    encode(
                        &owned,
                        handle,
                        &schema,
                        &plans,
                        &extensions,
                        coordinate_metadata,
                        &rx,
                    )
                })
                .map_err(|e| IoError::io(path, e))?
        };
        Ok(E57Sink {
            target: path.to_path_buf(),
            like: schema.clone(),
            tally: Tally::new(count),
            scan_field,
            scans,
            current: 0,
            tx: Some(tx),
            thread: Some(thread),
            file: Some(file),
            failed: false,
        })
    }

    /// The plan of a scan of an E57 source.
    fn like_scan(pc: &PointCloud, schema: &Schema, noise: bool) -> ScanPlan {
        let spherical_only = !pc.has_cartesian();
        let mut prototype = Vec::new();
        let mut values = Vec::new();
        let coords: &[(RecordName, usize)] = if spherical_only {
            &[
                (RecordName::SphericalRange, 3),
                (RecordName::SphericalAzimuth, 4),
                (RecordName::SphericalElevation, 5),
            ]
        } else {
            &[
                (RecordName::CartesianX, 0),
                (RecordName::CartesianY, 1),
                (RecordName::CartesianZ, 2),
            ]
        };
        for (name, k) in coords {
            prototype.push(Record {
                name: name.clone(),
                data_type: DOUBLE,
            });
            values.push(Value::Coordinate(*k));
        }
        let state = if spherical_only {
            RecordName::SphericalInvalidState
        } else {
            RecordName::CartesianInvalidState
        };
        for r in &pc.prototype {
            if is_coordinate(&r.name) {
                continue;
            }
            if r.name == state {
                prototype.push(Record {
                    name: state.clone(),
                    data_type: RecordDataType::Integer { min: 0, max: 2 },
                });
                values.push(Value::State);
                continue;
            }
            if matches!(
                r.name,
                RecordName::CartesianInvalidState | RecordName::SphericalInvalidState
            ) {
                continue; // the state of coordinates that are not written
            }
            prototype.push(r.clone());
            values.push(match schema.field_index(&field_name(&r.name)) {
                Some(f) => Value::Field(f),
                None => Value::Zero,
            });
        }
        if noise {
            Self::add_noise(&mut prototype, &mut values);
        }
        let (rotation, translation) = pose(pc.transform.as_ref());
        ScanPlan {
            source: Some(pc.clone()),
            prototype,
            values,
            rotation,
            translation,
        }
    }

    /// The plan for the single scan of a non-E57 source.
    fn fresh(schema: &Schema, noise: bool) -> ScanPlan {
        let mut prototype: Vec<Record> = [
            RecordName::CartesianX,
            RecordName::CartesianY,
            RecordName::CartesianZ,
        ]
        .into_iter()
        .map(|name| Record {
            name,
            data_type: DOUBLE,
        })
        .collect();
        let mut values = vec![
            Value::Coordinate(0),
            Value::Coordinate(1),
            Value::Coordinate(2),
        ];
        let has_colour = ["red", "green", "blue"]
            .iter()
            .all(|n| schema.field_index(n).is_some());
        let mut used = Vec::<RecordName>::new();
        for (i, f) in schema.fields.iter().enumerate() {
            if schema.xyz.contains(&i) {
                continue;
            }
            let mut r = record_for(f);
            let colour = matches!(
                r.name,
                RecordName::ColorRed | RecordName::ColorGreen | RecordName::ColorBlue
            );
            let index = matches!(r.name, RecordName::RowIndex | RecordName::ColumnIndex)
                || matches!(r.name, RecordName::ReturnIndex | RecordName::ReturnCount);
            // Colours need all three channels, indices an integer type; a record name may
            // appear once. Anything else goes to the qemd namespace.
            if (colour && !has_colour)
                || (index && !matches!(r.data_type, RecordDataType::Integer { .. }))
                || used.contains(&r.name)
            {
                r.name = RecordName::Unknown {
                    namespace: QEMD_NAMESPACE.into(),
                    name: xml_name(&f.name),
                };
            }
            if used.contains(&r.name) {
                continue;
            }
            used.push(r.name.clone());
            prototype.push(r);
            values.push(Value::Field(i));
        }
        // ReturnIndex needs ReturnCount and vice versa.
        let has = |p: &[Record], n: RecordName| p.iter().any(|r| r.name == n);
        if has(&prototype, RecordName::ReturnIndex) != has(&prototype, RecordName::ReturnCount) {
            for r in &mut prototype {
                if matches!(r.name, RecordName::ReturnIndex | RecordName::ReturnCount) {
                    r.name = RecordName::Unknown {
                        namespace: QEMD_NAMESPACE.into(),
                        name: field_name(&r.name),
                    };
                }
            }
        }
        prototype.push(Record {
            name: RecordName::CartesianInvalidState,
            data_type: RecordDataType::Integer { min: 0, max: 2 },
        });
        values.push(Value::State);
        if noise {
            Self::add_noise(&mut prototype, &mut values);
        }
        ScanPlan {
            source: None,
            prototype,
            values,
            rotation: DQuat::IDENTITY,
            translation: DVec3::ZERO,
        }
    }

    /// Appends the written normals' records to `plan` ([`normal_record`]), after removing the
    /// records that hold them already (the same record names, or fields of `schema` named as a
    /// normal value is, [`NormalField::aliases`]): one set, never two.
    fn add_normals(plan: &mut ScanPlan, schema: &Schema) {
        let targets: Vec<Record> = NormalField::ALL.iter().map(|&f| normal_record(f)).collect();
        let held = |i: &usize| NormalField::ALL.iter().any(|f| f.find(schema) == Some(*i));
        let (prototype, values): (Vec<Record>, Vec<Value>) = plan
            .prototype
            .drain(..)
            .zip(plan.values.drain(..))
            .filter(|(r, v)| {
                !targets.iter().any(|t| t.name == r.name)
                    && !matches!(v, Value::Field(i) if held(i))
            })
            .unzip();
        plan.prototype = prototype;
        plan.values = values;
        for (f, r) in NormalField::ALL.into_iter().zip(targets) {
            plan.prototype.push(r);
            plan.values.push(Value::Normal(f));
        }
    }

    fn add_noise(prototype: &mut Vec<Record>, values: &mut Vec<Value>) {
        prototype.retain(|r| {
            !matches!(&r.name, RecordName::Unknown { namespace, name }
                if namespace == QEMD_NAMESPACE && name == super::NOISE_FIELD)
        });
        values.truncate(prototype.len());
        prototype.push(Record {
            name: RecordName::Unknown {
                namespace: QEMD_NAMESPACE.into(),
                name: super::NOISE_FIELD.into(),
            },
            data_type: RecordDataType::Integer { min: 0, max: 1 },
        });
        values.push(Value::Noise);
    }

    /// The writer thread's error, once it has ended.
    fn thread_error(&mut self) -> IoError {
        self.failed = true;
        self.tx = None;
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(Err(e))) => e,
            _ => IoError::invalid(&self.target, "the E57 writer stopped"),
        }
    }
}

/// Converts `v` to a value of record type `dt` (integers round and clamp to the declared range).
fn to_value(v: f64, dt: &RecordDataType) -> RecordValue {
    match *dt {
        RecordDataType::Single { .. } => RecordValue::Single(v as f32),
        RecordDataType::Double { .. } => RecordValue::Double(v),
        RecordDataType::ScaledInteger {
            min,
            max,
            scale,
            offset,
        } => RecordValue::ScaledInteger((((v - offset) / scale).round() as i64).clamp(min, max)),
        RecordDataType::Integer { min, max } => {
            RecordValue::Integer((v.round() as i64).clamp(min, max))
        }
    }
}

/// The writer thread: writes the scans in order as their points arrive, then the XML.
fn encode(
    path: &Path,
    file: File,
    schema: &Schema,
    plans: &[ScanPlan],
    extensions: &[Extension],
    coordinate_metadata: Option<String>,
    rx: &Receiver<Msg>,
) -> Result<(), IoError> {
    let err = |e| e57_error(path, e);
    use sha2::Digest;
    let mut digest = sha2::Sha256::new();
    let mut w = E57Writer::new(file, &placeholder(None)).map_err(err)?;
    w.set_coordinate_metadata(coordinate_metadata);
    for e in extensions {
        w.register_extension(e.clone()).map_err(err)?;
    }
    let mut next = rx.recv().ok();
    for (k, plan) in plans.iter().enumerate() {
        let mut pc = w
            .add_pointcloud(&placeholder(Some(k)), plan.prototype.clone())
            .map_err(err)?;
        if let Some(s) = &plan.source {
            pc.set_name(s.name.clone());
            pc.set_description(s.description.clone());
            pc.set_transform(s.transform.clone());
            pc.set_original_guids(s.guid.clone().map(|g| vec![g]));
            pc.set_acquisition_start(s.acquisition_start.clone());
            pc.set_acquisition_end(s.acquisition_end.clone());
            pc.set_sensor_vendor(s.sensor_vendor.clone());
            pc.set_sensor_model(s.sensor_model.clone());
            pc.set_sensor_serial(s.sensor_serial.clone());
            pc.set_sensor_hw_version(s.sensor_hw_version.clone());
            pc.set_sensor_sw_version(s.sensor_sw_version.clone());
            pc.set_sensor_fw_version(s.sensor_fw_version.clone());
            pc.set_temperature(s.temperature);
            pc.set_humidity(s.humidity);
            pc.set_atmospheric_pressure(s.atmospheric_pressure);
            if s.intensity_limits.is_some() {
                pc.set_intensity_limits(s.intensity_limits.clone());
            }
            if s.color_limits.is_some() {
                pc.set_color_limits(s.color_limits.clone());
            }
        } else {
            pc.set_transform(Some(Transform {
                rotation: Quaternion::default(),
                translation: Translation::default(),
            }));
        }
        let inverse = plan.rotation.inverse();
        while let Some(Msg::Points(scan, positions, records, flags, normals)) = &next {
            if *scan != k {
                break;
            }
            let rl = schema.record_len;
            digest.update(k.to_le_bytes());
            digest.update(bytemuck::cast_slice::<DVec3, u8>(positions));
            digest.update(records);
            digest.update(flags);
            for n in normals {
                for v in n.normal.into_iter().chain([n.curvature]) {
                    digest.update(v.to_le_bytes());
                }
                digest.update([n.structure]);
            }
            for (i, p) in positions.iter().enumerate() {
                let rec = &records[i * rl..(i + 1) * rl];
                let local = inverse * (*p - plan.translation);
                let written = normals.get(i).copied().unwrap_or(PointNormal::NONE);
                // The normal in the scan's frame, as its coordinates are stored.
                let turned = inverse * DVec3::from_array(written.normal.map(f64::from));
                let turned = PointNormal {
                    // Rounding may leave a turned unit component a hair past ±1, the range
                    // the record declares.
                    normal: turned.to_array().map(|v| (v as f32).clamp(-1.0, 1.0)),
                    ..written
                };
                let valid = local.is_finite();
                let sph = || {
                    let r = local.length();
                    let az = libm::atan2(local.y, local.x);
                    let el = if r > 0.0 {
                        libm::asin(local.z / r)
                    } else {
                        0.0
                    };
                    [r, az, el]
                };
                let values = plan
                    .values
                    .iter()
                    .zip(&plan.prototype)
                    .map(|(v, r)| match v {
                        Value::Coordinate(c @ 0..3) => RecordValue::Double(local[*c]),
                        Value::Coordinate(c) => RecordValue::Double(sph()[*c - 3]),
                        Value::State => RecordValue::Integer(if valid { 0 } else { 2 }),
                        Value::Field(f) => to_value(schema.get_f64(rec, *f), &r.data_type),
                        Value::Noise => RecordValue::Integer(i64::from(
                            flags.get(i).is_some_and(|b| b & FLAG_NOISE != 0),
                        )),
                        Value::Normal(f) => to_value(f.value(&turned), &r.data_type),
                        Value::Zero => to_value(0.0, &r.data_type),
                    })
                    .collect();
                pc.add_point(values).map_err(err)?;
            }
            next = rx.recv().ok();
        }
        pc.finalize().map_err(err)?;
    }
    if next.is_some() {
        return Err(IoError::invalid(
            path,
            "points of an E57 scan came after those of a later scan",
        ));
    }
    let digest = digest.finalize();
    let scans = plans.len();
    w.finalize_customized_xml(|xml| {
        let mut xml = xml.replace(&placeholder(None), &guid_from(&digest, "file"));
        for k in 0..scans {
            xml = xml.replace(
                &placeholder(Some(k)),
                &guid_from(&digest, &format!("scan {k}")),
            );
        }
        Ok(xml)
    })
    .map_err(err)?;
    Ok(())
}

impl Sink for E57Sink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        if self.failed {
            return Err(IoError::invalid(&self.target, "an earlier write failed"));
        }
        check_batch(&self.target, &self.like, batch)?;
        self.tally.add(&self.target, batch.len())?;
        // Split the batch where the scan changes; each run goes to the writer thread.
        let mut start = 0;
        while start < batch.len() {
            let scan_of = |i: usize| {
                self.scan_field
                    .map_or(0, |f| self.like.get_f64(batch.record(i), f) as usize)
            };
            let scan = scan_of(start);
            if scan < self.current || scan >= self.scans {
                self.failed = true;
                return Err(IoError::invalid(
                    &self.target,
                    format!(
                        "point {}: scan {scan} after scan {} (E57 output needs each scan's points \
                         together, in scan order, and scan indices below {})",
                        batch.start + start as u64,
                        self.current,
                        self.scans
                    ),
                ));
            }
            self.current = scan;
            let mut end = start + 1;
            while end < batch.len() && scan_of(end) == scan {
                end += 1;
            }
            let rl = batch.record_len;
            let flags = if batch.flags.is_empty() {
                Vec::new()
            } else {
                batch.flags[start..end].to_vec()
            };
            let normals = if batch.normals.is_empty() {
                Vec::new()
            } else {
                batch.normals[start..end].to_vec()
            };
            let msg = Msg::Points(
                scan,
                batch.positions[start..end].to_vec(),
                batch.records[start * rl..end * rl].to_vec(),
                flags,
                normals,
            );
            let sent = self.tx.as_ref().is_some_and(|tx| tx.send(msg).is_ok());
            if !sent {
                return Err(self.thread_error());
            }
            start = end;
        }
        Ok(())
    }

    fn finish(mut self: Box<Self>, _extras: &Extras) -> Result<(), IoError> {
        if self.failed {
            return Err(IoError::invalid(&self.target, "an earlier write failed"));
        }
        self.tally.check(&self.target)?;
        self.tx = None;
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(Ok(()))) => {}
            Some(Ok(Err(e))) => return Err(e),
            _ => return Err(IoError::invalid(&self.target, "the E57 writer stopped")),
        }
        self.file.take().expect("finish runs once").commit()
    }
}

impl Drop for E57Sink {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
