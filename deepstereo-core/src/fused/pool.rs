//! The any-number-of-views family's per-pixel steps across views (`crate::pool` has the
//! maths): each a single pass over the pixels, in parallel, instead of a dozen broadcast
//! ops and their backward passes.
//!
//! - [`pool_front`]: from the sweep `x` `[N, V, 4, P]`, the encoder's input
//!   `[N * V, 7, P]` (RGBA and colour minus the alpha-weighted mean) and the pooled
//!   input's first channels `[N, 4, P]` (the mean colour and the coverage `s / (1 + s)`).
//!   The sweep is data: no gradient flows to it.
//! - [`view_stats`]: alpha-weighted mean and variance over views of the features `e`
//!   `[N, V, C, P]` -> `[N, 2C, P]`, with its gradient to `e` (alphas read from `x`).
//!
//! The colour blend's passes are in `blend.rs`.
//!
//! `P` is the pixels of a plane (`H * W`). Off the CPU, or for dtypes other than f32 and
//! f64, the same maths runs as candle ops (`pool.rs`); tests compare the two.

use super::{data, on_cpu, slice};
use crate::pool::POOL_EPS;
use candle_core::{bail, CpuStorage, CustomOp2, DType, Layout, Result, Shape, Tensor, WithDType};
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
/// the CPU.
pub fn pool_front(x: &Tensor) -> Result<Option<(Tensor, Tensor)>> {
    let (n, v, c, p) = x.dims4()?;
    if c != 4 {
        bail!("pool_front: expected [N, V, 4, P], got {:?}", x.dims());
    }
    if !on_cpu(&[x]) {
        return Ok(None);
    }
    let x = x.contiguous()?;
    fn run<T: WithDType + Float + NumAssignOps + AsPrimitive<f64>>(
        x: &Tensor,
        (n, v, p): (usize, usize, usize),
    ) -> Result<(Tensor, Tensor)> {
        let (st, l) = x.storage_and_layout();
        let xs = data::<T>(&st, l)?;
        let mut enc = vec![T::zero(); n * v * 7 * p];
        let mut front = vec![T::zero(); n * 4 * p];
        enc.par_chunks_mut(v * 7 * p)
            .zip(front.par_chunks_mut(4 * p))
            .enumerate()
            .for_each(|(i, (enc, front))| {
                let xi = &xs[i * v * 4 * p..][..v * 4 * p];
                // sum_v a_v rgb_v and sum_v a_v (in f64), then the mean and the coverage.
                let (mut m64, mut cover64) = (vec![0f64; 3 * p], vec![0f64; p]);
                for k in 0..v {
                    let a = &xi[(k * 4 + 3) * p..][..p];
                    for (ch, mc) in m64.chunks_exact_mut(p).enumerate() {
                        let rgb = &xi[(k * 4 + ch) * p..][..p];
                        for j in 0..p {
                            mc[j] += wide(a[j]) * wide(rgb[j]);
                        }
                    }
                    for j in 0..p {
                        cover64[j] += wide(a[j]);
                    }
                }
                let (m, rest) = front.split_at_mut(3 * p);
                let cover = &mut rest[..p];
                for j in 0..p {
                    let den = cover64[j] + POOL_EPS;
                    for ch in 0..3 {
                        m[ch * p + j] = cast(m64[ch * p + j] / den);
                    }
                    cover[j] = cast(cover64[j] / (cover64[j] + 1.0));
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
            });
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

/// Alpha-weighted mean and variance over views: `e` `[N, V, C, P]` with the sources'
/// RGBA `x` `[N, V, 4, P]` (alpha: channel 3) -> `[N, 2C, P]` (means, then variances);
/// `None` off the CPU.
pub fn view_stats(e: &Tensor, x: &Tensor) -> Result<Option<Tensor>> {
    let (n, v, _, p) = e.dims4()?;
    if x.dims() != [n, v, 4, p] {
        bail!(
            "view_stats: sources {:?} do not match features {:?}",
            x.dims(),
            e.dims()
        );
    }
    if !on_cpu(&[e, x]) {
        return Ok(None);
    }
    e.contiguous()?
        .apply_op2(&x.contiguous()?, ViewStats)
        .map(Some)
}

/// View `k`'s alpha plane of item `i` in `x` `[N, V, 4, P]`.
fn alpha<T>(x: &[T], (i, k, v, p): (usize, usize, usize, usize)) -> &[T] {
    &x[((i * v + k) * 4 + 3) * p..][..p]
}

/// `sum_v a_v + eps` per pixel of item `i`, in f64.
fn alpha_sum<T: Float + AsPrimitive<f64>>(x: &[T], (i, v, p): (usize, usize, usize)) -> Vec<f64> {
    let mut den = vec![POOL_EPS; p];
    for k in 0..v {
        for (d, &a) in den.iter_mut().zip(alpha(x, (i, k, v, p))) {
            *d += wide(a);
        }
    }
    den
}

/// The alpha-weighted mean over views of channel `ch` of item `i` (f64), given `den`.
fn weighted_mean<T: Float + AsPrimitive<f64>>(
    e: &[T],
    x: &[T],
    den: &[f64],
    (i, ch, v, c, p): (usize, usize, usize, usize, usize),
) -> Vec<f64> {
    let mut mean = vec![0f64; p];
    for k in 0..v {
        let (ak, ek) = (
            alpha(x, (i, k, v, p)),
            &e[((i * v + k) * c + ch) * p..][..p],
        );
        for j in 0..p {
            mean[j] += wide(ak[j]) * wide(ek[j]);
        }
    }
    for (m, d) in mean.iter_mut().zip(den) {
        *m /= d;
    }
    mean
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
                let den = alpha_sum(x, (i, v, p));
                for ch in 0..c {
                    let mean64 = weighted_mean(e, x, &den, (i, ch, v, c, p));
                    let mut var64 = vec![0f64; p];
                    for k in 0..v {
                        let (ak, ek) = (
                            alpha(x, (i, k, v, p)),
                            &e[((i * v + k) * c + ch) * p..][..p],
                        );
                        for j in 0..p {
                            let dev = wide(ek[j]) - mean64[j];
                            var64[j] += wide(ak[j]) * dev * dev;
                        }
                    }
                    let mean = &mut means[ch * p..][..p];
                    let var = &mut vars[ch * p..][..p];
                    for j in 0..p {
                        mean[j] = cast(mean64[j]);
                        var[j] = cast(var64[j] / den[j]);
                    }
                }
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
}

impl CustomOp2 for ViewStats {
    fn name(&self) -> &'static str {
        "deepstereo-view-stats"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (n, v, c, p) = l1.shape().dims4()?;
        let y = match s1 {
            CpuStorage::F32(_) => CpuStorage::F32(Self::fwd(
                slice::<f32>(s1, l1)?,
                slice::<f32>(s2, l2)?,
                (n, v, c, p),
            )),
            CpuStorage::F64(_) => CpuStorage::F64(Self::fwd(
                slice::<f64>(s1, l1)?,
                slice::<f64>(s2, l2)?,
                (n, v, c, p),
            )),
            _ => bail!("view_stats: f32 or f64 only"),
        };
        Ok((y, Shape::from((n, 2 * c, p))))
    }

    fn bwd(
        &self,
        e: &Tensor,
        x: &Tensor,
        _y: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let dims = e.dims4()?;
        let g = g.contiguous()?;
        fn run<T: WithDType + Float + NumAssignOps + AsPrimitive<f64>>(
            e: &Tensor,
            x: &Tensor,
            g: &Tensor,
            dims: (usize, usize, usize, usize),
        ) -> Result<Tensor> {
            let de = {
                let (es, el) = e.storage_and_layout();
                let (xs, xl) = x.storage_and_layout();
                let (gs, gl) = g.storage_and_layout();
                ViewStats::bwd(
                    data::<T>(&es, el)?,
                    data::<T>(&xs, xl)?,
                    data::<T>(&gs, gl)?,
                    dims,
                )
            };
            Tensor::from_vec(de, e.shape(), e.device())
        }
        let de = match e.dtype() {
            DType::F32 => run::<f32>(e, x, &g, dims)?,
            DType::F64 => run::<f64>(e, x, &g, dims)?,
            dt => bail!("view_stats: f32 or f64 only, got {dt:?}"),
        };
        Ok((Some(de), None))
    }
}
