//! The four sensors, their presets, and the pulses each fires.
//!
//! # Brief overview
//!
//! [`SensorFlags`] holds what a user may set (every field optional: the `qemd synth lidar` flags);
//! [`Sensor::resolve`] lays it over the sensor's preset ([`Sensor::preset`], the one table of
//! defaults) and validates it. [`Sensor::pulses`] then lists every pulse in firing order, each
//! with its origin, nominal unit direction, GPS time, ring, scanner channel, scan angle, point
//! source id and scan flags; [`Sensor::trajectory`] gives the sensor's position over time in the
//! format of [`crate::io::trajectory`].
//!
//! | sensor | geometry | pulses (defaults) | σ range | divergence |
//! |---|---|---|---|---|
//! | `spinning` `kitti64` | HDL-64E: 64 beams, +2° to −24.8° (32 at 1/3°, 32 at 1/2°), 0.17° azimuth, 1.73 m high | 64 × 2118, one 360° sweep, 10 Hz | 2 cm | 2 mrad |
//! | `spinning` `nuscenes32` | HDL-32E: 32 beams +10.67° to −30.67° (1.33°), 0.16° azimuth, 1.84 m | 32 × 2250 | 2 cm | 2.8 mrad |
//! | `spinning` `vlp16` | VLP-16: 16 beams ±15° (2°), 0.2° azimuth, 1.5 m | 16 × 1800 | 3 cm | 3 mrad |
//! | `mobile` | one profile scanner on a van, 2.6 m high, driving 20 m at 10 m/s along the right lane; each profile a full circle in a plane turned 45° about the vertical from the cross-section; profiles 0.2 m apart, 0.1° between pulses | 100 × 3600 | 2 cm | 0.5 mrad |
//! | `airborne` | line scanner at 500 m, ±25°, two strips along the street flown in opposite directions with 50 % side overlap, 60 m/s, 12 pulses/m² per strip, zig-zag (or parallel) lines; only pulses aimed into the scene are fired | about 135 k | 5 cm | 0.3 mrad |
//! | `terrestrial` | one station on a sidewalk, 1.6 m high, looking across the street (azimuth ±35°, elevation −12° to +25°), 0.1° grid, column by column | 700 × 370 per station | 4 mm | 0.3 mrad |
//!
//! Times: a sweep starts at GPS time 1000 s; pulses are evenly spaced over the sweep (spinning),
//! the profile (mobile), the scan line (airborne) or at 1 MHz (terrestrial), so every pulse has
//! its own time and times increase in file order. `--density F` multiplies the pulse count by
//! about F (the azimuth step of a sweep by 1/F; both steps of a grid by 1/√F).

use glam::{DVec2, DVec3};

use super::LidarError;
use super::beam::Physics;
use super::street::Layout;
use crate::io::trajectory::Trajectory;

/// GPS time of the first pulse (s).
pub const START_TIME: f64 = 1000.0;

/// The kind of sensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum SensorKind {
    /// A spinning multi-beam sensor on a car: one 360° sweep.
    Spinning,
    /// A profile scanner on a moving van (mobile mapping).
    Mobile,
    /// An airborne line scanner, overlapping strips.
    Airborne,
    /// Terrestrial station(s): a spherical grid.
    Terrestrial,
}

impl SensorKind {
    /// The CLI name.
    pub fn name(self) -> &'static str {
        match self {
            SensorKind::Spinning => "spinning",
            SensorKind::Mobile => "mobile",
            SensorKind::Airborne => "airborne",
            SensorKind::Terrestrial => "terrestrial",
        }
    }
}

/// Presets of the spinning sensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Velodyne HDL-64E as on the KITTI car.
    Kitti64,
    /// Velodyne HDL-32E as on the nuScenes car.
    Nuscenes32,
    /// Velodyne VLP-16.
    Vlp16,
}

impl Preset {
    /// The CLI name.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Kitti64 => "kitti64",
            Preset::Nuscenes32 => "nuscenes32",
            Preset::Vlp16 => "vlp16",
        }
    }
}

/// Airborne scan pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Pattern {
    /// An oscillating mirror: lines alternate direction.
    Zigzag,
    /// A rotating polygon: every line in the same direction.
    Parallel,
}

