//! The network's head: [`select_softmax`] (selection probabilities) and [`composite`]
//! (the rendered colour).

use super::{apply2, on_cpu, par_columns, read, shaped, Kernels2, Real, COLUMNS};
use crate::cpu::{softmax_columns, SharedMut};
use candle_core::{bail, Result, Shape, Tensor, WithDType};
use num_traits::Float;
use rayon::prelude::*;

/// Selection probabilities from the last depth layer: `x` `[B, D, P]`, `log_scale` `[1]`
/// -> `softmax over D of tanh(x) * exp(log_scale)`, `[B, D, P]`.
pub fn select_softmax(x: &Tensor, log_scale: &Tensor) -> Result<Tensor> {
    x.dims3()?;
    if log_scale.dims() != [1] {
        bail!(
            "select_softmax: log_scale must be [1], got {:?}",
            log_scale.dims()
        );
    }
    if !on_cpu(&[x, log_scale]) {
        let logits = x.tanh()?.broadcast_mul(&log_scale.exp()?)?;
        return candle_nn::ops::softmax(&logits, 1);
    }
    apply2::<SelectSoftmax>(&x.contiguous()?, log_scale)
}

struct SelectSoftmax;

impl SelectSoftmax {
    fn fwd<T: WithDType + Float>(x: &[T], a: T, (d, p): (usize, usize)) -> Vec<T> {
        let mut s = vec![T::zero(); x.len()];
        let sp = SharedMut(s.as_mut_ptr());
        par_columns(x.len() / (d * p), p, |b, j0, j1| {
            // SAFETY: items own disjoint columns of one batch item.
            unsafe {
                softmax_columns(
                    &x[b * d * p..][..d * p],
                    sp.get().add(b * d * p),
                    a,
                    (d, p),
                    j0,
                    j1,
                )
            }
        });
        s
    }

    /// `(dx, d log_scale)` from the output `s` and its gradient `ds`.
    fn bwd_typed<T: WithDType + Float>(
        x: &[T],
        s: &[T],
        ds: &[T],
        a: T,
        (d, p): (usize, usize),
    ) -> (Vec<T>, T) {
        let mut dx = vec![T::zero(); x.len()];
        let dxp = SharedMut(dx.as_mut_ptr());
        let per = p.div_ceil(COLUMNS);
        let dls: Vec<T> = (0..x.len() / (d * p) * per)
            .into_par_iter()
            .map(|it| {
                let (b, j0) = (it / per, (it % per) * COLUMNS);
                let j1 = (j0 + COLUMNS).min(p);
                let o = b * d * p;
                let mut dls = T::zero();
                for j in j0..j1 {
                    let dot = (0..d).fold(T::zero(), |acc, i| {
                        acc + s[o + i * p + j] * ds[o + i * p + j]
                    });
                    for i in 0..d {
                        let k = o + i * p + j;
                        let dz = s[k] * (ds[k] - dot);
                        let t = x[k].tanh();
                        dls += dz * t * a;
                        // SAFETY: items own disjoint columns.
                        unsafe { *dxp.get().add(k) = dz * a * (T::one() - t * t) };
                    }
                }
                dls
            })
            .collect();
        (dx, dls.into_iter().fold(T::zero(), |acc, v| acc + v))
    }
}

impl Kernels2 for SelectSoftmax {
    const NAME: &'static str = "select_softmax";
    const OP: &'static str = "deepstereo-select-softmax";

    fn forward<T: Real>(x: &[T], log_scale: &[T], shape: &Shape) -> Result<Vec<T>> {
        let (_, d, p) = shape.dims3()?;
        Ok(Self::fwd(x, log_scale[0].exp(), (d, p)))
    }

    fn backward<T: Real>(
        x: &Tensor,
        ls: &Tensor,
        s: &Tensor,
        ds: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, d, p) = x.dims3()?;
        let (dx, dls) = read([x, s, ds, ls], |[x, s, g, ls]: [&[T]; 4]| {
            Ok(Self::bwd_typed(x, s, g, ls[0].exp(), (d, p)))
        })?;
        let dls = Tensor::from_vec(vec![dls], 1, x.device())?;
        Ok((Some(shaped(dx, x)?), Some(dls)))
    }
}

