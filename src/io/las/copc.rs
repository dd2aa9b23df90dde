//! COPC 1.0 output (`*.copc.laz`): a LAZ 1.4 file whose points are grouped into the nodes of an
//! octree, one variable-size LAZ chunk per node, described by the COPC info VLR and the hierarchy
//! EVLR, so that readers fetch only the nodes a query or a level of detail needs.
//!
//! # Brief overview
//!
//! ```text
//!  write_batch ──► LasSink (uncompressed LAS 1.x in a scratch folder beside the target)
//!  finish      ──► read it back ─► convert to PDRF 6/7/8 ─► octree ─► one LAZ chunk per node
//!
//!  header (375 B, LAS 1.4) │ copc info VLR │ other VLRs │ laszip VLR (variable chunks)
//!  chunk table offset │ node chunks, breadth first │ chunk table │ hierarchy EVLR │ other EVLRs
//! ```
//!
//! * **Everything the plain LAS sink does first**: the points are written through [`LasSink`]
//!   (same frame, the source's header, VLRs and EVLRs, the noise flag, foreign schemas as extra
//!   bytes), so a COPC output keeps exactly what a LAS output keeps. The stale COPC records of a
//!   COPC source (`copc` info, hierarchy and the `copc`/10000 extents) are dropped and rebuilt.
//! * **Point formats**: COPC allows only PDRF 6, 7 and 8. Formats 0–5 are converted losslessly:
//!   0, 1 → 6; 2, 3 → 7 (RGB); return number and number of returns move to 4-bit fields; the
//!   classification's low 5 bits become the class byte and its synthetic, key-point and withheld
//!   bits the classification flags; scan direction and edge of flight line keep their bits;
//!   the scan angle rank (whole degrees) becomes the scan angle in 0.006° steps
//!   (`round(rank / 0.006)`, which maps back to the same rank); GPS time is 0 where the source
//!   had none. The waveform fields of formats 4, 5, 9 and 10 (not allowed in COPC) are kept as
//!   extra bytes `wave_packet_index`, `wave_offset`, … (the Extra Bytes VLR describes them), and
//!   4 → 6, 5 → 7, 9 → 6, 10 → 8; the waveform bits of the global encoding are cleared and its
//!   WKT bit set (LAS 1.4 requires it for PDRF 6–10; copclib refuses a file without it). Every
//!   other VLR and EVLR is kept verbatim, GeoTIFF keys included; qemd does not translate a
//!   GeoTIFF CRS to WKT, so a reader that follows the WKT bit finds no CRS in such a file.
//! * **The octree**: the cube's lower corner is the minimum of the bounds of the quantised points
//!   on every axis (where the header bounds start), its half size half the largest extent (so the
//!   cube spans the header bounds along that axis); every node has a grid of [`GRID`]³ cells and each point goes to
//!   the shallowest node whose cell for it is still free (in file order), down to a depth where a
//!   cell is no larger than the scale step (there, or at depth [`MAX_DEPTH`], a node takes every
//!   point left). So the root holds an even sample of the whole cloud and each level doubles the
//!   resolution; `spacing` in the info VLR is the root's cell size, `2 × halfsize / GRID`. A node
//!   with points always has its parent in the hierarchy.
//! * **Point order is not kept**: COPC stores points node by node (nodes breadth first, by depth
//!   then key). Every record is kept, as a multiset.
//! * **Memory**: the records are held in memory while the octree is built (the record length plus
//!   about 40 bytes per point); the scratch LAS file is on disk beside the target and removed.

