//! `deepstereo mpi`: multiplane images baked by the network, with a browser viewer; or,
//! with `--eval`, held-out views seen through MPIs beside the network's own renders.

use super::args::SceneModelArgs;
use crate::cmd::support::outdir::StagedDir;
use crate::rendering::mpi::{
    bake_at, bake_settings, eval_through_mpi, BakeOptions, MpiEvalOptions, OwnPhoto, BAKE_AGREE,
    BAKE_SMOOTH,
};
use crate::rendering::{PlaneSpan, Prepared, RenderSettings};
use anyhow::{bail, Context, Result};
use deepstereo_core::camera::Camera;
use deepstereo_core::imageio::write_atomic;
use deepstereo_core::mpi::{io, viewer};
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use std::path::{Path, PathBuf};

#[derive(Debug, clap::Args)]
pub struct Args {
    // The scene whose views are the sources. The model that bakes the layers, and its
    // settings.
    // The held-out views: never sources.
    #[command(flatten)]
    pub input: SceneModelArgs,
    /// Bake at view I's camera (showing there the render with its own photograph among
    /// the sources; see --own-photo-as-source).
    #[arg(long, conflicts_with_all = ["targets", "pose", "eval"])]
    pub target: Option<usize>,
    /// Bake one MPI at each of these views (`I,J,K`, at most 8), blended by distance in
    /// the viewer and by `render --mpi`, for a wider range of motion.
    #[arg(long, conflicts_with_all = ["pose", "eval"])]
    pub targets: Option<String>,
    /// Bake at a camera given as JSON (as `render --pose` takes it).
    #[arg(long, conflicts_with = "eval")]
    pub pose: Option<PathBuf>,
    /// With --pose FILE holding `inspect --json`'s output: the view whose camera to bake
    /// at.
    #[arg(long, requires = "pose")]
    pub view: Option<usize>,
    /// Bake at --target/--targets views without their own photographs: the planes come
    /// from the other views only (the reference view is then the network's prediction of
    /// it, as `render --target` gives, not the photograph).
    #[arg(long, help_heading = super::args::EXPERT)]
    pub exclude_own_photo: bool,
    /// Bake at --target/--targets views with their own photograph as one more source, as
    /// `render --pose` at that camera runs the network. Without it (and without
    /// --exclude-own-photo), the MPI of the other views is baked and its colours moved so
    /// that at its reference it shows that render: the same picture there, and the other
    /// views' depths elsewhere, 3.0 dB closer to held-out views on average than this bake
    /// (docs/results.md).
    #[arg(long, conflicts_with = "exclude_own_photo", help_heading = super::args::EXPERT)]
    pub own_photo_as_source: bool,
    /// Pixels added on every side of each MPI's image beyond its reference camera's (the
    /// principal point moves with them; the network fills them from the sources): an
    /// MPI then covers what cameras moved away from the reference see beyond its image
    /// (measured in docs/results.md). `mpi.json` records it; the viewer's `?fit=native`
    /// leaves it out. 0: the reference image only; at most the image's larger side.
    #[arg(long, default_value_t = 64, help_heading = super::args::EXPERT)]
    pub margin: u32,
    /// Each texel's selection (its planes' shares of the picture) averaged over the box
    /// of (2R+1)x(2R+1) texels around it before it becomes alpha: one depth profile for
    /// neighbouring pixels instead of the network's pixel-by-pixel choice, which a moved
    /// camera shows as misplaced detail. The picture at the reference stays the
    /// network's. 0: the network's selection as it is.
    #[arg(long, value_name = "R", default_value_t = BAKE_SMOOTH, help_heading = super::args::EXPERT)]
    pub smooth: usize,
    /// With the default bake (the photograph moves the colours of its own image): each
    /// texel's selection, from the other views, weighed per plane by how well the
    /// photograph agrees with those views there, exp(-e / TAU), e the mean of the closer
    /// half of their colour errors (RGB in [0, 1]), before it is smoothed: plane-sweep
    /// stereo with the photograph, which the network cannot do with it among its sources.
    /// The picture at the reference stays the network's. 0: not reweighed.
    #[arg(long, value_name = "TAU", default_value_t = BAKE_AGREE, value_parser = parse_agree, help_heading = super::args::EXPERT)]
    pub agree: f64,
    /// Instead of writing MPIs: render every held-out view through an MPI baked at its
    /// nearest view that is not held out, beside the network's render of it; writes
    /// eval.json into --out.
    #[arg(long)]
    pub eval: bool,
    /// With --eval: MPIs per held-out view, baked at its nearest views that are not held
    /// out and blended by distance.
    #[arg(long, default_value_t = 1, requires = "eval", help_heading = super::args::EXPERT)]
    pub eval_mpis: usize,
    /// Output directory: mpi.json, plane_NN.png, index.html and mpi.js (with --targets,
    /// one mpi_NN/ per MPI beside index.html and mpi.js).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let scene = a.input.scene.load_working()?;
    let n = scene.views.len();
    let holdout = a.input.holdout.list(n)?;
    let backend = a.input.model.backend()?;
    let net = a.input.model.settings()?;
    // The views that may be sources of a bake: neither held out nor, without its
    // photograph, the reference view (a --pose camera is none).
    let own = own_photo(&a);
    let own_left_out = own != OwnPhoto::Source && a.pose.is_none();
    let available = n.saturating_sub(holdout.len() + usize::from(own_left_out));
    let settings = bake_settings(&net, backend.config(), available);
    if a.eval {
        return run_eval(&a, backend.as_ref(), &scene, &holdout, (&net, &settings));
    }
    let targets = bake_targets(&a, &scene, &holdout)?;
    let staged = StagedDir::new(&a.out)?;
    let bake = Bake {
        backend: backend.as_ref(),
        scene: &scene,
        holdout: &holdout,
        own,
        settings: &settings,
    };
    let (names, range) = bake_all(&a, &bake, &targets, staged.path())?;
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    viewer::write(staged.path(), &refs, range)?;
    staged.commit()?;
    eprintln!(
        "wrote the viewer: open {} in a browser (?fit=native: the reference view pixel for pixel)",
        a.out.join("index.html").display()
    );
    Ok(())
}

