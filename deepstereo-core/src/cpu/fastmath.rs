//! Branch-free f32 `exp`, `tanh` and `ln`, written so that a loop over a slice vectorises
//! (no libm call per element); the blend's bounded exponential (`fused/fastmath.rs`) is
//! built on them, the per-view cue's logarithms (`sweep/cue.rs`) on `ln`. Rendering only: training and the candle composition keep libm's `tanh` and
//! `exp`; the tests bound the difference.
//!
//! `exp` is Cephes' `expf` (range reduction by `ln 2` split in two parts, a degree-5
//! polynomial on `[-ln 2 / 2, ln 2 / 2]`, the power of two built from the exponent
//! bits): within 2 ulp of libm over the range it is used on.

/// Inputs are clamped to this range: `2^n` stays a normal f32 for the rounded `n`.
const EXP_MIN: f32 = -87.0;
const EXP_MAX: f32 = 88.0;
/// `1.5 * 2^23`: adding it rounds an f32 of magnitude below `2^22` to an integer, whose
/// value is then the difference of the two bit patterns.
const ROUND_MAGIC: f32 = 12_582_912.0;
const LOG2E: f32 = std::f32::consts::LOG2_E;
/// `ln 2` as a part exact in f32 products with small integers, and the rest.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Cephes `expf` coefficients of `(exp(r) - 1 - r) / r^2`, highest degree first.
const EXP_POLY: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];
/// `tanh` is 1 in f32 from here on.
const TANH_SATURATE: f32 = 9.0;
/// Below this `|x|`, `tanh` takes its Taylor series (where `(1 - e) / (1 + e)` cancels).
const TANH_SERIES: f32 = 0.3;
/// Taylor coefficients of `tanh(x) / x` in `x^2`, from degree 2 up: -1/3, 2/15, -17/315,
/// 62/2835.
const TANH_TAYLOR: [f32; 4] = [-1.0 / 3.0, 2.0 / 15.0, -17.0 / 315.0, 62.0 / 2835.0];

/// `e^x` (NaN stays NaN; beyond the clamp range, the range's ends).
#[inline(always)]
pub(crate) fn exp_f32(x: f32) -> f32 {
    let x = x.clamp(EXP_MIN, EXP_MAX);
    let k = x * LOG2E + ROUND_MAGIC;
    let n = k - ROUND_MAGIC;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = EXP_POLY[1..]
        .iter()
        .fold(EXP_POLY[0], |acc, &c| acc * r + c);
    let e = p * r * r + r + 1.0;
    // The integer n, biased, in the exponent field: 2^n.
    let bits = (k.to_bits() as i32 - ROUND_MAGIC.to_bits() as i32 + 127) << 23;
    e * f32::from_bits(bits as u32)
}

/// `tanh(x)` from [`exp_f32`] (its Taylor series near 0).
#[inline(always)]
pub(crate) fn tanh_f32(x: f32) -> f32 {
    let a = x.abs().min(TANH_SATURATE);
    let q = exp_f32(-2.0 * a);
    let far = (1.0 - q) / (1.0 + q);
    let a2 = a * a;
    let poly = TANH_TAYLOR[..3]
        .iter()
        .rev()
        .fold(TANH_TAYLOR[3], |acc, &c| acc * a2 + c);
    let series = a * (1.0 + a2 * poly);
    let t = if a < TANH_SERIES { series } else { far };
    t.copysign(x)
}

/// `sqrt(2)`: mantissas above it are halved (and the exponent raised) so that the series
/// variable stays within `+-0.172`.
const SQRT2: f32 = std::f32::consts::SQRT_2;
/// Coefficients of `ln(m) = 2 f (1 + f^2 / 3 + f^4 / 5 + ...)`, `f = (m - 1) / (m + 1)`,
/// highest degree first (the next term is below 3e-10).
const LN_SERIES: [f32; 5] = [1.0 / 9.0, 1.0 / 7.0, 1.0 / 5.0, 1.0 / 3.0, 1.0];

