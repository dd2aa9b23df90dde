//! Raw float32 scans: headerless little-endian `f32` records — KITTI Velodyne `.bin`, nuScenes
//! `.pcd.bin` sweeps, and any other layout given with `--bin-fields`.
//!
//! # Brief overview
//!
//! ```text
//!  KITTI (.bin)          | x f32 | y f32 | z f32 | intensity f32 |                16 bytes, LE
//!  nuScenes (.pcd.bin)   | x f32 | y f32 | z f32 | intensity f32 | ring f32 |     20 bytes, LE
//!  --bin-fields SPEC     any order of x, y, z, intensity (i), ring, time (t), _ (unnamed)
//! ```
//!
//! A [`BinLayout`] names the `f32` fields of a record. The point count is the file size divided
//! by the record length; a size that is not a multiple of it is a one-line error naming both.
//! Both directions stream: the reader reads one batch of records at a time, the writer writes
//! each batch as it comes. Records travel through unchanged, except x, y and z, which are
//! rewritten only when the position differs from the record's (so an unchanged write is
//! byte-identical, NaN payloads included).
//!
//! **nuScenes is never read as KITTI.** The layouts are told apart by name (`*.pcd.bin` is
//! nuScenes, another `*.bin` KITTI) or by the format given. A file read as KITTI whose size is a
//! multiple of 20 bytes and whose every fifth `f32` (in the first 4096 20-byte records) is a
//! whole number in 0..=255 — the ring index of a nuScenes sweep — is refused with a hint, as is
//! a KITTI-sized read of a file whose size is a multiple of 20 but not of 16. (A genuine KITTI
//! scan has arbitrary x, y, z there. `--bin-fields x,y,z,i` reads such a file as KITTI anyway.)
//!
//! Records of another layout are converted field by field: x, y, z from the positions, every
//! other named field from the source field of that name (`intensity` also from `reflectance`),
//! 0 when there is none. Faces cannot be stored; a sink ignores [`Extras::faces`]. Nor can a
//! noise flag: a raw record has no room for one, so [`create_with`](super::create_with) refuses
//! [`SinkOptions::noise_flag`](super::SinkOptions::noise_flag) for raw output.

use std::io::{BufReader, Read, Write};
use std::path::Path;

use super::reader::seek_record;
use super::tally::{Tally, check_batch};
use super::{
    AtomicFile, BodyStats, Extras, Format, Input, IoError, Meta, Sink, Source, SourceInfo,
};
use crate::points::{Endian, PointBatch, Rounding, ScalarType, Schema, stored_toward};

/// Bytes per KITTI record.
pub const RECORD_LEN: usize = 16;

/// Most `f32` fields a [`BinLayout`] can name.
pub const MAX_BIN_FIELDS: usize = 32;

/// What one `f32` of a raw record holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BinField {
    /// x coordinate.
    X,
    /// y coordinate.
    Y,
    /// z coordinate.
    Z,
    /// Intensity or reflectance.
    Intensity,
    /// Laser ring (beam) index.
    Ring,
    /// Time stamp or time offset.
    Time,
    /// A field without a name (`_` in a spec); called `f<index>` in the schema.
    Unnamed,
}

impl BinField {
    fn parse(name: &str) -> Option<BinField> {
        Some(match name.trim().to_ascii_lowercase().as_str() {
            "x" => BinField::X,
            "y" => BinField::Y,
            "z" => BinField::Z,
            "i" | "intensity" | "reflectance" => BinField::Intensity,
            "ring" | "r" => BinField::Ring,
            "t" | "time" | "timestamp" => BinField::Time,
            "_" => BinField::Unnamed,
            _ => return None,
        })
    }

    fn name(self, index: usize) -> String {
        match self {
            BinField::X => "x".into(),
            BinField::Y => "y".into(),
            BinField::Z => "z".into(),
            BinField::Intensity => "intensity".into(),
            BinField::Ring => "ring".into(),
            BinField::Time => "time".into(),
            BinField::Unnamed => format!("f{index}"),
        }
    }
}

/// The fields of a raw little-endian `f32` record, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct BinLayout {
    len: u8,
    fields: [BinField; MAX_BIN_FIELDS],
}

impl BinLayout {
    /// KITTI: x, y, z, intensity.
    pub const KITTI: BinLayout =
        BinLayout::of(&[BinField::X, BinField::Y, BinField::Z, BinField::Intensity]);

