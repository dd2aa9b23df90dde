//! The on-disk formats of the tiled path: spill files (points per tile) and result files
//! (finished tiles), both little-endian fixed-size records, in the work directory
//! ([`super::workdir`] names them).
//!
//! ```text
//!  spill  tile_<t>.pts   [ index|HALO<<63|HELD<<62 : u64 | x : f64 | y : f64 | z : f64 ]   32 bytes
//!  blocks tile_<t>.blk   [ records|RUN_END<<63 : u64 | min x y z : f64 | max x y z : f64 ] 56 bytes
//!                        per block of the spill file, in file order
//!  result tile_<t>.res   [ index : u64 | x : f64 | y : f64 | z : f64 | knn_mean : f64 ] 40 bytes,
//!                        sorted by index, written atomically: a result file is a checkpoint
//!          with normals  [ … 40 bytes as above | nx ny nz curvature : f32 | structure : u8 | 0 × 7 ]
//!                        64 bytes, only when the run writes normals (`--write-normals`)
//! ```
//!
//! Spill files and block tables live in the directory of the partition part that wrote them
//! (`part_<p>/`, see [`super::workdir`]): a tile has one of each per part, and readers read the
//! parts in order. Each part appends a tile's records a buffer at a time, in global-index order
//! across buffers; each buffer (a *run*) is written owned records first, in Morton order over the
//! cloud's bounds and cut into blocks of [`SPILL_BLOCK`] records (each block's records in index
//! order), then the halo copies as one block, present even when empty and flagged `RUN_END`.
//! The block table gives each block's record count and the box of its owned points (empty for
//! the halo block), so halo growth, which reads only owned points near a group, reads only the
//! blocks whose box meets the group's span ([`read_owned_near`]) instead of whole files.
//! Readers return records in global-index order (merging each run's sorted blocks), so results
//! never depend on the file order.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Read, Seek, SeekFrom, Write};

use std::path::{Path, PathBuf};

use glam::DVec3;
use rayon::prelude::*;

use super::TilingError;
use super::workdir::{
    blocks_path, merge_path, part_dir, range_merge_path, result_path, spill_path,
};
use crate::io::AtomicFile;
use crate::neighbours::MortonGrid;
use crate::points::{Aabb, PointNormal};

/// Bytes per spill record.
pub const SPILL_RECORD: usize = 32;
/// Owned records per block of a spill file (8 KiB: a box per block costs 0.7 % of the file).
pub const SPILL_BLOCK: usize = 256;
/// Bytes per entry of a block table.
pub const BLOCK_ENTRY: usize = 56;
/// Bit 63 of a block table entry's record count: the block (of halo copies) ends a run.
const RUN_END: u64 = 1 << 63;
/// Bytes per result record.
pub const RESULT_RECORD: usize = 40;
/// Bytes per result record of a run that writes normals ([`TileResult::normal`]).
pub const RESULT_RECORD_NORMALS: usize = 64;

/// Bytes per result record of a run that writes normals (`normals`) or not.
pub const fn result_record(normals: bool) -> usize {
    if normals {
        RESULT_RECORD_NORMALS
    } else {
        RESULT_RECORD
    }
}
/// Bit 63 of a spill record's index: the point is a halo copy, owned by another tile.
const HALO: u64 = 1 << 63;
/// Bit 62 of a spill record's index: the point keeps its position (`--classes`). Global indices
/// are record numbers of one file, far below 2⁶².
const HELD: u64 = 1 << 62;
/// Write buffer per open spill file.
const BUFFER: usize = 1 << 18;

fn err(path: &Path, e: std::io::Error) -> TilingError {
    TilingError::Io {
        path: path.to_path_buf(),
        error: e,
    }
}

/// Writers of the spill files of every tile (pass 2).
///
/// Each tile gets a memory buffer; a full buffer is appended to the tile's file, which is opened
/// only for that write. So any number of tiles works within the open-file limit, and the buffers
/// together stay within the memory the caller gives. A buffer is one sorted run of blocks: the
/// longer the buffers, the smaller each block's box.
pub struct SpillWriter {
    dir: PathBuf,
    buffers: Vec<Vec<u8>>,
    cap: usize,
    bytes: u64,
    grid: MortonGrid,
    /// Scratch of [`SpillWriter::flush`]: the sort keys, a record's Morton code (all ones for a
    /// halo copy) with its place in the buffer in the low 16 bits.
    keys: Vec<u64>,
    /// Scratch: the buffer in block order, and its block table.
    ordered: Vec<u8>,
    table: Vec<u8>,
}

/// Most bytes one tile's buffer holds: 2¹⁶ records, so a record's place in its buffer fits the
/// low 16 bits of its sort key.
const MAX_TILE_BUFFER: usize = SPILL_RECORD << 16;

impl SpillWriter {
    /// Creates one empty spill file and block table per tile in `dir`, for points within
    /// `bounds` (the cloud's: it only orders the blocks, so any box is correct), with `memory`
    /// bytes for the buffers of all tiles together (each between 4 KiB and 2 MiB).
    ///
    /// # Errors
    /// The files cannot be created.
    pub fn create(
        dir: &Path,
        tiles: usize,
        bounds: &Aabb,
        memory: u64,
    ) -> Result<SpillWriter, TilingError> {
        for t in 0..tiles {
            for p in [spill_path(dir, t), blocks_path(dir, t)] {
                File::create(&p).map_err(|e| err(&p, e))?;
            }
        }
        let share = usize::try_from(memory / tiles.max(1) as u64).unwrap_or(usize::MAX);
        let cap = share.clamp(4 << 10, MAX_TILE_BUFFER) / SPILL_RECORD * SPILL_RECORD;
        Ok(SpillWriter {
            dir: dir.to_path_buf(),
            buffers: vec![Vec::new(); tiles],
            cap,
            bytes: 0,
            grid: MortonGrid::new(bounds),
            keys: Vec::new(),
            ordered: Vec::new(),
            table: Vec::new(),
        })
    }

