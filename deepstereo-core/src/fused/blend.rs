//! The any-number-of-views family's colour blend (`pool.rs` has the maths), one pass
//! over the pixels each, with gradients:
//!
//! - [`blend_colours`]: the blend of the source colours from the raw logits `y`
//!   `[N, V, P]` -> `[N, 3, P]`, with its gradient to `y`, and to the sources `x` where
//!   they carry one (alphas weighed by the cue);
//! - [`add_views_relu`]: the blend's first layer, `relu(a + b)` with `b` broadcast over
//!   the views.
//!
//! Off the CPU, or for dtypes other than f32 and f64, `pool.rs` runs the same maths as
//! candle ops; tests compare the two.

use super::pool::{cast, wide};
use super::{apply2, check_sources, on_cpu, read, shaped, source_grad, Kernels2, Real};
use crate::config::{BLEND_EPS, BLEND_LOGIT_BOUND};
use candle_core::{bail, Result, Shape, Tensor};
use num_traits::{AsPrimitive, Float, NumAssignOps};
use rayon::prelude::*;

/// The blended source colours from the raw logits `y` `[N, V, P]` and the sources' RGBA
/// `x` `[N, V, 4, P]`: `sum_v w_v rgb_v` with `w_v = a_v exp(L(y_v)) / (sum_u a_u
/// exp(L(y_u)) + eps)`, `L(y) = B tanh(y / B)`; `[N, 3, P]`. `None` off the CPU.
pub fn blend_colours(y: &Tensor, x: &Tensor) -> Result<Option<Tensor>> {
    check_sources("blend_colours", x, y.dims3()?, ("logits", y))?;
    if !on_cpu(&[y, x]) {
        return Ok(None);
    }
    apply2::<BlendColours>(&y.contiguous()?, &x.contiguous()?).map(Some)
}

struct BlendColours;

/// One pixel `j` of a batch item in [`BlendColours`]'s backward: the item's logits `y`,
/// sources `x` and output gradient `g`, with the pixel's view weights `ex`, their sum
/// `den` and its blended colour `out`.
struct Pixel<'a, T> {
    y: &'a [T],
    x: &'a [T],
    g: &'a [T],
    j: usize,
    ex: &'a [T],
    den: f64,
    out: [f64; 3],
}

/// `exp(L(y))` with the bounded logit `L(y) = B tanh(y / B)` (`B` = [`BLEND_LOGIT_BOUND`]),
/// the unnormalised weight of a view that sees the pixel.
#[inline(always)]
pub(super) fn bounded_exp<T: Float>(y: T) -> T {
    let b = cast::<T>(BLEND_LOGIT_BOUND);
    (b * (y / b).tanh()).exp()
}

impl BlendColours {
    /// `exp(L(y_v)) a_v` of one pixel's views into `ex`, returning their sum plus eps
    /// (summed in f64, as every sum over views here: see [`wide`]).
    fn weights<T: Float + NumAssignOps + AsPrimitive<f64>>(
        y: &[T],
        x: &[T],
        (v, p, j): (usize, usize, usize),
        ex: &mut [T],
    ) -> f64 {
        let mut den = BLEND_EPS;
        for k in 0..v {
            ex[k] = bounded_exp(y[k * p + j]) * x[(k * 4 + 3) * p + j];
            den += wide(ex[k]);
        }
        den
    }

    /// The blended colour of pixel `j` (f64) from its views' weights `ex` and their sum
    /// `den` ([`Self::weights`]).
    fn blended<T: Float + AsPrimitive<f64>>(
        xi: &[T],
        ex: &[T],
        den: f64,
        (p, j): (usize, usize),
    ) -> [f64; 3] {
        let mut out = [0f64; 3];
        for (ch, o) in out.iter_mut().enumerate() {
            for (k, &w) in ex.iter().enumerate() {
                *o += wide(w) * wide(xi[(k * 4 + ch) * p + j]);
            }
            *o /= den;
        }
        out
    }

