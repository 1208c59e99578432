//! One training sample: a scene, a target view and its sources, a tile of it, and the
//! tile's inputs and target patch, optionally augmented.

use super::{mix, Sampling, SceneData, AUGMENT_EXPOSURE, AUGMENT_WHITE_BALANCE, MAX_FLAT_REDRAWS};
use crate::training::scene_weights::SceneWeights;
use anyhow::bail;
use deepstereo_core::camera::Camera;
use deepstereo_core::config::Config;
use deepstereo_core::geometry::inverse_depths;
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::inputs::features::{tile_warps, TileWarps};
use deepstereo_core::inputs::{
    tile_inputs, tile_inputs_without_features, PyramidSource, TileInputs,
};

/// Builds sample `k` of batch `b` with `views` sources: returns per-level inputs and the
/// target patch. A pooled model gets empty views (alpha 0, which change nothing) where
/// a scene has fewer.
pub(super) fn sample(
    cfg: &Config,
    sampling: &Sampling,
    scenes: &[SceneData],
    (seed, b, k): (u64, u64, usize),
    views: usize,
) -> anyhow::Result<Sample> {
    let mut state = mix(seed ^ mix(b.wrapping_mul(0x1000_0000_01B3) ^ mix(k as u64)));
    let mut next = || {
        state = mix(state);
        state
    };
    let s = pick_scene(scenes, sampling, next(), next());
    let n = s.cameras.len();
    let pad = cfg.pool.is_some();
    if n < 2 || (n <= views && !pad) {
        bail!(
            "scene {} has {n} views; the model needs {views} sources plus a target",
            s.name,
        );
    }
    let target = s.draw_target(next());
    // A stride range of one value draws nothing (the samples of runs before it).
    let stride = match sampling.view_stride {
        (lo, hi) if lo < hi => lo + (next() % (hi - lo + 1) as u64) as usize,
        (lo, _) => lo,
    };
    let src = s.strided_sources(target, views, stride);
    let t = cfg.tile;
    let (x0, y0) = draw_tile(cfg, sampling, (s, target), &mut next)?;
    let cam = &s.cameras[target];
    let inv = inverse_depths(s.near, s.far, cfg.planes);
    let empty = PyramidSource::empty(cam, cfg.levels);
    let mut srcs: Vec<&PyramidSource> = src.iter().map(|&i| &s.pyramids[i]).collect();
    srcs.resize(views, &empty);
    let origin = (x0 as i64, y0 as i64);
    let (mut inputs, mut warps) = tile_parts(cfg, (cam, &srcs, &inv), origin)?;
    let mut patch = patch(
        &s.pyramids[target].images[0],
        (x0 as u32, y0 as u32),
        (t, t),
    );
    let flipped =
        sampling.augment && augment(&mut inputs, warps.as_mut(), (&mut patch, t), &mut next);
    Ok(Sample {
        levels: inputs.levels,
        target: patch,
        warps,
        tile: TileRef {
            camera: *cam,
            inv_depths: inv,
            origin: (x0 as usize, y0 as usize),
            side: t,
            flipped,
        },
    })
}

/// The offset of a training tile in the target view `target` of `s`: random, aligned,
/// and (with `skip_flat`) redrawn a few times while the tile is flat.
fn draw_tile(
    cfg: &Config,
    sampling: &Sampling,
    (s, target): (&SceneData, usize),
    next: &mut impl FnMut() -> u64,
) -> anyhow::Result<(u64, u64)> {
    let t = cfg.tile;
    let a = cfg.tile_align() as u64;
    let cam = &s.cameras[target];
    let (w, h) = (cam.intrinsics.width as u64, cam.intrinsics.height as u64);
    if w < t as u64 || h < t as u64 {
        bail!(
            "scene {}: images {w}x{h} are smaller than the {t}px training tile",
            s.name
        );
    }
    let mut draw = || {
        let x0 = aligned_offset(next(), w, t, a);
        (x0, aligned_offset(next(), h, t, a))
    };
    let (mut x0, mut y0) = draw();
    if let Some(min_std) = sampling.skip_flat {
        // Redraw flat tiles (a few times at most: a flat image keeps its last draw).
        let img = &s.pyramids[target].images[0];
        for _ in 0..MAX_FLAT_REDRAWS {
            if luminance_std(img, (x0 as u32, y0 as u32), t as u32) >= min_std {
                break;
            }
            (x0, y0) = draw();
        }
    }
    Ok((x0, y0))
}

/// The tile's inputs at `origin` seen from `cam` through `srcs` at `inv`, and for the
/// features family (whose maps the graph appends) the sources' warps.
fn tile_parts(
    cfg: &Config,
    (cam, srcs, inv): (&Camera, &[&PyramidSource], &[f64]),
    origin: (i64, i64),
) -> anyhow::Result<(TileInputs, Option<TileWarps>)> {
    let t = cfg.tile;
    let radius = cfg
        .pool
        .as_ref()
        .and_then(|p| p.features.as_ref())
        .map(|f| f.radius());
    let inputs = match radius {
        Some(_) => tile_inputs_without_features(cfg, cam, srcs, inv, origin, (t, t))?,
        None => tile_inputs(cfg, cam, srcs, inv, origin, (t, t))?,
    };
    let warps = match radius {
        Some(r) => Some(tile_warps(cfg, (cam, srcs, inv), origin, &inputs.sizes, r)?),
        None => None,
    };
    Ok((inputs, warps))
}

