//! The truth file of a simulated scan: the scene mesh and every return's noise-free position.
//!
//! A binary little-endian PLY, readable by any PLY reader (`qemd render` and MeshLab show the
//! scene; `qemd eval --clean` takes its mesh):
//!
//! ```text
//! ply
//! format binary_little_endian 1.0
//! comment qemd lidar truth 1
//! comment sensor spinning kitti64          the sensor and preset
//! comment sigma 0.02                        range noise σ (m)
//! comment seed 0 scene_seed 0
//! comment frame sensor 0 -1.8 1.73          the frame of every coordinate, and its origin in
//!                                           the street frame (street: 0 0 0)
//! comment time_origin 1000                  GPS time of the first pulse (PCD `time` is relative)
//! element vertex V                          the scene: double x y z
//! element face F                            list uchar uint vertex_indices,
//!                                           uchar class (LAS code of the kind), uint object
//! element return R                          one per return, in the scan's order:
//!   double x y z                              noise-free position (o + d·r)
//!   double ox oy oz                           beam origin (the sensor at that pulse)
//!   double gps_time
//!   uchar class                               LAS code of the kind (68: mixed pixel)
//!   uint object                               object id (faces with the same id)
//!   uchar flags                               bit 0 mixed pixel, bit 1 off-centre
//!   ushort ring, ushort intensity
//! end_header
//! ```
//!
//! [`Truth::read`] reads it back with `ply-rs-bw` (typed elements); the scorer needs nothing else.

use std::io::{BufReader, Write};
use std::path::Path;

use glam::DVec3;
use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{PropertyAccess, PropertyAccessResult};

use super::LidarError;
use super::kinds::Kind;
use crate::io::{AtomicFile, IoError};

/// The version written in the first comment.
const MAGIC: &str = "qemd lidar truth 1";

/// Bit of [`TruthReturn::flags`]: a mixed pixel.
pub const FLAG_MIXED: u8 = 1;
/// Bit of [`TruthReturn::flags`]: an off-centre return.
pub const FLAG_OFFCENTRE: u8 = 2;

/// What the truth says about the scan as a whole.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TruthMeta {
    /// Sensor and preset, e.g. `spinning kitti64`.
    pub sensor: String,
    /// Range noise σ (m).
    pub sigma: f64,
    /// Seed of the pulses' noise.
    pub seed: u64,
    /// Seed of the scene.
    pub scene_seed: u64,
    /// `street` or `sensor`.
    pub frame: String,
    /// The frame's origin in street coordinates.
    pub frame_origin: DVec3,
    /// GPS time of the first pulse.
    pub time_origin: f64,
}

/// One return's truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthReturn {
    /// Noise-free position.
    pub position: DVec3,
    /// Beam origin.
    pub origin: DVec3,
    /// GPS time.
    pub time: f64,
    /// Kind (`Mixed` for a mixed pixel).
    pub kind: Kind,
    /// Object id.
    pub object: u32,
    /// [`FLAG_MIXED`], [`FLAG_OFFCENTRE`].
    pub flags: u8,
    /// Beam index.
    pub ring: u16,
    /// Intensity.
    pub intensity: u16,
}

/// A truth file in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Truth {
    /// The header's facts.
    pub meta: TruthMeta,
    /// Scene vertices.
    pub positions: Vec<DVec3>,
    /// Scene triangles.
    pub triangles: Vec<[u32; 3]>,
    /// Kind of each triangle.
    pub face_kind: Vec<Kind>,
    /// Object of each triangle.
    pub face_object: Vec<u32>,
    /// The returns, in the scan's order.
    pub returns: Vec<TruthReturn>,
}

