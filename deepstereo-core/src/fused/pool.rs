//! The any-number-of-views family's per-pixel steps across views (`pool.rs` has the
//! maths): each a single pass over the pixels, in parallel, instead of a dozen broadcast
//! ops and their backward passes.
//!
//! - [`pool_front`]: from the sweep `x` `[N, V, 4, P]`, the encoder's input
//!   `[N * V, 7, P]` (RGBA and colour minus the alpha-weighted mean) and the pooled
//!   input's first channels `[N, 4, P]` (the mean colour and the coverage `s / (1 + s)`).
//!   Where the sweep carries a gradient (its alphas weighed by the cue), it returns it.
//! - [`view_stats`]: alpha-weighted mean and variance over views of the features `e`
//!   `[N, V, C, P]` -> `[N, 2C, P]`, with its gradient to `e` (alphas read from `x`), and
//!   to the alphas where `x` carries a gradient (weighed by the cue).
//! - [`pooled_stats`]: the same moments written after `front` into the whole pooled input
//!   `[N, 4 + 2C, P]` (rendering: no gradient, and no concatenation copy).
//!
//! The colour blend's passes are in `blend.rs`.
//!
//! `P` is the pixels of a plane (`H * W`). Off the CPU, or for dtypes other than f32 and
//! f64, the same maths runs as candle ops (`pool.rs`); tests compare the two.

use super::{apply2, check_sources, on_cpu, read, shaped, slice, source_grad, Kernels2, Real};
use crate::config::POOL_EPS;
use candle_core::{bail, CpuStorage, CustomOp1, DType, Layout, Result, Shape, Tensor};
use num_traits::{AsPrimitive, Float, NumAssignOps};
use rayon::prelude::*;

pub(super) fn cast<T: Float>(v: f64) -> T {
    T::from(v).unwrap_or_else(T::zero)
}

/// `v` as f64: sums over views accumulate in f64 whatever the dtype, so that their
/// rounding does not depend on the order of the views (an f32 sum's does, by ~1e-7
/// relative, which a trained network's sharp selection amplifies past 1e-6; the f64 sum
/// rounds back to the same f32 except at ties).
#[inline(always)]
pub(super) fn wide<T: AsPrimitive<f64>>(v: T) -> f64 {
    v.as_()
}

/// `(encoder input [N*V, 7, P], front [N, 4, P])` from `x` `[N, V, 4, P]`; `None` off
/// the CPU. Where `x` carries a gradient (its alphas weighed by the cue), one op with
/// its backward ([`PoolFront`]); else two buffers written directly, with no graph.
pub fn pool_front(x: &Tensor) -> Result<Option<(Tensor, Tensor)>> {
    let (n, v, c, p) = x.dims4()?;
    if c != 4 {
        bail!("pool_front: expected [N, V, 4, P], got {:?}", x.dims());
    }
    if !on_cpu(&[x]) {
        return Ok(None);
    }
    let x = x.contiguous()?;
    if x.track_op() {
        let y = x.apply_op1(PoolFront)?; // [N, 7V + 4, P]
        let enc = y.narrow(1, 0, 7 * v)?.reshape((n * v, 7, p))?; // [N*V, 7, P]
        let front = y.narrow(1, 7 * v, 4)?; // [N, 4, P]
        return Ok(Some((enc, front)));
    }
    fn run<T: Real>(x: &Tensor, (n, v, p): (usize, usize, usize)) -> Result<(Tensor, Tensor)> {
        let (enc, front) = read([x], |[xs]: [&[T]; 1]| {
            let mut enc = vec![T::zero(); n * v * 7 * p];
            let mut front = vec![T::zero(); n * 4 * p];
            enc.par_chunks_mut(v * 7 * p)
                .zip(front.par_chunks_mut(4 * p))
                .zip(xs.par_chunks(v * 4 * p))
                .for_each(|((enc, front), xi)| front_item(xi, (v, p), enc, front));
            Ok((enc, front))
        })?;
        let dev = x.device();
        Ok((
            Tensor::from_vec(enc, (n * v, 7, p), dev)?,
            Tensor::from_vec(front, (n, 4, p), dev)?,
        ))
    }
    match x.dtype() {
        DType::F32 => run::<f32>(&x, (n, v, p)).map(Some),
        DType::F64 => run::<f64>(&x, (n, v, p)).map(Some),
        _ => Ok(None),
    }
}

