//! Format backends end to end: OBJ, OFF, XYZ/PTS text clouds and KITTI scans.
//!
//! `cargo test --test tests io_formats::` selects them all.
//! Tests marked `#[ignore = "needs ../shared"]` read the real data beside the repository.

use std::path::Path;

use crate::util::{listing, put, rewrite};
use glam::DVec3;
use qem_denoise::io::{self, Cloud, Format, IoError, Meta, Trailer};
use qem_denoise::points::{Faces, PointBatch, ScalarType};

// -----------------------------------------------------------------------------------------
// Helpers.

/// Writes `c` to `out` announcing `count` points and giving only the first `give` of them,
/// and asserts that the write fails and leaves the directory as it was.
fn assert_failed_write_leaves_nothing(c: &Cloud, out: &Path, count: u64, give: usize) {
    let dir = out.parent().unwrap();
    let before = listing(dir);
    let mut sink = io::create(out, None, &c.info, count).unwrap();
    let rl = c.info.schema.record_len;
    let mut b = PointBatch::with_capacity(rl, give);
    for i in 0..give {
        b.push(c.positions[i], &c.records[i * rl..(i + 1) * rl]);
    }
    let res = sink.write_batch(&b).and_then(|()| sink.finish(&c.extras));
    let e = res.expect_err("the write must fail");
    assert!(e.to_string().contains(&out.display().to_string()), "{e}");
    assert!(!out.exists());
    assert_eq!(listing(dir), before, "no temporary file is left");
}

/// The numbers of a line (`v ` prefix skipped), `None` when a token is not a number.
fn numbers(line: &str) -> Option<Vec<f64>> {
    let line = line.strip_prefix("v ").unwrap_or(line);
    line.split_ascii_whitespace()
        .map(|t| t.parse::<f64>().ok())
        .collect()
}

/// Same lines, except number lines that may be spelled differently but hold equal values.
fn assert_same_lines(a: &[u8], b: &[u8], what: &str) {
    let a = String::from_utf8_lossy(a);
    let b = String::from_utf8_lossy(b);
    let la: Vec<&str> = a.lines().collect();
    let lb: Vec<&str> = b.lines().collect();
    assert_eq!(la.len(), lb.len(), "{what}: line count");
    for (k, (x, y)) in la.iter().zip(&lb).enumerate() {
        if x == y {
            continue;
        }
        let (nx, ny) = (numbers(x), numbers(y));
        assert!(
            nx.is_some() && nx == ny && (x.starts_with("v ") == y.starts_with("v ")),
            "{what}: line {} differs: `{x}` vs `{y}`",
            k + 1
        );
    }
}

fn tri_mesh() -> Cloud {
    Cloud::generated(
        vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.5, 0.0, -0.25),
            DVec3::new(0.0, 2.0, 1e-3),
            DVec3::new(1.0, 1.0, 1.0),
        ],
        Some(Faces::from_triangles(&[[0, 1, 2], [1, 3, 2]])),
        ScalarType::F64,
    )
}

fn kitti_bytes(points: &[[f32; 4]]) -> Vec<u8> {
    points
        .iter()
        .flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes()))
        .collect()
}

// -----------------------------------------------------------------------------------------
// OBJ.

const OBJ: &str = "# test mesh\r\nmtllib m.mtl\r\no quad\r\n\
    v 0 0 0 1 0 0\r\nv 1 0 0 0 1 0\r\nv 1 1 0 0 0 1\r\nv 0 1 0 0.5 0.5 0.5\r\n\
    vt 0 0\r\nvt 1 0\r\nvn 0 0 1\r\ng g1\r\nusemtl red\r\ns 1\r\n\
    f 1/1/1 2/2/1 3/1/1\r\nf 1//1 3//1 4//1\r\nf -4 -2 -1\r\nl 1 3\r\np 2\r\n\r\n# end\r\n";

