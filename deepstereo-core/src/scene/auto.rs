//! Depth bounds found from a scene's own images when it gives none (no file bounds, no
//! sparse points, no `--near`/`--far`).
//!
//! # Method: a coarse-to-fine photo-consistency plane sweep with the known poses
//! 1. Up to [`AUTO_REFERENCES`] reference views, evenly spaced over the scene's view list,
//!    each with its [`AUTO_NEIGHBOURS`] nearest neighbours (by camera centre) among the
//!    views that look the same way (optical axes within [`MAX_AXIS_ANGLE_DEG`]) from a
//!    different place (baseline above [`MIN_BASELINE_FRACTION`] of the cameras' spread).
//!    Images are box-downscaled by powers of two to at most [`AUTO_MAX_WIDTH`] pixels wide,
//!    intrinsics scaled to match.
//! 2. For each reference, [`COARSE_PLANES`] fronto-parallel planes uniform in inverse
//!    depth from `rho_max` to 0 (infinity), `rho_max` putting [`DISPARITY_FRACTION`] of the
//!    image width of disparity between the reference and its nearest neighbour
//!    (`rho_max = DISPARITY_FRACTION * w / (fx * baseline)`): a range far wider than any
//!    scene needs. Each neighbour is warped onto each plane by [`crate::sweep::sweep`];
//!    the cost of a pixel at a plane is `1 - NCC` of the grey levels in a
//!    `(2 * WINDOW_RADIUS + 1)^2` window (insensitive to exposure changes), averaged over
//!    the neighbours; a plane counts only where every neighbour's warp covers the whole
//!    window. Bounds are taken from this pass (step 4), then the sweep is run again with
//!    [`FINE_PLANES`] planes between those bounds (the coarse pass resolves inverse depth
//!    only to `rho_max / COARSE_PLANES`, too coarse near infinity), and step 4 is applied
//!    to the second pass's matches.
//! 3. A pixel is kept only if its reference window is textured (grey standard deviation
//!    at least [`MIN_TEXTURE_STD`]), enough planes were scored, its best cost is low
//!    ([`MAX_COST`]), distinct (at most [`RATIO`] times the best cost more than
//!    [`EXCLUSION_PLANES`] planes away: repetitive and flat pixels fail this), and not on
//!    the nearest plane (a surface nearer than the search). Its inverse depth is refined by
//!    a parabola through the three costs around the minimum, and the pixel becomes a world
//!    point (the reference ray at that depth).
//!    A minimum on the farthest plane passes a weaker test ([`FAR_END_RATIO`]): distant,
//!    smooth textures have broad minima there.
//! 4. Bounds: the [`DEPTH_PERCENTILES`] of the points' inverse depths (in their reference
//!    views), widened in inverse depth by [`REL_MARGIN`] of themselves, [`SPAN_MARGIN`] of
//!    their span and [`STEP_MARGIN`] plane steps (the sweep's resolution). `far` is
//!    infinite when its inverse depth falls to [`INFINITE_FAR_FRACTION`] of near's or
//!    below: a far bound too near leaves distant, weakly textured surfaces (that no
//!    matcher finds) without a plane, one too far costs at most that fraction of the
//!    planes. The points within the bounds (at most [`MAX_POINTS`], subsampled with a fixed
//!    stride; points at infinity placed at the depth of half a plane step) become the
//!    scene's sparse points, so that per-target pruning gets per-view ranges too.
//!
//! Deterministic: references, neighbours and planes are fixed by the poses, the references
//! are processed independently and their points concatenated in order. Nothing is written.
//!
//! # Limits
//! Surfaces without texture at the matching scale give no points: a scene whose nearest
//! or farthest surfaces are plain gets bounds that miss them (a procedural scene whose
//! backdrop is smooth noise, for one, gets a far bound of 23 against a true 1124); pass
//! `--near`/`--far` then. Cost: about 2 s for a 10-view 160x120 scene, 1.8 s for a 302-view
//! video at 480x270 and 5 s for 67 views at 1080x1920 (decoding the full-size JPEGs
//! dominates) on 2 cores.

