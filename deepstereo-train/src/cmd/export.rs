//! `deepstereo export`: the network as an ONNX file (weights as initializers).

use crate::rendering::models::{load_model, model_name};
use anyhow::Context;
use deepstereo_core::imageio::write_atomic;
use deepstereo_export::{DEFAULT_OPSET, MAX_OPSET, MIN_OPSET};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Model weights (safetensors with its config), or `embedded` (the default: the
    /// embedded default model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Output ONNX file. Inputs `level0..` [B, D, 4V, H_l, W_l] (batch, planes and size
    /// dynamic); outputs `image` [B, 3, th, tw] and `selection` [B, D, th, tw]. A model
    /// of the features family also gets NAME.features.onnx, its per-source CNN.
    #[arg(long)]
    pub out: PathBuf,
    /// ONNX opset (17 or newer).
    #[arg(long, default_value_t = DEFAULT_OPSET)]
    pub opset: i64,
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
    let weights = deepstereo_export::model_weights(&t)?;
    let features = deepstereo_export::export_features(t.model.config(), &weights, a.opset)?;
    if let Some(fb) = &features {
        let path = deepstereo_export::features_path(&a.out);
        write_atomic(&path, fb).with_context(|| format!("cannot write {}", path.display()))?;
        eprintln!(
            "exported the per-source feature graph to {} ({} bytes): run it once on each source image and level, and warp its output into the network's inputs",
            path.display(),
            fb.len()
        );
    }
    write_atomic(&a.out, &bytes).with_context(|| format!("cannot write {}", a.out.display()))?;
    eprintln!(
        "exported {} ('{}', opset {}) to {} ({} bytes)",
        model_name(a.model.as_deref()),
        t.model.config().name,
        a.opset,
        a.out.display(),
        bytes.len()
    );
    if t.model.prior().is_some() {
        eprintln!(
            "note: the model's scene prior (from `deepstereo tune`) reweighs the selection outside the network and is not part of the ONNX graph: the graph renders as the tuned network without it (render with candle to apply it)"
        );
    }
    Ok(())
}
