//! Rendering only: the any-number-of-views family's per-view encoder and the pooling over
//! views of one input level (`pool::ViewEncoder::forward`'s steps 1-3) as one pass over
//! each plane's pixels, a chunk of [`CHUNK`] pixels at a time, instead of three passes
//! over whole tensors ([`super::pool_front`], the encoder's 1x1 chain, [`super::pooled_stats`]):
//! the encoder's input (RGBA, colour minus the mean, and the cue when the level carries
//! one) and its layers' activations live
//! in a per-thread scratch that stays in L1, and the view features are written out only
//! where the blend reads them (level 0).
//!
//! The arithmetic and its order are those of the three passes, bit for bit: the mean
//! colour and the moments summed over views in f64 in view order, the colour difference
//! in f32, and every 1x1 layer as the AVX2 kernels compute it (`acc = bias`, then one
//! fused multiply-add per input channel in channel order, then ReLU). It runs only where
//! those kernels run (f32 on a CPU with AVX2 and FMA); the tests compare it with the
//! three passes.

use super::blend_infer::Dense;
use super::data;
use super::pool::{cast, wide};
use crate::config::{ENCODER_IN, POOL_EPS};
use candle_core::{bail, DType, Result, Tensor};
use rayon::prelude::*;

/// Pixels per chunk: the scratch of a few views' activations stays in L1.
const CHUNK: usize = 64;
/// Pixels summed at once in [`dense_relu`] (one AVX register); divides [`CHUNK`].
const LANES: usize = 8;

/// `(stats [N, 4 + 2 C, P], features [N, V, C, P] when `features`)` from the sources `x`
/// `[N, V, C_v, P]` (RGBA, then each view's other channels the encoder reads: with
/// `C_v` = 4 + [`crate::config::CUE_CHANNELS`] its cue, with the features family its warped source
/// features) and the encoder's 1x1 layers (each followed by ReLU; the first takes
/// `7 + C_v - 4` channels, in the order RGBA, colour minus mean, the other channels). `None` where it does not apply (not
/// f32, not on the CPU, no AVX2 + FMA, layers that do not chain): the caller runs the
/// three passes.
pub fn encode_pool(
    x: &Tensor,
    layers: &[Dense],
    features: bool,
) -> Result<Option<(Tensor, Option<Tensor>)>> {
    let (n, v, cv, p) = x.dims4()?;
    if cv < 4 {
        bail!(
            "encode_pool: expected [N, V, C_v >= 4, P], got {:?}",
            x.dims()
        );
    }
    let chained = layers.windows(2).all(|l| l[0].cout == l[1].cin);
    let usable = x.dtype() == DType::F32
        && x.device().is_cpu()
        && crate::cpu::avx2_fma_available()
        && layers.first().is_some_and(|l| l.cin == ENCODER_IN + cv - 4)
        && chained
        && v > 0;
    if !usable || n * p == 0 {
        return Ok(None);
    }
    let c = layers[layers.len() - 1].cout;
    let widest = layers.iter().map(|l| l.cout).max().unwrap_or(c);
    let x = x.contiguous()?;
    let (xs, xl) = x.storage_and_layout();
    let xd = data::<f32>(&xs, xl)?;
    let mut stats = vec![0f32; n * (4 + 2 * c) * p];
    let mut feats = vec![0f32; if features { n * v * c * p } else { 0 }];
    let per_item = if features { v * c * p } else { 0 };
    let mut feat_items: Vec<&mut [f32]> = match features {
        true => feats.chunks_mut(per_item.max(1)).collect(),
        false => (0..n).map(|_| <&mut [f32]>::default()).collect(),
    };
    stats
        .par_chunks_mut((4 + 2 * c) * p)
        .zip(feat_items.par_iter_mut())
        .enumerate()
        .for_each(|(i, (st, fe))| {
            let xi = &xd[i * v * cv * p..][..v * cv * p];
            let dims = Dims {
                v,
                cv,
                c,
                p,
                widest,
            };
            // SAFETY: `usable` checked AVX2 and FMA.
            #[cfg(target_arch = "x86_64")]
            unsafe {
                item_avx2(xi, layers, dims, st, fe)
            }
        });
    drop(feat_items);
    let dev = x.device();
    let stats = Tensor::from_vec(stats, (n, 4 + 2 * c, p), dev)?;
    let feats = match features {
        true => Some(Tensor::from_vec(feats, (n, v, c, p), dev)?),
        false => None,
    };
    Ok(Some((stats, feats)))
}

/// Views, channels per view in the input, feature channels, pixels per plane, and the
/// widest layer (scratch rows).
#[derive(Clone, Copy)]
struct Dims {
    v: usize,
    cv: usize,
    c: usize,
    p: usize,
    widest: usize,
}

