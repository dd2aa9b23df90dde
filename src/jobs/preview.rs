//! Bounded, deterministic previews of a finished job for the web viewer: the same points before
//! and after, so that the page can draw both and colour each point by how far it moved, without
//! ever downloading the full result.
//!
//! # What a preview is
//!
//! * **Selection.** A job's points are numbered in the order the pipeline keeps them (the
//!   result's order: input points minus those dropped for a non-finite or out-of-range
//!   coordinate). A scan of at most `preview_points` ([`super::Settings::preview_points`],
//!   default [`super::service::PREVIEW_POINTS`]) kept points is taken whole; a larger one keeps the
//!   `preview_points` indices whose [`mix`] hash is smallest (a bottom-k sample of
//!   the index hashes, independent of the data, the thread count or the tiling). The same indices
//!   are read from the input and from the result, so the two halves of the preview are the same
//!   points, and the same job always gives the same bytes.
//! * **Meshes** of at most `preview_points` vertices are sent whole with their faces
//!   (polygons fanned into triangles); larger ones are sampled like clouds and drawn as points.
//! * **Unpaired results.** With `outliers: remove` and outliers found, result point *j* is no
//!   longer input point *j*; both sides are then sampled on their own (same rule) and the
//!   preview says `paired: false` and carries no displacement.
//! * **Files.** `before.ply` and `after.ply` are binary little-endian PLY: `float x y z`
//!   relative to `origin` (the f64 centre of the input's sampled bounding box, so UTM-sized
//!   coordinates keep their precision in `float`), then `float displacement` (paired previews:
//!   |after − before| in the input's units, computed in f64), `float intensity` and `uchar
//!   class` when the input has them (LAS, or a field named `intensity` / `class[ification]`),
//!   and a `face` element for whole meshes. `preview.json` ([`PreviewMeta`]) describes them.
//!   They live in `jobs/<id>/preview-v1/`, are written by temp + rename with the description
//!   last, and go with the job's directory when it is dismissed.
//!
//! Building is synchronous and streaming: the input and the result are read once each in
//! batches; memory is O(`preview_points`) whatever the scan's size. The async entry point,
//! [`Jobs::preview`], runs it on the blocking pool, one build at a time.

use std::io::Write;
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::requests::format_of;
use super::store::Status;
use super::{Jobs, JobsError, bridge};
use crate::io::{AtomicFile, IoError};
use crate::pipeline::{OutlierMode, Report};
use crate::points::{Faces, PointBatch, Schema, in_range};

/// The preview directory's name inside a job's directory (bumped when the layout changes, so a
/// server never serves a preview an older version built).
const DIR: &str = "preview-v1";

/// Points read per batch while building.
const BATCH: usize = 1 << 16;

/// A point's selection key: SplitMix64 of its index (a bijection of `u64`, so keys are
/// distinct and the bottom-k sample has exactly k points).
pub fn mix(i: u64) -> u64 {
    let mut z = i.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The indices among `0..n` a preview of at most `cap` points keeps, ascending: all of them when
/// `n <= cap`, else the `cap` whose [`mix`] keys are smallest.
pub fn select(n: u64, cap: u64) -> Vec<u64> {
    if n <= cap {
        return (0..n).collect();
    }
    let cap_len = usize::try_from(cap).unwrap_or(usize::MAX);
    // Keep only keys below a threshold expected to pass ~1.25 cap of them, then cut to cap;
    // raise the threshold in the rare case too few passed.
    let mut frac = (1.25 * cap as f64 / n as f64).min(1.0);
    loop {
        let limit = if frac >= 1.0 {
            u64::MAX
        } else {
            (frac * u64::MAX as f64) as u64
        };
        let mut keyed: Vec<(u64, u64)> = (0..n)
            .filter_map(|i| {
                let k = mix(i);
                (k <= limit).then_some((k, i))
            })
            .collect();
        if keyed.len() >= cap_len {
            if keyed.len() > cap_len {
                keyed.select_nth_unstable(cap_len);
                keyed.truncate(cap_len);
            }
            let mut out: Vec<u64> = keyed.into_iter().map(|(_, i)| i).collect();
            out.sort_unstable();
            return out;
        }
        frac = (frac * 2.0).min(1.0);
    }
}

/// Summary of the displacement of a paired preview, in the input's units.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DisplacementStats {
    /// Mean.
    pub mean: f64,
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// 99th percentile (the page's default colour-scale top).
    pub p99: f64,
    /// Largest.
    pub max: f64,
}

