//! Issue 11, Kubernetes: the manifests of a planned job, checked against golden files in
//! `tests/k8s/` (regenerate with `QEMD_BLESS=1 cargo test k8s::`). That the binary honours every
//! field they set is checked by running their pods' commands against a real S3 server in
//! `tests/s3.rs` (`issue11_s3_k8s_manifests_run_as_their_pods_would`).

use std::path::Path;

use qem_denoise::k8s::{K8sOptions, manifests};
use qem_denoise::pipeline::scaleout::{Phase, WorkUrl};

#[test]
fn issue11_k8s_manifests_match_the_golden_files() {
    let work = WorkUrl::parse("s3://scans/jobs/survey-7").unwrap();
    let tasks = |p: Phase| match p {
        Phase::Partition | Phase::Stitch => 1,
        Phase::Globals | Phase::Tiles => 24,
    };
    let opts = K8sOptions {
        name: Some("survey-7".into()),
        namespace: Some("lidar".into()),
        image: "registry.example.com/qemd:0.1.0".into(),
        secret: "survey-s3".into(),
        parallelism: 16,
        backoff_per_index: 2,
        cpus: 4,
    };
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/k8s");
    let bless = std::env::var_os("QEMD_BLESS").is_some();
    let got = manifests(&work, tasks, 2 << 30, &opts).unwrap();
    assert_eq!(got.len(), 4);
    for m in &got {
        let path = dir.join(m.file_name());
        let yaml = m.to_yaml().unwrap();
        if bless {
            std::fs::write(&path, &yaml).unwrap();
        }
        let want = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("{}: {e} (QEMD_BLESS=1 writes it)", path.display()));
        assert_eq!(yaml, want, "{} differs", path.display());
    }
}
