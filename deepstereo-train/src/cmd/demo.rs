//! `deepstereo demo`: the whole pipeline with no files: a procedural scene, a held-out
//! view rendered with the embedded model, scored against both baselines.

use super::args::ModelArgs;
use crate::cmd::support::video::write_video;
use crate::rendering::path::{path_cameras, render_path, PathKind};
use crate::rendering::{evaluate, EvalReport, Prepared, RenderSettings};
use anyhow::{Context, Result};
use deepstereo_core::render::Backend;
use deepstereo_core::scene::{LoadOptions, Scene};
use deepstereo_core::synth::{generate, scene_seed, write_scene, Rig, SynthOptions};
use deepstereo_core::viz::{depth_image, titled_side_by_side};
use std::path::PathBuf;

/// Base seed of demo scenes; training uses `--seed` (default 0) and validation that seed
/// xor a salt, so demo scenes are never trained on.
pub const DEMO_SEED: u64 = 0xDE40_0000_0000_0001;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub model: ModelArgs,
    /// Output directory: the scene (NeRF format), image.png, depth.png, comparison.png.
    #[arg(long, default_value = "deepstereo-demo")]
    pub out: PathBuf,
    /// Which demo scene (any number; each is a different procedural scene).
    #[arg(long, default_value_t = 0)]
    pub scene_index: usize,
    /// Camera rig of the scene: forward, rosette, ring, handheld, mixed.
    #[arg(long, default_value = "mixed")]
    pub rig: Rig,
    /// Image size of the scene, WxH.
    #[arg(long, default_value = "240x180")]
    pub size: String,
    /// Frames of the camera-path video of the scene (a circle through the views):
    /// path/frame_NNNN.png and path.mp4 (path.gif without ffmpeg); 0: none.
    #[arg(long, default_value_t = DEMO_PATH_FRAMES)]
    pub path_frames: usize,
}

/// Frames of the demo's path video: short, so that the demo stays quick.
pub const DEMO_PATH_FRAMES: usize = 12;
/// Frames per second of the demo's path video.
const DEMO_PATH_FPS: f64 = 8.0;

pub fn run(a: Args) -> Result<()> {
    let settings = a.model.settings()?;
    let (width, height) = super::args::size_of("--size", &a.size)?;
    let opts = SynthOptions {
        views: 10,
        width,
        height,
        rig: a.rig,
        ..SynthOptions::default()
    };
    let t0 = std::time::Instant::now();
    let synth = generate(scene_seed(DEMO_SEED, a.scene_index), &opts)?;
    let dir = a.out.join("scene");
    write_scene(&dir, &synth)
        .with_context(|| format!("writing the demo scene to {}", dir.display()))?;
    eprintln!(
        "procedural scene ({} views, {width}x{height}) in {:.2} s: {}",
        synth.cameras.len(),
        t0.elapsed().as_secs_f64(),
        dir.display()
    );
    let scene = Scene::load(&dir, &LoadOptions::default())?;
    let target = scene.views.len() / 2;
    let backend = a.model.backend()?;
    let name = a.model.name();
    let mut saved: Result<()> = Ok(());
    let out = a.out.clone();
    let (near, far) = (scene.near, scene.far);
    let report = evaluate(
        backend.as_ref(),
        &name,
        &scene,
        &[target],
        &settings,
        |_, imgs| {
            let r = imgs.rendered;
            let depth = depth_image(&r.depth, r.image.width, r.image.height, near, far);
            saved = (|| {
                r.image.save_png(&out.join("image.png"))?;
                depth.save_png(&out.join("depth.png"))?;
                let panels = [
                    (imgs.truth, "truth"),
                    (imgs.nearest, "nearest view"),
                    (imgs.plane_sweep, "plane sweep"),
                    (&r.image, "DeepStereo"),
                    (&depth, "depth"),
                ];
                titled_side_by_side(&panels, 4).save_png(&out.join("comparison.png"))?;
                Ok(())
            })();
        },
    )?;
    saved?;
    print_scores(&report);
    println!("wrote {0}/image.png, {0}/depth.png and {0}/comparison.png (titled: truth, nearest view, plane sweep, DeepStereo, depth)", a.out.display());
    if a.path_frames > 0 {
        write_path(&a, backend.as_ref(), &scene, &settings, report.views)?;
    }
    Ok(())
}

/// The held-out view's scores: the network's, the plane sweep's and the nearest source's.
fn print_scores(report: &EvalReport) {
    let v = &report.per_view[0];
    println!(
        "held-out view {} of a procedural scene, {} planes, {} source views",
        v.target, report.planes, report.views
    );
    println!(
        "{:<22} {:>8} {:>7} {:>9}",
        "method", "PSNR dB", "SSIM", "seconds"
    );
    println!(
        "{:<22} {:>8.2} {:>7.3} {:>9.2}",
        format!("DeepStereo ({})", report.backend),
        v.psnr,
        v.ssim,
        v.seconds
    );
    let ps = &v.baselines.plane_sweep;
    println!(
        "{:<22} {:>8.2} {:>7.3} {:>9.2}",
        "plane sweep (classical)",
        ps.psnr,
        ps.ssim,
        ps.seconds.unwrap_or(0.0)
    );
    let nn = &v.baselines.nearest;
    println!(
        "{:<22} {:>8.2} {:>7.3} {:>9}",
        "nearest source view", nn.psnr, nn.ssim, "-"
    );
}

/// The camera-path video: `--path-frames` frames on a circle through the views, rendered
/// from `views` sources into `path/`, and `path.mp4` (or `path.gif`).
fn write_path(
    a: &Args,
    backend: &dyn Backend,
    scene: &Scene,
    settings: &RenderSettings,
    views: usize,
) -> Result<()> {
    let cams = path_cameras(scene, PathKind::Circle, a.path_frames)?;
    let frames_dir = a.out.join("path");
    let staged = crate::cmd::support::outdir::StagedDir::new(&frames_dir)?;
    let t1 = std::time::Instant::now();
    let frames = render_path(
        backend,
        scene,
        &mut Prepared::new(scene),
        &cams,
        views,
        settings,
        staged.path(),
    )?;
    staged.commit()?;
    let video = write_video(&frames, &a.out.join("path.mp4"), DEMO_PATH_FPS)?;
    println!(
        "wrote a {}-frame camera path in {:.1} s: {} (frames in {})",
        a.path_frames,
        t1.elapsed().as_secs_f64(),
        video.path().display(),
        frames_dir.display()
    );
    Ok(())
}
