//! Multi-resolution plane-sweep inputs of the network for one output tile.
//!
//! Level `l` is the plane sweep of the sources' level-`l` pyramid images into the target
//! camera downsampled by `2^l`, over the region [`Config::input_origin`] /
//! [`Config::input_size`] give (see `config.rs` for the tile geometry). Only the pixels a
//! tile needs are warped. With a `pool.disagree`, each view's colour disagreement with the
//! nearest is taken from the sweep first ([`crate::view_weights::disagreement`]). With a
//! `pool.agree` in the config, the alpha of the views beyond
//! the nearest is gated by their colours' agreement with the nearest
//! ([`crate::view_weights::agree_gate`]); with a `pool.falloff`, every view's alpha is then
//! scaled by its weight ([`crate::view_weights`]); with `pool.cue` or `pool.weigh`, every
//! view's geometric cue ([`crate::sweep::cue`]) follows its RGBA, then its disagreement.

use crate::camera::Camera;
use crate::config::{Config, CUE_CHANNELS, MAX_VIEWS};
use crate::error::{Error, Result};
use crate::features::{FeatureMap, FeatureNet};
use crate::imageio::RgbImage;
use crate::sweep::cue::{centre_in, cue_slice, CueRays};
use crate::sweep::{alloc_volume, sweep_into, target_rays, Region, Source, CHANNELS};
use crate::view_weights::{agree_gate, disagreement, near_views, view_weights};
use glam::DVec3;

/// A source view prepared for sampling: its camera at every pyramid level and the images.
#[derive(Clone, Debug)]
pub struct PyramidSource {
    /// `cameras[l]`: the camera of pyramid level `l` (intrinsics divided by `2^l`).
    pub cameras: Vec<Camera>,
    pub images: Vec<RgbImage>,
    /// `features[l]`: the `features` family's map of `images[l]`
    /// ([`PyramidSource::with_features`]); empty until computed.
    pub features: Vec<FeatureMap>,
}

impl PyramidSource {
    /// Builds `levels` pyramid levels of `image` seen by `camera`.
    pub fn new(camera: &Camera, image: &RgbImage, levels: usize) -> Self {
        let images = image.pyramid(levels);
        let cameras = images
            .iter()
            .enumerate()
            .map(|(l, img)| level_camera(camera, l, img.width, img.height))
            .collect();
        Self {
            cameras,
            images,
            features: Vec::new(),
        }
    }

    /// This source with the feature map of every level from `net`: the CNN runs once
    /// per level image (the `features` family's "read each source once").
    pub fn with_features(self, net: &FeatureNet) -> Result<Self> {
        self.with_features_from(|img| {
            net.image_features(img, &candle_core::Device::Cpu)
                .map_err(|e| Error::Invalid(format!("source features: {e}")))
        })
    }

    /// This source with the map `features(image)` of every level image.
    pub fn with_features_from(
        mut self,
        features: impl Fn(&RgbImage) -> Result<FeatureMap>,
    ) -> Result<Self> {
        self.features = self.images.iter().map(features).collect::<Result<_>>()?;
        Ok(self)
    }

    /// Level `l` as a source for the plane sweep (its camera and image); `l` must be one
    /// of its levels.
    pub fn level(&self, l: usize) -> Source<'_> {
        Source {
            camera: &self.cameras[l],
            image: &self.images[l],
        }
    }
}

impl PyramidSource {
    /// The pyramid of `levels` levels whose level 0 is this one's level `l` (the same
    /// image and camera, downscaled by `2^l`); this one unchanged when it has no level
    /// `l` (callers check the level exists: `train --mpi-scale 2` needs 2 levels).
    pub fn from_level(&self, l: usize, levels: usize) -> Self {
        match (self.images.get(l), self.cameras.get(l)) {
            (Some(img), Some(cam)) => Self::new(cam, img, levels),
            _ => self.clone(),
        }
    }

    /// A source that sees nothing: `levels` empty images, so every sample of it has alpha
    /// 0 (the network's input for a view that is not there). `camera` only fills the
    /// slot.
    pub fn empty(camera: &Camera, levels: usize) -> Self {
        Self {
            cameras: vec![*camera; levels.max(1)],
            images: vec![RgbImage::new(0, 0); levels.max(1)],
            features: Vec::new(),
        }
    }
}

pub mod features;

/// The camera of level `l` (`1 / 2^l` resolution) with the given image size.
pub fn level_camera(camera: &Camera, l: usize, width: u32, height: u32) -> Camera {
    camera.downscaled((1u64 << l) as f64, width, height)
}

