//! The any-number-of-views family's view pooling and colour blend ([`ViewPool`]).
//!
//! The paper's network concatenates the sources' RGBA along channels, so it takes a fixed
//! number of views in a fixed order. This family removes both limits: every step that
//! sees views either runs on each view alone with weights shared across views, or
//! combines views by alpha-weighted sums, which do not depend on the views' order and
//! are unchanged by a view whose alpha is zero (it adds exact zeros).
//!
//! Per input level, with `N = B * D` planes folded into the batch and `a_v` a view's
//! alpha (1 where the source sees the pixel):
//! 1. `m = sum_v a_v rgb_v / (sum_v a_v + eps)`: the mean colour, `[N, 1, 3, H, W]`.
//! 2. `e_v = encoder([rgba_v, rgb_v - m])`: 1x1 layers, ReLU after each, on
//!    `[N * V, 7, H, W]` -> `[N, V, C_f, H, W]`. With the cue (`ViewPool::cue`), the
//!    input level is `[B, D, V, 4 + K, H, W]` (each view's RGBA, then its
//!    [`crate::sweep::cue`] of `K` channels) and the encoder reads
//!    `[rgba_v, rgb_v - m, cue_v]`, `[N * V, 7 + K, H, W]`: the cue reaches the pooled
//!    statistics and the blend through `e_v`, while the weights of the pooling and the
//!    blend stay the alphas (a view that is not there still adds exact zeros).
//! 3. Tower input `[m, s / (1 + s), mean_a(e), var_a(e)]`: `[B, D, 4 + 2 C_f, H, W]`,
//!    where `s = sum_v a_v` (how many views see the pixel, bounded) and `mean_a` /
//!    `var_a` are the alpha-weighted mean and variance over views (variance is the
//!    classical photo-consistency cue).
//!
//! The towers then run as in the paper's family. The colour at each plane is
//! `sum_v w_v rgb_v + out(f)`: a learned per-pixel blend of the source colours plus the
//! colour tower's linear RGB (`f`: its features `[N, C_c, th, tw]`), with
//! `w_v = a_v exp(l_v) / (sum_u a_u exp(l_u) + eps)` and the logit
//! `l_v = B tanh(blend([e_v, f]) / B)` (1x1 layers, ReLU between, bounded by
//! [`BLEND_LOGIT_BOUND`] so that `exp` never overflows, whatever a view that is not there
//! computes).
//!
//! With [`ViewPool::weigh`], the cue weighs the views before all of this
//! ([`ViewWeigh`]): each view's alpha becomes `a_v k_v` with
//! `k_v = 1 + tanh(S g(cue_v))` (computed as `2 sigmoid(2 S g)`, which keeps a small
//! weight's relative precision in f32 where `1 + tanh` cancels; in `(0, 2)`, `S` = [`WEIGH_SCALE`];
//! `g`: 1x1 layers, ReLU between; the last one starts at zero, so that `k_v = 1`, and
//! `python/add_cue.py --weigh` adds them so to a trained model, which then renders as it
//! did), and steps 1-3 and the blend read that alpha. The cue thus sets how much each
//! view counts in the mean, the variance and the blend, without entering the features
//! whose variance is pooled; a view that is not there still has alpha 0, and `k_v`
//! depends on its own cue alone, so the order of the views still does not matter. With
//! [`ViewPool::disagree`], the cue has one more channel, the view's colour disagreement
//! with the nearest views (`crate::view_weights::disagreement`; `python/add_cue.py
//! --disagree` adds its zero column to a trained model's `g`), so `k_v` can turn down a
//! view that shows something else than the nearest ones there.
//!
//! Parameter names (equal to the PyTorch reference's): `views.encode.{i}.{weight,bias}`,
//! `colour.blend.{i}.{weight,bias}` (the last one the 1-channel logit layer),
//! `views.weigh.{i}.{weight,bias}` (the last one the 1-channel `g`).

use crate::config::{ViewPool, ENCODER_IN, WEIGH_SCALE};
use crate::conv::{pointwise_chain, Conv2d};
use crate::fused;
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::VarBuilder;

pub use crate::config::{BLEND_EPS, BLEND_LOGIT_BOUND, POOL_EPS};

