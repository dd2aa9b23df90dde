//! `exp` in plain IEEE arithmetic, for the Gaussian weights of the operators.
//!
//! The weights of the normal filters, the bilateral operator and the guarded operator's
//! agreement are `exp` of a non-positive argument, evaluated some ten times per list entry. The
//! C library's `exp` is a call the compiler cannot inline, and its last bit differs between
//! libraries (glibc, musl, the macOS libm): a tile run on another machine or in another
//! container image would then write other bytes. [`exp`] uses only additions and
//! multiplications (no fused multiply-add, no table, no libm call), so it inlines, gives the
//! same bits on every platform and is within a few ulp of the exact value (the tests compare it
//! with the library's over the whole range).
//!
//! Method (Tang's): `x = (64m + j)·ln 2 / 64 + r` with `64m + j` the nearest integer to
//! `64x / ln 2`, `0 ≤ j < 64` and `|r| ≤ ln 2 / 128` (Cody and Waite's two-part `ln 2`, exact
//! for every multiple in range); `eˣ = 2ᵐ · 2^(j/64) · eʳ` with `2^(j/64)` from a table
//! (each entry the double nearest the exact value, computed offline at 60 digits) and `eʳ − 1`
//! by its Taylor series to degree 5 (the first omitted term is below 4·10⁻¹⁷ relative).

/// `ln 2 / 64`'s leading bits (fdlibm's `ln2_hi`, 6.93147180369123816490e−1, over 64):
/// `k · LN2_HI_64` is exact for `|k| < 2²⁰`.
const LN2_HI_64: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000) / 64.0;
/// `ln 2 / 64 − LN2_HI_64` (fdlibm's `ln2_lo`, 1.90821492927058770002e−10, over 64).
const LN2_LO_64: f64 = f64::from_bits(0x3dea_39ef_3579_3c76) / 64.0;
/// `64 / ln 2`.
const INV_LN2_64: f64 = 64.0 * std::f64::consts::LOG2_E;
/// Adding then subtracting `1.5 · 2⁵²` rounds a value below `2⁵¹` in magnitude to the nearest
/// integer (ties to even) without a libm call.
const ROUND: f64 = 6_755_399_441_055_744.0;
/// Above this, `eˣ` overflows.
const OVER: f64 = 709.782_712_893_384;
/// Below this, `eˣ` rounds to zero.
const UNDER: f64 = -745.133_219_101_941_1;

/// `2^(j/64)`, `j = 0 .. 64`.
#[rustfmt::skip]
const TABLE: [f64; 64] = [
    1.0, 1.0108892860517005, 1.0218971486541166, 1.0330248790212284,
    1.0442737824274138, 1.0556451783605572, 1.0671404006768237, 1.0787607977571199,
    1.0905077326652577, 1.102382583307841, 1.1143867425958924, 1.1265216186082418,
    1.1387886347566916, 1.1511892299529827, 1.1637248587775775, 1.1763969916502812,
    1.189207115002721, 1.202156731452703, 1.215247359980469, 1.22848053610687,
    1.241857812073484, 1.255380757024691, 1.2690509571917332, 1.2828700160787783,
    1.2968395546510096, 1.3109612115247644, 1.3252366431597413, 1.339667524053303,
    1.3542555469368927, 1.3690024229745905, 1.383909881963832, 1.3989796725383112,
    std::f64::consts::SQRT_2, 1.42961333839197, 1.4451808069770467, 1.460917794180647,
    1.4768261459394993, 1.4929077282912648, 1.5091644275934228, 1.5255981507445384,
    1.5422108254079407, 1.559004400237837, 1.5759808451078865, 1.593142151342267,
    1.6104903319492543, 1.6280274218573478, 1.645755478153965, 1.6636765803267364,
    1.681792830507429, 1.7001063537185235, 1.718619298122478, 1.7373338352737062,
    1.7562521603732995, 1.7753764925265212, 1.7947090750031072, 1.8142521755003989,
    1.8340080864093424, 1.8539791250833855, 1.8741676341103, 1.8945759815869656,
    1.9152065613971474, 1.9360617934922943, 1.9571441241754002, 1.978456026387951,
];

/// `2ᵏ` for `−1022 ≤ k ≤ 1023`.
#[inline]
fn pow2(k: i64) -> f64 {
    f64::from_bits(((k + 1023) as u64) << 52)
}