    fn fwd<T: Float + NumAssignOps + Send + Sync + AsPrimitive<f64>>(
        y: &[T],
        x: &[T],
        (n, v, p): (usize, usize, usize),
    ) -> Vec<T> {
        let mut out = vec![T::zero(); n * 3 * p];
        out.par_chunks_mut(3 * p).enumerate().for_each(|(i, o)| {
            let (yi, xi) = (&y[i * v * p..][..v * p], &x[i * v * 4 * p..][..v * 4 * p]);
            let mut ex = vec![T::zero(); v];
            for j in 0..p {
                let den = Self::weights(yi, xi, (v, p, j), &mut ex);
                for (ch, c) in Self::blended(xi, &ex, den, (p, j)).into_iter().enumerate() {
                    o[ch * p + j] = cast(c);
                }
            }
        });
        out
    }

    /// `dy` from the output gradient `g` `[N, 3, P]`: `d out_c / d L_v = w_v (rgb_vc -
    /// out_c)`, `d L / d y = 1 - tanh(y / B)^2`.
    fn bwd<T: Float + NumAssignOps + Send + Sync + AsPrimitive<f64>>(
        y: &[T],
        x: &[T],
        g: &[T],
        (_, v, p): (usize, usize, usize),
    ) -> Vec<T> {
        let mut dy = vec![T::zero(); y.len()];
        let b = cast::<T>(BLEND_LOGIT_BOUND);
        Self::per_pixel((y, x, g), (v, p), (&mut dy, v * p), |d, px| {
            let (yi, xi, gi, j) = (px.y, px.x, px.g, px.j);
            for (k, &w) in px.ex.iter().enumerate() {
                let mut gl = 0f64;
                for ch in 0..3 {
                    gl += wide(gi[ch * p + j]) * (wide(xi[(k * 4 + ch) * p + j]) - px.out[ch]);
                }
                let t = wide((yi[k * p + j] / b).tanh());
                d[k * p + j] = cast(gl * wide(w) / px.den * (1.0 - t * t));
            }
        });
        dy
    }

    /// Runs `f(d, pixel)` on every pixel of every batch item: `d` the item's chunk of
    /// `grad` (`per` values an item), `pixel` the item's logits, sources and output
    /// gradient with the pixel's view weights, their sum and its blended colour.
    fn per_pixel<T: Float + NumAssignOps + Send + Sync + AsPrimitive<f64>>(
        (y, x, g): (&[T], &[T], &[T]),
        (v, p): (usize, usize),
        (grad, per): (&mut [T], usize),
        f: impl Fn(&mut [T], &Pixel<'_, T>) + Sync,
    ) {
        grad.par_chunks_mut(per).enumerate().for_each(|(i, d)| {
            let (yi, xi) = (&y[i * v * p..][..v * p], &x[i * v * 4 * p..][..v * 4 * p]);
            let gi = &g[i * 3 * p..][..3 * p];
            let mut ex = vec![T::zero(); v];
            for j in 0..p {
                let den = Self::weights(yi, xi, (v, p, j), &mut ex);
                let out = Self::blended(xi, &ex, den, (p, j));
                let px = Pixel {
                    y: yi,
                    x: xi,
                    g: gi,
                    j,
                    ex: &ex,
                    den,
                    out,
                };
                f(d, &px);
            }
        });
    }

    /// `dx` `[N, V, 4, P]` from the output gradient `g` (the alphas weighed by the cue
    /// carry a gradient): with `E_v = exp(L(y_v))`, `d out_c / d rgb_vc = w_v` and
    /// `d out_c / d a_v = E_v (rgb_vc - out_c) / den`.
    fn bwd_x<T: Float + NumAssignOps + Send + Sync + AsPrimitive<f64>>(
        y: &[T],
        x: &[T],
        g: &[T],
        (_, v, p): (usize, usize, usize),
    ) -> Vec<T> {
        let mut dx = vec![T::zero(); x.len()];
        Self::per_pixel((y, x, g), (v, p), (&mut dx, v * 4 * p), |d, px| {
            let (yi, xi, gi, j, den) = (px.y, px.x, px.g, px.j, px.den);
            for (k, &w) in px.ex.iter().enumerate() {
                let mut ga = 0f64;
                for (ch, &o) in px.out.iter().enumerate() {
                    let gc = wide(gi[ch * p + j]);
                    d[(k * 4 + ch) * p + j] = cast(gc * wide(w) / den);
                    ga += gc * (wide(xi[(k * 4 + ch) * p + j]) - o);
                }
                d[(k * 4 + 3) * p + j] = cast(ga * wide(bounded_exp(yi[k * p + j])) / den);
            }
        });
        dx
    }
}

impl Kernels2 for BlendColours {
    const NAME: &'static str = "blend_colours";
    const OP: &'static str = "deepstereo-blend-colours";

