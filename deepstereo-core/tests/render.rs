//! Full-image rendering: tiles compose without seams.

use anyhow::Result;
use candle_core::Device;
use deepstereo_core::config::Config;
use deepstereo_core::geometry::inverse_depths;
use deepstereo_core::inputs::PyramidSource;
use deepstereo_core::render::{render_view, CandleBackend};
use deepstereo_core::synth::{generate, SynthOptions};
use deepstereo_core::weights::init;

#[test]
fn tiled_render_equals_whole_image_render() -> Result<()> {
    let cfg = Config::tiny();
    let opts = SynthOptions {
        views: 6,
        width: 70,
        height: 52,
        ..SynthOptions::default()
    };
    let s = generate(21, &opts)?;
    let t = init(&cfg, &Device::Cpu)?;
    let backend = CandleBackend {
        model: t.model,
        device: Device::Cpu,
    };
    let pyr: Vec<PyramidSource> = s
        .cameras
        .iter()
        .zip(&s.images)
        .map(|(c, i)| PyramidSource::new(c, i, cfg.levels))
        .collect();
    let srcs: Vec<&PyramidSource> = pyr[1..=cfg.views].iter().collect();
    let inv = inverse_depths(s.near, s.far, 12);
    let whole = render_view(&backend, &s.cameras[0], &srcs, &inv, 80, &|_, _| {})?;
    let mut worst = 0f32;
    for tile in [2, 8, 14, 24] {
        let tiled = render_view(&backend, &s.cameras[0], &srcs, &inv, tile, &|_, _| {})?;
        for (a, b) in whole.image.data.iter().zip(&tiled.image.data) {
            worst = worst.max((a - b).abs());
        }
        for (a, b) in whole.depth.iter().zip(&tiled.depth) {
            assert!(
                (a - b).abs() <= 1e-4 * a.abs().max(1.0),
                "depth differs: {a} vs {b}"
            );
        }
    }
    println!("worst image difference tiled vs whole: {worst:e}");
    assert!(worst < 1e-5, "tiled render differs by {worst}");
    Ok(())
}
