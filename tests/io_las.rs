//! Integration tests of the LAS/LAZ backend: lossless round trips for every point format with extra
//! bytes, VLRs and EVLRs, quantisation with the file's scale and offset (UTM precision), the noise
//! flag, bad input, and (ignored by default) the shared LiDAR files.
//!
//! Test files are written with the `las` crate's writer from raw records, and outputs are checked
//! with an independent byte-level parser plus the `las` crate's reader.
//!
//! `cargo test --test tests io_las::` selects exactly these tests.

use std::path::{Path, PathBuf};

use glam::DVec3;
use las::point::Format as PointFormat;
use las::{Builder, PointDataBuilder, Transform, Vector, Version, Vlr};
use qem_denoise::io::las::{LasSink, LasSource};
use qem_denoise::io::{
    self, Cloud, Extras, Format, IoError, Meta, Sink, SinkOptions, Source, SourceInfo,
};
use qem_denoise::points::{FLAG_NOISE, PointBatch, ScalarType, Schema};

// ---------------------------------------------------------------------------------------------
// Building test files with the `las` crate.

/// Standard record length of each PDRF.
const BASE: [usize; 11] = [20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67];

struct Spec {
    minor: u8,
    pdrf: u8,
    extra: u16,
    compressed: bool,
    n: usize,
    scale: f64,
    offset: [f64; 3],
    /// Bytes after the points (uncompressed files).
    padding: Vec<u8>,
}

impl Spec {
    fn new(minor: u8, pdrf: u8, compressed: bool) -> Spec {
        Spec {
            minor,
            pdrf,
            extra: 5,
            compressed,
            n: 257,
            scale: 0.01,
            offset: [1000.0, -2000.0, 5.0],
            padding: Vec::new(),
        }
    }

    fn record_len(&self) -> usize {
        BASE[usize::from(self.pdrf)] + usize::from(self.extra)
    }
}

/// A small deterministic generator.
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        self.0 >> 33
    }
}

fn extra_bytes_vlr() -> Vlr {
    // One f32 "amplitude" and one u8 "flag": 5 extra bytes.
    let mut data = vec![0u8; 2 * 192];
    data[2] = 9;
    data[4..13].copy_from_slice(b"amplitude");
    data[192 + 2] = 1;
    data[192 + 4..192 + 8].copy_from_slice(b"flag");
    Vlr {
        user_id: "LASF_Spec".into(),
        record_id: 4,
        description: "Extra Bytes".into(),
        data,
    }
}

