//! The sensor trajectory text format: where the sensor was at each GPS time.
//!
//! This is the one definition of the format `qemd synth lidar --trajectory-out` writes and a
//! reader of scans takes to know each return's beam origin (matched by GPS time):
//!
//! ```text
//! # qemd trajectory: gps_time x y z (seconds; the points' coordinates)
//! 1000 0 -1.8 1.73
//! 1000.02 0.2 -1.8 1.734
//! ```
//!
//! * One sample per line: GPS time, then x, y and z of the sensor's origin, in the same frame as
//!   the points (a file's sensor frame, or its world coordinates), separated by spaces or tabs.
//!   Further columns (an SBET export's attitude, say) are ignored.
//! * Lines that are empty or start with `#` are comments.
//! * Times never decrease. Between two samples the position is interpolated linearly (exact for
//!   the simulator's straight paths, which it samples at every mobile profile and every 0.01 s of
//!   an airborne strip). Outside the samples' time span a return has no known origin (`None`:
//!   `qemd denoise --trajectory` denoises it without a beam, rather than give it one from an end
//!   sample seconds away), except that a single sample is a sensor standing still at any time. A
//!   sweep or a terrestrial station is a sensor standing still: two samples with the same
//!   position at its first and last pulse, or one.
//!
//! Numbers are written in Rust's shortest round-trip form, so a trajectory reads back exactly.
//!
//! [`TimeField`] finds the time a return is matched by: LAS `gps_time`, else a field named
//! `gps_time`, `time`, `timestamp` or `t` (PLY, PCD — ROS drivers' `time` —, text columns), in
//! the trajectory's time base.

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::{AtomicFile, IoError};
use crate::points::Schema;

/// A sensor's positions over time.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trajectory {
    /// `(gps_time, position)`, times non-decreasing.
    pub samples: Vec<(f64, DVec3)>,
}

/// The comment line the writer puts first.
pub const HEADER: &str = "# qemd trajectory: gps_time x y z (seconds; the points' coordinates)";

impl Trajectory {
    /// Reads a trajectory file.
    ///
    /// # Errors
    /// An unreadable file; a line that does not start with four finite numbers; a time smaller
    /// than the one before; no samples at all. Each names the file (and the line).
    pub fn read(path: &Path) -> Result<Trajectory, IoError> {
        let file = super::open_file(path)?;
        let mut samples: Vec<(f64, DVec3)> = Vec::new();
        for (n, line) in BufReader::new(file).lines().enumerate() {
            let line = line.map_err(|e| IoError::io(path, e))?;
            let t = line.trim();
            if t.is_empty() || t.starts_with('#') {
                continue;
            }
            let bad = |what: &str| IoError::invalid(path, format!("line {}: {what}", n + 1));
            let v: Vec<f64> = t
                .split_whitespace()
                .take(4)
                .map(|w| {
                    w.parse::<f64>()
                        .map_err(|_| bad(&format!("`{w}` is not a number")))
                })
                .collect::<Result<_, _>>()?;
            if v.len() < 4 {
                return Err(bad("expected gps_time x y z"));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(bad("a value is not finite"));
            }
            if let Some(&(prev, _)) = samples.last()
                && v[0] < prev
            {
                return Err(bad(&format!(
                    "time {} comes after {prev}: times must not decrease",
                    v[0]
                )));
            }
            samples.push((v[0], DVec3::new(v[1], v[2], v[3])));
        }
        if samples.is_empty() {
            return Err(IoError::invalid(path, "the trajectory has no samples"));
        }
        Ok(Trajectory { samples })
    }

    /// Writes the trajectory (atomically).
    ///
    /// # Errors
    /// The file cannot be written.
    pub fn write(&self, path: &Path) -> Result<(), IoError> {
        let mut f = AtomicFile::create(path)?;
        let mut text = String::with_capacity(64 * (self.samples.len() + 1));
        text.push_str(HEADER);
        text.push('\n');
        for (t, p) in &self.samples {
            text.push_str(&format!("{t} {} {} {}\n", p.x, p.y, p.z));
        }
        f.write_all(text.as_bytes()).map_err(|e| f.err(e))?;
        f.commit()
    }

