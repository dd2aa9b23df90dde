//! The streaming LAS/LAZ writer.

use std::io::{Seek, SeekFrom, Write};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use glam::DVec3;
use laz::{LasZipCompressor, LazVlr, LazVlrBuilder};

use super::foreign::{self, Slot};
use super::layout::{
    self, BASE_LEN, VLR_HEADER, at, classification_byte, get_f64, get_i32, get_u16, get_u32,
    get_u64, is_extended, put, return_number, vlr_bytes,
};
use super::{LASZIP_RECORD, LASZIP_USER, LAZ_CHUNK_SIZE, LasMeta, LasVlr, Piece, laz_error};
use crate::io::tally::{Tally, check_batch};
use crate::io::{
    AtomicFile, BodyStats, Extras, Format, IoError, Meta, NormalField, NormalNames, Sink,
    SinkOptions, SourceInfo, Trailer,
};
use crate::points::{
    Endian, FLAG_NOISE, PointBatch, Rounding, ScalarType, Schema, integer_toward, write_scalar,
};

/// Where the points go: straight to the file, or through a LAZ compressor.
enum Out {
    Plain(AtomicFile),
    Laz(Box<LasZipCompressor<'static, AtomicFile>>),
}

/// How records of the source become LAS records.
enum Conv {
    /// The source record is a LAS record of this layout, possibly followed by extra bytes the
    /// sink appends (written normals): copy it, zero the rest, rewrite X, Y, Z.
    Same,
    /// Another layout: a fresh PDRF 6–8 record; `(source field, target offset)` per extra
    /// field, `(source field, slot)` per field mapped onto a core dimension.
    Foreign(Vec<(usize, usize)>, Vec<(usize, Slot)>),
}

/// What a sink writes before the points, and how.
struct Plan {
    /// Public header block (counts, bounds and offsets patched at the end).
    header: Vec<u8>,
    /// VLRs and the bytes up to the point data.
    vlrs: Vec<u8>,
    /// Number of VLRs in `vlrs`.
    vlr_count: u32,
    conv: Conv,
    /// Scale and offset, unless chosen from the first batch.
    frame: Option<Frame>,
    /// Fill the legacy 32-bit counts.
    legacy: bool,
    /// The LASzip VLR of compressed output.
    laz: Option<LazVlr>,
    /// Where the written normals go ([`SinkOptions::normals`]).
    normals: Vec<NormalSlot>,
}

/// Where one written normal value goes in an output record: a scalar extra-bytes field at
/// `offset` of type `ty`, storing `(value − add) / scale` (1 and 0 unless the field's
/// descriptor scales it).
#[derive(Debug, Clone, Copy)]
struct NormalSlot {
    offset: usize,
    ty: ScalarType,
    scale: f64,
    add: f64,
    field: NormalField,
}

/// The Extra Bytes VLR (LASF_Spec, record 4) with `payload`, or an error when it does not fit a
/// VLR's 16-bit length.
fn extra_bytes_vlr(path: &Path, description: &str, payload: &[u8]) -> Result<Vec<u8>, IoError> {
    if payload.len() > usize::from(u16::MAX) {
        return Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: format!(
                "{} extra-bytes descriptors do not fit one Extra Bytes VLR",
                payload.len() / 192
            ),
        });
    }
    Ok(vlr_bytes("LASF_Spec", 4, description, payload, false))
}

/// Scale and offset of X, Y, Z.
#[derive(Debug, Clone, Copy)]
struct Frame {
    scale: [f64; 3],
    offset: [f64; 3],
}

/// Streaming LAS/LAZ writer.
pub struct LasSink {
    out: Out,
    target: PathBuf,
    header: Vec<u8>,
    minor: u8,
    format: u8,
    record_len: usize,
    frame: Option<Frame>,
    conv: Conv,
    like: Schema,
    /// Fill the legacy (32-bit) point counts.
    legacy: bool,
    noise: bool,
    /// How moved coordinates round to what the output stores ([`SinkOptions::rounding`]).
    rounding: Rounding,
    /// Where the written normals go.
    normals: Vec<NormalSlot>,
    /// Start of the waveform data packet record in the source (0 if none).
    source_waveform: u64,
    tally: Tally,
    by_return: [u64; 15],
    min: [i32; 3],
    max: [i32; 3],
    buf: Vec<u8>,
    /// A write failed; the file is unusable.
    failed: bool,
}

