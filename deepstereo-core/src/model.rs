//! The DeepStereo network (Flynn et al. 2016) in candle.
//!
//! Shape letters, used everywhere: `B` batch, `D` planes, `V` source views, `C` channels,
//! `H`, `W` spatial. Input level `l` is a plane-sweep tensor `[B, D, 4V, H_l, W_l]` (the
//! paper's family: views concatenated, exactly `Config::views` of them) or
//! `[B, D, V, 4, H_l, W_l]` (the any-number-of-views family, `Config::pool`: any `V`;
//! `[B, D, V, 4 + K, H_l, W_l]` with each view's geometric cue after its RGBA; its view
//! pooling and colour blend are in [`crate::pool`]). Both families then run the
//! same towers on `[B*D, C, H_l, W_l]`.
//!
//! Parameter names equal the PyTorch reference's attribute names (`python/deepstereo_ref.py`),
//! so one safetensors file loads in both:
//! `select.levels.{l}.{i}.{weight,bias}`, `select.merge.{i}.*`, `select.depth.{i}.*`
//! (weights `[C_out, C_in, k, 1]`: convolutions along depth), `select.log_scale` `[1]`,
//! `colour.levels.{l}.{i}.*`, `colour.merge.{i}.*`, `colour.out.*`; the
//! any-number-of-views family adds `views.encode.{i}.*` and `colour.blend.{i}.*`, and with
//! the cue as view weights (`pool.weigh`) `views.weigh.{i}.*`.

mod tower;

pub use tower::Tower;

use crate::config::{Config, TowerConfig};
use crate::conv::{depth_head, pointwise_colours, Conv2d};
use crate::features::FeatureNet;
pub use crate::fused::upsample_nearest;
use crate::fused::{composite, pad_rows, select_softmax};
use crate::pool::{rgba, view_dims, Blend, ViewEncoder, ViewWeigh};
use candle_core::Module;
use candle_core::{DType, Result, Tensor, D};
use candle_nn::VarBuilder;

/// What the network returns for a batch of tiles.
#[derive(Debug)]
pub struct Output {
    /// `[B, 3, th, tw]`, the rendered colour `sum_z s_z * c_z`.
    pub image: Tensor,
    /// `[B, D, th, tw]`, selection probabilities (sum to 1 over D).
    pub selection: Tensor,
    /// `[B, D, 3, th, tw]`, the colour tower's colour `c_z` of every plane (what a
    /// multiplane image stores).
    pub colours: Tensor,
}

/// The two-tower DeepStereo network.
#[derive(Debug, Clone)]
pub struct DeepStereo {
    cfg: Config,
    select: Tower,
    depth: Vec<Conv2d>,
    log_scale: Tensor,
    colour: Tower,
    colour_out: Conv2d,
    /// The any-number-of-views family's encoder and blend.
    pool: Option<(ViewEncoder, Blend)>,
    /// The cue's view weights ([`crate::config::ViewPool::weigh`]).
    weigh: Option<ViewWeigh>,
    /// The `features` family's per-source CNN ([`crate::features`]); its warped maps
    /// are part of the inputs ([`Self::forward`]), the network run once per source image
    /// by whoever builds them ([`crate::inputs::PyramidSource::with_features`], training).
    features: Option<FeatureNet>,
    /// A scene's selection prior (`deepstereo tune`), applied by the renderers outside
    /// the network ([`crate::prior`]); not part of the ONNX graph.
    prior: Option<std::sync::Arc<crate::prior::PriorGrid>>,
}

/// Pixels per depth row at which rows alias in the caches (128 floats = 512 bytes).
const ALIASING_ROW: usize = 128;
/// Zero columns added to such rows (one cache line).
const ROW_SHIFT: usize = 16;

/// Initial value of the selection scale's logarithm: `exp(2.3) ~ 10` lets the softmax
/// over tanh-bounded logits reach near one-hot selections from the start of training.
pub const INIT_LOG_SCALE: f64 = 2.3;

