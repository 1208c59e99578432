//! The any-number-of-views family: invariance to the views' order and to views that see
//! nothing, every view count from 1 to 16, gradients through the pooling and the blend by
//! finite differences, the fused inference path against training's, and tiled renders.

use anyhow::Result;
use candle_core::{DType, Device, Tensor};
use deepstereo_core::config::{Config, Conv, TowerConfig, ViewPool};
use deepstereo_core::geometry::inverse_depths;
use deepstereo_core::inputs::PyramidSource;
use deepstereo_core::render::{render_view, CandleBackend};
use deepstereo_core::synth::{generate, SynthOptions, SynthScene};
use deepstereo_core::weights::{init_seeded, named_vars};

/// A small pooled config: 2 levels, merge and depth convs, two encoder and blend layers.
fn small() -> Config {
    let c = |k, ch| Conv {
        kernel: k,
        channels: ch,
    };
    Config {
        name: "small-pooled".into(),
        views: 3,
        planes: 5,
        levels: 2,
        tile: 4,
        select: TowerConfig {
            levels: 2,
            level_convs: vec![c(3, 4)],
            merge_convs: vec![c(3, 4)],
        },
        depth_convs: vec![c(3, 3), c(3, 1)],
        colour: TowerConfig {
            levels: 1,
            level_convs: vec![c(1, 3)],
            merge_convs: vec![c(1, 3)],
        },
        colour_skip: false,
        render_planes: None,
        pool: Some(ViewPool {
            encoder: vec![c(1, 4), c(1, 3)],
            blend: vec![c(1, 4)],
            falloff: None,
            cue: false,
            weigh: None,
            agree: None,
            disagree: None,
            features: None,
        }),
    }
}

/// `cfg` with the per-view cue.
fn with_cue(mut cfg: Config) -> Config {
    if let Some(p) = cfg.pool.as_mut() {
        p.cue = true;
    }
    cfg
}

/// `cfg` with the views weighed by their cue, `g` linear in it (no hidden layer, so no
/// ReLU kink for the finite differences to straddle: a hidden layer on random cues puts
/// about one of its ~10^4 pre-activations within 1e-5 of 0; `nviews-weigh`'s hidden
/// layer is checked by the other tests here and against PyTorch's gradients in
/// `python/ddp_check.py`).
fn with_weigh(mut cfg: Config) -> Config {
    if let Some(p) = cfg.pool.as_mut() {
        p.weigh = Some(vec![]);
    }
    cfg
}

/// `init_seeded`, with the cue's view-weight layers (the last starts at zero) drawn in
/// [-0.1, 0.1), so that the tests see factors other than 1 (0.2 to 1.8 on these inputs).
fn init(cfg: &Config, dtype: DType, seed: u64) -> Result<deepstereo_core::weights::Trainable> {
    let t = init_seeded(cfg, dtype, &Device::Cpu, seed)?;
    for (name, var) in named_vars(&t.varmap) {
        if name.starts_with("views.weigh.") {
            let n = var.as_tensor().elem_count();
            let v = Tensor::from_vec(
                rand_vec(n, seed + n as u64, -0.1, 0.1),
                var.as_tensor().dims(),
                &Device::Cpu,
            )?;
            var.set(&v.to_dtype(dtype)?)?;
        }
    }
    Ok(t)
}

/// [`with_weigh`] with a hidden layer of 3 (as `nviews-weigh`'s 8): the fused rendering
/// pass against the training forward.
fn with_weigh_hidden(mut cfg: Config) -> Config {
    if let Some(p) = cfg.pool.as_mut() {
        p.weigh = Some(vec![Conv {
            kernel: 1,
            channels: 3,
        }]);
    }
    cfg
}

/// `cfg` (with `weigh`) given the colour-disagreement channel: its cue has one more
/// channel, which the view weights read.
fn with_disagree(mut cfg: Config) -> Config {
    if let Some(p) = cfg.pool.as_mut() {
        p.disagree = Some(deepstereo_core::config::ViewDisagree { near: 2 });
    }
    cfg
}

