//! Integration tests of the noise flag in PLY and text output, its refusal by KITTI, OBJ and OFF,
//! and the coordinate precision of cross-format writes (LAS → PLY, PCD, XYZ, PTS).
//!
//! `cargo test --test tests io_flags::` selects exactly these tests.

use std::path::Path;

use crate::util::{listing, put};
use glam::DVec3;
use las::point::Format as PointFormat;
use las::{Builder, Transform, Vector};
use qem_denoise::io::ply::{PlyEncoding, PlyType};
use qem_denoise::io::{self, Cloud, Format, IoError, Meta, Rounding, SinkOptions};
use qem_denoise::points::{Endian, FLAG_NOISE, PointBatch, ScalarType, write_scalar};

const NOISE: SinkOptions = SinkOptions {
    noise_flag: true,
    normals: false,
    temp_dir: None,
    body: false,
    rounding: Rounding::Nearest,
};

// ---------------------------------------------------------------------------------------------
// Helpers.

/// Writes `c` to `out` with the noise flag, in two batches, giving `flags` (possibly empty).
fn write_flagged(c: &Cloud, out: &Path, flags: &[u8]) {
    let mut sink = io::create_with(out, None, &c.info, c.len() as u64, &NOISE).unwrap();
    let rl = c.info.schema.record_len;
    let half = c.len() / 2;
    for (start, end) in [(0, half), (half, c.len())] {
        let mut b = PointBatch::with_capacity(rl, end - start);
        b.clear(start as u64);
        for i in start..end {
            b.push(c.positions[i], &c.records[i * rl..(i + 1) * rl]);
        }
        if !flags.is_empty() {
            b.flags = flags[start..end].to_vec();
        }
        sink.write_batch(&b).unwrap();
    }
    sink.finish(&c.extras).unwrap();
}

/// Flags of `n` points: noise on every third point; one point carries another bit only.
fn flags(n: usize) -> Vec<u8> {
    (0..n)
        .map(|i| match i % 3 {
            0 => FLAG_NOISE,
            1 if i == 1 => 0x80,
            2 => FLAG_NOISE | 0x40,
            _ => 0,
        })
        .collect()
}

fn expected_noise(flags: &[u8], n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| f64::from(u8::from(flags.get(i).is_some_and(|f| f & FLAG_NOISE != 0))))
        .collect()
}

/// Field `name` of point `i`.
fn value(c: &Cloud, i: usize, name: &str) -> f64 {
    let s = &c.info.schema;
    let k = s
        .field_index(name)
        .unwrap_or_else(|| panic!("no field {name}"));
    s.get_f64(&c.records[i * s.record_len..(i + 1) * s.record_len], k)
}

// ---------------------------------------------------------------------------------------------
// PLY.

fn ply_type(ty: ScalarType) -> &'static str {
    match ty {
        ScalarType::U8 => "uchar",
        ScalarType::I16 => "short",
        ScalarType::F32 => "float",
        ScalarType::F64 => "double",
        _ => unreachable!(),
    }
}

/// A PLY file with vertex properties `props`, vertex rows `rows` and, when `face`, one
/// triangle after the vertices.
fn ply_file(
    enc: PlyEncoding,
    props: &[(&str, ScalarType)],
    rows: &[Vec<f64>],
    face: bool,
) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat {} 1.0\ncomment flags test\nelement vertex {}\n",
        enc.keyword(),
        rows.len()
    )
    .into_bytes();
    for (name, ty) in props {
        out.extend_from_slice(format!("property {} {name}\n", ply_type(*ty)).as_bytes());
    }
    if face {
        out.extend_from_slice(b"element face 1\nproperty list uchar int vertex_indices\n");
    }
    out.extend_from_slice(b"end_header\n");
    let endian = match enc {
        PlyEncoding::BinaryBigEndian => Endian::Big,
        _ => Endian::Little,
    };
    for row in rows {
        if enc == PlyEncoding::Ascii {
            let t: Vec<String> = row.iter().map(|v| v.to_string()).collect();
            out.extend_from_slice(t.join(" ").as_bytes());
            out.push(b'\n');
        } else {
            for ((_, ty), &v) in props.iter().zip(row) {
                let at = out.len();
                out.resize(at + ty.size(), 0);
                write_scalar(&mut out[at..], *ty, endian, v);
            }
        }
    }
    if face {
        if enc == PlyEncoding::Ascii {
            out.extend_from_slice(b"3 0 1 2\n");
        } else {
            out.push(3);
            for v in [0i32, 1, 2] {
                let at = out.len();
                out.resize(at + 4, 0);
                write_scalar(&mut out[at..], ScalarType::I32, endian, f64::from(v));
            }
        }
    }
    out
}

