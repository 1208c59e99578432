//! Implicit-GEMM forward for f32 on x86-64 with AVX2 and FMA: no im2col buffer.
//!
//! Flat positions: output pixel `(r, c)` of an image sits at `q = r * W + c` (the input's
//! row stride), so tap `k = (ci * kh + i) * kw + j` reads input `q + offset[k]` with
//! `offset[k] = ci * H * W + i * W + j`, whatever `q` is.
//!
//! A tile is [`MR`] output channels x [`NC`] positions: per tap, 2 unaligned loads of `x`,
//! `MR` broadcast weights, `2 MR` FMAs into 12 registers. Weights are packed once per
//! call into panels `[K, MR]`; taps are cut into blocks of [`KC`] so that a panel's block
//! stays in L1 while the tiles of a work block sweep it (partial sums of the work block's
//! tiles wait in a small buffer between tap blocks). Bias starts the sums; ReLU is
//! applied on the way out.
//!
//! Tiles follow output rows (full tiles, then the row's remainder as a half tile of 8 or
//! a full tile shifted left to end at the row's end) when rows are long enough
//! ([`by_rows`]); otherwise they run over flat positions `q < Q = (Ho - 1) * W + Wo`,
//! computing and dropping the `kw - 1` columns past `Wo` of each row (the last tile
//! shifted left to end at `Q`). Layers need `Q >= NC` ([`applies`]); smaller ones keep the
//! im2col path. Threads take runs of up to [`BLOCK_TILES`] tiles of one image; a tile that
//! overlaps its neighbour stays in its neighbour's run.

use super::im2col::Geom;
use crate::cpu::{avx2_fma_available as available, SharedMut};
use rayon::prelude::*;

/// Output channels per tile.
pub(crate) const MR: usize = 6;
/// Output positions per tile (two 8-lane vectors).
pub(crate) const NC: usize = 16;
/// Taps per block: a panel's block (`KC x MR` floats, 6 KiB) and the input lines a tile
/// reads for them stay in L1 (128 and 512 measured no better on the paper's 5x5 layers).
const KC: usize = 256;
/// Most tiles per work block.
const BLOCK_TILES: usize = 32;
/// Work blocks wanted per thread, for load balance.
const BLOCKS_PER_THREAD: usize = 8;
/// Relative speed of a half tile (6 accumulators, where the FMA units want 8 chains).
const HALF_EFFICIENCY: f64 = 0.75;
/// Relative speed assumed for flat tiles (scattered stores of tiles that cross rows) in
/// [`by_rows`].
const SCATTER_EFFICIENCY: f64 = 0.8;

/// Flat positions per image that hold outputs: `Q = (Ho - 1) * W + Wo`.
pub(crate) fn flat_len(g: &Geom) -> usize {
    (g.ho() - 1) * g.w + g.wo()
}

/// Input offset of every tap, `k = (ci * kh + i) * kw + j`.
pub(crate) fn tap_offsets(g: &Geom) -> Vec<usize> {
    (0..g.cin)
        .flat_map(|ci| {
            (0..g.kh).flat_map(move |i| (0..g.kw).map(move |j| ci * g.hw() + i * g.w + j))
        })
        .collect()
}

/// Bytes of a cache line: packed weights start on one, so that the kernels' 32-byte
/// vector loads of a panel never straddle two lines (glibc's blocks start 16 bytes off
/// one; no speed difference was measurable on the development machine, whose speed
/// wanders more than that).
const LINE: usize = 64;

/// A zeroed `f32` buffer that starts on a cache line.
pub(crate) struct LineAligned {
    buf: Vec<f32>,
    off: usize,
    len: usize,
}

impl LineAligned {
    pub(crate) fn zeros(len: usize) -> Self {
        let lanes = LINE / std::mem::size_of::<f32>();
        let buf = vec![0f32; len + lanes];
        let off = (LINE - buf.as_ptr() as usize % LINE) % LINE / std::mem::size_of::<f32>();
        Self { buf, off, len }
    }
}

impl std::ops::Deref for LineAligned {
    type Target = [f32];
    fn deref(&self) -> &[f32] {
        &self.buf[self.off..self.off + self.len]
    }
}

impl std::ops::DerefMut for LineAligned {
    fn deref_mut(&mut self) -> &mut [f32] {
        &mut self.buf[self.off..self.off + self.len]
    }
}

/// Whether [`forward`] can run this layer (f32 callers only): the CPU has AVX2 and FMA
/// and an image holds at least one tile. `plan.rs` chooses among the kernels that can.
pub(crate) fn applies(g: &Geom) -> bool {
    available() && flat_len(g) >= NC
}

