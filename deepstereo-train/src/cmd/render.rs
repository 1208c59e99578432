//! `deepstereo render`: new views of a scene, tile by tile.

use super::model_args::ModelArgs;
use super::SceneArgs;
use crate::inference::{pick_sources, render_camera, Prepared};
use crate::outdir::StagedDir;
use anyhow::{bail, Context, Result};
use deepstereo_core::camera::{Camera, Intrinsics, WorldToCamera};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::render::Rendered;
use deepstereo_core::scene::npy::write_npy_f32;
use deepstereo_core::scene::Scene;
use deepstereo_core::viz::{depth_image, grey_image};
use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum PathKind {
    Spiral,
    Circle,
    Line,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Render the scene's view I (left out of its own sources).
    #[arg(long, conflicts_with_all = ["pose", "path"])]
    pub target: Option<usize>,
    /// Render a camera given as JSON: {"width","height","fx","fy","cx","cy","R" (9 numbers,
    /// row-major world-to-camera, OpenCV axes), "t"} and optionally "rolling_shutter"
    /// ({"R_start","t_start","R_end","t_end","time_origin","time_per_pixel"}: each row is
    /// then rendered at its own pose): one view as `inspect --json` prints it, or the
    /// whole of `inspect --json`'s output with --view I.
    #[arg(long, conflicts_with = "path")]
    pub pose: Option<PathBuf>,
    /// With --pose FILE holding `inspect --json`'s output: which of its views to render.
    #[arg(long, requires = "pose")]
    pub view: Option<usize>,
    /// Render a camera path around the views (LLFF-style) as a numbered PNG sequence.
    #[arg(long, value_enum)]
    pub path: Option<PathKind>,
    /// Frames of --path.
    #[arg(long, default_value_t = 30)]
    pub frames: usize,
    /// With --path, also write the frames as a video: H.264 MP4 through ffmpeg when it is
    /// on the PATH, else (or for a `.gif` path) an animated GIF, written natively.
    #[arg(long, requires = "path")]
    pub video: Option<PathBuf>,
    /// Frames per second of --video.
    #[arg(long, default_value_t = crate::video::DEFAULT_FPS, requires = "video")]
    pub fps: f64,
    /// Output directory: image.png (and image.npy, [H, W, 3] f32), depth.png (colour-mapped), depth.npy (raw, [H, W] f32),
    /// confidence.png, coverage.png; with --path, frame_XXXX.png.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let settings = a.model.settings()?;
    if let Some(v) = &a.video {
        crate::video::check(v, a.fps)?;
    }
    if a.path.is_some() && a.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let scene = a.scene.load()?;
    let backend = a.model.backend()?;
    let v = settings.source_count(backend.config())?;
    let mut prepared = Prepared::new(&scene);
    if let Some(kind) = a.path {
        let cams = path_cameras(&scene, kind, a.frames)?;
        let staged = StagedDir::new(&a.out)?;
        let frames = render_path(
            backend.as_ref(),
            &scene,
            &mut prepared,
            &cams,
            v,
            &settings,
            staged.path(),
        )?;
        let video = match &a.video {
            Some(p) => Some(crate::video::write_video(&frames, p, a.fps)?),
            None => None,
        };
        staged.commit()?;
        eprintln!(
            "wrote frame_0000.png .. frame_{:04}.png to {}",
            a.frames - 1,
            a.out.display()
        );
        if let Some(v) = video {
            eprintln!(
                "wrote {} ({} frames at {} fps)",
                v.path().display(),
                a.frames,
                a.fps
            );
        }
        return Ok(());
    }
    let (cam, srcs) = match (a.target, &a.pose) {
        (Some(t), None) => {
            if t >= scene.views.len() {
                bail!(
                    "--target {t} is out of range: the scene has {} views",
                    scene.views.len()
                );
            }
            let cam = scene.views[t].camera;
            (cam, pick_sources(&scene, &cam, &[t], v, &settings))
        }
        (None, Some(p)) => {
            let cam = read_pose(p, a.view)?;
            (cam, pick_sources(&scene, &cam, &[], v, &settings))
        }
        _ => bail!("pass one of --target I, --pose FILE or --path KIND"),
    };
    let staged = StagedDir::new(&a.out)?;
    let bar = indicatif::ProgressBar::new(0);
    let progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let t0 = std::time::Instant::now();
    let (r, _) = render_camera(
        backend.as_ref(),
        &scene,
        &mut prepared,
        &cam,
        &srcs,
        &settings,
        &progress,
    )?;
    bar.finish_and_clear();
    eprintln!(
        "rendered {}x{} in {:.2} s from views {srcs:?}",
        r.image.width,
        r.image.height,
        t0.elapsed().as_secs_f64()
    );
    if let Some(p) = &r.prune {
        eprintln!("{}", p.summary());
    }
    write_outputs(staged.path(), &r, scene.near, scene.far)?;
    staged.commit()?;
    eprintln!(
        "wrote image.png, image.npy, depth.png, depth.npy, confidence.png, coverage.png to {}",
        a.out.display()
    );
    Ok(())
}

