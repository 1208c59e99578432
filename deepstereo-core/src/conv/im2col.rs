//! Work planning, im2col / col2im, and the single-threaded gemm call behind the kernels.
//!
//! Column space: output pixel `p` of image `n` is column `n * P + p` (`P = Ho * Wo`), so the
//! convolution is `Y [Cout, N*P] = W [Cout, K] x cols [K, N*P]` with `K = Cin * kh * kw`.
//! That product is cut into [`Chunk`]s of whole images or of output rows of one image.

use crate::cpu::SharedMut;
use candle_core::WithDType;
use gemm::{gemm, Parallelism};
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Bytes of one chunk's im2col buffer (`K x cols`), about the L2 cache of one core.
const CHUNK_BYTES: usize = 1 << 20;
/// Fewest columns in a chunk, so that gemm calls stay efficient.
const MIN_COLS: usize = 128;
/// Chunks wanted per thread (for load balance), when the work allows it.
const CHUNKS_PER_THREAD: usize = 4;

/// Shapes of one convolution (valid padding, stride 1): x `[n, cin, h, w]`,
/// weight `[cout, cin, kh, kw]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Geom {
    pub n: usize,
    pub cin: usize,
    pub h: usize,
    pub w: usize,
    pub cout: usize,
    pub kh: usize,
    pub kw: usize,
}

impl Geom {
    /// The input gradient's convolution: `gy` padded to `[n, cout, h + kh - 1, w + kw - 1]`
    /// (1x1: not padded) -> `[n, cin, h, w]`.
    pub(crate) fn transposed(&self) -> Geom {
        Geom {
            n: self.n,
            cin: self.cout,
            h: if self.direct() {
                self.h
            } else {
                self.h + self.kh - 1
            },
            w: if self.direct() {
                self.w
            } else {
                self.w + self.kw - 1
            },
            cout: self.cin,
            kh: self.kh,
            kw: self.kw,
        }
    }

    pub fn ho(&self) -> usize {
        self.h + 1 - self.kh
    }
    pub fn wo(&self) -> usize {
        self.w + 1 - self.kw
    }
    pub fn p(&self) -> usize {
        self.ho() * self.wo()
    }
    pub fn k(&self) -> usize {
        self.cin * self.kh * self.kw
    }
    pub fn hw(&self) -> usize {
        self.h * self.w
    }
    /// 1x1 kernels need no im2col: gemm reads `x` and writes `dx` in place.
    pub fn direct(&self) -> bool {
        self.kh == 1 && self.kw == 1
    }
}

/// Output columns handled together: images `n0..n1` whole, or output rows `r0..r1` of image
/// `n0` (then `n1 = n0 + 1`). `phase` 1 marks odd row chunks of an image: chunks of one
/// phase never touch the same input pixels (row chunks have at least `kh` rows).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Chunk {
    pub n0: usize,
    pub n1: usize,
    pub r0: usize,
    pub r1: usize,
    pub phase: usize,
}

impl Chunk {
    pub fn cols(&self, g: &Geom) -> usize {
        (self.n1 - self.n0) * self.cols_per_image(g)
    }
    pub fn cols_per_image(&self, g: &Geom) -> usize {
        (self.r1 - self.r0) * g.wo()
    }
}

/// Cuts the column space into chunks of about [`CHUNK_BYTES`] of im2col (whole images up to
/// 1.5 times that), and at least [`CHUNKS_PER_THREAD`] per thread when there are enough
/// columns.
pub(crate) fn plan(g: &Geom, elem_bytes: usize) -> Vec<Chunk> {
    let (p, ho) = (g.p(), g.ho());
    let want = rayon::current_num_threads() * CHUNKS_PER_THREAD;
    let target = (CHUNK_BYTES / elem_bytes / g.k())
        .min((g.n * p).div_ceil(want))
        .max(MIN_COLS);
    let mut chunks = Vec::new();
    if 2 * p <= 3 * target {
        let group = (target / p).max(1);
        for n0 in (0..g.n).step_by(group) {
            chunks.push(Chunk {
                n0,
                n1: (n0 + group).min(g.n),
                r0: 0,
                r1: ho,
                phase: 0,
            });
        }
    } else {
        // Rows split evenly; at least kh rows so that chunks two apart never overlap.
        let rows = ho.div_ceil(p.div_ceil(target)).max(g.kh);
        for n0 in 0..g.n {
            for (i, r0) in (0..ho).step_by(rows).enumerate() {
                chunks.push(Chunk {
                    n0,
                    n1: n0 + 1,
                    r0,
                    r1: (r0 + rows).min(ho),
                    phase: i % 2,
                });
            }
        }
    }
    chunks
}

