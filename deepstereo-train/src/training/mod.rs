//! Training (role): the loop below, its data ([`data`]: scenes and the online sampler),
//! optimisers ([`optim`]), learning-rate schedules ([`lr`]) and scene weights
//! ([`scene_weights`]). Uses `deepstereo-core`; never the command line.
//!
//! The training loop: L1 loss (or L2, `--loss l2`), Adagrad or Adam, a JSONL log,
//! validation PSNR, atomic checkpoints (periodic and on Ctrl-C), exact resume, and a guard
//! against non-finite losses and gradients.
//!
//! Files in the run directory: `model.safetensors` (weights + config, what `render` loads),
//! `checkpoint.safetensors` (weights, optimizer state, step, run options), `log.jsonl`.

mod checkpoint;
pub mod data;
pub mod lr;
pub mod optim;
mod progress;
pub mod scene_weights;
mod scenes;

pub use checkpoint::save_checkpoint;
use checkpoint::{restore, truncate_log};
pub use progress::plot_log;
use progress::{progress_bar, show_line};
use scenes::load_scenes;
pub use scenes::{check_data, procedural_batch, synth_options, training_scenes};

use crate::training::data::{spawn_loader, Batch, MpiPairs, PairBatch, Sampling};
use crate::training::lr::LrSchedule;
use crate::training::optim::{Optimizer, OptimizerKind};
use crate::training::scene_weights::SceneWeights;
use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use deepstereo_core::config::Config;
use deepstereo_core::imageio::write_atomic;
use deepstereo_core::inputs::features::warped_features;
use deepstereo_core::model::{l1_loss, l2_loss};
use deepstereo_core::weights::{self, named_vars, Trainable};
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// Consecutive non-finite steps after which training stops.
pub const MAX_CONSECUTIVE_BAD_STEPS: u32 = 5;
/// Metadata key of the run options in a checkpoint.
pub const RUN_KEY: &str = "deepstereo.run";
/// Metadata key of the step count in a checkpoint.
pub const STEP_KEY: &str = "deepstereo.step";

/// The training loss on the rendered tile.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Loss {
    /// Mean absolute error (the paper's).
    #[default]
    L1,
    /// Mean squared error.
    L2,
}

impl Loss {
    /// The loss of `pred` against `target` (same shapes), a scalar.
    pub fn of(self, pred: &Tensor, target: &Tensor) -> candle_core::Result<Tensor> {
        match self {
            Loss::L1 => l1_loss(pred, target),
            Loss::L2 => l2_loss(pred, target),
        }
    }
}

/// Everything that defines a training run (saved in checkpoints; a resume must match).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunOptions {
    pub config: Config,
    pub data: Vec<PathBuf>,
    pub synthetic: usize,
    pub synth_width: u32,
    pub synth_height: u32,
    pub synth_views: usize,
    pub batch: usize,
    pub lr: f64,
    pub optimizer: OptimizerKind,
    pub seed: u64,
    pub val_scenes: usize,
    pub val_batches: usize,
    /// Source views per batch, a range (`None`: the config's).
    #[serde(default)]
    pub views: Option<(usize, usize)>,
    /// Scenes validated on (never trained on), beside the procedural validation scenes.
    #[serde(default)]
    pub val_data: Vec<PathBuf>,
    /// Percent of samples from procedural scenes when real ones are there too.
    #[serde(default)]
    pub synthetic_percent: Option<u32>,
    /// Photometric augmentation and flips.
    #[serde(default)]
    pub augment: bool,
    /// The learning rate against the step (a resume may change it).
    #[serde(default)]
    pub lr_schedule: LrSchedule,
    /// The model file the weights started from (`None`: a seeded random initialisation).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init: Option<PathBuf>,
    /// The loss (runs before it was an option trained with L1).
    #[serde(default)]
    pub loss: Loss,
    /// Source stride range (`None`: the nearest views, as runs before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub view_stride: Option<(usize, usize)>,
    /// Flat-tile threshold (`None`: every tile, as runs before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skip_flat: Option<f32>,
    /// Weights of named real scenes (`None`: every scene equally likely, as runs before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_weights: Option<SceneWeights>,
    /// The loss through the MPI renderer at a neighbouring view (`None`: the plain
    /// tiles, as runs before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mpi_loss: Option<MpiPairs>,
}