/// The per-view encoder (`views.encode.*`).
#[derive(Debug, Clone)]
pub struct ViewEncoder {
    convs: Vec<Conv2d>,
    /// Channels of one view in an input level ([`ViewPool::view_channels`]): 4, or with
    /// the cue after the RGBA 4 + `K` ([`ViewPool::cue_channels`]); then the features
    /// family's `F` warped source features.
    view_channels: usize,
    /// `F` ([`ViewPool::feature_channels`]; 0 for other models).
    feature_channels: usize,
}

/// One level's pooled tower input and, for the colour blend, the views' features.
pub struct Pooled {
    /// `[B, D, 4 + 2 C_f, H, W]`.
    pub stats: Tensor,
    /// `[B * D, V, C_f, H, W]`.
    pub features: Tensor,
}

/// Splits an input level `[B, D, V, C_v, H, W]` into `(B*D, V, H, W, B)`, checking the
/// rank and that `C_v` is `channels` (4, or 4 + `K` with the cue).
pub fn view_dims(x: &Tensor, channels: usize) -> Result<(usize, usize, usize, usize, usize)> {
    match *x.dims() {
        [b, d, v, c, h, w] if c == channels => Ok((b * d, v, h, w, b)),
        ref got => candle_core::bail!(
            "expected an input level [B, D, V, {channels}, H, W] (any-number-of-views model{}), got {got:?}",
            if channels > 4 { " with the per-view cue" } else { "" }
        ),
    }
}

/// The RGBA of every view of an input level `[B, D, V, C_v, H, W]`: `[B, D, V, 4, H, W]`,
/// contiguous (the level itself when it has no cue).
pub fn rgba(x: &Tensor) -> Result<Tensor> {
    match x.dim(3)? {
        4 => Ok(x.clone()),
        _ => x.narrow(3, 0, 4)?.contiguous(),
    }
}

/// `sum_v a_v t_v / den` over dim 1: `t` `[N, V, C, H, W]`, `a` `[N, V, 1, H, W]`,
/// `den` `[N, 1, 1, H, W]` -> `[N, 1, C, H, W]`.
fn weighted_mean(t: &Tensor, a: &Tensor, den: &Tensor) -> Result<Tensor> {
    t.broadcast_mul(a)?.sum_keepdim(1)?.broadcast_div(den)
}

impl ViewEncoder {
    pub fn new(pool: &ViewPool, vb: VarBuilder) -> Result<Self> {
        let mut ch = pool.encoder_in();
        let mut convs = Vec::with_capacity(pool.encoder.len());
        for (i, c) in pool.encoder.iter().enumerate() {
            convs.push(Conv2d::new(ch, c.channels, (1, 1), vb.pp(i))?);
            ch = c.channels;
        }
        Ok(Self {
            convs,
            view_channels: pool.encoder_view_channels(),
            feature_channels: pool.feature_channels(),
        })
    }

    /// Channels of one view in an input level.
    pub fn view_channels(&self) -> usize {
        self.view_channels
    }

    /// What the encoder reads of every view besides its colours, `[B * D * V, K + F, H, W]`:
    /// the cue of `x` `[B, D, V, 4 + K, H, W]` (`K` 0 without it), then the source
    /// features `feats` `[B, D, V, F, H, W]`; `None` when there is neither.
    fn extra_of(&self, x: &Tensor, feats: Option<&Tensor>) -> Result<Option<Tensor>> {
        let (n, v, h, w, _) = view_dims(x, self.view_channels - self.feature_channels)?;
        let k = x.dim(3)? - 4;
        let cue = match k {
            0 => None,
            _ => Some(x.narrow(3, 4, k)?.contiguous()?.reshape((n * v, k, h, w))?), // [N*V, K, H, W]
        };
        let feats = match feats {
            Some(f) => Some(
                f.contiguous()?
                    .reshape((n * v, self.feature_channels, h, w))?,
            ), // [N*V, F, H, W]
            None => None,
        };
        match (cue, feats) {
            (Some(c), Some(f)) => Ok(Some(Tensor::cat(&[&c, &f], 1)?)),
            (c, f) => Ok(c.or(f)),
        }
    }

    /// An input level `[B, D, V, C_v, H, W]` split into the part before the source
    /// features and the features (`None` for other models).
    fn split(&self, x: &Tensor) -> Result<(Tensor, Option<Tensor>)> {
        let f = self.feature_channels;
        if f == 0 {
            return Ok((x.clone(), None));
        }
        let c = x.dim(3)?;
        Ok((x.narrow(3, 0, c - f)?, Some(x.narrow(3, c - f, f)?)))
    }