/// Runs `f` over `chunks` on all rayon threads. Consecutive chunks form `blocks` blocks
/// that threads take one at a time; `f` gets its thread's scratch state and its block's
/// accumulator. Returns the accumulators in block order, so that sums over them do not
/// depend on the schedule (gradients are deterministic for a given thread count).
pub(crate) fn for_each_chunk<S, A: Send>(
    chunks: &[Chunk],
    blocks: usize,
    scratch: impl Fn() -> S + Sync,
    acc: impl Fn() -> A + Sync,
    f: impl Fn(&mut S, &mut A, &Chunk) + Sync,
) -> Vec<A> {
    let blocks = blocks.clamp(1, chunks.len().max(1));
    let next = AtomicUsize::new(0);
    let threads = rayon::current_num_threads().min(blocks);
    let mut done: Vec<(usize, A)> = (0..threads)
        .into_par_iter()
        .flat_map_iter(|_| {
            let (mut state, mut done) = (scratch(), Vec::new());
            loop {
                let b = next.fetch_add(1, Ordering::Relaxed);
                if b >= blocks {
                    return done;
                }
                let mut a = acc();
                let range = b * chunks.len() / blocks..(b + 1) * chunks.len() / blocks;
                chunks[range].iter().for_each(|c| f(&mut state, &mut a, c));
                done.push((b, a));
            }
        })
        .collect();
    done.sort_by_key(|(b, _)| *b);
    done.into_iter().map(|(_, a)| a).collect()
}

/// Blocks for [`for_each_chunk`] when their accumulators are summed.
pub(crate) fn reduction_blocks() -> usize {
    rayon::current_num_threads() * CHUNKS_PER_THREAD
}

/// `dst := (dst if accumulate) + lhs x rhs`, single-threaded; `(m, n, k)` and strides in
/// elements as (row stride, column stride).
///
/// # Safety
/// Pointers and strides must address `m x k`, `k x n` and `m x n` matrices in bounds, and
/// no other thread may access `dst`'s elements meanwhile.
pub(crate) unsafe fn matmul<T: WithDType>(
    (m, n, k): (usize, usize, usize),
    (dst, dst_rs, dst_cs): (*mut T, usize, usize),
    accumulate: bool,
    (lhs, lhs_rs, lhs_cs): (*const T, usize, usize),
    (rhs, rhs_rs, rhs_cs): (*const T, usize, usize),
) {
    let (zero, one) = (T::from_f64(0.0), T::from_f64(1.0));
    let alpha = if accumulate { one } else { zero };
    let s = |v: usize| v as isize;
    gemm(
        m,
        n,
        k,
        dst,
        s(dst_cs),
        s(dst_rs),
        accumulate,
        lhs,
        s(lhs_cs),
        s(lhs_rs),
        rhs,
        s(rhs_cs),
        s(rhs_rs),
        alpha,
        one,
        false,
        false,
        false,
        Parallelism::None,
    );
}

/// Calls `f(k, column offset in the chunk, offset in x, length)` for every contiguous
/// run that im2col copies: row `k = (ci*kh + i)*kw + j` of the chunk's cols holds
/// `x[n, ci, r + i, j .. j + Wo]` for the chunk's images `n` and output rows `r`.
fn runs(g: &Geom, c: &Chunk, mut f: impl FnMut(usize, usize, usize, usize)) {
    let (wo, hw, rows) = (g.wo(), g.hw(), c.r1 - c.r0);
    for n in c.n0..c.n1 {
        let base = (n - c.n0) * rows * wo;
        for ci in 0..g.cin {
            let xc = (n * g.cin + ci) * hw;
            for i in 0..g.kh {
                for j in 0..g.kw {
                    let k = (ci * g.kh + i) * g.kw + j;
                    if g.kw == 1 {
                        // Wo == W: the rows are one contiguous run.
                        f(k, base, xc + (c.r0 + i) * g.w, rows * wo);
                    } else {
                        for r in 0..rows {
                            f(k, base + r * wo, xc + (c.r0 + r + i) * g.w + j, wo);
                        }
                    }
                }
            }
        }
    }
}

/// The chunk's columns `[K, cols]` from `x` into `buf`.
pub(crate) fn im2col<T: WithDType>(g: &Geom, c: &Chunk, x: &[T], buf: &mut Vec<T>) {
    let cols = c.cols(g);
    buf.resize(g.k() * cols, T::from_f64(0.0));
    runs(g, c, |k, col, xo, len| {
        buf[k * cols + col..][..len].copy_from_slice(&x[xo..][..len]);
    });
}

/// Adds the chunk's columns `[K, cols]` in `buf` onto the input gradient `dx`.
///
/// # Safety
/// `dx` must hold the whole input; no other thread may touch the pixels this chunk reads.
pub(crate) unsafe fn col2im<T: WithDType>(g: &Geom, c: &Chunk, buf: &[T], dx: SharedMut<T>) {
    let cols = c.cols(g);
    runs(g, c, |k, col, xo, len| {
        let dst = std::slice::from_raw_parts_mut(dx.get().add(xo), len);
        for (d, s) in dst.iter_mut().zip(&buf[k * cols + col..][..len]) {
            *d += *s;
        }
    });
}