/// What a preview holds (`preview.json`, served by `GET /v1/jobs/{id}/preview`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PreviewMeta {
    /// `mesh` (whole, with faces) or `points`.
    pub kind: String,
    /// Points of the scan (kept by the pipeline, input side).
    pub points_total: u64,
    /// Points in the preview, before side.
    pub points_before: u64,
    /// Points in the preview, after side (equal to `points_before` when paired).
    pub points_after: u64,
    /// Triangles (whole meshes), else 0.
    pub triangles: u64,
    /// The same points on both sides, with their displacement.
    pub paired: bool,
    /// What the positions are relative to (f64).
    pub origin: [f64; 3],
    /// Bounding box of the before side, absolute.
    pub min: [f64; 3],
    /// Bounding box of the before side, absolute.
    pub max: [f64; 3],
    /// The PLY files carry `intensity`.
    pub intensity: bool,
    /// The PLY files carry `class`.
    pub class: bool,
    /// Displacement summary (paired previews).
    pub displacement: Option<DisplacementStats>,
    /// The unit of lengths (coordinates and displacements): `m`, `ft` or `US ft` when the input's
    /// CRS (LAS, COPC, E57) says it, `°` for a geographic one; `None`: the file does not say, and
    /// lengths are in the input's own units.
    #[serde(default)]
    pub units: Option<String>,
    /// The sampling rule, in words.
    pub selection: String,
    /// The bound it was built with (`preview_points`).
    pub max_points: u64,
}

/// A built preview's files.
#[derive(Debug, Clone)]
pub struct PreviewFiles {
    /// The description.
    pub meta: PreviewMeta,
    /// `before.ply`.
    pub before: PathBuf,
    /// `after.ply`.
    pub after: PathBuf,
}

/// One side of a preview, read from a file.
#[derive(Debug, Default)]
struct Side {
    positions: Vec<DVec3>,
    intensity: Option<Vec<f32>>,
    class: Option<Vec<u8>>,
    faces: Option<Faces>,
    /// The unit of the coordinates, when the file's CRS says it.
    unit: Option<crate::io::crs::LinearUnit>,
}

/// Where a scalar field is in a schema, and how to read it.
#[derive(Debug, Clone, Copy)]
enum Attr {
    Intensity(usize),
    /// Index and whether only the low five bits are the class (LAS PDRF 0–5).
    Class(usize, bool),
}

fn attrs(schema: &Schema) -> (Option<Attr>, Option<Attr>) {
    let find = |names: &[&str]| names.iter().find_map(|n| schema.field_index(n));
    let intensity = find(&["intensity", "scalar_intensity", "reflectance"]).map(Attr::Intensity);
    let las_low_bits = schema.field_index("classification_flags").is_none()
        && schema.field_index("return_number").is_some();
    let class = find(&["classification", "class", "label"]).map(|i| Attr::Class(i, las_low_bits));
    (intensity, class)
}

/// Reads the chosen points of `path` (`chosen` indexes the kept points, ascending; `None` keeps
/// all, and the faces too). `keep_all` counts every point as kept (a result, a mesh, an organized
/// cloud); otherwise points failing [`in_range`] are skipped as the pipeline drops them.
/// Returns the side and the number of kept points seen.
fn read_side(
    path: &Path,
    ext: &str,
    chosen: Option<&[u64]>,
    keep_all: Option<bool>,
) -> Result<(Side, u64), JobsError> {
    let io = |e: IoError| JobsError::Internal(format!("preview: {e}"));
    let mut source = crate::io::open(path, Some(format_of(ext)?)).map_err(io)?;
    let info = source.info().clone();
    let keep_all = keep_all.unwrap_or(info.has_faces() || info.is_organized());
    let (ia, ca) = attrs(&info.schema);
    let mut side = Side {
        intensity: ia.map(|_| Vec::new()),
        class: ca.map(|_| Vec::new()),
        ..Side::default()
    };
    let mut batch = PointBatch::default();
    let (mut kept, mut next) = (0u64, 0usize);
    loop {
        let n = source.read_batch(&mut batch, BATCH).map_err(io)?;
        if n == 0 {
            break;
        }
        for k in 0..n {
            let p = batch.positions[k];
            if !keep_all && !in_range(p) {
                continue;
            }
            let j = kept;
            kept += 1;
            let take = match chosen {
                None => true,
                Some(c) => {
                    if c.get(next) == Some(&j) {
                        next += 1;
                        true
                    } else {
                        false
                    }
                }
            };
            if !take {
                continue;
            }
            side.positions.push(p);
            let rec = batch.record(k);
            if let (Some(Attr::Intensity(i)), Some(v)) = (ia, side.intensity.as_mut()) {
                v.push(info.schema.get_f64(rec, i) as f32);
            }
            if let (Some(Attr::Class(i, low)), Some(v)) = (ca, side.class.as_mut()) {
                let c = info.schema.get_f64(rec, i).clamp(0.0, 255.0) as u8;
                v.push(if low { c & 0x1f } else { c });
            }
        }
    }
    let extras = source.finish().map_err(io)?;
    side.unit =
        crate::io::crs::Crs::of_file(&info.meta, Some(&extras.trailer)).and_then(|c| c.unit);
    if chosen.is_none() {
        side.faces = extras.faces;
    }
    Ok((side, kept))
}