impl DeepStereo {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        cfg.validate().map_err(candle_core::Error::msg)?;
        let cin = cfg.tower_in_channels();
        let select = Tower::new(&cfg.select, cin, vb.pp("select"))?;
        let mut ch = cfg.select.out_channels(cin);
        let mut depth = Vec::new();
        for (i, c) in cfg.depth_convs.iter().enumerate() {
            depth.push(Conv2d::new(
                ch,
                c.channels,
                (c.kernel, 1),
                vb.pp("select").pp("depth").pp(i),
            )?);
            ch = c.channels;
        }
        let log_scale = vb.pp("select").get_with_hints(
            1,
            "log_scale",
            candle_nn::Init::Const(INIT_LOG_SCALE),
        )?;
        let colour = Tower::new(&cfg.colour, cin, vb.pp("colour"))?;
        let cout_in = cfg.colour.out_channels(cin) + if cfg.colour_skip { cin } else { 0 };
        let colour_out = Conv2d::new(cout_in, 3, (1, 1), vb.pp("colour").pp("out"))?;
        let pool = match &cfg.pool {
            Some(p) => Some((
                ViewEncoder::new(p, vb.pp("views").pp("encode"))?,
                Blend::new(p, cfg.colour.out_channels(cin), vb.pp("colour").pp("blend"))?,
            )),
            None => None,
        };
        let weigh = match cfg
            .pool
            .as_ref()
            .and_then(|p| Some((p.weigh.as_deref()?, p)))
        {
            Some((hidden, p)) => Some(ViewWeigh::new(
                hidden,
                p.cue_channels(),
                vb.pp("views").pp("weigh"),
            )?),
            None => None,
        };
        let features = match cfg.pool.as_ref().and_then(|p| p.features.as_ref()) {
            Some(f) => Some(FeatureNet::new(f, vb.pp("features"))?),
            None => None,
        };
        Ok(Self {
            cfg: cfg.clone(),
            select,
            depth,
            log_scale,
            colour,
            colour_out,
            pool,
            weigh,
            features,
            prior: None,
        })
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// The per-source feature CNN of the `features` family.
    pub fn feature_net(&self) -> Option<&FeatureNet> {
        self.features.as_ref()
    }

    /// The scene prior the model carries (a tuned model), if any.
    pub fn prior(&self) -> Option<&crate::prior::PriorGrid> {
        self.prior.as_deref()
    }

    /// The model with `prior` (or none).
    pub fn with_prior(mut self, prior: Option<crate::prior::PriorGrid>) -> Self {
        self.prior = prior.map(std::sync::Arc::new);
        self
    }

    /// `inputs[l]`: `[B, D, 4V, H_l, W_l]` (paper family) or `[B, D, V, C_v, H_l, W_l]`
    /// (any-number-of-views family, `V >= 1`, `C_v` = `Config::view_channels()`) with
    /// `H_l = Config::input_size(l, th)`, for `l < Config::levels`. `th`, `tw` multiples of
    /// `Config::tile_align()`.
    pub fn forward(&self, inputs: &[Tensor]) -> Result<Output> {
        self.run(inputs, false)
    }

    /// [`Self::forward`] for rendering: the depth layers and the selection softmax, and a
    /// colour tower of one level of 1x1 convolutions with its output layer, each run as
    /// one fused pass over blocks of pixels where the CPU kernels apply (`conv/chain.rs`),
    /// else as in [`Self::forward`]. The outputs are detached (the fused passes record no
    /// gradients, so none flow through any of it); train with [`Self::forward`].
    pub fn infer(&self, inputs: &[Tensor]) -> Result<Output> {
        let out = self.run(inputs, true)?;
        Ok(Output {
            image: out.image.detach(),
            selection: out.selection.detach(),
            colours: out.colours.detach(),
        })
    }

    /// [`Self::forward`] with the features family's warped maps apart: `inputs[l]`
    /// `[B, D, V, C_v - F, H_l, W_l]` and `feats[l]` `[B, D, V, F, H_l, W_l]` (training's
    /// graph, where slicing them out of one tensor would cost a copy of it per slice in
    /// the backward pass).
    pub fn forward_parts(&self, inputs: &[Tensor], feats: Option<&[Tensor]>) -> Result<Output> {
        self.run_parts(inputs, feats, false)
    }

    /// [`Self::infer`] with the features family's maps apart ([`Self::forward_parts`]).
    pub fn infer_parts(&self, inputs: &[Tensor], feats: Option<&[Tensor]>) -> Result<Output> {
        let out = self.run_parts(inputs, feats, true)?;
        Ok(Output {
            image: out.image.detach(),
            selection: out.selection.detach(),
            colours: out.colours.detach(),
        })
    }

