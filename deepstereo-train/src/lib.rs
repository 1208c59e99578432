//! DeepStereo training, evaluation and the `deepstereo` command line.
//!
//! Kept apart as in burn's examples: [`data`] (scenes and the online sampler),
//! [`optim`] (Adagrad, Adam), [`training`] (the loop), [`cmd`] (the subcommands).

pub use deepstereo_core::alloc;
pub mod camera_json;
pub mod cmd;
pub mod colmap_run;
pub mod data;
pub mod inference;
pub mod interrupt;
pub mod lr;
pub mod models;
pub mod mpi;
pub mod optim;
pub mod outdir;
pub mod path;
pub mod prior;
pub mod scene_weights;
#[cfg(test)]
mod test_scene;
pub mod training;
pub mod tune;
pub mod tune_plan;
pub mod video;