/// Weights `[Cout, K]` as panels of `width` output channels, each `[K, width]` (the last
/// panel zero-padded), from a cache line on: the layout the tile kernels read.
pub(crate) fn pack(w: &[f32], cout: usize, k: usize, width: usize) -> LineAligned {
    let panels = cout.div_ceil(width);
    let mut p = LineAligned::zeros(panels * k * width);
    for co in 0..cout {
        let (panel, r) = (co / width, co % width);
        for kk in 0..k {
            p[(panel * k + kk) * width + r] = w[co * k + kk];
        }
    }
    p
}

/// A tile: flat input position `q` of its first output and, when its outputs are
/// consecutive in the output plane (one row), their offset there; `half` tiles (a row's
/// last few outputs) have 8 outputs instead of [`NC`].
#[derive(Clone, Copy)]
struct Tile {
    q: usize,
    out: Option<usize>,
    half: bool,
}

/// Columns of a row's tiles: full tiles from 0, then the remainder covered by a half
/// tile (up to 8 left) or a full tile shifted left, both ending at `Wo`.
fn row_tiles(wo: usize) -> impl Iterator<Item = (usize, bool)> {
    let full = wo / NC;
    let rem = wo % NC;
    let last = match rem {
        0 => None,
        1..=8 => Some((wo - NC / 2, true)),
        _ => Some((wo - NC, false)),
    };
    (0..full).map(|t| (t * NC, false)).chain(last)
}

/// Cost of a row in [`row_tiles`], in full-tile widths (a half tile runs at
/// [`HALF_EFFICIENCY`]).
fn row_cost(wo: usize) -> f64 {
    row_tiles(wo)
        .map(|(_, half)| if half { 0.5 / HALF_EFFICIENCY } else { 1.0 })
        .sum::<f64>()
        * NC as f64
}

/// Whether tiles follow output rows (each row cut into tiles, the last one shifted left
/// to end at the row's end) rather than flat positions. Rows waste the overlap of their
/// last tile, flat positions the `kw - 1` columns past `Wo` and a slower scattered store
/// for tiles that cross a row; rows win unless the overlap is large.
fn by_rows(g: &Geom) -> bool {
    let wo = g.wo();
    let rows = wo as f64 / row_cost(wo);
    let flat = wo as f64 / g.w as f64 * SCATTER_EFFICIENCY;
    wo >= NC && rows >= flat
}

/// Work blocks, each a list of tiles of one image (`(image, tiles)`): whole output rows
/// ([`by_rows`]) or runs of flat positions, about [`BLOCK_TILES`] tiles each and at least
/// [`BLOCKS_PER_THREAD`] per thread when the work allows.
fn blocks(g: &Geom) -> Vec<(usize, Vec<Tile>)> {
    let (w, wo, q) = (g.w, g.wo(), flat_len(g));
    let want = rayon::current_num_threads() * BLOCKS_PER_THREAD;
    let flat_tile = |q: usize| Tile {
        q,
        out: (q % w + NC <= wo).then(|| q / w * wo + q % w),
        half: false,
    };
    // Tiles of one image, in order, and how many make a block.
    let image: Vec<Tile> = if by_rows(g) {
        (0..g.ho())
            .flat_map(|r| {
                row_tiles(wo).map(move |(c, half)| Tile {
                    q: r * w + c,
                    out: Some(r * wo + c),
                    half,
                })
            })
            .collect()
    } else {
        (0..q.div_ceil(NC))
            .map(|t| flat_tile((t * NC).min(q - NC)))
            .collect()
    };
    // Tiles that may overlap: a row's last two, or (flat) an image's last two.
    let per_row = if by_rows(g) {
        row_tiles(wo).count()
    } else {
        image.len()
    };
    let per = (image.len().min((g.n * image.len()).div_ceil(want))).clamp(1, BLOCK_TILES);
    let mut out = Vec::new();
    if per_row > per {
        // Long rows (or flat images) are cut into runs of tiles; the last tile may overlap
        // the one before it, so the two stay in one run (one thread writes their outputs).
        for n in 0..g.n {
            for row in image.chunks(per_row) {
                let mut runs: Vec<&[Tile]> = row.chunks(per).collect();
                if runs.len() > 1 && runs[runs.len() - 1].len() < 2 {
                    let tail = runs.len() - 2;
                    runs[tail] = &row[tail * per..];
                    runs.pop();
                }
                out.extend(runs.into_iter().map(|r| (n, r.to_vec())));
            }
        }
    } else {
        // Blocks of whole rows.
        let per = per.div_ceil(per_row) * per_row;
        for n in 0..g.n {
            out.extend(image.chunks(per).map(|c| (n, c.to_vec())));
        }
    }
    out
}

