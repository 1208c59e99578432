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

/// A scene prior applied by the renderer: a grid of zeros renders as the network does;
/// a grid favouring near points renders `sum_z s'_z c_z` of the network's layers with
/// the reweighed selection, tile by tile as the whole image; a model file carries the
/// prior through a save and a load.
#[test]
fn scene_prior_reweighs_the_render() -> Result<()> {
    use deepstereo_core::mpi::layers;
    use deepstereo_core::prior::PriorGrid;
    use glam::DVec3;
    let cfg = Config::tiny();
    let opts = SynthOptions {
        views: 6,
        width: 40,
        height: 32,
        ..SynthOptions::default()
    };
    let s = generate(5, &opts)?;
    let t = init(&cfg, &Device::Cpu)?;
    let pyr: Vec<PyramidSource> = (s.cameras.iter().zip(&s.images))
        .map(|(c, i)| PyramidSource::new(c, i, cfg.levels))
        .collect();
    let srcs: Vec<&PyramidSource> = pyr[1..=cfg.views].iter().collect();
    let inv = inverse_depths(s.near, s.far, 8);
    let cam = &s.cameras[0];
    let plain = CandleBackend {
        model: t.model.clone(),
        device: Device::Cpu,
    };
    let reference = render_view(&plain, cam, &srcs, &inv, 16, &|_, _| {})?;
    // A box around everything the camera sees on the planes.
    let c = cam.pose.centre();
    let (lo, hi) = (c - DVec3::splat(2.0 * s.far), c + DVec3::splat(2.0 * s.far));
    let zero = PriorGrid::zeros(lo, hi, 8)?;
    let with = |g: PriorGrid| CandleBackend {
        model: t.model.clone().with_prior(Some(g)),
        device: Device::Cpu,
    };
    let r0 = render_view(&with(zero.clone()), cam, &srcs, &inv, 16, &|_, _| {})?;
    let worst = (reference.image.data.iter().zip(&r0.image.data))
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-5, "a zero prior changed the render by {worst}");
    // Log-weights falling with camera depth (a linear field, which trilinear
    // interpolation keeps exactly): nearer planes are favoured.
    let mut shell = zero.clone();
    let [nx, ny, _] = shell.dims;
    for (i, v) in shell.values.iter_mut().enumerate() {
        let p = shell.origin
            + DVec3::new(
                (i % nx) as f64,
                ((i / nx) % ny) as f64,
                (i / (nx * ny)) as f64,
            ) * shell.cell;
        let depth = cam.pose.transform_point(p).z;
        *v = (-4.0 * (depth - s.near) / (s.far - s.near)) as f32;
    }
    let favoured = render_view(&with(shell.clone()), cam, &srcs, &inv, 16, &|_, _| {})?;
    let (cl, sl) = layers(&plain, cam, &srcs, &inv, 16, &|_, _| {})?;
    let n = 40 * 32;
    let image = shell.apply_tile(
        cam,
        &inv,
        (0, 0),
        40,
        &pad(&cl, 8 * 3, n),
        &mut pad(&sl, 8, n),
    );
    let mut differs = 0f32;
    for p in 0..n {
        let (x, y) = (p % 40, p / 40);
        for ch in 0..3 {
            let want = image[ch * 1600 + y * 40 + x].clamp(0.0, 1.0);
            let got = favoured.image.data[p * 3 + ch];
            assert!((want - got).abs() < 1e-4, "pixel {p}: {got} vs {want}");
            differs = differs.max((got - reference.image.data[p * 3 + ch]).abs());
        }
    }
    assert!(differs > 0.01, "the prior changed nothing ({differs})");
    // Through a file.
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("tuned.safetensors");
    deepstereo_core::weights::save_with_prior(&path, &cfg, &t.varmap, Some(&shell), &[])?;
    let back = deepstereo_core::weights::load(&path, &Device::Cpu)?;
    let got = back.model.prior().expect("the prior read back");
    assert_eq!((got.dims, &got.values), (shell.dims, &shell.values));
    let moved = (got.origin - shell.origin).length() + (got.cell - shell.cell).abs();
    assert!(moved < 1e-9 * shell.cell, "placement moved by {moved}");
    Ok(())
}

/// `[planes, h*w]` layers of a 40 x 32 image laid out as one 40 x 40 tile.
fn pad(v: &[f32], planes: usize, n: usize) -> Vec<f32> {
    let mut out = vec![0f32; planes * 1600];
    for z in 0..planes {
        out[z * 1600..z * 1600 + n].copy_from_slice(&v[z * n..(z + 1) * n]);
    }
    out
}
