//! Exact, order-independent summation of f64 values.
//!
//! Global scalars (mean edge length, mean spacing, outlier thresholds) must come out as the same
//! bits whether the cloud is processed whole, in threads or in tiles. Floating-point addition is not
//! associative, so the terms are accumulated exactly in a fixed-point integer wide enough for every
//! finite f64 (2^-1074 … 2^1024 plus 64 bits of headroom), and rounded once at the end.

/// Number of 64-bit limbs: 2098 significant bits plus carry headroom.
const LIMBS: usize = 35;

/// An exact accumulator of f64 values; partial sums merge with [`ExactSum::merge`].
#[derive(Clone, PartialEq, Eq)]
pub struct ExactSum {
    pos: [u64; LIMBS],
    neg: [u64; LIMBS],
    count: u64,
    non_finite: u64,
}

impl Default for ExactSum {
    fn default() -> Self {
        ExactSum::new()
    }
}

impl std::fmt::Debug for ExactSum {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ExactSum")
            .field("value", &self.value())
            .field("count", &self.count)
            .finish()
    }
}

fn add_shifted(acc: &mut [u64; LIMBS], m: u64, shift: usize) {
    let limb = shift / 64;
    let bit = shift % 64;
    let wide = (m as u128) << bit;
    let mut carry = 0u128;
    let parts = [wide as u64, (wide >> 64) as u64];
    let mut i = limb;
    for p in parts {
        let s = acc[i] as u128 + p as u128 + carry;
        acc[i] = s as u64;
        carry = s >> 64;
        i += 1;
    }
    while carry != 0 && i < LIMBS {
        let s = acc[i] as u128 + carry;
        acc[i] = s as u64;
        carry = s >> 64;
        i += 1;
    }
}

/// `a − b` for `a ≥ b`.
fn sub(a: &[u64; LIMBS], b: &[u64; LIMBS]) -> [u64; LIMBS] {
    let mut out = [0u64; LIMBS];
    let mut borrow = 0u64;
    for i in 0..LIMBS {
        let (d1, o1) = a[i].overflowing_sub(b[i]);
        let (d2, o2) = d1.overflowing_sub(borrow);
        out[i] = d2;
        borrow = (o1 || o2) as u64;
    }
    out
}

fn greater_eq(a: &[u64; LIMBS], b: &[u64; LIMBS]) -> bool {
    for i in (0..LIMBS).rev() {
        if a[i] != b[i] {
            return a[i] > b[i];
        }
    }
    true
}

/// Rounds the big integer `mag · 2^-1074` to f64.
fn to_f64(mag: &[u64; LIMBS]) -> f64 {
    let Some(top) = (0..LIMBS).rev().find(|&i| mag[i] != 0) else {
        return 0.0;
    };
    // Take the two limbs at and below the top one as a u128, with a sticky bit for the rest, so
    // u128 → f64 rounds as the exact value would.
    let hi = mag[top] as u128;
    let lo = if top > 0 { mag[top - 1] as u128 } else { 0 };
    let mut v = (hi << 64) | lo;
    let sticky = top >= 2 && mag[..top - 1].iter().any(|&x| x != 0);
    if sticky {
        v |= 1;
    }
    let base_bit = (top as i32 - 1) * 64 - 1074;
    let f = v as f64;
    // Scale by 2^base_bit in two steps to stay within the exponent range.
    let half = base_bit / 2;
    f * 2f64.powi(half) * 2f64.powi(base_bit - half)
}

impl ExactSum {
    /// An empty sum.
    pub fn new() -> ExactSum {
        ExactSum {
            pos: [0; LIMBS],
            neg: [0; LIMBS],
            count: 0,
            non_finite: 0,
        }
    }

    /// Adds `x`; non-finite values are counted and skipped.
    pub fn add(&mut self, x: f64) {
        if !x.is_finite() {
            self.non_finite += 1;
            return;
        }
        self.count += 1;
        if x == 0.0 {
            return;
        }
        let bits = x.to_bits();
        let exp = ((bits >> 52) & 0x7ff) as usize;
        let frac = bits & ((1u64 << 52) - 1);
        let (m, shift) = if exp == 0 {
            (frac, 0)
        } else {
            (frac | (1u64 << 52), exp - 1)
        };
        if bits >> 63 == 1 {
            add_shifted(&mut self.neg, m, shift);
        } else {
            add_shifted(&mut self.pos, m, shift);
        }
    }

