//! Subcommands of the `deepstereo` binary, one module each, and the options they share.

pub mod curve;
pub mod demo;
pub mod eval;
pub mod export;
pub mod forward;
pub mod inspect;
pub mod model_args;
pub mod poses;
pub mod poses_masks;
pub mod render;
pub mod report;
pub mod report_html;
pub mod samples;
pub mod sampling_args;
pub mod shutter_json;
pub mod sweep;
pub mod synth;
pub mod train;
pub mod tune;

use clap::{Args, Parser, Subcommand};
use deepstereo_core::scene::{LoadOptions, Scene, SceneFormat};
use std::path::PathBuf;

/// DeepStereo: learned view synthesis from posed images.
#[derive(Debug, Parser)]
#[command(name = "deepstereo", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Print a scene's detected format, cameras and depth bounds.
    Inspect(inspect::Args),
    /// Build the plane-sweep volume of one target view and write it as safetensors.
    Sweep(sweep::Args),
    /// Train a model on procedural and/or real scenes.
    Train(train::Args),
    /// Render new views of a scene with a model: a view, a posed camera, or a path.
    Render(render::Args),
    /// Score held-out views against the photographs and the classical baselines.
    Eval(eval::Args),
    /// Everything with no files: a procedural scene, a held-out view, the embedded model.
    Demo(demo::Args),
    /// Error against run time over a grid of settings: CSV, markdown table and plot.
    Report(report::Args),
    /// Write the network as ONNX (opset 17+, dynamic planes and size, weights as initializers).
    Export(export::Args),
    /// Run the network (candle or onnxruntime) on input tensors from a safetensors file.
    Forward(forward::Args),
    /// Write procedural posed scenes (images, exact depths, transforms.json) for training.
    Synth(synth::Args),
    /// Find camera poses for a folder of photographs with COLMAP; writes a COLMAP scene.
    Poses(poses::Args),
    /// Write the trainer's samples as numbered safetensors shards (for train_ddp.py).
    Samples(samples::Args),
    /// Plot a run's log.jsonl: training loss and validation PSNR against steps.
    Curve(curve::Args),
    /// Fine-tune a model on one scene by leaving one view out; writes a model for --model.
    Tune(tune::Args),
}

/// Runs one parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Inspect(a) => inspect::run(a),
        Command::Sweep(a) => sweep::run(a),
        Command::Train(a) => train::run(a),
        Command::Render(a) => render::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Report(a) => report::run(a),
        Command::Export(a) => export::run(a),
        Command::Forward(a) => forward::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Poses(a) => poses::run(a),
        Command::Samples(a) => samples::run(a),
        Command::Curve(a) => curve::run(a),
        Command::Tune(a) => tune::run(a),
    }
}

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

/// Scene directories under `dir`: `dir` itself when it is a scene, else its immediate
/// subdirectories that are (sorted), e.g. the output of `deepstereo synth`.
pub fn scene_dirs(dir: &std::path::Path) -> anyhow::Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        anyhow::bail!("{}: not a directory", dir.display());
    }
    if deepstereo_core::scene::detect(dir).is_ok() {
        return Ok(vec![dir.to_path_buf()]);
    }
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir() && deepstereo_core::scene::detect(p).is_ok())
        .collect();
    out.sort();
    if out.is_empty() {
        anyhow::bail!(
            "{}: neither a scene nor a directory of scenes",
            dir.display()
        );
    }
    Ok(out)
}
