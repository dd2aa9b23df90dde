//! Exactness at tile seams: the tiled path writes the same bytes as the in-memory path for any
//! tile size, on random, clustered, sparse and duplicate-heavy clouds, with outliers, for the
//! iterated operator and for the bilateral filter (which needs a global pre-pass).

use std::path::{Path, PathBuf};

use glam::DVec3;
use qem_denoise::denoise::{Method, Params};
use qem_denoise::io::Cloud;
use qem_denoise::pipeline::{Job, OutlierMode, Report, RunOptions, run};
use qem_denoise::points::ScalarType;

struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn g(&mut self) -> f64 {
        let (u, v) = (self.f().max(1e-300), self.f());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// A wavy surface with far outliers.
fn surface(n: usize, seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed | 1);
    let mut v: Vec<DVec3> = (0..n)
        .map(|_| {
            let (x, y) = (r.f() * 10.0, r.f() * 10.0);
            DVec3::new(x, y, (x * 0.8).sin() + 0.02 * r.g())
        })
        .collect();
    for i in (0..n).step_by(97) {
        v[i].z += 5.0 + r.f() * 5.0;
    }
    v
}

/// Gaussian clusters of very different density, plus sparse background points.
fn clustered(n: usize, seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed | 1);
    let centres = [
        (DVec3::new(0.0, 0.0, 0.0), 0.05),
        (DVec3::new(3.0, 1.0, 0.5), 0.5),
        (DVec3::new(-2.0, 4.0, 1.0), 0.2),
    ];
    (0..n)
        .map(|i| {
            if i % 50 == 0 {
                return DVec3::new(r.f(), r.f(), r.f()) * 20.0 - DVec3::splat(10.0);
            }
            let (c, s) = centres[i % 3];
            c + DVec3::new(r.g(), r.g(), r.g() * 0.3) * s
        })
        .collect()
}

/// A lattice where every point appears several times (ties and zero distances everywhere), lying
/// in the plane x = 5 of a box stretched along x by a few points at x = 0 and x = 10. Splitting
/// the long axis cannot separate the plane, so the planner leaves empty tiles beside it, and one
/// stack of 40 copies is more than a small tile holds.
fn duplicates(seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed | 1);
    let mut v = vec![DVec3::new(5.0, 0.75, 0.75); 40];
    for i in 0..20 {
        for j in 0..20 {
            let p = DVec3::new(
                5.0,
                i as f64 * 0.1,
                j as f64 * 0.1 + ((i * j) % 3) as f64 * 0.01,
            );
            for _ in 0..(1 + (r.f() * 4.0) as usize) {
                v.push(p);
            }
        }
    }
    for i in 0..30 {
        let (y, z) = (r.f() * 2.0, r.f() * 2.0);
        v.push(DVec3::new(if i % 2 == 0 { 0.0 } else { 10.0 }, y, z));
    }
    v
}

/// Sparse, volumetric, with a huge spread in spacing.
fn sparse(n: usize, seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed | 1);
    (0..n)
        .map(|i| {
            let s = if i % 10 == 0 { 1000.0 } else { 1.0 };
            DVec3::new(r.f(), r.f(), r.f()) * s
        })
        .collect()
}

fn write(dir: &Path, name: &str, pts: Vec<DVec3>) -> PathBuf {
    let p = dir.join(name);
    Cloud::generated(pts, None, ScalarType::F64)
        .write(&p, None)
        .unwrap();
    p
}

fn denoise(input: &Path, out: &Path, job: &Job, tile_points: Option<u64>) -> (Vec<u8>, Report) {
    let job = Job {
        input: input.to_path_buf(),
        output: out.to_path_buf(),
        ..job.clone()
    };
    let opts = RunOptions {
        tile_points,
        ..RunOptions::default()
    };
    let r = run(&job, &opts).unwrap();
    (std::fs::read(out).unwrap(), r)
}