impl RunOptions {
    /// How training samples are drawn.
    pub fn sampling(&self) -> Sampling {
        Sampling {
            views: self.views.unwrap_or((self.config.views, self.config.views)),
            synthetic_percent: self.synthetic_percent,
            augment: self.augment,
            view_stride: self.view_stride.unwrap_or((1, 1)),
            skip_flat: self.skip_flat,
            scene_weights: self.scene_weights.clone().unwrap_or_default(),
            mpi: self.mpi_loss,
        }
    }
}

/// How long and how often.
#[derive(Clone, Debug)]
pub struct Schedule {
    pub steps: u64,
    pub checkpoint_every: u64,
    pub validate_every: u64,
    pub log_every: u64,
    pub progress: bool,
}

/// One line of `log.jsonl`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LogLine {
    pub step: u64,
    pub loss: Option<f64>,
    pub lr: f64,
    pub samples_per_s: f64,
    pub grad_norm: Option<f64>,
    pub val_psnr: Option<f64>,
    pub skipped: bool,
    pub seconds: f64,
    /// With `--mpi-loss`: the loss through the MPI renderer alone (unweighted), which
    /// `loss` includes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mpi_loss: Option<f64>,
}

/// Batch tensors on `device`: inputs per level and the target.
///
/// For the `features` family, the sources' feature maps are computed by the model's CNN
/// from the batch's crops and warped in the graph ([`warped_features`]), so the loss trains
/// the CNN too; they stay apart from the levels ([`BatchInputs`]).
pub fn batch_tensors(
    model: &deepstereo_core::model::DeepStereo,
    b: &Batch,
    device: &Device,
) -> Result<(BatchInputs, Tensor)> {
    let levels = b
        .levels
        .iter()
        .zip(&b.level_shapes)
        .map(|(d, s)| Tensor::from_slice(d, s.as_slice(), device))
        .collect::<candle_core::Result<Vec<_>>>()?;
    let features = match (model.feature_net(), &b.warps) {
        (Some(net), Some(warps)) => Some(warped_features(net, &levels, warps)?),
        (None, None) => None,
        _ => anyhow::bail!("a batch drawn for another model (source features differ)"),
    };
    let target = Tensor::from_slice(&b.target, b.target_shape.as_slice(), device)?;
    Ok((BatchInputs { levels, features }, target))
}

/// A batch's network inputs: the levels, and the features family's warped maps apart.
pub struct BatchInputs {
    pub levels: Vec<Tensor>,
    pub features: Option<Vec<Tensor>>,
}

impl BatchInputs {
    /// The model's training forward on these inputs.
    pub fn forward(
        &self,
        model: &deepstereo_core::model::DeepStereo,
    ) -> Result<deepstereo_core::model::Output> {
        Ok(model.forward_parts(&self.levels, self.features.as_deref())?)
    }
    /// The model's rendering forward (no gradients) on these inputs.
    pub fn infer(
        &self,
        model: &deepstereo_core::model::DeepStereo,
    ) -> Result<deepstereo_core::model::Output> {
        Ok(model.infer_parts(&self.levels, self.features.as_deref())?)
    }
}

/// Mean PSNR (dB, colours in [0, 1]) of the model over validation batches.
pub fn validate(
    model: &deepstereo_core::model::DeepStereo,
    batches: &[Batch],
    device: &Device,
) -> Result<f64> {
    psnr_of(batches, |b| {
        let (x, y) = batch_tensors(model, b, device)?;
        Ok((x.infer(model)?.image, y))
    })
}

/// The PSNR over `batches` of the images `render` gives (clamped to [0, 1]) against its
/// targets: `render(batch) = (image, target)`, both `[B, 3, t, t]`.
pub fn psnr_of(
    batches: &[Batch],
    mut render: impl FnMut(&Batch) -> Result<(Tensor, Tensor)>,
) -> Result<f64> {
    let (mut se, mut n) = (0f64, 0usize);
    for b in batches {
        let (image, y) = render(b)?;
        let d = image.clamp(0f32, 1f32)?.sub(&y)?;
        se += d.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
        n += d.elem_count();
    }
    Ok(psnr_from_mse(se / n.max(1) as f64))
}

/// PSNR in dB of a mean squared error for colours in [0, 1].
pub fn psnr_from_mse(mse: f64) -> f64 {
    -10.0 * mse.max(1e-12).log10()
}

