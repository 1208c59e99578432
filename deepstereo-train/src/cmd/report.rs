//! `deepstereo report`: error against run time over a grid of settings.

use super::model_args::ModelArgs;
use super::SceneArgs;
use crate::inference::{evaluate, holdout_list, make_backend, BackendKind, RenderSettings};
use anyhow::{bail, Context, Result};
use deepstereo_core::imageio::write_atomic;
use deepstereo_core::plot::{pareto_front, plot, Series};
use deepstereo_core::prune::{PruneMode, PruneOptions};
use std::fmt::Write as _;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Held-out view indices, comma-separated.
    #[arg(long)]
    pub holdout: Option<String>,
    /// Hold out every Nth view.
    #[arg(long)]
    pub llffhold: Option<usize>,
    /// Plane counts to try, comma-separated.
    #[arg(long, default_value = "8,16,32,64,96")]
    pub planes_grid: String,
    /// Backends to try, comma-separated (candle, ort).
    #[arg(long, default_value = "candle")]
    pub backends: String,
    /// Pruning settings to try, comma-separated (off, auto; the thresholds come from the
    /// --prune-* options).
    #[arg(long, default_value = "off,auto")]
    pub prune_grid: String,
    /// Output directory: report.csv, report.md, report.png.
    #[arg(long)]
    pub out: PathBuf,
}

struct Row {
    method: String,
    planes: usize,
    prune: PruneMode,
    psnr: f64,
    ssim: f64,
    seconds: f64,
}

