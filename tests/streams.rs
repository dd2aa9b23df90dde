//! Issue 12: standard input and output, and output paths that are not regular files.
//!
//! Every test runs the real `qemd` binary. A pipe through `qemd denoise - -o -` gives the bytes
//! the path form gives; `-o /dev/null`, `-o /dev/stdout`, a FIFO and a symbolic link are written
//! through and never replaced.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use crate::util::s;
use glam::DVec3;
use qem_denoise::io::Cloud;
use qem_denoise::points::ScalarType;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_qemd")
}

fn qemd(args: &[&str]) -> Output {
    Command::new(bin()).args(args).output().expect("qemd runs")
}

fn ok(o: &Output) {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// Runs qemd with `stdin` piped in; returns its output (stdout captured).
fn qemd_piped(args: &[&str], stdin: &[u8]) -> Output {
    let mut child = Command::new(bin())
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("qemd runs");
    let mut pipe = child.stdin.take().unwrap();
    let data = stdin.to_vec();
    let writer = std::thread::spawn(move || {
        // qemd may fail before reading everything; a broken pipe is its answer then.
        let _ = pipe.write_all(&data);
    });
    let out = child.wait_with_output().unwrap();
    writer.join().unwrap();
    out
}

/// A wavy, noisy height field of `n`×`n` points (deterministic).
fn scan(n: usize) -> Vec<DVec3> {
    let mut v = Vec::with_capacity(n * n);
    let mut h = 0x9e37_79b9_u64;
    for i in 0..n {
        for j in 0..n {
            h ^= h << 13;
            h ^= h >> 7;
            h ^= h << 17;
            let e = (h % 1000) as f64 / 1000.0 - 0.5;
            let (x, y) = (i as f64 * 0.1, j as f64 * 0.1);
            v.push(DVec3::new(
                500_000.0 + x,
                4_000_000.0 + y,
                10.0 + 0.2 * (x * 0.7).sin() + 0.01 * e,
            ));
        }
    }
    v
}

/// Writes the scan as `name` (format from the extension) in `dir`.
fn write_scan(dir: &Path, name: &str) -> PathBuf {
    let p = dir.join(name);
    Cloud::generated(scan(40), None, ScalarType::F64)
        .write(&p, None)
        .unwrap();
    p
}

/// The path form: `qemd denoise input -o out`.
fn by_path(input: &Path, out: &Path) -> Vec<u8> {
    ok(&qemd(&["denoise", s(input), "-o", s(out), "-q"]));
    std::fs::read(out).unwrap()
}

#[test]
fn issue12_stdin_to_stdout_gives_the_path_bytes() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["in.las", "in.ply", "in.pcd", "in.xyz"] {
        let input = write_scan(dir.path(), name);
        let ext = input.extension().unwrap().to_str().unwrap().to_string();
        let expected = by_path(&input, &dir.path().join(format!("out.{ext}")));
        let bytes = std::fs::read(&input).unwrap();
        // No format flag: the input format is sniffed, the output takes the input's format.
        let o = qemd_piped(&["denoise", "-", "-o", "-", "-q"], &bytes);
        ok(&o);
        assert!(
            o.stdout == expected,
            "{name}: stdin → stdout differs from the path form"
        );
        let o = qemd_piped(
            &["denoise", "-", "-o", "-", "--output-format", &ext, "-q"],
            &bytes,
        );
        ok(&o);
        assert!(o.stdout == expected, "{name}: --output-format");
    }
    // The spool is removed: nothing of qemd's is left in the temporary directory given.
    let spool = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(dir.path().join("in.las")).unwrap();
    let o = qemd_piped(
        &[
            "denoise",
            "-",
            "-o",
            "-",
            "-q",
            "--temp-dir",
            s(spool.path()),
        ],
        &bytes,
    );
    ok(&o);
    assert_eq!(std::fs::read_dir(spool.path()).unwrap().count(), 0);
}

#[test]
fn issue12_dev_stdin_from_a_pipe() {
    let dir = tempfile::tempdir().unwrap();
    let input = write_scan(dir.path(), "in.ply");
    let expected = by_path(&input, &dir.path().join("a.ply"));
    let out = dir.path().join("b.ply");
    let o = qemd_piped(
        &["denoise", "/dev/stdin", "-o", s(&out), "-q"],
        &std::fs::read(&input).unwrap(),
    );
    ok(&o);
    assert!(std::fs::read(&out).unwrap() == expected);
}

