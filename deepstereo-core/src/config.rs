//! Network configuration, presets, and the tile geometry derived from it.
//!
//! # Tile geometry
//! The network is fully convolutional with valid (unpadded) convolutions. For an output
//! tile of `th x tw` pixels whose top-left corner `(x0, y0)` is a multiple of
//! [`Config::tile_align`] (`2^(L-1)`), level `l` of a tower reads level-`l` pixels (image
//! downsampled by `2^l`) starting at `x0 / 2^l - pad_l`, where
//! `pad_l = ceil(rf / 2^(l+1)) + r0 / 2`, `r0` = the reduction of the tower's per-level
//! convolutions and `rf` that of its merge convolutions. After the per-level convolutions,
//! level `l`'s features are upsampled by `2^l` (nearest) and cropped at offset
//! `2^l * ceil(rf / 2^(l+1)) - rf / 2` to `th + rf`. Because every level's pixel grid is
//! aligned with the same global grid, tiles rendered separately give exactly the image
//! rendered whole.

mod layers;
mod validate;

pub use layers::LayerInfo;
use serde::{Deserialize, Serialize};

/// One convolution: a square `kernel x kernel` 2D convolution across planes' pixels, or
/// a `kernel`-tap convolution along depth in the selection tower's depth stack.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Conv {
    pub kernel: usize,
    pub channels: usize,
}

const fn c(kernel: usize, channels: usize) -> Conv {
    Conv { kernel, channels }
}

/// A 3x3 convolution of `channels`.
const fn c3(channels: usize) -> Conv {
    c(3, channels)
}

/// The 2D part of a tower: per-level convolutions (own weights per level, shared across
/// planes), then, after nearest upsampling and concatenation, the merge convolutions.
/// All are followed by ReLU.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TowerConfig {
    /// Number of resolution levels this tower reads (1..=`Config::levels`).
    pub levels: usize,
    pub level_convs: Vec<Conv>,
    pub merge_convs: Vec<Conv>,
}

impl TowerConfig {
    /// Pixels lost by the per-level convolutions (`r0`).
    pub fn level_reduction(&self) -> usize {
        self.level_convs.iter().map(|c| c.kernel - 1).sum()
    }
    /// Pixels lost by the merge convolutions (`rf`).
    pub fn merge_reduction(&self) -> usize {
        self.merge_convs.iter().map(|c| c.kernel - 1).sum()
    }
    /// Channels after the per-level convolutions of one level.
    pub fn level_channels(&self, in_channels: usize) -> usize {
        self.level_convs.last().map_or(in_channels, |c| c.channels)
    }
    /// Channels of the tower's output features.
    pub fn out_channels(&self, in_channels: usize) -> usize {
        self.merge_convs
            .last()
            .map_or(self.level_channels(in_channels) * self.levels, |c| {
                c.channels
            })
    }
    /// Level-`l` border (in level-`l` pixels) read on each side of the tile's footprint.
    pub fn pad(&self, l: usize) -> usize {
        let rf = self.merge_reduction();
        rf.div_ceil(1 << (l + 1)) + self.level_reduction() / 2
    }
    /// Offset of the tile's `th + rf` window in level `l`'s upsampled features.
    pub fn upsample_crop(&self, l: usize) -> usize {
        let rf = self.merge_reduction();
        (1 << l) * rf.div_ceil(1 << (l + 1)) - rf / 2
    }
}

/// Upper limits checked by [`Config::validate`]: far above any useful network, they keep
/// every size derived from a config (parameter counts, layer costs) from overflowing, so
/// that a corrupt config in a weights file is an error, not a panic or a huge allocation.
pub const MAX_VIEWS: usize = 64;
pub const MAX_PLANES: usize = 4096;
pub const MAX_TILE: usize = 4096;
pub const MAX_KERNEL: usize = 31;
pub const MAX_CHANNELS: usize = 4096;
/// Most convolutions in one list (`level_convs`, `merge_convs` or `depth_convs`).
pub const MAX_CONVS: usize = 32;