    /// nuScenes: x, y, z, intensity, ring.
    pub const NUSCENES: BinLayout = BinLayout::of(&[
        BinField::X,
        BinField::Y,
        BinField::Z,
        BinField::Intensity,
        BinField::Ring,
    ]);

    const fn of(fields: &[BinField]) -> BinLayout {
        let mut all = [BinField::Unnamed; MAX_BIN_FIELDS];
        let mut i = 0;
        while i < fields.len() {
            all[i] = fields[i];
            i += 1;
        }
        BinLayout {
            len: fields.len() as u8,
            fields: all,
        }
    }

    /// Parses `--bin-fields`: a comma-separated list of `x`, `y`, `z`, `intensity` (`i`),
    /// `ring`, `time` (`t`) and `_` (unnamed), each once except `_`, with x, y and z present; or
    /// a count N ≥ 3: x, y, z and N − 3 unnamed fields.
    ///
    /// # Errors
    /// A message naming what is wrong.
    pub fn parse(spec: &str) -> Result<BinLayout, String> {
        let spec = spec.trim();
        let fields: Vec<BinField> = if let Ok(n) = spec.parse::<usize>() {
            if !(3..=MAX_BIN_FIELDS).contains(&n) {
                return Err(format!(
                    "a field count must be 3 to {MAX_BIN_FIELDS}, not {n}"
                ));
            }
            let mut f = vec![BinField::X, BinField::Y, BinField::Z];
            f.resize(n, BinField::Unnamed);
            f
        } else {
            spec.split(',')
                .map(|t| {
                    BinField::parse(t).ok_or_else(|| {
                        format!(
                            "unknown field `{}` (use x, y, z, intensity/i, ring, time/t, or _ \
                             for an unnamed one)",
                            t.trim()
                        )
                    })
                })
                .collect::<Result<_, _>>()?
        };
        if fields.len() > MAX_BIN_FIELDS {
            return Err(format!("at most {MAX_BIN_FIELDS} fields"));
        }
        for f in [
            BinField::X,
            BinField::Y,
            BinField::Z,
            BinField::Intensity,
            BinField::Ring,
            BinField::Time,
        ] {
            let n = fields.iter().filter(|&&g| g == f).count();
            if n > 1 {
                return Err(format!("field `{}` given {n} times", f.name(0)));
            }
            if n == 0 && matches!(f, BinField::X | BinField::Y | BinField::Z) {
                return Err(format!("no `{}` field", f.name(0)));
            }
        }
        Ok(BinLayout::of(&fields))
    }

    /// The fields in order.
    pub fn fields(&self) -> &[BinField] {
        &self.fields[..usize::from(self.len)]
    }

    /// Bytes per record.
    pub fn record_len(&self) -> usize {
        4 * self.fields().len()
    }

    /// The record schema: every field `f32`, little-endian.
    pub fn schema(&self) -> Schema {
        let names: Vec<String> = self
            .fields()
            .iter()
            .enumerate()
            .map(|(i, f)| f.name(i))
            .collect();
        let fields: Vec<(&str, ScalarType)> = names
            .iter()
            .map(|n| (n.as_str(), ScalarType::F32))
            .collect();
        Schema::packed(&fields, Endian::Little).expect("x, y and z are present by construction")
    }

    /// The spec that [`BinLayout::parse`] reads back (`x,y,z,intensity`).
    pub fn spec(&self) -> String {
        self.fields()
            .iter()
            .map(|f| match f {
                BinField::Unnamed => "_".to_string(),
                f => f.name(0),
            })
            .collect::<Vec<_>>()
            .join(",")
    }
}

/// The KITTI record: x, y, z and intensity, `f32` little-endian.
pub fn kitti_schema() -> Schema {
    BinLayout::KITTI.schema()
}