    fn run(&self, inputs: &[Tensor], fuse: bool) -> Result<Output> {
        let f = self.cfg.pool.as_ref().map_or(0, |p| p.feature_channels());
        if f == 0 {
            return self.run_parts(inputs, None, fuse);
        }
        let mut base = Vec::with_capacity(inputs.len());
        let mut feats = Vec::with_capacity(inputs.len());
        for x in inputs {
            let c = x.dim(3)?;
            if c < f {
                candle_core::bail!(
                    "an input level of {c} channels per view, expected {}",
                    self.cfg.view_channels()
                );
            }
            base.push(x.narrow(3, 0, c - f)?);
            feats.push(x.narrow(3, c - f, f)?);
        }
        self.run_parts(&base, Some(&feats), fuse)
    }

    fn run_parts(&self, inputs: &[Tensor], feats: Option<&[Tensor]>, fuse: bool) -> Result<Output> {
        let cfg = &self.cfg;
        if inputs.len() != cfg.levels || feats.is_some_and(|f| f.len() != cfg.levels) {
            candle_core::bail!("expected {} input levels, got {}", cfg.levels, inputs.len());
        }
        // With the cue's view weights, every level's alpha weighed first: [B, D, V, 4, H_l, W_l].
        let weighed = match &self.weigh {
            Some(weigh) => Some(
                (inputs.iter())
                    .map(|x| match fuse {
                        true => weigh.infer(x),
                        false => weigh.forward(x),
                    })
                    .collect::<Result<Vec<_>>>()?,
            ),
            None => None,
        };
        let inputs = weighed.as_deref().unwrap_or(inputs);
        let (towers_in, features) = self.towers_input(inputs, feats, fuse)?;
        let (b, d, cin, h0, w0) = towers_in[0].dims5()?;
        let (th, tw) = (h0 - 2 * cfg.pad(0), w0 - 2 * cfg.pad(0));
        let folded = |t: &TowerConfig, from: usize| -> Result<Vec<Tensor>> {
            (from..t.levels)
                .map(|l| {
                    let x = &towers_in[l];
                    let (_, _, _, h, w) = x.dims5()?;
                    let off = cfg.pad(l) - t.pad(l);
                    x.narrow(3, off, h - 2 * off)?
                        .narrow(4, off, w - 2 * off)?
                        .reshape((b * d, cin, h - 2 * off, w - 2 * off)) // [B*D, C, H_l, W_l]
                })
                .collect()
        };
        let selection = self.select_probabilities(&folded, (b, d), (th, tw), fuse)?; // [B, D, th*tw]
        let out = match (&self.pool, features) {
            (Some((_, blend)), Some(e)) => {
                self.blended_colours(blend, inputs, &folded, &e, (th, tw), fuse)?
            }
            _ => self.paper_colours(inputs, &folded, (b, d, cin, h0, w0), (th, tw), fuse)?,
        }; // [B*D, 3, th, tw]
        let colours = out.reshape((b, d, 3, th * tw))?; // [B, D, 3, th*tw]
        let image = composite(&colours, &selection)? // sum over D of s * c
            .reshape((b, 3, th, tw))?; // [B, 3, th, tw]
        let selection = selection.reshape((b, d, th, tw))?; // [B, D, th, tw]
        let colours = colours.reshape((b, d, 3, th, tw))?; // [B, D, 3, th, tw]
        Ok(Output {
            image,
            selection,
            colours,
        })
    }

    /// The towers' input per level, `[B, D, C, H_l, W_l]`: the sweep itself (paper
    /// family) or the pooled statistics; and, pooled, level 0's view features.
    fn towers_input(
        &self,
        inputs: &[Tensor],
        feats: Option<&[Tensor]>,
        fuse: bool,
    ) -> Result<(Vec<Tensor>, Option<Tensor>)> {
        let cfg = &self.cfg;
        let Some((encoder, _)) = &self.pool else {
            let cin = inputs[0].dims5()?.2;
            if cin != cfg.in_channels() {
                candle_core::bail!(
                    "expected {} input channels (4 x {} views), got {cin}",
                    cfg.in_channels(),
                    cfg.views
                );
            }
            return Ok((inputs.to_vec(), None));
        };
        let c = encoder.view_channels()
            - feats.map_or(0, |_| cfg.pool.as_ref().map_or(0, |p| p.feature_channels()));
        let v = view_dims(&inputs[0], c)?.1;
        let mut stats = Vec::with_capacity(inputs.len());
        let mut features = None;
        for (l, x) in inputs.iter().enumerate() {
            if view_dims(x, c)?.1 != v {
                candle_core::bail!("input level {l} has a different number of views");
            }
            // Rendering: one fused pass where it runs (view features at level 0 only), the
            // source features beside the rest of each view's channels.
            let fused = match (fuse, feats) {
                (true, None) => encoder.infer(x, l == 0)?,
                (true, Some(f)) => encoder.infer(&Tensor::cat(&[x, &f[l]], 3)?, l == 0)?,
                (false, _) => None,
            };
            let (s, e) = match fused {
                Some(pooled) => pooled,
                None => {
                    let pooled = encoder.forward_parts(x, feats.map(|f| &f[l]), fuse)?;
                    (pooled.stats, Some(pooled.features))
                }
            };
            stats.push(s);
            if l == 0 {
                features = e;
            }
        }
        Ok((stats, features))
    }

