//! The ONNX protobuf pieces the graphs are made of: dimensions, value infos, the network
//! graph's documented inputs and outputs, the model around a graph, attributes and
//! constant tensors.

use super::{features, input_name, ir_version};
use crate::error::{Error, Result};
use crate::onnx_proto::{
    attribute_proto::AttributeType, tensor_proto::DataType, tensor_shape_proto, type_proto,
    AttributeProto, GraphProto, ModelProto, OperatorSetIdProto, StringStringEntryProto,
    TensorProto, TensorShapeProto, TypeProto, ValueInfoProto,
};
use deepstereo_core::config::Config;
use deepstereo_core::weights::CONFIG_KEY;

/// A dynamic dimension named `name`.
pub(crate) fn dim(name: &str) -> tensor_shape_proto::Dimension {
    tensor_shape_proto::Dimension {
        denotation: None,
        value: Some(tensor_shape_proto::dimension::Value::DimParam(
            name.to_string(),
        )),
    }
}

/// A dimension of fixed size `v`.
pub(crate) fn fixed(v: usize) -> tensor_shape_proto::Dimension {
    tensor_shape_proto::Dimension {
        denotation: None,
        value: Some(tensor_shape_proto::dimension::Value::DimValue(v as i64)),
    }
}

/// A float tensor's name, dimensions and description.
pub(crate) fn value_info(
    name: &str,
    dims: Vec<tensor_shape_proto::Dimension>,
    doc: &str,
) -> ValueInfoProto {
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
pub(crate) fn graph_inputs(cfg: &Config) -> Vec<ValueInfoProto> {
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
pub(crate) fn graph_outputs() -> Vec<ValueInfoProto> {
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
pub(crate) fn model_proto(cfg: &Config, graph: GraphProto, opset: i64) -> Result<ModelProto> {
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

pub(crate) fn attr_int(name: &str, v: i64) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::Int as i32),
        i: Some(v),
        ..Default::default()
    }
}

pub(crate) fn attr_ints(name: &str, v: &[i64]) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::Ints as i32),
        ints: v.to_vec(),
        ..Default::default()
    }
}

pub(crate) fn attr_str(name: &str, v: &str) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::String as i32),
        s: Some(v.as_bytes().to_vec()),
        ..Default::default()
    }
}

pub(crate) fn attr_tensor(name: &str, t: TensorProto) -> AttributeProto {
    AttributeProto {
        name: Some(name.into()),
        r#type: Some(AttributeType::Tensor as i32),
        t: Some(t),
        ..Default::default()
    }
}

pub(crate) fn f32_tensor(name: &str, dims: &[usize], values: &[f32]) -> TensorProto {
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: Some(DataType::Float as i32),
        name: Some(name.into()),
        raw_data: Some(values.iter().flat_map(|v| v.to_le_bytes()).collect()),
        ..Default::default()
    }
}

pub(crate) fn i64_tensor(name: &str, values: &[i64]) -> TensorProto {
    TensorProto {
        dims: vec![values.len() as i64],
        data_type: Some(DataType::Int64 as i32),
        name: Some(name.into()),
        raw_data: Some(values.iter().flat_map(|v| v.to_le_bytes()).collect()),
        ..Default::default()
    }
}
