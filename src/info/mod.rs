//! What a file holds, as `pdal info` and `lasinfo` tell it (`qemd info FILE [--json]`).
//!
//! # Brief overview
//!
//! [`inspect`] opens any readable file (the format from `--input-format`, the extension, or the
//! content), reads its header, then streams every point once in bounded memory:
//!
//! ```text
//!  header      format and its own details (LAS version, point format, VLRs, PLY encoding,
//!              PCD DATA kind and viewpoint, E57 scans), the record schema, declared counts,
//!              LAS scale and offset, the CRS (LAS WKT or GeoTIFF keys, E57 coordinateMetadata)
//!  points      count, non-finite count, bounds of the finite points, classes present (LAS
//!              classification, or a `class`/`label` field) with their counts
//!  sample      up to SAMPLE finite points, drawn uniformly (a seeded reservoir, so the same
//!              file always gives the same figures): the median nearest-neighbour spacing
//!  extras      the faces a mesh holds (counted after the points, as OBJ states none before)
//! ```
//!
//! The spacing is exact (every point) for clouds of at most [`SAMPLE`] points. For larger ones it
//! is the sample's median spacing scaled by √(sample / points), the spacing a surface sampled at
//! the file's density has (LiDAR and photogrammetry sample surfaces); `spacing.sampled` says how
//! many points it came from. Nothing is written and the file is not modified.

mod show;

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use glam::DVec3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use thiserror::Error;

use crate::io::classes::{ClassField, las_class_name};
use crate::io::crs::Crs;
use crate::io::{self, Format, IoError, Meta, SourceInfo};
use crate::neighbours::{KnnIndex, NeighboursError, median_spacing};
use crate::points::{PointBatch, ScalarType};

/// Points the spacing is measured on at most.
pub const SAMPLE: usize = 1 << 18;

/// Errors of `qemd info`.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum InfoError {
    /// The file could not be read.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The spacing could not be measured.
    #[error("{path}: spacing: {source}", path = .path.display())]
    Spacing {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        source: NeighboursError,
    },
}

/// One field of the record schema.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct FieldInfo {
    /// Its name as the file spells it.
    pub name: String,
    /// Its stored type (`u8`, `i32`, `f64`, …).
    #[serde(rename = "type")]
    pub ty: &'static str,
}

/// The bounds of the finite points.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Bounds {
    /// Smallest x, y, z.
    pub min: [f64; 3],
    /// Largest x, y, z.
    pub max: [f64; 3],
}

/// The median nearest-neighbour spacing.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Spacing {
    /// The spacing, in the file's units.
    pub median: f64,
    /// Points of the sample it was measured on, when the cloud is larger (`None`: every point).
    pub sampled: Option<u64>,
}

/// The classes present and their point counts.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Classes {
    /// The field they come from (`classification`, `class`, `label`).
    pub field: String,
    /// Points per class code, ascending.
    pub counts: BTreeMap<u32, u64>,
    /// ASPRS names of the codes (LAS only).
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub names: BTreeMap<u32, &'static str>,
}

/// What a file holds.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Info {
    /// The file as named.
    pub path: PathBuf,
    /// Its format ([`Format::name`]).
    pub format: String,
    /// The format's own description (`LAS 1.4, point format 6, LAZ`, `PLY binary_little_endian`).
    pub kind: String,
    /// Points read.
    pub points: u64,
    /// Points the header declares, when it does.
    pub declared_points: Option<u64>,
    /// Faces, for a mesh.
    pub faces: Option<u64>,
    /// Points with a non-finite coordinate.
    pub non_finite: u64,
    /// Bytes per record.
    pub record_length: usize,
    /// The record schema, in record order.
    pub fields: Vec<FieldInfo>,
    /// The fields beyond the format's standard record: LAS extra bytes, or for other formats
    /// every field but x, y and z.
    pub extra_fields: Vec<String>,
    /// Bounds of the finite points (`None` without any).
    pub bounds: Option<Bounds>,
    /// LAS scale factors of x, y, z.
    pub scale: Option<[f64; 3]>,
    /// LAS offsets of x, y, z.
    pub offset: Option<[f64; 3]>,
    /// The coordinate reference system the file declares.
    pub crs: Option<Crs>,
    /// The median nearest-neighbour spacing (`None` with fewer than two distinct points).
    pub spacing: Option<Spacing>,
    /// The classes present (`None` without a class field).
    pub classes: Option<Classes>,
    /// The format's own header fields.
    pub header: Value,
    /// Decimals the stored coordinates have (LAS: the scale's), or `None` for float storage.
    #[serde(skip)]
    decimals: Option<usize>,
    /// The coordinates are stored as `f32` (shown as the `f32` they are).
    #[serde(skip)]
    float32: bool,
}