#[test]
fn obj_roundtrip_is_line_identical() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", OBJ);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.format, Format::Obj);
    assert_eq!(c.len(), 4);
    assert_eq!(c.info.len, Some(4));
    assert_eq!(c.info.faces, Some(3));
    let f = c.faces().unwrap();
    assert_eq!(f.face(0), &[0, 1, 2]);
    assert_eq!(f.face(1), &[0, 2, 3]);
    assert_eq!(f.face(2), &[0, 2, 3]);
    let names: Vec<&str> = c
        .info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect();
    assert_eq!(names, ["x", "y", "z", "r", "g", "b"]);
    assert!(c.info.schema.fields.iter().all(|f| f.ty == ScalarType::F64));
    assert_eq!(rewrite(&p, "b.obj"), OBJ.as_bytes());
}

#[test]
fn obj_moved_positions_change_only_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", OBJ);
    let mut c = Cloud::read(&p, None).unwrap();
    for q in &mut c.positions {
        *q += DVec3::new(0.5, -1.0, 0.125);
    }
    let out = dir.path().join("b.obj");
    c.write(&out, None).unwrap();
    let text = std::fs::read_to_string(&out).unwrap();
    let expected = OBJ
        .replace("v 0 0 0 1 0 0", "v 0.5 -1 0.125 1 0 0")
        .replace("v 1 0 0 0 1 0", "v 1.5 -1 0.125 0 1 0")
        .replace("v 1 1 0 0 0 1", "v 1.5 0 0.125 0 0 1")
        .replace("v 0 1 0 0.5 0.5 0.5", "v 0.5 0 0.125 0.5 0.5 0.5");
    assert_eq!(text, expected);
}

#[test]
fn obj_streams_in_small_batches() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", OBJ);
    let whole = Cloud::read(&p, None).unwrap();
    let mut src = io::open(&p, None).unwrap();
    let mut b = PointBatch::default();
    let mut got = Vec::new();
    while src.read_batch(&mut b, 3).unwrap() > 0 {
        assert_eq!(b.start as usize, got.len());
        got.extend_from_slice(&b.positions);
    }
    assert_eq!(got, whole.positions);
    let ex = src.finish().unwrap();
    assert_eq!(ex.faces.unwrap().len(), 3);
    assert!(matches!(ex.trailer, Trailer::Obj(_)));
}

#[test]
fn obj_face_index_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(
        dir.path(),
        "a.obj",
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n",
    );
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    let msg = e.to_string();
    assert!(msg.contains("line 5") && msg.contains("a.obj"), "{msg}");
    let p = put(dir.path(), "b.obj", "v 0 0 0\nf -1 -2 -1\n");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(e.to_string().contains("line 2"), "{e}");
}

#[test]
fn obj_zero_face_index() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("line 4: face index 0"), "{e}");
}

#[test]
fn obj_bad_number() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", "# x\nv 0 0 0\nv 1 0,5 0\n");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("line 3: bad number `0,5`"), "{e}");
}

#[test]
fn obj_empty_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", "");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("empty file"), "{e}");
}

#[test]
fn obj_failed_writes_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", OBJ);
    let c = Cloud::read(&p, None).unwrap();
    assert_failed_write_leaves_nothing(&c, &dir.path().join("o.obj"), 4, 3);
    assert_failed_write_leaves_nothing(&c, &dir.path().join("o.obj"), 3, 4);
}

#[test]
fn obj_non_finite_coordinates_are_delivered() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", "v nan 0 inf\nv 1 -inf 0\n");
    let c = Cloud::read(&p, None).unwrap();
    assert!(c.positions[0].x.is_nan());
    assert_eq!(c.positions[0].z, f64::INFINITY);
    assert_eq!(c.positions[1].y, f64::NEG_INFINITY);
    assert_eq!(rewrite(&p, "b.obj"), b"v NaN 0 inf\nv 1 -inf 0\n");
}

// -----------------------------------------------------------------------------------------
// OFF.

const OFF: &str = "OFF\n# four vertices\n4 3 6\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n\
                   3 0 1 2\n3 0 1 3 0.5 0.5 0.5\n4 1 2 3 0\n";