/// What a user may set; `None` keeps the preset's value.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct SensorFlags {
    /// Spinning preset: kitti64 (default), nuscenes32 or vlp16.
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    pub preset: Option<Preset>,
    /// Range noise σ along the beam (m).
    #[cfg_attr(feature = "cli", arg(long))]
    pub sigma: Option<f64>,
    /// Angular jitter σ of the beam direction (degrees; 0: none).
    #[cfg_attr(feature = "cli", arg(long))]
    pub jitter: Option<f64>,
    /// Full beam divergence (mrad; 0: a thin ray).
    #[cfg_attr(feature = "cli", arg(long))]
    pub divergence: Option<f64>,
    /// Sub-rays over the footprint: 1, 7 or 19.
    #[cfg_attr(feature = "cli", arg(long))]
    pub footprint_rays: Option<usize>,
    /// Share of pulses dropped at random (0–1).
    #[cfg_attr(feature = "cli", arg(long))]
    pub dropout: Option<f64>,
    /// No return beyond this range (m).
    #[cfg_attr(feature = "cli", arg(long))]
    pub max_range: Option<f64>,
    /// Hits within this range of each other form one echo (the pulse-mixing distance, m).
    #[cfg_attr(feature = "cli", arg(long))]
    pub mix_distance: Option<f64>,
    /// Smallest share of the footprint an echo needs to be detected (0–1].
    #[cfg_attr(feature = "cli", arg(long))]
    pub detect: Option<f64>,
    /// Pulse count multiplier (about; see the sensor table).
    #[cfg_attr(feature = "cli", arg(long))]
    pub density: Option<f64>,
    /// Sensor height above the ground below it (m).
    #[cfg_attr(feature = "cli", arg(long))]
    pub height: Option<f64>,
    /// Spinning: the sensor's (x, y) in the street frame [default: right lane, middle].
    #[cfg_attr(feature = "cli", arg(long, value_parser = parse_xy))]
    pub position: Option<DVec2>,
    /// Spinning: number of beams, spread evenly over --fov-up … --fov-down (replaces the
    /// preset's beam table).
    #[cfg_attr(feature = "cli", arg(long))]
    pub beams: Option<usize>,
    /// Spinning: elevation of the highest beam (degrees).
    #[cfg_attr(feature = "cli", arg(long, allow_hyphen_values = true))]
    pub fov_up: Option<f64>,
    /// Spinning: elevation of the lowest beam (degrees).
    #[cfg_attr(feature = "cli", arg(long, allow_hyphen_values = true))]
    pub fov_down: Option<f64>,
    /// Spinning: azimuth step (degrees).
    #[cfg_attr(feature = "cli", arg(long))]
    pub azimuth_step: Option<f64>,
    /// Mobile: turn of the profile plane about the vertical from the cross-section (degrees).
    #[cfg_attr(feature = "cli", arg(long, allow_hyphen_values = true))]
    pub tilt: Option<f64>,
    /// Mobile: distance between profiles (m).
    #[cfg_attr(feature = "cli", arg(long))]
    pub profile_spacing: Option<f64>,
    /// Mobile: angle between pulses of a profile (degrees); terrestrial: the grid step.
    #[cfg_attr(feature = "cli", arg(long))]
    pub point_step: Option<f64>,
    /// Mobile: van speed; airborne: aircraft speed (m/s).
    #[cfg_attr(feature = "cli", arg(long))]
    pub speed: Option<f64>,
    /// Mobile: length driven (m).
    #[cfg_attr(feature = "cli", arg(long))]
    pub drive: Option<f64>,
    /// Mobile: curvature of the path (1/m; 0: straight).
    #[cfg_attr(feature = "cli", arg(long, allow_hyphen_values = true))]
    pub curvature: Option<f64>,
    /// Airborne: flying height above the street (m).
    #[cfg_attr(feature = "cli", arg(long))]
    pub altitude: Option<f64>,
    /// Airborne: half field of view (degrees).
    #[cfg_attr(feature = "cli", arg(long))]
    pub fov: Option<f64>,
    /// Airborne: number of strips.
    #[cfg_attr(feature = "cli", arg(long))]
    pub strips: Option<usize>,
    /// Airborne: side overlap of neighbouring strips (0–0.9).
    #[cfg_attr(feature = "cli", arg(long))]
    pub overlap: Option<f64>,
    /// Airborne: pulses per m² per strip (at nadir).
    #[cfg_attr(feature = "cli", arg(long))]
    pub pulse_density: Option<f64>,
    /// Airborne: zigzag or parallel scan lines.
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    pub pattern: Option<Pattern>,
    /// Terrestrial: number of stations along the sidewalk, 20 m apart.
    #[cfg_attr(feature = "cli", arg(long))]
    pub stations: Option<usize>,
    /// Terrestrial: a station at (x, y) in the street frame (repeat for several; replaces
    /// --stations).
    #[cfg_attr(feature = "cli", arg(long = "station", value_parser = parse_xy))]
    pub station: Vec<DVec2>,
}

