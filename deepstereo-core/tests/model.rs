//! The network against references: finite-difference gradients in f64, selection
//! normalisation, and overfitting a fixed batch.

use anyhow::Result;
use candle_core::{DType, Device, Tensor, Var};
use deepstereo_core::config::{Config, Conv, TowerConfig};
use deepstereo_core::model::l1_loss;
use deepstereo_core::weights::{init_dtype, named_vars};

/// A small config exercising every part of the model (2 levels, merge convs, depth
/// convs, colour skip).
fn small() -> Config {
    let c = |k, ch| Conv {
        kernel: k,
        channels: ch,
    };
    Config {
        name: "small".into(),
        views: 2,
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
            merge_convs: vec![c(3, 3)],
        },
        colour_skip: true,
        render_planes: None,
        pool: None,
    }
}

/// Deterministic pseudo-random values in [lo, hi).
fn rand_vec(n: usize, seed: u64, lo: f64, hi: f64) -> Vec<f64> {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((s >> 11) as f64 / (1u64 << 53) as f64)
        })
        .collect()
}

fn inputs(cfg: &Config, b: usize, dtype: DType, seed: u64) -> Result<Vec<Tensor>> {
    (0..cfg.levels)
        .map(|l| {
            let s = cfg.input_size(l, cfg.tile);
            let shape = (b, cfg.planes, cfg.in_channels(), s, s);
            let n = b * cfg.planes * cfg.in_channels() * s * s;
            Ok(
                Tensor::from_vec(rand_vec(n, seed + l as u64, 0.0, 1.0), shape, &Device::Cpu)?
                    .to_dtype(dtype)?,
            )
        })
        .collect()
}

#[test]
fn gradients_match_finite_differences_f64() -> Result<()> {
    let cfg = small();
    let t = init_dtype(&cfg, DType::F64, &Device::Cpu)?;
    let x = inputs(&cfg, 2, DType::F64, 7)?;
    let (th, d) = (cfg.tile, cfg.planes);
    let r1 = Tensor::from_vec(
        rand_vec(2 * 3 * th * th, 11, -1.0, 1.0),
        (2, 3, th, th),
        &Device::Cpu,
    )?;
    let r2 = Tensor::from_vec(
        rand_vec(2 * d * th * th, 13, -1.0, 1.0),
        (2, d, th, th),
        &Device::Cpu,
    )?;
    let loss_of = || -> Result<Tensor> {
        let o = t.model.forward(&x)?;
        Ok(((o.image * &r1)?.sum_all()? + (o.selection * &r2)?.sum_all()?)?)
    };
    let grads = loss_of()?.backward()?;
    let eps = 1e-6;
    let mut worst = 0f64;
    for (name, var) in named_vars(&t.varmap) {
        let g = grads
            .get(var.as_tensor())
            .ok_or_else(|| anyhow::anyhow!("no gradient for {name}"))?;
        let g = g.flatten_all()?.to_vec1::<f64>()?;
        let w0 = var.as_tensor().flatten_all()?.to_vec1::<f64>()?;
        let picks: Vec<usize> = rand_vec(3, name.len() as u64, 0.0, w0.len() as f64)
            .iter()
            .map(|v| *v as usize)
            .collect();
        for &i in &picks {
            let eval = |delta: f64| -> Result<f64> {
                let mut w = w0.clone();
                w[i] += delta;
                var.set(&Tensor::from_vec(w, var.as_tensor().dims(), &Device::Cpu)?)?;
                Ok(loss_of()?.to_scalar::<f64>()?)
            };
            let fd = (eval(eps)? - eval(-eps)?) / (2.0 * eps);
            var.set(&Tensor::from_vec(
                w0.clone(),
                var.as_tensor().dims(),
                &Device::Cpu,
            )?)?;
            let err = (fd - g[i]).abs() / (1e-6 + fd.abs().max(g[i].abs()));
            worst = worst.max(err);
            assert!(
                err < 1e-4,
                "{name}[{i}]: autograd {} vs finite difference {fd}",
                g[i]
            );
        }
    }
    println!("worst relative gradient error {worst:.2e}");
    Ok(())
}

#[test]
fn selection_sums_to_one_and_outputs_are_finite() -> Result<()> {
    for cfg in [small(), Config::tiny()] {
        let t = init_dtype(&cfg, DType::F32, &Device::Cpu)?;
        let x = inputs(&cfg, 1, DType::F32, 3)?;
        let o = t.model.forward(&x)?;
        let s = o.selection.sum(1)?.flatten_all()?.to_vec1::<f32>()?;
        assert!(s.iter().all(|v| (v - 1.0).abs() < 1e-5), "{s:?}");
        let img = o.image.flatten_all()?.to_vec1::<f32>()?;
        assert!(img.iter().all(|v| v.is_finite()));
        assert_eq!(o.image.dims(), &[1, 3, cfg.tile, cfg.tile]);
    }
    Ok(())
}

/// Adam on one fixed batch: the L1 loss must fall at least 10x.
#[test]
fn overfits_a_fixed_batch() -> Result<()> {
    let cfg = small();
    let t = init_dtype(&cfg, DType::F32, &Device::Cpu)?;
    let x = inputs(&cfg, 2, DType::F32, 5)?;
    // Target: view 0's colour at plane 2, centre crop: learnable by selecting plane 2.
    let p = cfg.pad(0);
    let th = cfg.tile;
    let y = x[0]
        .narrow(1, 2, 1)?
        .narrow(2, 0, 3)?
        .narrow(3, p, th)?
        .narrow(4, p, th)?
        .squeeze(1)?
        .contiguous()?;
    let vars: Vec<Var> = named_vars(&t.varmap).into_iter().map(|(_, v)| v).collect();
    let mut opt = candle_nn::optim::AdamW::new(
        vars,
        candle_nn::optim::ParamsAdamW {
            lr: 1e-2,
            weight_decay: 0.0,
            ..Default::default()
        },
    )?;
    use candle_nn::optim::Optimizer;
    let first = l1_loss(&t.model.forward(&x)?.image, &y)?.to_scalar::<f32>()?;
    let mut last = first;
    for _ in 0..300 {
        let loss = l1_loss(&t.model.forward(&x)?.image, &y)?;
        last = loss.to_scalar::<f32>()?;
        opt.backward_step(&loss)?;
    }
    println!("L1 {first:.4} -> {last:.4}");
    assert!(last < first / 10.0, "loss fell only from {first} to {last}");
    Ok(())
}
