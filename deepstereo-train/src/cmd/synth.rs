//! `deepstereo synth`: write a set of procedural posed scenes (images, exact depth maps,
//! NeRF-style `transforms.json`) for training and testing.

use super::args::parse_size;
use anyhow::{bail, Context};
use deepstereo_core::synth::{
    contact_sheet, generate, load_textures, scene_seed, write_scenes_progress, Rig, SynthOptions,
    MAX_SUPERSAMPLE, MIN_VIEWS,
};
use std::path::PathBuf;

/// Scenes shown on the contact sheet.
const SHEET_SCENES: usize = 6;
/// Views shown per scene on the contact sheet.
const SHEET_VIEWS: usize = 3;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output directory; scene `i` is written to `scene_NNNN/` inside it (NeRF layout:
    /// `transforms.json`, `images/view_NNN.png`, `depth/view_NNN.npy`).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of scenes to write.
    #[arg(long)]
    pub scenes: usize,
    /// Base seed: scene `i` is generated from a seed hashed from it and `i`, so the same
    /// seed and options always give the same files.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Views per scene (at least 2; the trainer uses the nearest views as sources).
    #[arg(long, default_value_t = 10)]
    pub views: usize,
    /// Image size in pixels, as WIDTHxHEIGHT.
    #[arg(long, default_value = "160x120", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Camera rig: forward (LLFF-like grid), rosette (positions with several yaws each),
    /// ring (arc around an object cluster), handheld (random walk), or mixed (one of
    /// them per scene).
    #[arg(long, default_value_t = Rig::Mixed)]
    pub rig: Rig,
    /// Anti-aliasing: K x K rays per pixel, box filtered (1 to 8).
    #[arg(long, default_value_t = 3)]
    pub supersample: u32,
    /// Folder of PNG/JPEG photos: surfaces get random crops of them instead of
    /// procedural textures.
    #[arg(long)]
    pub textures: Option<PathBuf>,
    /// Rolling shutter: S in [0, 1] is the share of the camera's motion between
    /// neighbouring views that happens while one view's rows are read out (top to
    /// bottom); written in instant-ngp's convention (`transform_matrix_start`/`_end`,
    /// `rolling_shutter`). 0 (the default) is a global shutter.
    #[arg(
        long,
        default_value_t = 0.0,
        value_name = "S",
        allow_negative_numbers = true
    )]
    pub rolling_shutter: f64,
    /// Also write a contact sheet PNG here: a few views of the first scenes, each next to
    /// its colour-mapped inverse depth (bright = near).
    #[arg(long)]
    pub sheet: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.scenes == 0 {
        bail!("--scenes must be at least 1");
    }
    if args.views < MIN_VIEWS {
        bail!(
            "--views must be at least {MIN_VIEWS} (a target and a source), got {}",
            args.views
        );
    }
    if args.supersample == 0 || args.supersample > MAX_SUPERSAMPLE {
        bail!(
            "--supersample must be between 1 and {MAX_SUPERSAMPLE}, got {}",
            args.supersample
        );
    }
    let textures = match &args.textures {
        Some(dir) => {
            let t = load_textures(dir)
                .with_context(|| format!("cannot load --textures {}", dir.display()))?;
            eprintln!("loaded {} texture photos from {}", t.len(), dir.display());
            t
        }
        None => Vec::new(),
    };
    let (width, height) = args.size;
    let opts = SynthOptions {
        views: args.views,
        width,
        height,
        rig: args.rig,
        supersample: args.supersample,
        textures,
        rolling_shutter: args.rolling_shutter,
    };
    opts.validate()?;
    let bar = indicatif::ProgressBar::new(args.scenes as u64);
    let t0 = std::time::Instant::now();
    let staged = crate::cmd::support::outdir::StagedDir::new(&args.out)?;
    write_scenes_progress(staged.path(), args.scenes, args.seed, &opts, &|_| {
        bar.inc(1)
    })
    .with_context(|| format!("cannot write scenes to {}", args.out.display()))?;
    bar.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    println!(
        "wrote {} scenes ({} views of {width}x{height}, rig {}, supersample {}) to {} in {secs:.2} s: {:.2} scenes/s",
        args.scenes,
        args.views,
        args.rig,
        args.supersample,
        args.out.display(),
        args.scenes as f64 / secs.max(1e-9)
    );
    if let Some(path) = &args.sheet {
        let scenes = (0..args.scenes.min(SHEET_SCENES))
            .map(|i| generate(scene_seed(args.seed, i), &opts))
            .collect::<Result<Vec<_>, _>>()?;
        contact_sheet(&scenes, SHEET_VIEWS).save_png(path)?;
        println!("wrote contact sheet {}", path.display());
    }
    // Only now, with the contact sheet written too, do the scenes appear.
    staged.commit()?;
    Ok(())
}
