//! Backward of the implicit-GEMM convolution (`direct.rs`), f32 on x86-64 with AVX2 and
//! FMA, again without im2col:
//!
//! - `gy`, the ReLU-masked output gradient, is laid out at the input's row stride (zeros
//!   past `Wo`), the bias gradient summed on the way;
//! - input gradient: the "full" convolution of `gy` (laid out again, zero-padded by
//!   `kh - 1`, `kw - 1`; one layout serves both when `kw = 1`) with the weights flipped in
//!   space and transposed in channels, run by the forward kernel `plan.rs` picks for it;
//! - weight gradient `dW [Cout, K] = sum over flat positions q of gy[co, q] x[q +
//!   offset[k]]` (positions as in `direct.rs`; those past `Wo` add zero): a reduction
//!   vectorised along positions. A tile holds [`GR`] output channels x [`GK`] taps in 12
//!   registers; per 8 positions it loads `GR + GK` vectors for `GR * GK` FMAs. Work blocks
//!   of about [`BLOCK_PIXELS`] positions (small images share one) keep `x`'s band in L2 and
//!   the tile's `gy` rows in L1 while all taps sweep them. Threads add into one
//!   accumulator per group of blocks; groups are summed in a fixed order, so gradients do
//!   not depend on the schedule.

use super::direct::{flat_len, tap_offsets};
use super::im2col::Geom;
use super::{plan, winograd};
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Output channels per weight-gradient tile (with [`GK`]: 12 accumulators, 3 + 1 more
/// registers for the loaded vectors, all of AVX2's 16).
const GR: usize = 3;
/// Taps per weight-gradient tile.
const GK: usize = 4;
/// Output pixels wanted per block of the weight gradient.
const BLOCK_PIXELS: usize = 1024;
/// Accumulator groups per thread (load balance against the memory of accumulators).
const GROUPS_PER_THREAD: usize = 4;

/// The input gradient alone, for layers whose weight gradient stays on the im2col path
/// (more than [`plan::MAX_DIRECT_GRAD_K`] taps) and whose input gradient's convolution is a Winograd layer
/// (`plan.rs`): Winograd's forward on the padded, masked output gradient with flipped
/// weights, as in [`backward`].
pub(crate) fn input_grad(g: &Geom, w: &[f32], y: &[f32], dy: &[f32], relu: bool) -> Vec<f32> {
    let mask = Mask { dy, y, relu };
    let t = g.transposed();
    let (padded, _) = mask.laid_out(g, t.w, g.kh - 1, g.kw - 1);
    winograd::forward(&t, &padded, &flipped(g, w), &vec![0f32; g.cin], false)
}

/// Gradients of `act(conv(x, w) + b)` from `dy` (`y` is the forward output, read when
/// `relu`): `(dx if need_dx, dw, db)`.
pub(crate) fn backward(
    g: &Geom,
    x: &[f32],
    w: &[f32],
    y: &[f32],
    dy: &[f32],
    relu: bool,
    need_dx: bool,
) -> (Option<Vec<f32>>, Vec<f32>, Vec<f32>) {
    let mask = Mask { dy, y, relu };
    let t = g.transposed();
    let wt = flipped(g, w);
    let zero_bias = vec![0f32; g.cin];
    let (ph, pw) = if g.direct() {
        (0, 0)
    } else {
        (g.kh - 1, g.kw - 1)
    };
    // dx reads gy zero-padded (rows of t.w); the weight gradient reads it at the input's
    // row stride (zeros past Wo). With kw = 1 the two are one layout.
    let (padded, db) = mask.laid_out(g, t.w, ph, pw);
    let dx = need_dx.then(|| plan::forward_f32(&t, &padded, &wt, &zero_bias, false));
    let dw = if g.kw == 1 {
        weight_grad(g, x, &padded, t.hw(), ph * g.w)
    } else {
        let (wide, _) = mask.laid_out(g, g.w, 0, 0);
        weight_grad(g, x, &wide, g.ho() * g.w, 0)
    };
    (dx, dw, db)
}

/// The output gradient with the ReLU mask applied (`dy` where `y > 0`).
struct Mask<'a> {
    dy: &'a [f32],
    y: &'a [f32],
    relu: bool,
}