/// Fans every polygon into triangles.
fn triangles(faces: &Faces) -> Vec<[u32; 3]> {
    let mut out = Vec::with_capacity(faces.len());
    for f in faces.iter() {
        for w in 1..f.len().saturating_sub(1) {
            out.push([f[0], f[w], f[w + 1]]);
        }
    }
    out
}

/// The value at quantile `q` of sorted `v` (nearest rank).
fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let i = ((v.len() - 1) as f64 * q).round() as usize;
    v[i.min(v.len() - 1)]
}

/// Writes one side as binary little-endian PLY.
fn write_ply(
    target: &Path,
    side: &Side,
    origin: DVec3,
    displacement: Option<&[f32]>,
    tris: &[[u32; 3]],
    label: &str,
) -> Result<(), JobsError> {
    let fail = |e: std::io::Error| JobsError::io(format!("write {}", target.display()), e);
    let mut f =
        AtomicFile::create(target).map_err(|e| JobsError::Internal(format!("preview: {e}")))?;
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment qemd preview ({label}); positions relative \
         to origin {} {} {}\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n",
        origin.x,
        origin.y,
        origin.z,
        side.positions.len()
    );
    if displacement.is_some() {
        header.push_str("property float displacement\n");
    }
    if side.intensity.is_some() {
        header.push_str("property float intensity\n");
    }
    if side.class.is_some() {
        header.push_str("property uchar class\n");
    }
    if !tris.is_empty() {
        header.push_str(&format!(
            "element face {}\nproperty list uchar int vertex_indices\n",
            tris.len()
        ));
    }
    header.push_str("end_header\n");
    f.write_all(header.as_bytes()).map_err(fail)?;
    let mut rec = Vec::with_capacity(24);
    for (i, p) in side.positions.iter().enumerate() {
        rec.clear();
        let r = *p - origin;
        for c in [r.x, r.y, r.z] {
            rec.extend_from_slice(&(c as f32).to_le_bytes());
        }
        if let Some(d) = displacement {
            rec.extend_from_slice(&d[i].to_le_bytes());
        }
        if let Some(v) = &side.intensity {
            rec.extend_from_slice(&v[i].to_le_bytes());
        }
        if let Some(v) = &side.class {
            rec.push(v[i]);
        }
        f.write_all(&rec).map_err(fail)?;
    }
    for t in tris {
        rec.clear();
        rec.push(3);
        for &v in t {
            rec.extend_from_slice(&(v as i32).to_le_bytes());
        }
        f.write_all(&rec).map_err(fail)?;
    }
    f.commit()
        .map_err(|e| JobsError::Internal(format!("preview: {e}")))
}

/// Keeps the entries of `side` whose `keep` flag is set.
fn retain(side: &mut Side, keep: &[bool]) {
    let mut it = keep.iter();
    side.positions.retain(|_| *it.next().unwrap_or(&true));
    if let Some(v) = side.intensity.as_mut() {
        let mut it = keep.iter();
        v.retain(|_| *it.next().unwrap_or(&true));
    }
    if let Some(v) = side.class.as_mut() {
        let mut it = keep.iter();
        v.retain(|_| *it.next().unwrap_or(&true));
    }
}

