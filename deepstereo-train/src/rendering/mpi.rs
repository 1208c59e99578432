//! Multiplane images of a scene: baked by the network at a camera from the scene's views
//! (`deepstereo_core::mpi` holds the format and the rendering), and held-out views seen
//! through them, beside the network's own renders of those views.

use crate::rendering::{
    network_inputs, pick_planned_sources, plan_pruning, render_held_out, source_inputs,
    spanned_planes, PlaneSpan, Prepared, RenderSettings,
};
use anyhow::{anyhow, bail, Result};
use deepstereo_core::camera::Camera;
use deepstereo_core::config::Config;
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::metrics::{psnr, ssim};
use deepstereo_core::mpi::planned::layers_planned;
use deepstereo_core::mpi::{io, layers, reference_camera, render_blend, viewer, with_margin, Mpi};
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use deepstereo_core::sweep::Source;
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// What an MPI's bake adds to the network's layers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BakeOptions {
    /// Pixels added on every side of the reference image ([`with_margin`]).
    pub margin: u32,
    /// The radius (texels) of the box each texel's selection is averaged over
    /// ([`Mpi::with_smoothed_selection`]); 0: the network's own.
    pub smooth: usize,
    /// The colour scale of the photograph's agreement with the other views, which
    /// reweighs the residual bake's selection before it is smoothed
    /// ([`Mpi::with_photo_agreement`]); 0: not reweighed.
    pub agree: f64,
}

/// The radius `mpi` smooths the selection with when `--smooth` is not given: one MPI at
/// held-out views of the training scenes and of the evaluation scenes is closer to the
/// photographs with it than with radius 0 (docs/results.md, "MPIs").
pub const BAKE_SMOOTH: usize = 10;

/// The colour scale `mpi` reweighs the residual bake's selection with when `--agree` is
/// not given (chosen on training scenes: docs/results.md, "MPIs").
pub const BAKE_AGREE: f64 = 0.0125;

/// Bakes the MPI of `camera` as [`network_mpi`] does, then smooths its selection
/// (`opts.smooth`) and restores its composite in the reference image to the network's
/// render ([`finish`]).
pub fn bake_camera(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    (camera, opts): (&Camera, BakeOptions),
    sources: &[usize],
    settings: &RenderSettings,
    progress: &dyn Fn(usize, usize),
) -> Result<Mpi> {
    let place = (camera, opts.margin);
    let mpi = network_mpi(backend, scene, prepared, place, sources, settings, progress)?;
    finish(mpi, opts.smooth, None)
}

/// The network's MPI of `camera` (made a pinhole at its mid-readout pose, with `margin`
/// pixels more on every side: [`with_margin`]) from the scene's views `sources` (the
/// first `k` of them, `k` from `settings`; pruning's coarse pass reads them all) at the
/// settings' planes. With pruning on, as `render` prunes that camera ([`plan_pruning`]):
/// the planes run, and per block the planes the coarse pass keeps (alpha 0 on the
/// others), so the MPI's composite is the pruned render; with `--prune off`, every plane
/// of every pixel.
fn network_mpi(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    (camera, margin): (&Camera, u32),
    sources: &[usize],
    settings: &RenderSettings,
    progress: &dyn Fn(usize, usize),
) -> Result<Mpi> {
    let cfg = backend.config().clone();
    let k = settings.source_count(&cfg)?;
    let (srcs, inv) = source_inputs(&cfg, scene, prepared, sources, settings)?;
    // source_inputs refused fewer than k sources.
    let network = network_inputs(&srcs, sources.len() - k);
    check_margin(camera, margin)?;
    // The margin is added to the pinhole at the mid-readout pose (its height decides it).
    let camera = with_margin(&reference_camera(camera), margin);
    let inv = spanned_planes(scene, &camera, sources, inv, settings.span);
    let (inv, (colours, selection)) = if settings.prune.is_on() {
        let (inv, pruner) = plan_pruning(backend, scene, &camera, &srcs, sources, &inv, settings)?;
        let planned = layers_planned(
            backend,
            &camera,
            network,
            &inv,
            settings.tile,
            &pruner,
            progress,
        )?;
        (inv, planned)
    } else {
        let whole = layers(backend, &camera, network, &inv, settings.tile, progress)?;
        (inv, whole)
    };
    let mut mpi = Mpi::from_layers(camera, inv, &colours, &selection)?;
    mpi.margin = margin;
    Ok(mpi)
}

