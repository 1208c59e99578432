//! `--scene` and the options of how to read it: shared by every command that reads a scene.

use clap::Args;
use deepstereo_core::scene::{LoadOptions, Scene, SceneFormat};
use std::path::PathBuf;

/// How to read a scene: shared by every command that takes `--scene`.
#[derive(Debug, Clone, Args)]
pub struct SceneArgs {
    /// Scene directory (LLFF, COLMAP, NeRF/instant-ngp or Middlebury; detected).
    #[arg(long)]
    pub scene: PathBuf,
    /// Force the scene format instead of detecting it: llff, colmap, nerf, middlebury.
    #[arg(long)]
    pub format: Option<SceneFormat>,
    /// LLFF: read images from `images_<FACTOR>/` (default: `images/`, else the smallest).
    #[arg(long)]
    pub factor: Option<u32>,
    /// Nearest depth of the planes (overrides the scene's bounds).
    #[arg(long)]
    pub near: Option<f64>,
    /// Farthest depth of the planes; `inf` for a plane at infinity.
    #[arg(long)]
    pub far: Option<f64>,
    /// Read the images at 1/N resolution (N a power of two), intrinsics scaled to match.
    #[arg(long)]
    pub downscale: Option<u32>,
    /// Ignore rolling shutters: every camera is a global shutter at its mid-readout pose
    /// (the pose `inspect` prints), as a shutter-unaware reader would see the scene.
    #[arg(long)]
    pub ignore_rolling_shutter: bool,
}

impl SceneArgs {
    /// Loads the scene, printing the reader's notes to stderr.
    pub fn load(&self) -> anyhow::Result<Scene> {
        let opts = LoadOptions {
            format: self.format,
            factor: self.factor,
            near: self.near,
            far: self.far,
            downscale: self.downscale,
            ignore_rolling_shutter: self.ignore_rolling_shutter,
        };
        let scene = Scene::load(&self.scene, &opts)?;
        for n in &scene.notes {
            eprintln!("note: {n}");
        }
        Ok(scene)
    }
}