/// The rendered colour `sum over D of s c`: colours `[B, D, 3, P]`, selection `[B, D, P]`
/// -> `[B, 3, P]`.
pub fn composite(colours: &Tensor, selection: &Tensor) -> Result<Tensor> {
    let (b, d, _, p) = colours.dims4()?;
    if selection.dims() != [b, d, p] {
        bail!(
            "composite: selection {:?} does not match colours {:?}",
            selection.dims(),
            colours.dims()
        );
    }
    if !on_cpu(&[colours, selection]) {
        return colours.broadcast_mul(&selection.unsqueeze(2)?)?.sum(1);
    }
    apply2::<Composite>(&colours.contiguous()?, &selection.contiguous()?)
}

struct Composite;

impl Composite {
    fn fwd<T: WithDType>(col: &[T], sel: &[T], (d, c, p): (usize, usize, usize)) -> Vec<T> {
        let mut out = vec![T::zero(); col.len() / d];
        let op = SharedMut(out.as_mut_ptr());
        par_columns(col.len() / (d * c * p), p, |b, j0, j1| {
            for z in 0..d {
                let s = &sel[(b * d + z) * p..][j0..j1];
                for ch in 0..c {
                    let cz = &col[((b * d + z) * c + ch) * p..][j0..j1];
                    // SAFETY: items own disjoint columns of the output.
                    let o = unsafe {
                        std::slice::from_raw_parts_mut(op.get().add((b * c + ch) * p + j0), j1 - j0)
                    };
                    for ((ov, &cv), &sv) in o.iter_mut().zip(cz).zip(s) {
                        *ov += cv * sv;
                    }
                }
            }
        });
        out
    }

    /// `(d colours, d selection)` from the output gradient `g` `[B, C, P]`.
    fn bwd_typed<T: WithDType>(
        col: &[T],
        sel: &[T],
        g: &[T],
        (d, c, p): (usize, usize, usize),
    ) -> (Vec<T>, Vec<T>) {
        let mut dcol = vec![T::zero(); col.len()];
        let mut dsel = vec![T::zero(); sel.len()];
        dcol.par_chunks_mut(c * p)
            .zip(dsel.par_chunks_mut(p))
            .enumerate()
            .for_each(|(bz, (dc, ds))| {
                let (b, s) = (bz / d, &sel[bz * p..][..p]);
                for ch in 0..c {
                    let gc = &g[(b * c + ch) * p..][..p];
                    let cz = &col[(bz * c + ch) * p..][..p];
                    let dcc = &mut dc[ch * p..][..p];
                    for j in 0..p {
                        dcc[j] = s[j] * gc[j];
                        ds[j] += cz[j] * gc[j];
                    }
                }
            });
        (dcol, dsel)
    }
}

impl Kernels2 for Composite {
    const NAME: &'static str = "composite";
    const OP: &'static str = "deepstereo-composite";

    fn out_shape(shape: &Shape) -> Result<Shape> {
        let (b, _, c, p) = shape.dims4()?;
        Ok(Shape::from((b, c, p)))
    }

    fn forward<T: Real>(col: &[T], sel: &[T], shape: &Shape) -> Result<Vec<T>> {
        let (_, d, c, p) = shape.dims4()?;
        Ok(Self::fwd(col, sel, (d, c, p)))
    }

    fn backward<T: Real>(
        col: &Tensor,
        sel: &Tensor,
        _out: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, d, c, p) = col.dims4()?;
        let (dc, ds) = read([col, sel, g], |[cd, sd, gd]: [&[T]; 3]| {
            Ok(Self::bwd_typed(cd, sd, gd, (d, c, p)))
        })?;
        Ok((Some(shaped(dc, col)?), Some(shaped(ds, sel)?)))
    }
}