/// One plane: `xi` `[V, C_v, P]` -> `st` `[4 + 2C, P]` and (when not empty) `fe` `[V, C, P]`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn item_avx2(xi: &[f32], layers: &[Dense], d: Dims, st: &mut [f32], fe: &mut [f32]) {
    let mut sc = Scratch::new(d);
    let mut j0 = 0;
    while j0 < d.p {
        let ch = Chunk {
            xi,
            d,
            j0,
            len: CHUNK.min(d.p - j0),
        };
        mean_cover(ch, &mut sc, st);
        for k in 0..d.v {
            encode_view(ch, layers, k, &mut sc);
            if !fe.is_empty() {
                for c in 0..d.c {
                    fe[(k * d.c + c) * d.p + j0..][..ch.len]
                        .copy_from_slice(&sc.e[(k * d.c + c) * CHUNK..][..ch.len]);
                }
            }
        }
        feature_moments(ch, &mut sc, st);
        j0 += ch.len;
    }
}

/// The per-thread scratch of [`item_avx2`]: the encoder's input, two layer buffers, every
/// view's features, and the f64 sums, of one chunk.
struct Scratch {
    input: Vec<f32>,
    ha: Vec<f32>,
    hb: Vec<f32>,
    e: Vec<f32>,
    cover: [f64; CHUNK],
    den: [f64; CHUNK],
    s64: [f64; CHUNK],
    mean: [f32; 3 * CHUNK],
}

impl Scratch {
    #[inline(always)]
    fn new(d: Dims) -> Self {
        Scratch {
            input: vec![0f32; (ENCODER_IN + d.cv - 4) * CHUNK],
            ha: vec![0f32; d.widest * CHUNK],
            hb: vec![0f32; d.widest * CHUNK],
            e: vec![0f32; d.v * d.c * CHUNK],
            cover: [0f64; CHUNK],
            den: [0f64; CHUNK],
            s64: [0f64; CHUNK],
            mean: [0f32; 3 * CHUNK],
        }
    }
}

/// One chunk of a plane: pixels `j0..j0 + len` of the sources `xi` `[V, C_v, P]`.
#[derive(Clone, Copy)]
struct Chunk<'a> {
    xi: &'a [f32],
    d: Dims,
    j0: usize,
    len: usize,
}

impl<'a> Chunk<'a> {
    /// Channel `ch` of view `k` over the chunk.
    #[inline(always)]
    fn plane(&self, k: usize, ch: usize) -> &'a [f32] {
        &self.xi[(k * self.d.cv + ch) * self.d.p + self.j0..][..self.len]
    }
}

/// The coverage and the mean colour (pool_front's sums: view 0's term first) into the
/// scratch and `st`'s first four rows.
#[inline(always)]
fn mean_cover(x: Chunk, sc: &mut Scratch, st: &mut [f32]) {
    let (Dims { v, p, .. }, j0, len) = (x.d, x.j0, x.len);
    for k in 0..v {
        for (s, &a) in sc.cover[..len].iter_mut().zip(x.plane(k, 3)) {
            *s = if k == 0 { wide(a) } else { *s + wide(a) };
        }
    }
    for ch in 0..3 {
        for k in 0..v {
            let (a, col) = (x.plane(k, 3), x.plane(k, ch));
            for j in 0..len {
                let t = wide(a[j]) * wide(col[j]);
                sc.s64[j] = if k == 0 { t } else { sc.s64[j] + t };
            }
        }
        let (m, out) = (
            &mut sc.mean[ch * CHUNK..][..len],
            &mut st[ch * p + j0..][..len],
        );
        for j in 0..len {
            m[j] = cast(sc.s64[j] / (sc.cover[j] + POOL_EPS));
            out[j] = m[j];
        }
    }
    for (o, &cv) in st[3 * p + j0..][..len].iter_mut().zip(&sc.cover[..len]) {
        *o = cast(cv / (cv + 1.0));
    }
}

/// The encoder on view `k` of the chunk: its input (RGBA, colour minus the mean, the
/// cue), layer 0 from it, the hidden layers between `ha` and `hb`, the last into the
/// view's features in `e`.
#[inline(always)]
fn encode_view(x: Chunk, layers: &[Dense], k: usize, sc: &mut Scratch) {
    let (Dims { cv, c, .. }, len) = (x.d, x.len);
    let input = &mut sc.input;
    for ch in 0..4 {
        input[ch * CHUNK..][..len].copy_from_slice(x.plane(k, ch));
    }
    for ch in 0..3 {
        let (src, m) = (x.plane(k, ch), &sc.mean[ch * CHUNK..][..len]);
        let dst = &mut input[(4 + ch) * CHUNK..][..len];
        for j in 0..len {
            dst[j] = src[j] - m[j];
        }
    }
    for ch in 4..cv {
        input[(ENCODER_IN + ch - 4) * CHUNK..][..len].copy_from_slice(x.plane(k, ch));
    }
    let ek = &mut sc.e[k * c * CHUNK..][..c * CHUNK];
    let (ha, hb) = (&mut sc.ha, &mut sc.hb);
    let nl = layers.len();
    if nl == 1 {
        dense_relu(&layers[0], input, ek, len);
    } else {
        dense_relu(&layers[0], input, ha, len);
        for (li, l) in layers.iter().enumerate().skip(1) {
            match (li + 1 == nl, li % 2) {
                (true, 1) => dense_relu(l, ha, ek, len),
                (true, _) => dense_relu(l, hb, ek, len),
                (false, 1) => dense_relu(l, ha, hb, len),
                (false, _) => dense_relu(l, hb, ha, len),
            }
        }
    }
}

