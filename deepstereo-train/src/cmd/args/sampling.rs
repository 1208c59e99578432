//! Options shared by `train` and `samples`: how training samples are drawn (a shard of
//! `samples` is batch `b` of `train` with the same ones).

use super::parse_range_of;
use crate::training::scene_weights::SceneWeights;
use anyhow::Result;

#[derive(Debug, Clone, clap::Args)]
pub struct SamplingArgs {
    /// Source views per sample, `K` or a range `MIN-MAX` drawn afresh for every batch (or
    /// shard) (the any-number-of-views family, e.g. `2-8`; the paper's family takes
    /// exactly its config's). Default: the config's views.
    #[arg(long)]
    pub views: Option<String>,
    /// Percent of samples drawn from the procedural scenes when real ones (--data) are
    /// there too (default: every scene equally likely).
    #[arg(long)]
    pub synthetic_percent: Option<u32>,
    /// Photometric augmentation (a random exposure and white balance per sample, on the
    /// sources and the target alike) and random horizontal flips.
    #[arg(long)]
    pub augment: bool,
    /// Sparser sources, `S` or a range `MIN-MAX` drawn per sample: the sources are the
    /// S-th, 2S-th, ... nearest views, as if the scene had one view in S (wider
    /// baselines). Default: 1, the nearest views.
    #[arg(long)]
    pub view_stride: Option<String>,
    /// Skip flat tiles: redraw (up to 8 times) a training tile whose target luminance has
    /// a standard deviation under this (colours in [0, 1], e.g. 0.02). Default: every tile.
    #[arg(long)]
    pub skip_flat: Option<f32>,
    /// Draw some real scenes more or less often: `NAME=W[,NAME=W...]`, a scene named by
    /// its directory's last component drawn W times as often as an unnamed one (weight 1)
    /// among the real scenes. Default: every scene equally likely.
    #[arg(long)]
    pub scene_weights: Option<String>,
}

impl SamplingArgs {
    /// `--views` parsed (`None`: the config's).
    pub fn views_range(&self) -> Result<Option<(usize, usize)>> {
        (self.views.as_deref())
            .map(|s| parse_range_of("--views", s))
            .transpose()
    }

    /// `--view-stride` parsed (`None`: the nearest views).
    pub fn view_stride_range(&self) -> Result<Option<(usize, usize)>> {
        (self.view_stride.as_deref())
            .map(|s| parse_range_of("--view-stride", s))
            .transpose()
    }

    /// `--scene-weights` parsed (`None`: every scene alike).
    pub fn weights(&self) -> Result<Option<SceneWeights>> {
        (self.scene_weights.as_deref())
            .map(SceneWeights::parse)
            .transpose()
    }
}
