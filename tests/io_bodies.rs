//! Issue 11: a sink that takes its points as bodies — written apart by body sinks
//! (`SinkOptions::body`) and appended in order — writes the bytes it writes from the points,
//! in every format that can (PLY binary and ascii, PCD binary and ascii, XYZ, PTS, KITTI, LAS
//! from a LAS source); the formats that cannot say so (`splittable` false).

use std::path::Path;

use glam::DVec3;
use qem_denoise::io::{
    self, AtomicFile, BATCH, Cloud, Format, Sink, SinkOptions, create_in, create_with,
};
use qem_denoise::points::{FLAG_NOISE, PointBatch, ScalarType};

/// Points on a wavy sheet, some far above it.
fn sheet(n: usize) -> Vec<DVec3> {
    (0..n)
        .map(|i| {
            let (a, b) = ((i % 37) as f64 * 0.27, (i / 37) as f64 * 0.31);
            let up = if i % 11 == 0 { 3.5 } else { 0.0 };
            DVec3::new(a, b, (a * 0.7).sin() + up)
        })
        .collect()
}

/// The batch of `cloud`'s points in `range` (every 5th flagged as noise), positions moved a
/// little so that the sinks write new coordinates.
fn batch(cloud: &Cloud, range: std::ops::Range<usize>) -> PointBatch {
    let rl = cloud.info.schema.record_len;
    let mut b = PointBatch::with_capacity(rl, BATCH);
    b.clear(range.start as u64);
    for i in range {
        b.positions
            .push(cloud.positions[i] + DVec3::splat(0.001 * (i % 7) as f64));
        b.records
            .extend_from_slice(&cloud.records[i * rl..(i + 1) * rl]);
        b.flags.push(if i % 5 == 0 { FLAG_NOISE } else { 0 });
    }
    b
}

/// Writes `cloud` to `out` (format `format`) in one pass, and again as bodies of `cuts`;
/// asserts the same bytes.
fn bodies_write_one_pass(dir: &Path, cloud: &Cloud, format: Format, cuts: &[usize]) {
    let opts = SinkOptions {
        noise_flag: format != Format::Kitti,
        ..SinkOptions::default()
    };
    let n = cloud.positions.len();
    let ext = format.name();
    let whole = dir.join(format!("whole.{ext}"));
    let mut sink = create_with(&whole, Some(format), &cloud.info, n as u64, &opts).unwrap();
    sink.write_batch(&batch(cloud, 0..n)).unwrap();
    sink.finish(&cloud.extras).unwrap();

    let cut = dir.join(format!("cut.{ext}"));
    let mut sink: Box<dyn Sink> =
        create_with(&cut, Some(format), &cloud.info, n as u64, &opts).unwrap();
    assert!(sink.splittable(), "{ext}");
    let body_opts = SinkOptions {
        body: true,
        ..opts.clone()
    };
    let mut at = 0;
    for (k, &end) in cuts.iter().chain([&n]).enumerate() {
        let path = dir.join(format!("body_{k}"));
        let mut body = create_in(
            AtomicFile::create(&path).unwrap(),
            format,
            &cloud.info,
            0,
            &body_opts,
        )
        .unwrap();
        // A body of two batches, to check a body sink's state carries over.
        let mid = at + (end - at) / 2;
        body.write_batch(&batch(cloud, at..mid)).unwrap();
        body.write_batch(&batch(cloud, mid..end)).unwrap();
        let stats = body.finish_body().unwrap();
        assert_eq!(stats.points, (end - at) as u64);
        sink.append_body(&path, &stats).unwrap();
        at = end;
    }
    sink.finish(&cloud.extras).unwrap();
    let (a, b) = (std::fs::read(&whole).unwrap(), std::fs::read(&cut).unwrap());
    assert!(a == b, "{ext}: bodies changed the bytes");
}

#[test]
fn issue11_bodies_appended_in_order_write_the_bytes_of_one_pass() {
    let d = tempfile::tempdir().unwrap();
    let generated = Cloud::generated(sheet(2_000), None, ScalarType::F32);
    // Cuts with an empty body in the middle and at the start.
    let cuts = [0, 700, 700, 1_999];
    for format in [
        Format::Ply,
        Format::Pcd,
        Format::Xyz,
        Format::Pts,
        Format::Kitti,
    ] {
        bodies_write_one_pass(d.path(), &generated, format, &cuts);
    }

    // Sources whose encoding the output keeps: ascii PLY and PCD, a LAS file (its scale and
    // offset known before the first point).
    let mut ply = String::from(
        "ply\nformat ascii 1.0\nelement vertex 500\nproperty float x\nproperty float y\n\
         property float z\nproperty uchar noise\nend_header\n",
    );
    let mut pcd = String::from(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n\
         WIDTH 500\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 500\nDATA ascii\n",
    );
    for p in sheet(500) {
        ply.push_str(&format!("{} {} {} 0\n", p.x, p.y, p.z));
        pcd.push_str(&format!("{} {} {}\n", p.x, p.y, p.z));
    }
    let las = d.path().join("src.las");
    generated.write(&las, None).unwrap();
    for (name, text) in [
        ("src.ply", Some(ply)),
        ("src.pcd", Some(pcd)),
        ("src.las", None),
    ] {
        let path = d.path().join(name);
        if let Some(text) = text {
            std::fs::write(&path, text).unwrap();
        }
        let cloud = Cloud::read(&path, None).unwrap();
        let format = cloud.info.format;
        bodies_write_one_pass(d.path(), &cloud, format, &[1, 250, 333]);
    }
}

#[test]
fn issue11_compressed_outputs_and_a_frame_from_the_first_points_take_no_bodies() {
    let d = tempfile::tempdir().unwrap();
    let generated = Cloud::generated(sheet(100), None, ScalarType::F32);
    let las = d.path().join("src.las");
    generated.write(&las, None).unwrap();
    let from_las = Cloud::read(&las, None).unwrap();
    let opts = SinkOptions::default();
    let splittable = |cloud: &Cloud, name: &str| {
        io::create_with(&d.path().join(name), None, &cloud.info, 100, &opts)
            .unwrap()
            .splittable()
    };
    // LAZ compresses across bodies; a LAS written from another format picks its scale and
    // offset from its first points, which a later body does not see.
    assert!(!splittable(&from_las, "out.laz"));
    assert!(!splittable(&generated, "out.las"));
    assert!(splittable(&from_las, "out.las"));
}
