//! The renderer's fused passes of the any-number-of-views family against what they
//! replace: the encoder + pooling pass (`ViewEncoder::infer`, `fused::encode_pool`)
//! against the three passes of `ViewEncoder::forward` with `fuse` (the same stats and view
//! features, bit for bit, for any number of views, planes whose pixel count is not a
//! multiple of the pass's chunk, encoders of one to three layers, up to more outputs than
//! one register block holds), and the blend pass (`fused::blend_infer`) against the
//! training forward for every blend depth.

use anyhow::Result;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use deepstereo_core::config::{Conv, ViewPool};
use deepstereo_core::pool::ViewEncoder;

/// Sources `[B, D, V, 4, H, W]`: colours in [0, 1), alphas 0, 1 or fractional.
fn sources(shape: (usize, usize, usize, usize, usize), seed: u64) -> Result<Tensor> {
    sources_with(shape, 4, seed)
}

/// Sources `[B, D, V, C_v, H, W]`: as [`sources`], then (`C_v` > 4) cue channels in
/// [-7, 3).
fn sources_with(
    shape: (usize, usize, usize, usize, usize),
    cv: usize,
    seed: u64,
) -> Result<Tensor> {
    let (b, d, v, h, w) = shape;
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let data: Vec<f32> = (0..b * d * v * cv * h * w)
        .map(|i| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            let x = (s >> 40) as f32 / (1u64 << 24) as f32;
            match (i / (h * w)) % cv {
                3 if x < 0.2 => 0.0,
                3 if x > 0.5 => 1.0,
                c if c >= 4 => x * 10.0 - 7.0,
                _ => x,
            }
        })
        .collect();
    Ok(Tensor::from_vec(data, (b, d, v, cv, h, w), &Device::Cpu)?)
}

/// Whether the fused pass can run here (it needs AVX2 + FMA; elsewhere `infer` is `None`
/// and the renderer runs the three passes).
fn fused_runs() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

fn max_diff(a: &Tensor, b: &Tensor) -> Result<f32> {
    Ok((a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?)
}

fn encoder(channels: &[usize]) -> Result<(ViewEncoder, VarMap)> {
    encoder_with(channels, false)
}

fn encoder_with(channels: &[usize], cue: bool) -> Result<(ViewEncoder, VarMap)> {
    let pool = ViewPool {
        encoder: channels
            .iter()
            .map(|&c| Conv {
                kernel: 1,
                channels: c,
            })
            .collect(),
        blend: vec![],
        falloff: None,
        cue,
        weigh: None,
        agree: None,
        disagree: None,
        features: None,
    };
    let vm = VarMap::new();
    let enc = ViewEncoder::new(
        &pool,
        VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu),
    )?;
    Ok((enc, vm))
}

/// The largest differences of the fused pass's stats and level-0 features from the three
/// passes' on `x`.
fn diffs(enc: &ViewEncoder, x: &Tensor) -> Result<(f32, f32)> {
    let want = enc.forward(x, true)?;
    let Some((stats, Some(e))) = enc.infer(x, true)? else {
        anyhow::bail!("the fused pass did not run");
    };
    Ok((
        max_diff(&stats, &want.stats)?,
        max_diff(&e, &want.features)?,
    ))
}

#[test]
fn the_fused_pass_equals_the_three_passes() -> Result<()> {
    if !fused_runs() {
        let (enc, _vm) = encoder(&[6, 6])?;
        assert!(enc.infer(&sources((1, 2, 2, 3, 3), 1)?, true)?.is_none());
        return Ok(());
    }
    // [6, 6]: the shipped encoder; [9, 5, 3]: a hidden layer wider than a register block.
    for channels in [vec![6, 6], vec![9, 5, 3], vec![2, 8]] {
        let (enc, _vm) = encoder(&channels)?;
        for (v, h, w) in [(1, 3, 5), (3, 7, 9), (6, 9, 17), (4, 16, 16)] {
            let x = sources((2, 3, v, h, w), (v * 100 + h) as u64)?;
            let (ds, de) = diffs(&enc, &x)?;
            assert!(
                ds == 0.0 && de == 0.0,
                "{channels:?}, {v} views, {h}x{w}: stats {ds:e}, features {de:e}"
            );
            // Without the features (levels above 0): the same stats.
            let Some((again, None)) = enc.infer(&x, false)? else {
                anyhow::bail!("features written when not asked for");
            };
            assert_eq!(max_diff(&again, &enc.forward(&x, true)?.stats)?, 0.0);
        }
    }
    Ok(())
}