/// Builds the preview of a job into `dir` from its input and result.
///
/// # Errors
/// The files cannot be read or written, or the input and the result disagree on the number of
/// points the report states.
pub fn build(
    dir: &Path,
    input: (&Path, &str),
    result: (&Path, &str),
    report: &Report,
    cap: u64,
) -> Result<PreviewMeta, JobsError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| JobsError::io(format!("create {}", dir.display()), e))?;
    let kept_in = report.points_in.saturating_sub(report.dropped_non_finite);
    let paired = report.outliers != OutlierMode::Remove || report.outliers_found == 0;
    let chosen_in = select(kept_in, cap);
    let whole = kept_in <= cap;
    let chosen_before = (!whole).then_some(chosen_in.as_slice());
    let (mut before, seen_in) = read_side(input.0, input.1, chosen_before, None)?;
    let chosen_out;
    let chosen_after = if paired {
        chosen_before
    } else {
        chosen_out = select(report.points_out, cap);
        (report.points_out > cap).then_some(chosen_out.as_slice())
    };
    let (mut after, seen_out) = read_side(result.0, result.1, chosen_after, Some(true))?;
    let disagree = |what: &str, seen: u64, want: u64| {
        JobsError::Internal(format!(
            "preview: the {what} has {seen} points, the report {want}"
        ))
    };
    if seen_in != kept_in {
        return Err(disagree("input", seen_in, kept_in));
    }
    if seen_out != report.points_out {
        return Err(disagree("result", seen_out, report.points_out));
    }
    let faces = before.faces.take().or(after.faces.take());
    let mesh = whole && faces.is_some();
    let tris = faces.as_ref().map(triangles).unwrap_or_default();
    // Points that are not finite on either side (organized clouds keep NaN placeholders) cannot
    // be drawn; a mesh keeps every vertex so that face indices stay valid.
    let mut displacement = None;
    if paired {
        if before.positions.len() != after.positions.len() {
            return Err(disagree(
                "result preview",
                after.positions.len() as u64,
                before.positions.len() as u64,
            ));
        }
        if !mesh {
            let keep: Vec<bool> = before
                .positions
                .iter()
                .zip(&after.positions)
                .map(|(a, b)| a.is_finite() && b.is_finite())
                .collect();
            retain(&mut before, &keep);
            retain(&mut after, &keep);
        }
        let d: Vec<f64> = before
            .positions
            .iter()
            .zip(&after.positions)
            .map(|(a, b)| a.distance(*b))
            .collect();
        displacement = Some(d);
    } else {
        for s in [&mut before, &mut after] {
            let keep: Vec<bool> = s.positions.iter().map(|p| p.is_finite()).collect();
            retain(s, &keep);
        }
    }
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for p in before.positions.iter().filter(|p| p.is_finite()) {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    if before.positions.is_empty() {
        (lo, hi) = (DVec3::ZERO, DVec3::ZERO);
    }
    let origin = (lo + hi) * 0.5;
    let stats = displacement.as_ref().map(|d| {
        let mut s: Vec<f64> = d.iter().copied().filter(|x| x.is_finite()).collect();
        s.sort_unstable_by(f64::total_cmp);
        DisplacementStats {
            mean: s.iter().sum::<f64>() / s.len().max(1) as f64,
            p50: quantile(&s, 0.5),
            p95: quantile(&s, 0.95),
            p99: quantile(&s, 0.99),
            max: s.last().copied().unwrap_or(0.0),
        }
    });
    let d32: Option<Vec<f32>> = displacement.map(|d| d.iter().map(|&x| x as f32).collect());
    write_ply(
        &dir.join("before.ply"),
        &before,
        origin,
        d32.as_deref(),
        if mesh { &tris } else { &[] },
        "before",
    )?;
    write_ply(
        &dir.join("after.ply"),
        &after,
        origin,
        d32.as_deref(),
        if mesh { &tris } else { &[] },
        "after",
    )?;
    let meta = PreviewMeta {
        kind: if mesh { "mesh" } else { "points" }.into(),
        points_total: kept_in,
        points_before: before.positions.len() as u64,
        points_after: after.positions.len() as u64,
        triangles: if mesh { tris.len() as u64 } else { 0 },
        paired,
        origin: origin.to_array(),
        min: lo.to_array(),
        max: hi.to_array(),
        intensity: before.intensity.is_some() && after.intensity.is_some(),
        class: before.class.is_some() && after.class.is_some(),
        displacement: stats,
        units: before.unit.map(|u| u.symbol().to_string()),
        selection: if whole {
            "every point".into()
        } else {
            format!("the {cap} point indices with the smallest SplitMix64 hash")
        },
        max_points: cap,
    };
    let json = serde_json::to_vec_pretty(&meta)
        .map_err(|e| JobsError::Internal(format!("preview: {e}")))?;
    let target = dir.join("preview.json");
    let mut f =
        AtomicFile::create(&target).map_err(|e| JobsError::Internal(format!("preview: {e}")))?;
    f.write_all(&json)
        .map_err(|e| JobsError::io(format!("write {}", target.display()), e))?;
    f.commit()
        .map_err(|e| JobsError::Internal(format!("preview: {e}")))?;
    Ok(meta)
}

