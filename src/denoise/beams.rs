//! Where each return's beam comes from: the sensor's position when the point was measured.
//!
//! # Brief overview
//!
//! LiDAR measures a range along a beam, so its noise lies along the beam and its direction is
//! exact. The guarded operator uses the beam where it is known ([`super::structure`] fits each
//! list along it, [`super::guarded`] moves each point only along it). A beam is the unit
//! direction from the sensor to the return:
//!
//! ```text
//!   sensor o ──────────────▶ p      d = (p − o) / |p − o|
//! ```
//!
//! The sensor is one point for a sweep or a station ([`SensorOrigin::At`]; `Auto` puts it at the
//! origin for formats stored in their sensor's frame, decided by the pipeline, which knows the
//! format), or moves along a trajectory (the pipeline interpolates it at each return's GPS time
//! and hands the directions in). Range noise moves a return along its own beam, so the direction
//! from the noisy position is the true one: directions are computed once, from the input.

use glam::DVec3;
use rayon::prelude::*;

/// Where the beams of a point cloud come from (`--sensor-origin`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum SensorOrigin {
    /// From the input: formats stored in their sensor's frame (KITTI `.bin`, nuScenes
    /// `.pcd.bin`) have their sensor at `(0, 0, 0)`; other inputs have no beams unless a
    /// trajectory gives them. Without an input (arrays), no beams.
    #[default]
    Auto,
    /// No beams: every list is fitted by PCA and every step is free.
    Off,
    /// One sensor position for every return (a sweep, a terrestrial station), in the input's
    /// coordinates.
    At([f64; 3]),
}

impl SensorOrigin {
    /// The sensor position, when it is one given point.
    pub fn point(self) -> Option<DVec3> {
        match self {
            SensorOrigin::At(p) => Some(DVec3::from_array(p)),
            _ => None,
        }
    }

    /// True when every coordinate is finite.
    pub fn is_valid(self) -> bool {
        self.point().is_none_or(|p| p.is_finite())
    }
}

impl std::fmt::Display for SensorOrigin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SensorOrigin::Auto => f.write_str("auto"),
            SensorOrigin::Off => f.write_str("none"),
            SensorOrigin::At([x, y, z]) => write!(f, "{x},{y},{z}"),
        }
    }
}

impl std::str::FromStr for SensorOrigin {
    type Err = String;

    /// `auto`, `none`, or `X,Y,Z`.
    fn from_str(s: &str) -> Result<SensorOrigin, String> {
        match s.trim() {
            "auto" => return Ok(SensorOrigin::Auto),
            "none" | "off" => return Ok(SensorOrigin::Off),
            _ => {}
        }
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        let bad = || format!("expected auto, none or X,Y,Z, got {s:?}");
        let [x, y, z] = parts.as_slice() else {
            return Err(bad());
        };
        let num = |t: &str| t.parse::<f64>().map_err(|_| bad());
        Ok(SensorOrigin::At([num(x)?, num(y)?, num(z)?]))
    }
}

impl serde::Serialize for SensorOrigin {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            SensorOrigin::At(p) => p.serialize(s),
            other => s.serialize_str(&other.to_string()),
        }
    }
}

impl<'de> serde::Deserialize<'de> for SensorOrigin {
    /// `"auto"`, `"none"`, `"X,Y,Z"` (a query string) or `[X, Y, Z]` (JSON).
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<SensorOrigin, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Wire {
            Text(String),
            Point([f64; 3]),
        }
        match Wire::deserialize(d)? {
            Wire::Text(t) => t.parse().map_err(serde::de::Error::custom),
            Wire::Point(p) => Ok(SensorOrigin::At(p)),
        }
    }
}

/// The unit direction from `origin` to `p`; zero where they coincide (no beam).
#[inline]
pub fn direction(p: DVec3, origin: DVec3) -> DVec3 {
    (p - origin).normalize_or_zero()
}

/// The beam of every position from one sensor position.
pub fn from_origin(positions: &[DVec3], origin: DVec3) -> Vec<DVec3> {
    positions
        .par_iter()
        .with_min_len(4096)
        .map(|&p| direction(p, origin))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sensor_origins_parse_print_and_round_trip_through_json() {
        for (text, want) in [
            ("auto", SensorOrigin::Auto),
            ("none", SensorOrigin::Off),
            ("1,-2.5, 3e2", SensorOrigin::At([1.0, -2.5, 300.0])),
        ] {
            let o: SensorOrigin = text.parse().unwrap();
            assert_eq!(o, want);
            assert_eq!(o.to_string().parse::<SensorOrigin>().unwrap(), o);
            let json = serde_json::to_string(&o).unwrap();
            assert_eq!(serde_json::from_str::<SensorOrigin>(&json).unwrap(), o);
        }
        assert_eq!(
            serde_json::from_str::<SensorOrigin>("[0, 0, 1.73]").unwrap(),
            SensorOrigin::At([0.0, 0.0, 1.73])
        );
        assert!("1,2".parse::<SensorOrigin>().is_err());
        assert!("a,b,c".parse::<SensorOrigin>().is_err());
        assert!(!SensorOrigin::At([f64::NAN, 0.0, 0.0]).is_valid());
    }

    #[test]
    fn a_beam_points_from_the_sensor_to_the_return() {
        let o = DVec3::new(1.0, 2.0, 3.0);
        let d = from_origin(&[DVec3::new(4.0, 6.0, 3.0), o], o);
        assert!((d[0] - DVec3::new(0.6, 0.8, 0.0)).length() < 1e-15);
        assert_eq!(d[1], DVec3::ZERO);
    }
}
