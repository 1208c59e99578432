//! A run's checkpoint: written with the weights-only model, restored on `--resume`, and
//! the log cut back to it.

use super::{LogLine, RunOptions, RUN_KEY, STEP_KEY};
use crate::training::optim::Optimizer;
use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use deepstereo_core::imageio::write_atomic;
use deepstereo_core::tensorio::{f32_values, write_safetensors, NamedArray};
use deepstereo_core::weights::{self, metadata, tensor_f32, Trainable};
use std::path::Path;

/// Writes the checkpoint and the weights-only model, both atomically.
pub fn save_checkpoint(
    ckpt: &Path,
    model: &Path,
    run: &RunOptions,
    t: &Trainable,
    opt: &Optimizer,
    step: u64,
) -> Result<()> {
    let mut arrays = weights::weight_arrays(&t.varmap)?;
    weights::check_finite(ckpt, &arrays)?;
    for (name, tensor) in opt.state() {
        arrays.push(NamedArray::f32(&name, tensor.dims(), &tensor_f32(&tensor)?));
    }
    let meta = metadata(
        &run.config,
        &[
            (RUN_KEY, serde_json::to_string(run)?),
            (STEP_KEY, step.to_string()),
            ("optimizer.steps", opt.steps.to_string()),
        ],
    )?;
    write_safetensors(ckpt, &arrays, Some(meta))?;
    weights::save(model, &run.config, &t.varmap)?;
    Ok(())
}

/// Restores weights and optimizer state; returns the step to continue from.
pub(super) fn restore(
    ckpt: &Path,
    run: &RunOptions,
    t: &Trainable,
    opt: &mut Optimizer,
) -> Result<u64> {
    let bytes =
        std::fs::read(ckpt).with_context(|| format!("--resume: cannot read {}", ckpt.display()))?;
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes)
        .map_err(|e| anyhow::anyhow!("{}: {e}", ckpt.display()))?;
    let m = meta.metadata().clone().unwrap_or_default();
    let saved: RunOptions = serde_json::from_str(m.get(RUN_KEY).map(String::as_str).unwrap_or(""))
        .with_context(|| format!("{}: no run options in the checkpoint", ckpt.display()))?;
    let same_but_lr = RunOptions {
        lr_schedule: run.lr_schedule,
        ..saved.clone()
    };
    if &same_but_lr != run {
        bail!("{}: the checkpoint was made with different options:\n  saved: {saved:?}\n  now:   {run:?}", ckpt.display());
    }
    if saved.lr_schedule != run.lr_schedule {
        eprintln!(
            "{}: learning-rate schedule changed from {:?} to {:?}",
            ckpt.display(),
            saved.lr_schedule,
            run.lr_schedule
        );
    }
    let step: u64 = m
        .get(STEP_KEY)
        .and_then(|s| s.parse().ok())
        .context("checkpoint has no step")?;
    let osteps: u64 = m
        .get("optimizer.steps")
        .and_then(|s| s.parse().ok())
        .unwrap_or(step);
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| anyhow::anyhow!("{}: {e}", ckpt.display()))?;
    weights::assign(ckpt, &st, &t.varmap, "")?;
    opt.restore(osteps, |name| {
        let v = st
            .tensor(name)
            .map_err(|_| anyhow::anyhow!("{}: missing '{name}'", ckpt.display()))?;
        let data = f32_values(&v);
        Ok(Tensor::from_vec(data, v.shape(), &Device::Cpu)?)
    })?;
    Ok(step)
}

/// Keeps only the log lines up to `step` (a resume repeats the steps after it).
pub(super) fn truncate_log(path: &Path, step: u64) -> Result<()> {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let kept: String = text
        .lines()
        .filter(|l| {
            serde_json::from_str::<LogLine>(l)
                .map(|x| x.step <= step)
                .unwrap_or(false)
        })
        .map(|l| format!("{l}\n"))
        .collect();
    write_atomic(path, kept.as_bytes())?;
    Ok(())
}