    /// Steps 1-3 of the module doc for one level `x` `[B, D, V, C_v, H, W]`: fused passes
    /// on the CPU (`fused/pool.rs`), else candle ops ([`Self::forward_reference`]).
    /// With `fuse` (rendering: no gradients), the encoder runs as one fused chain and the
    /// pooled statistics are written in one buffer ([`fused::pooled_stats`]).
    /// Where `x` carries a gradient (its alpha weighed by [`ViewWeigh`] in training), the
    /// passes return it ([`fused::pool_front`], [`fused::view_stats`]), and no `fuse`.
    pub fn forward(&self, x: &Tensor, fuse: bool) -> Result<Pooled> {
        view_dims(x, self.view_channels())?;
        let (base, feats) = self.split(x)?;
        self.forward_parts(&base, feats.as_ref(), fuse)
    }

    /// [`Self::forward`] with the features family's maps `feats` `[B, D, V, F, H, W]`
    /// apart from the rest of the level `x` `[B, D, V, C_v - F, H, W]`: training keeps
    /// them apart, since a slice of a tensor that carries a gradient costs a copy of the
    /// whole tensor in the backward pass.
    pub fn forward_parts(&self, x: &Tensor, feats: Option<&Tensor>, fuse: bool) -> Result<Pooled> {
        let (n, v, h, w, b) = view_dims(x, self.view_channels - self.feature_channels)?;
        // Where `x` carries a gradient (weighed alphas), the fused passes return it to the
        // RGBA; the cue and the features reach the encoder through candle's ops.
        let tracked = x.track_op() || feats.is_some_and(|f| f.track_op());
        let fuse = fuse && !tracked;
        let xp = rgba(x)?.reshape((n, v, 4, h * w))?; // [N, V, 4, P]
        let Some((enc, front)) = fused::pool_front(&xp)? else {
            return self.forward_reference_parts(x, feats);
        };
        let enc = enc.reshape((n * v, ENCODER_IN, h, w))?; // [N*V, 7, H, W]
        let enc = match self.extra_of(x, feats)? {
            Some(extra) => Tensor::cat(&[&enc, &extra], 1)?, // [N*V, 7 + K + F, H, W]
            None => enc,
        };
        let chained = match fuse {
            true => pointwise_chain(&enc, &self.convs.iter().collect::<Vec<_>>())?,
            false => None,
        };
        let e = match chained {
            Some(e) => e,
            None => self.encode(enc)?,
        }; // [N*V, C_f, H, W]
        let cf = e.dim(1)?;
        let e = e.reshape((n, v, cf, h * w))?; // [N, V, C_f, P]
                                               // Rendering: the moments written straight after `front` (no gradient, no copy);
                                               // training: the differentiable moments, then the concatenation.
        let stats = match fuse {
            true => fused::pooled_stats(&front, &e, &xp)?,
            false => match fused::view_stats(&e, &xp)? {
                Some(moments) => Some(Tensor::cat(&[&front, &moments], 1)?), // [N, 2 C_f, P] after [N, 4, P]
                None => None,
            },
        };
        let Some(stats) = stats else {
            return self.forward_reference_parts(x, feats);
        }; // [N, 4 + 2 C_f, P]
        let stats = stats.reshape((b, n / b.max(1), 4 + 2 * cf, h, w))?; // [B, D, 4 + 2 C_f, H, W]
        let features = e.reshape((n, v, cf, h, w))?; // [N, V, C_f, H, W]
        Ok(Pooled { stats, features })
    }