/// Parses `X,Y`.
///
/// # Errors
/// Anything but two finite numbers.
pub fn parse_xy(s: &str) -> Result<DVec2, String> {
    let v = parse_numbers(s, 2)?;
    Ok(DVec2::new(v[0], v[1]))
}

/// Parses `X,Y,Z`.
///
/// # Errors
/// Anything but three finite numbers.
pub fn parse_xyz(s: &str) -> Result<DVec3, String> {
    let v = parse_numbers(s, 3)?;
    Ok(DVec3::new(v[0], v[1], v[2]))
}

fn parse_numbers(s: &str, n: usize) -> Result<Vec<f64>, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e}"))?;
    if v.len() != n || v.iter().any(|x| !x.is_finite()) {
        return Err(format!(
            "`{s}`: expected {n} finite numbers separated by commas"
        ));
    }
    Ok(v)
}

/// The geometry of a resolved sensor.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Geometry {
    /// One sweep.
    Spinning {
        /// Beam elevations (degrees), ascending: ring 0 is the lowest.
        elevations: Vec<f64>,
        /// Azimuth step (degrees).
        azimuth_step: f64,
        /// Height above the road.
        height: f64,
        /// (x, y) in the street frame.
        position: DVec2,
        /// Beams of the upper block (scanner channel 0); the rest are channel 1.
        upper_block: usize,
    },
    /// A profile scanner on a moving van.
    Mobile {
        /// Profile plane turn about the vertical (degrees).
        tilt: f64,
        /// Distance between profiles (m).
        profile_spacing: f64,
        /// Angle between pulses (degrees).
        point_step: f64,
        /// Speed (m/s).
        speed: f64,
        /// Height above the road.
        height: f64,
        /// Length driven.
        drive: f64,
        /// Path curvature (1/m).
        curvature: f64,
    },
    /// An airborne line scanner.
    Airborne {
        /// Flying height (m).
        altitude: f64,
        /// Half field of view (degrees).
        fov: f64,
        /// Strips.
        strips: usize,
        /// Side overlap.
        overlap: f64,
        /// Pulses per m² per strip.
        pulse_density: f64,
        /// Scan pattern.
        pattern: Pattern,
        /// Aircraft speed (m/s).
        speed: f64,
    },
    /// Terrestrial stations.
    Terrestrial {
        /// Station positions (x, y) in the street frame.
        stations: Vec<DVec2>,
        /// Grid step (degrees).
        step: f64,
        /// Height above the ground.
        height: f64,
        /// Azimuth window (degrees, counter-clockwise from +x).
        azimuth: (f64, f64),
        /// Elevation window (degrees).
        elevation: (f64, f64),
    },
}

/// A resolved, validated sensor.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Sensor {
    /// Its kind.
    pub kind: SensorKind,
    /// Its preset (spinning only).
    pub preset: Option<Preset>,
    /// What it measures with.
    pub physics: Physics,
    /// Where and how it scans.
    pub geometry: Geometry,
}

/// One pulse, before it meets the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pulse {
    /// Where it leaves the sensor (street frame).
    pub origin: DVec3,
    /// Nominal unit direction (what the encoders report).
    pub dir: DVec3,
    /// GPS time (s).
    pub time: f64,
    /// Beam index of a multi-beam sensor (0 = lowest), 0 otherwise.
    pub ring: u16,
    /// LAS scanner channel (0–3).
    pub channel: u8,
    /// Scan angle (degrees, −180 to 180): the azimuth of a sweep or station, the angle in the
    /// profile plane, the angle from nadir across the flight line.
    pub scan_angle: f64,
    /// LAS point source id: the strip or station (1-based), 1 for one sweep or drive.
    pub source: u16,
    /// LAS scan direction (bit 6) and edge of flight line (bit 7) flags.
    pub flags: u8,
}

/// The elevations of the HDL-64E as KITTI mounted it: 32 upper beams from +2° down at 1/3°
/// steps, 32 lower beams from −8.83° down to −24.8° at 0.515° (the datasheet's "+2° to −24.8°").
fn hdl64_elevations() -> Vec<f64> {
    let mut e: Vec<f64> = (0..32).map(|i| 2.0 - i as f64 * (10.33 / 31.0)).collect();
    e.extend((0..32).map(|i| -8.83 - i as f64 * ((24.8 - 8.83) / 31.0)));
    e.sort_by(f64::total_cmp);
    e
}

fn even(n: usize, hi: f64, lo: f64) -> Vec<f64> {
    (0..n)
        .map(|i| lo + (hi - lo) * i as f64 / (n.max(2) - 1) as f64)
        .collect()
}

