//! Tuning (role): [`tune`](self) below, its planning ([`plan`]) and the scene prior's fit
//! ([`prior`]). Uses training's optimisers and data, and rendering; never the command line.
//!
//! Per-scene fine-tuning: the paper's leave-one-out training applied to the user's own
//! capture. A model (the embedded default or any other) keeps training on tiles of the
//! scene's views, each rendered from its nearest other views, and the weights that score
//! best on a few views set aside for validation are kept.
//!
//! What the tuner sees is only the [`SceneData`] it is given: the caller builds it from
//! the views that are not held out (`Scene::load_views`), so a held-out photograph can be
//! neither a target nor a source, and cannot move the depth bounds either.
//!
//! The learning rate follows a cosine from `lr` down to `lr * lr_final` over the budget
//! (`p = step / steps`, or elapsed / budget time with a time budget):
//! `lr(p) = lr * (f + (1 - f) * (1 + cos(pi * p)) / 2)`.

pub mod plan;
pub mod prior;
pub mod through;

use crate::training::data::{
    make_batch, spawn_loader, Batch, Sampling, SceneData, VALIDATION_SALT,
};
use crate::training::optim::{Optimizer, OptimizerKind};
use crate::training::Loss;
use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor, Var};
use deepstereo_core::prior::PriorGrid;
use deepstereo_core::weights::{named_vars, Trainable};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use through::{render_batch, validate_through};

/// The fewest views a scene must keep for tuning (two to train on, one to validate).
pub const MIN_TUNE_VIEWS: usize = 3;
/// Most views set aside for validation.
pub const MAX_VALIDATION_VIEWS: usize = 3;

/// How long to tune.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Budget {
    /// Exactly this many optimizer steps (the output depends only on the inputs and seed).
    Steps(u64),
    /// Until this many seconds of tuning have passed (checked after each step).
    Seconds(f64),
}

/// The recipe.
#[derive(Clone, Debug)]
pub struct TuneOptions {
    pub budget: Budget,
    pub seed: u64,
    /// Adam's initial learning rate.
    pub lr: f64,
    /// The final rate's share of `lr` (cosine decay over the budget).
    pub lr_final: f64,
    /// Tiles per step.
    pub batch: usize,
    /// Source views per tile.
    pub views: usize,
    /// Photometric augmentation and flips.
    pub augment: bool,
    /// Validation every this many steps (and at the start and the end).
    pub validate_every: u64,
    /// Fixed validation batches (of `batch` tiles each).
    pub val_batches: usize,
    /// Snapshot times (seconds of tuning) at which the best weights so far are kept for
    /// an error-against-time curve.
    pub snapshots: Vec<f64>,
}

/// One validation of the run.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ValPoint {
    pub step: u64,
    pub seconds: f64,
    pub psnr: f64,
}

/// What a tune did.
pub struct TuneResult {
    /// Steps taken (fewer than asked when interrupted).
    pub steps: u64,
    /// Seconds of tuning (sample loading and validation included).
    pub seconds: f64,
    /// Every validation, the first one at step 0 (the model as given).
    pub validation: Vec<ValPoint>,
    /// The step whose weights are kept (0: no step improved on the model given).
    pub best_step: u64,
    /// Whether Ctrl-C ended it early.
    pub interrupted: bool,
    /// The best weights at each snapshot time of [`TuneOptions::snapshots`] reached.
    pub snapshots: Vec<(f64, Vec<Tensor>)>,
}

impl TuneResult {
    /// The validation PSNR of the kept weights.
    pub fn best_psnr(&self) -> f64 {
        (self.validation.iter())
            .filter(|v| v.step == self.best_step)
            .map(|v| v.psnr)
            .next()
            .unwrap_or(f64::NAN)
    }
}

/// Views (indices into a scene of `n` views) set aside for validation: about one in
/// ten, at most [`MAX_VALIDATION_VIEWS`], spread evenly and away from the ends.
pub fn validation_views(n: usize) -> Vec<usize> {
    let k = (n / 10).clamp(1, MAX_VALIDATION_VIEWS);
    (0..k).map(|i| (2 * i + 1) * n / (2 * k)).collect()
}

/// The learning rate after a share `p` (0 to 1) of the budget.
pub fn lr_at(opts: &TuneOptions, p: f64) -> f64 {
    let p = p.clamp(0.0, 1.0);
    let f = opts.lr_final;
    opts.lr * (f + (1.0 - f) * 0.5 * (1.0 + (std::f64::consts::PI * p).cos()))
}

