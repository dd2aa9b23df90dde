//! Issue 47: LiDAR returns are measured along beams. With the beams known (a sensor origin, a
//! sweep in its sensor's frame, a trajectory), the default operator fits each neighbourhood along
//! them and moves each return only along its own; without them it still reads a scan line's noise.

use glam::DVec3;
use qem_denoise::denoise::cloud::run_all;
use qem_denoise::denoise::{Params, SensorOrigin};
use qem_denoise::io::Format;
use qem_denoise::pipeline::DenoiseSpec;

use crate::util::{Sweep, put, qemd, qemd_ok, s};

const SIGMA: f64 = 0.02;

fn sweep(sigma: f64) -> Sweep {
    Sweep::new(16, 1.0, sigma, 7)
}

fn with_origin(o: DVec3) -> Params {
    Params {
        sensor_origin: SensorOrigin::At(o.to_array()),
        ..Params::default()
    }
}

/// Mean distance of `pts` to the surfaces the sweep's returns hit.
fn mean_distance(sw: &Sweep, pts: &[DVec3]) -> f64 {
    pts.iter()
        .enumerate()
        .map(|(i, &p)| sw.distance(i, p))
        .sum::<f64>()
        / pts.len() as f64
}

#[test]
fn issue47_with_its_beams_a_sweep_moves_only_along_them_and_loses_its_range_noise() {
    let sw = sweep(SIGMA);
    let r = run_all(&sw.noisy, &with_origin(sw.origin)).unwrap();
    let mut moved = 0;
    for (&p, &q) in sw.noisy.iter().zip(&r.positions) {
        let m = q - p;
        if m == DVec3::ZERO {
            continue;
        }
        moved += 1;
        let d = (p - sw.origin).normalize();
        assert!(
            m.cross(d).length() <= 1e-9 * m.length(),
            "{p} moved {m}, off its beam {d}"
        );
    }
    assert!(moved > sw.noisy.len() / 2, "{moved} of {}", sw.noisy.len());
    let (before, after) = (
        mean_distance(&sw, &sw.noisy),
        mean_distance(&sw, &r.positions),
    );
    assert!(after < 0.6 * before, "mean distance {before} → {after}");
    // The noise estimate is the range noise along the beams, within 2×.
    let e = r.stats.noise_estimate.unwrap();
    assert!(e > 0.5 * SIGMA && e < 2.0 * SIGMA, "estimate {e}");
}

#[test]
fn issue47_without_beams_a_sweep_still_reads_its_noise_and_moves() {
    // Scan lines whose returns are noisy along their beams: the plane through each line's
    // nearest points holds that noise, which read the scan as noise-free (0.04 mm where the
    // sensor had 2 cm) and capped every step to nothing.
    let sw = sweep(SIGMA);
    let params = Params {
        sensor_origin: SensorOrigin::Off,
        ..Params::default()
    };
    let r = run_all(&sw.noisy, &params).unwrap();
    let e = r.stats.noise_estimate.unwrap();
    assert!(e > 0.3 * SIGMA, "estimate {e}");
    let (before, after) = (
        mean_distance(&sw, &sw.noisy),
        mean_distance(&sw, &r.positions),
    );
    assert!(after < 0.9 * before, "mean distance {before} → {after}");
}

#[test]
fn issue47_a_noise_free_sweep_stays_calm() {
    let sw = sweep(0.0);
    let r = run_all(&sw.clean, &with_origin(sw.origin)).unwrap();
    let most = sw
        .clean
        .iter()
        .zip(&r.positions)
        .map(|(p, q)| (*q - *p).length())
        .fold(0.0, f64::max);
    assert!(most <= 0.5 * SIGMA, "largest move {most}");
}

