//! The streaming LAS/LAZ reader.

use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use glam::DVec3;
use laz::{LasZipDecompressor, LazVlr};

use super::chunks::{self, Chunks};
use super::layout::{
    self, BASE_LEN, EVLR_HEADER, VLR_HEADER, at, get_i32, get_u16, get_u32, get_u64,
    min_header_size,
};
use super::{LasMeta, LasTrailer, LasVlr, Piece, guarded, laz_error, laz_io_error, read_at};
use crate::io::reader::{Reopener, seek_record};
use crate::io::{Extras, Format, Input, IoError, Meta, Source, SourceInfo, Trailer};
use crate::points::PointBatch;

/// Where the pieces after the points lie in the source: `(offset, length, is an EVLR)`.
type TailPlan = Vec<(u64, u64, bool)>;

/// The point reader: raw records or a LAZ decompressor.
enum Points {
    /// No point to read.
    Empty(BufReader<Input>),
    /// Uncompressed records.
    Plain(BufReader<Input>),
    /// LASzip-compressed records.
    Laz(Box<LasZipDecompressor<'static, BufReader<Input>>>),
    /// A LAZ decoder panicked; its state is lost.
    Broken,
}

/// Streaming LAS/LAZ reader.
pub struct LasSource {
    info: SourceInfo,
    points: Points,
    scale: [f64; 3],
    offset: [f64; 3],
    read: u64,
    total: u64,
    tail: TailPlan,
    /// Where the point records start.
    data_start: u64,
    /// True when [`Source::seek_point`] can move (plain records, or LAZ with a chunk table of
    /// fixed-size chunks).
    seekable: bool,
    /// Opens the input again to read the tail after a decoder panic.
    again: Reopener,
}

impl LasSource {
    /// Opens a LAS or LAZ (or COPC) file, validates its header, VLRs, EVLRs and point data size,
    /// and positions the reader at the first point.
    ///
    /// # Errors
    /// [`IoError::Header`] when the file is empty, not LAS, or its header or VLRs are malformed;
    /// [`IoError::Truncated`] when the file is shorter than its header, VLRs, points or EVLRs
    /// declare (a header claiming more points than the file holds);
    /// [`IoError::Unsupported`] for LAS versions other than 1.0–1.4 or point formats above 10;
    /// [`IoError::Invalid`] for bad LAZ data.
    pub fn open(path: &Path) -> Result<LasSource, IoError> {
        LasSource::new(Input::from_path(path)?)
    }

    /// [`LasSource::open`] on any [`Input`] whose length is known.
    ///
    /// # Errors
    /// As [`LasSource::open`]; an input of unknown length.
    pub fn new(mut file: Input) -> Result<LasSource, IoError> {
        let owned = file.name().to_path_buf();
        let path = owned.as_path();
        let again = file.reopener();
        let size = file
            .len()
            .ok_or_else(|| IoError::invalid(path, "a LAS file needs a known size, not a stream"))?;
        let io = |e| IoError::io(path, e);
        if size == 0 {
            return Err(IoError::header(path, "empty file, not a LAS file"));
        }
        let prefix = read_at(&mut file, 0, size.min(227) as usize).map_err(io)?;
        if prefix.len() < 4 || &prefix[..4] != b"LASF" {
            return Err(IoError::header(
                path,
                "not a LAS file (no `LASF` signature)",
            ));
        }
        if prefix.len() < 227 {
            return Err(IoError::truncated(
                path,
                format!("the file ends inside the public header ({size} of 227 bytes)"),
            ));
        }
        let version = (prefix[at::VERSION], prefix[at::VERSION + 1]);
        if version.0 != 1 || version.1 > 4 {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: format!("LAS version {}.{}", version.0, version.1),
            });
        }
        let header_size = usize::from(get_u16(&prefix, at::HEADER_SIZE));
        let need = min_header_size(version.1);
        if header_size < need {
            return Err(IoError::header(
                path,
                format!(
                    "header size {header_size} is smaller than the {need} bytes of LAS {}.{}",
                    version.0, version.1
                ),
            ));
        }
        if header_size as u64 > size {
            return Err(IoError::truncated(
                path,
                format!("the file ends inside the {header_size}-byte public header"),
            ));
        }
        let header = read_at(&mut file, 0, header_size).map_err(io)?;
        let raw = las::raw::Header::read_from(&header[..])
            .map_err(|e| IoError::header(path, e.to_string()))?;