#[test]
fn off_roundtrip_is_line_identical() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.off", OFF);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.format, Format::Off);
    assert_eq!((c.len(), c.info.faces), (4, Some(3)));
    assert_eq!(c.faces().unwrap().face(2), &[1, 2, 3, 0]);
    assert_eq!(rewrite(&p, "b.off"), OFF.as_bytes());
}

#[test]
fn off_moved_positions_change_only_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let text = "COFF\r\n3 1 0\r\n0 0 0 255 0 0 255\r\n1 0 0 0 255 0 255\r\n0 1 0 0 0 255 255\r\n3 0 1 2 9 9 9\r\n";
    let p = put(dir.path(), "a.off", text);
    let mut c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.schema.fields.len(), 7);
    c.positions[1] = DVec3::new(0.75, 0.1, -3.5);
    let out = dir.path().join("b.off");
    c.write(&out, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&out).unwrap(),
        text.replace("1 0 0 0 255 0 255", "0.75 0.1 -3.5 0 255 0 255")
    );
}

#[test]
fn off_counts_on_the_header_line() {
    let dir = tempfile::tempdir().unwrap();
    let text = "OFF 3 1 3\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    let p = put(dir.path(), "a.off", text);
    assert_eq!(Cloud::read(&p, None).unwrap().len(), 3);
    assert_eq!(rewrite(&p, "b.off"), text.as_bytes());
}

#[test]
fn off_truncated_vertices() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Truncated { .. }), "{e}");
    assert!(e.to_string().contains("4 vertices"), "{e}");
}

#[test]
fn off_truncated_faces() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(
        dir.path(),
        "a.off",
        "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
    );
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Truncated { .. }), "{e}");
    assert!(e.to_string().contains("2 faces"), "{e}");
}

#[test]
fn off_face_index_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(
        dir.path(),
        "a.off",
        "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n",
    );
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("line 6: face index 3"), "{e}");
}

#[test]
fn off_bad_number() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(
        dir.path(),
        "a.off",
        "OFF\n3 1 0\n0 0 0\n1 0 O\n0 1 0\n3 0 1 2\n",
    );
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("line 4: bad number `O`"), "{e}");
}

#[test]
fn off_empty_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.off", "");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Header { .. }), "{e}");
}

#[test]
fn off_failed_writes_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.off", OFF);
    let c = Cloud::read(&p, None).unwrap();
    assert_failed_write_leaves_nothing(&c, &dir.path().join("o.off"), 4, 2);
    // A mesh whose faces do not match the count its header announces.
    let mut g = tri_mesh();
    g.extras.faces = Some(Faces::from_triangles(&[[0, 1, 2]]));
    let out = dir.path().join("g.off");
    assert!(g.write(&out, None).is_err());
    assert!(!out.exists());
    assert_eq!(listing(dir.path()), ["a.off"]);
}

// -----------------------------------------------------------------------------------------
// Text clouds.

#[test]
fn xyz_roundtrip_keeps_comments_names_and_separator() {
    let dir = tempfile::tempdir().unwrap();
    let text =
        "# scanner A\n//X Y Z Intensity R G B\n1.5 2 3 0.25 10 20 30\n-1 -2 -3 0.5 0 0 0\n# done\n";
    let p = put(dir.path(), "a.xyz", text);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.format, Format::Xyz);
    let names: Vec<&str> = c
        .info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect();
    assert_eq!(names, ["x", "y", "z", "intensity", "r", "g", "b"]);
    assert_eq!(rewrite(&p, "b.xyz"), text.as_bytes());

    let text = "1.5,2,3,7\n4,5,6,8\n";
    let p = put(dir.path(), "c.txt", text);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.schema.fields[3].name, "c3");
    assert_eq!(rewrite(&p, "d.txt"), text.as_bytes());
}

