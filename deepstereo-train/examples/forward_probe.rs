//! Times the network's forward on one render tile (`DeepStereo::infer`, the renderer's
//! path), or (`step` as fourth argument) a training step as in `benches/network.rs`, in a
//! loop, for profiling (`perf record -g target/release/examples/forward_probe tiny 200`).
//!
//! `cargo run --release -p deepstereo-train --example forward_probe -- [preset] [iterations] [tile] [step]`;
//! `PROBE_ORT=1` also times onnxruntime on the same tile after each forward (needs the
//! onnxruntime library, as `deepstereo --backend ort`); `DEEPSTEREO_CONV=im2col` runs the
//! im2col path instead of the AVX2 kernels (see `deepstereo_core::conv`).

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor};
use deepstereo_core::config::Config;
use deepstereo_core::model::l1_loss;
use deepstereo_core::weights::{init_seeded, named_vars, Trainable};
use deepstereo_export::export::{export_trainable, DEFAULT_OPSET};
use deepstereo_export::OrtBackend;
use deepstereo_train::training::optim::{Optimizer, OptimizerKind};
use deepstereo_train::training::{batch_tensors, procedural_batch};
use std::time::Instant;

fn main() -> Result<()> {
    deepstereo_train::alloc::tune_allocator();
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).map_or("tiny", String::as_str);
    let iters: usize = args.get(2).map_or(Ok(50), |s| s.parse())?;
    let cfg = Config::preset(name).with_context(|| format!("unknown preset {name}"))?;
    let default_tile = if name == "paper" { 32 } else { 64 };
    let tile: usize = args.get(3).map_or(Ok(default_tile), |s| s.parse())?;
    let step = args.get(4).is_some_and(|s| s == "step");
    let t = init_seeded(&cfg, DType::F32, &Device::Cpu, 0)?;
    let mut times = match step {
        true => time_steps(&t, &cfg, name, iters)?,
        false => time_forward(&t, &cfg, tile, iters)?,
    };
    times.sort_by(f64::total_cmp);
    let what = if step {
        "training step".to_string()
    } else {
        format!("forward, {tile}x{tile} tile")
    };
    println!(
        "{name} {what}: best {:.1} ms, median {:.1} ms over {iters}",
        times[0],
        times[iters / 2]
    );
    Ok(())
}

/// Milliseconds of `iters` training steps (Adam, L1) on a procedural batch.
fn time_steps(t: &Trainable, cfg: &Config, name: &str, iters: usize) -> Result<Vec<f64>> {
    let batch = if name == "paper" { 1 } else { 8 };
    let (x, y) = batch_tensors(&t.model, &procedural_batch(cfg, batch)?, &Device::Cpu)?;
    let mut opt = Optimizer::new(OptimizerKind::Adam, 1e-4, named_vars(&t.varmap))?;
    let mut times = Vec::with_capacity(iters);
    for _ in 0..iters {
        let t0 = Instant::now();
        let loss = l1_loss(&x.forward(&t.model)?.image, &y)?;
        opt.step(&loss.backward()?)?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(times)
}

/// Milliseconds of `iters` forwards of one render tile of side `tile` (random inputs),
/// with `PROBE_ORT` each followed by onnxruntime's, whose best it prints.
fn time_forward(t: &Trainable, cfg: &Config, tile: usize, iters: usize) -> Result<Vec<f64>> {
    let mut times = Vec::with_capacity(iters);
    let xs: Vec<Tensor> = (0..cfg.levels)
        .map(|l| {
            let s = cfg.input_size(l, tile);
            // PROBE_VIEWS=K: K source views (the any-number-of-views family).
            let views = std::env::var("PROBE_VIEWS")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(cfg.views);
            let shape = cfg.input_shape(1, cfg.planes, views, s, s);
            Tensor::rand(0f32, 1., shape, &Device::Cpu)
        })
        .collect::<candle_core::Result<_>>()?;
    // PROBE_ORT=1: onnxruntime runs the same tile after each candle forward, as in
    // benches/network.rs.
    let with_ort = std::env::var("PROBE_ORT").is_ok();
    let ort = if with_ort {
        Some(OrtBackend::from_bytes(&export_trainable(
            t,
            DEFAULT_OPSET,
        )?)?)
    } else {
        None
    };
    let data = xs
        .iter()
        .map(|x| Ok((x.dims().to_vec(), x.flatten_all()?.to_vec1::<f32>()?)))
        .collect::<Result<Vec<_>>>()?;
    let views: Vec<(&[usize], &[f32])> = data
        .iter()
        .map(|(s, d)| (s.as_slice(), d.as_slice()))
        .collect();
    let mut ort_best = f64::MAX;
    for _ in 0..iters {
        let t0 = Instant::now();
        let out = t.model.infer(&xs)?.image.flatten_all()?.to_vec1::<f32>()?;
        std::hint::black_box(out);
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        if let Some(ort) = &ort {
            let t0 = Instant::now();
            ort.forward(&views)?;
            ort_best = ort_best.min(t0.elapsed().as_secs_f64() * 1e3);
        }
    }
    if with_ort {
        println!("onnxruntime: best {ort_best:.1} ms");
    }
    Ok(times)
}
