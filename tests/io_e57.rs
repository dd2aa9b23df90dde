//! E57 input and output (issue 12): Cartesian and spherical scans, poses, intensity and colour,
//! several scans per file; round trips through qemd's writer, files written by the `e57` crate
//! directly and by `pye57` (libE57Format), and a CLI denoise of an E57 scan.

use std::path::Path;
use std::process::Command;

use e57::{
    E57Reader, E57Writer, Quaternion, Record, RecordDataType, RecordName, RecordValue, Transform,
    Translation,
};
use glam::{DQuat, DVec3};
use qem_denoise::io::{self, Cloud, Format, IoError, Meta};
use qem_denoise::points::ScalarType;

const PI: f64 = std::f64::consts::PI;

/// A deterministic pseudo-random sequence in [0, 1).
fn rng(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn int(min: i64, max: i64) -> RecordDataType {
    RecordDataType::Integer { min, max }
}

/// The poses of the two scans of [`two_scans`].
fn poses() -> [(DQuat, DVec3); 2] {
    [
        (
            DQuat::from_rotation_z(0.7) * DQuat::from_rotation_x(0.2),
            DVec3::new(512_000.25, 5_401_000.5, 120.0),
        ),
        (
            DQuat::from_rotation_z(-1.1),
            DVec3::new(512_010.0, 5_401_003.0, 121.5),
        ),
    ]
}

fn transform(q: DQuat, t: DVec3) -> Transform {
    Transform {
        rotation: Quaternion {
            w: q.w,
            x: q.x,
            y: q.y,
            z: q.z,
        },
        translation: Translation {
            x: t.x,
            y: t.y,
            z: t.z,
        },
    }
}

/// Expected world positions and (intensity, rgb) of the points of [`two_scans`].
struct Expected {
    world: Vec<DVec3>,
    intensity: Vec<f64>,
    rgb: Vec<Option<[f64; 3]>>,
}

/// An E57 file written with the `e57` crate: scan 0 Cartesian (scaled-integer coordinates,
/// float intensity, 8-bit colour), scan 1 spherical (double range/azimuth/elevation, integer
/// intensity), each with its own pose.
fn two_scans(path: &Path, n: usize) -> Expected {
    let mut exp = Expected {
        world: Vec::new(),
        intensity: Vec::new(),
        rgb: Vec::new(),
    };
    let [(q0, t0), (q1, t1)] = poses();
    let mut w = E57Writer::from_file(path, "{file-guid}").unwrap();
    let scale = 0.0001;
    let proto0 = vec![
        Record {
            name: RecordName::CartesianX,
            data_type: RecordDataType::ScaledInteger {
                min: -1_000_000,
                max: 1_000_000,
                scale,
                offset: 0.0,
            },
        },
        Record {
            name: RecordName::CartesianY,
            data_type: RecordDataType::ScaledInteger {
                min: -1_000_000,
                max: 1_000_000,
                scale,
                offset: 0.0,
            },
        },
        Record {
            name: RecordName::CartesianZ,
            data_type: RecordDataType::ScaledInteger {
                min: -1_000_000,
                max: 1_000_000,
                scale,
                offset: 0.0,
            },
        },
        Record {
            name: RecordName::Intensity,
            data_type: RecordDataType::Single {
                min: Some(0.0),
                max: Some(1.0),
            },
        },
        Record {
            name: RecordName::ColorRed,
            data_type: int(0, 255),
        },
        Record {
            name: RecordName::ColorGreen,
            data_type: int(0, 255),
        },
        Record {
            name: RecordName::ColorBlue,
            data_type: int(0, 255),
        },
    ];
    let mut r = rng(1);
    {
        let mut pc = w.add_pointcloud("{scan-0}", proto0).unwrap();
        pc.set_name(Some("south".into()));
        pc.set_transform(Some(transform(q0, t0)));
        for _ in 0..n {
            let l = [
                ((r() * 20.0 - 10.0) / scale).round() as i64,
                ((r() * 20.0 - 10.0) / scale).round() as i64,
                ((r() * 4.0) / scale).round() as i64,
            ];
            let i = r() as f32;
            let c = [
                (r() * 255.0) as i64,
                (r() * 255.0) as i64,
                (r() * 255.0) as i64,
            ];
            let local = DVec3::new(l[0] as f64, l[1] as f64, l[2] as f64) * scale;
            exp.world.push(q0 * local + t0);
            exp.intensity.push(f64::from(i));
            exp.rgb.push(Some(c.map(|v| v as f64)));
            pc.add_point(vec![
                RecordValue::ScaledInteger(l[0]),
                RecordValue::ScaledInteger(l[1]),
                RecordValue::ScaledInteger(l[2]),
                RecordValue::Single(i),
                RecordValue::Integer(c[0]),
                RecordValue::Integer(c[1]),
                RecordValue::Integer(c[2]),
            ])
            .unwrap();
        }
        pc.finalize().unwrap();
    }
    let double = RecordDataType::Double {
        min: None,
        max: None,
    };
    let proto1 = vec![
        Record {
            name: RecordName::SphericalRange,
            data_type: double.clone(),
        },
        Record {
            name: RecordName::SphericalAzimuth,
            data_type: double.clone(),
        },
        Record {
            name: RecordName::SphericalElevation,
            data_type: double,
        },
        Record {
            name: RecordName::Intensity,
            data_type: int(0, 2047),
        },
    ];
    {
        let mut pc = w.add_pointcloud("{scan-1}", proto1).unwrap();
        pc.set_name(Some("north".into()));
        pc.set_transform(Some(transform(q1, t1)));
        for _ in 0..n {
            let (range, az, el) = (1.0 + r() * 30.0, r() * 2.0 * PI - PI, r() * PI - PI / 2.0);
            let i = (r() * 2047.0) as i64;
            let local = DVec3::new(
                range * el.cos() * az.cos(),
                range * el.cos() * az.sin(),
                range * el.sin(),
            );
            exp.world.push(q1 * local + t1);
            exp.intensity.push(i as f64);
            exp.rgb.push(None);
            pc.add_point(vec![
                RecordValue::Double(range),
                RecordValue::Double(az),
                RecordValue::Double(el),
                RecordValue::Integer(i),
            ])
            .unwrap();
        }
        pc.finalize().unwrap();
    }
    w.finalize().unwrap();
    exp
}

fn field(c: &Cloud, name: &str, i: usize) -> f64 {
    let s = &c.info.schema;
    let rl = s.record_len;
    s.get_f64(
        &c.records[i * rl..(i + 1) * rl],
        s.field_index(name).unwrap(),
    )
}

fn assert_close(a: DVec3, b: DVec3, what: &str) {
    // Coordinates around 5e6 m: f64 carries about 1e-9 m there.
    assert_within(a, b, 1e-7, what);
}

fn assert_within(a: DVec3, b: DVec3, tol: f64, what: &str) {
    assert!(
        (a - b).abs().max_element() < tol,
        "{what}: {a} vs {b} ({})",
        (a - b).abs().max_element()
    );
}

fn check_against(c: &Cloud, exp: &Expected) {
    assert_eq!(c.len(), exp.world.len());
    let n = exp.world.len() / 2;
    for i in 0..c.len() {
        assert_close(c.positions[i], exp.world[i], &format!("point {i}"));
        assert_eq!(field(c, "scan", i), if i < n { 0.0 } else { 1.0 });
        let got = field(c, "intensity", i);
        assert!(
            (got - exp.intensity[i]).abs() <= 1e-6 * exp.intensity[i].abs().max(1.0),
            "intensity {i}: {got} vs {}",
            exp.intensity[i]
        );
        if let Some(rgb) = exp.rgb[i] {
            let got = [
                field(c, "red", i),
                field(c, "green", i),
                field(c, "blue", i),
            ];
            assert_eq!(got, rgb, "colour {i}");
        }
    }
}

#[test]
fn issue12_e57_two_scans_read_with_poses_spherical_and_attributes() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("two.e57");
    let exp = two_scans(&p, 500);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.format, Format::E57);
    let names: Vec<_> = c
        .info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect();
    assert_eq!(
        names,
        ["x", "y", "z", "intensity", "red", "green", "blue", "scan"]
    );
    let s = &c.info.schema;
    let ty = |n: &str| s.fields[s.field_index(n).unwrap()].ty;
    // Float intensity in scan 0 and integer intensity in scan 1: widened to f64.
    assert_eq!(
        (ty("intensity"), ty("red"), ty("scan")),
        (ScalarType::F64, ScalarType::U8, ScalarType::U32)
    );
    check_against(&c, &exp);
    // Sniffed by content.
    let head = std::fs::read(&p).unwrap();
    assert_eq!(io::sniff::sniff(&head[..64]), Some(io::Format::E57));
}