/// The any-number-of-views family (see `model.rs`): each source view's plane-sweep slice
/// goes through `encoder` (1x1 convolutions, ReLU after each, weights shared across
/// views, planes and levels) on `[R, G, B, A, R - m_R, G - m_G, B - m_B]` (`m`: the
/// alpha-weighted mean colour across views); views are then pooled by alpha-weighted
/// statistics, and the colour at each plane is a learned per-pixel blend of the source
/// colours (`blend`: 1x1 layers on each view's features and the colour tower's, then one
/// logit per view, softmax over the views that see the pixel) plus the colour tower's
/// linear RGB.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewPool {
    /// Per-view convolutions (kernel 1).
    pub encoder: Vec<Conv>,
    /// Hidden layers of the blend head (kernel 1); a 1-channel logit layer follows.
    pub blend: Vec<Conv>,
    /// Down-weighting of the sources beyond the nearest few (`crate::view_weights`):
    /// their alpha is scaled by a weight from their distance to the target. `None`:
    /// every source counts alike (models trained before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub falloff: Option<ViewFalloff>,
    /// Each view's geometric cue ([`crate::sweep::cue`], [`CUE_CHANNELS`] channels after
    /// its RGBA in the input) is fed to the encoder beside its colours, so the view
    /// features, their pooled statistics and the blend logits can depend on how the
    /// source sees each plane point. `false`: RGBA alone (models trained before it).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub cue: bool,
    /// The cue weighs the views instead ([`crate::pool::ViewWeigh`]): each view's alpha
    /// is multiplied by `1 + tanh(WEIGH_SCALE g(cue_v))` (in `(0, 2)`, 1 where `g` is 0),
    /// `g` a chain of 1x1 layers of these hidden widths, then one channel. The pooled mean and
    /// variance and the blend then weigh each view by how it sees the plane point, while
    /// the features whose variance is pooled stay the colours'. Exclusive with `cue`.
    /// `None`: views weigh by their alpha alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub weigh: Option<Vec<Conv>>,
    /// The sources beyond the nearest few count where their colour agrees with a near
    /// one's (`crate::view_weights::agree_gate`): their alpha at each plane point is
    /// scaled by a Gaussian of the colour distance. `None`: no gate (models trained
    /// before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agree: Option<ViewAgree>,
    /// One more cue channel, read by the view weights ([`Self::weigh`]): each view's
    /// colour disagreement with the nearest sources at each plane point
    /// ([`crate::view_weights::disagreement`]), so the weights learn per pixel which views
    /// show the surface the near ones see. Needs `weigh`. `None`: the geometric cue alone
    /// (models trained before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disagree: Option<ViewDisagree>,
    /// The `features` family: a CNN run once on each source image at each level
    /// ([`crate::features`]), its maps warped into the sweep after each view's RGBA and
    /// cue, and read by the encoder beside the colours. `None`: the sweep's RGBA alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub features: Option<SourceFeatures>,
}

/// The per-source feature CNN ([`ViewPool::features`], [`crate::features::FeatureNet`]):
/// valid `k x k` convolutions on the image zero-padded by [`Self::radius`], ReLU after all
/// but the last; weights shared across views and levels.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SourceFeatures {
    pub convs: Vec<Conv>,
}

impl SourceFeatures {
    /// Pixels each side a feature reads beyond its own: `sum (k - 1) / 2`.
    pub fn radius(&self) -> usize {
        self.convs.iter().map(|c| c.kernel / 2).sum()
    }
    /// Channels of a feature map.
    pub fn channels(&self) -> usize {
        self.convs.last().map_or(0, |c| c.channels)
    }
    /// Checks the layers: at least one, odd kernels, channels within bounds.
    pub fn validate(&self) -> Result<(), String> {
        if self.convs.is_empty() || self.convs.len() > MAX_CONVS {
            return Err(format!("pool.features: 1 to {MAX_CONVS} convolutions"));
        }
        match self.convs.iter().find(|c| {
            c.kernel % 2 == 0 || c.kernel > MAX_KERNEL || c.channels == 0 || c.channels > MAX_CHANNELS
        }) {
            Some(c) => Err(format!(
                "pool.features: kernels must be odd and at most {MAX_KERNEL}, channels 1 to {MAX_CHANNELS}, got {c:?}"
            )),
            None => Ok(()),
        }
    }
}

/// The cue's disagreement channel ([`ViewPool::disagree`]): references are the `near`
/// sources nearest the target (camera centre distance, as [`ViewFalloff`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ViewDisagree {
    pub near: usize,
}

