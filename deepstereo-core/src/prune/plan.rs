//! Per-tile decisions: which planes the network runs on, or whether it runs at all.

use super::PruneOptions;
use crate::baseline::MIN_ALPHA;
use crate::camera::Camera;
use crate::config::Config;
use crate::geometry::{apply_h, plane_homography};
use crate::inputs::{level_camera, PyramidSource};
use crate::sweep::{sample_bilinear, IN_FRONT_EPS};
use glam::{DMat3, DVec2};
use rayon::prelude::*;

/// What to do with one block of output pixels.
#[derive(Clone, Debug, PartialEq)]
pub enum TilePlan {
    /// No source covers the block's input footprint at any plane: the network's
    /// response to empty input.
    Uncovered,
    /// Every sampled source colour equals `colour` (within [`PruneOptions::flat`]);
    /// `coverage`: the fraction of the sources that see the samples.
    Flat { colour: [f32; 3], coverage: f32 },
    /// Run the network on these planes (increasing indices; a union of contiguous bands).
    Planes(Vec<usize>),
}

/// A square block of a tile (level-0 pixels; it may reach beyond the image) and its plan.
#[derive(Clone, Debug, PartialEq)]
pub struct Block {
    pub x0: usize,
    pub y0: usize,
    pub size: usize,
    pub plan: TilePlan,
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
    /// The level-0 input border (`Config::pad(0)`) and the tile alignment.
    pad0: usize,
    align: usize,
    /// Level-0 pixels a source image's samples reach beyond its border.
    reach: f64,
    /// Whether the exact coverage test applies (no lens distortion anywhere).
    pinhole: bool,
    /// The pairs of sources whose photo-consistency says something about depth: those
    /// with a baseline (two views from one place agree at every depth).
    pairs: Vec<(usize, usize)>,
}