/// Runs `job` in memory and tiled at every size in `sizes`; asserts identical bytes.
fn assert_seamless(input: &Path, job: &Job, sizes: &[u64]) -> Vec<Report> {
    let dir = input.parent().unwrap();
    let (want, r0) = denoise(input, &dir.join("whole.ply"), job, None);
    assert_eq!(r0.mode, "points");
    let mut reports = Vec::new();
    for &s in sizes {
        let (got, r) = denoise(input, &dir.join(format!("tiled_{s}.ply")), job, Some(s));
        assert_eq!(r.mode, "tiled");
        assert!(
            got == want,
            "{} with tiles of {s} points ({} tiles, {} halo growths) differs from the in-memory output",
            input.display(),
            r.tiles,
            r.halo_growths
        );
        assert_eq!(r.stats.moved, r0.stats.moved);
        assert_eq!(r.stats.duplicates, r0.stats.duplicates);
        assert_eq!(r.outliers_found, r0.outliers_found);
        reports.push(r);
    }
    reports
}

fn job(params: Params) -> Job {
    let mut j = Job::new("", "");
    j.spec.params = params;
    j
}

/// Tile sizes from one tile down to a dozen points per tile (hundreds of tiles). Debug builds
/// (the plain `cargo test`) skip the slowest sizes; CI's release run covers them all.
const SIZES: &[u64] = if cfg!(debug_assertions) {
    &[1_000_000, 700, 30]
} else {
    &[1_000_000, 3000, 700, 90, 12]
};

#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn surface_with_outliers_any_tile_size() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "surface.ply", surface(4000, 1));
    let reports = assert_seamless(&input, &job(Params::default()), SIZES);
    assert!(reports.last().unwrap().tiles > 100);
}

#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn clustered_cloud_with_removed_outliers() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "clusters.ply", clustered(3000, 2));
    let mut j = job(Params {
        knn: Some(10),
        ..Params::default()
    });
    j.spec.outliers = OutlierMode::Remove;
    j.spec.outlier_alpha = 1.0;
    let reports = assert_seamless(&input, &j, SIZES);
    assert!(reports[0].outliers_found > 0);
    assert!(
        reports.iter().any(|r| r.halo_growths > 0),
        "some tile needed a larger halo"
    );
}

#[test]
fn duplicate_heavy_lattice_with_empty_tiles() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "dups.ply", duplicates(3));
    let reports = assert_seamless(&input, &job(Params::default()), SIZES);
    assert!(reports[0].stats.duplicates > 100);
    assert!(
        reports.iter().any(|r| r.empty_tiles > 0),
        "{:?}",
        reports
            .iter()
            .map(|r| (r.tiles, r.empty_tiles))
            .collect::<Vec<_>>()
    );
}

#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn sparse_volume_iterated_operator() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "sparse.ply", sparse(2500, 4));
    assert_seamless(
        &input,
        &job(Params {
            iterations: 2,
            ..Params::default()
        }),
        SIZES,
    );
}

/// The guarded operator's gains read the first update's offsets of the list, one hop past that
/// update: with a single update per cycle that hop is the reach's, not the second update's.
/// (This fails when the reach is far too short, as at 1 hop; a reach one hop short is within the
/// halo's margin and passes.)
#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn guarded_gains_with_one_update_per_cycle() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "one_update.ply", surface(3000, 6));
    assert_seamless(
        &input,
        &job(Params {
            updates: Some(1),
            iterations: 2,
            ..Params::default()
        }),
        SIZES,
    );
}

/// `--radius` caps every list in the input's units, the same in every tile: this surface has
/// about 8 points within 0.25 of each point, so some lists are shorter than 16 and still serve,
/// and the points with fewer than 8 keep their position.
#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn issue9_radius_caps_lists_any_tile_size() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "radius.ply", surface(4000, 8));
    let reports = assert_seamless(
        &input,
        &job(Params {
            radius: Some(0.25),
            ..Params::default()
        }),
        SIZES,
    );
    let s = &reports[0].stats;
    assert!(
        s.isolated > 400 && s.isolated < 3600,
        "isolated {} of 4000",
        s.isolated
    );
    assert!(s.moved > 400, "moved {} of 4000", s.moved);
}