        let format_byte = raw.point_data_record_format;
        let compressed = format_byte & 0x80 != 0;
        let format = format_byte & 0x3f;
        if format > 10 {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: format!("point data record format {format}"),
            });
        }
        let record_len = usize::from(raw.point_data_record_length);
        let base = BASE_LEN[usize::from(format)];
        if record_len < base {
            return Err(IoError::header(
                path,
                format!(
                    "point record length {record_len} is shorter than the {base} bytes of \
                     point format {format}"
                ),
            ));
        }
        let scale = [raw.x_scale_factor, raw.y_scale_factor, raw.z_scale_factor];
        let offset = [raw.x_offset, raw.y_offset, raw.z_offset];
        if scale.iter().any(|s| !s.is_finite() || *s == 0.0)
            || offset.iter().any(|o| !o.is_finite())
        {
            return Err(IoError::header(
                path,
                format!("scale {scale:?} and offset {offset:?} must be finite, scale non-zero"),
            ));
        }
        let data_start = u64::from(raw.offset_to_point_data);
        if data_start < header_size as u64 {
            return Err(IoError::header(
                path,
                format!(
                    "offset to point data {data_start} lies inside the {header_size}-byte header"
                ),
            ));
        }
        if data_start > size {
            return Err(IoError::truncated(
                path,
                format!("the point data should start at byte {data_start}, the file has {size}"),
            ));
        }

        // VLRs and whatever lies between them and the points.
        let block = read_at(
            &mut file,
            header_size as u64,
            (data_start - header_size as u64) as usize,
        )
        .map_err(io)?;
        let declared = raw.number_of_variable_length_records;
        let mut vlrs = Vec::new();
        let mut p = 0usize;
        for i in 0..declared {
            let fits = p + VLR_HEADER <= block.len()
                && p + VLR_HEADER + usize::from(get_u16(&block, p + 20)) <= block.len();
            if !fits {
                return Err(IoError::header(
                    path,
                    format!(
                        "VLR {} of {declared} does not fit before the point data at byte {data_start}",
                        i + 1
                    ),
                ));
            }
            let len = VLR_HEADER + usize::from(get_u16(&block, p + 20));
            vlrs.push(LasVlr {
                raw: block[p..p + len].to_vec(),
                extended: false,
            });
            p += len;
        }
        let vlr_padding = block[p..].to_vec();

        let legacy = u64::from(raw.number_of_point_records);
        let count = match raw.large_file {
            Some(l) if l.number_of_point_records != 0 => l.number_of_point_records,
            _ => legacy,
        };
        let extra = vlrs.iter().find(|v| v.is("LASF_Spec", 4)).map(|v| v.data());
        let schema = layout::schema(format, record_len, extra);

        let evlr = raw.evlr.unwrap_or_default();
        let waveform = raw.start_of_waveform_data_packet_record.unwrap_or(0);
        // A LAS 1.3 waveform data packet record is one EVLR; an offset outside the file is ignored.
        let waveform_evlr = version.1 == 3
            && waveform > data_start
            && waveform.saturating_add(EVLR_HEADER as u64) <= size;
        let tail_start = if compressed {
            let start = if evlr.number_of_evlrs > 0 {
                evlr.start_of_first_evlr
            } else if waveform_evlr {
                waveform
            } else {
                size
            };
            if start < data_start + 8 {
                return Err(IoError::header(
                    path,
                    format!("the first EVLR at byte {start} lies before the point data"),
                ));
            }
            start
        } else {
            count
                .checked_mul(record_len as u64)
                .and_then(|b| b.checked_add(data_start))
                .filter(|&end| end <= size)
                .ok_or_else(|| {
                    let held = (size - data_start) / record_len as u64;
                    IoError::truncated(
                        path,
                        format!(
                            "the header declares {count} points of {record_len} bytes but the \
                             file holds {held}"
                        ),
                    )
                })?
        };
        let first_evlr = if version.1 >= 4 && evlr.number_of_evlrs > 0 {
            Some((evlr.start_of_first_evlr, u64::from(evlr.number_of_evlrs)))
        } else if waveform_evlr && waveform >= tail_start {
            Some((waveform, 1))
        } else {
            None
        };
        let tail = plan_tail(path, &mut file, size, tail_start, first_evlr)?;
        let (points, seekable) = if compressed {
            open_laz(path, file, size, data_start, &vlrs, record_len, count)?
        } else {
            file.seek(SeekFrom::Start(data_start)).map_err(io)?;
            let reader = BufReader::with_capacity(1 << 16, file);
            if count == 0 {
                (Points::Empty(reader), false)
            } else {
                (Points::Plain(reader), true)
            }
        };

        let meta = LasMeta {
            header,
            vlrs,
            vlr_padding,
            version,
            format,
            record_len,
            compressed,
            scale,
            offset,
            count,
        };
        Ok(LasSource {
            info: SourceInfo {
                path: path.to_path_buf(),
                // A COPC file is a LAZ file to a reader.
                format: if compressed { Format::Laz } else { Format::Las },
                schema,
                len: Some(count),
                faces: None,
                meta: Meta::Las(meta),
            },
            points,
            scale,
            offset,
            read: 0,
            total: count,
            tail,
            data_start,
            seekable,
            again,
        })
    }

    /// The LAS header of the open file.
    pub fn meta(&self) -> &LasMeta {
        match &self.info.meta {
            Meta::Las(m) => m,
            _ => unreachable!("a LAS source always carries LAS meta"),
        }
    }
}

