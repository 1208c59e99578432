//! The DeepStereo network as an ONNX graph.
//!
//! The graph follows [`deepstereo_core::model::DeepStereo::forward`] step by step (the
//! comments name the step). Shapes use the model's letters: `B` batch, `D` planes, `C`
//! channels, `th x tw` the output tile; every one of them is dynamic in the graph, read from
//! the inputs with `Shape`. Only standard operators of the default domain are used: Shape,
//! Sub, Add, Concat, Slice, Reshape, Conv, Relu, Resize (nearest, integer factors, exact),
//! Transpose, Tanh, Exp, Mul, Softmax, Unsqueeze, ReduceSum, Constant.

use crate::error::{Error, Result};
use crate::onnx_proto::{AttributeProto, GraphProto, ModelProto, NodeProto, TensorProto};
use deepstereo_core::config::Config;
use deepstereo_core::weights::{self, Trainable, CONFIG_KEY};
use prost::Message;
use std::collections::{BTreeMap, BTreeSet};

mod features;
mod network;
mod pool;
mod proto;

use proto::{attr_int, attr_ints, attr_str, attr_tensor, f32_tensor, i64_tensor};
pub(crate) use proto::{dim, fixed, graph_inputs, graph_outputs, model_proto, value_info};

pub use features::{build_features_model, export_features, features_path};

/// The opset written by default.
pub const DEFAULT_OPSET: i64 = 17;
/// The oldest opset this exporter writes (`Shape` with `start`/`end`, `Softmax` on one
/// axis, `ReduceSum` / `Unsqueeze` with axes as inputs).
pub const MIN_OPSET: i64 = 17;
/// The newest opset this exporter knows the IR version of (the pinned `onnx` 1.23 package).
pub const MAX_OPSET: i64 = 28;

/// One named weight tensor: `(name, shape, row-major values)`.
pub type Weight = (String, Vec<usize>, Vec<f32>);

/// Name of the graph input holding level `l`.
pub fn input_name(l: usize) -> String {
    format!("level{l}")
}

/// The IR version that goes with an opset (onnx's `helper.VERSION_TABLE`): the lowest that
/// allows it, so older runtimes still read the file.
fn ir_version(opset: i64) -> i64 {
    match opset {
        ..=18 => 8,
        19 | 20 => 9,
        21 | 22 => 10,
        23 => 11,
        24 => 12,
        25..=27 => 13,
        _ => 14,
    }
}

/// The weights of a model as `(name, shape, values)`, sorted by name.
pub fn model_weights(t: &Trainable) -> Result<Vec<Weight>> {
    weights::named_vars(&t.varmap)
        .into_iter()
        .map(|(name, var)| {
            let tensor = var.as_tensor();
            Ok((name, tensor.dims().to_vec(), weights::tensor_f32(tensor)?))
        })
        .collect()
}

/// Exports a loaded (or freshly initialised) model.
pub fn export_trainable(t: &Trainable, opset: i64) -> Result<Vec<u8>> {
    export(t.model.config(), &model_weights(t)?, opset)
}

/// Builds the ONNX model of the network `cfg` with `weights` (`(name, shape, values)`, named
/// as in the safetensors file; every tensor the model has must be there, and no other) and
/// returns its serialized bytes.
pub fn export(cfg: &Config, weights: &[Weight], opset: i64) -> Result<Vec<u8>> {
    Ok(build_model(cfg, weights, opset)?.encode_to_vec())
}

/// Reads the network's config from an ONNX file's metadata (written by [`export()`]).
pub fn read_config(onnx: &[u8]) -> Result<Config> {
    let model = ModelProto::decode(onnx).map_err(|e| Error::Onnx {
        what: "ONNX model".into(),
        msg: format!("cannot decode: {e}"),
    })?;
    config_of(&model)
}

pub(crate) fn config_of(model: &ModelProto) -> Result<Config> {
    let json = model
        .metadata_props
        .iter()
        .find(|p| p.key.as_deref() == Some(CONFIG_KEY))
        .and_then(|p| p.value.as_deref())
        .ok_or_else(|| Error::Onnx {
            what: "ONNX model".into(),
            msg: format!("no '{CONFIG_KEY}' metadata: not exported by deepstereo"),
        })?;
    let cfg: Config = serde_json::from_str(json).map_err(|e| Error::Onnx {
        what: "ONNX model".into(),
        msg: format!("invalid '{CONFIG_KEY}' metadata: {e}"),
    })?;
    cfg.validate().map_err(Error::Config)?;
    Ok(cfg)
}