/// [`pool_front`] of one item: its sweep `xi` `[V, 4, P]` -> the encoder's input `enc`
/// `[V, 7, P]` and `front` `[4, P]` (every value written).
fn front_item<T: Float + AsPrimitive<f64>>(
    xi: &[T],
    (v, p): (usize, usize),
    enc: &mut [T],
    front: &mut [T],
) {
    // sum_v a_v rgb_v and sum_v a_v (in f64), then the mean and the coverage.
    let plane = |k: usize, ch: usize| &xi[(k * 4 + ch) * p..][..p];
    let cover64 = sum_views(v, p, 0.0, |k| plane(k, 3).iter().map(|&a| wide(a)));
    let (m, rest) = front.split_at_mut(3 * p);
    for (ch, mc) in m.chunks_exact_mut(p).enumerate() {
        let m64 = sum_views(v, p, 0.0, |k| {
            let (a, rgb) = (plane(k, 3), plane(k, ch));
            a.iter().zip(rgb).map(|(&a, &c)| wide(a) * wide(c))
        });
        for ((m, s), c) in mc.iter_mut().zip(&m64).zip(&cover64) {
            *m = cast(s / (c + POOL_EPS));
        }
    }
    for (cv, &c) in rest[..p].iter_mut().zip(&cover64) {
        *cv = cast(c / (c + 1.0));
    }
    for k in 0..v {
        let (xk, ek) = (&xi[k * 4 * p..][..4 * p], &mut enc[k * 7 * p..][..7 * p]);
        ek[..4 * p].copy_from_slice(xk);
        for ch in 0..3 {
            for j in 0..p {
                ek[(4 + ch) * p + j] = xk[ch * p + j] - m[ch * p + j];
            }
        }
    }
}

/// [`pool_front`] as a differentiable op: `x` `[N, V, 4, P]` -> `[N, 7V + 4, P]`, per
/// item the encoder's input `[V, 7, P]` then the front `[4, P]`.
struct PoolFront;

impl PoolFront {
    fn fwd<T: Float + Send + Sync + AsPrimitive<f64>>(
        x: &[T],
        (n, v, p): (usize, usize, usize),
    ) -> Vec<T> {
        let mut y = vec![T::zero(); n * (7 * v + 4) * p];
        y.par_chunks_mut((7 * v + 4) * p)
            .zip(x.par_chunks(v * 4 * p))
            .for_each(|(yi, xi)| {
                let (enc, front) = yi.split_at_mut(7 * v * p);
                front_item(xi, (v, p), enc, front);
            });
        y
    }