#[test]
fn issue12_e57_round_trip_keeps_scans_poses_and_attributes() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("two.e57");
    let exp = two_scans(&p, 300);
    let c = Cloud::read(&p, None).unwrap();
    let q = dir.path().join("copy.e57");
    c.write(&q, None).unwrap();
    let d = Cloud::read(&q, None).unwrap();
    assert_eq!(d.info.schema, c.info.schema);
    check_against(&d, &exp);
    assert_eq!(d.records, c.records, "every attribute byte kept");

    // The structure: two scans, names, poses, the spherical scan still spherical.
    let r = E57Reader::from_file(&q).unwrap();
    let pcs = r.pointclouds();
    assert_eq!(pcs.len(), 2);
    assert_eq!(pcs[0].name.as_deref(), Some("south"));
    assert_eq!(pcs[1].name.as_deref(), Some("north"));
    assert!(pcs[0].has_cartesian() && !pcs[0].has_spherical());
    assert!(pcs[1].has_spherical() && !pcs[1].has_cartesian());
    assert_eq!(pcs[0].original_guids, Some(vec!["{scan-0}".to_string()]));
    for (pc, (q, t)) in pcs.iter().zip(poses()) {
        let tr = pc.transform.as_ref().unwrap();
        assert!((tr.translation.x - t.x).abs() < 1e-9 && (tr.rotation.w - q.w).abs() < 1e-12);
        assert_eq!(pc.records, 300);
    }
    // Colour stays 8-bit integer, the spherical scan's intensity stays an 11-bit integer.
    let ty = |pc: &e57::PointCloud, n: RecordName| {
        pc.prototype
            .iter()
            .find(|r| r.name == n)
            .map(|r| r.data_type.clone())
    };
    assert!(matches!(
        ty(&pcs[0], RecordName::ColorRed),
        Some(RecordDataType::Integer { min: 0, max: 255 })
    ));
    assert!(matches!(
        ty(&pcs[1], RecordName::Intensity),
        Some(RecordDataType::Integer { min: 0, max: 2047 })
    ));

    // Moved points: the writer stores what it is given, within float precision.
    let mut moved = c.clone();
    for p in &mut moved.positions {
        *p += DVec3::new(0.001, -0.002, 0.003);
    }
    let m = dir.path().join("moved.e57");
    moved.write(&m, None).unwrap();
    let back = Cloud::read(&m, None).unwrap();
    for (a, b) in back.positions.iter().zip(&moved.positions) {
        assert_close(*a, *b, "moved");
    }
}