fn ply_rows(n: usize, with_noise: Option<usize>) -> Vec<Vec<f64>> {
    (0..n)
        .map(|i| {
            let f = i as f64;
            let mut r = vec![
                0.5 + f,
                -1.25 * f,
                0.125 * f,
                (i * 37 % 256) as f64,
                -3.0 * f,
            ];
            if let Some(at) = with_noise {
                r.insert(at, ((i + 1) % 2) as f64);
            }
            r
        })
        .collect()
}

const PLY_PROPS: [(&str, ScalarType); 5] = [
    ("x", ScalarType::F32),
    ("y", ScalarType::F32),
    ("z", ScalarType::F32),
    ("red", ScalarType::U8),
    ("quality", ScalarType::I16),
];

/// Names of the vertex properties of a PLY cloud.
fn vertex_names(c: &Cloud) -> Vec<String> {
    let Meta::Ply(m) = &c.info.meta else {
        panic!("PLY meta expected")
    };
    m.vertex_element()
        .unwrap()
        .properties
        .iter()
        .map(|p| p.name.clone())
        .collect()
}

#[test]
fn ply_noise_flag_appends_a_uchar_property_in_every_encoding() {
    let dir = tempfile::tempdir().unwrap();
    let n = 9;
    let fl = flags(n);
    let want = expected_noise(&fl, n);
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        for face in [false, true] {
            let name = format!("{}_{face}.ply", enc.keyword());
            let src = put(
                dir.path(),
                &name,
                ply_file(enc, &PLY_PROPS, &ply_rows(n, None), face),
            );
            let c = Cloud::read(&src, None).unwrap();
            let out = dir.path().join(format!("noise_{name}"));
            write_flagged(&c, &out, &fl);

            // The header is the source's with one property line added to the vertex element.
            let bytes = std::fs::read(&out).unwrap();
            let text = String::from_utf8_lossy(&bytes);
            let head = &text[..text.find("end_header\n").unwrap()];
            let mut want_head = format!(
                "ply\nformat {} 1.0\ncomment flags test\nelement vertex {n}\nproperty float x\n\
                 property float y\nproperty float z\nproperty uchar red\nproperty short quality\n\
                 property uchar noise\n",
                enc.keyword()
            );
            if face {
                want_head.push_str("element face 1\nproperty list uchar int vertex_indices\n");
            }
            assert_eq!(head, want_head, "{name}");

            let d = Cloud::read(&out, None).unwrap();
            let Meta::Ply(m) = &d.info.meta else {
                panic!("PLY meta expected")
            };
            assert_eq!(m.encoding(), enc);
            assert_eq!(
                vertex_names(&d),
                ["x", "y", "z", "red", "quality", "noise"],
                "{name}"
            );
            let noise = &m.vertex_element().unwrap().properties[5];
            assert_eq!(noise.ty, PlyType::Scalar(ScalarType::U8));
            assert_eq!(d.positions, c.positions);
            for (i, w) in want.iter().enumerate() {
                for (p, _) in PLY_PROPS {
                    assert_eq!(value(&d, i, p), value(&c, i, p), "{name} point {i} {p}");
                }
                assert_eq!(value(&d, i, "noise"), *w, "{name} point {i}");
            }
            assert_eq!(d.faces(), c.faces(), "{name}");

            // Without flags in the batches every point gets 0.
            let zero = dir.path().join(format!("zero_{name}"));
            write_flagged(&c, &zero, &[]);
            let z = Cloud::read(&zero, None).unwrap();
            assert!((0..n).all(|i| value(&z, i, "noise") == 0.0), "{name}");
        }
    }
}

#[test]
fn ply_existing_noise_property_is_overwritten_not_duplicated() {
    let dir = tempfile::tempdir().unwrap();
    let n = 7;
    let fl = flags(n);
    let want = expected_noise(&fl, n);
    let mut props = PLY_PROPS.to_vec();
    props.insert(3, ("noise", ScalarType::U8));
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        let name = format!("had_{}.ply", enc.keyword());
        let bytes = ply_file(enc, &props, &ply_rows(n, Some(3)), false);
        let src = put(dir.path(), &name, &bytes);
        let c = Cloud::read(&src, None).unwrap();
        let out = dir.path().join(format!("noise_{name}"));
        write_flagged(&c, &out, &fl);
        let got = std::fs::read(&out).unwrap();
        let end = |b: &[u8]| b.windows(11).position(|w| w == b"end_header\n").unwrap();
        assert_eq!(got[..end(&got)], bytes[..end(&bytes)], "header unchanged");
        let d = Cloud::read(&out, None).unwrap();
        assert_eq!(vertex_names(&d), ["x", "y", "z", "noise", "red", "quality"]);
        for (i, w) in want.iter().enumerate() {
            assert_eq!(value(&d, i, "noise"), *w, "{name} point {i}");
            for (p, _) in PLY_PROPS {
                assert_eq!(value(&d, i, p), value(&c, i, p), "{name} point {i} {p}");
            }
        }
    }
}