/// Refuses to read a nuScenes sweep as KITTI (see the [module overview](self)).
fn refuse_nuscenes_as_kitti(path: &Path, file: &mut Input, size: u64) -> Result<(), IoError> {
    const NU: u64 = 20;
    let hint = "looks like a nuScenes sweep (5 float32 per point: x, y, z, intensity, ring); \
                name it *.pcd.bin or give --input-format nuscenes (--bin-fields x,y,z,i reads \
                it as KITTI anyway)";
    if !size.is_multiple_of(NU) {
        return Ok(());
    }
    if !size.is_multiple_of(RECORD_LEN as u64) {
        return Err(IoError::invalid(path, hint));
    }
    let records = (size / NU).min(4096) as usize;
    let mut head = vec![0u8; records * NU as usize];
    file.read_exact(&mut head)
        .map_err(|e| IoError::io(path, e))?;
    use std::io::Seek;
    file.seek(std::io::SeekFrom::Start(0))
        .map_err(|e| IoError::io(path, e))?;
    let ring_like = head.chunks_exact(NU as usize).all(|r| {
        let v = f32::from_le_bytes([r[16], r[17], r[18], r[19]]);
        v.fract() == 0.0 && (0.0..=255.0).contains(&v)
    });
    if ring_like {
        return Err(IoError::invalid(path, hint));
    }
    Ok(())
}

/// Streaming reader of raw `f32` records.
pub struct RawSource {
    info: SourceInfo,
    reader: BufReader<Input>,
    record_len: usize,
    /// Points delivered so far.
    read: u64,
    /// Points in the file.
    total: u64,
}

/// The KITTI reader (a [`RawSource`] with the KITTI layout).
pub type KittiSource = RawSource;

impl RawSource {
    /// Opens a KITTI scan.
    ///
    /// # Errors
    /// As [`RawSource::open_as`].
    pub fn open(path: &Path) -> Result<RawSource, IoError> {
        RawSource::open_as(path, Format::Kitti)
    }

    /// Opens a raw scan of `format` (KITTI, nuScenes or a [`Format::Bin`] layout); the point
    /// count comes from the file size.
    ///
    /// # Errors
    /// Unreadable file, an empty file, a size that is not a multiple of the record, a nuScenes
    /// sweep read as KITTI.
    pub fn open_as(path: &Path, format: Format) -> Result<RawSource, IoError> {
        RawSource::new(Input::from_path(path)?, format)
    }

    /// [`RawSource::open_as`] on any [`Input`] whose length is known.
    ///
    /// # Errors
    /// As [`RawSource::open_as`]; an input of unknown length.
    pub fn new(mut file: Input, format: Format) -> Result<RawSource, IoError> {
        let owned = file.name().to_path_buf();
        let path = owned.as_path();
        let layout = format
            .bin_layout()
            .expect("a raw source is made for a raw format");
        let rl = layout.record_len();
        let size = file.len().ok_or_else(|| {
            IoError::invalid(path, "a raw scan needs a file of known size, not a stream")
        })?;
        if size == 0 {
            return Err(IoError::invalid(
                path,
                format!("empty file: no {rl}-byte record"),
            ));
        }
        if format == Format::Kitti {
            refuse_nuscenes_as_kitti(path, &mut file, size)?;
        }
        if size % rl as u64 != 0 {
            return Err(IoError::truncated(
                path,
                format!(
                    "file size {size} is not a multiple of the {rl}-byte record ({} float32: {})",
                    rl / 4,
                    layout.spec()
                ),
            ));
        }
        let total = size / rl as u64;
        Ok(RawSource {
            info: SourceInfo {
                path: path.to_path_buf(),
                format,
                schema: layout.schema(),
                len: Some(total),
                faces: None,
                meta: Meta::None,
            },
            reader: BufReader::with_capacity(1 << 16, file),
            record_len: rl,
            read: 0,
            total,
        })
    }
}

impl Source for RawSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn seek_point(&mut self, index: u64) -> Result<bool, IoError> {
        if index > self.total {
            return Ok(false);
        }
        let records = (0, self.record_len);
        seek_record(&mut self.reader, &self.info.path, records, index)?;
        self.read = index;
        Ok(true)
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        let rl = self.record_len;
        batch.clear(self.read);
        batch.record_len = rl;
        let n = (self.total - self.read).min(max as u64) as usize;
        batch.records.resize(n * rl, 0);
        self.reader
            .read_exact(&mut batch.records)
            .map_err(|e| IoError::io(&self.info.path, e))?;
        let schema = &self.info.schema;
        batch
            .positions
            .extend(batch.records.chunks_exact(rl).map(|r| schema.position(r)));
        self.read += n as u64;
        Ok(n)
    }

    fn finish(self: Box<Self>) -> Result<Extras, IoError> {
        Ok(Extras::default())
    }
}

/// How a sink fills a record.
enum Layout {
    /// The source has this record: copy it.
    Same,
    /// Another layout: x, y, z from the positions; per target field, the source field (if any).
    Foreign(Vec<Option<usize>>),
}