impl<'a> Pruner<'a> {
    /// `range`: the planes the scene can need at all, `first..=last` (from
    /// [`super::plane_range_from_points`] or [`super::plane_range_from_bounds`]); `None`:
    /// all of them.
    pub fn new(
        cfg: &Config,
        target: &Camera,
        sources: &'a [&'a PyramidSource],
        inv_depths: &[f64],
        range: Option<(usize, usize)>,
        opts: &PruneOptions,
    ) -> Self {
        let d = inv_depths.len();
        let level = opts.level.min(cfg.levels - 1).min(
            sources
                .iter()
                .map(|s| s.images.len())
                .min()
                .unwrap_or(1)
                .saturating_sub(1),
        );
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
            && sources
                .iter()
                .all(|s| s.cameras.iter().all(|c| c.intrinsics.distortion.is_none()));
        let last = d.saturating_sub(1);
        let range = range.map_or((0, last), |(a, b)| (a.min(b).min(last), b.max(a).min(last)));
        Self {
            opts: opts.clone(),
            margin: opts.margin,
            sources,
            planes: d,
            range,
            level,
            coarse_target: level_camera(target, level, w >> level, h >> level),
            target: *target,
            homs,
            footprint,
            pad0: cfg.pad(0),
            align: cfg.tile_align(),
            reach: (1u64 << (cfg.levels - 1)) as f64 + 1.0,
            pinhole,
            pairs: depth_pairs(sources),
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
        let (a, b) = (
            (x0 as f64 - f, y0 as f64 - f),
            ((x0 + tile) as f64 + f, (y0 + tile) as f64 + f),
        );
        let corners = [(a.0, a.1), (b.0, a.1), (a.0, b.1), (b.0, b.1)]
            .map(|(u, v)| self.target.intrinsics.unproject_pixel(DVec2::new(u, v)));
        for (k, s) in self.sources.iter().enumerate() {
            let intr = &s.cameras[0].intrinsics;
            let (w, h) = (
                intr.width as f64 + self.reach,
                intr.height as f64 + self.reach,
            );
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
                let (lo, hi) = p.iter().fold((DVec2::MAX, DVec2::MIN), |(lo, hi), p| {
                    (lo.min(*p), hi.max(*p))
                });
                if hi.x > -self.reach && hi.y > -self.reach && lo.x < w && lo.y < h {
                    return true;
                }
            }
        }
        false
    }

    /// Decides what to do with the tile at `(x0, y0)` of side `tile` (level-0 pixels):
    /// one block for the whole tile, or (when its planes differ across it and the smaller
    /// inputs' borders cost less than the planes saved) quadrants down to
    /// [`PruneOptions::min_block`], each with its own planes.
    pub fn plan(&self, x0: usize, y0: usize, tile: usize) -> Vec<Block> {
        let whole = |plan| {
            vec![Block {
                x0,
                y0,
                size: tile,
                plan,
            }]
        };
        if !self.covered(x0, y0, tile) {
            return whole(TilePlan::Uncovered);
        }
        let samples = self.coarse(x0, y0, tile);
        if let Some(plan) = self.flat(&samples) {
            return whole(plan);
        }
        let all: Vec<usize> = (0..samples.pos.len()).collect();
        self.split(&samples, &all, x0, y0, tile).1
    }

    /// Cost of running the network on `planes` planes of a block of side `size`: the
    /// level-0 input area times the planes.
    fn cost(&self, size: usize, planes: usize) -> f64 {
        let side = (size + self.pad0) as f64;
        side * side * planes as f64
    }

    /// The cheapest blocks for the samples `idx` of the block at `(x0, y0)`.
    fn split(
        &self,
        s: &Samples,
        idx: &[usize],
        x0: usize,
        y0: usize,
        size: usize,
    ) -> (f64, Vec<Block>) {
        let planes = self.needed(s, idx);
        let here = self.cost(size, planes.len());
        let half = size / 2;
        if half >= self.opts.min_block.max(1) && half.is_multiple_of(self.align) {
            let mut total = 0.0;
            let mut blocks = Vec::new();
            for (qx, qy) in [
                (x0, y0),
                (x0 + half, y0),
                (x0, y0 + half),
                (x0 + half, y0 + half),
            ] {
                let sub: Vec<usize> = idx
                    .iter()
                    .copied()
                    .filter(|&i| {
                        (qx..qx + half).contains(&s.pos[i].0)
                            && (qy..qy + half).contains(&s.pos[i].1)
                    })
                    .collect();
                if sub.is_empty() {
                    continue; // outside the image
                }
                let (c, b) = self.split(s, &sub, qx, qy, half);
                total += c;
                blocks.extend(b);
            }
            if total < here {
                return (total, blocks);
            }
        }
        (
            here,
            vec![Block {
                x0,
                y0,
                size,
                plan: TilePlan::Planes(planes),
            }],
        )
    }

    /// Level-0 positions and normalized rays of the coarse samples of a tile: every
    /// `stride`-th pixel of the coarse level inside the image, and the first and last.
    fn rays(&self, x0: usize, y0: usize, tile: usize) -> (Vec<(usize, usize)>, Vec<DVec2>, usize) {
        let intr = &self.coarse_target.intrinsics;
        let f = 1usize << self.level;
        let s = (self.opts.stride >> self.level).max(1);
        let (tw, th) = (
            self.target.intrinsics.width as usize,
            self.target.intrinsics.height as usize,
        );
        let span = |a: usize, n: usize| -> Vec<usize> {
            let (lo, hi) = (a / f, (a + tile).min(n).div_ceil(f));
            let mut v: Vec<usize> = (lo..hi).skip(s / 2).step_by(s).collect();
            v.extend([lo, hi.saturating_sub(1)].into_iter().filter(|&i| i < hi));
            v.sort_unstable();
            v.dedup();
            v
        };
        let (xs, ys) = (span(x0, tw), span(y0, th));
        let mut pos = Vec::with_capacity(xs.len() * ys.len());
        let mut rays = Vec::with_capacity(xs.len() * ys.len());
        for &j in &ys {
            for &i in &xs {
                pos.push((i * f, j * f));
                rays.push(intr.unproject_pixel(DVec2::new(i as f64 + 0.5, j as f64 + 0.5)));
            }
        }
        (pos, rays, xs.len())
    }

    /// The coarse cost volume of a tile.
    fn coarse(&self, x0: usize, y0: usize, tile: usize) -> Samples {
        let (pos, rays, nx) = self.rays(x0, y0, tile);
        let (z0, z1) = self.range;
        let nz = z1 + 1 - z0;
        let mut out = Samples {
            nz,
            pos,
            cost: vec![f32::NAN; rays.len() * nz],
            cost0: vec![f32::NAN; rays.len() * nz],
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
            sum: [0.0; 3],
            count: 0,
            all_seen: true,
        };
        let v = self.sources.len();
        let np = rays.len();
        // Colours [sample, plane, source] (alpha-normalized; `None` where unseen).
        let mut col = vec![None; np * nz * v];
        for (p, n) in rays.iter().enumerate() {
            for z in z0..=z1 {
                let mut cnt = 0usize;
                for (k, s) in self.sources.iter().enumerate() {
                    let q = apply_h(&self.homs[k * self.planes + z], n.x, n.y);
                    if q.z <= IN_FRONT_EPS * q.length() {
                        continue;
                    }
                    let cam = &s.cameras[self.level];
                    let uv = cam
                        .intrinsics
                        .project_normalized(DVec2::new(q.x / q.z, q.y / q.z));
                    let c = sample_bilinear(&s.images[self.level], uv.x, uv.y);
                    if c[3] > MIN_ALPHA {
                        let rgb = [c[0] / c[3], c[1] / c[3], c[2] / c[3]];
                        for (ch, &x) in rgb.iter().enumerate() {
                            out.lo[ch] = out.lo[ch].min(x);
                            out.hi[ch] = out.hi[ch].max(x);
                            out.sum[ch] += x;
                        }
                        col[(p * nz + z - z0) * v + k] = Some(rgb);
                        cnt += 1;
                    }
                }
                out.count += cnt;
                if cnt == 0 {
                    out.all_seen = false;
                }
            }
        }
        let ny = np / nx.max(1);
        let r = self.opts.window;
        let costs: Vec<(Vec<f32>, Vec<f32>)> = (0..nz)
            .into_par_iter()
            .map(|zi| {
                let mut best = vec![f32::NAN; np];
                let mut best0 = vec![f32::NAN; np];
                let mut acc = vec![[0f32; 2]; np];
                for &(a, b) in &self.pairs {
                    {
                        for (p, m) in acc.iter_mut().enumerate() {
                            *m = match (col[(p * nz + zi) * v + a], col[(p * nz + zi) * v + b]) {
                                (Some(x), Some(y)) => {
                                    [1.0, (0..3).map(|c| (x[c] - y[c]).powi(2)).sum()]
                                }
                                _ => [0.0; 2],
                            };
                            if m[0] > 0.0 && (best0[p].is_nan() || best0[p] > m[1] / 3.0) {
                                best0[p] = m[1] / 3.0;
                            }
                        }
                        let sums = box_sum(&acc, nx, ny, r);
                        let full = ((2 * r + 1) * (2 * r + 1)) as f32;
                        for (p, m) in sums.iter().enumerate() {
                            let n = m[0];
                            if n < 3.0 || n < 0.5 * full.min((nx * ny) as f32) {
                                continue;
                            }
                            // Mean squared colour difference of the pair over the window.
                            let c = m[1] / (3.0 * n);
                            if best[p].is_nan() || best[p] > c {
                                best[p] = c;
                            }
                        }
                    }
                }
                (best, best0)
            })
            .collect();
        for (zi, (c, c0)) in costs.iter().enumerate() {
            for p in 0..np {
                out.cost[p * nz + zi] = c[p];
                out.cost0[p * nz + zi] = c0[p];
            }
        }
        out
    }

    /// Per sample of a tile, its level-0 position and its cost per plane of the range.
    #[cfg(test)]
    pub(crate) fn debug_costs(
        &self,
        x0: usize,
        y0: usize,
        tile: usize,
    ) -> Vec<((usize, usize), Vec<f32>)> {
        let s = self.coarse(x0, y0, tile);
        s.pos
            .iter()
            .enumerate()
            .map(|(p, &xy)| (xy, s.cost[p * s.nz..(p + 1) * s.nz].to_vec()))
            .collect()
    }

    /// The flat plan when every sampled source colour is the same.
    fn flat(&self, s: &Samples) -> Option<TilePlan> {
        let flat = (0..3).all(|ch| s.hi[ch] - s.lo[ch] <= 2.0 * self.opts.flat);
        (s.count > 0 && s.all_seen && flat).then(|| TilePlan::Flat {
            colour: s.sum.map(|x| x / s.count as f32),
            coverage: s.count as f32 / (s.cost.len() * self.sources.len()).max(1) as f32,
        })
    }

    /// The planes the samples `idx` need. Each informative sample finds plausible the
    /// planes whose cost lies within the tolerance of its least; the kept planes are a
    /// small set (chosen greedily, the plane most samples find plausible first) such that
    /// [`PruneOptions::mass`] of the informative samples find one of them plausible,
    /// widened by the margin on each side.
    fn needed(&self, s: &Samples, idx: &[usize]) -> Vec<usize> {
        let (z0, z1) = self.range;
        let mut total = vec![0f32; s.nz];
        let mut good: Vec<Vec<usize>> = Vec::new();
        for &p in idx {
            // The sample alone, when its best plane stands out: thin structures that the
            // window averages away.
            let c0 = &s.cost0[p * s.nz..(p + 1) * s.nz];
            let mut k0: Vec<(usize, f32)> = c0
                .iter()
                .copied()
                .enumerate()
                .filter(|(_, x)| !x.is_nan())
                .collect();
            if k0.len() >= 3 {
                k0.sort_by(|a, b| a.1.total_cmp(&b.1));
                let (best, lo0, med0) = (k0[0].0, k0[0].1, k0[k0.len() / 2].1);
                if med0 - lo0 >= self.opts.contrast && lo0 <= self.opts.standout * med0 {
                    good.push(vec![best]);
                }
            }
            let c = &s.cost[p * s.nz..(p + 1) * s.nz];
            let known = || c.iter().enumerate().filter(|(_, x)| !x.is_nan());
            let (lo, hi) = known().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), (_, &x)| {
                (a.min(x), b.max(x))
            });
            if known().count() < 2 || hi - lo < self.opts.contrast {
                for (z, &x) in known() {
                    total[z] += x;
                }
                continue;
            }
            let cut = lo + self.opts.tolerance * (hi - lo);
            good.push(known().filter(|(_, &x)| x <= cut).map(|(z, _)| z).collect());
        }
        let mut want = vec![false; self.planes];
        if !good.is_empty() {
            // Each sample spreads a unit of support over its plausible planes; keep the
            // most supported planes until they hold `mass` of it all.
            let mut support = vec![0f32; s.nz];
            for g in &good {
                for &z in g {
                    support[z] += 1.0 / g.len() as f32;
                }
            }
            let mut order: Vec<usize> = (0..s.nz).filter(|&z| support[z] > 0.0).collect();
            order.sort_by(|&a, &b| support[b].total_cmp(&support[a]).then(a.cmp(&b)));
            let all: f32 = support.iter().sum();
            let mut acc = 0f32;
            for z in order {
                if acc >= self.opts.mass * all {
                    break;
                }
                acc += support[z];
                want[z0 + z] = true;
            }
        } else {
            // Nothing here tells depths apart: the plane of least total cost, or every
            // plane of the range when no source sees any sample.
            match total
                .iter()
                .enumerate()
                .filter(|(_, x)| **x > 0.0)
                .min_by(|a, b| a.1.total_cmp(b.1))
            {
                Some((z, _)) => want[z0 + z] = true,
                None => want[z0..=z1].iter_mut().for_each(|w| *w = true),
            }
        }
        // The margin stays inside the depth range: nothing is beyond it.
        let m = self.margin;
        (z0..=z1)
            .filter(|&z| (z.saturating_sub(m)..=(z + m).min(z1)).any(|q| want[q]))
            .collect()
    }
}