/// The input tensors' data for one tile: `levels[l]` is `[D, V, C_v, h_l, w_l]` f32 with
/// `C_v` = [`Config::view_channels`] (RGBA, then the cue); the paper family reads the same
/// bytes as `[D, 4V, h_l, w_l]`.
#[derive(Clone, Debug, PartialEq)]
pub struct TileInputs {
    pub levels: Vec<Vec<f32>>,
    /// `(h_l, w_l)` per level.
    pub sizes: Vec<(usize, usize)>,
    /// Source views `V`.
    pub views: usize,
    /// Channels per view `C_v` (alpha is channel 3).
    pub channels: usize,
}

impl TileInputs {
    /// Index of view `k`'s alpha at plane `z`, level-`l` pixel `(x, y)`.
    pub fn alpha_index(&self, l: usize, z: usize, k: usize, (x, y): (usize, usize)) -> usize {
        let (h, w) = self.sizes[l];
        ((z * self.views + k) * self.channels + 3) * h * w + y * w + x
    }
}

/// Checks a tile placement against the config's alignment.
pub fn check_tile(cfg: &Config, x0: i64, y0: i64, th: usize, tw: usize) -> Result<()> {
    let a = cfg.tile_align();
    if x0.rem_euclid(a as i64) != 0
        || y0.rem_euclid(a as i64) != 0
        || !th.is_multiple_of(a)
        || !tw.is_multiple_of(a)
        || th == 0
        || tw == 0
    {
        return Err(Error::Invalid(format!(
            "tile origin ({x0}, {y0}) and size {th}x{tw} must be positive multiples of {a}"
        )));
    }
    Ok(())
}

/// Builds every level's plane sweep for the output tile at `(x0, y0)` of `th x tw` pixels.
pub fn tile_inputs(
    cfg: &Config,
    target: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    origin: (i64, i64),
    size: (usize, usize),
) -> Result<TileInputs> {
    let mut inputs = tile_inputs_without_features(cfg, target, sources, inv_depths, origin, size)?;
    let f = cfg.pool.as_ref().map_or(0, |p| p.feature_channels());
    if f > 0 {
        features::append_warped(cfg, &mut inputs, (target, sources, inv_depths), origin, f)?;
    }
    Ok(inputs)
}

/// [`tile_inputs`] without the `features` family's warped maps: `[D, V, C_v - F, h_l, w_l]`
/// per level (training adds them in its graph, [`features::TileWarps`]).
pub fn tile_inputs_without_features(
    cfg: &Config,
    target: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    (x0, y0): (i64, i64),
    (th, tw): (usize, usize),
) -> Result<TileInputs> {
    check_tile(cfg, x0, y0, th, tw)?;
    check_view_count(cfg, sources.len())?;
    let mods = ViewMods::new(cfg, target, sources);
    let mut levels = Vec::with_capacity(cfg.levels);
    let mut sizes = Vec::with_capacity(cfg.levels);
    for l in 0..cfg.levels {
        if sources.iter().any(|s| s.images.len() <= l) {
            return Err(Error::Invalid(format!(
                "source pyramids have fewer than {} levels",
                l + 1
            )));
        }
        let region = Region {
            x0: cfg.input_origin(l, x0),
            y0: cfg.input_origin(l, y0),
            width: cfg.input_size(l, tw),
            height: cfg.input_size(l, th),
        };
        let tcam = level_camera(
            target,
            l,
            target.intrinsics.width >> l,
            target.intrinsics.height >> l,
        );
        let srcs: Vec<Source> = sources.iter().map(|s| s.level(l)).collect();
        let mut buf = alloc_volume(inv_depths.len(), sources.len(), region)?;
        sweep_into(&tcam, region, &srcs, inv_depths, &mut buf);
        let q = mods.apply(&mut buf, region.len());
        if cfg.pool.as_ref().is_some_and(|p| p.reads_cue()) {
            let centres: Vec<DVec3> = srcs.iter().map(|s| centre_in(&tcam, s.camera)).collect();
            buf = with_cue(&buf, &tcam, region, &centres, inv_depths, q.as_deref())?;
        }
        levels.push(buf);
        sizes.push((region.height, region.width));
    }
    Ok(TileInputs {
        levels,
        sizes,
        views: sources.len(),
        channels: cfg.view_channels() - cfg.pool.as_ref().map_or(0, |p| p.feature_channels()),
    })
}