/// Deterministic pseudo-random values in [lo, hi).
fn rand_vec(n: usize, seed: u64, lo: f64, hi: f64) -> Vec<f64> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            lo + (hi - lo) * ((s >> 11) as f64 / (1u64 << 53) as f64)
        })
        .collect()
}

/// Random inputs `[B, D, V, C_v, H, W]` per level: colours in [0, 1], alphas 0, 1 or
/// fractional, cue channels (when the config has them) in [-7, 3].
fn inputs(cfg: &Config, b: usize, v: usize, dtype: DType, seed: u64) -> Result<Vec<Tensor>> {
    let c = cfg.view_channels();
    (0..cfg.levels)
        .map(|l| {
            let s = cfg.input_size(l, cfg.tile);
            let n = b * cfg.planes * v * c * s * s;
            let mut data = rand_vec(n, seed + l as u64, 0.0, 1.0);
            for (i, x) in data.iter_mut().enumerate() {
                if (i / (s * s)) % c >= 4 {
                    *x = *x * 10.0 - 7.0;
                } else if (i / (s * s)) % c == 3 {
                    *x = if *x < 0.2 {
                        0.0
                    } else if *x > 0.5 {
                        1.0
                    } else {
                        *x
                    };
                }
            }
            let t = Tensor::from_vec(data, (b, cfg.planes, v, c, s, s), &Device::Cpu)?;
            Ok(t.to_dtype(dtype)?)
        })
        .collect()
}

/// The views of every level in the order `order` (indices into the views axis).
fn reorder(x: &[Tensor], order: &[usize]) -> Result<Vec<Tensor>> {
    x.iter()
        .map(|t| {
            let idx = Tensor::from_vec(
                order.iter().map(|&i| i as u32).collect::<Vec<_>>(),
                order.len(),
                t.device(),
            )?;
            Ok(t.index_select(&idx, 2)?)
        })
        .collect()
}

/// Gradients below this are compared absolutely.
const GRAD_FLOOR: f64 = 1e-5;

