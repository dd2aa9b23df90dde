//! Issue 15, items 3–8: hostile files that used to abort, panic, lose an upload or be read
//! wrongly now give one-line errors (or the right result), checked through the real binary where
//! the failure showed there.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use qem_denoise::io::Cloud;

const BIN: &str = env!("CARGO_BIN_EXE_qemd");

/// Runs `qemd` with `args`.
fn qemd(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().expect("qemd runs")
}

/// Asserts `out` is a failure with exactly one line on stderr naming `path`, no panic, no signal.
fn assert_one_line_error(out: &Output, path: &Path) -> String {
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(
        out.status.code(),
        Some(1),
        "exit status {:?}: {err}",
        out.status
    );
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(err.contains(&path.display().to_string()), "{err}");
    err
}

/// `n` points of a wavy surface as `x y z` lines.
fn surface_text(n: usize) -> String {
    let mut x = 0x2545f4914f6cdd1du64;
    let mut rnd = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let (u, v) = (rnd() * 4.0, rnd() * 4.0);
            format!(
                "{u:.6} {v:.6} {:.6}\n",
                (u * 1.5).sin() * 0.3 + rnd() * 0.01
            )
        })
        .collect()
}

/// A LAZ file of `n` points, LAS 1.4 point format 6 (layered compression), written by qemd.
fn layered_laz(dir: &Path, n: usize) -> PathBuf {
    let txt = dir.join("surface.xyz");
    std::fs::write(&txt, surface_text(n)).unwrap();
    let laz = dir.join("surface.laz");
    Cloud::read(&txt, None).unwrap().write(&laz, None).unwrap();
    laz
}

fn u16_at(b: &[u8], at: usize) -> usize {
    usize::from(u16::from_le_bytes([b[at], b[at + 1]]))
}

fn u32_at(b: &[u8], at: usize) -> usize {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap()) as usize
}

/// Where the first layer size of the first chunk of a layered LAZ lies.
fn first_layer_size_at(b: &[u8]) -> usize {
    let data = u32_at(b, 96);
    let record_len = u16_at(b, 105);
    data + 8 + record_len + 4
}

/// Peak resident memory (VmHWM) of a child process that decodes `path` with the library, in
/// bytes, and whether the decode failed. The child is this test binary running
/// [`decode_child`] alone, so no other test shares its peak.
fn decode_peak(path: &Path) -> (u64, bool) {
    let out = Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "decode_child",
            "--include-ignored",
            "--nocapture",
        ])
        .args(["--test-threads", "1"])
        .env("QEMD_DECODE_CHILD", path)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(out.status.success(), "child failed: {out:?}");
    // The harness prints `test decode_child ... ` on the same line.
    let line = text
        .lines()
        .find_map(|l| l.split_once("decode_child: ").map(|(_, r)| r))
        .unwrap_or_else(|| panic!("no result line: {text}"));
    let (peak, ok) = line.split_once(' ').unwrap();
    (peak.parse().unwrap(), ok == "err")
}

/// Not a test: the child of [`decode_peak`] (does nothing without `QEMD_DECODE_CHILD`).
#[test]
#[ignore = "helper process of decode_peak, runs only with QEMD_DECODE_CHILD"]
fn decode_child() {
    let Some(path) = std::env::var_os("QEMD_DECODE_CHILD") else {
        return;
    };
    let failed = Cloud::read(Path::new(&path), None).is_err();
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let kib: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0);
    println!(
        "decode_child: {} {}",
        kib * 1024,
        if failed { "err" } else { "ok" }
    );
}

/// Issue 15, item 3: one flipped byte in a layer size of a point-format-6 LAZ made the decoder
/// allocate 4 GiB (and abort under a memory limit). The layer sizes are now checked against the
/// chunk's bytes before decoding: the run fails with one line and stays small.
#[test]
fn issue15_hostile_laz_layer_size_is_an_error_without_a_big_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let laz = layered_laz(dir.path(), 3000);
    let good = std::fs::read(&laz).unwrap();
    let size = good.len() as u64;
    assert!(size < 64 * 1024, "a small file: {size} bytes");
    let (clean_peak, failed) = decode_peak(&laz);
    assert!(!failed, "the clean file decodes");

    let at = first_layer_size_at(&good);
    let bad = dir.path().join("bad.laz");
    // The high byte of each of the nine Point14 layer sizes: 2^24 … 4 GiB asked for.
    for k in 0..9 {
        let mut b = good.clone();
        b[at + 4 * k + 3] = 0xff;
        std::fs::write(&bad, &b).unwrap();
        let (peak, failed) = decode_peak(&bad);
        assert!(failed, "layer {k}: decoded");
        assert!(
            peak < clean_peak + 64 * size,
            "layer {k}: peak {peak} B against {clean_peak} B for the clean file ({size} B)"
        );
    }
    let o = dir.path().join("out.laz");
    let run = qemd(&["denoise", bad.to_str().unwrap(), "-o", o.to_str().unwrap()]);
    let err = assert_one_line_error(&run, &bad);
    assert!(err.contains("layers declare"), "{err}");
    assert!(!o.exists(), "no output left");
}