    /// `dx` `[N, V, 4, P]` from `g` `[N, 7V + 4, P]` (`g_e` the encoder input's part,
    /// `g_f` the front's). With `A = sum_v a_v`, `D = A + eps`, `m = sum_v a_v rgb_v / D`:
    /// `dm = g_f[rgb] - sum_v g_e[v, diff]`, `dA = g_f[cover] / (A + 1)^2 - dm . m / D`,
    /// `d rgb_v = g_e[v, rgb] + g_e[v, diff] + a_v dm / D` and
    /// `d a_v = g_e[v, a] + rgb_v . dm / D + dA`.
    fn bwd<T: Float + Send + Sync + AsPrimitive<f64>>(
        x: &[T],
        g: &[T],
        (n, v, p): (usize, usize, usize),
    ) -> Vec<T> {
        let mut dx = vec![T::zero(); n * v * 4 * p];
        dx.par_chunks_mut(v * 4 * p)
            .zip(x.par_chunks(v * 4 * p))
            .zip(g.par_chunks((7 * v + 4) * p))
            .for_each(|((dxi, xi), gi)| {
                let plane = |k: usize, ch: usize| &xi[(k * 4 + ch) * p..][..p];
                let ge = |k: usize, ch: usize| &gi[(k * 7 + ch) * p..][..p];
                let gf = |ch: usize| &gi[(7 * v + ch) * p..][..p];
                let asum = sum_views(v, p, 0.0, |k| plane(k, 3).iter().map(|&a| wide(a)));
                // Per colour channel: dm / D; and dA.
                let mut dm_d = vec![0f64; 3 * p];
                let mut da: Vec<f64> = (gf(3).iter().zip(&asum))
                    .map(|(&g, &a)| wide(g) / ((a + 1.0) * (a + 1.0)))
                    .collect();
                for ch in 0..3 {
                    let s = sum_views(v, p, 0.0, |k| {
                        let (a, rgb) = (plane(k, 3), plane(k, ch));
                        a.iter().zip(rgb).map(|(&a, &c)| wide(a) * wide(c))
                    });
                    let gdiff = sum_views(v, p, 0.0, |k| ge(k, 4 + ch).iter().map(|&g| wide(g)));
                    let dm = &mut dm_d[ch * p..][..p];
                    for j in 0..p {
                        let d = asum[j] + POOL_EPS;
                        let m = s[j] / d;
                        dm[j] = (wide(gf(ch)[j]) - gdiff[j]) / d;
                        da[j] -= dm[j] * m;
                    }
                }
                for k in 0..v {
                    let (a, dxk) = (plane(k, 3), &mut dxi[k * 4 * p..][..4 * p]);
                    let mut dak: Vec<f64> = (ge(k, 3).iter().zip(&da))
                        .map(|(&g, &d)| wide(g) + d)
                        .collect();
                    for ch in 0..3 {
                        let (rgb, dm) = (plane(k, ch), &dm_d[ch * p..][..p]);
                        let (gr, gd) = (ge(k, ch), ge(k, 4 + ch));
                        let out = &mut dxk[ch * p..][..p];
                        for j in 0..p {
                            out[j] = cast(wide(gr[j]) + wide(gd[j]) + wide(a[j]) * dm[j]);
                            dak[j] += wide(rgb[j]) * dm[j];
                        }
                    }
                    for (o, d) in dxk[3 * p..].iter_mut().zip(dak) {
                        *o = cast(d);
                    }
                }
            });
        dx
    }
}

impl CustomOp1 for PoolFront {
    fn name(&self) -> &'static str {
        "deepstereo-pool-front"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, v, _, p) = l.shape().dims4()?;
        let y = match s {
            CpuStorage::F32(_) => CpuStorage::F32(Self::fwd(slice::<f32>(s, l)?, (n, v, p))),
            CpuStorage::F64(_) => CpuStorage::F64(Self::fwd(slice::<f64>(s, l)?, (n, v, p))),
            _ => bail!("pool_front: f32 or f64 only"),
        };
        Ok((y, Shape::from((n, 7 * v + 4, p))))
    }

    fn bwd(&self, x: &Tensor, _y: &Tensor, g: &Tensor) -> Result<Option<Tensor>> {
        fn run<T: Real>(x: &Tensor, g: &Tensor) -> Result<Tensor> {
            let (n, v, _, p) = x.dims4()?;
            let dx = read([x, g], |[xd, gd]: [&[T]; 2]| {
                Ok(PoolFront::bwd(xd, gd, (n, v, p)))
            })?;
            Tensor::from_vec(dx, x.shape(), x.device())
        }
        let g = g.contiguous()?;
        let dx = match x.dtype() {
            DType::F32 => run::<f32>(x, &g)?,
            DType::F64 => run::<f64>(x, &g)?,
            dt => bail!("pool_front: f32 or f64 only, got {dt:?}"),
        };
        Ok(Some(dx))
    }
}