use std::io::{Cursor, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use laz::laszip::{ChunkTable, ChunkTableEntry};
use laz::{LasZipCompressor, LazVlr, LazVlrBuilder};
use rayon::prelude::*;
use rustc_hash::FxHashSet;

use super::layout::{
    self, BASE_LEN, at, get_f64, get_i32, get_u16, put, standard_fields, vlr_bytes,
};
use super::{LASZIP_RECORD, LASZIP_USER, LasSink, LasSource, LasVlr, Piece, quietly};
use crate::io::{AtomicFile, Extras, IoError, Sink, SinkOptions, Source, SourceInfo, Trailer};
use crate::points::PointBatch;

/// Cells per side of every node's grid.
pub const GRID: u32 = 128;

/// Deepest octree level (the root is 0).
pub const MAX_DEPTH: u8 = 20;

/// Bytes of the COPC info VLR payload.
const INFO_LEN: usize = 160;

/// Bytes of one hierarchy entry.
const ENTRY_LEN: usize = 32;

/// Name of the scratch LAS file in the scratch folder.
const SCRATCH_NAME: &str = "points.las";

/// Nodes compressed in parallel before they are written.
const NODE_GROUP: usize = 64;

/// Streaming COPC writer: a [`LasSink`] into a scratch file, turned into COPC at [`Sink::finish`].
pub struct CopcSink {
    inner: Option<Box<LasSink>>,
    /// Holds the scratch LAS file ([`SCRATCH_NAME`]); removed when the sink is dropped.
    scratch: tempfile::TempDir,
    out: Option<AtomicFile>,
    target: PathBuf,
}

/// `e` with its path replaced by `target` (errors of the scratch file name the output).
fn retarget(e: IoError, target: &Path) -> IoError {
    let t = target.to_path_buf();
    match e {
        IoError::Io { error, .. } => IoError::Io { path: t, error },
        IoError::Truncated { detail, .. } => IoError::Truncated { path: t, detail },
        IoError::Header { detail, .. } => IoError::Header { path: t, detail },
        IoError::Invalid { detail, .. } => IoError::Invalid { path: t, detail },
        IoError::UnknownFormat { known, .. } => IoError::UnknownFormat { path: t, known },
        IoError::Unsupported { detail, .. } => IoError::Unsupported { path: t, detail },
    }
}

impl CopcSink {
    /// Creates a sink that writes `count` points laid out like `like` as COPC at `path`.
    ///
    /// # Errors
    /// As [`LasSink::create`]; the directory is not writable.
    pub fn create(
        path: &Path,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<CopcSink, IoError> {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if crate::io::output::is_stream_output(path) {
            return Err(IoError::Unsupported {
                path: path.to_path_buf(),
                detail: "COPC output needs a regular file (its chunk table and hierarchy are \
                         written after the points)"
                    .into(),
            });
        }
        let out = AtomicFile::create(path)?;
        let scratch = tempfile::Builder::new()
            .prefix(&format!(".{name}."))
            .tempdir_in(dir)
            .map_err(|e| IoError::io(path, e))?;
        let points = scratch.path().join(SCRATCH_NAME);
        let inner = LasSink::create_as(&points, like, count, options, false)
            .map_err(|e| retarget(e, path))?;
        Ok(CopcSink {
            inner: Some(Box::new(inner)),
            scratch,
            out: Some(out),
            target: path.to_path_buf(),
        })
    }
}

impl Sink for CopcSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        match &mut self.inner {
            Some(s) => s.write_batch(batch).map_err(|e| retarget(e, &self.target)),
            None => Err(IoError::invalid(&self.target, "the sink is finished")),
        }
    }

    fn finish(mut self: Box<Self>, extras: &Extras) -> Result<(), IoError> {
        let target = self.target.clone();
        let inner = self
            .inner
            .take()
            .ok_or_else(|| IoError::invalid(&target, "the sink is finished"))?;
        inner.finish(extras).map_err(|e| retarget(e, &target))?;
        let mut out = self.out.take().expect("finish runs once");
        let points = self.scratch.path().join(SCRATCH_NAME);
        write_copc(&points, &mut out).map_err(|e| retarget(e, &target))?;
        out.commit() // the scratch folder goes with `self`
    }
}

/// Where the fields of a source record go in its COPC record.
struct Convert {
    from: u8,
    to: u8,
    /// Extra bytes of the source (after its standard fields).
    extra: usize,
    /// Length of a converted record.
    len: usize,
    /// Offset of the GPS time in a source record.
    gps: Option<usize>,
    /// Offsets of RGB in a source and a COPC record.
    rgb: Option<(usize, usize)>,
    /// Offsets of NIR in a source and a COPC record.
    nir: Option<(usize, usize)>,
}

/// The COPC point format of LAS point format `f`.
fn copc_format(f: u8) -> u8 {
    match f {
        0 | 1 | 4 | 6 | 9 => 6,
        2 | 3 | 5 | 7 => 7,
        _ => 8,
    }
}

/// Offset of the waveform fields in a record of format `f`, if it has them.
fn wave_at(f: u8) -> Option<usize> {
    match f {
        4 | 5 | 9 | 10 => Some(BASE_LEN[usize::from(f)] - 29),
        _ => None,
    }
}

