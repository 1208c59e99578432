//! Channel-vectorised implicit-GEMM forward (f32, AVX2 and FMA) for wide layers: output
//! channels a multiple of [`CV`] and many taps (the `paper` preset's layers).
//!
//! A tile is [`CV`] output channels (two 8-lane vectors) x [`NP`] consecutive outputs of
//! one row. Per tap: two aligned loads of packed weights (`[K, CV]` panels), `NP` scalar
//! broadcasts of `x` (never split across cache lines, unlike `direct.rs`'s unaligned
//! vector loads), `2 NP` FMAs into 12 registers. Rows are cut into tiles of `NP` (the
//! last one shifted left to end at the row's end), so a row wastes less than `NP`
//! outputs, against up to 15 for `direct.rs`'s 16-wide tiles. Outputs leave through an
//! 8 x 8 register transpose and masked stores of `NP` lanes (channels are planes in NCHW;
//! scalar stores had taken about 8% of a `paper` forward).
//! Taps are blocked by [`KC`] as in `direct.rs`.

use super::direct::{available, kernels_allowed, tap_offsets, Kernels};
use super::im2col::{Geom, SharedMut};
use rayon::prelude::*;

/// Output channels per tile.
pub(crate) const CV: usize = 16;
/// Outputs per tile.
pub(crate) const NP: usize = 6;
/// Fewest taps for this kernel (below it the transposed stores cost too much).
const MIN_K: usize = 256;
/// Taps per block: a panel's block (`KC x CV` floats, 8 KiB), the block's partial sums
/// and the input lines stay in L1 (128 ran the paper's layers faster than 256).
const KC: usize = 128;
/// Tiles wanted per work block.
const BLOCK_TILES: usize = 16;
/// Work blocks wanted per thread, for load balance.
const BLOCKS_PER_THREAD: usize = 8;

/// Whether [`forward`] runs this layer (f32 callers only).
pub(crate) fn applies(g: &Geom) -> bool {
    available()
        && kernels_allowed() == Kernels::Auto
        && g.cout.is_multiple_of(CV)
        && g.k() >= MIN_K
        && g.wo() >= NP
}

/// Weights `[Cout, K]` as panels of [`CV`] output channels, each `[K, CV]`.
fn pack(w: &[f32], cout: usize, k: usize) -> Vec<f32> {
    let mut p = vec![0f32; cout * k];
    for co in 0..cout {
        let (panel, r) = (co / CV, co % CV);
        for kk in 0..k {
            p[(panel * k + kk) * CV + r] = w[co * k + kk];
        }
    }
    p
}

