//! The kinds of object a simulated scene is made of, and the class each kind's returns carry.
//!
//! | kind | LAS class | why that code |
//! |---|---|---|
//! | `ground` | 2 | ASPRS ground (road, kerbs, sidewalks, yards) |
//! | `low_vegetation` | 3 | ASPRS low vegetation (bushes) |
//! | `high_vegetation` | 5 | ASPRS high vegetation (tree trunks and leaves) |
//! | `building` | 6 | ASPRS building |
//! | `wire` | 14 | ASPRS wire – conductor |
//! | `pole` | 64 | user code (ASPRS has no pole class) |
//! | `car` | 65 | user code |
//! | `fence` | 66 | user code |
//! | `object` | 67 | user code: the sculpted shape and any `--mesh` placed in the scene |
//! | `mixed` | 68 | user code: a return whose footprint mixed two objects at a depth edge |
//!
//! Codes 7 (noise) and 18 (high noise) are never written: the denoiser uses them to flag outliers.
//! User codes start at 64, the first code LAS 1.4 leaves to users.

use std::fmt;

/// What a triangle of the scene, or a return, belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// Road, kerbs, sidewalks and yards.
    Ground,
    /// Bushes.
    LowVegetation,
    /// Tree trunks and leaves.
    HighVegetation,
    /// Walls and roofs.
    Building,
    /// Overhead wires between poles.
    Wire,
    /// Street-light poles.
    Pole,
    /// Parked cars.
    Car,
    /// Fences.
    Fence,
    /// The sculpted object and meshes placed with `--mesh`.
    Object,
    /// A return that mixed two objects at a depth edge (never a triangle's kind).
    Mixed,
}

impl Kind {
    /// Every kind, in code order.
    pub const ALL: [Kind; 10] = [
        Kind::Ground,
        Kind::LowVegetation,
        Kind::HighVegetation,
        Kind::Building,
        Kind::Wire,
        Kind::Pole,
        Kind::Car,
        Kind::Fence,
        Kind::Object,
        Kind::Mixed,
    ];

    /// The kinds whose returns are the "surfaces" of the scorer: smooth, closed, well sampled.
    pub const SURFACES: [Kind; 4] = [Kind::Ground, Kind::Building, Kind::Car, Kind::Object];

    /// The name in files and tables.
    pub fn name(self) -> &'static str {
        match self {
            Kind::Ground => "ground",
            Kind::LowVegetation => "low_vegetation",
            Kind::HighVegetation => "high_vegetation",
            Kind::Building => "building",
            Kind::Wire => "wire",
            Kind::Pole => "pole",
            Kind::Car => "car",
            Kind::Fence => "fence",
            Kind::Object => "object",
            Kind::Mixed => "mixed",
        }
    }

    /// The LAS classification code (see the module table).
    pub fn las_class(self) -> u8 {
        match self {
            Kind::Ground => 2,
            Kind::LowVegetation => 3,
            Kind::HighVegetation => 5,
            Kind::Building => 6,
            Kind::Wire => 14,
            Kind::Pole => 64,
            Kind::Car => 65,
            Kind::Fence => 66,
            Kind::Object => 67,
            Kind::Mixed => 68,
        }
    }

    /// The kind of a LAS classification code written by [`Kind::las_class`].
    pub fn from_las_class(code: u8) -> Option<Kind> {
        Kind::ALL.into_iter().find(|k| k.las_class() == code)
    }

    /// Diffuse reflectance at the sensor's wavelength (near infrared), for the intensity.
    pub fn reflectance(self) -> f64 {
        match self {
            Kind::Ground => 0.25,
            Kind::LowVegetation | Kind::HighVegetation => 0.5,
            Kind::Building => 0.4,
            Kind::Wire => 0.2,
            Kind::Pole => 0.35,
            Kind::Car => 0.6,
            Kind::Fence => 0.45,
            Kind::Object => 0.7,
            Kind::Mixed => 0.3,
        }
    }

    /// True for the scorer's surfaces ([`Kind::SURFACES`]).
    pub fn is_surface(self) -> bool {
        Kind::SURFACES.contains(&self)
    }
}

impl fmt::Display for Kind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_distinct_and_never_the_noise_classes() {
        let mut codes: Vec<u8> = Kind::ALL.iter().map(|k| k.las_class()).collect();
        assert!(!codes.contains(&7) && !codes.contains(&18));
        for k in Kind::ALL {
            assert_eq!(Kind::from_las_class(k.las_class()), Some(k));
        }
        codes.sort_unstable();
        codes.dedup();
        assert_eq!(codes.len(), Kind::ALL.len());
    }
}