    /// Adds every term of another partial sum.
    pub fn merge(&mut self, o: &ExactSum) {
        for (acc, other) in [(&mut self.pos, &o.pos), (&mut self.neg, &o.neg)] {
            let mut carry = 0u128;
            for i in 0..LIMBS {
                let s = acc[i] as u128 + other[i] as u128 + carry;
                acc[i] = s as u64;
                carry = s >> 64;
            }
        }
        self.count += o.count;
        self.non_finite += o.non_finite;
    }

    /// Number of finite terms added.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Number of non-finite terms skipped.
    pub fn non_finite(&self) -> u64 {
        self.non_finite
    }

    /// The sum, correctly rounded to f64 (up to double rounding in the last place).
    pub fn value(&self) -> f64 {
        if greater_eq(&self.pos, &self.neg) {
            to_f64(&sub(&self.pos, &self.neg))
        } else {
            -to_f64(&sub(&self.neg, &self.pos))
        }
    }

    /// The mean of the finite terms, 0 when there are none.
    pub fn mean(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.value() / self.count as f64
        }
    }
}

/// The serialised form: the limbs as lists (serde has no impls for arrays this long).
#[derive(serde::Serialize, serde::Deserialize)]
struct ExactSumRepr {
    pos: Vec<u64>,
    neg: Vec<u64>,
    count: u64,
    non_finite: u64,
}

impl serde::Serialize for ExactSum {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        ExactSumRepr {
            pos: self.pos.to_vec(),
            neg: self.neg.to_vec(),
            count: self.count,
            non_finite: self.non_finite,
        }
        .serialize(s)
    }
}

impl<'de> serde::Deserialize<'de> for ExactSum {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let r = ExactSumRepr::deserialize(d)?;
        let limbs = |v: Vec<u64>| -> Result<[u64; LIMBS], D::Error> {
            v.try_into()
                .map_err(|_| serde::de::Error::custom(format!("expected {LIMBS} limbs")))
        };
        Ok(ExactSum {
            pos: limbs(r.pos)?,
            neg: limbs(r.neg)?,
            count: r.count,
            non_finite: r.non_finite,
        })
    }
}

impl FromIterator<f64> for ExactSum {
    fn from_iter<I: IntoIterator<Item = f64>>(iter: I) -> Self {
        let mut s = ExactSum::new();
        for x in iter {
            s.add(x);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn cancellation_is_exact() {
        let s: ExactSum = [1e100, 1.0, -1e100, 1e-300, -1e-300, 0.5]
            .into_iter()
            .collect();
        assert_eq!(s.value(), 1.5);
        let s: ExactSum = [0.1, 0.2, 0.3].into_iter().collect();
        // The exact sum of the three doubles rounds to the double nearest 0.6.
        assert_eq!(s.value(), 0.6);
        let s: ExactSum = [f64::MIN_POSITIVE / 4.0, f64::MIN_POSITIVE / 4.0]
            .into_iter()
            .collect();
        assert_eq!(s.value(), f64::MIN_POSITIVE / 2.0);
        let s: ExactSum = [-3.0, 1.0, f64::NAN].into_iter().collect();
        assert_eq!((s.value(), s.count(), s.non_finite()), (-2.0, 2, 1));
        assert_eq!(ExactSum::new().mean(), 0.0);
    }

    #[test]
    fn serde_round_trip_keeps_every_bit() {
        let s: ExactSum = [1e300, -3.5, 1e-300, f64::NAN].into_iter().collect();
        let back: ExactSum = serde_json::from_str(&serde_json::to_string(&s).unwrap()).unwrap();
        assert!(back == s);
    }

    proptest! {
        /// Any order and any grouping give the same bits.
        #[test]
        fn order_and_grouping_independent(
            xs in proptest::collection::vec(-1e12f64..1e12, 0..200),
            split in 0usize..200,
        ) {
            let whole: ExactSum = xs.iter().copied().collect();
            let mut rev: ExactSum = xs.iter().rev().copied().collect();
            let k = split.min(xs.len());
            let mut a: ExactSum = xs[..k].iter().copied().collect();
            let b: ExactSum = xs[k..].iter().copied().collect();
            a.merge(&b);
            prop_assert_eq!(whole.value().to_bits(), a.value().to_bits());
            rev.merge(&ExactSum::new());
            prop_assert_eq!(whole.value().to_bits(), rev.value().to_bits());
            // And it is as accurate as a long double would be.
            let naive: f64 = xs.iter().sum();
            let scale: f64 = xs.iter().map(|x| x.abs()).sum::<f64>().max(1.0);
            prop_assert!((whole.value() - naive).abs() <= 1e-12 * scale);
        }
    }
}
