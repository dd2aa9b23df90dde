//! A denoising run's bounds hold in the file it writes, not only in f64: coarse storage (float32
//! UTM coordinates, LAS scales) must not lengthen a move past the operator's reach cap or the
//! user's `--max-move` (issue 9, do no harm).

use std::path::Path;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::util::{qemd_ok, s};
use qem_denoise::io::Cloud;
use qem_denoise::neighbours::brute;

/// A binary little-endian PLY of float x, y, z.
fn ply_f32(points: &[[f64; 3]]) -> Vec<u8> {
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\n\
         property float y\nproperty float z\nend_header\n",
        points.len()
    )
    .into_bytes();
    for p in points {
        for &c in p {
            b.extend_from_slice(&(c as f32).to_le_bytes());
        }
    }
    b
}

/// A 40 × 40 grid at UTM coordinates (x near 5·10⁵ m, float32 steps of 1/32 m; y near 5·10⁶ m,
/// steps of 0.5 m), spacing `spacing`, with iso Gaussian noise `sigma`.
fn utm_plane(spacing: f64, sigma: f64, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut gauss = move || rng.sample::<f64, _>(StandardNormal);
    let mut pts = Vec::new();
    for i in 0..40 {
        for j in 0..40 {
            pts.push([
                512_000.0 + i as f64 * spacing + sigma * gauss(),
                5_123_000.0 + j as f64 * spacing + sigma * gauss(),
                210.0 + 0.05 * i as f64 + sigma * gauss(),
            ]);
        }
    }
    pts
}

/// Each point's displacement from `input` to `output` (same order).
fn moves(input: &Path, output: &Path) -> (Vec<glam::DVec3>, Vec<f64>) {
    let a = Cloud::read(input, None).unwrap();
    let b = Cloud::read(output, None).unwrap();
    assert_eq!(a.len(), b.len());
    let d = a
        .positions
        .iter()
        .zip(&b.positions)
        .map(|(p, q)| (*q - *p).length())
        .collect();
    (a.positions, d)
}

#[test]
fn issue9_max_move_holds_after_float32_rounding() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("utm.ply");
    std::fs::write(&input, ply_f32(&utm_plane(0.4, 0.15, 1))).unwrap();
    let out = dir.path().join("out.ply");
    let cap = 0.07;
    qemd_ok(&[
        "denoise",
        s(&input),
        "-o",
        s(&out),
        "-q",
        "--max-move",
        "0.07",
    ]);
    let (_, d) = moves(&input, &out);
    let moved = d.iter().filter(|&&m| m > 0.0).count();
    let worst = d.iter().copied().fold(0.0, f64::max);
    // Rounded to nearest, x's 1/32 m steps lengthen moves clamped at the cap by up to 1/64 m.
    assert!(
        worst <= cap,
        "a written move of {worst} m past --max-move {cap}"
    );
    assert!(
        moved > 100,
        "only {moved} points moved: the test no longer exercises the cap"
    );
}

#[test]
fn issue9_reach_cap_holds_after_float32_rounding() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("utm.ply");
    // Spacing 0.4 m against y's 0.5 m float32 steps: a y move rounded up to a whole step would
    // pass a quarter of the k-NN radius.
    std::fs::write(&input, ply_f32(&utm_plane(0.4, 0.12, 2))).unwrap();
    let out = dir.path().join("out.ply");
    qemd_ok(&["denoise", s(&input), "-o", s(&out), "-q"]);
    let (pos, d) = moves(&input, &out);
    let mut worst: f64 = 0.0;
    for (i, &m) in d.iter().enumerate() {
        // r16: the farthest of the point's 16 nearest, itself counted (the operator's list).
        let far = *brute::knn(&pos, pos[i], 16).last().unwrap() as usize;
        let r16 = (pos[far] - pos[i]).length();
        worst = worst.max(m / r16);
    }
    assert!(worst <= 0.25 + 1e-9, "a written move of {worst} × r16");
    assert!(d.iter().any(|&m| m > 0.0), "nothing moved");
}

#[test]
fn issue9_las_scale_rounding_keeps_max_move() {
    let dir = tempfile::tempdir().unwrap();
    let xyz = dir.path().join("utm.xyz");
    let text: String = utm_plane(0.4, 0.15, 3)
        .iter()
        .map(|p| format!("{} {} {}\n", p[0], p[1], p[2]))
        .collect();
    std::fs::write(&xyz, text).unwrap();
    // A LAS copy (qemd picks a 1 mm scale for UTM coordinates), denoised LAS to LAS.
    let las = dir.path().join("utm.las");
    qemd_ok(&["noise", s(&xyz), "-o", s(&las), "--level", "0"]);
    let out = dir.path().join("out.las");
    qemd_ok(&[
        "denoise",
        s(&las),
        "-o",
        s(&out),
        "-q",
        "--max-move",
        "0.0305",
    ]);
    let (_, d) = moves(&las, &out);
    let worst = d.iter().copied().fold(0.0, f64::max);
    assert!(worst <= 0.0305 + 1e-9, "a written move of {worst} m");
    assert!(d.iter().filter(|&&m| m > 0.0).count() > 100);
}
