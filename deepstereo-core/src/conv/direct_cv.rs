//! Channel-vectorised implicit-GEMM forward (f32, AVX2 and FMA) for wide layers: output
//! channels a multiple of [`CV`] and many taps (the `paper` preset's layers).
//!
//! A tile is [`CV`] output channels (two 8-lane vectors) x [`NP`] outputs, each with its
//! own input pointer. Per tap: two aligned loads of packed weights (`[K, CV]` panels),
//! `NP` scalar broadcasts of `x` (never split across cache lines, unlike `direct.rs`'s
//! unaligned vector loads), `2 NP` FMAs into 12 registers. Rows are cut into tiles of `NP`
//! consecutive outputs; the last `Wo % NP` outputs of each row are gathered across a work
//! block's rows into tiles of their own, so nothing is computed twice but the padding of
//! a block's last gathered tile (shifting a row's last tile left instead recomputed 4 of
//! 24 outputs in rows of 20 and 4 of 12 in rows of 8, sizes of the `paper` layers).
//! Row tiles' outputs leave through an 8 x 8 register transpose and masked stores of `NP`
//! lanes (channels are planes in NCHW; scalar stores had taken about 8% of a `paper`
//! forward); gathered tiles store theirs one by one.
//! Taps are blocked by [`KC`] as in `direct.rs`.

use super::direct::{pack, tap_offsets};
use super::im2col::Geom;
use crate::cpu::{avx2_fma_available as available, SharedMut};
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

/// Whether [`forward`] can run this layer (f32 callers only; `plan.rs` chooses).
pub(crate) fn applies(g: &Geom) -> bool {
    available() && g.cout.is_multiple_of(CV) && g.k() >= MIN_K && g.wo() >= NP
}

/// A tile's outputs: [`NP`] consecutive outputs of row `r` from column `c`, or [`NP`]
/// `(row, column)` outputs gathered from the ends of rows (each row's last `Wo % NP`).
#[derive(Clone, Copy)]
enum Tile {
    Row { r: usize, c: usize },
    Gather([(usize, usize); NP]),
}

/// The tiles of output rows `rows`: each row's whole tiles, then the rows' leftover
/// outputs in groups of [`NP`] (the last group padded by repeating its last output, which
/// is then written twice with one value).
fn block_tiles(rows: std::ops::Range<usize>, wo: usize) -> Vec<Tile> {
    let (full, rem) = (wo / NP, wo % NP);
    let mut tiles: Vec<Tile> = rows
        .clone()
        .flat_map(|r| (0..full).map(move |t| Tile::Row { r, c: t * NP }))
        .collect();
    let ends: Vec<(usize, usize)> = rows
        .flat_map(|r| (wo - rem..wo).map(move |c| (r, c)))
        .collect();
    tiles.extend(ends.chunks(NP).map(|group| {
        let mut px = [group[group.len() - 1]; NP];
        px[..group.len()].copy_from_slice(group);
        Tile::Gather(px)
    }));
    tiles
}

/// Output rows per work block: about [`BLOCK_TILES`] tiles, a multiple of the rows whose
/// leftovers fill whole gathered tiles where the image allows, and at least
/// [`BLOCKS_PER_THREAD`] blocks per thread when the work allows.
fn block_rows(g: &Geom) -> usize {
    let (wo, ho) = (g.wo(), g.ho());
    let want = rayon::current_num_threads() * BLOCKS_PER_THREAD;
    let rows = (BLOCK_TILES / wo.div_ceil(NP))
        .clamp(1, ho)
        .min((g.n * ho).div_ceil(want).max(1));
    let rem = wo % NP;
    if rem == 0 {
        return rows;
    }
    let (mut a, mut b) = (rem, NP);
    while b != 0 {
        (a, b) = (b, a % b);
    }
    let step = NP / a;
    (rows.div_ceil(step) * step).min(ho)
}

/// `y = act(conv(x, w) + b)`, as [`super::kernels::forward`]; call only when
/// [`applies`] holds.
pub(crate) fn forward(g: &Geom, x: &[f32], w: &[f32], b: &[f32], relu: bool) -> Vec<f32> {
    let (k, p, cout, wo, ho) = (g.k(), g.p(), g.cout, g.wo(), g.ho());
    let offsets = tap_offsets(g);
    let wp = pack(w, cout, k, CV); // each tap's CV weights fill one cache line
    let rows = block_rows(g);
    let per_image = ho.div_ceil(rows);
    let len = g.n * cout * p;
    // Every output is written below (all blocks, panels and tiles) before `set_len`.
    let mut y = Vec::<f32>::with_capacity(len);
    let yp = SharedMut(y.as_mut_ptr());
    (0..g.n * per_image).into_par_iter().for_each(|blk| {
        let (n, r0) = (blk / per_image, (blk % per_image) * rows);
        let tiles = block_tiles(r0..(r0 + rows).min(ho), wo);
        let mut partial = vec![[[0f32; CV]; NP]; tiles.len()];
        let x_img = &x[n * g.cin * g.hw()..(n + 1) * g.cin * g.hw()];
        for panel in 0..cout / CV {
            let wpp = &wp[panel * k * CV..][..k * CV];
            let bias = &b[panel * CV..][..CV];
            let plane = (n * cout + panel * CV) * p;
            for k0 in (0..k).step_by(KC) {
                let k1 = (k0 + KC).min(k);
                for (tile, part) in tiles.iter().zip(partial.iter_mut()) {
                    if k0 == 0 {
                        part.iter_mut().for_each(|px| px.copy_from_slice(bias));
                    }
                    // Where each output's taps start, and (last tap block of a row tile)
                    // where its channels' outputs go, `NP` consecutive in each plane.
                    let (xs, out) = match *tile {
                        Tile::Row { r, c } => (
                            std::array::from_fn(|px| r * g.w + c + px),
                            (k1 == k).then(|| yp.get().wrapping_add(plane + r * wo + c)),
                        ),
                        Tile::Gather(px) => (px.map(|(r, c)| r * g.w + c), None),
                    };
                    // SAFETY: `applies` checked the CPU; output (r, c) reads x at r * W + c
                    // + offsets[k] (r < Ho, c < Wo: a valid convolution's inputs); a row
                    // tile writes NP outputs in each of the panel's CV planes (stride p),
                    // which the block owns (rows r0.. of image n).
                    #[cfg(target_arch = "x86_64")]
                    unsafe {
                        avx2::tile(
                            &offsets[k0..k1],
                            xs.map(|q| x_img.as_ptr().add(q)),
                            &wpp[k0 * CV..k1 * CV],
                            part,
                            false,
                            out.map(|y| (y, p, relu)),
                        );
                    }
                    if let (Tile::Gather(px), true) = (tile, k1 == k) {
                        for (&(r, c), vals) in px.iter().zip(part.iter()) {
                            for (co, &v) in vals.iter().enumerate() {
                                let v = if relu { v.max(0.0) } else { v };
                                // SAFETY: as above, an output of the block's rows.
                                unsafe { *yp.get().add(plane + co * p + r * wo + c) = v };
                            }
                        }
                    }
                }
            }
        }
    });
    // SAFETY: the blocks above wrote all `len` outputs.
    unsafe { y.set_len(len) };
    y
}

