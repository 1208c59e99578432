//! The DeepStereo network as an ONNX graph.
//!
//! The graph follows [`deepstereo_core::model::DeepStereo::forward`] step by step (the
//! comments name the step). Shapes use the model's letters: `B` batch, `D` planes, `C`
//! channels, `th x tw` the output tile; every one of them is dynamic in the graph, read from
//! the inputs with `Shape`. Only standard operators of the default domain are used: Shape,
//! Sub, Add, Concat, Slice, Reshape, Conv, Relu, Resize (nearest, integer factors, exact),
//! Transpose, Tanh, Exp, Mul, Softmax, Unsqueeze, ReduceSum, Constant.

use crate::error::{Error, Result};
use crate::onnx_proto::{
    attribute_proto::AttributeType, tensor_proto::DataType, tensor_shape_proto, type_proto,
    AttributeProto, GraphProto, ModelProto, NodeProto, OperatorSetIdProto, StringStringEntryProto,
    TensorProto, TensorShapeProto, TypeProto, ValueInfoProto,
};
use deepstereo_core::config::{Config, TowerConfig};
use deepstereo_core::weights::{self, Trainable, CONFIG_KEY};
use prost::Message;
use std::collections::{BTreeMap, BTreeSet};

mod features;
mod pool;

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

/// A dynamic dimension named `name`.
fn dim(name: &str) -> tensor_shape_proto::Dimension {
    tensor_shape_proto::Dimension {
        denotation: None,
        value: Some(tensor_shape_proto::dimension::Value::DimParam(
            name.to_string(),
        )),
    }
}

/// A dimension of fixed size `v`.
fn fixed(v: usize) -> tensor_shape_proto::Dimension {
    tensor_shape_proto::Dimension {
        denotation: None,
        value: Some(tensor_shape_proto::dimension::Value::DimValue(v as i64)),
    }
}

/// A float tensor's name, dimensions and description.
fn value_info(name: &str, dims: Vec<tensor_shape_proto::Dimension>, doc: &str) -> ValueInfoProto {
    ValueInfoProto {
        name: Some(name.to_string()),
        r#type: Some(TypeProto {
            denotation: None,
            value: Some(type_proto::Value::TensorType(type_proto::Tensor {
                elem_type: Some(DataType::Float as i32),
                shape: Some(TensorShapeProto { dim: dims }),
            })),
        }),
        doc_string: Some(doc.to_string()),
        metadata_props: vec![],
    }
}

/// The graph's inputs: one plane-sweep level each, with its layout (and the view falloff,
/// which whoever builds the inputs applies) in its description.
fn graph_inputs(cfg: &Config) -> Vec<ValueInfoProto> {
    let cin = cfg.in_channels();
    (0..cfg.levels)
        .map(|l| {
            let (h, w) = (
                dim(&format!("level{l}_height")),
                dim(&format!("level{l}_width")),
            );
            let (dims, layout) = match &cfg.pool {
                Some(p) if p.reads_cue() => (
                    vec![
                        dim("batch"),
                        dim("planes"),
                        dim("views"),
                        fixed(p.view_channels()),
                        h,
                        w,
                    ],
                    format!(
                        "[B, D, V, {}, H, W] (per source and plane: RGBA, then the geometric cue \
                         [u_x, u_y, u_z, ln(n + 1e-3), clamp(ln(|X - c_v| / |X - c_t|), -5, 5)], \
                         u = (d_v - d_t) / (n + 1e-3), n = |d_v - d_t|, d_t and d_v the unit rays \
                         from the target and the source to the plane point in target camera \
                         coordinates: deepstereo-core/src/sweep/cue.rs{}; any V >= 1)",
                        p.view_channels(),
                        match p.disagree {
                            Some(d) => format!(
                                ", then sqrt(min_n |rgb_v - rgb_n|^2) over the other sources n among \
                                 the {} nearest to the target centre with sweep alpha >= 0.5 (0 where \
                                 none): deepstereo-core/src/view_weights.rs, disagreement",
                                d.near
                            ),
                            None => String::new(),
                        } + &features::input_doc(p)
                    ),
                ),
                Some(p) => (
                    vec![dim("batch"), dim("planes"), dim("views"), fixed(p.view_channels()), h, w],
                    format!(
                        "[B, D, V, {}, H, W] (RGBA of each source per plane{}, any V >= 1)",
                        p.view_channels(),
                        features::input_doc(p)
                    ),
                ),
                None => (
                    vec![dim("batch"), dim("planes"), fixed(cin), h, w],
                    "[B, D, 4V, H, W] (RGBA of each source per plane)".into(),
                ),
            };
            // A falloff is applied by whoever builds the inputs: say so where they look.
            let falloff = match cfg.pool.as_ref().and_then(|p| p.falloff) {
                Some(f) => format!(
                    "; alpha of each source times its weight (1 for the {} nearest to the \
                     target centre, (d_ref / d)^{} beyond: deepstereo-core/src/view_weights.rs)",
                    f.full, f.power
                ),
                None => String::new(),
            };
            let agree = match cfg.pool.as_ref().and_then(|p| p.agree) {
                Some(a) => format!(
                    "; alpha of each source beyond the {} nearest first times exp(-e / (2 * {}^2)), \
                     e its least squared RGB distance to a near source's colour where that one's \
                     alpha >= 0.5: deepstereo-core/src/view_weights.rs, agree_gate",
                    a.near, a.sigma
                ),
                None => String::new(),
            };
            let doc = format!(
                "plane sweep at 1/{} resolution: {layout}, H_{l} = (th >> {l}) + {}{agree}{falloff}",
                1 << l,
                2 * cfg.pad(l)
            );
            value_info(&input_name(l), dims, &doc)
        })
        .collect()
}

