//! Rendering only: the any-number-of-views family's colour blend (`pool::Blend`) as one
//! pass over the tile's pixels, row by row: the blend's 1x1 layers on `[e_v, f]` (the
//! colour features' part once per pixel, not per view), ReLU between them, the bounded
//! logit, the alpha-masked softmax over the views and the weighted source colours. It reads
//! the view features and the sources straight from level 0's uncropped tensors, so none
//! of the crops, reshapes and per-layer tensors of the composition are built. The same
//! maths as `Blend::forward` (tests compare them), but the bounded weight
//! `exp(B tanh(y / B))` comes from `fastmath.rs`'s vectorisable `exp` and `tanh` (within
//! 4e-6 of libm's), and the loops over a row's pixels are compiled for AVX2 where the CPU
//! has it (the arithmetic and its order are the same either way); f32 on the CPU only, no
//! gradient.

use super::data;
use super::fastmath::bounded_exp_slice;
use super::pool::wide;
use crate::config::BLEND_EPS;
use candle_core::{bail, DType, Result, Tensor};
use rayon::prelude::*;

/// One 1x1 layer as plain arrays: `weight[o * cin + i]`, `bias[o]`.
pub struct Dense {
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
    pub cin: usize,
    pub cout: usize,
}

/// The blended colours `[N, 3, th * tw]` from the view features `e` `[N, V, C_f, H, W]`
/// and the sources `x` `[N, V, 4, H, W]` (both uncropped: the tile sits at `(pad, pad)`),
/// the colour tower's features `f` `[N, C_c, th, tw]` and the blend's layers (the first
/// takes `C_f + C_c` inputs, the last gives 1). `None` where it does not apply (not f32
/// on the CPU, or shapes it does not expect): the caller runs the composition.
pub fn blend_infer(
    e: &Tensor,
    x: &Tensor,
    f: &Tensor,
    layers: &[Dense],
    pad: usize,
) -> Result<Option<Tensor>> {
    let all_f32 = [e, x, f].iter().all(|t| t.dtype() == DType::F32);
    if !all_f32 || ![e, x, f].iter().all(|t| t.device().is_cpu()) || layers.is_empty() {
        return Ok(None);
    }
    let (n, v, cf, h, w) = e.dims5()?;
    let (nf, cc, th, tw) = f.dims4()?;
    if x.dims() != [n, v, 4, h, w] || nf != n || th + 2 * pad > h || tw + 2 * pad > w {
        bail!(
            "blend_infer: features {:?}, sources {:?}, colour {:?}, pad {pad}",
            e.dims(),
            x.dims(),
            f.dims()
        );
    }
    let chained = layers.windows(2).all(|p| p[0].cout == p[1].cin);
    let last = layers.len() - 1;
    if layers[0].cin != cf + cc || layers[last].cout != 1 || !chained {
        return Ok(None);
    }
    let (e, x, f) = (e.contiguous()?, x.contiguous()?, f.contiguous()?);
    let (es, el) = e.storage_and_layout();
    let (xs, xl) = x.storage_and_layout();
    let (fs, fl) = f.storage_and_layout();
    let (ed, xd, fd) = (
        data::<f32>(&es, el)?,
        data::<f32>(&xs, xl)?,
        data::<f32>(&fs, fl)?,
    );
    let p = th * tw;
    let mut out = vec![0f32; n * 3 * p];
    let ctx = Ctx {
        ed,
        xd,
        fd,
        layers,
        dims: (v, cf, cc, h, w),
        tile: (th, tw, pad),
    };
    let avx2 = crate::cpu::avx2_fma_available();
    out.par_chunks_mut(3 * p).enumerate().for_each(|(i, o)| {
        if avx2 {
            // SAFETY: the CPU has AVX2 and FMA (checked above).
            #[cfg(target_arch = "x86_64")]
            unsafe {
                item_avx2(&ctx, i, o)
            }
        } else {
            item(&ctx, i, o)
        }
    });
    Ok(Some(Tensor::from_vec(out, (n, 3, p), e.device())?))
}

/// The tensors' data and sizes [`item`] reads.
struct Ctx<'a> {
    ed: &'a [f32],
    xd: &'a [f32],
    fd: &'a [f32],
    layers: &'a [Dense],
    /// `(V, C_f, C_c, H, W)`.
    dims: (usize, usize, usize, usize, usize),
    /// `(th, tw, pad)`.
    tile: (usize, usize, usize),
}

