//! `--write-normals` (issue 9, section 2): each point's normal, surface variation and structure
//! class written as fields, in every point format that can hold them; the same bytes tiled and in
//! memory; stored normal fields overwritten, not doubled; refused, before any output exists, by
//! the formats that cannot hold them.
//!
//! `cargo test --test tests normals::` selects exactly these tests.

use std::path::{Path, PathBuf};

use e57::{E57Writer, Quaternion, Record, RecordDataType, RecordName, RecordValue, Transform};
use glam::{DQuat, DVec3};
use qem_denoise::denoise::Method;
use qem_denoise::denoise::structure::Structure;
use qem_denoise::io::{Cloud, Format};
use qem_denoise::pipeline::{Job, NormalsAction, Report, RunOptions, run};
use qem_denoise::points::ScalarType;

use crate::util::{listing, put, qemd, s};

/// The names of the five values in PLY (and text), PCD, LAS and E57 output (E57 as read back:
/// qemd's own `qemd:` fields read under the names they were written from).
const PLY: [&str; 5] = ["nx", "ny", "nz", "curvature", "structure"];
const PCD: [&str; 5] = ["normal_x", "normal_y", "normal_z", "curvature", "structure"];
const LAS: [&str; 5] = ["NormalX", "NormalY", "NormalZ", "Curvature", "Structure"];
const E57: [&str; 5] = [
    "nor_normalX",
    "nor_normalY",
    "nor_normalZ",
    "curvature",
    "structure",
];

struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn g(&mut self) -> f64 {
        let (u, v) = (self.f().max(1e-300), self.f());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// The plane of [`plane_and_line`]: z = 0.3 x + 0.2 y + 1.
fn plane_normal() -> DVec3 {
    DVec3::new(-0.3, -0.2, 1.0).normalize()
}

/// A noisy tilted plane (60 × 60 grid, spacing 0.1, σ = 0.004) and, far from it, a noisy line
/// of 300 points along (1, 1, 0.5); returns the points and where the line starts.
fn plane_and_line() -> (Vec<DVec3>, usize) {
    let mut r = Rng(0x9e37_79b9_7f4a_7c15);
    let mut v = Vec::new();
    for i in 0..60 {
        for j in 0..60 {
            let (x, y) = (i as f64 * 0.1, j as f64 * 0.1);
            v.push(DVec3::new(x, y, 0.3 * x + 0.2 * y + 1.0 + 0.004 * r.g()));
        }
    }
    let line = v.len();
    let dir = DVec3::new(1.0, 1.0, 0.5).normalize();
    for i in 0..300 {
        let jitter = DVec3::new(r.g(), r.g(), r.g()) * 0.002;
        v.push(DVec3::new(50.0, -20.0, 3.0) + dir * (i as f64 * 0.05) + jitter);
    }
    (v, line)
}

/// A noisy wavy sheet of `n` points (for the format and seam tests).
fn sheet(n: usize, seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed | 1);
    (0..n)
        .map(|_| {
            let (x, y) = (r.f() * 8.0, r.f() * 8.0);
            DVec3::new(x, y, (x * 0.7).sin() * 0.5 + 0.01 * r.g())
        })
        .collect()
}

/// Writes `pts` as a binary PLY of float x, y, z at `dir/name`.
fn ply(dir: &Path, name: &str, pts: &[DVec3]) -> PathBuf {
    let p = dir.join(name);
    Cloud::generated(pts.to_vec(), None, ScalarType::F32)
        .write(&p, None)
        .unwrap();
    p
}

/// Runs `input` → `output` with `--write-normals` (and `tile_points` when given).
fn denoise(input: &Path, output: &Path, tile_points: Option<u64>) -> Report {
    let mut job = Job::new(input, output);
    job.spec.params.write_normals = true;
    let opts = RunOptions {
        tile_points,
        ..RunOptions::default()
    };
    run(&job, &opts).unwrap()
}

