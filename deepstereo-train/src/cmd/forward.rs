//! `deepstereo forward`: the network on tensors from a file (for parity checks).

use crate::rendering::models::load_model;
use crate::rendering::BackendKind;
use anyhow::{bail, Context};
use candle_core::{Device, Tensor};
use deepstereo_core::features::FeatureMap;
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::tensorio::{f32_values, write_safetensors, NamedArray};
use deepstereo_export::{input_name, OrtBackend};
use safetensors::SafeTensors;
use std::collections::HashMap;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Model weights (safetensors with its config); default: the embedded default model.
    /// With `--backend ort --onnx FILE` it may be left out (the ONNX file holds the config).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Input safetensors with `level0..level{L-1}`, each [B, D, 4V, H_l, W_l] f32
    /// ([B, D, V, 4, H_l, W_l] for the any-number-of-views family, [B, D, V, 9, H_l, W_l]
    /// with the per-view cue) (as `deepstereo sweep --model` writes them). With a
    /// `source_image` [3, H, W] and a model of the features family, its per-source feature
    /// map is computed too.
    #[arg(long)]
    pub inputs: PathBuf,
    /// Output safetensors: `image` [B, 3, th, tw] and `selection` [B, D, th, tw] f32 (and
    /// `source_features` [F, H, W] for a `source_image`).
    #[arg(long)]
    pub out: PathBuf,
    /// Runtime: candle, or ort (onnxruntime on the exported model).
    #[arg(long, value_parser = super::args::choice::<BackendKind>(), default_value = "candle")]
    pub backend: BackendKind,
    /// With `--backend ort`: the ONNX file to run (default: the model exported in memory).
    #[arg(long)]
    pub onnx: Option<PathBuf>,
}

/// `(shape, data)` of the f32 tensor `name`.
fn read_f32(
    st: &SafeTensors<'_>,
    name: &str,
    file: &std::path::Path,
) -> anyhow::Result<(Vec<usize>, Vec<f32>)> {
    let view = st
        .tensor(name)
        .map_err(|_| anyhow::anyhow!("{}: no tensor '{name}'", file.display()))?;
    if view.dtype() != safetensors::Dtype::F32 {
        bail!(
            "{}: tensor '{name}' is {:?}, expected F32",
            file.display(),
            view.dtype()
        );
    }
    let data = f32_values(&view);
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        bail!(
            "{}: tensor '{name}' holds a non-finite value ({} at flat index {i}); the network's inputs must be finite",
            file.display(),
            data[i]
        );
    }
    Ok((view.shape().to_vec(), data))
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if a.onnx.is_some() && a.backend != BackendKind::Ort {
        bail!("--onnx needs --backend ort");
    }
    let bytes =
        std::fs::read(&a.inputs).with_context(|| format!("cannot read {}", a.inputs.display()))?;
    let st = SafeTensors::deserialize(&bytes)
        .with_context(|| format!("{}: not a safetensors file", a.inputs.display()))?;
    let t0 = std::time::Instant::now();
    let ((image, image_shape, selection, selection_shape), features) = match a.backend {
        BackendKind::Candle => forward_candle(&a, &st)?,
        BackendKind::Ort => forward_ort(&a, &st)?,
    };
    let backend = format!("{:?}", a.backend).to_lowercase();
    eprintln!(
        "forward ({backend}) in {:.3} s: image {image_shape:?}, selection {selection_shape:?}",
        t0.elapsed().as_secs_f64()
    );
    let meta = HashMap::from([("backend".to_string(), backend)]);
    let mut arrays = vec![
        NamedArray::f32("image", &image_shape, &image),
        NamedArray::f32("selection", &selection_shape, &selection),
    ];
    if let Some((data, shape)) = &features {
        arrays.push(NamedArray::f32(SOURCE_FEATURES, shape, data));
    }
    write_safetensors(&a.out, &arrays, Some(meta))?;
    eprintln!("wrote {}", a.out.display());
    Ok(())
}