    fn out_shape(shape: &Shape) -> Result<Shape> {
        let (n, _, p) = shape.dims3()?;
        Ok(Shape::from((n, 3, p)))
    }

    fn forward<T: Real>(y: &[T], x: &[T], shape: &Shape) -> Result<Vec<T>> {
        Ok(Self::fwd(y, x, shape.dims3()?))
    }

    fn backward<T: Real>(
        y: &Tensor,
        x: &Tensor,
        _out: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let dims = y.dims3()?;
        read([y, x, g], |[yd, xd, gd]: [&[T]; 3]| {
            let dy = shaped(Self::bwd(yd, xd, gd, dims), y)?;
            Ok((Some(dy), source_grad(x, || Self::bwd_x(yd, xd, gd, dims))?))
        })
    }
}

/// `relu(a + b)` with `b` broadcast over the views: `a` `[N, V, C, P]`, `b` `[N, C, P]`
/// -> `[N, V, C, P]` (the blend's first layer: its part for the colour tower's features
/// is computed once per plane); `None` off the CPU.
pub fn add_views_relu(a: &Tensor, b: &Tensor) -> Result<Option<Tensor>> {
    let (n, _, c, p) = a.dims4()?;
    if b.dims() != [n, c, p] {
        bail!(
            "add_views_relu: {:?} does not broadcast over {:?}",
            b.dims(),
            a.dims()
        );
    }
    if !on_cpu(&[a, b]) {
        return Ok(None);
    }
    apply2::<AddViewsRelu>(&a.contiguous()?, &b.contiguous()?).map(Some)
}

struct AddViewsRelu;

impl AddViewsRelu {
    fn fwd<T: Float + NumAssignOps + Send + Sync>(
        a: &[T],
        b: &[T],
        (v, cp): (usize, usize),
    ) -> Vec<T> {
        let mut y = vec![T::zero(); a.len()];
        y.par_chunks_mut(cp).enumerate().for_each(|(iv, yc)| {
            let (ac, bc) = (&a[iv * cp..][..cp], &b[(iv / v) * cp..][..cp]);
            for ((o, &x), &z) in yc.iter_mut().zip(ac).zip(bc) {
                *o = (x + z).max(T::zero());
            }
        });
        y
    }

    /// `(da, db)`: the output gradient where the output is positive, and its sum over
    /// the views.
    fn bwd<T: Float + NumAssignOps + Send + Sync>(
        y: &[T],
        g: &[T],
        (v, cp): (usize, usize),
    ) -> (Vec<T>, Vec<T>) {
        let mut da = vec![T::zero(); y.len()];
        da.par_chunks_mut(cp).enumerate().for_each(|(iv, d)| {
            let (yc, gc) = (&y[iv * cp..][..cp], &g[iv * cp..][..cp]);
            for ((o, &yv), &gv) in d.iter_mut().zip(yc).zip(gc) {
                *o = if yv > T::zero() { gv } else { T::zero() };
            }
        });
        let mut db = vec![T::zero(); y.len() / v];
        db.par_chunks_mut(cp).enumerate().for_each(|(i, d)| {
            for k in 0..v {
                for (o, &x) in d.iter_mut().zip(&da[(i * v + k) * cp..][..cp]) {
                    *o += x;
                }
            }
        });
        (da, db)
    }
}

impl Kernels2 for AddViewsRelu {
    const NAME: &'static str = "add_views_relu";
    const OP: &'static str = "deepstereo-add-views-relu";

    fn forward<T: Real>(a: &[T], b: &[T], shape: &Shape) -> Result<Vec<T>> {
        let (_, v, c, p) = shape.dims4()?;
        Ok(Self::fwd(a, b, (v, c * p)))
    }

    fn backward<T: Real>(
        a: &Tensor,
        b: &Tensor,
        y: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, v, c, p) = a.dims4()?;
        let (da, db) = read([y, g], |[yd, gd]: [&[T]; 2]| {
            Ok(Self::bwd(yd, gd, (v, c * p)))
        })?;
        Ok((Some(shaped(da, a)?), Some(shaped(db, b)?)))
    }
}
