//! Training pipeline throughput, in one run on one machine: the sampler (samples/s with
//! all cores) against the trainer's consumption (forward + backward + Adam step), for the
//! `tiny` and `paper` configs. `cargo bench -p deepstereo-train --bench pipeline`.

use anyhow::Result;
use candle_core::{DType, Device};
use deepstereo_core::config::Config;
use deepstereo_core::model::l1_loss;
use deepstereo_core::synth::SynthOptions;
use deepstereo_core::weights::{init_seeded, named_vars};
use deepstereo_train::training::batch_tensors;
use deepstereo_train::training::data::{make_batch, synth_scenes, Sampling};
use deepstereo_train::training::optim::{Optimizer, OptimizerKind};
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn bench(cfg: &Config, batch: usize, reps: usize) -> Result<()> {
    let opts = SynthOptions {
        views: 8,
        width: 160,
        height: 120,
        ..SynthOptions::default()
    };
    let scenes = synth_scenes(8, 1, &opts, cfg.levels)?;
    let mut sample_t = Vec::new();
    for b in 0..reps as u64 {
        let t0 = Instant::now();
        make_batch(cfg, &Sampling::fixed(cfg), &scenes, 9, b, batch)?;
        sample_t.push(t0.elapsed().as_secs_f64());
    }
    let t = init_seeded(cfg, DType::F32, &Device::Cpu, 0)?;
    let mut opt = Optimizer::new(OptimizerKind::Adam, 1e-4, named_vars(&t.varmap))?;
    let mut step_t = Vec::new();
    let mut fwd_t = Vec::new();
    for b in 0..reps as u64 {
        let batch_data = make_batch(cfg, &Sampling::fixed(cfg), &scenes, 9, b, batch)?;
        let (x, y) = batch_tensors(&t.model, &batch_data, &Device::Cpu)?;
        let t0 = Instant::now();
        let out = x.forward(&t.model)?;
        let loss = l1_loss(&out.image, &y)?;
        loss.to_scalar::<f32>()?;
        fwd_t.push(t0.elapsed().as_secs_f64());
        let grads = loss.backward()?;
        opt.step(&grads)?;
        step_t.push(t0.elapsed().as_secs_f64());
    }
    let (s, st, f) = (median(sample_t), median(step_t), median(fwd_t));
    let px = (cfg.tile * cfg.tile * batch) as f64;
    println!(
        "{:<6} batch {batch:3} tile {:2}x{:<2} D {:3} V {}: sampler {:8.1} samples/s | train step {:7.3} s = {:7.1} samples/s, {:9.0} output px/s | forward {:7.1} samples/s | sampler/trainer {:5.1}x",
        cfg.name, cfg.tile, cfg.tile, cfg.planes, cfg.views,
        batch as f64 / s, st, batch as f64 / st, px / st, batch as f64 / f, st / s
    );
    Ok(())
}

fn main() -> Result<()> {
    println!("threads: {}", rayon::current_num_threads());
    bench(&Config::tiny(), 8, 5)?;
    bench(&Config::paper(), 8, 3)?;
    Ok(())
}
