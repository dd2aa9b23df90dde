//! COPC output (issue 12): `-o *.copc.laz` writes a COPC 1.0 file (LAS 1.4, PDRF 6/7/8, octree
//! node order, hierarchy EVLR, info VLR). Read back with qemd's own reader here; validated by
//! laspy (lazrs) and copclib in the ignored tests (tests/copc_check.py).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use glam::DVec3;
use qem_denoise::io::{Cloud, Meta};
use qem_denoise::points::ScalarType;

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}
fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}
fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

/// A LAS 1.2 PDRF 3 file with two undocumented extra bytes per point and a GeoTIFF VLR: the
/// legacy layout COPC output must convert.
fn legacy_las(n: usize, seed: u64) -> Vec<u8> {
    let rl = 34 + 2;
    let vlr_payload = b"geotiff keys, kept verbatim".to_vec();
    let mut vlr = vec![0u8; 54];
    vlr[2..17].copy_from_slice(b"LASF_Projection");
    vlr[18..20].copy_from_slice(&34735u16.to_le_bytes());
    vlr[20..22].copy_from_slice(&(vlr_payload.len() as u16).to_le_bytes());
    vlr.extend_from_slice(&vlr_payload);
    let data_start = 227 + vlr.len();
    let mut h = vec![0u8; 227];
    h[..4].copy_from_slice(b"LASF");
    h[24] = 1;
    h[25] = 2;
    h[26..31].copy_from_slice(b"tests");
    h[94..96].copy_from_slice(&227u16.to_le_bytes());
    h[96..100].copy_from_slice(&(data_start as u32).to_le_bytes());
    h[100..104].copy_from_slice(&1u32.to_le_bytes());
    h[104] = 3;
    h[105..107].copy_from_slice(&(rl as u16).to_le_bytes());
    h[107..111].copy_from_slice(&(n as u32).to_le_bytes());
    let scale: [f64; 3] = [0.01, 0.01, 0.001];
    let offset: [f64; 3] = [500_000.0, 4_000_000.0, 0.0];
    for a in 0..3 {
        h[131 + 8 * a..139 + 8 * a].copy_from_slice(&scale[a].to_le_bytes());
        h[155 + 8 * a..163 + 8 * a].copy_from_slice(&offset[a].to_le_bytes());
    }
    let mut s = seed;
    let mut r = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        s >> 16
    };
    let mut body = Vec::with_capacity(n * rl);
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for _ in 0..n {
        let x = (r() % 40_000) as i32;
        let y = (r() % 30_000) as i32;
        // A gently curved terrain, millimetre z.
        let z = 100_000 + (x / 7 + y / 11) + (r() % 300) as i32;
        for (a, v) in [x, y, z].into_iter().enumerate() {
            lo[a] = lo[a].min(v);
            hi[a] = hi[a].max(v);
            body.extend_from_slice(&v.to_le_bytes());
        }
        body.extend_from_slice(&((r() % 65_536) as u16).to_le_bytes());
        let num = 1 + (r() % 5) as u8;
        let ret = 1 + (r() % u64::from(num)) as u8;
        body.push(ret | (num << 3) | (((r() % 2) as u8) << 6) | (((r() % 2) as u8) << 7));
        body.push((r() % 32) as u8 | (((r() % 8) as u8) << 5));
        body.push(((r() % 181) as i64 - 90) as i8 as u8); // scan angle rank

        body.push((r() % 256) as u8);
        body.extend_from_slice(&((r() % 65_536) as u16).to_le_bytes());
        body.extend_from_slice(&((r() % 1_000_000) as f64 / 7.0).to_le_bytes());
        for _ in 0..3 {
            body.extend_from_slice(&((r() % 65_536) as u16).to_le_bytes());
        }
        body.push((r() % 256) as u8);
        body.push((r() % 256) as u8);
    }
    for a in 0..3 {
        let (l, u) = (
            f64::from(lo[a]) * scale[a] + offset[a],
            f64::from(hi[a]) * scale[a] + offset[a],
        );
        h[179 + 16 * a..187 + 16 * a].copy_from_slice(&u.to_le_bytes());
        h[187 + 16 * a..195 + 16 * a].copy_from_slice(&l.to_le_bytes());
    }
    let mut file = h;
    file.extend_from_slice(&vlr);
    file.extend_from_slice(&body);
    file
}

