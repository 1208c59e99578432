//! The planes a target can need at all, from the scene's sparse points or per-view bounds.

use crate::camera::Camera;
use crate::camera::IN_FRONT_EPS;
use crate::geometry::{apply_h, plane_homography};
use glam::{DMat3, DVec2, DVec3};

/// Fewest points a point set needs to be treated as a cloud (in-frustum filtering);
/// smaller sets (such as the 8 corners of a bounding box) bound the scene as a hull.
pub const MIN_CLOUD_POINTS: usize = 16;
/// Quantiles of the in-frustum point depths taken as the target's depth range.
pub const POINT_QUANTILES: (f64, f64) = (0.005, 0.995);
/// Relative margin on the target's point depth range (near x (1 - m), far x (1 + m)).
pub const POINT_MARGIN: f64 = 0.1;

/// The planes (`first..=last` of `inv_depths`, which decrease) that the scene's sparse
/// `points` seen by `target` need: the planes between the nearest and farthest point
/// depths (robust quantiles, widened by [`POINT_MARGIN`]), plus the plane just outside
/// on each side. Fewer than [`MIN_CLOUD_POINTS`] points are taken as a hull: every point
/// in front of the camera counts, in view or not. `None` when the points say nothing.
pub fn plane_range_from_points(
    target: &Camera,
    points: &[DVec3],
    inv_depths: &[f64],
) -> Option<(usize, usize)> {
    let d = inv_depths.len();
    if d == 0 || points.is_empty() {
        return None;
    }
    let cloud = points.len() >= MIN_CLOUD_POINTS;
    let (w, h) = (
        target.intrinsics.width as f64,
        target.intrinsics.height as f64,
    );
    let mut depths: Vec<f64> = points
        .iter()
        .filter_map(|&p| {
            let pc = target.pose.transform_point(p);
            if !(pc.z > 0.0 && pc.z.is_finite()) {
                return None;
            }
            if cloud {
                let (uv, _) = target.project(p);
                if !(uv.x >= 0.0 && uv.y >= 0.0 && uv.x < w && uv.y < h) {
                    return None;
                }
            }
            Some(pc.z)
        })
        .collect();
    if depths.len() < if cloud { 8 } else { 2 } {
        return None;
    }
    depths.sort_by(f64::total_cmp);
    let q = |f: f64| depths[((depths.len() - 1) as f64 * f).round() as usize];
    let (lo, hi) = if cloud {
        (q(POINT_QUANTILES.0), q(POINT_QUANTILES.1))
    } else {
        (depths[0], depths[depths.len() - 1])
    };
    planes_between(
        lo * (1.0 - POINT_MARGIN),
        hi * (1.0 + POINT_MARGIN),
        inv_depths,
    )
}

/// Relative margin on the sources' bounds (LLFF's near bound is a low percentile of
/// the sparse points' depths, not their minimum).
pub const BOUNDS_MARGIN: f64 = 0.1;

/// The planes the per-view depth bounds of the sources (LLFF's `poses_bounds.npy`) allow:
/// between the least near and the largest far of the sources, widened by
/// [`BOUNDS_MARGIN`], plus the plane just outside on each side. The sources' bounds stand for the target's, which holds for sources near
/// the target (the target's own bounds are not used: a held-out view's bounds come from
/// its own photograph). `None` when a source has no bounds.
pub fn plane_range_from_bounds(
    bounds: &[Option<(f64, f64)>],
    inv_depths: &[f64],
) -> Option<(usize, usize)> {
    if bounds.is_empty() || inv_depths.is_empty() {
        return None;
    }
    let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
    for b in bounds {
        let (n, f) = (*b)?;
        if !(n > 0.0 && f > n) {
            return None;
        }
        lo = lo.min(n);
        hi = hi.max(f);
    }
    planes_between(
        lo * (1.0 - BOUNDS_MARGIN),
        hi * (1.0 + BOUNDS_MARGIN),
        inv_depths,
    )
}

/// The planes (of decreasing `inv_depths`) with depths in `[near, far]`, plus the plane
/// just outside on each side.
fn planes_between(near: f64, far: f64, inv_depths: &[f64]) -> Option<(usize, usize)> {
    let d = inv_depths.len();
    let (rho_hi, rho_lo) = (1.0 / near, 1.0 / far);
    let first = inv_depths
        .iter()
        .position(|&r| r <= rho_hi)
        .unwrap_or(d - 1)
        .saturating_sub(1);
    let last = inv_depths
        .iter()
        .rposition(|&r| r >= rho_lo)
        .map_or(0, |z| (z + 1).min(d - 1));
    (first <= last).then_some((first, last))
}