/// `eˣ`, within a few ulp, the same bits on every platform. NaN gives NaN.
///
/// One test keeps the common case (a finite argument, a normal result) on the straight path:
/// the integer part of `64x / ln 2` is read from the bits of the rounded sum (exact: its
/// magnitude is below 2¹⁷) instead of a saturating float-to-integer conversion. This gives the
/// bits of the first version with early returns (kept in the tests) at about 20 % less time per
/// call (3.7 against 4.7 ns in a loop of lists of 16; docs/BENCHMARKS.md).
#[inline]
pub fn exp(x: f64) -> f64 {
    if !(UNDER..=OVER).contains(&x) {
        return if x.is_nan() {
            x
        } else if x > 0.0 {
            f64::INFINITY
        } else {
            0.0
        };
    }
    let sum = x * INV_LN2_64 + ROUND;
    let kf = sum - ROUND;
    let k = (sum.to_bits() as i64) - (ROUND.to_bits() as i64);
    let r = (x - kf * LN2_HI_64) - kf * LN2_LO_64;
    let r2 = r * r;
    let em1 = r + r2 * (0.5 + r * (1.0 / 6.0)) + (r2 * r2) * (1.0 / 24.0 + r * (1.0 / 120.0));
    let t = TABLE[(k & 63) as usize];
    let p = t + t * em1;
    let m = k >> 6;
    if (-1021..=1023).contains(&m) {
        p * pow2(m)
    } else if m < -1021 {
        // Subnormal results: scale in two steps, exact until the last rounding.
        p * pow2(m + 1000) * pow2(-1000)
    } else {
        p * pow2(m - 1) * 2.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in ulp between two positive finite values.
    fn ulps(a: f64, b: f64) -> u64 {
        a.to_bits().abs_diff(b.to_bits())
    }

    #[test]
    fn within_two_ulp_of_the_library_exp_over_the_range() {
        let mut worst = 0;
        let n = 200_000;
        for i in 0..=n {
            let x = UNDER + (OVER - UNDER) * i as f64 / n as f64;
            let (a, b) = (exp(x), x.exp());
            if b == 0.0 || b.is_infinite() || b < f64::MIN_POSITIVE {
                // Subnormal results carry fewer digits: compare absolutely.
                assert!(
                    (a - b).abs() <= 4.0 * f64::from_bits(1),
                    "{x}: {a} against {b}"
                );
                continue;
            }
            worst = worst.max(ulps(a, b));
        }
        assert!(worst <= 2, "worst {worst} ulp");
        // The weights' own range, finely: Gaussian arguments in [−50, 0].
        for i in 0..=100_000 {
            let x = -50.0 * i as f64 / 100_000.0;
            assert!(ulps(exp(x), x.exp()) <= 2, "{x}");
        }
    }

    /// The first version (early returns, a saturating float-to-integer conversion): [`exp`]
    /// must give its bits, so no output of the operators changed with the faster one.
    fn branchy(x: f64) -> f64 {
        if x.is_nan() {
            return x;
        }
        if x > OVER {
            return f64::INFINITY;
        }
        if x < UNDER {
            return 0.0;
        }
        let kf = (x * INV_LN2_64 + ROUND) - ROUND;
        let r = (x - kf * LN2_HI_64) - kf * LN2_LO_64;
        let r2 = r * r;
        let em1 = r + r2 * (0.5 + r * (1.0 / 6.0)) + (r2 * r2) * (1.0 / 24.0 + r * (1.0 / 120.0));
        let k = kf as i64;
        let t = TABLE[(k & 63) as usize];
        let p = t + t * em1;
        let m = k >> 6;
        if m < -1021 {
            p * pow2(m + 1000) * pow2(-1000)
        } else if m > 1023 {
            p * pow2(m - 1) * 2.0
        } else {
            p * pow2(m)
        }
    }

    #[test]
    fn the_bits_of_the_first_version() {
        let mut xs: Vec<f64> = (0..=400_000)
            .map(|i| UNDER - 5.0 + (OVER - UNDER + 10.0) * i as f64 / 400_000.0)
            .collect();
        // The weights' own range, finely, and the edges of every branch.
        xs.extend((0..=100_000).map(|i| -50.0 * i as f64 / 100_000.0));
        xs.extend([
            0.0,
            -0.0,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            OVER,
            UNDER,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            1e-300,
            -708.39,
            -708.4,
            -745.0,
            709.7,
        ]);
        for x in xs {
            let (a, b) = (exp(x), branchy(x));
            assert!(
                a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                "{x}: {a} against the first version's {b}"
            );
        }
    }

    #[test]
    fn exact_and_special_values() {
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(-0.0), 1.0);
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
        assert_eq!(exp(f64::INFINITY), f64::INFINITY);
        assert!(exp(f64::NAN).is_nan());
        assert_eq!(exp(-800.0), 0.0);
        assert_eq!(exp(710.0), f64::INFINITY);
        assert!(exp(-744.0) > 0.0 && exp(-744.0) < f64::MIN_POSITIVE);
        assert!(exp(709.0).is_finite());
    }
}