/// Describes the file at `path` (`-` for standard input, spooled to `temp_dir`), read as `format`
/// (`None`: from the extension, else from the content).
///
/// # Errors
/// A file that cannot be read as its format, with the one-line error naming it.
pub fn inspect(
    path: &Path,
    format: Option<Format>,
    temp_dir: Option<&Path>,
) -> Result<Info, InfoError> {
    let input = io::InputFile::open(path, format, temp_dir)?;
    let shown = input.shown().to_path_buf();
    let format = match input.format() {
        Some(f) => f,
        None => Format::from_path(input.path()).or_else(|e| sniffed(input.path()).ok_or(e))?,
    };
    let mut src =
        io::open(input.path(), Some(format)).map_err(|e| e.with_path(input.path(), &shown))?;
    let info = src.info().clone();
    let classes = ClassField::of(&info.schema, format.is_las());
    let mut tally = Tally::new(classes);
    let mut batch = PointBatch::with_capacity(info.schema.record_len, io::BATCH);
    loop {
        let n = src
            .read_batch(&mut batch, io::BATCH)
            .map_err(|e| e.with_path(input.path(), &shown))?;
        if n == 0 {
            break;
        }
        tally.add(&info, &batch);
    }
    let extras = src
        .finish()
        .map_err(|e| e.with_path(input.path(), &shown))?;
    let spacing = tally.spacing().map_err(|source| InfoError::Spacing {
        path: shown.clone(),
        source,
    })?;
    let faces = extras.faces.as_ref().map(|f| f.len() as u64).or(info.faces);
    let evlrs: Vec<&io::las::LasVlr> = match &extras.trailer {
        io::Trailer::Las(t) => t.evlrs().collect(),
        _ => Vec::new(),
    };
    Ok(Info {
        path: shown,
        format: format.name().to_string(),
        kind: kind(&info),
        points: tally.points,
        declared_points: info.len,
        faces,
        non_finite: tally.non_finite,
        record_length: info.schema.record_len,
        fields: info
            .schema
            .fields
            .iter()
            .map(|f| FieldInfo {
                name: f.name.clone(),
                ty: type_name(f.ty),
            })
            .collect(),
        extra_fields: extra_fields(&info),
        bounds: tally.bounds(),
        scale: las_meta(&info).map(|m| m.scale().to_array()),
        offset: las_meta(&info).map(|m| m.offset().to_array()),
        crs: Crs::of_file(&info.meta, Some(&extras.trailer)),
        spacing,
        classes: tally.classes(&info),
        header: header(&info, &evlrs),
        decimals: las_meta(&info).map(|m| {
            let s = m.scale().min_element();
            if s > 0.0 && s < 1.0 {
                (-s.log10()).ceil() as usize
            } else {
                0
            }
        }),
        float32: info
            .schema
            .xyz
            .iter()
            .all(|&i| info.schema.fields[i].ty == ScalarType::F32),
    })
}

/// The format content starting the file at `path` has, when it can be told.
fn sniffed(path: &Path) -> Option<Format> {
    let mut head = Vec::with_capacity(io::sniff::SNIFF_LEN);
    std::fs::File::open(path)
        .and_then(|f| f.take(io::sniff::SNIFF_LEN as u64).read_to_end(&mut head))
        .ok()?;
    io::sniff::sniff(&head)
}