    /// Appends tile `t`'s buffer to its spill file in block order, and its blocks to the table.
    fn flush(&mut self, t: usize) -> Result<(), TilingError> {
        let buf = &self.buffers[t];
        self.keys.clear();
        const PLACE: u64 = (1 << 16) - 1;
        debug_assert!(buf.len() <= MAX_TILE_BUFFER, "a place must fit PLACE");
        for (i, rec) in buf.chunks_exact(SPILL_RECORD).enumerate() {
            let (raw, p) = decode_spill(rec);
            // 47 bits of Morton code (almost 16 per axis) are plenty for blocks of 256.
            let code = if raw & HALO != 0 {
                !PLACE
            } else {
                self.grid.key(p) & !PLACE
            };
            self.keys.push(code | i as u64);
        }
        // Morton codes have 63 bits, so the halo copies sort last, in their buffer order.
        self.keys.sort_unstable();
        let owned = self.keys.partition_point(|k| k & !PLACE != !PLACE);
        self.ordered.clear();
        self.table.clear();
        let (ordered, table) = (&mut self.ordered, &mut self.table);
        let mut block = |keys: &[u64], owned: bool| {
            let mut bx = Aabb::empty();
            for &k in keys {
                let rec = &buf[(k & PLACE) as usize * SPILL_RECORD..][..SPILL_RECORD];
                if owned {
                    // Every point, not only those `Aabb::grow` takes: the box must hold them all.
                    let p = decode_spill(rec).1;
                    (bx.min, bx.max) = (bx.min.min(p), bx.max.max(p));
                }
                ordered.extend_from_slice(rec);
            }
            let n = keys.len() as u64 | if owned { 0 } else { RUN_END };
            table.extend_from_slice(&n.to_le_bytes());
            for v in [bx.min, bx.max] {
                for a in 0..3 {
                    table.extend_from_slice(&v[a].to_le_bytes());
                }
            }
        };
        for keys in self.keys[..owned].chunks_mut(SPILL_BLOCK) {
            // A block's records in buffer order, which is index order: readers merge sorted
            // blocks instead of sorting scattered records (the box is the same either way).
            keys.sort_unstable_by_key(|k| k & PLACE);
            block(keys, true);
        }
        // Always, even empty: it ends the run for readers.
        block(&self.keys[owned..], false);
        for (path, bytes) in [
            (spill_path(&self.dir, t), &self.ordered),
            (blocks_path(&self.dir, t), &self.table),
        ] {
            let mut f = std::fs::OpenOptions::new()
                .append(true)
                .open(&path)
                .map_err(|e| err(&path, e))?;
            f.write_all(bytes).map_err(|e| err(&path, e))?;
        }
        self.buffers[t].clear();
        Ok(())
    }

    /// Appends `point` to tile `t`, as owned or as a halo copy. Each tile's points come in
    /// increasing global-index order (the partition streams the input in order; readers rely
    /// on it).
    ///
    /// # Errors
    /// Write failures.
    pub fn push(&mut self, t: usize, point: &TilePoint) -> Result<(), TilingError> {
        let b = &mut self.buffers[t];
        if b.capacity() == 0 {
            b.reserve_exact(self.cap);
        }
        debug_assert!(point.index & (HALO | HELD) == 0);
        let raw =
            point.index | if point.owned { 0 } else { HALO } | if point.held { HELD } else { 0 };
        let p = point.p;
        b.extend_from_slice(&raw.to_le_bytes());
        b.extend_from_slice(&p.x.to_le_bytes());
        b.extend_from_slice(&p.y.to_le_bytes());
        b.extend_from_slice(&p.z.to_le_bytes());
        self.bytes += SPILL_RECORD as u64;
        if b.len() >= self.cap {
            self.flush(t)?;
        }
        Ok(())
    }

    /// Flushes every buffer; returns the bytes spilled.
    ///
    /// # Errors
    /// Write failures (a full disk shows here).
    pub fn finish(mut self) -> Result<u64, TilingError> {
        for t in 0..self.buffers.len() {
            if !self.buffers[t].is_empty() {
                self.flush(t)?;
            }
        }
        Ok(self.bytes)
    }
}

/// One point of a tile's working set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TilePoint {
    /// Global index.
    pub index: u64,
    /// Position.
    pub p: DVec3,
    /// True when the tile owns the point (false for halo copies).
    pub owned: bool,
    /// True when the point keeps its position (`--classes`).
    pub held: bool,
}

/// Records in tile `t`'s spill files (one in each of the `parts` part directories of the work
/// directory `dir`): exactly the points its first load holds.
///
/// # Errors
/// A file's metadata cannot be read.
pub fn spilled_points(dir: &Path, parts: u64, t: usize) -> Result<u64, TilingError> {
    let mut n = 0;
    for part in 0..parts {
        let path = spill_path(&part_dir(dir, part), t);
        n += std::fs::metadata(&path).map_err(|e| err(&path, e))?.len() / SPILL_RECORD as u64;
    }
    Ok(n)
}