#[test]
fn xyz_moved_positions_change_only_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let text = "1, 2, 3, 9\n4, 5, 6, 8\n";
    let p = put(dir.path(), "a.xyz", text);
    let mut c = Cloud::read(&p, None).unwrap();
    c.positions[0] = DVec3::new(0.1, 0.2, 0.3);
    let out = dir.path().join("b.xyz");
    c.write(&out, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&out).unwrap(),
        "0.1, 0.2, 0.3, 9\n4, 5, 6, 8\n"
    );
}

#[test]
fn pts_roundtrip_and_count_line() {
    let dir = tempfile::tempdir().unwrap();
    let text = "3\n1 2 3 -100 255 0 0\n4 5 6 0 0 255 0\n7 8 9 100 0 0 255\n";
    let p = put(dir.path(), "a.pts", text);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.format, Format::Pts);
    assert_eq!(c.info.len, Some(3));
    assert_eq!(rewrite(&p, "b.pts"), text.as_bytes());
    // Writing fewer points writes the actual count.
    let sub = Cloud {
        positions: c.positions[..2].to_vec(),
        records: c.records[..2 * c.info.schema.record_len].to_vec(),
        ..c.clone()
    };
    let out = dir.path().join("c.pts");
    sub.write(&out, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&out).unwrap(),
        "2\n1 2 3 -100 255 0 0\n4 5 6 0 0 255 0\n"
    );
}

#[test]
fn text_non_finite_values_are_delivered() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.xyz", "nan 1 2\n-inf inf 0\nNaN 0 0\n");
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.len(), 3);
    assert!(c.positions[0].x.is_nan() && c.positions[2].x.is_nan());
    assert_eq!(
        c.positions[1],
        DVec3::new(f64::NEG_INFINITY, f64::INFINITY, 0.0)
    );
}

#[test]
fn text_streams_one_batch_at_a_time() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("# header\n");
    for i in 0..1000 {
        text.push_str(&format!("{i} {} {}\n", i * 2, i * 3));
    }
    let p = put(dir.path(), "a.xyz", &text);
    let mut src = io::open(&p, None).unwrap();
    assert_eq!(src.info().len, None);
    let mut b = PointBatch::default();
    let mut n = 0;
    while src.read_batch(&mut b, 64).unwrap() > 0 {
        assert!(b.len() <= 64);
        assert_eq!(b.start, n);
        assert_eq!(b.positions[0].x, n as f64);
        n += b.len() as u64;
    }
    assert_eq!(n, 1000);
    src.finish().unwrap();
}

#[test]
fn xyz_bad_number() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.xyz", "# h\n1 2 3\n4 5 6\n7 8 9..\n");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Invalid { .. }), "{e}");
    assert!(e.to_string().contains("line 4: bad number `9..`"), "{e}");
}

#[test]
fn pts_truncated() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.pts", "5\n1 2 3\n4 5 6\n");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Truncated { .. }), "{e}");
    assert!(e.to_string().contains("declares 5 points"), "{e}");
}

#[test]
fn text_empty_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.xyz", "");
    assert!(
        Cloud::read(&p, None)
            .unwrap_err()
            .to_string()
            .contains("empty file")
    );
    let p = put(dir.path(), "a.pts", "");
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Header { .. }), "{e}");
}

#[test]
fn text_failed_writes_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.pts", "2\n1 2 3\n4 5 6\n");
    let c = Cloud::read(&p, None).unwrap();
    assert_failed_write_leaves_nothing(&c, &dir.path().join("o.pts"), 3, 2);
    assert_failed_write_leaves_nothing(&c, &dir.path().join("o.xyz"), 1, 2);
}

// -----------------------------------------------------------------------------------------
// KITTI.

#[test]
fn kitti_roundtrip_is_byte_identical() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = kitti_bytes(&[
        [1.0, 2.0, 3.0, 0.5],
        [-4.25, 0.1, f32::NAN, 0.0],
        [1e-30, 3.3e30, -0.0, 1.0],
    ]);
    let p = put(dir.path(), "a.bin", &bytes);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.format, Format::Kitti);
    assert_eq!(c.info.len, Some(3));
    assert!(c.positions[1].z.is_nan());
    assert_eq!(rewrite(&p, "b.bin"), bytes);
}

