//! Properties of the denoising operators on synthetic input: determinism across thread counts,
//! equivariance under rigid motions, and preservation of clean sharp features.

use glam::{DMat3, DQuat, DVec3};
use proptest::prelude::*;
use qem_denoise::denoise::{Method, Params, SolveKind, denoise};
use qem_denoise::points::Faces;

/// A small deterministic generator (xorshift) so the fixtures need no RNG crate.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (u, v) = (self.next().max(1e-300), self.next());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// Noisy samples of the unit sphere.
fn noisy_sphere(n: usize, sigma: f64, seed: u64) -> Vec<DVec3> {
    let mut r = Rng(seed.wrapping_mul(0x9e3779b97f4a7c15) | 1);
    (0..n)
        .map(|_| {
            let p = DVec3::new(r.gauss(), r.gauss(), r.gauss()).normalize();
            p + DVec3::new(r.gauss(), r.gauss(), r.gauss()) * sigma
        })
        .collect()
}

/// A noisy height-field mesh over an `n × n` grid.
fn noisy_grid(n: u32, sigma: f64, seed: u64) -> (Vec<DVec3>, Faces) {
    let mut r = Rng(seed.wrapping_mul(0x9e3779b97f4a7c15) | 1);
    let mut pos = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let (x, y) = (i as f64 / n as f64, j as f64 / n as f64);
            let z = 0.2 * (3.0 * x).sin() * (2.0 * y).cos();
            pos.push(DVec3::new(x, y, z) + DVec3::new(r.gauss(), r.gauss(), r.gauss()) * sigma);
        }
    }
    let mut faces = Faces::new();
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = j * n + i;
            faces.push(&[a, a + 1, a + n]);
            faces.push(&[a + 1, a + n + 1, a + n]);
        }
    }
    (pos, faces)
}

fn run_with_threads(
    threads: usize,
    pos: &[DVec3],
    faces: Option<&Faces>,
    params: &Params,
) -> Vec<DVec3> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| denoise(pos, faces, params).unwrap().positions)
}

fn bits(v: &[DVec3]) -> Vec<[u64; 3]> {
    v.iter()
        .map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
        .collect()
}

#[test]
#[cfg_attr(debug_assertions, ignore = "release only: heavy in the debug build")]
fn output_is_identical_for_any_thread_count() {
    let cloud = noisy_sphere(6000, 0.01, 1);
    let (grid, faces) = noisy_grid(60, 0.004, 2);
    let cases: Vec<(Params, bool)> = vec![
        (Params::default(), false),
        (
            Params {
                knn: Some(12),
                iterations: 2,
                ..Params::default()
            },
            false,
        ),
        (
            Params {
                method: Method::Bilateral,
                iterations: 2,
                ..Params::default()
            },
            false,
        ),
        (Params::default(), true),
        (
            Params {
                method: Method::Bilateral,
                iterations: 2,
                ..Params::default()
            },
            true,
        ),
    ];
    for (params, mesh) in cases {
        let (pos, f) = if mesh {
            (&grid[..], Some(&faces))
        } else {
            (&cloud[..], None)
        };
        let one = bits(&run_with_threads(1, pos, f, &params));
        for t in [2, 3, 8] {
            assert_eq!(
                one,
                bits(&run_with_threads(t, pos, f, &params)),
                "{params:?} mesh={mesh} threads={t}"
            );
        }
    }
}

fn rigid(q: DQuat, t: DVec3, v: &[DVec3]) -> Vec<DVec3> {
    v.iter().map(|&p| q * p + t).collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// Denoising a rotated and translated input gives the rotated and translated output.
    #[test]
    fn operator_commutes_with_rigid_motions(
        axis in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
        angle in -3.1f64..3.1,
        t in (-1e3f64..1e3, -1e3f64..1e3, -1e3f64..1e3),
        seed in 0u64..1000,
        mode in 0usize..4,
    ) {
        let axis = DVec3::new(axis.0, axis.1, axis.2);
        prop_assume!(axis.length() > 1e-2);
        let q = DQuat::from_axis_angle(axis.normalize(), angle);
        let t = DVec3::new(t.0, t.1, t.2);
        let (pos, faces) = if mode < 2 {
            (noisy_sphere(1500, 0.01, seed), None)
        } else {
            let (p, f) = noisy_grid(25, 0.005, seed);
            (p, Some(f))
        };
        let params = match mode {
            0 | 2 => Params { solve: SolveKind::Robust, ..Params::default() },
            _ => Params { method: Method::Bilateral, iterations: 2, ..Params::default() },
        };
        let a = denoise(&pos, faces.as_ref(), &params).unwrap().positions;
        let b = denoise(&rigid(q, t, &pos), faces.as_ref(), &params).unwrap().positions;
        let expect = rigid(q, t, &a);
        // Coordinates near 1e3 carry ~1e-13 absolute rounding, and the motion itself adds more;
        // PCA normals and two bilateral passes amplify it to ~1e-11 of the coordinates' size
        // (CI saw 1.03e-8 at |t| = 853). A frame-dependent operator errs by the noise (1e-2).
        let tol = 1e-10 * (1.0 + t.length());
        for (x, y) in b.iter().zip(&expect) {
            prop_assert!((*x - *y).length() < tol, "{} vs {}", x, y);
        }
    }
}