#[test]
fn ply_noise_flag_for_a_foreign_source() {
    let dir = tempfile::tempdir().unwrap();
    let pts: Vec<DVec3> = (0..5).map(|i| DVec3::new(i as f64, 0.5, -1.0)).collect();
    let c = Cloud::generated(pts.clone(), None, ScalarType::F32);
    let out = dir.path().join("g.ply");
    let fl = flags(5);
    write_flagged(&c, &out, &fl);
    let d = Cloud::read(&out, None).unwrap();
    assert_eq!(vertex_names(&d), ["x", "y", "z", "noise"]);
    assert_eq!(d.positions, pts);
    let want = expected_noise(&fl, 5);
    assert!((0..5).all(|i| value(&d, i, "noise") == want[i]));

    // Flag off: the output has no noise property.
    let plain = dir.path().join("p.ply");
    c.write(&plain, None).unwrap();
    assert_eq!(
        vertex_names(&Cloud::read(&plain, None).unwrap()),
        ["x", "y", "z"]
    );
}

// ---------------------------------------------------------------------------------------------
// Text.

/// Writes `text` as `name`, rewrites it with the noise flag and `fl`, returns the output.
fn text_with_noise(dir: &Path, name: &str, text: &str, fl: &[u8]) -> (String, Cloud) {
    let src = put(dir, name, text);
    let c = Cloud::read(&src, None).unwrap();
    let out = dir.join(format!("noise_{name}"));
    write_flagged(&c, &out, fl);
    (
        std::fs::read_to_string(&out).unwrap(),
        Cloud::read(&out, None).unwrap(),
    )
}

fn names(c: &Cloud) -> Vec<&str> {
    c.info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect()
}

#[test]
fn text_noise_flag_appends_a_column_and_names_it() {
    let dir = tempfile::tempdir().unwrap();
    let fl = [FLAG_NOISE, 0, 0x80, FLAG_NOISE | 2];

    let (out, d) = text_with_noise(
        dir.path(),
        "a.xyz",
        "# scan\n//X Y Z Intensity\n1.5 2 3 0.5\n4 5 6 0.25\n7 8 9 1\n-1 -2 -3 0\n# end\n",
        &fl,
    );
    assert_eq!(
        out,
        "# scan\n//X Y Z Intensity noise\n1.5 2 3 0.5 1\n4 5 6 0.25 0\n7 8 9 1 0\n\
         -1 -2 -3 0 1\n# end\n"
    );
    assert_eq!(names(&d), ["x", "y", "z", "intensity", "noise"]);

    // Commas, CRLF: the separator of the data and of the header comment are kept.
    let (out, d) = text_with_noise(
        dir.path(),
        "b.txt",
        "# x, y, z\r\n1,2,3\r\n4,5,6\r\n7,8,9\r\n1,1,1\r\n",
        &fl,
    );
    assert_eq!(
        out,
        "# x, y, z, noise\r\n1,2,3,1\r\n4,5,6,0\r\n7,8,9,0\r\n1,1,1,1\r\n"
    );
    assert_eq!(names(&d), ["x", "y", "z", "noise"]);

    // PTS: a names comment after the count line; tab separators.
    let (out, _) = text_with_noise(
        dir.path(),
        "c.pts",
        "# made by hand\n4\n# x y z r\n1\t2\t3\t9\n4\t5\t6\t9\n7\t8\t9\t9\n0\t0\t0\t9",
        &fl,
    );
    assert_eq!(
        out,
        "# made by hand\n4\n# x y z r noise\n1\t2\t3\t9\t1\n4\t5\t6\t9\t0\n7\t8\t9\t9\t0\n\
         0\t0\t0\t9\t1"
    );

    // No names comment: only the column; no flags in the batches: all 0.
    let (out, d) = text_with_noise(dir.path(), "d.xyz", "1 2 3\n4 5 6\n", &[]);
    assert_eq!(out, "1 2 3 0\n4 5 6 0\n");
    assert_eq!(names(&d), ["x", "y", "z", "c3"]);
}

