//! Samples for the loss through the MPI renderer (`train --mpi-loss`): the network runs
//! at a reference view `r` on a tile, as for any sample, and its layers, made an MPI,
//! are also rendered at a neighbouring view `t` of the same scene and compared with `t`'s
//! photograph over the pixels that see the tile on every plane
//! ([`deepstereo_core::mpi::warp`]). Neither `r` nor `t` is a source, as when an MPI
//! baked at a kept view is judged at a held-out one (`mpi --exclude-own-photo`).

use super::{aligned_offset, mix, patch, pick_scene, Sampling, SceneData};
use anyhow::bail;
use deepstereo_core::config::Config;
use deepstereo_core::geometry::inverse_depths;
use deepstereo_core::inputs::{tile_inputs, PyramidSource};
use deepstereo_core::mpi::reference_camera;
use deepstereo_core::mpi::warp::WarpPlan;
use glam::DVec2;
use serde::{Deserialize, Serialize};

/// How pair samples are drawn (`train --mpi-loss`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MpiPairs {
    /// Weight of the loss through the MPI beside the reference tile's own loss.
    pub weight: f32,
    /// Width and height of the reference tile and of the target crop (pixels, multiples
    /// of the model's alignment): a target pixel counts only when its ray meets every
    /// plane inside the tile, so the tile must exceed the disparity range between
    /// neighbours; a wide tile covers the sideways motion of most captures.
    pub tile: (usize, usize),
    /// The target is one of the reference's `neighbours` nearest views.
    pub neighbours: usize,
    /// Pair samples are drawn from the images downscaled by this factor (1 or 2;
    /// pyramid level 1 for 2): the same tile then spans twice the disparity, so pairs
    /// as far apart as an evaluation's held-out views and their nearest kept ones fit.
    #[serde(default = "one")]
    pub scale: u32,
}

fn one() -> u32 {
    1
}

impl MpiPairs {
    pub fn check(&self, cfg: &Config) -> anyhow::Result<()> {
        let a = cfg.tile_align();
        if !(self.weight.is_finite() && self.weight > 0.0) {
            bail!("the MPI loss weight must be a positive number");
        }
        let (w, h) = self.tile;
        if [w, h].iter().any(|&s| s < 2 * a || !s.is_multiple_of(a)) {
            bail!(
                "the MPI tile's sides must be multiples of {a} of at least {}",
                2 * a
            );
        }
        if self.neighbours == 0 {
            bail!("the MPI target is one of the reference's nearest views: 1 or more");
        }
        if !matches!(self.scale, 1 | 2) || (self.scale == 2 && cfg.levels < 2) {
            bail!(
                "the MPI pairs' scale is 1 or 2 (2 needs a model of 2 or more levels), not {}",
                self.scale
            );
        }
        Ok(())
    }
}

/// One pair sample: the reference tile's inputs per level and photograph `[3, H, W]`,
/// the warp of the tile to the target crop, and the target's photograph `[3, H, W]`.
pub struct PairSample {
    pub levels: Vec<Vec<f32>>,
    pub reference: Vec<f32>,
    pub plan: WarpPlan,
    pub target: Vec<f32>,
}

/// Most draws of a pair whose warp counts too few pixels.
const MAX_PAIR_DRAWS: usize = 8;
/// A pair is kept when at least one target pixel in this many counts.
const MIN_COUNTED: usize = 10;

/// A reference view `r` and its tile at `(x0, y0)`, a neighbour `t` and its crop at
/// `(tx0, ty0)`, and the warp between them.
struct Pair {
    r: usize,
    t: usize,
    x0: i64,
    y0: i64,
    tx0: i64,
    ty0: i64,
    plan: WarpPlan,
}