/// Alpha-weighted moments of the features over views (pooled_stats' sums) into `st`'s
/// rows after the first four.
#[inline(always)]
fn feature_moments(x: Chunk, sc: &mut Scratch, st: &mut [f32]) {
    let (Dims { v, c, p, .. }, j0, len) = (x.d, x.j0, x.len);
    let (den, s64, e) = (&mut sc.den, &mut sc.s64, &sc.e);
    for (s, &a) in den[..len].iter_mut().zip(x.plane(0, 3)) {
        *s = POOL_EPS + wide(a);
    }
    for k in 1..v {
        for (s, &a) in den[..len].iter_mut().zip(x.plane(k, 3)) {
            *s += wide(a);
        }
    }
    for ch in 0..c {
        for k in 0..v {
            let (a, ek) = (x.plane(k, 3), &e[(k * c + ch) * CHUNK..][..len]);
            for j in 0..len {
                let t = wide(a[j]) * wide(ek[j]);
                s64[j] = if k == 0 { t } else { s64[j] + t };
            }
        }
        for j in 0..len {
            s64[j] /= den[j];
        }
        let mut var = [0f64; CHUNK];
        for k in 0..v {
            let (a, ek) = (x.plane(k, 3), &e[(k * c + ch) * CHUNK..][..len]);
            for j in 0..len {
                let dev = wide(ek[j]) - s64[j];
                let t = wide(a[j]) * dev * dev;
                var[j] = if k == 0 { t } else { var[j] + t };
            }
        }
        let mo = &mut st[(4 + ch) * p + j0..][..len];
        for j in 0..len {
            mo[j] = cast(s64[j]);
        }
        let vo = &mut st[(4 + c + ch) * p + j0..][..len];
        for j in 0..len {
            vo[j] = cast(var[j] / den[j]);
        }
    }
}

/// `to[o] = relu(bias[o] + sum_i w[o, i] from[i])` over the first `len` pixels rounded up
/// to [`LANES`] (rows [`CHUNK`] apart; pixels past `len` are scratch), the sum as the AVX2
/// kernels form it: from the bias, one fused multiply-add per input channel in order.
#[inline(always)]
fn dense_relu(l: &Dense, from: &[f32], to: &mut [f32], len: usize) {
    match l.cout {
        1 => dense_block::<1>(l, from, to, len, 0),
        2 => dense_block::<2>(l, from, to, len, 0),
        3 => dense_block::<3>(l, from, to, len, 0),
        4 => dense_block::<4>(l, from, to, len, 0),
        5 => dense_block::<5>(l, from, to, len, 0),
        6 => dense_block::<6>(l, from, to, len, 0),
        7 => dense_block::<7>(l, from, to, len, 0),
        8 => dense_block::<8>(l, from, to, len, 0),
        _ => {
            for o in (0..l.cout).step_by(8) {
                dense_block::<8>(l, from, to, len, o)
            }
        }
    }
}

/// Outputs `o0..o0 + O` (those that exist) of [`dense_relu`]: `O` sums of [`LANES`]
/// pixels side by side in registers, so that consecutive multiply-adds are independent.
#[inline(always)]
fn dense_block<const O: usize>(l: &Dense, from: &[f32], to: &mut [f32], len: usize, o0: usize) {
    let outs = O.min(l.cout - o0);
    for b in (0..len.div_ceil(LANES)).map(|b| b * LANES) {
        let mut acc = [[0f32; LANES]; O];
        for (o, a) in acc.iter_mut().enumerate().take(outs) {
            *a = [l.bias[o0 + o]; LANES];
        }
        for i in 0..l.cin {
            let xs = &from[i * CHUNK + b..][..LANES];
            for (o, a) in acc.iter_mut().enumerate().take(outs) {
                let w = l.weight[(o0 + o) * l.cin + i];
                for (av, &xv) in a.iter_mut().zip(xs) {
                    *av = w.mul_add(xv, *av);
                }
            }
        }
        for (o, a) in acc.iter().enumerate().take(outs) {
            for (y, &av) in to[(o0 + o) * CHUNK + b..][..LANES].iter_mut().zip(a) {
                *y = av.max(0.0);
            }
        }
    }
}