impl Mask<'_> {
    /// Masked `gy` in planes of rows of `row` values, each output row at `(r + ph, pw)`
    /// (zeros elsewhere; `Ho + 2 ph` rows), and the bias gradient (sums per channel).
    fn laid_out(&self, g: &Geom, row: usize, ph: usize, pw: usize) -> (Vec<f32>, Vec<f32>) {
        let (ho, wo, p) = (g.ho(), g.wo(), g.p());
        let plane = (ho + 2 * ph) * row;
        let len = g.n * g.cout * plane;
        let mut out = Vec::<f32>::with_capacity(len);
        let sums: Vec<f32> = out.spare_capacity_mut()[..len]
            .par_chunks_mut(plane)
            .enumerate()
            .map(|(i, dst)| {
                let dy = &self.dy[i * p..][..p];
                let y = &self.y[if self.relu { i * p..(i + 1) * p } else { 0..0 }];
                let mut sum = 0f32;
                let zero = |d: &mut [MaybeUninit<f32>]| {
                    d.iter_mut().for_each(|v| {
                        v.write(0.0);
                    })
                };
                for (rr, d) in dst.chunks_exact_mut(row).enumerate() {
                    let Some(r) = rr.checked_sub(ph).filter(|&r| r < ho) else {
                        zero(d);
                        continue;
                    };
                    let (head, rest) = d.split_at_mut(pw);
                    let (mid, tail) = rest.split_at_mut(wo);
                    zero(head);
                    zero(tail);
                    let dy = &dy[r * wo..][..wo];
                    if self.relu {
                        let y = &y[r * wo..][..wo];
                        for ((v, &g), &yv) in mid.iter_mut().zip(dy).zip(y) {
                            let g = if yv > 0.0 { g } else { 0.0 };
                            sum += g;
                            v.write(g);
                        }
                    } else {
                        for (v, &g) in mid.iter_mut().zip(dy) {
                            sum += g;
                            v.write(g);
                        }
                    }
                }
                sum
            })
            .collect();
        // SAFETY: every plane's rows were written in full above.
        unsafe { out.set_len(len) };
        let mut db = vec![0f32; g.cout];
        for (i, s) in sums.iter().enumerate() {
            db[i % g.cout] += s;
        }
        (out, db)
    }
}

/// Weights flipped in space and transposed in channels: `[Cin, Cout, kh, kw]`.
fn flipped(g: &Geom, w: &[f32]) -> Vec<f32> {
    let (kh, kw, k) = (g.kh, g.kw, g.k());
    let mut wt = vec![0f32; g.cin * g.cout * kh * kw];
    for co in 0..g.cout {
        for ci in 0..g.cin {
            for i in 0..kh {
                for j in 0..kw {
                    wt[((ci * g.cout + co) * kh + kh - 1 - i) * kw + kw - 1 - j] =
                        w[co * k + (ci * kh + i) * kw + j];
                }
            }
        }
    }
    wt
}

/// A run of flat positions `q0 .. q0 + len` of image `n` (see `direct.rs`).
#[derive(Clone, Copy)]
struct Segment {
    n: usize,
    q0: usize,
    len: usize,
}

/// Segments of at most [`BLOCK_PIXELS`] positions, gathered into blocks of about that
/// many (small images share a block).
fn segment_blocks(g: &Geom) -> Vec<Vec<Segment>> {
    let q = flat_len(g);
    let mut blocks = vec![Vec::new()];
    let mut filled = 0;
    for n in 0..g.n {
        for q0 in (0..q).step_by(BLOCK_PIXELS) {
            let len = (q - q0).min(BLOCK_PIXELS);
            if filled + len > BLOCK_PIXELS && filled > 0 {
                blocks.push(Vec::new());
                filled = 0;
            }
            if let Some(b) = blocks.last_mut() {
                b.push(Segment { n, q0, len });
            }
            filled += len;
        }
    }
    blocks
}

/// `dW [Cout, K] = sum over images and flat positions q of gy[co, q] x[q + offset[k]]`,
/// with `gy` at the input's row stride (zeros past `Wo`, so those positions add nothing).
/// Channel `co` of image `n` starts at `gy[(n * Cout + co) * plane + first]`.
fn weight_grad(g: &Geom, x: &[f32], gy: &[f32], plane: usize, first: usize) -> Vec<f32> {
    let (k, cout) = (g.k(), g.cout);
    let offsets = tap_offsets(g);
    let blocks = segment_blocks(g);
    let groups = (rayon::current_num_threads() * GROUPS_PER_THREAD)
        .min(blocks.len())
        .max(1);
    let accs: Vec<Vec<f32>> = (0..groups)
        .into_par_iter()
        .map(|grp| {
            let mut acc = vec![0f32; cout * k];
            for segs in &blocks[grp * blocks.len() / groups..(grp + 1) * blocks.len() / groups] {
                for c0 in (0..cout).step_by(GR) {
                    let mr = (cout - c0).min(GR);
                    let parts: Vec<Part> = segs
                        .iter()
                        .map(|s| Part {
                            x: &x[s.n * g.cin * g.hw()..(s.n + 1) * g.cin * g.hw()],
                            gy: &gy[(s.n * cout + c0) * plane + first..(s.n + 1) * cout * plane],
                            q0: s.q0,
                            len: s.len,
                        })
                        .collect();
                    for k0 in (0..k).step_by(GK) {
                        let nk = (k - k0).min(GK);
                        let sums = tile_dispatch(mr, nk, &parts, plane, &offsets[k0..k0 + nk]);
                        for (m, row) in sums.iter().enumerate().take(mr) {
                            for (q, &v) in row.iter().enumerate().take(nk) {
                                acc[(c0 + m) * k + k0 + q] += v;
                            }
                        }
                    }
                }
            }
            acc
        })
        .collect();
    let mut dw = vec![0f32; cout * k];
    for a in &accs {
        dw.iter_mut().zip(a).for_each(|(d, &v)| *d += v);
    }
    dw
}

