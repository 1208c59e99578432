//! Classical baselines a learned renderer must beat, on the same sources and planes.
//!
//! - `nearest`: the nearest source image, as it is (no warping).
//! - `plane_sweep`: per pixel and plane, the colour variance across the sources that see
//!   the point (alpha above [`MIN_ALPHA`]), averaged over a `(2r+1)^2` window; the plane of
//!   least cost wins (winner-take-all) and the pixel takes the sources' mean colour there.

use crate::camera::Camera;
use crate::imageio::RgbImage;
use crate::sweep::{sweep_into, Region, Source, CHANNELS};
use rayon::prelude::*;

/// Sources with less alpha than this at a pixel do not vote there.
pub const MIN_ALPHA: f32 = 0.5;
/// Cost of a pixel and plane that fewer than two sources see.
pub const UNSEEN_COST: f32 = 1.0;
/// Half-size of the cost aggregation window.
pub const WINDOW_RADIUS: usize = 2;
/// Rows processed per band (bounds memory to `D * V * 4 * band * W` floats).
const BAND_ROWS: usize = 32;

/// Classical plane-sweep stereo rendering of `target` from `sources` at `inv_depths`.
/// Returns the image and the winning plane index per pixel.
pub fn plane_sweep(
    target: &Camera,
    sources: &[Source<'_>],
    inv_depths: &[f64],
) -> (RgbImage, Vec<u16>) {
    let (w, h) = (
        target.intrinsics.width as usize,
        target.intrinsics.height as usize,
    );
    let (d, v) = (inv_depths.len(), sources.len());
    let r = WINDOW_RADIUS;
    let mut img = RgbImage::new(w as u32, h as u32);
    let mut planes = vec![0u16; w * h];
    let mut y0 = 0;
    while y0 < h {
        let rows = BAND_ROWS.min(h - y0);
        // Sweep the band plus the window margin.
        let region = Region {
            x0: -(r as i64),
            y0: y0 as i64 - r as i64,
            width: w + 2 * r,
            height: rows + 2 * r,
        };
        let n = region.len();
        let mut psv = vec![0f32; d * v * CHANNELS * n];
        sweep_into(target, region, sources, inv_depths, &mut psv);
        let per_plane: Vec<(Vec<f32>, Vec<[f32; 3]>)> = (0..d)
            .into_par_iter()
            .map(|z| {
                let plane = &psv[z * v * CHANNELS * n..][..v * CHANNELS * n];
                let (cost, mean) = plane_cost(plane, v, n);
                let rw = region.width;
                // The mean colours of the output pixels (the band without its margin).
                let centre = (0..rows * w)
                    .map(|i| mean[(i / w + r) * rw + i % w + r])
                    .collect();
                (box_sum(&cost, rw, (w, rows), r), centre)
            })
            .collect();
        for i in 0..rows * w {
            let best = (0..d)
                .min_by(|&a, &b| per_plane[a].0[i].total_cmp(&per_plane[b].0[i]))
                .unwrap_or(0);
            let pix = (y0 + i / w) * w + i % w;
            planes[pix] = best as u16;
            img.data[pix * 3..pix * 3 + 3].copy_from_slice(&per_plane[best].1[i]);
        }
        y0 += rows;
    }
    (img, planes)
}

/// Per pixel of one plane's sweep `plane` `[V, 4, n]`: the variance of the colours of
/// the views that see it ([`UNSEEN_COST`] where fewer than two do) and their mean colour.
fn plane_cost(plane: &[f32], v: usize, n: usize) -> (Vec<f32>, Vec<[f32; 3]>) {
    let mut cost = vec![UNSEEN_COST; n];
    let mut mean = vec![[0f32; 3]; n];
    for p in 0..n {
        let (mut s, mut s2, mut cnt) = ([0f32; 3], 0f32, 0f32);
        for k in 0..v {
            let base = k * CHANNELS * n;
            let a = plane[base + 3 * n + p];
            if a > MIN_ALPHA {
                for c in 0..3 {
                    let x = plane[base + c * n + p] / a;
                    s[c] += x;
                    s2 += x * x;
                }
                cnt += 1.0;
            }
        }
        if cnt > 0.0 {
            mean[p] = [s[0] / cnt, s[1] / cnt, s[2] / cnt];
        }
        if cnt >= 2.0 {
            let m2: f32 = mean[p].iter().map(|m| m * m).sum();
            cost[p] = (s2 / cnt - m2).max(0.0) / 3.0;
        }
    }
    (cost, mean)
}

/// The sums of `cost` (rows `rw` wide) over the `(2r+1)^2` box below-right of each of the
/// `w x rows` output pixels (the box aggregation of the band without its margin).
fn box_sum(cost: &[f32], rw: usize, (w, rows): (usize, usize), r: usize) -> Vec<f32> {
    let mut agg = vec![0f32; rows * w];
    for y in 0..rows {
        for x in 0..w {
            let mut acc = 0.0;
            for dy in 0..=2 * r {
                for dx in 0..=2 * r {
                    acc += cost[(y + dy) * rw + x + dx];
                }
            }
            agg[y * w + x] = acc;
        }
    }
    agg
}