fn max_diff(a: &Tensor, b: &Tensor) -> Result<f32> {
    Ok(a.sub(b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?)
}

#[test]
fn views_order_does_not_matter() -> Result<()> {
    for cfg in [
        Config::nviews(),
        Config::nviews_cue(),
        Config::nviews_weigh(),
        with_disagree(Config::nviews_weigh()),
    ] {
        let t = init(&cfg, DType::F32, 3)?;
        let x = inputs(&cfg, 1, 5, DType::F32, 1)?;
        let a = t.model.forward(&x)?;
        let b = t.model.forward(&reorder(&x, &[3, 0, 4, 2, 1])?)?;
        let (di, ds) = (
            max_diff(&a.image, &b.image)?,
            max_diff(&a.selection, &b.selection)?,
        );
        println!(
            "{}: shuffled views: image {di:e}, selection {ds:e}",
            cfg.name
        );
        assert!(di < 1e-6 && ds < 1e-6, "image {di}, selection {ds}");
    }
    Ok(())
}

/// Empty views have alpha and colour 0; with the cue, their cue is arbitrary (it is
/// what the geometry gives), and must not matter either.
#[test]
fn a_view_that_sees_nothing_changes_nothing() -> Result<()> {
    for cfg in [
        Config::nviews(),
        Config::nviews_cue(),
        Config::nviews_weigh(),
        with_disagree(Config::nviews_weigh()),
    ] {
        let t = init(&cfg, DType::F32, 4)?;
        let x = inputs(&cfg, 2, 3, DType::F32, 2)?;
        let with = |extra: usize, at: usize| -> Result<Vec<Tensor>> {
            x.iter()
                .zip(inputs(&cfg, 2, extra, DType::F32, 99)?)
                .map(|(t, noise)| {
                    let c = t.dim(3)?;
                    let mut shape = t.dims().to_vec();
                    (shape[2], shape[3]) = (extra, 4);
                    let zeros = Tensor::zeros(shape, t.dtype(), t.device())?;
                    let empty = match c {
                        4 => zeros,
                        _ => Tensor::cat(&[&zeros, &noise.narrow(3, 4, c - 4)?], 3)?,
                    };
                    let (front, back) = (t.narrow(2, 0, at)?, t.narrow(2, at, 3 - at)?);
                    Ok(Tensor::cat(&[&front, &empty, &back], 2)?)
                })
                .collect()
        };
        // Each path against itself (training's forward and the fused rendering passes
        // agree to rounding, tested in `every_view_count_from_1_to_16_runs`).
        let (base_f, base_i) = (t.model.forward(&x)?, t.model.infer(&x)?);
        for (extra, at) in [(1, 3), (1, 0), (4, 1)] {
            let x2 = with(extra, at)?;
            for (base, o) in [
                (&base_f, t.model.forward(&x2)?),
                (&base_i, t.model.infer(&x2)?),
            ] {
                let di = max_diff(&base.image, &o.image)?;
                let ds = max_diff(&base.selection, &o.selection)?;
                println!(
                    "{}: {extra} empty views at {at}: image {di:e}, selection {ds:e}",
                    cfg.name
                );
                assert!(di < 2e-6 && ds < 2e-6, "image {di}, selection {ds}");
            }
        }
    }
    Ok(())
}

#[test]
fn every_view_count_from_1_to_16_runs() -> Result<()> {
    let weighs = [
        with_weigh(small()),
        with_weigh_hidden(small()),
        with_disagree(with_weigh_hidden(small())),
    ];
    for cfg in [small(), with_cue(small())].into_iter().chain(weighs) {
        every_view_count(&cfg)?;
    }
    Ok(())
}

fn every_view_count(cfg: &Config) -> Result<()> {
    let cfg = cfg.clone();
    let t = init(&cfg, DType::F32, 5)?;
    for v in 1..=16 {
        let x = inputs(&cfg, 2, v, DType::F32, 10 + v as u64)?;
        let o = t.model.forward(&x)?;
        let f = t.model.infer(&x)?;
        assert_eq!(o.image.dims(), [2, 3, cfg.tile, cfg.tile]);
        let sums = o.selection.sum(1)?.flatten_all()?.to_vec1::<f32>()?;
        assert!(sums.iter().all(|s| (s - 1.0).abs() < 1e-5), "V={v}");
        let img = o.image.flatten_all()?.to_vec1::<f32>()?;
        assert!(img.iter().all(|p| p.is_finite()), "V={v}");
        let di = max_diff(&o.image, &f.image)?;
        assert!(di < 1e-5, "V={v}: infer differs from forward by {di}");
    }
    Ok(())
}

#[test]
fn wrong_input_layout_is_an_error() -> Result<()> {
    let cfg = small();
    let t = init(&cfg, DType::F32, 5)?;
    let s = cfg.input_size(0, cfg.tile);
    let flat = Tensor::zeros((1, cfg.planes, 12, s, s), DType::F32, &Device::Cpu)?;
    let err = t.model.forward(&[flat.clone(), flat]).err();
    assert!(err.is_some_and(|e| e.to_string().contains("[B, D, V, 4, H, W]")));
    // RGBA alone where the model reads the cue, and the reverse.
    let cue = with_cue(small());
    let tc = init(&cue, DType::F32, 5)?;
    let err = tc.model.forward(&inputs(&cfg, 1, 2, DType::F32, 3)?).err();
    assert!(err.is_some_and(|e| e.to_string().contains("[B, D, V, 9, H, W]")));
    assert!(t
        .model
        .forward(&inputs(&cue, 1, 2, DType::F32, 3)?)
        .is_err());
    let weigh = with_weigh(small());
    let tw = init(&weigh, DType::F32, 5)?;
    let err = tw.model.forward(&inputs(&cfg, 1, 2, DType::F32, 3)?).err();
    assert!(err.is_some_and(|e| e.to_string().contains("[B, D, V, 9, H, W]")));
    Ok(())
}

#[test]
fn gradients_through_the_pooling_match_finite_differences_f64() -> Result<()> {
    // Input seeds chosen so that no ReLU pre-activation lies within eps of its kink (with
    // seed 7, the disagreement config puts one of the colour tower's there: its bias's
    // difference quotient then straddles the kink, 7% off at eps 1e-5, within 1e-4 at 1e-7).
    for (cfg, seed) in [
        (small(), 7),
        (with_cue(small()), 7),
        (with_weigh(small()), 7),
        (with_disagree(with_weigh(small())), 8),
    ] {
        pooling_gradients(&cfg, seed)?;
    }
    Ok(())
}

fn pooling_gradients(cfg: &Config, seed: u64) -> Result<()> {
    let cfg = cfg.clone();
    let t = init(&cfg, DType::F64, 6)?;
    let x = inputs(&cfg, 2, 3, DType::F64, seed)?;
    let (th, d) = (cfg.tile, cfg.planes);
    let dev = &Device::Cpu;
    let r1 = Tensor::from_vec(
        rand_vec(2 * 3 * th * th, 11, -1.0, 1.0),
        (2, 3, th, th),
        dev,
    )?;
    let r2 = Tensor::from_vec(
        rand_vec(2 * d * th * th, 13, -1.0, 1.0),
        (2, d, th, th),
        dev,
    )?;
    let loss_of = || -> Result<Tensor> {
        let o = t.model.forward(&x)?;
        Ok(((o.image * &r1)?.sum_all()? + (o.selection * &r2)?.sum_all()?)?)
    };
    let grads = loss_of()?.backward()?;
    // Central differences: truncation ~eps^2, rounding ~1e-16 |loss| / eps.
    let eps = 1e-5;
    let mut worst = 0f64;
    let mut checked = 0;
    for (name, var) in named_vars(&t.varmap) {
        let g = grads
            .get(var.as_tensor())
            .ok_or_else(|| anyhow::anyhow!("no gradient for {name}"))?
            .flatten_all()?
            .to_vec1::<f64>()?;
        let w0 = var.as_tensor().flatten_all()?.to_vec1::<f64>()?;
        for i in [0, w0.len() / 2, w0.len() - 1] {
            let eval = |delta: f64| -> Result<f64> {
                let mut w = w0.clone();
                w[i] += delta;
                var.set(&Tensor::from_vec(w, var.as_tensor().dims(), dev)?)?;
                Ok(loss_of()?.to_scalar::<f64>()?)
            };
            let fd = (eval(eps)? - eval(-eps)?) / (2.0 * eps);
            var.set(&Tensor::from_vec(w0.clone(), var.as_tensor().dims(), dev)?)?;
            // Relative, with a floor for gradients that are zero in exact arithmetic (the
            // logit layer's bias cancels in the softmax over views).
            let err = (fd - g[i]).abs() / fd.abs().max(g[i].abs()).max(GRAD_FLOOR);
            worst = worst.max(err);
            checked += 1;
            assert!(
                err < 1e-4,
                "{name}[{i}]: autograd {} vs finite difference {fd}",
                g[i]
            );
        }
    }
    println!("{checked} gradients, worst relative error {worst:.2e}");
    assert!(checked >= 3 * 16, "only {checked} gradients checked");
    Ok(())
}

/// A procedural scene of `views` views at `(width, height)` and every view's pyramid.
fn scene_pyramids(
    seed: u64,
    views: usize,
    (width, height): (u32, u32),
    levels: usize,
) -> Result<(SynthScene, Vec<PyramidSource>)> {
    let opts = SynthOptions {
        views,
        width,
        height,
        ..SynthOptions::default()
    };
    let s = generate(seed, &opts)?;
    let pyr = (s.cameras.iter().zip(&s.images))
        .map(|(c, i)| PyramidSource::new(c, i, levels))
        .collect();
    Ok((s, pyr))
}

#[test]
fn tiled_render_equals_whole_image_render_any_views() -> Result<()> {
    for cfg in [Config::nviews(), with_disagree(Config::nviews_weigh())] {
        tiled_render(&cfg)?;
    }
    Ok(())
}

fn tiled_render(cfg: &Config) -> Result<()> {
    let (s, pyr) = scene_pyramids(22, 9, (70, 52), cfg.levels)?;
    let t = init(cfg, DType::F32, 8)?;
    let backend = CandleBackend {
        model: t.model,
        device: Device::Cpu,
    };
    let inv = inverse_depths(s.near, s.far, 10);
    for v in [2, 8] {
        let srcs: Vec<&PyramidSource> = pyr[1..=v].iter().collect();
        let whole = render_view(&backend, &s.cameras[0], &srcs, &inv, 80, &|_, _| {})?;
        let mut worst = 0f32;
        for tile in [4, 12, 24] {
            let tiled = render_view(&backend, &s.cameras[0], &srcs, &inv, tile, &|_, _| {})?;
            for (a, b) in whole.image.data.iter().zip(&tiled.image.data) {
                worst = worst.max((a - b).abs());
            }
        }
        println!(
            "{}, {v} views: worst image difference tiled vs whole {worst:e}",
            cfg.name
        );
        assert!(worst < 1e-5, "{v} views: tiled render differs by {worst}");
    }
    Ok(())
}

/// The shipped default model (`deepstereo-train/assets/nviews-disagree-scratch.safetensors`).
fn shipped() -> Result<deepstereo_core::weights::Trainable> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deepstereo-train/assets/nviews-disagree-scratch.safetensors");
    Ok(deepstereo_core::weights::load(&path, &Device::Cpu)?)
}