/// Random records (every byte random, X/Y/Z small integers) for `spec`.
fn records(spec: &Spec, seed: u64) -> Vec<u8> {
    let rl = spec.record_len();
    let mut g = Lcg(seed);
    let mut out = vec![0u8; spec.n * rl];
    for rec in out.chunks_exact_mut(rl) {
        for b in rec.iter_mut() {
            *b = g.next() as u8;
        }
        if spec.minor < 4 {
            // LAS < 1.4 counts returns 1–5 only.
            let (r, n) = (1 + g.next() % 5, 1 + g.next() % 5);
            rec[14] = (rec[14] & 0xc0) | (n << 3) as u8 | r as u8;
        }
        for axis in 0..3 {
            let v = (g.next() % 200_001) as i32 - 100_000;
            rec[4 * axis..4 * axis + 4].copy_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Writes a LAS/LAZ file for `spec` with a CRS VLR, an Extra Bytes VLR, an EVLR (1.4) and
/// distinctive header fields; returns the records written.
fn build(path: &Path, spec: &Spec, seed: u64) -> Vec<u8> {
    let mut b = Builder::default();
    b.version = Version::new(1, spec.minor);
    let mut f = PointFormat::new(spec.pdrf).unwrap();
    f.extra_bytes = spec.extra;
    f.is_compressed = spec.compressed;
    b.point_format = f;
    let t = |i: usize| Transform {
        scale: spec.scale,
        offset: spec.offset[i],
    };
    b.transforms = Vector {
        x: t(0),
        y: t(1),
        z: t(2),
    };
    b.system_identifier = "qemd test system".into();
    b.generating_software = "qemd io_las tests".into();
    b.file_source_id = 42;
    b.vlrs.push(Vlr {
        user_id: "LASF_Projection".into(),
        record_id: 2112,
        description: "WKT".into(),
        data: b"PROJCS[\"test\"]\0".to_vec(),
    });
    if spec.extra > 0 {
        b.vlrs.push(extra_bytes_vlr());
    }
    b.vlrs.push(Vlr {
        user_id: "qemd-test".into(),
        record_id: 7,
        description: "a user VLR".into(),
        data: (0..=255u8).collect(),
    });
    if spec.minor >= 4 {
        b.has_wkt_crs = true;
        b.evlrs.push(Vlr {
            user_id: "qemd-test".into(),
            record_id: 9,
            description: "an EVLR".into(),
            data: (0..1000u32).map(|i| (i * 7) as u8).collect(),
        });
    }
    b.point_padding = spec.padding.clone();
    let header = b.into_header().unwrap();
    let recs = records(spec, seed);
    let pd = PointDataBuilder::new()
        .for_header(&header)
        .build_from_bytes(recs.clone())
        .unwrap();
    let mut w = las::Writer::from_path(path, header).unwrap();
    w.write_points(&pd).unwrap();
    w.close().unwrap();
    drop(w);
    // Distinctive GUID and creation date, patched in place.
    let mut bytes = std::fs::read(path).unwrap();
    for (k, b) in bytes[8..24].iter_mut().enumerate() {
        *b = 0xa0 + k as u8;
    }
    bytes[90..94].copy_from_slice(&[123, 0, 0xe5, 0x07]);
    std::fs::write(path, &bytes).unwrap();
    recs
}

// ---------------------------------------------------------------------------------------------
// An independent byte-level view of a LAS file.

struct Raw {
    header: Vec<u8>,
    vlrs: Vec<Vec<u8>>,
    evlrs: Vec<Vec<u8>>,
    records: Vec<u8>,
    record_len: usize,
    scale: [f64; 3],
    offset: [f64; 3],
}

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}
fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}
fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

fn user_record(v: &[u8]) -> (String, u16) {
    let uid = &v[2..18];
    let end = uid.iter().position(|&c| c == 0).unwrap_or(16);
    (
        String::from_utf8_lossy(&uid[..end]).into_owned(),
        u16_at(v, 18),
    )
}

/// Parses header, VLRs and EVLRs by hand; the records come from the `las` crate's reader.
fn parse(path: &Path) -> Raw {
    let b = std::fs::read(path).unwrap();
    let hs = usize::from(u16_at(&b, 94));
    let data = u32_at(&b, 96) as usize;
    let mut vlrs = Vec::new();
    let mut p = hs;
    for _ in 0..u32_at(&b, 100) {
        let len = 54 + usize::from(u16_at(&b, p + 20));
        vlrs.push(b[p..p + len].to_vec());
        p += len;
    }
    assert!(p <= data);
    let mut evlrs = Vec::new();
    if b[25] >= 4 {
        let mut p = u64_at(&b, 235) as usize;
        for _ in 0..u32_at(&b, 243) {
            let len = 60 + u64_at(&b, p + 20) as usize;
            evlrs.push(b[p..p + len].to_vec());
            p += len;
        }
    }
    let mut reader = las::Reader::from_path(path).unwrap();
    let records = reader.read_all().unwrap().raw_bytes().to_vec();
    Raw {
        header: b[..hs].to_vec(),
        vlrs,
        evlrs,
        records,
        record_len: usize::from(u16_at(&b, 105)),
        scale: [f64_at(&b, 131), f64_at(&b, 139), f64_at(&b, 147)],
        offset: [f64_at(&b, 155), f64_at(&b, 163), f64_at(&b, 171)],
    }
}

/// The header with the fields the writer recomputes zeroed: counts, bounds and the offsets
/// of what follows the points.
fn masked_header(h: &[u8]) -> Vec<u8> {
    let mut h = h.to_vec();
    let minor = h[25];
    h[107..131].fill(0);
    h[179..227].fill(0);
    if minor >= 3 {
        h[227..235].fill(0);
    }
    if minor >= 4 {
        h[235..247].fill(0);
        h[247..375].fill(0);
    }
    h
}

/// Records with X, Y, Z zeroed.
fn masked_records(r: &[u8], rl: usize) -> Vec<u8> {
    let mut r = r.to_vec();
    for rec in r.chunks_exact_mut(rl) {
        rec[..12].fill(0);
    }
    r
}

fn xyz(r: &[u8], rl: usize, i: usize) -> [i32; 3] {
    let rec = &r[i * rl..];
    [0, 4, 8].map(|o| i32::from_le_bytes(rec[o..o + 4].try_into().unwrap()))
}

/// Checks `out` reproduces `inp`: header except counts/bounds/offsets, VLRs, EVLRs, records.
fn assert_same_file(inp: &Raw, out: &Raw, records_too: bool) {
    assert_eq!(masked_header(&inp.header), masked_header(&out.header));
    assert_eq!(inp.vlrs, out.vlrs, "VLRs");
    assert_eq!(inp.evlrs, out.evlrs, "EVLRs");
    if records_too {
        assert!(inp.records == out.records, "records differ");
    }
}

/// The header's bounds are the extremes of the positions.
fn assert_bounds(h: &[u8], positions: &[DVec3]) {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for p in positions {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    let got: Vec<f64> = (0..6).map(|k| f64_at(h, 179 + 8 * k)).collect();
    assert_eq!(got, [hi.x, lo.x, hi.y, lo.y, hi.z, lo.z], "bounds");
}

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

fn ext(compressed: bool) -> &'static str {
    if compressed { "laz" } else { "las" }
}

/// The (version, PDRF) pairs tested: every PDRF in LAS 1.4, and 0–5 in the oldest version
/// that has them.
fn combos() -> Vec<(u8, u8)> {
    let mut c: Vec<(u8, u8)> = (0..=10).map(|f| (4, f)).collect();
    c.extend([(2, 0), (2, 1), (2, 2), (2, 3), (3, 4), (3, 5)]);
    c
}

// ---------------------------------------------------------------------------------------------
// Round trips.

#[test]
fn every_point_format_round_trips_byte_identically() {
    let dir = tmp();
    for compressed in [false, true] {
        for (minor, pdrf) in combos() {
            let spec = Spec::new(minor, pdrf, compressed);
            let e = ext(compressed);
            let src = dir.path().join(format!("in_{minor}_{pdrf}.{e}"));
            let recs = build(&src, &spec, u64::from(pdrf) * 31 + u64::from(minor));
            let c = Cloud::read(&src, None).unwrap();
            let what = format!("LAS 1.{minor} PDRF {pdrf} {e}");
            assert_eq!(c.len(), spec.n, "{what}");
            let want = if compressed { Format::Laz } else { Format::Las };
            assert_eq!(c.info.format, want, "{what}");
            assert_eq!(c.info.schema.record_len, spec.record_len(), "{what}");
            assert_eq!(c.records, recs, "{what}: records as written");
            let s = &c.info.schema;
            for name in ["x", "y", "z"] {
                let f = &s.fields[s.field_index(name).unwrap()];
                assert_eq!(f.ty, ScalarType::I32);
            }
            assert!(s.field_index("amplitude").is_some() && s.field_index("flag").is_some());
            let Meta::Las(m) = &c.info.meta else {
                panic!("{what}: no LAS meta")
            };
            assert_eq!((m.version(), m.point_format()), ((1, minor), pdrf));
            assert_eq!(m.is_compressed(), compressed);
            // Positions are X·scale + offset.
            let rl = spec.record_len();
            for i in [0, spec.n / 2, spec.n - 1] {
                let q = xyz(&recs, rl, i);
                let want = DVec3::new(
                    f64::from(q[0]) * 0.01 + 1000.0,
                    f64::from(q[1]) * 0.01 - 2000.0,
                    f64::from(q[2]) * 0.01 + 5.0,
                );
                assert_eq!(c.positions[i], want, "{what} point {i}");
            }
            let dst = dir.path().join(format!("out_{minor}_{pdrf}.{e}"));
            c.write(&dst, None).unwrap();
            let (a, b) = (parse(&src), parse(&dst));
            assert_same_file(&a, &b, true);
            // Counts are recomputed; the las crate computed the same ones. (Its bounds
            // floor (X − offset)/scale in floating point and can be one step off.)
            assert_eq!(
                a.header[107..131],
                b.header[107..131],
                "{what}: legacy counts"
            );
            assert_bounds(&b.header, &c.positions);
            if minor >= 4 {
                assert_eq!(a.header[243..375], b.header[243..375], "{what}: 1.4 counts");
            }
            // And it reads back the same.
            let d = Cloud::read(&dst, None).unwrap();
            assert_eq!(d.positions, c.positions);
            assert_eq!(d.records, c.records);
        }
    }
}

#[test]
fn moved_positions_change_only_xyz() {
    let dir = tmp();
    for (compressed, pdrf) in [(false, 3), (true, 1), (false, 8), (true, 7)] {
        let spec = Spec::new(4, pdrf, compressed);
        let e = ext(compressed);
        let src = dir.path().join(format!("in{pdrf}.{e}"));
        build(&src, &spec, 5);
        let mut c = Cloud::read(&src, None).unwrap();
        for (i, p) in c.positions.iter_mut().enumerate() {
            *p += DVec3::new(0.01 * (i % 7) as f64, -0.02, 0.0049);
        }
        let dst = dir.path().join(format!("out{pdrf}.{e}"));
        c.write(&dst, None).unwrap();
        let (a, b) = (parse(&src), parse(&dst));
        assert_same_file(&a, &b, false);
        let rl = a.record_len;
        assert_eq!(
            masked_records(&a.records, rl),
            masked_records(&b.records, rl)
        );
        for i in 0..spec.n {
            let (qa, qb) = (xyz(&a.records, rl, i), xyz(&b.records, rl, i));
            assert_eq!(qb[0] - qa[0], (i % 7) as i32);
            assert_eq!(qb[1] - qa[1], -2);
            assert_eq!(qb[2] - qa[2], 0, "0.0049 rounds to 0 hundredths");
        }
        // Bounds follow the new coordinates.
        let c2 = Cloud::read(&dst, None).unwrap();
        assert_bounds(&b.header, &c2.positions);
    }
}

#[test]
fn utm_coordinates_keep_millimetres() {
    let dir = tmp();
    // A LAS source with scale 0.001 and UTM offsets; a 1 mm staircase.
    let spec = Spec {
        minor: 2,
        pdrf: 1,
        extra: 0,
        compressed: false,
        n: 2000,
        scale: 0.001,
        offset: [500_000.0, 5_000_000.0, 0.0],
        padding: Vec::new(),
    };
    let src = dir.path().join("utm.las");
    let mut recs = build(&src, &spec, 3);
    let rl = spec.record_len();
    for (i, rec) in recs.chunks_exact_mut(rl).enumerate() {
        let q = [
            123_456 + i as i32,
            654_321 - i as i32,
            100_000 + (i % 2) as i32,
        ];
        for a in 0..3 {
            rec[4 * a..4 * a + 4].copy_from_slice(&q[a].to_le_bytes());
        }
    }
    let bytes = std::fs::read(&src).unwrap();
    let data = u32_at(&bytes, 96) as usize;
    let mut patched = bytes.clone();
    patched[data..data + recs.len()].copy_from_slice(&recs);
    std::fs::write(&src, &patched).unwrap();

    let mut c = Cloud::read(&src, None).unwrap();
    assert_eq!(
        c.positions[1] - c.positions[0],
        c.positions[1] - c.positions[0]
    );
    assert_eq!(
        c.positions[0],
        DVec3::new(500_123.456, 5_000_654.321, 100.0)
    );
    assert!((c.positions[1].x - c.positions[0].x - 0.001).abs() < 1e-9);
    // Unchanged: exact.
    let dst = dir.path().join("same.las");
    c.write(&dst, None).unwrap();
    let d = Cloud::read(&dst, None).unwrap();
    assert_eq!(d.positions, c.positions);
    assert_eq!(d.records, c.records);
    // Moved by exactly 1 mm steps: the integers move by exactly 1.
    for (i, p) in c.positions.iter_mut().enumerate() {
        p.x += 0.001 * (i % 3) as f64;
        p.z -= 0.001;
    }
    c.write(&dst, None).unwrap();
    let d = Cloud::read(&dst, None).unwrap();
    for i in 0..spec.n {
        let (a, b) = (xyz(&recs, rl, i), xyz(&d.records, rl, i));
        assert_eq!(
            [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
            [(i % 3) as i32, 0, -1]
        );
        assert!((d.positions[i] - c.positions[i]).abs().max_element() < 1e-9);
    }

    // A generated cloud at UTM coordinates, 1 mm apart, written as LAS: exact as well.
    let pts: Vec<DVec3> = (0..5000)
        .map(|i| {
            DVec3::new(
                500_000.0 + i as f64 * 0.001,
                5_000_000.0 + (i % 100) as f64 * 0.001,
                250.0 + (i % 7) as f64 * 0.001,
            )
        })
        .collect();
    let g = Cloud::generated(pts.clone(), None, ScalarType::F64);
    for e in ["las", "laz"] {
        let out = dir.path().join(format!("gen.{e}"));
        g.write(&out, None).unwrap();
        let r = Cloud::read(&out, None).unwrap();
        assert_eq!(r.positions, pts, "{e}");
        let raw = parse(&out);
        // A 5 m extent: 10 µm steps, offsets at multiples of 10 m.
        assert_eq!(raw.scale, [1e-5; 3]);
        assert_eq!(raw.offset, [500_000.0, 5_000_000.0, 250.0]);
        let q: Vec<i32> = (0..5000).map(|i| xyz(&raw.records, 30, i)[0]).collect();
        assert!(
            q.windows(2).all(|w| w[1] - w[0] == 100),
            "{e}: 1 mm = 100 steps"
        );
    }
}

#[test]
fn generated_and_foreign_clouds_become_las_1_4_pdrf_6() {
    let dir = tmp();
    let pts: Vec<DVec3> = (0..300)
        .map(|i| DVec3::new(i as f64 * 0.0005, (i % 17) as f64 * 0.001, -0.05))
        .collect();
    let g = Cloud::generated(pts.clone(), None, ScalarType::F32);
    let out = dir.path().join("g.las");
    g.write(&out, None).unwrap();
    let raw = parse(&out);
    assert_eq!((raw.header[24], raw.header[25], raw.header[104]), (1, 4, 6));
    assert_eq!(raw.record_len, 30);
    assert_eq!(raw.scale, [1e-6; 3], "0.15 m extent: micrometres");
    let r = Cloud::read(&out, None).unwrap();
    for (a, b) in r.positions.iter().zip(&pts) {
        assert!((*a - *b).abs().max_element() <= 0.5e-6 + 1e-12);
    }
    let hdr = las::Reader::from_path(&out).unwrap().header().clone();
    assert_eq!(hdr.number_of_points(), 300);

    // A foreign record (big-endian, with attributes) keeps its fields as extra bytes.
    let schema = Schema::packed(
        &[
            ("x", ScalarType::F64),
            ("intensity", ScalarType::F32),
            ("y", ScalarType::F64),
            ("z", ScalarType::F64),
            ("label", ScalarType::I16),
        ],
        qem_denoise::points::Endian::Big,
    )
    .unwrap();
    let mut info = SourceInfo::generated(Format::Ply, ScalarType::F64, 3, None);
    info.schema = schema.clone();
    let mut sink = io::create(&dir.path().join("f.laz"), None, &info, 3).unwrap();
    let mut batch = PointBatch::with_capacity(schema.record_len, 3);
    for i in 0..3 {
        let mut rec = vec![0u8; schema.record_len];
        let p = DVec3::new(10.0 + i as f64, 20.0, 30.0);
        schema.set_position(&mut rec, p);
        schema.set_f64(&mut rec, 1, 0.5 + i as f64);
        schema.set_f64(&mut rec, 4, -7.0 * i as f64);
        batch.push(p, &rec);
    }
    sink.write_batch(&batch).unwrap();
    sink.finish(&Extras::default()).unwrap();
    let r = Cloud::read(&dir.path().join("f.laz"), None).unwrap();
    let s = &r.info.schema;
    assert_eq!(s.record_len, 30 + 4 + 2);
    let (fi, fl) = (
        s.field_index("extra_intensity").unwrap(),
        s.field_index("label").unwrap(),
    );
    for i in 0..3 {
        assert_eq!(s.get_f64(&r.records[i * 36..], fi), 0.5 + i as f64);
        assert_eq!(s.get_f64(&r.records[i * 36..], fl), -7.0 * i as f64);
        assert_eq!(r.positions[i], DVec3::new(10.0 + i as f64, 20.0, 30.0));
    }
}

#[test]
fn compression_follows_the_extension() {
    let dir = tmp();
    let spec = Spec::new(4, 7, false);
    let src = dir.path().join("a.las");
    build(&src, &spec, 11);
    let c = Cloud::read(&src, None).unwrap();
    let laz = dir.path().join("b.laz");
    c.write(&laz, None).unwrap();
    let back = dir.path().join("c.las");
    Cloud::read(&laz, None).unwrap().write(&back, None).unwrap();
    let (a, z, b) = (parse(&src), parse(&laz), parse(&back));
    assert_eq!(z.header[104], 0x87);
    assert_eq!(z.vlrs.len(), a.vlrs.len() + 1);
    assert_eq!(user_record(z.vlrs.last().unwrap()).0, "laszip encoded");
    assert_eq!(z.records, a.records);
    assert_same_file(&a, &b, true);
    assert_eq!(a.header, b.header, "LAS → LAZ → LAS gives the header back");
    assert_eq!(std::fs::read(&src).unwrap(), std::fs::read(&back).unwrap());
}

#[test]
fn evlr_offsets_follow_when_points_are_dropped() {
    let dir = tmp();
    let mut spec = Spec::new(4, 4, false);
    spec.padding = b"bytes after the points".to_vec();
    let src = dir.path().join("w.las");
    build(&src, &spec, 2);
    // Point the waveform data packet record at the EVLR.
    let mut bytes = std::fs::read(&src).unwrap();
    let evlr = u64_at(&bytes, 235);
    bytes[227..235].copy_from_slice(&evlr.to_le_bytes());
    std::fs::write(&src, &bytes).unwrap();
    let mut s = io::open(&src, None).unwrap();
    let info = s.info().clone();
    let dst = dir.path().join("fewer.las");
    let mut sink = io::create(&dst, None, &info, 200).unwrap();
    let mut b = PointBatch::default();
    s.read_batch(&mut b, 200).unwrap();
    sink.write_batch(&b).unwrap();
    while s.read_batch(&mut b, 1000).unwrap() > 0 {}
    let extras = s.finish().unwrap();
    sink.finish(&extras).unwrap();
    let out = std::fs::read(&dst).unwrap();
    let (first, wave) = (u64_at(&out, 235) as usize, u64_at(&out, 227) as usize);
    let end = u32_at(&out, 96) as usize + 200 * spec.record_len();
    assert_eq!(&out[end..end + spec.padding.len()], &spec.padding[..]);
    assert_eq!(first, end + spec.padding.len());
    assert_eq!(user_record(&out[first..]), ("qemd-test".to_string(), 9));
    assert_eq!(wave, first);
    assert_eq!(
        u64_at(&bytes, 227),
        evlr,
        "the source pointed at its EVLR too"
    );
    assert_eq!(u64_at(&out, 247), 200);
    let (a, z) = (parse(&src), parse(&dst));
    assert_eq!(a.evlrs, z.evlrs);
    assert_eq!(z.records, a.records[..200 * spec.record_len()]);
}

// ---------------------------------------------------------------------------------------------
// Noise flag.

#[test]
fn noise_flag_sets_class_7_on_flagged_points_only() {
    let dir = tmp();
    for (pdrf, compressed) in [(3u8, false), (1, true), (6, false), (10, true)] {
        let spec = Spec::new(4, pdrf, compressed);
        let e = ext(compressed);
        let src = dir.path().join(format!("n{pdrf}.{e}"));
        build(&src, &spec, 9);
        let c = Cloud::read(&src, None).unwrap();
        let dst = dir.path().join(format!("n{pdrf}_out.{e}"));
        let opts = SinkOptions {
            noise_flag: true,
            ..SinkOptions::default()
        };
        let mut sink = io::create_with(&dst, None, &c.info, c.len() as u64, &opts).unwrap();
        let mut batch = PointBatch::with_capacity(c.info.schema.record_len, c.len());
        batch.positions.extend_from_slice(&c.positions);
        batch.records.extend_from_slice(&c.records);
        batch.flags = (0..c.len())
            .map(|i| if i % 3 == 0 { FLAG_NOISE } else { 0 })
            .collect();
        sink.write_batch(&batch).unwrap();
        sink.finish(&Extras::default()).unwrap();
        let (a, b) = (parse(&src), parse(&dst));
        let rl = a.record_len;
        let at = if pdrf >= 6 { 16 } else { 15 };
        for i in 0..c.len() {
            let (ra, rb) = (
                &a.records[i * rl..(i + 1) * rl],
                &b.records[i * rl..(i + 1) * rl],
            );
            if i % 3 == 0 {
                if pdrf >= 6 {
                    assert_eq!(rb[at], 7);
                } else {
                    assert_eq!(rb[at], (ra[at] & 0xe0) | 7, "flag bits kept");
                }
            } else {
                assert_eq!(rb[at], ra[at]);
            }
            for k in (0..rl).filter(|&k| k != at) {
                assert_eq!(ra[k], rb[k], "PDRF {pdrf} point {i} byte {k}");
            }
        }
        // Independent decoder agrees.
        let pd = las::Reader::from_path(&dst).unwrap().read_all().unwrap();
        for (i, class) in pd.classification().enumerate() {
            if i % 3 == 0 {
                assert_eq!(class, 7);
            }
        }
    }
    // Formats without a noise flag still refuse it.
    let g = Cloud::generated(vec![DVec3::ZERO], None, ScalarType::F32);
    let e = io::create_with(
        &dir.path().join("x.bin"),
        None,
        &g.info,
        1,
        &SinkOptions {
            noise_flag: true,
            ..SinkOptions::default()
        },
    )
    .err()
    .unwrap();
    assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
}

// ---------------------------------------------------------------------------------------------
// Bad input.

fn open_err(path: &Path) -> IoError {
    match LasSource::open(path) {
        Ok(_) => panic!("{} opened", path.display()),
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.contains(&path.display().to_string()), "{msg}");
            assert!(!msg.contains('\n'), "one line: {msg}");
            e
        }
    }
}

