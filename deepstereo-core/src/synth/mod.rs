//! Procedural posed scenes for training: textured planar rectangles (fronto-parallel,
//! slanted and grazing) at random depths that occlude each other, a few thin poles and
//! bars, and a distant backdrop, ray traced with anti-aliasing from cameras on one of
//! several rigs, with exact depth maps.
//!
//! # Conventions
//! Cameras follow [`crate::camera`]: OpenCV axes, world-to-camera poses, pixel `(i, j)`
//! covering `[i, i+1) x [j, j+1)`. The world is the frame of a reference camera of the
//! rig (origin, looking down +z). Depth maps hold the camera-space z of the ray through
//! each pixel centre. `near` is slightly below the smallest depth any view sees and `far`
//! slightly beyond the largest (the backdrop's).
//!
//! # Determinism
//! [`generate`] is a pure function of its seed and options: the same inputs give
//! bit-identical scenes on the same build (a private SplitMix64, no global state; views
//! are rendered in parallel but independently). Scene `i` of a set uses
//! `generate(scene_seed(base, i), ...)`.
//!
//! # On disk
//! [`write_scene`] writes the NeRF / instant-ngp layout read by
//! [`crate::scene::nerf`]: `transforms.json`, `images/view_NNN.png`, and
//! `depth/view_NNN.npy` (float32 `[H, W]`).

mod layout;
mod noise;
mod raytrace;
mod rig;
mod rng;
mod shutter;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_rolling;
#[cfg(test)]
mod tests_sweep;
mod texture;
mod write;

pub use rng::Rng;
pub use write::{
    contact_sheet, load_textures, scene_dir, write_scene, write_scenes, write_scenes_progress,
};

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::imageio::{RgbImage, MAX_IMAGE_SIDE};
use rayon::prelude::*;
use rng::mix64;

/// Fewest views a scene may have (a target and one source).
pub const MIN_VIEWS: usize = 2;
/// Largest sub-pixel ray grid side.
pub const MAX_SUPERSAMPLE: u32 = 8;
/// Largest per-view exposure change (relative).
pub const EXPOSURE_JITTER: f64 = 0.05;
/// `near` is the smallest depth seen times this.
pub const NEAR_MARGIN: f64 = 0.95;
/// `far` is the largest depth seen (the backdrop's) times this.
pub const FAR_MARGIN: f64 = 1.05;
/// Largest [`SynthOptions::rolling_shutter`] (a readout as long as the frame interval).
pub const MAX_ROLLING_SHUTTER: f64 = 1.0;

/// How the cameras of a scene are arranged.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Rig {
    /// LLFF-like: a grid of cameras on a plane, looking roughly forward.
    Forward,
    /// Street-View-like: a few positions along a path, several yaw directions at each.
    Rosette,
    /// An arc of cameras around a central object cluster, looking at it.
    Ring,
    /// A jittered random-walk path with small rotations.
    Handheld,
    /// One of the others, picked per scene from its seed.
    Mixed,
}

impl Rig {
    /// The rigs a scene can actually have (all but [`Rig::Mixed`]).
    pub const CONCRETE: [Rig; 4] = [Rig::Forward, Rig::Rosette, Rig::Ring, Rig::Handheld];

    pub fn name(self) -> &'static str {
        match self {
            Rig::Forward => "forward",
            Rig::Rosette => "rosette",
            Rig::Ring => "ring",
            Rig::Handheld => "handheld",
            Rig::Mixed => "mixed",
        }
    }
}

impl std::fmt::Display for Rig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Rig {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "forward" => Ok(Rig::Forward),
            "rosette" => Ok(Rig::Rosette),
            "ring" => Ok(Rig::Ring),
            "handheld" => Ok(Rig::Handheld),
            "mixed" => Ok(Rig::Mixed),
            other => Err(Error::Invalid(format!(
                "unknown rig '{other}' (expected forward, rosette, ring, handheld or mixed)"
            ))),
        }
    }
}

/// What to generate.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    /// Views per scene (at least [`MIN_VIEWS`]).
    pub views: usize,
    pub width: u32,
    pub height: u32,
    pub rig: Rig,
    /// Sub-pixel rays per pixel along each axis (`supersample^2` rays per pixel).
    pub supersample: u32,
    /// Photos whose random crops texture the surfaces; empty for procedural textures.
    pub textures: Vec<RgbImage>,
    /// Rolling shutter: the share of the camera's motion between neighbouring views that
    /// happens during one view's readout (0 = global shutter; see `shutter.rs`). The
    /// scene content and the readout start poses are those of the global-shutter scene
    /// of the same seed.
    pub rolling_shutter: f64,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            views: 10,
            width: 160,
            height: 120,
            rig: Rig::Mixed,
            supersample: 3,
            textures: Vec::new(),
            rolling_shutter: 0.0,
        }
    }
}