/// The five written values of every point of `c`, read from the fields `names`, as `f32` (the
/// written type: a text column's shortest decimal reads back as the same `f32`).
fn values(c: &Cloud, names: [&str; 5]) -> Vec<[f32; 5]> {
    let s = &c.info.schema;
    let idx = names.map(|n| {
        let hits = s.fields.iter().filter(|f| f.name == n).count();
        assert_eq!(hits, 1, "{n}: {hits} fields in {:?}", names_of(c));
        s.field_index(n).unwrap()
    });
    let rl = s.record_len;
    (0..c.len())
        .map(|i| idx.map(|k| s.get_f64(&c.records[i * rl..(i + 1) * rl], k) as f32))
        .collect()
}

fn names_of(c: &Cloud) -> Vec<String> {
    c.info
        .schema
        .fields
        .iter()
        .map(|f| f.name.clone())
        .collect()
}

fn normal_of(v: &[f32; 5]) -> DVec3 {
    DVec3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]))
}

// ---------------------------------------------------------------------------------------------
// What is written.

#[test]
fn issue9_write_normals_plane_points_along_its_normal_and_a_line_is_a_line() {
    let dir = tempfile::tempdir().unwrap();
    let (pts, line) = plane_and_line();
    let input = ply(dir.path(), "in.ply", &pts);
    let out = dir.path().join("out.ply");
    let report = denoise(&input, &out, None);
    assert_eq!(report.normals, NormalsAction::Written);
    let c = Cloud::read(&out, None).unwrap();
    assert_eq!(
        names_of(&c),
        ["x", "y", "z", "nx", "ny", "nz", "curvature", "structure"]
    );
    let v = values(&c, PLY);
    let want = plane_normal();
    let mut angles: Vec<f64> = v[..line]
        .iter()
        .map(|p| normal_of(p).angle_between(want).to_degrees())
        .collect();
    angles.sort_by(f64::total_cmp);
    // Oriented up: the angle to the upward normal, not to either sign of it.
    assert!(
        angles[angles.len() / 2] < 1.0,
        "median {}°",
        angles[angles.len() / 2]
    );
    assert!(
        angles[angles.len() * 99 / 100] < 5.0,
        "p99 {}°",
        angles[angles.len() * 99 / 100]
    );
    for p in &v {
        let n = normal_of(p);
        assert!((n.length() - 1.0).abs() < 1e-6 || n == DVec3::ZERO, "{n}");
        assert!(n.z >= 0.0, "{n}");
    }
    let surface = v[..line]
        .iter()
        .filter(|p| p[4] == f32::from(Structure::Surface as u8))
        .count();
    assert!(surface as f64 > 0.95 * line as f64, "{surface} of {line}");
    let mut curvature: Vec<f32> = v[..line].iter().map(|p| p[3]).collect();
    curvature.sort_by(f32::total_cmp);
    assert!(curvature[line / 2] < 0.01, "{}", curvature[line / 2]);
    let lines = v[line..]
        .iter()
        .filter(|p| p[4] == f32::from(Structure::Line as u8))
        .count();
    assert!(
        lines as f64 > 0.9 * (v.len() - line) as f64,
        "{lines} line points"
    );
}

/// Byte offsets of the LAS public header fields the tests read.
const HEADER_SIZE: usize = 94;
const POINT_DATA: usize = 96;
const VLR_COUNT: usize = 100;
const RECORD_LEN: usize = 105;

fn u16_at(b: &[u8], at: usize) -> usize {
    usize::from(u16::from_le_bytes([b[at], b[at + 1]]))
}

fn u32_at(b: &[u8], at: usize) -> usize {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap()) as usize
}

/// The VLRs of the LAS file `bytes`, parsed by hand: (user id, record id, payload).
fn vlrs(bytes: &[u8]) -> Vec<(String, u16, Vec<u8>)> {
    let mut at = u16_at(bytes, HEADER_SIZE);
    let mut out = Vec::new();
    for _ in 0..u32_at(bytes, VLR_COUNT) {
        let text = |a: usize, n: usize| {
            let raw = &bytes[a..a + n];
            let end = raw.iter().position(|&c| c == 0).unwrap_or(n);
            String::from_utf8_lossy(&raw[..end]).into_owned()
        };
        let user = text(at + 2, 16);
        let record = u16_at(bytes, at + 18) as u16;
        let len = u16_at(bytes, at + 20);
        out.push((user, record, bytes[at + 54..at + 54 + len].to_vec()));
        at += 54 + len;
    }
    assert_eq!(
        at,
        u32_at(bytes, POINT_DATA),
        "the VLRs end where the points start"
    );
    out
}