/// As many planes as `inv_depths` (which decrease) spread uniformly in inverse depth over
/// `first..=last` of them, from `inv_depths[first]` to `inv_depths[last]`: the planes of a
/// range from [`plane_range_from_points`] or [`plane_range_from_bounds`] resampled as
/// finely as the whole grid was, so the depths a camera sees get every plane. With
/// `D = inv_depths.len() >= 2`, plane `i` is
/// `rho_i = rho_first + (rho_last - rho_first) i / (D - 1)`; one plane, or a range that
/// is not one (`first > last`, out of bounds), leaves `inv_depths` as they are.
pub fn span_planes(inv_depths: &[f64], (first, last): (usize, usize)) -> Vec<f64> {
    let d = inv_depths.len();
    if d < 2 || first > last || last >= d {
        return inv_depths.to_vec();
    }
    let (a, b) = (inv_depths[first], inv_depths[last]);
    (0..d)
        .map(|i| match i {
            0 => a,
            i if i == d - 1 => b,
            i => a + (b - a) * i as f64 / (d - 1) as f64,
        })
        .collect()
}

/// Target pixels sampled per image side when measuring plane steps.
const STEP_SAMPLES: usize = 5;

/// The largest shift, in source pixels, that any sampled target pixel's image in any
/// source makes between two consecutive planes of `inv_depths` (the disparity step of
/// the plane grid). Samples behind a source are skipped; 0 when none is seen.
pub fn max_plane_step(target: &Camera, sources: &[&Camera], inv_depths: &[f64]) -> f64 {
    let (w, h) = (
        target.intrinsics.width as f64,
        target.intrinsics.height as f64,
    );
    let mut best = 0.0f64;
    for s in sources {
        let rel = target.pose.relative_to(&s.pose);
        let homs: Vec<DMat3> = inv_depths
            .iter()
            .map(|&r| plane_homography(&rel, r))
            .collect();
        for j in 0..STEP_SAMPLES {
            for i in 0..STEP_SAMPLES {
                let uv = DVec2::new(
                    w * (i as f64 + 0.5) / STEP_SAMPLES as f64,
                    h * (j as f64 + 0.5) / STEP_SAMPLES as f64,
                );
                let n = target.intrinsics.unproject_pixel(uv);
                let mut prev: Option<DVec2> = None;
                for hm in &homs {
                    let q = apply_h(hm, n.x, n.y);
                    let p = (q.z > IN_FRONT_EPS * q.length()).then(|| {
                        s.intrinsics
                            .project_normalized(DVec2::new(q.x / q.z, q.y / q.z))
                    });
                    if let (Some(a), Some(b)) = (prev, p) {
                        let d = a.distance(b);
                        if d.is_finite() {
                            best = best.max(d);
                        }
                    }
                    prev = p;
                }
            }
        }
    }
    best
}

/// The fewest planes [`thin_planes`] thins to, for a model of `model_planes` planes,
/// where their disparity step exceeds [`SUBPIXEL_STEP`]: three quarters of them (and
/// below the model's own count only within [`FINE_STEP`]).
pub fn thin_floor(model_planes: usize) -> usize {
    (3 * model_planes).div_ceil(4).max(1)
}

/// Disparity step, in pixels, below which planes add nothing the image can show:
/// [`thin_planes`] thins planes closer than this regardless of how many remain.
pub const SUBPIXEL_STEP: f64 = 1.0;

/// Disparity step, in pixels, within which [`thin_planes`] may run fewer planes than the
/// model's own count (down to [`thin_floor`]). Measured with the embedded model
/// (docs/performance.md): 32 planes thinned to 24 with neighbours 2 pixels apart or less
/// lost nothing (procedural scenes, ethiopianHead), while 3-8 pixels apart lost up to
/// 5.7 dB on a view of templeRing from 2 sources.
pub const FINE_STEP: f64 = 2.0;

/// The planes a scene with a small disparity range needs: `n` of the `d` planes spread
/// evenly over the grid, the first and the last among them (plane `round(i (d - 1) / (n -
/// 1))` for `i` in `0..n`, so neighbours are at most `ceil((d - 1) / (n - 1))` grid steps
/// apart). `n` is the fewest that keep the disparity step (`step_px` per grid step) within
/// `max_step_px`, but no fewer than `model_planes` (the model's own count: the spacing it
/// was trained at), or than [`thin_floor`] while the step stays within [`FINE_STEP`], or
/// than keep the step within [`SUBPIXEL_STEP`]. All planes when `max_step_px` is 0 or the
/// step is unknown.
pub fn thin_planes(d: usize, step_px: f64, max_step_px: f64, model_planes: usize) -> Vec<usize> {
    if !(max_step_px > 0.0 && step_px > 0.0 && step_px.is_finite()) || d < 2 {
        return (0..d).collect();
    }
    // Fewest planes whose neighbours are at most `limit` pixels apart (all when one grid
    // step is already more).
    let planes_for = |limit: f64| -> usize {
        let k = (limit / step_px).floor();
        if k < 1.0 {
            d
        } else {
            (d - 1).div_ceil((k as usize).min(d - 1)) + 1
        }
    };
    let fine = planes_for(FINE_STEP).max(thin_floor(model_planes));
    let lower = model_planes.min(fine).min(planes_for(SUBPIXEL_STEP));
    let n = planes_for(max_step_px).max(lower).clamp(2, d);
    if n == d {
        return (0..d).collect();
    }
    let span = (d - 1) as f64 / (n - 1) as f64;
    (0..n).map(|i| (i as f64 * span).round() as usize).collect()
}
