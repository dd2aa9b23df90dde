//! The tiled driver: a point cloud larger than the memory budget (or any, with `tile_points`)
//! runs out of core as a sequence of named phases, each a function with typed inputs and
//! outputs that can run on its own against a work directory ([`crate::tiling::workdir`]):
//!
//! ```text
//!  plan        input ─────────────────────────▶ Plan             (plan.json)
//!  partition   input, Plan ───────────────────▶ Partition        (part_<p>/tile_<t>.pts, spill.done)
//!  globals     Plan, spill files ─────────────▶ Globals          (globals.json)
//!  tiles       Plan, spill files, Globals ────▶ Tiles            (tile_<t>.res, tile_<t>.json)
//!  threshold   Tiles' sums, result files ─────▶ Threshold
//!  stitch      input, result files, Threshold ▶ the output file
//! ```
//!
//! Every phase but the last commits what it made in the work directory, so a run interrupted at
//! any point resumes there with only what is not committed; the per-tile phases also expose one
//! tile as a task ([`globals::tile_partial`], [`tiles::tile`]).

pub mod globals;
pub mod outliers;
pub mod partition;
pub mod plan;
pub mod scratch;
pub mod stitch;
pub mod tiles;

use crate::denoise::{PhaseTiming, Stats, Timer};
use crate::io::SourceInfo;
use crate::pipeline::{Job, PipelineError, Report, RunOptions};

pub use scratch::TILED_DISK_PER_POINT;