/// The (name, data type) of each descriptor of the Extra Bytes VLR of the LAS file `bytes`.
fn extra_bytes(bytes: &[u8]) -> Vec<(String, u8)> {
    let all = vlrs(bytes);
    let eb: Vec<_> = all
        .iter()
        .filter(|(u, r, _)| u == "LASF_Spec" && *r == 4)
        .collect();
    assert_eq!(eb.len(), 1, "one Extra Bytes VLR");
    let payload = &eb[0].2;
    assert_eq!(payload.len() % 192, 0);
    payload
        .chunks_exact(192)
        .map(|d| {
            let end = d[4..36].iter().position(|&c| c == 0).unwrap_or(32);
            (String::from_utf8_lossy(&d[4..4 + end]).into_owned(), d[2])
        })
        .collect()
}

#[test]
fn issue9_write_normals_every_format_holds_the_same_values() {
    let dir = tempfile::tempdir().unwrap();
    let pts = sheet(3000, 7);
    let input = ply(dir.path(), "in.ply", &pts);
    let reference = dir.path().join("out.ply");
    denoise(&input, &reference, None);
    let want = values(&Cloud::read(&reference, None).unwrap(), PLY);
    // The written values are f32 (the class an integer): every format holds the same numbers.
    for (ext, names) in [
        ("pcd", PCD),
        ("xyz", PLY),
        ("las", LAS),
        ("laz", LAS),
        ("e57", E57),
    ] {
        let out = dir.path().join(format!("out.{ext}"));
        denoise(&input, &out, None);
        let c = Cloud::read(&out, None).unwrap();
        assert_eq!(c.len(), pts.len(), "{ext}");
        assert_eq!(values(&c, names), want, "{ext}");
    }
    // PTS names no columns: the five come last.
    let out = dir.path().join("out.pts");
    denoise(&input, &out, None);
    let c = Cloud::read(&out, None).unwrap();
    assert_eq!(names_of(&c), ["x", "y", "z", "c3", "c4", "c5", "c6", "c7"]);
    assert_eq!(values(&c, ["c3", "c4", "c5", "c6", "c7"]), want);
    // COPC stores points node by node: the same values, in another order.
    let out = dir.path().join("out.copc.laz");
    denoise(&input, &out, None);
    let sorted = |mut v: Vec<[f32; 5]>| {
        v.sort_by_key(|a| a.map(f32::to_bits));
        v
    };
    let c = Cloud::read(&out, None).unwrap();
    assert_eq!(sorted(values(&c, LAS)), sorted(want.clone()));

    // The LAS Extra Bytes VLR, read by hand: five descriptors, float and unsigned char.
    for ext in ["las", "laz"] {
        let bytes = std::fs::read(dir.path().join(format!("out.{ext}"))).unwrap();
        let eb = extra_bytes(&bytes);
        let expected: Vec<(String, u8)> = LAS
            .iter()
            .zip([9, 9, 9, 9, 1])
            .map(|(n, t)| (n.to_string(), t))
            .collect();
        assert_eq!(eb, expected, "{ext}");
        // PDRF 6 (30 bytes) plus 4 × 4 + 1.
        assert_eq!(u16_at(&bytes, RECORD_LEN), 30 + 17, "{ext}");
    }
}

#[test]
fn issue9_write_normals_ascii_ply_and_a_foreign_xyz_header_name_the_columns() {
    let dir = tempfile::tempdir().unwrap();
    let text = (0..400)
        .map(|i| {
            let (x, y) = ((i % 20) as f64 * 0.1, (i / 20) as f64 * 0.1);
            format!("{x} {y} {}\n", 0.01 * ((i * 7919) % 13) as f64)
        })
        .collect::<String>();
    let header = "ply\nformat ascii 1.0\nelement vertex 400\nproperty float x\nproperty float y\n\
                  property float z\nend_header\n";
    let input = put(dir.path(), "in.ply", format!("{header}{text}"));
    let out = dir.path().join("out.ply");
    denoise(&input, &out, None);
    let head = std::fs::read_to_string(&out).unwrap();
    assert!(
        head.starts_with(
            "ply\nformat ascii 1.0\nelement vertex 400\nproperty float x\nproperty float y\n\
             property float z\nproperty float nx\nproperty float ny\nproperty float nz\n\
             property float curvature\nproperty uchar structure\nend_header\n"
        ),
        "{}",
        &head[..300]
    );
    let xyz = dir.path().join("out.xyz");
    denoise(&input, &xyz, None);
    let first = std::fs::read_to_string(&xyz).unwrap();
    assert!(
        first.starts_with("# x y z nx ny nz curvature structure\n"),
        "{}",
        &first[..80]
    );
    assert_eq!(
        values(&Cloud::read(&xyz, None).unwrap(), PLY),
        values(&Cloud::read(&out, None).unwrap(), PLY)
    );
}

