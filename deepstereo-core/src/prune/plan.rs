//! Per-tile decisions: which planes the network runs on, or whether it runs at all.

use super::PruneOptions;
use crate::baseline::MIN_ALPHA;
use crate::camera::Camera;
use crate::config::Config;
use crate::geometry::{apply_h, plane_homography};
use crate::inputs::{level_camera, PyramidSource};
use crate::sweep::{sample_bilinear, IN_FRONT_EPS};
use glam::{DMat3, DVec2};

/// What to do with one output tile.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TilePlan {
    /// No source covers the tile's input footprint at any plane: the network's response
    /// to empty input.
    Uncovered,
    /// Every sampled source colour equals `colour` (within [`PruneOptions::flat`]);
    /// `coverage`: the fraction of the sources that see the samples.
    Flat { colour: [f32; 3], coverage: f32 },
    /// Run the network on planes `first..=last`.
    Band { first: usize, last: usize },
}

/// Plans the tiles of one render (one target, its sources and planes).
pub struct Pruner<'a> {
    opts: PruneOptions,
    margin: usize,
    sources: &'a [&'a PyramidSource],
    planes: usize,
    /// Planes the coarse pass looks at (`first..=last`): the depth range.
    range: (usize, usize),
    /// Coarse pyramid level and the target camera there.
    level: usize,
    coarse_target: Camera,
    target: Camera,
    /// `homs[k * D + z]`: target -> source `k` normalized coordinates, plane `z`.
    homs: Vec<DMat3>,
    /// Level-0 pixels the network's input footprint reaches beyond a tile on each side.
    footprint: usize,
    /// Level-0 pixels a source image's samples reach beyond its border.
    reach: f64,
    /// Whether the exact coverage test applies (no lens distortion anywhere).
    pinhole: bool,
}