/// Runs `job` in tiles; `per_point` is the kernel's working set per point
/// ([`crate::pipeline::bytes_per_point`]).
///
/// # Errors
/// Any phase's.
pub(crate) fn run(
    job: &Job,
    opts: &RunOptions,
    info: &SourceInfo,
    per_point: u64,
) -> Result<Report, PipelineError> {
    let mut phases = Stats::default();
    let mut timer = Timer::start();
    // The disk the run needs, from the header's count, before the first pass.
    let disk = scratch::run_disk_per_point(job.spec.params.write_normals, info.schema.record_len);
    if let Some(n) = info.len {
        scratch::check_disk(opts, n, disk)?;
    }
    let limits = plan::Limits::new(opts, per_point);
    let plan = plan::plan(job, opts, info, &limits)?;
    timer.lap("plan", &mut phases);

    let work = scratch::work_dir(opts, plan.finite * disk)?;
    let partition = partition::partition(job, opts, &plan, &limits, &work)?;
    let budget = partition.budget(&limits);
    timer.lap("partition", &mut phases);

    let globals = globals::globals(job, opts, &plan, &work, &budget)?;
    timer.lap("globals", &mut phases);
    let tiles = tiles::tiles(job, opts, &plan, &work, &budget, &globals)?;
    timer.lap("tiles", &mut phases);

    let threshold = outliers::threshold(job, &plan, &work, &tiles.knn_mean)?;
    let stitched = stitch::Stitch {
        job,
        opts,
        info,
        plan: &plan,
        work: &work,
        threshold: &threshold,
    }
    .run()?;
    timer.lap("stitch", &mut phases);
    drop(work);

    let mut r = Report::empty(job, "tiled");
    r.normals = stitched.normals;
    r.points_in = plan.points;
    r.points_out = stitched.written;
    r.dropped_non_finite = stitched.dropped;
    r.outliers_found = stitched.found;
    r.tiles = plan.tiles.len() as u64;
    r.empty_tiles = tiles.empty;
    r.halo_growths = tiles.halo_growths;
    r.cell_runs = tiles.cell_runs;
    r.narrower_runs = tiles.narrower_runs;
    r.tiles_resumed = tiles.resumed;
    r.bytes_spilled = partition.bytes + tiles.result_bytes;
    r.stats = tiles.stats;
    let mut all = phases.phases;
    // The kernel phases run inside the tiles; keep their totals too.
    all.extend(tiles.kernel.phases.into_iter().map(|p| PhaseTiming {
        name: format!("tiles.{}", p.name),
        ..p
    }));
    r.phases = all;
    Ok(r)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use glam::DVec3;

    use super::*;
    use crate::denoise::cloud::GlobalsPartial;
    use crate::io::{self, Cloud};
    use crate::pipeline::{OutlierMode, bytes_per_point};
    use crate::points::ScalarType;
    use crate::tiling::workdir::WorkDir;

    /// A wavy sheet of `n` points with a little noise and a few far points (outliers).
    fn cloud(path: &Path, n: usize) {
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut f = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        let pts: Vec<DVec3> = (0..n)
            .map(|i| {
                let (u, v) = (f() * 40.0, f() * 40.0);
                let lift = if i % 997 == 0 { 3.0 } else { 0.0 };
                DVec3::new(u, v, (u * 0.25).sin() + 0.02 * f() + lift)
            })
            .collect();
        Cloud::generated(pts, None, ScalarType::F32)
            .write(path, None)
            .unwrap();
    }

    fn job(d: &Path, out: &str) -> Job {
        let mut job = Job::new(d.join("in.ply"), d.join(out));
        job.spec.outliers = OutlierMode::Classify;
        job
    }

    /// A tiled job on `d/in.ply` at 4000 points a tile, planned and partitioned in a work
    /// directory under `d`, output `d/b.ply`.
    struct Phased {
        job: Job,
        opts: RunOptions,
        info: SourceInfo,
        limits: plan::Limits,
        plan: crate::tiling::plan::Plan,
        work: WorkDir,
        part: partition::Partition,
    }

    fn planned_and_partitioned(d: &Path) -> Phased {
        let job = job(d, "b.ply");
        let opts = RunOptions {
            tile_points: Some(4000),
            ..RunOptions::default()
        };
        let info = io::open(&job.input, None).unwrap().info().clone();
        let limits = plan::Limits::new(&opts, bytes_per_point(&job.spec.params, 12));
        let plan = plan::plan(&job, &opts, &info, &limits).unwrap();
        let work = WorkDir::temporary_in(d).unwrap();
        let part = partition::partition(&job, &opts, &plan, &limits, &work).unwrap();
        Phased {
            job,
            opts,
            info,
            limits,
            plan,
            work,
            part,
        }
    }

    #[test]
    fn issue10_phases_called_one_by_one_write_the_in_memory_bytes() {
        let d = tempfile::tempdir().unwrap();
        cloud(&d.path().join("in.ply"), 20_000);
        let whole = crate::pipeline::run(&job(d.path(), "a.ply"), &RunOptions::default()).unwrap();
        assert_eq!(whole.mode, "points");
        assert!(whole.outliers_found > 0);

        let p = planned_and_partitioned(d.path());
        assert!(p.plan.tiles.len() >= 4, "{}", p.plan.tiles.len());
        assert!(!p.part.resumed && p.part.bytes > 0);
        let budget = p.part.budget(&p.limits);
        let g = globals::globals(&p.job, &p.opts, &p.plan, &p.work, &budget).unwrap();
        // Each tile is a task of its own, here in reverse order; the phase then finds them all
        // committed.
        for t in (0..p.plan.tiles.len()).rev() {
            tiles::tile(&p.job, &p.opts, &p.plan, &p.work, (&budget, &g), t, None).unwrap();
        }
        let tiles = tiles::tiles(&p.job, &p.opts, &p.plan, &p.work, &budget, &g).unwrap();
        assert_eq!(tiles.resumed, p.plan.tiles.len() as u64);
        assert_eq!(tiles.stats.moved, whole.stats.moved);
        let threshold = outliers::threshold(&p.job, &p.plan, &p.work, &tiles.knn_mean).unwrap();
        let stitched = stitch::Stitch {
            job: &p.job,
            opts: &p.opts,
            info: &p.info,
            plan: &p.plan,
            work: &p.work,
            threshold: &threshold,
        }
        .run()
        .unwrap();
        assert_eq!(stitched.found, whole.outliers_found);
        assert_eq!(stitched.written, 20_000);
        assert_eq!(
            std::fs::read(&p.job.output).unwrap(),
            std::fs::read(d.path().join("a.ply")).unwrap()
        );

        // The same plan in the same directory: the partition is committed there.
        let again = partition::partition(&p.job, &p.opts, &p.plan, &p.limits, &p.work).unwrap();
        assert!(again.resumed);
        assert_eq!(again.bytes, p.part.bytes);
    }

    #[test]
    fn the_globals_pass_sums_the_same_from_a_narrowed_first_load() {
        // The sheet with its far points (one in 997 lifted by 3): their lists reach past the
        // narrowed first load, and the growth rounds redo them.
        let d = tempfile::tempdir().unwrap();
        cloud(&d.path().join("in.ply"), 20_000);
        let Phased {
            job,
            plan,
            work,
            part,
            limits,
            ..
        } = planned_and_partitioned(d.path());
        let budget = part.budget(&limits);
        let narrow = crate::tiling::globals_halo(&plan).unwrap();
        assert!(narrow < plan.halo / 3.0, "{narrow} {}", plan.halo);
        let (mut a, mut b) = (GlobalsPartial::default(), GlobalsPartial::default());
        let mut grew = 0;
        for t in 0..plan.tiles.len() {
            let (whole, _) = crate::tiling::globals_of_tile_from(
                work.path(),
                &plan,
                &budget,
                (t, None),
                &job.spec.params,
            )
            .unwrap();
            let (narrowed, g) = crate::tiling::globals_of_tile_from(
                work.path(),
                &plan,
                &budget,
                (t, Some(narrow)),
                &job.spec.params,
            )
            .unwrap();
            assert_eq!(narrowed, whole, "tile {t}");
            grew += g.rounds;
            a.merge(&whole);
            b.merge(&narrowed);
        }
        assert!(
            grew > 0,
            "no tile needed a growth round: the test shows nothing"
        );
        assert_eq!(a.finish(), b.finish());
        assert!(a.finish().noise > 0.0);
    }

    #[test]
    fn the_tiled_driver_runs_the_phases_to_the_same_bytes() {
        let d = tempfile::tempdir().unwrap();
        cloud(&d.path().join("in.ply"), 20_000);
        let whole = crate::pipeline::run(&job(d.path(), "a.ply"), &RunOptions::default()).unwrap();
        let opts = RunOptions {
            tile_points: Some(6000),
            temp_dir: Some(d.path().to_path_buf()),
            ..RunOptions::default()
        };
        let tiled = crate::pipeline::run(&job(d.path(), "b.ply"), &opts).unwrap();
        assert_eq!(tiled.mode, "tiled");
        assert!(tiled.tiles >= 3);
        assert_eq!(tiled.outliers_found, whole.outliers_found);
        assert_eq!(
            std::fs::read(d.path().join("b.ply")).unwrap(),
            std::fs::read(d.path().join("a.ply")).unwrap()
        );
        let names: Vec<String> = ["plan", "partition", "globals", "tiles", "stitch"]
            .map(String::from)
            .into();
        let got: Vec<String> = tiled
            .phases
            .iter()
            .take(5)
            .map(|p| p.name.clone())
            .collect();
        assert_eq!(got, names);
    }
}