/// One segment as the kernel reads it: `x` the image, `gy` from the tile's first channel
/// (channel `m` at `m * plane`), positions `q0 .. q0 + len`.
struct Part<'a> {
    x: &'a [f32],
    gy: &'a [f32],
    q0: usize,
    len: usize,
}

/// `sums[m][t] = sum over the parts' positions q of gy[m * plane + q] * x[taps[t] + q]`.
fn tile_dispatch(
    mr: usize,
    nk: usize,
    parts: &[Part],
    plane: usize,
    taps: &[usize],
) -> [[f32; GK]; GR] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: `available` checked the CPU (callers go through `applies`); positions are
    // below Q, so reads stay in the image (valid convolution) and in the gy planes.
    unsafe {
        macro_rules! go {
            ($($m:literal $q:literal),*) => {
                match (mr, nk) {
                    $(($m, $q) => avx2::tile::<$m, $q>(parts, plane, taps),)*
                    _ => [[0.0; GK]; GR],
                }
            };
        }
        go!(1 1, 1 2, 1 3, 1 4, 2 1, 2 2, 2 3, 2 4, 3 1, 3 2, 3 3, 3 4)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (mr, nk, parts, plane, taps);
        [[0.0; GK]; GR]
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Part, GK, GR};
    use std::arch::x86_64::*;

    /// Lanes `< n` set (n <= 8), as a mask for `maskload`.
    #[target_feature(enable = "avx2")]
    unsafe fn lanes(n: usize) -> __m256i {
        let idx = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        _mm256_cmpgt_epi32(_mm256_set1_epi32(n as i32), idx)
    }

    #[target_feature(enable = "avx2")]
    unsafe fn hsum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        _mm_cvtss_f32(_mm_add_ss(s, _mm_shuffle_ps(s, s, 1)))
    }

    /// See [`super::tile_dispatch`]; `R` channels, `Q` taps.
    ///
    /// # Safety
    /// AVX2 and FMA present; every read address in bounds of the parts' slices.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn tile<const R: usize, const Q: usize>(
        parts: &[Part],
        plane: usize,
        taps: &[usize],
    ) -> [[f32; GK]; GR] {
        let mut acc = [[_mm256_setzero_ps(); Q]; R];
        let mut tap = [0usize; Q];
        tap.copy_from_slice(&taps[..Q]);
        for part in parts {
            let (xp, gp) = (part.x.as_ptr().add(part.q0), part.gy.as_ptr().add(part.q0));
            let full = part.len / 8 * 8;
            let mut q = 0;
            while q < full {
                let mut gv = [_mm256_setzero_ps(); R];
                for (m, v) in gv.iter_mut().enumerate() {
                    *v = _mm256_loadu_ps(gp.add(m * plane + q));
                }
                for t in 0..Q {
                    let xv = _mm256_loadu_ps(xp.add(tap[t] + q));
                    for m in 0..R {
                        acc[m][t] = _mm256_fmadd_ps(gv[m], xv, acc[m][t]);
                    }
                }
                q += 8;
            }
            if full < part.len {
                let tail = lanes(part.len - full);
                let mut gv = [_mm256_setzero_ps(); R];
                for (m, v) in gv.iter_mut().enumerate() {
                    *v = _mm256_maskload_ps(gp.add(m * plane + q), tail);
                }
                for t in 0..Q {
                    let xv = _mm256_maskload_ps(xp.add(tap[t] + q), tail);
                    for m in 0..R {
                        acc[m][t] = _mm256_fmadd_ps(gv[m], xv, acc[m][t]);
                    }
                }
            }
        }
        let mut out = [[0f32; GK]; GR];
        for m in 0..R {
            for t in 0..Q {
                out[m][t] = hsum(acc[m][t]);
            }
        }
        out
    }
}