/// Returns the LASzip VLR payload `laz` can compress with: the source's (with a variable chunk
/// size made fixed), or `None` when it cannot.
fn reusable_laszip(vlr: &LasVlr) -> Option<(Vec<u8>, LazVlr)> {
    let mut raw = vlr.raw.clone();
    let d = VLR_HEADER;
    if raw.len() < d + 16 {
        return None;
    }
    let chunk = get_u32(&raw, d + 12);
    if chunk == 0 || chunk == u32::MAX {
        put(&mut raw, d + 12, &LAZ_CHUNK_SIZE.to_le_bytes());
    }
    let parsed = catch_unwind(|| LazVlr::from_buffer(&raw[d..]).ok()).ok()??;
    let usable = catch_unwind(|| {
        LasZipCompressor::new(std::io::Cursor::new(Vec::<u8>::new()), parsed.clone()).is_ok()
    })
    .unwrap_or(false);
    usable.then_some((raw, parsed))
}

/// A new LASzip VLR for `format` with `extra` extra bytes.
fn new_laszip(path: &Path, format: u8, extra: usize) -> Result<(Vec<u8>, LazVlr), IoError> {
    let unsupported = |e: String| IoError::Unsupported {
        path: path.to_path_buf(),
        detail: format!("LAZ compression of point format {format}: {e}"),
    };
    let extra = u16::try_from(extra).map_err(|e| unsupported(e.to_string()))?;
    let vlr = LazVlrBuilder::default()
        .with_point_format(format, extra)
        .map_err(|e| unsupported(e.to_string()))?
        .build();
    let mut data = Vec::new();
    vlr.write_to(&mut data).map_err(|e| IoError::io(path, e))?;
    Ok((
        vlr_bytes(
            LASZIP_USER,
            LASZIP_RECORD,
            LazVlr::DESCRIPTION,
            &data,
            false,
        ),
        vlr,
    ))
}

/// Today's (day of year, year), UTC.
fn today() -> (u16, u16) {
    let mut days = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs() / 86_400);
    let mut year = 1970u64;
    loop {
        let leap =
            (year.is_multiple_of(4) && !year.is_multiple_of(100)) || year.is_multiple_of(400);
        let len = if leap { 366 } else { 365 };
        if days < len {
            break;
        }
        days -= len;
        year += 1;
    }
    (days as u16 + 1, year as u16)
}

/// `10^k` computed exactly for small `k`.
fn pow10(k: i32) -> f64 {
    if k >= 0 {
        10f64.powi(k)
    } else {
        1.0 / 10f64.powi(-k)
    }
}