    /// Rendering: steps 1-3 for one level `x` `[B, D, V, C_v, H, W]` as one fused pass
    /// ([`fused::encode_pool`]: the same values as [`Self::forward`]'s passes, bit for bit
    /// for encoders of two or more layers; a one-layer encoder runs there as a candle
    /// convolution, which sums in another order, and agrees to rounding): the stats
    /// `[B, D, 4 + 2 C_f, H, W]` and, with `features` (level 0, where the blend reads
    /// them), the view features `[B * D, V, C_f, H, W]`. `None` where the fused pass does
    /// not run (the caller then runs [`Self::forward`]).
    pub fn infer(&self, x: &Tensor, features: bool) -> Result<Option<(Tensor, Option<Tensor>)>> {
        let (n, v, h, w, b) = view_dims(x, self.view_channels())?;
        let Some(layers) = dense_layers(&self.convs)? else {
            return Ok(None);
        };
        let xp = x.reshape((n, v, self.view_channels(), h * w))?; // [N, V, C_v, P]
        let Some((stats, e)) = fused::encode_pool(&xp, &layers, features)? else {
            return Ok(None);
        };
        let c = stats.dim(1)?;
        let stats = stats.reshape((b, n / b.max(1), c, h, w))?; // [B, D, 4 + 2 C_f, H, W]
        let e = match e {
            Some(e) => Some(e.reshape((n, v, (c - 4) / 2, h, w))?), // [N, V, C_f, H, W]
            None => None,
        };
        Ok(Some((stats, e)))
    }

    fn encode(&self, mut e: Tensor) -> Result<Tensor> {
        for conv in &self.convs {
            e = conv.forward_relu(&e)?;
        }
        Ok(e)
    }

    /// [`Self::forward`] as candle ops (the fused passes' reference and fallback).
    pub fn forward_reference(&self, x: &Tensor) -> Result<Pooled> {
        view_dims(x, self.view_channels())?;
        let (base, feats) = self.split(x)?;
        self.forward_reference_parts(&base, feats.as_ref())
    }

    /// [`Self::forward_reference`] with the source features apart ([`Self::forward_parts`]).
    pub fn forward_reference_parts(&self, x_in: &Tensor, feats: Option<&Tensor>) -> Result<Pooled> {
        let (n, v, h, w, b) = view_dims(x_in, self.view_channels - self.feature_channels)?;
        let x = rgba(x_in)?.reshape((n, v, 4, h, w))?; // [N, V, 4, H, W]
        let rgb = x.narrow(2, 0, 3)?; // [N, V, 3, H, W]
        let a = x.narrow(2, 3, 1)?; // [N, V, 1, H, W]
        let asum = a.sum_keepdim(1)?; // [N, 1, 1, H, W]
        let den = (&asum + POOL_EPS)?; // [N, 1, 1, H, W]
        let mean_rgb = weighted_mean(&rgb, &a, &den)?; // [N, 1, 3, H, W]
        let diff = rgb.broadcast_sub(&mean_rgb)?; // [N, V, 3, H, W]
        let e_in = Tensor::cat(&[&x, &diff], 2)?.reshape((n * v, ENCODER_IN, h, w))?; // [N*V, 7, H, W]
        let e_in = match self.extra_of(x_in, feats)? {
            Some(extra) => Tensor::cat(&[&e_in, &extra], 1)?, // [N*V, 7 + K + F, H, W]
            None => e_in,
        };
        let e = self.encode(e_in)?;
        let cf = e.dim(1)?;
        let e = e.reshape((n, v, cf, h, w))?; // [N, V, C_f, H, W]
        let mean_e = weighted_mean(&e, &a, &den)?; // [N, 1, C_f, H, W]
        let var_e = weighted_mean(&e.broadcast_sub(&mean_e)?.sqr()?, &a, &den)?; // [N, 1, C_f, H, W]
        let cover = asum.div(&(&asum + 1.0)?)?; // [N, 1, 1, H, W]
        let stats = Tensor::cat(&[&mean_rgb, &cover, &mean_e, &var_e], 2)? // [N, 1, 4 + 2 C_f, H, W]
            .reshape((b, n / b.max(1), 4 + 2 * cf, h, w))?; // [B, D, 4 + 2 C_f, H, W]
        Ok(Pooled { stats, features: e })
    }
}

/// The cue's view weights (`views.weigh.*`, [`ViewPool::weigh`]; module doc).
#[derive(Debug, Clone)]
pub struct ViewWeigh {
    /// Hidden layers, then the 1-channel `g` (starting at zero, in [`Self::new`] and
    /// `weights::init_seeded`).
    layers: Vec<Conv2d>,
    /// Channels of each view's cue `K` ([`ViewPool::cue_channels`]).
    cue_channels: usize,
}

