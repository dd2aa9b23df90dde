//! The on-disk formats of the tiled path: spill files (points per tile) and result files
//! (finished tiles), both little-endian fixed-size records, in the work directory
//! ([`super::workdir`] names them).
//!
//! ```text
//!  spill  tile_<t>.pts   [ index|HALO<<63|HELD<<62 : u64 | x : f64 | y : f64 | z : f64 ]   32 bytes
//!  result tile_<t>.res   [ index : u64 | x : f64 | y : f64 | z : f64 | knn_mean : f64 ] 40 bytes,
//!                        sorted by index, written atomically: a result file is a checkpoint
//!          with normals  [ … 40 bytes as above | nx ny nz curvature : f32 | structure : u8 | 0 × 7 ]
//!                        64 bytes, only when the run writes normals (`--write-normals`)
//! ```

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};

use std::path::{Path, PathBuf};

use glam::DVec3;
use rayon::prelude::*;

use super::TilingError;
use super::workdir::{merge_path, result_path, spill_path};
use crate::io::AtomicFile;
use crate::points::PointNormal;

/// Bytes per spill record.
pub const SPILL_RECORD: usize = 32;
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
/// together stay under [`BUFFERS_TOTAL`].
pub struct SpillWriter {
    dir: PathBuf,
    buffers: Vec<Vec<u8>>,
    cap: usize,
    bytes: u64,
}

/// Memory for all spill buffers together.
pub const BUFFERS_TOTAL: usize = 32 << 20;

impl SpillWriter {
    /// Creates one empty spill file per tile in `dir`.
    ///
    /// # Errors
    /// The files cannot be created.
    pub fn create(dir: &Path, tiles: usize) -> Result<SpillWriter, TilingError> {
        for t in 0..tiles {
            let p = spill_path(dir, t);
            File::create(&p).map_err(|e| err(&p, e))?;
        }
        let cap =
            (BUFFERS_TOTAL / tiles.max(1)).clamp(4 << 10, BUFFER) / SPILL_RECORD * SPILL_RECORD;
        Ok(SpillWriter {
            dir: dir.to_path_buf(),
            buffers: vec![Vec::new(); tiles],
            cap,
            bytes: 0,
        })
    }

    fn flush(&mut self, t: usize) -> Result<(), TilingError> {
        let path = spill_path(&self.dir, t);
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .map_err(|e| err(&path, e))?;
        f.write_all(&self.buffers[t]).map_err(|e| err(&path, e))?;
        self.buffers[t].clear();
        Ok(())
    }

    /// Appends `point` to tile `t`, as owned or as a halo copy.
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

/// Records in tile `t`'s spill file: exactly the points its first load holds.
///
/// # Errors
/// The file's metadata cannot be read.
pub fn spilled_points(dir: &Path, t: usize) -> Result<u64, TilingError> {
    let path = spill_path(dir, t);
    let len = std::fs::metadata(&path).map_err(|e| err(&path, e))?.len();
    Ok(len / SPILL_RECORD as u64)
}

/// Reads tile `t`'s spill file; `keep` filters the records by (index, position, is_halo).
///
/// # Errors
/// Read failures, a file whose length is not a whole number of records.
pub fn read_spill(
    dir: &Path,
    t: usize,
    mut keep: impl FnMut(u64, DVec3, bool) -> bool,
    out: &mut Vec<TilePoint>,
) -> Result<(), TilingError> {
    let path = spill_path(dir, t);
    let f = File::open(&path).map_err(|e| err(&path, e))?;
    let len = f.metadata().map_err(|e| err(&path, e))?.len();
    if len % SPILL_RECORD as u64 != 0 {
        return Err(TilingError::Corrupt {
            path,
            detail: format!("{len} bytes is not a whole number of {SPILL_RECORD}-byte records"),
        });
    }
    // Whole buffers of records, decoded in place (reading record by record through a
    // `BufReader` copied every record once more: growth reads spill files many times).
    let mut r = f;
    let mut buf = vec![0u8; BUFFER];
    let mut left = len;
    while left > 0 {
        // A grown halo reads many files: honour Ctrl-C every buffer (8192 records).
        if crate::neighbours::cancel_requested() {
            return Err(TilingError::Cancelled);
        }
        let take = usize::try_from(left.min(BUFFER as u64)).expect("at most BUFFER");
        let chunk = &mut buf[..take];
        r.read_exact(chunk).map_err(|e| err(&path, e))?;
        left -= take as u64;
        for rec in chunk.chunks_exact(SPILL_RECORD) {
            let raw = u64::from_le_bytes(rec[0..8].try_into().expect("8 bytes"));
            let f = |o: usize| f64::from_le_bytes(rec[o..o + 8].try_into().expect("8 bytes"));
            let p = DVec3::new(f(8), f(16), f(24));
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
        let mut rec = [0u8; RESULT_RECORD_NORMALS];
        let rec = &mut rec[..self.record];
        self.reader
            .read_exact(rec)
            .map_err(|e| err(&self.path, e))?;
        Ok(Some(decode(rec)))
    }
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
        let record = result_record(normals);
        let mut paths: Vec<PathBuf> = (0..tiles).map(|t| result_path(dir, t)).collect();
        let mut level = 0;
        while paths.len() > MAX_OPEN {
            let mut next = Vec::new();
            for (g, group) in paths.chunks(MAX_OPEN).enumerate() {
                let path = merge_path(dir, level, g);
                let mut m = ResultMerge::from_paths(group, record)?;
                let mut w = BufWriter::new(File::create(&path).map_err(|e| err(&path, e))?);
                while let Some(r) = m.next_result()? {
                    let (rec, n) = encode(&r);
                    w.write_all(&rec[..n]).map_err(|e| err(&path, e))?;
                }
                w.into_inner().map_err(|e| err(&path, e.into_error()))?;
                next.push(path);
            }
            paths = next;
            level += 1;
        }
        ResultMerge::from_paths(&paths, record)
    }

    fn from_paths(paths: &[PathBuf], record: usize) -> Result<ResultMerge, TilingError> {
        let mut cursors = Vec::with_capacity(paths.len());
        for path in paths {
            let f = File::open(path).map_err(|e| err(path, e))?;
            let len = f.metadata().map_err(|e| err(path, e))?.len();
            if len % record as u64 != 0 {
                return Err(TilingError::Corrupt {
                    path: path.clone(),
                    detail: format!("{len} bytes is not a whole number of {record}-byte records"),
                });
            }
            cursors.push(Cursor {
                path: path.clone(),
                reader: BufReader::with_capacity(1 << 16, f),
                left: len / record as u64,
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
        let Some(Reverse((_, t))) = self.heap.pop() else {
            return Ok(None);
        };
        let r = self.pending[t].take();
        self.refill(t)?;
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
        let mut w = SpillWriter::create(dir.path(), 2).unwrap();
        let a = DVec3::new(1.0, 2.0, 3.0);
        w.push(0, &point(5, a, true, false)).unwrap();
        w.push(1, &point(5, a, false, false)).unwrap();
        let far = DVec3::new(-1.0, 0.5, f64::MAX);
        w.push(1, &point(9, far, true, true)).unwrap();
        assert_eq!(w.finish().unwrap(), 96);
        let mut pts = Vec::new();
        read_spill(dir.path(), 1, |_, _, _| true, &mut pts).unwrap();
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

    #[test]
    fn more_tiles_than_open_files_merge_in_levels() {
        let dir = tempfile::tempdir().unwrap();
        let tiles = MAX_OPEN * 2 + 3;
        let mut w = SpillWriter::create(dir.path(), tiles).unwrap();
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
