//! `deepstereo tune`: fine-tunes a model on the user's own scene by leaving one view out
//! (the paper's training, on the capture itself), and writes a model every command takes
//! with `--model`.

mod curve;
mod phases;
mod progress;
mod scene;

use self::curve::*;
use self::phases::*;
use self::progress::*;
use self::scene::*;
use super::args::{SceneArgs, SceneModelArgs};
use crate::rendering::{evaluate, RenderSettings};
use crate::training::data::SceneData;
use crate::tuning::plan;
use crate::tuning::prior::{
    fit_scene, PriorBudget, PriorNeed, PriorOptions, PriorProgress, SceneFit,
};
use crate::tuning::{tune, validation_views, Budget, Progress, TuneOptions, TuneResult};
use anyhow::{bail, Context, Result};
use candle_core::Tensor;
use deepstereo_core::config::Config;
use deepstereo_core::imageio::write_atomic;
use deepstereo_core::prior::PriorGrid;
use deepstereo_core::render::CandleBackend;
use deepstereo_core::scene::{Scene, MAX_DOWNSCALE};
use deepstereo_core::weights::{self, named_vars};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

/// Adam's initial rate of the recipe.
pub const DEFAULT_LR: f64 = 5e-4;

/// The rate's final share (cosine decay over the budget).
pub const DEFAULT_LR_FINAL: f64 = 0.1;

/// Metadata key of the tune's options in the model it writes.
pub const TUNE_KEY: &str = "deepstereo.tune";

#[derive(Debug, clap::Args)]
pub struct Args {
    // The scene to tune on. The model to start from (`--model`, default the embedded one),
    // the views per tile (`--views`, default the model's) and, for `--curve`, how held-out
    // views are rendered.
    // The held-out views: never a target, never a source, their images
    // never read while tuning.
    #[command(flatten)]
    pub input: SceneModelArgs,
    /// Tune for this many minutes (of tuning; the output then depends on the machine's
    /// speed).
    #[arg(long, conflicts_with = "steps", required_unless_present = "steps")]
    pub minutes: Option<f64>,
    /// Tune for exactly this many steps (same seed and steps: the same output, bit for bit).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Seed of the tiles drawn.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Adam's initial learning rate (a cosine decay to --lr-final times it over the budget).
    #[arg(long, default_value_t = DEFAULT_LR, help_heading = super::args::EXPERT)]
    pub lr: f64,
    /// The final rate's share of --lr.
    #[arg(long, default_value_t = DEFAULT_LR_FINAL, help_heading = super::args::EXPERT)]
    pub lr_final: f64,
    /// Tiles per step.
    #[arg(long, default_value_t = 8, help_heading = super::args::EXPERT)]
    pub batch: usize,
    /// Photometric augmentation and flips of the tiles.
    #[arg(long, help_heading = super::args::EXPERT)]
    pub augment: bool,
    /// Validate (on views set aside from the tuning views) every this many steps.
    #[arg(long, default_value_t = 25, help_heading = super::args::EXPERT)]
    pub validate_every: u64,
    /// Validation batches of --batch tiles each.
    #[arg(long, default_value_t = 8, help_heading = super::args::EXPERT)]
    pub val_batches: usize,
    /// The tuned model: a safetensors file with its config (written atomically at the
    /// end, or on Ctrl-C with the best weights so far).
    #[arg(long)]
    pub out: PathBuf,
    /// Error against tuning time: after tuning, render the held-out views with the best
    /// weights of each --curve-minutes time and write curve.csv, curve.json and curve.png
    /// into this directory.
    #[arg(long)]
    pub curve: Option<PathBuf>,
    /// Times of the curve, in minutes (those within the budget are drawn).
    #[arg(long, default_value = "0,1,2,5,10,20")]
    pub curve_minutes: String,
    /// Share of the budget (time, or steps) for fine-tuning the network's weights, after
    /// the scene prior (a world-space grid that reweighs the network's selection) is
    /// fitted with the rest; the network is tuned through the fitted prior. 0: the prior
    /// alone; 1: the network alone, without a prior. Default with --minutes: the prior
    /// gets what it needs (one view rendered and a few fit steps timed first), at most
    /// half, and the network the rest; with --steps: 0.
    #[arg(long, help_heading = super::args::EXPERT)]
    pub network_share: Option<f64>,
    /// After the network's fine-tune through the prior, read the views again with the
    /// tuned network and refit the prior from the one fitted before (the network's time
    /// shortened by the prior's; with --steps, the prior's steps again).
    #[arg(long, help_heading = super::args::EXPERT)]
    pub refit: bool,
    /// Cells along the longest side of the scene prior's grid.
    #[arg(long, default_value_t = PriorOptions::default().cells, help_heading = super::args::EXPERT)]
    pub prior_cells: usize,
    /// Weight of the squared difference of neighbouring cells of the scene prior's
    /// log-weights in its fit (0: none).
    #[arg(long, default_value_t = PriorOptions::default().smooth, help_heading = super::args::EXPERT)]
    pub prior_smooth: f32,
    /// Keep the scene prior's sharpness at 1 (the network's own selection, reweighed)
    /// instead of fitting it with the grid.
    #[arg(long, help_heading = super::args::EXPERT)]
    pub no_sharpen: bool,
    /// Depth planes a model with a scene prior renders at by default (written into its
    /// config as `render_planes`; `--planes` still overrides it when rendering). Default:
    /// the most of 0.75x to 1.5x the network's planes in eighths (24, 28, ..., 48) at
    /// which the tuned model does no more work than the model it started from on the
    /// views set aside and a few tuning views (the coarse pass of `--prune auto` applies
    /// the prior, so the planes run depend on it).
    #[arg(long, help_heading = super::args::EXPERT)]
    pub render_planes: Option<usize>,
    /// Print a line per validation instead of a progress bar (the default when standard
    /// error is not a terminal).
    #[arg(long)]
    pub no_progress: bool,
}