/// The shipped default's trained weights (a sharp selection softmax amplifies rounding):
/// shuffling 5 or 10 views changes neither the training forward nor the renderer's fused
/// inference by more than 1e-6 (sums over views accumulate in f64 for this).
#[test]
fn views_order_does_not_matter_for_the_shipped_weights() -> Result<()> {
    let t = shipped()?;
    let cfg = t.model.config().clone();
    for (v, order) in [
        (5, vec![3, 0, 4, 2, 1]),
        (10, vec![9, 2, 7, 0, 5, 1, 8, 3, 6, 4]),
    ] {
        let x = inputs(&cfg, 1, v, DType::F32, 7 + v as u64)?;
        let y = reorder(&x, &order)?;
        for (what, a, b) in [
            ("forward", t.model.forward(&x)?, t.model.forward(&y)?),
            ("infer", t.model.infer(&x)?, t.model.infer(&y)?),
        ] {
            let (di, ds) = (
                max_diff(&a.image, &b.image)?,
                max_diff(&a.selection, &b.selection)?,
            );
            println!("shipped weights, {v} views shuffled, {what}: image {di:e}, selection {ds:e}");
            assert!(
                di < 1e-6 && ds < 1e-6,
                "{what}, {v} views: image {di}, selection {ds}"
            );
        }
    }
    Ok(())
}