/// `mpi` with its selection smoothed over boxes of radius `smooth`
/// ([`Mpi::with_smoothed_selection`]; 0: as it is) and its composite in the reference
/// image made `picture` ([`Mpi::with_composite`]), or, without one, what it was before
/// smoothing.
fn finish(mpi: Mpi, smooth: usize, picture: Option<RgbImage>) -> Result<Mpi> {
    if smooth == 0 && picture.is_none() {
        return Ok(mpi);
    }
    let picture = picture.unwrap_or_else(|| mpi.composite());
    let smoothed = if smooth > 0 {
        mpi.with_smoothed_selection(smooth)?
    } else {
        mpi
    };
    Ok(smoothed.with_composite(&picture)?)
}

/// An MPI baked at `camera`: at view `view`'s (its photograph entering as `own` says,
/// see [`bake_view`]), or, at a camera that is no view, from the sources a render there
/// would read ([`bake_camera`]); with the sources it read.
#[allow(clippy::too_many_arguments)]
pub fn bake_at(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    (camera, view, opts): (&Camera, Option<usize>, BakeOptions),
    holdout: &[usize],
    own: OwnPhoto,
    settings: &RenderSettings,
    progress: &dyn Fn(usize, usize),
) -> Result<(Mpi, Vec<usize>)> {
    if let Some(v) = view {
        let place = (v, opts);
        return bake_view(
            backend, scene, prepared, place, holdout, own, settings, progress,
        );
    }
    let cfg = backend.config();
    let k = settings.source_count(cfg)?;
    let srcs = pick_planned_sources(scene, camera, holdout, (k, cfg), settings);
    let place = (camera, opts);
    let mpi = bake_camera(backend, scene, prepared, place, &srcs, settings, progress)?;
    Ok((mpi, srcs[..k.min(srcs.len())].to_vec()))
}

/// Source views an MPI of the any-number-of-views family is baked from when `--views`
/// is not given. An MPI is seen from cameras around its reference, and sources beyond
/// the nearest four see what those cameras see: one MPI from 8 views is 0.6 dB better at
/// held-out views than from the model's 4 (docs/results.md, "MPIs").
pub const BAKE_VIEWS: usize = 8;

/// Where an MPI's planes lie when `--plane-span` is not given: over the depths its
/// reference camera sees. Seen from elsewhere, an MPI shows a surface between two planes
/// as a blend of both, shifted apart by their disparity; planes beyond what the camera
/// sees hold nothing, so spreading them all over its depths (on juicebox 10 to 19 of the
/// scene's 32 planes lie there for most views) brings one MPI up to 0.8 dB closer to the
/// held-out views at the same frame time, for a longer bake (docs/results.md, "MPIs").
pub const BAKE_SPAN: PlaneSpan = PlaneSpan::View;

/// The settings an MPI is baked with: `settings`, where `--views` was not given and the
/// model takes any number of views, with [`BAKE_VIEWS`] sources, or as many as the
/// scene offers (`available`) when fewer, but no fewer than the model's default; where
/// `--plane-span` was not given, [`BAKE_SPAN`].
pub fn bake_settings(settings: &RenderSettings, cfg: &Config, available: usize) -> RenderSettings {
    let mut s = settings.clone();
    if s.views.is_none() && cfg.pool.is_some() {
        s.views = Some(BAKE_VIEWS.min(available).max(cfg.views));
    }
    s.span = s.span.or(Some(BAKE_SPAN));
    s
}

/// The sources of an MPI baked at view `reference`: `k` views that are not held out,
/// chosen as `render` chooses them, followed by those only pruning's coarse pass reads
/// ([`pick_planned_sources`] with the model `cfg`). With `own_photo`, `reference` itself
/// is among them (as for `render --pose` at its camera: the MPI then shows the
/// photograph at its reference); without, the planes' colours come from the other views
/// only (as for `render --target`).
pub fn reference_sources(
    scene: &Scene,
    reference: usize,
    holdout: &[usize],
    own_photo: bool,
    (k, cfg): (usize, &Config),
    settings: &RenderSettings,
) -> Result<Vec<usize>> {
    if holdout.contains(&reference) {
        bail!("view {reference} is held out: an MPI is baked at a view that is not");
    }
    let cam = scene.views[reference].camera;
    let mut exclude = holdout.to_vec();
    if !own_photo {
        exclude.push(reference);
    }
    Ok(pick_planned_sources(
        scene,
        &cam,
        &exclude,
        (k, cfg),
        settings,
    ))
}

