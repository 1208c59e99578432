//! Chunked im2col + gemm kernels behind [`super::Conv2d`] (the design is in the module doc).
//!
//! Column space: output pixel `p` of image `n` is column `n * P + p` (`P = Ho * Wo`), so the
//! convolution is `Y [Cout, N*P] = W [Cout, K] x cols [K, N*P]` with `K = Cin * kh * kw`.
//! That product is cut into [`Chunk`]s of whole images or of output rows of one image;
//! each chunk's im2col, gemm and scatter run on one thread in buffers that fit in L2.

use candle_core::WithDType;
use gemm::{gemm, Parallelism};
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Bytes of one chunk's im2col buffer (`K x cols`); the cores' L2 holds 1 MiB each.
const CHUNK_BYTES: usize = 384 << 10;
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
    pub fn ho(&self) -> usize {
        self.h + 1 - self.kh
    }
    pub fn wo(&self) -> usize {
        self.w + 1 - self.kw
    }
    fn p(&self) -> usize {
        self.ho() * self.wo()
    }
    fn k(&self) -> usize {
        self.cin * self.kh * self.kw
    }
    fn hw(&self) -> usize {
        self.h * self.w
    }
}

/// Output columns handled together: images `n0..n1` whole, or output rows `r0..r1` of image
/// `n0` (then `n1 = n0 + 1`). `phase` 1 marks odd row chunks of an image: chunks of one
/// phase never touch the same input pixels (row chunks have at least `kh` rows).
#[derive(Clone, Copy, Debug)]
struct Chunk {
    n0: usize,
    n1: usize,
    r0: usize,
    r1: usize,
    phase: usize,
}

impl Chunk {
    fn cols(&self, g: &Geom) -> usize {
        (self.n1 - self.n0) * (self.r1 - self.r0) * g.wo()
    }
}

/// Cuts the column space into chunks. `direct`: a 1x1 kernel whose chunks all lie in one
/// image, so gemm reads `x` (and writes the input gradient) in place without im2col.
fn plan(g: &Geom, elem_bytes: usize) -> (Vec<Chunk>, bool) {
    let (p, ho) = (g.p(), g.ho());
    let want = rayon::current_num_threads() * CHUNKS_PER_THREAD;
    let cb = std::env::var("CONV_CB").ok().and_then(|v| v.parse().ok()).unwrap_or(CHUNK_BYTES);
    let mc = std::env::var("CONV_MC").ok().and_then(|v| v.parse().ok()).unwrap_or(MIN_COLS);
    let target = (cb / elem_bytes / g.k()).min((g.n * p).div_ceil(want)).max(mc);
    let mut chunks = Vec::new();
    if p <= target {
        let group = (target / p).max(1);
        for n0 in (0..g.n).step_by(group) {
            let (n1, phase) = ((n0 + group).min(g.n), 0);
            chunks.push(Chunk { n0, n1, r0: 0, r1: ho, phase });
        }
    } else {
        let rows = (target / g.wo()).max(g.kh).max(1);
        for n0 in 0..g.n {
            for (i, r0) in (0..ho).step_by(rows).enumerate() {
                let r1 = (r0 + rows).min(ho);
                chunks.push(Chunk { n0, n1: n0 + 1, r0, r1, phase: i % 2 });
            }
        }
    }
    let direct = g.kh == 1 && g.kw == 1 && chunks.iter().all(|c| c.n1 - c.n0 == 1);
    (chunks, direct)
}

/// Runs `f` over `chunks` on all rayon threads (dynamic schedule), one state per thread.
fn for_each_chunk<S: Send>(
    chunks: &[Chunk],
    init: impl Fn() -> S + Sync,
    f: impl Fn(&mut S, &Chunk) + Sync,
) -> Vec<S> {
    let next = AtomicUsize::new(0);
    let threads = rayon::current_num_threads().min(chunks.len()).max(1);
    (0..threads)
        .into_par_iter()
        .map(|_| {
            let mut state = init();
            loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                match chunks.get(i) {
                    Some(c) => f(&mut state, c),
                    None => return state,
                }
            }
        })
        .collect()
}

/// A pointer shared by threads that write disjoint parts of its buffer.
#[derive(Clone, Copy)]
struct SharedMut<T>(*mut T);
unsafe impl<T> Send for SharedMut<T> {}
unsafe impl<T> Sync for SharedMut<T> {}

impl<T> SharedMut<T> {
    fn get(self) -> *mut T {
        self.0
    }
}

