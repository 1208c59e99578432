//! Rendering with a model (role): the settings and source choice below, the embedded
//! model and model loading ([`models`]), the MPI bake ([`mpi`]) and camera paths
//! ([`path`]). Uses `deepstereo-core` only; never the command line.
//!
//! Rendering scene views with a model (candle or onnxruntime) and evaluating them against
//! the withheld photographs and the classical baselines.

pub mod models;
pub mod mpi;
pub mod path;
pub mod sweep;

use anyhow::{bail, Context, Result};
use deepstereo_core::baseline::plane_sweep;
use deepstereo_core::camera::Camera;
use deepstereo_core::config::Config;
use deepstereo_core::geometry::inverse_depths;
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::inputs::PyramidSource;
use deepstereo_core::metrics::{psnr, ssim};
use deepstereo_core::prune::{
    guide_planes, max_plane_step, network_guide, plane_range_from_bounds, plane_range_from_points,
    rank_views, span_planes, thin_planes, CoarsePass, PruneOptions, PruneStats, Pruner,
};
use deepstereo_core::render::{render_view, render_view_pruned, Backend, Rendered};
use deepstereo_core::scene::{nearest_to_point, Scene};
use deepstereo_core::sweep::Source;
use serde::Serialize;
use std::time::Instant;

pub use crate::rendering::models::{
    candle_backend, make_backend, model_name, BackendKind, EMBEDDED_MODEL, EMBEDDED_NAME,
};

/// How to render: shared by `render`, `eval`, `report` and `demo`.
#[derive(Clone, Debug, Serialize)]
pub struct RenderSettings {
    /// Planes (`None`: the model's default).
    pub planes: Option<usize>,
    /// Source views (default: the model's). The paper's family takes at most its
    /// config's (its remaining inputs are then empty views, alpha 0 everywhere, as for
    /// pixels no source sees); the any-number-of-views family any number.
    pub views: Option<usize>,
    /// Output tile side for rendering (bounded memory).
    pub tile: usize,
    /// What to leave out (`deepstereo_core::prune`).
    pub prune: PruneOptions,
    /// Source views pruning's coarse pass reads ([`RenderSettings::plan_count`]): the
    /// network's and, up to this many in all, the next best-ranked of the scene's others.
    pub plan_views: usize,
    /// Where the planes lie (`None`: the command's default, [`PlaneSpan::Scene`] but for
    /// `mpi`'s bakes).
    pub span: Option<PlaneSpan>,
}

/// Where a render's planes lie, uniform in inverse depth either way.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum PlaneSpan {
    /// Between the scene's near and far.
    Scene,
    /// As many planes over the depths the camera sees: between the nearest and farthest
    /// of the scene's sparse points in its view (or its sources' per-view bounds), widened
    /// as pruning widens that range, so every plane samples depths the view holds. The
    /// scene's planes where neither says anything.
    View,
}

impl RenderSettings {
    /// The number of real source views to use with a model of config `cfg`.
    pub fn source_count(&self, cfg: &Config) -> Result<usize> {
        let k = self.views.unwrap_or(cfg.views);
        if cfg.pool.is_some() {
            if !cfg.accepts_views(k) {
                bail!(
                    "--views {k}: this model takes 1 to {} source views",
                    deepstereo_core::config::MAX_VIEWS
                );
            }
            return Ok(k);
        }
        if k == 0 || k > cfg.views {
            bail!(
                "--views {k}: this model takes 1 to {} source views (fewer leave its other inputs empty)",
                cfg.views
            );
        }
        Ok(k)
    }

    /// How many views pruning's coarse pass reads when the network reads `k`:
    /// `plan_views` with pruning on, for the any-number-of-views family, when more than
    /// `k`; else `k` (the paper's family takes its own count).
    pub fn plan_count(&self, cfg: &Config, k: usize) -> usize {
        if self.prune.is_on() && cfg.pool.is_some() {
            k.max(self.plan_views)
        } else {
            k
        }
    }
}