#[test]
fn text_existing_noise_column_is_overwritten() {
    let dir = tempfile::tempdir().unwrap();
    let (out, d) = text_with_noise(
        dir.path(),
        "a.xyz",
        "# x y z noise i\n1 2 3 0 7\n4 5 6 1 8\n",
        &[FLAG_NOISE, 0],
    );
    assert_eq!(out, "# x y z noise i\n1 2 3 1 7\n4 5 6 0 8\n");
    assert_eq!(names(&d), ["x", "y", "z", "noise", "i"]);
}

#[test]
fn text_noise_flag_for_a_foreign_source() {
    let dir = tempfile::tempdir().unwrap();
    let c = Cloud::generated(
        vec![DVec3::new(0.5, 1.0, 2.0), DVec3::new(-1.0, 0.0, 3.0)],
        None,
        ScalarType::F64,
    );
    for (name, want) in [
        ("g.xyz", "# x y z noise\n0.5 1 2 0\n-1 0 3 1\n"),
        ("g.pts", "2\n0.5 1 2 0\n-1 0 3 1\n"),
    ] {
        let out = dir.path().join(name);
        write_flagged(&c, &out, &[0, FLAG_NOISE]);
        assert_eq!(std::fs::read_to_string(&out).unwrap(), want);
    }
}

// ---------------------------------------------------------------------------------------------
// Formats that refuse the flag.

#[test]
fn kitti_obj_and_off_refuse_the_noise_flag_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let c = Cloud::generated(vec![DVec3::ZERO; 3], None, ScalarType::F32);
    for (name, msg) in [
        (
            "a.bin",
            "a KITTI .bin record has no room for a noise flag; use --outliers remove or \
             another output format",
        ),
        ("a.obj", "outlier flags apply to point clouds"),
        ("a.off", "outlier flags apply to point clouds"),
    ] {
        let out = dir.path().join(name);
        let e = io::create_with(&out, None, &c.info, 3, &NOISE)
            .err()
            .unwrap_or_else(|| panic!("{name} accepted the noise flag"));
        assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
        let text = e.to_string();
        assert!(text.contains(msg), "{text}");
        assert!(text.contains(&out.display().to_string()), "{text}");
        assert!(listing(dir.path()).is_empty(), "{name}: no file left");
    }
    // The format can also come from the argument.
    let e = io::create_with(
        &dir.path().join("k"),
        Some(Format::Kitti),
        &c.info,
        3,
        &NOISE,
    );
    assert!(e.is_err());
    assert!(listing(dir.path()).is_empty());
}

// ---------------------------------------------------------------------------------------------
// Cross-format precision: LAS (scaled I32 x, y, z) to PLY, PCD, XYZ and PTS.