impl ViewWeigh {
    /// `hidden`: the hidden layers' widths ([`ViewPool::weigh`]); `cue_channels`: `K`.
    pub fn new(
        hidden: &[crate::config::Conv],
        cue_channels: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let mut ch = cue_channels;
        let mut layers = Vec::with_capacity(hidden.len() + 1);
        for (i, c) in hidden.iter().enumerate() {
            layers.push(Conv2d::new(ch, c.channels, (1, 1), vb.pp(i))?);
            ch = c.channels;
        }
        layers.push(Conv2d::zeros(ch, 1, (1, 1), vb.pp(hidden.len()))?);
        Ok(Self {
            layers,
            cue_channels,
        })
    }

    /// Each view's weight `k_v = 1 + tanh(WEIGH_SCALE g(cue_v))` from an input level `x`
    /// `[B, D, V, 4 + K, H, W]`: `[B, D, V, 1, H, W]`.
    pub fn weights(&self, x: &Tensor) -> Result<Tensor> {
        let k = self.cue_channels;
        let (n, v, h, w, b) = view_dims(x, 4 + k)?;
        let mut g = x.narrow(3, 4, k)?.contiguous()?; // [B, D, V, K, H, W]
        g = g.reshape((n * v, k, h, w))?; // [N*V, K, H, W]
        let last = self.layers.len() - 1;
        for (i, conv) in self.layers.iter().enumerate() {
            g = match i < last {
                true => conv.forward_relu(&g)?,
                false => conv.forward(&g)?,
            };
        } // [N*V, 1, H, W]
          // 1 + tanh(S g) as 2 sigmoid(2 S g): where g is very negative, 1 + tanh cancels
          // to a few f32 ulps while the sigmoid keeps the small weight's relative precision.
        let k = (candle_nn::ops::sigmoid(&(g * (2.0 * WEIGH_SCALE))?)? * 2.0)?;
        k.reshape((b, n / b.max(1), v, 1, h, w)) // [B, D, V, 1, H, W]
    }

    /// [`Self::forward`] for rendering, in one fused pass where it runs
    /// ([`fused::weigh_views`]; equal to rounding, since its sums run in another order).
    pub fn infer(&self, x: &Tensor) -> Result<Tensor> {
        let fused = match dense_layers(&self.layers)? {
            Some(dense) => fused::weigh_views(x, &dense)?,
            None => None,
        };
        match fused {
            Some(y) => Ok(y),
            None => self.forward(x),
        }
    }

    /// The weighed level: `x` `[B, D, V, 4 + K, H, W]` -> `[B, D, V, 4, H, W]`, each
    /// view's RGB and its alpha times [`Self::weights`].
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let k = self.weights(x)?; // [B, D, V, 1, H, W]
        let rgb = x.narrow(3, 0, 3)?; // [B, D, V, 3, H, W]
        let a = x.narrow(3, 3, 1)?.mul(&k)?; // [B, D, V, 1, H, W]
        Tensor::cat(&[&rgb, &a], 3) // [B, D, V, 4, H, W]
    }
}

/// The colour blend head (`colour.blend.*`).
#[derive(Debug, Clone)]
pub struct Blend {
    /// Hidden layers, then the 1-channel logit layer.
    layers: Vec<Conv2d>,
}

impl Blend {
    /// `features`: `C_f`; `colour`: `C_c` (the colour tower's output channels).
    pub fn new(pool: &ViewPool, colour: usize, vb: VarBuilder) -> Result<Self> {
        let mut ch = pool.features() + colour;
        let mut layers = Vec::with_capacity(pool.blend.len() + 1);
        let widths = pool.blend.iter().map(|c| c.channels).chain([1]);
        for (i, cout) in widths.enumerate() {
            layers.push(Conv2d::new(ch, cout, (1, 1), vb.pp(i))?);
            ch = cout;
        }
        Ok(Self { layers })
    }