/// Trains (or resumes) a run in `out`. Returns the log lines written in this call.
pub fn train(
    run: &RunOptions,
    sched: &Schedule,
    out: &Path,
    resume: bool,
    stop: Arc<AtomicBool>,
) -> Result<Vec<LogLine>> {
    let sampling = check_run(run)?;
    let device = Device::Cpu;
    let t = weights::init_seeded(&run.config, candle_core::DType::F32, &device, run.seed)?;
    let vars = named_vars(&t.varmap);
    let mut opt = Optimizer::new(run.optimizer, run.lr, vars)?;
    let ckpt = out.join("checkpoint.safetensors");
    let log_path = out.join("log.jsonl");
    let start = open_run(run, out, resume, &t, &mut opt)?;
    let t0 = Instant::now();
    let (train_scenes, val, n_val) = load_scenes(run)?;
    eprintln!(
        "{} training scenes, {} validation scenes ({:.1} s)",
        train_scenes.len(),
        n_val,
        t0.elapsed().as_secs_f64()
    );
    let rx = spawn_loader(
        run.config.clone(),
        sampling,
        Arc::new(train_scenes),
        run.seed,
        start,
        run.batch,
        2,
    );
    let mut log = StepLog::open(&log_path, progress_bar(sched, start), t0)?;
    let (mut bad, mut step) = (0u32, start);
    while step < sched.steps {
        let batch = rx.recv().context("the sample loader stopped")??;
        step += 1;
        log.window.1 += run.batch;
        let outcome = optimize(run, &t, &mut opt, &batch, &device, step)?;
        let skipped = outcome.3;
        bad = if skipped { bad + 1 } else { 0 };
        if bad >= MAX_CONSECUTIVE_BAD_STEPS {
            bail!("{bad} consecutive non-finite steps: training stopped; the last good checkpoint is {}", ckpt.display());
        }
        let validate_now = step.is_multiple_of(sched.validate_every) || step == sched.steps;
        if step.is_multiple_of(sched.log_every) || validate_now || skipped {
            let val_psnr = || {
                (validate_now)
                    .then(|| validate(&t.model, &val, &device))
                    .transpose()
            };
            log.write((run, sched), step, outcome, opt.lr, val_psnr)?;
        }
        log.bar.set_position(step);
        let stopping = stop.load(Ordering::SeqCst);
        if step.is_multiple_of(sched.checkpoint_every) || step == sched.steps || stopping {
            save_checkpoint(&ckpt, &out.join("model.safetensors"), run, &t, &opt, step)?;
        }
        if stopping {
            eprintln!("interrupted: checkpoint saved at step {step}; continue with --resume");
            break;
        }
    }
    if step == 0 {
        // `--steps 0`: write the initial model (used to make weights for tests and parity).
        save_checkpoint(&ckpt, &out.join("model.safetensors"), run, &t, &opt, 0)?;
    }
    log.bar.finish();
    plot_log(&log_path, &out.join("curve.png"))?;
    Ok(log.lines)
}

/// A run's log as its steps write it: `log.jsonl`, the lines written in this call, the
/// progress bar, the samples since the last line and when that line was written (the
/// throughput), and when the run started.
struct StepLog {
    file: std::fs::File,
    lines: Vec<LogLine>,
    bar: indicatif::ProgressBar,
    window: (Instant, usize),
    t0: Instant,
}

impl StepLog {
    /// Appends to the log at `path`.
    fn open(path: &Path, bar: indicatif::ProgressBar, t0: Instant) -> Result<Self> {
        let file = std::fs::OpenOptions::new()
            .append(true)
            .create(true)
            .open(path)?;
        Ok(Self {
            file,
            lines: Vec::new(),
            bar,
            window: (Instant::now(), 0),
            t0,
        })
    }