/// The renderer's fused path (the blend in one pass, `fused::blend_infer`) against the
/// training forward on the shipped weights, at 1, 4 and 10 views.
#[test]
fn fused_inference_equals_the_forward_for_the_shipped_weights() -> Result<()> {
    let t = shipped()?;
    let cfg = t.model.config().clone();
    for v in [1, 4, 10] {
        let x = inputs(&cfg, 2, v, DType::F32, 30 + v as u64)?;
        let (a, b) = (t.model.forward(&x)?, t.model.infer(&x)?);
        let (di, ds) = (
            max_diff(&a.image, &b.image)?,
            max_diff(&a.selection, &b.selection)?,
        );
        println!("shipped weights, {v} views: infer vs forward: image {di:e}, selection {ds:e}");
        assert!(
            di < 1e-5 && ds < 1e-5,
            "{v} views: image {di}, selection {ds}"
        );
    }
    Ok(())
}

/// `pool.falloff`: at `full` views or fewer the inputs equal the unweighted ones; beyond,
/// the alpha of each view is scaled by its distance weight and nothing else changes.
#[test]
fn falloff_scales_only_the_alpha_of_views_beyond_the_nearest() -> Result<()> {
    use deepstereo_core::inputs::tile_inputs;
    use deepstereo_core::view_weights::view_weights;
    let cfg = Config::nviews();
    let f = cfg
        .pool
        .as_ref()
        .and_then(|p| p.falloff)
        .ok_or_else(|| anyhow::anyhow!("the nviews preset has a falloff"))?;
    let mut plain = cfg.clone();
    if let Some(p) = plain.pool.as_mut() {
        p.falloff = None;
    }
    let (s, pyr) = scene_pyramids(5, 10, (48, 36), cfg.levels)?;
    let inv = inverse_depths(s.near, s.far, 6);
    let t = cfg.tile;
    for v in [f.full, 9] {
        let srcs: Vec<&PyramidSource> = pyr[1..=v].iter().collect();
        let a = tile_inputs(&cfg, &s.cameras[0], &srcs, &inv, (0, 0), (t, t))?;
        let b = tile_inputs(&plain, &s.cameras[0], &srcs, &inv, (0, 0), (t, t))?;
        let centres: Vec<_> = srcs
            .iter()
            .map(|p| Some(p.cameras[0].pose.centre()))
            .collect();
        let g = view_weights(f, s.cameras[0].pose.centre(), &centres);
        assert_eq!(g.iter().filter(|&&w| w < 1.0).count(), v - f.full.min(v));
        for ((la, lb), &(h, w)) in a.levels.iter().zip(&b.levels).zip(&a.sizes) {
            let hw = h * w;
            for (i, (sa, sb)) in la.chunks(4 * hw).zip(lb.chunks(4 * hw)).enumerate() {
                assert_eq!(sa[..3 * hw], sb[..3 * hw], "colours changed");
                let gv = g[i % v] as f32;
                for (x, y) in sa[3 * hw..].iter().zip(&sb[3 * hw..]) {
                    assert!(
                        (x - y * gv).abs() <= 1e-7,
                        "view {}: alpha {x} vs {y} * {gv}",
                        i % v
                    );
                }
            }
        }
    }
    Ok(())
}