// ---------------------------------------------------------------------------------------------
// Tiled = in memory.

#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn issue9_write_normals_tiled_writes_the_in_memory_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let pts = sheet(20_000, 3);
    let input = ply(dir.path(), "in.ply", &pts);
    for ext in ["ply", "las", "pcd"] {
        let whole = dir.path().join(format!("whole.{ext}"));
        let tiled = dir.path().join(format!("tiled.{ext}"));
        let a = denoise(&input, &whole, None);
        let b = denoise(&input, &tiled, Some(3000));
        assert_eq!((a.mode.as_str(), b.mode.as_str()), ("points", "tiled"));
        assert!(b.tiles >= 4, "{}", b.tiles);
        assert_eq!(b.normals, NormalsAction::Written);
        assert!(
            std::fs::read(&whole).unwrap() == std::fs::read(&tiled).unwrap(),
            "{ext}: tiled output differs"
        );
    }
    // The methods without the guard classify for the output only; bilateral with one pass
    // reaches one hop further for it.
    for (method, iterations, guard) in [(Method::Bilateral, 1, true), (Method::Qem, 0, false)] {
        let run_with = |out: &Path, tile_points| {
            let mut job = Job::new(&input, out);
            job.spec.params.write_normals = true;
            job.spec.params.method = method;
            job.spec.params.iterations = iterations;
            job.spec.params.guard = guard;
            let opts = RunOptions {
                tile_points,
                ..RunOptions::default()
            };
            run(&job, &opts).unwrap();
            std::fs::read(out).unwrap()
        };
        let whole = run_with(&dir.path().join("m.ply"), None);
        let tiled = run_with(&dir.path().join("t.ply"), Some(2500));
        assert!(
            whole == tiled,
            "{method:?} guard {guard}: tiled output differs"
        );
        let c = Cloud::read(&dir.path().join("m.ply"), None).unwrap();
        let classes = values(&c, PLY).iter().filter(|v| v[4] == 0.0).count();
        assert!(
            classes > pts.len() / 2,
            "{method:?}: {classes} surface points"
        );
    }
}

#[test]
#[ignore = "needs ../shared"]
fn issue9_write_normals_tiled_equals_in_memory_on_real_scans() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        ("../shared/data/lidar/lone-star.copc.laz", "laz", 60_000),
        ("../shared/data/lidar/4_6_crop.las", "las", 3_000),
        (
            "../shared/data/scans/table_scene_mug_stereo_textured.pcd",
            "pcd",
            25_000,
        ),
        ("../shared/data/scans/terrain_samp11-utm.pcd", "pcd", 4_000),
        ("../shared/data/scans/kitti_000008.bin", "ply", 2_000),
    ];
    for (input, ext, tile) in cases {
        let input = Path::new(input);
        let run_with = |tag: &str, tile_points| {
            let out = dir.path().join(format!("{tag}.{ext}"));
            let mut job = Job::new(input, &out);
            job.spec.params.write_normals = true;
            job.spec.outliers = qem_denoise::pipeline::OutlierMode::Classify;
            let opts = RunOptions {
                tile_points,
                ..RunOptions::default()
            };
            let r = run(&job, &opts).unwrap_or_else(|e| panic!("{}: {e}", input.display()));
            (r, std::fs::read(&out).unwrap())
        };
        let (_, whole) = run_with("whole", None);
        let (r, tiled) = run_with("tiled", Some(tile));
        assert!(r.tiles > 3, "{}: {} tiles", input.display(), r.tiles);
        assert!(whole == tiled, "{}: tiled output differs", input.display());
    }
}

