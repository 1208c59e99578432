//! The input and output transforms (AVX2 and FMA), eight tiles or eight channels per
//! vector.

use super::algos::Algo;
use super::{Layout, A, LANES, POS, UNIT_TILES};
use crate::conv::direct_cv::CV;
use crate::conv::im2col::Geom;
#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// `[e(0), .., e(5)]` (or `e(0)..e(3)`), expanded in place: constant indices let the
/// transforms compile to straight-line code with their coefficients folded.
#[cfg(target_arch = "x86_64")]
macro_rules! arr6 {
    (|$i:ident| $e:expr) => {
        [
            {
                let $i = 0;
                $e
            },
            {
                let $i = 1;
                $e
            },
            {
                let $i = 2;
                $e
            },
            {
                let $i = 3;
                $e
            },
            {
                let $i = 4;
                $e
            },
            {
                let $i = 5;
                $e
            },
        ]
    };
}
#[cfg(target_arch = "x86_64")]
macro_rules! arr4 {
    (|$i:ident| $e:expr) => {
        [
            {
                let $i = 0;
                $e
            },
            {
                let $i = 1;
                $e
            },
            {
                let $i = 2;
                $e
            },
            {
                let $i = 3;
                $e
            },
        ]
    };
}

/// `sum_i row[i] * v[i]`, skipping zero coefficients (constants after inlining).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn dot6(row: &[f32; A], v: &[__m256; A]) -> __m256 {
    let mut acc = _mm256_setzero_ps();
    for i in 0..A {
        if row[i] != 0.0 {
            acc = _mm256_fmadd_ps(_mm256_set1_ps(row[i]), v[i], acc);
        }
    }
    acc
}

/// `V[pos][ci][slot] = (B^T d B)[pos]` for the unit's `groups` groups of [`LANES`] slots
/// from slot `s0` (`d` the tile's `A x A` inputs, at `taps[i][j]` from its slot).
///
/// # Safety
/// AVX2 and FMA present; `x` holds `cin` channels of `channel` floats in the phase layout.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn input_transform<T: Algo>(
    x: &[f32],
    channel: usize,
    taps: &[[usize; A]; A],
    s0: usize,
    groups: usize,
    v: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    {
        let cin = x.len() / channel;
        assert!(v.len() >= POS * cin * UNIT_TILES && groups * LANES <= UNIT_TILES);
        let last_tap = taps.iter().flatten().copied().max().unwrap_or(0);
        assert!(s0 + groups * LANES + last_tap <= channel);
        let (vp, xp) = (v.as_mut_ptr(), x.as_ptr());
        // Channel by channel, so that a channel's rows of V (36 x 3 lines) stay in L1.
        for ci in 0..cin {
            for grp in 0..groups {
                // In bounds: asserted above (the last load ends at the last slot + tap).
                let xc = xp.add(ci * channel + s0 + grp * LANES);
                // Columns of d through B^T: tmp[j][p] = sum_i B^T[p][i] d[i][j].
                let tmp: [[__m256; A]; A] = arr6!(|j| {
                    let col = arr6!(|i| _mm256_loadu_ps(xc.add(taps[i][j])));
                    arr6!(|pi| dot6(&T::BT[pi], &col))
                });
                let out = vp.add(ci * UNIT_TILES + grp * LANES);
                let _ = arr6!(|pi| {
                    let row = arr6!(|j| tmp[j][pi]);
                    arr6!(|q| _mm256_storeu_ps(
                        out.add((pi * A + q) * cin * UNIT_TILES),
                        dot6(&T::BT[q], &row)
                    ))
                });
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (x, channel, taps, s0, groups, v);
}

/// `y = act(A^T M A + bias)` for the unit's slots, eight channels at a time (`M` is
/// `[POS, panels, slots, CV]`), written to the outputs inside the image (`y` addresses
/// image n's `[Cout, Ho, Wo]`; padding slots are skipped).
///
/// # Safety
/// AVX2 and FMA present; no other thread writes these tiles' outputs.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn output_transform<T: Algo>(
    g: &Geom,
    lay: &Layout,
    m: &[f32],
    b: &[f32],
    relu: bool,
    s0: usize,
    groups: usize,
    y: *mut f32,
) {
    #[cfg(target_arch = "x86_64")]
    {
        let (cout, ho, wo, mm, p) = (g.cout, g.ho(), g.wo(), T::M, g.p());
        let panels = cout / CV;
        let zero = _mm256_setzero_ps();
        // Each slot's first output (row, column), or none for padding slots.
        let mut first = [None; UNIT_TILES];
        for (slot, f) in first.iter_mut().enumerate().take(groups * LANES) {
            let (ty, tx) = ((s0 + slot) / lay.wp, (s0 + slot) % lay.wp);
            *f = (ty < lay.ty && tx < lay.tx).then_some((ty * mm, tx * mm));
        }
        assert!(m.len() >= POS * cout * UNIT_TILES && b.len() >= cout);
        let mp = m.as_ptr();
        // Eight channels at a time, slot after slot: M is read in runs of lines.
        for c8 in (0..cout).step_by(LANES) {
            let (panel, h) = (c8 / CV, c8 % CV);
            let bias = _mm256_loadu_ps(b[c8..c8 + LANES].as_ptr());
            for (slot, f) in first.iter().enumerate().take(groups * LANES) {
                let Some((r0, c0)) = *f else { continue };
                let (rows, cols) = (mm.min(ho - r0), mm.min(wo - c0));
                // In bounds: asserted above (pos < POS, panel < cout / CV, slot < UNIT_TILES).
                let at = mp.add((panel * UNIT_TILES + slot) * CV + h);
                // tmp[j][a] = sum_i A^T[a][i] M[i][j].
                let tmp: [[__m256; 4]; A] = arr6!(|j| {
                    let col =
                        arr6!(|i| _mm256_loadu_ps(at.add((i * A + j) * panels * UNIT_TILES * CV)));
                    arr4!(|a| dot6(&T::AT[a], &col))
                });
                let _ = arr4!(|a| if a < rows {
                    let row = arr6!(|j| tmp[j][a]);
                    let _ = arr4!(|bq| if bq < cols {
                        let o = _mm256_add_ps(dot6(&T::AT[bq], &row), bias);
                        let o = if relu { _mm256_max_ps(o, zero) } else { o };
                        let mut vals = [0f32; LANES];
                        _mm256_storeu_ps(vals.as_mut_ptr(), o);
                        let dst = y.add(c8 * p + (r0 + a) * wo + c0 + bq);
                        for (l, &v) in vals.iter().enumerate() {
                            *dst.add(l * p) = v;
                        }
                    });
                });
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (g, lay, m, b, relu, s0, groups, y);
}