#[test]
fn issue12_stdin_without_a_signature_needs_the_format() {
    let raw: Vec<u8> = (0..400u32)
        .flat_map(|i| {
            let v = [i as f32 * 0.01, (i % 20) as f32 * 0.1, 1.0, 0.5];
            v.into_iter()
                .flat_map(f32::to_le_bytes)
                .collect::<Vec<u8>>()
        })
        .collect();
    let o = qemd_piped(&["denoise", "-", "-o", "-", "-q"], &raw);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("<stdin>") && err.contains("give the input format"),
        "{err}"
    );
    assert!(o.stdout.is_empty());
    let o = qemd_piped(&["denoise", "-", "-o", "-", "-q"], b"");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("<stdin>: empty input"), "{err}");
    let o = qemd_piped(
        &["denoise", "-", "-o", "-", "--input-format", "kitti", "-q"],
        &raw,
    );
    ok(&o);
    assert_eq!(o.stdout.len(), raw.len(), "a KITTI scan back on stdout");
}

#[test]
fn issue12_dev_null_is_written_not_replaced() {
    use std::os::unix::fs::FileTypeExt;
    let dir = tempfile::tempdir().unwrap();
    let input = write_scan(dir.path(), "in.las");
    ok(&qemd(&["denoise", s(&input), "-o", "/dev/null", "-q"]));
    ok(&qemd(&[
        "denoise",
        s(&input),
        "-o",
        "/dev/null",
        "--format",
        "ply",
        "-q",
    ]));
    let m = std::fs::symlink_metadata("/dev/null").unwrap();
    assert!(
        m.file_type().is_char_device(),
        "/dev/null is still a device"
    );
}

#[test]
fn issue12_dev_stdout_goes_down_the_pipe() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["in.las", "in.ply"] {
        let input = write_scan(dir.path(), name);
        let expected = by_path(&input, &dir.path().join(format!("out-{name}")));
        let before = std::fs::symlink_metadata("/dev/stdout").unwrap();
        let o = qemd(&["denoise", s(&input), "-o", "/dev/stdout", "-q"]);
        ok(&o);
        assert!(o.stdout == expected, "{name}: the bytes arrive on the pipe");
        let after = std::fs::symlink_metadata("/dev/stdout").unwrap();
        assert_eq!(
            before.file_type().is_symlink(),
            after.file_type().is_symlink(),
            "/dev/stdout is not replaced"
        );
        assert!(!after.file_type().is_file());
    }
}

#[test]
fn issue12_fifo_is_written_not_replaced() {
    use std::os::unix::fs::FileTypeExt;
    let dir = tempfile::tempdir().unwrap();
    for name in ["in.las", "in.xyz"] {
        let input = write_scan(dir.path(), name);
        let expected = by_path(&input, &dir.path().join(format!("out-{name}")));
        let fifo = dir.path().join(format!("fifo-{name}"));
        let m = Command::new("mkfifo").arg(&fifo).status().unwrap();
        assert!(m.success());
        let f = fifo.clone();
        let reader = std::thread::spawn(move || std::fs::read(&f).unwrap());
        ok(&qemd(&["denoise", s(&input), "-o", s(&fifo), "-q"]));
        let got = reader.join().unwrap();
        assert!(got == expected, "{name}: the FIFO's reader gets the output");
        let m = std::fs::symlink_metadata(&fifo).unwrap();
        assert!(m.file_type().is_fifo(), "still a FIFO");
    }
    // Nothing but the inputs, outputs and FIFOs (no temporary file) is left.
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "fifo-in.las",
            "fifo-in.xyz",
            "in.las",
            "in.xyz",
            "out-in.las",
            "out-in.xyz"
        ]
    );
}