/// Offset of a standard field of format `f`.
fn field_at(f: u8, name: &str) -> Option<usize> {
    standard_fields(f)
        .into_iter()
        .find(|(n, _, _)| *n == name)
        .map(|(_, _, o)| o)
}

impl Convert {
    fn new(from: u8, record_len: usize) -> Convert {
        let to = copc_format(from);
        let extra = record_len - BASE_LEN[usize::from(from)];
        let wave = if wave_at(from).is_some() { 29 } else { 0 };
        let both = |n: &str| field_at(from, n).zip(field_at(to, n));
        Convert {
            from,
            to,
            extra,
            len: BASE_LEN[usize::from(to)] + wave + extra,
            gps: field_at(from, "gps_time"),
            rgb: both("red"),
            nir: both("nir"),
        }
    }

    /// True when records are copied as they are.
    fn is_identity(&self) -> bool {
        self.from == self.to
    }

    /// Writes the COPC record of `src` into `dst` (`self.len` bytes).
    fn record(&self, src: &[u8], dst: &mut [u8]) {
        if self.is_identity() {
            dst.copy_from_slice(src);
            return;
        }
        dst.fill(0);
        let (from, to) = (self.from, self.to);
        if from >= 6 {
            dst[..30].copy_from_slice(&src[..30]);
        } else {
            dst[..14].copy_from_slice(&src[..14]); // X, Y, Z, intensity
            let rf = src[14];
            let (ret, num, dir, edge) = (rf & 7, (rf >> 3) & 7, (rf >> 6) & 1, rf >> 7);
            dst[14] = ret | (num << 4);
            let c = src[15];
            dst[15] = (c >> 5) | (dir << 6) | (edge << 7);
            dst[16] = c & 0x1f;
            dst[17] = src[17];
            let rank = f64::from(src[16] as i8);
            put(dst, 18, &((rank / 0.006).round() as i16).to_le_bytes());
            dst[20..22].copy_from_slice(&src[18..20]);
            if let Some(g) = self.gps {
                dst[22..30].copy_from_slice(&src[g..g + 8]);
            }
        }
        if let Some((s, d)) = self.rgb {
            dst[d..d + 6].copy_from_slice(&src[s..s + 6]);
        }
        if let Some((s, d)) = self.nir {
            dst[d..d + 2].copy_from_slice(&src[s..s + 2]);
        }
        let mut o = BASE_LEN[usize::from(to)];
        if let Some(w) = wave_at(from) {
            dst[o..o + 29].copy_from_slice(&src[w..w + 29]);
            o += 29;
        }
        let base = BASE_LEN[usize::from(from)];
        dst[o..o + self.extra].copy_from_slice(&src[base..base + self.extra]);
    }

    /// Extra Bytes descriptors of the waveform fields moved into extra bytes.
    fn wave_descriptors(&self) -> Vec<u8> {
        let mut d = Vec::new();
        if wave_at(self.from).is_some() {
            for (name, ty, _) in standard_fields(self.from)
                .into_iter()
                .filter(|(n, _, _)| n.starts_with("wave_"))
            {
                d.extend_from_slice(&layout::extra_descriptor(name, ty));
            }
        }
        d
    }
}

/// The octree cube.
#[derive(Debug, Clone, Copy)]
struct Cube {
    center: [f64; 3],
    half: f64,
}

/// A node key: depth, x, y, z.
type Key = (u8, u32, u32, u32);