    /// Writes and shows step `step`'s line from its [`optimize`] outcome, the rate `lr`
    /// and the validation PSNR `val_psnr()` gives (when due).
    fn write(
        &mut self,
        (run, sched): (&RunOptions, &Schedule),
        step: u64,
        (loss_v, mpi_v, gnorm, skipped): (f64, Option<f64>, f64, bool),
        lr: f64,
        val_psnr: impl FnOnce() -> Result<Option<f64>>,
    ) -> Result<()> {
        let secs = self.window.0.elapsed().as_secs_f64();
        let line = LogLine {
            step,
            loss: loss_v.is_finite().then_some(loss_v),
            lr,
            samples_per_s: self.window.1 as f64 / secs.max(1e-9),
            grad_norm: gnorm.is_finite().then_some(gnorm),
            val_psnr: val_psnr()?,
            skipped,
            seconds: self.t0.elapsed().as_secs_f64(),
            mpi_loss: mpi_v.filter(|v| v.is_finite()),
        };
        writeln!(self.file, "{}", serde_json::to_string(&line)?)?;
        self.file.flush()?;
        show_line(&self.bar, sched, run, loss_v, &line);
        self.lines.push(line);
        self.window = (Instant::now(), 0);
        Ok(())
    }
}

/// The run's options checked (config, batch, sampling, data and scene weights) before
/// anything is written or loaded; its sampling.
fn check_run(run: &RunOptions) -> Result<Sampling> {
    run.config.validate().map_err(anyhow::Error::msg)?;
    if run.batch == 0 {
        bail!("--batch must be at least 1");
    }
    let sampling = run.sampling();
    sampling.check(&run.config)?;
    if let Some(p) = run.mpi_loss.filter(|_| run.synthetic > 0) {
        let (w, h) = p.tile;
        let s = p.scale.max(1) as usize;
        if (run.synth_width as usize) < w * s || (run.synth_height as usize) < h * s {
            bail!(
                "the procedural scenes' images ({}x{}) are smaller than the {w}x{h} MPI tile at scale {s}: pass a larger --synth-size or a smaller --mpi-tile",
                run.synth_width,
                run.synth_height
            );
        }
    }
    check_data(&run.data, run.scene_weights.as_ref())?;
    Ok(sampling)
}

/// Readies the run directory `out`: with `resume`, restores the checkpoint into the model
/// and the optimizer and cuts the log back to it; else refuses a directory that holds a
/// checkpoint, loads `--init`'s weights, and creates the directory and an empty log.
/// Returns the step to start at.
fn open_run(
    run: &RunOptions,
    out: &Path,
    resume: bool,
    t: &Trainable,
    opt: &mut Optimizer,
) -> Result<u64> {
    let ckpt = out.join("checkpoint.safetensors");
    let log_path = out.join("log.jsonl");
    if resume {
        let start = restore(&ckpt, run, t, opt)?;
        truncate_log(&log_path, start)?;
        eprintln!("resuming {} at step {start}", out.display());
        return Ok(start);
    }
    if ckpt.exists() {
        bail!(
            "{} already holds a checkpoint: pass --resume to continue it, or choose another --out",
            out.display()
        );
    }
    if let Some(init) = &run.init {
        let bytes = std::fs::read(init)
            .with_context(|| format!("--init: cannot read {}", init.display()))?;
        let st = safetensors::SafeTensors::deserialize(&bytes).map_err(|e| {
            anyhow::anyhow!("--init {}: not a safetensors file: {e}", init.display())
        })?;
        weights::assign(init, &st, &t.varmap, "")?;
        eprintln!("starting from the weights of {}", init.display());
    }
    // Created only now: options and --init that are refused leave nothing behind.
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    write_atomic(&log_path, b"")?;
    Ok(0)
}

/// Step `step` on `batch`: the loss, its part through the MPI renderer (unweighted; with
/// `--mpi-loss`), the gradient norm, and whether the step was skipped (a non-finite loss
/// or gradient norm; the weights are then left as they are).
fn optimize(
    run: &RunOptions,
    t: &Trainable,
    opt: &mut Optimizer,
    batch: &Batch,
    device: &Device,
    step: u64,
) -> Result<(f64, Option<f64>, f64, bool)> {
    let (x, y) = batch_tensors(&t.model, batch, device)?;
    let pred = x.forward(&t.model)?;
    let mut loss = run.loss.of(&pred.image, &y)?;
    let mut mpi_v = None;
    if let (Some(pairs), Some(p)) = (&run.mpi_loss, &batch.mpi) {
        let m = mpi_loss(&pred, p, device)?;
        mpi_v = Some(m.to_scalar::<f32>()? as f64);
        loss = (loss + (m * pairs.weight as f64)?)?;
    }
    let loss_v = loss.to_scalar::<f32>()? as f64;
    let grads = loss.backward()?;
    let gnorm = opt.grad_norm(&grads)?;
    let skipped = !(loss_v.is_finite() && gnorm.is_finite());
    if skipped {
        eprintln!("step {step}: non-finite loss {loss_v} or gradient norm {gnorm}: step skipped");
    } else {
        opt.lr = run.lr_schedule.lr_at(run.lr, opt.steps);
        opt.step(&grads)?;
    }
    Ok((loss_v, mpi_v, gnorm, skipped))
}