#[test]
fn issue12_e57_from_other_formats_keeps_every_field() {
    let dir = tempfile::tempdir().unwrap();
    // A PLY with colour, intensity and an extra property.
    let mut ply = String::from(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
         property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
         property float intensity\nproperty short label\nend_header\n",
    );
    ply += "0 0 0 255 0 10 0.5 -3\n1 0 0 0 255 20 0.25 7\n0 1 0.5 9 8 7 1 300\n";
    let p = dir.path().join("in.ply");
    std::fs::write(&p, ply).unwrap();
    let c = Cloud::read(&p, None).unwrap();
    let e = dir.path().join("out.e57");
    c.write(&e, None).unwrap();
    let d = Cloud::read(&e, None).unwrap();
    assert_eq!(d.positions, c.positions);
    let names: Vec<_> = d
        .info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect();
    assert_eq!(
        names,
        [
            "x",
            "y",
            "z",
            "red",
            "green",
            "blue",
            "intensity",
            "label",
            "cartesian_invalid"
        ]
    );
    for i in 0..3 {
        for (a, b) in [
            ("red", "red"),
            ("green", "green"),
            ("blue", "blue"),
            ("intensity", "intensity"),
            ("label", "label"),
        ] {
            assert_eq!(field(&c, a, i), field(&d, b, i), "{a} of point {i}");
        }
    }
    let r = E57Reader::from_file(&e).unwrap();
    assert!(r.extensions().iter().any(|x| x.namespace == "qemd"));
}