/// The clean corner of a cube sampled as a point cloud, far from the origin and rotated: points
/// whose neighbourhood (within the operator's reach) lies on one face stay exactly on it; points
/// near the edges, whose PCA normals blend two faces, take bounded steps and stay close to the
/// surface. Checked for the paper's operator and for the default.
#[test]
fn clean_corner_cloud_keeps_its_planes() {
    let mut pts = Vec::new();
    let n = 40;
    let h = 1.0 / n as f64;
    for i in 0..n {
        for j in 0..n {
            let (a, b) = (i as f64 * h, j as f64 * h);
            pts.push(DVec3::new(0.0, a + 0.5 * h, b + 0.5 * h));
            pts.push(DVec3::new(a + 0.5 * h, 0.0, b));
            pts.push(DVec3::new(a, b, 0.0));
        }
    }
    let rot = DMat3::from_quat(DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.7, 1.1));
    let off = DVec3::new(500_000.0, 5_000_000.0, 120.0);
    let moved: Vec<DVec3> = pts.iter().map(|&p| rot * p + off).collect();
    // (parameters, interior distance in h, largest step near edges, largest distance off the
    // surface near edges): every normal used within the reach (k-NN radius ≈ 2.3 h per hop) of an
    // interior point is exact.
    let cases = [
        (
            Params {
                knn: Some(16),
                solve: SolveKind::Robust,
                ..Params::paper()
            },
            6.0,
            4.0,
            0.25,
        ),
        (
            Params {
                knn: Some(16),
                ..Params::default()
            },
            18.0,
            4.0,
            0.5,
        ),
    ];
    for (params, interior_at, max_step, max_off) in cases {
        let out = denoise(&moved, None, &params).unwrap();
        let mut interior = 0;
        for (o, p) in out.positions.iter().zip(&pts) {
            let local = rot.transpose() * (*o - off);
            let step = (local - *p).length();
            // Distance of the start point to the second-nearest coordinate plane: to an edge.
            let mut c = [p.x.abs(), p.y.abs(), p.z.abs()];
            c.sort_by(f64::total_cmp);
            if c[1] > interior_at * h {
                interior += 1;
                assert!(
                    step < 1e-8,
                    "{params:?}: interior point {p} moved by {step}"
                );
            } else {
                // Near features the operator snaps points towards the edge or corner (the
                // paper's feature enhancement): bounded steps close to the surface.
                let surface = local.x.abs().min(local.y.abs()).min(local.z.abs());
                assert!(step < max_step * h, "{params:?}: point {p} moved by {step}");
                assert!(
                    surface < max_off * h,
                    "{params:?}: point {p} left the surface by {surface}"
                );
            }
        }
        assert!(interior > pts.len() / 10, "{interior}");
    }
}

/// A vertex displaced off a flat region returns onto the plane. With the paper's operator only
/// vertices whose 2-ring saw the tilted faces move; the default (filtered normals, repeated
/// updates) spreads the bump's remainder: no vertex stays above a quarter of it, and on average
/// the plane is flat to 1 % of it.
#[test]
fn displaced_vertex_on_a_plane_returns_to_it() {
    let (mut pos, faces) = noisy_grid(20, 0.0, 3);
    for p in &mut pos {
        p.z = 0.0;
    }
    let k = 10 * 20 + 10;
    pos[k].z = 0.01;
    let out = denoise(&pos, Some(&faces), &Params::paper()).unwrap();
    // The displaced vertex's own tilted plane pulls a little; every other plane in its 2-ring is
    // z = 0 exactly, so the result lies much closer to the plane than it started.
    assert!(
        out.positions[k].z.abs() < 0.01 * 0.2,
        "{}",
        out.positions[k].z
    );
    for (i, p) in out.positions.iter().enumerate() {
        if (p - pos[i]).length() > 0.0 {
            // Only vertices whose ring saw the tilted faces may move.
            assert!((pos[i] - pos[k]).length() < 0.25, "vertex {i} moved");
        }
    }
    let out = denoise(&pos, Some(&faces), &Params::default()).unwrap();
    for p in &out.positions {
        assert!(p.z.abs() < 0.01 * 0.25, "{p}");
    }
    let mean = out.positions.iter().map(|p| p.z.abs()).sum::<f64>() / out.positions.len() as f64;
    assert!(mean < 0.01 * 0.01, "{mean}");
}

