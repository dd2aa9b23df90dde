//! One task of one phase (`qemd worker`), built on the tiled driver's phase functions
//! ([`crate::pipeline::tiled`]): it reads the frozen job, checks that the phases before it are
//! committed, does its share — tile `t` belongs to task `t mod N` — skipping what is committed,
//! and commits each result atomically.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::frozen::FrozenJob;
use super::index::TaskIndex;
use super::layout::{STITCH_DONE, commit_json, globals_partial_path, load_json};
use super::lock::PhaseLock;
use super::url::WorkUrl;
use super::{Phase, ScaleoutError, resolve_index};
use crate::denoise::Displacements;
use crate::denoise::cloud::{self, Globals, GlobalsPartial};
use crate::geometry::ExactSum;
use crate::io;
use crate::pipeline::NormalsAction;
use crate::pipeline::tiled::partition::{self, Partition};
use crate::pipeline::tiled::{globals, outliers, stitch, tiles};
use crate::pipeline::{Job, PipelineError, Progress, RunOptions};
use crate::tiling::workdir::{WorkDir, body_done_path, body_path};

/// What a task did.
#[derive(Debug, Clone, Serialize)]
pub struct TaskReport {
    /// The phase.
    pub phase: Phase,
    /// Which task.
    pub task: TaskIndex,
    /// Units (partition parts, tiles, or the one stitch) that are this task's.
    pub assigned: u64,
    /// Units it did.
    pub done: u64,
    /// Units it found committed and skipped.
    pub skipped: u64,
    /// Wall time in seconds.
    pub wall_s: f64,
}

/// A tile's partial sums of the global scalars as stored (`globals_<t>.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct StoredPartial {
    spacing: ExactSum,
    noise: Displacements,
}

/// The committed stitch (`stitch.json`): what it wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StitchDone {
    /// Points written.
    pub written: u64,
    /// Points flagged or removed as outliers.
    pub found: u64,
    /// Unprocessed points dropped.
    pub dropped: u64,
    /// What happened to stored normals.
    pub normals: NormalsAction,
    /// Bytes of the output file.
    pub bytes: u64,
}

/// How a task reports progress and is cancelled.
#[derive(Clone)]
pub struct Hooks {
    /// Progress updates.
    pub progress: Arc<dyn Progress>,
    /// Set to stop at the next batch or tile.
    pub cancel: Arc<AtomicBool>,
}

impl Default for Hooks {
    fn default() -> Hooks {
        let o = RunOptions::default();
        Hooks {
            progress: o.progress,
            cancel: o.cancel,
        }
    }
}

/// Tiles of `tiles` that are task `i` of `n`'s: `t ≡ i (mod n)`.
pub fn assigned(i: u64, n: u64, tiles: usize) -> impl Iterator<Item = usize> {
    (i as usize..tiles).step_by(n.max(1) as usize)
}

/// A loaded job and the handles every phase uses.
struct Ctx {
    frozen: FrozenJob,
    job: Job,
    opts: RunOptions,
    work: WorkDir,
}

impl Ctx {
    fn new(dir: &Path, hooks: &Hooks) -> Result<Ctx, ScaleoutError> {
        let frozen = FrozenJob::load(dir)?;
        let job = frozen.job(dir);
        let opts = RunOptions {
            progress: hooks.progress.clone(),
            cancel: hooks.cancel.clone(),
            ..frozen.options(dir)
        };
        let work = WorkDir::persistent(dir).map_err(|e| io::IoError::io(dir, e))?;
        Ok(Ctx {
            frozen,
            job,
            opts,
            work,
        })
    }

    fn not_ready(&self, phase: Phase, detail: String) -> ScaleoutError {
        ScaleoutError::NotReady {
            path: self.work.path().to_path_buf(),
            phase,
            detail,
        }
    }