#[test]
fn issue12_e57_bad_input_is_a_one_line_error() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.e57");
    std::fs::write(&p, b"not an e57 file at all").unwrap();
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Header { .. }), "{e}");
    assert!(e.to_string().contains("bad.e57") && e.to_string().contains("ASTM-E57"));
    // A truncated real file.
    let good = dir.path().join("good.e57");
    two_scans(&good, 200);
    let bytes = std::fs::read(&good).unwrap();
    let cut = dir.path().join("cut.e57");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = Cloud::read(&cut, None).unwrap_err();
    assert!(e.to_string().contains("cut.e57"), "{e}");
    assert_eq!(e.to_string().lines().count(), 1);
}

#[test]
fn issue12_e57_noise_flag_is_an_extension_attribute() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("two.e57");
    two_scans(&p, 50);
    let c = Cloud::read(&p, None).unwrap();
    let q = dir.path().join("flagged.e57");
    let mut sink = io::create_with(
        &q,
        None,
        &c.info,
        c.len() as u64,
        &io::SinkOptions {
            noise_flag: true,
            ..io::SinkOptions::default()
        },
    )
    .unwrap();
    let mut batch = qem_denoise::points::PointBatch::with_capacity(c.info.schema.record_len, 100);
    batch.positions.extend_from_slice(&c.positions);
    batch.records.extend_from_slice(&c.records);
    batch.flags = (0..c.len()).map(|i| u8::from(i % 3 == 0)).collect();
    sink.write_batch(&batch).unwrap();
    sink.finish(&c.extras).unwrap();
    let d = Cloud::read(&q, None).unwrap();
    for i in 0..d.len() {
        assert_eq!(field(&d, "noise", i), f64::from(u8::from(i % 3 == 0)));
    }
    let Meta::E57(m) = &d.info.meta else { panic!() };
    assert_eq!(m.scans().len(), 2);

    // A sink dropped before finish leaves nothing behind; the same output twice is the same
    // bytes (GUIDs derived from the content).
    {
        let mut sink = io::create(&dir.path().join("dropped.e57"), None, &c.info, 10).unwrap();
        let mut b = qem_denoise::points::PointBatch::with_capacity(c.info.schema.record_len, 5);
        b.positions.extend_from_slice(&c.positions[..5]);
        b.records
            .extend_from_slice(&c.records[..5 * c.info.schema.record_len]);
        sink.write_batch(&b).unwrap();
    }
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert!(names.iter().all(|n| !n.contains("dropped")), "{names:?}");
    let again = dir.path().join("again.e57");
    let once = dir.path().join("once.e57");
    c.write(&once, None).unwrap();
    c.write(&again, None).unwrap();
    assert_eq!(
        std::fs::read(&once).unwrap(),
        std::fs::read(&again).unwrap()
    );
}

