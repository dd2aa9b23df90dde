//! Point data: ascii values, the column-major layout of `binary_compressed` data, and LZF.

use std::io::Write;

use super::header::PcdField;
use crate::points::ScalarType;

// ---------------------------------------------------------------------------------------------
// Ascii values.

/// Parses one ascii value of type `ty` into its little-endian bytes `out` (`ty.size()` bytes).
///
/// Floats accept `nan` and `inf` in any case and sign, and are parsed directly in their own
/// precision (no double rounding through `f64`). Integers must fit their type; a float spelling
/// of an integral value (`3.0`, `1e3`) is accepted. Returns false for anything else.
pub(super) fn parse_value(tok: &[u8], ty: ScalarType, out: &mut [u8]) -> bool {
    let Ok(s) = std::str::from_utf8(tok) else {
        return false;
    };
    macro_rules! put {
        ($v:expr) => {{
            out.copy_from_slice(&$v.to_le_bytes());
            true
        }};
    }
    macro_rules! int {
        ($t:ty, $parse:ident) => {
            match $parse(s).and_then(|v| <$t>::try_from(v).ok()) {
                Some(v) => put!(v),
                None => false,
            }
        };
    }
    match ty {
        ScalarType::F32 => s.parse::<f32>().map(|v| put!(v)).unwrap_or(false),
        ScalarType::F64 => s.parse::<f64>().map(|v| put!(v)).unwrap_or(false),
        ScalarType::I8 => int!(i8, parse_i64),
        ScalarType::I16 => int!(i16, parse_i64),
        ScalarType::I32 => int!(i32, parse_i64),
        ScalarType::I64 => int!(i64, parse_i64),
        ScalarType::U8 => int!(u8, parse_u64),
        ScalarType::U16 => int!(u16, parse_u64),
        ScalarType::U32 => int!(u32, parse_u64),
        ScalarType::U64 => int!(u64, parse_u64),
    }
}

/// An integral float spelling (`3.0`, `1e3`) as f64, `None` otherwise.
fn integral(s: &str) -> Option<f64> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite() && v.fract() == 0.0)
}

fn parse_i64(s: &str) -> Option<i64> {
    s.parse::<i64>().ok().or_else(|| {
        integral(s)
            .filter(|v| (-9.223_372_036_854_776e18..9.223_372_036_854_776e18).contains(v))
            .map(|v| v as i64)
    })
}

fn parse_u64(s: &str) -> Option<u64> {
    s.parse::<u64>().ok().or_else(|| {
        integral(s)
            .filter(|v| (0.0..1.844_674_407_370_955_2e19).contains(v))
            .map(|v| v as u64)
    })
}

/// Appends the ascii form of the little-endian value `b` of type `ty`.
///
/// Integers print exactly. Floats print like PCL's writer (C's `%.8g`: 8 significant digits,
/// trailing zeros dropped, `1e-07` / `3e+20` outside 1e-4 ≤ |v| < 1e8) whenever that text reads
/// back as the same value in the field's precision, and otherwise as the shortest text that does
/// (so nothing is ever lost, and a file written by PCL comes back byte for byte). NaN prints as
/// `nan`, infinities as `inf` / `-inf`.
pub(super) fn push_value(out: &mut Vec<u8>, ty: ScalarType, b: &[u8]) {
    macro_rules! le {
        ($t:ty) => {
            <$t>::from_le_bytes(b.try_into().expect("slice length equals the scalar size"))
        };
    }
    // Writing into a Vec<u8> cannot fail.
    let _ = match ty {
        ScalarType::I8 => write!(out, "{}", b[0] as i8),
        ScalarType::U8 => write!(out, "{}", b[0]),
        ScalarType::I16 => write!(out, "{}", le!(i16)),
        ScalarType::U16 => write!(out, "{}", le!(u16)),
        ScalarType::I32 => write!(out, "{}", le!(i32)),
        ScalarType::U32 => write!(out, "{}", le!(u32)),
        ScalarType::I64 => write!(out, "{}", le!(i64)),
        ScalarType::U64 => write!(out, "{}", le!(u64)),
        ScalarType::F32 => {
            let v = le!(f32);
            let exact = |t: &str| t.parse::<f32>().is_ok_and(|w| w.to_bits() == v.to_bits());
            push_float(out, f64::from(v), exact, &format!("{v:e}"), &format!("{v}"))
        }
        ScalarType::F64 => {
            let v = le!(f64);
            let exact = |t: &str| t.parse::<f64>().is_ok_and(|w| w.to_bits() == v.to_bits());
            push_float(out, v, exact, &format!("{v:e}"), &format!("{v}"))
        }
    };
}

