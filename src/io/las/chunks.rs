//! Checks of LAZ chunk framing that the `laz` decoder trusts, made before it decodes a byte.
//!
//! # Brief overview
//!
//! ```text
//!  laszip VLR: compressor type ─► must agree with the item version (1–2 point-wise, 3–4 layered)
//!  layered chunk (PDRF 6–10):  first point (record bytes) │ u32 count │ u32 layer sizes │ layers
//!                              └─ every layer size summed must fit in the chunk's bytes
//! ```
//!
//! * The layered decoder of point formats 6–10 allocates a buffer of each **layer size** stored
//!   at the start of every chunk before reading it, so one flipped byte asks for 4 GiB and the
//!   process aborts on allocation failure, which no error handling can catch. [`check_layers`]
//!   reads every chunk's layer sizes (through the chunk table when there is one, walking the
//!   chunks one after the other otherwise) and refuses a chunk whose layers do not fit in its
//!   bytes, so no buffer the decoder allocates is larger than the file.
//! * A laszip VLR whose compressor type disagrees with its items (point-wise chunks of variable
//!   size, which need a chunk table the point-wise reader never reads) makes `laz` panic on the
//!   first point; [`check_compressor`] refuses it first.
//! * Layers per item: Point14 9, RGB14 1, RGBNIR14 2, Byte14(n) n, WavePacket14 1 (LASzip's
//!   layered format). Cost: one read of about 100 bytes per chunk (a chunk holds 50,000 points by
//!   default, a COPC node a few thousand).

use std::io::{Read, Seek};
use std::path::Path;

use laz::{LazItemType, LazVlr};

use super::read_at;
use crate::io::IoError;

/// The compressor types of the laszip VLR (its first two bytes).
const POINT_WISE: u16 = 1;
/// Point-wise chunks.
const POINT_WISE_CHUNKED: u16 = 2;
/// Layered chunks (items of version 3 and 4).
const LAYERED: u16 = 3;

/// Whether the items are compressed in layers (PDRF 6–10, item versions 3 and 4).
pub(super) fn is_layered(vlr: &LazVlr) -> bool {
    vlr.items().first().is_some_and(|i| i.version() >= 3)
}

/// Refuses a laszip VLR whose compressor type does not match its items, or point-wise
/// compression with variable-size chunks.
///
/// # Errors
/// [`IoError::Header`] naming the compressor type and item version.
pub(super) fn check_compressor(path: &Path, raw: &[u8], vlr: &LazVlr) -> Result<(), IoError> {
    let compressor = raw.get(..2).map_or(0, |b| u16::from_le_bytes([b[0], b[1]]));
    let version = vlr.items().first().map_or(0, |i| i.version());
    let fits = match compressor {
        LAYERED => version >= 3,
        POINT_WISE_CHUNKED => version <= 2,
        POINT_WISE => version <= 2 && !vlr.uses_variable_size_chunks(),
        _ => false,
    };
    if fits {
        Ok(())
    } else {
        Err(IoError::header(
            path,
            format!(
                "bad laszip VLR: compressor type {compressor} with items of version {version}{}",
                if vlr.uses_variable_size_chunks() {
                    " and variable-size chunks"
                } else {
                    ""
                }
            ),
        ))
    }
}

/// Layers each chunk stores for the items of `vlr`.
fn layer_count(path: &Path, vlr: &LazVlr) -> Result<usize, IoError> {
    vlr.items().iter().try_fold(0usize, |n, item| {
        let k = match item.item_type() {
            LazItemType::Point14 => 9,
            LazItemType::RGB14 | LazItemType::WavePacket14 => 1,
            LazItemType::RGBNIR14 => 2,
            LazItemType::Byte14(c) => usize::from(c),
            t => {
                return Err(IoError::header(
                    path,
                    format!("bad laszip VLR: item {t:?} in layered compression"),
                ));
            }
        };
        Ok(n + k)
    })
}

/// Where the chunks lie: from the chunk table, or to be found by walking.
pub(super) enum Chunks<'a> {
    /// The byte count of every chunk, from the chunk table, and where the table starts.
    Table(&'a [u64], u64),
    /// No chunk table: fixed-size chunks follow each other up to `end`, enough for `count`
    /// points of `chunk_size` each.
    Walk {
        end: u64,
        count: u64,
        chunk_size: u64,
    },
}

/// Checks that the layers of every layered chunk fit in the chunk's bytes.
///
/// `first` is the byte where the first chunk starts (after the 8-byte chunk table offset),
/// `record_len` the size of the raw first point.
///
/// # Errors
/// [`IoError::Invalid`] for a chunk whose layer sizes run past its end or the file's;
/// [`IoError::Truncated`] when the chunks end before the points the header declares.
pub(super) fn check_layers<R: Read + Seek>(
    path: &Path,
    file: &mut R,
    vlr: &LazVlr,
    first: u64,
    record_len: u64,
    chunks: Chunks<'_>,
) -> Result<(), IoError> {
    let layers = layer_count(path, vlr)?;
    let head = record_len + 4 + 4 * layers as u64;
    let io = |e| IoError::io(path, e);
    // The bytes of the layers of the chunk at `start`, `limit` bytes long at most.
    let mut layers_of = |k: usize, start: u64, limit: u64| -> Result<u64, IoError> {
        let bad = |what: String| {
            IoError::invalid(
                path,
                format!("bad LAZ chunk {} at byte {start}: {what}", k + 1),
            )
        };
        if head > limit {
            return Err(bad(format!(
                "its {head}-byte header does not fit in {limit} bytes"
            )));
        }
        let h = read_at(file, start, head as usize).map_err(io)?;
        let sizes = h[record_len as usize + 4..]
            .chunks_exact(4)
            .map(|b| u64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])));
        let total: u64 = sizes.sum();
        if total > limit - head {
            return Err(bad(format!(
                "its layers declare {total} bytes, {} remain",
                limit - head
            )));
        }
        Ok(head + total)
    };
    match chunks {
        Chunks::Table(bytes, table_at) => {
            let mut start = first;
            for (k, &len) in bytes.iter().enumerate() {
                let end = start.saturating_add(len);
                if end > table_at {
                    return Err(IoError::invalid(
                        path,
                        format!(
                            "bad LAZ chunk table: chunk {} ends at byte {end}, past the table at \
                             byte {table_at}",
                            k + 1
                        ),
                    ));
                }
                layers_of(k, start, len)?;
                start = end;
            }
        }
        Chunks::Walk {
            end,
            count,
            chunk_size,
        } => {
            let n = count.div_ceil(chunk_size.max(1));
            let mut start = first;
            for k in 0..n {
                if start >= end {
                    return Err(IoError::truncated(
                        path,
                        format!(
                            "the header declares {count} points but the LAZ data ends after {k} \
                             chunks of {chunk_size}"
                        ),
                    ));
                }
                start += layers_of(k as usize, start, end - start)?;
            }
        }
    }
    Ok(())
}
