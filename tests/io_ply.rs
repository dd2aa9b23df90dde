//! Integration tests of the PLY backend: lossless round trips for every encoding and scalar type,
//! extra elements, cross-format writes, bad input, and (ignored by default) the shared data files.
//!
//! `cargo test --test tests io_ply::` selects exactly these tests.

use std::path::{Path, PathBuf};

use glam::DVec3;
use qem_denoise::io::ply::{PlyEncoding, PlySink, PlySource, PlyType};
use qem_denoise::io::{self, Cloud, Extras, IoError, Meta, Sink, Source, Trailer};
use qem_denoise::points::{Endian, Faces, PointBatch, ScalarType, write_scalar};

// ---------------------------------------------------------------------------------------------
// A small, independent PLY generator for the tests.

#[derive(Clone, Copy)]
enum P {
    S(ScalarType),
    L(ScalarType, ScalarType),
}

struct El {
    name: &'static str,
    props: Vec<(String, P)>,
    /// One `Vec` per property per row (scalars have one value, lists their items).
    rows: Vec<Vec<Vec<f64>>>,
}

const ALL: [ScalarType; 8] = [
    ScalarType::I8,
    ScalarType::U8,
    ScalarType::I16,
    ScalarType::U16,
    ScalarType::I32,
    ScalarType::U32,
    ScalarType::F32,
    ScalarType::F64,
];

fn spell(ty: ScalarType, alt: bool) -> &'static str {
    use ScalarType::*;
    match (ty, alt) {
        (I8, false) => "char",
        (I8, true) => "int8",
        (U8, false) => "uchar",
        (U8, true) => "uint8",
        (I16, false) => "short",
        (I16, true) => "int16",
        (U16, false) => "ushort",
        (U16, true) => "uint16",
        (I32, false) => "int",
        (I32, true) => "int32",
        (U32, false) => "uint",
        (U32, true) => "uint32",
        (F32, false) => "float",
        (F32, true) => "float32",
        (F64, false) => "double",
        (F64, true) => "float64",
        _ => unreachable!(),
    }
}

fn enc_name(e: PlyEncoding) -> &'static str {
    match e {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
        PlyEncoding::BinaryBigEndian => "binary_big_endian",
    }
}

fn text_of(ty: ScalarType, v: f64) -> String {
    match ty {
        ScalarType::F32 => format!("{}", v as f32),
        ScalarType::F64 => format!("{v}"),
        _ => format!("{}", v as i64),
    }
}

fn put(out: &mut Vec<u8>, enc: PlyEncoding, ty: ScalarType, v: f64, first: bool) {
    match enc {
        PlyEncoding::Ascii => {
            if !first {
                out.push(b' ');
            }
            out.extend_from_slice(text_of(ty, v).as_bytes());
        }
        _ => {
            let endian = if enc == PlyEncoding::BinaryBigEndian {
                Endian::Big
            } else {
                Endian::Little
            };
            let at = out.len();
            out.resize(at + ty.size(), 0);
            write_scalar(&mut out[at..], ty, endian, v);
        }
    }
}

struct Style {
    alt: bool,
    nl: &'static str,
    trailing_space: bool,
}

const PLAIN: Style = Style {
    alt: false,
    nl: "\n",
    trailing_space: false,
};

fn ply_bytes(enc: PlyEncoding, els: &[El], style: &Style, trailing: &[u8]) -> Vec<u8> {
    let nl = style.nl;
    let mut h = format!(
        "ply{nl}format {} 1.0{nl}comment made by the tests{nl}",
        enc_name(enc)
    );
    h += &format!("obj_info some info{nl}");
    for e in els {
        h += &format!("element {} {}{nl}", e.name, e.rows.len());
        for (name, p) in &e.props {
            h += &match p {
                P::S(t) => format!("property {} {name}{nl}", spell(*t, style.alt)),
                P::L(c, t) => format!(
                    "property list {} {} {name}{nl}",
                    spell(*c, style.alt),
                    spell(*t, !style.alt)
                ),
            };
        }
    }
    h += &format!("comment a late comment{nl}end_header{nl}");
    let mut out = h.into_bytes();
    for e in els {
        for row in &e.rows {
            let mut first = true;
            for ((_, p), vals) in e.props.iter().zip(row) {
                match *p {
                    P::S(t) => put(&mut out, enc, t, vals[0], first),
                    P::L(c, t) => {
                        put(&mut out, enc, c, vals.len() as f64, first);
                        for &v in vals {
                            put(&mut out, enc, t, v, false);
                        }
                    }
                }
                first = false;
            }
            if enc == PlyEncoding::Ascii {
                if style.trailing_space {
                    out.push(b' ');
                }
                out.extend_from_slice(nl.as_bytes());
            }
        }
    }
    out.extend_from_slice(trailing);
    out
}

