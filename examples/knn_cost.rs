//! Measures the all-points k-NN pass on real files: process CPU seconds per point.
//!
//! ```sh
//! cargo run --release --example knn_cost -- [--k 16] [--repeat 3] FILE...
//! ```
//!
//! Each file is read, its finite points indexed relative to their bounding box's corner (as the
//! operator does) and [`KnnIndex::knn_all`] run `repeat` times; the best run's CPU seconds are
//! printed, with the cost per point.

use std::path::PathBuf;

use cpu_time::ProcessTime;
use glam::DVec3;
use qem_denoise::denoise::origin_of;
use qem_denoise::io::Cloud;
use qem_denoise::neighbours::KnnIndex;

fn main() -> anyhow::Result<()> {
    let mut k = 16usize;
    let mut repeat = 3usize;
    let mut files = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--k" => k = args.next().unwrap_or_default().parse()?,
            "--repeat" => repeat = args.next().unwrap_or_default().parse()?,
            _ => files.push(PathBuf::from(a)),
        }
    }
    println!(
        "file\tpoints\tk\tcpu_s\tus_per_point\tcandidates_per_query\ttree_queries\tlevels\tmax_block"
    );
    for f in files {
        let cloud = Cloud::read(&f, None)?;
        let pts: Vec<DVec3> = cloud
            .positions
            .iter()
            .copied()
            .filter(|p| p.is_finite())
            .collect();
        let index = KnnIndex::build(&pts, origin_of(&pts))?;
        let mut best = f64::INFINITY;
        let mut work = None;
        for _ in 0..repeat.max(1) {
            let t = ProcessTime::now();
            let r = index.knn_all_counted(k)?;
            best = best.min(t.elapsed().as_secs_f64());
            work = Some(r.2);
            std::hint::black_box(r);
        }
        let w = work.unwrap_or_default();
        println!(
            "{}\t{}\t{k}\t{best:.3}\t{:.2}\t{:.1}\t{}\t{}\t{}",
            f.display(),
            pts.len(),
            best * 1e6 / pts.len() as f64,
            w.candidates as f64 / w.queries.max(1) as f64,
            w.tree_queries,
            w.levels,
            w.max_block
        );
    }
    Ok(())
}