/// Source views pruning's coarse pass reads by default ([`RenderSettings::plan_views`],
/// `--prune-views`): at 2 and 4 views the network renders the six evaluation scenes
/// 0.04-0.80 dB better when the planes it runs are chosen with 8 views, for about the
/// same time, and no better with 12 (docs/performance.md, "Planning with more views";
/// docs/experiments.md).
pub const DEFAULT_PLAN_VIEWS: usize = 8;

/// The `k` source views for `target`, never one of `exclude` (its own index in the
/// scene, and in an evaluation every held-out view: sources come from the other views
/// only): the nearest with pruning off; with pruning on, those that see most of the
/// target frustum for their distance ([`rank_views`]).
pub fn pick_sources(
    scene: &Scene,
    target: &Camera,
    exclude: &[usize],
    k: usize,
    settings: &RenderSettings,
) -> Vec<usize> {
    let allowed: Vec<usize> = (0..scene.views.len())
        .filter(|i| !exclude.contains(i))
        .collect();
    let picked = if settings.prune.is_on() {
        let cams: Vec<Camera> = allowed.iter().map(|&i| scene.views[i].camera).collect();
        rank_views(&cams, target, k, None, scene.near, scene.far).0
    } else {
        let views: Vec<_> = allowed.iter().map(|&i| scene.views[i].clone()).collect();
        nearest_to_point(&views, target.pose.centre(), k, None)
    };
    picked.into_iter().map(|j| allowed[j]).collect()
}

/// A scene's views prepared for rendering (pyramids built once).
pub struct Prepared {
    pub pyramids: Vec<Option<PyramidSource>>,
    /// The paper family's padding: a view that sees nothing (set by [`source_inputs`]).
    empty: Option<PyramidSource>,
}

impl Prepared {
    pub fn new(scene: &Scene) -> Self {
        Self {
            pyramids: vec![None; scene.views.len()],
            empty: None,
        }
    }

    /// The pyramid of view `i`, loading its image on first use.
    pub fn get(&mut self, scene: &Scene, i: usize, levels: usize) -> Result<&PyramidSource> {
        if self.pyramids[i].is_none() {
            let img = scene.load_image(i)?;
            self.pyramids[i] = Some(PyramidSource::new(&scene.views[i].camera, &img, levels));
        }
        self.pyramids[i].as_ref().context("pyramid missing")
    }
}

/// [`pick_sources`]'s `k` views, followed by the views only pruning's coarse pass reads
/// (none with pruning off): the next best-ranked of the others, never one of `exclude`,
/// up to [`RenderSettings::plan_count`] in all.
pub fn pick_planned_sources(
    scene: &Scene,
    target: &Camera,
    exclude: &[usize],
    (k, cfg): (usize, &Config),
    settings: &RenderSettings,
) -> Vec<usize> {
    let mut picked = pick_sources(scene, target, exclude, k, settings);
    let plan = settings.plan_count(cfg, k);
    if plan > k {
        for j in pick_sources(scene, target, exclude, plan, settings) {
            if !picked.contains(&j) {
                picked.push(j);
            }
        }
    }
    picked
}

/// What the model takes for the first `k` of `sources` (`k` from `settings`): their
/// pyramids (loaded on first use) padded, for the paper family, with views that see
/// nothing up to its input count, then the pyramids of the others (the views only
/// pruning's coarse pass reads, [`pick_planned_sources`]); and the requested inverse
/// depths, near to far.
pub fn source_inputs<'a>(
    cfg: &Config,
    scene: &Scene,
    prepared: &'a mut Prepared,
    sources: &[usize],
    settings: &RenderSettings,
) -> Result<(Vec<&'a PyramidSource>, Vec<f64>)> {
    let k = settings.source_count(cfg)?;
    if sources.is_empty() {
        bail!(
            "{k} source views are needed and none is left: each of the scene's {} views is \
             the target or held out (hold out fewer: a larger --llffhold, a shorter --holdout)",
            scene.views.len()
        );
    }
    if sources.len() < k {
        bail!(
            "{k} source views are needed, {} are left besides the target and any held-out \
             views (try --views {})",
            sources.len(),
            sources.len()
        );
    }
    let (network, plan) = sources.split_at(k);
    if cfg.pool.is_none() && !plan.is_empty() {
        bail!(
            "{} source views for a model of the paper's family, which reads its {k} alone",
            sources.len()
        );
    }
    let planes = settings.planes.unwrap_or(cfg.default_render_planes());
    if planes == 0 {
        bail!("--planes must be at least 1");
    }
    for &i in sources {
        prepared.get(scene, i, cfg.levels)?;
    }
    prepared.empty = (network.first())
        .and_then(|&i| prepared.pyramids[i].as_ref())
        .map(|s| PyramidSource::empty(&s.cameras[0], cfg.levels));
    let prepared: &'a Prepared = prepared;
    let pyramid = |&i: &usize| prepared.pyramids[i].as_ref();
    let mut srcs: Vec<&PyramidSource> = network.iter().filter_map(pyramid).collect();
    if let Some(e) = prepared.empty.as_ref().filter(|_| cfg.pool.is_none()) {
        while srcs.len() < cfg.views {
            srcs.push(e);
        }
    }
    srcs.extend(plan.iter().filter_map(pyramid));
    Ok((srcs, inverse_depths(scene.near, scene.far, planes)))
}