#[test]
fn bad_input_is_a_one_line_error() {
    let dir = tmp();
    let p = |n: &str| dir.path().join(n);
    std::fs::write(p("empty.las"), b"").unwrap();
    assert!(matches!(open_err(&p("empty.las")), IoError::Header { .. }));
    std::fs::write(p("text.las"), b"ply\nformat ascii 1.0\nend_header\n").unwrap();
    let e = open_err(&p("text.las"));
    assert!(e.to_string().contains("not a LAS file"), "{e}");
    std::fs::write(p("short.las"), b"LASF\x00\x00").unwrap();
    assert!(matches!(
        open_err(&p("short.las")),
        IoError::Truncated { .. }
    ));

    for compressed in [false, true] {
        let e_ = ext(compressed);
        let spec = Spec::new(2, 1, compressed);
        let good = p(&format!("good.{e_}"));
        build(&good, &spec, 1);
        let bytes = std::fs::read(&good).unwrap();
        let data = u32_at(&bytes, 96) as usize;

        // Truncated in the middle of the points.
        let cut = p(&format!("cut.{e_}"));
        std::fs::write(&cut, &bytes[..data + (bytes.len() - data) / 2]).unwrap();
        assert!(matches!(open_err(&cut), IoError::Truncated { .. }), "{e_}");
        // Truncated in the VLRs.
        std::fs::write(&cut, &bytes[..300]).unwrap();
        open_err(&cut);

        // A header that claims more points than the file holds.
        let lying = p(&format!("lying.{e_}"));
        let mut b = bytes.clone();
        let claim: u32 = if compressed { 50_001 } else { 258 };
        b[107..111].copy_from_slice(&claim.to_le_bytes());
        std::fs::write(&lying, &b).unwrap();
        let e = open_err(&lying);
        assert!(matches!(e, IoError::Truncated { .. }), "{e}");
        assert!(e.to_string().contains(&claim.to_string()), "{e}");
    }

    // Bad LAZ framing and data.
    let spec = Spec::new(4, 6, true);
    let good = p("g6.laz");
    build(&good, &spec, 4);
    let bytes = std::fs::read(&good).unwrap();
    let data = u32_at(&bytes, 96) as usize;
    let bad = p("bad.laz");
    let mut b = bytes.clone();
    b[data..data + 8].copy_from_slice(&(1u64 << 40).to_le_bytes());
    std::fs::write(&bad, &b).unwrap();
    assert!(matches!(open_err(&bad), IoError::Truncated { .. }));
    // Mangled laszip VLR: wrong item sizes.
    let raw = parse(&good);
    let mut at = 375;
    for v in &raw.vlrs {
        if user_record(v).0 == "laszip encoded" {
            break;
        }
        at += v.len();
    }
    let mut b = bytes.clone();
    b[at + 54 + 34 + 2] ^= 0x40;
    std::fs::write(&bad, &b).unwrap();
    assert!(matches!(open_err(&bad), IoError::Header { .. }));
    // Garbage in the compressed stream: an error or garbage points, never a panic.
    let mut b = bytes.clone();
    for (k, x) in b[data + 8..data + 8 + 400].iter_mut().enumerate() {
        *x = (k * 37) as u8;
    }
    std::fs::write(&bad, &b).unwrap();
    let _ = Cloud::read(&bad, None);
    // A 1.4 file whose EVLRs run past the end.
    let mut b = bytes.clone();
    let evlr = u64_at(&b, 235) as usize;
    b.truncate(evlr + 70);
    std::fs::write(&bad, &b).unwrap();
    assert!(matches!(open_err(&bad), IoError::Truncated { .. }));
}