/// The attributes of point `i` of `c` in one canonical form, whatever the point format: x, y, z
/// (scaled integers), intensity, return number, number of returns, scan direction, edge, class,
/// classification flags, scan angle rank, user data, point source id, GPS time bits, RGB, extras.
fn canonical(c: &Cloud, i: usize) -> Vec<i64> {
    let s = &c.info.schema;
    let rl = s.record_len;
    let rec = &c.records[i * rl..(i + 1) * rl];
    let f = |n: &str| s.get_f64(rec, s.field_index(n).unwrap());
    let mut v = vec![
        f("x") as i64,
        f("y") as i64,
        f("z") as i64,
        f("intensity") as i64,
    ];
    if s.field_index("return_flags").is_some() {
        let rf = f("return_flags") as u8;
        let c = f("classification") as u8;
        v.extend(
            [
                rf & 7,
                (rf >> 3) & 7,
                (rf >> 6) & 1,
                rf >> 7,
                c & 31,
                c >> 5,
            ]
            .map(i64::from),
        );
        v.push(f("scan_angle_rank") as i64);
    } else {
        let rn = f("return_numbers") as u8;
        let cf = f("classification_flags") as u8;
        let c = f("classification") as u8;
        v.extend([rn & 15, rn >> 4, (cf >> 6) & 1, cf >> 7, c, cf & 15].map(i64::from));
        v.push((f("scan_angle") * 0.006).round() as i64);
    }
    v.push(f("user_data") as i64);
    v.push(f("point_source_id") as i64);
    v.push(f("gps_time").to_bits() as i64);
    for n in ["red", "green", "blue", "extra_0", "extra_1"] {
        v.push(f(n) as i64);
    }
    v
}

fn multiset(c: &Cloud) -> Vec<Vec<i64>> {
    let mut v: Vec<_> = (0..c.len()).map(|i| canonical(c, i)).collect();
    v.sort();
    v
}

/// The COPC structure of a file: info (center, halfsize, spacing) and hierarchy entries
/// `(depth, x, y, z, offset, bytes, points)`.
struct Copc {
    center: [f64; 3],
    half: f64,
    spacing: f64,
    entries: Vec<(i32, i32, i32, i32, u64, i32, i32)>,
}

fn parse_copc(b: &[u8]) -> Copc {
    assert_eq!(&b[..4], b"LASF");
    assert_eq!((b[24], b[25]), (1, 4), "LAS 1.4");
    assert_eq!(u16_at(b, 94), 375, "header size");
    assert!(matches!(b[104], 0x86..=0x88), "PDRF 6-8, compressed");
    // The info VLR first, at 375.
    assert_eq!(&b[375 + 2..375 + 6], b"copc");
    assert_eq!(u16_at(b, 375 + 18), 1);
    assert_eq!(u16_at(b, 375 + 20), 160);
    let d = 375 + 54;
    let center = [f64_at(b, d), f64_at(b, d + 8), f64_at(b, d + 16)];
    let (half, spacing) = (f64_at(b, d + 24), f64_at(b, d + 32));
    let (root, size) = (u64_at(b, d + 40) as usize, u64_at(b, d + 48) as usize);
    // The hierarchy EVLR's payload is where the info says.
    let evlr = root - 60;
    assert_eq!(&b[evlr + 2..evlr + 6], b"copc");
    assert_eq!(u16_at(b, evlr + 18), 1000);
    assert_eq!(u64_at(b, evlr + 20) as usize, size);
    assert_eq!(u64_at(b, 235) as usize, evlr, "first EVLR");
    let entries = b[root..root + size]
        .chunks_exact(32)
        .map(|e| {
            let i = |k: usize| i32::from_le_bytes(e[k..k + 4].try_into().unwrap());
            (i(0), i(4), i(8), i(12), u64_at(e, 16), i(24), i(28))
        })
        .collect();
    Copc {
        center,
        half,
        spacing,
        entries,
    }
}

/// Checks the nodes against the points in file order: each node's chunk holds the next points,
/// all inside its cube; every node but the root has its parent.
fn check_nodes(copc: &Copc, c: &Cloud) {
    let mut entries = copc.entries.clone();
    entries.sort_by_key(|e| e.4);
    let keys: std::collections::HashSet<_> = entries.iter().map(|e| (e.0, e.1, e.2, e.3)).collect();
    let mut at = 0usize;
    for &(d, x, y, z, _, bytes, count) in &entries {
        assert!(bytes > 0 && count > 0);
        if d > 0 {
            assert!(
                keys.contains(&(d - 1, x / 2, y / 2, z / 2)),
                "parent of {d}/{x}/{y}/{z}"
            );
        }
        let size = 2.0 * copc.half / f64::from(1u32 << d);
        for p in &c.positions[at..at + count as usize] {
            for (a, k) in [x, y, z].into_iter().enumerate() {
                let lo = copc.center[a] - copc.half + f64::from(k) * size;
                assert!(
                    p[a] >= lo - 1e-9 && p[a] <= lo + size + 1e-9,
                    "point {p} outside node {d}/{x}/{y}/{z}"
                );
            }
        }
        at += count as usize;
    }
    assert_eq!(at, c.len(), "the nodes hold every point");
    assert!((copc.spacing - 2.0 * copc.half / 128.0).abs() < 1e-12 * copc.half);
}

