//! Candle training steps on `deepstereo samples` shards, writing the gradients of every
//! step and the weights after them (for `python/ddp_check.py`, which applies
//! `optim_ref.py` to the same gradients and compares).
//!
//! `cargo run --release -p deepstereo-train --example candle_step -- WEIGHTS OPTIMIZER LR OUT SHARD...`
//!
//! Step `s` (0-based) uses the whole of `SHARD[s]`: L1 loss, backward, one `optim.rs`
//! update. Writes `OUT/grads-{s}.safetensors` (the gradient of every variable, by name,
//! before step `s`'s update) and `OUT/model.safetensors` (the weights after the last step).

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use deepstereo_core::model::l1_loss;
use deepstereo_core::tensorio::{f32_values, write_safetensors, NamedArray};
use deepstereo_core::weights::{self, named_vars, tensor_f32};
use deepstereo_train::training::optim::{Optimizer, OptimizerKind};
use std::path::PathBuf;

fn read(st: &safetensors::SafeTensors<'_>, name: &str) -> Result<Tensor> {
    let v = st
        .tensor(name)
        .with_context(|| format!("no tensor '{name}'"))?;
    let data = f32_values(&v);
    Ok(Tensor::from_vec(data, v.shape(), &Device::Cpu)?)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 5 {
        bail!("usage: candle_step WEIGHTS adam|adagrad LR OUT SHARD...");
    }
    let weights_path = PathBuf::from(&args[0]);
    let kind = match args[1].as_str() {
        "adam" => OptimizerKind::Adam,
        "adagrad" => OptimizerKind::Adagrad,
        o => bail!("unknown optimizer '{o}'"),
    };
    let lr: f64 = args[2].parse().context("LR")?;
    let out = PathBuf::from(&args[3]);
    let bytes = std::fs::read(&weights_path)
        .with_context(|| format!("cannot read {}", weights_path.display()))?;
    let t = weights::load_bytes(&weights_path, &bytes, &Device::Cpu)?;
    let cfg = t.model.config().clone();
    let vars = named_vars(&t.varmap);
    let mut opt = Optimizer::new(kind, lr, vars.clone())?;
    for (s, shard) in args[4..].iter().enumerate() {
        let bytes = std::fs::read(shard).with_context(|| format!("cannot read {shard}"))?;
        let st = safetensors::SafeTensors::deserialize(&bytes)?;
        let x = (0..cfg.levels)
            .map(|l| read(&st, &format!("level{l}")))
            .collect::<Result<Vec<_>>>()?;
        let y = read(&st, "target")?;
        let loss = l1_loss(&t.model.forward(&x)?.image, &y)?;
        let grads = loss.backward()?;
        let mut arrays = Vec::new();
        for (name, v) in &vars {
            if let Some(g) = grads.get(v.as_tensor()) {
                arrays.push(NamedArray::f32(name, g.dims(), &tensor_f32(g)?));
            }
        }
        write_safetensors(&out.join(format!("grads-{s}.safetensors")), &arrays, None)?;
        opt.step(&grads)?;
    }
    weights::save(&out.join("model.safetensors"), &cfg, &t.varmap)?;
    Ok(())
}
