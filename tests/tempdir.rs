//! The tiled path's temporary space: checked up front with a clear error, cleaned up on
//! success, on failure and on Ctrl-C, and the input never modified.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use glam::DVec3;
use qem_denoise::io::Cloud;
use qem_denoise::points::ScalarType;

fn qemd() -> Command {
    Command::new(env!("CARGO_BIN_EXE_qemd"))
}

fn cloud(path: &Path, n: usize) {
    let mut x = 0x9e3779b97f4a7c15u64;
    let mut f = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    let pts: Vec<DVec3> = (0..n)
        .map(|_| {
            let (u, v) = (f() * 30.0, f() * 30.0);
            DVec3::new(u, v, (u * 0.3).sin() + 0.01 * f())
        })
        .collect();
    Cloud::generated(pts, None, ScalarType::F32)
        .write(path, None)
        .unwrap();
}

fn entries(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn missing_temp_dir_is_a_clear_error_before_any_output() {
    let d = tempfile::tempdir().unwrap();
    let input = d.path().join("in.ply");
    cloud(&input, 2000);
    let out = qemd()
        .args(["denoise", input.to_str().unwrap(), "-o"])
        .arg(d.path().join("out.ply"))
        .args(["--tile-points", "500", "--temp-dir"])
        .arg(d.path().join("nope"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("nope") && err.contains("temporary directory"),
        "{err}"
    );
    assert_eq!(entries(d.path()), vec!["in.ply"]);
}

#[test]
fn temp_space_is_removed_on_success_and_on_failure() {
    let d = tempfile::tempdir().unwrap();
    let tmp = d.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let input = d.path().join("in.ply");
    cloud(&input, 3000);
    let before = std::fs::read(&input).unwrap();
    let ok = qemd()
        .args(["denoise", input.to_str().unwrap(), "-o"])
        .arg(d.path().join("out.ply"))
        .args(["--tile-points", "400", "-q", "--temp-dir"])
        .arg(&tmp)
        .status()
        .unwrap();
    assert!(ok.success());
    assert!(entries(&tmp).is_empty(), "{:?}", entries(&tmp));
    // Failure after the tiles: the output directory does not exist.
    let fail = qemd()
        .args(["denoise", input.to_str().unwrap(), "-o"])
        .arg(d.path().join("missing/out.ply"))
        .args(["--tile-points", "400", "-q", "--temp-dir"])
        .arg(&tmp)
        .output()
        .unwrap();
    assert_eq!(fail.status.code(), Some(1));
    assert!(entries(&tmp).is_empty(), "{:?}", entries(&tmp));
    assert_eq!(std::fs::read(&input).unwrap(), before, "input unchanged");
}

#[test]
fn ctrl_c_stops_the_run_and_cleans_up() {
    let d = tempfile::tempdir().unwrap();
    let tmp = d.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let input = d.path().join("in.ply");
    cloud(&input, 400_000);
    let output = d.path().join("out.ply");
    let child = qemd()
        .args(["denoise", input.to_str().unwrap(), "-o"])
        .arg(&output)
        .args(["--tile-points", "2000", "-q", "--temp-dir"])
        .arg(&tmp)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the run has spilled something, then interrupt it.
    let start = Instant::now();
    while entries(&tmp).is_empty() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the run never started"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    let killed = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("cancelled"), "{err}");
    assert!(entries(&tmp).is_empty(), "{:?}", entries(&tmp));
    assert!(!output.exists());
    let leftovers: Vec<String> = entries(d.path())
        .into_iter()
        .filter(|n| n != "in.ply" && n != "tmp")
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn issue10_a_killed_runs_temp_space_is_removed_by_the_next_run() {
    let d = tempfile::tempdir().unwrap();
    let tmp = d.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    // A persistent job directory and a foreign directory in the same base are never touched.
    let foreign = ["job", "qemd-tiles-foreign"];
    for name in foreign {
        std::fs::create_dir(tmp.join(name)).unwrap();
        std::fs::write(tmp.join(name).join("plan.json"), b"{}").unwrap();
    }
    let input = d.path().join("in.ply");
    cloud(&input, 400_000);
    let mut child = qemd()
        .args(["denoise", input.to_str().unwrap(), "-o"])
        .arg(d.path().join("killed.ply"))
        .args(["--tile-points", "2000", "-q", "--temp-dir"])
        .arg(&tmp)
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Wait until the run has its directory and has recorded its owner in it (the directory is
    // made first, the `pid` file right after), then kill it outright (no cleanup possible).
    let owned = || {
        entries(&tmp)
            .iter()
            .filter(|n| !foreign.contains(&n.as_str()))
            .any(|n| {
                std::fs::read_to_string(tmp.join(n).join("pid")).is_ok_and(|s| s.ends_with('\n'))
            })
    };
    let start = Instant::now();
    while !owned() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the run never started"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let left: Vec<String> = entries(&tmp)
        .into_iter()
        .filter(|n| !foreign.contains(&n.as_str()))
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
    assert!(left[0].starts_with("qemd-tiles-"), "{left:?}");
    assert!(tmp.join(&left[0]).join("pid").exists());

    // The next tiled run in the same base removes it, and only it.
    let small = d.path().join("small.ply");
    cloud(&small, 3000);
    let ok = qemd()
        .args(["denoise", small.to_str().unwrap(), "-o"])
        .arg(d.path().join("out.ply"))
        .args(["--tile-points", "400", "-q", "--temp-dir"])
        .arg(&tmp)
        .status()
        .unwrap();
    assert!(ok.success());
    assert_eq!(entries(&tmp), foreign.map(String::from).to_vec());
}

/// Issue 51: `kill -9` while the output is written leaves its temporary file
/// (`.out.xyz.XXXXXX.tmp`) beside it; the next successful run towards the same output removes it,
/// and never the file of a writer that is still alive (it holds a lock on it).
#[test]
fn issue51_a_killed_writers_temporary_output_is_removed_by_the_next_run() {
    let d = tempfile::tempdir().unwrap();
    let input = d.path().join("in.ply");
    cloud(&input, 30_000);
    let output = d.path().join("out.xyz");
    // Kill the first run as soon as its temporary output exists.
    let mut child = qemd()
        .args(["denoise", input.to_str().unwrap(), "-o"])
        .arg(&output)
        .arg("-q")
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let start = Instant::now();
    let temp = |d: &Path| {
        entries(d)
            .into_iter()
            .filter(|n| n.starts_with(".out.xyz.") && n.ends_with(".tmp"))
            .collect::<Vec<_>>()
    };
    while temp(d.path()).is_empty() {
        assert!(
            child.try_wait().unwrap().is_none(),
            "finished before it was killed"
        );
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "no temporary output"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let left = temp(d.path());
    assert_eq!(left.len(), 1, "{left:?}");
    // A live writer's file: created and locked by this process.
    let live = d.path().join(".out.xyz.live01.tmp");
    let held = std::fs::File::create(&live).unwrap();
    held.lock().unwrap();
    std::thread::sleep(Duration::from_millis(1100));
    let out = qemd()
        .args(["denoise", input.to_str().unwrap(), "-o"])
        .arg(&output)
        .arg("-q")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        temp(d.path()),
        [".out.xyz.live01.tmp"],
        "the killed run's file is gone"
    );
    drop(held);
}
