//! Forward and backward of the convolution on contiguous CPU buffers (the design is in
//! the module doc). Each [`Chunk`] runs on one thread: im2col into a buffer reused by that
//! thread, one gemm, then bias and ReLU (forward) or col2im (backward).

use super::im2col::{col2im, for_each_chunk, im2col, matmul, plan, reduction_blocks, Chunk, Geom};
use crate::cpu::SharedMut;
use candle_core::WithDType;

/// `dst = act(src + bias)` with `act` ReLU or identity.
fn bias_act<T: WithDType>(dst: &mut [T], src: Option<&[T]>, bias: T, relu: bool) {
    let zero = T::from_f64(0.0);
    let f = |v: T| {
        let v = v + bias;
        if relu && v < zero {
            zero
        } else {
            v
        }
    };
    match src {
        Some(src) => dst.iter_mut().zip(src).for_each(|(d, &s)| *d = f(s)),
        None => dst.iter_mut().for_each(|d| *d = f(*d)),
    }
}

/// Forward: `y = act(conv(x, w) + b)` with `act` ReLU or identity; `y` is
/// `[n, cout, Ho, Wo]`, contiguous.
pub(crate) fn forward<T: WithDType>(g: &Geom, x: &[T], w: &[T], b: &[T], relu: bool) -> Vec<T> {
    let chunks = plan(g, std::mem::size_of::<T>());
    let (k, p, wo, cout, cin, hw) = (g.k(), g.p(), g.wo(), g.cout, g.cin, g.hw());
    let zero = T::from_f64(0.0);
    let mut y = vec![zero; g.n * cout * p];
    let yp = SharedMut(y.as_mut_ptr());
    for_each_chunk(
        &chunks,
        chunks.len(),
        || (Vec::new(), Vec::new()),
        || (),
        |(buf, tmp), _, c| {
            let (cols, per) = (c.cols(g), c.cols_per_image(g));
            let lhs = (w.as_ptr(), k, 1);
            // The chunk's outputs of image n, channel co.
            let out = |n: usize, co: usize| unsafe {
                std::slice::from_raw_parts_mut(yp.get().add((n * cout + co) * p + c.r0 * wo), per)
            };
            // SAFETY: chunks cover disjoint outputs; offsets and strides follow Geom.
            unsafe {
                if g.direct() {
                    for n in c.n0..c.n1 {
                        let dst = (yp.get().add(n * cout * p + c.r0 * wo), p, 1);
                        let rhs = (x.as_ptr().add(n * cin * hw + c.r0 * g.w), hw, 1);
                        matmul((cout, per, k), dst, false, lhs, rhs);
                        (0..cout).for_each(|co| bias_act(out(n, co), None, b[co], relu));
                    }
                } else if c.n1 - c.n0 == 1 {
                    im2col(g, c, x, buf);
                    let dst = (yp.get().add(c.n0 * cout * p + c.r0 * wo), p, 1);
                    matmul((cout, cols, k), dst, false, lhs, (buf.as_ptr(), cols, 1));
                    (0..cout).for_each(|co| bias_act(out(c.n0, co), None, b[co], relu));
                } else {
                    im2col(g, c, x, buf);
                    tmp.resize(cout * cols, zero);
                    matmul(
                        (cout, cols, k),
                        (tmp.as_mut_ptr(), cols, 1),
                        false,
                        lhs,
                        (buf.as_ptr(), cols, 1),
                    );
                    for n in c.n0..c.n1 {
                        for co in 0..cout {
                            let src = &tmp[co * cols + (n - c.n0) * per..][..per];
                            bias_act(out(n, co), Some(src), b[co], relu);
                        }
                    }
                }
            }
        },
    );
    y
}

/// Gradients of [`forward`]; `dx` only when asked for, `dw` zero when not asked for.
pub(crate) struct Grads<T> {
    pub dx: Option<Vec<T>>,
    pub dw: Vec<T>,
    pub db: Vec<T>,
}

/// Scratch buffers of one thread in [`backward`].
struct Scratch<T> {
    /// im2col columns, then the columns' gradient.
    buf: Vec<T>,
    /// The chunk's output gradient `[cout, cols]`, ReLU-masked.
    gy: Vec<T>,
}

/// What a block of chunks accumulates in [`backward`].
struct Acc<T> {
    /// Weight gradient, transposed (`[K, cout]`): gemm then reads the im2col buffer
    /// without repacking it.
    dwt: Vec<T>,
    db: Vec<T>,
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
    let chunks = plan(g, std::mem::size_of::<T>());
    let (k, cout, cin, hw) = (g.k(), g.cout, g.cin, g.hw());
    let zero = T::from_f64(0.0);
    let mut dx = need_dx.then(|| vec![zero; g.n * cin * hw]);
    let dxp = SharedMut(dx.as_mut().map_or(std::ptr::null_mut(), |v| v.as_mut_ptr()));
    let scratch = || Scratch {
        buf: Vec::new(),
        gy: Vec::new(),
    };
    let acc = || Acc {
        dwt: vec![zero; k * cout],
        db: vec![zero; cout],
    };
    let step = |s: &mut Scratch<T>, a: &mut Acc<T>, c: &Chunk| {
        masked_gy(g, c, (y, dy, relu), &mut s.gy, &mut a.db);
        // SAFETY: offsets and strides follow Geom; concurrent chunks write disjoint parts
        // of dx (1x1 chunks own their pixels, other chunks run one phase at a time).
        unsafe {
            if need_dw {
                add_weight_grad(g, c, x, &s.gy, &mut s.buf, &mut a.dwt);
            }
            if need_dx {
                input_grad_chunk(g, c, w, &s.gy, &mut s.buf, dxp);
            }
        }
    };
    let run = |chunks: &[Chunk]| for_each_chunk(chunks, reduction_blocks(), scratch, acc, step);
    let accs = if need_dx && !g.direct() {
        let phase = |i: usize| {
            chunks
                .iter()
                .filter(|c| c.phase == i)
                .copied()
                .collect::<Vec<_>>()
        };
        let mut accs = run(&phase(0));
        accs.extend(run(&phase(1)));
        accs
    } else {
        run(&chunks)
    };
    let (dw, db) = sum_accumulators(&accs, k, cout);
    Grads { dx, dw, db }
}

