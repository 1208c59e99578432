//! The classical checks on generated scenes: a plane sweep over the 4 nearest views beats
//! copying the nearest one, and those 4 views see most of every view.

use super::tests::{centre, nearest, small, TestResult};
use super::*;
use crate::camera::Camera;
use crate::geometry::inverse_depths;
use crate::sweep::{sweep, Region, Source, CHANNELS};

/// Half-size of the window the classical plane sweep aggregates its costs over.
const COST_WINDOW: usize = 2;

/// Classical check: per pixel, the plane where the sources' colours vary least (variance
/// averaged over a small window, among the planes where the most sources see the pixel),
/// rendered as their mean there; pixels that fewer than two sources see at every plane
/// take what one source sees at the farthest such plane.
pub(super) fn plane_sweep_render(
    target: &Camera,
    sources: &[Source<'_>],
    near: f64,
    far: f64,
    planes: usize,
) -> RgbImage {
    let inv = inverse_depths(near, far, planes);
    let region = Region::full(&target.intrinsics);
    let vol = sweep(target, region, sources, &inv);
    let (hw, nv, w, h) = (region.len(), sources.len(), region.width, region.height);
    let mut cost = vec![f32::INFINITY; inv.len() * hw];
    let mut mean = vec![0f32; inv.len() * hw * 3];
    let mut count = vec![0f32; inv.len() * hw];
    for d in 0..inv.len() {
        for p in 0..hw {
            let (mut sum, mut sq, mut n) = ([0f32; 3], [0f32; 3], 0.0f32);
            for k in 0..nv {
                let base = (d * nv + k) * CHANNELS * hw;
                let a = vol[base + 3 * hw + p];
                if a < 0.99 {
                    continue;
                }
                for c in 0..3 {
                    let x = vol[base + c * hw + p] / a;
                    sum[c] += x;
                    sq[c] += x * x;
                }
                n += 1.0;
            }
            count[d * hw + p] = n;
            if n >= 1.0 {
                for c in 0..3 {
                    mean[(d * hw + p) * 3 + c] = sum[c] / n;
                }
            }
            if n >= 2.0 {
                cost[d * hw + p] = (0..3).map(|c| sq[c] / n - (sum[c] / n).powi(2)).sum();
            }
        }
    }
    // A plane where some sources fall outside their images would win just by having
    // fewer colours to disagree: only planes where the most sources see the pixel count.
    for p in 0..hw {
        let most = (0..inv.len())
            .map(|d| count[d * hw + p])
            .fold(0.0f32, f32::max);
        for d in 0..inv.len() {
            if count[d * hw + p] < most {
                cost[d * hw + p] = f32::INFINITY;
            }
        }
    }
    let mut out = RgbImage::new(target.intrinsics.width, target.intrinsics.height);
    for p in 0..hw {
        let (x, y) = (p % w, p / w);
        let mut best = (f32::INFINITY, usize::MAX);
        for d in 0..inv.len() {
            if !cost[d * hw + p].is_finite() {
                continue;
            }
            let (mut acc, mut n) = (0.0f32, 0.0f32);
            for yy in y.saturating_sub(COST_WINDOW)..(y + COST_WINDOW + 1).min(h) {
                for xx in x.saturating_sub(COST_WINDOW)..(x + COST_WINDOW + 1).min(w) {
                    let c = cost[d * hw + yy * w + xx];
                    if c.is_finite() {
                        acc += c;
                        n += 1.0;
                    }
                }
            }
            if acc / n < best.0 {
                best = (acc / n, d);
            }
        }
        // Without a plane seen by two sources, the farthest plane any source sees.
        let plane = if best.1 < inv.len() {
            Some(best.1)
        } else {
            (0..inv.len()).rev().find(|&d| count[d * hw + p] > 0.0)
        };
        let c = match plane {
            Some(d) => {
                let i = (d * hw + p) * 3;
                [mean[i], mean[i + 1], mean[i + 2]]
            }
            None => sources[0].image.pixel(x as u32, y as u32),
        };
        out.data[3 * p..3 * p + 3].copy_from_slice(&c);
    }
    out
}

/// The view whose camera centre is nearest the centroid of all centres.
pub(super) fn central_view(cams: &[Camera]) -> usize {
    let mean = cams.iter().map(|c| c.pose.centre()).sum::<glam::DVec3>() / cams.len() as f64;
    (0..cams.len())
        .min_by(|&a, &b| {
            cams[a]
                .pose
                .centre()
                .distance(mean)
                .total_cmp(&cams[b].pose.centre().distance(mean))
        })
        .unwrap_or(0)
}

pub(super) fn psnr(a: &RgbImage, b: &RgbImage) -> f64 {
    let mse = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.data.len() as f64;
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

#[test]
fn synth_plane_sweep_beats_nearest_source() -> TestResult {
    for rig in Rig::CONCRETE {
        let mut gains = Vec::new();
        for seed in [33, 34, 35] {
            let s = generate(seed, &small(rig, 9, 96, 72))?;
            let t = central_view(&s.cameras);
            let src = nearest(&s.cameras, t, 4);
            let sources: Vec<Source<'_>> = src
                .iter()
                .map(|&i| Source {
                    camera: &s.cameras[i],
                    image: &s.images[i],
                })
                .collect();
            let swept = plane_sweep_render(&s.cameras[t], &sources, s.near, s.far, 32);
            let (p_sweep, p_copy) = (
                psnr(&swept, &s.images[t]),
                psnr(&s.images[src[0]], &s.images[t]),
            );
            println!("{rig} seed {seed} view {t}: plane sweep {p_sweep:.2} dB, nearest source {p_copy:.2} dB");
            gains.push(p_sweep - p_copy);
        }
        let mean = gains.iter().sum::<f64>() / gains.len() as f64;
        let worst = gains.iter().fold(f64::INFINITY, |m, &g| m.min(g));
        assert!(
            mean > 4.0 && worst > 2.0,
            "{rig}: plane sweep gains only {gains:?} dB over the nearest source"
        );
    }
    Ok(())
}

/// Fractions of view `t`'s pixels whose surface point falls inside at least one and at
/// least two of its 4 nearest views (occlusion ignored).
fn coverage(s: &SynthScene, t: usize) -> (f64, f64) {
    let cam = &s.cameras[t];
    let w = cam.intrinsics.width as usize;
    let nb = nearest(&s.cameras, t, 4);
    let (mut one, mut two, mut n) = (0usize, 0usize, 0usize);
    for p in (0..s.depths[t].len()).step_by(3) {
        let pt = cam.unproject(centre(p, w), s.depths[t][p] as f64);
        let seen = nb
            .iter()
            .filter(|&&i| {
                let k = &s.cameras[i].intrinsics;
                let (uv, z) = s.cameras[i].project(pt);
                z > 0.0
                    && uv.x >= 0.0
                    && uv.y >= 0.0
                    && uv.x < k.width as f64
                    && uv.y < k.height as f64
            })
            .count();
        one += usize::from(seen >= 1);
        two += usize::from(seen >= 2);
        n += 1;
    }
    (one as f64 / n as f64, two as f64 / n as f64)
}

#[test]
fn synth_every_rig_has_overlapping_neighbours() -> TestResult {
    let mut worst = Vec::new();
    for rig in Rig::CONCRETE {
        let (mut min1, mut min2) = (1.0f64, 1.0f64);
        for seed in 0..8 {
            let s = generate(
                scene_seed(99, seed),
                &SynthOptions {
                    supersample: 1,
                    ..small(rig, 10, 64, 48)
                },
            )?;
            for t in 0..s.cameras.len() {
                let (one, two) = coverage(&s, t);
                min1 = min1.min(one);
                min2 = min2.min(two);
            }
        }
        println!("{rig}: worst view seen by >=1 neighbour {min1:.3}, by >=2 {min2:.3}");
        worst.push((rig, min1, min2));
    }
    for (rig, min1, min2) in worst {
        assert!(
            min1 > 0.8 && min2 > 0.6,
            "{rig}: neighbours overlap too little ({min1}, {min2})"
        );
    }
    Ok(())
}