/// One preview build at a time: a build reads two whole files; a second request for the same
/// job waits and then finds it built.
static BUILDING: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

impl Jobs {
    /// The preview of job `id` of `tenant`, built on first use.
    ///
    /// # Errors
    /// [`JobsError::NoSuch`] (another tenant's job too), [`JobsError::WrongState`] while the job
    /// is not successful, build failures.
    pub async fn preview(&self, tenant: &str, id: &str) -> Result<PreviewFiles, JobsError> {
        // The result first: it answers 409 until the job is successful, and a successful row
        // read after it has its report (read the other way round, a job finishing in between
        // gave a row without a report and a 500: the flaky test of issue 13).
        let result = self.result(tenant, id).await?;
        let info = self.job(tenant, id).await?;
        let row = info.row;
        let report = row.report.clone().ok_or_else(|| {
            JobsError::Internal(format!("job {id} is successful but has no report"))
        })?;
        let (t, up) = (tenant.to_string(), row.upload.clone());
        let upload =
            self.db(move |s| s.upload(Some(&t), &up))
                .await?
                .ok_or(JobsError::WrongState {
                    detail: format!("the input of job {id} was deleted; there is no preview"),
                    offset: None,
                })?;
        let in_format = upload
            .format
            .ok_or_else(|| JobsError::Internal(format!("upload {} has no format", upload.id)))?;
        let in_path = self.upload_path(&upload.id, in_format);
        let dir = self.job_dir(id).join(DIR);
        let files = |meta| PreviewFiles {
            meta,
            before: dir.join("before.ply"),
            after: dir.join("after.ply"),
        };
        let cap = self.settings().preview_points;
        if let Some(meta) = read_meta(&dir, cap).await {
            return Ok(files(meta));
        }
        let _one = BUILDING.lock().await;
        if let Some(meta) = read_meta(&dir, cap).await {
            return Ok(files(meta));
        }
        let (d, rp, rf) = (dir.clone(), result.path.clone(), result.format);
        let started = std::time::Instant::now();
        let meta = bridge::blocking(move || {
            build(
                &d,
                (&in_path, in_format.name()),
                (&rp, rf.name()),
                &report,
                cap,
            )
        })
        .await??;
        // A job dismissed while its preview was built has lost its directory: answer as for any
        // dismissed job.
        let again = self.job(tenant, id).await?;
        if again.row.status != Status::Successful {
            return Err(JobsError::NoSuch("job"));
        }
        tracing::info!(
            job = id,
            points = meta.points_before,
            ms = started.elapsed().as_millis() as u64,
            "preview built"
        );
        Ok(files(meta))
    }
}

/// The built preview's description, unless it is missing, unreadable or built with another
/// bound (then it is built again).
async fn read_meta(dir: &Path, cap: u64) -> Option<PreviewMeta> {
    let bytes = tokio::fs::read(dir.join("preview.json")).await.ok()?;
    serde_json::from_slice::<PreviewMeta>(&bytes)
        .ok()
        .filter(|m| m.max_points == cap)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selection_is_bounded_sorted_and_deterministic() {
        assert_eq!(select(5, 10), vec![0, 1, 2, 3, 4]);
        let a = select(100_000, 1_000);
        assert_eq!(a.len(), 1_000);
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(a, select(100_000, 1_000));
        // Spread over the whole range, not a prefix.
        assert!(*a.last().unwrap() > 90_000 && a[0] < 10_000);
        // Exactly the bottom-k of the hashes.
        let worst = a.iter().map(|&i| mix(i)).max().unwrap();
        let below = (0..100_000u64).filter(|&i| mix(i) <= worst).count();
        assert_eq!(below, 1_000);
    }

    #[test]
    fn polygons_fan_into_triangles() {
        let mut f = Faces::new();
        f.push(&[0, 1, 2, 3]);
        f.push(&[4, 5, 6]);
        assert_eq!(triangles(&f), vec![[0, 1, 2], [0, 2, 3], [4, 5, 6]]);
    }
}
