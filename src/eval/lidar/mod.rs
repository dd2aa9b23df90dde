//! A LiDAR simulator with exact truth (`qemd synth lidar`) and its scorer (`qemd score`).
//!
//! # Brief overview
//!
//! ```text
//!  StreetSpec + scene seed ──street()──▶ Scene (triangles, object, kind) ──▶ Bvh
//!  SensorKind + SensorFlags ──Sensor::resolve()──▶ Sensor ──pulses()──▶ [Pulse]
//!  [Pulse] + Physics + seed ──fire_all()──▶ [Return] (clean and noisy position, kind, object)
//!       └─▶ write_scan() noisy / clean   Truth::write()   Trajectory::write()
//!  denoised file + Truth (+ the input) ──score()──▶ per-class table
//! ```
//!
//! * [`kinds`]: the object kinds and their LAS classes.
//! * [`scene`]: triangles with objects, and the primitives (boxes, prisms, cylinders, tubes,
//!   leaves, meshes); [`street`]: the parametric street; [`bvh`]: ray casts and closest points.
//! * [`sensors`]: the four sensors, their presets and pulses; [`beam`]: what happens to one
//!   pulse (footprint, echoes, mixed pixels, noise).
//! * [`writers`]: the scan in LAS/LAZ, PLY, text, PCD, KITTI and nuScenes; [`truth`]: the truth
//!   file; [`score`](mod@score): the scorer.
//!
//! Everything is deterministic: the scene from the scene seed, pulse `i`'s randomness from
//! stream `i` of the seed, whatever the thread count.

pub mod beam;
pub mod bvh;
pub mod kinds;
pub mod scene;
pub mod score;
pub mod sensors;
pub mod street;
pub mod truth;
pub mod writers;

use std::path::Path;

use glam::DVec3;
use thiserror::Error;

pub use self::beam::{Physics, Return};
pub use self::kinds::Kind;
pub use self::score::{Score, ScoreRow, score};
pub use self::sensors::{Pulse, Sensor, SensorFlags, SensorKind};
pub use self::street::{Layout, Street, StreetSpec};
pub use self::truth::{Truth, TruthMeta, TruthReturn};

use crate::io::trajectory::Trajectory;
use crate::io::{Format, IoError};

/// Errors of the simulator and the scorer.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum LidarError {
    /// A parameter is out of range or does not apply.
    #[error("invalid --{name}: {detail}")]
    Param {
        /// The flag, as the CLI spells it.
        name: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// The scene cannot be built.
    #[error("cannot build the scene: {0}")]
    Scene(String),
    /// A scored file does not pair with the truth (one line naming the file).
    #[error("{0}")]
    Mismatch(String),
    /// Reading or writing a file failed.
    #[error(transparent)]
    Io(#[from] IoError),
}

/// The frame the files of one simulation are written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Frame {
    /// The street's frame: x along the street, z up, origin on the axis at mid-length.
    Street,
    /// The sensor's: the street's axes, origin at the sensor (a sweep, or one station).
    Sensor,
}

/// Everything a simulation needs.
#[derive(Debug, Clone)]
pub struct LidarSpec {
    /// The sensor.
    pub sensor: SensorKind,
    /// Its settings.
    pub flags: SensorFlags,
    /// The street.
    pub street: StreetSpec,
    /// Seed of the pulses' randomness.
    pub seed: u64,
    /// Seed of the scene.
    pub scene_seed: u64,
    /// The frame (`None`: the sensor frame for a sweep written as PCD, KITTI or nuScenes, the
    /// street frame otherwise).
    pub frame: Option<Frame>,
}

/// A finished simulation.
pub struct Simulation {
    /// The street.
    pub street: Street,
    /// The resolved sensor.
    pub sensor: Sensor,
    /// Every pulse fired.
    pub pulses: Vec<Pulse>,
    /// The returns, in pulse order.
    pub returns: Vec<Return>,
    /// The frame of the files.
    pub frame: Frame,
    /// The frame's origin in the street frame.
    pub frame_origin: DVec3,
}

/// The frame a simulation's files take by default, given the scan's output format.
pub fn default_frame(sensor: SensorKind, output: Format) -> Frame {
    match (sensor, output) {
        (SensorKind::Spinning, Format::Pcd | Format::Kitti | Format::Nuscenes) => Frame::Sensor,
        _ => Frame::Street,
    }
}

