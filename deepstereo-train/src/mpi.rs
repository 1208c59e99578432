//! Multiplane images of a scene: baked by the network at a camera from the scene's views
//! (`deepstereo_core::mpi` holds the format and the rendering), and held-out views seen
//! through them, beside the network's own renders of those views.

use crate::inference::{pick_sources, render_camera, source_inputs, Prepared, RenderSettings};
use anyhow::{bail, Result};
use deepstereo_core::camera::Camera;
use deepstereo_core::metrics::{psnr, ssim};
use deepstereo_core::mpi::{bake, io, render_blend, viewer, Mpi};
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// Bakes the MPI of `camera` from the scene's views `sources` (the first `k` of them,
/// `k` from `settings`) at the settings' planes; every plane is kept (`--prune` does not
/// apply: an MPI is seen from other cameras).
pub fn bake_camera(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    camera: &Camera,
    sources: &[usize],
    settings: &RenderSettings,
    progress: &dyn Fn(usize, usize),
) -> Result<Mpi> {
    let cfg = backend.config().clone();
    let (srcs, inv) = source_inputs(&cfg, scene, prepared, sources, settings)?;
    Ok(bake(backend, camera, &srcs, &inv, settings.tile, progress)?)
}

/// The sources of an MPI baked at view `reference`: `k` views that are not held out,
/// chosen as `render` chooses them. With `own_photo`, `reference` itself is among them
/// (as for `render --pose` at its camera: the MPI then shows the photograph at its
/// reference); without, the planes' colours come from the other views only (as for
/// `render --target`).
pub fn reference_sources(
    scene: &Scene,
    reference: usize,
    holdout: &[usize],
    own_photo: bool,
    k: usize,
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
    Ok(pick_sources(scene, &cam, &exclude, k, settings))
}

/// The view that is not held out nearest to view `target` (by camera centre).
pub fn nearest_kept_view(scene: &Scene, target: usize, holdout: &[usize]) -> Option<usize> {
    let c = scene.views[target].camera.pose.centre();
    (0..scene.views.len())
        .filter(|i| !holdout.contains(i))
        .min_by(|&a, &b| {
            let da = (scene.views[a].camera.pose.centre() - c).length();
            let db = (scene.views[b].camera.pose.centre() - c).length();
            da.total_cmp(&db)
        })
}

/// One held-out view rendered by the network and through an MPI baked at its nearest
/// view that is not held out.
#[derive(Clone, Debug, Serialize)]
pub struct MpiViewResult {
    pub target: usize,
    pub name: String,
    /// The view the MPI was baked at.
    pub reference: usize,
    pub network_psnr: f64,
    pub network_ssim: f64,
    pub mpi_psnr: f64,
    pub mpi_ssim: f64,
    /// The MPI's render against the network's render of the same view.
    pub mpi_vs_network_psnr: f64,
    /// The network's render of the held-out view.
    pub network_seconds: f64,
    /// Baking the MPI (the network at the reference camera, every plane kept).
    pub bake_seconds: f64,
    /// Rendering the held-out view from the baked MPI on the CPU.
    pub mpi_render_seconds: f64,
}

/// Every held-out view of `holdout` rendered by the network (as `eval` does) and through
/// the MPI baked at its nearest view that is not held out (with that view's photograph
/// among its sources when `own_photo`).
pub fn eval_through_mpi(
    backend: &dyn Backend,
    scene: &Scene,
    holdout: &[usize],
    own_photo: bool,
    settings: &RenderSettings,
    mut on_view: impl FnMut(&MpiViewResult),
) -> Result<Vec<MpiViewResult>> {
    let k = settings.source_count(backend.config())?;
    let mut prepared = Prepared::new(scene);
    let mut out = Vec::new();
    for &t in holdout {
        if t >= scene.views.len() {
            bail!(
                "held-out view {t} is out of range: the scene has {} views",
                scene.views.len()
            );
        }
        let Some(reference) = nearest_kept_view(scene, t, holdout) else {
            bail!("every view is held out: no view is left to bake an MPI at");
        };
        let truth = scene.load_image(t)?;
        let cam = scene.views[t].camera;
        let srcs = pick_sources(scene, &cam, holdout, k, settings);
        let t0 = Instant::now();
        let (net, _) = render_camera(
            backend,
            scene,
            &mut prepared,
            &cam,
            &srcs,
            settings,
            &|_, _| {},
        )?;
        let network_seconds = t0.elapsed().as_secs_f64();
        let ref_srcs = reference_sources(scene, reference, holdout, own_photo, k, settings)?;
        let t0 = Instant::now();
        let mpi = bake_camera(
            backend,
            scene,
            &mut prepared,
            &scene.views[reference].camera,
            &ref_srcs,
            settings,
            &|_, _| {},
        )?;
        let bake_seconds = t0.elapsed().as_secs_f64();
        let t0 = Instant::now();
        let img = render_blend(std::slice::from_ref(&mpi), &cam);
        let mpi_render_seconds = t0.elapsed().as_secs_f64();
        let r = MpiViewResult {
            target: t,
            name: scene.views[t].name.clone(),
            reference,
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