/// `pool.agree`: at `near` views or fewer the inputs equal the ungated ones; beyond, only
/// the alpha of the views beyond the nearest changes, never upwards, and some of it does.
#[test]
fn the_colour_gate_lowers_only_the_alpha_of_views_beyond_the_nearest() -> Result<()> {
    use deepstereo_core::config::ViewAgree;
    use deepstereo_core::inputs::tile_inputs;
    use deepstereo_core::view_weights::near_views;
    let mut plain = Config::nviews();
    if let Some(p) = plain.pool.as_mut() {
        p.falloff = None;
    }
    let mut cfg = plain.clone();
    let near = 4;
    if let Some(p) = cfg.pool.as_mut() {
        p.agree = Some(ViewAgree { near, sigma: 0.1 });
    }
    let (s, pyr) = scene_pyramids(5, 10, (48, 36), cfg.levels)?;
    let inv = inverse_depths(s.near, s.far, 6);
    let t = cfg.tile;
    for v in [near, 9] {
        let srcs: Vec<&PyramidSource> = pyr[1..=v].iter().collect();
        let a = tile_inputs(&cfg, &s.cameras[0], &srcs, &inv, (0, 0), (t, t))?;
        let b = tile_inputs(&plain, &s.cameras[0], &srcs, &inv, (0, 0), (t, t))?;
        if v <= near {
            assert_eq!(a.levels, b.levels, "gated at {v} views");
            continue;
        }
        let centres: Vec<_> = srcs
            .iter()
            .map(|p| Some(p.cameras[0].pose.centre()))
            .collect();
        let is_near = near_views(near, s.cameras[0].pose.centre(), &centres);
        let mut lowered = 0;
        for (la, lb) in a.levels.iter().zip(&b.levels) {
            let hw = la.len() / (inv.len() * v * 4);
            for (i, (sa, sb)) in la.chunks(4 * hw).zip(lb.chunks(4 * hw)).enumerate() {
                assert_eq!(sa[..3 * hw], sb[..3 * hw], "colours changed");
                if is_near[i % v] {
                    assert_eq!(sa[3 * hw..], sb[3 * hw..], "a near view's alpha changed");
                }
                for (x, y) in sa[3 * hw..].iter().zip(&sb[3 * hw..]) {
                    assert!(*x <= *y && *x >= 0.0, "alpha {x} from {y}");
                    lowered += usize::from(*x < *y);
                }
            }
        }
        assert!(lowered > 0, "the gate changed nothing at {v} views");
    }
    Ok(())
}