    /// The blended source colours `sum_v w_v rgb_v` `[N, 3, th, tw]` from the views'
    /// features `e` `[N, V, C_f, th, tw]`, their RGBA `x` `[N, V, 4, th, tw]` and the
    /// colour tower's features `f` `[N, C_c, th, tw]`, all at the tile's pixels.
    pub fn forward(&self, e: &Tensor, x: &Tensor, f: &Tensor) -> Result<Tensor> {
        let (n, v, cf, th, tw) = e.dims5()?;
        // First layer on [e_v, f] without repeating f for every view: its part for f is
        // computed once per plane and broadcast over the views.
        let (ye, yf) = self.layers[0].forward_split(&e.reshape((n * v, cf, th, tw))?, f)?;
        let c0 = ye.dim(1)?;
        let p = th * tw;
        let last = self.layers.len() - 1;
        let mut y = if last > 0 {
            // relu(ye + yf) with yf broadcast over the views: fused on the CPU.
            let (ye4, yf3) = (ye.reshape((n, v, c0, p))?, yf.reshape((n, c0, p))?);
            match fused::add_views_relu(&ye4, &yf3)? {
                Some(h) => h, // [N, V, C_0, P]
                None => ye4.broadcast_add(&yf3.unsqueeze(1)?)?.relu()?,
            }
            .reshape((n * v, c0, th, tw))? // [N*V, C_0, th, tw]
        } else {
            ye.reshape((n, v, c0, th, tw))? // [N, V, C_0, th, tw]
                .broadcast_add(&yf.unsqueeze(1)?)? // + [N, 1, C_0, th, tw]
        };
        if last > 0 {
            for (i, conv) in self.layers.iter().enumerate().skip(1) {
                y = if i < last {
                    conv.forward_relu(&y)?
                } else {
                    conv.forward(&y)?
                };
            }
        }
        let xp = x.contiguous()?.reshape((n, v, 4, p))?; // [N, V, 4, P]
        match fused::blend_colours(&y.reshape((n, v, p))?, &xp)? {
            Some(c) => c.reshape((n, 3, th, tw)), // [N, 3, th, tw]
            None => blend_reference(&y.reshape((n, v, 1, th, tw))?, x),
        }
    }

    /// [`Self::forward`] for rendering, as one fused pass ([`fused::blend_infer`]) that
    /// reads the uncropped level-0 features `e` `[N, V, C_f, H, W]` and sources `x`
    /// `[N, V, 4, H, W]` around the tile at `(pad, pad)`; `None` where it does not apply.
    pub fn infer(&self, e: &Tensor, x: &Tensor, f: &Tensor, pad: usize) -> Result<Option<Tensor>> {
        match dense_layers(&self.layers)? {
            Some(dense) => fused::blend_infer(e, x, f, &dense, pad),
            None => Ok(None),
        }
    }
}

/// 1x1 convolutions as plain f32 arrays (the fused rendering passes'); `None` if one is not
/// 1x1.
fn dense_layers(convs: &[Conv2d]) -> Result<Option<Vec<fused::Dense>>> {
    let mut dense = Vec::with_capacity(convs.len());
    for l in convs {
        let (cout, cin, kh, kw) = l.weight().dims4()?;
        if (kh, kw) != (1, 1) {
            return Ok(None);
        }
        dense.push(fused::Dense {
            weight: l.weight().to_dtype(DType::F32)?.flatten_all()?.to_vec1()?,
            bias: l.bias().to_dtype(DType::F32)?.to_vec1()?,
            cin,
            cout,
        });
    }
    Ok(Some(dense))
}