impl Sensor {
    /// The preset of `kind` (for a spinning sensor, of `preset`, kitti64 by default): the table
    /// of the module overview.
    pub fn preset(kind: SensorKind, preset: Option<Preset>, layout: &Layout) -> Sensor {
        let physics = |sigma: f64, jitter: f64, divergence: f64, max_range: f64| Physics {
            sigma,
            jitter_deg: jitter,
            divergence_mrad: divergence,
            footprint_rays: 7,
            dropout: 0.01,
            max_range,
            mix_distance: 0.5,
            detect: 0.1,
        };
        let lane = DVec2::new(0.0, layout.lane_y());
        match kind {
            SensorKind::Spinning => {
                let preset = preset.unwrap_or(Preset::Kitti64);
                let (elevations, azimuth_step, height, upper, p) = match preset {
                    Preset::Kitti64 => (
                        hdl64_elevations(),
                        0.17,
                        1.73,
                        32,
                        physics(0.02, 0.01, 2.0, 120.0),
                    ),
                    Preset::Nuscenes32 => (
                        even(32, 10.67, -30.67),
                        0.16,
                        1.84,
                        32,
                        physics(0.02, 0.01, 2.8, 100.0),
                    ),
                    Preset::Vlp16 => (
                        even(16, 15.0, -15.0),
                        0.2,
                        1.5,
                        16,
                        physics(0.03, 0.01, 3.0, 100.0),
                    ),
                };
                Sensor {
                    kind,
                    preset: Some(preset),
                    physics: p,
                    geometry: Geometry::Spinning {
                        elevations,
                        azimuth_step,
                        height,
                        position: lane,
                        upper_block: upper,
                    },
                }
            }
            SensorKind::Mobile => Sensor {
                kind,
                preset: None,
                physics: physics(0.02, 0.005, 0.5, 80.0),
                geometry: Geometry::Mobile {
                    tilt: 45.0,
                    profile_spacing: 0.2,
                    point_step: 0.1,
                    speed: 10.0,
                    height: 2.6,
                    drive: 20.0,
                    curvature: 0.0,
                },
            },
            SensorKind::Airborne => Sensor {
                kind,
                preset: None,
                physics: physics(0.05, 0.002, 0.3, 2000.0),
                geometry: Geometry::Airborne {
                    altitude: 500.0,
                    fov: 25.0,
                    strips: 2,
                    overlap: 0.5,
                    pulse_density: 12.0,
                    pattern: Pattern::Zigzag,
                    speed: 60.0,
                },
            },
            SensorKind::Terrestrial => Sensor {
                kind,
                preset: None,
                physics: physics(0.004, 0.002, 0.3, 60.0),
                geometry: Geometry::Terrestrial {
                    stations: vec![DVec2::new(0.0, layout.sidewalk_y(-1.0))],
                    step: 0.1,
                    height: 1.6,
                    azimuth: (55.0, 125.0),
                    elevation: (-12.0, 25.0),
                },
            },
        }
    }