/// Renders `target` (a camera) from the scene's views `sources`.
pub fn render_camera(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    target: &Camera,
    sources: &[usize],
    settings: &RenderSettings,
    progress: &dyn Fn(usize, usize),
) -> Result<(Rendered, Vec<f64>)> {
    let cfg = backend.config().clone();
    let k = settings.source_count(&cfg)?;
    let (srcs, requested) = source_inputs(&cfg, scene, prepared, sources, settings)?;
    let network = network_inputs(&srcs, sources.len() - k);
    let requested = spanned_planes(scene, target, sources, requested, settings.span);
    if !settings.prune.is_on() {
        let r = render_view(
            backend,
            target,
            network,
            &requested,
            settings.tile,
            progress,
        )?;
        return Ok((r, requested));
    }
    let (inv, pruner) = plan_pruning(backend, scene, target, &srcs, sources, &requested, settings)?;
    let mut r = render_view_pruned(
        backend,
        target,
        network,
        &inv,
        settings.tile,
        Some(&pruner),
        progress,
    )?;
    if let Some(st) = r.prune.as_mut() {
        if inv.len() < requested.len() {
            st.thinned = Some((requested.len(), inv.len()));
            st.planes_total = st.planes_total / inv.len() * requested.len();
        }
    }
    Ok((r, requested))
}

/// The network's inputs among [`source_inputs`]'s `srcs`: all but the last `plan_only`
/// (the views only pruning's coarse pass reads).
pub fn network_inputs<'a, 'b>(
    srcs: &'a [&'b PyramidSource],
    plan_only: usize,
) -> &'a [&'b PyramidSource] {
    &srcs[..srcs.len().saturating_sub(plan_only)]
}

/// Pruning's plan for rendering `target` from `srcs` (the pyramids of the scene's views
/// `sources`, which pick their depth bounds: the network's, then any its coarse pass
/// reads too) at the `requested` inverse depths: the planes run (fewer, spread evenly,
/// when the requested ones are closer than `max_step` pixels apart in every one of the
/// network's sources: a subset of the requested planes) and the pruner, with the
/// network's coarse pass when the settings ask for it.
pub fn plan_pruning<'a>(
    backend: &dyn Backend,
    scene: &Scene,
    target: &Camera,
    srcs: &'a [&'a PyramidSource],
    sources: &[usize],
    requested: &[f64],
    settings: &RenderSettings,
) -> Result<(Vec<f64>, Pruner<'a>)> {
    let cfg = backend.config();
    // Planes closer than the step the network's own views resolve are thinned; the
    // depth range and the coarse pass read every view.
    let k = settings.source_count(cfg)?.min(srcs.len());
    let cams: Vec<&Camera> = srcs[..k].iter().map(|s| &s.cameras[0]).collect();
    let step = max_plane_step(target, &cams, requested);
    let inv: Vec<f64> = thin_planes(requested.len(), step, settings.prune.max_step, cfg.planes)
        .into_iter()
        .map(|z| requested[z])
        .collect();
    let range = camera_plane_range(scene, target, sources, &inv);
    let mut pruner = Pruner::new(cfg, target, srcs, &inv, range, &settings.prune);
    if settings.prune.coarse == CoarsePass::Network {
        let t0 = Instant::now();
        let guide = network_guide(
            backend,
            target,
            srcs,
            &inv,
            pruner.range(),
            settings.prune.guide_level,
            settings.tile,
            guide_planes(cfg.planes, inv.len()),
            settings.prune.error > 0.0,
        )?;
        if let Some(g) = guide {
            pruner = pruner.with_guide(g, t0.elapsed().as_secs_f64());
        }
    }
    Ok((inv, pruner))
}

