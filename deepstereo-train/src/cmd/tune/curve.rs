//! `tune --curve`: held-out PSNR and SSIM against tuning time, from the snapshots the
//! tune keeps.

use super::*;

/// A curve time, the network's weights (in `named_vars` order) and the prior.
pub(super) type Snapshot = (f64, Vec<Tensor>, Option<PriorGrid>);

/// What the tune's phases left, for its curve.
pub(super) struct Phases<'a> {
    /// The network's weights before tuning (in `named_vars` order).
    pub original: &'a [Tensor],
    pub prior: Option<&'a SceneFit>,
    /// The network's fine-tune and when it began (seconds on the tune's clock; its
    /// snapshots' times are counted from there).
    pub network: Option<(&'a TuneResult, f64)>,
    /// The prior's refit on the tuned network and when it began.
    pub refit: Option<(&'a SceneFit, f64)>,
    /// The prior the model was written with (and the network tuned through).
    pub written: Option<&'a PriorGrid>,
}

/// Per curve time of `times` (seconds on the tune's clock): the network's weights and the
/// prior that a tune stopped then would have written.
pub(super) fn curve_snapshots(
    times: &[f64],
    budget: Budget,
    start: &deepstereo_core::weights::Trainable,
    p: &Phases<'_>,
) -> Result<Vec<Snapshot>> {
    let now = copy_weights(start)?;
    let end = match (p.refit, p.network, p.prior) {
        (Some((f, from)), _, _) => from + f.seconds,
        (None, Some((r, from)), _) => from + r.seconds,
        (None, None, Some(f)) => f.seconds,
        (None, None, None) => 0.0,
    };
    // A tune that read every view before its time was up ends with the model a longer
    // one would also write: the curve holds it up to the budget.
    let interrupted = p.network.is_some_and(|(r, _)| r.interrupted)
        || p.prior.is_some_and(|f| f.interrupted)
        || p.refit.is_some_and(|(f, _)| f.interrupted);
    let limit = match budget {
        Budget::Seconds(b) if !interrupted => b.max(end),
        _ => end,
    };
    let original = p.original.to_vec();
    let mut out = Vec::new();
    for &t in times {
        if t > limit + 1e-9 && t > 0.0 {
            continue;
        }
        let from_prior = (p.prior.iter())
            .flat_map(|f| f.snapshots.iter())
            .find(|(s, _)| *s == t);
        let from_net = p.network.filter(|(_, from)| t > *from).map(|(r, from)| {
            (r.snapshots.iter())
                .find(|(s, _)| (s - (t - from)).abs() < 1e-6)
                .map_or(now.clone(), |s| s.1.clone())
        });
        let from_refit = p.refit.filter(|(_, from)| t > *from).map(|(f, _)| {
            let snap = f.snapshots.iter().find(|(s, _)| *s == t);
            snap.map_or(p.written.cloned(), |(_, g)| Some(g.clone()))
        });
        if let Some(g) = from_refit {
            out.push((t, now.clone(), g));
            continue;
        }
        out.push(match (t, from_net, from_prior) {
            (t, _, _) if t == 0.0 => (t, original.clone(), None),
            (t, Some(w), _) => (t, w, p.written.cloned()),
            (t, None, Some((_, g))) => (t, original.clone(), Some(g.clone())),
            (t, None, None) => (t, original.clone(), p.written.cloned()),
        });
    }
    Ok(out)
}

/// Parses `0,1,2.5,...` (minutes, each finite and not negative).
pub(super) fn parse_minutes(s: &str) -> Result<Vec<f64>> {
    let mut out = Vec::new();
    for t in s.split(',') {
        let m: f64 = t
            .trim()
            .parse()
            .with_context(|| format!("--curve-minutes: '{t}' is not a number of minutes"))?;
        if !(m.is_finite() && m >= 0.0) {
            bail!("--curve-minutes: '{t}' must be 0 or more");
        }
        out.push(m);
    }
    Ok(out)
}

/// One point of the error-against-time curve.
#[derive(serde::Serialize)]
pub(super) struct CurvePoint {
    minutes: f64,
    psnr: f64,
    ssim: f64,
    seconds_per_view: f64,
}

/// Renders the held-out views with each snapshot and writes the curve: a snapshot with a
/// prior as the tuned model's config renders (`tuned`), one without as `cfg`.
pub(super) fn write_curve(
    dir: &Path,
    a: &Args,
    (cfg, tuned): (&Config, &Config),
    snapshots: &[Snapshot],
    holdout: &[usize],
    settings: &RenderSettings,
) -> Result<()> {
    let scene = a.input.scene.load_working()?;
    let mut points = Vec::new();
    for (secs, weights, prior) in snapshots {
        let c = if prior.is_some() { tuned } else { cfg };
        let backend = backend_with(c, weights, prior.clone())?;
        let name = format!("tuned {:.1} min", secs / 60.0);
        let r = evaluate(&backend, &name, &scene, holdout, settings, |_, _| {})?;
        eprintln!(
            "{:5.1} min: held-out PSNR {:.2} SSIM {:.3}",
            secs / 60.0,
            r.mean.psnr,
            r.mean.ssim
        );
        points.push(CurvePoint {
            minutes: secs / 60.0,
            psnr: r.mean.psnr,
            ssim: r.mean.ssim,
            seconds_per_view: r.mean.seconds,
        });
    }
    let mut csv = String::from("minutes,psnr,ssim,seconds_per_view\n");
    for p in &points {
        csv += &format!(
            "{},{:.4},{:.5},{:.3}\n",
            p.minutes, p.psnr, p.ssim, p.seconds_per_view
        );
    }
    let json = serde_json::json!({ "scene": scene.root, "holdout": holdout, "points": points });
    let plot = deepstereo_core::plot::plot(
        &format!("tuning {}", scene.root.display()),
        "minutes of tuning",
        "held-out PSNR dB",
        &[deepstereo_core::plot::Series {
            label: "tuned".into(),
            colour: [0.1, 0.4, 0.85],
            points: points.iter().map(|p| (p.minutes, p.psnr)).collect(),
            line: true,
            marker: 3,
            labels: Vec::new(),
        }],
        false,
    );
    write_atomic(&dir.join("curve.csv"), csv.as_bytes())?;
    write_atomic(
        &dir.join("curve.json"),
        serde_json::to_string_pretty(&json)?.as_bytes(),
    )?;
    plot.save_png(&dir.join("curve.png"))?;
    eprintln!("curve: {}", dir.display());
    Ok(())
}

/// A candle backend running `cfg` with these weights (in `named_vars` order).
pub(super) fn backend_with(
    cfg: &Config,
    values: &[Tensor],
    prior: Option<PriorGrid>,
) -> Result<CandleBackend> {
    let t = weights::init(cfg, &candle_core::Device::Cpu)?;
    for ((_, var), v) in named_vars(&t.varmap).iter().zip(values) {
        var.set(v)?;
    }
    Ok(CandleBackend {
        model: t.model.with_prior(prior),
        device: candle_core::Device::Cpu,
    })
}