/// A LAS file (PDRF 1, scale `scale`, offsets `offset`) of `pts`, with intensity `100 + i`
/// and GPS time `1000.5 + i`.
fn build_las(path: &Path, pts: &[DVec3], scale: f64, offset: [f64; 3]) {
    let mut b = Builder::default();
    b.version = las::Version::new(1, 2);
    b.point_format = PointFormat::new(1).unwrap();
    let t = |i: usize| Transform {
        scale,
        offset: offset[i],
    };
    b.transforms = Vector {
        x: t(0),
        y: t(1),
        z: t(2),
    };
    let mut w = las::Writer::from_path(path, b.into_header().unwrap()).unwrap();
    for (i, p) in pts.iter().enumerate() {
        w.write_point(las::Point {
            x: p.x,
            y: p.y,
            z: p.z,
            intensity: 100 + i as u16,
            return_number: 1,
            number_of_returns: 1,
            gps_time: Some(1000.5 + i as f64),
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
}

/// Offsets that keep the scaled northing within 32 bits (the easting keeps a large integer).
const UTM_OFFSET: [f64; 3] = [0.0, 5_000_000.0, 0.0];

fn utm_points() -> Vec<DVec3> {
    (0..6)
        .map(|i| {
            let f = i as f64;
            DVec3::new(
                500_000.123 + 0.001 * f,
                5_400_000.987 - 0.017 * f,
                123.456 + 0.333 * f,
            )
        })
        .collect()
}

fn assert_close(got: &[DVec3], want: &[DVec3], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}");
    for (g, w) in got.iter().zip(want) {
        for (a, b) in [(g.x, w.x), (g.y, w.y), (g.z, w.z)] {
            assert!(
                (a - b).abs() <= 1e-9 * b.abs(),
                "{what}: {a} instead of {b} (rounded?)"
            );
        }
    }
}

fn xyz_types(c: &Cloud) -> [ScalarType; 3] {
    c.info.schema.xyz.map(|i| c.info.schema.fields[i].ty)
}

#[test]
fn las_to_ply_pcd_and_text_keeps_sub_unit_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let pts = utm_points();
    let las = dir.path().join("utm.las");
    build_las(&las, &pts, 0.001, UTM_OFFSET);
    let c = Cloud::read(&las, None).unwrap();
    assert_eq!(xyz_types(&c), [ScalarType::I32; 3]);
    assert_close(&c.positions, &pts, "las");

    for name in ["o.ply", "o.pcd", "o.xyz", "o.pts"] {
        let out = dir.path().join(name);
        c.write(&out, None).unwrap();
        let d = Cloud::read(&out, None).unwrap();
        assert_close(&d.positions, &c.positions, name);
        assert_eq!(xyz_types(&d), [ScalarType::F64; 3], "{name}");
        // Other fields keep their types (the text formats read every column as F64).
        if !name.ends_with("xyz") && !name.ends_with("pts") {
            let k = d.info.schema.field_index("intensity").unwrap();
            assert_eq!(d.info.schema.fields[k].ty, ScalarType::U16, "{name}");
            let k = d.info.schema.field_index("gps_time").unwrap();
            assert_eq!(d.info.schema.fields[k].ty, ScalarType::F64, "{name}");
        }
        // PTS has no line naming the columns.
        let (intensity, gps) = if name.ends_with("pts") {
            ("c3", "c9")
        } else {
            ("intensity", "gps_time")
        };
        for i in 0..pts.len() {
            assert_eq!(value(&d, i, intensity), 100.0 + i as f64, "{name}");
            assert_eq!(value(&d, i, gps), 1000.5 + i as f64, "{name}");
        }
    }
    let ply = std::fs::read(dir.path().join("o.ply")).unwrap();
    let ply = String::from_utf8_lossy(&ply[..200]);
    assert!(
        ply.contains("property double x\nproperty double y\nproperty double z\n"),
        "{ply}"
    );
    let pcd = std::fs::read(dir.path().join("o.pcd")).unwrap();
    let pcd = String::from_utf8_lossy(&pcd[..300]);
    assert!(pcd.contains("\nSIZE 8 8 8 "), "{pcd}");
    assert!(pcd.contains("\nTYPE F F F "), "{pcd}");
    // Text prints the f64 positions in full (shortest round-trip digits).
    let xyz = std::fs::read_to_string(dir.path().join("o.xyz")).unwrap();
    let first: Vec<&str> = xyz.lines().nth(1).unwrap().split(' ').take(3).collect();
    let p = c.positions[0];
    assert_eq!(first, [p.x, p.y, p.z].map(|v| v.to_string()), "{xyz}");
    assert!(first.iter().all(|t| t.contains('.')), "{xyz}");
}

#[test]
fn las_with_integral_positions_still_writes_every_coordinate() {
    // Scale 1, offset 0: the decoded positions equal the stored integers.
    let dir = tempfile::tempdir().unwrap();
    let pts: Vec<DVec3> = (0..4)
        .map(|i| DVec3::new(600_000.0 + i as f64, 4_000_000.0, -12.0 - i as f64))
        .collect();
    let las = dir.path().join("int.las");
    build_las(&las, &pts, 1.0, [0.0; 3]);
    let c = Cloud::read(&las, None).unwrap();
    for name in ["i.ply", "i.pcd", "i.xyz"] {
        let out = dir.path().join(name);
        c.write(&out, None).unwrap();
        let d = Cloud::read(&out, None).unwrap();
        assert_eq!(d.positions, pts, "{name}");
    }
}

#[test]
fn las_to_ply_and_pcd_with_noise_flag() {
    let dir = tempfile::tempdir().unwrap();
    let pts = utm_points();
    let las = dir.path().join("utm.las");
    build_las(&las, &pts, 0.001, UTM_OFFSET);
    let c = Cloud::read(&las, None).unwrap();
    let fl = flags(pts.len());
    let want = expected_noise(&fl, pts.len());
    for name in ["n.ply", "n.pcd", "n.xyz"] {
        let out = dir.path().join(name);
        write_flagged(&c, &out, &fl);
        let d = Cloud::read(&out, None).unwrap();
        assert_close(&d.positions, &c.positions, name);
        assert_eq!(d.info.schema.fields.last().unwrap().name, "noise", "{name}");
        for (i, w) in want.iter().enumerate() {
            assert_eq!(value(&d, i, "noise"), *w, "{name} point {i}");
            assert_eq!(value(&d, i, "intensity"), 100.0 + i as f64, "{name}");
        }
    }
}