/// UTM-sized coordinates keep full precision: a 10 cm patch with a 1 mm step at
/// (500 000, 5 000 000) denoises, through a LAS file, to the same result as the same patch at the
/// origin, and the 1 mm step survives.
#[test]
fn utm_coordinates_keep_a_one_millimetre_step() {
    let mut r = Rng(99);
    let mut local = Vec::new();
    for i in 0..100 {
        for j in 0..100 {
            let (x, y) = (i as f64 * 1e-3, j as f64 * 1e-3);
            let z = if x < 0.05 { 0.0 } else { 1e-3 } + r.gauss() * 5e-5;
            local.push(DVec3::new(x, y, z));
        }
    }
    let utm = DVec3::new(500_000.0, 5_000_000.0, 100.0);
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("utm.las");
    let output = dir.path().join("utm_out.las");
    let moved: Vec<DVec3> = local.iter().map(|p| *p + utm).collect();
    qem_denoise::io::Cloud::generated(moved, None, qem_denoise::points::ScalarType::F64)
        .write(&input, None)
        .unwrap();
    let stored = qem_denoise::io::Cloud::read(&input, None).unwrap();
    let job = qem_denoise::pipeline::Job::new(&input, &output);
    qem_denoise::pipeline::run(&job, &qem_denoise::pipeline::RunOptions::default()).unwrap();
    let out = qem_denoise::io::Cloud::read(&output, None).unwrap();
    // The same points (as stored, quantised by the LAS scale), moved to the origin.
    let at_origin: Vec<DVec3> = stored.positions.iter().map(|p| *p - utm).collect();
    let want = denoise(&at_origin, None, &Params::default())
        .unwrap()
        .positions;
    let scale = 1e-6; // LAS quantum for a 10 cm extent is finer than this
    let mut low = Vec::new();
    let mut high = Vec::new();
    for ((o, w), l) in out.positions.iter().zip(&want).zip(&local) {
        let got = *o - utm;
        assert!((got - *w).length() < scale, "{got} vs {w}");
        if l.x < 0.045 {
            low.push(got.z);
        } else if l.x > 0.055 {
            high.push(got.z);
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let step = mean(&high) - mean(&low);
    assert!((step - 1e-3).abs() < 1e-4, "the 1 mm step became {step}");
}

/// Regression (issue 3): an isolated outlier's k-NN list reaches a distant surface, and the
/// robust solve would project it onto that surface, a jump of the whole distance. Steps beyond
/// the neighbourhood's sampling scale are refused: the point stays and is counted.
#[test]
fn issue_3_isolated_point_does_not_jump_onto_a_distant_surface() {
    let mut pts = Vec::new();
    for i in 0..10 {
        for j in 0..10 {
            pts.push(DVec3::new(i as f64, j as f64, 0.01 * ((i * j) % 3) as f64));
        }
    }
    pts.push(DVec3::new(50.0, 50.0, 50.0));
    // The guarded default classifies it as sparse and leaves it (issue 9).
    let out = denoise(&pts, None, &Params::default()).unwrap();
    assert_eq!(out.positions[100], DVec3::new(50.0, 50.0, 50.0));
    assert_eq!(out.stats.structure.sparse, 1);
    assert_eq!(out.stats.isolated, 1);
    // Without the guard, and with the paper's plain solve (which has no step bound), it is
    // farther than the isolation radius from any 16 points (issue 16): it stays, counted.
    for solve in [SolveKind::Damped, SolveKind::Plain] {
        let unguarded = Params {
            guard: false,
            solve,
            ..Params::default()
        };
        let out = denoise(&pts, None, &unguarded).unwrap();
        assert_eq!(out.positions[100], DVec3::new(50.0, 50.0, 50.0));
        assert_eq!((out.stats.isolated, out.stats.far), (1, 0));
    }
    // Nearer than the isolation radius, the step bound of the unguarded solve refuses the jump.
    pts[100] = DVec3::new(4.5, 4.5, 20.0);
    let unguarded = Params {
        guard: false,
        ..Params::default()
    };
    let out = denoise(&pts, None, &unguarded).unwrap();
    assert_eq!(out.stats.isolated, 0);
    assert_eq!(out.positions[100], DVec3::new(4.5, 4.5, 20.0));
    assert_eq!(out.stats.far, 1);
}