pub fn run(a: Args) -> Result<()> {
    let setup = Setup::new(&a)?;
    let Setup {
        settings,
        budget,
        start,
        cfg,
        scene,
        holdout,
        validation,
        ..
    } = &setup;
    let shared = (scene, &validation[..], settings);
    let plan = plan(&a, *budget, start, shared)?;
    let mut opts = setup.options(&a, &plan)?;
    eprintln!(
        "tuning {} on {} views ({} held out, {} set aside for validation), {} per tile; {}",
        a.input.model.name(),
        scene.views.len(),
        holdout.len(),
        validation.len(),
        opts.views,
        plan.describe()
    );
    let stop = crate::cmd::support::interrupt::graceful();
    let bar = progress_bar(!a.no_progress);
    let original = copy_weights(start)?;
    let times = opts.snapshots.clone();
    let prior = match plan.prior {
        true => Some(run_prior(&a, &setup, &plan, (&times, None), (&stop, &bar))?),
        false => None,
    };
    // A grid no step improved on is the model as given: no prior is written, and the
    // network is tuned without one.
    let improved = |p: &&SceneFit| p.fit.as_ref().is_some_and(|f| f.best_step > 0);
    let grid = prior.as_ref().filter(improved).and_then(|p| p.grid.clone());
    let interrupted = prior.as_ref().is_some_and(|p| p.interrupted);
    let from = plan.clock.elapsed().as_secs_f64();
    let network = match plan.network_budget() {
        Some(nb) if !interrupted => {
            opts.budget = nb;
            opts.snapshots = (times.iter())
                .filter(|&&t| t > from)
                .map(|t| t - from)
                .collect();
            let data = SceneData::from_scene(scene, cfg.levels)?;
            let g = grid.as_ref();
            let span = Span(plan.share_at(*budget, from), 1.0);
            Some(tune_network(
                start,
                data,
                validation,
                &opts,
                g,
                &stop,
                (&bar, span),
            )?)
        }
        _ => None,
    };
    let refit_from = plan.clock.elapsed().as_secs_f64();
    let refit = match (&grid, &network) {
        (Some(g), Some(r)) if plan.refit.is_some() && !r.interrupted => {
            let init = Some(g.clone());
            Some(run_prior(&a, &setup, &plan, (&times, init), (&stop, &bar))?)
        }
        _ => None,
    };
    // The refit starts from the grid, so its best is never worse on the views set aside.
    let grid = refit.as_ref().and_then(|r| r.grid.clone()).or(grid);
    bar.finish_and_clear();
    let (tuned_cfg, choice) = tuned_config(&a, &setup, &plan, grid.as_ref(), &original)?;
    let outcome = Outcome {
        network: network.as_ref(),
        prior: prior.as_ref(),
        refit: refit.as_ref(),
        grid: grid.as_ref(),
        tuned: &tuned_cfg,
        choice: choice.as_ref(),
    };
    let provenance = provenance(&a, &setup, &plan, &opts, &outcome);
    save_model(
        &a.out,
        &tuned_cfg,
        &start.varmap,
        grid.as_ref(),
        &provenance.to_string(),
    )?;
    eprintln!(
        "model: {} ({:.0} s of tuning)",
        a.out.display(),
        plan.clock.elapsed().as_secs_f64()
    );
    if let Some(dir) = &a.curve {
        let phases = Phases {
            original: &original,
            prior: prior.as_ref(),
            network: network.as_ref().map(|r| (r, from)),
            refit: refit.as_ref().map(|r| (r, refit_from)),
            written: grid.as_ref(),
        };
        let snaps = curve_snapshots(&times, *budget, start, &phases)?;
        write_curve(dir, &a, (cfg, &tuned_cfg), &snaps, holdout, settings)?;
    }
    Ok(())
}