/// Alpha-weighted mean and variance over views: `e` `[N, V, C, P]` with the sources'
/// RGBA `x` `[N, V, 4, P]` (alpha: channel 3) -> `[N, 2C, P]` (means, then variances);
/// `None` off the CPU.
pub fn view_stats(e: &Tensor, x: &Tensor) -> Result<Option<Tensor>> {
    let (n, v, _, p) = e.dims4()?;
    check_sources("view_stats", x, (n, v, p), ("features", e))?;
    if !on_cpu(&[e, x]) {
        return Ok(None);
    }
    apply2::<ViewStats>(&e.contiguous()?, &x.contiguous()?).map(Some)
}

/// View `k`'s alpha plane of item `i` in `x` `[N, V, 4, P]`.
fn alpha<T>(x: &[T], (i, k, v, p): (usize, usize, usize, usize)) -> &[T] {
    &x[((i * v + k) * 4 + 3) * p..][..p]
}

/// `init + t_0 + t_1 + ... + t_{v-1}` per pixel, in f64 and in that order, with `t_k`
/// the `p` terms of view `k` (`term(k)`): the sum starts from view 0's terms, so its
/// buffer is written once, not zero-filled first (the rounding is that of the plain loop).
fn sum_views<I: Iterator<Item = f64>>(
    v: usize,
    p: usize,
    init: f64,
    mut term: impl FnMut(usize) -> I,
) -> Vec<f64> {
    if v == 0 {
        return vec![init; p];
    }
    let mut acc: Vec<f64> = term(0).map(|t| init + t).collect();
    for k in 1..v {
        for (s, t) in acc.iter_mut().zip(term(k)) {
            *s += t;
        }
    }
    acc
}

/// `sum_v a_v + eps` per pixel of item `i`, in f64.
fn alpha_sum<T: Float + AsPrimitive<f64>>(x: &[T], (i, v, p): (usize, usize, usize)) -> Vec<f64> {
    sum_views(v, p, POOL_EPS, |k| {
        alpha(x, (i, k, v, p)).iter().map(|&a| wide(a))
    })
}

/// Channel `ch` of view `k` of item `i` in `e` `[N, V, C, P]`.
fn feature<T>(e: &[T], (i, k, ch, v, c, p): (usize, usize, usize, usize, usize, usize)) -> &[T] {
    &e[((i * v + k) * c + ch) * p..][..p]
}

/// The alpha-weighted mean over views of channel `ch` of item `i` (f64), given `den`.
fn weighted_mean<T: Float + AsPrimitive<f64>>(
    e: &[T],
    x: &[T],
    den: &[f64],
    (i, ch, v, c, p): (usize, usize, usize, usize, usize),
) -> Vec<f64> {
    let mut mean = sum_views(v, p, 0.0, |k| {
        let (ak, ek) = (alpha(x, (i, k, v, p)), feature(e, (i, k, ch, v, c, p)));
        ak.iter().zip(ek).map(|(&a, &e)| wide(a) * wide(e))
    });
    for (m, d) in mean.iter_mut().zip(den) {
        *m /= d;
    }
    mean
}

/// Item `i`'s alpha-weighted means and variances over views of the features `e`
/// `[N, V, C, P]`, written into `means` and `vars` (each `[C, P]`, every value).
fn moments<T: Float + AsPrimitive<f64>>(
    e: &[T],
    x: &[T],
    (i, v, c, p): (usize, usize, usize, usize),
    means: &mut [T],
    vars: &mut [T],
) {
    let den = alpha_sum(x, (i, v, p));
    let planes = means.chunks_exact_mut(p).zip(vars.chunks_exact_mut(p));
    for (ch, (mean, var)) in planes.enumerate() {
        let (mean64, var64) = mean_var(e, x, &den, (i, ch, v, c, p));
        for ((mo, vo), (&m, &s)) in mean
            .iter_mut()
            .zip(var.iter_mut())
            .zip(mean64.iter().zip(&var64))
        {
            *mo = cast(m);
            *vo = cast(s);
        }
    }
}