/// Extreme and ordinary values of each type.
fn samples(ty: ScalarType) -> [f64; 3] {
    use ScalarType::*;
    match ty {
        I8 => [-128.0, 127.0, 5.0],
        U8 => [0.0, 255.0, 7.0],
        I16 => [-32768.0, 32767.0, -3.0],
        U16 => [0.0, 65535.0, 300.0],
        I32 => [i32::MIN as f64, i32::MAX as f64, -70000.0],
        U32 => [0.0, u32::MAX as f64, 123456.0],
        F32 => [0.1f32 as f64, -3.4e38f32 as f64, 1.0e-7f32 as f64],
        F64 => [0.1, -1.0e300, 5e-324],
        _ => unreachable!(),
    }
}

/// A vertex element with x, y, z of type `xyz` and one attribute of every scalar type.
fn vertex_all_types(xyz: ScalarType, n: usize) -> El {
    let mut props = vec![
        ("x".to_string(), P::S(xyz)),
        ("y".to_string(), P::S(xyz)),
        ("z".to_string(), P::S(xyz)),
    ];
    for (k, t) in ALL.iter().enumerate() {
        props.insert(1 + k % 3, (format!("attr{k}"), P::S(*t)));
    }
    let rows = (0..n)
        .map(|i| {
            props
                .iter()
                .map(|(name, p)| {
                    let P::S(t) = *p else { unreachable!() };
                    if ["x", "y", "z"].contains(&name.as_str()) {
                        vec![(i * 3 + name.as_bytes()[0] as usize % 3) as f64]
                    } else {
                        vec![samples(t)[i % 3]]
                    }
                })
                .collect()
        })
        .collect();
    El {
        name: "vertex",
        props,
        rows,
    }
}

fn face_el(faces: &[&[u32]], count: ScalarType, item: ScalarType) -> El {
    El {
        name: "face",
        props: vec![("vertex_indices".into(), P::L(count, item))],
        rows: faces
            .iter()
            .map(|f| vec![f.iter().map(|&v| v as f64).collect()])
            .collect(),
    }
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

fn roundtrip(input: &Path, output: &Path) -> Cloud {
    let c = Cloud::read(input, None).unwrap();
    c.write(output, None).unwrap();
    c
}

/// Compares two ascii PLY files value by value (headers must be identical).
fn assert_same_values(a: &[u8], b: &[u8]) {
    let (a, b) = (
        std::str::from_utf8(a).unwrap(),
        std::str::from_utf8(b).unwrap(),
    );
    let split = |s: &str| {
        let i = s.find("end_header").unwrap();
        let j = i + s[i..].find('\n').unwrap() + 1;
        (s[..j].to_string(), s[j..].to_string())
    };
    let ((ha, ba), (hb, bb)) = (split(a), split(b));
    assert_eq!(ha, hb, "headers differ");
    let (la, lb): (Vec<_>, Vec<_>) = (ba.lines().collect(), bb.lines().collect());
    assert_eq!(la.len(), lb.len(), "line counts differ");
    for (n, (x, y)) in la.iter().zip(&lb).enumerate() {
        let tx: Vec<f64> = x.split_whitespace().map(|t| t.parse().unwrap()).collect();
        let ty: Vec<f64> = y.split_whitespace().map(|t| t.parse().unwrap()).collect();
        assert_eq!(tx.len(), ty.len(), "body line {n}: `{x}` vs `{y}`");
        for (u, v) in tx.iter().zip(&ty) {
            assert!(
                u == v || (u.is_nan() && v.is_nan()),
                "body line {n}: `{x}` vs `{y}`"
            );
        }
    }
}

fn dir_is_empty_but(dir: &Path, keep: &[&Path]) -> bool {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .all(|p| keep.contains(&p.as_path()))
}

// ---------------------------------------------------------------------------------------------
// Round trips

#[test]
fn roundtrip_every_encoding_and_scalar_type() {
    let dir = tempfile::tempdir().unwrap();
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        for (k, xyz) in ALL.iter().enumerate() {
            let faces = face_el(&[&[0, 1, 2], &[2, 1, 0, 3]], ALL[k % 6], ALL[(k + 1) % 6]);
            let style = Style {
                alt: k % 2 == 1,
                nl: "\n",
                trailing_space: k % 3 == 0,
            };
            let bytes = ply_bytes(enc, &[vertex_all_types(*xyz, 5), faces], &style, b"");
            let input = write(dir.path(), "in.ply", &bytes);
            let output = dir.path().join("out.ply");
            let c = roundtrip(&input, &output);
            let ctx = format!("{enc:?} xyz {xyz:?}");
            assert_eq!(c.len(), 5, "{ctx}");
            assert_eq!(c.info.schema.fields.len(), 11, "{ctx}");
            assert_eq!(c.info.schema.fields[c.info.schema.xyz[0]].ty, *xyz, "{ctx}");
            assert_eq!(c.positions[4], DVec3::new(12.0, 13.0, 14.0), "{ctx}");
            assert_eq!(c.info.faces, Some(2), "{ctx}");
            assert_eq!(c.faces().unwrap().face(1), &[2, 1, 0, 3], "{ctx}");
            let out = std::fs::read(&output).unwrap();
            if enc == PlyEncoding::Ascii {
                assert_same_values(&bytes, &out);
            } else {
                assert!(out == bytes, "{ctx}: output differs from input");
            }
            // Reading the output gives the same records.
            let again = Cloud::read(&output, None).unwrap();
            assert_eq!(again.records, c.records, "{ctx}");
            assert_eq!(again.positions, c.positions, "{ctx}");
        }
    }
}