/// A spill record's raw index word and position.
fn decode_spill(rec: &[u8]) -> (u64, DVec3) {
    let f = |o: usize| f64::from_le_bytes(rec[o..o + 8].try_into().expect("8 bytes"));
    let raw = u64::from_le_bytes(rec[0..8].try_into().expect("8 bytes"));
    (raw, DVec3::new(f(8), f(16), f(24)))
}

/// Opens tile `t`'s spill file in the part directory `part`; returns it with its length in
/// bytes.
fn open_spill(part: &Path, t: usize) -> Result<(File, PathBuf, u64), TilingError> {
    let path = spill_path(part, t);
    let f = File::open(&path).map_err(|e| err(&path, e))?;
    let len = f.metadata().map_err(|e| err(&path, e))?.len();
    if len % SPILL_RECORD as u64 != 0 {
        return Err(TilingError::Corrupt {
            path,
            detail: format!("{len} bytes is not a whole number of {SPILL_RECORD}-byte records"),
        });
    }
    Ok((f, path, len))
}

/// Decodes `len` bytes of records from `f`'s position, a whole buffer at a time and in place
/// (growth reads spill files many times; a `BufReader` copied every record once more); `keep`
/// filters them by (index, position, is_halo).
fn decode_range(
    f: &mut File,
    path: &Path,
    len: u64,
    buf: &mut Vec<u8>,
    keep: &mut impl FnMut(u64, DVec3, bool) -> bool,
    out: &mut Vec<TilePoint>,
) -> Result<(), TilingError> {
    buf.resize(BUFFER, 0);
    let mut left = len;
    while left > 0 {
        // A grown halo reads many files: honour Ctrl-C every buffer (8192 records).
        if crate::neighbours::cancel_requested() {
            return Err(TilingError::Cancelled);
        }
        let take = usize::try_from(left.min(BUFFER as u64)).expect("at most BUFFER");
        let chunk = &mut buf[..take];
        f.read_exact(chunk).map_err(|e| err(path, e))?;
        left -= take as u64;
        for rec in chunk.chunks_exact(SPILL_RECORD) {
            let (raw, p) = decode_spill(rec);
            let halo = raw & HALO != 0;
            let index = raw & !(HALO | HELD);
            if keep(index, p, halo) {
                out.push(TilePoint {
                    index,
                    p,
                    owned: !halo,
                    held: raw & HELD != 0,
                });
            }
        }
    }
    Ok(())
}

/// Reads tile `t`'s spill files (one in each of the `parts` part directories of `dir`); `keep`
/// filters the records by (index, position, is_halo). The records it keeps are appended in
/// global-index order.
///
/// # Errors
/// Read failures, a file whose length is not a whole number of records, a block table that
/// does not describe its file.
pub fn read_spill(
    dir: &Path,
    parts: u64,
    t: usize,
    mut keep: impl FnMut(u64, DVec3, bool) -> bool,
    out: &mut Vec<TilePoint>,
) -> Result<(), TilingError> {
    for part in 0..parts {
        read_blocks(&part_dir(dir, part), t, |_| true, &mut keep, out)?;
    }
    Ok(())
}

/// Reads the owned records of tile `t`'s spill file in the partition's parts `parts` that `keep`
/// accepts, where `keep` accepts nothing outside `span` (up to rounding): only the blocks whose
/// box meets `span` and passes `near` are read, from the block table (`near` must pass every box
/// that holds a point `keep` accepts). Appends the kept points in global-index order: exactly
/// what [`read_spill`] keeps of those parts' owned records `keep` accepts.
///
/// # Errors
/// Read failures, a block table that does not describe the file.
pub fn read_owned_near(
    dir: &Path,
    parts: std::ops::Range<u64>,
    t: usize,
    (span, near): (&Aabb, impl Fn(&Aabb) -> bool),
    mut keep: impl FnMut(DVec3) -> bool,
    out: &mut Vec<TilePoint>,
) -> Result<(), TilingError> {
    // `keep` decides; the span only picks blocks, widened so that a point `keep` places in a
    // cell whose box (computed from the cell's key) rounds a few ulps short is not missed.
    let pad = |a: usize| 1e-9 * (span.min[a].abs() + span.max[a].abs()) + f64::MIN_POSITIVE;
    let (lo, hi) = (
        DVec3::new(
            span.min.x - pad(0),
            span.min.y - pad(1),
            span.min.z - pad(2),
        ),
        DVec3::new(
            span.max.x + pad(0),
            span.max.y + pad(1),
            span.max.z + pad(2),
        ),
    );
    let meets = |b: &Aabb| (0..3).all(|a| b.min[a] <= hi[a] && b.max[a] >= lo[a]) && near(b);
    for part in parts {
        read_blocks(
            &part_dir(dir, part),
            t,
            meets,
            |_, p, halo| !halo && keep(p),
            out,
        )?;
    }
    Ok(())
}