impl<'a> Pruner<'a> {
    /// `range`: the planes the scene can need at all (from [`super::plane_range_from_points`]);
    /// `None`: all of them.
    pub fn new(
        cfg: &Config,
        target: &Camera,
        sources: &'a [&'a PyramidSource],
        inv_depths: &[f64],
        range: Option<(usize, usize)>,
        opts: &PruneOptions,
    ) -> Self {
        let d = inv_depths.len();
        let level = opts.level.min(cfg.levels - 1).min(sources.iter().map(|s| s.images.len()).min().unwrap_or(1).saturating_sub(1));
        let (w, h) = (target.intrinsics.width, target.intrinsics.height);
        let homs = sources
            .iter()
            .flat_map(|s| {
                let rel = target.pose.relative_to(&s.cameras[0].pose);
                inv_depths.iter().map(move |&r| plane_homography(&rel, r))
            })
            .collect();
        let footprint = (0..cfg.levels).map(|l| cfg.pad(l) << l).max().unwrap_or(0);
        let pinhole = target.intrinsics.distortion.is_none()
            && sources.iter().all(|s| s.cameras.iter().all(|c| c.intrinsics.distortion.is_none()));
        let range = range.map_or((0, d.saturating_sub(1)), |(a, b)| (a.min(d - 1), b.min(d - 1)));
        Self {
            opts: opts.clone(),
            margin: opts.margin_for(cfg),
            sources,
            planes: d,
            range,
            level,
            coarse_target: level_camera(target, level, w >> level, h >> level),
            target: *target,
            homs,
            footprint,
            reach: (1u64 << (cfg.levels - 1)) as f64 + 1.0,
            pinhole,
        }
    }

    /// The planes the coarse pass considers (`first..=last`).
    pub fn range(&self) -> (usize, usize) {
        self.range
    }

    /// Whether any source may see any point of the input footprint of the tile at
    /// `(x0, y0)` of side `tile`, at any plane (conservative: `true` when unsure).
    pub fn covered(&self, x0: usize, y0: usize, tile: usize) -> bool {
        if !self.pinhole {
            return true;
        }
        let f = self.footprint as f64;
        let (a, b) = ((x0 as f64 - f, y0 as f64 - f), ((x0 + tile) as f64 + f, (y0 + tile) as f64 + f));
        let corners = [(a.0, a.1), (b.0, a.1), (a.0, b.1), (b.0, b.1)]
            .map(|(u, v)| self.target.intrinsics.unproject_pixel(DVec2::new(u, v)));
        for (k, s) in self.sources.iter().enumerate() {
            let intr = &s.cameras[0].intrinsics;
            let (w, h) = (intr.width as f64 + self.reach, intr.height as f64 + self.reach);
            for z in 0..self.planes {
                let hm = &self.homs[k * self.planes + z];
                let q = corners.map(|n| apply_h(hm, n.x, n.y));
                let front = q.iter().filter(|q| q.z > 0.0).count();
                if front == 0 {
                    continue; // the whole (convex) patch is behind the source
                }
                if front < 4 {
                    return true;
                }
                let p = q.map(|q| intr.project_normalized(DVec2::new(q.x / q.z, q.y / q.z)));
                let (lo, hi) = p.iter().fold((DVec2::MAX, DVec2::MIN), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
                if hi.x > -self.reach && hi.y > -self.reach && lo.x < w && lo.y < h {
                    return true;
                }
            }
        }
        false
    }

    /// Decides what to do with the tile at `(x0, y0)` of side `tile` (level-0 pixels).
    pub fn plan(&self, x0: usize, y0: usize, tile: usize) -> TilePlan {
        if !self.covered(x0, y0, tile) {
            return TilePlan::Uncovered;
        }
        let samples = self.coarse(x0, y0, tile);
        self.decide(&samples)
    }

    /// Normalized rays of the coarse samples of a tile.
    fn rays(&self, x0: usize, y0: usize, tile: usize) -> Vec<DVec2> {
        let intr = &self.coarse_target.intrinsics;
        let f = 1usize << self.level;
        let s = (self.opts.stride >> self.level).max(1);
        let (tw, th) = (self.target.intrinsics.width as usize, self.target.intrinsics.height as usize);
        // Every `s`-th level pixel of the tile's part of the image, and its first and last.
        let span = |a: usize, len: usize, n: usize| -> Vec<usize> {
            let (lo, hi) = (a / f, (a + len).min(n).div_ceil(f));
            let mut v: Vec<usize> = (lo..hi).skip(s / 2).step_by(s).collect();
            v.extend([lo, hi.saturating_sub(1)].into_iter().filter(|&i| i < hi));
            v.sort_unstable();
            v.dedup();
            v
        };
        let mut rays = Vec::new();
        let ys = span(y0, tile, th);
        for i in span(x0, tile, tw) {
            for &j in &ys {
                rays.push(intr.unproject_pixel(DVec2::new(i as f64 + 0.5, j as f64 + 0.5)));
            }
        }
        rays
    }

    /// The coarse cost volume of a tile.
    fn coarse(&self, x0: usize, y0: usize, tile: usize) -> Samples {
        let rays = self.rays(x0, y0, tile);
        let (z0, z1) = self.range;
        let nz = z1 + 1 - z0;
        let mut out = Samples {
            nz,
            cost: vec![f32::NAN; rays.len() * nz],
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
            sum: [0.0; 3],
            count: 0,
            all_seen: true,
        };
        let v = self.sources.len();
        let mut rgb = vec![[0f32; 3]; v];
        for (p, n) in rays.iter().enumerate() {
            for z in z0..=z1 {
                let mut cnt = 0usize;
                for (k, s) in self.sources.iter().enumerate() {
                    let q = apply_h(&self.homs[k * self.planes + z], n.x, n.y);
                    if q.z <= IN_FRONT_EPS * q.length() {
                        continue;
                    }
                    let cam = &s.cameras[self.level];
                    let uv = cam.intrinsics.project_normalized(DVec2::new(q.x / q.z, q.y / q.z));
                    let c = sample_bilinear(&s.images[self.level], uv.x, uv.y);
                    if c[3] > MIN_ALPHA {
                        rgb[cnt] = [c[0] / c[3], c[1] / c[3], c[2] / c[3]];
                        cnt += 1;
                    }
                }
                if cnt == 0 {
                    out.all_seen = false;
                }
                let mut mean = [0f32; 3];
                for c in &rgb[..cnt] {
                    for ch in 0..3 {
                        mean[ch] += c[ch] / cnt as f32;
                        out.lo[ch] = out.lo[ch].min(c[ch]);
                        out.hi[ch] = out.hi[ch].max(c[ch]);
                        out.sum[ch] += c[ch];
                    }
                }
                out.count += cnt;
                if cnt >= 2 {
                    let var: f32 = rgb[..cnt].iter().map(|c| (0..3).map(|ch| (c[ch] - mean[ch]).powi(2)).sum::<f32>()).sum();
                    out.cost[p * nz + z - z0] = var / (3 * cnt) as f32;
                }
            }
        }
        out
    }

    /// The plan from a tile's coarse samples.
    fn decide(&self, s: &Samples) -> TilePlan {
        let (z0, z1) = self.range;
        let flat = (0..3).all(|ch| s.hi[ch] - s.lo[ch] <= 2.0 * self.opts.flat);
        if s.count > 0 && s.all_seen && flat {
            let coverage = s.count as f32 / (s.cost.len() * self.sources.len()).max(1) as f32;
            return TilePlan::Flat { colour: s.sum.map(|x| x / s.count as f32), coverage };
        }
        let (mut los, mut his) = (Vec::new(), Vec::new());
        let mut total = vec![0f32; s.nz];
        for c in s.cost.chunks(s.nz) {
            let known = || c.iter().enumerate().filter(|(_, x)| !x.is_nan());
            let (lo, hi) = known().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), (_, &x)| (a.min(x), b.max(x)));
            if known().count() < 2 || hi - lo < self.opts.contrast {
                for (z, &x) in known() {
                    total[z] += x;
                }
                continue;
            }
            let cut = lo + self.opts.tolerance * (hi - lo);
            let good = || known().filter(|(_, &x)| x <= cut).map(|(z, _)| z);
            los.push(good().min().unwrap_or(0));
            his.push(good().max().unwrap_or(s.nz - 1));
        }
        let (first, last) = if los.is_empty() {
            // Nothing in the tile tells depths apart: the plane of least total cost.
            match total.iter().enumerate().filter(|(_, x)| **x > 0.0).min_by(|a, b| a.1.total_cmp(b.1)) {
                Some((z, _)) => (z, z),
                None => (0, s.nz - 1),
            }
        } else {
            los.sort_unstable();
            his.sort_unstable();
            let drop = ((1.0 - self.opts.mass as f64) * los.len() as f64).floor() as usize;
            let (a, b) = (los[drop.min(los.len() - 1)], his[his.len() - 1 - drop.min(his.len() - 1)]);
            (a.min(b), a.max(b))
        };
        let first = (z0 + first).saturating_sub(self.margin);
        let last = (z0 + last + self.margin).min(self.planes - 1);
        debug_assert!(first <= last && last <= z1.max(last));
        TilePlan::Band { first, last }
    }
}

/// The coarse pass's view of a tile.
struct Samples {
    /// Planes of the range.
    nz: usize,
    /// `[sample, plane]` colour variance across the sources that see the point (NaN
    /// where fewer than two do).
    cost: Vec<f32>,
    /// Per channel, the least and largest source colour seen, and the sum and count.
    lo: [f32; 3],
    hi: [f32; 3],
    sum: [f32; 3],
    count: usize,
    /// Whether every sample and plane had at least one source.
    all_seen: bool,
}