#[test]
fn ascii_style_crlf_and_trailing_spaces_is_byte_identical() {
    let dir = tempfile::tempdir().unwrap();
    let v = El {
        name: "vertex",
        props: vec![
            ("x".into(), P::S(ScalarType::F32)),
            ("y".into(), P::S(ScalarType::F32)),
            ("z".into(), P::S(ScalarType::F32)),
            ("confidence".into(), P::S(ScalarType::F32)),
            ("red".into(), P::S(ScalarType::U8)),
        ],
        rows: (0..4)
            .map(|i| {
                vec![
                    vec![-0.0378297 + i as f64],
                    vec![0.12794],
                    vec![0.00447467],
                    vec![0.850855],
                    vec![200.0],
                ]
            })
            .collect(),
    };
    let f = face_el(&[&[0, 1, 2], &[1, 2, 3]], ScalarType::U8, ScalarType::I32);
    for style in [
        Style {
            alt: false,
            nl: "\r\n",
            trailing_space: true,
        },
        Style {
            alt: true,
            nl: "\n",
            trailing_space: false,
        },
    ] {
        let bytes = ply_bytes(
            PlyEncoding::Ascii,
            &[v.clone_el(), f.clone_el()],
            &style,
            b"",
        );
        let input = write(dir.path(), "in.ply", &bytes);
        let output = dir.path().join("out.ply");
        roundtrip(&input, &output);
        assert!(std::fs::read(&output).unwrap() == bytes);
    }
}

trait CloneEl {
    fn clone_el(&self) -> El;
}
impl CloneEl for El {
    fn clone_el(&self) -> El {
        El {
            name: self.name,
            props: self.props.clone(),
            rows: self.rows.clone(),
        }
    }
}

#[test]
fn non_finite_coordinates_are_delivered_and_kept() {
    let dir = tempfile::tempdir().unwrap();
    let mut v = vertex_all_types(ScalarType::F32, 3);
    let z = v.props.iter().position(|p| p.0 == "z").unwrap();
    v.rows[1][0] = vec![f64::NAN];
    v.rows[2][z] = vec![f64::INFINITY];
    for enc in [PlyEncoding::BinaryLittleEndian, PlyEncoding::Ascii] {
        let bytes = ply_bytes(enc, &[v.clone_el()], &PLAIN, b"");
        let input = write(dir.path(), "in.ply", &bytes);
        let output = dir.path().join("out.ply");
        let c = roundtrip(&input, &output);
        assert!(c.positions[1].x.is_nan());
        assert_eq!(c.positions[2].z, f64::INFINITY);
        let out = std::fs::read(&output).unwrap();
        if enc == PlyEncoding::Ascii {
            assert_same_values(&bytes, &out);
        } else {
            assert!(out == bytes);
        }
    }
}

#[test]
fn small_batches_and_early_finish() {
    let dir = tempfile::tempdir().unwrap();
    for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryBigEndian] {
        let faces = face_el(&[&[0, 1, 2], &[3, 4, 5]], ScalarType::U8, ScalarType::U32);
        let bytes = ply_bytes(
            enc,
            &[vertex_all_types(ScalarType::F64, 20), faces],
            &PLAIN,
            b"",
        );
        let input = write(dir.path(), "in.ply", &bytes);
        let whole = Cloud::read(&input, None).unwrap();
        let mut src = io::open(&input, None).unwrap();
        let mut batch = PointBatch::with_capacity(src.info().schema.record_len, 7);
        let mut got = Vec::new();
        let mut records = Vec::new();
        loop {
            let n = src.read_batch(&mut batch, 7).unwrap();
            if n == 0 {
                break;
            }
            assert_eq!(batch.start as usize, got.len());
            got.extend_from_slice(&batch.positions);
            records.extend_from_slice(&batch.records);
        }
        assert_eq!(got, whole.positions);
        assert_eq!(records, whole.records);
        let extras = src.finish().unwrap();
        assert_eq!(extras.faces.unwrap().len(), 2);

        // Finishing after a partial read still yields the faces.
        let mut src = io::open(&input, None).unwrap();
        src.read_batch(&mut batch, 3).unwrap();
        let extras = src.finish().unwrap();
        assert_eq!(
            extras.faces.unwrap(),
            Faces {
                offsets: vec![0, 3, 6],
                indices: vec![0, 1, 2, 3, 4, 5]
            }
        );
    }
}