/// Reads the blocks of tile `t`'s spill file in the part directory `part` that `select` picks
/// by their box (a halo block's is empty), keeping the records `keep` accepts, and appends them
/// in global-index order. Each buffer the partition wrote is a run of an index range above the
/// previous run's (a part streams its range of the input in index order), ending with its halo
/// block, so sorting each run's records by index orders them all; parts cover increasing
/// ranges, so reading them in order keeps the order.
fn read_blocks(
    part: &Path,
    t: usize,
    select: impl Fn(&Aabb) -> bool,
    mut keep: impl FnMut(u64, DVec3, bool) -> bool,
    out: &mut Vec<TilePoint>,
) -> Result<(), TilingError> {
    let (mut f, path, len) = open_spill(part, t)?;
    let mut buf = Vec::new();
    let (blocks, table_path) = read_table(part, t)?;
    let total: u64 = blocks.iter().map(|b| b.n).fold(0, u64::saturating_add);
    if total.saturating_mul(SPILL_RECORD as u64) != len {
        return Err(TilingError::Corrupt {
            path: table_path,
            detail: format!("its blocks hold {total} records, the spill file {len} bytes"),
        });
    }
    // Consecutive picked blocks are read at once: (first byte, bytes).
    let mut pending: Option<(u64, u64)> = None;
    let mut run_from = out.len();
    let mut at = 0u64;
    for &Block { n, end, bx } in &blocks {
        let bytes = n * SPILL_RECORD as u64;
        if select(&bx) {
            pending = match pending {
                Some((from, size)) if from + size == at => Some((from, size + bytes)),
                other => {
                    read_at(&mut f, &path, other, &mut buf, &mut keep, out)?;
                    Some((at, bytes))
                }
            };
        }
        at += bytes;
        if end {
            read_at(&mut f, &path, pending.take(), &mut buf, &mut keep, out)?;
            sort_run(&mut out[run_from..]);
            run_from = out.len();
        }
    }
    read_at(&mut f, &path, pending, &mut buf, &mut keep, out)?;
    sort_run(&mut out[run_from..]);
    Ok(())
}

/// One entry of a block table.
#[derive(Clone, Copy)]
struct Block {
    /// Records in the block.
    n: u64,
    /// Whether it ends a run (the halo block).
    end: bool,
    /// The box of its owned points (empty for the halo block).
    bx: Aabb,
}

/// The block table of tile `t`'s spill file in the part directory `part`, and its path.
fn read_table(part: &Path, t: usize) -> Result<(Vec<Block>, PathBuf), TilingError> {
    let path = blocks_path(part, t);
    let table = std::fs::read(&path).map_err(|e| err(&path, e))?;
    if table.len() % BLOCK_ENTRY != 0 {
        return Err(TilingError::Corrupt {
            detail: format!(
                "{} bytes is not a whole number of {BLOCK_ENTRY}-byte entries",
                table.len()
            ),
            path,
        });
    }
    let blocks = table
        .chunks_exact(BLOCK_ENTRY)
        .map(|e| {
            let count = u64::from_le_bytes(e[0..8].try_into().expect("8 bytes"));
            let v = |o: usize| f64::from_le_bytes(e[o..o + 8].try_into().expect("8 bytes"));
            Block {
                n: count & !RUN_END,
                end: count & RUN_END != 0,
                bx: Aabb {
                    min: DVec3::new(v(8), v(16), v(24)),
                    max: DVec3::new(v(32), v(40), v(48)),
                },
            }
        })
        .collect();
    Ok((blocks, path))
}

/// The owned records of tile `t`'s spill files in the partition's parts `parts` whose block's
/// box `inside` accepts, from the block tables alone: where `inside` accepts only boxes in which
/// a load keeps every point, a lower bound on what the load keeps, for the cost of reading the
/// tables (56 bytes per 256 records).
///
/// # Errors
/// Read failures, a table that is not whole entries.
pub fn owned_within(
    dir: &Path,
    parts: std::ops::Range<u64>,
    t: usize,
    inside: impl Fn(&Aabb) -> bool,
) -> Result<u64, TilingError> {
    let mut sum = 0u64;
    for part in parts {
        let (blocks, _) = read_table(&part_dir(dir, part), t)?;
        for b in blocks.iter().filter(|b| !b.end && inside(&b.bx)) {
            sum = sum.saturating_add(b.n);
        }
    }
    Ok(sum)
}

/// Orders the records read from one run by index. Each block holds its records in index order
/// (files written before that: in Morton order), so the records are a sequence of sorted
/// stretches, which the standard library's stable sort finds and merges; indices are distinct
/// within a run, so the result is the one order whichever sort is used. The sort's scratch is
/// at most one run's records (a run holds at most 2¹⁶), small beside the budget.
fn sort_run(records: &mut [TilePoint]) {
    records.sort_by_key(|p| p.index);
}

/// Decodes the byte range `range` (first byte, bytes) of `f`, if any.
fn read_at(
    f: &mut File,
    path: &Path,
    range: Option<(u64, u64)>,
    buf: &mut Vec<u8>,
    keep: &mut impl FnMut(u64, DVec3, bool) -> bool,
    out: &mut Vec<TilePoint>,
) -> Result<(), TilingError> {
    let Some((from, size)) = range else {
        return Ok(());
    };
    f.seek(SeekFrom::Start(from)).map_err(|e| err(path, e))?;
    decode_range(f, path, size, buf, keep, out)
}

/// One finished point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileResult {
    /// Global index.
    pub index: u64,
    /// New position.
    pub p: DVec3,
    /// Mean distance to the other members of its k-NN list.
    pub knn_mean: f64,
    /// What the output writes for it, in a run that writes normals.
    pub normal: Option<PointNormal>,
}

/// Files a merge keeps open at once.
pub const MAX_OPEN: usize = 256;