/// Builds the ONNX model (see [`export()`]).
pub fn build_model(cfg: &Config, weights: &[Weight], opset: i64) -> Result<ModelProto> {
    if !(MIN_OPSET..=MAX_OPSET).contains(&opset) {
        return Err(Error::Opset {
            got: opset,
            min: MIN_OPSET,
            max: MAX_OPSET,
        });
    }
    cfg.validate().map_err(Error::Config)?;
    // The features family's CNN is a graph of its own ([`features::build_features_model`]).
    let network: Vec<Weight> = (weights.iter())
        .filter(|w| !features::is_feature_weight(&w.0))
        .cloned()
        .collect();
    let mut g = Graph::new(cfg, &network)?;
    let (image, selection) = g.forward(cfg)?;
    g.rename_output(&image, "image")?;
    g.rename_output(&selection, "selection")?;
    g.check_all_weights_used()?;
    let graph = GraphProto {
        node: g.nodes,
        name: Some(format!("deepstereo_{}", cfg.name)),
        initializer: g.initializers,
        doc_string: Some(format!(
            "DeepStereo network '{}': {} views, {} levels; output tile th x tw, th and tw multiples of {}",
            cfg.name,
            cfg.views,
            cfg.levels,
            cfg.tile_align()
        )),
        input: graph_inputs(cfg),
        output: graph_outputs(),
        ..Default::default()
    };
    model_proto(cfg, graph, opset)
}

/// A graph under construction.
struct Graph<'w> {
    nodes: Vec<NodeProto>,
    initializers: Vec<TensorProto>,
    weights: BTreeMap<&'w str, (&'w [usize], &'w [f32])>,
    used: BTreeSet<String>,
    config_name: String,
    count: usize,
    /// `[B, D]` (int64) of the inputs.
    bd: String,
    /// `[th, tw]` (int64) of the output tile.
    tile: String,
    /// The levels the view pooling and the blend read, where they are not the inputs
    /// themselves (the weighed levels with `pool.weigh`).
    view_levels: Vec<String>,
}

impl<'w> Graph<'w> {
    fn new(cfg: &Config, weights: &'w [Weight]) -> Result<Self> {
        let mut g = Self::bare(cfg, weights)?;
        // (B, D) and (th, tw) = (H_0 - 2 pad_0, W_0 - 2 pad_0), read from level 0.
        let level0 = input_name(0);
        g.bd = g.op(
            "Shape",
            &[&level0],
            vec![attr_int("start", 0), attr_int("end", 2)],
            "batch_planes",
        );
        let hw_axis = if cfg.pool.is_some() { 4 } else { 3 };
        let hw0 = g.op(
            "Shape",
            &[&level0],
            vec![attr_int("start", hw_axis), attr_int("end", hw_axis + 2)],
            "level0_size",
        );
        let p0 = 2 * cfg.pad(0) as i64;
        let border = g.const_i64(&[p0, p0], "level0_border");
        g.tile = g.op("Sub", &[&hw0, &border], vec![], "tile_size");
        Ok(g)
    }

    /// A graph with `weights` to draw on and no nodes.
    fn bare(cfg: &Config, weights: &'w [Weight]) -> Result<Self> {
        let mut map = BTreeMap::new();
        for (name, shape, values) in weights {
            if shape.iter().product::<usize>() != values.len() {
                return Err(Error::Weights {
                    config: cfg.name.clone(),
                    msg: format!(
                        "tensor '{name}' has shape {shape:?} but {} values",
                        values.len()
                    ),
                });
            }
            if values.iter().any(|v| !v.is_finite()) {
                return Err(Error::Weights {
                    config: cfg.name.clone(),
                    msg: format!("tensor '{name}' holds non-finite values"),
                });
            }
            if map
                .insert(name.as_str(), (shape.as_slice(), values.as_slice()))
                .is_some()
            {
                return Err(Error::Weights {
                    config: cfg.name.clone(),
                    msg: format!("tensor '{name}' given twice"),
                });
            }
        }
        Ok(Self {
            nodes: Vec::new(),
            initializers: Vec::new(),
            weights: map,
            used: BTreeSet::new(),
            config_name: cfg.name.clone(),
            count: 0,
            bd: String::new(),
            tile: String::new(),
            view_levels: Vec::new(),
        })
    }

    fn fresh(&mut self, hint: &str) -> String {
        self.count += 1;
        format!("{hint}_{}", self.count)
    }

