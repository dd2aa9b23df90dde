//! Kernel benchmarks, reported in points (or matrices) per second:
//! k-NN for k = 8/16/32, PCA normals, the quadric solve, the eigensolver against nalgebra, and the
//! whole point-mode operator.
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

criterion_group!(benches, knn, normals_and_solve, eigen);
criterion_main!(benches);