/// Writes `v` as `%.8g` when `exact` accepts that text, else from Rust's shortest round-trip text
/// in the field's precision: `shortest` in exponent form (`1.00787915e-2`), `positional` without
/// (`0.0100787915`).
fn push_float(
    out: &mut Vec<u8>,
    v: f64,
    exact: impl Fn(&str) -> bool,
    shortest: &str,
    positional: &str,
) -> std::io::Result<()> {
    if v.is_nan() {
        out.extend_from_slice(b"nan");
        return Ok(());
    }
    if v.is_infinite() {
        out.extend_from_slice(if v < 0.0 { b"-inf" } else { b"inf" });
        return Ok(());
    }
    let g = format_g(v, 8);
    if exact(&g) {
        out.extend_from_slice(g.as_bytes());
        return Ok(());
    }
    // More digits are needed: the shortest exact digits, laid out the `%g` way.
    let (mant, exp) = shortest.split_once('e').unwrap_or((shortest, "0"));
    let x: i32 = exp.parse().unwrap_or(0);
    let digits = mant.trim_start_matches('-').replace('.', "").len() as i32;
    if (-4..digits.max(8)).contains(&x) {
        write!(out, "{positional}")
    } else {
        write!(out, "{}", c_exponent(mant, x))
    }
}

/// C's `%.{p}g` of a finite `v`.
fn format_g(v: f64, p: usize) -> String {
    let e = format!("{:.*e}", p - 1, v);
    let (mant, exp) = e.split_once('e').unwrap_or((&e, "0"));
    let x: i32 = exp.parse().unwrap_or(0);
    if x >= -4 && x < p as i32 {
        let decimals = (p as i32 - 1 - x) as usize;
        strip_zeros(&format!("{v:.decimals$}")).to_string()
    } else {
        c_exponent(strip_zeros(mant), x)
    }
}

/// `m` without trailing fractional zeros (and without a trailing point).
fn strip_zeros(m: &str) -> &str {
    if m.contains('.') {
        m.trim_end_matches('0').trim_end_matches('.')
    } else {
        m
    }
}

/// `m` followed by C's exponent: sign and at least two digits (`e+20`, `e-07`).
fn c_exponent(m: &str, x: i32) -> String {
    format!(
        "{m}e{}{:02}",
        if x < 0 { '-' } else { '+' },
        x.unsigned_abs()
    )
}

// ---------------------------------------------------------------------------------------------
// Column-major layout of binary_compressed data.

/// Where one PCD field lives in a record and in the column-major block.
#[derive(Debug, Clone, Copy)]
struct Column {
    /// Byte offset in the (row) record.
    offset: usize,
    /// Bytes per point (`SIZE × COUNT`).
    width: usize,
    /// Byte offset of the column in the block.
    start: usize,
}

/// The column-major layout of `binary_compressed` data for a given point count.
///
/// ```text
///  record (row):   [ x | y | z | _ pad | rgba ]         fields in FIELDS order
///  block (column): [ x0 x1 … xn-1 | y0 … | z0 … | rgba0 … ]   padding `_` fields not stored
/// ```
#[derive(Debug, Clone)]
pub(super) struct Columns {
    cols: Vec<Column>,
    block_len: usize,
}

