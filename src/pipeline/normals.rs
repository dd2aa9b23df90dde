//! Normals stored in the input are never written back stale.
//!
//! # Brief overview
//!
//! Denoising moves points, so normals stored with them (PLY and OFF `nx ny nz`, PCD
//! `normal_x normal_y normal_z`, text columns of those names, OBJ `vn` lines) no longer describe
//! the surface. What the output gets instead:
//!
//! * **Meshes: recomputed** from the denoised faces. Per-vertex normal fields get the
//!   area-weighted vertex normal; OBJ `vn` lines get the area-weighted sum of the face normals
//!   of every face corner that references them (so split normals along sharp edges stay split).
//!   The face winding orients them; when most stored normals point the other way (a file whose
//!   normals disagree with its winding), all new ones are turned to match. A normal with nothing
//!   to compute it from (an unreferenced vertex or `vn`) stays.
//! * **Point clouds: cleared** (NaN; 0 in an integer field), with a warning. A cloud's normals
//!   would need a k-NN pass over the denoised points, which the tiled path does not have, and
//!   both paths must write the same bytes. Recompute them downstream (PDAL `filters.normal`,
//!   Open3D `estimate_normals`, PCL `NormalEstimation`) — or ask for the run's own:
//! * **Point clouds with `--write-normals`: written.** The normals of the run's last cycle
//!   ([`crate::denoise::written`]) go into the stored normal fields (and new ones where the
//!   input has none), so a stored set is replaced, never doubled.

use glam::DVec3;

use crate::denoise::NormalWeighting;
use crate::denoise::normals::{face_cross, vertex_normals};
use crate::io::obj::{obj_normals, set_obj_normals};
use crate::io::{Cloud, Meta, Trailer};
use crate::points::{Faces, Schema};

/// What happened to the input's stored normals.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NormalsAction {
    /// The input stores no normals.
    #[default]
    None,
    /// Recomputed from the denoised geometry (meshes).
    Recomputed,
    /// Cleared to NaN (point clouds).
    Cleared,
    /// The run's normals written as fields (point clouds with `--write-normals`), into the
    /// stored ones where the input had them.
    Written,
}

/// The per-point normal fields of `schema`: `nx ny nz` or `normal_x normal_y normal_z`.
pub fn normal_fields(schema: &Schema) -> Option<[usize; 3]> {
    [["nx", "ny", "nz"], ["normal_x", "normal_y", "normal_z"]]
        .iter()
        .find_map(|names| {
            Some([
                schema.field_index(names[0])?,
                schema.field_index(names[1])?,
                schema.field_index(names[2])?,
            ])
        })
}

/// True when most of the `new` normals point against the stored `old` ones (a file whose
/// stored normals follow the opposite winding): then all are turned.
fn flip_all(pairs: impl Iterator<Item = (DVec3, DVec3)>) -> bool {
    let (mut against, mut with) = (0u64, 0u64);
    for (new, old) in pairs {
        if !old.is_finite() || new == DVec3::ZERO {
            continue;
        }
        let d = new.dot(old);
        against += (d < 0.0) as u64;
        with += (d > 0.0) as u64;
    }
    against > with
}

/// Recomputes the stored normals of a denoised mesh (`cloud.positions` already moved).
pub fn recompute_mesh(cloud: &mut Cloud) -> NormalsAction {
    let Some(faces) = cloud.extras.faces.clone() else {
        return NormalsAction::None;
    };
    let mut action = NormalsAction::None;
    let schema = cloud.info.schema.clone();
    if let Some(f) = normal_fields(&schema)
        && schema.record_len > 0
    {
        let vn = vertex_normals(&cloud.positions, &faces, NormalWeighting::Area).normals;
        let old = |rec: &[u8]| {
            DVec3::new(
                schema.get_f64(rec, f[0]),
                schema.get_f64(rec, f[1]),
                schema.get_f64(rec, f[2]),
            )
        };
        let records = cloud.records.chunks_exact(schema.record_len);
        let sign = if flip_all(vn.iter().copied().zip(records.map(old))) {
            -1.0
        } else {
            1.0
        };
        for (rec, n) in cloud.records.chunks_exact_mut(schema.record_len).zip(vn) {
            if n == DVec3::ZERO {
                continue;
            }
            let n = sign * n;
            for (axis, &i) in f.iter().enumerate() {
                schema.set_f64(rec, i, n[axis]);
            }
        }
        action = NormalsAction::Recomputed;
    }
    if let (Meta::Obj(meta), Trailer::Obj(trailer)) =
        (&mut cloud.info.meta, &mut cloud.extras.trailer)
    {
        let stored = obj_normals(meta, trailer);
        if !stored.normals.is_empty() {
            let new = corner_normals(&cloud.positions, &faces, &stored.corners, &stored.normals);
            set_obj_normals(meta, trailer, &new);
            action = NormalsAction::Recomputed;
        }
    }
    action
}

/// The `vn` values recomputed from the faces whose corners reference them.
fn corner_normals(
    pos: &[DVec3],
    faces: &Faces,
    corners: &[Option<usize>],
    old: &[DVec3],
) -> Vec<DVec3> {
    let mut acc = vec![DVec3::ZERO; old.len()];
    let mut corner = corners.iter();
    for f in faces.iter() {
        let n = face_cross(pos, f);
        for _ in f {
            if let Some(Some(vn)) = corner.next()
                && *vn < acc.len()
            {
                acc[*vn] += n;
            }
        }
    }
    // No face references a `vn` (the per-vertex convention, `f 1 2 3` with one `vn` per `v`):
    // vertex i's normal goes to `vn` i.
    if corners.iter().all(Option::is_none) && old.len() == pos.len() {
        acc = vertex_normals(pos, faces, NormalWeighting::Area).normals;
    }
    let unit: Vec<DVec3> = acc.iter().map(|a| a.normalize_or_zero()).collect();
    let sign = if flip_all(unit.iter().copied().zip(old.iter().copied())) {
        -1.0
    } else {
        1.0
    };
    unit.iter()
        .zip(old)
        .map(|(&n, &o)| if n == DVec3::ZERO { o } else { sign * n })
        .collect()
}

/// Clears the normal fields `f` of every record in `records` (NaN, or 0 in integer fields).
pub fn clear_points(schema: &Schema, f: [usize; 3], record: &mut [u8]) {
    for &i in &f {
        let v = if schema.fields[i].ty.is_float() {
            f64::NAN
        } else {
            0.0
        };
        schema.set_f64(record, i, v);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::points::{Endian, ScalarType};

    #[test]
    fn fields_by_name() {
        let s = Schema::packed(
            &[
                ("x", ScalarType::F32),
                ("y", ScalarType::F32),
                ("z", ScalarType::F32),
                ("normal_x", ScalarType::F32),
                ("normal_y", ScalarType::F32),
                ("normal_z", ScalarType::F32),
            ],
            Endian::Little,
        )
        .unwrap();
        assert_eq!(normal_fields(&s), Some([3, 4, 5]));
        let mut rec = vec![0u8; s.record_len];
        clear_points(&s, [3, 4, 5], &mut rec);
        assert!(s.get_f64(&rec, 4).is_nan());
        assert_eq!(normal_fields(&Schema::xyz_only(ScalarType::F64)), None);
    }
}
