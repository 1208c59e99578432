//! Options shared by the commands that run a model: `render`, `eval`, `report`, `demo`.

use crate::inference::{BackendKind, RenderSettings};
use anyhow::{bail, Result};
use deepstereo_core::render::Backend;
use std::path::PathBuf;

#[derive(Debug, Clone, clap::Args)]
pub struct ModelArgs {
    /// Model weights (safetensors with its config); default: the embedded `tiny` model.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Depth planes, uniform in inverse depth between near and far (default: the model's).
    #[arg(long)]
    pub planes: Option<usize>,
    /// Source views, the nearest to the target (must equal the model's; default: it).
    #[arg(long)]
    pub views: Option<usize>,
    /// Output tile side in pixels when rendering (bounds memory; rounded up to the model's
    /// alignment). The result does not depend on it.
    #[arg(long, default_value_t = 64)]
    pub tile: usize,
    /// Runtime for the network: candle, or ort (onnxruntime on the exported model).
    #[arg(long, value_enum, default_value_t = BackendKind::Candle)]
    pub backend: BackendKind,
}

impl ModelArgs {
    pub fn settings(&self) -> Result<RenderSettings> {
        if self.tile == 0 {
            bail!("--tile must be at least 1");
        }
        if self.planes == Some(0) {
            bail!("--planes must be at least 1");
        }
        Ok(RenderSettings { planes: self.planes, views: self.views, tile: self.tile })
    }

    pub fn backend(&self) -> Result<Box<dyn Backend>> {
        crate::inference::make_backend(self.backend, self.model.as_deref())
    }

    pub fn name(&self) -> String {
        crate::inference::model_name(self.model.as_ref())
    }
}
