//! Options shared by the commands that run a model: `render`, `eval`, `report`, `demo`.

use crate::rendering::{BackendKind, PlaneSpan, RenderSettings, DEFAULT_PLAN_VIEWS};
use anyhow::{bail, Result};
use deepstereo_core::prune::{
    CoarsePass, PruneMode, PruneOptions, DEFAULT_ERROR, DEFAULT_GUIDE_LEVEL, DEFAULT_KEEP,
    DEFAULT_MARGIN, DEFAULT_MASS, DEFAULT_MAX_STEP, DEFAULT_TOLERANCE, DEFAULT_WINDOW,
};
use deepstereo_core::render::Backend;
use std::path::PathBuf;

#[derive(Debug, Clone, clap::Args)]
pub struct ModelArgs {
    /// Model weights (safetensors with its config), or `embedded` (the default: the
    /// embedded default model, `assets/nviews-disagree-scratch.safetensors`; reports name it
    /// `embedded`).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Depth planes, uniform in inverse depth between near and far (default: the model's).
    #[arg(long)]
    pub planes: Option<usize>,
    /// Source views, the nearest to the target (default: the model's). The
    /// any-number-of-views family takes any number; the paper's family at most its
    /// config's, the others being empty views (alpha 0).
    #[arg(long)]
    pub views: Option<usize>,
    /// Output tile side in pixels when rendering (bounds memory; at most the image's
    /// larger side, rounded up to the model's alignment). With --prune off the result
    /// does not depend on it (with auto, the planes are chosen per tile and block).
    #[arg(long, default_value_t = 64, help_heading = super::EXPERT)]
    pub tile: usize,
    /// Leave out what the scene does not need: `auto` keeps the planes within the depth
    /// range the scene's sparse points (or per-view bounds) allow, thins planes closer
    /// than --prune-max-step pixels of disparity, runs the network per block only on the
    /// planes a coarse pass finds surfaces on, picks the source views that see the
    /// target, and skips tiles no source covers or that are constant; `off` runs every
    /// plane of every tile from the nearest views (the plain renderer). `auto` is the
    /// default: at 32, 64 and 96 planes it rendered every real scene measured faster than
    /// `off` (2x or more at 64 and 96), mostly at a higher PSNR (docs/performance.md).
    #[arg(long, default_value_t = PruneMode::Auto)]
    pub prune: PruneMode,
    /// --prune auto: the coarse pass: `network` (the model itself at low resolution) or
    /// `photo` (photo-consistency of the sources).
    #[arg(long, default_value = "network", help_heading = super::EXPERT)]
    pub prune_coarse: CoarsePass,
    /// --prune auto, network pass: fraction of each coarse pixel's selection probability
    /// the kept planes must hold (1 keeps every plane; lower is faster).
    #[arg(long, default_value_t = DEFAULT_KEEP, help_heading = super::EXPERT)]
    pub prune_keep: f32,
    /// --prune auto, network pass (candle): a coarse pixel also needs no more planes once
    /// those kept hold 70% of its selection and leaving out the rest moves its colour by
    /// at most this (0-1 scale, every channel; 0: the selection probability alone decides).
    #[arg(long, default_value_t = DEFAULT_ERROR, help_heading = super::EXPERT)]
    pub prune_error: f32,
    /// --prune auto, network pass: pyramid level of the coarse render (1: half resolution,
    /// 2: a quarter).
    #[arg(long, default_value_t = DEFAULT_GUIDE_LEVEL, help_heading = super::EXPERT)]
    pub prune_guide_level: usize,
    /// --prune auto: largest disparity step, in source pixels, between the planes run:
    /// requested planes closer than a pixel in every source are thinned (fewer planes
    /// spread evenly), and beyond that down to the model's own plane count while the step
    /// stays within this (to three quarters of it within 2 pixels; 0: never thin).
    #[arg(long, default_value_t = DEFAULT_MAX_STEP, help_heading = super::EXPERT)]
    pub prune_max_step: f64,
    /// --prune auto, photo pass: fraction of a tile's photo-consistency evidence the kept
    /// planes must hold (1 keeps every plane any coarse sample finds plausible; lower is
    /// faster).
    #[arg(long, default_value_t = DEFAULT_MASS, help_heading = super::EXPERT)]
    pub prune_mass: f32,
    /// --prune auto: source views the coarse pass reads when the network reads fewer (the
    /// any-number-of-views family): the network's, then the next best-ranked of the
    /// others. More views choose the planes better: at 2 and 4 views the evaluation
    /// scenes' renders gain 0.04-0.80 dB for about the same time (docs/performance.md).
    /// 0: only the network's.
    #[arg(long, default_value_t = DEFAULT_PLAN_VIEWS, help_heading = super::EXPERT)]
    pub prune_views: usize,
    /// --prune auto: planes kept on each side of every plane the coarse pass keeps.
    #[arg(long, default_value_t = DEFAULT_MARGIN, help_heading = super::EXPERT)]
    pub prune_margin: usize,
    /// --prune auto, photo pass: a coarse sample finds a plane plausible when its cost is within this
    /// fraction of its cost range of its best.
    #[arg(long, default_value_t = DEFAULT_TOLERANCE, help_heading = super::EXPERT)]
    pub prune_tolerance: f32,
    /// --prune auto, photo pass: radius, in coarse samples (2 pixels apart), of the window the
    /// photo-consistency cost is averaged over.
    #[arg(long, default_value_t = DEFAULT_WINDOW, help_heading = super::EXPERT)]
    pub prune_window: usize,
    /// Where the planes lie, uniform in inverse depth: `scene` between the scene's near and
    /// far; `view` as many over the depths the camera sees (the nearest to the farthest of
    /// the scene's sparse points in its view, or its sources' per-view bounds, widened by
    /// 10% and a plane), finer where a scene's bounds are wide. Default: `scene`, and
    /// `view` for `mpi`'s bakes.
    #[arg(long, value_parser = super::choice::<PlaneSpan>())]
    pub plane_span: Option<PlaneSpan>,
    /// Runtime for the network: candle, or ort (onnxruntime on the exported model).
    #[arg(long, value_parser = super::choice::<BackendKind>(), default_value = "candle")]
    pub backend: BackendKind,
}

impl ModelArgs {
    pub fn settings(&self) -> Result<RenderSettings> {
        if self.tile == 0 {
            bail!("--tile must be at least 1");
        }
        if self.planes == Some(0) {
            bail!("--planes must be at least 1");
        }
        let prune = PruneOptions {
            mode: self.prune,
            coarse: self.prune_coarse,
            keep: self.prune_keep,
            error: self.prune_error,
            guide_level: self.prune_guide_level,
            max_step: self.prune_max_step,
            mass: self.prune_mass,
            margin: self.prune_margin,
            tolerance: self.prune_tolerance,
            window: self.prune_window,
            ..PruneOptions::default()
        };
        prune.validate()?;
        Ok(RenderSettings {
            planes: self.planes,
            views: self.views,
            tile: self.tile,
            prune,
            plan_views: self.prune_views,
            span: self.plane_span,
        })
    }

    pub fn backend(&self) -> Result<Box<dyn Backend>> {
        crate::rendering::models::make_backend(self.backend, self.model.as_deref())
    }

    pub fn name(&self) -> String {
        crate::rendering::models::model_name(self.model.as_deref())
    }
}