/// Steps of the path progress bar per frame (the bar advances tile by tile).
const BAR_STEPS_PER_FRAME: u64 = 1000;

/// Renders `cams` in order, saving each as `dir/frame_NNNN.png`, with a progress bar
/// (frames done, time left); returns the frames.
pub fn render_path(
    backend: &dyn deepstereo_core::render::Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    cams: &[Camera],
    views: usize,
    settings: &crate::inference::RenderSettings,
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
        let srcs = pick_sources(scene, cam, &[], views, settings);
        let (r, _) = render_camera(backend, scene, prepared, cam, &srcs, settings, &progress)?;
        r.image.save_png(&dir.join(format!("frame_{f:04}.png")))?;
        bar.set_position(base + BAR_STEPS_PER_FRAME);
        if bar.is_hidden() {
            eprintln!("frame {}/{n}", f + 1);
        }
        frames.push(r.image);
    }
    bar.finish_and_clear();
    Ok(frames)
}

/// Writes image, depth (picture and raw), confidence and coverage.
pub fn write_outputs(dir: &Path, r: &Rendered, near: f64, far: f64) -> Result<()> {
    let (w, h) = (r.image.width, r.image.height);
    r.image.save_png(&dir.join("image.png"))?;
    write_npy_f32(
        &dir.join("image.npy"),
        &[h as usize, w as usize, 3],
        &r.image.data,
    )?;
    depth_image(&r.depth, w, h, near, far).save_png(&dir.join("depth.png"))?;
    write_npy_f32(&dir.join("depth.npy"), &[h as usize, w as usize], &r.depth)?;
    grey_image(&r.confidence, w, h).save_png(&dir.join("confidence.png"))?;
    grey_image(&r.coverage, w, h).save_png(&dir.join("coverage.png"))?;
    Ok(())
}

/// Reads a camera from a JSON file (world-to-camera, OpenCV axes): one view, or with
/// `view` the view of that index in `inspect --json`'s output.
pub fn read_pose(path: &Path, view: Option<usize>) -> Result<Camera> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let all: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: invalid JSON", path.display()))?;
    let j = match (all.get("views").and_then(|v| v.as_array()), view) {
        (Some(views), Some(i)) => views.get(i).with_context(|| {
            format!(
                "{}: --view {i} is out of range: the file holds {} views",
                path.display(),
                views.len()
            )
        })?,
        (Some(views), None) => bail!(
            "{}: holds {} views (inspect --json's output); pick one with --view I",
            path.display(),
            views.len()
        ),
        (None, Some(_)) => bail!(
            "{}: --view needs a file with a 'views' list (inspect --json's output)",
            path.display()
        ),
        (None, None) => &all,
    };
    let num = |k: &str| -> Result<f64> {
        j.get(k)
            .and_then(|v| v.as_f64())
            .with_context(|| format!("{}: missing or non-numeric '{k}'", path.display()))
    };
    let arr = |k: &str, n: usize| -> Result<Vec<f64>> {
        let a: Vec<f64> = j
            .get(k)
            .and_then(|v| v.as_array())
            .map(|a| a.iter().filter_map(|x| x.as_f64()).collect())
            .unwrap_or_default();
        if a.len() != n {
            bail!("{}: '{k}' must be an array of {n} numbers", path.display());
        }
        Ok(a)
    };
    let (w, h) = (num("width")?, num("height")?);
    if !(w >= 1.0 && h >= 1.0 && w <= 32768.0 && h <= 32768.0) {
        bail!("{}: width and height must be 1..=32768", path.display());
    }
    let intr = Intrinsics::pinhole(
        num("fx")?,
        num("fy")?,
        num("cx")?,
        num("cy")?,
        w as u32,
        h as u32,
    );
    intr.validate()
        .map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
    let r = arr("R", 9)?;
    let t = arr("t", 3)?;
    let rot = DMat3::from_cols(
        DVec3::new(r[0], r[3], r[6]),
        DVec3::new(r[1], r[4], r[7]),
        DVec3::new(r[2], r[5], r[8]),
    );
    let pose = WorldToCamera::new_checked(rot, DVec3::new(t[0], t[1], t[2]))
        .map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
    // With a rolling shutter, each row is rendered at its own pose; `R`/`t` (the pose at
    // the image centre's time, as `inspect` prints it) are then not used.
    Ok(match super::shutter_json::from_json(j, path)? {
        Some(rs) => Camera::rolling(intr, rs),
        None => Camera::global(intr, pose),
    })
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
