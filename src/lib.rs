//! qemd: feature-preserving denoising of meshes and point clouds with the Quadric Error Metric
//! operator of Vieira et al., "Mesh Denoising Using Quadric Error Metric".
//!
//! # Brief overview
//!
//! The crate is layered; each layer uses only the ones before it:
//!
//! * [`points`]: the data model (`PointBatch`, `Schema`, `Faces`, `Aabb`).
//! * [`io`]: streaming `Source`s and `Sink`s per file format (depends only on `points`).
//! * [`geometry`]: quadrics, the symmetric 3×3 eigensolver, PCA normals, exact sums.
//! * [`neighbours`]: k-NN (kiddo), radius balls and mesh k-rings.
//! * [`denoise`]: the QEM operator (meshes and point clouds), the bilateral baseline, parameters
//!   and statistics.
//! * [`eval`]: synthetic shapes, noise, the quality metrics, Table I, rendering.
//! * [`tiling`]: the out-of-core path (plan, partition, tiles with halos, stitch).
//! * [`pipeline`]: source → denoise → sink with progress, cancellation, checkpoints and a report.
//! * [`info`]: what a file holds (`qemd info`): format, schema, counts, bounds, CRS, spacing,
//!   classes.
//! * [`jobs`]: the service's job store (SQLite), uploads, scheduler and the one bridge from the
//!   async runtime to rayon; nothing before it knows about tokio.
//! * [`api`]: the HTTP API (axum): routes, uploads, downloads, errors, OpenAPI, server.
//! * [`objects`]: object-store (S3) work directories for the scale-out commands: a task's local
//!   mirror of the objects it reads and writes (its own tokio runtime).
//! * [`k8s`]: Kubernetes Indexed Job manifests, one per phase of a planned job.
//! * [`config`], [`cli`]: configuration (figment) and the `qemd` command line.
//!
//! # Features
//!
//! `default = ["cli", "service", "eval", "s3", "k8s"]`. Without features the crate is `points`, `io`,
//! `geometry`, `neighbours`, `denoise`, `tiling` and `pipeline`: `eval` adds the evaluation layer
//! (plotters, rustfft), `service` adds `jobs` and `api` (tokio, axum, rusqlite) and `cli` adds
//! `cli` and `config` (clap, figment), `s3` adds `objects` (object_store, tokio) and `k8s` adds
//! `k8s` (k8s-openapi); the `qemd` binary needs all five.

#![warn(missing_docs)]
#![forbid(unsafe_code)]

#[cfg(feature = "service")]
pub mod api;
#[cfg(feature = "cli")]
pub mod cli;
#[cfg(feature = "cli")]
pub mod config;
pub mod denoise;
#[cfg(feature = "eval")]
pub mod eval;
pub mod geometry;
pub mod info;
pub mod io;
#[cfg(feature = "service")]
pub mod jobs;
#[cfg(feature = "k8s")]
pub mod k8s;
pub mod neighbours;
#[cfg(feature = "s3")]
pub mod objects;
pub mod pipeline;
pub mod points;
pub mod tiling;
