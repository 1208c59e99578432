//! Rendering: the cue's view weights ([`crate::pool::ViewWeigh`]) in one pass over the
//! pixels, instead of a slice copy, two convolutions, `tanh` and a concatenation. The
//! layers run on blocks of pixels, channel by channel, so that the loops vectorise
//! (compiled for AVX2 + FMA where the CPU has them).

use super::{data, Dense};
use crate::config::WEIGH_SCALE;
use crate::cpu::fastmath::exp_f32;
use candle_core::{bail, DType, Result, Tensor};
use rayon::prelude::*;

/// Pixels per block.
const BLOCK: usize = 64;

/// `x` `[B, D, V, 4 + K, H, W]` -> `[B, D, V, 4, H, W]`: each view's RGB, and its alpha
/// times `1 + tanh(WEIGH_SCALE g)`, with `g` the dense `layers` (ReLU between them) on the
/// view's cue at that pixel, computed as `2 / (1 + exp(-2 WEIGH_SCALE g))` (`exp` from
/// [`exp_f32`]: rendering only), as the training forward does. `None` where it
/// does not apply (not f32 on the CPU, or layers that do not chain from `K` channels to
/// 1): the caller runs the candle ops.
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
    if c != 4 + layers[0].cin || layers[last].cout != 1 || !chained {
        return Ok(None);
    }
    let x = x.contiguous()?;
    let (st, l) = x.storage_and_layout();
    let xs = data::<f32>(&st, l)?;
    let p = h * w;
    let mut out = vec![0f32; b * d * v * 4 * p];
    out.par_chunks_mut(4 * p)
        .zip(xs.par_chunks(c * p))
        .for_each(|(o, xi)| weigh_view(xi, o, layers, p));
    Tensor::from_vec(out, (b, d, v, 4, h, w), x.device()).map(Some)
}

/// One view of one plane: `xi` `[4 + K, P]` -> `o` `[4, P]`.
fn weigh_view(xi: &[f32], o: &mut [f32], layers: &[Dense], p: usize) {
    #[cfg(target_arch = "x86_64")]
    if crate::cpu::avx2_fma_available() {
        // SAFETY: the CPU has AVX2 and FMA (checked).
        return unsafe { weigh_view_avx2(xi, o, layers, p) };
    }
    weigh_view_generic(xi, o, layers, p)
}

/// [`weigh_view_generic`] compiled for AVX2 + FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn weigh_view_avx2(xi: &[f32], o: &mut [f32], layers: &[Dense], p: usize) {
    weigh_view_generic(xi, o, layers, p)
}

#[inline(always)]
fn weigh_view_generic(xi: &[f32], o: &mut [f32], layers: &[Dense], p: usize) {
    o[..3 * p].copy_from_slice(&xi[..3 * p]);
    let width = layers.iter().map(|l| l.cin.max(l.cout)).max().unwrap_or(1);
    let (mut a, mut z) = (vec![0f32; width * BLOCK], vec![0f32; width * BLOCK]);
    let last = layers.len() - 1;
    let scale = -2.0 * WEIGH_SCALE as f32;
    for j0 in (0..p).step_by(BLOCK) {
        let m = BLOCK.min(p - j0);
        for k in 0..layers[0].cin {
            a[k * BLOCK..][..m].copy_from_slice(&xi[(4 + k) * p + j0..][..m]);
        }
        for (li, layer) in layers.iter().enumerate() {
            for (oc, zo) in z.chunks_exact_mut(BLOCK).take(layer.cout).enumerate() {
                let zo = &mut zo[..m];
                zo.fill(layer.bias[oc]);
                let row = &layer.weight[oc * layer.cin..][..layer.cin];
                for (&wi, ai) in row.iter().zip(a.chunks_exact(BLOCK)) {
                    for (zz, &aa) in zo.iter_mut().zip(&ai[..m]) {
                        *zz += wi * aa;
                    }
                }
                if li < last {
                    for zz in zo.iter_mut() {
                        *zz = zz.max(0.0);
                    }
                }
            }
            std::mem::swap(&mut a, &mut z);
        } // a[..m]: g
        let (alpha, dst) = (&xi[3 * p + j0..][..m], &mut o[3 * p + j0..][..m]);
        for ((dv, &av), &g) in dst.iter_mut().zip(alpha).zip(&a[..m]) {
            *dv = av * 2.0 / (1.0 + exp_f32(scale * g));
        }
    }
}