/// The frame of a fresh file, from the positions of its first batch (see the module docs).
fn choose_frame(positions: &[DVec3]) -> Frame {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for p in positions.iter().filter(|p| p.is_finite()) {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    if lo.x > hi.x {
        return Frame {
            scale: [0.001; 3],
            offset: [0.0; 3],
        };
    }
    let extent = (hi - lo).max_element();
    let k = if extent > 0.0 {
        (libm::log10(extent).ceil() as i32 - 6).clamp(-9, -3)
    } else {
        -3
    };
    let scale = pow10(k);
    let unit = pow10(k + 6);
    let round_down = |v: f64| {
        if unit >= 1.0 {
            (v / unit).floor() * unit
        } else {
            let inv = (1.0 / unit).round();
            (v * inv).floor() / inv
        }
    };
    Frame {
        scale: [scale; 3],
        offset: [round_down(lo.x), round_down(lo.y), round_down(lo.z)],
    }
}

/// A quantised coordinate (an integer-valued `q`, `(v − offset) / scale` rounded) as LAS
/// stores it; `None` when it is not finite or outside the 32-bit range.
fn stored_i32(q: f64) -> Option<i32> {
    (q.is_finite() && q >= f64::from(i32::MIN) && q <= f64::from(i32::MAX)).then_some(q as i32)
}

impl LasSink {
    /// Creates a sink that writes `count` points laid out like `like`; see the module docs for what
    /// is kept and how a non-LAS source is written. `.laz` in `path` means compressed output,
    /// `.las` uncompressed, anything else as the source was.
    ///
    /// # Errors
    /// As [`LasSink::create_as`].
    pub fn create(
        path: &Path,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<LasSink, IoError> {
        let compress = match Format::from_path(path) {
            Ok(Format::Laz) => true,
            Ok(Format::Las) => false,
            _ => matches!(&like.meta, Meta::Las(m) if m.compressed),
        };
        Self::create_as(path, like, count, options, compress)
    }

    /// [`LasSink::create`], compressed (LAZ) or not as `compress` says, whatever the path.
    ///
    /// # Errors
    /// The directory is not writable; more than 2³²−1 points for a LAS version below 1.4; a point
    /// format `laz` cannot compress.
    pub fn create_as(
        path: &Path,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
        compress: bool,
    ) -> Result<LasSink, IoError> {
        let file = AtomicFile::create_seekable(path, options.temp_dir.as_deref())?;
        LasSink::new(file, like, count, options, compress)
    }

    /// [`LasSink::create_as`] writing to `file`, which must seek (a file, a spooled stream,
    /// memory: see [`AtomicFile::create_seekable`]).
    ///
    /// # Errors
    /// As [`LasSink::create_as`].
    pub fn new(
        mut file: AtomicFile,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
        compress: bool,
    ) -> Result<LasSink, IoError> {
        let shown = file.target().to_path_buf();
        let path = shown.as_path();
        let source = match &like.meta {
            Meta::Las(m) if m.record_len == like.schema.record_len => Some(m),
            _ => None,
        };
        let Plan {
            mut header,
            vlrs: vlr_block,
            vlr_count,
            conv,
            frame,
            legacy,
            laz,
            normals,
        } = match source {
            Some(m) => Self::like_las(path, m, &like.schema, compress, options.normals)?,
            None => Self::fresh(path, &like.schema, compress, options.normals)?,
        };
        let minor = header[at::VERSION + 1];
        let format = header[at::FORMAT] & 0x3f;
        let record_len = usize::from(get_u16(&header, at::RECORD_LEN));
        if minor < 4 && count > u64::from(u32::MAX) && !options.body {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: format!("{count} points need LAS 1.4 (the source is LAS 1.{minor})"),
            });
        }
        let data_start = header.len() + vlr_block.len();
        let data_start32 = u32::try_from(data_start).map_err(|_| {
            IoError::invalid(path, "the VLRs exceed the 4 GiB a LAS header can address")
        })?;
        put(&mut header, at::POINT_DATA, &data_start32.to_le_bytes());
        put(&mut header, at::VLR_COUNT, &vlr_count.to_le_bytes());
        let source_waveform = match source {
            Some(m) if m.version.1 >= 3 => get_u64(&m.header, at::WAVEFORM),
            _ => 0,
        };

        // A body holds the point records alone.
        if !options.body {
            file.write_all(&header).map_err(|e| file.err(e))?;
            file.write_all(&vlr_block).map_err(|e| file.err(e))?;
        }
        let out = match laz {
            Some(vlr) => Out::Laz(Box::new(
                LasZipCompressor::new(file, vlr).map_err(|e| laz_error(path, e))?,
            )),
            None => Out::Plain(file),
        };
        Ok(LasSink {
            out,
            target: path.to_path_buf(),
            header,
            minor,
            format,
            record_len,
            frame,
            conv,
            like: like.schema.clone(),
            legacy,
            noise: options.noise_flag,
            rounding: options.rounding,
            normals,
            source_waveform,
            tally: Tally::new(count),
            by_return: [0; 15],
            min: [i32::MAX; 3],
            max: [i32::MIN; 3],
            buf: Vec::new(),
            failed: false,
        })
    }

    /// The plan for a LAS source: its header and VLRs; with `normals`, the normal fields the
    /// record already has (by name, [`NormalField::aliases`]) and extra bytes for the others,
    /// described in the Extra Bytes VLR (extended, or added).
    fn like_las(
        path: &Path,
        m: &LasMeta,
        schema: &Schema,
        compress: bool,
        normals: bool,
    ) -> Result<Plan, IoError> {
        let mut header = m.header.clone();
        let mut block = Vec::new();
        let mut n = 0u32;
        let mut laz = None;
        let eb = m.vlrs.iter().find(|v| v.is("LASF_Spec", 4));
        let extra = layout::extra_layout(m.format, m.record_len, eb.map(|v| v.data()));
        let mut slots = Vec::new();
        let mut payload = extra.descriptors.clone();
        let mut record_len = m.record_len;
        if normals {
            // Bytes past the described ones get an undocumented descriptor first, so the new
            // descriptors describe the bytes they are for.
            let mut gap = m.record_len - extra.end;
            while gap > 0 {
                let k = gap.min(255);
                payload.extend_from_slice(&layout::undocumented_descriptor(k as u8));
                gap -= k;
            }
            for f in NormalField::ALL {
                let slot = match f.find(schema) {
                    Some(i) => {
                        let field = &schema.fields[i];
                        let (scale, add) = extra
                            .scaled
                            .iter()
                            .find(|s| s.0 == field.offset)
                            .map_or((1.0, 0.0), |s| (s.1, s.2));
                        NormalSlot {
                            offset: field.offset,
                            ty: field.ty,
                            scale,
                            add,
                            field: f,
                        }
                    }
                    None => {
                        payload.extend_from_slice(&layout::extra_descriptor(
                            f.name(NormalNames::Las),
                            f.ty(),
                        ));
                        record_len += f.ty().size();
                        NormalSlot {
                            offset: record_len - f.ty().size(),
                            ty: f.ty(),
                            scale: 1.0,
                            add: 0.0,
                            field: f,
                        }
                    }
                };
                slots.push(slot);
            }
        }
        let grown = record_len != m.record_len;
        let record_len16 = u16::try_from(record_len).map_err(|_| IoError::Unsupported {
            path: path.to_path_buf(),
            detail: format!("a {record_len}-byte LAS point record (the limit is 65535)"),
        })?;
        let mut eb_written = false;
        for v in m.vlrs.iter().filter(|v| !v.is_copc_layout()) {
            if grown && v.is("LASF_Spec", 4) {
                if !eb_written {
                    block.extend(extra_bytes_vlr(path, &v.description(), &payload)?);
                    n += 1;
                    eb_written = true;
                }
                continue;
            }
            if v.is_laszip() {
                // A record that grows needs a LASzip VLR for its new length.
                if compress
                    && !grown
                    && laz.is_none()
                    && let Some((raw, vlr)) = reusable_laszip(v)
                {
                    block.extend_from_slice(&raw);
                    n += 1;
                    laz = Some(vlr);
                }
                continue;
            }
            block.extend_from_slice(&v.raw);
            n += 1;
        }
        if grown && !eb_written {
            block.extend(extra_bytes_vlr(path, "Extra Bytes", &payload)?);
            n += 1;
        }
        if compress && laz.is_none() {
            let extra_bytes = record_len - BASE_LEN[usize::from(m.format)];
            let (raw, vlr) = new_laszip(path, m.format, extra_bytes)?;
            block.extend_from_slice(&raw);
            n += 1;
            laz = Some(vlr);
        }
        block.extend_from_slice(&m.vlr_padding);
        put(&mut header, at::RECORD_LEN, &record_len16.to_le_bytes());
        header[at::FORMAT] = match (compress, m.compressed) {
            (true, true) | (false, false) => header[at::FORMAT],
            (true, false) => m.format | 0x80,
            (false, true) => m.format,
        };
        let legacy = m.version.1 < 4 || get_u32(&m.header, at::LEGACY_COUNT) != 0 || m.count == 0;
        let frame = Frame {
            scale: m.scale,
            offset: m.offset,
        };
        Ok(Plan {
            header,
            vlrs: block,
            vlr_count: n,
            conv: Conv::Same,
            frame: Some(frame),
            legacy,
            laz,
            normals: slots,
        })
    }

    /// The plan for a source of another format: LAS 1.4 PDRF 6 plus one extra field per non-xyz
    /// field of `schema`; with `normals`, the normal fields among them (by name) and extra bytes
    /// for the others.
    fn fresh(path: &Path, schema: &Schema, compress: bool, normals: bool) -> Result<Plan, IoError> {
        let mapping = foreign::map(schema);
        let format = mapping.format;
        let base = BASE_LEN[usize::from(format)];
        let mut extras = Vec::new();
        let mut descriptors = Vec::new();
        let mut at_ = base;
        for (i, name) in &mapping.extras {
            let f = &schema.fields[*i];
            extras.push((*i, at_));
            descriptors.extend_from_slice(&layout::extra_descriptor(name, f.ty));
            at_ += f.ty.size();
        }
        let mut slots = Vec::new();
        for f in NormalField::ALL.iter().filter(|_| normals) {
            let existing = f
                .find(schema)
                .and_then(|i| extras.iter().find(|e| e.0 == i).map(|e| (e.1, i)));
            let (offset, ty) = match existing {
                Some((offset, i)) => (offset, schema.fields[i].ty),
                None => {
                    descriptors.extend_from_slice(&layout::extra_descriptor(
                        f.name(NormalNames::Las),
                        f.ty(),
                    ));
                    at_ += f.ty().size();
                    (at_ - f.ty().size(), f.ty())
                }
            };
            slots.push(NormalSlot {
                offset,
                ty,
                scale: 1.0,
                add: 0.0,
                field: *f,
            });
        }
        let record_len = u16::try_from(at_).map_err(|_| IoError::Unsupported {
            path: path.to_path_buf(),
            detail: format!("a {at_}-byte LAS point record (the limit is 65535)"),
        })?;
        let mut block = Vec::new();
        let mut n = 0u32;
        if !descriptors.is_empty() {
            if descriptors.len() > usize::from(u16::MAX) {
                return Err(IoError::Unsupported {
                    path: path.to_path_buf(),
                    detail: format!("{} extra fields in one Extra Bytes VLR", extras.len()),
                });
            }
            block.extend(vlr_bytes(
                "LASF_Spec",
                4,
                "Extra Bytes",
                &descriptors,
                false,
            ));
            n += 1;
        }
        let laz = if compress {
            let (raw, vlr) = new_laszip(path, format, at_ - base)?;
            block.extend_from_slice(&raw);
            n += 1;
            Some(vlr)
        } else {
            None
        };
        let mut h = vec![0u8; 375];
        put(&mut h, 0, b"LASF");
        put(&mut h, at::GLOBAL_ENCODING, &0x10u16.to_le_bytes());
        h[at::VERSION] = 1;
        h[at::VERSION + 1] = 4;
        put(&mut h, at::SYSTEM_ID, b"OTHER");
        let software = format!("qemd {}", env!("CARGO_PKG_VERSION"));
        put(
            &mut h,
            at::SOFTWARE,
            &software.as_bytes()[..software.len().min(32)],
        );
        let (day, year) = today();
        put(&mut h, at::DAY, &day.to_le_bytes());
        put(&mut h, at::DAY + 2, &year.to_le_bytes());
        put(&mut h, at::HEADER_SIZE, &375u16.to_le_bytes());
        h[at::FORMAT] = if compress { format | 0x80 } else { format };
        put(&mut h, at::RECORD_LEN, &record_len.to_le_bytes());
        for a in 0..3 {
            put(&mut h, at::SCALE + 8 * a, &0.001f64.to_le_bytes());
        }
        Ok(Plan {
            header: h,
            vlrs: block,
            vlr_count: n,
            conv: Conv::Foreign(extras, mapping.core),
            frame: None,
            legacy: false,
            laz,
            normals: slots,
        })
    }

    /// The output file, with the compressor (if any) finished.
    fn into_file(out: Out, path: &Path) -> Result<AtomicFile, IoError> {
        match out {
            Out::Plain(f) => Ok(f),
            Out::Laz(mut c) => {
                catch_unwind(AssertUnwindSafe(|| c.done()))
                    .unwrap_or_else(|_| Err(std::io::Error::other("the LAZ compressor failed")))
                    .map_err(|e| IoError::io(path, e))?;
                Ok(c.into_inner())
            }
        }
    }
}

