//! The coarse photo-consistency pass of a tile.

use super::{Pruner, TilePlan};
use crate::baseline::MIN_ALPHA;
use crate::camera::IN_FRONT_EPS;
use crate::geometry::apply_h;
use crate::inputs::PyramidSource;
use crate::sweep::sample_bilinear;
use glam::DVec2;
use rayon::prelude::*;

impl Pruner<'_> {
    /// Level-0 positions and normalized rays of the coarse samples of a tile: every
    /// `stride`-th pixel of the coarse level inside the image, and the first and last.
    pub(super) fn rays(
        &self,
        x0: usize,
        y0: usize,
        tile: usize,
    ) -> (Vec<(usize, usize)>, Vec<DVec2>, usize) {
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

    /// Source `k`'s colour (alpha-normalized) on plane `z` along the normalized target
    /// ray `n`, at the coarse level; `None` where the source does not see it.
    fn colour_at(&self, k: usize, z: usize, n: &DVec2) -> Option<[f32; 3]> {
        let q = apply_h(&self.homs[k * self.planes + z], n.x, n.y);
        if q.z <= IN_FRONT_EPS * q.length() {
            return None;
        }
        let s = &self.sources[k];
        let uv = s.cameras[self.level]
            .intrinsics
            .project_normalized(DVec2::new(q.x / q.z, q.y / q.z));
        let c = sample_bilinear(&s.images[self.level], uv.x, uv.y);
        (c[3] > MIN_ALPHA).then(|| [c[0] / c[3], c[1] / c[3], c[2] / c[3]])
    }

    /// The flat plan of a tile whose coarse samples (the rays of [`Self::coarse`]) see one
    /// colour in every source at every plane of the range; `None` as soon as two sampled
    /// colours differ by more than twice [`super::PruneOptions::flat`], or a sample is seen
    /// by no source. Both coarse passes ask this first: it samples as the
    /// photo-consistency pass does, and a flat tile needs no cost volume.
    pub(super) fn flat_probe(&self, x0: usize, y0: usize, tile: usize) -> Option<TilePlan> {
        let (_, rays, _) = self.rays(x0, y0, tile);
        let (z0, z1) = self.range;
        let limit = 2.0 * self.opts.flat;
        let (mut lo, mut hi, mut sum) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3], [0f64; 3]);
        let mut count = 0usize;
        for n in &rays {
            for z in z0..=z1 {
                let mut seen = false;
                for k in 0..self.sources.len() {
                    if let Some(rgb) = self.colour_at(k, z, n) {
                        for ch in 0..3 {
                            lo[ch] = lo[ch].min(rgb[ch]);
                            hi[ch] = hi[ch].max(rgb[ch]);
                            sum[ch] += rgb[ch] as f64;
                            if hi[ch] - lo[ch] > limit {
                                return None;
                            }
                        }
                        seen = true;
                        count += 1;
                    }
                }
                if !seen {
                    return None;
                }
            }
        }
        let total = rays.len() * (z1 + 1 - z0) * self.sources.len();
        (count > 0).then(|| TilePlan::Flat {
            colour: sum.map(|x| (x / count as f64) as f32),
            coverage: count as f32 / total.max(1) as f32,
        })
    }

    /// The coarse cost volume of a tile.
    pub(super) fn coarse(&self, x0: usize, y0: usize, tile: usize) -> Samples {
        let (pos, rays, nx) = self.rays(x0, y0, tile);
        let (z0, z1) = self.range;
        let nz = z1 + 1 - z0;
        let mut out = Samples {
            nz,
            pos,
            cost: vec![f32::NAN; rays.len() * nz],
            cost0: vec![f32::NAN; rays.len() * nz],
        };
        let v = self.sources.len();
        let np = rays.len();
        // Colours [sample, plane, source] (alpha-normalized; `None` where unseen).
        let mut col = vec![None; np * nz * v];
        for (p, n) in rays.iter().enumerate() {
            for z in z0..=z1 {
                for k in 0..self.sources.len() {
                    col[(p * nz + z - z0) * v + k] = self.colour_at(k, z, n);
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
}

/// Least baseline of a pair of sources, relative to the largest baseline between any two,
/// for its photo-consistency to count.
const MIN_BASELINE: f64 = 0.02;

/// The pairs of sources with a baseline (see [`Pruner`]); every pair when none has.
pub(super) fn depth_pairs(sources: &[&PyramidSource]) -> Vec<(usize, usize)> {
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
pub(super) struct Samples {
    /// Planes of the range.
    pub(super) nz: usize,
    /// Level-0 position of each sample (the top-left of its coarse pixel).
    pub(super) pos: Vec<(usize, usize)>,
    /// `[sample, plane]` colour variance across the sources that see the point (NaN
    /// where fewer than two do).
    pub(super) cost: Vec<f32>,
    /// The same cost of the sample alone (no window).
    pub(super) cost0: Vec<f32>,
}