impl Columns {
    /// The layout of `points` records of `fields`; `None` when the block size overflows `usize`.
    pub(super) fn new(fields: &[PcdField], points: u64) -> Option<Columns> {
        let points = usize::try_from(points).ok()?;
        let mut cols = Vec::with_capacity(fields.len());
        let (mut offset, mut start) = (0usize, 0usize);
        for f in fields {
            let width = f.byte_len();
            if !f.is_padding() {
                cols.push(Column {
                    offset,
                    width,
                    start,
                });
                start = start.checked_add(width.checked_mul(points)?)?;
            }
            offset += width;
        }
        Some(Columns {
            cols,
            block_len: start,
        })
    }

    /// Bytes of the uncompressed block.
    pub(super) fn block_len(&self) -> usize {
        self.block_len
    }

    /// Copies points `first .. first + n` from `block` into `n` zeroed records of `rl` bytes.
    pub(super) fn gather(&self, block: &[u8], first: usize, rl: usize, records: &mut [u8]) {
        for c in &self.cols {
            let src = &block[c.start + first * c.width..];
            for (rec, val) in records.chunks_exact_mut(rl).zip(src.chunks_exact(c.width)) {
                rec[c.offset..c.offset + c.width].copy_from_slice(val);
            }
        }
    }

    /// Copies the records `rows` (`rl` bytes each) into `block` as points `first …`.
    pub(super) fn scatter(&self, rows: &[u8], first: usize, rl: usize, block: &mut [u8]) {
        for c in &self.cols {
            let dst = &mut block[c.start + first * c.width..];
            for (val, rec) in dst.chunks_exact_mut(c.width).zip(rows.chunks_exact(rl)) {
                val.copy_from_slice(&rec[c.offset..c.offset + c.width]);
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// LZF.

/// Longest output of one LZF back reference (3 bytes → 264 bytes): no valid block expands more.
const LZF_MAX_RATIO: u64 = 88;

/// True when `compressed` bytes of LZF can possibly decode to `uncompressed` bytes. Checked
/// before allocating the output, so that a corrupt size field cannot request gigabytes.
pub(super) fn plausible_sizes(compressed: u64, uncompressed: u64) -> bool {
    (compressed == 0) == (uncompressed == 0)
        && uncompressed <= compressed.saturating_mul(LZF_MAX_RATIO)
}

/// Decompresses a whole LZF block that must decode to exactly `expected` bytes.
pub(super) fn decompress(data: &[u8], expected: usize) -> Result<Vec<u8>, String> {
    if data.is_empty() && expected == 0 {
        return Ok(Vec::new());
    }
    let out = lzf::decompress(data, expected).map_err(|e| e.to_string())?;
    if out.len() != expected {
        return Err(format!(
            "it decodes to {} bytes instead of {expected}",
            out.len()
        ));
    }
    Ok(out)
}

/// Compresses `data` into one LZF block (deterministic). Data LZF cannot shrink (the `lzf` crate
/// then refuses) is stored as literal runs, which every LZF decoder reads, as PCL itself allows
/// the block to be larger than its input.
pub(super) fn compress(data: &[u8]) -> Vec<u8> {
    if data.is_empty() {
        return Vec::new();
    }
    lzf::compress(data).unwrap_or_else(|_| literal_runs(data))
}

/// `data` as LZF literal runs: a control byte `len - 1` (< 32) before every 32 bytes.
fn literal_runs(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(data.len() + data.len().div_ceil(32));
    for run in data.chunks(32) {
        out.push((run.len() - 1) as u8);
        out.extend_from_slice(run);
    }
    out
}

#[cfg(test)]
mod io_pcd {
    use super::*;

    fn value(tok: &str, ty: ScalarType) -> Option<Vec<u8>> {
        let mut b = vec![0; ty.size()];
        parse_value(tok.as_bytes(), ty, &mut b).then_some(b)
    }

    fn text(ty: ScalarType, b: &[u8]) -> String {
        let mut out = Vec::new();
        push_value(&mut out, ty, b);
        String::from_utf8(out).unwrap()
    }

    #[test]
    fn ascii_values_roundtrip_exactly() {
        let cases = [
            ("-10.015625", ScalarType::F32),
            ("0.042999268", ScalarType::F32),
            ("nan", ScalarType::F32),
            ("-inf", ScalarType::F64),
            ("1e-07", ScalarType::F32),
            ("4.2108e+20", ScalarType::F64),
            ("1.0995116e+12", ScalarType::F32),
            ("4808000", ScalarType::F32),
            ("0.1", ScalarType::F64),
            ("0.30000000000000004", ScalarType::F64),
            ("-0.21999741", ScalarType::F32),
            ("0.0100787915", ScalarType::F32),
            ("123456789", ScalarType::F64),
            ("1.2345678912e+20", ScalarType::F64),
            ("-0", ScalarType::F32),
            ("1e+100", ScalarType::F64),
            ("9.9999997e-05", ScalarType::F32),
            ("0.0001", ScalarType::F64),
            ("255", ScalarType::U8),
            ("-128", ScalarType::I8),
            ("18446744073709551615", ScalarType::U64),
            ("-9223372036854775808", ScalarType::I64),
            ("4294967295", ScalarType::U32),
        ];
        for (tok, ty) in cases {
            let b = value(tok, ty).unwrap_or_else(|| panic!("{tok}"));
            assert_eq!(text(ty, &b), tok, "{ty:?}");
        }
        assert_eq!(
            value("NaN", ScalarType::F32)
                .map(|b| text(ScalarType::F32, &b))
                .unwrap(),
            "nan"
        );
        assert_eq!(
            value("3.0", ScalarType::I16),
            Some(3i16.to_le_bytes().to_vec())
        );
        assert_eq!(
            value("-0.5", ScalarType::F32),
            Some((-0.5f32).to_le_bytes().to_vec())
        );
        for (tok, ty) in [
            ("256", ScalarType::U8),
            ("-1", ScalarType::U16),
            ("1.5", ScalarType::I32),
            ("abc", ScalarType::F32),
            ("nan", ScalarType::U8),
            ("", ScalarType::F64),
        ] {
            assert!(value(tok, ty).is_none(), "{tok} as {ty:?}");
        }
    }

    #[test]
    fn columns_transpose_and_skip_padding() {
        let fields = [
            PcdField::new("x", ScalarType::U8, 1),
            PcdField::new("_", ScalarType::U8, 2),
            PcdField::new("n", ScalarType::U8, 2),
        ];
        let c = Columns::new(&fields, 3).unwrap();
        assert_eq!(c.block_len(), 9);
        let rows = [1, 0, 0, 10, 11, 2, 0, 0, 20, 21, 3, 0, 0, 30, 31];
        let mut block = vec![0; 9];
        c.scatter(&rows[5..], 1, 5, &mut block);
        c.scatter(&rows[..5], 0, 5, &mut block);
        assert_eq!(block, [1, 2, 3, 10, 11, 20, 21, 30, 31]);
        let mut back = vec![0; 10];
        c.gather(&block, 1, 5, &mut back);
        assert_eq!(back, rows[5..]);
    }

    #[test]
    fn lzf_roundtrip_including_incompressible_data() {
        let smooth: Vec<u8> = (0..4000u32).flat_map(|i| (i / 7).to_le_bytes()).collect();
        let c = compress(&smooth);
        assert!(c.len() < smooth.len());
        assert_eq!(decompress(&c, smooth.len()).unwrap(), smooth);
        let mut x = 0x1234_5678u32;
        let noisy: Vec<u8> = (0..1000)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                x as u8
            })
            .collect();
        for data in [&noisy[..], &noisy[..1], &noisy[..33]] {
            let c = compress(data);
            assert_eq!(decompress(&c, data.len()).unwrap(), data);
        }
        assert!(decompress(&[0xff, 0x00], 10).is_err());
        assert!(decompress(&c, smooth.len() + 1).is_err());
        assert!(plausible_sizes(10, 880) && !plausible_sizes(10, 881) && !plausible_sizes(0, 1));
    }
}
