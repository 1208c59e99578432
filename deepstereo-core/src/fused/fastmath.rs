//! The blend's bounded exponential on [`crate::cpu::fastmath`]'s vectorisable `exp` and
//! `tanh`. Rendering only: training and the candle composition keep libm's `tanh` and
//! `exp`; the tests bound the difference.

use crate::config::BLEND_LOGIT_BOUND;
use crate::cpu::fastmath::{exp_f32, tanh_f32};

/// `y[i] <- exp(B tanh(y[i] / B))`, the blend's bounded weight ([`super::blend`]'s
/// `bounded_exp`), over a slice.
#[inline(always)]
pub(crate) fn bounded_exp_slice(y: &mut [f32]) {
    let b = BLEND_LOGIT_BOUND as f32;
    for v in y.iter_mut() {
        *v = exp_f32(b * tanh_f32(*v / b));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cpu::fastmath::tests::rel;

    #[test]
    fn the_bounded_weight_matches_libm_and_stays_finite() {
        let b = BLEND_LOGIT_BOUND;
        let xs: Vec<f32> = (-4000..=4000)
            .map(|i| i as f32 * 0.025)
            .chain([
                1e6,
                -1e6,
                f32::MAX,
                f32::MIN,
                f32::INFINITY,
                f32::NEG_INFINITY,
            ])
            .collect();
        let mut ys = xs.clone();
        bounded_exp_slice(&mut ys);
        for (&x, &y) in xs.iter().zip(&ys) {
            let want = (b * (x as f64 / b).tanh()).exp();
            // The logit near +-20 carries f32's rounding of 20 (half an ulp: 1e-6 of the
            // weight) whichever way it is computed; libm's f32 path is as far off.
            let libm = ((b as f32) * (x / b as f32).tanh()).exp();
            assert!(y.is_finite() && rel(y, want) < 4e-6, "{x}: {y} vs {want}");
            assert!(rel(y, libm as f64) < 4e-6, "{x}: {y} vs libm {libm}");
        }
    }
}