/// `dst := beta * dst + lhs x rhs` (`beta` 0 or 1), single-threaded; strides in elements
/// as (row stride, column stride).
///
/// # Safety
/// Pointers and strides must address `m x k`, `k x n` and `m x n` matrices in bounds,
/// and no other thread may access `dst`'s elements meanwhile.
#[allow(clippy::too_many_arguments)]
unsafe fn matmul<T: WithDType>(
    (m, n, k): (usize, usize, usize),
    dst: *mut T,
    dst_rs: usize,
    accumulate: bool,
    lhs: *const T,
    (lhs_rs, lhs_cs): (usize, usize),
    rhs: *const T,
    (rhs_rs, rhs_cs): (usize, usize),
) {
    let (zero, one) = (T::from_f64(0.0), T::from_f64(1.0));
    let alpha = if accumulate { one } else { zero };
    gemm(
        m, n, k, dst, 1, dst_rs as isize, accumulate, lhs, lhs_cs as isize, lhs_rs as isize,
        rhs, rhs_cs as isize, rhs_rs as isize, alpha, one, false, false, false, Parallelism::None,
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
fn im2col<T: WithDType>(g: &Geom, c: &Chunk, x: &[T], buf: &mut Vec<T>) {
    let cols = c.cols(g);
    buf.resize(g.k() * cols, T::from_f64(0.0));
    runs(g, c, |k, col, xo, len| {
        buf[k * cols + col..][..len].copy_from_slice(&x[xo..][..len]);
    });
}

/// Adds the chunk's columns `[K, cols]` in `buf` back onto the image gradient `dx`.
///
/// # Safety
/// No other thread may touch the input pixels that this chunk reads.
unsafe fn col2im<T: WithDType>(g: &Geom, c: &Chunk, buf: &[T], dx: SharedMut<T>) {
    let cols = c.cols(g);
    runs(g, c, |k, col, xo, len| {
        let dst = std::slice::from_raw_parts_mut(dx.get().add(xo), len);
        for (d, s) in dst.iter_mut().zip(&buf[k * cols + col..][..len]) {
            *d += *s;
        }
    });
}

/// Forward: `y = act(conv(x, w) + b)` with `act` ReLU or identity; `y` is
/// `[n, cout, Ho, Wo]`, contiguous.
pub(crate) fn forward<T: WithDType>(g: &Geom, x: &[T], w: &[T], b: &[T], relu: bool) -> Vec<T> {
    let (chunks, direct) = plan(g, std::mem::size_of::<T>());
    let (k, p, wo, cout, hw) = (g.k(), g.p(), g.wo(), g.cout, g.hw());
    let zero = T::from_f64(0.0);
    let mut y = vec![zero; g.n * cout * p];
    let yp = SharedMut(y.as_mut_ptr());
    let act = |v: T| if relu && v < zero { zero } else { v };
    for_each_chunk(&chunks, || (Vec::new(), Vec::new()), |(buf, tmp), c| {
        let cols = c.cols(g);
        let single = c.n1 - c.n0 == 1;
        let (rhs, rhs_rs) = if direct {
            (x[c.n0 * g.cin * hw + c.r0 * g.w..].as_ptr(), hw)
        } else {
            im2col(g, c, x, buf);
            (buf.as_ptr(), cols)
        };
        // SAFETY: chunks cover disjoint columns of y; shapes follow Geom.
        unsafe {
            let (dst, dst_rs) = if single {
                (yp.get().add(c.n0 * cout * p + c.r0 * wo), p)
            } else {
                tmp.resize(cout * cols, zero);
                (tmp.as_mut_ptr(), cols)
            };
            matmul((cout, cols, k), dst, dst_rs, false, w.as_ptr(), (k, 1), rhs, (rhs_rs, 1));
            for (co, &bias) in b.iter().enumerate() {
                if single {
                    let row = std::slice::from_raw_parts_mut(dst.add(co * p), cols);
                    row.iter_mut().for_each(|v| *v = act(*v + bias));
                } else {
                    for n in c.n0..c.n1 {
                        let src = &tmp[co * cols + (n - c.n0) * p..][..p];
                        let row = std::slice::from_raw_parts_mut(yp.get().add((n * cout + co) * p), p);
                        row.iter_mut().zip(src).for_each(|(v, &s)| *v = act(s + bias));
                    }
                }
            }
        }
    });
    y
}

static PROBE: [std::sync::atomic::AtomicU64; 5] = [const { std::sync::atomic::AtomicU64::new(0) }; 5];
/// Gradients of [`forward`]; `dx` only when asked for, `dw` zero when not asked for.
pub(crate) struct Grads<T> {
    pub dx: Option<Vec<T>>,
    pub dw: Vec<T>,
    pub db: Vec<T>,
}

/// Backward of [`forward`] from `dy` (`[n, cout, Ho, Wo]`); `y` is forward's output, read
/// only with `relu` (its ReLU mask).
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward<T: WithDType>(
    g: &Geom,
    x: &[T],
    w: &[T],
    y: &[T],
    dy: &[T],
    relu: bool,
    need_dx: bool,
    need_dw: bool,
) -> Grads<T> {
    let (chunks, direct) = plan(g, std::mem::size_of::<T>());
    let (k, p, wo, cout, hw) = (g.k(), g.p(), g.wo(), g.cout, g.hw());
    let zero = T::from_f64(0.0);
    let mut dx = need_dx.then(|| vec![zero; g.n * g.cin * hw]);
    let dxp = SharedMut(dx.as_mut().map_or(std::ptr::null_mut(), |v| v.as_mut_ptr()));
    // State per thread: (dw, db, cols buffer, masked dy buffer).
    let init = || (vec![zero; cout * k], vec![zero; cout], Vec::new(), Vec::new());
    let step = |(dw, db, buf, gy): &mut (Vec<T>, Vec<T>, Vec<T>, Vec<T>), c: &Chunk| {
        let (cols, rows) = (c.cols(g), c.r1 - c.r0);
        let tt = std::time::Instant::now();
        // Masked output gradient [cout, cols], and the bias gradient.
        gy.resize(cout * cols, zero);
        for n in c.n0..c.n1 {
            for (co, dbc) in db.iter_mut().enumerate() {
                let off = (n * cout + co) * p + c.r0 * wo;
                let dst = &mut gy[co * cols + (n - c.n0) * rows * wo..][..rows * wo];
                let src = &dy[off..][..rows * wo];
                if relu {
                    let mask = &y[off..][..rows * wo];
                    for ((d, &s), &m) in dst.iter_mut().zip(src).zip(mask) {
                        *d = if m > zero { s } else { zero };
                    }
                } else {
                    dst.copy_from_slice(src);
                }
                *dbc += dst.iter().fold(zero, |a, &v| a + v);
            }
        }
        let x0 = c.n0 * g.cin * hw + c.r0 * g.w;
        // SAFETY: shapes follow Geom; dx writes of concurrent chunks are disjoint (direct
        // chunks own their pixels, others run one phase at a time).
        unsafe {
            if need_dw {
                PROBE[0].fetch_add(tt.elapsed().as_nanos() as u64, Ordering::Relaxed);
                let tt = std::time::Instant::now();
                let (rhs, rhs_cs) = if direct {
                    (x[x0..].as_ptr(), hw)
                } else {
                    im2col(g, c, x, buf);
                    (buf.as_ptr(), cols)
                };
                PROBE[1].fetch_add(tt.elapsed().as_nanos() as u64, Ordering::Relaxed);
                let tt = std::time::Instant::now();
                // dw [cout, K] += gy [cout, cols] x cols^T [cols, K]
                matmul((cout, k, cols), dw.as_mut_ptr(), k, true, gy.as_ptr(), (cols, 1), rhs, (1, rhs_cs));
                PROBE[2].fetch_add(tt.elapsed().as_nanos() as u64, Ordering::Relaxed);
            }
            let tt = std::time::Instant::now();
            if need_dx {
                // dcols [K, cols] = w^T [K, cout] x gy [cout, cols]
                let (dst, dst_rs) = if direct {
                    (dxp.get().add(x0), hw)
                } else {
                    buf.resize(k * cols, zero);
                    (buf.as_mut_ptr(), cols)
                };
                matmul((k, cols, cout), dst, dst_rs, false, w.as_ptr(), (1, k), gy.as_ptr(), (cols, 1));
                PROBE[3].fetch_add(tt.elapsed().as_nanos() as u64, Ordering::Relaxed);
                let tt = std::time::Instant::now();
                if !direct {
                    col2im(g, c, buf, dxp);
                }
                PROBE[4].fetch_add(tt.elapsed().as_nanos() as u64, Ordering::Relaxed);
            }
        }
    };
    let t0 = std::time::Instant::now();
    let mut states = Vec::new();
    if need_dx && !direct {
        for phase in 0..2 {
            let part: Vec<Chunk> = chunks.iter().filter(|c| c.phase == phase).copied().collect();
            states.extend(for_each_chunk(&part, &init, &step));
        }
    } else {
        states = for_each_chunk(&chunks, &init, &step);
    }
    let (mut dw, mut db) = (vec![zero; cout * k], vec![zero; cout]);
    for (sw, sb, _, _) in &states {
        dw.iter_mut().zip(sw).for_each(|(a, &v)| *a += v);
        db.iter_mut().zip(sb).for_each(|(a, &v)| *a += v);
    }
    if std::env::var("CONV_PROBE").is_ok() { eprintln!("kernels::backward {:?} chunks {} direct {direct} stages(ms, summed over threads) gather {:.1} im2col {:.1} gemm_dw {:.1} gemm_dcols {:.1} col2im {:.1}", t0.elapsed(), chunks.len(), PROBE[0].swap(0, Ordering::Relaxed) as f64*1e-6, PROBE[1].swap(0, Ordering::Relaxed) as f64*1e-6, PROBE[2].swap(0, Ordering::Relaxed) as f64*1e-6, PROBE[3].swap(0, Ordering::Relaxed) as f64*1e-6, PROBE[4].swap(0, Ordering::Relaxed) as f64*1e-6); }
    Grads { dx, dw, db }
}