/// How a view's own photograph enters an MPI baked at its camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum OwnPhoto {
    /// Left out: the planes come from the other views, and the MPI shows the network's
    /// prediction of the view at its camera (`--exclude-own-photo`).
    Excluded,
    /// One of the sources, as `render --pose` at that camera runs the network
    /// (`--own-photo-as-source`).
    Source,
    /// The MPI of the other views, its colours moved so that its composite at the
    /// reference is the render with the photograph among the sources
    /// ([`Mpi::with_composite`]): the planes' depths of [`OwnPhoto::Excluded`], the
    /// picture of [`OwnPhoto::Source`] at the reference; the margin, which the photograph
    /// does not show, is the other views' alone. The default: seen from elsewhere it
    /// scores above both (docs/results.md, "MPIs").
    Residual,
}

/// Bakes the MPI of view `reference` (not held out), with `opts` and `own` for its
/// photograph, from `k` views chosen by [`reference_sources`]; and the views it was baked
/// from (with [`OwnPhoto::Residual`], the reference and the views of its
/// [`OwnPhoto::Source`] bake).
#[allow(clippy::too_many_arguments)]
pub fn bake_view(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    (reference, opts): (usize, BakeOptions),
    holdout: &[usize],
    own: OwnPhoto,
    settings: &RenderSettings,
    progress: &dyn Fn(usize, usize),
) -> Result<(Mpi, Vec<usize>)> {
    let cfg = backend.config();
    let k = settings.source_count(cfg)?;
    let camera = scene.views[reference].camera;
    let with_own = own != OwnPhoto::Excluded;
    let srcs = reference_sources(scene, reference, holdout, with_own, (k, cfg), settings)?;
    let network = srcs[..k.min(srcs.len())].to_vec();
    if own != OwnPhoto::Residual {
        let place = (&camera, opts);
        let mpi = bake_camera(backend, scene, prepared, place, &srcs, settings, progress)?;
        return Ok((mpi, network));
    }
    // The render with the photograph gives only its picture, in the reference image (the
    // margin is the other views' alone, so it is not rendered); the other views' MPI its
    // depths, smoothed once and moved straight to that picture.
    check_margin(&camera, opts.margin)?;
    let place = (&camera, 0);
    let photo = network_mpi(backend, scene, prepared, place, &srcs, settings, progress)?;
    let picture = with_border(&photo.composite(), opts.margin);
    drop(photo);
    let others = reference_sources(scene, reference, holdout, false, (k, cfg), settings)?;
    let place = (&camera, opts.margin);
    let base = network_mpi(backend, scene, prepared, place, &others, settings, progress)?;
    let others = &others[..k.min(others.len())];
    let levels = backend.config().levels;
    let base = agree_with_photo(
        scene,
        prepared,
        levels,
        (reference, others),
        base,
        opts.agree,
    )?;
    Ok((finish(base, opts.smooth, Some(picture))?, network))
}

/// `mpi` reweighed by view `reference`'s photograph's agreement with the views `others`
/// at each plane ([`Mpi::with_photo_agreement`]), at full resolution (a view not loaded
/// yet is loaded with the model's pyramid `levels`); as it is when `tau` is 0.
fn agree_with_photo(
    scene: &Scene,
    prepared: &mut Prepared,
    levels: usize,
    (reference, others): (usize, &[usize]),
    mpi: Mpi,
    tau: f64,
) -> Result<Mpi> {
    if tau == 0.0 {
        return Ok(mpi);
    }
    for &i in std::iter::once(&reference).chain(others) {
        prepared.get(scene, i, levels)?;
    }
    let source = |i: usize| {
        let p = prepared.pyramids[i].as_ref();
        p.map(|p| p.level(0))
            .ok_or_else(|| anyhow!("view {i} was not loaded"))
    };
    let photo = source(reference)?;
    let others: Vec<Source> = others.iter().map(|&i| source(i)).collect::<Result<_>>()?;
    Ok(mpi.with_photo_agreement(photo, &others, tau)?)
}

/// Refuses a margin wider than `camera`'s larger side.
fn check_margin(camera: &Camera, margin: u32) -> Result<()> {
    let side = camera.intrinsics.width.max(camera.intrinsics.height);
    if margin > side {
        bail!(
            "--margin {margin}: at most the reference image's larger side ({side} pixels); \
             beyond it the network only extrapolates"
        );
    }
    Ok(())
}

/// `image` inside a black border of `margin` pixels on every side.
fn with_border(image: &RgbImage, margin: u32) -> RgbImage {
    let (w, m) = (image.width as usize, margin as usize);
    let mut out = RgbImage::new(image.width + 2 * margin, image.height + 2 * margin);
    let stride = (w + 2 * m) * 3;
    for (y, row) in image.data.chunks(w * 3).enumerate() {
        let at = (y + m) * stride + m * 3;
        out.data[at..at + w * 3].copy_from_slice(row);
    }
    out
}