#[test]
fn moving_positions_changes_only_xyz_bytes() {
    let dir = tempfile::tempdir().unwrap();
    for enc in [
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        for xyz in [ScalarType::F32, ScalarType::F64, ScalarType::I32] {
            let faces = face_el(&[&[0, 1, 2]], ScalarType::U8, ScalarType::I32);
            let bytes = ply_bytes(enc, &[vertex_all_types(xyz, 6), faces], &PLAIN, b"");
            let input = write(dir.path(), "in.ply", &bytes);
            let output = dir.path().join("moved.ply");
            let mut c = Cloud::read(&input, None).unwrap();
            for p in &mut c.positions {
                *p += DVec3::new(100.0, -50.0, 7.0);
            }
            c.write(&output, None).unwrap();
            let out = std::fs::read(&output).unwrap();
            assert_eq!(out.len(), bytes.len());
            let s = &c.info.schema;
            let hdr = bytes
                .windows(11)
                .position(|w| w == b"end_header\n")
                .unwrap()
                + 11;
            let xyz_bytes = |i: usize| {
                if i < hdr || i >= hdr + 6 * s.record_len {
                    return false;
                }
                let off = (i - hdr) % s.record_len;
                s.xyz.iter().any(|&f| {
                    let f = &s.fields[f];
                    (f.offset..f.offset + f.ty.size()).contains(&off)
                })
            };
            let mut changed = 0;
            for (i, (a, b)) in bytes.iter().zip(&out).enumerate() {
                if a != b {
                    assert!(
                        xyz_bytes(i),
                        "{enc:?} {xyz:?}: byte {i} outside x/y/z changed"
                    );
                    changed += 1;
                }
            }
            assert!(changed >= 6, "{enc:?} {xyz:?}: positions did not move");
            let again = Cloud::read(&output, None).unwrap();
            assert_eq!(again.positions, c.positions);
        }
    }

    // Ascii: only the x, y and z tokens change.
    let bytes = ply_bytes(
        PlyEncoding::Ascii,
        &[vertex_all_types(ScalarType::F32, 4)],
        &PLAIN,
        b"",
    );
    let input = write(dir.path(), "in.ply", &bytes);
    let output = dir.path().join("moved.ply");
    let mut c = Cloud::read(&input, None).unwrap();
    c.positions[2].y = 0.25;
    c.write(&output, None).unwrap();
    let (a, b) = (
        String::from_utf8(bytes).unwrap(),
        String::from_utf8(std::fs::read(&output).unwrap()).unwrap(),
    );
    let names: Vec<&str> = c
        .info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect();
    let y = names.iter().position(|n| *n == "y").unwrap();
    let body = |s: &str| -> Vec<Vec<String>> {
        s.split("end_header\n")
            .nth(1)
            .unwrap()
            .lines()
            .map(|l| l.split_whitespace().map(String::from).collect())
            .collect()
    };
    let (ra, rb) = (body(&a), body(&b));
    for (i, (la, lb)) in ra.iter().zip(&rb).enumerate() {
        for (k, (ta, tb)) in la.iter().zip(lb).enumerate() {
            if i == 2 && k == y {
                assert_eq!(tb, "0.25");
            } else {
                assert_eq!(ta.parse::<f64>().unwrap(), tb.parse::<f64>().unwrap());
            }
        }
    }
}

fn extra_elements(enc: PlyEncoding) -> Vec<u8> {
    let camera = El {
        name: "camera",
        props: vec![
            ("view_px".into(), P::S(ScalarType::F32)),
            ("id".into(), P::S(ScalarType::U16)),
            ("tags".into(), P::L(ScalarType::U8, ScalarType::I16)),
        ],
        rows: vec![
            vec![vec![1.5], vec![7.0], vec![-1.0, 2.0]],
            vec![vec![2.5], vec![9.0], vec![]],
        ],
    };
    let grid = El {
        name: "range_grid",
        props: vec![(
            "vertex_indices".into(),
            P::L(ScalarType::U8, ScalarType::I32),
        )],
        rows: (0..8)
            .map(|i| {
                vec![if i % 3 == 0 {
                    vec![]
                } else {
                    vec![i as f64 % 4.0]
                }]
            })
            .collect(),
    };
    let face = El {
        name: "face",
        props: vec![
            (
                "vertex_indices".into(),
                P::L(ScalarType::U8, ScalarType::U32),
            ),
            ("flags".into(), P::S(ScalarType::U8)),
            ("texcoord".into(), P::L(ScalarType::U8, ScalarType::F32)),
        ],
        rows: vec![
            vec![vec![0.0, 1.0, 2.0], vec![3.0], vec![0.5, 0.25]],
            vec![vec![3.0, 2.0, 1.0], vec![0.0], vec![]],
        ],
    };
    ply_bytes(
        enc,
        &[camera, vertex_all_types(ScalarType::F32, 4), face, grid],
        &PLAIN,
        b"\n% trailing garbage kept verbatim\n",
    )
}