#[test]
fn issue12_copc_output_keeps_every_point_and_attribute_in_octree_order() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("legacy.las");
    std::fs::write(&src, legacy_las(30_000, 7)).unwrap();
    let c = Cloud::read(&src, None).unwrap();
    let out = dir.path().join("out.copc.laz");
    c.write(&out, None).unwrap();
    let bytes = std::fs::read(&out).unwrap();
    let copc = parse_copc(&bytes);
    assert_eq!(bytes[104], 0x87, "PDRF 3 becomes 7");
    let d = Cloud::read(&out, None).unwrap();
    let Meta::Las(m) = &d.info.meta else { panic!() };
    assert!(m.is_copc());
    assert_eq!((m.point_format(), m.version()), (7, (1, 4)));
    assert_eq!(d.len(), c.len());
    assert_eq!(
        multiset(&d),
        multiset(&c),
        "the same points, every attribute"
    );
    assert_ne!(d.positions, c.positions, "octree order, not file order");
    check_nodes(&copc, &d);
    let depth = copc.entries.iter().map(|e| e.0).max().unwrap();
    assert!(
        depth >= 1 && copc.entries.len() > 8,
        "a real octree: {depth} levels"
    );
    let root_points = copc.entries.iter().find(|e| e.0 == 0).unwrap().6;
    assert!(root_points > 500 && (root_points as usize) < c.len() / 2);
    // The GeoTIFF VLR is kept verbatim; the laszip VLR says variable chunks.
    let geo = m
        .vlrs()
        .iter()
        .find(|v| v.user_id() == "LASF_Projection")
        .unwrap();
    assert_eq!(geo.data(), b"geotiff keys, kept verbatim");
    let laz = m
        .vlrs()
        .iter()
        .find(|v| v.user_id() == "laszip encoded")
        .unwrap();
    assert_eq!(u32_at(laz.data(), 12), u32::MAX);
    // Header bounds are the points' bounds.
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for p in &d.positions {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    for a in 0..3 {
        assert_eq!(f64_at(&bytes, 179 + 16 * a), hi[a]);
        assert_eq!(f64_at(&bytes, 187 + 16 * a), lo[a]);
    }
    assert_eq!(u64_at(&bytes, 247), 30_000, "LAS 1.4 point count");
    assert_eq!(u32_at(&bytes, 107), 0, "legacy count zero for PDRF 7");

    // Written again from the COPC itself: COPC again, same points (the stale records replaced).
    let again = dir.path().join("again.copc.laz");
    d.write(&again, None).unwrap();
    let e = Cloud::read(&again, None).unwrap();
    assert_eq!(multiset(&e), multiset(&c));
    check_nodes(&parse_copc(&std::fs::read(&again).unwrap()), &e);
}

#[test]
fn issue12_copc_source_to_plain_laz_or_las_drops_the_copc_records() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("legacy.las");
    std::fs::write(&src, legacy_las(5_000, 3)).unwrap();
    let copc = dir.path().join("a.copc.laz");
    Cloud::read(&src, None).unwrap().write(&copc, None).unwrap();
    let c = Cloud::read(&copc, None).unwrap();
    for name in ["plain.laz", "plain.las"] {
        let p = dir.path().join(name);
        c.write(&p, None).unwrap();
        let d = Cloud::read(&p, None).unwrap();
        let Meta::Las(m) = &d.info.meta else { panic!() };
        assert!(!m.is_copc(), "{name}");
        assert!(m.vlrs().iter().all(|v| v.user_id() != "copc"), "{name}");
        let Some(t) = (match &d.extras.trailer {
            qem_denoise::io::Trailer::Las(t) => Some(t),
            _ => None,
        }) else {
            panic!()
        };
        assert!(
            t.evlrs().all(|v| v.user_id() != "copc"),
            "{name}: hierarchy EVLR"
        );
        assert_eq!(
            d.positions, c.positions,
            "{name}: order of the COPC file kept"
        );
    }
}

