//! `deepstereo report`: error against run time over a grid of settings.

mod html;

use super::args::{SceneArgs, SceneModelArgs};
use crate::cmd::support::outdir::StagedDir;
use crate::rendering::{evaluate, make_backend, BackendKind, RenderSettings};
use anyhow::{bail, Context, Result};
use deepstereo_core::imageio::write_atomic;
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::metrics::{psnr, ssim};
use deepstereo_core::plot::{pareto_front, plot, Series, PALETTE};
use deepstereo_core::prune::{PruneMode, PruneOptions};
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use html::{page, picture_names, PageRow, ViewPictures, BEST_DIR};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

#[derive(Debug, clap::Args)]
pub struct Args {
    // The scene whose held-out views are scored in every setting. The model, and the
    // settings a grid does not vary.
    #[command(flatten)]
    pub input: SceneModelArgs,
    /// Plane counts to try, comma-separated.
    #[arg(long, default_value = "8,16,32,64,96")]
    pub planes_grid: String,
    /// Source-view counts to try, comma-separated (1 to the model's; default: the
    /// model's). With fewer views than the model takes, its other inputs are empty.
    #[arg(long)]
    pub views_grid: Option<String>,
    /// Backends to try, comma-separated (candle, ort).
    #[arg(long, default_value = "candle")]
    pub backends: String,
    /// Image scales to try, comma-separated: 1/N of the scene's resolution (after
    /// --downscale; N a power of two). Renders at lower scales are upsampled (bilinear)
    /// and scored against the photographs at the scene's resolution.
    #[arg(long, default_value = "1")]
    pub downscale_grid: String,
    /// Pruning settings to try, comma-separated (off, auto; the thresholds come from the
    /// --prune-* options).
    #[arg(long, default_value = "off,auto")]
    pub prune_grid: String,
    /// Output directory: report.csv, report.md, report.png and index.html (the plot, the
    /// table, the Pareto front and the best setting's renders beside the photographs and
    /// both baselines, in best/; a static page that opens from the file system).
    #[arg(long)]
    pub out: PathBuf,
}

struct Row {
    method: String,
    planes: usize,
    views: usize,
    scale: u32,
    prune: PruneMode,
    psnr: f64,
    ssim: f64,
    seconds: f64,
}

/// The settings `report` tries: every combination of them.
struct Grid {
    planes: Vec<usize>,
    /// `None`: the model's.
    views: Vec<Option<usize>>,
    /// Each image scale 1/N with its scene: `None` for the base scene (N = 1), else the
    /// same files read at 1/N.
    scaled: Vec<(u32, Option<Scene>)>,
    backends: Vec<BackendKind>,
    prunes: Vec<PruneMode>,
}

/// What the grid's runs measured.
struct Measured {
    rows: Vec<Row>,
    /// The nearest source's (PSNR, SSIM), from the first setting.
    nearest: Option<(f64, f64)>,
    /// The best network setting: its row and its pictures.
    best: Option<(usize, Vec<ViewPictures>)>,
}

pub fn run(a: Args) -> Result<()> {
    let base = a.input.model.settings()?;
    let scene = a.input.scene.load_working()?;
    let targets = a.input.holdout.required(scene.views.len(), "report")?;
    let grid = parse_grid(&a, 1 << scene.downscale_levels)?;
    let staged = StagedDir::new(&a.out)?;
    let out = staged.path().to_path_buf();
    let Measured {
        rows,
        nearest,
        best,
    } = measure(&a, &base, &scene, &targets, &grid)?;
    let net: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r.method.starts_with("deepstereo"))
        .map(|r| (r.seconds, r.psnr))
        .collect();
    let front = pareto_front(&net);
    let (csv, md) = tables(&rows, nearest, &scene, &a.input.model.name(), &targets)?;
    let img = plot(
        "PSNR against run time (labels: planes)",
        "seconds per image (log)",
        "PSNR dB",
        &plot_series(&rows, &net, &front, nearest),
        true,
    );
    img.save_png(&out.join("report.png"))?;
    write_atomic(&out.join("report.csv"), csv.as_bytes())?;
    write_atomic(&out.join("report.md"), md.as_bytes())?;
    let heading = format!(
        "Scene {}, model {}, held-out views {targets:?}. Scale 1/N: rendered at 1/N of the resolution, upsampled, scored at full resolution.",
        scene.root.display(),
        a.input.model.name()
    );
    write_page(&out, &heading, &rows, &front, nearest, best)?;
    staged.commit()?;
    print!("{md}");
    eprintln!(
        "wrote report.csv, report.md, report.png, index.html and {BEST_DIR}/ to {}",
        a.out.display()
    );
    Ok(())
}

