//! DeepStereo: learned view synthesis from posed images (Flynn et al., CVPR 2016).
//!
//! Geometry (cameras, homographies, plane sweeps) is f64 on the CPU with no candle types;
//! tensors appear only at the edge, in [`model`] and the modules that feed it.

pub mod alloc;
pub mod camera;
pub mod error;
pub mod imageio;
pub mod scene;

pub use error::{Error, Result};
pub mod backend;
pub mod baseline;
pub mod config;
pub mod conv;
mod cpu;
pub mod features;
pub mod fused;
pub mod geometry;
pub mod inputs;
pub mod metrics;
pub mod model;
pub mod mpi;
pub mod plot;
pub mod pool;
pub mod prior;
pub mod prune;
pub mod render;
pub mod sweep;
pub mod synth;
pub mod tensorio;
pub mod view_weights;
pub mod viz;
pub mod weights;
