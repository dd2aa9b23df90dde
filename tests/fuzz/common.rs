//! What every fuzz target does: the input becomes a file of the target's format, qemd reads it
//! as that format (the reader of the CLI and the service), and a file it accepts is written back
//! and read again. A target fails (a crash for libFuzzer) on a panic, on an error that is not
//! one line naming the file, on a written file qemd cannot read back, and — through libFuzzer's
//! `-rss_limit_mb` and `-timeout` — on an allocation or a loop the input's size does not bound.

#![allow(dead_code)]

use std::cell::RefCell;
use std::path::{Path, PathBuf};

use qem_denoise::io::{Cloud, Format};

thread_local! {
    /// One scratch directory per fuzzing thread, reused for every input.
    static DIR: RefCell<Option<tempfile::TempDir>> = const { RefCell::new(None) };
}

/// Writes `data` to `<scratch>/<name>` and returns the path.
fn file(name: &str, data: &[u8]) -> PathBuf {
    DIR.with(|d| {
        let mut d = d.borrow_mut();
        let dir = d.get_or_insert_with(|| tempfile::tempdir().expect("a scratch directory"));
        let p = dir.path().join(name);
        std::fs::write(&p, data).expect("the scratch file is written");
        p
    })
}

/// Panics unless `e` is one line naming `path`.
fn check_error(path: &Path, e: &dyn std::fmt::Display) {
    let msg = e.to_string();
    assert!(!msg.contains('\n'), "a multi-line error: {msg}");
    assert!(
        msg.contains(&path.display().to_string()),
        "an error not naming the file: {msg}"
    );
}

/// Reads `data` as `format` from a file called `name`; writes an accepted cloud back (same
/// extension) and reads that again: it must hold as many points.
fn read_write(name: &str, format: Format, data: &[u8]) {
    let path = file(name, data);
    let cloud = match Cloud::read(&path, Some(format)) {
        Ok(c) => c,
        Err(e) => return check_error(&path, &e),
    };
    let out = path.with_file_name(format!("out-{name}"));
    match cloud.write(&out, Some(format)) {
        Ok(()) => {
            let back = Cloud::read(&out, Some(format))
                .unwrap_or_else(|e| panic!("qemd cannot read what it wrote: {e}"));
            assert_eq!(back.positions.len(), cloud.positions.len(), "points lost");
        }
        // Some content cannot be written back (a coordinate LAS cannot quantise, a PCD field
        // type the writer refuses…): a clean error is fine.
        Err(e) => check_error(&out, &e),
    }
}

/// PLY, any encoding.
pub fn ply(data: &[u8]) {
    read_write("in.ply", Format::Ply, data);
}

/// PCD, any encoding, header included.
pub fn pcd(data: &[u8]) {
    read_write("in.pcd", Format::Pcd, data);
}

/// A PCD body under a valid header: the first byte picks the encoding (ascii, binary,
/// binary_compressed), the second the fields, the third the point count.
pub fn pcd_body(data: &[u8]) {
    let [enc, fields, n, body @ ..] = data else {
        return;
    };
    let encoding = ["ascii", "binary", "binary_compressed"][usize::from(*enc % 3)];
    let (names, size, ty, count) = match fields % 4 {
        0 => ("x y z", "4 4 4", "F F F", "1 1 1"),
        1 => ("x y z intensity", "4 4 4 4", "F F F F", "1 1 1 1"),
        2 => ("x y z rgb", "8 8 8 4", "F F F U", "1 1 1 1"),
        _ => ("x y z normal", "4 4 4 2", "F F F I", "1 1 1 3"),
    };
    let n = usize::from(*n) + 1;
    let mut file = format!(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS {names}\nSIZE {size}\nTYPE {ty}\nCOUNT {count}\n\
         WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {encoding}\n"
    )
    .into_bytes();
    file.extend_from_slice(body);
    read_write("body.pcd", Format::Pcd, &file);
}

/// LAS and LAZ (COPC read as LAZ): the header says which.
pub fn las(data: &[u8]) {
    let compressed = data.get(104).is_some_and(|f| f & 0x80 != 0);
    read_write(
        if compressed { "in.laz" } else { "in.las" },
        Format::Las,
        data,
    );
}

/// Wavefront OBJ.
pub fn obj(data: &[u8]) {
    read_write("in.obj", Format::Obj, data);
}

/// OFF.
pub fn off(data: &[u8]) {
    read_write("in.off", Format::Off, data);
}

/// Text clouds: `.xyz` and `.pts` (first byte picks).
pub fn text(data: &[u8]) {
    let [pick, body @ ..] = data else {
        return;
    };
    if pick % 2 == 0 {
        read_write("in.xyz", Format::Xyz, body);
    } else {
        read_write("in.pts", Format::Pts, body);
    }
}

/// KITTI `.bin` and nuScenes `.pcd.bin` raw scans (first byte picks).
pub fn raw(data: &[u8]) {
    let [pick, body @ ..] = data else {
        return;
    };
    if pick % 2 == 0 {
        read_write("in.bin", Format::Kitti, body);
    } else {
        read_write("in.pcd.bin", Format::Nuscenes, body);
    }
}

/// The upload path: sniff the content, then read it as the sniffed format, as the service does
/// with an upload that names no format.
pub fn sniff(data: &[u8]) {
    let head = &data[..data.len().min(qem_denoise::io::sniff::SNIFF_LEN)];
    if let Some(format) = qem_denoise::io::sniff::sniff(head) {
        let path = file(&format!("upload.{}", format.name()), data);
        if let Err(e) = Cloud::read(&path, Some(format)) {
            check_error(&path, &e);
        }
    }
}
