//! Golden agreement: the operators reproduce the reference outputs in `../shared/golden` per
//! vertex within 1e-9·L (EVALUATION.md, "Golden files").

use std::path::Path;

use glam::DVec3;
use qem_denoise::denoise::{Method, NormalWeighting, Params, SolveKind, denoise};
use qem_denoise::io::Cloud;

const GOLDEN: &str = "../shared/golden";
/// Mean edge length of the clean bunny, as EVALUATION.md gives it.
const L: f64 = 0.00147062152731;

fn read(name: &str) -> Cloud {
    Cloud::read(&Path::new(GOLDEN).join(name), None).unwrap()
}

/// Runs `params` on the noisy golden input and compares with `expected`; returns the worst
/// per-vertex deviation in units of L and how many vertices exceed `tol`.
fn compare(params: &Params, expected: &str, tol: f64) -> (f64, usize, usize) {
    let noisy = read("bunny_iso20_seed0_noisy.ply");
    let want = read(expected);
    let faces = if params.knn.is_some() {
        None
    } else {
        noisy.faces()
    };
    let got = denoise(&noisy.positions, faces, params).unwrap().positions;
    assert_eq!(got.len(), want.positions.len());
    let mut worst = 0.0f64;
    let mut bad = 0;
    let mut worst_i = 0;
    for (i, (g, w)) in got.iter().zip(&want.positions).enumerate() {
        let d = (*g - *w).length() / L;
        if d > tol {
            bad += 1;
        }
        if d > worst {
            worst = d;
            worst_i = i;
        }
    }
    (worst, bad, worst_i)
}

fn assert_golden(params: Params, expected: &str) {
    let (worst, bad, at) = compare(&params, expected, 1e-9);
    assert_eq!(
        bad, 0,
        "{expected}: {bad} vertices deviate by more than 1e-9·L (worst {worst:e}·L at vertex {at})"
    );
}

#[test]
#[ignore = "needs ../shared"]
fn golden_qem_plain_mean_normals_k2() {
    assert_golden(
        Params {
            rings: 2,
            normals: NormalWeighting::Mean,
            solve: SolveKind::Plain,
            ..Params::paper()
        },
        "out_qem_plain_avg_k2.ply",
    );
}

#[test]
#[ignore = "needs ../shared"]
fn golden_qem_plain_area_normals_k2() {
    assert_golden(
        Params {
            rings: 2,
            normals: NormalWeighting::Area,
            solve: SolveKind::Plain,
            ..Params::paper()
        },
        "out_qem_plain_area_k2.ply",
    );
}

#[test]
#[ignore = "needs ../shared"]
fn golden_qem_robust_mean_normals_k2() {
    // EVALUATION.md: vertices whose eigenvalue ratio is within 1e-9 of ε may differ; none does
    // on this input, so the comparison is strict.
    assert_golden(
        Params {
            rings: 2,
            normals: NormalWeighting::Mean,
            solve: SolveKind::Robust,
            eps: 1e-2,
            ..Params::paper()
        },
        "out_qem_robust1e-2_avg_k2.ply",
    );
}

#[test]
#[ignore = "needs ../shared"]
fn golden_qem_points_k16() {
    assert_golden(
        Params {
            knn: Some(16),
            solve: SolveKind::Plain,
            ..Params::paper()
        },
        "out_qem_points_k16.ply",
    );
}

#[test]
#[ignore = "needs ../shared"]
fn golden_bilateral_3_iterations() {
    assert_golden(
        Params {
            method: Method::Bilateral,
            iterations: 3,
            ..Params::default()
        },
        "out_bilateral_r1_3it.ply",
    );
}

#[test]
#[ignore = "needs ../shared"]
fn golden_input_is_what_evaluation_md_describes() {
    let noisy = read("bunny_iso20_seed0_noisy.ply");
    assert_eq!(noisy.len(), 35_947);
    assert_eq!(noisy.faces().unwrap().len(), 69_451);
    assert!(noisy.positions.iter().all(|p: &DVec3| p.is_finite()));
}