impl SynthOptions {
    /// Checks the options, with a message naming the bad one.
    pub fn validate(&self) -> Result<()> {
        if self.views < MIN_VIEWS {
            return Err(Error::Invalid(format!(
                "synth: need at least {MIN_VIEWS} views per scene, got {}",
                self.views
            )));
        }
        if self.width == 0
            || self.height == 0
            || self.width > MAX_IMAGE_SIDE
            || self.height > MAX_IMAGE_SIDE
        {
            return Err(Error::Invalid(format!(
                "synth: image size must be between 1x1 and {MAX_IMAGE_SIDE}x{MAX_IMAGE_SIDE}, got {}x{}",
                self.width, self.height
            )));
        }
        if self.supersample == 0 || self.supersample > MAX_SUPERSAMPLE {
            return Err(Error::Invalid(format!(
                "synth: supersample must be between 1 and {MAX_SUPERSAMPLE}, got {}",
                self.supersample
            )));
        }
        if !(0.0..=MAX_ROLLING_SHUTTER).contains(&self.rolling_shutter) {
            return Err(Error::Invalid(format!(
                "synth: the rolling-shutter share must be between 0 and {MAX_ROLLING_SHUTTER}, got {}",
                self.rolling_shutter
            )));
        }
        if let Some(i) = self
            .textures
            .iter()
            .position(|t| t.width == 0 || t.height == 0)
        {
            return Err(Error::Invalid(format!("synth: texture {i} is empty")));
        }
        Ok(())
    }
}

/// A generated scene: posed views, their images and exact depth maps.
#[derive(Clone, Debug, PartialEq)]
pub struct SynthScene {
    pub cameras: Vec<Camera>,
    pub images: Vec<RgbImage>,
    /// Per view, `[H * W]` row-major camera-space z of the ray through each pixel centre.
    pub depths: Vec<Vec<f32>>,
    pub near: f64,
    pub far: f64,
    /// The concrete rig (never [`Rig::Mixed`]).
    pub rig: Rig,
    /// The seed the scene was generated from.
    pub seed: u64,
}

/// The seed of scene `index` of a set with base seed `base` (a SplitMix64-style hash).
pub fn scene_seed(base: u64, index: usize) -> u64 {
    mix64(
        base ^ mix64(
            (index as u64)
                .wrapping_add(1)
                .wrapping_mul(0xD1B5_4A32_D192_ED03),
        ),
    )
}

/// Generates one scene; the same seed and options give a bit-identical scene.
pub fn generate(seed: u64, opts: &SynthOptions) -> Result<SynthScene> {
    generate_impl(seed, opts, false)
}

/// As [`generate`], but every view has the same ideal intrinsics: the first view's focal
/// length (`fx` for both axes) and the principal point at the image centre, as one real
/// camera (structure-from-motion tools estimate one such camera for a photo set).
pub fn generate_one_camera(seed: u64, opts: &SynthOptions) -> Result<SynthScene> {
    generate_impl(seed, opts, true)
}

fn generate_impl(seed: u64, opts: &SynthOptions, one_camera: bool) -> Result<SynthScene> {
    opts.validate()?;
    let mut rng = Rng::new(seed);
    let rig = match opts.rig {
        Rig::Mixed => Rig::CONCRETE[rng.below(Rig::CONCRETE.len())],
        r => r,
    };
    let (mut rig_rng, mut content_rng, mut exposure_rng) = (rng.fork(), rng.fork(), rng.fork());
    let mut layout = rig::build(rig, &mut rig_rng, opts.views, opts.width, opts.height)?;
    if let (true, Some(first)) = (one_camera, layout.cameras.first().copied()) {
        let k = first.intrinsics;
        let (w, h) = (k.width as f64, k.height as f64);
        let shared =
            crate::camera::Intrinsics::pinhole(k.fx, k.fx, 0.5 * w, 0.5 * h, k.width, k.height);
        for c in &mut layout.cameras {
            c.intrinsics = shared;
        }
    }
    let surfaces = layout::build(&mut content_rng, &layout, &opts.textures);
    shutter::apply(&mut layout.cameras, opts.rolling_shutter, rig::check_rays)?;
    let gains: Vec<f32> = (0..opts.views)
        .map(|_| (1.0 + exposure_rng.sym(EXPOSURE_JITTER)) as f32)
        .collect();
    let rendered: Vec<(RgbImage, Vec<f32>)> = layout
        .cameras
        .par_iter()
        .zip(gains.par_iter())
        .map(|(cam, &gain)| {
            raytrace::render(cam, &surfaces, opts.supersample, gain, &opts.textures)
        })
        .collect::<Result<_>>()?;
    let (images, depths): (Vec<_>, Vec<_>) = rendered.into_iter().unzip();
    let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
    for &z in depths.iter().flatten() {
        lo = lo.min(z as f64);
        hi = hi.max(z as f64);
    }
    let (near, far) = (lo * NEAR_MARGIN, hi * FAR_MARGIN);
    crate::scene::check_bounds(near, far)
        .map_err(|m| Error::Invalid(format!("synth: seed {seed}: {m}")))?;
    Ok(SynthScene {
        cameras: layout.cameras,
        images,
        depths,
        near,
        far,
        rig,
        seed,
    })
}
