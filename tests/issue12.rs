//! Issue 12's smaller fixes, through the real binary: every default in `denoise --help`, the
//! default operator in `qemd table`, the σ line of `qemd noise`.

use std::path::Path;
use std::process::{Command, Output};

fn qemd(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_qemd"))
        .args(args)
        .output()
        .expect("qemd runs")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn ok(args: &[&str]) -> Output {
    let o = qemd(args);
    assert!(
        o.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// The long help of one option: its lines up to the next option.
fn option_help<'a>(help: &'a str, flag: &str) -> String {
    let is_option = |l: &str| {
        let indent = l.len() - l.trim_start().len();
        l.trim_start().starts_with('-') && indent <= 6
    };
    let mut lines = help
        .lines()
        .skip_while(|l| !(is_option(l) && l.trim_start().split([' ', ',']).any(|w| w == flag)));
    let first: &'a str = lines.next().unwrap_or_else(|| panic!("{flag} in the help"));
    let rest: Vec<&str> = lines
        // Option lines are indented by at most 6 spaces, their help text (and the lists of
        // possible values) by more.
        .take_while(|l| !is_option(l))
        .collect();
    format!("{first}\n{}", rest.join("\n"))
}

#[test]
fn issue12_denoise_help_states_every_default() {
    let o = ok(&["denoise", "--help"]);
    let help = String::from_utf8(o.stdout).unwrap();
    for flag in [
        "--method",
        "--planes",
        "--filter",
        "--updates",
        "--mu",
        "--sigma-r",
        "--max-move",
        "--rings",
        "--knn",
        "--normals",
        "--solve",
        "--eps",
        "--lambda",
        "--iterations",
        "--threads",
        "--outliers",
        "--outlier-alpha",
        "--memory-budget",
        "--temp-dir",
        "--tile-points",
        "--bin-fields",
    ] {
        let text = option_help(&help, flag).to_lowercase();
        assert!(
            text.contains("default"),
            "{flag} states no default:\n{text}"
        );
    }
    assert!(option_help(&help, "--iterations").contains("1 on clouds"));
    assert!(option_help(&help, "--normals").contains("[default: area]"));
    assert!(option_help(&help, "--rings").contains("[default: 2]"));
    assert!(option_help(&help, "--eps").contains("[default: 0.01]"));
    assert!(option_help(&help, "--memory-budget").contains("1 GiB"));
    for flag in ["--format", "--input-format"] {
        let text = option_help(&help, flag);
        assert!(
            text.contains("[possible values: ply, obj, off, xyz, txt, pts, pcd, las, laz, kitti, bin, nuscenes]"),
            "{flag} lists its values:\n{text}"
        );
    }
    assert!(option_help(&help, "--format").contains("--output-format"));
}

#[test]
fn issue12_table_includes_the_default_operator() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("sphere.ply");
    ok(&["synth", "sphere", "-o", s(&mesh), "--resolution", "3"]);
    let o = ok(&["table", s(&mesh)]);
    let text = String::from_utf8(o.stdout).unwrap();
    for row in ["| qem |", "| bilateral |", "| default |"] {
        assert!(text.contains(row), "{row} in\n{text}");
    }
    let o = ok(&["table", s(&mesh), "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let names = j.to_string();
    assert!(names.contains("\"default\""), "{names}");
}

#[test]
fn issue12_noise_prints_level_times_l() {
    let dir = tempfile::tempdir().unwrap();
    let clean = dir.path().join("clean.ply");
    ok(&["synth", "cube", "-o", s(&clean), "--resolution", "6"]);
    let o = ok(&[
        "noise",
        s(&clean),
        "-o",
        s(&dir.path().join("noisy.ply")),
        "--level",
        "0.4",
    ]);
    let err = String::from_utf8(o.stderr).unwrap();
    // "… σ = 0.4 × L = <σ> (L = <L>)"
    let after = err
        .split("σ = 0.4 × L = ")
        .nth(1)
        .unwrap_or_else(|| panic!("{err}"));
    let sigma: f64 = after.split_whitespace().next().unwrap().parse().unwrap();
    let l: f64 = after
        .split("(L = ")
        .nth(1)
        .and_then(|r| r.split(')').next())
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        (sigma - 0.4 * l).abs() <= 1e-6 * l,
        "σ {sigma} vs 0.4 × L, L = {l}"
    );
}

#[test]
fn issue12_render_up_and_colour_flags() {
    use glam::DVec3;
    use qem_denoise::io::Cloud;
    use qem_denoise::points::ScalarType;
    let dir = tempfile::tempdir().unwrap();
    let pts: Vec<DVec3> = (0..900)
        .map(|i| DVec3::new((i % 30) as f64, (i / 30) as f64, 0.1 * (i % 7) as f64))
        .collect();
    let las = dir.path().join("ground.las");
    let ply = dir.path().join("ground.ply");
    let cloud = Cloud::generated(pts, None, ScalarType::F64);
    cloud.write(&las, None).unwrap();
    cloud.write(&ply, None).unwrap();
    for colour in ["height", "intensity", "class"] {
        let png = dir.path().join(format!("{colour}.png"));
        ok(&[
            "render",
            s(&las),
            "-o",
            s(&png),
            "--view",
            "top",
            "--colour",
            colour,
            "--size",
            "64x64",
        ]);
        assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
    }
    ok(&[
        "render",
        s(&ply),
        "-o",
        s(&dir.path().join("up.png")),
        "--up",
        "z",
        "--size",
        "64x64",
    ]);
    let out = dir.path().join("none.png");
    let o = qemd(&["render", s(&ply), "-o", s(&out), "--colour", "intensity"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.contains(s(&ply)) && err.contains("intensity"), "{err}");
    assert!(!out.exists());
}

#[test]
#[ignore = "needs ../shared"]
fn issue12_render_shared_las_by_class_from_the_top() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("top.png");
    ok(&[
        "render",
        "../shared/data/lidar/sample_c.las",
        "-o",
        s(&png),
        "--view",
        "top",
        "--colour",
        "class",
        "--size",
        "200x200",
    ]);
    assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
}