/// Runs `python3 -c script args…`, panicking with its stderr on failure.
fn python(script: &str, args: &[&Path]) -> String {
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "python failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

const PYE57_WRITE: &str = r#"
import sys, numpy as np, pye57
rng = np.random.default_rng(7)
n = 20000
u, v = rng.random(n) * 8.0, rng.random(n) * 6.0
z = 0.2 * np.sin(u) + rng.normal(0.0, 0.01, n)
data = {
    "cartesianX": u, "cartesianY": v, "cartesianZ": z,
    "intensity": rng.random(n),
    "colorRed": rng.integers(0, 256, n).astype(np.uint8),
    "colorGreen": rng.integers(0, 256, n).astype(np.uint8),
    "colorBlue": rng.integers(0, 256, n).astype(np.uint8),
}
e = pye57.E57(sys.argv[1], mode="w")
e.write_scan_raw(data, name="pye57 scan", rotation=np.array([0.9238795325112867, 0.0, 0.0, 0.3826834323650898]), translation=np.array([100.0, 200.0, 10.0]))
e.close()
with open(sys.argv[2], "w") as f:
    for i in range(n):
        f.write("%r %r %r %r %d %d %d\n" % (float(u[i]), float(v[i]), float(z[i]), float(data["intensity"][i]), int(data["colorRed"][i]), int(data["colorGreen"][i]), int(data["colorBlue"][i])))
"#;

const PYE57_WORLD: &str = r#"
import sys, pye57
d = pye57.E57(sys.argv[1]).read_scan(0, ignore_missing_fields=True, transform=True)
for i in range(50):
    print(repr(float(d["cartesianX"][i])), repr(float(d["cartesianY"][i])), repr(float(d["cartesianZ"][i])))
"#;

const PYE57_READ: &str = r#"
import sys, pye57
e = pye57.E57(sys.argv[1])
print(e.scan_count)
d = e.read_scan(0, intensity=True, colors=True, ignore_missing_fields=True, transform=True)
print(len(d["cartesianX"]), d["cartesianX"].min(), d["cartesianX"].max())
print(d["colorRed"].min(), d["colorRed"].max())
"#;

#[test]
#[ignore = "needs pip pye57"]
fn issue12_e57_written_by_pye57_reads_denoises_and_reads_back_in_pye57() {
    let dir = tempfile::tempdir().unwrap();
    let e57 = dir.path().join("pye57.e57");
    let truth = dir.path().join("truth.txt");
    python(PYE57_WRITE, &[&e57, &truth]);
    let c = Cloud::read(&e57, None).unwrap();
    let text = std::fs::read_to_string(&truth).unwrap();
    let (q, t) = (
        DQuat::from_xyzw(0.0, 0.0, 0.3826834323650898, 0.9238795325112867).normalize(),
        DVec3::new(100.0, 200.0, 10.0),
    );
    let mut n = 0;
    for (i, line) in text.lines().enumerate() {
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|x| x.parse().unwrap())
            .collect();
        // pye57 stores coordinates as scaled integers (a micrometre grid).
        assert_within(
            c.positions[i],
            q * DVec3::new(v[0], v[1], v[2]) + t,
            1e-6,
            "pye57 point",
        );
        assert!((field(&c, "intensity", i) - v[3]).abs() < 1e-6);
        assert_eq!(
            [
                field(&c, "red", i),
                field(&c, "green", i),
                field(&c, "blue", i)
            ],
            [v[4], v[5], v[6]]
        );
        n += 1;
    }
    assert_eq!((n, c.len()), (20_000, 20_000));
    // pye57's own pose application (libE57Format's convention) agrees with ours.
    let world = python(PYE57_WORLD, &[&e57]);
    for (i, line) in world.lines().enumerate() {
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|x| x.parse().unwrap())
            .collect();
        assert_within(
            c.positions[i],
            DVec3::new(v[0], v[1], v[2]),
            1e-6,
            "pye57 pose",
        );
    }

    // Denoise it end to end through the CLI; pye57 reads the result.
    let out = dir.path().join("clean.e57");
    let run = Command::new(env!("CARGO_BIN_EXE_qemd"))
        .args([
            "denoise",
            e57.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let d = Cloud::read(&out, None).unwrap();
    assert_eq!(d.len(), c.len());
    assert_eq!(d.records, c.records, "attributes kept");
    let moved = d
        .positions
        .iter()
        .zip(&c.positions)
        .filter(|(a, b)| a != b)
        .count();
    assert!(moved > d.len() / 2, "the denoiser moved {moved} points");
    let report = python(PYE57_READ, &[&out]);
    let lines: Vec<&str> = report.lines().collect();
    assert_eq!(lines[0], "1", "{report}");
    assert!(lines[1].starts_with("20000 "), "{report}");
    assert_eq!(lines[2], "0 255", "{report}");
}

/// Issue 51: a scan pose with a NaN or zero quaternion (or a NaN translation) was read as no
/// rotation; it is refused, naming the file and the scan.
#[test]
fn issue51_an_e57_pose_that_cannot_be_applied_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let bad = [
        (f64::NAN, DVec3::ZERO, "non-finite rotation"),
        (0.0, DVec3::ZERO, "zero rotation"),
        (
            1.0,
            DVec3::new(f64::NAN, 0.0, 0.0),
            "non-finite translation",
        ),
    ];
    for (k, (w, t, needle)) in bad.into_iter().enumerate() {
        let path = d.path().join(format!("bad{k}.e57"));
        let mut e = E57Writer::from_file(&path, "{guid}").unwrap();
        let double = RecordDataType::Double {
            min: None,
            max: None,
        };
        let proto = [
            RecordName::CartesianX,
            RecordName::CartesianY,
            RecordName::CartesianZ,
        ]
        .map(|name| Record {
            name,
            data_type: double.clone(),
        })
        .to_vec();
        let mut pc = e.add_pointcloud("{scan}", proto).unwrap();
        pc.set_name(Some("north".into()));
        let mut tr = transform(DQuat::IDENTITY, t);
        tr.rotation = Quaternion {
            w,
            x: 0.0,
            y: 0.0,
            z: 0.0,
        };
        pc.set_transform(Some(tr));
        for i in 0..10 {
            let v = f64::from(i);
            pc.add_point(vec![
                RecordValue::Double(v),
                RecordValue::Double(v * 0.5),
                RecordValue::Double(1.0),
            ])
            .unwrap();
        }
        pc.finalize().unwrap();
        e.finalize().unwrap();
        let err = Cloud::read(&path, None).unwrap_err().to_string();
        assert!(
            err.contains(path.to_str().unwrap())
                && err.contains("scan 0 (`north`)")
                && err.contains(needle),
            "{err}"
        );
    }
}