/// The record of `r`: its bytes and their length (40, or 64 with a normal).
fn encode(r: &TileResult) -> ([u8; RESULT_RECORD_NORMALS], usize) {
    let mut rec = [0u8; RESULT_RECORD_NORMALS];
    rec[0..8].copy_from_slice(&r.index.to_le_bytes());
    rec[8..16].copy_from_slice(&r.p.x.to_le_bytes());
    rec[16..24].copy_from_slice(&r.p.y.to_le_bytes());
    rec[24..32].copy_from_slice(&r.p.z.to_le_bytes());
    rec[32..40].copy_from_slice(&r.knn_mean.to_le_bytes());
    let Some(n) = r.normal else {
        return (rec, RESULT_RECORD);
    };
    for (k, v) in n.normal.into_iter().chain([n.curvature]).enumerate() {
        rec[40 + 4 * k..44 + 4 * k].copy_from_slice(&v.to_le_bytes());
    }
    rec[56] = n.structure;
    (rec, RESULT_RECORD_NORMALS)
}

/// Decodes one record of `rec.len()` bytes ([`result_record`]).
fn decode(rec: &[u8]) -> TileResult {
    let f = |o: usize| f64::from_le_bytes(rec[o..o + 8].try_into().expect("8 bytes"));
    let g = |o: usize| f32::from_le_bytes(rec[o..o + 4].try_into().expect("4 bytes"));
    TileResult {
        index: u64::from_le_bytes(rec[0..8].try_into().expect("8 bytes")),
        p: DVec3::new(f(8), f(16), f(24)),
        knn_mean: f(32),
        normal: (rec.len() == RESULT_RECORD_NORMALS).then(|| PointNormal {
            normal: [g(40), g(44), g(48)],
            curvature: g(52),
            structure: rec[56],
        }),
    }
}

/// Writes tile `t`'s results (sorted here by index) atomically: the file appears only complete.
///
/// # Errors
/// Write failures.
pub fn write_results(dir: &Path, t: usize, results: &mut [TileResult]) -> Result<u64, TilingError> {
    results.par_sort_unstable_by_key(|r| r.index);
    let path = result_path(dir, t);
    let mut f = AtomicFile::create(&path).map_err(|e| TilingError::Result(Box::new(e)))?;
    let bytes: Vec<u8> = results
        .par_iter()
        .flat_map_iter(|r| {
            let (rec, n) = encode(r);
            rec.into_iter().take(n)
        })
        .collect();
    f.write_all(&bytes).map_err(|e| err(&path, e))?;
    f.commit_unsynced()
        .map_err(|e| TilingError::Result(Box::new(e)))?;
    Ok(bytes.len() as u64)
}

struct Cursor {
    path: PathBuf,
    reader: BufReader<File>,
    left: u64,
    /// Bytes per record.
    record: usize,
}

impl Cursor {
    fn next(&mut self) -> Result<Option<TileResult>, TilingError> {
        if self.left == 0 {
            return Ok(None);
        }
        self.left -= 1;
        // Decoded in the reader's buffer when the record is there whole: a copy per record
        // (`read_exact`) was a third of a 100 M-point stitch.
        let buf = self.reader.fill_buf().map_err(|e| err(&self.path, e))?;
        if buf.len() >= self.record {
            let r = decode(&buf[..self.record]);
            self.reader.consume(self.record);
            return Ok(Some(r));
        }
        let mut rec = [0u8; RESULT_RECORD_NORMALS];
        let rec = &mut rec[..self.record];
        self.reader
            .read_exact(rec)
            .map_err(|e| err(&self.path, e))?;
        Ok(Some(decode(rec)))
    }
}

/// Calls `f` on every result of tiles `0..tiles` in `dir` (records with normals when `normals`),
/// tile by tile: for what does not depend on the order, without a merge.
///
/// # Errors
/// A missing or truncated result file.
pub fn for_each_result(
    dir: &Path,
    tiles: usize,
    normals: bool,
    mut f: impl FnMut(&TileResult),
) -> Result<(), TilingError> {
    let record = result_record(normals);
    for t in 0..tiles {
        let mut one = ResultMerge::from_paths(&[result_path(dir, t)], record, None)?;
        while let Some(r) = one.next_result()? {
            f(&r);
        }
    }
    Ok(())
}

