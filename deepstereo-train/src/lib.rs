//! DeepStereo training, tuning, rendering with a model, and the `deepstereo` command line,
//! one role a folder (as in burn's examples: model, data, training and inference apart):
//!
//! - [`training`]: the training loop, its data (scenes and the online sampler),
//!   optimisers, learning-rate schedules and scene weights. Uses `deepstereo-core`.
//! - [`tuning`]: `tune`, its planning, and the scene prior's fit. Uses training's
//!   optimisers and data, and rendering.
//! - [`rendering`]: rendering with a model (source choice, render settings, the MPI
//!   bake, camera paths, the embedded model, a view's plane-sweep volume and network
//!   inputs). Uses `deepstereo-core` (and `deepstereo-export` for the ort backend and
//!   the inputs' names).
//! - [`cmd`]: the command line: one file a command, the flags they share (`cmd/args`),
//!   and the helpers only commands use (`cmd/support`: camera JSON, the COLMAP runner,
//!   videos, output directories, interruption). The roles above never import it.

pub use deepstereo_core::alloc;
pub mod cmd;
pub mod rendering;
#[cfg(test)]
mod test_scene;
pub mod training;
pub mod tuning;
