//! A procedural scene on disk and a `tiny` model for the library's unit tests.

use crate::rendering::{RenderSettings, DEFAULT_PLAN_VIEWS};
use anyhow::Result;
use deepstereo_core::config::Config;
use deepstereo_core::prune::PruneOptions;
use deepstereo_core::render::CandleBackend;
use deepstereo_core::scene::{LoadOptions, Scene};
use deepstereo_core::synth::{generate, write_scene, SynthOptions};

/// The procedural scene `generate(seed)` of 6 views of `width x height`, written to `dir`
/// and loaded; a `tiny` model initialised as `init` does; render settings of tile side
/// `tile` with the default pruning.
pub fn tiny_case(
    dir: &std::path::Path,
    seed: u64,
    (width, height): (u32, u32),
    tile: usize,
) -> Result<(Scene, Config, CandleBackend, RenderSettings)> {
    let opts = SynthOptions {
        views: 6,
        width,
        height,
        ..SynthOptions::default()
    };
    write_scene(dir, &generate(seed, &opts)?)?;
    let scene = Scene::load(dir, &LoadOptions::default())?;
    let cfg = Config::tiny();
    let backend = CandleBackend {
        model: deepstereo_core::weights::init(&cfg, &candle_core::Device::Cpu)?.model,
        device: candle_core::Device::Cpu,
    };
    let settings = RenderSettings {
        planes: None,
        views: None,
        tile,
        prune: PruneOptions::default(),
        plan_views: DEFAULT_PLAN_VIEWS,
        span: None,
    };
    Ok((scene, cfg, backend, settings))
}
