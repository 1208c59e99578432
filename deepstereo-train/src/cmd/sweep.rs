//! `deepstereo sweep`: one target view's plane-sweep volume, as safetensors (and PNGs).

use super::args::SceneArgs;
use anyhow::bail;
use deepstereo_core::camera::Camera;
use deepstereo_core::config::Config;
use deepstereo_core::geometry::{depths_of, inverse_depths};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::inputs::{tile_inputs, PyramidSource};
use deepstereo_core::scene::Scene;
use deepstereo_core::sweep::{alloc_volume, sweep_into, Region, Source, CHANNELS};
use deepstereo_core::tensorio::{write_safetensors, NamedArray};
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
    let n = scene.views.len();
    if args.target >= n {
        bail!(
            "--target {} is out of range: the scene has {n} views",
            args.target
        );
    }
    if n < 2 {
        bail!("the scene has only one view: a target needs at least one other view as source");
    }
    let src_idx = scene.nearest_views(args.target, views);
    if src_idx.len() < views {
        eprintln!("note: only {} source views available", src_idx.len());
    }
    let target_img = scene.load_image(args.target)?;
    let images: Vec<RgbImage> = src_idx
        .iter()
        .map(|&i| scene.load_image(i))
        .collect::<Result<_, _>>()?;
    let sources: Vec<Source<'_>> = src_idx
        .iter()
        .zip(&images)
        .map(|(&i, image)| Source {
            camera: &scene.views[i].camera,
            image,
        })
        .collect();
    let cam = &scene.views[args.target].camera;
    let region = Region::full(&cam.intrinsics);
    // Allocated fallibly before anything of size `planes`: a huge --planes is an error.
    let mut psv = alloc_volume(planes, sources.len(), region)?;
    let inv = inverse_depths(scene.near, scene.far, planes);
    let t0 = std::time::Instant::now();
    sweep_into(cam, region, &sources, &inv, &mut psv);
    eprintln!(
        "swept {} planes x {} views at {}x{} in {:.3} s",
        planes,
        sources.len(),
        region.width,
        region.height,
        t0.elapsed().as_secs_f64()
    );
    let (d, v, h, w) = (planes, sources.len(), region.height, region.width);
    let depths: Vec<f32> = depths_of(&inv).iter().map(|&z| z as f32).collect();
    let target = channels_first(&target_img);
    let srcs: Vec<i64> = src_idx.iter().map(|&i| i as i64).collect();
    let mut arrays = vec![
        NamedArray::f32("psv", &[d, v, CHANNELS, h, w], &psv),
        NamedArray::f32("depths", &[d], &depths),
        NamedArray::f32("target", &[3, h, w], &target),
        NamedArray::i64("sources", &[v], &srcs),
    ];
    if let Some(cfg) = &cfg {
        arrays.extend(network_inputs(
            cfg,
            cam,
            &scene,
            &src_idx,
            &images,
            &inv,
            (h, w),
        )?);
    }
    // The PNGs go to a staged directory first, so that a failure leaves neither output.
    let staged = match &args.png {
        Some(dir) => Some(crate::cmd::support::outdir::StagedDir::new(dir)?),
        None => None,
    };
    if let Some(st) = &staged {
        for z in 0..d {
            plane_image(&psv, z, v, w, h).save_png(&st.path().join(format!("plane_{z:03}.png")))?;
        }
    }
    write_safetensors(&args.out, &arrays, None)?;
    eprintln!("wrote {}", args.out.display());
    if let Some(st) = staged {
        let dir = st.target().to_path_buf();
        st.commit()?;
        eprintln!("wrote {d} plane images to {}", dir.display());
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

/// An image's colours as [3, H, W].
fn channels_first(img: &RgbImage) -> Vec<f32> {
    let hw = img.width as usize * img.height as usize;
    let mut out = vec![0f32; 3 * hw];
    for (p, px) in img.data.chunks_exact(3).enumerate() {
        for c in 0..3 {
            out[c * hw + p] = px[c];
        }
    }
    out
}

/// The network's inputs (and `tile_origin`, `tile_size`) for one tile covering the whole
/// target image (`h` x `w`), through the same code that renders.
fn network_inputs(
    cfg: &Config,
    cam: &Camera,
    scene: &Scene,
    src_idx: &[usize],
    images: &[RgbImage],
    inv: &[f64],
    (h, w): (usize, usize),
) -> anyhow::Result<Vec<NamedArray>> {
    let d = inv.len();
    let a = cfg.tile_align();
    let mut arrays = Vec::new();
    let (th, tw) = (h.div_ceil(a) * a, w.div_ceil(a) * a);
    let pyramids: Vec<PyramidSource> = src_idx
        .iter()
        .zip(images)
        .map(|(&i, image)| PyramidSource::new(&scene.views[i].camera, image, cfg.levels))
        .collect();
    let refs: Vec<&PyramidSource> = pyramids.iter().collect();
    let t0 = std::time::Instant::now();
    let inputs = tile_inputs(cfg, cam, &refs, inv, (0, 0), (th, tw))?;
    for (l, (data, &(lh, lw))) in inputs.levels.iter().zip(&inputs.sizes).enumerate() {
        arrays.push(NamedArray::f32(
            &deepstereo_export::input_name(l),
            &cfg.input_shape(1, d, inputs.views, lh, lw),
            data,
        ));
    }
    arrays.push(NamedArray::i64("tile_origin", &[2], &[0, 0]));
    arrays.push(NamedArray::i64("tile_size", &[2], &[th as i64, tw as i64]));
    eprintln!(
        "network inputs for one {th}x{tw} tile ({} levels) in {:.3} s",
        cfg.levels,
        t0.elapsed().as_secs_f64()
    );
    Ok(arrays)
}

/// Plane `z` of the volume `psv` ([D, V, 4, H, W]) as a picture: the alpha-weighted mean
/// of the `v` sources' colours (black where no source has any weight).
fn plane_image(psv: &[f32], z: usize, v: usize, w: usize, h: usize) -> RgbImage {
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
        for (c, x) in acc.iter().enumerate() {
            img.data[p * 3 + c] = if wsum > 0.0 { x / wsum } else { 0.0 };
        }
    }
    img
}