/// Random exposure and white-balance gains on the inputs, the warps' colours and the
/// target patch (of side `t`), and a horizontal flip (none with source features);
/// whether it flipped.
fn augment(
    inputs: &mut TileInputs,
    warps: Option<&mut TileWarps>,
    (patch, t): (&mut [f32], usize),
    next: &mut impl FnMut() -> u64,
) -> bool {
    let unit = |r: u64| (r >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0;
    let exposure = (AUGMENT_EXPOSURE * unit(next())).exp();
    let gains: Vec<f32> = (0..3)
        .map(|_| (exposure * (1.0 + AUGMENT_WHITE_BALANCE * unit(next()))) as f32)
        .collect();
    // No flip with source features: the CNN sees the sources unmirrored when it
    // renders, and is not mirror-symmetric (the draw is kept, so other models'
    // samples stay as they were).
    let flip = next() & 1 == 1 && warps.is_none();
    if let Some(w) = warps {
        w.scale_colours(&gains);
    }
    let cycle = inputs.channels;
    for (data, &(h, w)) in inputs.levels.iter_mut().zip(&inputs.sizes) {
        augment_planes(data, (h * w, w, cycle), &gains, flip);
    }
    augment_planes(patch, (t * t, t, 3), &gains, flip);
    flip
}

/// One sample: its input levels, target patch, where its tile is and, for the features
/// family, warps.
pub(super) struct Sample {
    pub(super) levels: Vec<Vec<f32>>,
    pub(super) target: Vec<f32>,
    pub(super) warps: Option<TileWarps>,
    pub(super) tile: TileRef,
}

/// Where a sample's tile is: its target camera and planes, the tile's offset and side
/// in the target view (level 0), and whether augmentation mirrored it (its inputs and
/// target patch left-right). What a scene prior needs to reweigh the tile's selection.
#[derive(Clone, Debug)]
pub struct TileRef {
    pub camera: Camera,
    /// The planes' inverse depths, near to far.
    pub inv_depths: Vec<f64>,
    /// `(x0, y0)`, the tile's first pixel.
    pub origin: (usize, usize),
    pub side: usize,
    pub flipped: bool,
}

/// A tile's offset along a side of `size` pixels from the random `r`: a multiple of `a`
/// that leaves the `side`-pixel tile inside (`size >= side`).
pub(super) fn aligned_offset(r: u64, size: u64, side: usize, a: u64) -> u64 {
    (r % ((size - side as u64) / a + 1)) * a
}

/// The `w x h` patch of `img` at `(x0, y0)`, `[3, h, w]`.
pub(super) fn patch(img: &RgbImage, (x0, y0): (u32, u32), (w, h): (usize, usize)) -> Vec<f32> {
    let mut out = vec![0f32; 3 * w * h];
    for y in 0..h {
        for x in 0..w {
            let p = img.pixel(x0 + x as u32, y0 + y as u32);
            for c in 0..3 {
                out[(c * h + y) * w + x] = p[c];
            }
        }
    }
    out
}

/// The standard deviation of the luminance (Rec. 601 weights) over the `t x t` tile at
/// `(x0, y0)` of `img`.
pub(super) fn luminance_std(img: &RgbImage, (x0, y0): (u32, u32), t: u32) -> f32 {
    let (mut sum, mut sq) = (0f64, 0f64);
    for y in y0..y0 + t {
        for x in x0..x0 + t {
            let [r, g, b] = img.pixel(x, y);
            let l = (0.299 * r + 0.587 * g + 0.114 * b) as f64;
            sum += l;
            sq += l * l;
        }
    }
    let n = (t * t).max(1) as f64;
    let mean = sum / n;
    ((sq / n - mean * mean).max(0.0)).sqrt() as f32
}

/// Applies photometric gains and an optional horizontal flip to planes of `plane` pixels
/// in rows of `w`, channels cycling with period `cycle` (3 for the target patch; 4 or
/// 4 + `CUE_CHANNELS` per source view: R, G, B get the gains, alpha none). A flip mirrors
/// the target camera, which negates the cue's horizontal direction (its channel 0, the
/// volume's channel 4) and leaves the rest.
pub(super) fn augment_planes(
    data: &mut [f32],
    (plane, w, cycle): (usize, usize, usize),
    gains: &[f32],
    flip: bool,
) {
    for (i, p) in data.chunks_exact_mut(plane).enumerate() {
        let c = i % cycle;
        if let Some(&g) = gains.get(c) {
            p.iter_mut().for_each(|x| *x *= g);
        }
        if flip {
            p.chunks_exact_mut(w).for_each(|row| row.reverse());
            if c == 4 {
                p.iter_mut().for_each(|x| *x = -*x);
            }
        }
    }
}

/// A scene for one sample: with `synthetic_percent`, first procedural or real with that
/// chance (when both kinds are there), then among that kind: uniformly, or in proportion
/// to `scene_weights` (a procedural scene, or a real one not named, weighs 1).
pub(super) fn pick_scene<'a>(
    scenes: &'a [SceneData],
    sampling: &Sampling,
    r1: u64,
    r2: u64,
) -> &'a SceneData {
    let synth = scenes.iter().filter(|s| s.synthetic).count();
    let weighted = !sampling.scene_weights.is_empty();
    let pool: Vec<&SceneData> = match sampling.synthetic_percent {
        Some(p) if synth > 0 && synth < scenes.len() => {
            let want = r1 % 100 < p as u64;
            scenes.iter().filter(|s| s.synthetic == want).collect()
        }
        // Unweighted, the draws of the runs before weights: `r1` alone picks the scene.
        _ if !weighted => return &scenes[(r1 % scenes.len() as u64) as usize],
        _ => scenes.iter().collect(),
    };
    if !weighted {
        return pool[(r2 % pool.len() as u64) as usize];
    }
    let w: Vec<f64> = (pool.iter())
        .map(|s| match s.synthetic {
            true => 1.0,
            false => sampling.scene_weights.weight(&s.name),
        })
        .collect();
    pool[SceneWeights::draw(&w, r2)]
}
