//! Real benchmark pairs: published clean/noisy meshes with the same connectivity (vertex i of the
//! noisy mesh is vertex i of the clean one), denoised by a list of methods and measured against
//! the clean mesh (`ang_deg`, and `surf_std` in % of the clean mesh's L).
//!
//! [`benchmark_pairs`] lists the pairs of `../shared/data/meshes/pairs` (see its `MANIFEST.md`)
//! with the numbers the GCN-Denoiser paper (Shen et al. 2022) publishes for its two pairs.
//! [`run_pairs`] skips, with a note, the pairs whose files are absent, so a report can be made
//! where the data is not.

use std::path::{Path, PathBuf};

use glam::DVec3;

use super::EvalError;
use super::metrics::{Metrics, Reference};
use super::table::TableMethod;
use crate::denoise::denoise;
use crate::io::Cloud;
use crate::points::Faces;

/// Where the pairs are, relative to the repository root (CI runs there with `../shared` beside it).
pub const DEFAULT_DIR: &str = "../shared/data/meshes/pairs";

/// Numbers a publication reports for a pair.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Published {
    /// Who reports them.
    pub source: String,
    /// Mean face-normal angle in degrees.
    pub ang_deg: f64,
    /// Surface error in % of L.
    pub surf_std: f64,
}

/// A clean/noisy pair of files.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pair {
    /// Short name.
    pub name: String,
    /// Clean mesh file name (in the pairs directory).
    pub clean: String,
    /// Noisy mesh file name.
    pub noisy: String,
    /// Published results of another method on this pair, if any.
    pub published: Option<Published>,
}

impl Pair {
    fn new(name: &str, clean: &str, noisy: &str) -> Pair {
        Pair {
            name: name.into(),
            clean: clean.into(),
            noisy: noisy.into(),
            published: None,
        }
    }

    fn gcn(mut self, ang_deg: f64, surf_std: f64) -> Pair {
        self.published = Some(Published {
            source: "GCN-Denoiser (Shen et al. 2022, published)".into(),
            ang_deg,
            surf_std,
        });
        self
    }
}

/// The pairs of `../shared/data/meshes/pairs`.
pub fn benchmark_pairs() -> Vec<Pair> {
    vec![
        Pair::new("cnr_block_n1", "cnr_block_gt.obj", "cnr_block_n1_noisy.obj"),
        Pair::new(
            "l0_block_0.4",
            "l0_block_0.4_original.obj",
            "l0_block_0.4_noisy.obj",
        ),
        Pair::new(
            "l0_fandisk_0.3",
            "l0_fandisk_original.obj",
            "l0_fandisk_0.3_noisy.obj",
        ),
        Pair::new(
            "l0_julius_0.2",
            "l0_julius_0.2_original.obj",
            "l0_julius_0.2_noisy.obj",
        ),
        Pair::new(
            "l0_twelve_0.5imp",
            "l0_twelve_0.5imp_original.obj",
            "l0_twelve_0.5imp_noisy.obj",
        ),
        Pair::new(
            "gcn_fandisk_n6",
            "gcn_fandisk_gt.obj",
            "gcn_fandisk_gaus_n6_noisy.obj",
        )
        .gcn(3.95, 10.8),
        Pair::new(
            "gcn_fertility_n3",
            "gcn_fertility_gt.obj",
            "gcn_fertility_gaus_n3_noisy.obj",
        )
        .gcn(4.01, 8.4),
    ]
}

/// One method's result on a pair.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PairRow {
    /// Method name (`noisy` for the input).
    pub method: String,
    /// Its metrics against the clean mesh.
    pub metrics: Metrics,
}

/// The results on one pair.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PairResult {
    /// The pair.
    pub pair: Pair,
    /// Vertices.
    pub vertices: usize,
    /// Faces.
    pub faces: usize,
    /// The clean mesh's L.
    #[serde(rename = "L")]
    pub l: f64,
    /// The noisy input first, then the methods in order.
    pub rows: Vec<PairRow>,
}

/// What [`run_pairs`] did.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PairsOutcome {
    /// The directory searched.
    pub dir: PathBuf,
    /// Results of the pairs found, in list order.
    pub results: Vec<PairResult>,
    /// A note per pair (or for the whole directory) that was skipped.
    pub skipped: Vec<String>,
}

fn read_mesh(path: &Path) -> Result<(Vec<DVec3>, Faces), EvalError> {
    let cloud = Cloud::read(path, None)?;
    let faces = cloud
        .faces()
        .filter(|f| !f.is_empty())
        .cloned()
        .ok_or_else(|| EvalError::Empty {
            what: "benchmark mesh",
            detail: format!("{} has no faces", path.display()),
        })?;
    Ok((cloud.positions, faces))
}