#[test]
fn issue12_symlink_writes_through_to_its_target() {
    let dir = tempfile::tempdir().unwrap();
    let input = write_scan(dir.path(), "in.ply");
    let expected = by_path(&input, &dir.path().join("direct.ply"));
    let elsewhere = tempfile::tempdir().unwrap();
    let target = elsewhere.path().join("real.ply");
    std::fs::write(&target, b"old").unwrap();
    let link = dir.path().join("link.ply");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    ok(&qemd(&["denoise", s(&input), "-o", s(&link), "-q"]));
    assert!(
        std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink(),
        "the link stays a link"
    );
    assert_eq!(std::fs::read_link(&link).unwrap(), target);
    assert!(
        std::fs::read(&target).unwrap() == expected,
        "its target has the output"
    );
    assert_eq!(
        std::fs::read_dir(elsewhere.path()).unwrap().count(),
        1,
        "no temporary file left next to the target"
    );
    // A dangling link and a directory are refused, one line, nothing written.
    let dangling = dir.path().join("dangling.ply");
    std::os::unix::fs::symlink(elsewhere.path().join("missing.ply"), &dangling).unwrap();
    for (out, needle) in [
        (dangling.clone(), "dangling symbolic link"),
        (elsewhere.path().to_path_buf(), "is a directory"),
    ] {
        let o = qemd(&["denoise", s(&input), "-o", s(&out), "-q"]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
        assert!(err.contains(needle) && err.contains(s(&out)), "{err}");
    }
    assert!(!elsewhere.path().join("missing.ply").exists());
}

#[test]
fn issue12_missing_temp_dir_is_refused_up_front() {
    let dir = tempfile::tempdir().unwrap();
    let input = write_scan(dir.path(), "in.ply");
    let missing = dir.path().join("no-such-dir");
    let out = dir.path().join("out.ply");
    let o = qemd(&[
        "denoise",
        s(&input),
        "-o",
        s(&out),
        "--temp-dir",
        s(&missing),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains(s(&missing)) && err.contains("does not exist"),
        "{err}"
    );
    assert!(!out.exists());
}

/// The issue's shell pipeline on the shared LiDAR files: `cat x.las | qemd denoise - -o - > y`
/// gives the bytes of `qemd denoise x.las -o y.las`.
#[test]
#[ignore = "needs ../shared"]
fn issue12_shell_pipe_of_shared_las() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["sample_c.las", "4_6_crop.las", "32-1-472-150-76.laz"] {
        let input = Path::new("../shared/data/lidar").join(name);
        let ext = input.extension().unwrap().to_str().unwrap();
        let expected = by_path(&input, &dir.path().join(format!("path.{ext}")));
        let piped = dir.path().join(format!("piped.{ext}"));
        let script = format!(
            "cat '{}' | '{}' denoise - -o - -q > '{}'",
            s(&input),
            bin(),
            s(&piped)
        );
        let o = Command::new("sh").arg("-c").arg(&script).output().unwrap();
        ok(&o);
        assert!(
            std::fs::read(&piped).unwrap() == expected,
            "{name}: the pipe gives the path form's bytes"
        );
        let script = format!(
            "cat '{}' | '{}' denoise /dev/stdin -o /dev/stdout --output-format las -q > '{}'",
            s(&input),
            bin(),
            s(&piped)
        );
        let o = Command::new("sh").arg("-c").arg(&script).output().unwrap();
        ok(&o);
        if ext == "las" {
            assert!(
                std::fs::read(&piped).unwrap() == expected,
                "{name}: /dev/stdin"
            );
        }
    }
}

#[test]
fn issue10_format_laz_to_a_stream_is_compressed() {
    // LAZ is a format of its own: `--format laz` towards standard output compresses (it used to
    // write uncompressed LAS, the compression being picked from a file extension there is not).
    let dir = tempfile::tempdir().unwrap();
    let input = write_scan(dir.path(), "in.las");
    let expected = by_path(&input, &dir.path().join("out.laz"));
    let o = qemd(&["denoise", s(&input), "-o", "-", "--format", "laz", "-q"]);
    ok(&o);
    assert!(o.stdout == expected, "stdout differs from out.laz");
    // Bit 7 of the point data record format marks LASzip compression.
    assert_eq!(o.stdout[104] & 0x80, 0x80);
    let o = qemd(&["denoise", s(&input), "-o", "-", "--format", "las", "-q"]);
    ok(&o);
    assert_eq!(o.stdout[104] & 0x80, 0);
}