    /// `flags` over the preset of `kind`, validated.
    ///
    /// # Errors
    /// [`LidarError::Param`] naming the flag: a value out of range, or a flag of another sensor.
    pub fn resolve(
        kind: SensorKind,
        flags: &SensorFlags,
        layout: &Layout,
    ) -> Result<Sensor, LidarError> {
        let mut s = Sensor::preset(kind, flags.preset, layout);
        let bad = |name: &'static str, detail: String| Err(LidarError::Param { name, detail });
        let foreign = |name: &'static str, set: bool, owner: &str| -> Result<(), LidarError> {
            if set {
                return Err(LidarError::Param {
                    name,
                    detail: format!("applies to the {owner} sensor, not to {}", kind.name()),
                });
            }
            Ok(())
        };
        let p = &mut s.physics;
        set(&mut p.sigma, flags.sigma);
        set(&mut p.jitter_deg, flags.jitter);
        set(&mut p.divergence_mrad, flags.divergence);
        set(&mut p.footprint_rays, flags.footprint_rays);
        set(&mut p.dropout, flags.dropout);
        set(&mut p.max_range, flags.max_range);
        set(&mut p.mix_distance, flags.mix_distance);
        set(&mut p.detect, flags.detect);
        p.validate()?;
        let density = flags.density.unwrap_or(1.0);
        if !(density > 0.0 && density <= 100.0) {
            return bad("density", format!("must be in (0, 100], got {density}"));
        }
        let positive = |name: &'static str, v: f64| -> Result<(), LidarError> {
            if v > 0.0 && v.is_finite() {
                Ok(())
            } else {
                Err(LidarError::Param {
                    name,
                    detail: format!("must be a positive number, got {v}"),
                })
            }
        };
        let spinning = kind == SensorKind::Spinning;
        let mobile = kind == SensorKind::Mobile;
        let airborne = kind == SensorKind::Airborne;
        let terrestrial = kind == SensorKind::Terrestrial;
        foreign("preset", flags.preset.is_some() && !spinning, "spinning")?;
        foreign(
            "position",
            flags.position.is_some() && !spinning,
            "spinning",
        )?;
        foreign("beams", flags.beams.is_some() && !spinning, "spinning")?;
        foreign("fov-up", flags.fov_up.is_some() && !spinning, "spinning")?;
        foreign(
            "fov-down",
            flags.fov_down.is_some() && !spinning,
            "spinning",
        )?;
        foreign(
            "azimuth-step",
            flags.azimuth_step.is_some() && !spinning,
            "spinning",
        )?;
        foreign("tilt", flags.tilt.is_some() && !mobile, "mobile")?;
        foreign(
            "profile-spacing",
            flags.profile_spacing.is_some() && !mobile,
            "mobile",
        )?;
        foreign(
            "point-step",
            flags.point_step.is_some() && !(mobile || terrestrial),
            "mobile or terrestrial",
        )?;
        foreign(
            "speed",
            flags.speed.is_some() && !(mobile || airborne),
            "mobile or airborne",
        )?;
        foreign("drive", flags.drive.is_some() && !mobile, "mobile")?;
        foreign("curvature", flags.curvature.is_some() && !mobile, "mobile")?;
        foreign(
            "altitude",
            flags.altitude.is_some() && !airborne,
            "airborne",
        )?;
        foreign("fov", flags.fov.is_some() && !airborne, "airborne")?;
        foreign("strips", flags.strips.is_some() && !airborne, "airborne")?;
        foreign("overlap", flags.overlap.is_some() && !airborne, "airborne")?;
        foreign(
            "pulse-density",
            flags.pulse_density.is_some() && !airborne,
            "airborne",
        )?;
        foreign("pattern", flags.pattern.is_some() && !airborne, "airborne")?;
        foreign(
            "stations",
            flags.stations.is_some() && !terrestrial,
            "terrestrial",
        )?;
        foreign(
            "station",
            !flags.station.is_empty() && !terrestrial,
            "terrestrial",
        )?;
        foreign(
            "height",
            flags.height.is_some() && airborne,
            "spinning, mobile or terrestrial",
        )?;
        let half = layout.length / 2.0;
        let inside = |name: &'static str, q: DVec2| -> Result<(), LidarError> {
            if q.x.abs() <= half && q.y.abs() <= layout.half_depth {
                Ok(())
            } else {
                Err(LidarError::Param {
                    name,
                    detail: format!(
                        "({}, {}) is outside the scene (|x| ≤ {half}, |y| ≤ {})",
                        q.x, q.y, layout.half_depth
                    ),
                })
            }
        };
        match &mut s.geometry {
            Geometry::Spinning {
                elevations,
                azimuth_step,
                height,
                position,
                upper_block,
            } => {
                if flags.beams.is_some() || flags.fov_up.is_some() || flags.fov_down.is_some() {
                    let n = flags.beams.unwrap_or(elevations.len());
                    let hi = flags.fov_up.unwrap_or(elevations[elevations.len() - 1]);
                    let lo = flags.fov_down.unwrap_or(elevations[0]);
                    if !(1..=256).contains(&n) {
                        return bad("beams", format!("must be 1–256, got {n}"));
                    }
                    if !(-90.0..=90.0).contains(&lo) || !(-90.0..=90.0).contains(&hi) || lo > hi {
                        return bad(
                            "fov-down",
                            format!("the beams must span −90° ≤ {lo}° ≤ {hi}° ≤ 90°"),
                        );
                    }
                    *elevations = even(n, hi, lo);
                    *upper_block = n;
                }
                set(azimuth_step, flags.azimuth_step);
                positive("azimuth-step", *azimuth_step)?;
                *azimuth_step /= density;
                if 360.0 / *azimuth_step > 1e6 {
                    return bad(
                        "azimuth-step",
                        format!("{azimuth_step}° makes more than a million azimuths"),
                    );
                }
                set(height, flags.height);
                positive("height", *height)?;
                set(position, flags.position);
                inside("position", *position)?;
            }
            Geometry::Mobile {
                tilt,
                profile_spacing,
                point_step,
                speed,
                height,
                drive,
                curvature,
            } => {
                set(tilt, flags.tilt);
                if !(-80.0..=80.0).contains(tilt) {
                    return bad("tilt", format!("must be within ±80°, got {tilt}"));
                }
                set(profile_spacing, flags.profile_spacing);
                set(point_step, flags.point_step);
                set(speed, flags.speed);
                set(height, flags.height);
                set(drive, flags.drive);
                set(curvature, flags.curvature);
                positive("profile-spacing", *profile_spacing)?;
                positive("point-step", *point_step)?;
                positive("speed", *speed)?;
                positive("height", *height)?;
                positive("drive", *drive)?;
                *profile_spacing /= density.sqrt();
                *point_step /= density.sqrt();
                if *drive > layout.length {
                    return bad(
                        "drive",
                        format!("{drive} m is longer than the street ({} m)", layout.length),
                    );
                }
                if curvature.is_nan() || curvature.abs() > 0.05 {
                    return bad(
                        "curvature",
                        format!("must be within ±0.05 /m (a radius of 20 m), got {curvature}"),
                    );
                }
                if (*drive / *profile_spacing) * (360.0 / *point_step) > 2e7 {
                    return bad("point-step", "more than 20 million pulses".into());
                }
            }
            Geometry::Airborne {
                altitude,
                fov,
                strips,
                overlap,
                pulse_density,
                pattern,
                speed,
            } => {
                set(altitude, flags.altitude);
                set(fov, flags.fov);
                set(strips, flags.strips);
                set(overlap, flags.overlap);
                set(pulse_density, flags.pulse_density);
                set(pattern, flags.pattern);
                set(speed, flags.speed);
                positive("altitude", *altitude)?;
                positive("speed", *speed)?;
                positive("pulse-density", *pulse_density)?;
                if !(*fov > 0.0 && *fov <= 45.0) {
                    return bad("fov", format!("must be in (0, 45]°, got {fov}"));
                }
                if !(1..=20).contains(strips) {
                    return bad("strips", format!("must be 1–20, got {strips}"));
                }
                if !(0.0..=0.9).contains(overlap) {
                    return bad("overlap", format!("must be 0–0.9, got {overlap}"));
                }
                *pulse_density *= density;
                let area = layout.length * 2.0 * layout.half_depth;
                if *pulse_density * area * *strips as f64 > 2e7 {
                    return bad("pulse-density", "more than 20 million pulses".into());
                }
            }
            Geometry::Terrestrial {
                stations,
                step,
                height,
                ..
            } => {
                set(step, flags.point_step);
                set(height, flags.height);
                positive("point-step", *step)?;
                positive("height", *height)?;
                *step /= density.sqrt();
                if !flags.station.is_empty() {
                    *stations = flags.station.clone();
                } else if let Some(n) = flags.stations {
                    if !(1..=20).contains(&n) {
                        return bad("stations", format!("must be 1–20, got {n}"));
                    }
                    let y = layout.sidewalk_y(-1.0);
                    *stations = (0..n)
                        .map(|i| DVec2::new(20.0 * (i as f64 - (n - 1) as f64 / 2.0), y))
                        .collect();
                }
                for &q in stations.iter() {
                    inside("station", q)?;
                }
            }
        }
        Ok(s)
    }

    /// Every pulse in firing order.
    pub fn pulses(&self, layout: &Layout) -> Vec<Pulse> {
        match &self.geometry {
            Geometry::Spinning {
                elevations,
                azimuth_step,
                height,
                position,
                upper_block,
            } => spinning(
                layout,
                elevations,
                *azimuth_step,
                *height,
                *position,
                *upper_block,
            ),
            Geometry::Mobile { .. } => mobile(&self.geometry, layout),
            Geometry::Airborne { .. } => airborne(&self.geometry, layout),
            Geometry::Terrestrial { .. } => terrestrial(&self.geometry, layout),
        }
    }

    /// The sensor's positions over time: a sweep's or station's origin at its first and last
    /// pulse, the van or aircraft sampled at every profile or every 0.01 s of a strip.
    pub fn trajectory(&self, layout: &Layout, pulses: &[Pulse]) -> Trajectory {
        let mut samples: Vec<(f64, DVec3)> = Vec::new();
        match &self.geometry {
            Geometry::Mobile { .. } => {
                samples = self.path(layout).samples;
            }
            Geometry::Airborne { .. } => {
                // Each strip is a straight line at constant speed: samples at its ends and every
                // 0.01 s between (exact under linear interpolation).
                let mut start = 0;
                while start < pulses.len() {
                    let source = pulses[start].source;
                    let end = pulses[start..]
                        .iter()
                        .position(|p| p.source != source)
                        .map_or(pulses.len(), |k| start + k);
                    let (a, b) = (&pulses[start], &pulses[end - 1]);
                    let steps = (((b.time - a.time) / 0.01).ceil() as usize).max(1);
                    for k in 0..=steps {
                        let t = k as f64 / steps as f64;
                        samples.push((a.time + (b.time - a.time) * t, a.origin.lerp(b.origin, t)));
                    }
                    start = end;
                }
            }
            Geometry::Spinning { .. } | Geometry::Terrestrial { .. } => {
                let mut start = 0;
                while start < pulses.len() {
                    let source = pulses[start].source;
                    let end = pulses[start..]
                        .iter()
                        .position(|p| p.source != source)
                        .map_or(pulses.len(), |k| start + k);
                    samples.push((pulses[start].time, pulses[start].origin));
                    samples.push((pulses[end - 1].time, pulses[end - 1].origin));
                    start = end;
                }
            }
        }
        Trajectory { samples }
    }

    /// The van's path (mobile only; empty otherwise): the scanner's position at every profile's
    /// first pulse and at the end of the drive.
    fn path(&self, layout: &Layout) -> Trajectory {
        let Geometry::Mobile {
            profile_spacing,
            speed,
            height,
            drive,
            curvature,
            ..
        } = self.geometry
        else {
            return Trajectory::default();
        };
        let profiles = (drive / profile_spacing).floor() as usize;
        let samples = (0..=profiles)
            .map(|k| {
                let s = k as f64 * profile_spacing;
                (
                    START_TIME + s / speed,
                    van(layout, s, drive, curvature, height).0,
                )
            })
            .collect();
        Trajectory { samples }
    }
}

