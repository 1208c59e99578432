//! Loading a model, the one place that does: a safetensors file (with its config), or the
//! embedded default, which every command names `embedded` (`--model embedded`, and the
//! name reports give it).

use anyhow::Result;
use candle_core::Device;
use deepstereo_core::render::{Backend, CandleBackend};
use deepstereo_core::weights::{self, Trainable};
use std::path::Path;

/// The default model: the weights of the run `runs/nviews-disagree-scratch` (preset
/// `nviews-disagree`, the any-number-of-views family), trained on real captures and
/// procedural scenes (the README's model card lists them), named after that run. `tiny`, the
/// paper-family default before it, is `assets/tiny.safetensors`.
pub static EMBEDDED_MODEL: &[u8] =
    include_bytes!("../../assets/nviews-disagree-scratch.safetensors");
/// The name of the embedded model: accepted by `--model` and written in reports.
pub const EMBEDDED_NAME: &str = "embedded";

/// Which runtime runs the network.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    Candle,
    Ort,
}

/// The weights file `--model` names, or `None` for the embedded model (no `--model`, or
/// `--model embedded`).
pub fn model_file(model: Option<&Path>) -> Option<&Path> {
    model.filter(|p| p.as_os_str() != EMBEDDED_NAME)
}

/// Loads a model strictly on the CPU (`None` or `embedded`: the embedded model).
pub fn load_model(model: Option<&Path>) -> Result<Trainable> {
    let device = Device::Cpu;
    Ok(match model_file(model) {
        Some(p) => weights::load(p, &device)?,
        None => weights::load_bytes(Path::new(EMBEDDED_NAME), EMBEDDED_MODEL, &device)?,
    })
}

/// The model for the candle backend.
pub fn candle_backend(model: Option<&Path>) -> Result<CandleBackend> {
    Ok(CandleBackend {
        model: load_model(model)?.model,
        device: Device::Cpu,
    })
}

/// The backend of `kind` for `model`.
pub fn make_backend(kind: BackendKind, model: Option<&Path>) -> Result<Box<dyn Backend>> {
    match kind {
        BackendKind::Candle => Ok(Box::new(candle_backend(model)?)),
        BackendKind::Ort => {
            let t = load_model(model)?;
            if t.model.prior().is_some() {
                anyhow::bail!(
                    "{}: the model carries a scene prior (from `deepstereo tune`), which onnxruntime does not apply; render it with --backend candle",
                    model_name(model)
                );
            }
            Ok(Box::new(deepstereo_export::OrtBackend::from_model(&t)?))
        }
    }
}

/// The model's name in reports: its file, or `embedded`.
pub fn model_name(model: Option<&Path>) -> String {
    model_file(model)
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| EMBEDDED_NAME.to_string())
}
