//! `deepstereo train`: train a model on procedural and/or real scenes.

use super::args::{load_config, size_of, SamplingArgs};
use crate::training::data::MpiPairs;
use crate::training::lr::{LrSchedule, DEFAULT_LR_FINAL};
use crate::training::optim::OptimizerKind;
use crate::training::{train, Loss, RunOptions, Schedule};
use anyhow::bail;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Scene directories to train on (any readable format), or directories of scenes
    /// such as `deepstereo synth` writes. May be repeated and combined with --synthetic.
    #[arg(long, num_args = 1..)]
    pub data: Vec<PathBuf>,
    /// Also generate this many procedural scenes in memory (seeded by --seed).
    #[arg(long, default_value_t = 0)]
    pub synthetic: usize,
    /// Model config: a preset (`tiny`, `paper`, `nviews`) or a JSON file of a Config.
    #[arg(long, default_value = "tiny")]
    pub config: String,
    /// Total optimizer steps (a resumed run continues up to this count).
    #[arg(long, default_value_t = 1000)]
    pub steps: u64,
    /// Samples (tiles) per minibatch, mixed across scenes and views.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Run directory: model.safetensors, checkpoint.safetensors, log.jsonl.
    #[arg(long)]
    pub out: PathBuf,
    /// Continue the run in --out from its checkpoint (same options required).
    #[arg(long)]
    pub resume: bool,
    /// Initial learning rate (the paper's Adagrad rate is 5e-4).
    #[arg(long, default_value_t = 5e-4)]
    pub lr: f64,
    /// Optimizer: adagrad (the paper's) or adam.
    #[arg(long, value_parser = super::args::choice::<OptimizerKind>(), default_value = "adagrad")]
    pub optimizer: OptimizerKind,
    /// Seed of the data order and the procedural scenes.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write a checkpoint every this many steps (and at the end, and on Ctrl-C).
    #[arg(long, default_value_t = 100)]
    pub checkpoint_every: u64,
    /// Compute validation PSNR every this many steps.
    #[arg(long, default_value_t = 100)]
    pub validate_every: u64,
    /// Write a log line every this many steps.
    #[arg(long, default_value_t = 10)]
    pub log_every: u64,
    /// Procedural validation scenes (seeds disjoint from training).
    #[arg(long, default_value_t = 8)]
    pub val_scenes: usize,
    /// Validation minibatches (fixed for the whole run).
    #[arg(long, default_value_t = 4)]
    pub val_batches: usize,
    /// Size of procedural scenes' images, WxH.
    #[arg(long, default_value = "160x120")]
    pub synth_size: String,
    /// Views per procedural scene.
    #[arg(long, default_value_t = 10)]
    pub synth_views: usize,
    /// Print log lines instead of a progress bar (the default when standard error is
    /// not a terminal).
    #[arg(long)]
    pub no_progress: bool,
    /// Scene directories to validate on (never trained on), beside the procedural
    /// validation scenes.
    #[arg(long, num_args = 1..)]
    pub val_data: Vec<PathBuf>,
    /// Learning rate against the step: `constant`, or `cosine:START-END` (the initial
    /// rate up to step START, a cosine down to `--lr-final` times it at step END). A
    /// resumed run may add or change it.
    #[arg(long, default_value = "constant")]
    pub lr_schedule: String,
    /// The final rate's share of --lr for a decaying --lr-schedule.
    #[arg(long, default_value_t = DEFAULT_LR_FINAL)]
    pub lr_final: f64,
    /// Start from the weights of this model file instead of a random initialisation
    /// (fine-tuning; its tensors must have the names and shapes of --config). The
    /// optimizer starts afresh; a resume passes it again and continues from the checkpoint.
    #[arg(long)]
    pub init: Option<std::path::PathBuf>,
    /// Training loss: l1 (the paper's mean absolute error) or l2 (mean squared error).
    #[arg(long, value_parser = super::args::choice::<Loss>(), default_value = "l1")]
    pub loss: Loss,
    /// How samples are drawn.
    #[command(flatten)]
    pub sampling: SamplingArgs,
    /// Train for MPIs: besides its own loss, each sample's layers, made a multiplane
    /// image, are rendered at a neighbouring view (never a source) and compared with its
    /// photograph; this weighs that loss (e.g. 1). Samples are then `--mpi-tile` tiles.
    #[arg(long)]
    pub mpi_loss: Option<f32>,
    /// With --mpi-loss: the size of the reference tile and the target crop, WxH pixels
    /// (a target pixel counts when its ray meets every plane inside the tile: wide tiles
    /// for the sideways motion of most captures).
    #[arg(long, default_value = "224x64")]
    pub mpi_tile: String,
    /// With --mpi-loss: the target is one of the reference's N nearest views.
    #[arg(long, default_value_t = 2)]
    pub mpi_neighbours: usize,
    /// With --mpi-loss: draw the pairs from the images downscaled by this factor (1 or
    /// 2): at 2 the same tile spans twice the disparity, for pairs as far apart as a
    /// held-out view and its nearest kept one.
    #[arg(long, default_value_t = 1)]
    pub mpi_scale: u32,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let (w, h) = size_of("--synth-size", &a.synth_size)?;
    let (tile_w, tile_h) = size_of("--mpi-tile", &a.mpi_tile)?;
    for (name, v) in [
        ("--checkpoint-every", a.checkpoint_every),
        ("--validate-every", a.validate_every),
        ("--log-every", a.log_every),
    ] {
        if v == 0 {
            bail!("{name} must be at least 1");
        }
    }
    let run = RunOptions {
        config: load_config(&a.config)?,
        data: a.data,
        synthetic: a.synthetic,
        synth_width: w,
        synth_height: h,
        synth_views: a.synth_views,
        batch: a.batch,
        lr: a.lr,
        optimizer: a.optimizer,
        seed: a.seed,
        val_scenes: a.val_scenes,
        val_batches: a.val_batches,
        views: a.sampling.views_range()?,
        val_data: a.val_data,
        synthetic_percent: a.sampling.synthetic_percent,
        augment: a.sampling.augment,
        lr_schedule: LrSchedule::parse(&a.lr_schedule, a.lr_final)?,
        init: a.init,
        loss: a.loss,
        view_stride: a.sampling.view_stride_range()?,
        skip_flat: a.sampling.skip_flat,
        scene_weights: a.sampling.weights()?,
        mpi_loss: a.mpi_loss.map(|weight| MpiPairs {
            weight,
            tile: (tile_w as usize, tile_h as usize),
            neighbours: a.mpi_neighbours,
            scale: a.mpi_scale,
        }),
    };
    let sched = Schedule {
        steps: a.steps,
        checkpoint_every: a.checkpoint_every,
        validate_every: a.validate_every,
        log_every: a.log_every,
        // A progress bar on a terminal, plain lines in a log file or a pipe.
        progress: !a.no_progress && std::io::IsTerminal::is_terminal(&std::io::stderr()),
    };
    // The first Ctrl-C sets the flag (a checkpoint is written); a second one aborts.
    let stop = crate::cmd::support::interrupt::graceful();
    let lines = train(&run, &sched, &a.out, a.resume, stop)?;
    if let Some(last) = lines.last() {
        let num = |v: Option<f64>, digits: usize| {
            v.map_or_else(|| "-".to_string(), |x| format!("{x:.digits$}"))
        };
        let val = lines.iter().rev().find_map(|l| l.val_psnr);
        eprintln!(
            "step {}: loss {}, last validation PSNR {} dB",
            last.step,
            num(last.loss, 5),
            num(val, 2)
        );
    }
    eprintln!("model: {}", a.out.join("model.safetensors").display());
    Ok(())
}