/// With the per-view cue after each view's RGBA: the same, bit for bit.
#[test]
fn the_fused_pass_with_the_cue_equals_the_three_passes() -> Result<()> {
    use deepstereo_core::config::CUE_CHANNELS;
    let cv = 4 + CUE_CHANNELS;
    let (enc, _vm) = encoder_with(&[6, 6], true)?;
    if !fused_runs() {
        assert!(enc
            .infer(&sources_with((1, 2, 2, 3, 3), cv, 1)?, true)?
            .is_none());
        return Ok(());
    }
    for (v, h, w) in [(1, 3, 5), (3, 7, 9), (6, 9, 17)] {
        let x = sources_with((2, 3, v, h, w), cv, (v * 10 + h) as u64)?;
        let (ds, de) = diffs(&enc, &x)?;
        assert!(
            ds == 0.0 && de == 0.0,
            "cue, {v} views, {h}x{w}: stats {ds:e}, features {de:e}"
        );
    }
    // The cue reaches the stats: other cue values, other stats.
    let x = sources_with((1, 2, 3, 5, 5), cv, 7)?;
    let y = x.narrow(3, 0, 4)?.contiguous()?;
    let y = Tensor::cat(&[&y, &(x.narrow(3, 4, CUE_CHANNELS)? + 1.0)?], 3)?;
    let (Some((a, _)), Some((b, _))) = (enc.infer(&x, false)?, enc.infer(&y, false)?) else {
        anyhow::bail!("the fused pass did not run");
    };
    assert!(max_diff(&a, &b)? > 0.0, "the cue changed nothing");
    Ok(())
}

#[test]
fn a_one_layer_encoder_agrees_with_the_candle_layer() -> Result<()> {
    // One layer: the three passes run it as a candle convolution (a different summation
    // order), so the two agree to rounding only.
    let (enc, _vm) = encoder(&[5])?;
    let x = sources((1, 4, 3, 11, 13), 5)?;
    if !fused_runs() {
        assert!(enc.infer(&x, true)?.is_none());
        return Ok(());
    }
    let (ds, de) = diffs(&enc, &x)?;
    assert!(ds < 1e-6 && de < 1e-6, "stats {ds:e}, features {de:e}");
    Ok(())
}

/// The renderer's fused blend (`fused::blend_infer`) against the training forward for
/// blends of no, one (the register-blocked path) and two hidden layers, tiles whose width
/// is and is not a multiple of the block, and a hidden layer wider than the block holds.
#[test]
fn the_fused_blend_matches_the_forward_for_every_blend_depth() -> Result<()> {
    use deepstereo_core::config::{Config, TowerConfig};
    use deepstereo_core::weights::init_seeded;
    let c = |channels| Conv {
        kernel: 1,
        channels,
    };
    for (blend, tile) in [
        (vec![], 12),
        (vec![c(5)], 12),
        (vec![c(5)], 20),
        (vec![c(11)], 8),
        (vec![c(4), c(3)], 12),
    ] {
        let mut cfg = Config::preset("nviews").ok_or_else(|| anyhow::anyhow!("no nviews"))?;
        cfg.tile = tile;
        cfg.planes = 3;
        cfg.select = TowerConfig {
            levels: 1,
            ..cfg.select.clone()
        };
        cfg.levels = 1;
        if let Some(pool) = cfg.pool.as_mut() {
            pool.blend = blend.clone();
        }
        cfg.validate().map_err(anyhow::Error::msg)?;
        let t = init_seeded(&cfg, DType::F32, &Device::Cpu, 3)?;
        let s = cfg.input_size(0, tile);
        let x = sources((1, cfg.planes, 3, s, s), tile as u64)?;
        let xs = [x];
        let (a, b) = (t.model.forward(&xs)?, t.model.infer(&xs)?);
        let di = max_diff(&a.image, &b.image)?;
        assert!(di < 1e-5, "blend {blend:?}, tile {tile}: {di:e}");
    }
    Ok(())
}