/// `ln(x)` for `x` clamped to the positive normal range `[f32::MIN_POSITIVE, f32::MAX]` (so
/// 0 gives `ln(MIN_POSITIVE) ~ -87.3` and infinity `ln(MAX) ~ 88.7`; NaN stays NaN): the
/// exponent from the bits, and the series of `atanh` on the mantissa.
#[inline(always)]
pub(crate) fn ln_f32(x: f32) -> f32 {
    let nan = x.is_nan();
    let x = x.clamp(f32::MIN_POSITIVE, f32::MAX);
    let bits = x.to_bits();
    let e = ((bits >> 23) & 0xff) as i32 - 127;
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000); // [1, 2)
    let high = m > SQRT2;
    let (m, e) = if high { (m * 0.5, e + 1) } else { (m, e) };
    let f = (m - 1.0) / (m + 1.0);
    let f2 = f * f;
    let p = LN_SERIES[1..]
        .iter()
        .fold(LN_SERIES[0], |acc, &c| acc * f2 + c);
    let r = e as f32 * std::f32::consts::LN_2 + 2.0 * f * p;
    if nan {
        f32::NAN
    } else {
        r
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// The relative error of `a` against `b`.
    pub(crate) fn rel(a: f32, b: f64) -> f64 {
        ((a as f64 - b) / b).abs()
    }

    #[test]
    fn exp_is_within_two_ulp_of_the_exact_value() {
        let mut worst = 0f64;
        for i in -200_000..=200_000 {
            let x = i as f32 * 4.35e-4; // [-87, 87]
            worst = worst.max(rel(exp_f32(x), (x as f64).exp()));
        }
        assert!(worst < 2.5e-7, "worst relative error {worst:e}");
        assert_eq!(exp_f32(0.0), 1.0);
        assert!(exp_f32(f32::NAN).is_nan());
        assert!(exp_f32(-1e30) > 0.0 && exp_f32(1e30).is_finite());
    }

    #[test]
    fn ln_is_close_to_the_exact_value_from_the_smallest_to_the_largest_float() {
        let mut worst = 0f64;
        for i in 0..400_000 {
            // 1e-37 .. 3e38, logarithmically, and every mantissa near sqrt(2) and 1.
            let x = 10f32.powf(-37.0 + 75.4 * i as f32 / 400_000.0);
            let want = (x as f64).ln();
            let err = (ln_f32(x) as f64 - want).abs() / want.abs().max(1.0);
            worst = worst.max(err);
        }
        for i in 0..100_000 {
            let x = 0.5 + 1.5 * i as f32 / 100_000.0;
            let want = (x as f64).ln();
            worst = worst.max((ln_f32(x) as f64 - want).abs() / want.abs().max(1.0));
        }
        assert!(worst < 3e-7, "worst error {worst:e}");
        assert_eq!(ln_f32(1.0), 0.0);
        assert!((ln_f32(0.0) - f32::MIN_POSITIVE.ln()).abs() < 1e-4);
        assert!((ln_f32(f32::INFINITY) - f32::MAX.ln()).abs() < 1e-4);
        assert!(ln_f32(f32::NAN).is_nan());
    }

    #[test]
    fn tanh_is_close_to_the_exact_value_everywhere() {
        let mut worst = 0f64;
        for i in -100_000..=100_000 {
            let x = i as f32 * 1.2e-4; // [-12, 12], through the series' edge
            let want = (x as f64).tanh();
            let err = (tanh_f32(x) as f64 - want).abs() / want.abs().max(1e-30);
            worst = worst.max(if x == 0.0 { 0.0 } else { err });
        }
        assert!(worst < 4e-7, "worst relative error {worst:e}");
        assert_eq!(tanh_f32(0.0), 0.0);
        assert_eq!(tanh_f32(f32::INFINITY), 1.0);
        assert_eq!(tanh_f32(f32::NEG_INFINITY), -1.0);
    }
}
