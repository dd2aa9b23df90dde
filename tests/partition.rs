//! Issue 11: the partition cut into parts — ranges of input records read side by side, each a
//! task of `qemd worker --phase partition` — writes the bytes of a partition in one part (binary
//! PLY, PCD and KITTI here; LAS and LAZ from ../shared); a format that cannot seek to a record
//! (text, COPC's variable chunks) runs as one part.

use std::path::Path;

use qem_denoise::io::{self, BATCH};
use qem_denoise::points::PointBatch;

use crate::scaleout::{ok, surface};
use crate::util::s;

/// Plans `input` with `flags` into a fresh work directory; returns (points, partition tasks).
fn plan(d: &Path, input: &Path, flags: &[&str]) -> (u64, u64) {
    let work = tempfile::tempdir_in(d).unwrap();
    let mut args = vec!["plan", s(input), "--work", s(work.path()), "--json"];
    args.extend(flags);
    let v: serde_json::Value = serde_json::from_str(&ok(&args)).unwrap();
    (
        v["points"].as_u64().unwrap(),
        v["tasks"]["partition"].as_u64().unwrap(),
    )
}

/// `qemd denoise` of `input` in tiles of `tile` points, in one part and in parts of `part`
/// points; asserts the same bytes and returns the number of parts.
fn parts_change_no_byte(d: &Path, input: &Path, tile: &str, part: u64) -> u64 {
    let ext = input.extension().unwrap().to_string_lossy().into_owned();
    let part = part.to_string();
    // A KITTI record has no room for a flag: outliers go.
    let outliers = if ext == "bin" { "remove" } else { "classify" };
    let flags = ["--tile-points", tile, "--outliers", outliers];
    let run = |name: &str, more: &[&str]| {
        let out = d.join(format!("{name}.{ext}"));
        let mut args = vec!["denoise", s(input), "-o", s(&out), "-q"];
        args.extend(flags);
        args.extend(more);
        ok(&args);
        std::fs::read(out).unwrap()
    };
    let whole = run("whole", &["--part-points", "1000000000"]);
    let cut = run("cut", &["--part-points", &part]);
    assert!(
        whole == cut,
        "{}: parts changed the output",
        input.display()
    );
    let mut with = flags.to_vec();
    with.extend(["--part-points", &part]);
    plan(d, input, &with).1
}

/// Every record and position of `input` read from the start, and read after seeking to
/// record `at` of it: the second must be the tail of the first.
fn seek_reads_the_tail(input: &Path, at: u64) {
    let read = |seek: Option<u64>| {
        let mut src = io::open(input, None).unwrap();
        if let Some(at) = seek {
            assert!(src.seek_point(at).unwrap(), "{}", input.display());
        }
        let rl = src.info().schema.record_len;
        let mut b = PointBatch::with_capacity(rl, BATCH);
        let (mut records, mut positions, mut starts) = (Vec::new(), Vec::new(), Vec::new());
        while src.read_batch(&mut b, 777).unwrap() > 0 {
            starts.push(b.start);
            records.extend_from_slice(&b.records);
            positions.extend_from_slice(&b.positions);
        }
        (rl, records, positions, starts)
    };
    let (rl, all, pos, _) = read(None);
    let (_, tail, tail_pos, starts) = read(Some(at));
    assert_eq!(starts.first().copied(), Some(at), "{}", input.display());
    assert!(tail == all[at as usize * rl..], "{}", input.display());
    assert_eq!(tail_pos, pos[at as usize..], "{}", input.display());
}

#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn issue11_binary_ply_pcd_and_kitti_partitioned_in_parts_write_the_bytes_of_one_part() {
    let d = tempfile::tempdir().unwrap();
    let input = d.path().join("in.ply");
    surface(&input, 30_000);
    seek_reads_the_tail(&input, 12_345);
    assert_eq!(parts_change_no_byte(d.path(), &input, "3000", 4_000), 8);
    // PCD (binary) and KITTI `.bin` have fixed records too.
    for name in ["in.pcd", "in.bin"] {
        let path = d.path().join(name);
        surface(&path, 30_000);
        seek_reads_the_tail(&path, 20_001);
        assert_eq!(parts_change_no_byte(d.path(), &path, "3000", 4_000), 8);
    }
    // Text cannot seek to a record: one part, whatever the flag asks.
    let xyz = d.path().join("in.xyz");
    surface(&xyz, 30_000);
    assert!(!io::open(&xyz, None).unwrap().seek_point(0).unwrap());
    assert_eq!(parts_change_no_byte(d.path(), &xyz, "3000", 4_000), 1);
}

#[test]
#[ignore = "needs ../shared"]
fn issue11_las_and_laz_partitioned_in_parts_write_the_bytes_of_one_part() {
    let d = tempfile::tempdir().unwrap();
    let lidar = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/lidar");
    for name in ["4_6_crop.las", "32-1-472-150-76.laz"] {
        let input = lidar.join(name);
        let (points, _) = plan(d.path(), &input, &["--tile-points", "2000"]);
        seek_reads_the_tail(&input, points / 2 + 1);
        let parts = parts_change_no_byte(d.path(), &input, "2000", points / 3);
        assert!(parts >= 3, "{name}: {parts} parts");
    }
    // COPC has chunks of varying size: one part.
    let copc = lidar.join("lone-star.copc.laz");
    assert!(!io::open(&copc, None).unwrap().seek_point(0).unwrap());
    let (points, parts) = plan(d.path(), &copc, &["--part-points", "10000"]);
    assert!(points > 30_000);
    assert_eq!(parts, 1);
}