/// The colour-agreement gate of the sources beyond the `near` nearest (ranked by camera
/// centre distance to the target, as [`ViewFalloff`]): a far source's alpha at a plane
/// point times `exp(-e / (2 sigma^2))`, `e` the least squared RGB distance (0-1 scale)
/// from its colour to a near source's that sees the point. See
/// [`crate::view_weights::agree_gate`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewAgree {
    pub near: usize,
    pub sigma: f32,
}

/// The range of [`ViewAgree::sigma`] (colours are 0-1: below it the gate shuts every
/// far view that differs at all, and `sigma^2` would underflow; above it, it gates
/// nothing).
pub const AGREE_SIGMA_RANGE: (f32, f32) = (1e-3, 10.0);

/// The weight of a source view `v` at distance `d_v` from the target camera centre:
/// `1` for the `full` nearest, `(d_ref / d_v)^power` for the others (`d_ref`: the
/// `full`-th nearest distance). See [`crate::view_weights`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ViewFalloff {
    pub full: usize,
    pub power: u32,
}

/// Largest [`ViewFalloff::power`] (a view at 1.1 times `d_ref` then weighs 2e-3).
pub const MAX_FALLOFF_POWER: u32 = 64;

/// Channels of a view's encoder input: its RGBA and its colour minus the mean colour
/// (then its cue, with [`ViewPool::cue`]).
pub const ENCODER_IN: usize = 7;
/// Channels of a view's geometric cue ([`crate::sweep::cue`]).
pub const CUE_CHANNELS: usize = 5;
/// Added to the alpha sum before dividing (pixels no view sees get zero statistics).
pub const POOL_EPS: f64 = 1e-6;
/// Added to the blend weights' sum (pixels no view sees get colour `out(f)` alone).
pub const BLEND_EPS: f64 = 1e-12;
/// Scale of the cue's view weights ([`ViewPool::weigh`]): `k = 1 + tanh(WEIGH_SCALE g)`
/// (`= 2 sigmoid(8 g)`). Adam moves every weight by about the learning rate per step; the
/// scale lets the factor, which starts at 1 (`g = 0`), move as fast as the rest of a
/// trained model when it is fine-tuned (at 1/2, `g`'s weights grew to 0.015 in 700 steps
/// of Adam 2e-4, a factor within 0.1 of 1).
pub const WEIGH_SCALE: f64 = 4.0;
/// Bound on the blend logits: `exp(+-20)` stays far inside f32's range.
pub const BLEND_LOGIT_BOUND: f64 = 20.0;

impl ViewPool {
    /// Channels of the encoder's input: [`ENCODER_IN`], plus [`CUE_CHANNELS`] with the cue.
    pub fn encoder_in(&self) -> usize {
        ENCODER_IN + if self.cue { CUE_CHANNELS } else { 0 } + self.feature_channels()
    }
    /// Channels of each view's warped source features ([`Self::features`]; 0 without).
    pub fn feature_channels(&self) -> usize {
        self.features.as_ref().map_or(0, SourceFeatures::channels)
    }
    /// Whether the model reads each view's cue (in its encoder, or to weigh the views).
    pub fn reads_cue(&self) -> bool {
        self.cue || self.weigh.is_some()
    }
    /// Channels of each view's cue: [`CUE_CHANNELS`], plus 1 with [`Self::disagree`].
    pub fn cue_channels(&self) -> usize {
        CUE_CHANNELS + usize::from(self.disagree.is_some())
    }
    /// Channels of one view in an input level: RGBA, then the cue when the model reads it.
    pub fn view_channels(&self) -> usize {
        4 + if self.reads_cue() {
            self.cue_channels()
        } else {
            0
        } + self.feature_channels()
    }
    /// Channels of one view the encoder reads: RGBA, then the cue with [`Self::cue`]
    /// (with [`Self::weigh`], the weighed RGBA alone).
    pub fn encoder_view_channels(&self) -> usize {
        4 + if self.cue { CUE_CHANNELS } else { 0 } + self.feature_channels()
    }
    /// Channels of one view's features `e_v`.
    pub fn features(&self) -> usize {
        self.encoder
            .last()
            .map_or(self.encoder_in(), |c| c.channels)
    }
    /// Channels of the pooled tower input: mean RGB, coverage, mean and variance of `e`.
    pub fn pooled_channels(&self) -> usize {
        4 + 2 * self.features()
    }
}