/// What every bake of a run shares.
struct Bake<'a> {
    backend: &'a dyn Backend,
    scene: &'a Scene,
    holdout: &'a [usize],
    own: OwnPhoto,
    settings: &'a RenderSettings,
}

/// Bakes an MPI at each target into `dir` (`.` for one, else `mpi_NN`), with progress
/// bars and a line each on stderr; the directory names, and the farthest distance of a
/// reference or source camera from the first target's (the viewer's range of motion).
fn bake_all(
    a: &Args,
    b: &Bake,
    targets: &[(Camera, Option<usize>)],
    dir: &Path,
) -> Result<(Vec<String>, f64)> {
    let mut prepared = Prepared::new(b.scene);
    let mut names = Vec::new();
    let mut range = 0f64;
    let first = targets[0].0.pose.centre();
    for (i, (cam, view)) in targets.iter().enumerate() {
        let t0 = std::time::Instant::now();
        let bar = indicatif::ProgressBar::new(0);
        let progress = |done: usize, total: usize| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        };
        let (mpi, srcs) = bake_at(
            b.backend,
            b.scene,
            &mut prepared,
            (cam, *view, bake_options(a)),
            b.holdout,
            b.own,
            b.settings,
            &progress,
        )?;
        bar.finish_and_clear();
        let name = if targets.len() == 1 {
            ".".to_string()
        } else {
            format!("mpi_{i:02}")
        };
        io::write(&mpi, &dir.join(&name))?;
        let depth = |r: Option<&f64>| r.map_or(f64::NAN, |&r| 1.0 / r);
        eprintln!(
            "baked {}x{}, {} planes at depths {:.4}-{:.4}, in {:.2} s from views {srcs:?} into {}",
            mpi.width(),
            mpi.height(),
            mpi.planes().len(),
            depth(mpi.inv_depths.first()),
            depth(mpi.inv_depths.last()),
            t0.elapsed().as_secs_f64(),
            a.out.join(&name).display()
        );
        for &s in &srcs {
            range = range.max((b.scene.views[s].camera.pose.centre() - first).length());
        }
        range = range.max((mpi.camera.pose.centre() - first).length());
        names.push(name);
    }
    Ok((names, range))
}

/// The margin, smoothing and agreement of every bake.
fn bake_options(a: &Args) -> BakeOptions {
    BakeOptions {
        margin: a.margin,
        smooth: a.smooth,
        agree: a.agree,
    }
}

/// `--agree`: 0 (off) or a positive, finite colour scale.
fn parse_agree(s: &str) -> std::result::Result<f64, String> {
    let tau: f64 = s.parse().map_err(|e| format!("{s:?}: {e}"))?;
    if tau == 0.0 || (tau.is_finite() && tau > 0.0) {
        Ok(tau)
    } else {
        Err(format!("{s}: 0 (off) or a positive colour scale"))
    }
}

/// How the reference views' own photographs enter the bakes.
fn own_photo(a: &Args) -> OwnPhoto {
    match (a.exclude_own_photo, a.own_photo_as_source) {
        (true, _) => OwnPhoto::Excluded,
        (false, true) => OwnPhoto::Source,
        (false, false) => OwnPhoto::Residual,
    }
}