/// The cap of every move at a quarter of the point's own k-NN radius (`guarded::REACH`) reads
/// the point's list as every tile has it: on a plane whose noise is half its spacing (the kind
/// of cloud on which the cap's unit test in `denoise::cloud` finds it holding the largest
/// moves), the tiled bytes are the in-memory bytes.
#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn issue9_reach_cap_any_tile_size() {
    let d = tempfile::tempdir().unwrap();
    let mut r = Rng(99);
    let mut pts = Vec::new();
    for i in 0..60 {
        for j in 0..60 {
            let (dx, dy, dz) = (0.2 * r.g(), 0.2 * r.g(), 0.5 * r.g());
            pts.push(DVec3::new(i as f64 + dx, j as f64 + dy, dz));
        }
    }
    let input = write(d.path(), "reach.ply", pts);
    let reports = assert_seamless(&input, &job(Params::default()), SIZES);
    let s = &reports[0].stats;
    assert!(s.moved > 1000, "moved {} of 3600", s.moved);
    assert!(s.bounded > 20, "bounded {} of 3600", s.bounded);
}

/// `--classes`: points of other classes keep their position in every tile, as in memory, and
/// the tiled bytes are the in-memory bytes.
#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn issue9_classes_hold_the_others_any_tile_size() {
    use std::fmt::Write as _;
    let d = tempfile::tempdir().unwrap();
    let pts = surface(3000, 9);
    // Class 2 on the left half, 5 on the right, 7 for the far points (every 97th).
    let class = |i: usize, p: DVec3| {
        if i.is_multiple_of(97) {
            7
        } else if p.x < 5.0 {
            2
        } else {
            5
        }
    };
    let mut text = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\n\
         property double z\nproperty uchar class\nend_header\n",
        pts.len()
    );
    for (i, p) in pts.iter().enumerate() {
        writeln!(text, "{} {} {} {}", p.x, p.y, p.z, class(i, *p)).unwrap();
    }
    let input = d.path().join("classed.ply");
    std::fs::write(&input, text).unwrap();
    let mut j = job(Params::default());
    j.spec.classes = Some("2,7".parse().unwrap());
    let reports = assert_seamless(&input, &j, SIZES);
    let held = pts
        .iter()
        .enumerate()
        .filter(|(i, p)| class(*i, **p) == 5)
        .count();
    assert_eq!(reports[0].stats.held, held as u64);
    let out = Cloud::read(&d.path().join("whole.ply"), None).unwrap();
    let mut moved = 0;
    for (i, p) in pts.iter().enumerate() {
        if class(i, *p) == 5 {
            assert_eq!(out.positions[i], *p, "held point {i} moved");
        } else {
            moved += (out.positions[i] != *p) as usize;
        }
    }
    assert!(moved > 1000, "{moved} points of classes 2 and 7 moved");
}

/// LAS input without `--classes`: the noise classes 7 and 18 and the withheld points stay, in
/// memory and at every tile size; `--classes 0-255` moves the noise classes (withheld points
/// still stay).
#[test]
fn issue9_las_noise_and_withheld_points_stay_any_tile_size() {
    use std::fmt::Write as _;
    let d = tempfile::tempdir().unwrap();
    let pts = surface(3000, 11);
    // (class, flags): every 53rd point low noise, every 61st high noise, every 89th withheld
    // ground (bit 2 of the LAS 1.4 classification flags), the rest ground.
    let tag = |i: usize| match i {
        _ if i.is_multiple_of(53) => (7u8, 0u8),
        _ if i.is_multiple_of(61) => (18, 0),
        _ if i.is_multiple_of(89) => (2, 0x04),
        _ => (2, 0),
    };
    let mut text = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\n\
         property double z\nproperty uchar classification\nproperty uchar classification_flags\n\
         end_header\n",
        pts.len()
    );
    for (i, p) in pts.iter().enumerate() {
        let (c, f) = tag(i);
        writeln!(text, "{} {} {} {c} {f}", p.x, p.y, p.z).unwrap();
    }
    let ply = d.path().join("tagged.ply");
    std::fs::write(&ply, text).unwrap();
    let input = d.path().join("tagged.las");
    Cloud::read(&ply, None)
        .unwrap()
        .write(&input, None)
        .unwrap();
    // The LAS file rounds coordinates to its scale: compare against what it holds.
    let pts = Cloud::read(&input, None).unwrap().positions;
    let stays = |i: usize, noise_moves: bool| {
        let (c, f) = tag(i);
        f != 0 || (!noise_moves && (c == 7 || c == 18))
    };
    // Two runs per tile size: in a debug build (the README's `cargo test`) one tiled size is
    // enough to hold the rule; the release suite takes every size.
    let sizes: &[u64] = if cfg!(debug_assertions) {
        &[700]
    } else {
        SIZES
    };
    for noise_moves in [false, true] {
        let mut j = job(Params::default());
        if noise_moves {
            j.spec.classes = Some("0-255".parse().unwrap());
        }
        let reports = assert_seamless(&input, &j, sizes);
        let held = (0..pts.len()).filter(|&i| stays(i, noise_moves)).count();
        assert_eq!(
            reports[0].stats.held, held as u64,
            "noise moves: {noise_moves}"
        );
        let out = Cloud::read(&d.path().join("whole.ply"), None).unwrap();
        let mut moved = [0usize; 2];
        for (i, p) in pts.iter().enumerate() {
            if stays(i, noise_moves) {
                assert_eq!(
                    out.positions[i], *p,
                    "point {i} moved (noise moves: {noise_moves})"
                );
            } else {
                moved[(tag(i).0 != 2) as usize] += (out.positions[i] != *p) as usize;
            }
        }
        assert!(moved[0] > 1000, "{moved:?} ground points moved");
        assert_eq!(moved[1] > 0, noise_moves, "{moved:?} noise points moved");
    }
}

