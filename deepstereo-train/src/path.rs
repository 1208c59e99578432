//! Camera paths through a scene's views (LLFF-style: a circle, a spiral, a line) and
//! rendering them frame by frame, for `render --path` and `demo`.

use crate::inference::{pick_planned_sources, render_camera, Prepared, RenderSettings};
use anyhow::{bail, Context, Result};
use deepstereo_core::camera::{Camera, WorldToCamera};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use glam::{DMat3, DVec3};
use std::path::Path;

/// The shape of a camera path.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum PathKind {
    Spiral,
    Circle,
    Line,
}

/// Cameras along a path through the views: the mean orientation of the views, centres
/// offset from the mean centre in that frame by the spread of the views.
pub fn path_cameras(scene: &Scene, kind: PathKind, frames: usize) -> Result<Vec<Camera>> {
    let n = scene.views.len() as f64;
    let centre = scene
        .views
        .iter()
        .map(|v| v.camera.pose.centre())
        .sum::<DVec3>()
        / n;
    // Mean camera axes (rows of R are the camera axes in world coordinates).
    let axis = |i: usize| {
        scene
            .views
            .iter()
            .map(|v| v.camera.pose.rotation.row(i))
            .sum::<DVec3>()
            .normalize_or_zero()
    };
    let (x, z0) = (axis(0), axis(2));
    let z = z0;
    let y = z.cross(x).normalize_or_zero();
    let x = y.cross(z).normalize_or_zero();
    if !(x.is_finite() && y.is_finite() && z.is_finite()) || x.length() < 0.5 {
        bail!("cannot build a path: the views' orientations average to nothing");
    }
    let mut d: Vec<f64> = scene
        .views
        .iter()
        .map(|v| (v.camera.pose.centre() - centre).length())
        .collect();
    d.sort_by(f64::total_cmp);
    let radius = d[(d.len() * 9 / 10).min(d.len() - 1)].max(1e-9) * 0.5;
    let rot = DMat3::from_cols(x, y, z).transpose(); // world-to-camera: rows are axes
    let intr = scene.views[0].camera.intrinsics;
    (0..frames)
        .map(|f| {
            let s = f as f64 / frames as f64;
            let th = s * std::f64::consts::TAU;
            let off = match kind {
                PathKind::Circle => x * th.cos() + y * th.sin(),
                PathKind::Spiral => x * th.cos() - y * th.sin() - z * (0.5 * th).sin() * 0.5,
                PathKind::Line => x * (2.0 * (f as f64 / (frames.max(2) - 1) as f64) - 1.0),
            };
            let c = centre + off * radius;
            let pose = WorldToCamera::new_checked(rot, -(rot * c)).map_err(anyhow::Error::msg)?;
            Ok(Camera::global(intr, pose))
        })
        .collect()
}

/// Steps of the path progress bar per frame (the bar advances tile by tile).
const BAR_STEPS_PER_FRAME: u64 = 1000;

/// Renders `cams` in order, saving each as `dir/frame_NNNN.png` (`dir`: a staged
/// directory, put in place once complete; see [`RgbImage::save_frame_png`]), with a
/// progress bar (frames done, time left); returns the frames.
pub fn render_path(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    cams: &[Camera],
    views: usize,
    settings: &RenderSettings,
    dir: &Path,
) -> Result<Vec<RgbImage>> {
    let n = cams.len() as u64;
    let bar = indicatif::ProgressBar::new(n * BAR_STEPS_PER_FRAME);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {msg}, {eta} left",
        )
        .context("progress bar template")?,
    );
    let mut frames = Vec::with_capacity(cams.len());
    for (f, cam) in cams.iter().enumerate() {
        bar.set_message(format!("frame {}/{n}", f + 1));
        let base = f as u64 * BAR_STEPS_PER_FRAME;
        let progress = |done: usize, total: usize| {
            let part = done as u64 * BAR_STEPS_PER_FRAME / total.max(1) as u64;
            bar.set_position(base + part);
        };
        let srcs = pick_planned_sources(scene, cam, &[], (views, backend.config()), settings);
        let (r, _) = render_camera(backend, scene, prepared, cam, &srcs, settings, &progress)?;
        r.image
            .save_frame_png(&dir.join(format!("frame_{f:04}.png")))?;
        bar.set_position(base + BAR_STEPS_PER_FRAME);
        if bar.is_hidden() {
            eprintln!("frame {}/{n}", f + 1);
        }
        frames.push(r.image);
    }
    bar.finish_and_clear();
    Ok(frames)
}