    /// The selection tower and its head: `[B, D, th*tw]` (rendering: the depth layers and
    /// the softmax in one fused pass where it runs).
    fn select_probabilities(
        &self,
        folded: &dyn Fn(&TowerConfig, usize) -> Result<Vec<Tensor>>,
        (b, d): (usize, usize),
        (th, tw): (usize, usize),
        fuse: bool,
    ) -> Result<Tensor> {
        let s = self
            .select
            .forward(&folded(&self.cfg.select, 0)?, th, tw, fuse)?; // [B*D, C, th, tw]
        let fused = if fuse {
            depth_head(&s, d, &self.depth, &self.log_scale)?
        } else {
            None
        };
        match fused {
            Some(sel) => Ok(sel), // [B, D, th*tw]
            None => self.selection(&s, b, d, th, tw),
        }
    }

    /// Pooled family: the colour tower's linear RGB plus the blend of the sources' colours
    /// by the view features `e`, `[B*D, 3, th, tw]` (rendering: the blend in one fused
    /// pass where it runs).
    fn blended_colours(
        &self,
        blend: &Blend,
        inputs: &[Tensor],
        folded: &dyn Fn(&TowerConfig, usize) -> Result<Vec<Tensor>>,
        e: &Tensor,
        (th, tw): (usize, usize),
        fuse: bool,
    ) -> Result<Tensor> {
        let p = self.cfg.pad(0);
        let f = self
            .colour
            .forward(&folded(&self.cfg.colour, 0)?, th, tw, fuse)?; // [B*D, C_c, th, tw]
        let centre = |t: &Tensor| t.narrow(3, p, th)?.narrow(4, p, tw); // [B*D, V, C, th, tw]
        let x0 = rgba(&inputs[0])?; // [B, D, V, 4, H_0, W_0]
        let (v, h, w) = (x0.dim(2)?, x0.dim(4)?, x0.dim(5)?);
        let n = x0.dim(0)? * x0.dim(1)?;
        let x0 = x0.reshape((n, v, 4, h, w))?; // [B*D, V, 4, H_0, W_0]
        let fused = match fuse {
            true => blend.infer(e, &x0, &f, p)?, // [B*D, 3, th*tw]
            false => None,
        };
        let blended = match fused {
            Some(c) => c.reshape((n, 3, th, tw))?, // [B*D, 3, th, tw]
            None => blend.forward(&centre(e)?, &centre(&x0)?, &f)?, // [B*D, 3, th, tw]
        };
        blended + self.colour_out.forward(&f)?
    }

    /// Paper family: the colour tower, `[B*D, 3, th, tw]`; one fused pass for a 1x1 tower
    /// when rendering (the tile sits at `pad(0)` in level 0), else layer by layer.
    fn paper_colours(
        &self,
        inputs: &[Tensor],
        folded: &dyn Fn(&TowerConfig, usize) -> Result<Vec<Tensor>>,
        (b, d, cin, h0, w0): (usize, usize, usize, usize, usize),
        (th, tw): (usize, usize),
        fuse: bool,
    ) -> Result<Tensor> {
        let pointwise = match fuse.then(|| self.colour.pointwise()).flatten() {
            Some(convs) => {
                let x0 = inputs[0].reshape((b * d, cin, h0, w0))?; // [B*D, 4V, H_0, W_0]
                let (out, skip) = (&self.colour_out, self.cfg.colour_skip);
                pointwise_colours(&x0, self.cfg.pad(0), (th, tw), &convs, out, skip)?
            }
            None => None,
        };
        match pointwise {
            Some(out) => Ok(out),
            None => self.colours(inputs, folded, th, tw),
        }
    }