#[test]
fn bilateral_with_its_global_pre_pass() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "bilateral.ply", surface(3000, 5));
    assert_seamless(
        &input,
        &job(Params {
            method: Method::Bilateral,
            iterations: 2,
            ..Params::default()
        }),
        if cfg!(debug_assertions) {
            &[150]
        } else {
            &[2000, 150, 20]
        },
    );
}

/// Issue 15: dense clusters, a stack of coincident points and far outliers (up to 10⁶ units
/// away, which used to make the k-NN grid coarse and the k-NN quadratic) are exact at any tile
/// size. The k-NN refines the dense cells into finer grid levels; that must not change a bit.
#[test]
fn far_outliers_and_dense_clusters_any_tile_size() {
    let d = tempfile::tempdir().unwrap();
    let mut pts = surface(2500, 6);
    let mut r = Rng(11);
    for i in 0..1500 {
        let (c, s) = [
            (DVec3::new(3.0, 3.0, 1.5), 0.004),
            (DVec3::new(7.0, 2.0, 0.0), 0.03),
        ][i % 2];
        pts.push(c + DVec3::new(r.g(), r.g(), r.g()) * s);
    }
    pts.extend(std::iter::repeat_n(DVec3::new(5.0, 5.0, 2.0), 40));
    for far in [1e3, 1e6, -3e5] {
        pts.push(DVec3::new(far, 2.0, 1.0));
    }
    let input = write(d.path(), "far.ply", pts);
    assert_seamless(
        &input,
        &job(Params::default()),
        if cfg!(debug_assertions) {
            &[700]
        } else {
            &[1_000_000, 700, 90]
        },
    );
}

