//! Issue 15, items 1–2 and the k-NN part of "every phase cancellable": a huge coordinate is
//! dropped and counted at read time instead of hanging the run, and a cancel during the k-NN
//! pass ends the run as cancelled. (The work bound of the k-NN itself is tested against the
//! brute-force oracle in `src/neighbours/mod.rs`.)

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use qem_denoise::pipeline::{Job, PipelineError, Progress, Report, RunOptions, run};

/// 300 points on a wavy surface, as text lines.
fn surface_lines() -> Vec<String> {
    let mut x = 0x9e3779b97f4a7c15u64;
    let mut rnd = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..300)
        .map(|_| {
            let (u, v) = (rnd() * 3.0, rnd() * 3.0);
            format!("{u} {v} {}", (u * 2.0).sin() * 0.2 + rnd() * 0.01)
        })
        .collect()
}

fn write(dir: &Path, name: &str, lines: &[String]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, lines.join("\n") + "\n").unwrap();
    p
}

/// Runs `input` → `output` with a watchdog: if the run is not done after `limit`, the watchdog
/// cancels it, so a regression fails the test instead of hanging it.
fn run_watched(input: &Path, output: &Path, tile_points: Option<u64>) -> Result<Report, String> {
    let cancel = Arc::new(AtomicBool::new(false));
    let done = Arc::new(AtomicBool::new(false));
    let watchdog = {
        let (cancel, done) = (cancel.clone(), done.clone());
        std::thread::spawn(move || {
            for _ in 0..600 {
                if done.load(Ordering::Relaxed) {
                    return;
                }
                std::thread::sleep(Duration::from_millis(100));
            }
            cancel.store(true, Ordering::Relaxed);
        })
    };
    let opts = RunOptions {
        tile_points,
        cancel,
        ..RunOptions::default()
    };
    let r = run(&Job::new(input, output), &opts);
    done.store(true, Ordering::Relaxed);
    watchdog.join().unwrap();
    r.map_err(|e| format!("{e}"))
}

/// Issue 15, item 1: one coordinate whose square overflows (10²⁰⁰, or the largest f64) used to
/// make the k-NN and the halo growth loop forever, ignoring SIGINT. It is now dropped at read
/// time, counted, and the other 300 points give exactly the bytes they give alone.
#[test]
fn issue15_huge_coordinate_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let clean = surface_lines();
    let clean_in = write(dir.path(), "clean.xyz", &clean);
    let want_path = dir.path().join("clean_out.xyz");
    run_watched(&clean_in, &want_path, None).unwrap();
    let want = std::fs::read(&want_path).unwrap();
    for (name, extra) in [
        ("e200", vec!["1e200 0 0"]),
        ("max", vec!["1.7976931348623157e308 0 0", "0 -1e13 0"]),
    ] {
        let mut lines = clean.clone();
        for (i, e) in extra.iter().enumerate() {
            lines.insert(100 * i + 17, e.to_string());
        }
        let input = write(dir.path(), &format!("{name}.xyz"), &lines);
        for tile_points in [None, Some(60)] {
            let out = dir.path().join(format!("{name}_{tile_points:?}.xyz"));
            let r = run_watched(&input, &out, tile_points)
                .unwrap_or_else(|e| panic!("{name}, tiles {tile_points:?}: {e}"));
            assert_eq!(r.dropped_non_finite, extra.len() as u64);
            assert_eq!((r.points_in, r.points_out), (300 + extra.len() as u64, 300));
            assert!(
                std::fs::read(&out).unwrap() == want,
                "{name}, tiles {tile_points:?}: differs from the cloud without the huge point"
            );
        }
    }
}

/// Sets the run's cancel flag when a phase of the given name starts.
struct CancelAt {
    phase: &'static str,
    flag: Arc<AtomicBool>,
}

impl Progress for CancelAt {
    fn phase(&self, name: &str, _total: u64) {
        if name == self.phase {
            self.flag.store(true, Ordering::Relaxed);
        }
    }
    fn advance(&self, _done: u64) {}
}

/// A cancel that arrives while the in-memory operator runs (here, before its k-NN pass) ends the
/// run as cancelled, not as a denoiser error, and leaves no output.
#[test]
fn cancel_during_the_knn_pass_ends_the_run_as_cancelled() {
    let dir = tempfile::tempdir().unwrap();
    let input = write(dir.path(), "in.xyz", &surface_lines());
    let ply = dir.path().join("in.ply");
    // A PLY knows its point count, so the run is in memory.
    run_watched(&input, &ply, None).unwrap();
    let out = dir.path().join("out.ply");
    let flag = Arc::new(AtomicBool::new(false));
    let opts = RunOptions {
        progress: Arc::new(CancelAt {
            phase: "denoise",
            flag: flag.clone(),
        }),
        cancel: flag,
        ..RunOptions::default()
    };
    let err = run(&Job::new(&ply, &out), &opts).unwrap_err();
    assert!(matches!(err, PipelineError::Cancelled), "{err}");
    assert!(!out.exists());
}