/// The whole network's configuration. Serialized as JSON into the weights' metadata.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Config {
    pub name: String,
    /// Source views `V` per target.
    pub views: usize,
    /// Depth planes `D` used in training and by default when rendering.
    pub planes: usize,
    /// Resolution levels `L` of the input (level `l` at `1 / 2^l` resolution).
    pub levels: usize,
    /// Output tile side used for training samples.
    pub tile: usize,
    pub select: TowerConfig,
    /// Selection layers connected across depth: convolutions along the plane axis
    /// (zero-padded to keep `D`), ReLU between them; the last has 1 channel and is
    /// followed by `tanh`, a learned scale `exp(log_scale)`, and softmax over depth.
    pub depth_convs: Vec<Conv>,
    pub colour: TowerConfig,
    /// Feed the raw centre RGBA of the sources to the colour tower's linear layer.
    pub colour_skip: bool,
    /// `Some`: the any-number-of-views family (inputs `[B, D, V, 4, H, W]`, any `V`;
    /// `views` is then only the default); `None`: the paper's (views concatenated,
    /// inputs `[B, D, 4V, H, W]`, exactly `views`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pool: Option<ViewPool>,
    /// Depth planes a render uses unless told otherwise, when not `planes` (a tuned
    /// model's: `tune --render-planes`). `planes` stays the count the network was
    /// trained at, which pruning may thin requested planes down to.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub render_planes: Option<usize>,
}

impl Config {
    /// Depth planes a render uses unless told otherwise: `render_planes`, else `planes`.
    pub fn default_render_planes(&self) -> usize {
        self.render_planes.unwrap_or(self.planes)
    }

    /// As close to the paper as its text allows: 5 views, 96 planes, 4 levels, 8x8 output
    /// tiles from 26x26 level-0 inputs. The paper's figure with layer widths is not in the
    /// text; widths here follow its description (2D ReLU convs shared across planes,
    /// layers across depth, tanh, softmax; colour tower of 2D convs + linear RGB).
    pub fn paper() -> Self {
        Self {
            name: "paper".into(),
            views: 5,
            planes: 96,
            levels: 4,
            tile: 8,
            select: TowerConfig {
                levels: 4,
                level_convs: vec![c(5, 96), c(3, 48), c(3, 16)],
                merge_convs: vec![c(5, 96), c(5, 64), c(3, 32)],
            },
            depth_convs: vec![c(3, 32), c(3, 16), c(3, 1)],
            colour: TowerConfig {
                levels: 4,
                level_convs: vec![c(5, 96), c(3, 48), c(3, 16)],
                merge_convs: vec![c(5, 96), c(5, 64), c(3, 32)],
            },
            colour_skip: false,
            render_planes: None,
            pool: None,
        }
    }

    /// Sized to train usefully on 2 CPU cores: 4 views, 32 planes, 2 levels, narrow
    /// layers, and 24x24 output tiles (large tiles share the border work).
    pub fn tiny() -> Self {
        Self {
            name: "tiny".into(),
            views: 4,
            planes: 32,
            levels: 2,
            tile: 24,
            select: TowerConfig {
                levels: 2,
                level_convs: vec![c(3, 12), c(3, 12)],
                merge_convs: vec![c(3, 16), c(3, 12)],
            },
            depth_convs: vec![c(3, 12), c(3, 8), c(3, 1)],
            colour: TowerConfig {
                levels: 1,
                level_convs: vec![c(1, 12)],
                merge_convs: vec![c(1, 12)],
            },
            colour_skip: true,
            render_planes: None,
            pool: None,
        }
    }