    /// The committed partition (committed here when all its parts are), or
    /// [`ScaleoutError::NotReady`].
    fn partition(&self, phase: Phase) -> Result<Partition, ScaleoutError> {
        let plan = &self.frozen.plan;
        if self.work.committed_partition(plan).is_none() && self.work.commit_parts(plan)?.is_none()
        {
            let missing: Vec<u64> = (0..plan.parts())
                .filter(|&p| self.work.committed_part(p).is_none())
                .collect();
            return Err(self.not_ready(
                phase,
                format!(
                    "the partition phase committed ({} of {} parts missing)",
                    missing.len(),
                    plan.parts()
                ),
            ));
        }
        // Committed: this only reads it back and checks the tiles against the budget.
        let limits = self.frozen.limits(self.work.path());
        Ok(partition::partition(
            &self.job, &self.opts, plan, &limits, &self.work,
        )?)
    }

    /// The global scalars: zero when not needed, the committed ones, or reduced from every
    /// tile's committed partial sums (then committed; any task may, all write the same bytes).
    fn globals(&self, phase: Phase) -> Result<Globals, ScaleoutError> {
        if !cloud::needs_globals(&self.job.spec.params) {
            return Ok(Globals::default());
        }
        if let Some(g) = self.work.committed_globals() {
            return Ok(g);
        }
        let tiles = self.frozen.plan.tiles.len();
        let mut sum = GlobalsPartial::default();
        let mut missing = Vec::new();
        for t in 0..tiles {
            match load_json::<StoredPartial>(&globals_partial_path(self.work.path(), t)) {
                Some(p) => sum.merge(&GlobalsPartial {
                    spacing: p.spacing,
                    noise: p.noise,
                }),
                None => missing.push(t),
            }
        }
        if !missing.is_empty() {
            return Err(self.not_ready(
                phase,
                format!(
                    "the globals phase committed ({} of {tiles} tiles missing, first {})",
                    missing.len(),
                    missing[0]
                ),
            ));
        }
        let g = sum.finish();
        self.work.commit_globals(&g)?;
        Ok(g)
    }

    /// The exact sums of the outlier statistic over every committed tile, or
    /// [`ScaleoutError::NotReady`].
    fn knn_sums(&self, phase: Phase) -> Result<(ExactSum, ExactSum), ScaleoutError> {
        let tiles = self.frozen.plan.tiles.len();
        let mut sums = (ExactSum::default(), ExactSum::default());
        let mut missing = Vec::new();
        for t in 0..tiles {
            match self.work.committed_tile(t) {
                Some(o) => {
                    sums.0.merge(&o.knn_mean.0);
                    sums.1.merge(&o.knn_mean.1);
                }
                None => missing.push(t),
            }
        }
        if !missing.is_empty() {
            return Err(self.not_ready(
                phase,
                format!(
                    "the tiles phase committed ({} of {tiles} tiles missing, first {})",
                    missing.len(),
                    missing[0]
                ),
            ));
        }
        Ok(sums)
    }
}

/// The committed stitch of the job in `dir`: `stitch.json` and an output of its length.
pub fn committed_stitch(dir: &Path, frozen: &FrozenJob) -> Option<StitchDone> {
    let done: StitchDone = load_json(&dir.join(STITCH_DONE))?;
    let out = frozen.job(dir).output;
    let len = std::fs::metadata(&out).ok()?.len();
    (len == done.bytes).then_some(done)
}

/// A committed stitch range (`body_<r>.json`, written after its body).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
struct BodyDone {
    /// What the body holds.
    body: stitch::Body,
    /// Bytes of the body file.
    bytes: u64,
}

/// Stitch range `r` of the job in `dir` when committed: its body file, and what it holds.
fn committed_body(dir: &Path, r: u64) -> Option<(PathBuf, stitch::Body)> {
    let done: BodyDone = load_json(&body_done_path(dir, r))?;
    let path = body_path(dir, r);
    let len = std::fs::metadata(&path).ok()?.len();
    (len == done.bytes).then_some((path, done.body))
}