/// Assigns each point (quantised X, Y, Z decoded with `scale`, `offset`) to an octree node.
fn build_octree(xyz: &[[i32; 3]], scale: [f64; 3], offset: [f64; 3]) -> (Cube, Vec<Key>) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let world =
        |q: &[i32; 3]| -> [f64; 3] { [0, 1, 2].map(|a| f64::from(q[a]) * scale[a] + offset[a]) };
    for q in xyz {
        let p = world(q);
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let step = scale.iter().fold(0f64, |m, s| m.max(s.abs()));
    if xyz.is_empty() {
        return (
            Cube {
                center: [0.0; 3],
                half: step,
            },
            Vec::new(),
        );
    }
    // The cube starts at the minimum of the bounds on every axis (readers such as copclib
    // place nodes from the header minimum; with this choice both conventions agree).
    // Half the largest extent, so that the cube is the header bounds along that axis (copclib
    // sizes nodes from the header bounds, laspy from the info VLR; both agree then).
    let half = (0..3).fold(0f64, |m, a| m.max(0.5 * (hi[a] - lo[a])));
    let half = if half > 0.0 { half } else { step };
    let center = [0, 1, 2].map(|a| lo[a] + half);
    let cube = Cube { center, half };
    let corner = lo;
    let side = 2.0 * half;
    let finest = step.min(scale.iter().fold(f64::INFINITY, |m, s| m.min(s.abs())));
    let mut max_depth = 0u8;
    while max_depth < MAX_DEPTH && side / (f64::from(GRID) * f64::from(1u32 << max_depth)) > finest
    {
        max_depth += 1;
    }
    let mut taken: FxHashSet<Key> = FxHashSet::default();
    let keys = xyz
        .iter()
        .map(|q| {
            let p = world(q);
            let u = [0, 1, 2].map(|a| ((p[a] - corner[a]) / side).clamp(0.0, 1.0));
            for d in 0..=max_depth {
                let res = GRID << d;
                let cell = u.map(|v| ((v * f64::from(res)) as u32).min(res - 1));
                let cell_key = (d, cell[0], cell[1], cell[2]);
                if d == max_depth || taken.insert(cell_key) {
                    return (d, cell[0] / GRID, cell[1] / GRID, cell[2] / GRID);
                }
            }
            unreachable!("the deepest level takes every point")
        })
        .collect();
    (cube, keys)
}

/// Compresses `records` as one LAZ chunk with `vlr`.
fn compress_chunk(vlr: &LazVlr, records: &[u8]) -> std::io::Result<Vec<u8>> {
    quietly(|| {
        let mut c = LasZipCompressor::new(Cursor::new(Vec::new()), vlr.clone())
            .map_err(std::io::Error::other)?;
        c.compress_many(records)?;
        c.done()?;
        let bytes = c.into_inner().into_inner();
        // [offset to the chunk table][the chunk][the chunk table]
        let table = i64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
        Ok(bytes[8..table].to_vec())
    })
    .unwrap_or_else(|()| Err(std::io::Error::other("the LAZ compressor failed")))
}