/// The `n` views that are not held out nearest to view `target` (by camera centre),
/// nearest first.
pub fn nearest_kept_views(scene: &Scene, target: usize, holdout: &[usize], n: usize) -> Vec<usize> {
    let c = scene.views[target].camera.pose.centre();
    let mut kept: Vec<(f64, usize)> = (0..scene.views.len())
        .filter(|i| !holdout.contains(i))
        .map(|i| ((scene.views[i].camera.pose.centre() - c).length(), i))
        .collect();
    kept.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    kept.into_iter().take(n).map(|(_, i)| i).collect()
}

/// How held-out views are seen through MPIs.
#[derive(Clone, Copy, Debug)]
pub struct MpiEvalOptions {
    /// MPIs per held-out view, baked at its nearest views that are not held out and
    /// blended by distance.
    pub mpis: usize,
    /// How each MPI's reference photograph enters it.
    pub own_photo: OwnPhoto,
    /// The margin and smoothing of each MPI.
    pub bake: BakeOptions,
}

/// One held-out view rendered by the network and through MPIs baked at its nearest
/// views that are not held out.
#[derive(Clone, Debug, Serialize)]
pub struct MpiViewResult {
    pub target: usize,
    pub name: String,
    /// The views the MPIs were baked at.
    pub references: Vec<usize>,
    pub network_psnr: f64,
    pub network_ssim: f64,
    pub mpi_psnr: f64,
    pub mpi_ssim: f64,
    /// The MPIs' render against the network's render of the same view.
    pub mpi_vs_network_psnr: f64,
    /// The network's render of the held-out view.
    pub network_seconds: f64,
    /// Baking the MPIs (the network at each reference camera, pruned as `render` prunes it
    /// unless `--prune off`).
    pub bake_seconds: f64,
    /// Rendering the held-out view from the baked MPIs on the CPU.
    pub mpi_render_seconds: f64,
}

/// Every held-out view of `holdout` rendered by the network (as `eval` does, with
/// `settings`) and through MPIs baked at its nearest views that are not held out (with
/// `bake`: [`bake_settings`]).
pub fn eval_through_mpi(
    backend: &dyn Backend,
    scene: &Scene,
    holdout: &[usize],
    opts: MpiEvalOptions,
    (settings, bake): (&RenderSettings, &RenderSettings),
    mut on_view: impl FnMut(&MpiViewResult),
) -> Result<Vec<MpiViewResult>> {
    let k = settings.source_count(backend.config())?;
    if opts.mpis == 0 || opts.mpis > viewer::MAX_MPIS {
        bail!("1 to {} MPIs per view, not {}", viewer::MAX_MPIS, opts.mpis);
    }
    let mut prepared = Prepared::new(scene);
    let mut out = Vec::new();
    for &t in holdout {
        let held = render_held_out(backend, scene, &mut prepared, t, holdout, k, settings)?;
        let (net, network_seconds) = (held.rendered, held.seconds);
        let references = nearest_kept_views(scene, t, holdout, opts.mpis);
        if references.is_empty() {
            bail!("every view is held out: no view is left to bake an MPI at");
        }
        let truth = scene.load_image(t)?;
        let cam = scene.views[t].camera;
        let t0 = Instant::now();
        let mut mpis = Vec::new();
        for &r in &references {
            let none = &|_, _| {};
            let place = (r, opts.bake);
            let (mpi, _) = bake_view(
                backend,
                scene,
                &mut prepared,
                place,
                holdout,
                opts.own_photo,
                bake,
                none,
            )?;
            mpis.push(mpi);
        }
        let bake_seconds = t0.elapsed().as_secs_f64();
        let t0 = Instant::now();
        let img = render_blend(&mpis, &cam);
        let mpi_render_seconds = t0.elapsed().as_secs_f64();
        let r = MpiViewResult {
            target: t,
            name: scene.views[t].name.clone(),
            references,
            network_psnr: psnr(&net.image, &truth),
            network_ssim: ssim(&net.image, &truth),
            mpi_psnr: psnr(&img, &truth),
            mpi_ssim: ssim(&img, &truth),
            mpi_vs_network_psnr: psnr(&img, &net.image),
            network_seconds,
            bake_seconds,
            mpi_render_seconds,
        };
        on_view(&r);
        out.push(r);
    }
    Ok(out)
}

/// The MPIs of `dir` as `deepstereo mpi` writes them (one, or one per subdirectory).
pub fn read_mpis(dir: &Path) -> Result<Vec<Mpi>> {
    let mpis = io::read_dir(dir)?;
    if mpis.len() > viewer::MAX_MPIS {
        bail!(
            "{}: {} MPIs, at most {} are blended",
            dir.display(),
            mpis.len(),
            viewer::MAX_MPIS
        );
    }
    Ok(mpis)
}
