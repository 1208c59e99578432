//! `deepstereo eval`: held-out views against the photographs and the baselines.

use super::model_args::ModelArgs;
use super::SceneArgs;
use crate::inference::{evaluate, holdout_list};
use deepstereo_core::imageio::write_atomic;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Held-out view indices, comma-separated (each is left out of its own sources).
    #[arg(long)]
    pub holdout: Option<String>,
    /// Hold out every Nth view (LLFF's convention: 0, N, 2N, ...).
    #[arg(long)]
    pub llffhold: Option<usize>,
    /// Write the JSON report here (`-` for stdout).
    #[arg(long)]
    pub json: Option<String>,
    /// Also write each rendered view as PNG into this directory.
    #[arg(long)]
    pub images: Option<PathBuf>,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let settings = a.model.settings()?;
    let scene = a.scene.load()?;
    let targets = holdout_list(a.holdout.as_deref(), a.llffhold, scene.views.len())?;
    let backend = a.model.backend()?;
    let images = a.images.clone();
    let mut err = None;
    let report = evaluate(backend.as_ref(), &a.model.name(), &scene, &targets, &settings, |v, imgs| {
        eprintln!(
            "view {:3} {:<20} PSNR {:6.2} SSIM {:.3} ({:.2} s) | nearest {:6.2} | plane sweep {:6.2}",
            v.target, v.name, v.psnr, v.ssim, v.seconds, v.baselines.nearest.psnr, v.baselines.plane_sweep.psnr
        );
        if let Some(dir) = &images {
            if let Err(e) = imgs.rendered.image.save_png(&dir.join(format!("view_{:03}.png", v.target))) {
                err = Some(e);
            }
        }
    })?;
    if let Some(e) = err {
        return Err(e.into());
    }
    let m = &report.mean;
    eprintln!(
        "mean: DeepStereo PSNR {:.2} SSIM {:.3} ({:.2} s/view) | nearest {:.2} / {:.3} | plane sweep {:.2} / {:.3}",
        m.psnr, m.ssim, m.seconds, m.baselines.nearest.psnr, m.baselines.nearest.ssim, m.baselines.plane_sweep.psnr, m.baselines.plane_sweep.ssim
    );
    let json = serde_json::to_string_pretty(&report)?;
    match a.json.as_deref() {
        Some("-") => println!("{json}"),
        Some(p) => write_atomic(std::path::Path::new(p), json.as_bytes())?,
        None => {}
    }
    Ok(())
}
