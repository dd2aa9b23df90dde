//! PCD backend end to end: the three DATA kinds, COUNT > 1, organized clouds with NaN points, the
//! noise flag, moved positions, conversions, bad input, and (ignored by default) the shared scans.
//!
//! `cargo test --test tests io_pcd::` selects them all. Tests marked
//! `#[ignore = "needs ../shared"]` read the real data beside the repository.

use std::path::{Path, PathBuf};

use crate::util::{listing, put, rewrite};
use glam::DVec3;
use qem_denoise::io::pcd::{PcdData, PcdField};
use qem_denoise::io::{self, Cloud, Format, IoError, Meta, SinkOptions, Trailer};
use qem_denoise::points::{FLAG_NOISE, PointBatch, ScalarType};

// -----------------------------------------------------------------------------------------
// Helpers: PCD files built by hand from ascii tokens.

/// (name, SIZE, TYPE, COUNT)
type Spec = (&'static str, usize, char, usize);

/// Every PCD type, COUNT > 1 twice.
const FIELDS: &[Spec] = &[
    ("x", 4, 'F', 1),
    ("y", 4, 'F', 1),
    ("z", 4, 'F', 1),
    ("normal", 4, 'F', 3),
    ("intensity", 8, 'F', 1),
    ("rgba", 4, 'U', 1),
    ("label", 2, 'I', 1),
    ("ring", 1, 'U', 2),
    ("offset", 1, 'I', 1),
    ("stamp", 8, 'I', 1),
    ("id", 8, 'U', 1),
    ("w", 2, 'U', 1),
    ("k", 4, 'I', 1),
];

/// Tokens per point (COUNT expanded) for `FIELDS`, in shortest form.
fn rows(n: usize) -> Vec<Vec<String>> {
    let special = [
        vec![
            "1.5",
            "-2.25",
            "0.125",
            "0",
            "0",
            "1",
            "0.3",
            "4278190335",
            "-7",
            "3",
            "250",
            "-128",
            "-9000000000",
            "18446744073709551615",
            "65535",
            "-2147483648",
        ],
        vec![
            "nan",
            "nan",
            "nan",
            "0.60000002",
            "0.80000001",
            "0",
            "1e-07",
            "0",
            "32767",
            "0",
            "1",
            "127",
            "0",
            "42",
            "0",
            "2147483647",
        ],
        vec![
            "-10.015625",
            "0.042999268",
            "3.0000001e+20",
            "-1",
            "-0",
            "0",
            "-0.5",
            "16777215",
            "-32768",
            "255",
            "0",
            "0",
            "9223372036854775807",
            "0",
            "1",
            "0",
        ],
    ];
    (0..n)
        .map(|i| {
            if i < special.len() {
                return special[i].iter().map(|s| s.to_string()).collect();
            }
            let f = |v: f32| format!("{v}");
            vec![
                f((i % 17) as f32 * 0.25),
                f((i % 5) as f32 - 2.0),
                f(i as f32 * 0.5),
                "0".into(),
                "0".into(),
                "1".into(),
                format!("{}", (i % 3) as f64 * 0.5),
                format!("{}", 0xff00_0000u32 + (i % 4) as u32),
                format!("{}", i % 7),
                format!("{}", i % 2),
                "0".into(),
                "0".into(),
                format!("{}", i as i64 * 1000),
                format!("{i}"),
                "7".into(),
                "-1".into(),
            ]
        })
        .collect()
}

fn header(fields: &[Spec], w: usize, h: usize, data: &str) -> String {
    let col = |f: &dyn Fn(&Spec) -> String| fields.iter().map(f).collect::<Vec<_>>().join(" ");
    format!(
        "# .PCD v0.7 - Point Cloud Data file format\n# written by a test\nVERSION 0.7\n\
         FIELDS {}\nSIZE {}\nTYPE {}\nCOUNT {}\nWIDTH {w}\nHEIGHT {h}\n\
         VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {}\nDATA {data}\n",
        col(&|f| f.0.to_string()),
        col(&|f| f.1.to_string()),
        col(&|f| f.2.to_string()),
        col(&|f| f.3.to_string()),
        w * h
    )
}

/// The little-endian bytes of `tok` as SIZE/TYPE.
fn encode(size: usize, ty: char, tok: &str) -> Vec<u8> {
    match (ty, size) {
        ('F', 4) => tok.parse::<f32>().unwrap().to_le_bytes().to_vec(),
        ('F', 8) => tok.parse::<f64>().unwrap().to_le_bytes().to_vec(),
        ('I', 1) => tok.parse::<i8>().unwrap().to_le_bytes().to_vec(),
        ('I', 2) => tok.parse::<i16>().unwrap().to_le_bytes().to_vec(),
        ('I', 4) => tok.parse::<i32>().unwrap().to_le_bytes().to_vec(),
        ('I', 8) => tok.parse::<i64>().unwrap().to_le_bytes().to_vec(),
        ('U', 1) => tok.parse::<u8>().unwrap().to_le_bytes().to_vec(),
        ('U', 2) => tok.parse::<u16>().unwrap().to_le_bytes().to_vec(),
        ('U', 4) => tok.parse::<u32>().unwrap().to_le_bytes().to_vec(),
        ('U', 8) => tok.parse::<u64>().unwrap().to_le_bytes().to_vec(),
        _ => panic!("bad spec"),
    }
}

/// Per point, per PCD field: the bytes of its COUNT values.
fn values(fields: &[Spec], rows: &[Vec<String>]) -> Vec<Vec<Vec<u8>>> {
    rows.iter()
        .map(|toks| {
            let mut t = toks.iter();
            fields
                .iter()
                .map(|&(_, size, ty, count)| {
                    (0..count)
                        .flat_map(|_| encode(size, ty, t.next().unwrap()))
                        .collect()
                })
                .collect()
        })
        .collect()
}

fn ascii_file(fields: &[Spec], rows: &[Vec<String>], w: usize, h: usize) -> Vec<u8> {
    let mut s = header(fields, w, h, "ascii");
    for r in rows {
        s.push_str(&r.join(" "));
        s.push('\n');
    }
    s.into_bytes()
}

fn binary_file(fields: &[Spec], rows: &[Vec<String>], w: usize, h: usize) -> Vec<u8> {
    let mut b = header(fields, w, h, "binary").into_bytes();
    for p in values(fields, rows) {
        b.extend(p.concat());
    }
    b
}

/// The uncompressed column-major block (padding fields `_` left out, as PCL does).
fn column_block(fields: &[Spec], rows: &[Vec<String>]) -> Vec<u8> {
    let v = values(fields, rows);
    let mut block = Vec::new();
    for (k, f) in fields.iter().enumerate() {
        if f.0 != "_" {
            for p in &v {
                block.extend_from_slice(&p[k]);
            }
        }
    }
    block
}

fn compressed_file(
    fields: &[Spec],
    rows: &[Vec<String>],
    w: usize,
    h: usize,
    lzf_block: impl Fn(&[u8]) -> Vec<u8>,
) -> Vec<u8> {
    let mut b = header(fields, w, h, "binary_compressed").into_bytes();
    let block = column_block(fields, rows);
    let packed = lzf_block(&block);
    b.extend((packed.len() as u32).to_le_bytes());
    b.extend((block.len() as u32).to_le_bytes());
    b.extend(packed);
    b
}

/// LZF as the `lzf` crate writes it (what the sink uses).
fn lzf_crate(block: &[u8]) -> Vec<u8> {
    lzf::compress(block).expect("test data is compressible")
}

/// Valid LZF of another encoder: literal runs only.
fn literal_lzf(block: &[u8]) -> Vec<u8> {
    block
        .chunks(32)
        .flat_map(|c| std::iter::once((c.len() - 1) as u8).chain(c.iter().copied()))
        .collect()
}

fn meta(c: &Cloud) -> &io::pcd::PcdMeta {
    match &c.info.meta {
        Meta::Pcd(m) => m,
        other => panic!("not a PCD meta: {other:?}"),
    }
}

/// Equal positions, NaN equal to NaN.
fn same_position(a: DVec3, b: DVec3) -> bool {
    let eq = |x: f64, y: f64| x == y || (x.is_nan() && y.is_nan());
    eq(a.x, b.x) && eq(a.y, b.y) && eq(a.z, b.z)
}

/// The header of a PCD file (up to and including the DATA line).
fn header_of(bytes: &[u8]) -> String {
    let s = String::from_utf8_lossy(bytes);
    let i = s.find("DATA ").unwrap();
    let j = s[i..].find('\n').unwrap();
    s[..i + j + 1].to_string()
}

// -----------------------------------------------------------------------------------------
// Round trips of the three DATA kinds.

#[test]
fn binary_roundtrip_is_byte_identical_with_every_type_and_count() {
    let dir = tempfile::tempdir().unwrap();
    let rows = rows(5);
    let mut bytes = binary_file(FIELDS, &rows, 5, 1);
    bytes.extend_from_slice(&[0, 0, 0, 7]); // trailing bytes are kept too
    let p = put(dir.path(), "a.pcd", &bytes);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.format, Format::Pcd);
    assert_eq!(c.len(), 5);
    assert_eq!(c.info.len, Some(5));
    assert!(!c.info.is_organized());
    let names: Vec<&str> = c
        .info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect();
    assert_eq!(
        names,
        [
            "x",
            "y",
            "z",
            "normal[0]",
            "normal[1]",
            "normal[2]",
            "intensity",
            "rgba",
            "label",
            "ring[0]",
            "ring[1]",
            "offset",
            "stamp",
            "id",
            "w",
            "k"
        ]
    );
    let types: Vec<ScalarType> = c.info.schema.fields.iter().map(|f| f.ty).collect();
    use ScalarType::*;
    assert_eq!(
        types,
        [
            F32, F32, F32, F32, F32, F32, F64, U32, I16, U8, U8, I8, I64, U64, U16, I32
        ]
    );
    assert_eq!(
        c.info.schema.record_len,
        4 * 6 + 8 + 4 + 2 + 2 + 1 + 8 + 8 + 2 + 4
    );
    let m = meta(&c);
    assert_eq!(m.data(), PcdData::Binary);
    assert_eq!(m.fields()[3], PcdField::new("normal", F32, 3));
    assert_eq!((m.width(), m.height(), m.points()), (5, 1, 5));
    assert_eq!(m.version(), Some("0.7"));
    assert_eq!(m.comments().len(), 2);
    assert_eq!(m.viewpoint(), [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
    assert_eq!(c.positions[0], DVec3::new(1.5, -2.25, 0.125));
    assert!(c.positions[1].x.is_nan());
    // Records are the file's rows.
    let body = &bytes[header_of(&bytes).len()..];
    assert_eq!(&c.records[..], &body[..c.records.len()]);
    let id = c.info.schema.field_index("id").unwrap();
    let off = c.info.schema.fields[id].offset;
    assert_eq!(&c.records[off..off + 8], &u64::MAX.to_le_bytes());
    let Trailer::Pcd(t) = &c.extras.trailer else {
        panic!()
    };
    assert_eq!(t.tail_bytes(), &[0, 0, 0, 7]);

    assert_eq!(rewrite(&p, "b.pcd"), bytes);
}

#[test]
fn ascii_roundtrip_is_byte_identical_and_matches_binary_values() {
    let dir = tempfile::tempdir().unwrap();
    let rows = rows(6);
    let text = ascii_file(FIELDS, &rows, 6, 1);
    let p = put(dir.path(), "a.pcd", &text);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(meta(&c).data(), PcdData::Ascii);
    assert_eq!(c.len(), 6);
    let out = rewrite(&p, "b.pcd");
    assert_eq!(
        String::from_utf8_lossy(&out),
        String::from_utf8_lossy(&text)
    );

    let bin = put(dir.path(), "c.pcd", binary_file(FIELDS, &rows, 6, 1));
    let b = Cloud::read(&bin, None).unwrap();
    assert_eq!(b.info.schema, c.info.schema);
    assert_eq!(
        b.records, c.records,
        "ascii and binary decode to the same records"
    );

    // CRLF lines, tabs, blank lines and a last line without terminator.
    let mut crlf = header(FIELDS, 2, 1, "ascii").replace('\n', "\r\n");
    crlf.push_str(&rows[3].join("\t"));
    crlf.push_str("\r\n\r\n");
    crlf.push_str(&rows[4].join(" "));
    let p = put(dir.path(), "d.pcd", &crlf);
    let d = Cloud::read(&p, None).unwrap();
    assert_eq!(
        &d.records[..],
        &b.records[3 * d.info.schema.record_len..5 * d.info.schema.record_len]
    );
    let out = rewrite(&p, "e.pcd");
    let want = format!(
        "{}{}\r\n{}",
        header(FIELDS, 2, 1, "ascii").replace('\n', "\r\n"),
        rows[3].join(" "),
        rows[4].join(" ")
    );
    assert_eq!(String::from_utf8_lossy(&out), want);
}

#[test]
fn binary_compressed_roundtrip_is_byte_identical() {
    let dir = tempfile::tempdir().unwrap();
    let rows = rows(300);
    let mut bytes = compressed_file(FIELDS, &rows, 300, 1, lzf_crate);
    bytes.extend(vec![0u8; 1000]); // PCL pads its files with zeros
    let p = put(dir.path(), "a.pcd", &bytes);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(meta(&c).data(), PcdData::BinaryCompressed);
    assert_eq!(c.len(), 300);
    let bin = put(dir.path(), "b.pcd", binary_file(FIELDS, &rows, 300, 1));
    let b = Cloud::read(&bin, None).unwrap();
    assert_eq!(
        b.records, c.records,
        "the column-major block is transposed to rows"
    );
    assert_eq!(rewrite(&p, "c.pcd"), bytes);

    // Small batches read the same records.
    let mut src = io::open(&p, None).unwrap();
    let mut batch = PointBatch::default();
    let mut records = Vec::new();
    while src.read_batch(&mut batch, 7).unwrap() > 0 {
        records.extend_from_slice(&batch.records);
    }
    assert_eq!(records, c.records);
}

#[test]
fn binary_compressed_of_another_encoder_keeps_header_and_content() {
    // PCL's LZF encoder differs from the `lzf` crate's: compare header and decompressed
    // content, not the compressed bytes.
    let dir = tempfile::tempdir().unwrap();
    let rows = rows(64);
    let bytes = compressed_file(FIELDS, &rows, 64, 1, literal_lzf);
    let p = put(dir.path(), "a.pcd", &bytes);
    let out = rewrite(&p, "b.pcd");
    assert_ne!(out, bytes);
    assert_eq!(header_of(&out), header_of(&bytes));
    let (a, b) = (
        Cloud::read(&p, None).unwrap(),
        Cloud::read(&dir.path().join("b.pcd"), None).unwrap(),
    );
    assert_eq!(a.records, b.records);
    assert_eq!(
        out.len(),
        header_of(&out).len() + 8 + lzf_crate(&column_block(FIELDS, &rows)).len()
    );
}

#[test]
fn padding_fields_are_left_out_of_compressed_blocks() {
    let dir = tempfile::tempdir().unwrap();
    let fields: &[Spec] = &[
        ("x", 4, 'F', 1),
        ("y", 4, 'F', 1),
        ("z", 4, 'F', 1),
        ("_", 1, 'U', 4),
        ("rgb", 4, 'F', 1),
    ];
    let rows: Vec<Vec<String>> = (0..100)
        .map(|i| {
            let mut r: Vec<String> = vec![format!("{}", i as f32 * 0.5), "1".into(), "2".into()];
            r.extend(["0", "0", "0", "0"].map(String::from));
            r.push("4.5".into());
            r
        })
        .collect();
    let bytes = compressed_file(fields, &rows, 100, 1, lzf_crate);
    let p = put(dir.path(), "a.pcd", &bytes);
    let c = Cloud::read(&p, None).unwrap();
    assert_eq!(c.info.schema.record_len, 20);
    let bin = Cloud::read(
        &put(dir.path(), "b.pcd", binary_file(fields, &rows, 100, 1)),
        None,
    )
    .unwrap();
    assert_eq!(c.records, bin.records);
    assert_eq!(rewrite(&p, "c.pcd"), bytes);
}

#[test]
fn data_kinds_convert_into_each_other() {
    let dir = tempfile::tempdir().unwrap();
    let rows = rows(40);
    let p = put(dir.path(), "a.pcd", binary_file(FIELDS, &rows, 40, 1));
    let orig = Cloud::read(&p, None).unwrap();
    let mut c = orig.clone();
    for (kind, name) in [
        (PcdData::BinaryCompressed, "c.pcd"),
        (PcdData::Ascii, "d.pcd"),
        (PcdData::Binary, "e.pcd"),
    ] {
        let Meta::Pcd(m) = &mut c.info.meta else {
            panic!()
        };
        m.set_data(kind);
        let out = dir.path().join(name);
        c.write(&out, None).unwrap();
        c = Cloud::read(&out, None).unwrap();
        assert_eq!(meta(&c).data(), kind);
        assert_eq!(c.records, orig.records, "{kind:?}");
    }
    assert_eq!(
        std::fs::read(dir.path().join("e.pcd")).unwrap(),
        std::fs::read(&p).unwrap()
    );
}

// -----------------------------------------------------------------------------------------
// Organized clouds.

const ORGANIZED: &[Spec] = &[
    ("x", 4, 'F', 1),
    ("y", 4, 'F', 1),
    ("z", 4, 'F', 1),
    ("rgba", 4, 'U', 1),
];

fn organized_rows() -> Vec<Vec<String>> {
    (0..6)
        .map(|i| {
            let v = if i == 1 || i == 4 {
                vec!["nan".to_string(); 3]
            } else {
                vec![
                    format!("{}", i % 3),
                    format!("{}", i / 3),
                    "2.5".to_string(),
                ]
            };
            let mut v = v;
            v.push(format!("{}", 0xff00_0000u32 + i));
            v
        })
        .collect()
}

#[test]
fn organized_cloud_keeps_nan_points_and_its_size() {
    let dir = tempfile::tempdir().unwrap();
    let rows = organized_rows();
    for (name, bytes) in [
        ("bin.pcd", binary_file(ORGANIZED, &rows, 3, 2)),
        ("asc.pcd", ascii_file(ORGANIZED, &rows, 3, 2)),
        (
            "lzf.pcd",
            compressed_file(ORGANIZED, &rows, 3, 2, literal_lzf),
        ),
    ] {
        let p = put(dir.path(), name, &bytes);
        let mut c = Cloud::read(&p, None).unwrap();
        assert!(c.info.is_organized(), "{name}");
        assert!(meta(&c).is_organized());
        assert_eq!((meta(&c).width(), meta(&c).height()), (3, 2));
        assert_eq!(c.len(), 6);
        let nan: Vec<usize> = (0..6).filter(|&i| c.positions[i].x.is_nan()).collect();
        assert_eq!(nan, [1, 4], "{name}: NaN points are delivered in place");
        // Move the valid points, give the invalid ones back as NaN.
        for p in c.positions.iter_mut() {
            if p.is_finite() {
                p.z += 1.0;
            } else {
                *p = DVec3::splat(f64::NAN);
            }
        }
        let out = dir.path().join(format!("out_{name}"));
        c.write(&out, None).unwrap();
        let text = header_of(&std::fs::read(&out).unwrap());
        assert!(text.contains("WIDTH 3\nHEIGHT 2\n"), "{name}: {text}");
        let d = Cloud::read(&out, None).unwrap();
        assert!(d.info.is_organized());
        for i in 0..6 {
            assert!(
                same_position(d.positions[i], c.positions[i]),
                "{name} point {i}"
            );
        }
        assert_eq!(d.positions[0].z, 3.5);
        let rgba = d.info.schema.field_index("rgba").unwrap();
        for i in 0..6 {
            let rec = &d.records[i * 16..(i + 1) * 16];
            assert_eq!(
                d.info.schema.get_f64(rec, rgba),
                (0xff00_0000u32 + i as u32) as f64
            );
        }
    }
}

#[test]
fn organized_cloud_with_fewer_points_becomes_unorganized() {
    let dir = tempfile::tempdir().unwrap();
    let p = put(
        dir.path(),
        "a.pcd",
        binary_file(ORGANIZED, &organized_rows(), 3, 2),
    );
    let c = Cloud::read(&p, None).unwrap();
    let keep: Vec<usize> = (0..6).filter(|&i| c.positions[i].is_finite()).collect();
    let mut d = c.clone();
    d.positions = keep.iter().map(|&i| c.positions[i]).collect();
    d.records = keep
        .iter()
        .flat_map(|&i| c.records[i * 16..(i + 1) * 16].to_vec())
        .collect();
    let out = dir.path().join("b.pcd");
    d.write(&out, None).unwrap();
    let text = header_of(&std::fs::read(&out).unwrap());
    assert!(text.contains("WIDTH 4\nHEIGHT 1\n"), "{text}");
    assert!(text.contains("POINTS 4\n"), "{text}");
    assert!(text.starts_with("# .PCD v0.7 - Point Cloud Data file format\n# written by a test\n"));
    let e = Cloud::read(&out, None).unwrap();
    assert!(!e.info.is_organized());
    assert_eq!(e.records, d.records);
}

// -----------------------------------------------------------------------------------------
// Noise flag.

fn write_with_noise(c: &Cloud, out: &Path, flags: &[u8]) {
    let mut sink = io::create_with(
        out,
        None,
        &c.info,
        c.len() as u64,
        &SinkOptions {
            noise_flag: true,
            ..SinkOptions::default()
        },
    )
    .unwrap();
    let mut b = PointBatch::with_capacity(c.info.schema.record_len, c.len());
    for i in 0..c.len() {
        b.push(
            c.positions[i],
            &c.records[i * c.info.schema.record_len..][..c.info.schema.record_len],
        );
    }
    b.flags = flags.to_vec();
    sink.write_batch(&b).unwrap();
    sink.finish(&c.extras).unwrap();
}

#[test]
fn noise_flag_appends_a_noise_field_in_every_data_kind() {
    let dir = tempfile::tempdir().unwrap();
    let rows = organized_rows();
    let flags = [0, FLAG_NOISE, 0, FLAG_NOISE | 0x80, 0, 0];
    for (name, bytes) in [
        ("bin.pcd", binary_file(ORGANIZED, &rows, 6, 1)),
        ("asc.pcd", ascii_file(ORGANIZED, &rows, 6, 1)),
        (
            "lzf.pcd",
            compressed_file(ORGANIZED, &rows, 6, 1, literal_lzf),
        ),
    ] {
        let p = put(dir.path(), name, &bytes);
        let c = Cloud::read(&p, None).unwrap();
        let out = dir.path().join(format!("noise_{name}"));
        write_with_noise(&c, &out, &flags);
        let text = header_of(&std::fs::read(&out).unwrap());
        for line in [
            "FIELDS x y z rgba noise\n",
            "SIZE 4 4 4 4 1\n",
            "TYPE F F F U U\n",
            "COUNT 1 1 1 1 1\n",
        ] {
            assert!(text.contains(line), "{name}: {text}");
        }
        let d = Cloud::read(&out, None).unwrap();
        let s = &d.info.schema;
        assert_eq!(s.record_len, 17);
        let k = s.field_index("noise").unwrap();
        assert_eq!(s.fields[k].ty, ScalarType::U8);
        let got: Vec<f64> = (0..6)
            .map(|i| s.get_f64(&d.records[i * 17..(i + 1) * 17], k))
            .collect();
        assert_eq!(got, [0.0, 1.0, 0.0, 1.0, 0.0, 0.0], "{name}");
        for i in 0..6 {
            assert_eq!(
                &d.records[i * 17..i * 17 + 16],
                &c.records[i * 16..(i + 1) * 16]
            );
        }
        // A second run overwrites the field instead of adding another one.
        let again = dir.path().join(format!("again_{name}"));
        write_with_noise(&d, &again, &[1, 1, 0, 0, 0, 0]);
        let e = Cloud::read(&again, None).unwrap();
        assert_eq!(e.info.schema, d.info.schema);
        assert_eq!(e.records[16], 1);
        assert_eq!(e.records[17 + 16], 1);
        assert_eq!(e.records[3 * 17 + 16], 0);
    }
    // Without flags in the batch every point gets 0; other formats still refuse the option.
    let c = Cloud::read(&dir.path().join("bin.pcd"), None).unwrap();
    let out = dir.path().join("zero.pcd");
    write_with_noise(&c, &out, &[]);
    let d = Cloud::read(&out, None).unwrap();
    assert!((0..6).all(|i| d.records[i * 17 + 16] == 0));
    let e = io::create_with(
        &dir.path().join("x.bin"),
        None,
        &c.info,
        6,
        &SinkOptions {
            noise_flag: true,
            ..SinkOptions::default()
        },
    );
    assert!(matches!(e, Err(IoError::Unsupported { .. })));
}

// -----------------------------------------------------------------------------------------
// Moved positions.

#[test]
fn moved_positions_change_only_xyz() {
    let dir = tempfile::tempdir().unwrap();
    let rows = rows(50);
    for (name, bytes) in [
        ("bin.pcd", binary_file(FIELDS, &rows, 50, 1)),
        ("asc.pcd", ascii_file(FIELDS, &rows, 50, 1)),
        ("lzf.pcd", compressed_file(FIELDS, &rows, 50, 1, lzf_crate)),
    ] {
        let p = put(dir.path(), name, &bytes);
        let mut c = Cloud::read(&p, None).unwrap();
        for (i, q) in c.positions.iter_mut().enumerate() {
            if i % 2 == 0 {
                *q = DVec3::new(i as f64 + 0.5, -(i as f64), 100.25);
            }
        }
        let out = dir.path().join(format!("moved_{name}"));
        c.write(&out, None).unwrap();
        let d = Cloud::read(&out, None).unwrap();
        let rl = c.info.schema.record_len;
        for i in 0..50 {
            let (a, b) = (
                &c.records[i * rl..(i + 1) * rl],
                &d.records[i * rl..(i + 1) * rl],
            );
            assert_eq!(&a[12..], &b[12..], "{name}: point {i} attributes untouched");
            if i % 2 == 0 {
                assert_eq!(d.positions[i], c.positions[i], "{name}");
            } else {
                assert_eq!(
                    &a[..12],
                    &b[..12],
                    "{name}: unmoved point {i} is byte-identical"
                );
            }
        }
    }
}

// -----------------------------------------------------------------------------------------
// Other origins.

#[test]
fn generated_cloud_is_written_as_binary_with_its_schema() {
    let dir = tempfile::tempdir().unwrap();
    let pts = vec![DVec3::new(1.0, 2.0, 3.0), DVec3::new(-0.5, 0.25, 1e-3)];
    let c = Cloud::generated(pts.clone(), None, ScalarType::F64);
    let out = dir.path().join("g.pcd");
    c.write(&out, None).unwrap();
    let bytes = std::fs::read(&out).unwrap();
    let want = "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n\
                SIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n\
                VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA binary\n";
    assert_eq!(header_of(&bytes), want);
    assert_eq!(bytes.len(), want.len() + 48);
    let d = Cloud::read(&out, None).unwrap();
    assert_eq!(d.positions, pts);
}

#[test]
fn big_endian_ply_fields_are_converted() {
    let dir = tempfile::tempdir().unwrap();
    let mut ply = b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n\
                    property float y\nproperty float z\nproperty ushort val\nend_header\n"
        .to_vec();
    for (p, v) in [([1.0f32, 2.0, 3.0], 513u16), ([4.0, 5.0, 6.5], 7)] {
        for c in p {
            ply.extend(c.to_be_bytes());
        }
        ply.extend(v.to_be_bytes());
    }
    let src = put(dir.path(), "a.ply", &ply);
    let c = Cloud::read(&src, None).unwrap();
    let out = dir.path().join("a.pcd");
    c.write(&out, None).unwrap();
    let bytes = std::fs::read(&out).unwrap();
    let h = header_of(&bytes);
    assert!(
        h.contains("FIELDS x y z val\nSIZE 4 4 4 2\nTYPE F F F U\n"),
        "{h}"
    );
    let d = Cloud::read(&out, None).unwrap();
    assert_eq!(d.positions[1], DVec3::new(4.0, 5.0, 6.5));
    assert_eq!(d.info.schema.get_f64(&d.records[..14], 3), 513.0);
    assert_eq!(&bytes[h.len() + 12..h.len() + 14], &513u16.to_le_bytes());
}

#[test]
fn format_is_told_from_the_extension() {
    assert_eq!(
        Format::from_path(Path::new("scan.PCD")).unwrap(),
        Format::Pcd
    );
    assert_eq!(Format::from_name("pcd"), Some(Format::Pcd));
    assert_eq!(Format::Pcd.name(), "pcd");
}

// -----------------------------------------------------------------------------------------
// Bad input: one-line errors naming the file, no panic.

fn open_err(bytes: &[u8]) -> (IoError, String) {
    let dir = tempfile::tempdir().unwrap();
    let p = put(dir.path(), "bad.pcd", bytes);
    let e = match Cloud::read(&p, None) {
        Ok(_) => panic!("reading must fail"),
        Err(e) => e,
    };
    let msg = e.to_string();
    assert!(msg.contains("bad.pcd"), "{msg}");
    assert!(!msg.contains('\n'), "one line: {msg}");
    (e, msg)
}

fn small_rows() -> Vec<Vec<String>> {
    rows_of(3)
}

/// `n` points of `ORGANIZED` fields, ascii lines of 16 bytes.
fn rows_of(n: usize) -> Vec<Vec<String>> {
    (0..n)
        .map(|i| {
            vec![
                format!("{}.5", i % 10),
                "1.25".into(),
                "2.75".into(),
                "4".into(),
            ]
        })
        .collect()
}

#[test]
fn error_empty_file() {
    let (e, msg) = open_err(b"");
    assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
    assert!(msg.contains("empty file"), "{msg}");
}

#[test]
fn error_not_a_pcd() {
    let (e, msg) = open_err(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n");
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
    assert!(msg.contains("not a PCD file"), "{msg}");
    let (_, msg) = open_err(&[0x89, b'P', b'N', b'G', 0, 1, 2, 3]);
    assert!(msg.contains("not a PCD file"), "{msg}");
    let (_, msg) = open_err(b"# only a comment\n");
    assert!(msg.contains("not a PCD file"), "{msg}");
}

#[test]
fn error_truncated_binary_data() {
    let mut b = binary_file(ORGANIZED, &small_rows(), 3, 1);
    b.truncate(b.len() - 10);
    let (e, msg) = open_err(&b);
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
    assert!(
        msg.contains("header announces 3 points (48 bytes)"),
        "{msg}"
    );
}

#[test]
fn error_header_claims_more_points_than_present() {
    let text = ascii_file(ORGANIZED, &small_rows(), 3, 1);
    let more = String::from_utf8(text)
        .unwrap()
        .replace("WIDTH 3", "WIDTH 5")
        .replace("POINTS 3", "POINTS 5");
    let (e, msg) = open_err(more.as_bytes());
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
    assert!(
        msg.contains("header announces 5 points but the data ends after 3"),
        "{msg}"
    );
    // Far too little data is caught before any point is read.
    let few = more
        .replace("WIDTH 5", "WIDTH 50")
        .replace("POINTS 5", "POINTS 50");
    let (e, msg) = open_err(few.as_bytes());
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
    assert!(
        msg.contains("header announces 50 points (at least 399 bytes"),
        "{msg}"
    );

    let b = compressed_file(ORGANIZED, &small_rows(), 3, 1, literal_lzf);
    let b = String::from_utf8_lossy(&b[..header_of(&b).len()])
        .replace("WIDTH 3", "WIDTH 4")
        .replace("POINTS 3", "POINTS 4")
        .into_bytes()
        .into_iter()
        .chain(b[header_of(&b).len()..].iter().copied())
        .collect::<Vec<u8>>();
    let (_, msg) = open_err(&b);
    assert!(
        msg.contains("header announces 4 points (64 bytes uncompressed)"),
        "{msg}"
    );
}

#[test]
fn error_bad_lzf_block() {
    let b = compressed_file(ORGANIZED, &small_rows(), 3, 1, literal_lzf);
    let h = header_of(&b).len();
    // A back reference to before the start of the output.
    let mut bad = b.clone();
    bad[h + 8] = 0xe0;
    let (e, msg) = open_err(&bad);
    assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
    assert!(
        msg.contains("corrupt binary_compressed (LZF) block"),
        "{msg}"
    );
    // A block that stops short of its announced size.
    let mut short = b[..h].to_vec();
    short.extend(20u32.to_le_bytes());
    short.extend(48u32.to_le_bytes());
    short.extend(literal_lzf(&[7u8; 19]));
    let (_, msg) = open_err(&short);
    assert!(
        msg.contains("corrupt binary_compressed (LZF) block"),
        "{msg}"
    );
    // An impossible expansion ratio is refused before allocating.
    let big = compressed_file(ORGANIZED, &rows_of(300), 300, 1, literal_lzf);
    let h = header_of(&big).len();
    let mut huge = big[..h].to_vec();
    huge.extend(10u32.to_le_bytes());
    huge.extend(4800u32.to_le_bytes());
    huge.extend([0u8; 10]);
    let (_, msg) = open_err(&huge);
    assert!(
        msg.contains("10 LZF bytes cannot decode to 4800 bytes"),
        "{msg}"
    );
}

#[test]
fn error_truncated_lzf_block() {
    let b = compressed_file(ORGANIZED, &small_rows(), 3, 1, literal_lzf);
    let (e, msg) = open_err(&b[..b.len() - 5]);
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
    let h = header_of(&b).len();
    let (e, msg) = open_err(&b[..h + 5]);
    assert!(matches!(e, IoError::Truncated { .. }), "{msg}");
    assert!(msg.contains("8-byte size header"), "{msg}");
}

#[test]
fn error_bad_ascii_number() {
    let mut rows = small_rows();
    rows[1][2] = "1.2.3".into();
    let (e, msg) = open_err(&ascii_file(ORGANIZED, &rows, 3, 1));
    assert!(matches!(e, IoError::Invalid { .. }), "{msg}");
    assert!(
        msg.contains("line 14: bad number `1.2.3` for field `z`"),
        "{msg}"
    );
    let mut rows = small_rows();
    rows[0][3] = "-1".into();
    let (_, msg) = open_err(&ascii_file(ORGANIZED, &rows, 3, 1));
    assert!(
        msg.contains("line 13: bad number `-1` for field `rgba`"),
        "{msg}"
    );
}

#[test]
fn error_wrong_number_of_ascii_values() {
    let mut rows = small_rows();
    rows[2].push("9".into());
    let (_, msg) = open_err(&ascii_file(ORGANIZED, &rows, 3, 1));
    assert!(msg.contains("line 15: 5 values, expected 4"), "{msg}");
    let mut rows = small_rows();
    rows[0].pop();
    let (_, msg) = open_err(&ascii_file(ORGANIZED, &rows, 3, 1));
    assert!(msg.contains("line 13: 3 values, expected 4"), "{msg}");
}

#[test]
fn error_missing_xyz() {
    let fields: &[Spec] = &[("x", 4, 'F', 1), ("y", 4, 'F', 1), ("intensity", 4, 'F', 1)];
    let (e, msg) = open_err(header(fields, 0, 1, "binary").as_bytes());
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
    assert!(msg.contains("no field `z`"), "{msg}");
}

#[test]
fn error_inconsistent_header() {
    let h = header(ORGANIZED, 3, 2, "binary").replace("POINTS 6", "POINTS 7");
    let (e, msg) = open_err(h.as_bytes());
    assert!(matches!(e, IoError::Header { .. }), "{msg}");
    assert!(
        msg.contains("WIDTH 3 × HEIGHT 2 does not equal POINTS 7"),
        "{msg}"
    );
}

#[test]
fn error_missing_file_names_it() {
    let e = Cloud::read(Path::new("/nonexistent/dir/x.pcd"), None).unwrap_err();
    assert!(e.to_string().contains("/nonexistent/dir/x.pcd"), "{e}");
}

#[test]
fn failed_writes_leave_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let rows = small_rows();
    for (name, bytes) in [
        ("bin.pcd", binary_file(ORGANIZED, &rows, 3, 1)),
        ("asc.pcd", ascii_file(ORGANIZED, &rows, 3, 1)),
        (
            "lzf.pcd",
            compressed_file(ORGANIZED, &rows, 3, 1, literal_lzf),
        ),
    ] {
        let src = put(dir.path(), name, &bytes);
        let c = Cloud::read(&src, None).unwrap();
        let before = listing(dir.path());
        let out = dir.path().join(format!("out_{name}"));
        // Fewer points than announced: refused at finish.
        let mut sink = io::create(&out, None, &c.info, 3).unwrap();
        let mut b = PointBatch::with_capacity(16, 2);
        for i in 0..2 {
            b.push(c.positions[i], &c.records[i * 16..(i + 1) * 16]);
        }
        sink.write_batch(&b).unwrap();
        let e = sink.finish(&c.extras).unwrap_err();
        assert!(
            e.to_string()
                .contains("wrote 2 points but 3 were announced"),
            "{e}"
        );
        assert!(e.to_string().contains(&out.display().to_string()), "{e}");
        assert_eq!(
            listing(dir.path()),
            before,
            "{name}: no output or temporary file"
        );
        // More points than announced: refused at the batch.
        let mut sink = io::create(&out, None, &c.info, 1).unwrap();
        assert!(sink.write_batch(&b).is_err());
        drop(sink);
        assert_eq!(listing(dir.path()), before, "{name}");
        // Records of another layout: refused.
        let mut sink = io::create(&out, None, &c.info, 2).unwrap();
        let mut wrong = PointBatch::with_capacity(12, 1);
        wrong.push(DVec3::ZERO, &[0; 12]);
        assert!(sink.write_batch(&wrong).is_err());
        drop(sink);
        assert_eq!(listing(dir.path()), before, "{name}");
    }
}

// -----------------------------------------------------------------------------------------
// Shared data (run with `--include-ignored` from the repository root, `../shared` beside it).

fn shared(rel: &str) -> PathBuf {
    Path::new("../shared/data/scans").join(rel)
}

/// Reads `name`, checks count and fields, writes it back in its own DATA kind, re-reads and
/// compares every field value (NaN-aware) and the header.
fn check_shared(name: &str, points: u64, fields: &[&str], data: PcdData) -> Cloud {
    let path = shared(name);
    let c = Cloud::read(&path, None).unwrap();
    assert_eq!(c.len() as u64, points, "{name}");
    let names: Vec<&str> = c
        .info
        .schema
        .fields
        .iter()
        .map(|f| f.name.as_str())
        .collect();
    assert_eq!(names, fields, "{name}");
    assert_eq!(meta(&c).data(), data, "{name}");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join(name);
    c.write(&out, None).unwrap();
    let (a, b) = (std::fs::read(&path).unwrap(), std::fs::read(&out).unwrap());
    assert_eq!(header_of(&a), header_of(&b), "{name}: header reproduced");
    let d = Cloud::read(&out, None).unwrap();
    assert_eq!(meta(&d).data(), data);
    assert_eq!(d.len(), c.len());
    let s = &c.info.schema;
    let rl = s.record_len;
    for i in 0..c.len() {
        assert!(
            same_position(c.positions[i], d.positions[i]),
            "{name} point {i}"
        );
        let (ra, rb) = (
            &c.records[i * rl..(i + 1) * rl],
            &d.records[i * rl..(i + 1) * rl],
        );
        for k in 0..s.fields.len() {
            let (va, vb) = (s.get_f64(ra, k), s.get_f64(rb, k));
            assert!(
                va == vb || (va.is_nan() && vb.is_nan()),
                "{name} point {i} field {k}"
            );
        }
        assert_eq!(ra, rb, "{name} point {i}: record bytes");
    }
    match data {
        // Same encoding: the same bytes (the tail is kept too). Ascii values print like PCL's
        // `%.8g` whenever that is exact, so PCL's ascii files come back byte for byte too.
        PcdData::Binary | PcdData::Ascii => assert!(a == b, "{name}: output differs"),
        // PCL's LZF encoder differs from the lzf crate's; the trailing padding is kept.
        PcdData::BinaryCompressed => {
            let Trailer::Pcd(t) = &c.extras.trailer else {
                panic!()
            };
            assert!(b.ends_with(t.tail_bytes()));
        }
    }
    d
}

#[test]
#[ignore = "needs ../shared"]
fn shared_table_scene_is_organized_with_nan_points() {
    let d = check_shared(
        "table_scene_mug_stereo_textured.pcd",
        307_200,
        &["x", "y", "z", "rgba"],
        PcdData::BinaryCompressed,
    );
    assert!(d.info.is_organized());
    assert_eq!((meta(&d).width(), meta(&d).height()), (640, 480));
    let nan = d.positions.iter().filter(|p| p.x.is_nan()).count();
    assert!(nan > 1000, "{nan} NaN points");
    assert!(d.positions.iter().filter(|p| p.is_finite()).count() > 100_000);
    assert_eq!(d.info.schema.fields[3].ty, ScalarType::U32);
}

#[test]
#[ignore = "needs ../shared"]
fn shared_compressed_scans() {
    check_shared(
        "cturtle.pcd",
        167_198,
        &["x", "y", "z", "intensity"],
        PcdData::BinaryCompressed,
    );
    check_shared(
        "room_scan1.pcd",
        112_586,
        &["x", "y", "z"],
        PcdData::BinaryCompressed,
    );
    check_shared(
        "terrain_samp11-utm.pcd",
        38_010,
        &["x", "y", "z"],
        PcdData::BinaryCompressed,
    );
}

#[test]
#[ignore = "needs ../shared"]
fn shared_ascii_lamppost() {
    let d = check_shared("lamppost.pcd", 1_771, &["x", "y", "z"], PcdData::Ascii);
    assert!(!d.info.is_organized());
    assert_eq!(d.positions[0], DVec3::new(-10.0, 0.0, 0.0));
}

#[test]
#[ignore = "needs ../shared"]
fn shared_every_pcd_is_read() {
    let mut n = 0;
    for entry in std::fs::read_dir(shared("")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "pcd") {
            let c = Cloud::read(&path, None).unwrap();
            assert!(c.len() > 1000, "{}", path.display());
            n += 1;
        }
    }
    assert_eq!(n, 5);
}
