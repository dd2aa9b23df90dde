//! The point-cloud rules that turn an input record plus its result into an output record: the
//! outlier threshold, flagging or removing outliers, unprocessed points dropped or kept
//! (organized clouds), stale stored normals cleared, the run's normals carried to the sink
//! (`--write-normals`). Both point drivers assemble with it, so they write the same bytes.

use glam::DVec3;

use super::OutlierMode;
use super::normals::{self, NormalsAction};
use crate::geometry::ExactSum;
use crate::io::SourceInfo;
use crate::points::{FLAG_NOISE, PointBatch, PointNormal, Schema};

/// The outlier threshold `mean + alpha·σ` from exact sums of the statistic and its square.
pub fn threshold(sum: &ExactSum, sq: &ExactSum, alpha: f64) -> f64 {
    let n = sum.count().max(1) as f64;
    let mean = sum.value() / n;
    let var = (sq.value() / n - mean * mean).max(0.0);
    mean + alpha * var.sqrt()
}

/// True when `info`'s unprocessed points (failing [`crate::points::in_range`]) must be written
/// back unchanged (organized clouds) rather than dropped.
fn keeps_non_finite(info: &SourceInfo) -> bool {
    info.is_organized()
}

/// Assembles output records (see the module overview).
#[derive(Debug, Clone)]
pub struct Assembler {
    /// Unprocessed points are written back unchanged (organized clouds), not dropped.
    pub keep_non_finite: bool,
    mode: OutlierMode,
    /// A point whose k-NN mean distance is above it is an outlier.
    pub threshold: f64,
    /// Stored normal fields to clear (they would be stale).
    normals: Option<(Schema, [usize; 3])>,
    /// Carry each point's written normal to the sink (`--write-normals`).
    write_normals: bool,
}

impl Assembler {
    /// The rules for records of `info` with outlier handling `mode` at `threshold`.
    pub fn new(info: &SourceInfo, mode: OutlierMode, threshold: f64) -> Assembler {
        Assembler {
            keep_non_finite: keeps_non_finite(info),
            mode,
            threshold,
            normals: normals::normal_fields(&info.schema).map(|f| (info.schema.clone(), f)),
            write_normals: false,
        }
    }

    /// These rules, carrying each point's written normal to the sink (`on`).
    pub fn writing_normals(mut self, on: bool) -> Assembler {
        self.write_normals = on;
        self
    }

    /// What the output does with stored normals.
    pub fn normals_action(&self) -> NormalsAction {
        if self.write_normals {
            NormalsAction::Written
        } else if self.normals.is_some() {
            NormalsAction::Cleared
        } else {
            NormalsAction::None
        }
    }

    /// True when a point whose k-NN mean distance is `knn_mean` is flagged or removed.
    fn is_outlier(&self, knn_mean: f64) -> bool {
        self.mode != OutlierMode::Off && knn_mean > self.threshold
    }

    /// True when [`Assembler::push`] writes a record for a point with this result's k-NN mean
    /// distance (`None`: an unprocessed point).
    pub fn writes(&self, knn_mean: Option<f64>) -> bool {
        match knn_mean {
            None => self.keep_non_finite,
            Some(m) => {
                self.keep_non_finite || !(self.is_outlier(m) && self.mode == OutlierMode::Remove)
            }
        }
    }

    /// Appends a point to `out`, its stored normals cleared, with `normal` when normals are
    /// written.
    fn put(&self, out: &mut PointBatch, p: DVec3, record: &[u8], normal: PointNormal) {
        out.push(p, record);
        if let Some((schema, f)) = &self.normals {
            let end = out.records.len();
            normals::clear_points(schema, *f, &mut out.records[end - schema.record_len..end]);
        }
        if self.write_normals {
            out.normals.push(normal);
        }
    }

