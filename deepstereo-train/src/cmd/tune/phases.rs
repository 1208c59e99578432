//! The network's phase of `tune` and the render planes a tuned model gets.

use super::*;

/// Fine-tunes the network's weights in place (they end as the best found), through
/// `prior` when there is one.
pub(super) fn tune_network(
    start: &deepstereo_core::weights::Trainable,
    data: SceneData,
    validation: &[usize],
    opts: &TuneOptions,
    prior: Option<&PriorGrid>,
    stop: &Arc<AtomicBool>,
    (bar, span): (&indicatif::ProgressBar, Span),
) -> Result<TuneResult> {
    let r = tune(start, data, validation, opts, prior, stop.clone(), |p| {
        report(bar, p, span)
    })?;
    let first = r.validation.first().map_or(f64::NAN, |v| v.psnr);
    eprintln!(
        "{}network{}: {} steps in {:.0} s; validation PSNR {first:.2} -> {:.2} dB (the weights of step {})",
        if r.interrupted { "interrupted: " } else { "" },
        if prior.is_some() { " through the prior" } else { "" },
        r.steps,
        r.seconds,
        r.best_psnr(),
        r.best_step
    );
    Ok(r)
}

/// The views a prior is fitted on: all but those set aside.
pub(super) fn tuning_targets(scene: &Scene, validation: &[usize]) -> Vec<usize> {
    (0..scene.views.len())
        .filter(|i| !validation.contains(i))
        .collect()
}

/// `cfg` rendering at `planes` by default, checked.
pub(super) fn with_render_planes(cfg: &Config, planes: usize) -> Result<Config> {
    let c = Config {
        render_planes: Some(planes),
        ..cfg.clone()
    };
    c.validate()
        .map_err(|e| anyhow::anyhow!("--render-planes: {e}"))?;
    Ok(c)
}

/// The render planes of a tuned model with prior `grid` (its network's weights those
/// of `start` now), chosen on the views set aside against the model it started from
/// (`cfg` with the weights `original`, and its own prior if it had one).
pub(super) fn pick_planes(
    start: &deepstereo_core::weights::Trainable,
    (cfg, original): (&Config, &[Tensor]),
    grid: &PriorGrid,
    (scene, validation, settings): (&Scene, &[usize], &RenderSettings),
    seconds: f64,
) -> Result<plan::PlanesChoice> {
    let before = backend_with(cfg, original, start.model.prior().cloned())?;
    let tuned = CandleBackend {
        model: start.model.clone().with_prior(Some(grid.clone())),
        device: candle_core::Device::Cpu,
    };
    let choices = plan::plane_choices(cfg.planes);
    let targets = plan::choice_targets(&tuning_targets(scene, validation), validation);
    let c = plan::choose_render_planes(
        (&before, &tuned),
        scene,
        (&targets, validation),
        settings,
        (&choices, seconds),
    )?;
    let tried: Vec<String> = (c.work.iter())
        .map(|(p, r)| format!("{p} planes {r:.2}x"))
        .collect();
    eprintln!(
        "render planes: {} (work on {} views against the model started from: {}; {:.0} s{})",
        c.planes,
        targets.len(),
        tried.join(", "),
        c.seconds,
        if c.cut {
            "; stopped at the budget's end"
        } else {
            ""
        }
    );
    Ok(c)
}

/// Detached copies of a model's weights (in `named_vars` order).
pub(super) fn copy_weights(t: &deepstereo_core::weights::Trainable) -> Result<Vec<Tensor>> {
    crate::tuning::copy(&named_vars(&t.varmap))
}

/// A time budget's seconds; a budget of steps has no time limit.
pub(super) fn seconds_of(b: Budget) -> f64 {
    match b {
        Budget::Seconds(t) => t,
        Budget::Steps(_) => f64::INFINITY,
    }
}