pub fn run(a: Args) -> Result<()> {
    let base = a.model.settings()?;
    let scene = a.scene.load()?;
    let targets = holdout_list(a.holdout.as_deref(), a.llffhold, scene.views.len())?;
    let planes: Vec<usize> = a
        .planes_grid
        .split(',')
        .map(|s| {
            s.trim()
                .parse::<usize>()
                .ok()
                .filter(|&p| p > 0)
                .with_context(|| format!("--planes-grid: '{s}' is not a positive count"))
        })
        .collect::<Result<_>>()?;
    let backends: Vec<BackendKind> = a
        .backends
        .split(',')
        .map(|s| match s.trim() {
            "candle" => Ok(BackendKind::Candle),
            "ort" => Ok(BackendKind::Ort),
            o => bail!("--backends: unknown backend '{o}' (candle, ort)"),
        })
        .collect::<Result<_>>()?;
    let prunes: Vec<PruneMode> = a
        .prune_grid
        .split(',')
        .map(|s| {
            s.trim()
                .parse::<PruneMode>()
                .map_err(|e| anyhow::anyhow!("--prune-grid: {e}"))
        })
        .collect::<Result<_>>()?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let mut rows: Vec<Row> = Vec::new();
    let mut nearest = None;
    for (bi, &kind) in backends.iter().enumerate() {
        let backend = make_backend(kind, a.model.model.as_deref())?;
        for &p in &planes {
            for (pi, &mode) in prunes.iter().enumerate() {
                let prune = PruneOptions {
                    mode,
                    ..base.prune.clone()
                };
                let settings = RenderSettings {
                    planes: Some(p),
                    prune,
                    ..base.clone()
                };
                let r = evaluate(
                    backend.as_ref(),
                    &a.model.name(),
                    &scene,
                    &targets,
                    &settings,
                    |_, _| {},
                )?;
                let method = match mode {
                    PruneMode::Off => format!("deepstereo-{}", r.backend),
                    PruneMode::Auto => format!("deepstereo-{}-pruned", r.backend),
                };
                eprintln!("{method:>24} {p:3} planes: PSNR {:.2} SSIM {:.3} {:.2} s/view | plane sweep {:.2} dB {:.2} s", r.mean.psnr, r.mean.ssim, r.mean.seconds, r.mean.baselines.plane_sweep.psnr, r.mean.baselines.plane_sweep.seconds.unwrap_or(0.0));
                rows.push(Row {
                    method,
                    planes: p,
                    prune: mode,
                    psnr: r.mean.psnr,
                    ssim: r.mean.ssim,
                    seconds: r.mean.seconds,
                });
                if bi == 0 && pi == 0 {
                    let ps = &r.mean.baselines.plane_sweep;
                    rows.push(Row {
                        method: "plane_sweep".into(),
                        planes: p,
                        prune: mode,
                        psnr: ps.psnr,
                        ssim: ps.ssim,
                        seconds: ps.seconds.unwrap_or(0.0),
                    });
                    nearest = Some((r.mean.baselines.nearest.psnr, r.mean.baselines.nearest.ssim));
                }
            }
        }
    }
    let net: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r.method.starts_with("deepstereo"))
        .map(|r| (r.seconds, r.psnr))
        .collect();
    let front = pareto_front(&net);
    let mut csv = String::from("method,planes,prune,psnr,ssim,seconds_per_image\n");
    let mut md = format!("Scene `{}`, model `{}`, held-out views {targets:?}.\n\n| method | planes | prune | PSNR (dB) | SSIM | s / image |\n|---|---|---|---|---|---|\n", scene.root.display(), a.model.name());
    for r in &rows {
        writeln!(
            csv,
            "{},{},{},{:.4},{:.4},{:.4}",
            r.method, r.planes, r.prune, r.psnr, r.ssim, r.seconds
        )?;
        writeln!(
            md,
            "| {} | {} | {} | {:.2} | {:.3} | {:.3} |",
            r.method, r.planes, r.prune, r.psnr, r.ssim, r.seconds
        )?;
    }
    if let Some((p, s)) = nearest {
        writeln!(csv, "nearest,0,off,{p:.4},{s:.4},0")?;
        writeln!(md, "| nearest source | - | - | {p:.2} | {s:.3} | - |")?;
    }
    let colours = [
        [0.85, 0.2, 0.1],
        [0.1, 0.6, 0.2],
        [0.1, 0.4, 0.85],
        [0.5, 0.2, 0.7],
        [0.9, 0.6, 0.0],
    ];
    let mut series: Vec<Series> = Vec::new();
    let methods: Vec<String> =
        rows.iter()
            .map(|r| r.method.clone())
            .fold(Vec::new(), |mut v, m| {
                if !v.contains(&m) {
                    v.push(m);
                }
                v
            });
    for (k, m) in methods.iter().enumerate() {
        let pts: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| &r.method == m)
            .map(|r| (r.seconds.max(1e-4), r.psnr))
            .collect();
        series.push(Series {
            label: m.clone(),
            colour: colours[k % colours.len()],
            points: pts,
            line: false,
            marker: 3,
        });
    }
    let mut fp: Vec<(f64, f64)> = front
        .iter()
        .map(|&i| (net[i].0.max(1e-4), net[i].1))
        .collect();
    fp.sort_by(|a, b| a.0.total_cmp(&b.0));
    series.push(Series {
        label: "pareto front".into(),
        colour: [0.0, 0.0, 0.0],
        points: fp,
        line: true,
        marker: 0,
    });
    if let Some((p, _)) = nearest {
        let xs: Vec<f64> = rows.iter().map(|r| r.seconds.max(1e-4)).collect();
        let (lo, hi) = (
            xs.iter().cloned().fold(f64::MAX, f64::min),
            xs.iter().cloned().fold(f64::MIN, f64::max),
        );
        series.push(Series {
            label: "nearest source".into(),
            colour: [0.5, 0.5, 0.5],
            points: vec![(lo, p), (hi, p)],
            line: true,
            marker: 0,
        });
    }
    let img = plot(
        "PSNR against run time (labels: planes)",
        "seconds per image (log)",
        "PSNR dB",
        &series,
        true,
    );
    img.save_png(&a.out.join("report.png"))?;
    write_atomic(&a.out.join("report.csv"), csv.as_bytes())?;
    write_atomic(&a.out.join("report.md"), md.as_bytes())?;
    print!("{md}");
    eprintln!(
        "wrote report.csv, report.md, report.png to {}",
        a.out.display()
    );
    Ok(())
}