#[test]
fn kitti_moved_positions_change_only_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = kitti_bytes(&[[1.0, 2.0, 3.0, 0.5], [4.0, 5.0, 6.0, 0.75]]);
    let p = put(dir.path(), "a.bin", &bytes);
    let mut c = Cloud::read(&p, None).unwrap();
    c.positions[1] = DVec3::new(-1.0, -2.0, -3.0);
    let out = dir.path().join("b.bin");
    c.write(&out, None).unwrap();
    assert_eq!(
        std::fs::read(&out).unwrap(),
        kitti_bytes(&[[1.0, 2.0, 3.0, 0.5], [-1.0, -2.0, -3.0, 0.75]])
    );
}

#[test]
fn kitti_size_not_multiple_of_16() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.bin", vec![0u8; 275810]);
    let e = Cloud::read(&p, None).unwrap_err();
    assert!(matches!(e, IoError::Truncated { .. }), "{e}");
    assert!(
        e.to_string()
            .contains("file size 275810 is not a multiple of the 16-byte record"),
        "{e}"
    );
}

#[test]
fn kitti_empty_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.bin", b"");
    assert!(Cloud::read(&p, None).is_err());
}

#[test]
fn kitti_failed_writes_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.bin", kitti_bytes(&[[1.0, 2.0, 3.0, 0.5]; 3]));
    let c = Cloud::read(&p, None).unwrap();
    assert_failed_write_leaves_nothing(&c, &dir.path().join("o.bin"), 5, 3);
}

// -----------------------------------------------------------------------------------------
// Across formats.

#[test]
fn generated_mesh_to_obj_and_off() {
    let dir = tempfile::tempdir().unwrap();
    let g = tri_mesh();
    let obj = dir.path().join("g.obj");
    g.write(&obj, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&obj).unwrap(),
        "v 0 0 0\nv 1.5 0 -0.25\nv 0 2 0.001\nv 1 1 1\nf 1 2 3\nf 2 4 3\n"
    );
    let off = dir.path().join("g.off");
    g.write(&off, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&off).unwrap(),
        "OFF\n4 2 0\n0 0 0\n1.5 0 -0.25\n0 2 0.001\n1 1 1\n3 0 1 2\n3 1 3 2\n"
    );
    for p in [obj, off] {
        let c = Cloud::read(&p, None).unwrap();
        assert_eq!(c.positions, g.positions);
        assert_eq!(c.faces(), g.faces());
    }
}

#[test]
fn obj_to_off_and_back_keeps_the_mesh() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "a.obj", OBJ);
    let c = Cloud::read(&p, None).unwrap();
    let off = dir.path().join("b.off");
    c.write(&off, None).unwrap();
    let d = Cloud::read(&off, None).unwrap();
    assert_eq!(d.positions, c.positions);
    assert_eq!(d.faces(), c.faces());
    assert!(matches!(d.info.meta, Meta::Off(_)));
    let obj = dir.path().join("c.obj");
    d.write(&obj, None).unwrap();
    let e = Cloud::read(&obj, None).unwrap();
    assert_eq!(e.positions, c.positions);
    assert_eq!(e.faces(), c.faces());
}

#[test]
fn kitti_to_xyz_and_pts_and_back() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = kitti_bytes(&[[0.1, -2.5, 3.3, 0.29], [10.7, 0.0, -1.0e-3, 1.0]]);
    let p = put(dir.path(), "a.bin", &bytes);
    let c = Cloud::read(&p, None).unwrap();
    let xyz = dir.path().join("a.xyz");
    c.write(&xyz, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&xyz).unwrap(),
        "# x y z intensity\n0.1 -2.5 3.3 0.29\n10.7 0 -0.001 1\n"
    );
    let pts = dir.path().join("a.pts");
    c.write(&pts, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&pts).unwrap(),
        "2\n0.1 -2.5 3.3 0.29\n10.7 0 -0.001 1\n"
    );
    // The f32 values survive the text round trip exactly, intensity included (by name).
    let t = Cloud::read(&xyz, None).unwrap();
    assert_eq!(t.info.schema.fields[3].name, "intensity");
    let back = dir.path().join("b.bin");
    t.write(&back, None).unwrap();
    assert_eq!(std::fs::read(&back).unwrap(), bytes);
}