/// Keeps `v` unless `flag` is set.
fn set<T: Clone>(v: &mut T, flag: Option<T>) {
    if let Some(f) = flag {
        *v = f;
    }
}

/// An angle in degrees wrapped to (−180, 180].
fn wrap_deg(a: f64) -> f64 {
    let w = a.rem_euclid(360.0);
    if w > 180.0 { w - 360.0 } else { w }
}

/// A unit direction at azimuth `az` (counter-clockwise from +x) and elevation `el`, in degrees.
fn direction(az_deg: f64, el_deg: f64) -> DVec3 {
    let (az, el) = (az_deg.to_radians(), el_deg.to_radians());
    DVec3::new(
        libm::cos(el) * libm::cos(az),
        libm::cos(el) * libm::sin(az),
        libm::sin(el),
    )
}

fn spinning(
    layout: &Layout,
    elevations: &[f64],
    step: f64,
    height: f64,
    position: DVec2,
    upper_block: usize,
) -> Vec<Pulse> {
    let origin = DVec3::new(
        position.x,
        position.y,
        layout.ground_z(position.x, position.y) + height,
    );
    let azimuths = (360.0 / step).round() as usize;
    let beams = elevations.len();
    // One sweep in 0.1 s (10 Hz), every pulse its own time.
    let dt = 0.1 / (azimuths * beams) as f64;
    let mut out = Vec::with_capacity(azimuths * beams);
    for a in 0..azimuths {
        let az = 360.0 * a as f64 / azimuths as f64;
        for (b, &el) in elevations.iter().enumerate() {
            // The upper block is the higher beams (channel 0), as on the HDL-64E.
            let channel = u8::from(beams - 1 - b >= upper_block);
            out.push(Pulse {
                origin,
                dir: direction(az, el),
                time: START_TIME + (a * beams + b) as f64 * dt,
                ring: b as u16,
                channel,
                scan_angle: wrap_deg(az),
                source: 1,
                flags: 0,
            });
        }
    }
    out
}