/// The tuned model's config: with a prior, rendering at --render-planes or at the planes
/// chosen on the views set aside (and that choice); without one, as it was.
fn tuned_config(
    a: &Args,
    setup: &Setup,
    plan: &Plan,
    grid: Option<&PriorGrid>,
    original: &[Tensor],
) -> Result<(Config, Option<plan::PlanesChoice>)> {
    let cfg = &setup.cfg;
    Ok(match (grid, a.render_planes) {
        (None, _) => (cfg.clone(), None),
        (Some(_), Some(p)) => (with_render_planes(cfg, p)?, None),
        (Some(g), None) => {
            let left = seconds_of(setup.budget) - plan.clock.elapsed().as_secs_f64();
            let shared = (&setup.scene, &setup.validation[..], &setup.settings);
            let c = pick_planes(&setup.start, (cfg, original), g, shared, left)?;
            (with_render_planes(cfg, c.planes)?, Some(c))
        }
    })
}

/// What a tune reads and starts from, checked before anything runs.
struct Setup {
    settings: RenderSettings,
    budget: Budget,
    curve_minutes: Vec<f64>,
    start: deepstereo_core::weights::Trainable,
    cfg: Config,
    scene: Scene,
    holdout: Vec<usize>,
    validation: Vec<usize>,
}

