//! `deepstereo export`: the network as an ONNX file (weights as initializers).

use crate::inference::{model_name, EMBEDDED_MODEL, EMBEDDED_NAME};
use anyhow::Context;
use candle_core::Device;
use deepstereo_core::imageio::write_atomic;
use deepstereo_core::weights::{self, Trainable};
use deepstereo_export::{DEFAULT_OPSET, MAX_OPSET, MIN_OPSET};
use std::path::{Path, PathBuf};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Model weights (safetensors with its config); default: the embedded `tiny` model.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Output ONNX file. Inputs `level0..` [B, D, 4V, H_l, W_l] (batch, planes and size
    /// dynamic); outputs `image` [B, 3, th, tw] and `selection` [B, D, th, tw].
    #[arg(long)]
    pub out: PathBuf,
    /// ONNX opset (17 or newer).
    #[arg(long, default_value_t = DEFAULT_OPSET)]
    pub opset: i64,
}

/// Loads a weights file strictly on the CPU (`None`: the embedded model).
pub fn load_model(model: Option<&Path>) -> anyhow::Result<Trainable> {
    let device = Device::Cpu;
    Ok(match model {
        Some(p) => weights::load(p, &device)?,
        None => weights::load_bytes(Path::new(EMBEDDED_NAME), EMBEDDED_MODEL, &device)?,
    })
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if !(MIN_OPSET..=MAX_OPSET).contains(&a.opset) {
        anyhow::bail!(
            "--opset {} is not supported: use {MIN_OPSET}..={MAX_OPSET}",
            a.opset
        );
    }
    let t = load_model(a.model.as_deref())?;
    let bytes = deepstereo_export::export_trainable(&t, a.opset)?;
    write_atomic(&a.out, &bytes).with_context(|| format!("cannot write {}", a.out.display()))?;
    eprintln!(
        "exported {} ('{}', opset {}) to {} ({} bytes)",
        model_name(a.model.as_ref()),
        t.model.config().name,
        a.opset,
        a.out.display(),
        bytes.len()
    );
    Ok(())
}