/// Builds the scene, fires every pulse.
///
/// # Errors
/// Bad parameters (before any work), a sensor frame for a moving sensor.
pub fn simulate(spec: &LidarSpec, output: Format) -> Result<Simulation, LidarError> {
    let street = street::street(&spec.street, spec.scene_seed)?;
    let sensor = Sensor::resolve(spec.sensor, &spec.flags, &street.layout)?;
    let pulses = sensor.pulses(&street.layout);
    let frame = spec
        .frame
        .unwrap_or_else(|| default_frame(spec.sensor, output));
    let frame_origin = match frame {
        Frame::Street => DVec3::ZERO,
        Frame::Sensor => {
            let first = pulses.first().map_or(DVec3::ZERO, |p| p.origin);
            if pulses.iter().any(|p| p.origin != first) {
                return Err(LidarError::Param {
                    name: "frame",
                    detail: format!(
                        "the {} sensor moves (or has several stations): it has no single sensor frame",
                        spec.sensor.name()
                    ),
                });
            }
            first
        }
    };
    let bvh = bvh::Bvh::new(&street.scene.positions, &street.scene.triangles)?;
    let returns = beam::fire_all(&sensor.physics, &pulses, spec.seed, &street.scene, &bvh);
    Ok(Simulation {
        street,
        sensor,
        pulses,
        returns,
        frame,
        frame_origin,
    })
}

