//! KITTI Velodyne scans (`.bin`): headerless little-endian `f32` records.
//!
//! # Brief overview
//!
//! ```text
//!  offset  0        4        8        12       16
//!          | x f32  | y f32  | z f32  | intensity f32 |   one 16-byte record per point, LE
//! ```
//!
//! The point count is the file size divided by 16; a size that is not a multiple of 16 is
//! reported as truncated. Both directions stream: the reader reads one batch of records at a
//! time, the writer writes each batch as it comes. Records travel through unchanged, except x, y
//! and z, which are rewritten only when the position differs from the record's (so an unchanged
//! write is byte-identical, NaN payloads included).
//!
//! Records of another layout are converted field by field: x, y, z from the positions and the
//! intensity from a field named `intensity` or `reflectance` (0 when there is none). Faces
//! cannot be stored; a sink ignores [`Extras::faces`]. Nor can a noise flag: a 16-byte record has
//! no room for one, so [`create_with`](super::create_with) refuses
//! [`SinkOptions::noise_flag`](super::SinkOptions::noise_flag) for KITTI output.

use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::Path;

use super::text::{Tally, check_batch};
use super::{AtomicFile, Extras, Format, IoError, Meta, Sink, Source, SourceInfo};
use crate::points::{Endian, PointBatch, ScalarType, Schema};

/// Bytes per KITTI record.
pub const RECORD_LEN: usize = 16;

/// The KITTI record: x, y, z and intensity, `f32` little-endian.
pub fn kitti_schema() -> Schema {
    Schema::packed(
        &[
            ("x", ScalarType::F32),
            ("y", ScalarType::F32),
            ("z", ScalarType::F32),
            ("intensity", ScalarType::F32),
        ],
        Endian::Little,
    )
    .expect("x, y and z are present by construction")
}

/// Streaming KITTI reader.
pub struct KittiSource {
    info: SourceInfo,
    reader: BufReader<File>,
    /// Points delivered so far.
    read: u64,
    /// Points in the file.
    total: u64,
}

impl KittiSource {
    /// Opens a scan; the point count comes from the file size.
    ///
    /// # Errors
    /// Unreadable file, an empty file, a size that is not a multiple of 16 bytes.
    pub fn open(path: &Path) -> Result<KittiSource, IoError> {
        let file = super::open_file(path)?;
        let size = file.metadata().map_err(|e| IoError::io(path, e))?.len();
        if size == 0 {
            return Err(IoError::invalid(path, "empty file: no 16-byte record"));
        }
        if size % RECORD_LEN as u64 != 0 {
            return Err(IoError::truncated(
                path,
                format!("file size {size} is not a multiple of the {RECORD_LEN}-byte record"),
            ));
        }
        let total = size / RECORD_LEN as u64;
        Ok(KittiSource {
            info: SourceInfo {
                path: path.to_path_buf(),
                format: Format::Kitti,
                schema: kitti_schema(),
                len: Some(total),
                faces: None,
                meta: Meta::None,
            },
            reader: BufReader::with_capacity(1 << 16, file),
            read: 0,
            total,
        })
    }
}

impl Source for KittiSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        batch.clear(self.read);
        batch.record_len = RECORD_LEN;
        let n = (self.total - self.read).min(max as u64) as usize;
        batch.records.resize(n * RECORD_LEN, 0);
        self.reader
            .read_exact(&mut batch.records)
            .map_err(|e| IoError::io(&self.info.path, e))?;
        let schema = &self.info.schema;
        batch.positions.extend(
            batch
                .records
                .chunks_exact(RECORD_LEN)
                .map(|r| schema.position(r)),
        );
        self.read += n as u64;
        Ok(n)
    }

    fn finish(self: Box<Self>) -> Result<Extras, IoError> {
        Ok(Extras::default())
    }
}

/// How a sink fills the intensity of a record of another layout.
enum Layout {
    /// The source is a KITTI record: copy it.
    Same,
    /// Another layout: x, y, z from the positions, intensity from this field (if any).
    Foreign(Option<usize>),
}

/// Streaming KITTI writer.
pub struct KittiSink {
    out: AtomicFile,
    like: Schema,
    kitti: Schema,
    layout: Layout,
    tally: Tally,
    buf: Vec<u8>,
}