/// The alpha-weighted mean and variance over views of channel `ch` of item `i` (f64),
/// given `den` ([`alpha_sum`]).
fn mean_var<T: Float + AsPrimitive<f64>>(
    e: &[T],
    x: &[T],
    den: &[f64],
    (i, ch, v, c, p): (usize, usize, usize, usize, usize),
) -> (Vec<f64>, Vec<f64>) {
    let mean = weighted_mean(e, x, den, (i, ch, v, c, p));
    let mut var = sum_views(v, p, 0.0, |k| {
        let (ak, ek) = (alpha(x, (i, k, v, p)), feature(e, (i, k, ch, v, c, p)));
        ak.iter().zip(ek).zip(&mean).map(|((&a, &e), &m)| {
            let dev = wide(e) - m;
            wide(a) * dev * dev
        })
    });
    for (s, d) in var.iter_mut().zip(den) {
        *s /= d;
    }
    (mean, var)
}

/// [`view_stats`] written after `front` `[N, F, P]` (the mean colour and coverage from
/// [`pool_front`]): `[N, F + 2C, P]`, the tower input without a concatenation copy. For
/// rendering: no gradient flows through it. `None` off the CPU.
pub fn pooled_stats(front: &Tensor, e: &Tensor, x: &Tensor) -> Result<Option<Tensor>> {
    let (n, v, c, p) = e.dims4()?;
    let nf = front.dims3()?.1;
    if x.dims() != [n, v, 4, p] || front.dims() != [n, nf, p] {
        bail!(
            "pooled_stats: sources {:?} or front {:?} do not match features {:?}",
            x.dims(),
            front.dims(),
            e.dims()
        );
    }
    if !on_cpu(&[front, e, x]) {
        return Ok(None);
    }
    let (front, e, x) = (front.contiguous()?, e.contiguous()?, x.contiguous()?);
    fn run<T: Real>(
        front: &Tensor,
        e: &Tensor,
        x: &Tensor,
        (n, nf, v, c, p): (usize, usize, usize, usize, usize),
    ) -> Result<Tensor> {
        let out = read([front, e, x], |[fd, ed, xd]: [&[T]; 3]| {
            let mut out = vec![T::zero(); n * (nf + 2 * c) * p];
            out.par_chunks_mut((nf + 2 * c) * p)
                .zip(fd.par_chunks(nf * p))
                .enumerate()
                .for_each(|(i, (o, f))| {
                    let (head, rest) = o.split_at_mut(nf * p);
                    head.copy_from_slice(f);
                    let (means, vars) = rest.split_at_mut(c * p);
                    moments(ed, xd, (i, v, c, p), means, vars);
                });
            Ok(out)
        })?;
        Tensor::from_vec(out, (n, nf + 2 * c, p), e.device()) // [N, F + 2C, P]
    }
    let dims = (n, nf, v, c, p);
    match e.dtype() {
        DType::F32 => run::<f32>(&front, &e, &x, dims).map(Some),
        DType::F64 => run::<f64>(&front, &e, &x, dims).map(Some),
        _ => Ok(None),
    }
}

struct ViewStats;

impl ViewStats {
    fn fwd<T: Float + NumAssignOps + Send + Sync + AsPrimitive<f64>>(
        e: &[T],
        x: &[T],
        (n, v, c, p): (usize, usize, usize, usize),
    ) -> Vec<T> {
        let mut out = vec![T::zero(); n * 2 * c * p];
        out.par_chunks_mut(2 * c * p)
            .enumerate()
            .for_each(|(i, o)| {
                let (means, vars) = o.split_at_mut(c * p);
                moments(e, x, (i, v, c, p), means, vars);
            });
        out
    }

