//! Network cases: extreme inputs and selection scales must give finite outputs and
//! gradients with the selection summing to 1 over depth; reduced-precision inference is
//! measured against f32.

use super::fixtures::{inputs, small};
use super::table::{row, row_text};
use anyhow::Result;
use candle_core::{DType, Device, Tensor};
use deepstereo_core::config::Config;
use deepstereo_core::model::{l1_loss, DeepStereo};
use deepstereo_core::weights::{init, named_vars, Trainable};
use std::collections::HashMap;

/// Largest accepted |sum over depth of the selection - 1|.
const SUM_TOL: f64 = 1e-6;

fn set_log_scale(t: &Trainable, v: f32) -> Result<()> {
    let (_, var) = named_vars(&t.varmap)
        .into_iter()
        .find(|(n, _)| n == "select.log_scale")
        .expect("log_scale");
    var.set(&Tensor::new(&[v], &Device::Cpu)?)?;
    Ok(())
}

fn flat(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?)
}

/// Worst |sum_d s - 1| of a selection `[B, D, H, W]`, summed in f64.
fn worst_sum(sel: &Tensor) -> Result<f64> {
    let (b, d, h, w) = sel.dims4()?;
    let v = flat(sel)?;
    let mut worst = 0f64;
    for bi in 0..b {
        for p in 0..h * w {
            let s: f64 = (0..d).map(|z| v[(bi * d + z) * h * w + p] as f64).sum();
            worst = worst.max((s - 1.0).abs());
        }
    }
    Ok(worst)
}

/// Forward and backward; asserts finite outputs and gradients and the selection sum.
fn check(
    name: &str,
    cfg: &Config,
    d: usize,
    log_scale: Option<f32>,
    fill: impl Fn(bool, f32) -> f32,
) -> Result<()> {
    let t = init(cfg, &Device::Cpu)?;
    if let Some(v) = log_scale {
        set_log_scale(&t, v)?;
    }
    let x = inputs(cfg, 2, d, cfg.tile, 42, fill)?;
    let o = t.model.forward(&x)?;
    assert!(
        flat(&o.image)?.iter().all(|v| v.is_finite()),
        "{name}: non-finite image"
    );
    assert!(
        flat(&o.selection)?
            .iter()
            .all(|v| v.is_finite() && *v >= 0.0),
        "{name}: bad selection"
    );
    let worst = worst_sum(&o.selection)?;
    let target = o.image.ones_like()?.affine(0.5, 0.0)?;
    let weights = Tensor::from_vec(
        (0..o.selection.elem_count())
            .map(|i| (i % 7) as f32 - 3.0)
            .collect::<Vec<_>>(),
        o.selection.dims(),
        &Device::Cpu,
    )?;
    let loss = (l1_loss(&o.image, &target)? + (o.selection * weights)?.mean_all()?)?;
    assert!(
        loss.to_scalar::<f32>()?.is_finite(),
        "{name}: non-finite loss"
    );
    let grads = loss.backward()?;
    for (n, v) in named_vars(&t.varmap) {
        let g = grads
            .get(v.as_tensor())
            .ok_or_else(|| anyhow::anyhow!("{name}: no gradient for {n}"))?;
        assert!(
            flat(g)?.iter().all(|x| x.is_finite()),
            "{name}: non-finite gradient of {n}"
        );
    }
    row(
        name,
        "outputs and gradients finite; max abs(sum over depth of selection - 1)",
        worst,
    );
    assert!(worst <= SUM_TOL, "{name}: selection sums off by {worst:e}");
    Ok(())
}

#[test]
fn n01_saturated_tanh() -> Result<()> {
    let cfg = small();
    check("control: random RGBA in [0, 1]", &cfg, 5, None, |_, u| u)?;
    check("saturated tanh: inputs of +-1e4", &cfg, 5, None, |_, u| {
        (u - 0.5) * 2e4
    })?;
    check("saturated tanh: inputs of +-1e8", &cfg, 5, None, |_, u| {
        (u - 0.5) * 2e8
    })
}

