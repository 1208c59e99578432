//! A scene and the model run on it: shared by the commands that score or bake a scene's
//! views (`eval`, `report`, `tune`, `mpi`).

use super::{ModelArgs, SceneArgs};

/// `--scene` with how to read it, and `--model` with how to run it.
#[derive(Debug, clap::Args)]
pub struct SceneModelArgs {
    /// The scene (its views: the sources, the targets, the held-out views).
    #[command(flatten)]
    pub scene: SceneArgs,
    /// The model, and how it renders.
    #[command(flatten)]
    pub model: ModelArgs,
}
