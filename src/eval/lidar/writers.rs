//! Writing a simulated scan, through the project's own sinks (so `qemd` reads every output).
//!
//! The format comes from the extension; every output holds the returns in pulse order:
//!
//! | format | record | frame |
//! |---|---|---|
//! | `.las`, `.laz` | LAS 1.4 PDRF 6: x y z (scale 10⁻⁴ or 10⁻³ m from the extent, offset the lower corner), intensity, return 1 of 1, scanner channel, scan direction and edge flags, classification ([`Kind::las_class`]), scan angle (0.006° steps), point source id (strip or station), GPS time, and an extra-bytes `ring` (u16) | street or sensor |
//! | `.ply`, `.xyz`/`.txt` | the LAS fields by the same names, x y z as doubles | street or sensor |
//! | `.pcd` | ROS driver style: x y z (`F 4` in the sensor frame, `F 8` in the street frame), intensity (`F 4`, 0–1), ring (`U 2`), time (`F 4`, s since the first pulse), classification (`U 1`) | sensor for a sweep |
//! | `.bin` (KITTI) | f32 x y z reflectance (0–1) | sensor for a sweep |
//! | `.pcd.bin` (nuScenes) | f32 x y z intensity (0–255) ring | sensor for a sweep |
//!
//! COPC (octree order) and E57 are refused: the points must stay in the truth's order.

use std::path::Path;

use glam::DVec3;

use super::LidarError;
use super::beam::Return;
use super::sensors::Pulse;
use crate::io::{self, Extras, Format, IoError, Meta, SourceInfo};
use crate::points::{Endian, PointBatch, ScalarType, Schema};

/// KITTI reflectance (0–1) of a 16-bit intensity.
pub fn kitti_reflectance(intensity: u16) -> f32 {
    f32::from(intensity) / 65535.0
}

/// nuScenes intensity (0–255) of a 16-bit intensity.
pub fn nuscenes_intensity(intensity: u16) -> f32 {
    (f32::from(intensity) / 257.0).round()
}

/// The PCD `time` of a pulse: seconds since the first pulse, as `f32`.
pub fn relative_time(time: f64, origin: f64) -> f32 {
    (time - origin) as f32
}

/// The formats a scan can be written in, or why not.
///
/// # Errors
/// [`LidarError::Param`] for an unknown extension, COPC, E57, OBJ or OFF.
pub fn scan_format(path: &Path) -> Result<Format, LidarError> {
    let f = Format::from_path(path)?;
    match f {
        Format::Las
        | Format::Laz
        | Format::Ply
        | Format::Xyz
        | Format::Pcd
        | Format::Kitti
        | Format::Nuscenes => Ok(f),
        other => Err(LidarError::Param {
            name: "output",
            detail: format!(
                "{}: a scan cannot be written as {other} (the points must keep the truth's \
                 order): use .las, .laz, .ply, .xyz, .pcd, .bin or .pcd.bin",
                path.display()
            ),
        }),
    }
}

/// The fields of each family of formats.
enum Layout {
    /// LAS, PLY, text.
    Las,
    /// PCD, with x y z in this type.
    Pcd(ScalarType),
    /// KITTI.
    Kitti,
    /// nuScenes.
    Nuscenes,
}

impl Layout {
    fn of(format: Format, sensor_frame: bool) -> Layout {
        match format {
            Format::Pcd => Layout::Pcd(if sensor_frame {
                ScalarType::F32
            } else {
                ScalarType::F64
            }),
            Format::Kitti => Layout::Kitti,
            Format::Nuscenes => Layout::Nuscenes,
            _ => Layout::Las,
        }
    }

    fn schema(&self) -> Schema {
        use ScalarType::*;
        let fields: Vec<(&str, ScalarType)> = match self {
            Layout::Las => vec![
                ("x", F64),
                ("y", F64),
                ("z", F64),
                ("intensity", U16),
                ("return_numbers", U8),
                ("classification_flags", U8),
                ("classification", U8),
                ("user_data", U8),
                ("scan_angle", I16),
                ("point_source_id", U16),
                ("gps_time", F64),
                ("ring", U16),
            ],
            Layout::Pcd(t) => vec![
                ("x", *t),
                ("y", *t),
                ("z", *t),
                ("intensity", F32),
                ("ring", U16),
                ("time", F32),
                ("classification", U8),
            ],
            Layout::Kitti => vec![("x", F32), ("y", F32), ("z", F32), ("intensity", F32)],
            Layout::Nuscenes => vec![
                ("x", F32),
                ("y", F32),
                ("z", F32),
                ("intensity", F32),
                ("ring", F32),
            ],
        };
        Schema::packed(&fields, Endian::Little).expect("x, y and z are listed")
    }
}

/// What a writer needs besides the returns.
pub struct ScanFrame<'a> {
    /// The pulses the returns index.
    pub pulses: &'a [Pulse],
    /// Subtracted from every street-frame position.
    pub origin: DVec3,
    /// The points are in a sensor frame (f32 PCD).
    pub sensor_frame: bool,
    /// GPS time of the first pulse.
    pub time_origin: f64,
}

/// Writes the returns' clean or noisy positions to `path`, in the format of its extension.
///
/// # Errors
/// An unsupported format; anything the sink reports.
pub fn write_scan(
    path: &Path,
    returns: &[Return],
    clean: bool,
    frame: &ScanFrame<'_>,
) -> Result<(), LidarError> {
    let format = scan_format(path)?;
    let layout = Layout::of(format, frame.sensor_frame);
    let schema = layout.schema();
    let info = SourceInfo {
        path: Default::default(),
        format: Format::Ply,
        schema: schema.clone(),
        len: Some(returns.len() as u64),
        faces: None,
        meta: Meta::None,
    };
    let rl = schema.record_len;
    let mut batch = PointBatch::with_capacity(rl, returns.len());
    batch.clear(0);
    let mut rec = vec![0u8; rl];
    let idx = |name: &str| schema.field_index(name);
    for r in returns {
        let p = &frame.pulses[r.pulse as usize];
        let pos = if clean { r.clean } else { r.noisy } - frame.origin;
        rec.fill(0);
        schema.set_position(&mut rec, pos);
        let mut put = |name: &str, v: f64| {
            if let Some(i) = idx(name) {
                schema.set_f64(&mut rec, i, v);
            }
        };
        match layout {
            Layout::Las => {
                put("intensity", f64::from(r.intensity));
                put("return_numbers", f64::from(0x11u8));
                put(
                    "classification_flags",
                    f64::from((p.channel & 3) << 4 | p.flags),
                );
                put("classification", f64::from(r.kind.las_class()));
                put("scan_angle", (p.scan_angle / 0.006).round());
                put("point_source_id", f64::from(p.source));
                put("gps_time", p.time);
                put("ring", f64::from(p.ring));
            }
            Layout::Pcd(_) => {
                put("intensity", f64::from(kitti_reflectance(r.intensity)));
                put("ring", f64::from(p.ring));
                put("time", f64::from(relative_time(p.time, frame.time_origin)));
                put("classification", f64::from(r.kind.las_class()));
            }
            Layout::Kitti => put("intensity", f64::from(kitti_reflectance(r.intensity))),
            Layout::Nuscenes => {
                put("intensity", f64::from(nuscenes_intensity(r.intensity)));
                put("ring", f64::from(p.ring));
            }
        }
        batch.push(pos, &rec);
    }
    let mut sink = io::create(path, Some(format), &info, returns.len() as u64)?;
    sink.write_batch(&batch)?;
    sink.finish(&Extras::default())
        .map_err(|e: IoError| e.into())
}