/// Draws a pair of scene `s` with planes at `inv`.
fn draw(
    cfg: &Config,
    pairs: &MpiPairs,
    s: &SceneData,
    inv: &[f64],
    next: &mut impl FnMut() -> u64,
) -> anyhow::Result<Pair> {
    let r = s.draw_target(next());
    let near = s.sources(r, pairs.neighbours);
    let t = near[(next() % near.len() as u64) as usize];
    let (tw, th) = pairs.tile;
    let (cam_r, cam_t) = (&s.cameras[r], &s.cameras[t]);
    for cam in [cam_r, cam_t] {
        let k = &cam.intrinsics;
        if (k.width as usize) < tw || (k.height as usize) < th {
            bail!(
                "scene {}: images {}x{} are smaller than the {tw}x{th} MPI tile",
                s.name,
                k.width,
                k.height
            );
        }
    }
    let a = cfg.tile_align() as u64;
    let (w, h) = (
        cam_r.intrinsics.width as u64,
        cam_r.intrinsics.height as u64,
    );
    let x0 = aligned_offset(next(), w, tw, a) as i64;
    let y0 = aligned_offset(next(), h, th, a) as i64;
    // The target crop is centred where the tile's centre at the middle plane appears.
    let mid = inv[inv.len() / 2].max(1e-9);
    let centre = DVec2::new((x0 as usize + tw / 2) as f64, (y0 as usize + th / 2) as f64);
    let (uv, _) = cam_t.project(cam_r.unproject(centre, 1.0 / mid));
    let place = |c: f64, size: u32, side: usize| -> i64 {
        let hi = (size as usize - side) as f64;
        let v = if c.is_finite() {
            c - side as f64 / 2.0
        } else {
            hi / 2.0
        };
        v.round().clamp(0.0, hi) as i64
    };
    let (tx0, ty0) = (
        place(uv.x, cam_t.intrinsics.width, tw),
        place(uv.y, cam_t.intrinsics.height, th),
    );
    let plan = WarpPlan::new(
        &reference_camera(cam_r),
        inv,
        (x0, y0, tw, th),
        cam_t,
        (tx0, ty0, tw, th),
    );
    Ok(Pair {
        r,
        t,
        x0,
        y0,
        tx0,
        ty0,
        plan,
    })
}

/// Salt of the pair samples' random stream.
const PAIR_SALT: u64 = 0x0070_a125_0000_0001;

/// Pair sample `k` of batch `b` with `views` sources.
pub fn sample_pair(
    cfg: &Config,
    sampling: &Sampling,
    pairs: &MpiPairs,
    scenes: &[SceneData],
    (seed, b, k): (u64, u64, usize),
    views: usize,
) -> anyhow::Result<PairSample> {
    let mut state = mix(seed ^ PAIR_SALT ^ mix(b.wrapping_mul(0x1000_0000_01B3) ^ mix(k as u64)));
    let mut next = || {
        state = mix(state);
        state
    };
    let full = pick_scene(scenes, sampling, next(), next());
    let halved = (pairs.scale == 2).then(|| full.halved_cameras());
    let s = halved.as_ref().unwrap_or(full);
    let n = s.cameras.len();
    if n < 3 {
        bail!(
            "scene {} has {n} views; an MPI pair needs a reference, a target and a source",
            s.name
        );
    }
    let (tw, th) = pairs.tile;
    let inv = inverse_depths(s.near, s.far, cfg.planes);
    // Pairs whose warp counts too few pixels (the views too far apart for the tile) are
    // redrawn, a few times at most (the last draw is kept).
    let mut pair = draw(cfg, pairs, s, &inv, &mut next)?;
    for _ in 1..MAX_PAIR_DRAWS {
        if pair.plan.count() * MIN_COUNTED >= tw * th {
            break;
        }
        pair = draw(cfg, pairs, s, &inv, &mut next)?;
    }
    let Pair {
        r,
        t,
        x0,
        y0,
        tx0,
        ty0,
        plan,
    } = pair;
    let src: Vec<usize> = (s.sources(r, views + 1).into_iter())
        .filter(|&i| i != t)
        .take(views)
        .collect();
    if src.len() < views && cfg.pool.is_none() {
        bail!(
            "scene {} has {n} views; the model needs {views} sources besides an MPI pair",
            s.name
        );
    }
    let cam_r = &s.cameras[r];
    // At scale 2, the pyramids of the views used, from level 1 of the scene's own.
    let level = if halved.is_some() { 1 } else { 0 };
    let scaled: Vec<PyramidSource> = match level {
        0 => Vec::new(),
        _ => (src.iter())
            .map(|&i| full.pyramids[i].from_level(level, cfg.levels))
            .collect(),
    };
    let empty = PyramidSource::empty(cam_r, cfg.levels);
    let mut srcs: Vec<&PyramidSource> = match level {
        0 => src.iter().map(|&i| &s.pyramids[i]).collect(),
        _ => scaled.iter().collect(),
    };
    srcs.resize(views, &empty);
    let inputs = tile_inputs(cfg, cam_r, &srcs, &inv, (x0, y0), (th, tw))?;
    let image = |i: usize| &full.pyramids[i].images[level];
    Ok(PairSample {
        levels: inputs.levels,
        reference: patch(image(r), (x0 as u32, y0 as u32), (tw, th)),
        plan,
        target: patch(image(t), (tx0 as u32, ty0 as u32), (tw, th)),
    })
}
