//! Kubernetes manifests for a planned job (feature `k8s`): one `batch/v1` Indexed Job per phase
//! that has tasks, built from k8s-openapi's typed structs and written as YAML (`qemd k8s`).
//!
//! # Brief overview
//!
//! ```text
//!  qemd plan IN --work s3://b/p      the plan: each phase's task count, the memory budget
//!  qemd k8s --work s3://b/p -o DIR   DIR/1-partition.yaml … 4-stitch.yaml
//!  kubectl apply -f DIR/1-partition.yaml; kubectl wait --for=condition=complete job/…; …
//! ```
//!
//! Each Job runs `completions` = the phase's task count pods of the image's `qemd` entrypoint with
//! `worker --work URL --phase P --threads C --json`; Kubernetes sets `JOB_COMPLETION_INDEX` in
//! every pod of an Indexed Job, and the worker takes N from the plan. Credentials come from a
//! Secret as environment variables (`envFrom`: the `AWS_*` variables the S3 client reads);
//! `QEMD_SCRATCH` points the task's download mirror at an `emptyDir`. A failed pod is retried
//! per index (`backoffLimitPerIndex`); an index that keeps failing fails the Job at once
//! (`maxFailedIndexes: 0`), since the next phase cannot run without it. Every field set here is
//! one the binary or the scheduler reads; nothing else is written.
//!
//! Kubernetes has no dependencies between Jobs: the phases are applied in order, each after the
//! previous one completed (docs/SCALE-OUT.md). Only `s3://` work directories are accepted: pods
//! share no file system unless one is arranged for them, and a `file://` job reads its input by a
//! path of the planning machine.

use k8s_openapi::api::batch::v1::{Job, JobSpec};
use k8s_openapi::api::core::v1::{
    Container, EmptyDirVolumeSource, EnvFromSource, EnvVar, PodSpec, PodTemplateSpec,
    ResourceRequirements, SecretEnvSource, Volume, VolumeMount,
};
use k8s_openapi::apimachinery::pkg::api::resource::Quantity;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::ObjectMeta;
use std::collections::BTreeMap;
use thiserror::Error;

use crate::pipeline::scaleout::{Phase, WorkUrl};

/// Default image: the one `docker/Dockerfile` builds, tagged with this version.
pub const DEFAULT_IMAGE: &str = concat!("qemd:", env!("CARGO_PKG_VERSION"));
/// Default Secret holding the `AWS_*` variables.
pub const DEFAULT_SECRET: &str = "qemd-s3";
/// Default pods of one phase at a time.
pub const DEFAULT_PARALLELISM: u32 = 8;
/// Default retries of one index.
pub const DEFAULT_BACKOFF_PER_INDEX: u32 = 3;
/// Default cores per pod (also the worker's `--threads`).
pub const DEFAULT_CPUS: u32 = 2;
/// Memory a pod is given on top of the job's memory budget (the binary, the runtime, the mirror's
/// transfer buffers: eight 8 MiB parts).
pub const MEMORY_HEADROOM: u64 = 512 << 20;
/// Where the task's scratch directory (its mirror of the objects it reads) is mounted.
pub const SCRATCH_MOUNT: &str = "/scratch";

/// Errors of manifest generation.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum K8sError {
    /// The work directory is not one pods can reach.
    #[error(
        "{url}: Kubernetes manifests need an s3://bucket/prefix work directory (pods share no file system)"
    )]
    NotObjectStore {
        /// The work directory.
        url: String,
    },
    /// A name Kubernetes would refuse.
    #[error("job name `{name}`: {why}")]
    Name {
        /// The name.
        name: String,
        /// What is wrong with it.
        why: String,
    },
    /// A count of zero.
    #[error("{what} must be at least 1")]
    Zero {
        /// The option.
        what: &'static str,
    },
    /// YAML serialisation failed.
    #[error("cannot write the manifest as YAML: {0}")]
    Yaml(String),
}

/// What the manifests are made of, besides the plan.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct K8sOptions {
    /// The prefix of every Job's name (`<name>-<phase>`); by default derived from the work URL.
    pub name: Option<String>,
    /// The namespace (unset: the one `kubectl` applies to).
    pub namespace: Option<String>,
    /// The container image (its entrypoint is `qemd`).
    pub image: String,
    /// The Secret whose keys become the pods' environment.
    pub secret: String,
    /// Pods of one phase at a time (capped at the phase's task count).
    pub parallelism: u32,
    /// Retries of one index before the Job fails.
    pub backoff_per_index: u32,
    /// Cores per pod: the CPU request and the worker's `--threads`.
    pub cpus: u32,
}

