//! Runs the stages of the guarded default operator on a file's points one by one and prints each
//! stage's process CPU seconds and a hash of its output bits (so two builds can be compared for
//! speed and for identical results in one go).
//!
//! ```sh
//! cargo run --release --example stage_probe -- FILE [--only STAGE] [--repeat N]
//! valgrind --tool=callgrind target/release/examples/stage_probe FILE --only knn   # one stage
//! ```
//!
//! Stages: `order`, `knn`, `near`, `fits`, `classes`, `filter`, `update`. The stages before
//! `--only STAGE` still run (their inputs), untimed by callgrind only when its
//! `--toggle-collect` is used; the timing printed is per stage either way. Points are taken in
//! spatial order with their input indices as tie keys, as `denoise::cloud` lays them out.

use std::hash::{Hash, Hasher};
use std::path::PathBuf;

use cpu_time::ProcessTime;
use glam::DVec3;
use qem_denoise::denoise::guarded::{self, Guard};
use qem_denoise::denoise::normals::filter_point_normals;
use qem_denoise::denoise::structure::{
    Beams, classify, local_fits, near_residuals, noise_scale, planes,
};
use qem_denoise::denoise::{Params, origin_of};
use qem_denoise::io::Cloud;
use qem_denoise::neighbours::{KnnIndex, spatial_order};

fn hash_f64(xs: impl Iterator<Item = f64>) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for x in xs {
        x.to_bits().hash(&mut h);
    }
    h.finish()
}

fn hash_v(xs: &[DVec3]) -> u64 {
    hash_f64(xs.iter().flat_map(|v| v.to_array()))
}

fn main() -> anyhow::Result<()> {
    let mut file = None;
    let mut only: Option<String> = None;
    let mut repeat = 1usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--only" => only = args.next(),
            "--repeat" => repeat = args.next().unwrap_or_default().parse()?,
            _ => file = Some(PathBuf::from(a)),
        }
    }
    let file = file.ok_or_else(|| anyhow::anyhow!("no file"))?;
    let cloud = Cloud::read(&file, None)?;
    let input: Vec<DVec3> = cloud
        .positions
        .iter()
        .copied()
        .filter(|p| p.is_finite())
        .collect();
    let stop = |s: &str| only.as_deref() == Some(s);
    let time = |name: &str, f: &mut dyn FnMut() -> u64| {
        let mut best = f64::INFINITY;
        let mut h = 0;
        for _ in 0..repeat.max(1) {
            let t = ProcessTime::now();
            h = f();
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!("{name:>8}  {best:8.3} cpu-s  {h:016x}");
    };
    let mut order = Vec::new();
    time("order", &mut || {
        order = spatial_order(&input);
        order.len() as u64
    });
    let pts: Vec<DVec3> = order.iter().map(|&i| input[i as usize]).collect();
    let ties: Vec<u64> = order.iter().map(|&i| i as u64).collect();
    if stop("order") {
        return Ok(());
    }
    let index = KnnIndex::build_with_ties(&pts, origin_of(&pts), ties)?;
    let mut lists = Default::default();
    let mut radii = Vec::new();
    time("knn", &mut || {
        let (l, r, w) = index.knn_all_counted(16).expect("knn");
        eprintln!(
            "knn work: {:.1} candidates/query, {} cells, {} tree queries, {} levels, max block {}",
            w.candidates as f64 / w.queries.max(1) as f64,
            w.cells,
            w.tree_queries,
            w.levels,
            w.max_block
        );
        lists = l;
        radii = r;
        hash_f64(radii.iter().copied()) ^ hash_f64(lists.indices.iter().map(|&i| i as f64))
    });
    if stop("knn") {
        return Ok(());
    }
    let mut near = Vec::new();
    time("near", &mut || {
        near = near_residuals(&pts, &lists, Beams::NONE);
        hash_f64(near.iter().copied())
    });
    if stop("near") {
        return Ok(());
    }
    let m = near.len() / 2;
    let global = *near.select_nth_unstable_by(m, f64::total_cmp).1;
    let mut fits = Vec::new();
    time("fits", &mut || {
        fits = local_fits(&pts, &lists);
        hash_v(&fits.iter().map(|f| f.normal).collect::<Vec<_>>())
            ^ hash_f64(fits.iter().map(|f| f.residual))
    });
    if stop("fits") {
        return Ok(());
    }
    let (mut classes, mut noise) = (Vec::new(), Vec::new());
    time("classes", &mut || {
        classes = classify(&fits, &lists, &radii);
        noise = noise_scale(&fits, &lists);
        hash_f64(noise.iter().copied()) ^ classes.iter().map(|&c| c as u64).sum::<u64>()
    });
    if stop("classes") {
        return Ok(());
    }
    let bound: Vec<f64> = noise.iter().map(|s| s.min(global)).collect();
    let planes = planes(&fits, &classes);
    let mut normals = Vec::new();
    time("filter", &mut || {
        normals = filter_point_normals(&pts, &lists, &radii, &planes, 0.2, 3);
        hash_v(&normals)
    });
    if stop("filter") {
        return Ok(());
    }
    let params = Params::default();
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
    time("update", &mut || {
        let mut gain = None;
        let s1: Vec<DVec3> = guarded::step(&pts, &lists, &guard, &params, &mut gain, None)
            .into_iter()
            .map(|s| s.0)
            .collect();
        let s2: Vec<DVec3> = guarded::step(&s1, &lists, &guard, &params, &mut gain, None)
            .into_iter()
            .map(|s| s.0)
            .collect();
        hash_v(&s2)
    });
    Ok(())
}