/// What the points add up to while they stream by.
struct Tally {
    points: u64,
    non_finite: u64,
    min: DVec3,
    max: DVec3,
    classes: Option<ClassField>,
    counts: BTreeMap<u32, u64>,
    /// Finite points seen, for the reservoir.
    finite: u64,
    sample: Vec<DVec3>,
    rng: ChaCha8Rng,
}

impl Tally {
    fn new(classes: Option<ClassField>) -> Tally {
        Tally {
            points: 0,
            non_finite: 0,
            min: DVec3::splat(f64::INFINITY),
            max: DVec3::splat(f64::NEG_INFINITY),
            classes,
            counts: BTreeMap::new(),
            finite: 0,
            sample: Vec::new(),
            rng: ChaCha8Rng::seed_from_u64(0),
        }
    }

    fn add(&mut self, info: &SourceInfo, batch: &PointBatch) {
        for (i, &p) in batch.positions.iter().enumerate() {
            self.points += 1;
            if let Some(c) = &self.classes {
                *self
                    .counts
                    .entry(c.code(&info.schema, batch.record(i)))
                    .or_default() += 1;
            }
            if !p.is_finite() {
                self.non_finite += 1;
                continue;
            }
            self.min = self.min.min(p);
            self.max = self.max.max(p);
            // Reservoir sampling (Algorithm R): every finite point is kept with equal chance.
            self.finite += 1;
            if self.sample.len() < SAMPLE {
                self.sample.push(p);
            } else {
                let j = self.rng.random_range(0..self.finite);
                if let Ok(j) = usize::try_from(j)
                    && j < SAMPLE
                {
                    self.sample[j] = p;
                }
            }
        }
    }

    fn bounds(&self) -> Option<Bounds> {
        (self.finite > 0).then(|| Bounds {
            min: self.min.to_array(),
            max: self.max.to_array(),
        })
    }

    /// The median spacing of the sample, scaled to the whole cloud's density on a surface.
    fn spacing(&self) -> Result<Option<Spacing>, NeighboursError> {
        let origin = if self.finite > 0 {
            self.min
        } else {
            DVec3::ZERO
        };
        let index = KnnIndex::build(&self.sample, origin)?;
        let m = self.sample.len() as u64;
        Ok(median_spacing(&index)?.map(|d| {
            if m < self.finite {
                Spacing {
                    median: d * (m as f64 / self.finite as f64).sqrt(),
                    sampled: Some(m),
                }
            } else {
                Spacing {
                    median: d,
                    sampled: None,
                }
            }
        }))
    }

    fn classes(&self, info: &SourceInfo) -> Option<Classes> {
        let c = self.classes.as_ref()?;
        let names = if c.is_las() {
            self.counts
                .keys()
                .filter_map(|&k| las_class_name(k).map(|n| (k, n)))
                .collect()
        } else {
            BTreeMap::new()
        };
        Some(Classes {
            field: c.name(&info.schema).to_string(),
            counts: self.counts.clone(),
            names,
        })
    }
}

/// The name of a stored type.
fn type_name(ty: ScalarType) -> &'static str {
    match ty {
        ScalarType::I8 => "i8",
        ScalarType::U8 => "u8",
        ScalarType::I16 => "i16",
        ScalarType::U16 => "u16",
        ScalarType::I32 => "i32",
        ScalarType::U32 => "u32",
        ScalarType::I64 => "i64",
        ScalarType::U64 => "u64",
        ScalarType::F32 => "f32",
        ScalarType::F64 => "f64",
    }
}

fn las_meta(info: &SourceInfo) -> Option<&io::las::LasMeta> {
    match &info.meta {
        Meta::Las(m) => Some(m),
        _ => None,
    }
}