#[test]
fn extra_elements_before_and_after_vertex_survive_byte_identically() {
    let dir = tempfile::tempdir().unwrap();
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        let bytes = extra_elements(enc);
        let input = write(dir.path(), "in.ply", &bytes);
        let output = dir.path().join("out.ply");
        let c = roundtrip(&input, &output);
        let out = std::fs::read(&output).unwrap();
        if enc == PlyEncoding::Ascii {
            // Header, `camera` lines and everything after the vertices: identical bytes; vertex
            // lines: identical values (the generator prints some floats in long form).
            let lines = |b: &[u8]| -> Vec<String> {
                String::from_utf8(b.to_vec())
                    .unwrap()
                    .split_inclusive('\n')
                    .map(String::from)
                    .collect()
            };
            let (la, lb) = (lines(&bytes), lines(&out));
            assert_eq!(la.len(), lb.len());
            let first_vertex = la.iter().position(|l| l == "end_header\n").unwrap() + 3;
            for (i, (a, b)) in la.iter().zip(&lb).enumerate() {
                if (first_vertex..first_vertex + 4).contains(&i) {
                    assert_same_values(
                        format!("end_header\n{a}").as_bytes(),
                        format!("end_header\n{b}").as_bytes(),
                    );
                } else {
                    assert_eq!(a, b, "line {i}");
                }
            }
        } else {
            assert!(out == bytes, "{enc:?}");
        }
        assert_eq!(
            c.faces().unwrap(),
            &Faces::from_triangles(&[[0, 1, 2], [3, 2, 1]])
        );
        let Meta::Ply(meta) = &c.info.meta else {
            panic!("PLY meta expected")
        };
        assert_eq!(meta.encoding(), enc);
        let names: Vec<&str> = meta.elements().iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, ["camera", "vertex", "face", "range_grid"]);
        assert!(!meta.pre_vertex_bytes().is_empty());
        assert_eq!(meta.comments(), ["made by the tests", "a late comment"]);
        assert_eq!(meta.obj_info(), ["some info"]);
        assert!(matches!(
            meta.elements()[0].properties[2].ty,
            PlyType::List { .. }
        ));
        let Trailer::Ply(t) = &c.extras.trailer else {
            panic!("PLY trailer expected")
        };
        assert_eq!(t.elements().len(), 2);
        assert_eq!(t.trailing_bytes(), b"\n% trailing garbage kept verbatim\n");
        if enc == PlyEncoding::Ascii {
            assert_eq!(
                t.element_bytes(0).unwrap(),
                b"3 0 1 2 3 2 0.5 0.25\n3 3 2 1 0 0\n"
            );
        }

        // Moving the points keeps everything else; a changed face set is rejected because the face
        // element carries other properties.
        let mut moved = c.clone();
        moved.positions[0].x = 42.0;
        moved.write(&output, None).unwrap();
        let again = Cloud::read(&output, None).unwrap();
        assert_eq!(again.positions[0].x, 42.0);
        assert_eq!(again.faces(), c.faces());
        moved.extras.faces = Some(Faces::from_triangles(&[[0, 1, 3], [3, 2, 1]]));
        let e = moved.write(&dir.path().join("bad.ply"), None).unwrap_err();
        assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
        assert!(!dir.path().join("bad.ply").exists());
    }
}