    /// The depth layers and the softmax, one op at a time: `s` `[B*D, C, th, tw]` ->
    /// `[B, D, th*tw]`.
    fn selection(&self, s: &Tensor, b: usize, d: usize, th: usize, tw: usize) -> Result<Tensor> {
        let cfg = &self.cfg;
        let c = s.dim(1)?;
        let mut x = s
            .reshape((b, d, c, th * tw))? // [B, D, C, th*tw]
            .transpose(1, 2)?; // [B, C, D, th*tw], a view

        // Rows of th*tw pixels whose byte stride is a multiple of 512 put a layer's
        // channels and planes in the same cache sets; a few zero columns (their outputs
        // are dropped) shift them apart.
        let pp = th * tw;
        let extra = if pp.is_multiple_of(ALIASING_ROW) {
            ROW_SHIFT
        } else {
            0
        };
        let last = self.depth.len() - 1;
        for (i, conv) in self.depth.iter().enumerate() {
            let p = cfg.depth_convs[i].kernel / 2;
            let xp = pad_rows(&x, p, if i == 0 { extra } else { 0 })?; // [B, C, D + 2p, pp + extra]
            x = if i < last {
                conv.forward_relu(&xp)?
            } else {
                conv.forward(&xp)?
            }; // [B, C', D, pp + extra]
        }
        let x = x.narrow(3, 0, pp)?.reshape((b, d, pp))?; // [B, D, th*tw]
        select_softmax(&x, &self.log_scale) // softmax_D(tanh(x) exp(log_scale)), [B, D, th*tw]
    }

    /// The colour tower and its output layer, one op at a time: `[B*D, 3, th, tw]`.
    fn colours(
        &self,
        inputs: &[Tensor],
        folded: &dyn Fn(&TowerConfig, usize) -> Result<Vec<Tensor>>,
        th: usize,
        tw: usize,
    ) -> Result<Tensor> {
        // The skip input is the tile's own pixels, which is also the colour tower's
        // level-0 input when its convolutions are 1x1 (then cropped once).
        let cfg = &self.cfg;
        let (b, d, cin, _, _) = inputs[0].dims5()?;
        let p = cfg.pad(0);
        let centre = || {
            inputs[0]
                .narrow(3, p, th)?
                .narrow(4, p, tw)?
                .reshape((b * d, cin, th, tw)) // [B*D, 4V, th, tw]
        };
        let shared = cfg.colour_skip && cfg.colour.pad(0) == 0;
        let colour_in = if shared {
            let mut v = vec![centre()?];
            v.extend(folded(&cfg.colour, 1)?);
            v
        } else {
            folded(&cfg.colour, 0)?
        };
        let f = self.colour.forward(&colour_in, th, tw, false)?; // [B*D, C, th, tw]
        if cfg.colour_skip {
            let skip = if shared {
                colour_in[0].clone()
            } else {
                centre()?
            };
            // conv([f, skip]) without concatenating.
            self.colour_out.forward_pair(&f, &skip)
        } else {
            self.colour_out.forward(&f)
        } // [B*D, 3, th, tw]
    }
}

/// Mean absolute error between two tensors of the same shape (the paper's L1 loss,
/// averaged instead of summed so the learning rate does not depend on the tile size).
pub fn l1_loss(pred: &Tensor, target: &Tensor) -> Result<Tensor> {
    pred.sub(target)?.abs()?.mean_all()
}

/// Mean squared error between two tensors of the same shape (`train --loss l2`).
pub fn l2_loss(pred: &Tensor, target: &Tensor) -> Result<Tensor> {
    pred.sub(target)?.sqr()?.mean_all()
}

/// Expected depth per pixel from selection probabilities `[B, D, H, W]` and plane depths.
/// Uses inverse depth for the expectation (planes are uniform in it), returns depth.
pub fn expected_depth(selection: &Tensor, inv_depths: &[f64]) -> Result<Tensor> {
    let d = inv_depths.len();
    let rho = Tensor::from_vec(
        inv_depths.iter().map(|&r| r as f32).collect::<Vec<_>>(),
        (1, d, 1, 1),
        selection.device(),
    )?
    .to_dtype(selection.dtype())?;
    let e = selection.broadcast_mul(&rho)?.sum_keepdim(1)?; // [B, 1, H, W]
    e.recip()
}

/// Dtype helper for callers building inputs.
pub fn dtype_of(vb: &VarBuilder) -> DType {
    vb.dtype()
}

/// Sum over depth of the selection, for checks: `[B, D, H, W]` -> `[B, H, W]`.
pub fn selection_sum(selection: &Tensor) -> Result<Tensor> {
    selection.sum(D::Minus(3))
}