/// A LAS file (PDRF 1) of `n` points, each with a class and its flags, intensity, return
/// numbers, scan direction, edge of flight line, scan angle and a GPS time.
fn las_with_classes(path: &Path, n: usize) -> Vec<u8> {
    let mut b = las::Builder::default();
    b.point_format = las::point::Format::new(1).unwrap();
    let mut w = las::Writer::from_path(path, b.into_header().unwrap()).unwrap();
    let mut r = rng(51);
    let classes: Vec<u8> = (0..n).map(|i| [2, 3, 6, 7, 18][i % 5]).collect();
    for (i, &c) in classes.iter().enumerate() {
        w.write_point(las::Point {
            x: r() * 10.0,
            y: r() * 10.0,
            z: r(),
            intensity: (r() * 1000.0) as u16,
            return_number: 1 + (i % 3) as u8,
            number_of_returns: 3,
            scan_direction: if i % 2 == 0 {
                las::point::ScanDirection::LeftToRight
            } else {
                las::point::ScanDirection::RightToLeft
            },
            is_edge_of_flight_line: i % 7 == 0,
            classification: las::point::Classification::new(c).unwrap(),
            is_synthetic: i % 11 == 0,
            is_key_point: i % 13 == 0,
            is_withheld: i % 17 == 0,
            scan_angle: (i % 61) as f32 - 30.0,
            user_data: (i % 256) as u8,
            point_source_id: 7,
            gps_time: Some(r() * 100.0),
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
    classes
}

/// Issue 51: LAS → E57 → LAS gives each point its class back in the LAS classification field
/// (it went to extra bytes, as `qemd_classification`), and every LAS attribute round-trips.
#[test]
fn issue51_e57_to_las_maps_the_classification_back() {
    let d = tempfile::tempdir().unwrap();
    let las_in = d.path().join("in.las");
    let classes = las_with_classes(&las_in, 500);
    let c = Cloud::read(&las_in, None).unwrap();
    let e57 = d.path().join("mid.e57");
    c.write(&e57, None).unwrap();
    let m = Cloud::read(&e57, None).unwrap();
    assert!(m.info.schema.field_index("classification").is_some());
    assert!(m.info.schema.field_index("qemd_classification").is_none());
    let las_out = d.path().join("out.las");
    m.write(&las_out, None).unwrap();
    let mut r = las::Reader::from_path(&las_out).unwrap();
    // Extra bytes hold E57's own invalid-state attribute only: every LAS field is a LAS one.
    let extras: Vec<String> = r
        .header()
        .vlrs()
        .iter()
        .filter(|v| v.user_id == "LASF_Spec" && v.record_id == 4)
        .flat_map(|v| {
            v.data.chunks(192).map(|d| {
                String::from_utf8_lossy(&d[4..36])
                    .trim_end_matches('\0')
                    .to_string()
            })
        })
        .collect();
    assert_eq!(extras, ["cartesian_invalid"]);
    let got = r.read_all().unwrap();
    assert_eq!(got.classification().collect::<Vec<u8>>(), classes);
    let orig = las::Reader::from_path(&las_in).unwrap().read_all().unwrap();
    for (i, (a, b)) in orig.points().zip(got.points()).enumerate() {
        let (a, mut b) = (a.unwrap(), b.unwrap());
        // PDRF 6 stores the scan angle in 0.006° steps: the whole degree, within half a step.
        assert!((a.scan_angle - b.scan_angle).abs() <= 0.003, "point {i}");
        b.scan_angle = a.scan_angle;
        assert!(
            (a.x - b.x).abs() + (a.y - b.y).abs() + (a.z - b.z).abs() < 1e-6,
            "point {i}"
        );
        (b.x, b.y, b.z) = (a.x, a.y, a.z);
        assert_eq!(b.extra_bytes, [0], "point {i}: cartesian_invalid");
        b.extra_bytes.clear();
        assert_eq!(a, b, "point {i}: every LAS attribute round-trips");
    }
    assert_eq!(orig.len(), got.len());
}

/// Issue 51: pye57's `read_scan` reads an E57 qemd wrote from LAS without any option; its LAS
/// attributes are the declared `qemd` extension's, which `read_scan_raw` skips only with
/// `ignore_unsupported_fields=True`, as it skips E57's own `timeStamp` or `returnIndex`.
#[test]
#[ignore = "needs pip pye57"]
fn issue51_pye57_reads_a_qemd_e57_from_las_without_options() {
    let d = tempfile::tempdir().unwrap();
    let las_in = d.path().join("in.las");
    las_with_classes(&las_in, 500);
    let e57 = d.path().join("from_las.e57");
    crate::util::qemd_ok(&[
        "denoise",
        crate::util::s(&las_in),
        "-o",
        crate::util::s(&e57),
    ]);
    let out = python(
        r#"
import sys, pye57
e = pye57.E57(sys.argv[1])
d = e.read_scan(0)
print(len(d["cartesianX"]))
d = e.read_scan(0, intensity=True)
print(len(d["intensity"]))
raw = e.read_scan_raw(0, ignore_unsupported_fields=True)
print(sorted(raw))
print(sorted(e.get_header(0).point_fields))
"#,
        &[&e57],
    );
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines[..2], ["500", "500"], "{out}");
    assert!(lines[2].contains("'cartesianX'"), "{out}");
    assert!(lines[3].contains("'qemd:classification'"), "{out}");
}

/// A ground patch at UTM scale (x 515 370, northing 4 918 340) with 1 cm of noise, its
/// coordinates stored as E57 singles (`f32`, as pye57 writes them: 0.5 m apart in northing) or
/// doubles.
fn utm_patch(path: &Path, single: bool, n: usize) {
    let mut e = E57Writer::from_file(path, "{utm-guid}").unwrap();
    let ty = if single {
        RecordDataType::Single {
            min: None,
            max: None,
        }
    } else {
        RecordDataType::Double {
            min: None,
            max: None,
        }
    };
    let proto = [
        RecordName::CartesianX,
        RecordName::CartesianY,
        RecordName::CartesianZ,
    ]
    .map(|name| Record {
        name,
        data_type: ty.clone(),
    })
    .to_vec();
    let mut pc = e.add_pointcloud("{utm-scan}", proto).unwrap();
    let mut r = rng(51);
    let value = |v: f64| {
        if single {
            RecordValue::Single(v as f32)
        } else {
            RecordValue::Double(v)
        }
    };
    for _ in 0..n {
        let (x, y) = (3.0 * r(), 3.0 * r());
        let noise = 0.01 * (r() + r() + r() - 1.5) * 2.0;
        let z = 2330.0 + 0.1 * x + 0.05 * y + noise;
        pc.add_point(vec![value(515_370.0 + x), value(4_918_340.0 + y), value(z)])
            .unwrap();
    }
    pc.finalize().unwrap();
    e.finalize().unwrap();
}

#[test]
fn issue51_an_f32_utm_e57_that_moves_nothing_says_why() {
    let d = tempfile::tempdir().unwrap();
    let single = d.path().join("single.e57");
    utm_patch(&single, true, 8000);
    let out = d.path().join("single.out.e57");
    let o = crate::util::qemd_ok(&[
        "denoise",
        crate::util::s(&single),
        "-o",
        crate::util::s(&out),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("(0 moved"), "{err}");
    let why: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("nothing moved"))
        .collect();
    assert_eq!(why.len(), 1, "{err}");
    assert!(
        why[0].contains("below the input's coordinate resolution") && why[0].contains("y 5.000e-1"),
        "{err}"
    );
    // The same patch stored as doubles moves points, and the line is not there.
    let double = d.path().join("double.e57");
    utm_patch(&double, false, 8000);
    let out = d.path().join("double.out.e57");
    let o = crate::util::qemd_ok(&[
        "denoise",
        crate::util::s(&double),
        "-o",
        crate::util::s(&out),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !err.contains("(0 moved") && !err.contains("nothing moved"),
        "{err}"
    );
}