#[test]
fn issue12_copc_from_other_formats_and_empty_clouds() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("in.ply");
    let mut text = String::from(
        "ply\nformat ascii 1.0\nelement vertex 400\nproperty double x\nproperty double y\n\
         property double z\nproperty uchar label\nend_header\n",
    );
    for i in 0..400 {
        text += &format!("{} {} {} {}\n", i % 20, i / 20, (i % 7) as f64 * 0.1, i % 5);
    }
    std::fs::write(&ply, text).unwrap();
    let c = Cloud::read(&ply, None).unwrap();
    let out = dir.path().join("o.copc.laz");
    c.write(&out, None).unwrap();
    let d = Cloud::read(&out, None).unwrap();
    check_nodes(&parse_copc(&std::fs::read(&out).unwrap()), &d);
    let label = d.info.schema.field_index("label").unwrap();
    assert_eq!(d.info.schema.fields[label].ty, ScalarType::U8);
    let mut want: Vec<(i64, i64, i64, u8)> = c
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            (
                (p.x * 1e6) as i64,
                (p.y * 1e6) as i64,
                (p.z * 1e6).round() as i64,
                (i % 5) as u8,
            )
        })
        .collect();
    let rl = d.info.schema.record_len;
    let mut got: Vec<(i64, i64, i64, u8)> = d
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let l = d.info.schema.get_f64(&d.records[i * rl..], label) as u8;
            (
                (p.x * 1e6) as i64,
                (p.y * 1e6) as i64,
                (p.z * 1e6).round() as i64,
                l,
            )
        })
        .collect();
    want.sort();
    got.sort();
    assert_eq!(got, want);

    // A sink dropped before finish leaves nothing behind (no output, no scratch folder).
    {
        let dropped = dir.path().join("dropped.copc.laz");
        let mut sink = qem_denoise::io::create(&dropped, None, &c.info, c.len() as u64).unwrap();
        let mut batch = qem_denoise::points::PointBatch::with_capacity(c.info.schema.record_len, 8);
        batch.positions.extend_from_slice(&c.positions[..8]);
        batch
            .records
            .extend_from_slice(&c.records[..8 * c.info.schema.record_len]);
        sink.write_batch(&batch).unwrap();
    }
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.contains("dropped"))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");

    // No points: a valid, empty COPC file.
    let empty = Cloud::generated(Vec::new(), None, ScalarType::F64);
    let e = dir.path().join("empty.copc.laz");
    empty.write(&e, None).unwrap();
    let back = Cloud::read(&e, None).unwrap();
    assert_eq!(back.len(), 0);
    assert_eq!(parse_copc(&std::fs::read(&e).unwrap()).entries.len(), 1);
}

fn shared(name: &str) -> PathBuf {
    Path::new("../shared/data/lidar").join(name)
}

fn check_with_python(copc: &Path, source: Option<&Path>) -> String {
    let mut cmd = Command::new("python3");
    cmd.arg("tests/copc_check.py").arg(copc);
    if let Some(s) = source {
        cmd.arg(s);
    }
    let out = cmd.output().expect("python3 runs");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{}: {stdout}{}",
        copc.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[test]
#[ignore = "needs ../shared and pip laspy, lazrs, copclib"]
fn issue12_copc_output_validates_in_laspy_and_copclib() {
    let dir = tempfile::tempdir().unwrap();
    let mut counts = HashMap::new();
    // A COPC source, a LAS 1.2 PDRF 3 with GeoTIFF VLRs, a LAS 1.1 PDRF 1 LAZ: written as COPC
    // unchanged, compared point by point with the source by laspy.
    for name in ["lone-star.copc.laz", "4_6_crop.las", "32-1-472-150-76.laz"] {
        let src = shared(name);
        let c = Cloud::read(&src, None).unwrap();
        let out = dir.path().join(format!("{name}.copc.laz"));
        c.write(&out, None).unwrap();
        let report = check_with_python(&out, Some(&src));
        eprintln!("{name}: {report}");
        let d = Cloud::read(&out, None).unwrap();
        assert_eq!(d.len(), c.len());
        counts.insert(name, d.len());
    }
    // Denoised through the CLI: a valid COPC of the moved points, every attribute kept.
    let src = shared("lone-star.copc.laz");
    let out = dir.path().join("clean.copc.laz");
    let run = Command::new(env!("CARGO_BIN_EXE_qemd"))
        .args([
            "denoise",
            src.to_str().unwrap(),
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
    let report = check_with_python(&out, None);
    eprintln!("denoised: {report}");
    let (a, b) = (
        Cloud::read(&src, None).unwrap(),
        Cloud::read(&out, None).unwrap(),
    );
    assert_eq!(b.len(), a.len());
    let non_xyz = |c: &Cloud| {
        let rl = c.info.schema.record_len;
        let mut v: Vec<&[u8]> = c.records.chunks_exact(rl).map(|r| &r[12..]).collect();
        v.sort();
        v.into_iter().flatten().copied().collect::<Vec<u8>>()
    };
    assert_eq!(non_xyz(&a), non_xyz(&b), "every attribute but x, y, z kept");
    assert_eq!(counts["lone-star.copc.laz"], 518_862);
}