/// `pool.disagree`: the inputs gain one cue channel after the geometric cue, equal to
/// `view_weights::disagreement` of the sweep's own RGBA (before the falloff scales the
/// alpha); the RGBA and the geometric cue stay as they were.
#[test]
fn the_disagreement_channel_follows_the_cue_and_reads_the_sweeps_own_alpha() -> Result<()> {
    use deepstereo_core::config::{ViewDisagree, CUE_CHANNELS};
    use deepstereo_core::inputs::tile_inputs;
    use deepstereo_core::view_weights::{disagreement, near_views};
    let base = Config::nviews_weigh(); // with the proximity falloff 1:2
    assert!(base.pool.as_ref().is_some_and(|p| p.falloff.is_some()));
    let mut cfg = base.clone();
    let near = 3;
    if let Some(p) = cfg.pool.as_mut() {
        p.disagree = Some(ViewDisagree { near });
    }
    let mut raw = Config::nviews();
    if let Some(p) = raw.pool.as_mut() {
        p.falloff = None;
    }
    let (s, pyr) = scene_pyramids(5, 8, (48, 36), cfg.levels)?;
    let inv = inverse_depths(s.near, s.far, 5);
    let t = cfg.tile;
    let v = 6;
    let srcs: Vec<&PyramidSource> = pyr[1..=v].iter().collect();
    let a = tile_inputs(&cfg, &s.cameras[0], &srcs, &inv, (0, 0), (t, t))?;
    let b = tile_inputs(&base, &s.cameras[0], &srcs, &inv, (0, 0), (t, t))?;
    let r = tile_inputs(&raw, &s.cameras[0], &srcs, &inv, (0, 0), (t, t))?;
    assert_eq!(
        (a.channels, b.channels),
        (4 + CUE_CHANNELS + 1, 4 + CUE_CHANNELS)
    );
    let centres: Vec<_> = srcs
        .iter()
        .map(|p| Some(p.cameras[0].pose.centre()))
        .collect();
    let is_near = near_views(near, s.cameras[0].pose.centre(), &centres);
    let mut positive = 0;
    for ((la, lb), lr) in a.levels.iter().zip(&b.levels).zip(&r.levels) {
        let hw = lr.len() / (inv.len() * v * 4);
        let q = disagreement(lr, &is_near, hw);
        let (ca, cb) = (a.channels * hw, b.channels * hw);
        for (i, (sa, sb)) in la.chunks(ca).zip(lb.chunks(cb)).enumerate() {
            assert_eq!(sa[..cb], sb[..], "RGBA or cue changed (plane-view {i})");
            assert_eq!(sa[cb..], q[i * hw..(i + 1) * hw], "plane-view {i}");
            positive += sa[cb..].iter().filter(|&&x| x > 0.0).count();
        }
    }
    assert!(positive > 0, "every disagreement is 0");
    Ok(())
}

