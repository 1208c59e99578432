//! One target view's plane-sweep volume, and the inputs of a model's network for one
//! tile covering it, as `deepstereo sweep` writes them.

use anyhow::{bail, Result};
use deepstereo_core::camera::Camera;
use deepstereo_core::config::Config;
use deepstereo_core::geometry::{depths_of, inverse_depths};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::inputs::{tile_inputs, PyramidSource};
use deepstereo_core::scene::Scene;
use deepstereo_core::sweep::{alloc_volume, sweep_into, Region, Source, CHANNELS};
use deepstereo_core::tensorio::NamedArray;

/// A target view's plane-sweep volume, with what is written beside it.
pub struct SweptView {
    /// `[D, V, 4, H, W]`.
    pub psv: Vec<f32>,
    /// `(D, V, H, W)`.
    pub dims: (usize, usize, usize, usize),
    pub depths: Vec<f32>,
    /// The target's photograph, `[3, H, W]`.
    pub target: Vec<f32>,
    /// The source views' indices.
    pub sources: Vec<i64>,
    /// The network's inputs, when a model's config was given.
    pub inputs: Vec<NamedArray>,
}

impl SweptView {
    /// Everything as named arrays: `psv`, `depths`, `target`, `sources`, then the
    /// network's inputs.
    pub fn into_arrays(self) -> Vec<NamedArray> {
        let (d, v, h, w) = self.dims;
        let mut arrays = vec![
            NamedArray::f32("psv", &[d, v, CHANNELS, h, w], &self.psv),
            NamedArray::f32("depths", &[d], &self.depths),
            NamedArray::f32("target", &[3, h, w], &self.target),
            NamedArray::i64("sources", &[v], &self.sources),
        ];
        arrays.extend(self.inputs);
        arrays
    }

    /// Plane `z` as a picture ([`plane_image`]).
    pub fn plane_image(&self, z: usize) -> RgbImage {
        let (_, v, h, w) = self.dims;
        plane_image(&self.psv, z, v, w, h)
    }
}

/// The volume of view `target` of the scene over `planes` planes from its `views`
/// nearest views, and with `cfg` the network's inputs (progress on stderr).
pub fn sweep_view(
    scene: &Scene,
    target: usize,
    (planes, views): (usize, usize),
    cfg: Option<&Config>,
) -> Result<SweptView> {
    let n = scene.views.len();
    if target >= n {
        bail!("--target {target} is out of range: the scene has {n} views");
    }
    if n < 2 {
        bail!("the scene has only one view: a target needs at least one other view as source");
    }
    let src_idx = scene.nearest_views(target, views);
    if src_idx.len() < views {
        eprintln!("note: only {} source views available", src_idx.len());
    }
    let target_img = scene.load_image(target)?;
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
    let cam = &scene.views[target].camera;
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
    let (h, w) = (region.height, region.width);
    let inputs = match cfg {
        Some(cfg) => network_inputs(cfg, cam, scene, &src_idx, &images, &inv, (h, w))?,
        None => Vec::new(),
    };
    Ok(SweptView {
        psv,
        dims: (planes, sources.len(), h, w),
        depths: depths_of(&inv).iter().map(|&z| z as f32).collect(),
        target: channels_first(&target_img),
        sources: src_idx.iter().map(|&i| i as i64).collect(),
        inputs,
    })
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
) -> Result<Vec<NamedArray>> {
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
