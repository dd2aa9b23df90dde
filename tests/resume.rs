//! Checkpoints: a tiled run in a persistent working directory resumes with only the tiles that
//! have no checkpoint, and writes the same bytes as an uninterrupted run.

use std::path::Path;

use glam::DVec3;
use qem_denoise::io::Cloud;
use qem_denoise::pipeline::{Job, RunOptions, run};
use qem_denoise::points::ScalarType;

fn cloud(path: &Path) {
    let mut x = 0x1234_5678_9abc_def1u64;
    let mut f = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    let pts: Vec<DVec3> = (0..6000)
        .map(|_| {
            let (u, v) = (f() * 20.0, f() * 20.0);
            DVec3::new(u, v, (u * 0.4).cos() + 0.02 * f())
        })
        .collect();
    Cloud::generated(pts, None, ScalarType::F64)
        .write(path, None)
        .unwrap();
}

#[test]
fn interrupted_tiles_are_redone_and_finished_ones_kept() {
    let d = tempfile::tempdir().unwrap();
    let input = d.path().join("in.ply");
    cloud(&input);
    let work = d.path().join("job");
    let opts = RunOptions {
        tile_points: Some(700),
        work_dir: Some(work.clone()),
        ..RunOptions::default()
    };
    let first = run(&Job::new(&input, d.path().join("a.ply")), &opts).unwrap();
    assert!(first.tiles >= 8);
    assert_eq!(first.tiles_resumed, 0);
    let want = std::fs::read(d.path().join("a.ply")).unwrap();

    // Interrupt: some tiles lost their results, one was cut between its result and its outcome.
    std::fs::remove_file(work.join("tile_00001.res")).unwrap();
    std::fs::remove_file(work.join("tile_00003.res")).unwrap();
    std::fs::remove_file(work.join("tile_00005.json")).unwrap();
    let second = run(&Job::new(&input, d.path().join("b.ply")), &opts).unwrap();
    assert_eq!(second.tiles_resumed, first.tiles - 3);
    assert_eq!(std::fs::read(d.path().join("b.ply")).unwrap(), want);
    assert_eq!(second.stats.moved, first.stats.moved);

    // A different plan (other tile size) invalidates every checkpoint.
    let other = RunOptions {
        tile_points: Some(1500),
        ..opts.clone()
    };
    let third = run(&Job::new(&input, d.path().join("c.ply")), &other).unwrap();
    assert_eq!(third.tiles_resumed, 0);
    assert_eq!(std::fs::read(d.path().join("c.ply")).unwrap(), want);
}