/// `y = act(conv(x, w) + b)`, as [`super::kernels::forward`]; call only when
/// [`applies`] holds.
pub(crate) fn forward(g: &Geom, x: &[f32], w: &[f32], b: &[f32], relu: bool) -> Vec<f32> {
    let (k, p, cout, wo) = (g.k(), g.p(), g.cout, g.wo());
    let offsets = tap_offsets(g);
    let wp = pack(w, cout, k, MR);
    let len = g.n * cout * p;
    // Every output is written below (all blocks, panels and tiles) before `set_len`.
    let mut y = Vec::<f32>::with_capacity(len);
    let yp = SharedMut(y.as_mut_ptr());
    blocks(g).into_par_iter().for_each(|(n, tiles)| {
        // Partial sums per tile only between tap blocks; with one block, one scratch tile
        // serves the tiles whose outputs are scattered.
        let multi = k > KC;
        let mut partial = vec![[[0f32; NC]; MR]; if multi { tiles.len() } else { 1 }];
        let x_img = &x[n * g.cin * g.hw()..(n + 1) * g.cin * g.hw()];
        for panel in 0..cout.div_ceil(MR) {
            let mr = (cout - panel * MR).min(MR);
            let wpp = &wp[panel * k * MR..][..k * MR];
            let bias = &b[panel * MR..][..mr];
            let plane = |r: usize| (n * cout + panel * MR + r) * p;
            for k0 in (0..k).step_by(KC) {
                let k1 = (k0 + KC).min(k);
                let (first, last) = (k0 == 0, k1 == k);
                for (t, tile) in tiles.iter().enumerate() {
                    let part = &mut partial[if multi { t } else { 0 }];
                    // The last tap block of a tile with consecutive outputs stores them.
                    let end = match tile.out {
                        Some(o) if last => End::Store {
                            y: yp.get().wrapping_add(plane(0) + o),
                            stride: p,
                            relu,
                        },
                        _ => End::Partial,
                    };
                    let start = if first {
                        Start::Bias(bias)
                    } else {
                        Start::Partial
                    };
                    // SAFETY: `applies` checked the CPU; loads end at q + NC - 1 +
                    // offsets[k - 1] <= Q - 1 + offsets[K - 1] < C_in * H * W (valid
                    // convolution), inside the image's slice; stores go to this block's
                    // outputs (blocks are disjoint), `NC` of them in each plane.
                    unsafe {
                        let src = x_img.as_ptr().add(tile.q);
                        let (offs, w) = (&offsets[k0..k1], &wpp[k0 * MR..k1 * MR]);
                        tile_dispatch(mr, tile.half, offs, src, w, start, end, part);
                    }
                    if last && matches!(end, End::Partial) {
                        if relu {
                            part.iter_mut().flatten().for_each(|v| *v = v.max(0.0));
                        }
                        for (r, row) in part.iter().enumerate().take(mr) {
                            // SAFETY: as above; indices are < p within the plane.
                            unsafe { scatter(row, tile.q, g.w, wo, yp.get().add(plane(r))) };
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

/// Writes a tile row (flat positions `q .. q + NC`) to an output plane `[Ho, Wo]`,
/// dropping the positions past `Wo` in their row.
///
/// # Safety
/// `plane` addresses a whole output plane that no other thread writes at these pixels.
unsafe fn scatter(row: &[f32; NC], q: usize, w: usize, wo: usize, plane: *mut f32) {
    let mut l = 0;
    while l < NC {
        let (r, c) = ((q + l) / w, (q + l) % w);
        let run = (w - c).min(NC - l);
        let dst = plane.add(r * wo + c);
        for (i, &v) in row[l..l + run.min(wo.saturating_sub(c))].iter().enumerate() {
            *dst.add(i) = v;
        }
        l += run;
    }
}

/// Where a tile's sums start: the bias, or the partial sums of earlier tap blocks.
#[derive(Clone, Copy)]
enum Start<'a> {
    Bias(&'a [f32]),
    Partial,
}

/// Where they go: back to the partial sums, or (last tap block, one output run) to the
/// output rows `y + r * stride`, through the ReLU when `relu`.
#[derive(Clone, Copy)]
enum End {
    Partial,
    Store {
        y: *mut f32,
        stride: usize,
        relu: bool,
    },
}

/// `y[r * stride + 0..NC] = act(bias[r] + sum_k wp[k * MR + r] * x[offsets[k] + 0..NC])`
/// for `r < mr`: one whole tile, all taps at once (the fused chains of `chain.rs`).
///
/// # Safety
/// AVX2 and FMA present ([`available`]); `x + offsets[k] + NC` in bounds for every `k`;
/// `wp` holds `offsets.len() * MR` values; `bias` holds `mr`; `y + r * stride + NC` in
/// bounds for `r < mr` and not accessed by another thread.
#[allow(clippy::too_many_arguments)]
pub(crate) unsafe fn store_tile(
    mr: usize,
    offsets: &[usize],
    x: *const f32,
    wp: &[f32],
    bias: &[f32],
    y: *mut f32,
    stride: usize,
    relu: bool,
) {
    let mut unused = [[0f32; NC]; MR];
    let end = End::Store { y, stride, relu };
    tile_dispatch(
        mr,
        false,
        offsets,
        x,
        wp,
        Start::Bias(bias),
        end,
        &mut unused,
    );
}

/// Adds one tap block to a tile's sums, for `mr` (1..=MR) output channels and 8
/// (`half`) or [`NC`] outputs.
///
/// # Safety
/// See [`avx2::tile`].
#[allow(clippy::too_many_arguments)]
unsafe fn tile_dispatch(
    mr: usize,
    half: bool,
    offsets: &[usize],
    x: *const f32,
    wp: &[f32],
    start: Start,
    end: End,
    part: &mut [[f32; NC]; MR],
) {
    #[cfg(target_arch = "x86_64")]
    {
        macro_rules! go {
            ($($m:literal),*) => {
                match (mr, half) {
                    $(($m, false) => avx2::tile::<$m, 2>(offsets, x, wp, start, end, part),
                      ($m, true) => avx2::tile::<$m, 1>(offsets, x, wp, start, end, part),)*
                    _ => {}
                }
            };
        }
        go!(1, 2, 3, 4, 5, 6)
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (mr, half, offsets, x, wp, start, end, part);
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{End, Start, MR, NC};
    use std::arch::x86_64::*;

    /// `sums[r][0..8 V] = start[r] + sum_k wp[k * MR + r] * x[offsets[k] + 0..8 V]` for
    /// `r < R`, written to `end` (`V` = 1 or 2 vectors of 8).
    ///
    /// # Safety
    /// AVX2 and FMA present; `x + offsets[k] + 8 V` in bounds for every `k`; `wp` holds
    /// `offsets.len() * MR` values; a `Bias` holds `R`; a `Store` addresses `R` rows of
    /// `8 V` outputs that no other thread accesses.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn tile<const R: usize, const V: usize>(
        offsets: &[usize],
        x: *const f32,
        wp: &[f32],
        start: Start,
        end: End,
        part: &mut [[f32; NC]; MR],
    ) {
        const { assert!(NC == 16 && R <= MR && V >= 1 && V <= 2) };
        let mut acc = [[_mm256_setzero_ps(); V]; R];
        for (r, a) in acc.iter_mut().enumerate() {
            for (v, av) in a.iter_mut().enumerate() {
                *av = match start {
                    Start::Bias(b) => _mm256_set1_ps(b[r]),
                    Start::Partial => _mm256_loadu_ps(part[r].as_ptr().add(8 * v)),
                };
            }
        }
        let w = wp.as_ptr();
        for (kk, &o) in offsets.iter().enumerate() {
            let mut xv = [_mm256_setzero_ps(); V];
            for (v, xv) in xv.iter_mut().enumerate() {
                *xv = _mm256_loadu_ps(x.add(o + 8 * v));
            }
            let wk = w.add(kk * MR);
            for (r, a) in acc.iter_mut().enumerate() {
                let s = _mm256_broadcast_ss(&*wk.add(r));
                for (av, &xv) in a.iter_mut().zip(&xv) {
                    *av = _mm256_fmadd_ps(s, xv, *av);
                }
            }
        }
        match end {
            End::Partial => {
                for (a, p) in acc.iter().zip(part.iter_mut()) {
                    for (v, &av) in a.iter().enumerate() {
                        _mm256_storeu_ps(p.as_mut_ptr().add(8 * v), av);
                    }
                }
            }
            End::Store { y, stride, relu } => {
                let zero = _mm256_setzero_ps();
                for (r, a) in acc.iter().enumerate() {
                    for (v, &av) in a.iter().enumerate() {
                        let av = if relu { _mm256_max_ps(av, zero) } else { av };
                        _mm256_storeu_ps(y.add(r * stride + 8 * v), av);
                    }
                }
            }
        }
    }
}