impl Sink for LasSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        if self.failed {
            return Err(IoError::invalid(&self.target, "an earlier write failed"));
        }
        check_batch(&self.target, &self.like, batch)?;
        let first = self.tally.written();
        self.tally.add(&self.target, batch.len())?;
        if batch.is_empty() {
            return Ok(());
        }
        let frame = *self
            .frame
            .get_or_insert_with(|| choose_frame(&batch.positions));
        let rl = self.record_len;
        let class_at = classification_byte(self.format);
        self.buf.clear();
        for (i, &p) in batch.positions.iter().enumerate() {
            let start = self.buf.len();
            let src = batch.record(i);
            match &self.conv {
                Conv::Same => {
                    self.buf.extend_from_slice(src);
                    self.buf.resize(start + rl, 0);
                }
                Conv::Foreign(extras, core) => {
                    self.buf.resize(start + rl, 0);
                    for &(f, to) in extras {
                        let field = &self.like.fields[f];
                        let n = field.ty.size();
                        let dst = &mut self.buf[start + to..start + to + n];
                        dst.copy_from_slice(&src[field.offset..field.offset + n]);
                        if self.like.endian == Endian::Big {
                            dst.reverse();
                        }
                    }
                    for &(f, slot) in core {
                        let v = self.like.get_f64(src, f);
                        foreign::store(&mut self.buf[start..start + rl], slot, v).map_err(|e| {
                            IoError::invalid(
                                &self.target,
                                format!(
                                    "point {}: {} = {e}",
                                    first + i as u64,
                                    self.like.fields[f].name
                                ),
                            )
                        })?;
                    }
                }
            }
            let rec = &mut self.buf[start..start + rl];
            let v = p.to_array();
            let (s, o) = (frame.scale, frame.offset);
            let t: [f64; 3] = std::array::from_fn(|k| (v[k] - o[k]) / s[k]);
            let stored = if matches!(self.conv, Conv::Same) {
                // The record holds the input's integers, in the same frame: an axis that did
                // not move keeps its integer.
                let old: [f64; 3] = std::array::from_fn(|k| f64::from(get_i32(rec, 4 * k)));
                let at: [f64; 3] = std::array::from_fn(|k| {
                    let kept = (old[k] * s[k] + o[k]).to_bits() == v[k].to_bits();
                    if kept { old[k] } else { t[k] }
                });
                self.rounding
                    .store(at, old, s, |_, x, towards| integer_toward(x, towards))
            } else {
                t.map(f64::round)
            };
            for (axis, &v) in v.iter().enumerate() {
                let (s, o) = (s[axis], o[axis]);
                let q = stored_i32(stored[axis]).ok_or_else(|| {
                    let name = ["x", "y", "z"][axis];
                    IoError::invalid(
                        &self.target,
                        format!(
                            "point {}: {name} = {v} cannot be stored with scale {s} and offset \
                             {o} (not finite or outside the 32-bit range)",
                            first + i as u64
                        ),
                    )
                })?;
                put(rec, 4 * axis, &q.to_le_bytes());
                self.min[axis] = self.min[axis].min(q);
                self.max[axis] = self.max[axis].max(q);
            }
            if self.noise && batch.flag(i) & FLAG_NOISE != 0 {
                rec[class_at] = if is_extended(self.format) {
                    7
                } else {
                    (rec[class_at] & 0xe0) | 7
                };
            }
            if !self.normals.is_empty() {
                let n = batch.normal(i);
                for s in &self.normals {
                    let v = (s.field.value(&n) - s.add) / s.scale;
                    let end = s.offset + s.ty.size();
                    write_scalar(&mut rec[s.offset..end], s.ty, Endian::Little, v);
                }
            }
            let r = return_number(self.format, rec);
            if (1..=15).contains(&r) {
                self.by_return[r - 1] += 1;
            }
        }
        let buf = &self.buf;
        let r = match &mut self.out {
            Out::Plain(f) => f.write_all(buf),
            Out::Laz(c) => catch_unwind(AssertUnwindSafe(|| c.compress_many(buf)))
                .unwrap_or_else(|_| Err(std::io::Error::other("the LAZ compressor failed"))),
        };
        r.map_err(|e| {
            self.failed = true;
            IoError::io(&self.target, e)
        })
    }

    fn finish(self: Box<Self>, extras: &Extras) -> Result<(), IoError> {
        let this = *self;
        if this.failed {
            return Err(IoError::invalid(&this.target, "an earlier write failed"));
        }
        this.tally.check(&this.target)?;
        let path = this.target.clone();
        let io = |e| IoError::io(&path, e);
        let mut file = Self::into_file(this.out, &path)?;
        let mut h = this.header;
        let mut pos = file.seek(SeekFrom::End(0)).map_err(io)?;

        // What follows the points, with the source offsets mapped to the new ones.
        let mut first_evlr = 0u64;
        let mut evlrs = 0u32;
        let mut waveform = 0u64;
        if let Trailer::Las(t) = &extras.trailer {
            let mut old = t.start;
            for piece in &t.pieces {
                let len = piece.len();
                let keep = match piece {
                    Piece::Evlr(v) => !v.is_copc_layout(),
                    Piece::Bytes(_) => true,
                };
                if keep {
                    if (old..old + len).contains(&this.source_waveform) {
                        waveform = pos + (this.source_waveform - old);
                    }
                    match piece {
                        Piece::Evlr(v) => {
                            if evlrs == 0 {
                                first_evlr = pos;
                            }
                            evlrs += 1;
                            file.write_all(&v.raw).map_err(io)?;
                        }
                        Piece::Bytes(b) => file.write_all(b).map_err(io)?,
                    }
                    pos += len;
                }
                old += len;
            }
        }

        let n = this.tally.written();
        let legacy = this.legacy && n <= u64::from(u32::MAX);
        put(
            &mut h,
            at::LEGACY_COUNT,
            &(if legacy { n as u32 } else { 0 }).to_le_bytes(),
        );
        for r in 0..5 {
            let v = if legacy { this.by_return[r] as u32 } else { 0 };
            put(&mut h, at::LEGACY_BY_RETURN + 4 * r, &v.to_le_bytes());
        }
        let frame = this.frame.unwrap_or(Frame {
            scale: [
                get_f64(&h, at::SCALE),
                get_f64(&h, at::SCALE + 8),
                get_f64(&h, at::SCALE + 16),
            ],
            offset: [
                get_f64(&h, at::OFFSET),
                get_f64(&h, at::OFFSET + 8),
                get_f64(&h, at::OFFSET + 16),
            ],
        });
        for a in 0..3 {
            put(&mut h, at::SCALE + 8 * a, &frame.scale[a].to_le_bytes());
            put(&mut h, at::OFFSET + 8 * a, &frame.offset[a].to_le_bytes());
            let (lo, hi) = if n == 0 {
                (0.0, 0.0)
            } else {
                (
                    f64::from(this.min[a]) * frame.scale[a] + frame.offset[a],
                    f64::from(this.max[a]) * frame.scale[a] + frame.offset[a],
                )
            };
            put(&mut h, at::BOUNDS + 16 * a, &hi.to_le_bytes());
            put(&mut h, at::BOUNDS + 16 * a + 8, &lo.to_le_bytes());
        }
        if this.minor >= 3 {
            put(&mut h, at::WAVEFORM, &waveform.to_le_bytes());
        }
        if this.minor >= 4 {
            put(&mut h, at::FIRST_EVLR, &first_evlr.to_le_bytes());
            put(&mut h, at::EVLR_COUNT, &evlrs.to_le_bytes());
            put(&mut h, at::COUNT, &n.to_le_bytes());
            for r in 0..15 {
                put(
                    &mut h,
                    at::BY_RETURN + 8 * r,
                    &this.by_return[r].to_le_bytes(),
                );
            }
        }
        file.seek(SeekFrom::Start(0)).map_err(io)?;
        file.write_all(&h).map_err(io)?;
        file.commit()
    }

    /// Plain records, with the scale and offset known before the first point (a LAS source's):
    /// a body's records are then those the whole file would hold. LAZ compresses in chunks
    /// across bodies, and a frame chosen from the first points is not known to a later body.
    fn splittable(&self) -> bool {
        matches!(self.out, Out::Plain(_)) && self.frame.is_some()
    }

    fn finish_body(self: Box<Self>) -> Result<BodyStats, IoError> {
        let this = *self;
        if this.failed {
            return Err(IoError::invalid(&this.target, "an earlier write failed"));
        }
        let points = this.tally.written();
        let file = Self::into_file(this.out, &this.target)?;
        file.commit_unsynced()?;
        Ok(BodyStats {
            points,
            by_return: this.by_return,
            bounds: (points > 0).then_some((this.min, this.max)),
        })
    }

    fn append_body(&mut self, path: &Path, stats: &BodyStats) -> Result<(), IoError> {
        let Out::Plain(file) = &mut self.out else {
            return Err(IoError::Unsupported {
                path: self.target.clone(),
                detail: "LAZ output cannot be written in separate bodies".into(),
            });
        };
        if self.failed {
            return Err(IoError::invalid(&self.target, "an earlier write failed"));
        }
        self.tally.add_body(&self.target, stats)?;
        if let Err(e) = file.append_file(path) {
            self.failed = true;
            return Err(e);
        }
        for (n, add) in self.by_return.iter_mut().zip(stats.by_return) {
            *n += add;
        }
        if let Some((lo, hi)) = stats.bounds {
            for a in 0..3 {
                self.min[a] = self.min[a].min(lo[a]);
                self.max[a] = self.max[a].max(hi[a]);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_for_utm_and_small_objects() {
        let f = choose_frame(&[
            DVec3::new(500_123.456, 5_000_321.5, 101.25),
            DVec3::new(500_923.456, 5_000_921.5, 140.0),
        ]);
        assert_eq!(f.scale, [0.001; 3]);
        assert_eq!(f.offset, [500_000.0, 5_000_000.0, 0.0]);
        let f = choose_frame(&[DVec3::new(-0.07, 0.03, 0.1), DVec3::new(0.08, 0.18, 0.2)]);
        assert_eq!(f.scale, [1e-6; 3]);
        assert_eq!(f.offset, [-1.0, 0.0, 0.0]);
        let f = choose_frame(&[DVec3::new(3.25, 4.0, 5.0)]);
        assert_eq!(f.scale, [0.001; 3]);
        assert_eq!(stored_i32((1e300f64 / 0.001).round()), None);
        assert_eq!(stored_i32(f64::NAN), None);
        assert_eq!(
            stored_i32(((500_000.001 - 500_000.0) / 0.001f64).round()),
            Some(1)
        );
    }

    #[test]
    fn today_is_plausible() {
        let (day, year) = today();
        assert!((1..=366).contains(&day) && year >= 2024, "{day} {year}");
    }
}