/// Streaming writer of raw `f32` records.
pub struct RawSink {
    out: AtomicFile,
    like: Schema,
    raw: Schema,
    layout: Layout,
    /// How moved coordinates round to what the output stores ([`SinkOptions::rounding`]).
    rounding: Rounding,
    tally: Tally,
    buf: Vec<u8>,
}

/// The KITTI writer (a [`RawSink`] with the KITTI layout).
pub type KittiSink = RawSink;

impl RawSink {
    /// Creates a KITTI sink.
    ///
    /// # Errors
    /// As [`RawSink::create_as`].
    pub fn create(path: &Path, like: &SourceInfo, count: u64) -> Result<RawSink, IoError> {
        RawSink::create_as(path, Format::Kitti, like, count)
    }

    /// Creates a sink of raw `format` that writes `count` points laid out like `like`.
    ///
    /// # Errors
    /// The directory is not writable.
    pub fn create_as(
        path: &Path,
        format: Format,
        like: &SourceInfo,
        count: u64,
    ) -> Result<RawSink, IoError> {
        RawSink::new(
            AtomicFile::create(path)?,
            format,
            like,
            count,
            Rounding::Nearest,
        )
    }

    /// [`RawSink::create_as`] writing to `out` (a file, a stream or memory).
    ///
    /// # Errors
    /// As [`RawSink::create_as`].
    pub fn new(
        out: AtomicFile,
        format: Format,
        like: &SourceInfo,
        count: u64,
        rounding: Rounding,
    ) -> Result<RawSink, IoError> {
        let layout = format
            .bin_layout()
            .expect("create_as is called with a raw format");
        let raw = layout.schema();
        let layout = if like.schema == raw {
            Layout::Same
        } else {
            Layout::Foreign(
                raw.fields
                    .iter()
                    .map(|f| {
                        like.schema.field_index(&f.name).or_else(|| {
                            (f.name == "intensity")
                                .then(|| like.schema.field_index("reflectance"))
                                .flatten()
                        })
                    })
                    .collect(),
            )
        };
        Ok(RawSink {
            out,
            like: like.schema.clone(),
            raw,
            layout,
            rounding,
            tally: Tally::new(count),
            buf: Vec::new(),
        })
    }
}

impl Sink for RawSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        check_batch(self.out.target(), &self.like, batch)?;
        self.tally.add(self.out.target(), batch.len())?;
        self.buf.clear();
        let k = &self.raw;
        let rl = k.record_len;
        for (i, &p) in batch.positions.iter().enumerate() {
            let start = self.buf.len();
            match &self.layout {
                Layout::Same => {
                    self.buf.extend_from_slice(batch.record(i));
                    let rec = &mut self.buf[start..];
                    let old = k.position(rec).to_array();
                    let new = p.to_array();
                    let tys = k.xyz.map(|f| k.fields[f].ty);
                    let stored = self.rounding.store(new, old, [1.0; 3], |a, v, towards| {
                        stored_toward(v, towards, tys[a])
                    });
                    for axis in 0..3 {
                        if new[axis].to_bits() != old[axis].to_bits() {
                            k.set_f64(rec, k.xyz[axis], stored[axis]);
                        }
                    }
                }
                Layout::Foreign(from) => {
                    self.buf.resize(start + rl, 0);
                    let rec = &mut self.buf[start..];
                    for (f, src) in from.iter().enumerate() {
                        if k.xyz.contains(&f) {
                            continue;
                        }
                        let v = src.map_or(0.0, |s| self.like.get_f64(batch.record(i), s));
                        k.set_f64(rec, f, v);
                    }
                    k.set_position(rec, p);
                }
            }
        }
        self.out.write_all(&self.buf).map_err(|e| self.out.err(e))
    }

    fn finish(self: Box<Self>, _extras: &Extras) -> Result<(), IoError> {
        self.tally.check(self.out.target())?;
        self.out.commit()
    }

    fn splittable(&self) -> bool {
        true
    }

    fn finish_body(self: Box<Self>) -> Result<BodyStats, IoError> {
        let points = self.tally.written();
        self.out.commit_unsynced()?;
        Ok(BodyStats::count(points))
    }

    fn append_body(&mut self, path: &Path, stats: &BodyStats) -> Result<(), IoError> {
        self.tally.add_body(self.out.target(), stats)?;
        self.out.append_file(path)?;
        Ok(())
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