/// How many of the `ranges` stitch ranges of the job in `dir` are committed (by their markers,
/// which outlive the bodies once the output holds them).
pub fn committed_ranges(dir: &Path, ranges: u64) -> u64 {
    (0..ranges)
        .filter(|&r| load_json::<BodyDone>(&body_done_path(dir, r)).is_some())
        .count() as u64
}

/// What the stitch of a job reads besides the results: the input's description and the
/// outliers' threshold from every tile's sums.
struct StitchInputs {
    info: io::SourceInfo,
    threshold: outliers::Threshold,
}

impl StitchInputs {
    fn load(ctx: &Ctx, dir: &Path, job: &Job) -> Result<StitchInputs, ScaleoutError> {
        ctx.frozen.check_input(dir)?;
        let knn = ctx.knn_sums(Phase::Stitch)?;
        let threshold = outliers::threshold(job, &ctx.frozen.plan, &ctx.work, &knn)?;
        let info = io::open(&job.input, job.input_format)
            .map_err(PipelineError::from)?
            .info()
            .clone();
        Ok(StitchInputs { info, threshold })
    }

    /// The stitch of `job` (the job of `ctx`, or another output of it) with these inputs.
    fn stitch<'a>(&'a self, ctx: &'a Ctx, job: &'a Job) -> stitch::Stitch<'a> {
        stitch::Stitch {
            job,
            opts: &ctx.opts,
            info: &self.info,
            plan: &ctx.frozen.plan,
            work: &ctx.work,
            threshold: &self.threshold,
        }
    }
}

/// Stitches the job of `dir` into `job.output` (its format `job.output_format`): the threshold
/// from every tile's sums, then [`stitch::Stitch::run`]. The caller holds the stitch lock.
pub(super) fn stitch_into(
    dir: &Path,
    job: &Job,
    hooks: &Hooks,
) -> Result<stitch::Stitched, ScaleoutError> {
    let ctx = Ctx::new(dir, hooks)?;
    let s = StitchInputs::load(&ctx, dir, job)?;
    Ok(s.stitch(&ctx, job).run()?)
}

/// Removes what a killed stitch left: the output's temporary file, or `stitch.json`'s when it
/// was killed between the two. The caller holds the stitch lock, so no writer of either runs.
fn remove_stale_stitch_temps(dir: &Path, job: &Job) -> Result<(), ScaleoutError> {
    io::remove_stale_temps(&job.output)?;
    io::remove_stale_temps(&dir.join(STITCH_DONE))?;
    Ok(())
}

/// Commits the stitch of `dir` (`stitch.json` after the output, whose length it records).
fn commit_stitch(dir: &Path, job: &Job, s: &stitch::Stitched) -> Result<(), ScaleoutError> {
    let bytes = std::fs::metadata(&job.output)
        .map_err(|e| io::IoError::io(&job.output, e))?
        .len();
    let done = StitchDone {
        written: s.written,
        found: s.found,
        dropped: s.dropped,
        normals: s.normals,
        bytes,
    };
    commit_json(&dir.join(STITCH_DONE), &done, true)?;
    Ok(())
}

