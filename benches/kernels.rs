//! Kernel benchmarks, reported in points (or matrices) per second:
//! k-NN for k = 8/16/32, k-NN on a uniform against a cluttered cloud (`knn_clutter`), PCA normals,
//! the quadric solve, the stages of the guarded default (`guarded_k16`: fits, classes and noise
//! scales, the global noise pre-pass, the normal filter, one guarded update), the eigensolver
//! against nalgebra, the median of a 16-value list (`denoise::common::median` against std's
//! selection), and the whole point-mode operator.
//!
//! `QEMD_BENCH_POINTS` sets the cloud size (default 200 000).

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use qem_denoise::denoise::normals::pca_normals;
use qem_denoise::denoise::qem::points_step;
use qem_denoise::denoise::{Params, denoise, origin_of};
use qem_denoise::geometry::SymMat3;
use qem_denoise::neighbours::KnnIndex;
use rayon::prelude::*;

fn cloud(n: usize) -> Vec<DVec3> {
    // A noisy wavy surface, deterministic.
    let mut x = 0x2545f4914f6cdd1du64;
    let mut rnd = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let (u, v) = (rnd() * 100.0, rnd() * 100.0);
            DVec3::new(u, v, (u * 0.1).sin() * 3.0 + (rnd() - 0.5) * 0.05)
        })
        .collect()
}