/// `y = act(conv(x, w) + b)`, as [`super::kernels::forward`]; call only when
/// [`applies`] holds.
pub(crate) fn forward(g: &Geom, x: &[f32], w: &[f32], b: &[f32], relu: bool) -> Vec<f32> {
    let (k, p, cout, wo, ho) = (g.k(), g.p(), g.cout, g.wo(), g.ho());
    let offsets = tap_offsets(g);
    let wp = pack(w, cout, k);
    let cols: Vec<usize> = (0..wo.div_ceil(NP))
        .map(|t| (t * NP).min(wo - NP))
        .collect();
    let want = rayon::current_num_threads() * BLOCKS_PER_THREAD;
    let rows = (BLOCK_TILES / cols.len())
        .clamp(1, ho)
        .min((g.n * ho).div_ceil(want).max(1));
    let per_image = ho.div_ceil(rows);
    let len = g.n * cout * p;
    // Every output is written below (all blocks, panels and tiles) before `set_len`.
    let mut y = Vec::<f32>::with_capacity(len);
    let yp = SharedMut(y.as_mut_ptr());
    (0..g.n * per_image).into_par_iter().for_each(|blk| {
        let (n, r0) = (blk / per_image, (blk % per_image) * rows);
        let tiles: Vec<(usize, usize)> = (r0..(r0 + rows).min(ho))
            .flat_map(|r| cols.iter().map(move |&c| (r, c)))
            .collect();
        let mut partial = vec![[[0f32; CV]; NP]; tiles.len()];
        let x_img = &x[n * g.cin * g.hw()..(n + 1) * g.cin * g.hw()];
        for panel in 0..cout / CV {
            let wpp = &wp[panel * k * CV..][..k * CV];
            let bias = &b[panel * CV..][..CV];
            for k0 in (0..k).step_by(KC) {
                let k1 = (k0 + KC).min(k);
                for (&(r, c), part) in tiles.iter().zip(partial.iter_mut()) {
                    if k0 == 0 {
                        part.iter_mut().for_each(|px| px.copy_from_slice(bias));
                    }
                    // The last tap block stores the tile's outputs: channel `co`'s `NP`
                    // outputs are consecutive in its plane.
                    let out = (k1 == k).then(|| {
                        yp.get()
                            .wrapping_add((n * cout + panel * CV) * p + r * wo + c)
                    });
                    // SAFETY: `applies` checked the CPU; the tile reads x at r * W + c +
                    // px + offsets[k] (px < NP, c + NP <= Wo: a valid convolution's inputs)
                    // and writes NP outputs in each of the panel's CV planes (stride p),
                    // which the block owns (rows r0.. of image n; tiles of a row overlap
                    // only within this block).
                    #[cfg(target_arch = "x86_64")]
                    unsafe {
                        avx2::tile(
                            &offsets[k0..k1],
                            x_img.as_ptr().add(r * g.w + c),
                            &wpp[k0 * CV..k1 * CV],
                            part,
                            out.map(|y| (y, p, relu)),
                        );
                    }
                }
            }
        }
    });
    // SAFETY: the blocks above wrote all `len` outputs.
    unsafe { y.set_len(len) };
    y
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{CV, NP};
    use std::arch::x86_64::*;

    /// `part[px][co] += sum_k wp[k * CV + co] * x[offsets[k] + px]`; with `out = (y,
    /// stride, relu)` the sums go (through the ReLU when `relu`) to `y[co * stride + px]`
    /// instead of back to `part`.
    ///
    /// # Safety
    /// AVX2 and FMA present; `x + offsets[k] + NP` in bounds for every `k`; `wp` holds
    /// `offsets.len() * CV` values; `out` addresses `CV` rows of `NP` outputs that no
    /// other thread accesses.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn tile(
        offsets: &[usize],
        x: *const f32,
        wp: &[f32],
        part: &mut [[f32; CV]; NP],
        out: Option<(*mut f32, usize, bool)>,
    ) {
        const { assert!(CV == 16 && NP <= 8) };
        let mut acc = [[_mm256_setzero_ps(); 2]; NP];
        for (a, p) in acc.iter_mut().zip(part.iter()) {
            *a = [
                _mm256_loadu_ps(p.as_ptr()),
                _mm256_loadu_ps(p.as_ptr().add(8)),
            ];
        }
        let w = wp.as_ptr();
        for (kk, &o) in offsets.iter().enumerate() {
            let w0 = _mm256_loadu_ps(w.add(kk * CV));
            let w1 = _mm256_loadu_ps(w.add(kk * CV + 8));
            let xo = x.add(o);
            for (px, a) in acc.iter_mut().enumerate() {
                let s = _mm256_broadcast_ss(&*xo.add(px));
                a[0] = _mm256_fmadd_ps(s, w0, a[0]);
                a[1] = _mm256_fmadd_ps(s, w1, a[1]);
            }
        }
        let Some((y, stride, relu)) = out else {
            for (a, p) in acc.iter().zip(part.iter_mut()) {
                _mm256_storeu_ps(p.as_mut_ptr(), a[0]);
                _mm256_storeu_ps(p.as_mut_ptr().add(8), a[1]);
            }
            return;
        };
        // Lanes 0..NP of a row: the tile's outputs of one channel.
        let mask = _mm256_cmpgt_epi32(
            _mm256_set1_epi32(NP as i32),
            _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
        );
        let zero = _mm256_setzero_ps();
        for h in 0..2 {
            let mut rows = [zero; 8];
            for (r, a) in rows.iter_mut().zip(&acc) {
                *r = if relu {
                    _mm256_max_ps(a[h], zero)
                } else {
                    a[h]
                };
            }
            for (co, v) in transpose8(rows).into_iter().enumerate() {
                _mm256_maskstore_ps(y.add((h * 8 + co) * stride), mask, v);
            }
        }
    }

    /// The 8 x 8 transpose: lane `j` of row `i` becomes lane `i` of row `j`.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn transpose8(r: [__m256; 8]) -> [__m256; 8] {
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpackhi_ps(r[0], r[1]);
        let t2 = _mm256_unpacklo_ps(r[2], r[3]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        let t4 = _mm256_unpacklo_ps(r[4], r[5]);
        let t5 = _mm256_unpackhi_ps(r[4], r[5]);
        let t6 = _mm256_unpacklo_ps(r[6], r[7]);
        let t7 = _mm256_unpackhi_ps(r[6], r[7]);
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
        let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
        [
            _mm256_permute2f128_ps::<0x20>(u0, u4),
            _mm256_permute2f128_ps::<0x20>(u1, u5),
            _mm256_permute2f128_ps::<0x20>(u2, u6),
            _mm256_permute2f128_ps::<0x20>(u3, u7),
            _mm256_permute2f128_ps::<0x31>(u0, u4),
            _mm256_permute2f128_ps::<0x31>(u1, u5),
            _mm256_permute2f128_ps::<0x31>(u2, u6),
            _mm256_permute2f128_ps::<0x31>(u3, u7),
        ]
    }
}