/// The graph's outputs: the rendered colour and the selection probabilities.
fn graph_outputs() -> Vec<ValueInfoProto> {
    vec![
        value_info(
            "image",
            vec![
                dim("batch"),
                fixed(3),
                dim("tile_height"),
                dim("tile_width"),
            ],
            "rendered colour [B, 3, th, tw]",
        ),
        value_info(
            "selection",
            vec![
                dim("batch"),
                dim("planes"),
                dim("tile_height"),
                dim("tile_width"),
            ],
            "selection probabilities over planes [B, D, th, tw]",
        ),
    ]
}

/// The model around `graph`: opset, IR version, producer, and the config (and tile
/// alignment) in the metadata.
fn model_proto(cfg: &Config, graph: GraphProto, opset: i64) -> Result<ModelProto> {
    let config_json = serde_json::to_string(cfg).map_err(|e| Error::Config(e.to_string()))?;
    let meta = |k: &str, v: String| StringStringEntryProto {
        key: Some(k.to_string()),
        value: Some(v),
    };
    Ok(ModelProto {
        ir_version: Some(ir_version(opset)),
        opset_import: vec![OperatorSetIdProto {
            domain: Some(String::new()),
            version: Some(opset),
        }],
        producer_name: Some("deepstereo".into()),
        producer_version: Some(env!("CARGO_PKG_VERSION").into()),
        domain: None,
        model_version: Some(1),
        doc_string: Some("DeepStereo view synthesis (Flynn et al. 2016)".into()),
        graph: Some(graph),
        metadata_props: vec![
            meta(CONFIG_KEY, config_json),
            meta("deepstereo.tile_align", cfg.tile_align().to_string()),
        ],
        ..Default::default()
    })
}

fn attr_int(name: &str, v: i64) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::Int as i32),
        i: Some(v),
        ..Default::default()
    }
}

fn attr_ints(name: &str, v: &[i64]) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::Ints as i32),
        ints: v.to_vec(),
        ..Default::default()
    }
}

fn attr_str(name: &str, v: &str) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::String as i32),
        s: Some(v.as_bytes().to_vec()),
        ..Default::default()
    }
}

fn attr_tensor(name: &str, t: TensorProto) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::Tensor as i32),
        t: Some(t),
        ..Default::default()
    }
}

fn f32_tensor(name: &str, dims: &[usize], values: &[f32]) -> TensorProto {
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: Some(DataType::Float as i32),
        name: Some(name.into()),
        raw_data: Some(values.iter().flat_map(|v| v.to_le_bytes()).collect()),
        ..Default::default()
    }
}

