//! `deepstereo render`: new views of a scene, tile by tile.

use super::args::{ModelArgs, SceneArgs};
use crate::cmd::support::outdir::StagedDir;
use crate::rendering::path::{render_path, resolved_path, PathKind};
use crate::rendering::{pick_planned_sources, render_camera, Prepared, RenderSettings};
use anyhow::{bail, Result};
use deepstereo_core::camera::Camera;
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::render::{Backend, Rendered};
use deepstereo_core::scene::npy::write_npy_f32;
use deepstereo_core::scene::Scene;
use deepstereo_core::viz::{depth_image, grey_image};
use std::path::{Path, PathBuf};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The scene whose views are the sources.
    #[command(flatten)]
    pub scene: SceneArgs,
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
    /// Render a camera path as a numbered PNG sequence, with its cameras in
    /// `cameras.json`: `auto` (the default of a bare `--path`: spiral for a forward-facing
    /// capture, orbit for one around an object), `spiral`, `circle`, `line` (LLFF's, around
    /// the mean pose), `orbit` (around the point the cameras look at, at their distance and
    /// height), `interpolate` (a spline through the cameras in capture order), or a JSON
    /// file of cameras (a path's `cameras.json`, edited or not, or `inspect --json`'s
    /// output) to render them all.
    #[arg(long, value_name = "KIND|FILE", num_args = 0..=1, default_missing_value = "auto")]
    pub path: Option<String>,
    /// Render from the MPIs of this directory (written by `deepstereo mpi`) on the CPU,
    /// blended by distance, instead of running the network: image.png (with --pose or
    /// --target) or the frames of --path.
    #[arg(long)]
    pub mpi: Option<PathBuf>,
    /// The model, and how it renders (not used with --mpi).
    #[command(flatten)]
    pub model: ModelArgs,
    /// Frames of --path (a file's cameras are all rendered).
    #[arg(long, default_value_t = 30)]
    pub frames: usize,
    /// With --path, also write the frames as a video: H.264 MP4 through ffmpeg when it is
    /// on the PATH, else (or for a `.gif` path) an animated GIF, written natively.
    #[arg(long, requires = "path")]
    pub video: Option<PathBuf>,
    /// Frames per second of --video.
    #[arg(long, default_value_t = crate::cmd::support::video::DEFAULT_FPS, requires = "video")]
    pub fps: f64,
    /// Output directory: image.png (and image.npy, [H, W, 3] f32), depth.png (colour-mapped), depth.npy (raw, [H, W] f32),
    /// confidence.png, coverage.png; with --path, frame_XXXX.png.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let settings = a.model.settings()?;
    if let Some(v) = &a.video {
        crate::cmd::support::video::check(v, a.fps)?;
    }
    if a.path.is_some() && a.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let scene = a.scene.load_working()?;
    if let Some(dir) = &a.mpi {
        return render_mpis(&a, dir, &scene);
    }
    let backend = a.model.backend()?;
    let cfg = backend.config();
    let v = settings.source_count(cfg)?;
    let mut prepared = Prepared::new(&scene);
    if let Some(spec) = &a.path {
        let cams = path_cameras_of(spec, &scene, a.frames)?;
        return write_path(
            &a,
            &cams,
            backend.as_ref(),
            &scene,
            &mut prepared,
            v,
            &settings,
        );
    }
    write_view(&a, backend.as_ref(), &scene, &mut prepared, v, &settings)
}

