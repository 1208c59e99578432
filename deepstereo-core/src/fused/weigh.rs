//! Rendering: the cue's view weights ([`crate::pool::ViewWeigh`]) in one pass over the
//! pixels, instead of a slice copy, two convolutions, `tanh` and a concatenation.

use super::{data, Dense};
use crate::config::{CUE_CHANNELS, WEIGH_SCALE};
use candle_core::{bail, DType, Result, Tensor};
use rayon::prelude::*;

/// `x` `[B, D, V, 4 + K, H, W]` -> `[B, D, V, 4, H, W]`: each view's RGB, and its alpha
/// times `1 + tanh(WEIGH_SCALE g)`, with `g` the dense `layers` (ReLU between them) on the view's
/// cue at that pixel. `None` where it does not apply (not f32 on the CPU, or layers that
/// do not chain from `K` channels to 1): the caller runs the candle ops.
pub fn weigh_views(x: &Tensor, layers: &[Dense]) -> Result<Option<Tensor>> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() || layers.is_empty() {
        return Ok(None);
    }
    let (b, d, v, c, h, w) = match *x.dims() {
        [b, d, v, c, h, w] => (b, d, v, c, h, w),
        ref got => bail!("weigh_views: expected [B, D, V, C, H, W], got {got:?}"),
    };
    let last = layers.len() - 1;
    let chained = layers.windows(2).all(|p| p[0].cout == p[1].cin);
    if c != 4 + CUE_CHANNELS || layers[0].cin != CUE_CHANNELS || layers[last].cout != 1 || !chained
    {
        return Ok(None);
    }
    let x = x.contiguous()?;
    let (st, l) = x.storage_and_layout();
    let xs = data::<f32>(&st, l)?;
    let p = h * w;
    let width = layers.iter().map(|l| l.cin.max(l.cout)).max().unwrap_or(1);
    let mut out = vec![0f32; b * d * v * 4 * p];
    let scale = WEIGH_SCALE as f32;
    out.par_chunks_mut(4 * p)
        .zip(xs.par_chunks(c * p))
        .for_each(|(o, xi)| {
            o[..3 * p].copy_from_slice(&xi[..3 * p]);
            let (mut a, mut z) = (vec![0f32; width], vec![0f32; width]);
            for j in 0..p {
                for (k, ak) in a.iter_mut().take(CUE_CHANNELS).enumerate() {
                    *ak = xi[(4 + k) * p + j];
                }
                for (li, layer) in layers.iter().enumerate() {
                    let rows = layer.weight.chunks_exact(layer.cin);
                    for ((zo, row), &bias) in z.iter_mut().zip(rows).zip(&layer.bias) {
                        let s = row.iter().zip(&a).fold(bias, |s, (wi, ai)| s + wi * ai);
                        *zo = if li < last { s.max(0.0) } else { s };
                    }
                    std::mem::swap(&mut a, &mut z);
                }
                o[3 * p + j] = xi[3 * p + j] * (1.0 + (scale * a[0]).tanh());
            }
        });
    Tensor::from_vec(out, (b, d, v, 4, h, w), x.device()).map(Some)
}