#[test]
fn changed_faces_are_written_in_the_declared_types() {
    let dir = tempfile::tempdir().unwrap();
    for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryBigEndian] {
        let faces = face_el(&[&[0, 1, 2], &[1, 2, 3]], ScalarType::U16, ScalarType::U32);
        let bytes = ply_bytes(
            enc,
            &[vertex_all_types(ScalarType::F32, 4), faces],
            &PLAIN,
            b"",
        );
        let input = write(dir.path(), "in.ply", &bytes);
        let output = dir.path().join("out.ply");
        let mut c = Cloud::read(&input, None).unwrap();
        let new = Faces::from_triangles(&[[3, 2, 1], [0, 1, 3], [0, 2, 3]]);
        c.info.faces = Some(3);
        c.extras.faces = Some(new.clone());
        c.write(&output, None).unwrap();
        let again = Cloud::read(&output, None).unwrap();
        assert_eq!(again.faces(), Some(&new));
        assert_eq!(again.info.faces, Some(3));
        // Same face count, different faces: the raw face bytes must not be reused.
        let swapped = Faces::from_triangles(&[[0, 1, 3], [0, 2, 3], [3, 1, 2]]);
        let mut c2 = again.clone();
        c2.extras.faces = Some(swapped.clone());
        let output2 = dir.path().join("out2.ply");
        c2.write(&output2, None).unwrap();
        assert_eq!(Cloud::read(&output2, None).unwrap().faces(), Some(&swapped));
        let Meta::Ply(m) = &again.info.meta else {
            panic!()
        };
        assert_eq!(
            m.elements()[1].properties[0].ty,
            PlyType::List {
                count: ScalarType::U16,
                item: ScalarType::U32
            }
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Cross-format writes

#[test]
fn generated_cloud_with_faces_writes_a_readable_ply() {
    let dir = tempfile::tempdir().unwrap();
    let positions = vec![
        DVec3::new(0.0, 0.0, 0.0),
        DVec3::new(1.0, 0.0, 0.0),
        DVec3::new(0.0, 1.0, 0.5),
        DVec3::new(1.0, 1.0, -0.25),
    ];
    let faces = Faces::from_triangles(&[[0, 1, 2], [1, 3, 2]]);
    for ty in [ScalarType::F32, ScalarType::F64] {
        let c = Cloud::generated(positions.clone(), Some(faces.clone()), ty);
        let output = dir.path().join("gen.ply");
        c.write(&output, None).unwrap();
        let text = std::fs::read(&output).unwrap();
        let head = String::from_utf8_lossy(&text[..200]);
        assert!(head.starts_with("ply\nformat binary_little_endian 1.0\nelement vertex 4\n"));
        assert!(head.contains("element face 2\nproperty list uchar int vertex_indices\n"));
        let back = Cloud::read(&output, None).unwrap();
        assert_eq!(back.positions, positions);
        assert_eq!(back.faces(), Some(&faces));
        assert_eq!(back.info.schema.fields[0].ty, ty);
    }

    // A point cloud: no face element.
    let c = Cloud::generated(positions.clone(), None, ScalarType::F64);
    let output = dir.path().join("pts.ply");
    c.write(&output, None).unwrap();
    let back = Cloud::read(&output, None).unwrap();
    assert_eq!(back.info.faces, None);
    assert_eq!(back.positions, positions);
}

#[test]
fn records_in_another_encoding_are_converted_field_by_field() {
    use qem_denoise::io::{Format, SourceInfo};
    use qem_denoise::points::{Field, Schema};
    let dir = tempfile::tempdir().unwrap();
    // Big-endian, padded records with a 64-bit integer and odd names, as another format may have.
    let schema = Schema::new(
        vec![
            Field {
                name: "gps time".into(),
                ty: ScalarType::U64,
                offset: 0,
            },
            Field {
                name: "x".into(),
                ty: ScalarType::I32,
                offset: 8,
            },
            Field {
                name: "y".into(),
                ty: ScalarType::I32,
                offset: 12,
            },
            Field {
                name: "z".into(),
                ty: ScalarType::F64,
                offset: 16,
            },
            Field {
                name: "2nd".into(),
                ty: ScalarType::U16,
                offset: 24,
            },
        ],
        28,
        Endian::Big,
    )
    .unwrap();
    let info = SourceInfo {
        path: PathBuf::new(),
        format: Format::Obj,
        schema: schema.clone(),
        len: Some(2),
        faces: None,
        meta: Meta::None,
    };
    let mut batch = PointBatch::with_capacity(28, 2);
    for i in 0..2u64 {
        let mut rec = vec![0u8; 28];
        schema.set_f64(&mut rec, 0, 1e12 + i as f64);
        schema.set_f64(&mut rec, 4, 500.0 + i as f64);
        batch.push(DVec3::new(i as f64, 2.0, 3.5), &rec);
    }
    let output = dir.path().join("conv.ply");
    let mut sink: Box<dyn Sink> = Box::new(PlySink::create(&output, &info, 2).unwrap());
    sink.write_batch(&batch).unwrap();
    sink.finish(&Extras::default()).unwrap();
    let back = Cloud::read(&output, None).unwrap();
    let s = &back.info.schema;
    let names: Vec<&str> = s.fields.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["gps_time", "x", "y", "z", "_2nd"]);
    assert_eq!(s.fields[0].ty, ScalarType::F64);
    assert_eq!(s.endian, Endian::Little);
    assert_eq!(back.positions[1], DVec3::new(1.0, 2.0, 3.5));
    assert_eq!(
        s.get_f64(back.records.chunks(s.record_len).nth(1).unwrap(), 0),
        1e12 + 1.0
    );
    assert_eq!(s.get_f64(&back.records[..s.record_len], 4), 500.0);
}

// ---------------------------------------------------------------------------------------------
// Bad input

fn open_err(bytes: &[u8]) -> (IoError, String) {
    let dir = tempfile::tempdir().unwrap();
    let input = write(dir.path(), "broken-input.ply", bytes);
    let e = match Cloud::read(&input, None) {
        Err(e) => e,
        Ok(_) => panic!("reading succeeded"),
    };
    let msg = e.to_string();
    assert!(
        msg.contains("broken-input.ply"),
        "message does not name the file: {msg}"
    );
    assert!(!msg.contains('\n'), "message is not one line: {msg}");
    (e, msg)
}

fn small_mesh(enc: PlyEncoding) -> Vec<u8> {
    let faces = face_el(&[&[0, 1, 2], &[1, 2, 3]], ScalarType::U8, ScalarType::I32);
    ply_bytes(
        enc,
        &[vertex_all_types(ScalarType::F32, 4), faces],
        &PLAIN,
        b"",
    )
}

#[test]
fn error_truncated_binary_file() {
    let bytes = small_mesh(PlyEncoding::BinaryLittleEndian);
    let (e, msg) = open_err(&bytes[..bytes.len() - 3]);
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
    assert!(msg.contains("face"), "{msg}");
}

#[test]
fn error_truncated_ascii_file() {
    let bytes = small_mesh(PlyEncoding::Ascii);
    // Inside the last face line, inside the last vertex line, at the end of a vertex line.
    for cut in [3, 20, 16] {
        let (e, msg) = open_err(&bytes[..bytes.len() - cut]);
        assert!(matches!(e, IoError::Truncated { .. }), "cut {cut}: {msg}");
    }
}

#[test]
fn error_header_claims_more_vertices_than_present() {
    let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 35947\n\
    property float x\nproperty float y\nproperty float z\nend_header\n"
        .to_vec();
    bytes.extend(std::iter::repeat_n(0u8, 1000));
    let (e, msg) = open_err(&bytes);
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
    assert!(
        msg.contains(
            "header declares 35947 vertices (431364 bytes) but only 1000 bytes follow the header"
        ),
        "{msg}"
    );
    // The same lie in ascii is caught at open as well.
    let (e, msg) = open_err(
        b"ply\nformat ascii 1.0\nelement vertex 1000\nproperty float x\nproperty float y\n\
      property float z\nend_header\n1 2 3\n",
    );
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
}

#[test]
fn error_not_a_ply() {
    let (e, msg) = open_err(b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
    assert!(msg.contains("not a PLY"), "{msg}");
    let (e, msg) = open_err(&[0x89, b'P', b'N', b'G', 0, 0, 0, 13, 0xff, 0xfe]);
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
}

#[test]
fn error_empty_file() {
    let (e, msg) = open_err(b"");
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
    assert!(msg.contains("empty"), "{msg}");
}

#[test]
fn error_missing_end_header() {
    let (e, msg) = open_err(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n");
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
}

#[test]
fn error_face_index_out_of_range() {
    for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryBigEndian] {
        let faces = face_el(&[&[0, 1, 2], &[1, 2, 99]], ScalarType::U8, ScalarType::I32);
        let bytes = ply_bytes(
            enc,
            &[vertex_all_types(ScalarType::F32, 4), faces],
            &PLAIN,
            b"",
        );
        let (e, msg) = open_err(&bytes);
        assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
        assert!(
            msg.contains("face 1 references vertex 99 but the file has 4 vertices"),
            "{msg}"
        );
    }
    // Negative index.
    let faces = face_el(&[&[0, 1, 2]], ScalarType::U8, ScalarType::I32);
    let mut bytes = ply_bytes(
        PlyEncoding::Ascii,
        &[vertex_all_types(ScalarType::F32, 4), faces],
        &PLAIN,
        b"",
    );
    let n = bytes.len();
    bytes.splice(n - 6..n, b"0 1 -2\n".iter().copied());
    let (e, msg) = open_err(&bytes);
    assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
    assert!(msg.contains("vertex -2"), "{msg}");
}

#[test]
fn error_missing_z() {
    let (e, msg) = open_err(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
      property float w\nend_header\n1 2 3\n",
    );
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
    assert!(msg.contains("`z`"), "{msg}");
    let (e, msg) =
        open_err(b"ply\nformat ascii 1.0\nelement point 1\nproperty float x\nend_header\n1\n");
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
    assert!(msg.contains("no `vertex` element"), "{msg}");
}

#[test]
fn error_vertex_list_property_is_unsupported() {
    let (e, msg) = open_err(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
      property float z\nproperty list uchar float n\nend_header\n1 2 3 0\n",
    );
    assert!(matches!(e, IoError::Unsupported { .. }), "{msg}");
    assert!(msg.contains("list property `n`"), "{msg}");
}

#[test]
fn error_bad_ascii_number() {
    let (e, msg) = open_err(
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
      property float z\nproperty uchar red\nend_header\n1 2 3 4\n1 2 3 4\n1 2.5.1 3 4\n",
    );
    assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
    assert!(msg.contains("line 11") && msg.contains("`2.5.1`"), "{msg}");
    let (e, msg) = open_err(
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
      property float z\nproperty uchar red\nend_header\n1 2 3 4\n1 2 3 256\n1 2 3 4\n",
    );
    assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
    assert!(msg.contains("line 10") && msg.contains("uchar"), "{msg}");
    let (e, msg) = open_err(
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
      property float z\nproperty uchar red\nend_header\n1 2 3 4\n1 2 3\n10 20 30 40\n",
    );
    assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
    assert!(msg.contains("line 10"), "{msg}");
}

#[test]
fn error_missing_file_names_it() {
    let e = PlySource::open(Path::new("no/such/dir/broken-input.ply"))
        .err()
        .unwrap();
    assert!(matches!(e, IoError::Io { .. }));
    assert!(e.to_string().contains("broken-input.ply"));
}

#[test]
fn failed_writes_leave_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let input = write(
        dir.path(),
        "in.ply",
        &small_mesh(PlyEncoding::BinaryLittleEndian),
    );
    let c = Cloud::read(&input, None).unwrap();
    let out = dir.path().join("out.ply");
    let keep = [input.as_path()];

    // Fewer points than announced.
    let mut sink = io::create(&out, None, &c.info, 5).unwrap();
    let mut batch = PointBatch::with_capacity(c.info.schema.record_len, 4);
    batch.positions.extend_from_slice(&c.positions);
    batch.records.extend_from_slice(&c.records);
    sink.write_batch(&batch).unwrap();
    let e = sink.finish(&c.extras).unwrap_err();
    assert!(
        e.to_string().contains("out.ply") && e.to_string().contains("announces 5"),
        "{e}"
    );
    assert!(dir_is_empty_but(dir.path(), &keep));

    // More points than announced.
    let mut sink = io::create(&out, None, &c.info, 3).unwrap();
    let e = sink.write_batch(&batch).unwrap_err();
    assert!(e.to_string().contains("out.ply"), "{e}");
    drop(sink);
    assert!(dir_is_empty_but(dir.path(), &keep));

    // A face count that disagrees with the header.
    let mut info = c.info.clone();
    info.faces = Some(3);
    let mut sink = io::create(&out, None, &info, 4).unwrap();
    sink.write_batch(&batch).unwrap();
    let e = sink.finish(&c.extras).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("declares 3 faces but 2"), "{e}");
    assert!(dir_is_empty_but(dir.path(), &keep));

    // A face referencing a vertex that was not written.
    let g = Cloud::generated(
        c.positions.clone(),
        Some(Faces::from_triangles(&[[0, 1, 4]])),
        ScalarType::F32,
    );
    let e = g.write(&out, None).unwrap_err();
    assert!(e.to_string().contains("references vertex 4"), "{e}");
    assert!(dir_is_empty_but(dir.path(), &keep));

    // A sink dropped without finish.
    let mut sink = io::create(&out, None, &c.info, 4).unwrap();
    sink.write_batch(&batch).unwrap();
    drop(sink);
    assert!(dir_is_empty_but(dir.path(), &keep));
}