/// Issue 15, item 3: any single flipped byte of a small layered LAZ gives an error or a cloud,
/// never an abort or a large allocation.
#[test]
fn issue15_flipped_bytes_in_a_laz_never_abort() {
    let dir = tempfile::tempdir().unwrap();
    let laz = layered_laz(dir.path(), 1500);
    let good = std::fs::read(&laz).unwrap();
    let bad = dir.path().join("flip.laz");
    let data = u32_at(&good, 96);
    // Every byte of the first chunk's header and a spread of bytes across the file.
    let mut spots: Vec<usize> = (data..data + 8 + 30 + 4 + 36).collect();
    spots.extend((0..good.len()).step_by(97));
    for at in spots {
        for mask in [0x01u8, 0x80, 0xff] {
            let mut b = good.clone();
            b[at] ^= mask;
            std::fs::write(&bad, &b).unwrap();
            if let Err(e) = Cloud::read(&bad, None) {
                let msg = e.to_string();
                assert!(!msg.contains('\n'), "byte {at}: {msg}");
                assert!(msg.contains("flip.laz"), "byte {at}: {msg}");
            }
        }
    }
    let (peak, _) = decode_peak(&bad);
    assert!(peak < 256 << 20, "peak {peak}");
}

/// A LAS 1.2 file of point format 1 by hand (`n` points on a line).
fn las_pdrf1(n: usize) -> Vec<u8> {
    let mut h = vec![0u8; 227];
    h[..4].copy_from_slice(b"LASF");
    h[24] = 1;
    h[25] = 2;
    h[94..96].copy_from_slice(&227u16.to_le_bytes());
    h[96..100].copy_from_slice(&227u32.to_le_bytes());
    h[104] = 1;
    h[105..107].copy_from_slice(&28u16.to_le_bytes());
    h[107..111].copy_from_slice(&(n as u32).to_le_bytes());
    for a in 0..3 {
        h[131 + 8 * a..139 + 8 * a].copy_from_slice(&0.01f64.to_le_bytes());
    }
    let max = (n as f64 - 1.0) * 0.01;
    for (k, v) in [max, 0.0, max / 2.0, 0.0, 1.0, 0.0].iter().enumerate() {
        h[179 + 8 * k..187 + 8 * k].copy_from_slice(&f64::to_le_bytes(*v));
    }
    for i in 0..n {
        let mut r = [0u8; 28];
        r[..4].copy_from_slice(&(i as i32).to_le_bytes());
        r[4..8].copy_from_slice(&((i / 2) as i32).to_le_bytes());
        r[8..12].copy_from_slice(&((i % 100) as i32).to_le_bytes());
        r[14] = 0b0000_1001;
        r[20..28].copy_from_slice(&(i as f64).to_le_bytes());
        h.extend_from_slice(&r);
    }
    h
}

/// Issue 15, item 6: a point-wise LAZ whose laszip VLR declares variable-size chunks made the
/// `laz` decoder panic (message and backtrace on stderr) before the one-line error. It is now
/// refused from the VLR, with one line and no panic output.
#[test]
fn issue15_variable_chunks_without_a_table_print_no_panic() {
    let dir = tempfile::tempdir().unwrap();
    let las = dir.path().join("p1.las");
    std::fs::write(&las, las_pdrf1(500)).unwrap();
    let laz = dir.path().join("p1.laz");
    Cloud::read(&las, None).unwrap().write(&laz, None).unwrap();
    let mut b = std::fs::read(&laz).unwrap();
    // The laszip VLR follows the 227-byte header: 54-byte VLR header, then its data.
    assert_eq!(&b[227 + 2..227 + 2 + 14], b"laszip encoded");
    let vlr = 227 + 54;
    assert_eq!(u16_at(&b, vlr), 2, "point-wise chunked");
    b[vlr..vlr + 2].copy_from_slice(&1u16.to_le_bytes());
    b[vlr + 12..vlr + 16].copy_from_slice(&u32::MAX.to_le_bytes());
    let bad = dir.path().join("varchunks.laz");
    std::fs::write(&bad, &b).unwrap();
    let out = dir.path().join("out.las");
    let run = qemd(&[
        "denoise",
        bad.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    let err = assert_one_line_error(&run, &bad);
    assert!(err.contains("variable-size chunks"), "{err}");
    assert!(!out.exists());
}
