//! Helpers the test modules share: running the `qemd` binary and writing, rewriting and listing
//! files in a test's directory.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use qem_denoise::io::Cloud;

/// Runs the `qemd` binary built for these tests with `args`; returns its output.
pub fn qemd(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_qemd"))
        .args(args)
        .output()
        .expect("qemd runs")
}

/// [`qemd`], asserting that it succeeded (its stderr in the failure message).
pub fn qemd_ok(args: &[&str]) -> Output {
    let o = qemd(args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

/// A path as a command-line argument.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Writes `bytes` to `dir/name`; returns the path.
pub fn put(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

/// Reads `input`, writes it unchanged next to it as `out_name` and returns the output bytes.
pub fn rewrite(input: &Path, out_name: &str) -> Vec<u8> {
    let c = Cloud::read(input, None).unwrap();
    let out = input.with_file_name(out_name);
    c.write(&out, None).unwrap();
    std::fs::read(&out).unwrap()
}

/// Names of the files in `dir`, sorted.
pub fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}