/// The fields beyond the format's standard record.
fn extra_fields(info: &SourceInfo) -> Vec<String> {
    let schema = &info.schema;
    match las_meta(info) {
        Some(m) => schema
            .fields
            .iter()
            .filter(|f| f.offset >= m.base_record_len())
            .map(|f| f.name.clone())
            .collect(),
        None => schema
            .fields
            .iter()
            .enumerate()
            .filter(|(i, _)| !schema.xyz.contains(i))
            .map(|(_, f)| f.name.clone())
            .collect(),
    }
}

/// The format's own description, one line.
fn kind(info: &SourceInfo) -> String {
    match &info.meta {
        Meta::Las(m) => {
            let (major, minor) = m.version();
            let packing = if m.is_copc() {
                ", COPC"
            } else if m.is_compressed() {
                ", LAZ"
            } else {
                ""
            };
            format!(
                "LAS {major}.{minor}, point format {}, {}-byte records{packing}",
                m.point_format(),
                m.record_len()
            )
        }
        Meta::Ply(m) => format!("PLY {}", m.encoding().keyword()),
        Meta::Pcd(m) => {
            let organized = if m.is_organized() {
                format!(", organized {} × {}", m.width(), m.height())
            } else {
                String::new()
            };
            format!("PCD DATA {}{organized}", m.file_data().keyword())
        }
        Meta::E57(m) => {
            let n = m.scans().len();
            format!("E57, {n} scan{}", if n == 1 { "" } else { "s" })
        }
        Meta::Off(m) if m.keyword == "OFF" => "OFF".into(),
        Meta::Off(m) => format!("OFF ({})", m.keyword),
        Meta::Obj(_) => "Wavefront OBJ".into(),
        Meta::Text(m) => format!("text, columns separated by {:?}", m.separator),
        _ => match info.format.bin_layout() {
            Some(layout) => format!("raw little-endian f32 records ({})", layout.spec()),
            None => info.format.name().to_string(),
        },
    }
}

/// The format's own header fields, as JSON.
fn header(info: &SourceInfo, evlrs: &[&io::las::LasVlr]) -> Value {
    match &info.meta {
        Meta::Las(m) => {
            let (major, minor) = m.version();
            let (day, year) = m.creation();
            let (min, max) = m.header_bounds();
            let vlr = |v: &io::las::LasVlr| {
                json!({
                    "user_id": v.user_id(),
                    "record_id": v.record_id(),
                    "description": v.description(),
                    "length": v.data().len(),
                    "extended": v.is_extended(),
                })
            };
            json!({
                "version": format!("{major}.{minor}"),
                "point_format": m.point_format(),
                "compressed": m.is_compressed(),
                "copc": m.is_copc(),
                "system_identifier": m.system_identifier(),
                "generating_software": m.generating_software(),
                "creation_day": day,
                "creation_year": year,
                "header_bounds": {"min": min.to_array(), "max": max.to_array()},
                "vlrs": m.vlrs().iter().chain(evlrs.iter().copied()).map(vlr).collect::<Vec<_>>(),
            })
        }
        Meta::Ply(m) => json!({
            "encoding": m.encoding().keyword(),
            "elements": m.elements().iter().map(|e| json!({"name": e.name, "count": e.count})).collect::<Vec<_>>(),
            "comments": m.comments(),
            "obj_info": m.obj_info(),
        }),
        Meta::Pcd(m) => json!({
            "version": m.version(),
            "data": m.file_data().keyword(),
            "width": m.width(),
            "height": m.height(),
            "viewpoint": m.viewpoint(),
        }),
        Meta::E57(m) => json!({
            "guid": m.guid(),
            "coordinate_metadata": m.coordinate_metadata(),
            "scans": m.scans().iter().map(|s| json!({
                "name": s.name,
                "points": s.records,
                "posed": s.transform.is_some(),
            })).collect::<Vec<_>>(),
        }),
        Meta::Off(m) => json!({"keyword": m.keyword}),
        _ => json!({}),
    }
}
