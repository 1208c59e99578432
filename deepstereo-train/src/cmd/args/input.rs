//! A scene, the model run on it and the views held out: shared by the commands that score
//! or bake a scene's views (`eval`, `report`, `tune`, `mpi`).

use super::{HoldoutArgs, ModelArgs, SceneArgs};

/// `--scene` with how to read it, `--model` with how to run it, and `--holdout` /
/// `--llffhold`.
#[derive(Debug, clap::Args)]
pub struct SceneModelArgs {
    /// The scene (its views: the sources, the targets, the held-out views).
    #[command(flatten)]
    pub scene: SceneArgs,
    /// The model, and how it renders.
    #[command(flatten)]
    pub model: ModelArgs,
    /// The held-out views.
    #[command(flatten)]
    pub holdout: HoldoutArgs,
}