// ---------------------------------------------------------------------------------------------
// Shared data (run with `--include-ignored` from the repository root, `../shared` beside it)

fn shared(rel: &str) -> PathBuf {
    Path::new("../shared").join(rel)
}

fn check_roundtrip_shared(path: &Path) -> Cloud {
    let dir = tempfile::tempdir().unwrap();
    let output = dir.path().join("out.ply");
    let c = roundtrip(path, &output);
    let (a, b) = (
        std::fs::read(path).unwrap(),
        std::fs::read(&output).unwrap(),
    );
    let Meta::Ply(m) = &c.info.meta else { panic!() };
    if m.encoding() == PlyEncoding::Ascii {
        assert_same_values(&a, &b);
        // These files print shortest `%g`-style numbers, so even the bytes come back.
        assert!(a == b, "{}: ascii output differs", path.display());
    } else {
        assert!(a == b, "{}: output differs", path.display());
    }
    c
}

#[test]
#[ignore = "needs ../shared"]
fn shared_bun_zipper() {
    let c = check_roundtrip_shared(&shared("data/meshes/bun_zipper.ply"));
    assert_eq!(c.len(), 35_947);
    assert_eq!(c.info.faces, Some(69_451));
    assert_eq!(c.faces().unwrap().len(), 69_451);
    assert_eq!(c.info.schema.fields.len(), 5);
    assert_eq!(
        c.positions[0],
        DVec3::new(
            -0.0378297f32 as f64,
            0.12794f32 as f64,
            0.00447467f32 as f64
        )
    );
    check_roundtrip_shared(&shared("data/meshes/bun_zipper_res4.ply"));
}