use super::View;
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::imageio::RgbImage;
use crate::sweep::{sweep, Region, Source};
use glam::{DVec2, DVec3};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;

/// Most reference views swept.
pub const AUTO_REFERENCES: usize = 12;
/// Neighbours compared with each reference.
pub const AUTO_NEIGHBOURS: usize = 2;
/// Images are downscaled (by powers of two) to at most this width.
pub const AUTO_MAX_WIDTH: u32 = 160;
/// Planes of the first sweep, over a wide range.
pub const COARSE_PLANES: usize = 64;
/// Planes of the second sweep, over the first one's bounds.
pub const FINE_PLANES: usize = 64;
/// The nearest plane gives this fraction of the image width of disparity to the nearest
/// neighbour.
pub const DISPARITY_FRACTION: f64 = 0.5;
/// Neighbours' optical axes are within this angle of the reference's.
pub const MAX_AXIS_ANGLE_DEG: f64 = 60.0;
/// Neighbours are at least this fraction of the cameras' spread (bounding-box diagonal of
/// their centres) away from the reference: views taken from (almost) the same place, such
/// as the several directions of one rosette position, give no usable parallax.
pub const MIN_BASELINE_FRACTION: f64 = 0.02;
/// Half-size of the matching window, in downscaled pixels.
pub const WINDOW_RADIUS: usize = 2;
/// Least grey-level standard deviation of a reference window that counts as textured.
pub const MIN_TEXTURE_STD: f64 = 0.02;
/// Largest accepted best cost (`1 - NCC`).
pub const MAX_COST: f64 = 0.2;
/// The best cost must be at most this times the best cost away from it.
pub const RATIO: f64 = 0.35;
/// The same test for a minimum on the farthest plane.
pub const FAR_END_RATIO: f64 = 0.8;
/// Planes on each side of the minimum excluded from the "away from it" cost.
pub const EXCLUSION_PLANES: usize = 3;
/// Least fraction of the planes a pixel must be scored on.
pub const MIN_SCORED_FRACTION: f64 = 0.5;
/// A warped window counts as covered when its summed alpha is within this of its size.
pub const ALPHA_TOLERANCE: f64 = 1e-3;
/// Lower and upper percentiles of the points' inverse depths taken as far and near.
pub const DEPTH_PERCENTILES: (f64, f64) = (0.02, 0.98);
/// Relative margin on the percentile inverse depths.
pub const REL_MARGIN: f64 = 0.2;
/// Margin, as a fraction of the percentile inverse-depth span, on each side.
pub const SPAN_MARGIN: f64 = 0.05;
/// Margin, in plane steps of the coarse sweep, on each side.
pub const STEP_MARGIN: f64 = 1.0;
/// Far is infinite when its inverse depth is at most this fraction of near's.
pub const INFINITE_FAR_FRACTION: f64 = 0.2;
/// Fewest matched points for bounds to be trusted.
pub const MIN_POINTS: usize = 50;
/// Most points kept as the scene's sparse points.
pub const MAX_POINTS: usize = 20_000;

/// Bounds estimated from the images, with the points they came from.
#[derive(Clone, Debug)]
pub struct AutoBounds {
    pub near: f64,
    /// May be `f64::INFINITY`.
    pub far: f64,
    /// World points within the bounds (at most [`MAX_POINTS`]).
    pub points: Vec<DVec3>,
    /// Pixels matched (before the bounds and subsampling).
    pub matched: usize,
    /// Reference views that were swept.
    pub references: usize,
}

/// A view at the coarse resolution.
struct Small {
    camera: Camera,
    image: RgbImage,
}

/// The matches of a sweep and its plane step in inverse depth.
type PassMatches = (Vec<Match>, f64);

/// One matched pixel: its inverse depth in its reference view and its ray.
struct Match {
    rho: f64,
    /// The reference camera's centre.
    centre: DVec3,
    /// From the centre to the ray's point at depth 1.
    dir: DVec3,
}

