//! ONNX export of the DeepStereo network and an onnxruntime ([`ort`]) backend.
//!
//! - [`export()`] writes the network as an ONNX model (opset 17 or newer) whose graph mirrors
//!   [`deepstereo_core::model::DeepStereo::forward`] op for op: inputs `level0..` are the
//!   plane-sweep tensors `[B, D, 4V, H_l, W_l]` (batch, planes and spatial size dynamic),
//!   outputs `image` `[B, 3, th, tw]` and `selection` `[B, D, th, tw]`, the weights are
//!   initializers named as in the safetensors file.
//! - [`export_features`] writes the `features` family's per-source CNN as a second model
//!   (`NAME.features.onnx`): input `image` `[N, 3, H + 2R, W + 2R]`, output `features`
//!   `[N, F, H, W]`, run once per source image and level; the network's inputs then carry
//!   its warped output after each view's RGBA and cue.
//! - [`OrtBackend`] runs such a file through onnxruntime, loaded at run time
//!   (`ORT_DYLIB_PATH`, or the `onnxruntime` wheel in the project's `.venv`).
//!
//! The protobuf structs in [`onnx_proto`] are generated from the `onnx.proto` of the pinned
//! `onnx` Python package by `proto/regen.sh` and committed: building needs no protoc.

pub mod error;
pub mod export;
pub mod ort_backend;

#[allow(
    clippy::all,
    clippy::pedantic,
    missing_docs,
    rustdoc::all,
    non_camel_case_types
)]
pub mod onnx_proto;

pub use error::{Error, Result};
pub use export::{
    build_features_model, export, export_features, export_trainable, features_path, input_name,
    model_weights, read_config, Weight, DEFAULT_OPSET, MAX_OPSET, MIN_OPSET,
};
pub use ort_backend::{find_onnxruntime, Forward, OrtBackend};