#[test]
fn failed_writes_leave_nothing_behind() {
    let dir = tmp();
    let src = dir.path().join("in.laz");
    build(&src, &Spec::new(4, 6, true), 8);
    let c = Cloud::read(&src, None).unwrap();
    let out = tempfile::tempdir().unwrap();
    let listing = || std::fs::read_dir(out.path()).unwrap().count();
    for e in ["las", "laz"] {
        let dst = out.path().join(format!("o.{e}"));
        // Fewer points than announced.
        let mut sink = io::create(&dst, None, &c.info, c.len() as u64 + 1).unwrap();
        let mut batch = PointBatch::with_capacity(c.info.schema.record_len, c.len());
        batch.positions.extend_from_slice(&c.positions);
        batch.records.extend_from_slice(&c.records);
        sink.write_batch(&batch).unwrap();
        let err = sink.finish(&Extras::default()).unwrap_err();
        assert!(err.to_string().contains("announced"), "{err}");
        assert_eq!(listing(), 0);
        // A coordinate the file's scale and offset cannot hold, and a NaN.
        for bad in [1e12, f64::NAN] {
            let mut sink = io::create(&dst, None, &c.info, c.len() as u64).unwrap();
            batch.positions[5].y = bad;
            let err = sink.write_batch(&batch).unwrap_err();
            assert!(err.to_string().contains("point 5: y"), "{err}");
            drop(sink);
            assert_eq!(listing(), 0);
        }
        batch.positions[5] = c.positions[5];
    }
    // More points than announced.
    let mut sink = LasSink::create(
        &out.path().join("p.las"),
        &c.info,
        3,
        &SinkOptions::default(),
    )
    .unwrap();
    let rl = c.info.schema.record_len;
    let mut batch = PointBatch::with_capacity(rl, 4);
    for i in 0..4 {
        batch.push(c.positions[i], &c.records[i * rl..(i + 1) * rl]);
    }
    assert!(sink.write_batch(&batch).is_err());
    drop(sink);
    assert_eq!(listing(), 0);
}