/// The van after `s` metres: scanner position and unit heading.
fn van(layout: &Layout, s: f64, drive: f64, curvature: f64, height: f64) -> (DVec3, DVec3) {
    let (x0, y0) = (-drive / 2.0, layout.lane_y());
    let (x, y, heading) = if curvature == 0.0 {
        (x0 + s, y0, 0.0)
    } else {
        let a = curvature * s;
        (
            x0 + libm::sin(a) / curvature,
            y0 + (1.0 - libm::cos(a)) / curvature,
            a,
        )
    };
    let y = y.clamp(-layout.road_half, layout.road_half);
    (
        DVec3::new(x, y, layout.ground_z(x, y) + height),
        DVec3::new(libm::cos(heading), libm::sin(heading), 0.0),
    )
}

fn mobile(g: &Geometry, layout: &Layout) -> Vec<Pulse> {
    let Geometry::Mobile {
        tilt,
        profile_spacing,
        point_step,
        speed,
        height,
        drive,
        curvature,
    } = *g
    else {
        return Vec::new();
    };
    let per = (360.0 / point_step).round() as usize;
    let profiles = (drive / profile_spacing).floor() as usize;
    let period = profile_spacing / speed;
    let (ts, tc) = (libm::sin(tilt.to_radians()), libm::cos(tilt.to_radians()));
    let mut out = Vec::with_capacity(profiles * per);
    for k in 0..profiles {
        for j in 0..per {
            // The scanner moves during the profile, along the path at constant speed.
            let dt = period * (k as f64 + j as f64 / per as f64);
            let (origin, heading) = van(layout, speed * dt, drive, curvature, height);
            let left = DVec3::Z.cross(heading);
            // The cross-section plane (up, left) turned about the vertical by the tilt.
            let across = left * tc + heading * ts;
            let theta = (360.0 * j as f64 / per as f64).to_radians();
            let dir = (DVec3::Z * libm::cos(theta) + across * libm::sin(theta)).normalize();
            out.push(Pulse {
                origin,
                dir,
                time: START_TIME + dt,
                ring: 0,
                channel: 0,
                scan_angle: wrap_deg(theta.to_degrees()),
                source: 1,
                flags: 0,
            });
        }
    }
    out
}