impl Setup {
    /// The setup, and the scene's images for the network's tune.
    fn new(a: &Args) -> Result<Self> {
        let settings = a.input.model.settings()?;
        let budget = match (a.minutes, a.steps) {
            (Some(m), None) if m.is_finite() && m > 0.0 => Budget::Seconds(m * 60.0),
            (Some(m), None) => bail!("--minutes must be a positive number, got {m}"),
            (None, Some(0)) => bail!("--steps must be at least 1"),
            (None, Some(s)) => Budget::Steps(s),
            _ => bail!("pass --minutes M or --steps S"),
        };
        let curve_minutes = match &a.curve {
            Some(_) => parse_minutes(&a.curve_minutes)?,
            None => Vec::new(),
        };
        check_split(a)?;
        check_out(&a.out)?;
        let start = crate::rendering::models::load_model(a.input.model.model.as_deref())?;
        let cfg = start.model.config().clone();
        if cfg.pool.is_none() {
            bail!(
                "{}: tune takes the any-number-of-views family (like the embedded model); '{}' is the paper's family, which takes a fixed number of views",
                a.input.model.name(),
                cfg.name
            );
        }
        let (scene, holdout) =
            load_tuning_scene(&a.input.scene, &a.input.holdout, seconds_budget(budget))?;
        if a.curve.is_some() && holdout.is_empty() {
            bail!("--curve scores held-out views: pass --llffhold N or --holdout I,J,...");
        }
        let validation = validation_views(scene.views.len());
        // The config a model with a prior is written with, checked before anything runs.
        if let Some(p) = a.render_planes {
            with_render_planes(&cfg, p)?;
        }
        Ok(Self {
            settings,
            budget,
            curve_minutes,
            start,
            cfg,
            scene,
            holdout,
            validation,
        })
    }

    /// The network's tuning options under `plan` (its budget set when it starts),
    /// checked; `--curve`'s directory made.
    fn options(&self, a: &Args, plan: &Plan) -> Result<TuneOptions> {
        let opts = TuneOptions {
            budget: match plan.network {
                NetworkPlan::Steps(n) => Budget::Steps(n),
                _ => Budget::Steps(1),
            },
            seed: a.seed,
            lr: a.lr,
            lr_final: a.lr_final,
            batch: a.batch,
            views: a.input.model.views.unwrap_or(self.cfg.views),
            augment: a.augment,
            validate_every: a.validate_every,
            val_batches: a.val_batches,
            snapshots: self.curve_minutes.iter().map(|m| m * 60.0).collect(),
        };
        let name = self.scene.root.display().to_string();
        crate::tuning::check(&opts, &name, self.scene.views.len())?;
        if let Some(dir) = &a.curve {
            std::fs::create_dir_all(dir).with_context(|| {
                format!("--curve {}: cannot create the directory", dir.display())
            })?;
        }
        Ok(opts)
    }
}

/// The scene prior's fit: first (`init` `None`), all views and its share of the steps,
/// or until the plan's time for it; or its refit from `init` on the tuned network, the
/// prior's steps again or what is left before the planes choice. Curve snapshots at
/// `times` (seconds on the plan's clock).
fn run_prior(
    a: &Args,
    setup: &Setup,
    plan: &Plan,
    (times, init): (&[f64], Option<PriorGrid>),
    (stop, bar): (&AtomicBool, &indicatif::ProgressBar),
) -> Result<SceneFit> {
    let mut po = prior_options(a);
    po.view_share = plan.view_share;
    let now = plan.clock.elapsed().as_secs_f64();
    let refit = init.is_some();
    po.init = init;
    let pb = match (setup.budget, plan.prior_until) {
        (Budget::Seconds(b), Some(_)) if refit => PriorBudget::Seconds(b - now - plan.reserve),
        (Budget::Seconds(_), Some(until)) => PriorBudget::Seconds(until - now),
        (Budget::Steps(_), _) | (_, None) => {
            po.steps = plan.prior_steps;
            PriorBudget::AllViews
        }
    };
    let span = match refit {
        true => Span(plan.share_at(setup.budget, now), 1.0),
        false => Span(0.0, plan.prior_end(setup.budget)),
    };
    let phase = PriorPhase {
        scene: &setup.scene,
        validation: &setup.validation,
        settings: &setup.settings,
        opts: po,
        budget: pb,
        snapshots: (times, now),
        span,
    };
    phase.run(&setup.start, stop, bar)
}