    /// `de` from the output gradient `g` `[N, 2C, P]`: with `den = sum a + eps`,
    /// `d mean / d e_v = a_v / den`, `d var / d e_v = 2 a_v (e_v - m) / den`, and through
    /// the mean `d var / d m = -2 m eps / den`.
    fn bwd<T: Float + NumAssignOps + Send + Sync + AsPrimitive<f64>>(
        e: &[T],
        x: &[T],
        g: &[T],
        (n, v, c, p): (usize, usize, usize, usize),
    ) -> Vec<T> {
        let mut de = vec![T::zero(); e.len()];
        debug_assert_eq!(e.len(), n * v * c * p);
        de.par_chunks_mut(v * c * p)
            .enumerate()
            .for_each(|(i, dei)| {
                let den = alpha_sum(x, (i, v, p));
                for ch in 0..c {
                    let mean = weighted_mean(e, x, &den, (i, ch, v, c, p));
                    let gm = &g[(i * 2 * c + ch) * p..][..p];
                    let gv = &g[(i * 2 * c + c + ch) * p..][..p];
                    for k in 0..v {
                        let ak = alpha(x, (i, k, v, p));
                        let ek = &e[((i * v + k) * c + ch) * p..][..p];
                        let d = &mut dei[(k * c + ch) * p..][..p];
                        for j in 0..p {
                            let (gm, gv) = (wide(gm[j]), wide(gv[j]));
                            let through_mean = gm - gv * 2.0 * mean[j] * POOL_EPS / den[j];
                            d[j] = cast(
                                wide(ak[j]) / den[j]
                                    * (through_mean + gv * 2.0 * (wide(ek[j]) - mean[j])),
                            );
                        }
                    }
                }
            });
        de
    }

    /// `dx` `[N, V, 4, P]` from the output gradient `g` (the alphas weighed by the cue
    /// carry a gradient; the colours do not enter the moments, so their rows are 0): with
    /// `u_v = e_v - m`, `d mean / d a_v = u_v / den` and
    /// `d var / d a_v = (u_v^2 - var - 2 m eps u_v / den) / den`.
    fn bwd_x<T: Float + NumAssignOps + Send + Sync + AsPrimitive<f64>>(
        e: &[T],
        x: &[T],
        g: &[T],
        (n, v, c, p): (usize, usize, usize, usize),
    ) -> Vec<T> {
        let mut dx = vec![T::zero(); n * v * 4 * p];
        dx.par_chunks_mut(v * 4 * p)
            .enumerate()
            .for_each(|(i, dxi)| {
                let den = alpha_sum(x, (i, v, p));
                let mut da = vec![0f64; v * p];
                for ch in 0..c {
                    let (mean, var) = mean_var(e, x, &den, (i, ch, v, c, p));
                    let gm = &g[(i * 2 * c + ch) * p..][..p];
                    let gv = &g[(i * 2 * c + c + ch) * p..][..p];
                    for k in 0..v {
                        let ek = feature(e, (i, k, ch, v, c, p));
                        for j in 0..p {
                            let (m, d) = (mean[j], den[j]);
                            let u = wide(ek[j]) - m;
                            let dvar = (u * u - var[j] - 2.0 * m * POOL_EPS * u / d) / d;
                            da[k * p + j] += wide(gm[j]) * u / d + wide(gv[j]) * dvar;
                        }
                    }
                }
                for k in 0..v {
                    for (o, &d) in dxi[(k * 4 + 3) * p..][..p]
                        .iter_mut()
                        .zip(&da[k * p..][..p])
                    {
                        *o = cast(d);
                    }
                }
            });
        dx
    }
}

impl Kernels2 for ViewStats {
    const NAME: &'static str = "view_stats";
    const OP: &'static str = "deepstereo-view-stats";

    fn out_shape(shape: &Shape) -> Result<Shape> {
        let (n, _, c, p) = shape.dims4()?;
        Ok(Shape::from((n, 2 * c, p)))
    }

    fn forward<T: Real>(e: &[T], x: &[T], shape: &Shape) -> Result<Vec<T>> {
        Ok(Self::fwd(e, x, shape.dims4()?))
    }

    fn backward<T: Real>(
        e: &Tensor,
        x: &Tensor,
        _y: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let dims = e.dims4()?;
        read([e, x, g], |[ed, xd, gd]: [&[T]; 3]| {
            let de = shaped(Self::bwd(ed, xd, gd, dims), e)?;
            Ok((Some(de), source_grad(x, || Self::bwd_x(ed, xd, gd, dims))?))
        })
    }
}