/// [`item`] compiled for AVX2 + FMA (its loops over a row's pixels vectorise 8 wide; the
/// arithmetic and its order are those of [`item`], products and sums are not fused).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn item_avx2(ctx: &Ctx, i: usize, o: &mut [f32]) {
    item(ctx, i, o)
}

/// Item `i`'s blended colours `o` `[3, th * tw]`, row by row.
#[inline(always)]
fn item(ctx: &Ctx, i: usize, o: &mut [f32]) {
    let layers = ctx.layers;
    let (v, (th, tw, _)) = (ctx.dims.0, ctx.tile);
    let (p, c0) = (th * tw, layers[0].cout);
    let widest = layers.iter().map(|l| l.cout).max().unwrap_or(1);
    // Scratch: the colour part of layer 0 per pixel of a row, two layer buffers, and the
    // f64 sums over views of one row.
    let mut yf = vec![0f32; c0 * tw];
    let mut h = (vec![0f32; widest * tw], vec![0f32; widest * tw]);
    let mut den = vec![0f64; tw];
    let mut num = vec![0f64; 3 * tw];
    for r in 0..th {
        colour_part(ctx, (i, r), &mut yf);
        den.iter_mut().for_each(|d| *d = BLEND_EPS);
        num.iter_mut().for_each(|s| *s = 0.0);
        for k in 0..v {
            view_logits(ctx, (i, k, r), &yf, (&mut h.0, &mut h.1));
            // `h.0[..tw]` holds the logits: their bounded weights, then the sums over views.
            let weights = &mut h.0[..tw];
            bounded_exp_slice(weights);
            add_view(ctx, (i, k, r), weights, &mut den, &mut num);
        }
        for ch in 0..3 {
            for c in 0..tw {
                o[ch * p + r * tw + c] = (num[ch * tw + c] / den[c]) as f32;
            }
        }
    }
}

/// Row `r` of item `i`: the colour features' part of layer 0 into `yf` `[C_0, tw]`.
#[inline(always)]
fn colour_part(ctx: &Ctx, (i, r): (usize, usize), yf: &mut [f32]) {
    let ((_, cf, cc, _, _), (th, tw, _)) = (ctx.dims, ctx.tile);
    let l0 = &ctx.layers[0];
    yf.iter_mut().for_each(|y| *y = 0.0);
    for oc in 0..l0.cout {
        let yo = &mut yf[oc * tw..][..tw];
        for ic in 0..cc {
            let wgt = l0.weight[oc * l0.cin + cf + ic];
            let fr = &ctx.fd[((i * cc + ic) * th + r) * tw..][..tw];
            for (y, &fv) in yo.iter_mut().zip(fr) {
                *y += wgt * fv;
            }
        }
    }
}

/// View `k`'s logits at row `r` of item `i` into `ha[..tw]` (`hb`: scratch), from the
/// colour part `yf` ([`colour_part`]) and the view's features.
#[inline(always)]
fn view_logits(
    ctx: &Ctx,
    (i, k, r): (usize, usize, usize),
    yf: &[f32],
    (ha, hb): (&mut Vec<f32>, &mut Vec<f32>),
) {
    let (layers, (v, cf, _, h, w), (_, tw, pad)) = (ctx.layers, ctx.dims, ctx.tile);
    let (l0, last, c0) = (&layers[0], layers.len() - 1, layers[0].cout);
    let row =
        |c: usize| -> &[f32] { &ctx.ed[(((i * v + k) * cf + c) * h + r + pad) * w + pad..][..tw] };
    if layers.len() == 2 && c0 <= MAX_HIDDEN && layers[1].cout == 1 {
        // The common blend (one hidden layer): pixels in register blocks.
        let (l1, full) = (&layers[1], tw / LANES * LANES);
        for b0 in (0..full).step_by(LANES) {
            logits_block::<LANES>((l0, l1, cf), (yf, tw), &row, b0, ha);
        }
        for b0 in full..tw {
            logits_block::<1>((l0, l1, cf), (yf, tw), &row, b0, ha);
        }
        return;
    }
    // Layer 0: the features' part, the bias and the colour part.
    for oc in 0..c0 {
        let ho = &mut ha[oc * tw..][..tw];
        ho.copy_from_slice(&yf[oc * tw..][..tw]);
        for ic in 0..cf {
            let wgt = l0.weight[oc * l0.cin + ic];
            for (y, &ev) in ho.iter_mut().zip(row(ic)) {
                *y += wgt * ev;
            }
        }
        let b = l0.bias[oc];
        for y in ho.iter_mut() {
            *y += b;
            if last > 0 {
                *y = y.max(0.0);
            }
        }
    }
    for (li, l) in layers.iter().enumerate().skip(1) {
        for oc in 0..l.cout {
            let ho = &mut hb[oc * tw..][..tw];
            ho.iter_mut().for_each(|y| *y = l.bias[oc]);
            for ic in 0..l.cin {
                let wgt = l.weight[oc * l.cin + ic];
                for (y, &hv) in ho.iter_mut().zip(&ha[ic * tw..][..tw]) {
                    *y += wgt * hv;
                }
            }
            if li < last {
                ho.iter_mut().for_each(|y| *y = y.max(0.0));
            }
        }
        std::mem::swap(ha, hb);
    }
}