/// What the tune found, for the model's provenance.
struct Outcome<'a> {
    network: Option<&'a TuneResult>,
    prior: Option<&'a SceneFit>,
    refit: Option<&'a SceneFit>,
    grid: Option<&'a PriorGrid>,
    tuned: &'a Config,
    choice: Option<&'a plan::PlanesChoice>,
}

/// The tune's options and what it found, written into the model's metadata.
fn provenance(
    a: &Args,
    setup: &Setup,
    plan: &Plan,
    opts: &TuneOptions,
    o: &Outcome<'_>,
) -> serde_json::Value {
    let fit = o.prior.and_then(|p| p.fit.as_ref());
    serde_json::json!({
        "scene": setup.scene.root,
        "holdout": setup.holdout,
        "seed": a.seed,
        "steps": match setup.budget { Budget::Steps(s) => Some(s), Budget::Seconds(_) => None },
        "minutes": a.minutes,
        "network_share": plan.share,
        "network_share_given": a.network_share.is_some(),
        "prior_need_seconds": plan.need.map(|n| n.seconds()),
        "prior_view_share": plan.view_share,
        "network_steps": o.network.map(|r| r.steps),
        "network_best_step": o.network.map(|r| r.best_step),
        "network_through_prior": o.network.map(|_| o.grid.is_some()),
        "prior_views": o.prior.map(|p| p.views),
        "prior_steps": fit.map(|f| f.steps),
        "prior_best_step": fit.map(|f| f.best_step),
        "prior_sharpness": o.grid.map(|g| g.sharpness),
        "refit_views": o.refit.map(|p| p.views),
        "refit_best_step": o.refit.and_then(|p| p.fit.as_ref()).map(|f| f.best_step),
        "lr": a.lr,
        "lr_final": a.lr_final,
        "batch": a.batch,
        "views": opts.views,
        "augment": a.augment,
        "render_planes": o.tuned.default_render_planes(),
        "render_planes_work": o.choice.map(|c| &c.work),
        "render_planes_cut": o.choice.map(|c| c.cut),
        "start": a.input.model.name(),
    })
}

/// Fitting the scene prior on the (tuned) network.
struct PriorPhase<'a> {
    scene: &'a Scene,
    /// Views set aside for validation (never targets).
    validation: &'a [usize],
    settings: &'a RenderSettings,
    opts: PriorOptions,
    budget: PriorBudget,
    /// Curve times (seconds of the whole tune) and the seconds already spent.
    snapshots: (&'a [f64], f64),
    /// The part of the progress bar it fills.
    span: Span,
}

impl PriorPhase<'_> {
    fn run(
        &self,
        start: &deepstereo_core::weights::Trainable,
        stop: &AtomicBool,
        bar: &indicatif::ProgressBar,
    ) -> Result<SceneFit> {
        let backend = CandleBackend {
            model: start.model.clone().with_prior(None),
            device: candle_core::Device::Cpu,
        };
        let train = tuning_targets(self.scene, self.validation);
        let r = fit_scene(
            &backend,
            self.scene,
            (&train, self.validation),
            self.settings,
            &self.opts,
            self.budget,
            self.snapshots,
            stop,
            |p| report_prior(bar, p, self.span),
        )?;
        if let Some(f) = &r.fit {
            let first = f.validation.first().map_or(f64::NAN, |v| v.1);
            eprintln!(
                "{}scene prior{}: {} views, {} rays, {} steps in {:.0} s; validation PSNR {first:.2} -> {:.2} dB (step {}), sharpness {:.3}",
                if r.interrupted { "interrupted: " } else { "" },
                if self.opts.init.is_some() { ", refitted on the tuned network" } else { "" },
                r.views,
                r.rays,
                f.steps,
                r.seconds,
                f.best_psnr(),
                f.best_step,
                r.grid.as_ref().map_or(1.0, |g| g.sharpness)
            );
        }
        Ok(r)
    }
}