    /// The position at time `t`: linear between the samples around it; `None` outside the
    /// samples' time span (or for a non-finite `t`), but a single sample's position at any time.
    /// `None` without samples.
    pub fn position_at(&self, t: f64) -> Option<DVec3> {
        let s = &self.samples;
        let (first, last) = (s.first()?, s.last()?);
        if s.len() == 1 {
            return Some(first.1);
        }
        if t.is_nan() || t < first.0 || t > last.0 {
            return None;
        }
        let k = s.partition_point(|&(ts, _)| ts <= t);
        if k == s.len() {
            return Some(last.1);
        }
        let ((t0, p0), (t1, p1)) = (s[k - 1], s[k]);
        if t1 <= t0 {
            return Some(p1);
        }
        // p0 + (p1 - p0)·s rather than glam's lerp (p0·(1−s) + p1·s): a sensor that stands
        // still then sits exactly where it stands.
        Some(p0 + (p1 - p0) * ((t - t0) / (t1 - t0)))
    }
}

/// Which field of a record holds its time, for matching a trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TimeField {
    index: usize,
}

impl TimeField {
    /// Names a time field may have, in the order they are looked for.
    pub const NAMES: [&'static str; 4] = ["gps_time", "time", "timestamp", "t"];

    /// The time field of `schema`, `None` when it has none.
    pub fn of(schema: &Schema) -> Option<TimeField> {
        TimeField::NAMES
            .iter()
            .find_map(|n| schema.field_index(n))
            .map(|index| TimeField { index })
    }

    /// The time of `record`.
    pub fn get(&self, schema: &Schema, record: &[u8]) -> f64 {
        schema.get_f64(record, self.index)
    }
}

/// The error of an input without a time field, asked to match a trajectory.
pub fn no_time_field(input: &Path) -> IoError {
    IoError::Unsupported {
        path: PathBuf::from(input),
        detail: format!(
            "has no time field ({}) to match the trajectory's samples by",
            TimeField::NAMES.join(", ")
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_interpolation_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.txt");
        let t = Trajectory {
            samples: vec![
                (1000.0, DVec3::new(0.0, -1.8, 1.73)),
                (1000.1, DVec3::new(1.0, -1.8, 1.76)),
                (1000.3, DVec3::new(1.0, 0.2, 1.76)),
            ],
        };
        t.write(&path).unwrap();
        let back = Trajectory::read(&path).unwrap();
        assert_eq!(back, t);
        let mid = back.position_at(1000.05).unwrap();
        assert!((mid - DVec3::new(0.5, -1.8, 1.745)).length() < 1e-9);
        assert_eq!(back.position_at(1000.0), Some(t.samples[0].1));
        assert_eq!(back.position_at(1000.3), Some(t.samples[2].1));
        // Outside the span a return has no origin; a single sample stands still.
        assert_eq!(back.position_at(900.0), None);
        assert_eq!(back.position_at(2000.0), None);
        assert_eq!(back.position_at(f64::NAN), None);
        let still = Trajectory {
            samples: vec![(5.0, DVec3::ONE)],
        };
        assert_eq!(still.position_at(-1e9), Some(DVec3::ONE));
        // Extra columns are ignored; comments and blank lines skipped.
        std::fs::write(&path, "# c\n\n1 2 3 4 0.1 0.2 0.3\n").unwrap();
        assert_eq!(
            Trajectory::read(&path).unwrap().samples,
            vec![(1.0, DVec3::new(2.0, 3.0, 4.0))]
        );
        for bad in [
            "1 2 3\n",
            "2 0 0 0\n1 0 0 0\n",
            "a 0 0 0\n",
            "# only\n",
            "1 0 0 inf\n",
        ] {
            std::fs::write(&path, bad).unwrap();
            let e = Trajectory::read(&path).unwrap_err().to_string();
            assert!(e.contains("t.txt"), "{e}");
        }
    }
}