/// Checks the options and the scene (named `name`, of `views` views) before anything
/// runs.
pub fn check(opts: &TuneOptions, name: &str, views: usize) -> Result<()> {
    match opts.budget {
        Budget::Steps(0) => bail!("--steps must be at least 1"),
        Budget::Seconds(s) if !(s.is_finite() && s > 0.0) => {
            bail!("--minutes must be a positive number of minutes")
        }
        _ => {}
    }
    if opts.batch == 0 || opts.views == 0 || opts.validate_every == 0 || opts.val_batches == 0 {
        bail!("--batch, --views, --validate-every and --val-batches must be at least 1");
    }
    if !(opts.lr.is_finite() && opts.lr > 0.0) {
        bail!("--lr must be a positive number");
    }
    if !(opts.lr_final.is_finite() && opts.lr_final > 0.0 && opts.lr_final <= 1.0) {
        bail!("--lr-final must be in (0, 1]");
    }
    if views < MIN_TUNE_VIEWS {
        bail!(
            "{name}: {views} views are left for tuning; tuning needs at least {MIN_TUNE_VIEWS} (hold out fewer)"
        );
    }
    Ok(())
}

/// Tunes `t`'s weights on `scene` in place (they end as the best weights found).
/// `validation` are the scene's views set aside (never targets, still sources). With
/// `prior`, every tile is rendered through it ([`through`]), the prior fixed.
pub fn tune(
    t: &Trainable,
    mut scene: SceneData,
    validation: &[usize],
    opts: &TuneOptions,
    prior: Option<&PriorGrid>,
    stop: Arc<AtomicBool>,
    mut progress: impl FnMut(&Progress),
) -> Result<TuneResult> {
    check(opts, &scene.name, scene.cameras.len())?;
    let cfg = t.model.config();
    let (val, train_sampling) = split_scene(cfg, &mut scene, validation, opts)?;
    let device = Device::Cpu;
    let vars = named_vars(&t.varmap);
    let mut opt = Optimizer::new(OptimizerKind::Adam, opts.lr, vars.clone())?;
    let rx = spawn_loader(
        cfg.clone(),
        train_sampling,
        Arc::new(vec![scene]),
        opts.seed,
        0,
        opts.batch,
        2,
    );
    let t0 = Instant::now();
    let first = validate_through(&t.model, &val, prior, &device)?;
    let mut run = Run {
        best: copy(&vars)?,
        best_step: 0,
        best_psnr: first,
        validation: vec![ValPoint {
            step: 0,
            seconds: 0.0,
            psnr: first,
        }],
        snapshots: Vec::new(),
    };
    let mut step = 0u64;
    let mut interrupted = false;
    loop {
        let elapsed = t0.elapsed().as_secs_f64();
        run.snapshot_until(opts, elapsed);
        let share = opts.budget.share(step, elapsed);
        if share >= 1.0 {
            break;
        }
        if stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        let batch = rx.recv().context("the sample loader stopped")??;
        let loss_v = train_step(t, &mut opt, (&batch, prior), &device, lr_at(opts, share))?;
        step += 1;
        let last = opts.budget.spent(step, t0.elapsed().as_secs_f64());
        let mut val_psnr = None;
        if step.is_multiple_of(opts.validate_every) || last {
            let psnr = validate_through(&t.model, &val, prior, &device)?;
            run.record(&vars, step, t0.elapsed().as_secs_f64(), psnr)?;
            val_psnr = Some(psnr);
        }
        progress(&Progress {
            step,
            share: share.max(opts.budget.share(step, t0.elapsed().as_secs_f64())),
            loss: loss_v,
            val_psnr,
            best_psnr: run.best_psnr,
        });
    }
    for (v, b) in vars.iter().zip(&run.best) {
        v.1.set(b)?;
    }
    Ok(TuneResult {
        steps: step,
        seconds: t0.elapsed().as_secs_f64(),
        validation: run.validation,
        best_step: run.best_step,
        interrupted,
        snapshots: run.snapshots,
    })
}

/// The validation batches of `scene`'s `validation` views, and the sampling of its
/// training tiles, whose targets `scene` then holds: every view but those.
fn split_scene(
    cfg: &deepstereo_core::config::Config,
    scene: &mut SceneData,
    validation: &[usize],
    opts: &TuneOptions,
) -> Result<(Vec<Batch>, Sampling)> {
    let sampling = Sampling {
        views: (opts.views, opts.views),
        ..Sampling::fixed(cfg)
    };
    sampling.check(cfg)?;
    let n = scene.cameras.len();
    scene.targets = Some(validation.to_vec());
    let val = validation_batches(cfg, &sampling, scene, opts)?;
    scene.targets = Some((0..n).filter(|i| !validation.contains(i)).collect());
    let train_sampling = Sampling {
        augment: opts.augment,
        ..sampling
    };
    Ok((val, train_sampling))
}