/// Reads the scratch LAS file at `points` and writes it as COPC into `out`.
fn write_copc(points: &Path, out: &mut AtomicFile) -> Result<(), IoError> {
    let target = out.target().to_path_buf();
    let io = |e: std::io::Error| IoError::io(&target, e);
    let mut src = LasSource::open(points)?;
    let meta = src.meta().clone();
    let rl = meta.record_len();
    let n = usize::try_from(meta.point_count())
        .map_err(|_| IoError::invalid(&target, "too many points for COPC in memory"))?;
    let mut records = Vec::with_capacity(n * rl);
    let mut batch = PointBatch::with_capacity(rl, crate::io::BATCH);
    while src.read_batch(&mut batch, crate::io::BATCH)? > 0 {
        records.extend_from_slice(&batch.records);
    }
    let trailer = match Box::new(src).finish()?.trailer {
        Trailer::Las(t) => t,
        _ => unreachable!("a LAS source has a LAS trailer"),
    };

    let conv = Convert::new(meta.point_format(), rl);
    let xyz: Vec<[i32; 3]> = records
        .chunks_exact(rl)
        .map(|r| [get_i32(r, 0), get_i32(r, 4), get_i32(r, 8)])
        .collect();
    let scale = meta.scale().to_array();
    let offset = meta.offset().to_array();
    let (cube, keys) = build_octree(&xyz, scale, offset);
    let mut order: Vec<u32> = (0..n as u32).collect();
    order.sort_by_key(|&i| keys[i as usize]);

    // Header: LAS 1.4, 375 bytes, the COPC point format.
    let src_h = meta.header_bytes();
    let mut h = vec![0u8; 375];
    h[..227].copy_from_slice(&src_h[..227]);
    h[at::VERSION] = 1;
    h[at::VERSION + 1] = 4;
    put(&mut h, at::HEADER_SIZE, &375u16.to_le_bytes());
    h[at::FORMAT] = conv.to | 0x80;
    let len16 = u16::try_from(conv.len)
        .map_err(|_| IoError::invalid(&target, format!("a {}-byte COPC point record", conv.len)))?;
    put(&mut h, at::RECORD_LEN, &len16.to_le_bytes());
    // Waveform bits cleared (no waveform records in COPC); the WKT bit set, as LAS 1.4 requires
    // for PDRF 6-10 (copclib refuses a file without it).
    let encoding = (get_u16(src_h, at::GLOBAL_ENCODING) & !0b110) | 0x10;
    put(&mut h, at::GLOBAL_ENCODING, &encoding.to_le_bytes());
    put(&mut h, at::LEGACY_COUNT, &0u32.to_le_bytes());
    for r in 0..5 {
        put(&mut h, at::LEGACY_BY_RETURN + 4 * r, &0u32.to_le_bytes());
    }

    // VLRs: the COPC info first, then the source's (but LASzip and COPC), then LASzip.
    let wave = conv.wave_descriptors();
    let mut vlrs: Vec<Vec<u8>> = vec![vlr_bytes("copc", 1, "COPC info", &[0; INFO_LEN], false)];
    let mut described = false;
    for v in meta.vlrs() {
        if v.is_laszip() || v.user_id() == "copc" {
            continue;
        }
        if v.is("LASF_Spec", 4) && !wave.is_empty() {
            let mut data = wave.clone();
            data.extend_from_slice(v.data());
            vlrs.push(extra_bytes_vlr(&target, v, &data)?);
            described = true;
            continue;
        }
        vlrs.push(v.bytes().to_vec());
    }
    if !wave.is_empty() && !described {
        vlrs.push(vlr_bytes("LASF_Spec", 4, "Extra Bytes", &wave, false));
    }
    let extra = u16::try_from(conv.len - BASE_LEN[usize::from(conv.to)])
        .map_err(|_| IoError::invalid(&target, "too many extra bytes"))?;
    let laz_vlr = LazVlrBuilder::default()
        .with_point_format(conv.to, extra)
        .map_err(|e| IoError::Unsupported {
            path: target.clone(),
            detail: format!("LAZ compression of point format {}: {e}", conv.to),
        })?
        .with_variable_chunk_size()
        .build();
    let mut laz_data = Vec::new();
    laz_vlr.write_to(&mut laz_data).map_err(io)?;
    vlrs.push(vlr_bytes(
        LASZIP_USER,
        LASZIP_RECORD,
        LazVlr::DESCRIPTION,
        &laz_data,
        false,
    ));
    let vlr_len: usize = vlrs.iter().map(Vec::len).sum();
    let data_start = 375 + vlr_len;
    let data_start32 = u32::try_from(data_start)
        .map_err(|_| IoError::invalid(&target, "the VLRs exceed 4 GiB"))?;
    put(&mut h, at::POINT_DATA, &data_start32.to_le_bytes());
    put(&mut h, at::VLR_COUNT, &(vlrs.len() as u32).to_le_bytes());

    out.write_all(&h).map_err(io)?;
    for v in &vlrs {
        out.write_all(v).map_err(io)?;
    }
    out.write_all(&(-1i64).to_le_bytes()).map_err(io)?;
    let mut pos = data_start as u64 + 8;

    // Nodes, breadth first; one chunk each.
    let mut nodes: Vec<(Key, std::ops::Range<usize>)> = Vec::new();
    let mut s = 0;
    while s < n {
        let k = keys[order[s] as usize];
        let mut e = s + 1;
        while e < n && keys[order[e] as usize] == k {
            e += 1;
        }
        nodes.push((k, s..e));
        s = e;
    }
    let mut table = ChunkTable::with_capacity(nodes.len());
    let mut entries = Vec::with_capacity(nodes.len().max(1) * ENTRY_LEN);
    let mut by_return = [0u64; 15];
    let mut qmin = [i32::MAX; 3];
    let mut qmax = [i32::MIN; 3];
    let (mut tmin, mut tmax) = (f64::INFINITY, f64::NEG_INFINITY);
    for group in nodes.chunks(NODE_GROUP) {
        let chunks: Vec<std::io::Result<(Vec<u8>, usize)>> = group
            .par_iter()
            .map(|(_, range)| {
                let mut buf = vec![0u8; range.len() * conv.len];
                for (dst, &i) in buf.chunks_exact_mut(conv.len).zip(&order[range.clone()]) {
                    let i = i as usize;
                    conv.record(&records[i * rl..(i + 1) * rl], dst);
                }
                compress_chunk(&laz_vlr, &buf).map(|c| (c, range.len()))
            })
            .collect();
        for ((key, range), chunk) in group.iter().zip(chunks) {
            let (bytes, count) = chunk.map_err(io)?;
            for &i in &order[range.clone()] {
                let i = i as usize;
                let r = &records[i * rl..(i + 1) * rl];
                let ret = usize::from(if conv.from >= 6 {
                    r[14] & 0x0f
                } else {
                    r[14] & 0x07
                });
                if (1..=15).contains(&ret) {
                    by_return[ret - 1] += 1;
                }
                for a in 0..3 {
                    qmin[a] = qmin[a].min(xyz[i][a]);
                    qmax[a] = qmax[a].max(xyz[i][a]);
                }
                if let Some(g) = conv.gps {
                    let t = get_f64(r, g);
                    tmin = tmin.min(t);
                    tmax = tmax.max(t);
                }
            }
            out.write_all(&bytes).map_err(io)?;
            let (d, x, y, z) = *key;
            for v in [i32::from(d), x as i32, y as i32, z as i32] {
                entries.extend_from_slice(&v.to_le_bytes());
            }
            entries.extend_from_slice(&pos.to_le_bytes());
            entries.extend_from_slice(&(bytes.len() as i32).to_le_bytes());
            entries.extend_from_slice(&(count as i32).to_le_bytes());
            table.push(ChunkTableEntry {
                point_count: count as u64,
                byte_count: bytes.len() as u64,
            });
            pos += bytes.len() as u64;
        }
    }
    if nodes.is_empty() {
        // An empty cloud: the root, without points.
        entries.extend_from_slice(&[0u8; 16]);
        entries.extend_from_slice(&[0u8; 16]);
    }
    let table_at = pos;
    let mut table_bytes = Vec::new();
    table.write_to(&mut table_bytes, &laz_vlr).map_err(io)?;
    out.write_all(&table_bytes).map_err(io)?;
    pos += table_bytes.len() as u64;

    // EVLRs: the hierarchy (one page), then the source's but COPC's own.
    let first_evlr = pos;
    let hierarchy = vlr_bytes("copc", 1000, "EPT hierarchy", &entries, true);
    out.write_all(&hierarchy).map_err(io)?;
    let root_offset = pos + layout::EVLR_HEADER as u64;
    let mut evlrs = 1u32;
    for piece in &trailer.pieces {
        if let Piece::Evlr(v) = piece
            && v.user_id() != "copc"
        {
            out.write_all(v.bytes()).map_err(io)?;
            evlrs += 1;
        }
    }

    // Patch the header, the info VLR and the chunk table offset.
    put(&mut h, at::WAVEFORM, &0u64.to_le_bytes());
    put(&mut h, at::FIRST_EVLR, &first_evlr.to_le_bytes());
    put(&mut h, at::EVLR_COUNT, &evlrs.to_le_bytes());
    put(&mut h, at::COUNT, &(n as u64).to_le_bytes());
    for (r, c) in by_return.iter().enumerate() {
        put(&mut h, at::BY_RETURN + 8 * r, &c.to_le_bytes());
    }
    for a in 0..3 {
        let (lo, hi) = if n == 0 {
            (0.0, 0.0)
        } else {
            (
                f64::from(qmin[a]) * scale[a] + offset[a],
                f64::from(qmax[a]) * scale[a] + offset[a],
            )
        };
        put(&mut h, at::BOUNDS + 16 * a, &hi.to_le_bytes());
        put(&mut h, at::BOUNDS + 16 * a + 8, &lo.to_le_bytes());
    }
    let mut info = Vec::with_capacity(INFO_LEN);
    for v in cube.center {
        info.extend_from_slice(&v.to_le_bytes());
    }
    info.extend_from_slice(&cube.half.to_le_bytes());
    info.extend_from_slice(&(2.0 * cube.half / f64::from(GRID)).to_le_bytes());
    info.extend_from_slice(&root_offset.to_le_bytes());
    info.extend_from_slice(&(entries.len() as u64).to_le_bytes());
    let (tmin, tmax) = if tmin <= tmax {
        (tmin, tmax)
    } else {
        (0.0, 0.0)
    };
    info.extend_from_slice(&tmin.to_le_bytes());
    info.extend_from_slice(&tmax.to_le_bytes());
    info.resize(INFO_LEN, 0);
    out.seek(SeekFrom::Start(0)).map_err(io)?;
    out.write_all(&h).map_err(io)?;
    out.seek(SeekFrom::Start(375 + layout::VLR_HEADER as u64))
        .map_err(io)?;
    out.write_all(&info).map_err(io)?;
    out.seek(SeekFrom::Start(data_start as u64)).map_err(io)?;
    out.write_all(&(table_at as i64).to_le_bytes())
        .map_err(io)?;
    out.seek(SeekFrom::End(0)).map_err(io)?;
    Ok(())
}

