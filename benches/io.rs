//! PLY I/O throughput, in points per second, on a generated binary little-endian file with
//! `float x y z`, `uchar red green blue` and `float intensity` (19-byte records):
//!
//! * `ply_read/qemd_fast_path`: [`PlySource`] batches (one `read_exact` per batch, fixed-offset
//!   position decoding);
//! * `ply_read/ply_rs_bw_default_element`: `ply-rs-bw`'s full parser into `DefaultElement`s;
//! * `ply_write/qemd_sink`: [`Cloud::write`] of the same points (temp file, patch x/y/z, rename).
//!
//! `QEMD_BENCH_POINTS` sets the point count (default 1 000 000).

use std::hint::black_box;
use std::io::{BufReader, Write};
use std::path::Path;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use qem_denoise::io::ply::PlySource;
use qem_denoise::io::{BATCH, Cloud, Source};
use qem_denoise::points::PointBatch;

fn size() -> usize {
    std::env::var("QEMD_BENCH_POINTS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1_000_000)
}

/// Writes the benchmark file: a deterministic wavy surface with colours and intensities.
fn generate(path: &Path, n: usize) {
    let mut out = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment qemd io benchmark\nelement vertex {n}\n\
         property float x\nproperty float y\nproperty float z\nproperty uchar red\n\
         property uchar green\nproperty uchar blue\nproperty float intensity\nend_header\n"
    )
    .unwrap();
    let mut s = 0x2545f4914f6cdd1du64;
    for i in 0..n {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        let (u, v) = ((i % 1000) as f32 * 0.1, (i / 1000) as f32 * 0.1);
        let mut rec = [0u8; 19];
        rec[0..4].copy_from_slice(&u.to_le_bytes());
        rec[4..8].copy_from_slice(&v.to_le_bytes());
        rec[8..12].copy_from_slice(&((u * 0.3).sin() + (s % 100) as f32 * 1e-3).to_le_bytes());
        rec[12..15].copy_from_slice(&[(s >> 8) as u8, (s >> 16) as u8, (s >> 24) as u8]);
        rec[15..19].copy_from_slice(&((s >> 32) as f32 / u32::MAX as f32).to_le_bytes());
        out.write_all(&rec).unwrap();
    }
    out.flush().unwrap();
}

fn read_fast(path: &Path) -> usize {
    let mut src = PlySource::open(path).unwrap();
    let mut batch = PointBatch::with_capacity(src.info().schema.record_len, BATCH);
    let mut n = 0;
    let mut sum = 0.0;
    loop {
        let k = src.read_batch(&mut batch, BATCH).unwrap();
        if k == 0 {
            break;
        }
        sum += batch.positions[k - 1].x;
        n += k;
    }
    black_box(sum);
    black_box(Box::new(src).finish().unwrap());
    n
}

fn read_ply_rs(path: &Path) -> usize {
    let parser = ply_rs_bw::parser::Parser::<ply_rs_bw::ply::DefaultElement>::new();
    let mut f = BufReader::new(std::fs::File::open(path).unwrap());
    let ply = parser.read_ply(&mut f).unwrap();
    ply.payload["vertex"].len()
}

fn io(c: &mut Criterion) {
    let n = size();
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("bench.ply");
    generate(&input, n);
    assert_eq!(read_fast(&input), n);
    assert_eq!(read_ply_rs(&input), n);

    let mut g = c.benchmark_group("ply_read");
    g.sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(5))
        .throughput(Throughput::Elements(n as u64));
    g.bench_function("qemd_fast_path", |b| {
        b.iter(|| black_box(read_fast(&input)))
    });
    g.bench_function("ply_rs_bw_default_element", |b| {
        b.iter(|| black_box(read_ply_rs(&input)))
    });
    g.finish();

    let cloud = Cloud::read(&input, None).unwrap();
    let output = dir.path().join("out.ply");
    let mut g = c.benchmark_group("ply_write");
    g.sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(5))
        .throughput(Throughput::Elements(n as u64));
    g.bench_function("qemd_sink", |b| {
        b.iter(|| cloud.write(black_box(&output), None).unwrap())
    });
    g.finish();
    assert!(std::fs::read(&output).unwrap() == std::fs::read(&input).unwrap());
}

criterion_group!(benches, io);
criterion_main!(benches);