/// The L1 loss of the network's layers `pred` (at the reference tiles), made MPIs and
/// rendered at the pair batch's target crops, over the pixels that see the tile on every
/// plane ([`deepstereo_core::mpi::warp`]).
fn mpi_loss(
    pred: &deepstereo_core::model::Output,
    p: &PairBatch,
    device: &Device,
) -> Result<Tensor> {
    use deepstereo_core::mpi::warp::{masked_l1, plan_tensors, render_warped};
    let (b, d, th, tw) = pred.selection.dims4()?;
    let sel = pred.selection.reshape((b, d, th * tw))?; // [B, D, N_r]
    let col = pred.colours.reshape((b, d, 3, th * tw))?; // [B, D, 3, N_r]
    let plans: Vec<_> = p.plans.iter().collect();
    let (index, weight, mask) = plan_tensors(&plans, th * tw, sel.dtype(), device)?;
    let out = render_warped(&sel, &col, &index, &weight)?; // [B, 3, N_t]
    let target = Tensor::from_slice(&p.target, (b, 3, p.pixels), device)?;
    Ok(masked_l1(&out, &target, &mask)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn losses_match_hand_computed_values() -> Result<()> {
        let dev = Device::Cpu;
        let p = Tensor::new(&[0.5f32, 0.25, 1.0, 0.0], &dev)?;
        let y = Tensor::new(&[0.0f32, 0.5, 1.0, 0.5], &dev)?;
        // |d| = 0.5, 0.25, 0, 0.5; d^2 = 0.25, 0.0625, 0, 0.25.
        assert_eq!(Loss::L1.of(&p, &y)?.to_scalar::<f32>()?, 1.25 / 4.0);
        assert_eq!(Loss::L2.of(&p, &y)?.to_scalar::<f32>()?, 0.5625 / 4.0);
        Ok(())
    }

    #[test]
    fn run_options_saved_before_the_sampling_options_read_as_before() -> Result<()> {
        let run = RunOptions {
            config: Config::tiny(),
            data: Vec::new(),
            synthetic: 1,
            synth_width: 64,
            synth_height: 48,
            synth_views: 4,
            batch: 2,
            lr: 1e-3,
            optimizer: OptimizerKind::Adam,
            seed: 0,
            val_scenes: 1,
            val_batches: 1,
            views: None,
            val_data: Vec::new(),
            synthetic_percent: None,
            augment: false,
            lr_schedule: LrSchedule::default(),
            init: None,
            loss: Loss::L2,
            view_stride: Some((1, 3)),
            skip_flat: Some(0.02),
            scene_weights: Some(SceneWeights(vec![("maryrose".into(), 3.0)])),
            mpi_loss: Some(MpiPairs {
                weight: 1.0,
                tile: (224, 64),
                neighbours: 2,
                scale: 1,
            }),
        };
        let mut v = serde_json::to_value(&run)?;
        assert_eq!(v["loss"], "l2");
        assert_eq!(v["view_stride"], serde_json::json!([1, 3]));
        let obj = v.as_object_mut().context("an object")?;
        obj.remove("loss");
        obj.remove("view_stride");
        obj.remove("skip_flat");
        obj.remove("scene_weights");
        obj.remove("mpi_loss");
        let old: RunOptions = serde_json::from_value(v)?;
        assert_eq!(
            (old.loss, old.view_stride, old.skip_flat, &old.scene_weights),
            (Loss::L1, None, None, &None)
        );
        assert_eq!((old.mpi_loss, old.sampling().mpi), (None, None));
        assert_eq!(old.sampling().view_stride, (1, 1));
        assert!(old.sampling().scene_weights.is_empty());
        assert_eq!(
            RunOptions {
                loss: Loss::L2,
                view_stride: Some((1, 3)),
                skip_flat: Some(0.02),
                scene_weights: Some(SceneWeights(vec![("maryrose".into(), 3.0)])),
                mpi_loss: run.mpi_loss,
                ..old
            },
            run
        );
        Ok(())
    }
}
