//! `--scene` and the options of how to read it: shared by every command that reads a scene.

use clap::Args;
use deepstereo_core::scene::{LoadOptions, Scene, SceneFormat, WORKING_SIDE};
use std::path::PathBuf;

/// How to read a scene: shared by every command that takes `--scene`.
#[derive(Debug, Clone, Args)]
pub struct SceneArgs {
    /// Scene directory (LLFF, COLMAP, NeRF/instant-ngp or Middlebury; detected).
    #[arg(long)]
    pub scene: PathBuf,
    /// Force the scene format instead of detecting it: llff, colmap, nerf, middlebury.
    #[arg(long, help_heading = super::EXPERT)]
    pub format: Option<SceneFormat>,
    /// LLFF: read images from `images_<FACTOR>/` (default: `images/`, else the smallest).
    #[arg(long, help_heading = super::EXPERT)]
    pub factor: Option<u32>,
    /// Nearest depth of the planes (overrides the scene's bounds).
    #[arg(long)]
    pub near: Option<f64>,
    /// Farthest depth of the planes; `inf` for a plane at infinity.
    #[arg(long)]
    pub far: Option<f64>,
    /// Read the images at 1/N resolution (N a power of two), intrinsics scaled to match.
    /// Commands that run the network default to the working resolution: the smallest N
    /// that brings the images' larger side to at most 1024 px (a note says which);
    /// `--downscale 1` reads them whole.
    #[arg(long)]
    pub downscale: Option<u32>,
    /// Ignore rolling shutters: every camera is a global shutter at its mid-readout pose
    /// (the pose `inspect` prints), as a shutter-unaware reader would see the scene.
    #[arg(long, help_heading = super::EXPERT)]
    pub ignore_rolling_shutter: bool,
    /// Read images (and model files) that the scene's files name outside the scene
    /// directory, after resolving `..` and symbolic links. By default they are refused
    /// unread: a scene from elsewhere cannot make a command read your other files.
    #[arg(long, help_heading = super::EXPERT)]
    pub allow_outside_paths: bool,
}

impl SceneArgs {
    /// The reader's options these flags give.
    pub fn options(&self) -> LoadOptions {
        LoadOptions {
            format: self.format,
            factor: self.factor,
            near: self.near,
            far: self.far,
            downscale: self.downscale,
            ignore_rolling_shutter: self.ignore_rolling_shutter,
            allow_outside_paths: self.allow_outside_paths,
            max_side: None,
        }
    }

    /// [`Self::options`] at the working resolution of the commands that run the network:
    /// without `--downscale`, the larger side at most [`WORKING_SIDE`] pixels.
    pub fn working_options(&self) -> LoadOptions {
        LoadOptions {
            max_side: Some(WORKING_SIDE),
            ..self.options()
        }
    }

    /// Loads the scene at the working resolution ([`Self::working_options`]), printing the
    /// reader's notes.
    pub fn load_working(&self) -> anyhow::Result<Scene> {
        self.load_with(&self.working_options())
    }

    /// Loads the scene, printing the reader's notes to stderr.
    pub fn load(&self) -> anyhow::Result<Scene> {
        self.load_with(&self.options())
    }

    /// Loads the scene with `opts`, printing the reader's notes to stderr.
    fn load_with(&self, opts: &LoadOptions) -> anyhow::Result<Scene> {
        let scene = Scene::load(&self.scene, opts)?;
        for n in &scene.notes {
            eprintln!("note: {n}");
        }
        Ok(scene)
    }
}