#[test]
#[ignore = "needs ../shared"]
fn shared_bunny_scans() {
    let mut n = 0;
    for entry in std::fs::read_dir(shared("data/scans/bunny")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "ply") {
            let c = check_roundtrip_shared(&path);
            assert!(c.len() > 1000);
            assert_eq!(c.info.faces, None);
            let Trailer::Ply(t) = &c.extras.trailer else {
                panic!()
            };
            assert_eq!(t.elements()[0].name, "range_grid");
            n += 1;
        }
    }
    assert_eq!(n, 10);
}

#[test]
#[ignore = "needs ../shared"]
fn shared_golden_files() {
    let mut n = 0;
    for entry in std::fs::read_dir(shared("golden")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "ply") {
            let c = check_roundtrip_shared(&path);
            assert_eq!(c.len(), 35_947);
            assert_eq!(c.faces().unwrap().len(), 69_451);
            assert_eq!(c.info.schema.fields[0].ty, ScalarType::F64);
            n += 1;
        }
    }
    assert!(n >= 6);
}

#[test]
fn source_trait_objects_report_info() {
    let dir = tempfile::tempdir().unwrap();
    let input = write(
        dir.path(),
        "m.ply",
        &small_mesh(PlyEncoding::BinaryBigEndian),
    );
    let src: Box<dyn Source> = Box::new(PlySource::open(&input).unwrap());
    let info = src.info();
    assert_eq!(info.len, Some(4));
    assert_eq!(info.faces, Some(2));
    assert_eq!(info.schema.endian, Endian::Big);
    assert_eq!(info.path, input);
}
