//! Subcommands of the `deepstereo` binary, one module each, and the options they share
//! ([`args`]). A command uses [`args`] and the library, never another command; a command's
//! own helpers are its submodules (`report::html`, `poses::masks`).

pub mod args;
pub mod curve;
pub mod demo;
pub mod eval;
pub mod export;
pub mod forward;
pub mod inspect;
pub mod mpi;
pub mod poses;
pub mod render;
pub mod report;
pub mod samples;
pub mod support;
pub mod sweep;
pub mod synth;
pub mod train;
pub mod tune;

use clap::{Parser, Subcommand};

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
    /// Bake multiplane images with the network, with a browser viewer (or --eval: held-out
    /// views through them). Without --views, models that take any number of views bake
    /// from 8 sources (fewer where the scene has fewer), and --eval's network renders use
    /// the model's own default.
    Mpi(mpi::Args),
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
        Command::Mpi(a) => mpi::run(a),
    }
}
