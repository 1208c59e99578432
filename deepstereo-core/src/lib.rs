//! DeepStereo: learned view synthesis from posed images (Flynn et al., CVPR 2016).
//!
//! Geometry (cameras, homographies, plane sweeps) is f64 on the CPU with no candle types;
//! tensors appear only at the edge, in [`model`] and the modules that feed it.

pub mod camera;
pub mod error;
pub mod imageio;
pub mod scene;

pub use error::{Error, Result};
pub mod geometry;
pub mod sweep;
pub mod config;
pub mod conv;
pub mod model;
pub mod inputs;
pub mod render;
pub mod tensorio;
pub mod weights;
pub mod metrics;
pub mod baseline;
pub mod viz;
pub mod plot;
pub mod synth;
pub mod prune;
