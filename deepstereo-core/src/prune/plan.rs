//! Per-tile decisions: which planes the network runs on, or whether it runs at all.

mod coarse;

use super::guide::Guide;
use super::PruneOptions;
use crate::camera::Camera;
use crate::config::Config;
use crate::geometry::{apply_h, plane_homography};
use crate::inputs::{level_camera, PyramidSource};
use coarse::{depth_pairs, Samples};
use glam::{DMat3, DVec2};

/// Guide pixels around a block whose planes it also keeps (the selection at coarse
/// resolution blurs edges).
const GUIDE_DILATE: usize = 1;
/// Side of the block whose one-plane network call costs what a call's fixed overhead
/// does (see [`Pruner::call_cost`]).
const CALL_COST_SIDE: usize = 16;

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
    /// The network's coarse pass, when it replaces the photo-consistency pass.
    guide: Option<Guide>,
    /// Seconds the guide took to render.
    guide_seconds: f64,
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
            guide: None,
            guide_seconds: 0.0,
        }
    }

    /// Plans blocks from the network's own coarse selection (see [`super::network_guide`])
    /// instead of photo-consistency; `seconds`: what the guide cost, counted in the
    /// coarse pass's time.
    pub fn with_guide(mut self, guide: Guide, seconds: f64) -> Self {
        self.guide = Some(guide);
        self.guide_seconds = seconds;
        self
    }

    /// Whether the cheap flat probe finds the tile at `(x0, y0)` constant (tests).
    #[cfg(test)]
    pub(crate) fn flat_probe_for_tests(&self, x0: usize, y0: usize, tile: usize) -> bool {
        self.flat_probe(x0, y0, tile).is_some()
    }

    /// Seconds spent on the guide (0 without one).
    pub fn guide_seconds(&self) -> f64 {
        self.guide_seconds
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
        if let Some(plan) = self.flat_probe(x0, y0, tile) {
            return whole(plan);
        }
        if let Some(g) = &self.guide {
            return self.split_guided(g, x0, y0, tile).1;
        }
        let samples = self.coarse(x0, y0, tile);
        let all: Vec<usize> = (0..samples.pos.len()).collect();
        self.split(&samples, &all, x0, y0, tile, None).1
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
        parent: Option<&[usize]>,
    ) -> (f64, Vec<Block>) {
        // A block none of whose samples tells depths apart (textureless) takes the planes
        // of the block around it: its depth is most likely that of the surfaces nearby.
        let planes = match (self.needed(s, idx), parent) {
            (Some(p), _) => p,
            (None, Some(p)) => p.to_vec(),
            (None, None) => self.fallback(s, idx),
        };
        let here = self.cost(size, planes.len());
        self.cheapest(x0, y0, size, planes, here, |qx, qy, half, planes| {
            let sub: Vec<usize> = idx
                .iter()
                .copied()
                .filter(|&i| {
                    (qx..qx + half).contains(&s.pos[i].0) && (qy..qy + half).contains(&s.pos[i].1)
                })
                .collect();
            // No sample: the quadrant lies outside the image.
            (!sub.is_empty()).then(|| self.split(s, &sub, qx, qy, half, Some(planes)))
        })
    }

    /// The cheapest blocks for the block at `(x0, y0)` of side `size`, planes from the
    /// guide.
    fn split_guided(&self, g: &Guide, x0: usize, y0: usize, size: usize) -> (f64, Vec<Block>) {
        let (z0, z1) = self.range;
        let planes = match g.planes(x0, y0, size, GUIDE_DILATE, self.opts.keep, self.opts.error) {
            Some(want) => self.widen(&want),
            None => (z0..=z1).collect(),
        };
        let here = self.cost(size, planes.len()) + self.call_cost();
        let (w, h) = (
            self.target.intrinsics.width as usize,
            self.target.intrinsics.height as usize,
        );
        self.cheapest(x0, y0, size, planes, here, |qx, qy, half, _| {
            // A quadrant outside the image needs nothing.
            (qx < w && qy < h).then(|| self.split_guided(g, qx, qy, half))
        })
    }

    /// The block at `(x0, y0)` of side `size` run whole on `planes` (cost `here`), or its
    /// quadrants as `quadrant(x, y, half, planes)` plans them (`None`: nothing to run
    /// there), whichever costs less; quadrants only down to [`PruneOptions::min_block`]
    /// and the model's alignment.
    fn cheapest(
        &self,
        x0: usize,
        y0: usize,
        size: usize,
        planes: Vec<usize>,
        here: f64,
        mut quadrant: impl FnMut(usize, usize, usize, &[usize]) -> Option<(f64, Vec<Block>)>,
    ) -> (f64, Vec<Block>) {
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
                if let Some((c, b)) = quadrant(qx, qy, half, &planes) {
                    total += c;
                    blocks.extend(b);
                }
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

    /// Fixed cost of one network call, in the units of [`Self::cost`]: measured per
    /// call, a block of side 16 on one plane costs about as much as 2 planes would.
    fn call_cost(&self) -> f64 {
        let side = (CALL_COST_SIDE + self.pad0) as f64;
        side * side
    }

    /// The planes the samples `idx` need: each sample that tells depths apart spreads a
    /// unit of support over its plausible planes (those within the tolerance of its least
    /// cost, and its own best plane when that stands out); the most supported planes
    /// holding [`PruneOptions::mass`] of the support are kept, widened by the margin.
    /// `None` when no sample tells depths apart.
    fn needed(&self, s: &Samples, idx: &[usize]) -> Option<Vec<usize>> {
        let z0 = self.range.0;
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
                continue;
            }
            let cut = lo + self.opts.tolerance * (hi - lo);
            good.push(known().filter(|(_, &x)| x <= cut).map(|(z, _)| z).collect());
        }
        if good.is_empty() {
            return None;
        }
        // Each sample spreads a unit of support over its plausible planes; keep the most
        // supported planes until they hold `mass` of it all.
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
        let mut want = vec![false; self.planes];
        for z in order {
            if acc >= self.opts.mass * all {
                break;
            }
            acc += support[z];
            want[z0 + z] = true;
        }
        Some(self.widen(&want))
    }

    /// The planes of a tile none of whose samples tells depths apart: the plane of least
    /// total cost (the colour there hardly depends on depth), or every plane of the range
    /// when no source sees any sample.
    fn fallback(&self, s: &Samples, idx: &[usize]) -> Vec<usize> {
        let (z0, z1) = self.range;
        let mut total = vec![0f32; s.nz];
        for &p in idx {
            for (z, &x) in s.cost[p * s.nz..(p + 1) * s.nz].iter().enumerate() {
                if !x.is_nan() {
                    total[z] += x;
                }
            }
        }
        let mut want = vec![false; self.planes];
        match total
            .iter()
            .enumerate()
            .filter(|(_, x)| **x > 0.0)
            .min_by(|a, b| a.1.total_cmp(b.1))
        {
            Some((z, _)) => want[z0 + z] = true,
            None => want[z0..=z1].iter_mut().for_each(|w| *w = true),
        }
        self.widen(&want)
    }

    /// The wanted planes and [`PruneOptions::margin`] planes on each side of each.
    fn widen(&self, want: &[bool]) -> Vec<usize> {
        let (z0, z1) = self.range;
        // The margin stays inside the depth range: nothing is beyond it.
        let m = self.margin;
        (z0..=z1)
            .filter(|&z| (z.saturating_sub(m)..=(z + m).min(z1)).any(|q| want[q]))
            .collect()
    }
}