impl Default for K8sOptions {
    fn default() -> Self {
        K8sOptions {
            name: None,
            namespace: None,
            image: DEFAULT_IMAGE.into(),
            secret: DEFAULT_SECRET.into(),
            parallelism: DEFAULT_PARALLELISM,
            backoff_per_index: DEFAULT_BACKOFF_PER_INDEX,
            cpus: DEFAULT_CPUS,
        }
    }
}

/// One phase's manifest.
#[derive(Debug, Clone)]
pub struct Manifest {
    /// The phase.
    pub phase: Phase,
    /// The Job.
    pub job: Job,
}

impl Manifest {
    /// The file name `qemd k8s -o DIR` writes it as (`1-partition.yaml`…, in the order to apply).
    pub fn file_name(&self) -> String {
        let n = Phase::ALL
            .iter()
            .position(|&p| p == self.phase)
            .unwrap_or(0)
            + 1;
        format!("{n}-{}.yaml", self.phase.name())
    }

    /// The manifest as a YAML document.
    ///
    /// # Errors
    /// [`K8sError::Yaml`] (not expected for these types).
    pub fn to_yaml(&self) -> Result<String, K8sError> {
        serde_norway::to_string(&self.job).map_err(|e| K8sError::Yaml(e.to_string()))
    }
}

/// The default name prefix of a job in `work`: `qemd-` and 10 hex digits of the URL's SHA-256,
/// so the four Job names stay within Kubernetes's 63 characters and differ between work
/// directories.
pub fn default_name(work: &WorkUrl) -> String {
    use sha2::Digest;
    let h = sha2::Sha256::digest(work.to_string().as_bytes());
    let hex: String = h.iter().take(5).map(|b| format!("{b:02x}")).collect();
    format!("qemd-{hex}")
}

/// Kubernetes's rule for a Job name (an RFC 1123 label, with room for the pod suffixes the Job
/// controller adds: at most 52 characters keeps the pods' `job-name` label valid).
fn check_name(name: &str) -> Result<(), K8sError> {
    let why = if name.is_empty() || name.len() > 52 {
        Some("must be 1 to 52 characters".to_string())
    } else if !name
        .bytes()
        .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-')
    {
        Some("only lower-case letters, digits and '-'".to_string())
    } else if name.starts_with('-') || name.ends_with('-') {
        Some("must start and end with a letter or digit".to_string())
    } else {
        None
    };
    match why {
        Some(why) => Err(K8sError::Name {
            name: name.to_string(),
            why,
        }),
        None => Ok(()),
    }
}

