//! The median nearest-neighbour spacing of a cloud: the real-scan protocol's noise unit
//! (`qemd noise --unit median-spacing`) and the spacing `qemd info` reports.

use super::{KnnIndex, NeighboursError};

/// Neighbours looked at for a point's spacing: duplicates come first in a list, and some scans
/// store every point twice.
const LOOK: usize = 8;

/// The median distance from an indexed point of `index` to its nearest other point at a non-zero
/// distance among its 8 nearest (exact duplicates are skipped). `None` when every indexed point
/// duplicates another or fewer than two are indexed.
///
/// # Errors
/// As [`KnnIndex::knn_all`] (more points than u32 indices).
pub fn median_spacing(index: &KnnIndex) -> Result<Option<f64>, NeighboursError> {
    if index.indexed() < 2 {
        return Ok(None);
    }
    let (lists, _) = index.knn_all(LOOK.min(index.indexed()))?;
    let mut d: Vec<f64> = (0..lists.len())
        .filter_map(|i| {
            lists
                .get(i)
                .iter()
                .map(|&u| index.dist2(i, u as usize))
                .find(|&x| x > 0.0)
        })
        .map(f64::sqrt)
        .collect();
    if d.is_empty() {
        return Ok(None);
    }
    let m = d.len() / 2;
    Ok(Some(*d.select_nth_unstable_by(m, f64::total_cmp).1))
}