/// The Extra Bytes VLR `v` with payload `data` (its user id, record id and description kept).
fn extra_bytes_vlr(target: &Path, v: &LasVlr, data: &[u8]) -> Result<Vec<u8>, IoError> {
    if data.len() > usize::from(u16::MAX) {
        return Err(IoError::invalid(
            target,
            "the Extra Bytes VLR exceeds 65535 bytes",
        ));
    }
    Ok(vlr_bytes(
        &v.user_id(),
        v.record_id(),
        &v.description(),
        data,
        false,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn legacy_records_convert_losslessly() {
        // PDRF 3: X Y Z, intensity, return 2 of 3, scan dir, class 5 + synthetic + withheld,
        // scan angle rank -17, user data, point source id, GPS time, RGB; 2 extra bytes.
        let mut src = vec![0u8; 34 + 2];
        put(&mut src, 0, &7i32.to_le_bytes());
        put(&mut src, 4, &(-8i32).to_le_bytes());
        put(&mut src, 8, &9i32.to_le_bytes());
        put(&mut src, 12, &300u16.to_le_bytes());
        src[14] = 2 | (3 << 3) | (1 << 6);
        src[15] = 5 | 0x20 | 0x80;
        src[16] = (-17i8) as u8;
        src[17] = 42;
        put(&mut src, 18, &77u16.to_le_bytes());
        put(&mut src, 20, &1234.5f64.to_le_bytes());
        put(&mut src, 28, &[1, 2, 3, 4, 5, 6]);
        src[34] = 0xab;
        src[35] = 0xcd;
        let c = Convert::new(3, src.len());
        assert_eq!((c.to, c.len), (7, 36 + 2));
        let mut dst = vec![0u8; c.len];
        c.record(&src, &mut dst);
        assert_eq!(&dst[..14], &src[..14]);
        assert_eq!(dst[14], 2 | (3 << 4));
        assert_eq!(dst[15], 0b101 | (1 << 6)); // synthetic, withheld; scan direction
        assert_eq!(dst[16], 5);
        assert_eq!(dst[17], 42);
        let angle = i16::from_le_bytes([dst[18], dst[19]]);
        assert_eq!(angle, -2833);
        assert_eq!((f64::from(angle) * 0.006).round(), -17.0);
        assert_eq!(get_u16(&dst, 20), 77);
        assert_eq!(get_f64(&dst, 22), 1234.5);
        assert_eq!(&dst[30..36], &[1, 2, 3, 4, 5, 6]);
        assert_eq!(&dst[36..], &[0xab, 0xcd]);
        // Waveform fields become extra bytes ahead of the source's own.
        let c = Convert::new(4, 57 + 1);
        assert_eq!((c.to, c.len), (6, 30 + 29 + 1));
        assert_eq!(c.wave_descriptors().len(), 7 * 192);
    }

    #[test]
    fn every_point_lies_in_its_node() {
        let mut xyz = Vec::new();
        let mut s = 1u64;
        for _ in 0..20_000 {
            let mut r = || {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
                ((s >> 33) % 100_000) as i32
            };
            xyz.push([r(), r(), r() / 50]);
        }
        let scale = [0.001; 3];
        let offset = [500_000.0, 4_000_000.0, 0.0];
        let (cube, keys) = build_octree(&xyz, scale, offset);
        assert_eq!(keys.len(), xyz.len());
        let nodes: FxHashSet<Key> = keys.iter().copied().collect();
        let root = keys.iter().filter(|k| k.0 == 0).count();
        assert!(root > 1000 && root < xyz.len(), "root holds {root}");
        for (q, &(d, x, y, z)) in xyz.iter().zip(&keys) {
            let size = 2.0 * cube.half / f64::from(1u32 << d);
            for (a, k) in [x, y, z].into_iter().enumerate() {
                let p = f64::from(q[a]) * scale[a] + offset[a];
                let lo = cube.center[a] - cube.half + f64::from(k) * size;
                assert!(p >= lo - 1e-9 && p <= lo + size + 1e-9, "{p} outside node");
            }
            if d > 0 {
                let parent = (d - 1, x / 2, y / 2, z / 2);
                assert!(
                    nodes.contains(&parent),
                    "node {d}/{x}/{y}/{z} has no parent"
                );
            }
        }
    }
}