/// Denoises and measures every pair found in `dir` with every method; pairs whose files are
/// absent (or all of them, if `dir` is not a directory) are skipped with a note. `log` hears of
/// every pair started.
///
/// # Errors
/// A file that exists but cannot be read, a pair whose meshes do not correspond, a method's
/// failure.
pub fn run_pairs(
    dir: &Path,
    pairs: &[Pair],
    methods: &[TableMethod],
    log: &mut dyn FnMut(&str),
) -> Result<PairsOutcome, EvalError> {
    let mut out = PairsOutcome {
        dir: dir.to_path_buf(),
        results: Vec::new(),
        skipped: Vec::new(),
    };
    if !dir.is_dir() {
        out.skipped.push(format!(
            "{} is not a directory: the benchmark pairs were skipped",
            dir.display()
        ));
        return Ok(out);
    }
    for pair in pairs {
        let (cp, np) = (dir.join(&pair.clean), dir.join(&pair.noisy));
        let missing: Vec<String> = [&cp, &np]
            .into_iter()
            .filter(|p| !p.is_file())
            .map(|p| p.display().to_string())
            .collect();
        if !missing.is_empty() {
            out.skipped.push(format!(
                "{}: skipped, {} not found",
                pair.name,
                missing.join(" and ")
            ));
            continue;
        }
        log(&format!("pair {}", pair.name));
        let (clean, clean_faces) = read_mesh(&cp)?;
        let (noisy, noisy_faces) = read_mesh(&np)?;
        if clean.len() != noisy.len() || clean_faces != noisy_faces {
            return Err(EvalError::Mismatch(format!(
                "{}: {} and {} do not share vertices and faces ({} vs {} vertices)",
                pair.name,
                cp.display(),
                np.display(),
                clean.len(),
                noisy.len()
            )));
        }
        let reference = Reference::new(clean, Some(clean_faces))?;
        let faces = &noisy_faces;
        let mut rows = vec![PairRow {
            method: super::table::NOISY.into(),
            metrics: reference.evaluate(&noisy, Some(faces))?,
        }];
        for m in methods {
            let d = denoise(&noisy, Some(faces), &m.params)?;
            rows.push(PairRow {
                method: m.name.clone(),
                metrics: reference.evaluate(&d.positions, Some(faces))?,
            });
        }
        out.results.push(PairResult {
            pair: pair.clone(),
            vertices: noisy.len(),
            faces: faces.len(),
            l: reference.l(),
            rows,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::denoise::Params;
    use crate::eval::noise::{NoiseSpec, add_noise};
    use crate::eval::synth::Shape;

    #[test]
    #[ignore = "needs ../shared"]
    fn gcn_pairs_are_read_and_denoised() {
        let pairs: Vec<Pair> = benchmark_pairs()
            .into_iter()
            .filter(|p| p.published.is_some())
            .collect();
        assert_eq!(pairs.len(), 2);
        let methods = crate::eval::methods::report_methods();
        let out = run_pairs(Path::new(DEFAULT_DIR), &pairs, &methods, &mut |_| {}).unwrap();
        assert!(out.skipped.is_empty(), "{:?}", out.skipped);
        assert_eq!(out.results.len(), 2);
        for r in &out.results {
            assert_eq!(r.rows.len(), 4);
            let ang = |k: usize| r.rows[k].metrics.ang_deg.unwrap();
            let surf = |k: usize| r.rows[k].metrics.surf_std.unwrap();
            // The default operator improves both measures on both pairs (as measured when the
            // report was made: fandisk 44.7° → 7.6°, fertility 27.3° → 6.1°).
            assert_eq!(r.rows[3].method, "default");
            assert!(
                ang(3) < 0.5 * ang(0),
                "{}: {} vs {}",
                r.pair.name,
                ang(3),
                ang(0)
            );
            assert!(
                surf(3) < 0.6 * surf(0),
                "{}: {} vs {}",
                r.pair.name,
                surf(3),
                surf(0)
            );
        }
    }

    #[test]
    fn a_missing_directory_or_file_is_skipped_with_a_note() {
        let dir = tempfile::tempdir().unwrap();
        let methods = [TableMethod::new("default", Params::default())];
        let none = run_pairs(
            &dir.path().join("absent"),
            &benchmark_pairs(),
            &methods,
            &mut |_| {},
        )
        .unwrap();
        assert!(none.results.is_empty());
        assert!(none.skipped[0].contains("not a directory"));

        // One generated pair present, the published list absent.
        let m = Shape::Sphere.mesh(2).unwrap();
        let noisy = add_noise(&m.positions, Some(&m.faces), &NoiseSpec::default()).unwrap();
        m.clone()
            .into_cloud()
            .write(&dir.path().join("c.ply"), None)
            .unwrap();
        Cloud::generated(
            noisy.positions,
            Some(m.faces.clone()),
            crate::points::ScalarType::F64,
        )
        .write(&dir.path().join("n.ply"), None)
        .unwrap();
        let mut pairs = benchmark_pairs();
        pairs.push(Pair::new("sphere", "c.ply", "n.ply").gcn(1.0, 2.0));
        let mut logged = Vec::new();
        let out = run_pairs(dir.path(), &pairs, &methods, &mut |s| {
            logged.push(s.to_string())
        })
        .unwrap();
        assert_eq!(out.skipped.len(), benchmark_pairs().len());
        assert_eq!(out.results.len(), 1);
        assert_eq!(logged, ["pair sphere"]);
        let r = &out.results[0];
        assert_eq!(r.rows.len(), 2);
        let (before, after) = (&r.rows[0].metrics, &r.rows[1].metrics);
        assert!(after.surf_std.unwrap() < before.surf_std.unwrap());
        assert!(after.ang_deg.unwrap() < before.ang_deg.unwrap());

        // Meshes that do not correspond are an error.
        Shape::Sphere
            .mesh(1)
            .unwrap()
            .into_cloud()
            .write(&dir.path().join("n.ply"), None)
            .unwrap();
        assert!(matches!(
            run_pairs(dir.path(), &pairs, &methods, &mut |_| {}),
            Err(EvalError::Mismatch(_))
        ));
    }
}