/// The cluttered scene of issue 16 (as `benches/clutter.py scene` draws it): three boxes and a
/// sphere with iso noise, five dense Gaussian clusters (15 %), 1 % exact duplicates and 0.2 % far
/// outliers 50–500 units out.
fn cluttered(n: usize, seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed | 1);
    let boxes = [
        (DVec3::new(-4.0, -4.0, 0.0), DVec3::new(0.0, 0.0, 3.0)),
        (DVec3::new(1.0, -3.0, 0.0), DVec3::new(4.0, 1.0, 1.5)),
        (DVec3::new(-3.0, 1.0, 0.0), DVec3::new(-1.0, 4.0, 4.0)),
    ];
    let (n_far, n_dup, n_clu) = ((n / 500).max(1), n / 100, n * 15 / 100);
    let mut v = Vec::with_capacity(n);
    for i in 0..n - n_far - n_dup - n_clu {
        let p = if i % 4 == 0 {
            let u = DVec3::new(r.g(), r.g(), r.g()).normalize_or(DVec3::X);
            DVec3::new(2.5, 2.5, 1.5) + 1.5 * u
        } else {
            let (lo, hi) = boxes[i % 3];
            let mut p = lo + (hi - lo) * DVec3::new(r.f(), r.f(), r.f());
            let a = (r.f() * 3.0) as usize % 3;
            p[a] = if r.f() < 0.5 { lo[a] } else { hi[a] };
            p
        };
        v.push(p + 0.005 * DVec3::new(r.g(), r.g(), r.g()));
    }
    let centres = [
        (DVec3::new(-2.0, -2.0, 3.2), 0.02),
        (DVec3::new(2.5, -1.0, 1.6), 0.05),
        (DVec3::new(-2.0, 2.5, 4.1), 0.01),
        (DVec3::new(0.0, 0.0, 0.5), 0.1),
        (DVec3::new(3.0, 3.0, 3.0), 0.03),
    ];
    for i in 0..n_clu {
        let (c, s) = centres[i % centres.len()];
        v.push(c + s * DVec3::new(r.g(), r.g(), r.g()));
    }
    for _ in 0..n_dup {
        let p = v[(r.f() * v.len() as f64) as usize % v.len()];
        v.push(p);
    }
    for _ in 0..n_far {
        let u = DVec3::new(r.g(), r.g(), r.g()).normalize_or(DVec3::X);
        v.push((50.0 + 450.0 * r.f()) * u);
    }
    // Shuffle (Fisher–Yates) so no file order helps the tiles.
    for i in (1..v.len()).rev() {
        let j = (r.f() * (i + 1) as f64) as usize % (i + 1);
        v.swap(i, j);
    }
    v
}

fn qemd_denoise(input: &Path, out: &Path, report: &Path, budget: &str) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_qemd"))
        .args(["denoise", "-q", "--memory-budget", budget, "--report"])
        .arg(report)
        .arg(input)
        .arg("-o")
        .arg(out)
        .output()
        .unwrap()
}

/// Runs the real binary tiled under `budget` MiB, checks that it succeeded, wrote `want` and
/// stayed within the budget plus the stated constant of 24 MiB (binary, thread stacks, arenas,
/// the sample and the grid), and returns its report.
fn tiled_within(dir: &Path, input: &Path, want: &[u8], budget: u64) -> serde_json::Value {
    let out = dir.join("tiled.ply");
    let report = dir.join("report.json");
    let run = qemd_denoise(input, &out, &report, &format!("{budget}MiB"));
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(r["mode"], "tiled");
    assert!(std::fs::read(&out).unwrap() == want, "tiled output differs");
    let peak = r["peak_rss_bytes"].as_u64().unwrap();
    assert!(
        peak <= (budget + 24) << 20,
        "peak RSS {} MiB over a {budget} MiB budget",
        peak >> 20
    );
    r
}