/// The network's fine-tune, after the prior.
#[derive(Clone, Copy, Debug, PartialEq)]
enum NetworkPlan {
    None,
    /// Exactly this many steps.
    Steps(u64),
    /// Until this many seconds on the plan's clock, less the planes choice's reserve.
    Until(f64),
}

/// How the budget is spent: the prior first, then the network through it.
struct Plan {
    /// Whether the prior is fitted.
    prior: bool,
    /// With a time budget, the second on the clock by which the prior ends.
    prior_until: Option<f64>,
    /// With a budget of steps, the prior's fit steps.
    prior_steps: usize,
    network: NetworkPlan,
    /// With `--refit`, the seconds kept for the prior's refit after the network (0 with a
    /// budget of steps); `None`: no refit.
    refit: Option<f64>,
    /// The network's share of the budget (planned; with a time budget, estimated).
    share: f64,
    /// The prior's estimated time (measured with a time budget).
    need: Option<PriorNeed>,
    /// Seconds kept for choosing the render planes after both.
    reserve: f64,
    /// The share of each view's tiles the prior reads ([`plan::view_share`]).
    view_share: f64,
    /// When tuning began.
    clock: Instant,
}

impl Plan {
    /// The share of the whole tune (its progress bar) where the prior's phase ends.
    fn prior_end(&self, budget: Budget) -> f64 {
        match (budget, self.prior_until) {
            _ if self.network == NetworkPlan::None => 1.0,
            (Budget::Seconds(b), Some(until)) => until / b,
            (Budget::Steps(s), _) => self.prior_steps as f64 / s as f64,
            _ => 0.0,
        }
    }

    /// The share of the whole tune at `seconds` on the clock (with a budget of steps,
    /// where the prior's steps end).
    fn share_at(&self, budget: Budget, seconds: f64) -> f64 {
        match budget {
            Budget::Seconds(b) => seconds / b,
            Budget::Steps(_) => self.prior_end(budget),
        }
    }

    /// The network's budget when it starts now (`None`: it does not run).
    fn network_budget(&self) -> Option<Budget> {
        match self.network {
            NetworkPlan::None => None,
            NetworkPlan::Steps(n) => Some(Budget::Steps(n)),
            NetworkPlan::Until(end) => {
                let left = end - self.clock.elapsed().as_secs_f64();
                let t = plan::network_seconds(left, self.reserve + self.refit.unwrap_or(0.0));
                (t > 0.0).then_some(Budget::Seconds(t))
            }
        }
    }

    /// A line for people: what runs, for how long.
    fn describe(&self) -> String {
        let prior = match (self.prior, self.prior_until) {
            (false, _) => None,
            (true, Some(until)) => Some(format!("the scene prior for about {until:.0} s")),
            (true, None) => Some(format!("the scene prior ({} fit steps)", self.prior_steps)),
        };
        let net = match self.network {
            NetworkPlan::None => None,
            NetworkPlan::Steps(n) => Some(format!("the network for {n} steps")),
            NetworkPlan::Until(end) => {
                let until = end - self.reserve - self.refit.unwrap_or(0.0);
                Some(format!("the network until {until:.0} s"))
            }
        };
        let refit = match self.refit {
            Some(_) => ", then the prior refitted",
            None => "",
        };
        let what = match (prior, net) {
            (Some(p), Some(n)) => format!("{p}, then {n} through it{refit}"),
            (Some(p), None) => format!("{p} alone"),
            (None, Some(n)) => format!("{n} alone"),
            (None, None) => "nothing".to_string(),
        };
        let need = self.need.map_or(String::new(), |n| {
            let share = match self.view_share < 1.0 {
                true => format!("; it reads {:.0}% of each view", 100.0 * self.view_share),
                false => String::new(),
            };
            format!(
                " (the prior needs about {:.0} s: {} views at {:.1} s and its fit{share})",
                n.seconds(),
                n.views,
                n.per_view
            )
        });
        format!("{what}{need}")
    }
}