    /// The any-number-of-views family ([`ViewPool`]), sized to train on 2 CPU cores and
    /// to render within about twice `tiny`'s time: 6 views by default (any number works),
    /// 32 planes, 3 levels, 24x24 output tiles; widths multiples of 6 (the convolution
    /// kernels' tile); the view falloff `4:8` (`crate::view_weights`). The shipped default
    /// was fine-tuned from such a model (trained without a falloff) with the proximity
    /// weights `1:2` in its own config (`runs/nviews-prox/config.json`); training from
    /// scratch with them has not been measured.
    pub fn nviews() -> Self {
        Self {
            name: "nviews".into(),
            views: 6,
            planes: 32,
            levels: 3,
            tile: 24,
            select: TowerConfig {
                levels: 3,
                level_convs: vec![c(3, 12), c(3, 12)],
                merge_convs: vec![c(3, 12), c(3, 12)],
            },
            depth_convs: vec![c(3, 12), c(3, 6), c(3, 1)],
            colour: TowerConfig {
                levels: 1,
                level_convs: vec![c(1, 12)],
                merge_convs: vec![],
            },
            colour_skip: false,
            render_planes: None,
            pool: Some(ViewPool {
                encoder: vec![c(1, 6), c(1, 6)],
                blend: vec![c(1, 6)],
                falloff: Some(ViewFalloff { full: 4, power: 8 }),
                cue: false,
                weigh: None,
                agree: None,
                disagree: None,
                features: None,
            }),
        }
    }

    /// [`Self::nviews`] with the per-view geometric cue ([`ViewPool::cue`]) and the
    /// shipped default's proximity weights `1:2`.
    pub fn nviews_cue() -> Self {
        let mut c = Self::nviews();
        c.name = "nviews-cue".into();
        if let Some(p) = c.pool.as_mut() {
            p.cue = true;
            p.falloff = Some(ViewFalloff { full: 1, power: 2 });
        }
        c
    }

    /// [`Self::nviews`] with views weighed by their geometric cue ([`ViewPool::weigh`]:
    /// one hidden layer of 8) and the shipped default's proximity weights `1:2`.
    pub fn nviews_weigh() -> Self {
        let mut c = Self::nviews();
        c.name = "nviews-weigh".into();
        if let Some(p) = c.pool.as_mut() {
            p.weigh = Some(vec![Conv {
                kernel: 1,
                channels: 8,
            }]);
            p.falloff = Some(ViewFalloff { full: 1, power: 2 });
        }
        c
    }

    /// [`Self::nviews_weigh`] with the colour-disagreement channel in the cue
    /// ([`ViewPool::disagree`], the 4 nearest views as references).
    pub fn nviews_disagree() -> Self {
        let mut c = Self::nviews_weigh();
        c.name = "nviews-disagree".into();
        if let Some(p) = c.pool.as_mut() {
            p.disagree = Some(ViewDisagree { near: 4 });
        }
        c
    }

    /// [`Self::nviews_disagree`] reading each source once: a feature CNN per source image
    /// and level ([`ViewPool::features`]: two 3x3 layers of 12 and one of 8, radius 3,
    /// so 7 pixels at each level and 28 at level 2 in full-resolution pixels), its maps
    /// warped beside the RGBA, and an encoder of 8 then 6 channels reading them.
    pub fn nviews_features() -> Self {
        let mut c = Self::nviews_disagree();
        c.name = "nviews-features".into();
        if let Some(p) = c.pool.as_mut() {
            p.features = Some(SourceFeatures {
                convs: vec![c3(12), c3(12), c3(8)],
            });
            p.encoder = vec![
                Conv {
                    kernel: 1,
                    channels: 8,
                },
                Conv {
                    kernel: 1,
                    channels: 6,
                },
            ];
        }
        c
    }

    /// The presets' names, as [`Self::preset`] takes them.
    pub const PRESETS: [&'static str; 7] = [
        "tiny",
        "paper",
        "nviews",
        "nviews-cue",
        "nviews-weigh",
        "nviews-disagree",
        "nviews-features",
    ];

