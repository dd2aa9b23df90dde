//! The integration tests, one binary (as ripgrep's `tests/tests.rs`): one module per area, the
//! helpers they share in [`util`]. `cargo test --test tests seams::` runs one module's tests;
//! tests marked `#[ignore = "needs ../shared"]` read the real data beside the repository and run
//! with `cargo test --release -- --include-ignored`. Tests that take more than about ten seconds
//! in the debug build carry `#[cfg_attr(debug_assertions, ignore = "release only: …")]`: plain
//! `cargo test` stays a few minutes, and the release run (which CI does) runs them all
//! (docs/DECISIONS.md, "`cargo test` in minutes").

mod util;

mod beams;
mod cli;
mod docker;
mod golden;
mod info;
mod io_bodies;
mod io_copc;
mod io_e57;
mod io_flags;
mod io_formats;
mod io_las;
mod io_pcd;
mod io_ply;
mod issue12;
mod issue47;
mod k8s;
mod knn_bounds;
mod normals;
mod operator;
mod partition;
mod raw_bin;
mod real_data;
mod reliability;
mod resume;
mod s3;
mod scaleout;
mod seams;
mod server;
mod slurm;
mod stored_moves;
mod streams;
mod table;
mod tempdir;