/// Splits `[tail_start, size)` into raw bytes and EVLRs, checking every EVLR fits in the file.
fn plan_tail(
    path: &Path,
    file: &mut Input,
    size: u64,
    tail_start: u64,
    first_evlr: Option<(u64, u64)>,
) -> Result<TailPlan, IoError> {
    let mut plan = TailPlan::new();
    let mut p = tail_start.min(size);
    if let Some((first, n)) = first_evlr {
        if first < tail_start || first > size {
            return Err(IoError::header(
                path,
                format!(
                    "the first EVLR should start at byte {first}, outside the bytes after the \
                     point data ({tail_start}..{size})"
                ),
            ));
        }
        if first > p {
            plan.push((p, first - p, false));
        }
        p = first;
        for i in 0..n {
            let short = || {
                IoError::truncated(
                    path,
                    format!(
                        "EVLR {} of {n} at byte {p} ends past the end of the file",
                        i + 1
                    ),
                )
            };
            if size - p < EVLR_HEADER as u64 {
                return Err(short());
            }
            let h = read_at(file, p, EVLR_HEADER).map_err(|e| IoError::io(path, e))?;
            let len = get_u64(&h, 20);
            if len > size - p - EVLR_HEADER as u64 {
                return Err(short());
            }
            plan.push((p, EVLR_HEADER as u64 + len, true));
            p += EVLR_HEADER as u64 + len;
        }
    }
    if p < size {
        plan.push((p, size - p, false));
    }
    Ok(plan)
}