/// The cluttered scene of issue 16 at `n` points: three boxes and a sphere with iso noise
/// (σ = 0.005), five dense Gaussian clusters (15 % of the points, σ 0.01–0.1), 1 % exact
/// duplicates and 0.2 % far outliers 50–20 000 units from the scene, shuffled.
fn cluttered(n: usize) -> Vec<DVec3> {
    let mut x = 0x853c49e6748fea9bu64;
    let mut f = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    let g = |f: &mut dyn FnMut() -> f64| {
        let (u, v) = (f().max(1e-300), f());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let boxes = [
        (DVec3::new(-4.0, -4.0, 0.0), DVec3::new(0.0, 0.0, 3.0)),
        (DVec3::new(1.0, -3.0, 0.0), DVec3::new(4.0, 1.0, 1.5)),
        (DVec3::new(-3.0, 1.0, 0.0), DVec3::new(-1.0, 4.0, 4.0)),
    ];
    let centres = [
        (DVec3::new(-2.0, -2.0, 3.2), 0.02),
        (DVec3::new(2.5, -1.0, 1.6), 0.05),
        (DVec3::new(-2.0, 2.5, 4.1), 0.01),
        (DVec3::new(0.0, 0.0, 0.5), 0.1),
        (DVec3::new(3.0, 3.0, 3.0), 0.03),
    ];
    let (far, dup, clu) = ((n / 500).max(1), n / 100, n * 15 / 100);
    let mut v = Vec::with_capacity(n);
    for i in 0..n - far - dup - clu {
        let p = if i % 4 == 0 {
            let d = DVec3::new(g(&mut f), g(&mut f), g(&mut f)).normalize_or(DVec3::X);
            DVec3::new(2.5, 2.5, 1.5) + d * 1.5
        } else {
            let (lo, hi) = boxes[i % 3];
            let mut p = lo + (hi - lo) * DVec3::new(f(), f(), f());
            let a = (f() * 3.0) as usize % 3;
            p[a] = if f() < 0.5 { lo[a] } else { hi[a] };
            p
        };
        v.push(p + DVec3::new(g(&mut f), g(&mut f), g(&mut f)) * 0.005);
    }
    for i in 0..clu {
        let (c, s) = centres[i % centres.len()];
        v.push(c + DVec3::new(g(&mut f), g(&mut f), g(&mut f)) * s);
    }
    for _ in 0..dup {
        let p = v[(f() * v.len() as f64) as usize];
        v.push(p);
    }
    for _ in 0..far {
        let d = DVec3::new(g(&mut f), g(&mut f), g(&mut f)).normalize_or(DVec3::X);
        v.push(d * (50.0 + f() * 19_950.0));
    }
    for i in (1..v.len()).rev() {
        v.swap(i, (f() * (i + 1) as f64) as usize % (i + 1));
    }
    v
}

fn size() -> usize {
    std::env::var("QEMD_BENCH_POINTS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(200_000)
}

fn knn(c: &mut Criterion) {
    let pts = cloud(size());
    let index = KnnIndex::build(&pts, origin_of(&pts)).unwrap();
    let mut g = c.benchmark_group("knn");
    g.sample_size(10);
    g.throughput(Throughput::Elements(pts.len() as u64));
    for k in [8usize, 16, 32] {
        g.bench_with_input(BenchmarkId::from_parameter(k), &k, |b, &k| {
            b.iter(|| black_box(index.knn_all(k).unwrap()))
        });
    }
    g.bench_function("build", |b| {
        b.iter(|| black_box(KnnIndex::build(&pts, origin_of(&pts)).unwrap()))
    });
    // The crate alone, for comparison: kiddo's nearest_n(16) for every point, queries in Morton
    // order (the grid pass in `neighbours/grid.rs` exists because this is the bottleneck).
    let order = qem_denoise::neighbours::spatial_order(&pts);
    let local: Vec<[f64; 3]> = pts.iter().map(|p| p.to_array()).collect();
    let tree: kiddo::ImmutableKdTree<f64, 3> =
        kiddo::ImmutableKdTree::new_from_slice(&local).unwrap();
    g.bench_function("kiddo_nearest_n_16", |b| {
        b.iter(|| {
            let total: usize = order
                .par_iter()
                .map(|&i| {
                    tree.query(&local[i as usize])
                        .nearest_n::<kiddo::SquaredEuclidean<f64>>(
                            std::num::NonZeroUsize::new(16).unwrap(),
                        )
                        .execute()
                        .len()
                })
                .sum();
            black_box(total)
        })
    });
    g.finish();
}

/// The all-points k-NN (k = 16) on the uniform surface, the same surface with one point 10⁶ away,
/// and the cluttered scene: the grid levels keep the cost per point within 2× of the uniform
/// cloud's whatever the clutter (docs/BENCHMARKS.md, issue 15).
fn knn_clutter(c: &mut Criterion) {
    let n = size();
    let uniform = cloud(n);
    let mut far = uniform.clone();
    far[n / 2] = DVec3::new(1e6, 0.0, 0.0);
    let mut g = c.benchmark_group("knn_clutter");
    g.sample_size(10);
    g.throughput(Throughput::Elements(n as u64));
    for (name, pts) in [
        ("uniform", uniform),
        ("one_far_outlier", far),
        ("cluttered", cluttered(n)),
    ] {
        let index = KnnIndex::build(&pts, origin_of(&pts)).unwrap();
        let (_, _, w) = index.knn_all_counted(16).unwrap();
        eprintln!(
            "knn_clutter/{name}: {:.0} candidates per query, {} tree queries, {} levels",
            w.candidates as f64 / w.queries as f64,
            w.tree_queries,
            w.levels
        );
        g.bench_function(name, |b| b.iter(|| black_box(index.knn_all(16).unwrap())));
    }
    g.finish();
}

fn normals_and_solve(c: &mut Criterion) {
    let pts = cloud(size());
    let index = KnnIndex::build(&pts, origin_of(&pts)).unwrap();
    let (lists, radii) = index.knn_all(16).unwrap();
    let (normals, _) = pca_normals(&pts, &lists);
    let mut g = c.benchmark_group("kernels_k16");
    g.sample_size(10);
    g.throughput(Throughput::Elements(pts.len() as u64));
    g.bench_function("pca_normals", |b| {
        b.iter(|| black_box(pca_normals(&pts, &lists)))
    });
    g.bench_function("qem_solve_robust", |b| {
        b.iter(|| {
            black_box(points_step(
                &pts,
                &lists,
                &radii,
                &normals,
                &Params::paper(),
            ))
        })
    });
    g.bench_function("operator_end_to_end", |b| {
        let p = Params {
            knn: Some(16),
            ..Params::default()
        };
        b.iter(|| black_box(denoise(&pts, None, &p).unwrap()))
    });
    g.finish();
}

/// The stages of the guarded default operator after the k-NN (`denoise::cloud::run`), each on
/// the same 16-NN graph, in points per second.
fn guarded_stages(c: &mut Criterion) {
    use qem_denoise::denoise::guarded::{self, Guard};
    use qem_denoise::denoise::normals::filter_point_normals;
    use qem_denoise::denoise::structure::{
        Beams, classify, local_fits, near_residuals, noise_scale, planes,
    };
    let pts = cloud(size());
    let index = KnnIndex::build(&pts, origin_of(&pts)).unwrap();
    let (lists, radii) = index.knn_all(16).unwrap();
    let params = Params::default();
    let mut near = near_residuals(&pts, &lists, Beams::NONE);
    let m = near.len() / 2;
    let global = *near.select_nth_unstable_by(m, f64::total_cmp).1;
    let fits = local_fits(&pts, &lists);
    let classes = classify(&fits, &lists, &radii);
    let noise = noise_scale(&fits, &lists);
    let bound: Vec<f64> = noise.iter().map(|s| s.min(global)).collect();
    let planes = planes(&fits, &classes);
    let normals = filter_point_normals(&pts, &lists, &radii, &planes, 0.2, 3);
    let mut g = c.benchmark_group("guarded_k16");
    g.sample_size(10);
    g.throughput(Throughput::Elements(pts.len() as u64));
    g.bench_function("global_noise_prepass", |b| {
        b.iter(|| black_box(near_residuals(&pts, &lists, Beams::NONE)))
    });
    g.bench_function("local_fits", |b| {
        b.iter(|| black_box(local_fits(&pts, &lists)))
    });
    g.bench_function("classes_and_noise_scales", |b| {
        b.iter(|| black_box((classify(&fits, &lists, &radii), noise_scale(&fits, &lists))))
    });
    g.bench_function("normal_filter_3", |b| {
        b.iter(|| black_box(filter_point_normals(&pts, &lists, &radii, &planes, 0.2, 3)))
    });
    let guard = Guard {
        start: &pts,
        normals: &normals,
        fits: &fits,
        classes: &classes,
        noise: &noise,
        bound: &bound,
        radii: &radii,
        max_move: None,
        beams: Beams::NONE,
    };
    // The first update of a cycle: `&mut None` has its gains computed.
    g.bench_function("guarded_update", |b| {
        b.iter(|| {
            black_box(guarded::step(
                &pts, &lists, &guard, &params, &mut None, None,
            ))
        })
    });
    g.finish();
}

fn eigen(c: &mut Criterion) {
    let mats: Vec<SymMat3> = cloud(100_000)
        .chunks(4)
        .map(|q| {
            let mut m = SymMat3::ZERO;
            for p in q {
                m.add_outer(p.normalize(), 1.0);
            }
            m
        })
        .collect();
    let mut g = c.benchmark_group("eigen");
    g.throughput(Throughput::Elements(mats.len() as u64));
    g.bench_function("closed_form", |b| {
        b.iter(|| {
            for m in &mats {
                black_box(m.eigen());
            }
        })
    });
    g.bench_function("nalgebra_symmetric_eigen", |b| {
        b.iter(|| {
            for m in &mats {
                let a = m.0;
                let n =
                    nalgebra::Matrix3::new(a[0], a[1], a[2], a[1], a[3], a[4], a[2], a[4], a[5]);
                black_box(n.symmetric_eigen());
            }
        })
    });
    g.finish();
}

/// The median of 16 values per list, as the normal filter takes it per point: the sorting
/// network of `denoise::common::median` against std's `select_nth_unstable_by`.
fn median(c: &mut Criterion) {
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    let lists: Vec<[f64; 16]> = (0..100_000)
        .map(|_| {
            std::array::from_fn(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 11) as f64 / (1u64 << 53) as f64
            })
        })
        .collect();
    let mut g = c.benchmark_group("median");
    g.throughput(Throughput::Elements(lists.len() as u64));
    g.bench_function("network_16", |b| {
        b.iter(|| {
            let mut s = 0.0;
            for l in &lists {
                s += qem_denoise::denoise::common::median(&mut l.clone());
            }
            black_box(s)
        })
    });
    g.bench_function("select_nth_16", |b| {
        b.iter(|| {
            let mut s = 0.0;
            for l in &lists {
                s += *l.clone().select_nth_unstable_by(8, f64::total_cmp).1;
            }
            black_box(s)
        })
    });
    g.finish();
}

criterion_group!(
    benches,
    knn,
    knn_clutter,
    normals_and_solve,
    guarded_stages,
    eigen,
    median
);
criterion_main!(benches);
