//! The mesh driver: a mesh runs in memory ([`crate::denoise::denoise`]), since faces need the
//! whole vertex set; stored normals are recomputed.
//!
//! Mesh mode honours what the point path honours: the cancel flag (checked before and after the
//! read, and by the operator between its passes, [`crate::neighbours::with_cancel`]) and the
//! memory budget, which a mesh cannot be tiled under: a mesh whose working set
//! ([`working_set`]) exceeds it is refused with [`PipelineError::MeshBudget`], from its declared
//! counts before it is read, and from its faces (the neighbour lists they make) before the
//! operator runs.

use super::{Job, PipelineError, Report, RunOptions, normals};
use crate::denoise::{self, Stats, Timer};
use crate::io::{Cloud, IoError, SourceInfo};
use crate::neighbours::{HUB_VALENCE, with_cancel};
use crate::points::Faces;

// The constants are measured, not derived: peak RSS of `qemd denoise` (release, default
// operator) on the level-8 icosphere (655 362 vertices, 1 310 720 faces, 24-byte records) was
// 489 MiB, which they give within 1 % (docs/DECISIONS.md, "Mesh mode within its bounds").

/// Bytes mesh mode holds per vertex besides its record: the positions read and the operator's
/// copies (current, pass results with their flags, vertex normals, the written cloud's), the
/// adjacency and the vertex–face offsets.
const PER_VERTEX: u64 = 250;
/// Bytes per face besides its neighbour list: its corners and offsets, the vertex–face lists,
/// its geometry (normal, centroid, area), filtered normal and the list's own header.
const PER_FACE: u64 = 180;
/// Bytes per entry of a face's neighbour list.
const PER_LINK: u64 = 4;
/// A face's neighbour list in an ordinary mesh before duplicates go (itself and the faces of its
/// three corners, six around each): what the count-only estimate assumes before the faces are
/// read.
const TYPICAL_LINKS: u64 = 19;

/// The bytes mesh mode needs for `vertices` vertices of `record_len` bytes and `faces` faces
/// whose neighbour lists hold `links` entries in all.
pub(crate) fn working_set(record_len: usize, vertices: u64, faces: u64, links: u64) -> u64 {
    vertices
        .saturating_mul(record_len as u64 + PER_VERTEX)
        .saturating_add(faces.saturating_mul(PER_FACE))
        .saturating_add(links.saturating_mul(PER_LINK))
}

/// An upper bound of the entries of every face's neighbour list (the faces around its corners
/// but hubs', and itself; `FaceTopology`), counted in one pass over the corners.
fn links(vertices: usize, faces: &Faces) -> u64 {
    let mut around = vec![0u32; vertices];
    for f in faces.iter() {
        for &v in f {
            if let Some(n) = around.get_mut(v as usize) {
                *n = n.saturating_add(1);
            }
        }
    }
    faces
        .iter()
        .map(|f| {
            1 + f
                .iter()
                .map(|&v| around.get(v as usize).copied().unwrap_or(0))
                .filter(|&n| n as usize <= HUB_VALENCE)
                .map(u64::from)
                .sum::<u64>()
        })
        .sum()
}

/// Refuses a mesh whose working set exceeds the memory budget.
fn check_budget(
    job: &Job,
    opts: &RunOptions,
    (record_len, vertices, faces, links): (usize, u64, u64, u64),
) -> Result<(), PipelineError> {
    let needed = working_set(record_len, vertices, faces, links);
    if needed > opts.memory_budget {
        return Err(PipelineError::MeshBudget {
            path: job.input.clone(),
            vertices,
            faces,
            needed,
            budget: opts.memory_budget,
        });
    }
    Ok(())
}

/// Denoises the mesh `job` names, whose header `info` declares.
///
/// # Errors
/// Read, operator and write failures; the memory budget; cancellation.
pub(crate) fn run(
    job: &Job,
    opts: &RunOptions,
    info: &SourceInfo,
) -> Result<Report, PipelineError> {
    let (vertices, faces) = (info.len.unwrap_or(0), info.faces.unwrap_or(0));
    let typical = faces.saturating_mul(TYPICAL_LINKS);
    check_budget(
        job,
        opts,
        (info.schema.record_len, vertices, faces, typical),
    )?;
    opts.check_cancel()?;
    let timer = Timer::start();
    let cloud = Cloud::read(&job.input, job.input_format)?;
    run_cloud(job, opts, cloud, timer, |c| {
        c.write(&job.output, job.output_format)
    })
}

/// Denoises the mesh `cloud`, read for `job` since `timer` started, and writes it with `write`.
///
/// # Errors
/// Operator and write failures; the memory budget; cancellation.
pub(crate) fn run_cloud(
    job: &Job,
    opts: &RunOptions,
    mut cloud: Cloud,
    mut timer: Timer,
    write: impl FnOnce(&Cloud) -> Result<(), IoError>,
) -> Result<Report, PipelineError> {
    let mut phases = Stats::default();
    timer.lap("read", &mut phases);
    if let Some(f) = cloud.faces() {
        let size = (
            cloud.info.schema.record_len,
            cloud.len() as u64,
            f.len() as u64,
            links(cloud.len(), f),
        );
        check_budget(job, opts, size)?;
    }
    opts.check_cancel()?;
    let out = with_cancel(&opts.cancel, || {
        denoise::denoise(&cloud.positions, cloud.faces(), &job.spec.params)
    })
    .map_err(|e| PipelineError::denoise(&job.input, e))?;
    opts.check_cancel()?;
    let mut stats = out.stats;
    phases.merge(&Stats {
        phases: std::mem::take(&mut stats.phases),
        ..Stats::default()
    });
    cloud.positions = out.positions;
    let normals = normals::recompute_mesh(&mut cloud);
    timer = Timer::start();
    write(&cloud)?;
    timer.lap("write", &mut phases);
    let mut r = Report::empty(job, "mesh");
    r.points_in = cloud.len() as u64;
    r.points_out = cloud.len() as u64;
    r.faces = cloud.faces().map_or(0, |f| f.len() as u64);
    r.normals = normals;
    r.stats = stats;
    r.phases = phases.phases;
    Ok(r)
}