/// Fails unless the model takes `views` source views.
fn check_view_count(cfg: &Config, views: usize) -> Result<()> {
    if cfg.accepts_views(views) {
        return Ok(());
    }
    Err(Error::Invalid(match cfg.pool {
        Some(_) => format!("the model takes 1 to {MAX_VIEWS} source views, got {views}"),
        None => format!("the model takes {} source views, got {views}", cfg.views),
    }))
}

/// What the config does to each swept level per view: the alpha weights, the colour
/// gate's near views and width, and the near views of the disagreement cue
/// (crate::view_weights), each where the config has it.
struct ViewMods {
    weights: Option<Vec<f64>>,
    agree: Option<(Vec<bool>, f32)>,
    disagree: Option<Vec<bool>>,
}

impl ViewMods {
    fn new(cfg: &Config, target: &Camera, sources: &[&PyramidSource]) -> Self {
        let centres: Vec<_> = sources
            .iter()
            .map(|s| match (s.images.first(), s.cameras.first()) {
                (Some(img), Some(cam)) if img.width > 0 && img.height > 0 => {
                    Some(cam.pose.centre())
                }
                _ => None,
            })
            .collect();
        let pool = cfg.pool.as_ref();
        let c = target.pose.centre();
        ViewMods {
            weights: pool
                .and_then(|p| p.falloff)
                .map(|f| view_weights(f, c, &centres)),
            agree: pool
                .and_then(|p| p.agree)
                .map(|a| (near_views(a.near, c, &centres), a.sigma)),
            disagree: pool
                .and_then(|p| p.disagree)
                .map(|d| near_views(d.near, c, &centres)),
        }
    }

    /// The disagreement cue of the swept volume `buf` (`n` pixels per plane), then the
    /// colour gate and the alpha weights applied to it.
    fn apply(&self, buf: &mut [f32], n: usize) -> Option<Vec<f32>> {
        let q = self
            .disagree
            .as_deref()
            .map(|near| disagreement(buf, near, n));
        if let Some((near, sigma)) = &self.agree {
            agree_gate(buf, near, *sigma, n);
        }
        if let Some(w) = self
            .weights
            .as_deref()
            .filter(|w| w.iter().any(|&g| g != 1.0))
        {
            scale_alpha(buf, w, n);
        }
        q
    }
}

/// The volume `rgba` `[D, V, 4, h, w]` with every view's cue after its RGBA:
/// `[D, V, 4 + K, h, w]` (sources' centres in the target's coordinates), `K` =
/// `CUE_CHANNELS`, or one more with the disagreement channel `q` `[D, V, h, w]`
/// ([`crate::view_weights::disagreement`]) last.
fn with_cue(
    rgba: &[f32],
    target: &Camera,
    region: Region,
    centres: &[DVec3],
    inv_depths: &[f64],
    q: Option<&[f32]>,
) -> Result<Vec<f32>> {
    use rayon::prelude::*;
    let (hw, v) = (region.len(), centres.len());
    let rays = CueRays::new(&target_rays(&target.intrinsics, region));
    let cue_channels = CUE_CHANNELS + usize::from(q.is_some());
    let per_view = (CHANNELS + cue_channels) * hw;
    let mut out = crate::sweep::try_zeroed(
        &[inv_depths.len(), v, per_view],
        &format!(
            "a plane-sweep volume with its cue of {} planes x {v} views x {} x {}x{}",
            inv_depths.len(),
            CHANNELS + cue_channels,
            region.width,
            region.height
        ),
    )?;
    out.par_chunks_mut(per_view)
        .zip(rgba.par_chunks(CHANNELS * hw))
        .enumerate()
        .for_each(|(slice, (dst, src))| {
            let (d, k) = (slice / v, slice % v);
            let (colour, cue) = dst.split_at_mut(CHANNELS * hw);
            colour.copy_from_slice(src);
            let (cue, last) = cue.split_at_mut(CUE_CHANNELS * hw);
            cue_slice(&rays, inv_depths[d], centres[k], cue);
            if let Some(q) = q {
                last.copy_from_slice(&q[slice * hw..][..hw]);
            }
        });
    Ok(out)
}

/// Scales the alpha of view `v` by `weights[v]` in a volume `[D, V, 4, h, w]` of `hw`
/// pixels per plane (colours stay as sampled).
fn scale_alpha(volume: &mut [f32], weights: &[f64], hw: usize) {
    for (i, slice) in volume.chunks_exact_mut(CHANNELS * hw).enumerate() {
        let g = weights[i % weights.len()] as f32;
        for a in &mut slice[3 * hw..] {
            *a *= g;
        }
    }
}
