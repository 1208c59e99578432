//! Choosing source views by what they see of the target, not only by distance.

use crate::camera::Camera;
use crate::geometry::{apply_h, inverse_depths, plane_homography};
use glam::DVec2;
use serde::Serialize;

/// Views that see less than this fraction of the target frustum are not useful sources.
pub const MIN_VIEW_COVERAGE: f64 = 0.2;
/// Target pixels per side of the grid of rays [`view_coverage`] projects.
const GRID: usize = 8;
/// Depths (uniform in inverse depth between near and far) of the projected rays.
const DEPTHS: usize = 4;

/// A candidate source and how it ranks.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ViewRank {
    pub index: usize,
    /// Distance between the camera centres.
    pub distance: f64,
    /// Fraction of the target frustum (between near and far) the view sees.
    pub coverage: f64,
}

/// Fraction of a grid of target rays, at a few depths between `near` and `far` (may be
/// infinite), that land inside `source`'s image in front of it.
pub fn view_coverage(target: &Camera, source: &Camera, near: f64, far: f64) -> f64 {
    let rel = target.pose.relative_to(&source.pose);
    let (tw, th) = (
        target.intrinsics.width as f64,
        target.intrinsics.height as f64,
    );
    let (sw, sh) = (
        source.intrinsics.width as f64,
        source.intrinsics.height as f64,
    );
    let mut seen = 0usize;
    let inv = inverse_depths(near, far, DEPTHS);
    for &rho in &inv {
        let h = plane_homography(&rel, rho);
        for j in 0..GRID {
            for i in 0..GRID {
                let uv = DVec2::new(
                    (i as f64 + 0.5) * tw / GRID as f64,
                    (j as f64 + 0.5) * th / GRID as f64,
                );
                let n = target.intrinsics.unproject_pixel(uv);
                let q = apply_h(&h, n.x, n.y);
                if q.z > 1e-9 * q.length() {
                    let p = source
                        .intrinsics
                        .project_normalized(DVec2::new(q.x / q.z, q.y / q.z));
                    if p.x >= 0.0 && p.y >= 0.0 && p.x < sw && p.y < sh {
                        seen += 1;
                    }
                }
            }
        }
    }
    seen as f64 / (GRID * GRID * inv.len()) as f64
}

/// The `k` sources for `target` among `cameras` (`exclude`: the target's own index):
/// views that see at least [`MIN_VIEW_COVERAGE`] of the target frustum, ranked by their
/// distance divided by their coverage (a view that sees half the frustum counts as twice
/// as far); when fewer than `k` such views exist, the nearest of the others fill in.
/// Returned nearest first (the order the unpruned renderer and the trainer use), with
/// every candidate's rank for reports.
pub fn rank_views(
    cameras: &[Camera],
    target: &Camera,
    k: usize,
    exclude: Option<usize>,
    near: f64,
    far: f64,
) -> (Vec<usize>, Vec<ViewRank>) {
    let c = target.pose.centre();
    let mut ranks: Vec<ViewRank> = cameras
        .iter()
        .enumerate()
        .filter(|(i, _)| Some(*i) != exclude)
        .map(|(index, cam)| ViewRank {
            index,
            distance: cam.pose.centre().distance(c),
            coverage: view_coverage(target, cam, near, far),
        })
        .collect();
    ranks.sort_by(|a, b| {
        a.distance
            .total_cmp(&b.distance)
            .then(a.index.cmp(&b.index))
    });
    let key = |r: &ViewRank| r.distance / r.coverage.max(1e-9);
    let mut useful: Vec<&ViewRank> = ranks
        .iter()
        .filter(|r| r.coverage >= MIN_VIEW_COVERAGE)
        .collect();
    useful.sort_by(|a, b| key(a).total_cmp(&key(b)).then(a.index.cmp(&b.index)));
    let mut chosen: Vec<&ViewRank> = useful.into_iter().take(k).collect();
    for r in &ranks {
        if chosen.len() >= k {
            break;
        }
        if !chosen.iter().any(|c| c.index == r.index) {
            chosen.push(r);
        }
    }
    chosen.sort_by(|a, b| {
        a.distance
            .total_cmp(&b.distance)
            .then(a.index.cmp(&b.index))
    });
    (chosen.iter().map(|r| r.index).collect(), ranks)
}
