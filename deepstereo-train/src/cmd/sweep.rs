//! `deepstereo sweep`: one target view's plane-sweep volume, as safetensors (and PNGs).

use super::args::SceneArgs;
use crate::rendering::sweep::sweep_view;
use anyhow::bail;
use deepstereo_core::config::Config;
use deepstereo_core::tensorio::write_safetensors;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Index of the target view (left out of the sources).
    #[arg(long)]
    pub target: usize,
    /// Number of source views: the nearest to the target by camera centre (default: the
    /// model's with --model, else 4).
    #[arg(long)]
    pub views: Option<usize>,
    /// Number of depth planes, uniform in inverse depth between near and far (default: the
    /// model's with --model, else 32).
    #[arg(long)]
    pub planes: Option<usize>,
    /// Output safetensors file: `psv` [D, V, 4, H, W] f32, `depths` [D] f32, `target`
    /// [3, H, W] f32 in [0, 1], `sources` [V] i64 (view indices); with --model also the
    /// network's inputs (see --model).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write every input of this model's network (and of its ONNX export) for one
    /// tile covering the whole target image: `level0..level{L-1}` [1, D, 4V, H_l, W_l] f32
    /// (any-number-of-views models: [1, D, V, 4, H_l, W_l], or [1, D, V, 9, H_l, W_l] with
    /// each view's geometric cue after its RGBA; the image size rounded up to the model's alignment, plus the border the network
    /// reads), `tile_origin` [2] i64 (y0, x0) = (0, 0) and `tile_size` [2] i64 (th, tw).
    /// The network's output is then [1, 3, th, tw]; crop it to the image size.
    /// `embedded` names the embedded model.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Also write one PNG per plane (the alpha-weighted mean of the sources) here.
    #[arg(long)]
    pub png: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let model = match &args.model {
        Some(p) => Some(crate::rendering::models::load_model(Some(p))?),
        None => None,
    };
    let cfg = model.as_ref().map(|t| t.model.config().clone());
    let (planes, views) = counts(&args, cfg.as_ref())?;
    let scene = args.scene.load()?;
    let swept = sweep_view(&scene, args.target, (planes, views), cfg.as_ref())?;
    // The PNGs go to a staged directory first, so that a failure leaves neither output.
    let staged = match &args.png {
        Some(dir) => Some(crate::cmd::support::outdir::StagedDir::new(dir)?),
        None => None,
    };
    if let Some(st) = &staged {
        for z in 0..planes {
            let path = st.path().join(format!("plane_{z:03}.png"));
            swept.plane_image(z).save_png(&path)?;
        }
    }
    write_safetensors(&args.out, &swept.into_arrays(), None)?;
    eprintln!("wrote {}", args.out.display());
    if let Some(st) = staged {
        let dir = st.target().to_path_buf();
        st.commit()?;
        eprintln!("wrote {planes} plane images to {}", dir.display());
    }
    Ok(())
}

/// The plane and view counts: the options', else the model's, else 32 planes and 4
/// views; both at least 1, and views the model takes.
fn counts(args: &Args, cfg: Option<&Config>) -> anyhow::Result<(usize, usize)> {
    let planes = args.planes.or(cfg.map(|c| c.planes)).unwrap_or(32);
    let views = args.views.or(cfg.map(|c| c.views)).unwrap_or(4);
    if planes == 0 {
        bail!("--planes must be at least 1");
    }
    if views == 0 {
        bail!("--views must be at least 1");
    }
    if let Some(c) = cfg {
        if !c.accepts_views(views) {
            bail!("--views {views}: the model takes {} source views", c.views);
        }
    }
    Ok((planes, views))
}