/// Products for `winograd.rs`: for each group `t` of [`NP`] columns, `out[t][px][co] =
/// sum_k wp[k * CV + co] * v[offsets[k] + t NP + px]`, taps in blocks of [`KC`] (one call
/// for all groups, so that the tile kernel inlines).
///
/// # Safety
/// AVX2 and FMA present; `v + offsets[k] + out.len() * NP` in bounds for every `k`; `wp`
/// holds `offsets.len() * CV` values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn gemm_groups(
    offsets: &[usize],
    v: *const f32,
    wp: &[f32],
    out: &mut [[[f32; CV]; NP]],
) {
    for (t, part) in out.iter_mut().enumerate() {
        let xs = std::array::from_fn(|px| v.add(t * NP + px));
        for k0 in (0..offsets.len()).step_by(KC) {
            let k1 = (k0 + KC).min(offsets.len());
            avx2::tile(
                &offsets[k0..k1],
                xs,
                &wp[k0 * CV..k1 * CV],
                part,
                k0 == 0,
                None,
            );
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{CV, NP};
    use std::arch::x86_64::*;

    /// `part[px][co] += sum_k wp[k * CV + co] * xs[px][offsets[k]]` (`part` read as zeros
    /// when `zero`); with `out = (y,
    /// stride, relu)` the sums go (through the ReLU when `relu`) to `y[co * stride + px]`
    /// instead of back to `part`.
    ///
    /// # Safety
    /// AVX2 and FMA present; `xs[px] + offsets[k]` in bounds for every `k`; `wp` holds
    /// `offsets.len() * CV` values; `out` addresses `CV` rows of `NP` outputs that no
    /// other thread accesses.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn tile(
        offsets: &[usize],
        xs: [*const f32; NP],
        wp: &[f32],
        part: &mut [[f32; CV]; NP],
        zero: bool,
        out: Option<(*mut f32, usize, bool)>,
    ) {
        const { assert!(CV == 16 && NP <= 8) };
        let mut acc = [[_mm256_setzero_ps(); 2]; NP];
        if !zero {
            for (a, p) in acc.iter_mut().zip(part.iter()) {
                *a = [
                    _mm256_loadu_ps(p.as_ptr()),
                    _mm256_loadu_ps(p.as_ptr().add(8)),
                ];
            }
        }
        let w = wp.as_ptr();
        for (kk, &o) in offsets.iter().enumerate() {
            let w0 = _mm256_loadu_ps(w.add(kk * CV));
            let w1 = _mm256_loadu_ps(w.add(kk * CV + 8));
            for (a, &x) in acc.iter_mut().zip(&xs) {
                let s = _mm256_broadcast_ss(&*x.add(o));
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

#[cfg(test)]
mod tests {
    use super::{block_tiles, Tile, NP};
    use std::collections::BTreeSet;

    /// Tiles cover each output of their rows once (a padded gathered tile repeats only its
    /// own last output) and stay inside the rows.
    #[test]
    fn block_tiles_cover_rows_once() {
        for wo in NP..=40 {
            for (r0, rows) in [(0, 1), (3, 2), (0, 3), (5, 6), (1, 7)] {
                let mut seen = Vec::new();
                for t in block_tiles(r0..r0 + rows, wo) {
                    match t {
                        Tile::Row { r, c } => seen.extend((c..c + NP).map(|c| (r, c))),
                        Tile::Gather(px) => {
                            let mut px = px.to_vec();
                            px.dedup();
                            seen.extend(px);
                        }
                    }
                }
                let want: BTreeSet<_> = (r0..r0 + rows)
                    .flat_map(|r| (0..wo).map(move |c| (r, c)))
                    .collect();
                assert_eq!(
                    seen.len(),
                    want.len(),
                    "wo {wo}, rows {rows}: outputs repeated"
                );
                assert_eq!(seen.into_iter().collect::<BTreeSet<_>>(), want, "wo {wo}");
            }
        }
    }
}