#[test]
fn mesh_to_point_formats_drops_faces() {
    let dir = tempfile::tempdir().unwrap();
    let g = tri_mesh();
    let out = dir.path().join("g.xyz");
    g.write(&out, None).unwrap();
    assert_eq!(
        std::fs::read_to_string(&out).unwrap(),
        "0 0 0\n1.5 0 -0.25\n0 2 0.001\n1 1 1\n"
    );
    let out = dir.path().join("g.bin");
    g.write(&out, None).unwrap();
    assert_eq!(std::fs::read(&out).unwrap().len(), 4 * 16);
}

#[test]
fn format_names_and_extensions() {
    for (ext, f) in [
        ("xyz", Format::Xyz),
        ("TXT", Format::Xyz),
        ("pts", Format::Pts),
        ("bin", Format::Kitti),
    ] {
        assert_eq!(
            Format::from_path(Path::new(&format!("a.{ext}"))).unwrap(),
            f
        );
        assert_eq!(Format::from_name(f.name()), Some(f));
    }
    assert_eq!(Format::from_name("kitti"), Some(Format::Kitti));
}

// -----------------------------------------------------------------------------------------
// Real data beside the repository.

const SHARED: &str = "../shared/data";

/// Vertex and face counts from `../shared/data/MANIFEST.md`.
const MESHES: &[(&str, usize, usize)] = &[
    ("meshes/armadillo_43k.obj", 43_243, 86_482),
    ("meshes/fandisk.off", 7_229, 14_454),
    ("meshes/decimated-knight.off", 502, 1_000),
    ("meshes/screwdriver.off", 3_395, 6_786),
    ("meshes/rocker_arm.off", 800, 1_600),
    ("meshes/pairs/cnr_block_gt.obj", 8_771, 17_550),
    ("meshes/pairs/cnr_block_n1_noisy.obj", 8_771, 17_550),
    ("meshes/pairs/l0_block_0.4_original.obj", 8_771, 17_550),
    ("meshes/pairs/l0_block_0.4_noisy.obj", 8_771, 17_550),
    ("meshes/pairs/l0_fandisk_original.obj", 6_475, 12_946),
    ("meshes/pairs/l0_fandisk_0.3_noisy.obj", 6_475, 12_946),
    ("meshes/pairs/l0_twelve_0.5imp_original.obj", 4_610, 9_216),
    ("meshes/pairs/l0_twelve_0.5imp_noisy.obj", 4_610, 9_216),
    ("meshes/pairs/l0_julius_0.2_original.obj", 36_201, 71_912),
    ("meshes/pairs/l0_julius_0.2_noisy.obj", 36_201, 71_912),
    ("meshes/pairs/gcn_fandisk_gt.obj", 6_475, 12_946),
    ("meshes/pairs/gcn_fandisk_gaus_n6_noisy.obj", 6_475, 12_946),
    ("meshes/pairs/gcn_fertility_gt.obj", 13_971, 27_954),
    (
        "meshes/pairs/gcn_fertility_gaus_n3_noisy.obj",
        13_971,
        27_954,
    ),
];