/// The blend of the source colours from the raw logits `y` `[N, V, 1, th, tw]` and the
/// sources' RGBA `x` `[N, V, 4, th, tw]`, as candle ops: `[N, 3, th, tw]`.
pub fn blend_reference(y: &Tensor, x: &Tensor) -> Result<Tensor> {
    let logits = ((y / BLEND_LOGIT_BOUND)?.tanh()? * BLEND_LOGIT_BOUND)?;
    let rgb = x.narrow(2, 0, 3)?; // [N, V, 3, th, tw]
    let a = x.narrow(2, 3, 1)?; // [N, V, 1, th, tw]
    let ex = logits.exp()?.mul(&a)?; // [N, V, 1, th, tw]
    let den = (ex.sum_keepdim(1)? + BLEND_EPS)?; // [N, 1, 1, th, tw]
    let wts = ex.broadcast_div(&den)?; // [N, V, 1, th, tw]
    rgb.broadcast_mul(&wts)?.sum(1) // [N, 3, th, tw]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Conv;
    use candle_core::{DType, Device, Var};

    fn rand(shape: &[usize], seed: u64, alpha: bool) -> Result<Tensor> {
        let n: usize = shape.iter().product();
        let mut s = seed | 1;
        let v: Vec<f64> = (0..n)
            .map(|i| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                let u = (s >> 11) as f64 / (1u64 << 53) as f64;
                // Alpha planes (channel 3 of 4): 0, 1 or fractional.
                let c = (i / (shape[shape.len() - 1] * shape[shape.len() - 2])) % 4;
                match (alpha && c == 3, u) {
                    (true, u) if u < 0.3 => 0.0,
                    (true, u) if u > 0.6 => 1.0,
                    _ => u,
                }
            })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu)
    }

    /// The view weight `1 + tanh(S g)` keeps its relative precision in f32 where it is
    /// small (g down to -10: a weight of 2e-35), in the training forward and the fused
    /// rendering pass, against the exact `2 / (1 + e^(-2 S g))` in f64; and it is exactly
    /// 1 at g = 0 and finite at g = -1e30 and 1e30. Written as `1 + tanh`, f32 cancels it
    /// to 0 from g = -2.2 on.
    #[test]
    fn small_view_weights_keep_their_relative_precision() -> Result<()> {
        let gs = [
            0.0f32, -0.5, -1.0, -2.0, -4.0, -7.0, -10.0, 3.0, -1e30, 1e30,
        ];
        let vm = candle_nn::VarMap::new();
        let weigh = ViewWeigh::new(
            &[],
            1,
            VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu),
        )?;
        // g = w * cue + b with w = 1, b = 0: the cue channel is g itself.
        for (name, var) in vm
            .data()
            .lock()
            .map_err(|_| candle_core::Error::msg("lock"))?
            .iter()
        {
            if name.ends_with("weight") {
                var.set(&Tensor::ones((1, 1, 1, 1), DType::F32, &Device::Cpu)?)?;
            }
        }
        let p = gs.len();
        let mut x = vec![1f32; 5 * p]; // [1, 1, 1, 4 + 1, 1, P]: RGB 1, alpha 1, then g
        x[4 * p..].copy_from_slice(&gs);
        let x = Tensor::from_vec(x, (1, 1, 1, 5, 1, p), &Device::Cpu)?;
        let forward = weigh
            .forward(&x)?
            .narrow(3, 3, 1)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let infer = weigh
            .infer(&x)?
            .narrow(3, 3, 1)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        for (i, &g) in gs.iter().enumerate() {
            let exact = 2.0 / (1.0 + (-2.0 * WEIGH_SCALE * g as f64).exp());
            for (path, k) in [("forward", forward[i]), ("infer", infer[i])] {
                assert!(k.is_finite(), "{path}: g {g}: {k}");
                let err = (k as f64 - exact).abs();
                // Below f32's normal range, absolute (the fused `exp` clamps its argument).
                let ok = if exact < 1e-37 {
                    err < 1e-37
                } else {
                    err / exact < 1e-5
                };
                assert!(ok, "{path}: g {g}: {k} against {exact:e}");
            }
            if g == 0.0 {
                assert_eq!((forward[i], infer[i]), (1.0, 1.0));
            }
        }
        Ok(())
    }

    /// The fused passes equal the candle composition, values and gradients (f64).
    #[test]
    fn fused_pooling_and_blend_equal_the_candle_ops() -> Result<()> {
        let pool = ViewPool {
            encoder: vec![Conv {
                kernel: 1,
                channels: 5,
            }],
            blend: vec![],
            falloff: None,
            cue: false,
            weigh: None,
            agree: None,
            disagree: None,
            features: None,
        };
        let vm = candle_nn::VarMap::new();
        let enc = ViewEncoder::new(
            &pool,
            VarBuilder::from_varmap(&vm, DType::F64, &Device::Cpu),
        )?;
        let x = rand(&[2, 3, 4, 4, 5, 6], 7, true)?; // [B, D, V, 4, H, W]
        let a = enc.forward(&x, false)?;
        let b = enc.forward_reference(&x)?;
        let d = (a.stats.clone() - &b.stats)?
            .abs()?
            .max_all()?
            .to_scalar::<f64>()?;
        assert!(d < 1e-12, "stats differ by {d}");
        // Gradients to the encoder's weights through the variance.
        let r = rand(a.stats.dims(), 9, false)?;
        let ga = (a.stats * &r)?.sum_all()?.backward()?;
        let gb = (b.stats * &r)?.sum_all()?.backward()?;
        for (name, var) in vm
            .data()
            .lock()
            .map_err(|_| candle_core::Error::msg("lock"))?
            .iter()
        {
            let (ta, tb) = (ga.get(var.as_tensor()), gb.get(var.as_tensor()));
            let (Some(ta), Some(tb)) = (ta, tb) else {
                candle_core::bail!("no gradient for {name}");
            };
            let d = (ta - tb)?.abs()?.max_all()?.to_scalar::<f64>()?;
            assert!(d < 1e-10, "{name}: gradients differ by {d}");
        }
        // The blend: values and the gradient to the logits.
        let (n, v, th, tw) = (4, 3, 3, 5);
        let y = Var::from_tensor(&((rand(&[n, v, 1, th, tw], 3, false)? - 0.5)? * 60.0)?)?;
        let xs = rand(&[n, v, 4, th, tw], 5, true)?;
        let p = th * tw;
        let fused = fused::blend_colours(&y.reshape((n, v, p))?, &xs.reshape((n, v, 4, p))?)?
            .ok_or_else(|| candle_core::Error::msg("fused blend did not run"))?
            .reshape((n, 3, th, tw))?;
        let reference = blend_reference(y.as_tensor(), &xs)?;
        let d = (&fused - &reference)?
            .abs()?
            .max_all()?
            .to_scalar::<f64>()?;
        assert!(d < 1e-12, "blend differs by {d}");
        let r = rand(&[n, 3, th, tw], 11, false)?;
        let ga = (fused * &r)?.sum_all()?.backward()?;
        let gb = (reference * &r)?.sum_all()?.backward()?;
        let (Some(ta), Some(tb)) = (ga.get(y.as_tensor()), gb.get(y.as_tensor())) else {
            candle_core::bail!("no gradient for the logits");
        };
        let d = (ta - tb)?.abs()?.max_all()?.to_scalar::<f64>()?;
        assert!(d < 1e-10, "blend gradients differ by {d}");
        Ok(())
    }

    /// Sources that carry a gradient (alphas weighed by the cue): the fused moments and
    /// blend give the same gradients to them as the candle ops (f64).
    #[test]
    fn fused_gradients_to_the_sources_equal_the_candle_ops() -> Result<()> {
        let (n, v, c, p) = (3, 4, 5, 7);
        let x = Var::from_tensor(&rand(&[n, v, 4, p], 21, true)?)?;
        let e = rand(&[n, v, c, p], 23, false)?;
        let y = ((rand(&[n, v, p], 25, false)? - 0.5)? * 6.0)?;
        let grad_of = |out: &Tensor, seed: u64| -> Result<Tensor> {
            let r = rand(out.dims(), seed, false)?;
            let g = (out * &r)?.sum_all()?.backward()?;
            g.get(x.as_tensor())
                .cloned()
                .ok_or_else(|| candle_core::Error::msg("no gradient for the sources"))
        };
        let close = |a: &Tensor, b: &Tensor, what: &str| -> Result<()> {
            let d = (a - b)?.abs()?.max_all()?.to_scalar::<f64>()?;
            let m = b.abs()?.max_all()?.to_scalar::<f64>()?;
            assert!(
                m > 1e-3 && d < 1e-10,
                "{what}: gradients differ by {d} (max {m})"
            );
            Ok(())
        };
        // Moments: candle ops as in `forward_reference`.
        let fused = fused::view_stats(&e, x.as_tensor())?
            .ok_or_else(|| candle_core::Error::msg("fused moments did not run"))?;
        let (e5, x5) = (e.reshape((n, v, c, 1, p))?, x.reshape((n, v, 4, 1, p))?);
        let a = x5.narrow(2, 3, 1)?;
        let den = (a.sum_keepdim(1)? + POOL_EPS)?;
        let mean = weighted_mean(&e5, &a, &den)?;
        let var = weighted_mean(&e5.broadcast_sub(&mean)?.sqr()?, &a, &den)?;
        let reference = Tensor::cat(&[&mean, &var], 2)?.reshape((n, 2 * c, p))?;
        close(&grad_of(&fused, 27)?, &grad_of(&reference, 27)?, "moments")?;
        // Blend.
        let fused = fused::blend_colours(&y, x.as_tensor())?
            .ok_or_else(|| candle_core::Error::msg("fused blend did not run"))?;
        let reference = blend_reference(&y.reshape((n, v, 1, 1, p))?, &x5)?.reshape((n, 3, p))?;
        close(&grad_of(&fused, 29)?, &grad_of(&reference, 29)?, "blend")
    }
}
