//! The plane sweep with rolling-shutter cameras (see [`crate::camera::rolling`]).
//!
//! A slice whose target and source both have one pose per image keeps the homography
//! path of [`super::sweep_into`] (bit for bit). Otherwise every target pixel is a world
//! ray from the target's pose at that pixel's time (a rolling-shutter target renders each
//! row at its own pose), the plane at inverse depth `rho` is `z = 1 / rho` in that pose's
//! camera frame, and the plane point is projected into the source with
//! [`RollingProjector::solve`] (or with the source's single pose). No projection gives
//! RGBA = 0, as a point behind a camera does.

use super::{sample_bilinear, target_rays, Region, Source, IN_FRONT_EPS};
use crate::camera::rolling::RollingProjector;
use crate::camera::Camera;
use glam::{DVec2, DVec3};

/// World rays of the region's pixel centres: `(origin, direction)`, the direction being
/// `R^T (x, y, 1)` in the pose of the pixel's time, so the point at camera depth `z` is
/// `origin + z * direction`.
pub fn target_world_rays(target: &Camera, region: Region) -> Vec<(DVec3, DVec3)> {
    let rays = target_rays(&target.intrinsics, region);
    let fixed = target
        .moving_shutter()
        .is_none()
        .then(|| target.pose.inverse());
    rays.iter()
        .enumerate()
        .map(|(i, n)| {
            let c2w = match fixed {
                Some(p) => p,
                None => {
                    let uv = DVec2::new(
                        (region.x0 + (i % region.width) as i64) as f64 + 0.5,
                        (region.y0 + (i / region.width) as i64) as f64 + 0.5,
                    );
                    target.pose_at_pixel(uv).inverse()
                }
            };
            (c2w.translation, c2w.rotation * DVec3::new(n.x, n.y, 1.0))
        })
        .collect()
}

/// Warps one source at one plane into `out` (`[4, h, w]`) through per-pixel projection.
pub(super) fn rolling_slice(world: &[(DVec3, DVec3)], rho: f64, src: &Source<'_>, out: &mut [f32]) {
    let hw = world.len();
    project_rolling(world, rho, src.camera, |i, uv| {
        let rgba = uv.map_or([0.0; 4], |uv| sample_bilinear(src.image, uv.x, uv.y));
        for (ch, val) in rgba.into_iter().enumerate() {
            out[ch * hw + i] = val;
        }
    });
}

/// Calls `each(i, uv)` for every world ray `world[i]` with the pixel coordinate `uv` in
/// `cam` of its point on the plane at inverse depth `rho`, or `None` where there is no
/// projection (behind the camera, beyond the distortion's monotonic range, or no
/// rolling-shutter solution).
pub(crate) fn project_rolling(
    world: &[(DVec3, DVec3)],
    rho: f64,
    cam: &Camera,
    mut each: impl FnMut(usize, Option<DVec2>),
) {
    let intr = &cam.intrinsics;
    let projector = RollingProjector::new(cam);
    let (r, c) = (cam.pose.rotation, cam.pose.centre());
    let max_r2 = intr.distortion.map_or(f64::INFINITY, |d| d.max_radius2());
    let eps2 = IN_FRONT_EPS * IN_FRONT_EPS;
    for (i, (origin, dir)) in world.iter().enumerate() {
        // The plane point origin + dir / rho, homogeneous with weight rho.
        let p = *dir + *origin * rho;
        let uv = match &projector {
            Some(proj) => proj.solve(p, rho).map(|h| h.uv),
            None => {
                let q = r * (p - c * rho);
                if q.z > 0.0 && q.z * q.z > eps2 * q.length_squared() {
                    let n = DVec2::new(q.x / q.z, q.y / q.z);
                    (n.length_squared() < max_r2).then(|| intr.project_normalized(n))
                } else {
                    None
                }
            }
        };
        each(i, uv);
    }
}