#[test]
fn empty_files_round_trip() {
    let dir = tmp();
    for compressed in [false, true] {
        let mut spec = Spec::new(4, 1, compressed);
        spec.n = 0;
        let e = ext(compressed);
        let src = dir.path().join(format!("e.{e}"));
        build(&src, &spec, 1);
        let c = Cloud::read(&src, None).unwrap();
        assert!(c.is_empty());
        let dst = dir.path().join(format!("f.{e}"));
        c.write(&dst, None).unwrap();
        let (a, b) = (parse(&src), parse(&dst));
        assert_same_file(&a, &b, true);
    }
}

// ---------------------------------------------------------------------------------------------
// The shared LiDAR files.

fn shared(name: &str) -> PathBuf {
    Path::new("../shared/data/lidar").join(name)
}

#[test]
#[ignore = "needs ../shared"]
fn shared_files_round_trip() {
    let files = [
        ("4_6_crop.las", 23_875u64, "las"),
        ("sample_c.las", 14_408, "las"),
        ("warsaw_small.las", 3_000, "las"),
        ("32-1-472-150-76.laz", 5_658, "laz"),
        ("lone-star.copc.laz", 518_862, "laz"),
    ];
    let dir = tmp();
    for (name, count, e) in files {
        let src = shared(name);
        let c = Cloud::read(&src, None).unwrap();
        assert_eq!(c.len() as u64, count, "{name}");
        assert_eq!(c.info.len, Some(count));
        let Meta::Las(m) = &c.info.meta else {
            panic!("{name}: no LAS meta")
        };
        let copc = name.contains("copc");
        assert_eq!(m.is_copc(), copc, "{name}");
        let dst = dir.path().join(format!("out.{e}"));
        c.write(&dst, None).unwrap();
        let (a, b) = (parse(&src), parse(&dst));
        assert_eq!(a.records.len(), b.records.len(), "{name}");
        let rl = a.record_len;
        assert_eq!(
            masked_records(&a.records, rl),
            masked_records(&b.records, rl),
            "{name}: non-XYZ bytes"
        );
        let d = Cloud::read(&dst, None).unwrap();
        assert_eq!(d.positions, c.positions, "{name}: positions");
        assert_eq!(d.records, c.records, "{name}: records");
        if !copc {
            assert_same_file(&a, &b, true);
            continue;
        }
        // COPC → plain LAZ: the COPC layout records go, the laszip VLR gets fixed chunks.
        let mut ha = masked_header(&a.header);
        let mut hb = masked_header(&b.header);
        for h in [&mut ha, &mut hb] {
            h[96..104].fill(0); // offset to point data, number of VLRs
        }
        assert_eq!(ha, hb, "{name}: header");
        let keep = |v: &&Vec<u8>| {
            let (u, r) = user_record(v);
            !(u == "copc" && (r == 1 || r == 1000))
        };
        let fix = |v: &Vec<u8>| {
            let mut v = v.clone();
            if user_record(&v).0 == "laszip encoded" {
                v[54 + 12..54 + 16].fill(0);
            }
            v
        };
        let va: Vec<_> = a.vlrs.iter().filter(keep).map(fix).collect();
        let vb: Vec<_> = b.vlrs.iter().map(fix).collect();
        assert_eq!(va, vb, "{name}: VLRs");
        assert_eq!(b.vlrs.len(), a.vlrs.len() - 1);
        let ea: Vec<_> = a.evlrs.iter().filter(keep).cloned().collect();
        assert_eq!(ea, b.evlrs, "{name}: EVLRs");
        assert_eq!(b.evlrs.len() + 1, a.evlrs.len());
        let laszip = b.vlrs.iter().find(|v| user_record(v).0 == "laszip encoded");
        assert_eq!(u32_at(laszip.unwrap(), 54 + 12), 50_000);
    }
}

#[test]
#[ignore = "needs ../shared"]
fn shared_files_stream_in_batches() {
    // Streaming with small batches gives the same points as the whole-file read.
    let src = shared("32-1-472-150-76.laz");
    let whole = Cloud::read(&src, None).unwrap();
    let mut s = LasSource::open(&src).unwrap();
    let mut b = PointBatch::default();
    let mut got = Vec::new();
    let mut start = 0;
    loop {
        let n = s.read_batch(&mut b, 1000).unwrap();
        if n == 0 {
            break;
        }
        assert_eq!(b.start, start);
        start += n as u64;
        got.extend_from_slice(&b.positions);
    }
    assert_eq!(got, whole.positions);
    let _ = Box::new(s).finish().unwrap();
}
