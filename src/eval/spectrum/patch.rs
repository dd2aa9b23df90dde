//! The test patch of the frequency-response experiment: a jittered grid lifted by a height field
//! with waves, a ridge, a mesa and a cone ([`height_patch`]).

use std::f64::consts::PI;

use glam::DVec3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::eval::{EvalError, Mesh};
use crate::points::Faces;

/// Largest jitter of an interior vertex along x and y, in cells.
pub const JITTER: f64 = 0.2;

/// A triangulated height field over `[0, cells]²`: vertex (i, j) sits at (i, j) plus, inside,
/// a seeded jitter of up to `jitter` cells along x and y, lifted to z = `height(x, y)`; each cell
/// is split along the same diagonal, faces oriented towards +z.
///
/// # Errors
/// [`EvalError::Param`] for fewer than one or more than 4096 cells, or a jitter outside
/// [0, 0.45]; [`EvalError::NonFinite`] when `height` is not finite at a vertex.
pub fn height_field_mesh(
    cells: usize,
    jitter: f64,
    seed: u64,
    height: impl Fn(f64, f64) -> f64,
) -> Result<Mesh, EvalError> {
    if !(1..=4096).contains(&cells) {
        return Err(EvalError::Param {
            name: "patch",
            detail: format!("cells per side must be in 1..=4096, got {cells}"),
        });
    }
    if !(0.0..=0.45).contains(&jitter) {
        return Err(EvalError::Param {
            name: "jitter",
            detail: format!("must be in [0, 0.45] cells, got {jitter}"),
        });
    }
    let side = cells + 1;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut positions = Vec::with_capacity(side * side);
    for j in 0..side {
        for i in 0..side {
            let (mut x, mut y) = (i as f64, j as f64);
            let inside = i > 0 && j > 0 && i < cells && j < cells;
            if inside && jitter > 0.0 {
                x += rng.random_range(-jitter..=jitter);
                y += rng.random_range(-jitter..=jitter);
            }
            let z = height(x, y);
            if !z.is_finite() {
                return Err(EvalError::NonFinite {
                    what: "height field",
                    index: positions.len(),
                });
            }
            positions.push(DVec3::new(x, y, z));
        }
    }
    let id = |i: usize, j: usize| (j * side + i) as u32;
    let mut tris = Vec::with_capacity(2 * cells * cells);
    for j in 0..cells {
        for i in 0..cells {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            tris.push([a, b, c]);
            tris.push([a, c, d]);
        }
    }
    Ok(Mesh {
        positions,
        faces: Faces::from_triangles(&tris),
    })
}

/// The height of the test patch at (x, y) for a patch of `cells` cells (all sizes relative to
/// the side w):
///
/// * low-frequency waves, 1.5 and 1 periods across, amplitude 0.04 w;
/// * a ridge through the centre at 30°, half-width 0.12 w, height 0.06 w: creases at its crest
///   and feet;
/// * a mesa (a truncated cone: plateau of radius 0.06 w, foot 0.14 w, height 0.05 w) and a conical
///   pit (radius 0.1 w, depth 0.04 w): circular creases and a point, so that sharp features of
///   every orientation are present.
pub fn patch_height(x: f64, y: f64, cells: usize) -> f64 {
    let w = cells as f64;
    let waves = 0.04 * w * (2.0 * PI * 1.5 * x / w).sin() * (2.0 * PI * y / w).cos();
    let (s, c) = (PI / 6.0).sin_cos();
    let d = (x - 0.5 * w) * s - (y - 0.5 * w) * c;
    let ridge = 0.06 * w * (1.0 - d.abs() / (0.12 * w)).max(0.0);
    let r = (x - 0.3 * w).hypot(y - 0.75 * w);
    let mesa = 0.05 * w * ((0.14 * w - r) / (0.08 * w)).clamp(0.0, 1.0);
    let q = (x - 0.72 * w).hypot(y - 0.28 * w);
    let pit = -0.04 * w * (1.0 - q / (0.1 * w)).max(0.0);
    waves + ridge + mesa + pit
}

/// The test patch of the frequency-response experiment ([`patch_height`] on a jittered grid).
///
/// # Errors
/// As [`height_field_mesh`].
pub fn height_patch(cells: usize, seed: u64) -> Result<Mesh, EvalError> {
    height_field_mesh(cells, JITTER, seed, |x, y| patch_height(x, y, cells))
}
