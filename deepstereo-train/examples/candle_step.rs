//! Candle training steps on `deepstereo samples` shards, writing the gradients of every
//! step and the weights after them (for `python/ddp_check.py`, which applies
//! `optim_ref.py` to the same gradients and compares).
//!
//! `cargo run --release -p deepstereo-train --example candle_step -- WEIGHTS OPTIMIZER LR OUT SHARD...`
//!
//! Step `s` (0-based) uses the whole of `SHARD[s]` (with the features family's warps):
//! L1 loss, backward, one `optim.rs` update. Writes `OUT/grads-{s}.safetensors` (the gradient of every variable, by name,
//! before step `s`'s update) and `OUT/model.safetensors` (the weights after the last step).

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use deepstereo_core::features::FeatureWarp;
use deepstereo_core::inputs::features::{warped_features, TileWarps, ViewWarp};
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

/// The features family's warps of every sample of a shard (`warp.K.L.V.*`), for inputs
/// `x[l]` `[K, D, V, C_b, H, W]` and a CNN of radius `r`.
fn shard_warps(
    st: &safetensors::SafeTensors<'_>,
    x: &[Tensor],
    r: usize,
) -> Result<Vec<TileWarps>> {
    let dims = x[0].dims().to_vec();
    let (samples, planes, views) = (dims[0], dims[1], dims[2]);
    let mut tiles = Vec::with_capacity(samples);
    for k in 0..samples {
        let mut levels = Vec::with_capacity(x.len());
        for l in 0..x.len() {
            let mut row = Vec::with_capacity(views);
            for v in 0..views {
                let stem = format!("warp.{k}.{l}.{v}");
                if st.tensor(&format!("{stem}.crop")).is_err() {
                    row.push(None);
                    continue;
                }
                let crop = read(st, &format!("{stem}.crop"))?;
                let (c, h, w) = crop.dims3()?;
                let idx: Vec<i64> = (st.tensor(&format!("{stem}.index"))?.data().chunks_exact(8))
                    .map(|b| i64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
                    .collect();
                let wts = read(st, &format!("{stem}.weight"))?
                    .flatten_all()?
                    .to_vec1::<f32>()?;
                let op = FeatureWarp::from_taps(&idx, &wts, planes, (h - 2 * r, w - 2 * r))?;
                row.push(Some(ViewWarp {
                    input: crop.flatten_all()?.to_vec1::<f32>()?,
                    input_shape: (c, h, w),
                    op,
                }));
            }
            levels.push(row);
        }
        let sizes = x.iter().map(|t| (t.dims()[4], t.dims()[5])).collect();
        tiles.push(TileWarps {
            levels,
            sizes,
            planes,
        });
    }
    Ok(tiles)
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
        let feats = match t.model.feature_net() {
            Some(net) => Some(warped_features(
                net,
                &x,
                &shard_warps(&st, &x, net.radius())?,
            )?),
            None => None,
        };
        let y = read(&st, "target")?;
        let loss = l1_loss(&t.model.forward_parts(&x, feats.as_deref())?.image, &y)?;
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