/// One Adam step on `batch` (through `prior`) at rate `lr` (none where the loss or the
/// gradient norm is not finite); the L1 loss.
fn train_step(
    t: &Trainable,
    opt: &mut Optimizer,
    (batch, prior): (&Batch, Option<&PriorGrid>),
    device: &Device,
    lr: f64,
) -> Result<f64> {
    let (image, y) = render_batch(&t.model, batch, prior, device, false)?;
    let loss = Loss::L1.of(&image, &y)?;
    let loss_v = loss.to_scalar::<f32>()? as f64;
    let grads = loss.backward()?;
    let gnorm = opt.grad_norm(&grads)?;
    if loss_v.is_finite() && gnorm.is_finite() {
        opt.lr = lr;
        opt.step(&grads)?;
    }
    Ok(loss_v)
}

impl Budget {
    /// The share of the budget that `step` steps in `elapsed` seconds have used.
    fn share(&self, step: u64, elapsed: f64) -> f64 {
        match *self {
            Budget::Steps(s) => step as f64 / s as f64,
            Budget::Seconds(s) => elapsed / s,
        }
    }

    /// Whether `step` steps in `elapsed` seconds have spent the budget.
    fn spent(&self, step: u64, elapsed: f64) -> bool {
        match *self {
            Budget::Steps(s) => step >= s,
            Budget::Seconds(s) => elapsed >= s,
        }
    }
}

/// What the caller hears after each step.
pub struct Progress {
    pub step: u64,
    /// Share of the budget used (0 to 1).
    pub share: f64,
    pub loss: f64,
    /// The validation PSNR when this step validated.
    pub val_psnr: Option<f64>,
    pub best_psnr: f64,
}

/// The tune's running state: the best weights so far and the snapshots taken.
struct Run {
    best: Vec<Tensor>,
    best_step: u64,
    best_psnr: f64,
    validation: Vec<ValPoint>,
    snapshots: Vec<(f64, Vec<Tensor>)>,
}

impl Run {
    /// Records a validation, keeping the weights when they are the best so far.
    fn record(&mut self, vars: &[(String, Var)], step: u64, seconds: f64, psnr: f64) -> Result<()> {
        self.validation.push(ValPoint {
            step,
            seconds,
            psnr,
        });
        if psnr > self.best_psnr {
            self.best = copy(vars)?;
            self.best_step = step;
            self.best_psnr = psnr;
        }
        Ok(())
    }

    /// Takes the snapshots whose time has come (the best weights so far).
    fn snapshot_until(&mut self, opts: &TuneOptions, elapsed: f64) {
        for &s in &opts.snapshots {
            let taken = self.snapshots.iter().any(|(t, _)| *t == s);
            if !taken && s <= elapsed {
                self.snapshots.push((s, self.best.clone()));
            }
        }
    }
}

/// Detached copies of the variables' values.
pub fn copy(vars: &[(String, Var)]) -> Result<Vec<Tensor>> {
    Ok(vars
        .iter()
        .map(|(_, v)| v.as_tensor().copy())
        .collect::<candle_core::Result<_>>()?)
}

/// The fixed validation tiles: targets among the scene's current `targets`.
fn validation_batches(
    cfg: &deepstereo_core::config::Config,
    sampling: &Sampling,
    scene: &SceneData,
    opts: &TuneOptions,
) -> Result<Vec<Batch>> {
    let scenes = std::slice::from_ref(scene);
    (0..opts.val_batches as u64)
        .map(|b| {
            make_batch(
                cfg,
                sampling,
                scenes,
                opts.seed ^ VALIDATION_SALT,
                b,
                opts.batch,
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_views_are_spread_and_few() {
        assert_eq!(validation_views(3), vec![1]);
        assert_eq!(validation_views(9), vec![4]);
        assert_eq!(validation_views(20), vec![5, 15]);
        assert_eq!(validation_views(56), vec![9, 28, 46]);
        assert_eq!(validation_views(500).len(), MAX_VALIDATION_VIEWS);
    }

    #[test]
    fn the_rate_falls_from_lr_to_its_final_share() {
        let o = TuneOptions {
            budget: Budget::Steps(10),
            seed: 0,
            lr: 1e-3,
            lr_final: 0.1,
            batch: 1,
            views: 4,
            augment: false,
            validate_every: 1,
            val_batches: 1,
            snapshots: Vec::new(),
        };
        assert!((lr_at(&o, 0.0) - 1e-3).abs() < 1e-15);
        assert!((lr_at(&o, 0.5) - 0.55e-3).abs() < 1e-12);
        assert!((lr_at(&o, 1.0) - 1e-4).abs() < 1e-15);
        assert!((lr_at(&o, 7.0) - 1e-4).abs() < 1e-15);
    }
}
