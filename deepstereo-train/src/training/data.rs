//! Training data: scenes held in memory and the online sampler that feeds the trainer.
//!
//! A sample is the paper's: pick a scene, a target view, its `V` nearest source views
//! (never the target itself: leave-one-out is strict), an output tile location; build the
//! multi-resolution plane-sweep input of that tile (only the pixels it needs) and the
//! target patch. All geometry (tile size, levels, planes, views) comes from the model
//! [`Config`]. Sample `k` of batch `b` depends only on `(seed, b, k)`, so batches are
//! identical whatever the number of threads and after a resume.

use crate::training::scene_weights::SceneWeights;
use anyhow::{bail, Context};
use deepstereo_core::camera::Camera;
use deepstereo_core::config::Config;
use deepstereo_core::inputs::features::TileWarps;
use deepstereo_core::inputs::PyramidSource;
use deepstereo_core::scene::{nearest_to_point, LoadOptions, Scene, View};
use deepstereo_core::synth::{generate, scene_seed, SynthOptions, SynthScene};
use rayon::prelude::*;
use std::path::Path;
use std::sync::mpsc::{sync_channel, Receiver};

pub mod pairs;
mod sample;
pub use pairs::MpiPairs;
use pairs::{sample_pair, PairSample};
pub use sample::TileRef;
use sample::{aligned_offset, patch, pick_scene, sample, Sample};
#[cfg(test)]
use sample::{augment_planes, luminance_std};

/// Salt mixed into the seed of validation scenes so they never repeat training scenes.
pub const VALIDATION_SALT: u64 = 0x005e_ed0f_7a11_da7e;

/// One scene ready for sampling: cameras and image pyramids of every view.
pub struct SceneData {
    pub name: String,
    /// Procedural (made by `synth`) rather than read from a directory.
    pub synthetic: bool,
    pub cameras: Vec<Camera>,
    pub pyramids: Vec<PyramidSource>,
    pub near: f64,
    pub far: f64,
    /// The views a sample may take as its target (`None`: every view). The others are
    /// still sources: `tune` sets views aside for validation this way.
    pub targets: Option<Vec<usize>>,
}

impl SceneData {
    /// From a procedural scene held in memory.
    pub fn from_synth(name: String, s: &SynthScene, levels: usize) -> Self {
        let pyramids = s
            .cameras
            .iter()
            .zip(&s.images)
            .map(|(c, img)| PyramidSource::new(c, img, levels))
            .collect();
        Self {
            name,
            synthetic: true,
            cameras: s.cameras.clone(),
            pyramids,
            near: s.near,
            far: s.far,
            targets: None,
        }
    }

    /// From a scene directory in any format the readers accept.
    pub fn load(dir: &Path, levels: usize) -> anyhow::Result<Self> {
        let scene = Scene::load(dir, &LoadOptions::default())?;
        let mut data = Self::from_scene(&scene, levels)?;
        data.name = dir.display().to_string();
        Ok(data)
    }