/// Estimates near/far and a sparse point cloud from the images of `views` (at file
/// resolution). `dir` names the scene in errors.
pub fn estimate(dir: &Path, views: &[View]) -> Result<AutoBounds> {
    let fail = |why: String| {
        Error::format(
            dir,
            format!("cannot find depth bounds: {why}; pass --near and --far"),
        )
    };
    if views.len() < 2 {
        return Err(fail("a single view has no parallax".into()));
    }
    let plan = plan_pairs(views);
    if plan.is_empty() {
        return Err(fail(
            "no two views look the same way from different places".into(),
        ));
    }
    let mut needed: Vec<usize> = plan
        .iter()
        .flat_map(|(r, ns)| std::iter::once(*r).chain(ns.iter().copied()))
        .collect();
    needed.sort_unstable();
    needed.dedup();
    let loaded: Vec<Small> = needed
        .par_iter()
        .map(|&i| load_small(&views[i]))
        .collect::<Result<_>>()?;
    let small: BTreeMap<usize, &Small> = needed.iter().copied().zip(loaded.iter()).collect();
    let pairs: Vec<(&Small, Vec<&Small>)> = plan
        .iter()
        .filter_map(|(r, ns)| {
            let neighbours: Vec<&Small> = ns.iter().filter_map(|n| small.get(n).copied()).collect();
            Some((*small.get(r)?, neighbours))
        })
        .collect();
    // Pass 1: a wide range per reference; pass 2: the planes again, over pass 1's bounds.
    let coarse: Vec<(Vec<Match>, f64)> = pairs
        .par_iter()
        .filter_map(|(r, ns)| {
            let rho_max = widest_inverse_depth(r, ns)?;
            match_reference(r, ns, rho_max, 0.0, COARSE_PLANES)
        })
        .collect();
    let (rho_near, rho_far, _) = bounds_of(coarse).map_err(fail)?;
    let fine: Vec<(Vec<Match>, f64)> = pairs
        .par_iter()
        .filter_map(|(r, ns)| match_reference(r, ns, rho_near, rho_far.max(0.0), FINE_PLANES))
        .collect();
    let (rho_near, rho_far, (matches, step)) = bounds_of(fine).map_err(fail)?;
    let near = 1.0 / rho_near;
    let far = if rho_far > 0.0 {
        1.0 / rho_far
    } else {
        f64::INFINITY
    };
    let rho_cap = 0.5 * step;
    let kept: Vec<DVec3> = matches
        .iter()
        .filter(|m| m.rho <= rho_near && m.rho >= rho_far)
        .filter_map(|m| {
            if m.rho > rho_cap {
                Some(m.at(1.0 / m.rho))
            } else {
                (far.is_infinite() && rho_cap > 0.0).then(|| m.at(1.0 / rho_cap))
            }
        })
        .collect();
    let stride = kept.len().div_ceil(MAX_POINTS).max(1);
    let points: Vec<DVec3> = kept.into_iter().step_by(stride).collect();
    Ok(AutoBounds {
        near,
        far,
        points,
        matched: matches.len(),
        references: plan.len(),
    })
}

/// Near and far inverse depths (far 0 for infinity) from the matches of every reference,
/// with the matches and the coarsest plane step; the reason when there are too few.
fn bounds_of(per_ref: Vec<PassMatches>) -> std::result::Result<(f64, f64, PassMatches), String> {
    let step = per_ref.iter().map(|(_, s)| *s).fold(0.0f64, f64::max);
    let matches: Vec<Match> = per_ref.into_iter().flat_map(|(m, _)| m).collect();
    if matches.len() < MIN_POINTS {
        return Err(format!(
            "only {} textured pixels matched between views (at least {MIN_POINTS} needed)",
            matches.len()
        ));
    }
    let mut rhos: Vec<f64> = matches.iter().map(|m| m.rho).collect();
    rhos.sort_by(f64::total_cmp);
    let q = |f: f64| rhos[((rhos.len() - 1) as f64 * f).round() as usize];
    let (lo, hi) = (q(DEPTH_PERCENTILES.0), q(DEPTH_PERCENTILES.1));
    let span = hi - lo;
    let rho_near = hi * (1.0 + REL_MARGIN) + SPAN_MARGIN * span + STEP_MARGIN * step;
    let rho_far = lo * (1.0 - REL_MARGIN) - SPAN_MARGIN * span - STEP_MARGIN * step;
    if !(rho_near > 0.0 && rho_near.is_finite()) {
        return Err(format!(
            "the {} matched pixels all lie at infinity",
            matches.len()
        ));
    }
    let rho_far = if rho_far <= INFINITE_FAR_FRACTION * rho_near {
        0.0
    } else {
        rho_far
    };
    Ok((rho_near, rho_far, (matches, step)))
}

