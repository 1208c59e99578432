//! The `features` family's second graph: the per-source CNN
//! ([`deepstereo_core::features::FeatureNet`]), run once on each source image at each
//! pyramid level; its output, warped into the sweep like the source's colours, is the last
//! `F` channels of each view in the network graph's inputs.
//!
//! Input `image` `[N, 3, H + 2R, W + 2R]`: source images (level `l` of the pyramid,
//! colours in [0, 1]) zero-padded by `R` on every side; output `features`
//! `[N, F, H, W]`. `R` and `F` are in the graph's doc string and in the config.

use super::{dim, fixed, model_proto, value_info, Graph, Weight};
use crate::error::{Error, Result};
use crate::onnx_proto::{GraphProto, ModelProto};
use deepstereo_core::config::{Config, SourceFeatures, ViewPool};
use prost::Message;
use std::path::{Path, PathBuf};

/// Whether a weight belongs to the feature CNN (`features.*`), not the network graph.
pub fn is_feature_weight(name: &str) -> bool {
    name.starts_with("features.")
}

/// The file the feature graph of the network graph `onnx` goes to: `NAME.features.onnx`
/// beside `NAME.onnx`.
pub fn features_path(onnx: &Path) -> PathBuf {
    let stem = onnx
        .file_stem()
        .map_or_else(Default::default, |s| s.to_string_lossy().into_owned());
    onnx.with_file_name(format!("{stem}.features.onnx"))
}

/// What a network input's description says of the warped source features.
pub(super) fn input_doc(p: &ViewPool) -> String {
    match &p.features {
        Some(f) => format!(
            ", then {} channels of the source's features: the feature graph's output for the \
             source's level image, warped at the same positions as its RGB (zero-padded \
             bilinear, premultiplied by alpha at the border: deepstereo-core/src/features.rs)",
            f.channels()
        ),
        None => String::new(),
    }
}

/// The feature CNN of `cfg` as an ONNX model, `None` when the model has none. `weights`
/// are the model's (the `features.*` ones are used; every one of them must be).
pub fn build_features_model(
    cfg: &Config,
    weights: &[Weight],
    opset: i64,
) -> Result<Option<ModelProto>> {
    let Some(sf) = cfg.pool.as_ref().and_then(|p| p.features.as_ref()) else {
        return Ok(None);
    };
    let own: Vec<Weight> = (weights.iter())
        .filter(|w| is_feature_weight(&w.0))
        .cloned()
        .collect();
    let mut g = Graph::bare(cfg, &own)?;
    // ReLU after every layer but the last.
    let (last, hidden) = sf
        .convs
        .split_last()
        .ok_or_else(|| Error::Config("pool.features has no layer".into()))?;
    let x = g.conv_relu_chain("image", "features", 3, hidden)?;
    let ch = hidden.last().map_or(3, |c| c.channels);
    let name = format!("features.{}", hidden.len());
    let x = g.conv(
        &x,
        &name,
        (ch, last.channels),
        (last.kernel, last.kernel),
        [0; 4],
    )?;
    g.rename_output(&x, "features")?;
    g.check_all_weights_used()?;
    let graph = GraphProto {
        node: g.nodes,
        name: Some(format!("deepstereo_{}_features", cfg.name)),
        initializer: g.initializers,
        doc_string: Some(doc(sf)),
        input: vec![value_info(
            "image",
            vec![
                dim("images"),
                fixed(3),
                dim("padded_height"),
                dim("padded_width"),
            ],
            &format!(
                "source images zero-padded by {} pixels on every side",
                sf.radius()
            ),
        )],
        output: vec![value_info(
            "features",
            vec![
                dim("images"),
                fixed(sf.channels()),
                dim("height"),
                dim("width"),
            ],
            "feature maps over the unpadded images' pixels",
        )],
        ..Default::default()
    };
    model_proto(cfg, graph, opset).map(Some)
}

fn doc(sf: &SourceFeatures) -> String {
    format!(
        "DeepStereo per-source features: [N, 3, H + {r2}, W + {r2}] (zero-padded by R = {r}) -> \
         [N, {f}, H, W]; run once per source image and pyramid level",
        r = sf.radius(),
        r2 = 2 * sf.radius(),
        f = sf.channels()
    )
}

/// [`build_features_model`]'s serialized bytes.
pub fn export_features(cfg: &Config, weights: &[Weight], opset: i64) -> Result<Option<Vec<u8>>> {
    if !(super::MIN_OPSET..=super::MAX_OPSET).contains(&opset) {
        return Err(Error::Opset {
            got: opset,
            min: super::MIN_OPSET,
            max: super::MAX_OPSET,
        });
    }
    Ok(build_features_model(cfg, weights, opset)?.map(|m| m.encode_to_vec()))
}