/// The cameras to bake at, each with the view it is, if any (whose photograph enters its
/// bake as [`own_photo`] says).
fn bake_targets(
    a: &Args,
    scene: &Scene,
    holdout: &[usize],
) -> Result<Vec<(Camera, Option<usize>)>> {
    let n = scene.views.len();
    let views: Vec<usize> = match (a.target, &a.targets, &a.pose) {
        (Some(t), None, None) => vec![t],
        (None, Some(list), None) => list
            .split(',')
            .map(|s| {
                s.trim()
                    .parse::<usize>()
                    .with_context(|| format!("--targets: '{s}' is not a view index"))
            })
            .collect::<Result<_>>()?,
        (None, None, Some(p)) => {
            let cam = crate::cmd::support::camera_json::read_pose(p, a.view)?;
            return Ok(vec![(cam, None)]);
        }
        _ => bail!("pass one of --target I, --targets I,J,K or --pose FILE (or --eval)"),
    };
    if views.is_empty() || views.len() > viewer::MAX_MPIS {
        bail!(
            "--targets: 1 to {} views, not {}",
            viewer::MAX_MPIS,
            views.len()
        );
    }
    let mut out = Vec::new();
    for &v in &views {
        if v >= n {
            bail!("view {v} is out of range: the scene has {n} views");
        }
        if holdout.contains(&v) {
            bail!("view {v} is held out: bake at a view that is not");
        }
        if out.iter().any(|(_, o)| *o == Some(v)) {
            bail!("--targets: view {v} is listed twice");
        }
        out.push((scene.views[v].camera, Some(v)));
    }
    Ok(out)
}

/// `--eval`: held-out views through MPIs, a table on stderr and eval.json in --out.
fn run_eval(
    a: &Args,
    backend: &dyn Backend,
    scene: &Scene,
    holdout: &[usize],
    (settings, bake): (&RenderSettings, &RenderSettings),
) -> Result<()> {
    if holdout.is_empty() {
        bail!("--eval needs held-out views: pass --llffhold N or --holdout I,J,...");
    }
    let staged = StagedDir::new(&a.out)?;
    eprintln!("view  references  network dB  MPI dB  MPI-vs-network dB  network s  bake s  MPI s");
    let opts = MpiEvalOptions {
        mpis: a.eval_mpis,
        own_photo: own_photo(a),
        bake: bake_options(a),
    };
    let per_view = eval_through_mpi(backend, scene, holdout, opts, (settings, bake), |r| {
        eprintln!(
            "{:>4}  {:>10}  {:>10.2}  {:>6.2}  {:>17.2}  {:>9.2}  {:>6.2}  {:>5.3}",
            r.target,
            format!("{:?}", r.references),
            r.network_psnr,
            r.mpi_psnr,
            r.mpi_vs_network_psnr,
            r.network_seconds,
            r.bake_seconds,
            r.mpi_render_seconds
        );
    })?;
    let m = |f: fn(&crate::rendering::mpi::MpiViewResult) -> f64| {
        per_view.iter().map(f).sum::<f64>() / per_view.len() as f64
    };
    let mean = serde_json::json!({
        "network_psnr": m(|r| r.network_psnr),
        "network_ssim": m(|r| r.network_ssim),
        "mpi_psnr": m(|r| r.mpi_psnr),
        "mpi_ssim": m(|r| r.mpi_ssim),
        "network_seconds": m(|r| r.network_seconds),
        "bake_seconds": m(|r| r.bake_seconds),
        "mpi_render_seconds": m(|r| r.mpi_render_seconds),
    });
    eprintln!(
        "mean: network {:.2} dB, through MPIs {:.2} dB; a frame from an MPI is {:.0}x faster than the network's",
        mean["network_psnr"].as_f64().unwrap_or(f64::NAN),
        mean["mpi_psnr"].as_f64().unwrap_or(f64::NAN),
        m(|r| r.network_seconds) / m(|r| r.mpi_render_seconds).max(1e-9)
    );
    let report = serde_json::json!({
        "scene": a.input.scene.scene.display().to_string(),
        "model": a.input.model.name(),
        "planes": settings.planes.unwrap_or(backend.config().default_render_planes()),
        "views": settings.source_count(backend.config())?,
        "bake_views": bake.source_count(backend.config())?,
        "plane_span": settings.span.unwrap_or(PlaneSpan::Scene),
        "bake_plane_span": bake.span.unwrap_or(PlaneSpan::Scene),
        "own_photo": own_photo(a),
        "margin": a.margin,
        "smooth": a.smooth,
        "agree": a.agree,
        "mpis_per_view": a.eval_mpis,
        "per_view": per_view,
        "mean": mean,
    });
    write_json(&staged.path().join("eval.json"), &report)?;
    staged.commit()?;
    eprintln!("wrote {}", a.out.join("eval.json").display());
    Ok(())
}

fn write_json(path: &Path, v: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(v)?;
    write_atomic(path, text.as_bytes())?;
    Ok(())
}