/// `--target I` or `--pose FILE`: one view rendered from `views` sources, with its depth,
/// confidence and coverage.
fn write_view(
    a: &Args,
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    v: usize,
    settings: &RenderSettings,
) -> Result<()> {
    let cfg = backend.config();
    let (cam, exclude) = match (a.target, &a.pose) {
        (Some(t), None) if t < scene.views.len() => (scene.views[t].camera, vec![t]),
        (Some(t), None) => bail!(
            "--target {t} is out of range: the scene has {} views",
            scene.views.len()
        ),
        (None, Some(p)) => (
            crate::cmd::support::camera_json::read_pose(p, a.view)?,
            vec![],
        ),
        _ => bail!("pass one of --target I, --pose FILE or --path KIND"),
    };
    let srcs = pick_planned_sources(scene, &cam, &exclude, (v, cfg), settings);
    let staged = StagedDir::new(&a.out)?;
    let bar = indicatif::ProgressBar::new(0);
    let progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let t0 = std::time::Instant::now();
    let (r, _) = render_camera(backend, scene, prepared, &cam, &srcs, settings, &progress)?;
    bar.finish_and_clear();
    let (network, plan) = srcs.split_at(v.min(srcs.len()));
    eprintln!(
        "rendered {}x{} in {:.2} s from views {network:?}{}",
        r.image.width,
        r.image.height,
        t0.elapsed().as_secs_f64(),
        match plan.is_empty() {
            true => String::new(),
            false => format!(" (the planes chosen with views {plan:?} too)"),
        }
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

/// The cameras of `--path SPEC`: a path kind (printing which `auto` chose and why), or a
/// JSON file of cameras.
fn path_cameras_of(spec: &str, scene: &Scene, frames: usize) -> Result<Vec<Camera>> {
    if let Some(kind) = PathKind::parse(spec) {
        let (cams, chosen, why) = resolved_path(scene, kind, frames)?;
        match kind {
            PathKind::Auto => {
                eprintln!("path: {} ({why}; --path NAME picks another)", chosen.name())
            }
            _ => eprintln!("path: {} ({why})", chosen.name()),
        }
        return Ok(cams);
    }
    let file = Path::new(spec);
    if !file.is_file() {
        bail!(
            "--path {spec}: neither a path kind ({}) nor a JSON file of cameras",
            PathKind::NAMES
        );
    }
    let cams = crate::cmd::support::camera_json::read_cameras(file)?;
    eprintln!("path: the {} cameras of {}", cams.len(), file.display());
    Ok(cams)
}

/// Writes `cameras.json` (the path's cameras, [`crate::cmd::support::camera_json::path_json`]) into `dir`.
fn write_cameras(dir: &Path, cams: &[Camera], scene: &Scene) -> Result<()> {
    let json = crate::cmd::support::camera_json::path_json(cams, scene);
    let text = serde_json::to_string_pretty(&json)?;
    deepstereo_core::imageio::write_atomic(&dir.join("cameras.json"), text.as_bytes())?;
    Ok(())
}

/// `--path`: the path's frames rendered from `views` sources, its `cameras.json`, and
/// `--video`.
fn write_path(
    a: &Args,
    cams: &[Camera],
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    views: usize,
    settings: &RenderSettings,
) -> Result<()> {
    let staged = StagedDir::new(&a.out)?;
    write_cameras(staged.path(), cams, scene)?;
    let frames = render_path(
        backend,
        scene,
        prepared,
        cams,
        views,
        settings,
        staged.path(),
    )?;
    let wrote = format!(
        "frame_0000.png .. frame_{:04}.png and cameras.json to {}",
        frames.len() - 1,
        a.out.display()
    );
    finish_frames(a, staged, &frames, &wrote)
}

/// Writes `--video` of `frames` when asked, moves the staged output into place, and
/// says what it wrote (`wrote`, then the video).
fn finish_frames(a: &Args, staged: StagedDir, frames: &[RgbImage], wrote: &str) -> Result<()> {
    let video = match &a.video {
        Some(p) => Some(crate::cmd::support::video::write_video(frames, p, a.fps)?),
        None => None,
    };
    staged.commit()?;
    eprintln!("wrote {wrote}");
    if let Some(v) = video {
        eprintln!(
            "wrote {} ({} frames at {} fps)",
            v.path().display(),
            frames.len(),
            a.fps
        );
    }
    Ok(())
}

/// `--mpi DIR`: the cameras of --path, --pose or --target rendered from MPIs on the CPU.
fn render_mpis(a: &Args, dir: &Path, scene: &Scene) -> Result<()> {
    let mpis = crate::rendering::mpi::read_mpis(dir)?;
    let cams = match (&a.path, a.target, &a.pose) {
        (Some(spec), _, _) => path_cameras_of(spec, scene, a.frames)?,
        (None, Some(t), None) if t < scene.views.len() => vec![scene.views[t].camera],
        (None, Some(t), None) => bail!(
            "--target {t} is out of range: the scene has {} views",
            scene.views.len()
        ),
        (None, None, Some(p)) => vec![crate::cmd::support::camera_json::read_pose(p, a.view)?],
        _ => bail!("with --mpi pass one of --path KIND, --target I or --pose FILE"),
    };
    let staged = StagedDir::new(&a.out)?;
    if a.path.is_some() {
        write_cameras(staged.path(), &cams, scene)?;
    }
    let bar = indicatif::ProgressBar::new(cams.len() as u64);
    let t0 = std::time::Instant::now();
    let names = |f: usize| match a.path {
        Some(_) => format!("frame_{f:04}.png"),
        None => "image.png".to_string(),
    };
    let frames = render_mpi_frames(&mpis, &cams, staged.path(), names, &bar)?;
    bar.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    eprintln!(
        "rendered {} frame(s) from {} MPI(s) in {secs:.2} s ({:.3} s per frame)",
        frames.len(),
        mpis.len(),
        secs / frames.len() as f64
    );
    finish_frames(a, staged, &frames, &a.out.display().to_string())
}

/// `cams` rendered from `mpis`, each frame written as PNG into `dir` under `name(f)` by a
/// second thread while the next one renders; the frames, in order.
fn render_mpi_frames(
    mpis: &[deepstereo_core::mpi::Mpi],
    cams: &[deepstereo_core::camera::Camera],
    dir: &Path,
    name: impl Fn(usize) -> String,
    bar: &indicatif::ProgressBar,
) -> Result<Vec<RgbImage>> {
    std::thread::scope(|s| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<(PathBuf, RgbImage)>(2);
        let writer = s.spawn(move || -> Result<Vec<RgbImage>> {
            let mut frames = Vec::new();
            for (path, img) in rx {
                img.save_frame_png(&path)?;
                frames.push(img);
            }
            Ok(frames)
        });
        for (f, cam) in cams.iter().enumerate() {
            let img = deepstereo_core::mpi::render_blend(mpis, cam);
            if tx.send((dir.join(name(f)), img)).is_err() {
                break; // the writer failed; its error is returned below
            }
            bar.inc(1);
        }
        drop(tx);
        (writer.join()).map_err(|_| anyhow::anyhow!("the frame writer panicked"))?
    })
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