#[test]
fn issue47_kitti_and_nuscenes_sweeps_are_in_their_sensor_frame() {
    let spec = DenoiseSpec::default();
    for (format, want) in [
        (Format::Kitti, SensorOrigin::At([0.0; 3])),
        (Format::Nuscenes, SensorOrigin::At([0.0; 3])),
        (Format::Las, SensorOrigin::Off),
        (Format::Pcd, SensorOrigin::Off),
    ] {
        assert_eq!(
            spec.for_format(format).params.sensor_origin,
            want,
            "{format}"
        );
    }
    let mut given = DenoiseSpec::default();
    given.params.sensor_origin = SensorOrigin::At([1.0, 2.0, 3.0]);
    assert_eq!(given.for_format(Format::Kitti), given);
    given.params.sensor_origin = SensorOrigin::Off;
    assert_eq!(given.for_format(Format::Kitti), given);
}

/// The sweep as an ASCII PLY with a `gps_time` column (the return's index, in seconds).
fn sweep_ply(sw: &Sweep) -> String {
    let mut t = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\n\
         property double z\nproperty double gps_time\nend_header\n",
        sw.noisy.len()
    );
    for (i, p) in sw.noisy.iter().enumerate() {
        t.push_str(&format!("{:?} {:?} {:?} {i}\n", p.x, p.y, p.z));
    }
    t
}

#[test]
fn issue47_a_trajectory_gives_each_return_its_beam() {
    let dir = tempfile::tempdir().unwrap();
    let sw = sweep(SIGMA);
    let input = put(dir.path(), "sweep.ply", sweep_ply(&sw));
    // A sensor that stands still: the trajectory's beams are the sensor origin's.
    let o = sw.origin;
    let n = sw.noisy.len();
    let traj = put(
        dir.path(),
        "traj.txt",
        format!(
            "# gps_time x y z\n-1 {} {} {}\n{n} {} {} {}\n",
            o.x, o.y, o.z, o.x, o.y, o.z
        ),
    );
    let by_traj = dir.path().join("t.ply");
    let by_origin = dir.path().join("o.ply");
    let origin = format!("{},{},{}", o.x, o.y, o.z);
    qemd_ok(&[
        "denoise",
        s(&input),
        "-o",
        s(&by_traj),
        "--trajectory",
        s(&traj),
        "-q",
    ]);
    qemd_ok(&[
        "denoise",
        s(&input),
        "-o",
        s(&by_origin),
        "--sensor-origin",
        &origin,
        "-q",
    ]);
    let (a, b) = (
        std::fs::read(&by_traj).unwrap(),
        std::fs::read(&by_origin).unwrap(),
    );
    assert!(
        a == b,
        "the trajectory's output differs from the sensor origin's"
    );
    let none = dir.path().join("n.ply");
    qemd_ok(&["denoise", s(&input), "-o", s(&none), "-q"]);
    assert!(
        std::fs::read(&none).unwrap() != a,
        "the beams changed nothing"
    );

    // Refusals, each naming what is wrong, and no output written.
    let out = dir.path().join("refused.ply");
    let both = qemd(&[
        "denoise",
        s(&input),
        "-o",
        s(&out),
        "--trajectory",
        s(&traj),
        "--sensor-origin",
        &origin,
    ]);
    assert!(!both.status.success());
    let tiled = qemd(&[
        "denoise",
        s(&input),
        "-o",
        s(&out),
        "--trajectory",
        s(&traj),
        "--tile-points",
        "5000",
    ]);
    assert!(!tiled.status.success());
    assert!(String::from_utf8_lossy(&tiled.stderr).contains("trajectory"));
    let untimed_ply = sweep_ply(&sw).replace("gps_time", "intensity");
    let no_time = put(dir.path(), "untimed.ply", untimed_ply);
    let untimed = qemd(&[
        "denoise",
        s(&no_time),
        "-o",
        s(&out),
        "--trajectory",
        s(&traj),
    ]);
    assert!(!untimed.status.success());
    let err = String::from_utf8_lossy(&untimed.stderr);
    assert!(err.contains("untimed.ply") && err.contains("time"), "{err}");
    assert!(!out.exists());
}