impl KittiSink {
    /// Creates a sink that writes `count` points laid out like `like`.
    ///
    /// # Errors
    /// The directory is not writable.
    pub fn create(path: &Path, like: &SourceInfo, count: u64) -> Result<KittiSink, IoError> {
        let kitti = kitti_schema();
        let layout = if like.schema == kitti {
            Layout::Same
        } else {
            Layout::Foreign(
                like.schema
                    .field_index("intensity")
                    .or_else(|| like.schema.field_index("reflectance")),
            )
        };
        Ok(KittiSink {
            out: AtomicFile::create(path)?,
            like: like.schema.clone(),
            kitti,
            layout,
            tally: Tally::new(count),
            buf: Vec::new(),
        })
    }
}

impl Sink for KittiSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        check_batch(self.out.target(), &self.like, batch)?;
        self.tally.add(self.out.target(), batch.len())?;
        self.buf.clear();
        let k = &self.kitti;
        for (i, &p) in batch.positions.iter().enumerate() {
            let start = self.buf.len();
            match self.layout {
                Layout::Same => {
                    self.buf.extend_from_slice(batch.record(i));
                    let rec = &mut self.buf[start..];
                    let old = k.position(rec);
                    for (axis, (new, old)) in [(p.x, old.x), (p.y, old.y), (p.z, old.z)]
                        .into_iter()
                        .enumerate()
                    {
                        if new.to_bits() != old.to_bits() {
                            k.set_f64(rec, k.xyz[axis], new);
                        }
                    }
                }
                Layout::Foreign(intensity) => {
                    self.buf.resize(start + RECORD_LEN, 0);
                    let rec = &mut self.buf[start..];
                    k.set_position(rec, p);
                    let v = intensity.map_or(0.0, |f| self.like.get_f64(batch.record(i), f));
                    k.set_f64(rec, 3, v);
                }
            }
        }
        self.out.write_all(&self.buf).map_err(|e| self.out.err(e))
    }

    fn finish(self: Box<Self>, _extras: &Extras) -> Result<(), IoError> {
        self.tally.check(self.out.target())?;
        self.out.commit()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::Cloud;
    use glam::DVec3;

    fn scan(points: &[[f32; 4]]) -> Vec<u8> {
        points
            .iter()
            .flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes()))
            .collect()
    }

    #[test]
    fn roundtrip_is_byte_identical_and_moves_only_xyz() {
        let dir = tempfile::tempdir().unwrap();
        let nan = f32::from_bits(0x7fc0_1234);
        let bytes = scan(&[[1.5, -2.0, 0.1, 0.25], [nan, 3.0, 4.0, 0.5]]);
        let p = dir.path().join("a.bin");
        std::fs::write(&p, &bytes).unwrap();
        let mut c = Cloud::read(&p, None).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(c.positions[0], DVec3::new(1.5, -2.0, 0.1f32 as f64));
        let q = dir.path().join("b.bin");
        c.write(&q, None).unwrap();
        assert_eq!(std::fs::read(&q).unwrap(), bytes);

        c.positions[0].z = 7.0;
        c.write(&q, None).unwrap();
        let out = std::fs::read(&q).unwrap();
        assert_eq!(&out[8..12], &7f32.to_le_bytes());
        assert_eq!(&out[..8], &bytes[..8]);
        assert_eq!(&out[12..], &bytes[12..]);
    }

    #[test]
    fn size_not_multiple_of_16() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        std::fs::write(&p, vec![0u8; 34]).unwrap();
        let e = Cloud::read(&p, None).unwrap_err();
        assert!(matches!(e, IoError::Truncated { .. }));
        assert!(
            e.to_string()
                .contains("file size 34 is not a multiple of the 16-byte record"),
            "{e}"
        );
        std::fs::write(&p, b"").unwrap();
        assert!(Cloud::read(&p, None).is_err());
    }

    #[test]
    fn foreign_layout_converts_fields() {
        let dir = tempfile::tempdir().unwrap();
        let c = Cloud::generated(vec![DVec3::new(1.0, 2.0, 3.0)], None, ScalarType::F64);
        let p = dir.path().join("g.bin");
        c.write(&p, None).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), scan(&[[1.0, 2.0, 3.0, 0.0]]));
    }
}