/// Stitch ranges `mine` of the job of `ctx` (in `dir`), each a body committed on its own
/// (skipping the committed ones); then, when every range is committed, the output from the
/// bodies. Counts what it did in `r`.
fn stitch_ranges(
    ctx: &Ctx,
    dir: &Path,
    mine: &[u64],
    r: &mut TaskReport,
) -> Result<(), ScaleoutError> {
    let plan = &ctx.frozen.plan;
    r.assigned = mine.len() as u64;
    let todo: Vec<u64> = mine
        .iter()
        .copied()
        .filter(|&range| committed_body(dir, range).is_none())
        .collect();
    let mut inputs = None;
    if !todo.is_empty() {
        let s = StitchInputs::load(ctx, dir, &ctx.job)?;
        let read = AtomicU64::new(0);
        ctx.opts.progress.phase("stitch", plan.points);
        // The task's ranges side by side on its pool, as `qemd denoise` does.
        let did = todo
            .par_iter()
            .map(|&range| {
                ctx.opts.check_cancel()?;
                // A duplicate of this task waits here, then finds the range committed.
                let _lock = PhaseLock::acquire_range(dir, range)?;
                if committed_body(dir, range).is_some() {
                    return Ok(0);
                }
                let path = body_path(dir, range);
                // A killed writer of this range left its temporary files (the body's, or its
                // marker's when killed between the two); the lock says none runs.
                io::remove_stale_temps(&path)?;
                io::remove_stale_temps(&body_done_path(dir, range))?;
                let body = s.stitch(ctx, &ctx.job).write_body(range, &path, &read)?;
                let bytes = std::fs::metadata(&path)
                    .map_err(|e| io::IoError::io(&path, e))?
                    .len();
                commit_json(
                    &body_done_path(dir, range),
                    &BodyDone { body, bytes },
                    false,
                )?;
                Ok(1)
            })
            .collect::<Result<Vec<u64>, ScaleoutError>>()?;
        r.done = did.iter().sum();
        inputs = Some(s);
    }
    r.skipped = r.assigned - r.done;
    // The task that sees every range committed assembles the output; when none does (an
    // object store lists once per task), `qemd finish` does.
    let ranges = ctx.frozen.tasks_of(Phase::Stitch);
    let Some(bodies) = (0..ranges)
        .map(|range| committed_body(dir, range))
        .collect::<Option<Vec<_>>>()
    else {
        return Ok(());
    };
    let _lock = PhaseLock::acquire(dir, Phase::Stitch)?;
    if committed_stitch(dir, &ctx.frozen).is_some() {
        return Ok(());
    }
    remove_stale_stitch_temps(dir, &ctx.job)?;
    let s = match inputs {
        Some(s) => s,
        None => StitchInputs::load(ctx, dir, &ctx.job)?,
    };
    let stitched = s.stitch(ctx, &ctx.job).assemble(&bodies)?;
    commit_stitch(dir, &ctx.job, &stitched)?;
    // The output holds the bodies now: their bytes go (their markers stay, for `status`).
    for (path, _) in &bodies {
        let _ = std::fs::remove_file(path);
    }
    Ok(())
}