#[test]
fn issue9_write_normals_scale_out_tasks_write_the_denoise_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let input = ply(dir.path(), "in.ply", &sheet(8000, 29));
    let work = dir.path().join("work");
    let run_ok = |args: &[&str]| {
        let o = qemd(args);
        assert!(
            o.status.success(),
            "qemd {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    let flags = ["--write-normals", "--tile-points", "1500"];
    let mut plan = vec![
        "plan",
        s(&input),
        "--work",
        s(&work),
        "--format",
        "las",
        "-q",
    ];
    plan.extend(flags);
    run_ok(&plan);
    for phase in ["partition", "globals", "tiles", "stitch"] {
        run_ok(&["worker", "--work", s(&work), "--phase", phase, "-q"]);
    }
    let denoised = dir.path().join("denoise.las");
    let mut denoise = vec!["denoise", s(&input), "-o", s(&denoised), "-q"];
    denoise.extend(flags);
    run_ok(&denoise);
    // The stitched format, and another one the stitch writes from the same results.
    for (name, want) in [
        ("out.las", denoised.clone()),
        ("out.pcd", dir.path().join("d.pcd")),
    ] {
        let out = dir.path().join(name);
        run_ok(&["finish", "--work", s(&work), "-o", s(&out), "-q"]);
        if name.ends_with(".pcd") {
            let mut denoise = vec!["denoise", s(&input), "-o", s(&want), "-q"];
            denoise.extend(flags);
            run_ok(&denoise);
        }
        assert!(
            std::fs::read(&out).unwrap() == std::fs::read(&want).unwrap(),
            "{name}: scale-out output differs from qemd denoise"
        );
    }
    // A format without room is refused by the finish too, leaving nothing.
    let bin = dir.path().join("out.bin");
    let o = qemd(&["finish", "--work", s(&work), "-o", s(&bin), "-q"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("no room for normals"));
    assert!(!bin.exists());
}

// ---------------------------------------------------------------------------------------------
// Stored normals: overwritten, never doubled.

#[test]
fn issue9_write_normals_overwrite_stored_normal_fields() {
    let dir = tempfile::tempdir().unwrap();
    let pts = sheet(1500, 11);
    let plain = ply(dir.path(), "plain.ply", &pts);
    let fresh = dir.path().join("fresh.ply");
    denoise(&plain, &fresh, None);
    let want = values(&Cloud::read(&fresh, None).unwrap(), PLY);

    // An ascii PLY and an ascii PCD whose stored normals (and a class) are stale.
    let rows: String = pts
        .iter()
        .map(|p| format!("{} {} {} 7 7 7 9\n", p.x as f32, p.y as f32, p.z as f32))
        .collect();
    let n = pts.len();
    let stale_ply = put(
        dir.path(),
        "stale.ply",
        format!(
            "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n\
             property float z\nproperty float nx\nproperty float ny\nproperty float nz\n\
             property uchar structure\nend_header\n{rows}"
        ),
    );
    let stale_pcd = put(
        dir.path(),
        "stale.pcd",
        format!(
            "VERSION 0.7\nFIELDS x y z normal_x normal_y normal_z curvature\nSIZE 4 4 4 4 4 4 4\n\
             TYPE F F F F F F F\nCOUNT 1 1 1 1 1 1 1\nWIDTH {n}\nHEIGHT 1\n\
             VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n{rows}"
        ),
    );
    let out = dir.path().join("a.ply");
    denoise(&stale_ply, &out, None);
    let c = Cloud::read(&out, None).unwrap();
    // The stored nx ny nz and structure hold the new values; curvature is added.
    assert_eq!(
        names_of(&c),
        ["x", "y", "z", "nx", "ny", "nz", "structure", "curvature"]
    );
    assert_eq!(values(&c, PLY), want);
    let out = dir.path().join("a.pcd");
    denoise(&stale_pcd, &out, None);
    let c = Cloud::read(&out, None).unwrap();
    assert_eq!(
        names_of(&c),
        [
            "x",
            "y",
            "z",
            "normal_x",
            "normal_y",
            "normal_z",
            "curvature",
            "structure"
        ]
    );
    assert_eq!(values(&c, PCD), want);
    // PCD to PLY: the PCD names are taken as they are.
    let out = dir.path().join("b.ply");
    denoise(&stale_pcd, &out, None);
    assert_eq!(values(&Cloud::read(&out, None).unwrap(), PCD), want);

    // A second run over LAS output: the record and its Extra Bytes VLR keep one set.
    let las = dir.path().join("once.las");
    denoise(&plain, &las, None);
    let twice = dir.path().join("twice.laz");
    denoise(&las, &twice, None);
    let (a, b) = (std::fs::read(&las).unwrap(), std::fs::read(&twice).unwrap());
    assert_eq!(u16_at(&a, RECORD_LEN), u16_at(&b, RECORD_LEN));
    assert_eq!(extra_bytes(&a), extra_bytes(&b));
    let c = Cloud::read(&twice, None).unwrap();
    assert_eq!(
        c.info.schema.fields.len(),
        Cloud::read(&las, None).unwrap().info.schema.fields.len()
    );
}

#[test]
fn issue9_write_normals_organized_clouds_keep_their_nan_points_with_no_normal() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (40, 30);
    let mut rows = String::new();
    for j in 0..h {
        for i in 0..w {
            if (i * 7 + j * 3) % 23 == 0 {
                rows.push_str("nan nan nan\n");
            } else {
                let (x, y) = (i as f32 * 0.05, j as f32 * 0.05);
                rows.push_str(&format!("{x} {y} {}\n", 0.2 * x + 1.0));
            }
        }
    }
    let input = put(
        dir.path(),
        "org.pcd",
        format!(
            "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {w}\n\
             HEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {}\nDATA ascii\n{rows}",
            w * h
        ),
    );
    let out = dir.path().join("out.pcd");
    let tiled = dir.path().join("tiled.pcd");
    denoise(&input, &out, None);
    denoise(&input, &tiled, Some(300));
    assert!(std::fs::read(&out).unwrap() == std::fs::read(&tiled).unwrap());
    let c = Cloud::read(&out, None).unwrap();
    assert_eq!(c.len(), w * h);
    let v = values(&c, PCD);
    let mut nan = 0;
    for (p, v) in c.positions.iter().zip(&v) {
        if p.x.is_nan() {
            nan += 1;
            assert_eq!(*v, [0.0, 0.0, 0.0, 0.0, 5.0]);
        } else {
            assert!((normal_of(v).length() - 1.0).abs() < 1e-6);
        }
    }
    assert!(nan > 0);
}

/// A LAS 1.2 PDRF 0 file of `pts` whose 6 extra bytes are `NormalX`, `NormalY`, `NormalZ` as
/// i16 scaled by 1/32767 (as some tools store them), all 0.
fn las_with_scaled_normals(path: &Path, pts: &[DVec3]) {
    let mut b = las::Builder::default();
    b.version = las::Version::new(1, 2);
    let mut format = las::point::Format::new(0).unwrap();
    format.extra_bytes = 6;
    b.point_format = format;
    let mut payload = Vec::new();
    for name in ["NormalX", "NormalY", "NormalZ"] {
        let mut d = [0u8; 192];
        d[2] = 4; // i16
        d[3] = 0x08; // scale set
        d[4..4 + name.len()].copy_from_slice(name.as_bytes());
        d[112..120].copy_from_slice(&(1.0f64 / 32767.0).to_le_bytes());
        payload.extend_from_slice(&d);
    }
    b.vlrs.push(las::Vlr {
        user_id: "LASF_Spec".into(),
        record_id: 4,
        description: "Extra Bytes".into(),
        data: payload,
    });
    let t = las::Transform {
        scale: 0.0001,
        offset: 0.0,
    };
    b.transforms = las::Vector { x: t, y: t, z: t };
    let mut w = las::Writer::from_path(path, b.into_header().unwrap()).unwrap();
    for p in pts {
        w.write_point(las::Point {
            x: p.x,
            y: p.y,
            z: p.z,
            return_number: 1,
            number_of_returns: 1,
            extra_bytes: vec![0; 6],
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
}

#[test]
fn issue9_write_normals_into_scaled_las_extra_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.las");
    las_with_scaled_normals(&input, &sheet(2000, 5));
    let out = dir.path().join("out.las");
    denoise(&input, &out, None);
    let bytes = std::fs::read(&out).unwrap();
    // The stored three keep their descriptors; curvature and structure follow them.
    let eb = extra_bytes(&bytes);
    let names: Vec<&str> = eb.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, LAS);
    assert_eq!(u16_at(&bytes, RECORD_LEN), 20 + 6 + 5);
    let c = Cloud::read(&out, None).unwrap();
    let s = &c.info.schema;
    assert_eq!(
        s.fields[s.field_index("NormalX").unwrap()].ty,
        ScalarType::I16
    );
    for (i, p) in values(&c, LAS).iter().enumerate() {
        // Stored: round(n · 32767); decoded with the descriptor's scale, a unit vector again.
        let n = normal_of(p) / 32767.0;
        assert!((n.length() - 1.0).abs() < 1e-3, "point {i}: {n}");
        assert!(n.z >= 0.0);
    }
}

/// The LAS files of a PLY source (fresh PDRF 6), of a LAS 1.2 PDRF 0 source with extra bytes
/// (the record grows, the Extra Bytes VLR is extended) and of a second run, read by laspy: no
/// dimension twice, the five values there with their types, unit normals pointing up.
#[test]
#[ignore = "needs python3 with pip laspy[lazrs]"]
fn issue9_write_normals_las_reads_in_laspy() {
    let dir = tempfile::tempdir().unwrap();
    let pts = sheet(2000, 23);
    let input = ply(dir.path(), "in.ply", &pts);
    let scaled = dir.path().join("scaled.las");
    las_with_scaled_normals(&scaled, &pts);
    let mut files = Vec::new();
    for (src, name) in [
        (&input, "a.las"),
        (&input, "a.laz"),
        (&input, "a.copc.laz"),
        (&scaled, "b.laz"),
    ] {
        let out = dir.path().join(name);
        denoise(src, &out, None);
        files.push(out);
    }
    let again = dir.path().join("c.las");
    denoise(&files[1], &again, None);
    files.push(again);
    let script = r#"
import sys, laspy, numpy as np
for path in sys.argv[1:]:
    f = laspy.read(path)
    names = list(f.point_format.dimension_names)
    assert len(names) == len(set(names)), (path, names)
    extra = list(f.point_format.extra_dimension_names)
    assert extra[-2:] == ["Curvature", "Structure"], (path, extra)
    assert [n for n in extra if n.startswith("Normal")] == ["NormalX", "NormalY", "NormalZ"], extra
    n = np.stack([np.asarray(f[k], dtype=float) for k in ["NormalX", "NormalY", "NormalZ"]], 1)
    length = np.linalg.norm(n, axis=1)
    assert np.all(np.abs(length - 1) < 2e-3), (path, length.min(), length.max())
    assert np.all(n[:, 2] >= 0), path
    assert f["Structure"].dtype == np.uint8, f["Structure"].dtype
    assert set(np.unique(f["Structure"])) <= set(range(6))
    print("ok", path.rsplit("/", 1)[-1], len(f.points))
"#;
    let out = std::process::Command::new("python3")
        .args(["-c", script])
        .args(&files)
        .output()
        .expect("python3 runs");
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{text}");
    assert_eq!(text.matches("ok ").count(), files.len(), "{text}");
}

// ---------------------------------------------------------------------------------------------
// E57: the normals extension, in each scan's own frame.

#[test]
fn issue9_write_normals_e57_in_the_scan_frame() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.e57");
    let q = DQuat::from_rotation_z(0.6) * DQuat::from_rotation_x(0.9);
    {
        let mut w = E57Writer::from_file(&input, "{file-guid}").unwrap();
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
        let mut pc = w.add_pointcloud("{scan-guid}", proto).unwrap();
        pc.set_transform(Some(Transform {
            rotation: Quaternion {
                w: q.w,
                x: q.x,
                y: q.y,
                z: q.z,
            },
            translation: e57::Translation {
                x: 10.0,
                y: 20.0,
                z: 5.0,
            },
        }));
        // A noisy plane in the scan's frame: its normal is the local z axis.
        let mut r = Rng(99);
        for i in 0..40 {
            for j in 0..40 {
                let (x, y) = (i as f64 * 0.05, j as f64 * 0.05);
                let values = [x, y, 0.001 * r.g()].map(RecordValue::Double).to_vec();
                pc.add_point(values).unwrap();
            }
        }
        pc.finalize().unwrap();
        w.finalize().unwrap();
    }
    let e57_out = dir.path().join("out.e57");
    let ply_out = dir.path().join("out.ply");
    denoise(&input, &e57_out, None);
    denoise(&input, &ply_out, None);
    let reader = e57::E57Reader::from_file(&e57_out).unwrap();
    assert!(
        reader.extensions().iter().any(|e| e.namespace == "nor"
            && e.url == "http://www.libe57.org/E57_NOR_surface_normals.txt"),
        "{:?}",
        reader.extensions()
    );
    let local = values(&Cloud::read(&e57_out, None).unwrap(), E57);
    let world = values(&Cloud::read(&ply_out, None).unwrap(), PLY);
    for (l, w) in local.iter().zip(&world) {
        // The world normal, turned into the scan's frame, is the stored one.
        let turned = q.inverse() * normal_of(w);
        assert!(
            (turned - normal_of(l)).length() < 1e-6,
            "{turned} vs {}",
            normal_of(l)
        );
        assert!(normal_of(l).z.abs() > 0.99, "{}", normal_of(l));
        assert_eq!((l[3], l[4]), (w[3], w[4]));
    }
}

// ---------------------------------------------------------------------------------------------
// Off by default; the report; refusals.

#[test]
fn issue9_write_normals_is_off_by_default_and_the_report_says_when_on() {
    let dir = tempfile::tempdir().unwrap();
    let input = ply(dir.path(), "in.ply", &sheet(1000, 13));
    let (a, b) = (dir.path().join("a.las"), dir.path().join("b.ply"));
    for out in [&a, &b] {
        let o = qemd(&["denoise", s(&input), "-o", s(out), "-q"]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    assert_eq!(
        names_of(&Cloud::read(&b, None).unwrap()),
        names_of(&Cloud::read(&input, None).unwrap())
    );
    let bytes = std::fs::read(&a).unwrap();
    assert!(
        !vlrs(&bytes)
            .iter()
            .any(|(u, r, _)| u == "LASF_Spec" && *r == 4)
    );
    assert_eq!(u16_at(&bytes, RECORD_LEN), 30);

    let report = dir.path().join("r.json");
    let out = dir.path().join("c.ply");
    let o = qemd(&[
        "denoise",
        s(&input),
        "-o",
        s(&out),
        "--write-normals",
        "--report",
        s(&report),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(r["normals"], "written");
    assert_eq!(r["params"]["write_normals"], true);
    assert!(String::from_utf8_lossy(&o.stderr).contains("--write-normals"));
}

#[test]
fn issue9_write_normals_refused_formats_say_so_in_one_line_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let input = ply(dir.path(), "in.ply", &sheet(500, 17));
    let mesh = dir.path().join("mesh.ply");
    let o = qemd(&["synth", "sphere", "-o", s(&mesh), "--resolution", "2"]);
    assert!(o.status.success());
    let before = listing(dir.path());
    for (src, out, says) in [
        (
            &input,
            "a.bin",
            "a KITTI .bin record has no room for normals",
        ),
        (
            &input,
            "a.pcd.bin",
            "a raw .bin record has no room for normals",
        ),
        (&input, "a.obj", "--write-normals applies to point clouds"),
        (&input, "a.off", "--write-normals applies to point clouds"),
        (
            &mesh,
            "b.ply",
            "invalid parameter write_normals: applies to point clouds, not meshes",
        ),
    ] {
        let target = dir.path().join(out);
        let o = qemd(&["denoise", s(src), "-o", s(&target), "--write-normals", "-q"]);
        assert!(!o.status.success(), "{out} accepted");
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
        assert!(err.contains(says), "{out}: {err}");
        if src == &input {
            assert!(err.contains(&target.display().to_string()), "{err}");
        }
        assert_eq!(listing(dir.path()), before, "{out}: a file was left");
    }
    // The same refusal from the library, with the format named by the job.
    let mut job = Job::new(&input, dir.path().join("k"));
    job.spec.params.write_normals = true;
    job.output_format = Some(Format::Kitti);
    assert!(run(&job, &RunOptions::default()).is_err());
    assert_eq!(listing(dir.path()), before);
}