    /// Adds a node with one output and returns the output's name.
    fn op(
        &mut self,
        op: &str,
        inputs: &[&str],
        attribute: Vec<AttributeProto>,
        hint: &str,
    ) -> String {
        let out = self.fresh(hint);
        self.nodes.push(NodeProto {
            input: inputs.iter().map(|s| s.to_string()).collect(),
            output: vec![out.clone()],
            name: Some(format!("{op}/{out}")),
            op_type: Some(op.into()),
            attribute,
            ..Default::default()
        });
        out
    }

    fn const_i64(&mut self, values: &[i64], hint: &str) -> String {
        self.constant(hint, |out| i64_tensor(out, values))
    }

    fn const_f32(&mut self, dims: &[usize], values: &[f32], hint: &str) -> String {
        self.constant(hint, |out| f32_tensor(out, dims, values))
    }

    /// A `Constant` node holding `tensor(name)`; returns its output's name.
    fn constant(&mut self, hint: &str, tensor: impl FnOnce(&str) -> TensorProto) -> String {
        let out = self.fresh(hint);
        self.nodes.push(NodeProto {
            input: vec![],
            output: vec![out.clone()],
            name: Some(format!("Constant/{out}")),
            op_type: Some("Constant".into()),
            attribute: vec![attr_tensor("value", tensor(&out))],
            ..Default::default()
        });
        out
    }

    /// Adds the weight `name` (which must have `shape`) as an initializer; returns its name.
    fn weight(&mut self, name: &str, shape: &[usize]) -> Result<String> {
        let (got, values) = *self.weights.get(name).ok_or_else(|| Error::Weights {
            config: self.config_name.clone(),
            msg: format!("missing tensor '{name}'"),
        })?;
        if got != shape {
            return Err(Error::Weights {
                config: self.config_name.clone(),
                msg: format!("tensor '{name}' has shape {got:?}, the model expects {shape:?}"),
            });
        }
        if self.used.insert(name.to_string()) {
            self.initializers.push(f32_tensor(name, shape, values));
        }
        Ok(name.to_string())
    }

    fn check_all_weights_used(&self) -> Result<()> {
        if let Some(extra) = self.weights.keys().find(|k| !self.used.contains(**k)) {
            return Err(Error::Weights {
                config: self.config_name.clone(),
                msg: format!(
                    "unexpected tensor '{extra}' (not part of a '{}' model)",
                    self.config_name
                ),
            });
        }
        Ok(())
    }

    /// Makes `value` (the output of the last node that produced it) a graph output `name`.
    fn rename_output(&mut self, value: &str, name: &str) -> Result<()> {
        let node = self
            .nodes
            .iter_mut()
            .rev()
            .find(|n| n.output.iter().any(|o| o == value))
            .ok_or_else(|| Error::Config(format!("no node produces '{value}'")))?;
        for o in node.output.iter_mut().filter(|o| *o == value) {
            *o = name.to_string();
        }
        for n in &mut self.nodes {
            for i in n.input.iter_mut().filter(|i| *i == value) {
                *i = name.to_string();
            }
        }
        Ok(())
    }

    /// `Conv2d` of `model.rs`/`conv.rs` (valid, stride 1, bias) with optional zero `pads`
    /// `[top, left, bottom, right]`; weights `prefix.weight` `[cout, cin, kh, kw]` and
    /// `prefix.bias` `[cout]`.
    fn conv(
        &mut self,
        x: &str,
        prefix: &str,
        (cin, cout): (usize, usize),
        (kh, kw): (usize, usize),
        pads: [i64; 4],
    ) -> Result<String> {
        let w = self.weight(&format!("{prefix}.weight"), &[cout, cin, kh, kw])?;
        let b = self.weight(&format!("{prefix}.bias"), &[cout])?;
        let attrs = vec![
            attr_ints("kernel_shape", &[kh as i64, kw as i64]),
            attr_ints("pads", &pads),
            attr_ints("strides", &[1, 1]),
            attr_ints("dilations", &[1, 1]),
            attr_int("group", 1),
        ];
        Ok(self.op("Conv", &[x, &w, &b], attrs, prefix))
    }

    fn relu(&mut self, x: &str) -> String {
        self.op("Relu", &[x], vec![], "relu")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ir_versions_follow_onnx() {
        assert_eq!(ir_version(17), 8);
        assert_eq!(ir_version(21), 10);
        assert_eq!(ir_version(28), 14);
    }

    #[test]
    fn opset_out_of_range_is_an_error() {
        let cfg = Config::tiny();
        assert!(matches!(
            build_model(&cfg, &[], 16),
            Err(Error::Opset { .. })
        ));
        assert!(matches!(
            build_model(&cfg, &[], MAX_OPSET + 1),
            Err(Error::Opset { .. })
        ));
    }
}
