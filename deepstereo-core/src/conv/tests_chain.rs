//! The fused inference chains (`chain.rs`) against the layer-by-layer forward.

use crate::config::{Config, Conv};
use crate::weights::{init_seeded, named_vars};
use anyhow::Result;
use candle_core::{DType, Device, Tensor};

/// Random inputs `[B, D, 4V, H_l, W_l]` of a `th x tw` tile.
fn inputs(cfg: &Config, b: usize, d: usize, (th, tw): (usize, usize)) -> Result<Vec<Tensor>> {
    (0..cfg.levels)
        .map(|l| {
            let (h, w) = (cfg.input_size(l, th), cfg.input_size(l, tw));
            Ok(Tensor::rand(
                0f32,
                1.,
                (b, d, cfg.in_channels(), h, w),
                &Device::Cpu,
            )?)
        })
        .collect()
}

fn max_diff(a: &Tensor, b: &Tensor) -> Result<f32> {
    Ok((a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?)
}

/// `infer` (fused where it applies) equals `forward` on image and selection.
fn check(cfg: &Config, b: usize, d: usize, tile: (usize, usize)) -> Result<()> {
    let t = init_seeded(cfg, DType::F32, &Device::Cpu, 7)?;
    // Logits of both signs (the random weights left them all positive).
    let bias = format!("select.depth.{}.bias", cfg.depth_convs.len() - 1);
    for (name, var) in named_vars(&t.varmap) {
        if name == bias {
            var.set(&Tensor::new(&[-0.3f32], &Device::Cpu)?)?;
        }
    }
    let xs = inputs(cfg, b, d, tile)?;
    let (want, got) = (t.model.forward(&xs)?, t.model.infer(&xs)?);
    assert_eq!(want.image.dims(), got.image.dims());
    let (di, ds) = (
        max_diff(&want.image, &got.image)?,
        max_diff(&want.selection, &got.selection)?,
    );
    // Same kernels and tap order: equal up to the softmax's parallel split.
    assert!(di < 1e-6 && ds < 1e-6, "{} {tile:?}: {di} {ds}", cfg.name);
    let sums = got.selection.sum(1)?.flatten_all()?.to_vec1::<f32>()?;
    assert!(sums.iter().all(|s| (s - 1.0).abs() < 1e-5));
    Ok(())
}

#[test]
fn infer_matches_forward_on_presets() -> Result<()> {
    // tiny: fused depth head and 1x1 colour tower with the skip input.
    check(&Config::tiny(), 2, 5, (16, 16))?;
    // Blocks that cross rows and a last partial block (10 x 6 = 60 pixels).
    check(&Config::tiny(), 1, 3, (6, 10))?;
    // paper: fused depth head (32 -> 16 -> 1), colour tower layer by layer.
    check(&Config::paper(), 1, 4, (8, 8))
}

#[test]
fn infer_matches_forward_on_variants() -> Result<()> {
    let mut cfg = Config::tiny();
    cfg.colour_skip = false;
    cfg.depth_convs = vec![
        Conv {
            kernel: 5,
            channels: 7,
        },
        Conv {
            kernel: 1,
            channels: 1,
        },
    ];
    cfg.colour.merge_convs.push(Conv {
        kernel: 1,
        channels: 9,
    });
    cfg.validate().map_err(anyhow::Error::msg)?;
    check(&cfg, 2, 3, (4, 6))?;
    // A colour tower with a 3x3 layer keeps the layer-by-layer path.
    cfg.colour.level_convs[0].kernel = 3;
    check(&cfg, 1, 2, (8, 8))
}

#[test]
fn infer_falls_back_for_f64() -> Result<()> {
    let cfg = Config::tiny();
    let t = init_seeded(&cfg, DType::F64, &Device::Cpu, 3)?;
    let xs: Vec<Tensor> = inputs(&cfg, 1, 2, (8, 8))?
        .iter()
        .map(|x| x.to_dtype(DType::F64))
        .collect::<candle_core::Result<_>>()?;
    let (a, b) = (t.model.forward(&xs)?, t.model.infer(&xs)?);
    let d = (a.image - b.image)?.abs()?.max_all()?.to_scalar::<f64>()?;
    assert_eq!(d, 0.0);
    Ok(())
}