fn i64_tensor(name: &str, values: &[i64]) -> TensorProto {
    TensorProto {
        dims: vec![values.len() as i64],
        data_type: Some(DataType::Int64 as i32),
        name: Some(name.into()),
        raw_data: Some(values.iter().flat_map(|v| v.to_le_bytes()).collect()),
        ..Default::default()
    }
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
        let out = self.fresh(hint);
        self.nodes.push(NodeProto {
            input: vec![],
            output: vec![out.clone()],
            name: Some(format!("Constant/{out}")),
            op_type: Some("Constant".into()),
            attribute: vec![attr_tensor("value", i64_tensor(&out, values))],
            ..Default::default()
        });
        out
    }

    fn const_f32(&mut self, dims: &[usize], values: &[f32], hint: &str) -> String {
        let out = self.fresh(hint);
        self.nodes.push(NodeProto {
            input: vec![],
            output: vec![out.clone()],
            name: Some(format!("Constant/{out}")),
            op_type: Some("Constant".into()),
            attribute: vec![attr_tensor("value", f32_tensor(&out, dims, values))],
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

    /// `x[..., starts[i] .. starts[i] + tile[i] + extra, ...]` on `axes` (two of them), the
    /// tile size read from the graph: `narrow(axes[0], s0, th + extra).narrow(axes[1], s1, tw + extra)`.
    fn crop_to_tile(
        &mut self,
        x: &str,
        starts: [i64; 2],
        extra: i64,
        axes: [i64; 2],
        hint: &str,
    ) -> String {
        let s = self.const_i64(&starts, "starts");
        let add = self.const_i64(&[starts[0] + extra, starts[1] + extra], "end_offset");
        let tile = self.tile.clone();
        let ends = self.op("Add", &[&tile, &add], vec![], "ends");
        let ax = self.const_i64(&axes, "axes");
        self.op("Slice", &[x, &s, &ends, &ax], vec![], hint)
    }

    /// `Tower::forward` of `model.rs`: `inputs[l]` `[N, C_in, H_l, W_l]` -> `[N, C, th, tw]`.
    fn tower(
        &mut self,
        t: &TowerConfig,
        prefix: &str,
        inputs: &[String],
        cin: usize,
    ) -> Result<String> {
        let rf = t.merge_reduction();
        let mut feats = Vec::with_capacity(t.levels);
        for (l, input) in inputs.iter().enumerate().take(t.levels) {
            let mut x = input.clone();
            let mut ch = cin;
            for (i, c) in t.level_convs.iter().enumerate() {
                x = self.conv(
                    &x,
                    &format!("{prefix}.levels.{l}.{i}"),
                    (ch, c.channels),
                    (c.kernel, c.kernel),
                    [0; 4],
                )?;
                x = self.relu(&x);
                ch = c.channels;
            }
            if l > 0 {
                // upsample_nearest(x, 2^l): exact nearest with integer factors.
                let s = (1u32 << l) as f32;
                let scales = self.const_f32(&[4], &[1.0, 1.0, s, s], "scales");
                let attrs = vec![
                    attr_str("mode", "nearest"),
                    attr_str("coordinate_transformation_mode", "asymmetric"),
                    attr_str("nearest_mode", "floor"),
                ];
                x = self.op(
                    "Resize",
                    &[&x, "", &scales],
                    attrs,
                    &format!("{prefix}.levels.{l}.upsample"),
                );
            }
            // x.narrow(2, off, th + rf).narrow(3, off, tw + rf)
            let off = t.upsample_crop(l) as i64;
            x = self.crop_to_tile(
                &x,
                [off, off],
                rf as i64,
                [2, 3],
                &format!("{prefix}.levels.{l}.crop"),
            );
            feats.push(x);
        }
        let mut x = if feats.len() == 1 {
            feats.remove(0)
        } else {
            let refs: Vec<&str> = feats.iter().map(String::as_str).collect();
            self.op(
                "Concat",
                &refs,
                vec![attr_int("axis", 1)],
                &format!("{prefix}.concat"),
            )
        };
        let mut ch = t.level_channels(cin) * t.levels;
        for (i, c) in t.merge_convs.iter().enumerate() {
            x = self.conv(
                &x,
                &format!("{prefix}.merge.{i}"),
                (ch, c.channels),
                (c.kernel, c.kernel),
                [0; 4],
            )?;
            x = self.relu(&x);
            ch = c.channels;
        }
        Ok(x)
    }

    /// `[B, D, C, h, w]` -> `[B*D, C, h, w]` (`C` fixed, `h`, `w` read from `x`).
    fn fold_planes(&mut self, x: &str, c: usize, hint: &str) -> String {
        let lead = self.const_i64(&[-1, c as i64], "fold_lead");
        let hw = self.op("Shape", &[x], vec![attr_int("start", 3)], "fold_hw");
        let shape = self.op(
            "Concat",
            &[&lead, &hw],
            vec![attr_int("axis", 0)],
            "fold_shape",
        );
        self.op("Reshape", &[x, &shape], vec![], hint)
    }

    /// `folded(t)` of `DeepStereo::forward`: each level the tower reads (`levels[l]`,
    /// `[B, D, cin, H_l, W_l]`), cropped to its footprint and with planes folded into the
    /// batch.
    fn folded(
        &mut self,
        cfg: &Config,
        t: &TowerConfig,
        prefix: &str,
        levels: &[String],
        cin: usize,
    ) -> Vec<String> {
        (0..t.levels)
            .map(|l| {
                let off = (cfg.pad(l) - t.pad(l)) as i64;
                let mut x = levels[l].clone();
                if off > 0 {
                    // x.narrow(3, off, h - 2 off).narrow(4, off, w - 2 off)
                    let s = self.const_i64(&[off, off], "starts");
                    let e = self.const_i64(&[-off, -off], "ends");
                    let ax = self.const_i64(&[3, 4], "axes");
                    x = self.op(
                        "Slice",
                        &[&x, &s, &e, &ax],
                        vec![],
                        &format!("{prefix}.input{l}.crop"),
                    );
                }
                self.fold_planes(&x, cin, &format!("{prefix}.input{l}.folded"))
            })
            .collect()
    }

    /// `DeepStereo::forward`; returns the names of `image` and `selection`.
    fn forward(&mut self, cfg: &Config) -> Result<(String, String)> {
        let cin = cfg.tower_in_channels();
        // The towers' inputs: the sweep itself, or the pooled statistics.
        let (towers_in, features) = match &cfg.pool {
            Some(pool) => {
                if let Some(hidden) = &pool.weigh {
                    self.view_levels = self.weighed_levels(cfg, hidden)?;
                }
                let (stats, features) = self.pooled(cfg, pool)?;
                (stats, Some(features))
            }
            None => ((0..cfg.levels).map(input_name).collect(), None),
        };

        let selection = self.selection(cfg, &towers_in, cin)?; // [B, D, th, tw]
        let colours = self.colours(cfg, &towers_in, features.as_deref(), cin)?; // [B*D, 3, th, tw]
        let image = self.composite(&colours, &selection); // [B, 3, th, tw]
        Ok((image, selection))
    }

    /// Selection tower, the depth layers and the softmax over planes: `[B, D, th, tw]`.
    fn selection(&mut self, cfg: &Config, towers_in: &[String], cin: usize) -> Result<String> {
        let bd = self.bd.clone();
        let tile = self.tile.clone();
        let inputs = self.folded(cfg, &cfg.select, "select", towers_in, cin);
        let s = self.tower(&cfg.select, "select", &inputs, cin)?; // [B*D, C, th, tw]
        let c = cfg.select.out_channels(cin);
        let tail = self.const_i64(&[c as i64, -1], "select_tail");
        let shape = self.op(
            "Concat",
            &[&bd, &tail],
            vec![attr_int("axis", 0)],
            "select_shape",
        );
        let x = self.op("Reshape", &[&s, &shape], vec![], "select.unfold"); // [B, D, C, th*tw]
        let mut x = self.op(
            "Transpose",
            &[&x],
            vec![attr_ints("perm", &[0, 2, 1, 3])],
            "select.transpose",
        ); // [B, C, D, th*tw]
        let last = cfg.depth_convs.len() - 1;
        let mut ch = c;
        for (i, conv) in cfg.depth_convs.iter().enumerate() {
            // conv(pad_with_zeros(x, 2, p, p)): zero padding along depth only.
            let p = (conv.kernel / 2) as i64;
            x = self.conv(
                &x,
                &format!("select.depth.{i}"),
                (ch, conv.channels),
                (conv.kernel, 1),
                [p, 0, p, 0],
            )?;
            if i < last {
                x = self.relu(&x);
            }
            ch = conv.channels;
        }
        let x = self.op("Tanh", &[&x], vec![], "select.tanh");
        let log_scale = self.weight("select.log_scale", &[1])?;
        let scale = self.op("Exp", &[&log_scale], vec![], "select.scale");
        let logits = self.op("Mul", &[&x, &scale], vec![], "select.logits"); // [B, 1, D, th*tw]
        let sel = self.op(
            "Softmax",
            &[&logits],
            vec![attr_int("axis", 2)],
            "select.softmax",
        );
        let sel_shape = self.op(
            "Concat",
            &[&bd, &tile],
            vec![attr_int("axis", 0)],
            "selection_shape",
        );
        Ok(self.op("Reshape", &[&sel, &sel_shape], vec![], "selection")) // [B, D, th, tw]
    }

    /// Colour tower (with the skip input), its output layer and, pooled, the blend of the
    /// sources' colours by the view features: `[B*D, 3, th, tw]`.
    fn colours(
        &mut self,
        cfg: &Config,
        towers_in: &[String],
        features: Option<&str>,
        cin: usize,
    ) -> Result<String> {
        let inputs = self.folded(cfg, &cfg.colour, "colour", towers_in, cin);
        let mut f = self.tower(&cfg.colour, "colour", &inputs, cin)?; // [B*D, C, th, tw]
        let mut cout_in = cfg.colour.out_channels(cin);
        let blended = match (&cfg.pool, features) {
            (Some(pool), Some(e)) => Some(self.blend(cfg, pool, e, &f)?), // [B*D, 3, th, tw]
            _ => None,
        };
        if cfg.colour_skip {
            let p = cfg.pad(0) as i64;
            let centre = self.crop_to_tile(&input_name(0), [p, p], 0, [3, 4], "colour.centre");
            let centre = self.fold_planes(&centre, cfg.in_channels(), "colour.centre.folded"); // [B*D, 4V, th, tw]
            f = self.op(
                "Concat",
                &[&f, &centre],
                vec![attr_int("axis", 1)],
                "colour.skip",
            );
            cout_in += cin;
        }
        let mut colours = self.conv(&f, "colour.out", (cout_in, 3), (1, 1), [0; 4])?; // [B*D, 3, th, tw]
        if let Some(blended) = blended {
            colours = self.op("Add", &[&blended, &colours], vec![], "colour.sum");
        }
        Ok(colours)
    }

    /// The rendered colour `sum over D of s * c`: colours `[B*D, 3, th, tw]` and selection
    /// `[B, D, th, tw]` -> `[B, 3, th, tw]`.
    fn composite(&mut self, colours: &str, selection: &str) -> String {
        let bd = self.bd.clone();
        let tile = self.tile.clone();
        let three = self.const_i64(&[3], "three");
        let col_shape = self.op(
            "Concat",
            &[&bd, &three, &tile],
            vec![attr_int("axis", 0)],
            "colours_shape",
        );
        let colours = self.op("Reshape", &[colours, &col_shape], vec![], "colours"); // [B, D, 3, th, tw]
        let axis2 = self.const_i64(&[2], "axis2");
        let sel5 = self.op("Unsqueeze", &[selection, &axis2], vec![], "selection5"); // [B, D, 1, th, tw]
        let weighted = self.op("Mul", &[&colours, &sel5], vec![], "weighted"); // [B, D, 3, th, tw]
        let axis1 = self.const_i64(&[1], "axis1");
        self.op(
            "ReduceSum",
            &[&weighted, &axis1],
            vec![attr_int("keepdims", 0)],
            "image",
        ) // [B, 3, th, tw]
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