impl Truth {
    /// Writes the truth file (atomically).
    ///
    /// # Errors
    /// The file cannot be written.
    pub fn write(&self, path: &Path) -> Result<(), IoError> {
        let m = &self.meta;
        let o = m.frame_origin;
        let header = format!(
            "ply\nformat binary_little_endian 1.0\ncomment {MAGIC}\ncomment sensor {}\n\
             comment sigma {}\ncomment seed {} scene_seed {}\ncomment frame {} {} {} {}\n\
             comment time_origin {}\nelement vertex {}\nproperty double x\nproperty double y\n\
             property double z\nelement face {}\nproperty list uchar uint vertex_indices\n\
             property uchar class\nproperty uint object\nelement return {}\nproperty double x\n\
             property double y\nproperty double z\nproperty double ox\nproperty double oy\n\
             property double oz\nproperty double gps_time\nproperty uchar class\n\
             property uint object\nproperty uchar flags\nproperty ushort ring\n\
             property ushort intensity\nend_header\n",
            m.sensor,
            m.sigma,
            m.seed,
            m.scene_seed,
            m.frame,
            o.x,
            o.y,
            o.z,
            m.time_origin,
            self.positions.len(),
            self.triangles.len(),
            self.returns.len()
        );
        let mut b: Vec<u8> = Vec::with_capacity(
            header.len()
                + 24 * self.positions.len()
                + 18 * self.triangles.len()
                + 65 * self.returns.len(),
        );
        b.extend_from_slice(header.as_bytes());
        let v3 = |b: &mut Vec<u8>, p: DVec3| {
            for c in [p.x, p.y, p.z] {
                b.extend_from_slice(&c.to_le_bytes());
            }
        };
        for &p in &self.positions {
            v3(&mut b, p);
        }
        for ((t, k), obj) in self
            .triangles
            .iter()
            .zip(&self.face_kind)
            .zip(&self.face_object)
        {
            b.push(3);
            for v in t {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.push(k.las_class());
            b.extend_from_slice(&obj.to_le_bytes());
        }
        for r in &self.returns {
            v3(&mut b, r.position);
            v3(&mut b, r.origin);
            b.extend_from_slice(&r.time.to_le_bytes());
            b.push(r.kind.las_class());
            b.extend_from_slice(&r.object.to_le_bytes());
            b.push(r.flags);
            b.extend_from_slice(&r.ring.to_le_bytes());
            b.extend_from_slice(&r.intensity.to_le_bytes());
        }
        let mut f = AtomicFile::create(path)?;
        f.write_all(&b).map_err(|e| f.err(e))?;
        f.commit()
    }

    /// Reads a truth file.
    ///
    /// # Errors
    /// Not a qemd truth file, a malformed or truncated one, an unknown class code or a face
    /// index out of range; each names the file.
    pub fn read(path: &Path) -> Result<Truth, LidarError> {
        let bad = |detail: String| LidarError::Io(IoError::invalid(path, detail));
        let file = crate::io::open_file(path)?;
        let mut reader = Reader::new(BufReader::new(file));
        let header = Parser::<Vert>::new()
            .read_header(&mut reader)
            .map_err(|e| bad(format!("not a truth file: {e}")))?;
        if header.comments.first().map(String::as_str) != Some(MAGIC) {
            return Err(bad(format!(
                "not a truth file of `qemd synth lidar` (its first comment is not `{MAGIC}`)"
            )));
        }
        let comment = |key: &str| -> Result<Vec<String>, LidarError> {
            header
                .comments
                .iter()
                .find_map(|c| c.strip_prefix(key).and_then(|r| r.strip_prefix(' ')))
                .map(|r| r.split_whitespace().map(str::to_string).collect())
                .ok_or_else(|| bad(format!("the header has no `comment {key}`")))
        };
        let num = |key: &str, words: &[String], i: usize| -> Result<f64, LidarError> {
            words
                .get(i)
                .and_then(|w| w.parse::<f64>().ok())
                .ok_or_else(|| bad(format!("`comment {key}` is malformed")))
        };
        let sensor = comment("sensor")?.join(" ");
        let s = comment("sigma")?;
        let sigma = num("sigma", &s, 0)?;
        let seeds = comment("seed")?;
        let seed = num("seed", &seeds, 0)? as u64;
        let scene_seed = num("seed", &seeds, 2)? as u64;
        let fr = comment("frame")?;
        let frame = fr.first().cloned().unwrap_or_default();
        let frame_origin = DVec3::new(
            num("frame", &fr, 1)?,
            num("frame", &fr, 2)?,
            num("frame", &fr, 3)?,
        );
        let t = comment("time_origin")?;
        let time_origin = num("time_origin", &t, 0)?;
        let mut verts = Vec::new();
        let mut faces = Vec::new();
        let mut rets = Vec::new();
        for (name, def) in &header.elements {
            let e = |err| bad(format!("element {name}: {err}"));
            match name.as_str() {
                "vertex" => {
                    verts = Parser::<Vert>::new()
                        .read_payload_for_element(&mut reader, def, &header)
                        .map_err(e)?;
                }
                "face" => {
                    faces = Parser::<Face>::new()
                        .read_payload_for_element(&mut reader, def, &header)
                        .map_err(e)?;
                }
                "return" => {
                    rets = Parser::<Ret>::new()
                        .read_payload_for_element(&mut reader, def, &header)
                        .map_err(e)?;
                }
                other => return Err(bad(format!("unexpected element `{other}`"))),
            }
        }
        let kind = |code: u8| {
            Kind::from_las_class(code).ok_or_else(|| bad(format!("unknown class code {code}")))
        };
        let mut triangles = Vec::with_capacity(faces.len());
        let mut face_kind = Vec::with_capacity(faces.len());
        let mut face_object = Vec::with_capacity(faces.len());
        for (i, f) in faces.iter().enumerate() {
            let [a, b, c] = f.indices[..] else {
                return Err(bad(format!("face {i} is not a triangle")));
            };
            if [a, b, c].iter().any(|&v| v as usize >= verts.len()) {
                return Err(bad(format!(
                    "face {i} indexes a vertex beyond {}",
                    verts.len()
                )));
            }
            triangles.push([a, b, c]);
            face_kind.push(kind(f.class)?);
            face_object.push(f.object);
        }
        let returns = rets
            .iter()
            .map(|r| {
                Ok(TruthReturn {
                    position: r.p,
                    origin: r.o,
                    time: r.time,
                    kind: kind(r.class)?,
                    object: r.object,
                    flags: r.flags,
                    ring: r.ring,
                    intensity: r.intensity,
                })
            })
            .collect::<Result<_, LidarError>>()?;
        Ok(Truth {
            meta: TruthMeta {
                sensor,
                sigma,
                seed,
                scene_seed,
                frame,
                frame_origin,
                time_origin,
            },
            positions: verts.into_iter().map(|v| v.0).collect(),
            triangles,
            face_kind,
            face_object,
            returns,
        })
    }
}

/// A vertex as `ply-rs-bw` fills it.
#[derive(Default)]
struct Vert(DVec3);

impl PropertyAccess for Vert {
    fn new() -> Self {
        Vert::default()
    }
    fn set_double(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        match name {
            "x" => self.0.x = v,
            "y" => self.0.y = v,
            "z" => self.0.z = v,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }
}

#[derive(Default)]
struct Face {
    indices: Vec<u32>,
    class: u8,
    object: u32,
}

impl PropertyAccess for Face {
    fn new() -> Self {
        Face::default()
    }
    fn begin_list_uint(&mut self, name: &str, _len: usize) -> ply_rs_bw::ply::BeginList<'_, u32> {
        match name {
            "vertex_indices" => ply_rs_bw::ply::BeginList::Fill(&mut self.indices),
            _ => ply_rs_bw::ply::BeginList::UseSetter,
        }
    }
    fn set_uchar(&mut self, name: &str, v: u8) -> PropertyAccessResult {
        if name == "class" {
            self.class = v;
            return PropertyAccessResult::Set;
        }
        PropertyAccessResult::Ignored
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        if name == "object" {
            self.object = v;
            return PropertyAccessResult::Set;
        }
        PropertyAccessResult::Ignored
    }
}

#[derive(Default)]
struct Ret {
    p: DVec3,
    o: DVec3,
    time: f64,
    class: u8,
    object: u32,
    flags: u8,
    ring: u16,
    intensity: u16,
}

impl PropertyAccess for Ret {
    fn new() -> Self {
        Ret::default()
    }
    fn set_double(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        match name {
            "x" => self.p.x = v,
            "y" => self.p.y = v,
            "z" => self.p.z = v,
            "ox" => self.o.x = v,
            "oy" => self.o.y = v,
            "oz" => self.o.z = v,
            "gps_time" => self.time = v,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }
    fn set_uchar(&mut self, name: &str, v: u8) -> PropertyAccessResult {
        match name {
            "class" => self.class = v,
            "flags" => self.flags = v,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        if name == "object" {
            self.object = v;
            return PropertyAccessResult::Set;
        }
        PropertyAccessResult::Ignored
    }
    fn set_ushort(&mut self, name: &str, v: u16) -> PropertyAccessResult {
        match name {
            "ring" => self.ring = v,
            "intensity" => self.intensity = v,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }
}