fn airborne(g: &Geometry, layout: &Layout) -> Vec<Pulse> {
    let Geometry::Airborne {
        altitude,
        fov,
        strips,
        overlap,
        pulse_density,
        pattern,
        speed,
    } = *g
    else {
        return Vec::new();
    };
    let swath = 2.0 * altitude * libm::tan(fov.to_radians());
    let spacing = 1.0 / pulse_density.sqrt();
    let line_period = spacing / speed;
    // Pulses per line: the nadir spacing across equals the spacing along.
    let per_line = ((swath / spacing).round() as usize).max(2);
    let half = layout.length / 2.0;
    let margin = 5.0;
    let lines = ((layout.length + 2.0 * margin) / spacing).ceil() as usize;
    let mut out = Vec::new();
    let mut t_strip = START_TIME;
    for k in 0..strips {
        let centre = (k as f64 - (strips - 1) as f64 / 2.0) * swath * (1.0 - overlap);
        // Strips alternate direction, as flown.
        let forward = k % 2 == 0;
        let sign = if forward { 1.0 } else { -1.0 };
        let x_start = -sign * (half + margin);
        for line in 0..lines {
            let t_line = t_strip + line as f64 * line_period;
            let reverse = pattern == Pattern::Zigzag && line % 2 == 1;
            for j in 0..per_line {
                let jj = if reverse { per_line - 1 - j } else { j };
                let angle = -fov + 2.0 * fov * jj as f64 / (per_line - 1) as f64;
                let t = t_line + line_period * j as f64 / per_line as f64;
                let origin = DVec3::new(x_start + sign * speed * (t - t_strip), centre, altitude);
                // Nadir turned by the scan angle about the flight direction; positive angles
                // look to the right of the aircraft.
                let a = angle.to_radians();
                let dir = DVec3::new(0.0, -sign * libm::sin(a), -libm::cos(a));
                // Only pulses aimed into the scene (where they meet z = 0).
                let ground = origin + dir * (origin.z / -dir.z);
                if ground.x.abs() > half || ground.y.abs() > layout.half_depth {
                    continue;
                }
                let edge = jj == 0 || jj == per_line - 1;
                let up = if reverse { 0 } else { 0x40 };
                out.push(Pulse {
                    origin,
                    dir,
                    time: t,
                    ring: 0,
                    channel: 0,
                    scan_angle: angle,
                    source: (k + 1) as u16,
                    flags: up | if edge { 0x80 } else { 0 },
                });
            }
        }
        // The next strip starts after a 60 s turn.
        t_strip += lines as f64 * line_period + 60.0;
    }
    out
}

fn terrestrial(g: &Geometry, layout: &Layout) -> Vec<Pulse> {
    let Geometry::Terrestrial {
        stations,
        step,
        height,
        azimuth,
        elevation,
    } = g
    else {
        return Vec::new();
    };
    let cols = ((azimuth.1 - azimuth.0) / step).round() as usize + 1;
    let rows = ((elevation.1 - elevation.0) / step).round() as usize + 1;
    let dt = 1e-6;
    let mut out = Vec::with_capacity(stations.len() * cols * rows);
    let mut t0 = START_TIME;
    for (k, q) in stations.iter().enumerate() {
        let origin = DVec3::new(q.x, q.y, layout.ground_z(q.x, q.y) + height);
        for c in 0..cols {
            let az = azimuth.0 + c as f64 * step;
            for r in 0..rows {
                let el = elevation.0 + r as f64 * step;
                out.push(Pulse {
                    origin,
                    dir: direction(az, el),
                    time: t0 + (c * rows + r) as f64 * dt,
                    ring: 0,
                    channel: 0,
                    scan_angle: wrap_deg(az),
                    source: (k + 1) as u16,
                    flags: 0,
                });
            }
        }
        // The next station starts 5 minutes later.
        t0 += (cols * rows) as f64 * dt + 300.0;
    }
    out
}