/// View `k`'s share of row `r` of item `i`: its bounded `weights` times its alphas added
/// to `den`, and times its colours to `num` `[3, tw]` (f64).
#[inline(always)]
fn add_view(
    ctx: &Ctx,
    (i, k, r): (usize, usize, usize),
    weights: &[f32],
    den: &mut [f64],
    num: &mut [f64],
) {
    let ((v, _, _, h, w), (_, tw, pad)) = (ctx.dims, ctx.tile);
    let src =
        |ch: usize| -> &[f32] { &ctx.xd[(((i * v + k) * 4 + ch) * h + r + pad) * w + pad..][..tw] };
    let (rgb, alpha) = ([src(0), src(1), src(2)], src(3));
    for c in 0..tw {
        let ex = wide(weights[c] * alpha[c]);
        den[c] += ex;
        for (ch, s) in rgb.iter().enumerate() {
            num[ch * tw + c] += ex * wide(s[c]);
        }
    }
}

/// Pixels per register block of [`logits_block`].
const LANES: usize = 8;
/// Most hidden channels [`logits_block`] keeps in registers.
const MAX_HIDDEN: usize = 8;

/// One view's logits at pixels `b0..b0 + N` of a row into `logits` for a blend of one
/// hidden layer `l0` (at most [`MAX_HIDDEN`] channels, ReLU) and the logit layer `l1`:
/// `yf` holds the colour features' part of `l0` (`[C_0, tw]`), `row(c)` the row of the
/// view's feature `c < cf`. The same operations in the same order as the row-by-row
/// layers in [`item`] (so the same bits), with the `N` pixels' sums side by side in
/// registers.
#[inline(always)]
fn logits_block<'a, const N: usize>(
    (l0, l1, cf): (&Dense, &Dense, usize),
    (yf, tw): (&[f32], usize),
    row: &impl Fn(usize) -> &'a [f32],
    b0: usize,
    logits: &mut [f32],
) {
    let mut hidden = [[0f32; N]; MAX_HIDDEN];
    for (oc, hv) in hidden.iter_mut().enumerate().take(l0.cout) {
        // A local sum (registers), stored once: `hidden` is indexed at run time.
        let mut acc = [0f32; N];
        acc.copy_from_slice(&yf[oc * tw + b0..][..N]);
        for ic in 0..cf {
            let wgt = l0.weight[oc * l0.cin + ic];
            for (y, &ev) in acc.iter_mut().zip(&row(ic)[b0..][..N]) {
                *y += wgt * ev;
            }
        }
        let b = l0.bias[oc];
        for y in acc.iter_mut() {
            *y += b;
            *y = y.max(0.0);
        }
        *hv = acc;
    }
    let mut y = [l1.bias[0]; N];
    for (ic, hv) in hidden.iter().enumerate().take(l1.cin) {
        let wgt = l1.weight[ic];
        for (yv, &h) in y.iter_mut().zip(hv) {
            *yv += wgt * h;
        }
    }
    logits[b0..][..N].copy_from_slice(&y);
}
