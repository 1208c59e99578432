//! Rendering only: the any-number-of-views family's colour blend (`pool::Blend`) as one
//! pass over the tile's pixels, row by row: the blend's 1x1 layers on `[e_v, f]` (the
//! colour features' part once per pixel, not per view), ReLU between them, the bounded
//! logit, the alpha-masked softmax over the views and the weighted source colours. It reads
//! the view features and the sources straight from level 0's uncropped tensors, so none
//! of the crops, reshapes and per-layer tensors of the composition are built. The same
//! maths as `Blend::forward` (tests compare them); f32 on the CPU only, no gradient.

use super::blend::bounded_exp;
use super::data;
use super::pool::wide;
use crate::pool::BLEND_EPS;
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
    let c0 = layers[0].cout;
    let widest = layers.iter().map(|l| l.cout).max().unwrap_or(1);
    out.par_chunks_mut(3 * p).enumerate().for_each(|(i, o)| {
        // Scratch per item: the colour part of layer 0 per pixel of a row, two layer
        // buffers, and the f64 sums over views of one row.
        let mut yf = vec![0f32; c0 * tw];
        let (mut ha, mut hb) = (vec![0f32; widest * tw], vec![0f32; widest * tw]);
        let mut den = vec![0f64; tw];
        let mut num = vec![0f64; 3 * tw];
        let l0 = &layers[0];
        for r in 0..th {
            yf.iter_mut().for_each(|y| *y = 0.0);
            for oc in 0..c0 {
                let yo = &mut yf[oc * tw..][..tw];
                for ic in 0..cc {
                    let wgt = l0.weight[oc * l0.cin + cf + ic];
                    let fr = &fd[((i * cc + ic) * th + r) * tw..][..tw];
                    for (y, &fv) in yo.iter_mut().zip(fr) {
                        *y += wgt * fv;
                    }
                }
            }
            den.iter_mut().for_each(|d| *d = BLEND_EPS);
            num.iter_mut().for_each(|s| *s = 0.0);
            for k in 0..v {
                let row = |c: usize| -> &[f32] {
                    &ed[(((i * v + k) * cf + c) * h + r + pad) * w + pad..][..tw]
                };
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
                    std::mem::swap(&mut ha, &mut hb);
                }
                // `ha[..tw]` holds the logits; the weights and the sums over views.
                let src = |ch: usize| -> &[f32] {
                    &xd[(((i * v + k) * 4 + ch) * h + r + pad) * w + pad..][..tw]
                };
                let (rgb, alpha) = ([src(0), src(1), src(2)], src(3));
                for c in 0..tw {
                    let ex = wide(bounded_exp(ha[c]) * alpha[c]);
                    den[c] += ex;
                    for (ch, s) in rgb.iter().enumerate() {
                        num[ch * tw + c] += ex * wide(s[c]);
                    }
                }
            }
            for ch in 0..3 {
                for c in 0..tw {
                    o[ch * p + r * tw + c] = (num[ch * tw + c] / den[c]) as f32;
                }
            }
        }
    });
    Ok(Some(Tensor::from_vec(out, (n, 3, p), e.device())?))
}
