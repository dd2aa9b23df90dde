//! Issue 47: the LiDAR simulator and its scorer on the real binary.

use crate::util::{qemd, qemd_ok, s};

/// `qemd score --json` of `out` against `truth`, with the input `noisy`.
fn score(
    out: &std::path::Path,
    truth: &std::path::Path,
    noisy: &std::path::Path,
    extra: &[&str],
) -> serde_json::Value {
    let mut args = vec![
        "score",
        s(out),
        "--truth",
        s(truth),
        "--noisy",
        s(noisy),
        "--json",
    ];
    args.extend_from_slice(extra);
    serde_json::from_slice(&qemd_ok(&args).stdout).unwrap()
}

fn row<'a>(v: &'a serde_json::Value, class: &str) -> &'a serde_json::Value {
    v["rows"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["class"] == class)
        .unwrap()
}

#[test]
fn issue47_synth_lidar_then_score() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let o = qemd_ok(&[
        "synth",
        "lidar",
        "--preset",
        "vlp16",
        "--density",
        "0.5",
        "--length",
        "40",
        "--seed",
        "2",
        "-o",
        s(&p("scan.laz")),
        "--clean",
        s(&p("clean.las")),
        "--truth",
        s(&p("truth.ply")),
        "--trajectory-out",
        s(&p("traj.txt")),
        "--json",
    ]);
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let n = summary["returns"].as_u64().unwrap();
    assert!(n > 2000, "{n}");
    // The noisy scan scores 1 against itself, the clean one about 0, and denoising the clean
    // scan with an identity moves nothing.
    let same = score(&p("scan.laz"), &p("truth.ply"), &p("scan.laz"), &[]);
    assert_eq!(same["points"].as_u64(), Some(n));
    assert_eq!(
        same["checked"],
        serde_json::json!(["intensity", "gps_time", "ring"])
    );
    let surfaces = row(&same, "surfaces");
    assert_eq!(surfaces["dist_ratio"].as_f64(), Some(1.0));
    let clean = score(&p("clean.las"), &p("truth.ply"), &p("scan.laz"), &[]);
    assert!(row(&clean, "surfaces")["rms_ratio"].as_f64().unwrap() < 0.02);
    let calm = score(
        &p("clean.las"),
        &p("truth.ply"),
        &p("clean.las"),
        &["--calm"],
    );
    assert_eq!(row(&calm, "all")["moves"]["max"].as_f64(), Some(0.0));
    // The table form, and a file of another scan refused in one line naming it.
    let t = qemd_ok(&["score", s(&p("scan.laz")), "--truth", s(&p("truth.ply"))]);
    assert!(String::from_utf8_lossy(&t.stdout).contains("surfaces"));
    qemd_ok(&[
        "synth",
        "lidar",
        "--preset",
        "vlp16",
        "--density",
        "0.5",
        "--length",
        "40",
        "--seed",
        "3",
        "-o",
        s(&p("other.las")),
    ]);
    let bad = qemd(&["score", s(&p("other.las")), "--truth", s(&p("truth.ply"))]);
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("other.las") && err.trim().lines().count() == 1,
        "{err}"
    );
    // qemd reads the scan; the trajectory is the standing sensor.
    qemd_ok(&["harm", s(&p("scan.laz")), s(&p("scan.laz"))]);
    let traj = std::fs::read_to_string(p("traj.txt")).unwrap();
    assert_eq!(traj.lines().filter(|l| !l.starts_with('#')).count(), 2);
}

#[test]
fn issue47_sweep_formats_in_the_sensor_frame() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    for (name, truth) in [
        ("s.bin", "kt.ply"),
        ("s.pcd.bin", "nt.ply"),
        ("s.pcd", "pt.ply"),
    ] {
        qemd_ok(&[
            "synth",
            "lidar",
            "--preset",
            "nuscenes32",
            "--density",
            "0.1",
            "--length",
            "40",
            "-o",
            s(&p(name)),
            "--truth",
            s(&p(truth)),
            "--trajectory-out",
            s(&p("o.txt")),
        ]);
        let v = score(&p(name), &p(truth), &p(name), &[]);
        assert!(!v["checked"].as_array().unwrap().is_empty(), "{name}: {v}");
        assert_eq!(row(&v, "all")["rms_ratio"].as_f64(), Some(1.0));
        // The sensor sits at the origin of its frame.
        let traj = std::fs::read_to_string(p("o.txt")).unwrap();
        let first = traj.lines().find(|l| !l.starts_with('#')).unwrap();
        assert!(first.ends_with(" 0 0 0"), "{first}");
    }
}

#[test]
fn issue47_harm_pairs_copc_output_by_gps_time() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    qemd_ok(&[
        "synth",
        "lidar",
        "--preset",
        "vlp16",
        "--density",
        "0.3",
        "--length",
        "30",
        "-o",
        s(&p("scan.las")),
    ]);
    qemd_ok(&[
        "denoise",
        s(&p("scan.las")),
        "-o",
        s(&p("out.copc.laz")),
        "-q",
    ]);
    let o = qemd_ok(&["harm", s(&p("scan.las")), s(&p("out.copc.laz")), "--json"]);
    let h: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(h["pairing"]["by"], "attributes", "{h}");
    let all = h["rows"].as_array().unwrap().last().unwrap();
    // The same denoising written as LAS (order kept) measures the same moves.
    qemd_ok(&["denoise", s(&p("scan.las")), "-o", s(&p("out.las")), "-q"]);
    let o = qemd_ok(&["harm", s(&p("scan.las")), s(&p("out.las")), "--json"]);
    let kept: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(kept["pairing"]["by"], "index");
    let kept_all = kept["rows"].as_array().unwrap().last().unwrap();
    assert_eq!(all["relative"], kept_all["relative"], "{all} vs {kept_all}");
    assert!(all["relative"]["max"].as_f64().unwrap() < 1.0);
    // The XYZ output keeps x, y, z only: it pairs by index, unchecked …
    qemd_ok(&["denoise", s(&p("scan.las")), "-o", s(&p("out.xyz")), "-q"]);
    let rows: Vec<String> = std::fs::read_to_string(p("out.xyz"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .collect();
    std::fs::write(p("plain.xyz"), rows.join("\n") + "\n").unwrap();
    let o = qemd_ok(&["harm", s(&p("scan.las")), s(&p("plain.xyz")), "--json"]);
    let plain: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(plain["pairing"]["by"], "unchecked", "{plain}");
    let plain_all = plain["rows"].as_array().unwrap().last().unwrap();
    assert!(
        plain_all["relative"]["max"].as_f64().unwrap() < 1.0,
        "{plain_all}"
    );
    // … and the same points reversed are refused in one line naming the file.
    let reversed: Vec<&str> = rows.iter().rev().map(String::as_str).collect();
    std::fs::write(p("reversed.xyz"), reversed.join("\n") + "\n").unwrap();
    let o = qemd(&["harm", s(&p("scan.las")), s(&p("reversed.xyz"))]);
    assert!(!o.status.success());
    let err = String::from_utf8(o.stderr).unwrap();
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("reversed.xyz") && err.contains("not in the input's order"),
        "{err}"
    );
}