#[test]
#[ignore = "needs ../shared"]
fn shared_meshes_read_and_write_back() {
    // Every OBJ and OFF file under meshes/ is in the table.
    let mut found = Vec::new();
    for sub in ["meshes", "meshes/pairs"] {
        for e in std::fs::read_dir(Path::new(SHARED).join(sub)).unwrap() {
            let name = e.unwrap().file_name().to_string_lossy().into_owned();
            if name.ends_with(".obj") || name.ends_with(".off") {
                found.push(format!("{sub}/{name}"));
            }
        }
    }
    found.sort();
    let mut listed: Vec<String> = MESHES.iter().map(|m| m.0.to_string()).collect();
    listed.sort();
    assert_eq!(found, listed);

    let dir = tempfile::tempdir().unwrap();
    for &(rel, nv, nf) in MESHES {
        let path = Path::new(SHARED).join(rel);
        let c = Cloud::read(&path, None).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(c.len(), nv, "{rel}");
        assert_eq!(c.info.len, Some(nv as u64), "{rel}");
        assert_eq!(c.info.faces, Some(nf as u64), "{rel}");
        let faces = c.faces().unwrap();
        assert_eq!(faces.len(), nf, "{rel}");
        assert!(faces.min_vertex_count() <= nv, "{rel}");

        let ext = path.extension().unwrap().to_str().unwrap();
        let out = dir.path().join(format!("out.{ext}"));
        c.write(&out, None).unwrap();
        let original = std::fs::read(&path).unwrap();
        let written = std::fs::read(&out).unwrap();
        assert_same_lines(&original, &written, rel);
        let d = Cloud::read(&out, None).unwrap();
        assert_eq!(d.positions, c.positions, "{rel}");
        assert_eq!(d.records, c.records, "{rel}");
        assert_eq!(d.faces(), c.faces(), "{rel}");
    }
    assert_eq!(listing(dir.path()), ["out.obj", "out.off"]);
}

#[test]
#[ignore = "needs ../shared"]
fn shared_obj_with_normals_and_colours_moves_only_coordinates() {
    let path = Path::new(SHARED).join("meshes/pairs/l0_block_0.4_original.obj");
    let mut c = Cloud::read(&path, None).unwrap();
    assert_eq!(c.info.schema.fields.len(), 6, "v x y z r g b");
    for p in &mut c.positions {
        *p *= 2.0;
    }
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("moved.obj");
    c.write(&out, None).unwrap();
    let a = std::fs::read_to_string(&path).unwrap();
    let b = std::fs::read_to_string(&out).unwrap();
    assert!(b.contains("\r\n"), "keeps the CRLF line terminator");
    let (la, lb): (Vec<&str>, Vec<&str>) = (a.lines().collect(), b.lines().collect());
    assert_eq!(la.len(), lb.len());
    let mut moved = 0;
    for (x, y) in la.iter().zip(&lb) {
        if x.starts_with("v ") {
            let (nx, ny) = (numbers(x).unwrap(), numbers(y).unwrap());
            assert_eq!(ny[..3], [nx[0] * 2.0, nx[1] * 2.0, nx[2] * 2.0]);
            assert_eq!(nx[3..], ny[3..], "colour columns are kept");
            moved += 1;
        } else {
            assert_eq!(x, y);
        }
    }
    assert_eq!(moved, 8_771);
}

#[test]
#[ignore = "needs ../shared"]
fn shared_kitti_roundtrips_byte_identically() {
    let path = Path::new(SHARED).join("scans/kitti_000008.bin");
    let original = std::fs::read(&path).unwrap();
    let c = Cloud::read(&path, None).unwrap();
    assert_eq!(c.len(), 17_238);
    assert!(
        c.positions.iter().all(|p| p.x > 0.0),
        "cropped to the camera view"
    );
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("k.bin");
    c.write(&out, None).unwrap();
    assert_eq!(std::fs::read(&out).unwrap(), original);

    // Through text and back: f32 values print in their shortest form and read back exactly.
    let xyz = dir.path().join("k.xyz");
    c.write(&xyz, None).unwrap();
    let t = Cloud::read(&xyz, None).unwrap();
    assert_eq!(t.len(), 17_238);
    let back = dir.path().join("k2.bin");
    t.write(&back, None).unwrap();
    assert_eq!(std::fs::read(&back).unwrap(), original);
}