/// The grid options parsed, and the scene read at each scale.
fn parse_grid(a: &Args, base_downscale: u32) -> Result<Grid> {
    let positive = |n: &usize| *n > 0;
    let planes: Vec<usize> = grid(
        &a.planes_grid,
        "--planes-grid",
        "a positive count",
        positive,
    )?;
    let views: Vec<Option<usize>> = match &a.views_grid {
        None => vec![None],
        Some(g) => grid(g, "--views-grid", "a positive count", positive)?
            .into_iter()
            .map(Some)
            .collect(),
    };
    let scales: Vec<u32> = grid(
        &a.downscale_grid,
        "--downscale-grid",
        "a power of two",
        |n: &u32| n.is_power_of_two(),
    )?;
    // Each scale's scene: the base scene (read at 1/`base_downscale`), or the same files
    // read at 1/N of that.
    let scaled: Vec<(u32, Option<Scene>)> = scales
        .iter()
        .map(|&n| -> Result<_> {
            if n == 1 {
                return Ok((1, None));
            }
            let factor = base_downscale
                .checked_mul(n)
                .context("--downscale-grid: too large")?;
            let args = SceneArgs {
                downscale: Some(factor),
                ..a.input.scene.clone()
            };
            Ok((n, Some(args.load()?)))
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
    Ok(Grid {
        planes,
        views,
        scaled,
        backends,
        prunes,
    })
}

/// Runs every setting of the grid: a row for the network and (with the first backend)
/// one for the plane sweep on its sources, printing each as it is measured.
fn measure(
    a: &Args,
    base: &RenderSettings,
    scene: &Scene,
    targets: &[usize],
    g: &Grid,
) -> Result<Measured> {
    let mut m = Measured {
        rows: Vec::new(),
        nearest: None,
        best: None,
    };
    let rows = &mut m.rows;
    for (bi, &kind) in g.backends.iter().enumerate() {
        let backend = make_backend(kind, a.input.model.model.as_deref())?;
        for (si, (n, scaled_scene)) in g.scaled.iter().enumerate() {
            for (p, (vi, &nv)) in g
                .planes
                .iter()
                .flat_map(|&p| g.views.iter().enumerate().map(move |v| (p, v)))
            {
                for (pi, &mode) in g.prunes.iter().enumerate() {
                    let prune = PruneOptions {
                        mode,
                        ..base.prune.clone()
                    };
                    let settings = RenderSettings {
                        planes: Some(p),
                        views: nv.or(base.views),
                        prune,
                        ..base.clone()
                    };
                    let k = settings.source_count(backend.config())?;
                    let pt = point(
                        backend.as_ref(),
                        &a.input.model.name(),
                        scene,
                        scaled_scene.as_ref(),
                        *n,
                        targets,
                        &settings,
                    )?;
                    let (method, ps_method) = method_names(&pt.backend, mode, *n, g.views.len(), k);
                    eprintln!(
                    "{method:>28} {p:3} planes: PSNR {:.2} SSIM {:.3} {:.2} s/view | plane sweep {:.2} dB {:.2} s",
                    pt.net.0, pt.net.1, pt.net.2, pt.plane_sweep.0, pt.plane_sweep.2
                );
                    let better = (m.best.as_ref()).is_none_or(|(b, _)| pt.net.0 > rows[*b].psnr);
                    if better {
                        m.best = Some((rows.len(), pt.pictures));
                    }
                    let row = |method: String, (psnr, ssim, seconds): (f64, f64, f64)| Row {
                        method,
                        planes: p,
                        views: k,
                        scale: *n,
                        prune: mode,
                        psnr,
                        ssim,
                        seconds,
                    };
                    rows.push(row(method, pt.net));
                    if bi == 0 {
                        rows.push(row(ps_method, pt.plane_sweep));
                        if si == 0 && pi == 0 && vi == 0 {
                            m.nearest = Some(pt.nearest);
                        }
                    }
                }
            }
        }
    }
    Ok(m)
}

/// The names of a setting's network and plane-sweep rows: the backend, `-pruned`, the
/// scale `-1/N` when not 1 and `-{k}views` when the grid tries several view counts.
fn method_names(
    backend: &str,
    mode: PruneMode,
    n: u32,
    view_settings: usize,
    k: usize,
) -> (String, String) {
    // The plane sweep runs on the network's sources, which pruning picks.
    let (net, sweep) = match mode {
        PruneMode::Off => ("", "plane_sweep"),
        PruneMode::Auto => ("-pruned", "plane_sweep-pruned-views"),
    };
    let mut suffix = String::new();
    if n > 1 {
        suffix += &format!("-1/{n}");
    }
    if view_settings > 1 {
        suffix += &format!("-{k}views");
    }
    (
        format!("deepstereo-{backend}{net}{suffix}"),
        format!("{sweep}{suffix}"),
    )
}

/// report.csv and report.md: a line per row, then the nearest source's.
fn tables(
    rows: &[Row],
    nearest: Option<(f64, f64)>,
    scene: &Scene,
    model: &str,
    targets: &[usize],
) -> Result<(String, String)> {
    let mut csv = String::from("method,planes,views,scale,prune,psnr,ssim,seconds_per_image\n");
    let mut md = format!("Scene `{}`, model `{}`, held-out views {targets:?}; scale 1/N: rendered at 1/N of the resolution, upsampled, scored at full resolution.\n\n| method | planes | views | scale | prune | PSNR (dB) | SSIM | s / image |\n|---|---|---|---|---|---|---|---|\n", scene.root.display(), model);
    for r in rows {
        writeln!(
            csv,
            "{},{},{},{},{},{:.4},{:.4},{:.4}",
            r.method, r.planes, r.views, r.scale, r.prune, r.psnr, r.ssim, r.seconds
        )?;
        writeln!(
            md,
            "| {} | {} | {} | 1/{} | {} | {:.2} | {:.3} | {:.3} |",
            r.method, r.planes, r.views, r.scale, r.prune, r.psnr, r.ssim, r.seconds
        )?;
    }
    if let Some((p, s)) = nearest {
        writeln!(csv, "nearest,0,1,1,off,{p:.4},{s:.4},0")?;
        writeln!(
            md,
            "| nearest source | - | 1 | - | - | {p:.2} | {s:.3} | - |"
        )?;
    }
    Ok((csv, md))
}

/// The plot's series: one per method (points labelled with their planes), the network's
/// Pareto front (`front` indexes `net`, the network rows' (seconds, PSNR)) and the
/// nearest source's PSNR as a level line.
fn plot_series(
    rows: &[Row],
    net: &[(f64, f64)],
    front: &[usize],
    nearest: Option<(f64, f64)>,
) -> Vec<Series> {
    let colours = PALETTE;
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
        let mine: Vec<&Row> = rows.iter().filter(|r| &r.method == m).collect();
        let pts: Vec<(f64, f64)> = mine.iter().map(|r| (r.seconds.max(1e-4), r.psnr)).collect();
        let labels: Vec<String> = mine.iter().map(|r| r.planes.to_string()).collect();
        series.push(Series {
            label: m.clone(),
            colour: colours[k % colours.len()],
            points: pts,
            line: false,
            marker: 3,
            labels,
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
        labels: Vec::new(),
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
            labels: Vec::new(),
        });
    }
    series
}

/// index.html and the best setting's pictures in best/ (`front` indexes the network rows).
fn write_page(
    out: &Path,
    heading: &str,
    rows: &[Row],
    front: &[usize],
    nearest: Option<(f64, f64)>,
    best: Option<(usize, Vec<ViewPictures>)>,
) -> Result<()> {
    let net_rows: Vec<usize> = (0..rows.len())
        .filter(|&i| rows[i].method.starts_with("deepstereo"))
        .collect();
    let on_front: Vec<usize> = front.iter().map(|&i| net_rows[i]).collect();
    let page_rows: Vec<PageRow> = rows
        .iter()
        .enumerate()
        .map(|(i, r)| PageRow {
            method: r.method.clone(),
            planes: r.planes,
            views: r.views,
            scale: r.scale,
            prune: r.prune.to_string(),
            psnr: r.psnr,
            ssim: r.ssim,
            seconds: r.seconds,
            pareto: on_front.contains(&i),
        })
        .collect();
    let (best_row, pictures) = best.map_or((None, Vec::new()), |(b, p)| (Some(b), p));
    let best_dir = out.join(BEST_DIR);
    for v in &pictures {
        let names = picture_names(v.target);
        let images = [&v.truth, &v.rendered, &v.plane_sweep, &v.nearest];
        for (n, im) in names.iter().zip(images) {
            im.save_png(&best_dir.join(n))?;
        }
    }
    let html = page(heading, &page_rows, nearest, best_row, &pictures);
    write_atomic(&out.join("index.html"), html.as_bytes())?;
    Ok(())
}

/// The comma-separated values of the grid option `name`, each of which must parse and
/// pass `ok` (else an error naming the option, the value and `what` it must be).
fn grid<T: std::str::FromStr>(
    list: &str,
    name: &str,
    what: &str,
    ok: impl Fn(&T) -> bool,
) -> Result<Vec<T>> {
    list.split(',')
        .map(|s| {
            s.trim()
                .parse::<T>()
                .ok()
                .filter(&ok)
                .with_context(|| format!("{name}: '{s}' is not {what}"))
        })
        .collect()
}

/// A view's [network, plane sweep, nearest] x (PSNR, SSIM) and its pictures.
type Scored = ([(f64, f64); 3], ViewPictures);

/// One setting's mean scores: the network's and the plane sweep's (PSNR, SSIM, seconds)
/// and the nearest source's (PSNR, SSIM).
struct Point {
    backend: String,
    net: (f64, f64, f64),
    plane_sweep: (f64, f64, f64),
    nearest: (f64, f64),
    /// Each held-out view's pictures, at the scene's resolution.
    pictures: Vec<ViewPictures>,
}

/// Evaluates one setting on `scene`, or, with `scaled` (the scene read at 1/`n`), renders
/// there and scores the upsampled images against `scene`'s photographs.
#[allow(clippy::too_many_arguments)]
fn point(
    backend: &dyn Backend,
    model: &str,
    scene: &Scene,
    scaled: Option<&Scene>,
    n: u32,
    targets: &[usize],
    settings: &RenderSettings,
) -> Result<Point> {
    match scaled {
        None => point_full(backend, model, scene, targets, settings),
        Some(small) => point_scaled(backend, model, (scene, small, n), targets, settings),
    }
}

/// [`point`] at the scene's own resolution: the evaluation's scores and pictures.
fn point_full(
    backend: &dyn Backend,
    model: &str,
    scene: &Scene,
    targets: &[usize],
    settings: &RenderSettings,
) -> Result<Point> {
    let mut pictures = Vec::new();
    let r = evaluate(backend, model, scene, targets, settings, |v, im| {
        pictures.push(ViewPictures {
            target: v.target,
            name: v.name.clone(),
            truth: im.truth.clone(),
            rendered: im.rendered.image.clone(),
            plane_sweep: im.plane_sweep.clone(),
            nearest: im.nearest.clone(),
            psnr: [
                v.psnr,
                v.baselines.plane_sweep.psnr,
                v.baselines.nearest.psnr,
            ],
        });
    })?;
    let b = &r.mean.baselines;
    Ok(Point {
        backend: r.backend.clone(),
        net: (r.mean.psnr, r.mean.ssim, r.mean.seconds),
        plane_sweep: (
            b.plane_sweep.psnr,
            b.plane_sweep.ssim,
            b.plane_sweep.seconds.unwrap_or(0.0),
        ),
        nearest: (b.nearest.psnr, b.nearest.ssim),
        pictures,
    })
}

/// [`point`] at 1/`n` of the scene's resolution (`small`): the renders upsampled and
/// scored against the photographs of `scene`.
fn point_scaled(
    backend: &dyn Backend,
    model: &str,
    (scene, small, n): (&Scene, &Scene, u32),
    targets: &[usize],
    settings: &RenderSettings,
) -> Result<Point> {
    // [network, plane sweep, nearest] x (PSNR, SSIM) per view, scored at full resolution.
    let mut scored: Vec<Result<Scored>> = Vec::new();
    let r = evaluate(backend, model, small, targets, settings, |v, im| {
        scored.push(
            scene
                .load_image(v.target)
                .map_err(anyhow::Error::from)
                .map(|truth| {
                    let up = |img: &RgbImage| img.upsample(n, truth.width, truth.height);
                    let ups = [up(&im.rendered.image), up(im.plane_sweep), up(im.nearest)];
                    let score = |up: &RgbImage| (psnr(up, &truth), ssim(up, &truth));
                    let s = [score(&ups[0]), score(&ups[1]), score(&ups[2])];
                    let [rendered, plane_sweep, nearest] = ups;
                    let pictures = ViewPictures {
                        target: v.target,
                        name: v.name.clone(),
                        truth,
                        rendered,
                        plane_sweep,
                        nearest,
                        psnr: [s[0].0, s[1].0, s[2].0],
                    };
                    (s, pictures)
                }),
        );
    })?;
    let (scores, pictures): (Vec<[(f64, f64); 3]>, Vec<ViewPictures>) = scored
        .into_iter()
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .unzip();
    let k = scores.len().max(1) as f64;
    let mean = |i: usize| {
        let (p, s) = scores
            .iter()
            .fold((0.0, 0.0), |acc, v| (acc.0 + v[i].0, acc.1 + v[i].1));
        (p / k, s / k)
    };
    let ((np, ns), (pp, pss), nearest) = (mean(0), mean(1), mean(2));
    Ok(Point {
        backend: r.backend.clone(),
        net: (np, ns, r.mean.seconds),
        plane_sweep: (pp, pss, r.mean.baselines.plane_sweep.seconds.unwrap_or(0.0)),
        nearest,
        pictures,
    })
}
