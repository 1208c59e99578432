//! `deepstereo sweep`: one target view's plane-sweep volume, as safetensors (and PNGs).

use super::SceneArgs;
use anyhow::{bail, Context};
use deepstereo_core::geometry::{depths_of, inverse_depths};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::sweep::{sweep, Region, Source, CHANNELS};
use deepstereo_core::tensorio::{write_safetensors, NamedArray};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Index of the target view (left out of the sources).
    #[arg(long)]
    pub target: usize,
    /// Number of source views: the nearest to the target by camera centre.
    #[arg(long, default_value_t = 4)]
    pub views: usize,
    /// Number of depth planes, uniform in inverse depth between near and far.
    #[arg(long, default_value_t = 32)]
    pub planes: usize,
    /// Output safetensors file: `psv` [D, V, 4, H, W] f32, `depths` [D] f32, `target`
    /// [3, H, W] f32 in [0, 1], `sources` [V] i64 (view indices).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write one PNG per plane (the alpha-weighted mean of the sources) here.
    #[arg(long)]
    pub png: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.planes == 0 {
        bail!("--planes must be at least 1");
    }
    if args.views == 0 {
        bail!("--views must be at least 1");
    }
    let scene = args.scene.load()?;
    let n = scene.views.len();
    if args.target >= n {
        bail!("--target {} is out of range: the scene has {n} views", args.target);
    }
    if n < 2 {
        bail!("the scene has only one view: a target needs at least one other view as source");
    }
    let src_idx = scene.nearest_views(args.target, args.views);
    if src_idx.len() < args.views {
        eprintln!("note: only {} source views available", src_idx.len());
    }
    let target_img = scene.load_image(args.target)?;
    let images: Vec<RgbImage> = src_idx.iter().map(|&i| scene.load_image(i)).collect::<Result<_, _>>()?;
    let sources: Vec<Source<'_>> = src_idx
        .iter()
        .zip(&images)
        .map(|(&i, image)| Source { camera: &scene.views[i].camera, image })
        .collect();
    let cam = &scene.views[args.target].camera;
    let inv = inverse_depths(scene.near, scene.far, args.planes);
    let region = Region::full(&cam.intrinsics);
    let t0 = std::time::Instant::now();
    let psv = sweep(cam, region, &sources, &inv);
    eprintln!(
        "swept {} planes x {} views at {}x{} in {:.3} s",
        args.planes,
        sources.len(),
        region.width,
        region.height,
        t0.elapsed().as_secs_f64()
    );
    let (d, v, h, w) = (args.planes, sources.len(), region.height, region.width);
    let depths: Vec<f32> = depths_of(&inv).iter().map(|&z| z as f32).collect();
    let mut target = vec![0f32; 3 * h * w];
    for (p, px) in target_img.data.chunks_exact(3).enumerate() {
        for c in 0..3 {
            target[c * h * w + p] = px[c];
        }
    }
    let srcs: Vec<i64> = src_idx.iter().map(|&i| i as i64).collect();
    write_safetensors(
        &args.out,
        &[
            NamedArray::f32("psv", &[d, v, CHANNELS, h, w], &psv),
            NamedArray::f32("depths", &[d], &depths),
            NamedArray::f32("target", &[3, h, w], &target),
            NamedArray::i64("sources", &[v], &srcs),
        ],
        None,
    )?;
    eprintln!("wrote {}", args.out.display());
    if let Some(dir) = &args.png {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        for z in 0..d {
            let mut img = RgbImage::new(w as u32, h as u32);
            for p in 0..h * w {
                let mut acc = [0f32; 3];
                let mut wsum = 0f32;
                for k in 0..v {
                    let base = ((z * v + k) * CHANNELS) * h * w;
                    let a = psv[base + 3 * h * w + p];
                    for (c, x) in acc.iter_mut().enumerate() {
                        *x += psv[base + c * h * w + p];
                    }
                    wsum += a;
                }
                for c in 0..3 {
                    img.data[p * 3 + c] = if wsum > 0.0 { acc[c] / wsum } else { 0.0 };
                }
            }
            img.save_png(&dir.join(format!("plane_{z:03}.png")))?;
        }
        eprintln!("wrote {d} plane images to {}", dir.display());
    }
    Ok(())
}