/// Issue 16: far outliers used to grow every tile's halo to the whole scene (60 doublings on 6
/// tiles, 50× the in-memory time, 4× the budget at 30 M points). Now they are isolated, the
/// occupancy grid proves their balls complete, and a cluttered cloud tiled under a tiny budget
/// keeps the in-memory bytes with few halo growths and a bounded peak RSS (the real binary's,
/// from its report); a budget too small for one tile's first load is refused up front.
#[test]
#[cfg_attr(
    debug_assertions,
    ignore = "release only: 130 tiles of the debug binary take minutes"
)]
fn issue16_cluttered_cloud_tiles_within_a_tiny_budget() {
    let d = tempfile::tempdir().unwrap();
    let n = 200_000;
    let input = write(d.path(), "cluttered.ply", cluttered(n, 16));
    let (want, r0) = denoise(
        &input,
        &d.path().join("whole.ply"),
        &job(Params::default()),
        None,
    );
    assert!(
        r0.stats.isolated >= (n / 500) as u64,
        "{}",
        r0.stats.isolated
    );
    // Every kernel run (first loads and every group of a grown halo) is held to the budget.
    // Measured 54 MiB for this 48 MiB run (83 MiB before the growth was bounded).
    let r = tiled_within(d.path(), &input, &want, 48);
    let tiles = r["tiles"].as_u64().unwrap();
    assert!(tiles >= 3, "{tiles} tiles");
    assert!(
        r["halo_growths"].as_u64().unwrap() > 0,
        "no halo growth: the bound is not exercised"
    );
    // The far outliers do not drive growth (60 doublings on 6 tiles before). The planner narrows
    // the halos next to the dense clusters to the budget (down to 1/64 of the plan's, six
    // doublings back), so those tiles grow: measured 14 on 6 tiles.
    let growths = r["halo_growths"].as_u64().unwrap();
    assert!(
        growths <= 3 * tiles,
        "{growths} halo growths on {tiles} tiles"
    );
    // 8 MiB cannot hold one tile's halo: a one-line refusal naming the file, and no output.
    let small = d.path().join("small.ply");
    let run = qemd_denoise(&input, &small, &d.path().join("small.json"), "8MiB");
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(
        err.contains("cluttered.ply") && err.contains("raise --memory-budget"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(!small.exists());
}

/// A noisy grid plane over [0, 6]² (`side`² points) and a dense Gaussian blob of `blob` points
/// (σ = 0.03) above its middle, shuffled.
fn plane_and_blob(side: usize, blob: usize, seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed | 1);
    let step = 6.0 / (side - 1) as f64;
    let mut v = Vec::with_capacity(side * side + blob);
    for i in 0..side {
        for j in 0..side {
            let p = DVec3::new(i as f64 * step, j as f64 * step, 0.0);
            v.push(p + 0.002 * DVec3::new(r.g(), r.g(), r.g()));
        }
    }
    for _ in 0..blob {
        v.push(DVec3::new(3.0, 3.0, 0.3) + 0.03 * DVec3::new(r.g(), r.g(), r.g()));
    }
    for i in (1..v.len()).rev() {
        let j = (r.f() * (i + 1) as f64) as usize % (i + 1);
        v.swap(i, j);
    }
    v
}

/// Issue 16: beside a blob larger than one run may hold, the points near the blob cannot load
/// their halo; small groups of them load only the fine cells their dependencies reach
/// (`by_cells`), together, and keep the in-memory bytes within the budget. Before, every such
/// group was halved down to single points, each reading the spill files (356 CPU-s on a numpy
/// cloud of the same shape at 40 MiB, 9.7 now); at 64 MiB on a cloud twice the size it was
/// refused, because the occupancy cells (sized for the isolation radius, here about a third of a
/// unit) cannot be loaded in part. Groups whose shell at the round's halo holds the blob try
/// narrower halos, where their k-NN balls already fit.
#[test]
#[cfg_attr(debug_assertions, ignore = "release only: minutes in the debug binary")]
fn issue16_points_beside_a_blob_over_the_budget_load_the_cells_they_depend_on() {
    let d = tempfile::tempdir().unwrap();
    let input = write(d.path(), "blob.ply", plane_and_blob(245, 40_000, 16));
    let (want, _) = denoise(
        &input,
        &d.path().join("whole.ply"),
        &job(Params::default()),
        None,
    );
    let r = tiled_within(d.path(), &input, &want, 40);
    assert!(
        r["cell_runs"].as_u64().unwrap() > 0,
        "no run on the cells of lone points: the path is not exercised"
    );
    // Groups whose shell at the round's halo holds the blob, and whose halves cannot fit
    // either, run at a narrower halo (`load_widest`).
    assert!(
        r["narrower_runs"].as_u64().unwrap() > 0,
        "no group ran at a narrower halo: the path is not exercised"
    );
}

/// Issue 47: a sweep denoised along its beams (`--sensor-origin`) gives the same bytes tiled as
/// in memory: every tile computes its points' beams from their positions and the one origin.
#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn issue47_beams_any_tile_size() {
    let dir = tempfile::tempdir().unwrap();
    let sw = crate::util::Sweep::new(24, 0.5, 0.02, 3);
    let input = write(dir.path(), "sweep.ply", sw.noisy.clone());
    let params = Params {
        sensor_origin: qem_denoise::denoise::SensorOrigin::At(sw.origin.to_array()),
        ..Params::default()
    };
    let reports = assert_seamless(&input, &job(params), SIZES);
    assert!(reports[0].stats.moved > 0);
}