/// The inverse depth that gives [`DISPARITY_FRACTION`] of the image width of disparity
/// between a reference and its nearest neighbour.
fn widest_inverse_depth(reference: &Small, neighbours: &[&Small]) -> Option<f64> {
    let cam = &reference.camera;
    let baseline = neighbours
        .iter()
        .map(|n| n.camera.pose.centre().distance(cam.pose.centre()))
        .fold(f64::INFINITY, f64::min);
    let rho_max = DISPARITY_FRACTION * cam.intrinsics.width as f64 / (cam.intrinsics.fx * baseline);
    (rho_max.is_finite() && rho_max > 0.0).then_some(rho_max)
}

impl Match {
    /// The world point at camera depth `depth` along this match's ray.
    fn at(&self, depth: f64) -> DVec3 {
        self.centre + self.dir * depth
    }
}

/// Reference views (evenly spaced) and their neighbours.
fn plan_pairs(views: &[View]) -> Vec<(usize, Vec<usize>)> {
    let n = views.len();
    let centres: Vec<DVec3> = views.iter().map(|v| v.camera.pose.centre()).collect();
    let axes: Vec<DVec3> = views
        .iter()
        .map(|v| v.camera.pose.rotation.transpose() * DVec3::Z)
        .collect();
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for c in &centres {
        lo = lo.min(*c);
        hi = hi.max(*c);
    }
    let min_baseline = MIN_BASELINE_FRACTION * (hi - lo).length();
    let cos_max = MAX_AXIS_ANGLE_DEG.to_radians().cos();
    let refs = AUTO_REFERENCES.min(n);
    let mut out = Vec::new();
    for k in 0..refs {
        let r = (k * n + n / 2) / refs;
        let r = r.min(n - 1);
        let mut cands: Vec<(f64, usize)> = (0..n)
            .filter(|&j| j != r)
            .map(|j| (centres[j].distance(centres[r]), j))
            .filter(|&(d, j)| d > min_baseline && d.is_finite() && axes[j].dot(axes[r]) >= cos_max)
            .collect();
        cands.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let ns: Vec<usize> = cands
            .into_iter()
            .take(AUTO_NEIGHBOURS)
            .map(|(_, j)| j)
            .collect();
        if !ns.is_empty() {
            out.push((r, ns));
        }
    }
    out
}

/// A view's image and camera at the coarse resolution.
fn load_small(v: &View) -> Result<Small> {
    let k = &v.camera.intrinsics;
    let mut image = RgbImage::load_expecting(&v.image_path, k.width, k.height)?;
    let mut levels = 0u32;
    while (k.width >> levels) > AUTO_MAX_WIDTH && (k.height >> (levels + 1)) > 0 {
        levels += 1;
    }
    for _ in 0..levels {
        image = image.downsample2();
    }
    let f = (1u32 << levels) as f64;
    Ok(Small {
        camera: v.camera.downscaled(f, image.width, image.height),
        image,
    })
}