/// The manifests of the job planned in `work`: one per phase with tasks (`tasks(phase)`), in the
/// order they are applied. `memory_budget` is the plan's (each pod requests it plus
/// [`MEMORY_HEADROOM`], and is limited to that).
///
/// # Errors
/// A work directory pods cannot reach, a name Kubernetes refuses, a zero count.
pub fn manifests(
    work: &WorkUrl,
    tasks: impl Fn(Phase) -> u64,
    memory_budget: u64,
    opts: &K8sOptions,
) -> Result<Vec<Manifest>, K8sError> {
    if !matches!(work, WorkUrl::S3 { .. }) {
        return Err(K8sError::NotObjectStore {
            url: work.to_string(),
        });
    }
    for (what, v) in [("--parallelism", opts.parallelism), ("--cpus", opts.cpus)] {
        if v == 0 {
            return Err(K8sError::Zero { what });
        }
    }
    let prefix = opts.name.clone().unwrap_or_else(|| default_name(work));
    let memory = Quantity(format!(
        "{}Mi",
        (memory_budget + MEMORY_HEADROOM).div_ceil(1 << 20)
    ));
    let cpu = Quantity(opts.cpus.to_string());
    let mut out = Vec::new();
    for phase in Phase::ALL {
        let n = tasks(phase);
        if n == 0 {
            continue;
        }
        let name = format!("{prefix}-{}", phase.name());
        check_name(&name)?;
        let labels: BTreeMap<String, String> = [
            ("app.kubernetes.io/name", "qemd".to_string()),
            ("app.kubernetes.io/instance", prefix.clone()),
            ("app.kubernetes.io/component", phase.name().to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let count = i32::try_from(n).unwrap_or(i32::MAX);
        let container = Container {
            name: "qemd".into(),
            image: Some(opts.image.clone()),
            args: Some(
                [
                    "worker",
                    "--work",
                    &work.to_string(),
                    "--phase",
                    phase.name(),
                    "--threads",
                    &opts.cpus.to_string(),
                    "--json",
                ]
                .map(String::from)
                .to_vec(),
            ),
            env: Some(vec![EnvVar {
                name: "QEMD_SCRATCH".into(),
                value: Some(SCRATCH_MOUNT.into()),
                ..EnvVar::default()
            }]),
            env_from: Some(vec![EnvFromSource {
                secret_ref: Some(SecretEnvSource {
                    name: opts.secret.clone(),
                    optional: None,
                }),
                ..EnvFromSource::default()
            }]),
            resources: Some(ResourceRequirements {
                requests: Some(
                    [
                        ("cpu".to_string(), cpu.clone()),
                        ("memory".to_string(), memory.clone()),
                    ]
                    .into(),
                ),
                limits: Some([("memory".to_string(), memory.clone())].into()),
                ..ResourceRequirements::default()
            }),
            volume_mounts: Some(vec![VolumeMount {
                name: "scratch".into(),
                mount_path: SCRATCH_MOUNT.into(),
                ..VolumeMount::default()
            }]),
            ..Container::default()
        };
        let job = Job {
            metadata: ObjectMeta {
                name: Some(name),
                namespace: opts.namespace.clone(),
                labels: Some(labels.clone()),
                ..ObjectMeta::default()
            },
            spec: Some(JobSpec {
                completion_mode: Some("Indexed".into()),
                completions: Some(count),
                parallelism: Some(count.min(i32::try_from(opts.parallelism).unwrap_or(i32::MAX))),
                backoff_limit_per_index: Some(
                    i32::try_from(opts.backoff_per_index).unwrap_or(i32::MAX),
                ),
                max_failed_indexes: Some(0),
                template: PodTemplateSpec {
                    metadata: Some(ObjectMeta {
                        labels: Some(labels),
                        ..ObjectMeta::default()
                    }),
                    spec: Some(PodSpec {
                        restart_policy: Some("Never".into()),
                        containers: vec![container],
                        volumes: Some(vec![Volume {
                            name: "scratch".into(),
                            empty_dir: Some(EmptyDirVolumeSource::default()),
                            ..Volume::default()
                        }]),
                        ..PodSpec::default()
                    }),
                },
                ..JobSpec::default()
            }),
            ..Job::default()
        };
        out.push(Manifest { phase, job });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s3() -> WorkUrl {
        WorkUrl::parse("s3://bkt/jobs/a").unwrap()
    }

    #[test]
    fn one_indexed_job_per_phase_with_tasks() {
        let tasks = |p: Phase| match p {
            Phase::Globals => 0,
            Phase::Tiles => 12,
            _ => 1,
        };
        let m = manifests(&s3(), tasks, 1 << 30, &K8sOptions::default()).unwrap();
        let phases: Vec<Phase> = m.iter().map(|m| m.phase).collect();
        assert_eq!(phases, [Phase::Partition, Phase::Tiles, Phase::Stitch]);
        let tiles = m[1].job.spec.as_ref().unwrap();
        assert_eq!(tiles.completions, Some(12));
        assert_eq!(tiles.parallelism, Some(8));
        assert_eq!(tiles.completion_mode.as_deref(), Some("Indexed"));
        assert_eq!(m[0].job.spec.as_ref().unwrap().parallelism, Some(1));
        assert_eq!(m[1].file_name(), "3-tiles.yaml");
        let y = m[1].to_yaml().unwrap();
        assert!(y.starts_with("apiVersion: batch/v1\nkind: Job\n"), "{y}");
        assert!(y.contains("memory: 1536Mi"), "{y}");
    }

    #[test]
    fn refuses_what_pods_cannot_reach_and_bad_names() {
        let local = WorkUrl::parse("/tmp/job").unwrap();
        let e = manifests(&local, |_| 1, 0, &K8sOptions::default()).unwrap_err();
        assert!(e.to_string().contains("s3://bucket/prefix"), "{e}");
        for bad in ["Upper", "-x", "a_b", &"x".repeat(50)] {
            let opts = K8sOptions {
                name: Some(bad.to_string()),
                ..K8sOptions::default()
            };
            let e = manifests(&s3(), |_| 1, 0, &opts).unwrap_err();
            assert!(matches!(e, K8sError::Name { .. }), "{bad}: {e}");
        }
        let opts = K8sOptions {
            parallelism: 0,
            ..K8sOptions::default()
        };
        assert!(manifests(&s3(), |_| 1, 0, &opts).is_err());
        assert_eq!(default_name(&s3()).len(), 15);
        assert_ne!(
            default_name(&s3()),
            default_name(&WorkUrl::parse("s3://bkt/jobs/b").unwrap())
        );
    }
}
