//! The network behind one interface: [`Backend`] runs it on one tile's inputs, so the
//! renderers, pruning's coarse pass and the MPI bake run candle and onnxruntime (the
//! export crate's backend) through the same code. [`CandleBackend`] is candle's.

use crate::config::Config;
use crate::error::{Error, Result};
use crate::features::FeatureMap;
use crate::imageio::RgbImage;
use crate::inputs::{PyramidSource, TileInputs};
use crate::model::DeepStereo;
use crate::prior::PriorGrid;
use candle_core::{Device, Tensor};

/// Runs the network on one tile's inputs.
pub trait Backend: Sync {
    /// Name for reports (`candle`, `ort`).
    fn name(&self) -> &str;
    fn config(&self) -> &Config;
    /// Returns the image `[3, th, tw]` and the selection `[D, th, tw]`, row-major.
    fn run(&self, inputs: &TileInputs, planes: usize) -> Result<(Vec<f32>, Vec<f32>)>;
    /// Returns every plane's colour `[D, 3, th, tw]` and the selection `[D, th, tw]`,
    /// row-major: the layers a multiplane image is baked from. Backends that run only
    /// the exported graph (image and selection) refuse.
    fn run_layers(&self, _inputs: &TileInputs, _planes: usize) -> Result<(Vec<f32>, Vec<f32>)> {
        Err(Error::Invalid(format!(
            "the {} backend returns no per-plane colours: bake multiplane images with candle",
            self.name()
        )))
    }
    /// Whether [`Backend::run_layers`] works.
    fn has_layers(&self) -> bool {
        false
    }
    /// The scene prior the renderers apply to the network's selection (a tuned model's;
    /// [`crate::prior`]): it needs [`Backend::run_layers`].
    fn prior(&self) -> Option<&PriorGrid> {
        None
    }
    /// The `features` family's map of one source image `[F, H, W]` (the per-source CNN,
    /// run once on each source image before the network); other models have none.
    fn source_features(&self, _image: &RgbImage) -> Result<FeatureMap> {
        Err(Error::Invalid(format!(
            "the {} backend cannot compute the model's source features",
            self.name()
        )))
    }
}

/// `sources` with the feature maps the backend's model reads, where some lack them:
/// `None` when the model reads none or every source has them.
pub fn missing_features(
    backend: &dyn Backend,
    sources: &[&PyramidSource],
) -> Result<Option<Vec<PyramidSource>>> {
    let levels = backend.config().levels;
    let wanted = backend
        .config()
        .pool
        .as_ref()
        .is_some_and(|p| p.features.is_some());
    if !wanted || sources.iter().all(|s| s.features.len() >= levels) {
        return Ok(None);
    }
    let with = sources
        .iter()
        .map(|&s| match s.features.len() >= levels {
            true => Ok(s.clone()),
            false => s
                .clone()
                .with_features_from(|img| backend.source_features(img)),
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Some(with))
}

/// The candle backend (CPU, f32).
pub struct CandleBackend {
    pub model: DeepStereo,
    pub device: Device,
}

impl Backend for CandleBackend {
    fn name(&self) -> &str {
        "candle"
    }
    fn config(&self) -> &Config {
        self.model.config()
    }
    fn run(&self, inputs: &TileInputs, planes: usize) -> Result<(Vec<f32>, Vec<f32>)> {
        self.infer(inputs, planes, |out| &out.image)
    }
    fn run_layers(&self, inputs: &TileInputs, planes: usize) -> Result<(Vec<f32>, Vec<f32>)> {
        self.infer(inputs, planes, |out| &out.colours)
    }
    fn has_layers(&self) -> bool {
        true
    }
    fn prior(&self) -> Option<&PriorGrid> {
        self.model.prior()
    }
    fn source_features(&self, image: &RgbImage) -> Result<FeatureMap> {
        match self.model.feature_net() {
            Some(net) => Ok(net.image_features(image, &self.device)?),
            None => Err(Error::Invalid(format!(
                "the model '{}' reads no source features",
                self.config().name
            ))),
        }
    }
}

impl CandleBackend {
    /// The network on one tile: `colour(output)` (the image or the per-plane colours) and
    /// the selection, flattened.
    fn infer(
        &self,
        inputs: &TileInputs,
        planes: usize,
        colour: impl Fn(&crate::model::Output) -> &candle_core::Tensor,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let tensors = inputs_to_tensors(self.config(), inputs, 1, planes, &self.device)?;
        let out = self.model.infer(&tensors)?;
        let c = colour(&out).flatten_all()?.to_vec1::<f32>()?;
        let selection = out.selection.flatten_all()?.to_vec1::<f32>()?;
        Ok((c, selection))
    }
}

/// Wraps per-level data `[B * D * V * 4 * h * w]` as the tensors the model `cfg` takes:
/// `[B, D, 4V, h, w]` or `[B, D, V, 4, h, w]` ([`Config::input_shape`]).
pub fn inputs_to_tensors(
    cfg: &Config,
    inputs: &TileInputs,
    b: usize,
    d: usize,
    device: &Device,
) -> Result<Vec<Tensor>> {
    inputs
        .levels
        .iter()
        .zip(&inputs.sizes)
        .map(|(data, &(h, w))| {
            let shape = cfg.input_shape(b, d, inputs.views, h, w);
            Ok(Tensor::from_slice(data, shape, device)?)
        })
        .collect()
}
