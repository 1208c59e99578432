//! Rendering with a model (role): the settings and source choice below, the embedded
//! model and model loading ([`models`]), the MPI bake ([`mpi`]) and camera paths
//! ([`path`]). Uses `deepstereo-core` only; never the command line.
//!
//! Rendering scene views with a model (candle or onnxruntime) and evaluating them against
//! the withheld photographs and the classical baselines.

mod eval;
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
pub use eval::{
    evaluate, holdout_list, mean_over, render_held_out, Baselines, EvalReport, HeldOut, Mean,
    Score, Scores, ViewImages, ViewResult,
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