/// Runs task `index` of `of` (else from the environment `env`, see [`super::index`]) of `phase`
/// of the job in `work`.
///
/// # Errors
/// A work directory without a plan, a phase before this one not committed, the phase's errors,
/// cancellation.
pub fn run_task(
    work: &WorkUrl,
    phase: Phase,
    (index, of): (Option<u64>, Option<u64>),
    env: impl Fn(&str) -> Option<String>,
    hooks: &Hooks,
) -> Result<TaskReport, ScaleoutError> {
    let start = Instant::now();
    let dir = work.local()?;
    let ctx = Ctx::new(dir, hooks)?;
    let task = resolve_index(index, of, ctx.frozen.tasks_of(phase), env)?;
    let tiles = ctx.frozen.plan.tiles.len();
    let mut r = TaskReport {
        phase,
        task,
        assigned: 0,
        done: 0,
        skipped: 0,
        wall_s: 0.0,
    };
    let single = task.index == 0;
    match phase {
        Phase::Partition => {
            let plan = &ctx.frozen.plan;
            let parts = plan.parts();
            let mine = assigned(task.index, task.of, parts as usize).map(|p| p as u64);
            if ctx.work.committed_partition(plan).is_some() {
                r.assigned = mine.count() as u64;
                r.skipped = r.assigned;
            } else {
                ctx.frozen.check_input(dir)?;
                ctx.opts.progress.phase("partition", plan.points);
                let read = AtomicU64::new(0);
                let memory = ctx.opts.memory_budget / partition::SPILL_SHARE;
                for part in mine {
                    ctx.opts.check_cancel()?;
                    r.assigned += 1;
                    // A duplicate of this task waits here, then finds the part committed.
                    let _lock = PhaseLock::acquire_part(dir, part)?;
                    if ctx.work.committed_part(part).is_some() {
                        r.skipped += 1;
                        continue;
                    }
                    partition::write_part(
                        &ctx.job, &ctx.opts, plan, &ctx.work, part, memory, &read,
                    )?;
                    r.done += 1;
                }
                // The task that commits the last part commits the partition; when none saw
                // them all (an object store lists once), the next phase does.
                ctx.work.commit_parts(plan)?;
            }
        }
        Phase::Globals if cloud::needs_globals(&ctx.job.spec.params) => {
            let part = ctx.partition(phase)?;
            let limits = ctx.frozen.limits(dir);
            let budget = part.budget(&limits);
            ctx.opts.progress.phase("globals", tiles as u64);
            for t in assigned(task.index, task.of, tiles) {
                ctx.opts.check_cancel()?;
                r.assigned += 1;
                let path = globals_partial_path(dir, t);
                if load_json::<StoredPartial>(&path).is_some() {
                    r.skipped += 1;
                    continue;
                }
                let p = globals::tile_partial(
                    &ctx.job,
                    &ctx.opts,
                    &ctx.frozen.plan,
                    &ctx.work,
                    &budget,
                    t,
                )?;
                let stored = StoredPartial {
                    spacing: p.spacing,
                    noise: p.noise,
                };
                commit_json(&path, &stored, false)?;
                r.done += 1;
                ctx.opts.progress.advance(r.assigned);
            }
        }
        Phase::Tiles => {
            let part = ctx.partition(phase)?;
            let limits = ctx.frozen.limits(dir);
            let budget = part.budget(&limits);
            let g = ctx.globals(phase)?;
            ctx.opts.progress.phase("tiles", tiles as u64);
            for t in assigned(task.index, task.of, tiles) {
                ctx.opts.check_cancel()?;
                r.assigned += 1;
                if ctx.work.committed_tile(t).is_some() {
                    r.skipped += 1;
                    continue;
                }
                tiles::tile(
                    &ctx.job,
                    &ctx.opts,
                    &ctx.frozen.plan,
                    &ctx.work,
                    (&budget, &g),
                    t,
                    None,
                )?;
                r.done += 1;
                ctx.opts.progress.advance(r.assigned);
            }
        }
        Phase::Stitch if ctx.frozen.tasks_of(phase) > 1 => {
            let ranges = ctx.frozen.tasks_of(phase) as usize;
            let mine: Vec<u64> = assigned(task.index, task.of, ranges)
                .map(|x| x as u64)
                .collect();
            if committed_stitch(dir, &ctx.frozen).is_some() {
                r.assigned = mine.len() as u64;
                r.skipped = r.assigned;
            } else {
                stitch_ranges(&ctx, dir, &mine, &mut r)?;
            }
        }
        Phase::Stitch if single => {
            r.assigned = 1;
            let _lock = PhaseLock::acquire(dir, phase)?;
            if committed_stitch(dir, &ctx.frozen).is_some() {
                r.skipped = 1;
            } else {
                remove_stale_stitch_temps(dir, &ctx.job)?;
                let s = stitch_into(dir, &ctx.job, hooks)?;
                commit_stitch(dir, &ctx.job, &s)?;
                r.done = 1;
            }
        }
        // A task past the phase's count (a larger array than needed) has nothing to do.
        Phase::Globals | Phase::Stitch => {}
    }
    r.wall_s = start.elapsed().as_secs_f64();
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_are_dealt_round_robin() {
        let all: Vec<Vec<usize>> = (0..3).map(|i| assigned(i, 3, 8).collect()).collect();
        assert_eq!(all, vec![vec![0, 3, 6], vec![1, 4, 7], vec![2, 5]]);
        assert_eq!(assigned(9, 10, 4).count(), 0);
        assert_eq!(assigned(0, 1, 4).count(), 4);
    }
}