/// Validates the LAZ framing (laszip VLR, chunk table against the point count) and starts a
/// decompressor at the first point.
fn open_laz(
    path: &Path,
    file: Input,
    size: u64,
    data_start: u64,
    vlrs: &[LasVlr],
    record_len: usize,
    count: u64,
) -> Result<(Points, bool), IoError> {
    let io = |e| IoError::io(path, e);
    let vlr = vlrs
        .iter()
        .find(|v| v.is_laszip())
        .ok_or_else(|| IoError::header(path, "compressed point format but no laszip VLR"))?;
    let laz_vlr = guarded(path, || {
        LazVlr::from_buffer(vlr.data())
            .map_err(|e| IoError::header(path, format!("bad laszip VLR: {e}")))
    })?;
    chunks::check_compressor(path, vlr.data(), &laz_vlr)?;
    if laz_vlr.items().is_empty() || laz_vlr.items_size() != record_len as u64 {
        return Err(IoError::header(
            path,
            format!(
                "the laszip VLR describes {}-byte points, the header {record_len}-byte ones",
                laz_vlr.items_size()
            ),
        ));
    }
    let mut reader = BufReader::with_capacity(1 << 16, file);
    if count == 0 {
        return Ok((Points::Empty(reader), false));
    }
    if size < data_start + 8 {
        return Err(IoError::truncated(
            path,
            "the file ends before the compressed point data",
        ));
    }
    let table_at = i64::from_le_bytes(
        read_at(&mut reader, data_start, 8)
            .map_err(io)?
            .try_into()
            .expect("8 bytes"),
    );
    // `LasZipDecompressor::seek` needs the table, and finds a point's place in its chunk by the
    // fixed chunk size.
    let seekable = table_at > data_start as i64 && !laz_vlr.uses_variable_size_chunks();
    if table_at > data_start as i64 {
        let table_at = table_at as u64;
        if size < 8 || table_at > size - 8 {
            return Err(IoError::truncated(
                path,
                format!("the LAZ chunk table at byte {table_at} lies past the end of the file"),
            ));
        }
        let h = read_at(&mut reader, table_at, 8).map_err(io)?;
        let chunks = u64::from(get_u32(&h, 4));
        if chunks > size - data_start {
            return Err(IoError::invalid(
                path,
                format!("bad LAZ chunk table: {chunks} chunks in {size} bytes"),
            ));
        }
        reader.seek(SeekFrom::Start(data_start)).map_err(io)?;
        let table = guarded(path, || {
            laz::laszip::ChunkTable::read_from(&mut reader, &laz_vlr)
                .map_err(|e| laz_error(path, e))
        })?;
        let capacity: u64 = if laz_vlr.uses_variable_size_chunks() {
            table
                .as_ref()
                .iter()
                .fold(0u64, |s, e| s.saturating_add(e.point_count))
        } else {
            chunks.saturating_mul(u64::from(laz_vlr.chunk_size()))
        };
        if count > capacity {
            return Err(IoError::truncated(
                path,
                format!(
                    "the header declares {count} points but the LAZ chunk table holds at most \
                     {capacity}"
                ),
            ));
        }
        if chunks::is_layered(&laz_vlr) {
            let bytes: Vec<u64> = table.as_ref().iter().map(|e| e.byte_count).collect();
            let first = data_start + 8;
            chunks::check_layers(
                path,
                &mut reader,
                &laz_vlr,
                first,
                record_len as u64,
                Chunks::Table(&bytes, table_at),
            )?;
        }
    } else if laz_vlr.uses_variable_size_chunks() {
        return Err(IoError::invalid(
            path,
            "variable-size LAZ chunks but no chunk table",
        ));
    } else if chunks::is_layered(&laz_vlr) {
        chunks::check_layers(
            path,
            &mut reader,
            &laz_vlr,
            data_start + 8,
            record_len as u64,
            Chunks::Walk {
                end: size,
                count,
                chunk_size: u64::from(laz_vlr.chunk_size()),
            },
        )?;
    }
    reader.seek(SeekFrom::Start(data_start)).map_err(io)?;
    let dec = guarded(path, || {
        LasZipDecompressor::new(reader, laz_vlr).map_err(|e| laz_error(path, e))
    })?;
    Ok((Points::Laz(Box::new(dec)), seekable))
}