impl Simulation {
    /// The writers' view of the frame.
    pub fn scan_frame(&self) -> writers::ScanFrame<'_> {
        writers::ScanFrame {
            pulses: &self.pulses,
            origin: self.frame_origin,
            sensor_frame: self.frame == Frame::Sensor,
            time_origin: sensors::START_TIME,
        }
    }

    /// Writes the noisy (or `clean`) scan.
    ///
    /// # Errors
    /// As [`writers::write_scan`].
    pub fn write_scan(&self, path: &Path, clean: bool) -> Result<(), LidarError> {
        writers::write_scan(path, &self.returns, clean, &self.scan_frame())
    }

    /// The sensor and preset as the truth names them.
    pub fn sensor_name(&self) -> String {
        match self.sensor.preset {
            Some(p) => format!("{} {}", self.sensor.kind.name(), p.name()),
            None => self.sensor.kind.name().to_string(),
        }
    }

    /// The truth of this scan, in its frame.
    pub fn truth(&self, seed: u64, scene_seed: u64) -> Truth {
        let o = self.frame_origin;
        let scene = &self.street.scene;
        Truth {
            meta: TruthMeta {
                sensor: self.sensor_name(),
                sigma: self.sensor.physics.sigma,
                seed,
                scene_seed,
                frame: match self.frame {
                    Frame::Street => "street".into(),
                    Frame::Sensor => "sensor".into(),
                },
                frame_origin: o,
                time_origin: sensors::START_TIME,
            },
            positions: scene.positions.iter().map(|&p| p - o).collect(),
            triangles: scene.triangles.clone(),
            face_kind: (0..scene.triangles.len())
                .map(|t| scene.kind_of_face(t))
                .collect(),
            face_object: scene.face_object.clone(),
            returns: self
                .returns
                .iter()
                .map(|r| {
                    let p = &self.pulses[r.pulse as usize];
                    TruthReturn {
                        position: r.clean - o,
                        origin: p.origin - o,
                        time: p.time,
                        kind: r.kind,
                        object: r.object,
                        flags: (u8::from(r.mixed) * truth::FLAG_MIXED)
                            | (u8::from(r.offcentre) * truth::FLAG_OFFCENTRE),
                        ring: p.ring,
                        intensity: r.intensity,
                    }
                })
                .collect(),
        }
    }

    /// The sensor's trajectory, in the files' frame.
    pub fn trajectory(&self) -> Trajectory {
        let mut t = self.sensor.trajectory(&self.street.layout, &self.pulses);
        for s in &mut t.samples {
            s.1 -= self.frame_origin;
        }
        t
    }

    /// Returns per kind, in [`Kind::ALL`] order (kinds without returns left out).
    pub fn returns_per_kind(&self) -> Vec<(Kind, usize)> {
        let mut n = [0usize; Kind::ALL.len()];
        for r in &self.returns {
            n[r.kind as usize] += 1;
        }
        Kind::ALL
            .into_iter()
            .zip(n)
            .filter(|&(_, c)| c > 0)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small, quick scene and sensor: a 30 m street seen by a thinned VLP-16.
    fn small(seed: u64, flags: SensorFlags) -> LidarSpec {
        LidarSpec {
            sensor: SensorKind::Spinning,
            flags: SensorFlags {
                preset: Some(sensors::Preset::Vlp16),
                density: Some(0.25),
                ..flags
            },
            street: StreetSpec {
                length: 30.0,
                ..StreetSpec::default()
            },
            seed,
            scene_seed: seed,
            frame: None,
        }
    }

    #[test]
    fn issue47_truth_positions_lie_on_the_scene_mesh() {
        let sim = simulate(&small(3, SensorFlags::default()), Format::Las).unwrap();
        let scene = &sim.street.scene;
        let bvh = bvh::Bvh::new(&scene.positions, &scene.triangles).unwrap();
        let mut on = 0;
        for r in &sim.returns {
            if r.mixed || r.offcentre {
                continue;
            }
            let (d, tri) = bvh.distance(r.clean);
            assert!(
                d < 1e-9,
                "return of pulse {} is {d} m off the mesh",
                r.pulse
            );
            assert_eq!(scene.kind_of_face(tri as usize), r.kind);
            on += 1;
        }
        assert!(on > 1000, "{on}");
        // Mixed pixels lie between surfaces, never on the far side of the nearest hit's range.
        assert!(sim.returns.iter().any(|r| r.offcentre));
    }

    #[test]
    fn issue47_noise_is_along_the_beam_without_jitter() {
        let flags = SensorFlags {
            jitter: Some(0.0),
            ..SensorFlags::default()
        };
        let sim = simulate(&small(5, flags), Format::Las).unwrap();
        let mut moved = 0;
        for r in &sim.returns {
            let p = &sim.pulses[r.pulse as usize];
            let e = r.noisy - r.clean;
            assert!(
                e.cross(p.dir).length() < 1e-9,
                "sideways {}",
                e.cross(p.dir).length()
            );
            moved += usize::from(e.length() > 1e-4);
        }
        assert!(moved > sim.returns.len() / 2);
    }

    #[test]
    fn issue47_same_seed_same_bytes_other_seed_other_scene() {
        let dir = tempfile::tempdir().unwrap();
        let write = |seed: u64, name: &str| {
            let path = dir.path().join(name);
            let sim = simulate(&small(seed, SensorFlags::default()), Format::Las).unwrap();
            sim.write_scan(&path, false).unwrap();
            sim.truth(seed, seed)
                .write(&dir.path().join(format!("{name}.ply")))
                .unwrap();
            (
                std::fs::read(&path).unwrap(),
                sim.street.scene.positions.len(),
            )
        };
        let (a, na) = write(7, "a.las");
        let (b, _) = write(7, "b.las");
        assert_eq!(a, b);
        assert_eq!(
            std::fs::read(dir.path().join("a.las.ply")).unwrap(),
            std::fs::read(dir.path().join("b.las.ply")).unwrap()
        );
        let (c, nc) = write(8, "c.las");
        assert_ne!(a, c);
        assert_ne!(na, nc);
        // One thread or many: the same returns.
        let spec = small(7, SensorFlags::default());
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| simulate(&spec, Format::Las).unwrap().returns);
        assert_eq!(one, simulate(&spec, Format::Las).unwrap().returns);
    }

    #[test]
    fn issue47_truth_round_trips_and_every_sensor_fires() {
        let dir = tempfile::tempdir().unwrap();
        for kind in [
            SensorKind::Spinning,
            SensorKind::Mobile,
            SensorKind::Airborne,
            SensorKind::Terrestrial,
        ] {
            let spec = LidarSpec {
                sensor: kind,
                flags: SensorFlags {
                    density: Some(0.02),
                    drive: (kind == SensorKind::Mobile).then_some(5.0),
                    ..SensorFlags::default()
                },
                street: StreetSpec {
                    length: 30.0,
                    ..StreetSpec::default()
                },
                seed: 1,
                scene_seed: 1,
                frame: None,
            };
            let sim = simulate(&spec, Format::Las).unwrap();
            assert!(sim.returns.len() > 100, "{kind:?}: {}", sim.returns.len());
            let times: Vec<f64> = sim.pulses.iter().map(|p| p.time).collect();
            assert!(times.windows(2).all(|w| w[0] < w[1]), "{kind:?}: times");
            let path = dir.path().join("t.ply");
            let t = sim.truth(1, 1);
            t.write(&path).unwrap();
            assert_eq!(Truth::read(&path).unwrap(), t);
            // The scene mesh reads as a mesh for the rest of qemd.
            let cloud = crate::io::Cloud::read(&path, None).unwrap();
            assert_eq!(cloud.faces().unwrap().len(), t.triangles.len());
            let traj = sim.trajectory();
            for r in sim.returns.iter().step_by(97) {
                let p = &sim.pulses[r.pulse as usize];
                let o = traj.position_at(p.time).unwrap();
                assert!(
                    (o - p.origin).length() < 1e-6,
                    "{kind:?}: {o} vs {}",
                    p.origin
                );
            }
        }
    }

    #[test]
    fn issue47_flags_of_another_sensor_are_refused() {
        let spec = LidarSpec {
            flags: SensorFlags {
                altitude: Some(300.0),
                ..SensorFlags::default()
            },
            ..small(0, SensorFlags::default())
        };
        let e = simulate(&spec, Format::Las).err().unwrap().to_string();
        assert!(e.contains("--altitude") && e.contains("airborne"), "{e}");
        let spec = LidarSpec {
            sensor: SensorKind::Mobile,
            frame: Some(Frame::Sensor),
            flags: SensorFlags::default(),
            ..small(0, SensorFlags::default())
        };
        assert!(simulate(&spec, Format::Las).is_err());
    }
}