    /// Appends input point `i` of `batch` to `out` given its result (None for non-finite points)
    /// and what the run computed for its normal (written with `--write-normals`; `None` for a
    /// point without one); returns whether it was flagged or removed as an outlier.
    pub fn push(
        &self,
        batch: &PointBatch,
        i: usize,
        result: Option<(DVec3, f64)>,
        normal: Option<PointNormal>,
        out: &mut PointBatch,
    ) -> bool {
        let normal = normal.unwrap_or(PointNormal::NONE);
        let (p, outlier) = match result {
            None if !self.keep_non_finite => return false,
            None => (batch.positions[i], false),
            // A flagged outlier keeps its input position: it is reported, not "denoised" onto
            // a surface it does not belong to.
            Some((_, m)) if self.is_outlier(m) => (batch.positions[i], true),
            Some((p, _)) => (p, false),
        };
        if outlier && self.mode == OutlierMode::Remove {
            if self.keep_non_finite {
                // An organized cloud keeps its image layout: a removed point becomes a NaN
                // placeholder, as its invalid points are.
                self.put(out, DVec3::NAN, batch.record(i), PointNormal::NONE);
            }
            return true;
        }
        self.put(out, p, batch.record(i), normal);
        if self.mode == OutlierMode::Classify {
            out.flags.push(if outlier { FLAG_NOISE } else { 0 });
        }
        outlier
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::Format;
    use crate::points::ScalarType;

    fn batch() -> PointBatch {
        let mut b = PointBatch::with_capacity(12, 3);
        for (i, p) in [DVec3::ZERO, DVec3::ONE, DVec3::splat(2.0)]
            .iter()
            .enumerate()
        {
            b.push(*p, &[i as u8; 12]);
        }
        b
    }

    fn assemble(mode: OutlierMode) -> (PointBatch, u64) {
        let info = SourceInfo::generated(Format::Ply, ScalarType::F32, 3, None);
        let asm = Assembler::new(&info, mode, 0.5);
        let b = batch();
        let results = [Some((DVec3::X, 0.1)), None, Some((DVec3::Y, 0.9))];
        let mut out = PointBatch::with_capacity(12, 3);
        let mut found = 0;
        for (i, r) in results.iter().enumerate() {
            assert_eq!(asm.writes(r.map(|r| r.1)), {
                let before = out.len();
                found += asm.push(&b, i, *r, None, &mut out) as u64;
                out.len() > before
            });
        }
        (out, found)
    }

    #[test]
    fn outliers_are_left_flagged_or_removed_and_unprocessed_points_dropped() {
        let (off, found) = assemble(OutlierMode::Off);
        assert_eq!(found, 0);
        assert_eq!(off.positions, vec![DVec3::X, DVec3::Y]);
        assert!(off.flags.is_empty());
        let (classify, found) = assemble(OutlierMode::Classify);
        assert_eq!(found, 1);
        // The flagged outlier keeps its input position.
        assert_eq!(classify.positions, vec![DVec3::X, DVec3::splat(2.0)]);
        assert_eq!(classify.flags, vec![0, FLAG_NOISE]);
        assert_eq!(classify.record(1), &[2u8; 12]);
        let (remove, found) = assemble(OutlierMode::Remove);
        assert_eq!(found, 1);
        assert_eq!(remove.positions, vec![DVec3::X]);
    }

    #[test]
    fn issue9_written_normals_follow_their_points() {
        let info = SourceInfo::generated(Format::Ply, ScalarType::F32, 3, None);
        let n = |s: u8| PointNormal {
            normal: [0.0, 0.0, 1.0],
            curvature: 0.5,
            structure: s,
        };
        let b = batch();
        let results = [Some((DVec3::X, 0.1)), None, Some((DVec3::Y, 0.9))];
        let normals = [Some(n(0)), None, Some(n(2))];
        let run = |asm: Assembler| {
            let mut out = PointBatch::with_capacity(12, 3);
            for i in 0..3 {
                asm.push(&b, i, results[i], normals[i], &mut out);
            }
            out
        };
        let off = run(Assembler::new(&info, OutlierMode::Off, 0.5));
        assert!(off.normals.is_empty());
        let on = Assembler::new(&info, OutlierMode::Remove, 0.5).writing_normals(true);
        assert_eq!(on.normals_action(), NormalsAction::Written);
        // The removed outlier takes its normal with it; the unprocessed point is dropped.
        assert_eq!(run(on).normals, vec![n(0)]);
        let on = Assembler::new(&info, OutlierMode::Classify, 0.5).writing_normals(true);
        let out = run(on);
        assert_eq!(out.normals, vec![n(0), n(2)]);
        assert_eq!(out.len(), out.normals.len());
    }

    #[test]
    fn the_threshold_is_mean_plus_alpha_sigma() {
        let values = [1.0, 2.0, 3.0, 4.0];
        let sum: ExactSum = values.iter().copied().collect();
        let sq: ExactSum = values.iter().map(|v| v * v).collect();
        let sigma = 1.25f64.sqrt();
        assert!((threshold(&sum, &sq, 2.0) - (2.5 + 2.0 * sigma)).abs() < 1e-12);
        assert_eq!(threshold(&ExactSum::new(), &ExactSum::new(), 1.0), 0.0);
    }
}