fn grey(img: &RgbImage) -> Vec<f64> {
    img.data
        .chunks_exact(3)
        .map(|p| (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0)
        .collect()
}

/// Window sums of `v` (`w x h`) over `(2r+1)^2` windows, for pixels at least `r` from the
/// border (others 0).
fn box_sums(v: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    let mut integral = vec![0.0; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0.0;
        for x in 0..w {
            row += v[y * w + x];
            integral[(y + 1) * (w + 1) + x + 1] = integral[y * (w + 1) + x + 1] + row;
        }
    }
    let mut out = vec![0.0; w * h];
    if w <= 2 * r || h <= 2 * r {
        return out;
    }
    for y in r..h - r {
        for x in r..w - r {
            let (x0, x1, y0, y1) = (x - r, x + r + 1, y - r, y + r + 1);
            out[y * w + x] = integral[y1 * (w + 1) + x1]
                - integral[y0 * (w + 1) + x1]
                - integral[y1 * (w + 1) + x0]
                + integral[y0 * (w + 1) + x0];
        }
    }
    out
}

/// The matched pixels of one reference and the sweep's plane step in inverse depth;
/// `None` when the reference cannot be swept.
fn match_reference(
    reference: &Small,
    neighbours: &[&Small],
    rho_hi: f64,
    rho_lo: f64,
    planes: usize,
) -> Option<(Vec<Match>, f64)> {
    let cam = &reference.camera;
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let r = WINDOW_RADIUS;
    let d = planes;
    if neighbours.is_empty()
        || w <= 2 * r
        || h <= 2 * r
        || d < 2
        || rho_hi.partial_cmp(&rho_lo) != Some(std::cmp::Ordering::Greater)
    {
        return None;
    }
    let step = (rho_hi - rho_lo) / (d - 1) as f64;
    let rho_of = |z: f64| rho_hi - z * step;
    let hw = w * h;
    let windows = RefWindows::new(reference, (w, h));
    let region = Region::full(&cam.intrinsics);
    let mut cost_sum = vec![0.0f32; d * hw];
    let mut cost_n = vec![0u8; d * hw];
    let inv_depths: Vec<f64> = (0..d).map(|z| rho_of(z as f64)).collect();
    for nb in neighbours {
        let src = Source {
            camera: &nb.camera,
            image: &nb.image,
        };
        // One sweep over every plane: the reference's rays (lens distortion inverted
        // iteratively) are computed once.
        let volume = sweep(cam, region, &[src], &inv_depths);
        for (z, vol) in volume.chunks_exact(4 * hw).enumerate() {
            let costs = (&mut cost_sum[z * hw..][..hw], &mut cost_n[z * hw..][..hw]);
            windows.add_costs(vol, costs);
        }
    }
    let min_scored = (MIN_SCORED_FRACTION * d as f64).ceil() as usize;
    let mut out = Vec::new();
    let mut costs = vec![f64::NAN; d];
    for p in (0..hw).filter(|&p| windows.textured[p]) {
        let mut scored = 0;
        for z in 0..d {
            let n = cost_n[z * hw + p];
            // Planes are scored only where every neighbour covers the window, so that
            // costs from different neighbour sets are never compared.
            costs[z] = if n as usize == neighbours.len() {
                scored += 1;
                cost_sum[z * hw + p] as f64 / n as f64
            } else {
                f64::NAN
            };
        }
        if scored < min_scored {
            continue;
        }
        let Some(best) = pick(&costs) else {
            continue;
        };
        let rho = rho_of(best).max(0.0);
        let uv = DVec2::new((p % w) as f64 + 0.5, (p / w) as f64 + 0.5);
        let centre = cam.pose.centre();
        out.push(Match {
            rho,
            centre,
            dir: cam.unproject(uv, 1.0) - centre,
        });
    }
    Some((out, step))
}

/// The reference's matching windows (`2 WINDOW_RADIUS + 1` pixels square): grey values,
/// window sums and (unnormalised) variances, and which windows are textured enough to
/// match.
struct RefWindows {
    w: usize,
    h: usize,
    grey: Vec<f64>,
    sum: Vec<f64>,
    var: Vec<f64>,
    textured: Vec<bool>,
}

impl RefWindows {
    fn new(reference: &Small, (w, h): (usize, usize)) -> Self {
        let (r, hw) = (WINDOW_RADIUS, w * h);
        let nwin = ((2 * r + 1) * (2 * r + 1)) as f64;
        let g_ref = grey(&reference.image);
        let s_r = box_sums(&g_ref, w, h, r);
        let sq: Vec<f64> = g_ref.iter().map(|g| g * g).collect();
        let s_rr = box_sums(&sq, w, h, r);
        let var_r: Vec<f64> = (0..hw).map(|p| s_rr[p] - s_r[p] * s_r[p] / nwin).collect();
        let min_var = nwin * MIN_TEXTURE_STD * MIN_TEXTURE_STD;
        let textured: Vec<bool> = (0..hw).map(|p| var_r[p] >= min_var).collect();
        Self {
            w,
            h,
            grey: g_ref,
            sum: s_r,
            var: var_r,
            textured,
        }
    }

    /// Adds `1 - NCC` against one neighbour's swept plane `vol` (RGB planes, then alpha)
    /// to `(cost_sum, cost_n)` of every textured window the neighbour fully covers.
    fn add_costs(&self, vol: &[f32], (cost_sum, cost_n): (&mut [f32], &mut [u8])) {
        let (w, h, r) = (self.w, self.h, WINDOW_RADIUS);
        let hw = w * h;
        let nwin = ((2 * r + 1) * (2 * r + 1)) as f64;
        let (s_r, var_r) = (&self.sum, &self.var);
        let (rgb, alpha) = vol.split_at(3 * hw);
        let g: Vec<f64> = (0..hw)
            .map(|p| (rgb[p] as f64 + rgb[hw + p] as f64 + rgb[2 * hw + p] as f64) / 3.0)
            .collect();
        let a: Vec<f64> = alpha.iter().map(|&v| v as f64).collect();
        let s_a = box_sums(&a, w, h, r);
        let s_n = box_sums(&g, w, h, r);
        let gg: Vec<f64> = g.iter().map(|v| v * v).collect();
        let s_nn = box_sums(&gg, w, h, r);
        let rg: Vec<f64> = g.iter().zip(&self.grey).map(|(a, b)| a * b).collect();
        let s_rn = box_sums(&rg, w, h, r);
        for p in 0..hw {
            if !self.textured[p] || s_a[p] < nwin - ALPHA_TOLERANCE {
                continue;
            }
            let var_n = s_nn[p] - s_n[p] * s_n[p] / nwin;
            let cov = s_rn[p] - s_r[p] * s_n[p] / nwin;
            let denom = (var_r[p] * var_n).sqrt();
            let ncc = if var_n > 0.0 && denom > 0.0 {
                (cov / denom).clamp(-1.0, 1.0)
            } else {
                0.0
            };
            cost_sum[p] += (1.0 - ncc) as f32;
            cost_n[p] += 1;
        }
    }
}

/// The plane (fractional, refined by a parabola) of a pixel's distinct cost minimum, or
/// `None` when the minimum is not trusted.
fn pick(costs: &[f64]) -> Option<f64> {
    let d = costs.len();
    let (best, c_best) = costs
        .iter()
        .enumerate()
        .filter(|(_, c)| c.is_finite())
        .min_by(|a, b| a.1.total_cmp(b.1).then(a.0.cmp(&b.0)))?;
    let (best, c_best) = (best, *c_best);
    if best == 0 || c_best > MAX_COST {
        return None;
    }
    let c_away = costs
        .iter()
        .enumerate()
        .filter(|(z, c)| z.abs_diff(best) > EXCLUSION_PLANES && c.is_finite())
        .map(|(_, c)| *c)
        .fold(f64::INFINITY, f64::min);
    if best + 1 >= d {
        // The farthest plane: distant, smooth textures give broad minima there, and a far
        // bound too near costs more than one too far, so the test is weaker.
        return (c_away.is_finite() && c_best <= FAR_END_RATIO * c_away).then_some(best as f64);
    }
    if !(c_away.is_finite() && c_best <= RATIO * c_away) {
        return None;
    }
    let (a, b, c) = (costs[best - 1], c_best, costs[best + 1]);
    let curv = a - 2.0 * b + c;
    let offset = if a.is_finite() && c.is_finite() && curv > 0.0 {
        (0.5 * (a - c) / curv).clamp(-0.5, 0.5)
    } else {
        0.0
    };
    Some(best as f64 + offset)
}

#[cfg(test)]
#[path = "auto_tests.rs"]
mod tests;