/// The first of the `records` records of the result file `f` (sorted by index) whose index is
/// at least `index`, by binary search (`records` when none is).
fn first_at_least(
    f: &mut File,
    path: &Path,
    record: usize,
    records: u64,
    index: u64,
) -> Result<u64, TilingError> {
    let (mut lo, mut hi) = (0u64, records);
    let mut at = [0u8; 8];
    // At most 64 halvings.
    while lo < hi {
        let mid = lo + (hi - lo) / 2;
        f.seek(SeekFrom::Start(mid * record as u64))
            .and_then(|_| f.read_exact(&mut at))
            .map_err(|e| err(path, e))?;
        if u64::from_le_bytes(at) < index {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    Ok(lo)
}

/// Merges the result files of all tiles into one stream in global-index order.
pub struct ResultMerge {
    cursors: Vec<Cursor>,
    heap: BinaryHeap<Reverse<(u64, usize)>>,
    pending: Vec<Option<TileResult>>,
}

impl ResultMerge {
    /// Opens the result files of tiles `0..tiles` in `dir`, whose records hold normals
    /// (`normals`, [`result_record`]) or not. Beyond [`MAX_OPEN`] tiles, groups of result files
    /// are first merged into intermediate files in `dir`, so the merge never holds more than
    /// [`MAX_OPEN`] files open.
    ///
    /// # Errors
    /// A missing or truncated result file.
    pub fn open(dir: &Path, tiles: usize, normals: bool) -> Result<ResultMerge, TilingError> {
        ResultMerge::open_in(dir, tiles, normals, None)
    }

    /// [`ResultMerge::open`] restricted to the results whose index is in `indices`, for stitch
    /// range `range` (which names its intermediate merges): each result file is entered by a
    /// binary search on its sorted indices.
    ///
    /// # Errors
    /// As [`ResultMerge::open`].
    pub fn open_range(
        dir: &Path,
        tiles: usize,
        normals: bool,
        range: u64,
        indices: std::ops::Range<u64>,
    ) -> Result<ResultMerge, TilingError> {
        ResultMerge::open_in(dir, tiles, normals, Some((range, indices)))
    }

    fn open_in(
        dir: &Path,
        tiles: usize,
        normals: bool,
        range: Option<(u64, std::ops::Range<u64>)>,
    ) -> Result<ResultMerge, TilingError> {
        let record = result_record(normals);
        let mut paths: Vec<PathBuf> = (0..tiles).map(|t| result_path(dir, t)).collect();
        // Only the tiles' own files are cut to the range; the merges of a level are within it.
        let mut indices = range.as_ref().map(|(_, i)| i.clone());
        let mut level = 0;
        while paths.len() > MAX_OPEN {
            let mut next = Vec::new();
            for (g, group) in paths.chunks(MAX_OPEN).enumerate() {
                let path = match &range {
                    Some((r, _)) => range_merge_path(dir, *r, level, g),
                    None => merge_path(dir, level, g),
                };
                let mut m = ResultMerge::from_paths(group, record, indices.as_ref())?;
                let mut w = BufWriter::new(File::create(&path).map_err(|e| err(&path, e))?);
                while let Some(r) = m.next_result()? {
                    let (rec, n) = encode(&r);
                    w.write_all(&rec[..n]).map_err(|e| err(&path, e))?;
                }
                w.into_inner().map_err(|e| err(&path, e.into_error()))?;
                next.push(path);
            }
            paths = next;
            indices = None;
            level += 1;
        }
        ResultMerge::from_paths(&paths, record, indices.as_ref())
    }

    /// The merge of the result files `paths`; with `indices`, of their results in that range.
    fn from_paths(
        paths: &[PathBuf],
        record: usize,
        indices: Option<&std::ops::Range<u64>>,
    ) -> Result<ResultMerge, TilingError> {
        let mut cursors = Vec::with_capacity(paths.len());
        for path in paths {
            let mut f = File::open(path).map_err(|e| err(path, e))?;
            let len = f.metadata().map_err(|e| err(path, e))?.len();
            if len % record as u64 != 0 {
                return Err(TilingError::Corrupt {
                    path: path.clone(),
                    detail: format!("{len} bytes is not a whole number of {record}-byte records"),
                });
            }
            let records = len / record as u64;
            let (first, end) = match indices {
                Some(r) => (
                    first_at_least(&mut f, path, record, records, r.start)?,
                    first_at_least(&mut f, path, record, records, r.end)?,
                ),
                None => (0, records),
            };
            f.seek(SeekFrom::Start(first * record as u64))
                .map_err(|e| err(path, e))?;
            cursors.push(Cursor {
                path: path.clone(),
                reader: BufReader::with_capacity(1 << 16, f),
                left: end.saturating_sub(first),
                record,
            });
        }
        let n = cursors.len();
        let mut m = ResultMerge {
            heap: BinaryHeap::with_capacity(n),
            pending: vec![None; n],
            cursors,
        };
        for t in 0..n {
            m.refill(t)?;
        }
        Ok(m)
    }

    fn refill(&mut self, t: usize) -> Result<(), TilingError> {
        if let Some(r) = self.cursors[t].next()? {
            self.heap.push(Reverse((r.index, t)));
            self.pending[t] = Some(r);
        }
        Ok(())
    }

    /// The next result in global-index order.
    ///
    /// # Errors
    /// Read failures.
    pub fn next_result(&mut self) -> Result<Option<TileResult>, TilingError> {
        let Some(mut top) = self.heap.peek_mut() else {
            return Ok(None);
        };
        let t = top.0.1;
        let r = self.pending[t].take();
        // The file's next record replaces the top in place: one sift down, not a pop and a push.
        match self.cursors[t].next()? {
            Some(next) => {
                *top = Reverse((next.index, t));
                self.pending[t] = Some(next);
            }
            None => {
                std::collections::binary_heap::PeekMut::pop(top);
            }
        }
        Ok(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(index: u64, p: DVec3, owned: bool, held: bool) -> TilePoint {
        TilePoint {
            index,
            p,
            owned,
            held,
        }
    }

    #[test]
    fn spill_and_results_round_trip_and_merge_in_index_order() {
        let dir = tempfile::tempdir().unwrap();
        let part = part_dir(dir.path(), 0);
        std::fs::create_dir(&part).unwrap();
        let mut w = SpillWriter::create(&part, 2, &Aabb::empty(), 1 << 20).unwrap();
        let a = DVec3::new(1.0, 2.0, 3.0);
        w.push(0, &point(5, a, true, false)).unwrap();
        w.push(1, &point(5, a, false, false)).unwrap();
        let far = DVec3::new(-1.0, 0.5, f64::MAX);
        w.push(1, &point(9, far, true, true)).unwrap();
        assert_eq!(w.finish().unwrap(), 96);
        let mut pts = Vec::new();
        read_spill(dir.path(), 1, 1, |_, _, _| true, &mut pts).unwrap();
        assert_eq!(pts, [point(5, a, false, false), point(9, far, true, true)]);
        let r = |i: u64| TileResult {
            index: i,
            p: DVec3::splat(i as f64),
            knn_mean: 0.5,
            normal: None,
        };
        write_results(dir.path(), 0, &mut [r(7), r(1), r(4)]).unwrap();
        write_results(dir.path(), 1, &mut [r(3), r(0), r(9)]).unwrap();
        let mut m = ResultMerge::open(dir.path(), 2, false).unwrap();
        let mut got = Vec::new();
        while let Some(x) = m.next_result().unwrap() {
            got.push(x.index);
        }
        assert_eq!(got, vec![0, 1, 3, 4, 7, 9]);
    }

    /// Part `part` of one tile of `n` records at random positions, a quarter of them halo
    /// copies, some at one duplicated position: the records of `range`, written with `memory`
    /// bytes of buffer into the part's directory in `dir`.
    fn scattered_tile(dir: &Path, part: u64, range: std::ops::Range<u64>, n: u64, memory: u64) {
        let bounds = Aabb {
            min: DVec3::ZERO,
            max: DVec3::splat(10.0),
        };
        let part = part_dir(dir, part);
        std::fs::create_dir(&part).unwrap();
        let mut w = SpillWriter::create(&part, 1, &bounds, memory).unwrap();
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 * 10.0
        };
        for index in 0..n {
            let i = (index * 7919) % n;
            let p = if i.is_multiple_of(97) {
                DVec3::splat(5.0)
            } else {
                DVec3::new(rnd(), rnd(), rnd())
            };
            if range.contains(&index) {
                w.push(
                    0,
                    &point(index, p, !i.is_multiple_of(4), i.is_multiple_of(5)),
                )
                .unwrap();
            }
        }
        w.finish().unwrap();
    }

    /// Boxes to read by: inside, a thin slab, one point, outside, around everything.
    const SPANS: [(DVec3, DVec3); 5] = [
        (DVec3::splat(4.0), DVec3::splat(6.0)),
        (DVec3::new(0.0, 9.0, 0.0), DVec3::new(10.0, 10.0, 0.5)),
        (DVec3::splat(5.0), DVec3::splat(5.0)),
        (DVec3::splat(-3.0), DVec3::splat(-1.0)),
        (DVec3::splat(-1.0), DVec3::splat(11.0)),
    ];

    #[test]
    fn issue16_reads_by_block_keep_exactly_the_owned_points_a_whole_read_keeps() {
        let n = 40_000u64;
        // 64 KiB of buffer: 20 sorted runs; 32 MiB: one.
        for memory in [64 << 10, 32 << 20] {
            let dir = tempfile::tempdir().unwrap();
            scattered_tile(dir.path(), 0, 0..n, n, memory);
            let table_path = blocks_path(&part_dir(dir.path(), 0), 0);
            let table = std::fs::read(&table_path).unwrap();
            assert!(table.len() / BLOCK_ENTRY > 100, "{} blocks", table.len());
            let mut whole = Vec::new();
            read_spill(dir.path(), 1, 0, |_, _, _| true, &mut whole).unwrap();
            assert_eq!(whole.len(), n as usize);
            assert!(whole.windows(2).all(|w| w[0].index < w[1].index));
            for (lo, hi) in SPANS {
                let span = Aabb { min: lo, max: hi };
                let inside = |p: DVec3| (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]);
                let mut want = Vec::new();
                read_spill(dir.path(), 1, 0, |_, p, halo| !halo && inside(p), &mut want).unwrap();
                let mut seen = 0;
                let mut got = vec![point(u64::MAX, DVec3::ZERO, true, true)];
                let keep = |p| {
                    seen += 1;
                    inside(p)
                };
                read_owned_near(
                    dir.path(),
                    0..1,
                    0,
                    (&span, |_: &Aabb| true),
                    keep,
                    &mut got,
                )
                .unwrap();
                assert_eq!(got[1..], want[..], "{span:?}");
                // The blocks whose box lies in the span bound what the read keeps from below.
                let within = |b: &Aabb| (0..3).all(|a| b.min[a] >= lo[a] && b.max[a] <= hi[a]);
                let bound = owned_within(dir.path(), 0..1, 0, within).unwrap();
                assert!(
                    bound <= want.len() as u64,
                    "{bound} > {} {span:?}",
                    want.len()
                );
                // One sorted run reads a small span's blocks only (under a third of the 30 000
                // owned records for a span of 1 % of the volume or less).
                if memory > 1 << 20 && hi.x - lo.x < 5.0 {
                    assert!(seen < n as usize / 4, "read {seen} records for {span:?}");
                }
            }
            // A box of half the volume holds no more than its points; with one sorted run (117
            // Morton-ordered blocks) some blocks whole. With 20 short runs a block spreads over
            // most of the cube.
            let (lo, hi) = (DVec3::splat(1.0), DVec3::splat(9.0));
            let within = |b: &Aabb| (0..3).all(|a| b.min[a] >= lo[a] && b.max[a] <= hi[a]);
            let bound = owned_within(dir.path(), 0..1, 0, within).unwrap();
            let inside = whole
                .iter()
                .filter(|p| p.owned && (0..3).all(|a| p.p[a] >= lo[a] && p.p[a] <= hi[a]))
                .count() as u64;
            assert!(bound <= inside, "{bound} {inside}");
            assert!(memory < 1 << 20 || bound > 0, "{bound}");
            // Every owned block accepted: the tile's owned records (the halo block is not one).
            let owned = whole.iter().filter(|p| p.owned).count() as u64;
            assert_eq!(owned_within(dir.path(), 0..1, 0, |_| true).unwrap(), owned);
            assert!(owned > 0);
            // A table that does not describe the file is refused, a missing one too.
            let span = Aabb {
                min: DVec3::splat(2.0),
                max: DVec3::splat(3.0),
            };
            let inside = |p: DVec3| (0..3).all(|a| p[a] >= 2.0 && p[a] <= 3.0);
            let read = || {
                let mut out = Vec::new();
                read_owned_near(
                    dir.path(),
                    0..1,
                    0,
                    (&span, |_: &Aabb| true),
                    inside,
                    &mut out,
                )
            };
            let short = &table[..table.len() - BLOCK_ENTRY];
            std::fs::write(&table_path, short).unwrap();
            assert!(matches!(read(), Err(TilingError::Corrupt { .. })));
            std::fs::remove_file(&table_path).unwrap();
            assert!(matches!(read(), Err(TilingError::Io { .. })));
        }
    }

    #[test]
    fn issue16_each_block_holds_its_records_in_index_order() {
        let n = 40_000u64;
        let dir = tempfile::tempdir().unwrap();
        scattered_tile(dir.path(), 0, 0..n, n, 64 << 10);
        let part = part_dir(dir.path(), 0);
        let table = std::fs::read(blocks_path(&part, 0)).unwrap();
        let file = std::fs::read(spill_path(&part, 0)).unwrap();
        let (mut at, mut last, mut descents) = (0, None, 0);
        for e in table.chunks_exact(BLOCK_ENTRY) {
            let count = u64::from_le_bytes(e[0..8].try_into().unwrap()) & !RUN_END;
            let indices: Vec<u64> = file[at..at + count as usize * SPILL_RECORD]
                .chunks_exact(SPILL_RECORD)
                .map(|r| decode_spill(r).0 & !(HALO | HELD))
                .collect();
            assert!(
                indices.windows(2).all(|w| w[0] < w[1]),
                "block at byte {at}"
            );
            if let (Some(l), Some(&f)) = (last, indices.first()) {
                descents += usize::from(f < l);
            }
            last = indices.last().copied().or(last);
            at += count as usize * SPILL_RECORD;
        }
        assert_eq!(at, file.len());
        // The blocks themselves follow the Morton order, not the index order.
        assert!(descents > 10, "{descents}");
    }

    #[test]
    fn issue11_a_tile_spilled_in_parts_reads_as_the_tile_spilled_whole() {
        let n = 30_000u64;
        let whole = tempfile::tempdir().unwrap();
        scattered_tile(whole.path(), 0, 0..n, n, 256 << 10);
        let cut = tempfile::tempdir().unwrap();
        let ranges = [0..7_000, 7_000..7_001, 7_001..7_001, 7_001..n];
        for (part, range) in ranges.into_iter().enumerate() {
            scattered_tile(cut.path(), part as u64, range, n, 64 << 10);
        }
        let read = |dir: &Path, parts: u64| {
            let mut all = Vec::new();
            read_spill(dir, parts, 0, |_, _, _| true, &mut all).unwrap();
            let mut near = Vec::new();
            for (lo, hi) in SPANS {
                let span = Aabb { min: lo, max: hi };
                let inside = |p: DVec3| (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]);
                read_owned_near(
                    dir,
                    0..parts,
                    0,
                    (&span, |_: &Aabb| true),
                    inside,
                    &mut near,
                )
                .unwrap();
            }
            (all, near)
        };
        let (a, b) = (read(whole.path(), 1), read(cut.path(), 4));
        assert_eq!(a.0.len(), n as usize);
        assert!(a.1.len() > 1000);
        assert_eq!(a, b);
        assert_eq!(spilled_points(cut.path(), 4, 0).unwrap(), n);
    }

    #[test]
    fn more_tiles_than_open_files_merge_in_levels() {
        let dir = tempfile::tempdir().unwrap();
        let tiles = MAX_OPEN * 2 + 3;
        let mut w = SpillWriter::create(dir.path(), tiles, &Aabb::empty(), 1 << 20).unwrap();
        for t in 0..tiles {
            w.push(t, &point(t as u64, DVec3::ONE, true, false))
                .unwrap();
            let mut rs = [TileResult {
                index: (tiles - 1 - t) as u64,
                p: DVec3::ZERO,
                knn_mean: 0.0,
                normal: Some(PointNormal {
                    normal: [0.0, -0.5, t as f32],
                    curvature: 0.25,
                    structure: (t % 6) as u8,
                }),
            }];
            assert_eq!(
                write_results(dir.path(), t, &mut rs).unwrap(),
                RESULT_RECORD_NORMALS as u64
            );
        }
        w.finish().unwrap();
        let mut m = ResultMerge::open(dir.path(), tiles, true).unwrap();
        for want in 0..tiles as u64 {
            let r = m.next_result().unwrap().unwrap();
            assert_eq!(r.index, want);
            let t = tiles - 1 - want as usize;
            let n = r.normal.unwrap();
            assert_eq!((n.normal, n.curvature), ([0.0, -0.5, t as f32], 0.25));
            assert_eq!(n.structure, (t % 6) as u8);
        }
        assert!(m.next_result().unwrap().is_none());
        // Read as records without normals, the files do not divide: refused.
        assert!(matches!(
            ResultMerge::open(dir.path(), 3, false),
            Err(TilingError::Corrupt { .. })
        ));
    }
}