impl Source for LasSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        let rl = self.info.schema.record_len;
        batch.clear(self.read);
        batch.record_len = rl;
        let n = (self.total - self.read).min(max as u64) as usize;
        if n == 0 {
            return Ok(0);
        }
        batch.records.resize(n * rl, 0);
        let path = &self.info.path;
        match &mut self.points {
            Points::Plain(r) => r
                .read_exact(&mut batch.records)
                .map_err(|e| IoError::io(path, e))?,
            Points::Laz(d) => {
                let out = &mut batch.records;
                let r = guarded(path, || {
                    d.decompress_many(out).map_err(|e| laz_io_error(path, e))
                });
                if r.is_err() {
                    self.points = Points::Broken;
                }
                r?
            }
            Points::Empty(_) | Points::Broken => {
                return Err(IoError::invalid(path, "the LAZ decoder failed earlier"));
            }
        }
        let (s, o) = (self.scale, self.offset);
        batch
            .positions
            .extend(batch.records.chunks_exact(rl).map(|r| {
                DVec3::new(
                    f64::from(get_i32(r, 0)) * s[0] + o[0],
                    f64::from(get_i32(r, 4)) * s[1] + o[1],
                    f64::from(get_i32(r, 8)) * s[2] + o[2],
                )
            }));
        self.read += n as u64;
        Ok(n)
    }

    fn seek_point(&mut self, index: u64) -> Result<bool, IoError> {
        if !self.seekable || index > self.total {
            return Ok(false);
        }
        let path = &self.info.path;
        let records = (self.data_start, self.info.schema.record_len);
        match &mut self.points {
            Points::Plain(r) => seek_record(r, path, records, index)?,
            // The decompressor cannot seek to the end of its last chunk: nothing is left to
            // read there anyway.
            Points::Laz(_) if index == self.total => {}
            Points::Laz(d) => {
                let r = guarded(path, || d.seek(index).map_err(|e| laz_error(path, e)));
                if r.is_err() {
                    self.points = Points::Broken;
                }
                r?
            }
            Points::Empty(_) | Points::Broken => return Ok(false),
        }
        self.read = index;
        Ok(true)
    }

    fn finish(self: Box<Self>) -> Result<Extras, IoError> {
        let path = self.info.path.clone();
        let mut file = match self.points {
            Points::Empty(r) | Points::Plain(r) => r.into_inner(),
            Points::Laz(d) => d.into_inner().into_inner(),
            Points::Broken => self.again.open()?,
        };
        let mut pieces = Vec::with_capacity(self.tail.len());
        for &(offset, len, evlr) in &self.tail {
            let bytes =
                read_at(&mut file, offset, len as usize).map_err(|e| IoError::io(&path, e))?;
            pieces.push(if evlr {
                Piece::Evlr(LasVlr {
                    raw: bytes,
                    extended: true,
                })
            } else {
                Piece::Bytes(bytes)
            });
        }
        Ok(Extras {
            faces: None,
            trailer: Trailer::Las(LasTrailer {
                start: self.tail.first().map_or(0, |t| t.0),
                pieces,
            }),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::las::LasSink;
    use crate::io::{Cloud, Sink, SinkOptions};

    /// A LAS 1.0 file by hand: PDRF 0, no VLR, the 1.0 point data start signature, two points.
    fn las_1_0() -> Vec<u8> {
        let mut h = vec![0u8; 227];
        h[..4].copy_from_slice(b"LASF");
        h[24] = 1;
        h[25] = 0;
        h[26..33].copy_from_slice(b"OLD ONE");
        h[94..96].copy_from_slice(&227u16.to_le_bytes());
        h[96..100].copy_from_slice(&229u32.to_le_bytes());
        h[104] = 0;
        h[105..107].copy_from_slice(&20u16.to_le_bytes());
        h[107..111].copy_from_slice(&2u32.to_le_bytes());
        h[111..115].copy_from_slice(&2u32.to_le_bytes()); // two first returns
        for a in 0..3 {
            h[131 + 8 * a..139 + 8 * a].copy_from_slice(&0.5f64.to_le_bytes());
            h[155 + 8 * a..163 + 8 * a].copy_from_slice(&(100.0 * a as f64).to_le_bytes());
        }
        // max x, min x, max y, min y, max z, min z of X = (2, -4), Y = (6, 6), Z = (0, 1).
        for (k, v) in [1.0, -2.0, 103.0, 103.0, 200.5, 200.0].iter().enumerate() {
            h[179 + 8 * k..187 + 8 * k].copy_from_slice(&f64::to_le_bytes(*v));
        }
        h.extend_from_slice(&[0xdd, 0xcc]);
        for (x, y, z) in [(2i32, 6i32, 0i32), (-4, 6, 1)] {
            let mut r = [0u8; 20];
            r[..4].copy_from_slice(&x.to_le_bytes());
            r[4..8].copy_from_slice(&y.to_le_bytes());
            r[8..12].copy_from_slice(&z.to_le_bytes());
            r[12] = 77; // intensity
            r[14] = 0b0000_1001; // return 1 of 1
            r[15] = 2 | 0x20; // ground, synthetic
            h.extend_from_slice(&r);
        }
        h
    }

    #[test]
    fn las_1_0_reads_and_writes_back_identically() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("old.las");
        std::fs::write(&p, las_1_0()).unwrap();
        let c = Cloud::read(&p, None).unwrap();
        assert_eq!(
            c.positions,
            [
                DVec3::new(1.0, 103.0, 200.0),
                DVec3::new(-2.0, 103.0, 200.5)
            ]
        );
        let Meta::Las(m) = &c.info.meta else { panic!() };
        assert_eq!(
            (m.version(), m.point_format(), m.vlr_padding()),
            ((1, 0), 0, &[0xdd, 0xcc][..])
        );
        let s = &c.info.schema;
        assert_eq!(
            s.get_f64(&c.records, s.field_index("intensity").unwrap()),
            77.0
        );
        let q = dir.path().join("copy.las");
        c.write(&q, None).unwrap();
        assert_eq!(std::fs::read(&q).unwrap(), las_1_0());

        // The noise flag keeps the synthetic bit of a PDRF 0 record.
        let mut sink = LasSink::create(
            &q,
            &c.info,
            2,
            &SinkOptions {
                noise_flag: true,
                ..SinkOptions::default()
            },
        )
        .unwrap();
        let mut batch = PointBatch::with_capacity(20, 2);
        batch.positions.extend_from_slice(&c.positions);
        batch.records.extend_from_slice(&c.records);
        batch.flags = vec![0, crate::points::FLAG_NOISE];
        sink.write_batch(&batch).unwrap();
        Box::new(sink).finish(&Extras::default()).unwrap();
        let out = std::fs::read(&q).unwrap();
        assert_eq!((out[229 + 15], out[249 + 15]), (0x22, 0x27));
    }

    #[test]
    fn a_tail_is_split_into_bytes_and_evlrs() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.bin");
        let mut b = vec![9u8; 10];
        b.extend(layout::vlr_bytes("me", 3, "d", b"payload", true));
        b.extend_from_slice(b"end");
        std::fs::write(&p, &b).unwrap();
        let mut f = Input::from_path(&p).unwrap();
        let size = b.len() as u64;
        let plan = plan_tail(&p, &mut f, size, 4, Some((10, 1))).unwrap();
        assert_eq!(plan, [(4, 6, false), (10, 67, true), (77, 3, false)]);
        assert!(
            plan_tail(&p, &mut f, size, 4, Some((10, 2))).is_err(),
            "second EVLR missing"
        );
        assert!(
            plan_tail(&p, &mut f, size, 12, Some((10, 1))).is_err(),
            "EVLR before the tail"
        );
        assert_eq!(plan_tail(&p, &mut f, size, size, None).unwrap(), []);
    }
}
