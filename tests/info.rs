//! `qemd info` on every readable format (issue 51): the binary's JSON and text on small files of
//! known content — format, point count, fields and extra fields, exact bounds, the spacing of a
//! regular grid, classes, LAS scale, offset and CRS — and on every shared file (ignored).

use std::path::{Path, PathBuf};

use las::point::Classification;
use las::{Builder, Transform, Vector, Version, Vlr};
use qem_denoise::io::Cloud;
use serde_json::Value;

use crate::util::{put, qemd, qemd_ok, s};

/// The grid every file holds: 12 × 10 points 0.5 apart at z = 3, from (100, 200); the first six
/// columns are class 2, the others class 6.
const NX: usize = 12;
const NY: usize = 10;

fn grid() -> Vec<([f64; 3], u8)> {
    let mut v = Vec::new();
    for j in 0..NY {
        for i in 0..NX {
            let class = if i < 6 { 2 } else { 6 };
            v.push(([100.0 + 0.5 * i as f64, 200.0 + 0.5 * j as f64, 3.0], class));
        }
    }
    v
}

const MIN: [f64; 3] = [100.0, 200.0, 3.0];
const MAX: [f64; 3] = [105.5, 204.5, 3.0];

/// `qemd info FILE --json`, parsed.
fn info(path: &Path, extra: &[&str]) -> Value {
    let mut args = vec!["info", s(path), "--json"];
    args.extend_from_slice(extra);
    let out = qemd_ok(&args);
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Asserts what every format states of the grid.
fn assert_grid(v: &Value, format: &str, fields: &[&str], extra: &[&str]) {
    assert_eq!(v["format"], format, "{v}");
    assert_eq!(v["points"], (NX * NY) as u64, "{format}");
    assert_eq!(v["non_finite"], 0, "{format}");
    let b = |k: &str| -> Vec<f64> {
        v["bounds"][k]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    assert_eq!(b("min"), MIN, "{format}");
    assert_eq!(b("max"), MAX, "{format}");
    let spacing = v["spacing"]["median"].as_f64().unwrap();
    assert!((spacing - 0.5).abs() < 1e-6, "{format}: spacing {spacing}");
    assert_eq!(
        v["spacing"]["sampled"],
        Value::Null,
        "{format}: every point"
    );
    let names: Vec<&str> = v["fields"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, fields, "{format}");
    let extras: Vec<&str> = v["extra_fields"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert_eq!(extras, extra, "{format}");
}

/// Asserts the class counts of the grid, from `field`.
fn assert_classes(v: &Value, field: &str) {
    let c = &v["classes"];
    assert_eq!(c["field"], field, "{v}");
    assert_eq!(c["counts"]["2"], (6 * NY) as u64);
    assert_eq!(c["counts"]["6"], ((NX - 6) * NY) as u64);
}

/// The grid as text lines `x y z class`.
fn lines(sep: &str) -> String {
    grid()
        .iter()
        .map(|(p, c)| format!("{}{sep}{}{sep}{}{sep}{c}\n", p[0], p[1], p[2]))
        .collect()
}

/// A LAS file of the grid (PDRF 1, scale 0.01, offset 100 200 0) with `vlrs`.
fn las_file(path: &Path, vlrs: Vec<Vlr>, minor: u8) {
    let mut b = Builder::default();
    b.version = Version::new(1, minor);
    b.point_format = las::point::Format::new(1).unwrap();
    let t = |offset| Transform {
        scale: 0.01,
        offset,
    };
    b.transforms = Vector {
        x: t(100.0),
        y: t(200.0),
        z: t(0.0),
    };
    b.generating_software = "qemd info tests".into();
    b.has_wkt_crs = minor >= 4 && vlrs.iter().any(|v| v.record_id == 2112);
    b.vlrs = vlrs;
    let mut w = las::Writer::from_path(path, b.into_header().unwrap()).unwrap();
    for (p, c) in grid() {
        w.write_point(las::Point {
            x: p[0],
            y: p[1],
            z: p[2],
            classification: Classification::new(c).unwrap(),
            gps_time: Some(0.0),
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
}

/// GeoTIFF keys: projected EPSG 26915 in metres, vertical EPSG 5703.
fn geotiff() -> Vlr {
    let words: [u16; 20] = [
        1, 1, 0, 4, 1024, 0, 1, 1, 3072, 0, 1, 26915, 3076, 0, 1, 9001, 4096, 0, 1, 5703,
    ];
    Vlr {
        user_id: "LASF_Projection".into(),
        record_id: 34735,
        description: "GeoKeyDirectoryTag".into(),
        data: words.iter().flat_map(|w| w.to_le_bytes()).collect(),
    }
}

fn wkt() -> Vlr {
    Vlr {
        user_id: "LASF_Projection".into(),
        record_id: 2112,
        description: "OGC WKT".into(),
        data: br#"PROJCS["NAD83 / Texas Central (ftUS)",GEOGCS["NAD83",UNIT["degree",0.0174532925199433]],UNIT["US survey foot",0.304800609601219],AUTHORITY["EPSG","2277"]]"#.to_vec(),
    }
}

fn dir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

const LAS_FIELDS: [&str; 10] = [
    "x",
    "y",
    "z",
    "intensity",
    "return_flags",
    "classification",
    "scan_angle_rank",
    "user_data",
    "point_source_id",
    "gps_time",
];

#[test]
fn issue51_info_las_gives_scale_offset_geotiff_crs_and_classes() {
    let d = dir();
    let f = d.path().join("grid.las");
    las_file(&f, vec![geotiff()], 2);
    let v = info(&f, &[]);
    assert_grid(&v, "las", &LAS_FIELDS, &[]);
    assert_classes(&v, "classification");
    assert_eq!(v["classes"]["names"]["2"], "ground");
    assert_eq!(v["scale"], serde_json::json!([0.01, 0.01, 0.01]));
    assert_eq!(v["offset"], serde_json::json!([100.0, 200.0, 0.0]));
    assert_eq!(v["crs"]["epsg"], 26915);
    assert_eq!(v["crs"]["vertical_epsg"], 5703);
    assert_eq!(v["crs"]["unit"], "metre");
    assert_eq!(v["header"]["version"], "1.2");
    assert_eq!(v["header"]["generating_software"], "qemd info tests");
    // The text form says the same in lines.
    let text = String::from_utf8(qemd_ok(&["info", s(&f)]).stdout).unwrap();
    for want in [
        "LAS 1.2, point format 1",
        "points       120",
        "x 100.00 … 105.50  (5.50)",
        "scale        0.01 0.01 0.01",
        "EPSG:26915+5703",
        "2 ground: 60, 6 building: 60 (classification)",
        "spacing      0.5 ",
    ] {
        assert!(text.contains(want), "`{want}` missing:\n{text}");
    }
}

#[test]
fn issue51_info_laz_and_copc_read_the_wkt_crs() {
    let d = dir();
    let las = d.path().join("grid.las");
    las_file(&las, vec![wkt()], 4);
    let c = Cloud::read(&las, None).unwrap();
    for (name, format) in [("grid.laz", "laz"), ("grid.copc.laz", "copc.laz")] {
        let f = d.path().join(name);
        c.write(&f, None).unwrap();
        let v = info(&f, &[]);
        // LAS 1.4 written like a PDRF 1 source stays PDRF 1.
        assert_eq!(v["format"], format);
        assert_eq!(v["points"], 120);
        assert_eq!(v["bounds"]["min"], serde_json::json!(MIN));
        assert_classes(&v, "classification");
        assert_eq!(v["crs"]["epsg"], 2277, "{name}");
        assert_eq!(v["crs"]["unit"], "us_survey_foot", "{name}");
        assert_eq!(v["header"]["compressed"], true);
        assert_eq!(v["header"]["copc"], format == "copc.laz");
    }
}

#[test]
fn issue51_info_ply_obj_off_meshes_and_clouds() {
    let d = dir();
    let pts = grid();
    let mut ply = format!(
        "ply\nformat ascii 1.0\ncomment made by qemd tests\nelement vertex {}\nproperty double x\n\
         property double y\nproperty double z\nproperty uchar class\nelement face 1\n\
         property list uchar int vertex_indices\nend_header\n",
        pts.len()
    );
    ply += &lines(" ");
    ply += "3 0 1 12\n";
    let f = put(d.path(), "grid.ply", ply);
    let v = info(&f, &[]);
    assert_grid(&v, "ply", &["x", "y", "z", "class"], &["class"]);
    assert_classes(&v, "class");
    assert_eq!(v["faces"], 1);
    assert_eq!(v["header"]["encoding"], "ascii");
    assert_eq!(v["header"]["comments"][0], "made by qemd tests");

    let obj: String = pts
        .iter()
        .map(|(p, _)| format!("v {} {} {}\n", p[0], p[1], p[2]))
        .chain(["f 1 2 13\nf 2 14 13\n".to_string()])
        .collect();
    let f = put(d.path(), "grid.obj", obj);
    let v = info(&f, &[]);
    assert_grid(&v, "obj", &["x", "y", "z"], &[]);
    assert_eq!(v["faces"], 2);

    let off = format!("OFF\n{} 1 0\n", pts.len())
        + &pts
            .iter()
            .map(|(p, _)| format!("{} {} {}\n", p[0], p[1], p[2]))
            .collect::<String>()
        + "3 0 1 12\n";
    let f = put(d.path(), "grid.off", off);
    let v = info(&f, &[]);
    assert_grid(&v, "off", &["x", "y", "z"], &[]);
    assert_eq!(v["faces"], 1);
}

#[test]
fn issue51_info_text_clouds_xyz_and_pts() {
    let d = dir();
    let f = put(
        d.path(),
        "grid.xyz",
        format!("# x y z label\n{}", lines(" ")),
    );
    let v = info(&f, &[]);
    assert_eq!(v["format"], "xyz");
    assert_eq!(v["points"], 120);
    assert_eq!(v["bounds"]["max"], serde_json::json!(MAX));
    assert!((v["spacing"]["median"].as_f64().unwrap() - 0.5).abs() < 1e-9);
    let f = put(d.path(), "grid.pts", format!("120\n{}", lines(",")));
    let v = info(&f, &[]);
    assert_eq!(v["format"], "pts");
    assert_eq!(v["points"], 120);
    assert_eq!(v["bounds"]["min"], serde_json::json!(MIN));
}

#[test]
fn issue51_info_pcd_with_a_label_field() {
    let d = dir();
    let body = lines(" ");
    let pcd = format!(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z label\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n\
         WIDTH 120\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 120\nDATA ascii\n{body}"
    );
    let f = put(d.path(), "grid.pcd", pcd);
    let v = info(&f, &[]);
    assert_grid(&v, "pcd", &["x", "y", "z", "label"], &["label"]);
    assert_classes(&v, "label");
    assert_eq!(v["header"]["data"], "ascii");
}

#[test]
fn issue51_info_kitti_nuscenes_and_raw_layouts() {
    let d = dir();
    let rec = |n: usize| -> Vec<u8> {
        grid()
            .iter()
            .flat_map(|(p, c)| {
                let mut r = vec![p[0] as f32, p[1] as f32, p[2] as f32, f32::from(*c)];
                r.resize(n, 0.5);
                r.into_iter()
                    .flat_map(f32::to_le_bytes)
                    .collect::<Vec<u8>>()
            })
            .collect()
    };
    let f = put(d.path(), "grid.bin", rec(4));
    let v = info(&f, &[]);
    assert_grid(&v, "bin", &["x", "y", "z", "intensity"], &["intensity"]);
    let f = put(d.path(), "grid.pcd.bin", rec(5));
    let v = info(&f, &[]);
    assert_grid(
        &v,
        "pcd.bin",
        &["x", "y", "z", "intensity", "ring"],
        &["intensity", "ring"],
    );
    let f = put(d.path(), "grid.raw", rec(6));
    let v = info(
        &f,
        &["--input-format", "bin", "--bin-fields", "x,y,z,i,ring,t"],
    );
    assert_eq!(v["points"], 120);
    assert_eq!(v["fields"].as_array().unwrap().len(), 6);
}

#[test]
fn issue51_info_e57_names_its_scans() {
    let d = dir();
    let xyz = put(d.path(), "grid.xyz", lines(" "));
    let e57 = d.path().join("grid.e57");
    Cloud::read(&xyz, None).unwrap().write(&e57, None).unwrap();
    let v = info(&e57, &[]);
    assert_eq!(v["format"], "e57");
    assert_eq!(v["points"], 120);
    assert_eq!(v["bounds"]["min"], serde_json::json!(MIN));
    assert_eq!(v["header"]["scans"].as_array().unwrap().len(), 1);
    assert_eq!(v["header"]["scans"][0]["points"], 120);
}

#[test]
fn issue51_info_sniffs_content_and_reads_standard_input() {
    let d = dir();
    let las = d.path().join("grid.las");
    las_file(&las, vec![], 2);
    // No extension: told from the content.
    let bare = d.path().join("grid");
    std::fs::copy(&las, &bare).unwrap();
    assert_eq!(info(&bare, &[])["format"], "las");
    // Standard input.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_qemd"))
        .args(["info", "-", "--json"])
        .stdin(std::fs::File::open(&las).unwrap())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        (v["format"].as_str(), v["points"].as_u64()),
        (Some("las"), Some(120))
    );
    // A file that is not a scan: one line naming it.
    let bad = put(
        d.path(),
        "notes.ply",
        "ply\nformat ascii 1.0\nelement vertex 3\nend_header\n",
    );
    let out = qemd(&["info", s(&bad)]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1));
    assert!(err.contains(s(&bad)) && err.lines().count() == 1, "{err}");
}

fn shared(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data")
        .join(rel)
}

/// Every shared file: `info` reads it whole, its count is the reader's, and the LiDAR tiles name
/// their CRS.
#[test]
#[ignore = "needs ../shared"]
fn issue51_info_on_every_shared_file() {
    for rel in [
        "lidar/4_6_crop.las",
        "lidar/32-1-472-150-76.laz",
        "lidar/lone-star.copc.laz",
        "lidar/sample_c.las",
        "lidar/warsaw_small.las",
        "meshes/bun_zipper.ply",
        "meshes/armadillo_43k.obj",
        "meshes/fandisk.off",
        "scans/cturtle.pcd",
        "scans/terrain_samp11-utm.pcd",
        "scans/kitti_000008.bin",
    ] {
        let f = shared(rel);
        let v = info(&f, &[]);
        let c = Cloud::read(&f, None).unwrap();
        assert_eq!(v["points"], c.len() as u64, "{rel}");
        assert!(v["spacing"]["median"].as_f64().unwrap() > 0.0, "{rel}");
        if rel.starts_with("lidar/") {
            assert!(v["classes"].is_object(), "{rel}: no classes");
        }
        // The tiles that declare a CRS (sample_c.las declares none).
        let epsg = match rel {
            "lidar/4_6_crop.las" => Some(2903u64),
            "lidar/32-1-472-150-76.laz" => Some(25832),
            _ => None,
        };
        if epsg.is_some() {
            assert_eq!(v["crs"]["epsg"].as_u64(), epsg, "{rel}");
        }
        qemd_ok(&["info", s(&f)]);
    }
}