#[test]
fn n02_peaked_and_flat_softmax() -> Result<()> {
    let cfg = small();
    check(
        "very peaked softmax: log_scale 20 (logits to +-5e8)",
        &cfg,
        5,
        Some(20.0),
        |_, u| u,
    )?;
    check(
        "very peaked softmax: log_scale 88 (logits to +-1.7e38)",
        &cfg,
        5,
        Some(88.0),
        |_, u| u,
    )?;
    check(
        "very flat softmax: log_scale -30 (logits to +-1e-13)",
        &cfg,
        5,
        Some(-30.0),
        |_, u| u,
    )?;
    // The limit, documented rather than asserted: exp(log_scale) overflows f32 above 88.72,
    // and a logit with tanh = 0 then becomes 0 * inf = NaN.
    let t = init(&cfg, &Device::Cpu)?;
    set_log_scale(&t, 89.0)?;
    let sel = flat(
        &t.model
            .forward(&inputs(&cfg, 2, 5, cfg.tile, 42, |_, u| u)?)?
            .selection,
    )?;
    let bad = sel.iter().filter(|v| !v.is_finite()).count();
    let what = if bad == 0 {
        "finite".to_string()
    } else {
        format!("{bad} of {} selection values NaN", sel.len())
    };
    row_text(
        "limit: log_scale 89 (exp overflows f32)",
        "not asserted: is the selection finite?",
        &what,
    );
    Ok(())
}

#[test]
fn n03_degenerate_inputs() -> Result<()> {
    let cfg = small();
    check(
        "all alpha zero (no source covers the pixel)",
        &cfg,
        5,
        None,
        |_, _| 0.0,
    )?;
    check(
        "constant images (RGB 0.5, alpha 1)",
        &cfg,
        5,
        None,
        |a, _| if a { 1.0 } else { 0.5 },
    )?;
    check("colours at 0 and 1 (alpha 1)", &cfg, 5, None, |a, u| {
        if a || u > 0.5 {
            1.0
        } else {
            0.0
        }
    })
}

#[test]
fn n04_one_and_256_planes() -> Result<()> {
    let cfg = small();
    check("one plane (D = 1)", &cfg, 1, None, |_, u| u)?;
    check("256 planes", &cfg, 256, None, |_, u| u)?;
    check(
        "256 planes, flat softmax (log_scale -30)",
        &cfg,
        256,
        Some(-30.0),
        |_, u| u,
    )
}

/// The same model with its weights converted by `to_dtype`.
fn converted(cfg: &Config, t: &Trainable, dtype: DType) -> Result<DeepStereo> {
    let ts: HashMap<String, Tensor> = named_vars(&t.varmap)
        .into_iter()
        .map(|(n, v)| Ok((n, v.as_tensor().to_dtype(dtype)?)))
        .collect::<Result<_>>()?;
    Ok(DeepStereo::new(
        cfg,
        candle_nn::VarBuilder::from_tensors(ts, dtype, &Device::Cpu),
    )?)
}

#[test]
fn n05_reduced_precision() -> Result<()> {
    let cfg = Config::tiny();
    let t = init(&cfg, &Device::Cpu)?;
    let x = inputs(&cfg, 1, cfg.planes, 16, 7, |a, u| {
        if a {
            (u * 4.0).min(1.0)
        } else {
            u
        }
    })?;
    let o32 = t.model.forward(&x)?;
    let (img32, sel32) = (flat(&o32.image)?, flat(&o32.selection)?);
    for (dtype, name) in [(DType::F16, "f16"), (DType::BF16, "bf16")] {
        let m = converted(&cfg, &t, dtype)?;
        let xs = x
            .iter()
            .map(|v| v.to_dtype(dtype))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let case = format!("{name} inference vs f32 (tiny preset, 32 planes, 16x16 tile)");
        match m.forward(&xs) {
            Ok(o) => {
                let err = |a: &[f32], b: &[f32]| {
                    a.iter()
                        .zip(b)
                        .fold(0f64, |m, (p, q)| m.max((p - q).abs() as f64))
                };
                let (img, sel) = (flat(&o.image)?, flat(&o.selection)?);
                assert!(
                    img.iter().chain(&sel).all(|v| v.is_finite()),
                    "{name}: non-finite output"
                );
                row(
                    &case,
                    "max abs error of the image (colours in [0, 1])",
                    err(&img, &img32),
                );
                row(&case, "max abs error of the selection", err(&sel, &sel32));
                row(
                    &case,
                    "max abs(sum over depth of selection - 1), in that dtype",
                    worst_sum(&o.selection)?,
                );
            }
            Err(e) => {
                let msg = e
                    .to_string()
                    .lines()
                    .next()
                    .unwrap_or_default()
                    .replace('|', "/");
                row_text(&case, "forward on the CPU", &format!("unsupported: {msg}"));
            }
        }
    }
    Ok(())
}
