//! `deepstereo eval`: held-out views against the photographs and the baselines.

use super::args::{SceneArgs, SceneModelArgs};
use crate::rendering::{evaluate, mean_over, EvalReport, Mean};
use deepstereo_core::imageio::write_atomic;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    // The scene whose held-out views are scored. The model, and how it renders them.
    // The held-out views (each left out of every source list).
    // `--scene` may also be a directory of scenes (as `synth` writes): each is evaluated.
    #[command(flatten)]
    pub input: SceneModelArgs,
    /// Write the JSON report here (`-` for stdout).
    #[arg(long)]
    pub json: Option<String>,
    /// Also write each rendered view as PNG into this directory.
    #[arg(long)]
    pub images: Option<PathBuf>,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let settings = a.input.model.settings()?;
    let dirs = if a.input.scene.format.is_some() {
        vec![a.input.scene.scene.clone()]
    } else {
        deepstereo_core::scene::scene_dirs(&a.input.scene.scene)?
    };
    let backend = a.input.model.backend()?;
    // Images go to a staged directory, moved into place only when everything succeeded.
    let staged = match &a.images {
        Some(d) => Some(crate::cmd::support::outdir::StagedDir::new(d)?),
        None => None,
    };
    let mut reports = Vec::new();
    for dir in &dirs {
        let sa = SceneArgs {
            scene: dir.clone(),
            ..a.input.scene.clone()
        };
        let scene = sa.load_working()?;
        let targets = a.input.holdout.required(scene.views.len(), "eval")?;
        let images = staged.as_ref().map(|st| {
            let d = st.path();
            if dirs.len() > 1 {
                d.join(dir.file_name().unwrap_or_default())
            } else {
                d.to_path_buf()
            }
        });
        let mut err = None;
        let report = evaluate(
            backend.as_ref(),
            &a.input.model.name(),
            &scene,
            &targets,
            &settings,
            |v, imgs| {
                eprintln!(
                "view {:3} {:<20} PSNR {:6.2} SSIM {:.3} ({:.2} s) | nearest {:6.2} | plane sweep {:6.2}",
                v.target, v.name, v.psnr, v.ssim, v.seconds, v.baselines.nearest.psnr, v.baselines.plane_sweep.psnr
            );
                if let Some(p) = &v.prune {
                    eprintln!("         {}", p.summary());
                }
                if let Some(dir) = &images {
                    if let Err(e) = imgs
                        .rendered
                        .image
                        .save_png(&dir.join(format!("view_{:03}.png", v.target)))
                    {
                        err = Some(e);
                    }
                }
            },
        )?;
        if let Some(e) = err {
            return Err(e.into());
        }
        print_mean(&report.scene, &report.mean);
        reports.push(report);
    }
    let json = if reports.len() == 1 {
        serde_json::to_value(&reports[0])?
    } else {
        let mean = mean_of(&reports);
        print_mean(&format!("all {} scenes", reports.len()), &mean);
        serde_json::json!({ "scenes": reports, "mean": mean })
    };
    let text = serde_json::to_string_pretty(&json)?;
    match a.json.as_deref() {
        Some("-") => println!("{text}"),
        Some(p) => write_atomic(std::path::Path::new(p), text.as_bytes())?,
        None => {}
    }
    if let Some(st) = staged {
        st.commit()?;
    }
    Ok(())
}

fn print_mean(what: &str, m: &Mean) {
    eprintln!(
        "mean ({what}): DeepStereo PSNR {:.2} SSIM {:.3} ({:.2} s/view) | nearest {:.2} / {:.3} | plane sweep {:.2} / {:.3}",
        m.psnr, m.ssim, m.seconds, m.baselines.nearest.psnr, m.baselines.nearest.ssim, m.baselines.plane_sweep.psnr, m.baselines.plane_sweep.ssim
    );
}

/// The mean over scenes of the per-scene means (each scene weighs the same).
fn mean_of(reports: &[EvalReport]) -> Mean {
    mean_over(reports, |r| {
        let m = &r.mean;
        (m.psnr, m.ssim, m.seconds, &m.baselines)
    })
}
