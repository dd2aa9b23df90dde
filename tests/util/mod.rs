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

/// A small spinning-LiDAR sweep with exact truth, for the beam tests: a sensor 1.7 m above a
/// ground plane `z = 0`, beside a wall `y = 6`, `beams` rings from +2° down to −24° and an
/// azimuth step of `step` degrees over 360°; each return is the ray's first hit within 40 m,
/// its range perturbed along the beam by `sigma` times a deterministic standard normal draw.
pub struct Sweep {
    /// The sensor's position.
    pub origin: glam::DVec3,
    /// Noisy returns.
    pub noisy: Vec<glam::DVec3>,
    /// The same returns without noise.
    pub clean: Vec<glam::DVec3>,
    /// Which surface each return hit: 0 ground, 1 wall.
    pub surface: Vec<u8>,
}

impl Sweep {
    /// The sweep (see [`Sweep`]).
    pub fn new(beams: usize, step: f64, sigma: f64, seed: u64) -> Sweep {
        use glam::DVec3;
        let origin = DVec3::new(0.0, 0.0, 1.7);
        let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut normal = || {
            let (u, v) = (uniform(), uniform());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let (mut noisy, mut clean, mut surface) = (Vec::new(), Vec::new(), Vec::new());
        let columns = (360.0 / step).round() as usize;
        for b in 0..beams {
            let el = (2.0 - 26.0 * b as f64 / (beams - 1) as f64).to_radians();
            for c in 0..columns {
                let az = (c as f64 * step).to_radians();
                let d = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let ground = (d.z < 0.0).then(|| -origin.z / d.z);
                let wall = (d.y > 0.0).then(|| (6.0 - origin.y) / d.y);
                let (t, kind) = match (ground, wall) {
                    (Some(g), Some(w)) if w < g => (w, 1),
                    (Some(g), _) => (g, 0),
                    (None, Some(w)) => (w, 1),
                    (None, None) => continue,
                };
                if t > 40.0 {
                    continue;
                }
                clean.push(origin + d * t);
                noisy.push(origin + d * (t + sigma * normal()));
                surface.push(kind);
            }
        }
        Sweep {
            origin,
            noisy,
            clean,
            surface,
        }
    }

    /// Distance of `p` to the surface return `i` hit.
    pub fn distance(&self, i: usize, p: glam::DVec3) -> f64 {
        if self.surface[i] == 0 {
            p.z.abs()
        } else {
            (p.y - 6.0).abs()
        }
    }
}