/// Refuses an impossible `--network-share` or prior option ([`PriorOptions::check`]:
/// `--prior-cells`, `--prior-smooth`) before the scene is read.
fn check_split(a: &Args) -> Result<()> {
    if let Some(f) = a.network_share {
        if !(f.is_finite() && (0.0..=1.0).contains(&f)) {
            bail!("--network-share must be between 0 and 1, got {f}");
        }
    }
    prior_options(a).check()
}

/// Splits the budget between the prior, first, and the network through it:
/// `--network-share` as given, or (with a time budget) what the prior needs, measured
/// on the scene, up to [`plan::MAX_PRIOR_SHARE`] ([`crate::tuning::plan`]).
fn plan(
    a: &Args,
    budget: Budget,
    start: &deepstereo_core::weights::Trainable,
    (scene, validation, settings): (&Scene, &[usize], &RenderSettings),
) -> Result<Plan> {
    let clock = Instant::now();
    let prior = a.network_share.is_none_or(|f| f < 1.0);
    let need = match budget {
        Budget::Seconds(_) if prior => {
            let backend = CandleBackend {
                model: start.model.clone().with_prior(None),
                device: candle_core::Device::Cpu,
            };
            let train = tuning_targets(scene, validation);
            let po = prior_options(a);
            Some(PriorNeed::measure(
                &backend,
                scene,
                (&train, validation),
                settings,
                &po,
            )?)
        }
        _ => None,
    };
    let reserve = match (need, a.render_planes) {
        (Some(n), None) => {
            let targets = plan::choice_targets(&tuning_targets(scene, validation), validation);
            plan::choice_reserve(&n, targets.len(), seconds_of(budget))
        }
        _ => 0.0,
    };
    let mut p = Plan {
        prior,
        prior_until: None,
        prior_steps: 0,
        network: NetworkPlan::None,
        refit: None,
        share: a.network_share.unwrap_or(0.0),
        need,
        reserve,
        view_share: 1.0,
        clock,
    };
    match (budget, need) {
        (Budget::Steps(s), _) => {
            let n = (s as f64 * p.share).round() as u64;
            p.prior_steps = (s - n) as usize;
            p.prior &= p.prior_steps > 0;
            p.network = if n > 0 {
                NetworkPlan::Steps(n)
            } else {
                NetworkPlan::None
            };
        }
        (Budget::Seconds(b), need) => {
            let now = clock.elapsed().as_secs_f64();
            let left = b - now;
            let secs = match (a.network_share, need) {
                (Some(f), _) => (1.0 - f) * (left - reserve).max(0.0),
                (None, Some(n)) => plan::prior_seconds(left, n.seconds(), reserve),
                (None, None) => 0.0,
            };
            if let Some(n) = need {
                p.view_share = plan::view_share(&n, secs);
            }
            p.prior_until = Some(now + secs);
            p.share = ((left - reserve - secs) / b).max(0.0);
            p.network = match a.network_share {
                Some(0.0) => NetworkPlan::None,
                _ => NetworkPlan::Until(b),
            };
        }
    }
    // The refit reads the views as the first fit did: it keeps that fit's time.
    let networked = p.network != NetworkPlan::None;
    p.refit = match (budget, need) {
        _ if !(a.refit && p.prior && networked) => None,
        (Budget::Steps(_), _) => Some(0.0),
        (Budget::Seconds(_), Some(n)) => Some(n.seconds_at(p.view_share)),
        (Budget::Seconds(_), None) => None,
    };
    Ok(p)
}

fn prior_options(a: &Args) -> PriorOptions {
    PriorOptions {
        cells: a.prior_cells,
        smooth: a.prior_smooth,
        sharpen: !a.no_sharpen,
        validate_every: a.validate_every as usize,
        seed: a.seed,
        ..PriorOptions::default()
    }
}
