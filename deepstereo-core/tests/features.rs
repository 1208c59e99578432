//! The `features` family: the maps computed in training's graph from crops give the
//! inputs rendering builds from maps of whole images; gradients reach the CNN through
//! the warp; any number of views in any order.

use anyhow::Result;
use candle_core::{Device, Tensor};
use deepstereo_core::backend::{inputs_to_tensors, CandleBackend};
use deepstereo_core::config::Config;
use deepstereo_core::geometry::inverse_depths;
use deepstereo_core::inputs::features::{tile_warps, warped_features, with_warped_features};
use deepstereo_core::inputs::{tile_inputs, tile_inputs_without_features, PyramidSource};
use deepstereo_core::render::render_view;
use deepstereo_core::synth::{generate, SynthOptions, SynthScene};
use deepstereo_core::weights::{init_seeded, named_vars, Trainable};

fn scene() -> Result<(Config, SynthScene, Trainable, Vec<PyramidSource>)> {
    let mut cfg = Config::nviews_features();
    cfg.planes = 6;
    let s = generate(
        5,
        &SynthOptions {
            views: 5,
            width: 64,
            height: 48,
            ..SynthOptions::default()
        },
    )?;
    let t = init_seeded(&cfg, candle_core::DType::F32, &Device::Cpu, 3)?;
    let pyr = (s.cameras.iter().zip(&s.images))
        .map(|(c, i)| PyramidSource::new(c, i, cfg.levels))
        .collect();
    Ok((cfg, s, t, pyr))
}

fn max_diff(a: &Tensor, b: &Tensor) -> Result<f32> {
    Ok((a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?)
}

#[test]
fn training_inputs_equal_rendering_inputs_and_train_the_cnn() -> Result<()> {
    let (cfg, s, t, pyr) = scene()?;
    let net = t.model.feature_net().expect("a feature CNN");
    let inv = inverse_depths(s.near, s.far, cfg.planes);
    let a = cfg.tile_align();
    let (origin, size) = ((a as i64, 0), (2 * a, 2 * a));
    // Rendering: maps of whole images, warped in the sweep.
    let with: Vec<PyramidSource> = (pyr[1..].iter())
        .map(|p| p.clone().with_features(net))
        .collect::<Result<_, _>>()?;
    let srcs: Vec<&PyramidSource> = with.iter().collect();
    let full = tile_inputs(&cfg, &s.cameras[0], &srcs, &inv, origin, size)?;
    let render_in = inputs_to_tensors(&cfg, &full, 1, cfg.planes, &Device::Cpu)?;
    // Training: crops through the CNN in the graph.
    let base = tile_inputs_without_features(&cfg, &s.cameras[0], &srcs, &inv, origin, size)?;
    let warps = tile_warps(
        &cfg,
        (&s.cameras[0], &srcs, &inv),
        origin,
        &base.sizes,
        net.radius(),
    )?;
    let base_t = (base.levels.iter().zip(&base.sizes))
        .map(|(d, &(h, w))| {
            Tensor::from_slice(
                d,
                (1, cfg.planes, base.views, base.channels, h, w),
                &Device::Cpu,
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    let train_in = with_warped_features(net, &base_t, std::slice::from_ref(&warps))?;
    for (l, (r, tr)) in render_in.iter().zip(&train_in).enumerate() {
        assert_eq!(r.dims(), tr.dims(), "level {l}");
        let d = max_diff(r, tr)?;
        assert!(d < 1e-5, "level {l}: inputs differ by {d}");
    }
    // The model given the maps apart (training's path) renders as given them inside.
    let feats = warped_features(net, &base_t, &[warps])?;
    let whole = t.model.forward(&train_in)?;
    let out = t.model.forward_parts(&base_t, Some(&feats))?;
    let d = max_diff(&whole.image, &out.image)?;
    assert!(d < 1e-6, "forward_parts differs from forward by {d}");
    // Rendering's fused passes give the training forward's image.
    let fused = t.model.infer(&render_in)?;
    let d = max_diff(&whole.image, &fused.image)?;
    assert!(
        d < 1e-5,
        "the fused render differs from the training forward by {d}"
    );
    // The loss reaches the CNN's first layer through the warp.
    let grads = out.image.sqr()?.sum_all()?.backward()?;
    let vars = named_vars(&t.varmap);
    let (_, w0) = vars
        .iter()
        .find(|(n, _)| n == "features.0.weight")
        .expect("features.0.weight");
    let g = grads
        .get(w0.as_tensor())
        .expect("a gradient for features.0.weight");
    let norm = g.sqr()?.sum_all()?.to_scalar::<f32>()?;
    assert!(norm > 0.0 && norm.is_finite(), "gradient norm {norm}");
    Ok(())
}

#[test]
fn renders_any_number_of_views_in_any_order() -> Result<()> {
    let (cfg, s, t, pyr) = scene()?;
    let backend = CandleBackend {
        model: t.model,
        device: Device::Cpu,
    };
    let inv = inverse_depths(s.near, s.far, cfg.planes);
    let fwd: Vec<&PyramidSource> = pyr[1..].iter().collect();
    let rev: Vec<&PyramidSource> = pyr[1..].iter().rev().collect();
    let a = render_view(&backend, &s.cameras[0], &fwd, &inv, 32, &|_, _| {})?;
    let b = render_view(&backend, &s.cameras[0], &rev, &inv, 32, &|_, _| {})?;
    let worst = (a.image.data.iter().zip(&b.image.data))
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-5, "view order changes the render by {worst}");
    assert!(a.image.data.iter().all(|v| v.is_finite()));
    let one = render_view(&backend, &s.cameras[0], &fwd[..1], &inv, 32, &|_, _| {})?;
    assert!(one.image.data.iter().all(|v| v.is_finite()));
    Ok(())
}