    /// From a scene already read (every view's image is loaded now).
    pub fn from_scene(scene: &Scene, levels: usize) -> anyhow::Result<Self> {
        let pyramids = (0..scene.views.len())
            .map(|i| {
                Ok(PyramidSource::new(
                    &scene.views[i].camera,
                    &scene.load_image(i)?,
                    levels,
                ))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(Self {
            name: scene.root.display().to_string(),
            synthetic: false,
            cameras: scene.views.iter().map(|v| v.camera).collect(),
            pyramids,
            near: scene.near,
            far: scene.far,
            targets: None,
        })
    }

    /// The scene's cameras at pyramid level 1 (half the resolution), without images:
    /// what the pair sampler draws from at `--mpi-scale 2` (it builds the pyramids of
    /// the views it uses with [`PyramidSource::from_level`]).
    pub fn halved_cameras(&self) -> Self {
        Self {
            name: self.name.clone(),
            synthetic: self.synthetic,
            cameras: (self.pyramids.iter())
                .zip(&self.cameras)
                .map(|(p, c)| p.cameras.get(1).copied().unwrap_or(*c))
                .collect(),
            pyramids: Vec::new(),
            near: self.near,
            far: self.far,
            targets: self.targets.clone(),
        }
    }

    /// A target view from the random `r`: one of [`Self::targets`], or any view.
    pub fn draw_target(&self, r: u64) -> usize {
        match &self.targets {
            Some(t) if !t.is_empty() => t[(r % t.len() as u64) as usize],
            _ => (r % self.cameras.len() as u64) as usize,
        }
    }

    /// The `k` views nearest to view `target` (excluding it), nearest first.
    pub fn sources(&self, target: usize, k: usize) -> Vec<usize> {
        let views: Vec<View> = self
            .cameras
            .iter()
            .map(|c| View {
                name: String::new(),
                image_path: Default::default(),
                camera: *c,
                bounds: None,
            })
            .collect();
        nearest_to_point(&views, self.cameras[target].pose.centre(), k, Some(target))
    }

    /// `k` sources of view `target` at stride `s` (at least 1): its `s`-th, `2s`-th, ...
    /// nearest views, nearest first (fewer where the scene has fewer).
    pub fn strided_sources(&self, target: usize, k: usize, s: usize) -> Vec<usize> {
        let s = s.max(1);
        (self.sources(target, k * s).into_iter())
            .skip(s - 1)
            .step_by(s)
            .take(k)
            .collect()
    }
}

/// Generates `count` procedural scenes in parallel (scene `i` from `scene_seed(seed, i)`).
pub fn synth_scenes(
    count: usize,
    seed: u64,
    opts: &SynthOptions,
    levels: usize,
) -> anyhow::Result<Vec<SceneData>> {
    (0..count)
        .into_par_iter()
        .map(|i| {
            let s = generate(scene_seed(seed, i), opts)
                .with_context(|| format!("procedural scene {i}"))?;
            Ok(SceneData::from_synth(
                format!("synth-{seed}-{i}"),
                &s,
                levels,
            ))
        })
        .collect()
}

/// One minibatch: inputs per level (`[B, D, 4V, h_l, w_l]`, or `[B, D, V, C_v, h_l, w_l]`
/// for the any-number-of-views family) and targets `[B, 3, t, t]`, as flat f32 data with
/// their shapes.
pub struct Batch {
    pub index: u64,
    pub levels: Vec<Vec<f32>>,
    pub level_shapes: Vec<Vec<usize>>,
    /// Source views `V` of every sample in the batch.
    pub views: usize,
    pub target: Vec<f32>,
    pub target_shape: [usize; 4],
    /// With the loss through the MPI renderer ([`Sampling::mpi`]): the warp of each
    /// sample's tile to its neighbouring view and that view's photographs.
    pub mpi: Option<PairBatch>,
    /// The `features` family: per sample, the crops its feature CNN reads and their
    /// warps; `levels` then leave the features out (`C_v - F` channels), and the training
    /// graph appends them ([`crate::training::batch_tensors`]).
    pub warps: Option<Vec<TileWarps>>,
    /// Where each sample's tile is (empty for MPI pair batches), for a scene prior.
    pub tiles: Vec<TileRef>,
}

/// The MPI part of a batch ([`pairs`]).
pub struct PairBatch {
    /// Per sample, its tile's warp to the target crop.
    pub plans: Vec<deepstereo_core::mpi::warp::WarpPlan>,
    /// `[B, 3, N_t]`, the target crops' photographs.
    pub target: Vec<f32>,
    /// `N_t`, pixels per target crop.
    pub pixels: usize,
}

/// How samples are drawn beyond what the model's config fixes.
#[derive(Clone, Debug, PartialEq)]
pub struct Sampling {
    /// Source views per batch, drawn uniformly from this range for every batch (the
    /// any-number-of-views family); the paper's family takes exactly `Config::views`.
    pub views: (usize, usize),
    /// Share (percent) of samples drawn from procedural scenes when real ones are
    /// there too (`None`: every scene equally likely).
    pub synthetic_percent: Option<u32>,
    /// Photometric augmentation (an exposure and white-balance gain per sample, on the
    /// sources and the target alike) and horizontal flips.
    pub augment: bool,
    /// Sparser sources: per sample a stride `s` drawn uniformly from this range, and the
    /// sources are the `s`-th, `2s`-th, ... nearest views (`s = 1`: the nearest), as if
    /// the scene had been captured with one view in `s` (wider baselines).
    pub view_stride: (usize, usize),
    /// Skip flat tiles: a tile whose target luminance has a standard deviation under this
    /// (colours in [0, 1]) is redrawn, up to [`MAX_FLAT_REDRAWS`] times.
    pub skip_flat: Option<f32>,
    /// Relative weights of named real scenes ([`SceneWeights`]; empty: all equally likely).
    pub scene_weights: SceneWeights,
    /// Samples for the loss through the MPI renderer instead of plain tiles ([`pairs`]).
    pub mpi: Option<MpiPairs>,
}

/// Most redraws of a flat tile ([`Sampling::skip_flat`]).
pub const MAX_FLAT_REDRAWS: usize = 8;

/// Largest source stride of [`Sampling::view_stride`].
pub const MAX_VIEW_STRIDE: usize = 16;

/// Largest exposure change of the augmentation, as a log factor (`exp(+-0.25)`).
pub const AUGMENT_EXPOSURE: f64 = 0.25;
/// Largest per-channel white-balance change of the augmentation (`1 +- 0.1`).
pub const AUGMENT_WHITE_BALANCE: f64 = 0.1;

impl Sampling {
    /// Exactly the config's views, no augmentation, every scene equally likely.
    pub fn fixed(cfg: &Config) -> Self {
        Self {
            views: (cfg.views, cfg.views),
            synthetic_percent: None,
            augment: false,
            view_stride: (1, 1),
            skip_flat: None,
            scene_weights: SceneWeights::default(),
            mpi: None,
        }
    }

    /// Checks the range against the model.
    pub fn check(&self, cfg: &Config) -> anyhow::Result<()> {
        let (lo, hi) = self.views;
        if lo == 0 || lo > hi {
            bail!("the views range {lo}-{hi} must be 1 or more and increasing");
        }
        let (s_lo, s_hi) = self.view_stride;
        if s_lo == 0 || s_lo > s_hi || s_hi > MAX_VIEW_STRIDE {
            bail!("the view stride range {s_lo}-{s_hi} must be increasing, from 1 to {MAX_VIEW_STRIDE}");
        }
        if self.skip_flat.is_some_and(|s| !(0.0..=0.5).contains(&s)) {
            bail!(
                "the flat-tile threshold is a standard deviation of colours in [0, 1] (0 to 0.5)"
            );
        }
        self.scene_weights.check()?;
        if let Some(p) = &self.mpi {
            p.check(cfg)?;
            if cfg.pool.as_ref().is_some_and(|p| p.features.is_some()) {
                bail!("the MPI loss does not take the features family's models");
            }
            if self.augment || self.skip_flat.is_some() || self.view_stride != (1, 1) {
                bail!(
                    "the MPI loss takes neither augmentation, flat-tile skipping nor a view stride"
                );
            }
        }
        if self.synthetic_percent.is_some_and(|p| p > 100) {
            bail!("the share of procedural samples is a percentage (0 to 100)");
        }
        if !cfg.accepts_views(lo) || !cfg.accepts_views(hi) {
            bail!(
                "the views range {lo}-{hi} does not suit the '{}' model, which takes {}",
                cfg.name,
                if cfg.pool.is_some() {
                    format!("1 to {}", deepstereo_core::config::MAX_VIEWS)
                } else {
                    format!("exactly {}", cfg.views)
                }
            );
        }
        Ok(())
    }

    /// The number of views of batch `b`.
    pub fn views_of(&self, seed: u64, b: u64) -> usize {
        let (lo, hi) = self.views;
        let r = mix(seed ^ mix(b ^ VIEWS_SALT));
        lo + (r % (hi - lo + 1) as u64) as usize
    }
}

/// Salt of the per-batch view count's random stream.
const VIEWS_SALT: u64 = 0x0076_1e35_ca17_0000;

/// A deterministic 64-bit mix (splitmix64 finalizer).
pub fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The batch's input shapes per level for `th x tw` tiles.
fn level_shapes(
    cfg: &Config,
    batch: usize,
    views: usize,
    (th, tw): (usize, usize),
) -> Vec<Vec<usize>> {
    (0..cfg.levels)
        .map(|l| {
            let (h, w) = (cfg.input_size(l, th), cfg.input_size(l, tw));
            let mut shape = cfg.input_shape(batch, cfg.planes, views, h, w);
            // The features family's maps are appended in the graph.
            if let Some(p) = &cfg.pool {
                shape[3] -= p.feature_channels();
            }
            shape
        })
        .collect()
}

/// Per level, the samples' inputs (`samples[k][l]`) one after the other.
fn stack_levels(samples: &[&[Vec<f32>]], levels: usize) -> Vec<Vec<f32>> {
    (0..levels)
        .map(|l| samples.iter().flat_map(|s| s[l].iter().copied()).collect())
        .collect()
}

/// Builds batch `b` of `batch` samples, samples in parallel.
pub fn make_batch(
    cfg: &Config,
    sampling: &Sampling,
    scenes: &[SceneData],
    seed: u64,
    b: u64,
    batch: usize,
) -> anyhow::Result<Batch> {
    if scenes.is_empty() {
        bail!("no scenes to sample from");
    }
    sampling.check(cfg)?;
    let views = sampling.views_of(seed, b);
    if let Some(pairs) = &sampling.mpi {
        return pair_batch(cfg, sampling, pairs, scenes, (seed, b, batch), views);
    }
    let samples: Vec<Sample> = (0..batch)
        .into_par_iter()
        .map(|k| sample(cfg, sampling, scenes, (seed, b, k), views))
        .collect::<anyhow::Result<_>>()?;
    let t = cfg.tile;
    let parts: Vec<&[Vec<f32>]> = samples.iter().map(|s| s.levels.as_slice()).collect();
    let levels = stack_levels(&parts, cfg.levels);
    let target = samples
        .iter()
        .flat_map(|s| s.target.iter().copied())
        .collect();
    let tiles = samples.iter().map(|s| s.tile.clone()).collect();
    let warps = samples
        .into_iter()
        .map(|s| s.warps)
        .collect::<Option<Vec<_>>>();
    Ok(Batch {
        index: b,
        levels,
        level_shapes: level_shapes(cfg, batch, views, (t, t)),
        views,
        target,
        target_shape: [batch, 3, t, t],
        mpi: None,
        warps,
        tiles,
    })
}

/// [`make_batch`] of pair samples.
fn pair_batch(
    cfg: &Config,
    sampling: &Sampling,
    pairs: &MpiPairs,
    scenes: &[SceneData],
    (seed, b, batch): (u64, u64, usize),
    views: usize,
) -> anyhow::Result<Batch> {
    let samples: Vec<PairSample> = (0..batch)
        .into_par_iter()
        .map(|k| sample_pair(cfg, sampling, pairs, scenes, (seed, b, k), views))
        .collect::<anyhow::Result<_>>()?;
    let (tw, th) = pairs.tile;
    let parts: Vec<&[Vec<f32>]> = samples.iter().map(|s| s.levels.as_slice()).collect();
    let levels = stack_levels(&parts, cfg.levels);
    let target = samples
        .iter()
        .flat_map(|s| s.reference.iter().copied())
        .collect();
    let mpi_target = samples
        .iter()
        .flat_map(|s| s.target.iter().copied())
        .collect();
    Ok(Batch {
        index: b,
        levels,
        level_shapes: level_shapes(cfg, batch, views, (th, tw)),
        views,
        target,
        target_shape: [batch, 3, th, tw],
        mpi: Some(PairBatch {
            plans: samples.into_iter().map(|s| s.plan).collect(),
            target: mpi_target,
            pixels: th * tw,
        }),
        warps: None,
        tiles: Vec::new(),
    })
}

/// Background producer of batches `start, start + 1, ...`, a few ahead of the trainer.
pub fn spawn_loader(
    cfg: Config,
    sampling: Sampling,
    scenes: std::sync::Arc<Vec<SceneData>>,
    seed: u64,
    start: u64,
    batch: usize,
    ahead: usize,
) -> Receiver<anyhow::Result<Batch>> {
    let (tx, rx) = sync_channel(ahead.max(1));
    std::thread::spawn(move || {
        let mut b = start;
        loop {
            let r = make_batch(&cfg, &sampling, &scenes, seed, b, batch);
            let failed = r.is_err();
            if tx.send(r).is_err() || failed {
                return;
            }
            b += 1;
        }
    });
    rx
}

#[cfg(test)]
mod tests;
