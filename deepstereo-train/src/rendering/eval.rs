//! Held-out views rendered with the network and the classical baselines (the nearest
//! view, a plane sweep), and scored against their photographs: `eval`'s and `report`'s
//! numbers.

use super::*;

/// What a held-out view's evaluation produced, for callers that save pictures.
pub struct ViewImages<'a> {
    pub truth: &'a RgbImage,
    pub rendered: &'a Rendered,
    pub nearest: &'a RgbImage,
    pub plane_sweep: &'a RgbImage,
}

#[derive(Clone, Debug, Serialize)]
pub struct Score {
    pub psnr: f64,
    pub ssim: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Baselines {
    pub nearest: Score,
    pub plane_sweep: Score,
}

#[derive(Clone, Debug, Serialize)]
pub struct ViewResult {
    pub target: usize,
    pub name: String,
    pub psnr: f64,
    pub ssim: f64,
    pub seconds: f64,
    /// The network's source views, nearest first.
    pub sources: Vec<usize>,
    /// The views only pruning's coarse pass read besides them (absent when none).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub plan_sources: Vec<usize>,
    pub baselines: Baselines,
    /// What pruning left out (absent with `--prune off`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub prune: Option<PruneStats>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Mean {
    pub psnr: f64,
    pub ssim: f64,
    pub seconds: f64,
    pub baselines: Baselines,
}

/// `deepstereo eval`'s JSON.
#[derive(Clone, Debug, Serialize)]
pub struct EvalReport {
    pub scene: String,
    pub model: String,
    pub backend: String,
    pub planes: usize,
    pub views: usize,
    /// `off` or `auto`.
    pub prune: String,
    pub per_view: Vec<ViewResult>,
    pub mean: Mean,
}

/// Renders each held-out view with the network and both baselines, and scores them.
pub fn evaluate(
    backend: &dyn Backend,
    model_name: &str,
    scene: &Scene,
    targets: &[usize],
    settings: &RenderSettings,
    mut on_view: impl FnMut(&ViewResult, &ViewImages<'_>),
) -> Result<EvalReport> {
    let cfg = backend.config().clone();
    let k = settings.source_count(&cfg)?;
    let planes = settings.planes.unwrap_or(cfg.default_render_planes());
    let mut prepared = Prepared::new(scene);
    let mut per_view = Vec::new();
    for &t in targets {
        let truth = scene.load_image(t)?;
        let cam = scene.views[t].camera;
        let held = render_held_out(backend, scene, &mut prepared, t, targets, k, settings)?;
        let HeldOut {
            rendered: r,
            inv_depths: inv,
            sources: srcs,
            plan_sources,
            seconds,
        } = held;
        let nearest = scene.load_image(srcs[0])?;
        let near_score = nearest_score(&nearest, &truth);
        let (ps, ps_secs) = sweep_baseline(&prepared, &srcs, &cam, &inv);
        let v = ViewResult {
            target: t,
            name: scene.views[t].name.clone(),
            psnr: psnr(&r.image, &truth),
            ssim: ssim(&r.image, &truth),
            seconds,
            sources: srcs,
            plan_sources,
            baselines: Baselines {
                nearest: near_score,
                plane_sweep: Score {
                    psnr: psnr(&ps, &truth),
                    ssim: ssim(&ps, &truth),
                    seconds: Some(ps_secs),
                },
            },
            prune: r.prune.clone(),
        };
        on_view(
            &v,
            &ViewImages {
                truth: &truth,
                rendered: &r,
                nearest: &nearest,
                plane_sweep: &ps,
            },
        );
        per_view.push(v);
    }
    if per_view.is_empty() {
        bail!("no held-out views to evaluate");
    }
    Ok(EvalReport {
        scene: scene.root.display().to_string(),
        model: model_name.to_string(),
        backend: backend.name().to_string(),
        planes,
        views: k,
        prune: settings.prune.mode.name().to_string(),
        mean: mean_over(&per_view, |v| (v.psnr, v.ssim, v.seconds, &v.baselines)),
        per_view,
    })
}

/// The nearest source's score against the photograph (NaN when their sizes differ).
fn nearest_score(nearest: &RgbImage, truth: &RgbImage) -> Score {
    if nearest.width == truth.width && nearest.height == truth.height {
        Score {
            psnr: psnr(nearest, truth),
            ssim: ssim(nearest, truth),
            seconds: None,
        }
    } else {
        Score {
            psnr: f64::NAN,
            ssim: f64::NAN,
            seconds: None,
        }
    }
}

/// The classical plane sweep of `target` on the planes `inv` from the sources `srcs`
/// (their full-resolution pyramid levels), and the seconds it took.
fn sweep_baseline(
    prepared: &Prepared,
    srcs: &[usize],
    target: &Camera,
    inv: &[f64],
) -> (RgbImage, f64) {
    let t1 = Instant::now();
    let sources: Vec<Source<'_>> = srcs
        .iter()
        .filter_map(|&i| prepared.pyramids[i].as_ref().map(|p| p.level(0)))
        .collect();
    let (ps, _) = plane_sweep(target, &sources, inv);
    (ps, t1.elapsed().as_secs_f64())
}

/// An item's PSNR, SSIM, seconds and baselines, as [`mean_over`] averages them.
pub type Scores<'a> = (f64, f64, f64, &'a Baselines);

/// The mean of every score over `items` (none: 0/0), `scores` giving an item's
/// [`Scores`]: over the views of a scene, or over scenes' means.
pub fn mean_over<T>(items: &[T], scores: impl Fn(&T) -> Scores<'_>) -> Mean {
    let n = items.len().max(1) as f64;
    let avg = |f: &dyn Fn(Scores<'_>) -> f64| items.iter().map(|x| f(scores(x))).sum::<f64>() / n;
    Mean {
        psnr: avg(&|s| s.0),
        ssim: avg(&|s| s.1),
        seconds: avg(&|s| s.2),
        baselines: Baselines {
            nearest: Score {
                psnr: avg(&|s| s.3.nearest.psnr),
                ssim: avg(&|s| s.3.nearest.ssim),
                seconds: None,
            },
            plane_sweep: Score {
                psnr: avg(&|s| s.3.plane_sweep.psnr),
                ssim: avg(&|s| s.3.plane_sweep.ssim),
                seconds: Some(avg(&|s| s.3.plane_sweep.seconds.unwrap_or(0.0))),
            },
        },
    }
}

/// The network's render of a held-out view, and what made it.
pub struct HeldOut {
    pub rendered: Rendered,
    /// The requested inverse depths, near to far.
    pub inv_depths: Vec<f64>,
    /// The network's source views (none of them held out), nearest first.
    pub sources: Vec<usize>,
    /// The views only pruning's coarse pass read (none of them held out either).
    pub plan_sources: Vec<usize>,
    pub seconds: f64,
}

/// Renders held-out view `t` from `k` sources among the views not in `holdout`, as
/// `eval` does.
pub fn render_held_out(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    t: usize,
    holdout: &[usize],
    k: usize,
    settings: &RenderSettings,
) -> Result<HeldOut> {
    if t >= scene.views.len() {
        bail!(
            "held-out view {t} is out of range: the scene has {} views",
            scene.views.len()
        );
    }
    let cam = scene.views[t].camera;
    let mut sources = pick_planned_sources(scene, &cam, holdout, (k, backend.config()), settings);
    let t0 = Instant::now();
    let (rendered, inv_depths) = render_camera(
        backend,
        scene,
        prepared,
        &cam,
        &sources,
        settings,
        &|_, _| {},
    )?;
    let plan_sources = sources.split_off(k.min(sources.len()));
    Ok(HeldOut {
        rendered,
        inv_depths,
        sources,
        plan_sources,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Held-out view indices from `--holdout 0,8,16` or `--llffhold N` (every Nth view).
pub fn holdout_list(
    holdout: Option<&str>,
    llffhold: Option<usize>,
    n: usize,
) -> Result<Vec<usize>> {
    match (holdout, llffhold) {
        (Some(h), None) => h
            .split(',')
            .map(|s| {
                s.trim()
                    .parse::<usize>()
                    .with_context(|| format!("--holdout: '{s}' is not a view index"))
            })
            .collect(),
        (None, Some(0)) => bail!("--llffhold must be at least 1"),
        (None, Some(k)) => Ok((0..n).step_by(k).collect()),
        (None, None) => bail!("pass --holdout I,J,... or --llffhold N"),
        (Some(_), Some(_)) => bail!("pass either --holdout or --llffhold, not both"),
    }
}