/// The chunk's output gradient, ReLU-masked by `y` when `relu`, into `gy` (`[cout, cols]`),
/// each channel's sum added to `db` on the way.
fn masked_gy<T: WithDType>(
    g: &Geom,
    c: &Chunk,
    (y, dy, relu): (&[T], &[T], bool),
    gy: &mut Vec<T>,
    db: &mut [T],
) {
    let (p, wo, cout) = (g.p(), g.wo(), g.cout);
    let zero = T::from_f64(0.0);
    let (cols, per) = (c.cols(g), c.cols_per_image(g));
    gy.resize(cout * cols, zero);
    for n in c.n0..c.n1 {
        for co in 0..cout {
            let off = (n * cout + co) * p + c.r0 * wo;
            let dst = &mut gy[co * cols + (n - c.n0) * per..][..per];
            if relu {
                for ((d, &dv), &yv) in dst.iter_mut().zip(&dy[off..][..per]).zip(&y[off..][..per]) {
                    *d = if yv > zero { dv } else { zero };
                }
            } else {
                dst.copy_from_slice(&dy[off..][..per]);
            }
            db[co] += dst.iter().fold(zero, |a, &v| a + v);
        }
    }
}

/// `(pointer, row stride, column stride)` of image `n`'s columns of the chunk's `gy`.
fn gy_of<T>(gy: &[T], c: &Chunk, g: &Geom, n: usize) -> (*const T, usize, usize) {
    let (cols, per) = (c.cols(g), c.cols_per_image(g));
    (gy[(n - c.n0) * per..].as_ptr(), cols, 1)
}

/// `dw^T [K, cout] += cols [K, cols] x gy^T [cols, cout]`, as dw `[cout, K]` (1x1: the
/// columns are `x` itself; else im2col into `buf`).
///
/// # Safety
/// As [`matmul`]: `gy` holds the chunk's `[cout, cols]`, `dwt` `[K, cout]`.
unsafe fn add_weight_grad<T: WithDType>(
    g: &Geom,
    c: &Chunk,
    x: &[T],
    gy: &[T],
    buf: &mut Vec<T>,
    dwt: &mut [T],
) {
    let (k, cout, cin, hw) = (g.k(), g.cout, g.cin, g.hw());
    let (cols, per) = (c.cols(g), c.cols_per_image(g));
    let dst = (dwt.as_mut_ptr(), 1, cout);
    if g.direct() {
        for n in c.n0..c.n1 {
            let xt = (x.as_ptr().add(n * cin * hw + c.r0 * g.w), 1, hw);
            matmul((cout, k, per), dst, true, gy_of(gy, c, g, n), xt);
        }
    } else {
        im2col(g, c, x, buf);
        matmul(
            (cout, k, cols),
            dst,
            true,
            gy_of(gy, c, g, c.n0),
            (buf.as_ptr(), 1, cols),
        );
    }
}

/// `dcols [K, cols] = w^T [K, cout] x gy [cout, cols]`, written into `dx` (1x1) or into
/// `buf` and added to `dx` by col2im.
///
/// # Safety
/// As [`matmul`] and [`col2im`]: no other thread writes the chunk's part of `dx`.
unsafe fn input_grad_chunk<T: WithDType>(
    g: &Geom,
    c: &Chunk,
    w: &[T],
    gy: &[T],
    buf: &mut Vec<T>,
    dxp: SharedMut<T>,
) {
    let (k, cout, cin, hw) = (g.k(), g.cout, g.cin, g.hw());
    let (cols, per) = (c.cols(g), c.cols_per_image(g));
    let wt = (w.as_ptr(), 1, k);
    if g.direct() {
        for n in c.n0..c.n1 {
            let dst = (dxp.get().add(n * cin * hw + c.r0 * g.w), hw, 1);
            matmul((k, per, cout), dst, false, wt, gy_of(gy, c, g, n));
        }
    } else {
        buf.resize(k * cols, T::from_f64(0.0));
        matmul(
            (k, cols, cout),
            (buf.as_mut_ptr(), cols, 1),
            false,
            wt,
            gy_of(gy, c, g, c.n0),
        );
        col2im(g, c, buf, dxp);
    }
}

/// The blocks' accumulators summed in their order (deterministic): `(dw [cout, K], db)`.
fn sum_accumulators<T: WithDType>(accs: &[Acc<T>], k: usize, cout: usize) -> (Vec<T>, Vec<T>) {
    let zero = T::from_f64(0.0);
    let (mut dw, mut db) = (vec![zero; cout * k], vec![zero; cout]);
    for a in accs {
        for (kk, row) in a.dwt.chunks_exact(cout).enumerate() {
            row.iter()
                .enumerate()
                .for_each(|(co, &v)| dw[co * k + kk] += v);
        }
        db.iter_mut().zip(&a.db).for_each(|(d, &v)| *d += v);
    }
    (dw, db)
}