/// The network's image and selection (data and shapes) for the inputs `st`, by candle.
fn forward_candle(a: &Args, st: &SafeTensors<'_>) -> anyhow::Result<Outputs> {
    let t = load_model(a.model.as_deref())?;
    let cfg = t.model.config();
    let mut inputs = Vec::with_capacity(cfg.levels);
    for l in 0..cfg.levels {
        let (shape, data) = read_f32(st, &input_name(l), &a.inputs)?;
        let (rank, layout) = match cfg.pool {
            Some(_) => (6, "[B, D, V, C_v, H, W] with B, D and V"),
            None => (5, "[B, D, 4V, H, W] with B and D"),
        };
        if shape.len() != rank || shape[..rank - 3].contains(&0) {
            bail!(
                "{}: '{}' must be {layout} at least 1, got {shape:?}",
                a.inputs.display(),
                input_name(l)
            );
        }
        inputs.push(Tensor::from_vec(data, shape, &Device::Cpu)?);
    }
    let out = t.model.infer(&inputs)?;
    let features = source_features(st, &a.inputs, &|img| match t.model.feature_net() {
        Some(net) => Ok(net.image_features(img, &Device::Cpu)?),
        None => bail!("the model reads no source features"),
    })?;
    Ok((
        (
            out.image.flatten_all()?.to_vec1::<f32>()?,
            out.image.dims().to_vec(),
            out.selection.flatten_all()?.to_vec1::<f32>()?,
            out.selection.dims().to_vec(),
        ),
        features,
    ))
}

/// The input holding a source image `[3, H, W]` whose feature map (the features family's
/// per-source CNN) `forward` also writes, as `source_features` `[F, H, W]`.
const SOURCE_IMAGE: &str = "source_image";
const SOURCE_FEATURES: &str = "source_features";

/// The feature map of the inputs' `source_image` by `features`, when it is there.
fn source_features(
    st: &SafeTensors<'_>,
    path: &std::path::Path,
    features: &dyn Fn(&RgbImage) -> anyhow::Result<FeatureMap>,
) -> anyhow::Result<Option<(Vec<f32>, Vec<usize>)>> {
    if st.tensor(SOURCE_IMAGE).is_err() {
        return Ok(None);
    }
    let (shape, data) = read_f32(st, SOURCE_IMAGE, path)?;
    let &[3, h, w] = shape.as_slice() else {
        bail!(
            "{}: '{SOURCE_IMAGE}' must be [3, H, W], got {shape:?}",
            path.display()
        );
    };
    let mut img = RgbImage::new(w as u32, h as u32);
    for (i, px) in img.data.chunks_exact_mut(3).enumerate() {
        for (c, v) in px.iter_mut().enumerate() {
            *v = data[c * h * w + i];
        }
    }
    let f = features(&img)?;
    Ok(Some((f.data, vec![f.channels, h, w])))
}

/// The same by onnxruntime, on `--onnx` or the model exported in memory.
fn forward_ort(a: &Args, st: &SafeTensors<'_>) -> anyhow::Result<Outputs> {
    let backend = match (&a.onnx, &a.model) {
        (Some(onnx), model) => {
            let b = OrtBackend::from_file(onnx)?;
            if let Some(m) = model {
                let t = load_model(Some(m))?;
                if t.model.config() != deepstereo_core::render::Backend::config(&b) {
                    bail!(
                        "{} is not an export of {}: their configs differ",
                        onnx.display(),
                        m.display()
                    );
                }
            }
            b
        }
        (None, model) => OrtBackend::from_model(&load_model(model.as_deref())?)?,
    };
    let levels = deepstereo_core::render::Backend::config(&backend).levels;
    let inputs: Vec<(Vec<usize>, Vec<f32>)> = (0..levels)
        .map(|l| read_f32(st, &input_name(l), &a.inputs))
        .collect::<anyhow::Result<_>>()?;
    let refs: Vec<(&[usize], &[f32])> = inputs
        .iter()
        .map(|(s, d)| (s.as_slice(), d.as_slice()))
        .collect();
    let out = backend.forward(&refs)?;
    let features = source_features(st, &a.inputs, &|img| {
        Ok(deepstereo_core::render::Backend::source_features(
            &backend, img,
        )?)
    })?;
    Ok((
        (
            out.image,
            out.image_shape,
            out.selection,
            out.selection_shape,
        ),
        features,
    ))
}

/// Image and selection: data and shape each; and the source features when asked for.
type Outputs = (
    (Vec<f32>, Vec<usize>, Vec<f32>, Vec<usize>),
    Option<(Vec<f32>, Vec<usize>)>,
);