/// The shipped default carries the proximity falloff it was fine-tuned with (`1:2`, run
/// `runs/nviews-prox`, whose config.json has it) and renders from 4 views by default.
#[test]
fn the_shipped_default_has_the_view_falloff() -> Result<()> {
    let t = shipped()?;
    let cfg = t.model.config();
    let f = cfg.pool.as_ref().and_then(|p| p.falloff);
    assert_eq!(
        f,
        Some(deepstereo_core::config::ViewFalloff { full: 1, power: 2 })
    );
    assert_eq!(cfg.views, 4, "the default number of views");
    Ok(())
}

/// `pool.cue`: the input levels hold each view's RGBA exactly as without the cue, then its
/// cue: the geometry of `sweep::cue` for that pixel's ray, plane and source centre (a
/// source that is not there has alpha 0 and the cue of a source at the target).
#[test]
fn cue_inputs_are_the_sweep_then_the_geometry() -> Result<()> {
    use deepstereo_core::config::CUE_CHANNELS;
    use deepstereo_core::inputs::{level_camera, tile_inputs};
    use deepstereo_core::sweep::cue::{centre_in, cue};
    use glam::DVec3;
    let cfg = Config::nviews_cue();
    let mut plain = cfg.clone();
    if let Some(p) = plain.pool.as_mut() {
        p.cue = false;
    }
    let (s, pyr) = scene_pyramids(5, 10, (48, 36), cfg.levels)?;
    let inv = inverse_depths(s.near, s.far, 6);
    let (t, (x0, y0)) = (cfg.tile, (8i64, 0i64));
    let empty = PyramidSource::empty(&s.cameras[0], cfg.levels);
    let srcs: Vec<&PyramidSource> = vec![&pyr[1], &pyr[2], &empty, &pyr[3]];
    let a = tile_inputs(&cfg, &s.cameras[0], &srcs, &inv, (x0, y0), (t, t))?;
    let b = tile_inputs(&plain, &s.cameras[0], &srcs, &inv, (x0, y0), (t, t))?;
    assert_eq!((a.channels, b.channels), (4 + CUE_CHANNELS, 4));
    let v = srcs.len();
    let mut checked = 0;
    for (l, ((la, lb), &(h, w))) in a.levels.iter().zip(&b.levels).zip(&a.sizes).enumerate() {
        let hw = h * w;
        let tcam = level_camera(
            &s.cameras[0],
            l,
            s.cameras[0].intrinsics.width >> l,
            s.cameras[0].intrinsics.height >> l,
        );
        for (i, (sa, sb)) in la
            .chunks(a.channels * hw)
            .zip(lb.chunks(4 * hw))
            .enumerate()
        {
            assert_eq!(sa[..4 * hw], sb[..], "level {l}: RGBA changed");
            let (z, k) = (i / v, i % v);
            let centre = centre_in(&tcam, &srcs[k].cameras[l]);
            for p in [0, hw / 2 + 3, hw - 1] {
                let (px, py) = ((p % w) as i64, (p / w) as i64);
                let uv = glam::DVec2::new(
                    (cfg.input_origin(l, x0) + px) as f64 + 0.5,
                    (cfg.input_origin(l, y0) + py) as f64 + 0.5,
                );
                let r = tcam.intrinsics.unproject_pixel(uv);
                let want = cue(DVec3::new(r.x, r.y, 1.0), inv[z], centre);
                for (c, wv) in want.iter().enumerate() {
                    let got = sa[(4 + c) * hw + p];
                    assert!(
                        (got as f64 - wv).abs() <= 1e-6 * wv.abs().max(1.0),
                        "level {l}, plane {z}, view {k}, pixel {p}, channel {c}: {got} vs {wv}"
                    );
                }
                checked += 1;
            }
            if k == 2 {
                assert!(
                    sa[3 * hw..4 * hw].iter().all(|&x| x == 0.0),
                    "empty view's alpha"
                );
            }
        }
    }
    assert!(checked > 0);
    Ok(())
}