/// The planes of `inv` (`first..=last`) that `target` can need: those the scene's sparse
/// points in its view need, or else those the per-view bounds of the scene's views
/// `sources` allow (`deepstereo_core::prune::range`); `None` when neither says.
pub fn camera_plane_range(
    scene: &Scene,
    target: &Camera,
    sources: &[usize],
    inv: &[f64],
) -> Option<(usize, usize)> {
    let bounds: Vec<Option<(f64, f64)>> = sources.iter().map(|&i| scene.views[i].bounds).collect();
    plane_range_from_points(target, &scene.points, inv)
        .or_else(|| plane_range_from_bounds(&bounds, inv))
}

/// The planes to render `target` at from the scene's views `sources`: `requested` (the
/// scene's), or with [`PlaneSpan::View`] as many spread over the range of them
/// [`camera_plane_range`] gives ([`span_planes`]).
pub fn spanned_planes(
    scene: &Scene,
    target: &Camera,
    sources: &[usize],
    requested: Vec<f64>,
    span: Option<PlaneSpan>,
) -> Vec<f64> {
    match span {
        Some(PlaneSpan::View) => match camera_plane_range(scene, target, sources, &requested) {
            Some(range) => span_planes(&requested, range),
            None => requested,
        },
        Some(PlaneSpan::Scene) | None => requested,
    }
}

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

#[cfg(test)]
mod tests {
    use super::*;
    use deepstereo_core::prune::PruneMode;

    /// The views pruning's coarse pass reads besides the network's: the next best-ranked,
    /// never an excluded one, as many as asked for and the scene offers; none with pruning
    /// off, for the paper's family, or when no more than the network's are asked for.
    #[test]
    fn the_coarse_pass_reads_the_networks_views_then_the_next_ranked() -> Result<()> {
        let dir = tempfile::tempdir()?;
        let (scene, tiny, _, mut settings) =
            crate::test_scene::tiny_case(dir.path(), 5, (40, 32), 32)?;
        let any = Config::nviews();
        let target = scene.views[0].camera;
        let exclude = [0, 3];
        settings.prune.mode = PruneMode::Auto;
        settings.plan_views = 4;
        let picked = pick_planned_sources(&scene, &target, &exclude, (2, &any), &settings);
        assert_eq!(picked.len(), 4, "{picked:?}");
        assert_eq!(
            picked[..2],
            pick_sources(&scene, &target, &exclude, 2, &settings)[..]
        );
        let ranked = pick_sources(&scene, &target, &exclude, 4, &settings);
        for v in &picked {
            assert!(!exclude.contains(v) && ranked.contains(v), "{picked:?}");
            assert_eq!(picked.iter().filter(|w| *w == v).count(), 1, "{picked:?}");
        }
        // More than the scene offers: every view not excluded.
        settings.plan_views = 10;
        let all = pick_planned_sources(&scene, &target, &exclude, (2, &any), &settings);
        assert_eq!(all.len(), scene.views.len() - exclude.len(), "{all:?}");
        for (plan, cfg, mode) in [
            (10, &tiny, PruneMode::Auto),
            (10, &any, PruneMode::Off),
            (2, &any, PruneMode::Auto),
            (0, &any, PruneMode::Auto),
        ] {
            settings.plan_views = plan;
            settings.prune.mode = mode;
            let only = pick_planned_sources(&scene, &target, &exclude, (2, cfg), &settings);
            let network = pick_sources(&scene, &target, &exclude, 2, &settings);
            assert_eq!(only, network, "plan {plan}, {mode:?}");
        }
        Ok(())
    }
}