/// Least baseline of a pair of sources, relative to the largest baseline between any two,
/// for its photo-consistency to count.
const MIN_BASELINE: f64 = 0.02;

/// The pairs of sources with a baseline (see [`Pruner`]); every pair when none has.
fn depth_pairs(sources: &[&PyramidSource]) -> Vec<(usize, usize)> {
    let c: Vec<_> = sources.iter().map(|s| s.cameras[0].pose.centre()).collect();
    let all: Vec<(usize, usize)> = (0..c.len())
        .flat_map(|a| (a + 1..c.len()).map(move |b| (a, b)))
        .collect();
    let longest = all
        .iter()
        .map(|&(a, b)| c[a].distance(c[b]))
        .fold(0.0, f64::max);
    let with: Vec<(usize, usize)> = all
        .iter()
        .copied()
        .filter(|&(a, b)| c[a].distance(c[b]) > MIN_BASELINE * longest)
        .collect();
    if with.is_empty() {
        all
    } else {
        with
    }
}

/// Sums of `[f32; 2]` over the `(2r+1)^2` window around each sample of an `nx x ny`
/// grid (clipped at the borders).
fn box_sum(x: &[[f32; 2]], nx: usize, ny: usize, r: usize) -> Vec<[f32; 2]> {
    let add = |a: &mut [f32; 2], b: &[f32; 2]| a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
    let mut rows = vec![[0f32; 2]; x.len()];
    for y in 0..ny {
        for i in 0..nx {
            let mut m = [0f32; 2];
            for j in i.saturating_sub(r)..(i + r + 1).min(nx) {
                add(&mut m, &x[y * nx + j]);
            }
            rows[y * nx + i] = m;
        }
    }
    let mut out = vec![[0f32; 2]; x.len()];
    for y in 0..ny {
        for i in 0..nx {
            let mut m = [0f32; 2];
            for j in y.saturating_sub(r)..(y + r + 1).min(ny) {
                add(&mut m, &rows[j * nx + i]);
            }
            out[y * nx + i] = m;
        }
    }
    out
}

/// The coarse pass's view of a tile.
struct Samples {
    /// Planes of the range.
    nz: usize,
    /// Level-0 position of each sample (the top-left of its coarse pixel).
    pos: Vec<(usize, usize)>,
    /// `[sample, plane]` colour variance across the sources that see the point (NaN
    /// where fewer than two do).
    cost: Vec<f32>,
    /// The same cost of the sample alone (no window).
    cost0: Vec<f32>,
    /// Per channel, the least and largest source colour seen, and the sum and count.
    lo: [f32; 3],
    hi: [f32; 3],
    sum: [f32; 3],
    count: usize,
    /// Whether every sample and plane had at least one source.
    all_seen: bool,
}