    /// A preset by name.
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "paper" => Some(Self::paper()),
            "tiny" => Some(Self::tiny()),
            "nviews" => Some(Self::nviews()),
            "nviews-cue" => Some(Self::nviews_cue()),
            "nviews-weigh" => Some(Self::nviews_weigh()),
            "nviews-disagree" => Some(Self::nviews_disagree()),
            "nviews-features" => Some(Self::nviews_features()),
            _ => None,
        }
    }

    /// Input channels per plane with the default number of views: RGBA of every source.
    pub fn in_channels(&self) -> usize {
        4 * self.views
    }

    /// Channels per plane the towers read: the concatenated RGBA of the sources (paper
    /// family) or the pooled statistics ([`ViewPool::pooled_channels`]).
    pub fn tower_in_channels(&self) -> usize {
        self.pool
            .as_ref()
            .map_or(self.in_channels(), ViewPool::pooled_channels)
    }

    /// Whether the model takes `v` source views: exactly `views` for the paper family,
    /// 1 to [`MAX_VIEWS`] for the any-number-of-views family.
    pub fn accepts_views(&self, v: usize) -> bool {
        match self.pool {
            Some(_) => (1..=MAX_VIEWS).contains(&v),
            None => v == self.views,
        }
    }

    /// Channels of one view in an input level: 4 (RGBA), or with the cue
    /// [`ViewPool::view_channels`].
    pub fn view_channels(&self) -> usize {
        self.pool.as_ref().map_or(4, ViewPool::view_channels)
    }

    /// Shape of an input level for `v` views: `[B, D, 4V, H, W]` (paper family) or
    /// `[B, D, V, C_v, H, W]` (any-number-of-views family, `C_v` = [`Self::view_channels`]:
    /// 4, or 4 + [`CUE_CHANNELS`] with the cue); the same bytes either way.
    pub fn input_shape(&self, b: usize, d: usize, v: usize, h: usize, w: usize) -> Vec<usize> {
        match &self.pool {
            Some(p) => vec![b, d, v, p.view_channels(), h, w],
            None => vec![b, d, 4 * v, h, w],
        }
    }

    /// Tile origins and sizes must be multiples of this (`2^(L-1)`).
    pub fn tile_align(&self) -> usize {
        1 << (self.levels - 1)
    }

    /// The side of the tiles a `width x height` image is rendered in when `tile` is asked
    /// for: at least 1 and at most the image's larger side (a larger tile covers the same
    /// image and only adds padding), rounded up to [`Self::tile_align`].
    pub fn tile_side(&self, tile: usize, (width, height): (usize, usize)) -> usize {
        let a = self.tile_align();
        tile.clamp(1, width.max(height).max(1)).div_ceil(a) * a
    }

    fn towers(&self) -> [&TowerConfig; 2] {
        [&self.select, &self.colour]
    }

    /// Level-`l` border read on each side of the tile's footprint: the larger of the
    /// towers' needs (0 if no tower reads level `l`).
    pub fn pad(&self, l: usize) -> usize {
        self.towers()
            .iter()
            .filter(|t| l < t.levels)
            .map(|t| t.pad(l))
            .max()
            .unwrap_or(0)
    }

    /// Size of the level-`l` input for an output side of `t` pixels.
    pub fn input_size(&self, l: usize, t: usize) -> usize {
        (t >> l) + 2 * self.pad(l)
    }

    /// First level-`l` input pixel for an output tile starting at level-0 pixel `x0`.
    pub fn input_origin(&self, l: usize, x0: i64) -> i64 {
        x0.div_euclid(1 << l) - self.pad(l) as i64
    }

    /// Receptive field of one output pixel at level 0 (largest over towers and levels).
    pub fn receptive_field(&self) -> usize {
        (0..self.levels)
            .map(|l| (2 * self.pad(l) + 1) << l)
            .max()
            .unwrap_or(1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_are_aligned_and_no_larger_than_the_image() {
        let cfg = Config::paper();
        let a = cfg.tile_align();
        assert_eq!(cfg.tile_side(0, (100, 50)), a);
        assert_eq!(
            cfg.tile_side(usize::MAX, (100, 50)),
            100usize.div_ceil(a) * a
        );
        assert_eq!(cfg.tile_side(33, (100, 50)), 33usize.div_ceil(a) * a);
        assert_eq!(cfg.tile_side(7, (0, 0)), a);
    }

    #[test]
    fn paper_reads_26_from_8() {
        let p = Config::paper();
        p.validate().unwrap();
        assert_eq!(p.input_size(0, 8), 26);
        for l in 0..4 {
            // Every level covers at least the level-0 footprint.
            assert!((p.input_size(l, 8) << l) >= 26, "level {l}");
        }
    }

    #[test]
    fn every_preset_name_is_a_valid_preset() {
        for name in Config::PRESETS {
            let c = Config::preset(name).unwrap();
            assert_eq!(c.name, name);
            c.validate().unwrap();
        }
    }

    #[test]
    fn tiny_is_valid() {
        let t = Config::tiny();
        t.validate().unwrap();
        assert!(t.parameters() > 1000);
        assert!(t.macs_per_pixel() > 0.0);
    }

    /// A falloff outside its ranges is refused; a config without one still parses.
    #[test]
    fn falloff_is_validated_and_optional() {
        let mut c = Config::nviews();
        c.validate().unwrap();
        for (full, power) in [
            (0, 8),
            (4, 0),
            (MAX_VIEWS + 1, 8),
            (4, MAX_FALLOFF_POWER + 1),
        ] {
            if let Some(p) = c.pool.as_mut() {
                p.falloff = Some(ViewFalloff { full, power });
            }
            let err = c.validate().unwrap_err();
            assert!(err.contains("pool.falloff"), "{err}");
        }
        let mut json = serde_json::to_value(Config::nviews()).unwrap();
        json["pool"].as_object_mut().unwrap().remove("falloff");
        let old: Config = serde_json::from_value(json).unwrap();
        assert_eq!(old.pool.and_then(|p| p.falloff), None);
    }

    /// A gate outside its ranges is refused; a config without one still parses and
    /// does not write it.
    #[test]
    fn agree_is_validated_and_optional() {
        let mut c = Config::nviews_weigh();
        for (near, sigma) in [
            (0, 0.1),
            (MAX_VIEWS + 1, 0.1),
            (4, 0.0),
            (4, -1.0),
            (4, f32::NAN),
            (4, 1e-30),
            (4, f32::INFINITY),
        ] {
            if let Some(p) = c.pool.as_mut() {
                p.agree = Some(ViewAgree { near, sigma });
            }
            let err = c.validate().unwrap_err();
            assert!(err.contains("pool.agree"), "{err}");
        }
        if let Some(p) = c.pool.as_mut() {
            p.agree = Some(ViewAgree {
                near: 4,
                sigma: 0.1,
            });
        }
        c.validate().unwrap();
        let back: Config = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
        let json = serde_json::to_value(Config::nviews_weigh()).unwrap();
        assert!(json["pool"].get("agree").is_none());
    }

    /// The disagreement channel needs the view weights and a near count in range; it
    /// adds one cue channel; a config without it does not write it.
    #[test]
    fn disagree_is_validated_and_optional() {
        let mut c = Config::nviews_weigh();
        let cv = c.view_channels();
        for near in [0, MAX_VIEWS + 1] {
            if let Some(p) = c.pool.as_mut() {
                p.disagree = Some(ViewDisagree { near });
            }
            let err = c.validate().unwrap_err();
            assert!(err.contains("pool.disagree"), "{err}");
        }
        if let Some(p) = c.pool.as_mut() {
            p.disagree = Some(ViewDisagree { near: 4 });
        }
        c.validate().unwrap();
        assert_eq!(c.view_channels(), cv + 1);
        let back: Config = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
        if let Some(p) = c.pool.as_mut() {
            p.weigh = None;
            p.cue = true;
        }
        assert!(c.validate().unwrap_err().contains("needs pool.weigh"));
        let json = serde_json::to_value(Config::nviews_weigh()).unwrap();
        assert!(json["pool"].get("disagree").is_none());
    }

    /// `render_planes` is optional (absent from configs without it, and not written when
    /// `None`), is the renders' default when present, and is refused outside its range.
    #[test]
    fn render_planes_is_optional_and_validated() {
        let c = Config::nviews();
        assert!(!serde_json::to_string(&c).unwrap().contains("render_planes"));
        assert_eq!(c.default_render_planes(), c.planes);
        let tuned = Config {
            render_planes: Some(48),
            ..c.clone()
        };
        tuned.validate().unwrap();
        assert_eq!(tuned.default_render_planes(), 48);
        let back: Config = serde_json::from_str(&serde_json::to_string(&tuned).unwrap()).unwrap();
        assert_eq!(back, tuned);
        for bad in [0, MAX_PLANES + 1] {
            let err = Config {
                render_planes: Some(bad),
                ..c.clone()
            }
            .validate()
            .unwrap_err();
            assert!(err.contains("render_planes"), "{err}");
        }
    }

    #[test]
    fn origins_are_consistent_with_sizes() {
        let p = Config::paper();
        for l in 0..p.levels {
            let a = p.input_origin(l, 64);
            let b = p.input_origin(l, 72);
            assert_eq!(b - a, (8 >> l) as i64);
        }
    }
}
