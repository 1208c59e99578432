//! Rolling-shutter cameras: every pixel is exposed at its own time, and the camera moves
//! between the start and the end of the readout.
//!
//! # Model
//! - Time `t` is a fraction of the camera's motion interval: at `t = 0` the camera has
//!   the pose [`RollingShutter::start`], at `t = 1` the pose [`RollingShutter::end`]
//!   (both world-to-camera, `p_cam = R p_world + t`). In between (and, for times outside
//!   `[0, 1]`, beyond) the camera centre moves linearly, `c(t) = c0 + t (c1 - c0)`, and
//!   the rotation spherically, `R(t) = exp(t [w]x) R0` with `exp([w]x) = R1 R0^T` (the
//!   shorter way round); this is instant-ngp's `camera_slerp` of the camera-to-world
//!   matrices, written for world-to-camera ones.
//! - The pixel at continuous pixel coordinate `(u, v)` (pixel centres at `i + 0.5`) is
//!   exposed at `t(u, v) = time_origin + time_per_pixel.x * u + time_per_pixel.y * v`.
//!
//! # instant-ngp's `rolling_shutter` (checked in its loader)
//! `src/nerf_loader.cu` (`read_lens`) reads `rolling_shutter` as `[A, B, C]` or
//! `[A, B, C, D]` (D = 0 when absent), from the top level and then, overriding, from
//! the frame; `include/neural-graphics-primitives/common_device.h`
//! (`get_xform_given_rolling_shutter`) gives a ray the time
//! `t = A + B * u + C * v + D * motionblur_time`, with `(u, v)` the pixel position divided
//! by the resolution (in `[0, 1]`) and `motionblur_time` uniform in `[0, 1]` (drawn per
//! ray: `D` is the exposure's extent, a motion blur), and interpolates the frame's
//! `transform_matrix_start` (default `transform_matrix`) and `transform_matrix_end`
//! (default the start) with `camera_slerp` at that `t`. `t` is not clamped. Older
//! instant-ngp versions interpolated the matrices linearly; the slerp is the current one.
//!
//! Here a frame's `(A, B, C, D)` becomes `time_origin = A + D / 2` (the middle of the
//! exposure: motion blur itself is not modelled), `time_per_pixel = (B / W, C / H)`, so
//! the time is a function of pixel coordinates and scales exactly with the image
//! ([`RollingShutter::downscaled`]).
//!
//! # Projection
//! A world point is seen at the time `t*` with `t(pi(t*)) = t*`, where `pi(t)` is its
//! pixel in the camera posed at `t`: [`RollingProjector::solve`] finds it by Newton's
//! method in f64 (analytic derivative, distortion included), starting at the time of the
//! image centre, with the iterate kept within the times of the image widened by
//! [`RS_WINDOW_MARGIN`] pixels. It stops when the point's pixel and the pixels exposed at
//! `t` are less than [`RS_ROW_TOL`] pixels apart (rows, for a vertical readout), and gives
//! up (no projection: alpha 0 in a sweep) after [`RS_MAX_ITERS`] evaluations, when the
//! iterate sticks at the window's edge (the point is not in the image), when the point is
//! not in front of the camera or beyond the monotonic range of the lens distortion at an
//! iterate, or when the derivative vanishes. A point that two rows see (the camera moves
//! with it) projects to the solution Newton reaches from the centre's time, which is
//! one of them.

use super::{Camera, Intrinsics, WorldToCamera};
use glam::{DMat3, DQuat, DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// Convergence tolerance of the projection, in pixels along the readout (rows for a
/// vertical readout): distance between the point's pixel and the pixels exposed at the
/// time it was taken at.
pub const RS_ROW_TOL: f64 = 1e-6;
/// Largest number of projections [`RollingProjector::solve`] evaluates before giving up.
pub const RS_MAX_ITERS: usize = 16;
/// The Newton iterate is kept within the times of pixels at most this far outside the
/// image (a point projecting further out is not sampled anyway).
pub const RS_WINDOW_MARGIN: f64 = 2.0;
/// Below this `|dF/dt|` (F the time residual) the Newton step is undefined: no projection.
const RS_MIN_SLOPE: f64 = 1e-12;
/// In front of the camera: `z > IN_FRONT_EPS * |p|` (as in the plane sweep).
const IN_FRONT_EPS: f64 = super::IN_FRONT_EPS;

/// A rolling shutter: the poses at the start (`t = 0`) and end (`t = 1`) of the motion
/// and the time of every pixel (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RollingShutter {
    /// World-to-camera pose at `t = 0`: `p_cam = R0 p_world + t0`.
    pub start: WorldToCamera,
    /// World-to-camera pose at `t = 1`: `p_cam = R1 p_world + t1`.
    pub end: WorldToCamera,
    /// Time of pixel coordinate `(0, 0)`.
    pub time_origin: f64,
    /// `(dt/du, dt/dv)` per pixel.
    pub time_per_pixel: DVec2,
}

impl RollingShutter {
    /// A shutter after checking that its times are finite.
    pub fn new_checked(
        start: WorldToCamera,
        end: WorldToCamera,
        time_origin: f64,
        time_per_pixel: DVec2,
    ) -> Result<Self, String> {
        if !time_origin.is_finite() || !time_per_pixel.is_finite() {
            return Err(format!(
                "non-finite rolling-shutter times (origin {time_origin}, per pixel {time_per_pixel:?})"
            ));
        }
        Ok(Self {
            start,
            end,
            time_origin,
            time_per_pixel,
        })
    }

    /// From instant-ngp's `rolling_shutter = [A, B, C, D]` for a `width x height` image
    /// (see the module docs): `time_origin = A + D / 2`, `time_per_pixel = (B/W, C/H)`.
    pub fn from_instant_ngp(
        start: WorldToCamera,
        end: WorldToCamera,
        abcd: [f64; 4],
        width: u32,
        height: u32,
    ) -> Result<Self, String> {
        if abcd.iter().any(|v| !v.is_finite()) {
            return Err(format!("non-finite 'rolling_shutter' {abcd:?}"));
        }
        let [a, b, c, d] = abcd;
        Self::new_checked(
            start,
            end,
            a + 0.5 * d,
            DVec2::new(b / width.max(1) as f64, c / height.max(1) as f64),
        )
    }

    /// instant-ngp's `[A, B, C, D]` of this shutter for a `width x height` image
    /// (`D = 0`: no motion blur).
    pub fn to_instant_ngp(&self, width: u32, height: u32) -> [f64; 4] {
        [
            self.time_origin,
            self.time_per_pixel.x * width as f64,
            self.time_per_pixel.y * height as f64,
            0.0,
        ]
    }

    /// Time of the pixel at coordinate `uv`.
    #[inline]
    pub fn time_at(&self, uv: DVec2) -> f64 {
        self.time_origin + self.time_per_pixel.dot(uv)
    }

    /// Whether pixels see different poses: distinct start and end poses and a readout
    /// that takes time. Otherwise the camera is a global shutter at one pose.
    pub fn is_moving(&self) -> bool {
        self.start != self.end && self.time_per_pixel != DVec2::ZERO
    }

    /// The pose at time `t` (exactly `start` when `start == end` or `t == 0`, exactly
    /// `end` when `t == 1`).
    pub fn pose_at(&self, t: f64) -> WorldToCamera {
        if self.start == self.end || t == 0.0 {
            return self.start;
        }
        if t == 1.0 {
            return self.end;
        }
        Motion::new(&self.start, &self.end).pose(t)
    }

    /// The same shutter for an image resampled by `1 / factor` (pixel coordinates divide
    /// by `factor`, so the time per pixel multiplies by it).
    pub fn downscaled(&self, factor: f64) -> Self {
        Self {
            time_per_pixel: self.time_per_pixel * factor,
            ..*self
        }
    }

    /// The range of times of the pixels of a `width x height` image widened by
    /// `margin` pixels on every side.
    pub fn time_range(&self, width: u32, height: u32, margin: f64) -> (f64, f64) {
        let (w, h) = (width as f64 + margin, height as f64 + margin);
        let corners = [
            DVec2::new(-margin, -margin),
            DVec2::new(w, -margin),
            DVec2::new(-margin, h),
            DVec2::new(w, h),
        ];
        corners
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &c| {
                let t = self.time_at(c);
                (lo.min(t), hi.max(t))
            })
    }
}

/// The camera's motion between two poses, prepared for many evaluations.
#[derive(Clone, Copy, Debug)]
pub struct Motion {
    r0: DMat3,
    /// Rotation vector `w` of `R1 R0^T` (camera axes), `|w| <= pi`.
    omega: DVec3,
    axis: DVec3,
    angle: f64,
    c0: DVec3,
    /// `c1 - c0`.
    dc: DVec3,
}

impl Motion {
    pub fn new(start: &WorldToCamera, end: &WorldToCamera) -> Self {
        let rel = end.rotation * start.rotation.transpose();
        let mut q = DQuat::from_mat3(&rel).normalize();
        if q.w < 0.0 {
            q = -q;
        }
        let v = DVec3::new(q.x, q.y, q.z);
        let s = v.length();
        // atan2 keeps small angles accurate (acos(w) loses half the digits near 1).
        let angle = 2.0 * s.atan2(q.w);
        let axis = if s > 0.0 { v / s } else { DVec3::X };
        let c0 = start.centre();
        Self {
            r0: start.rotation,
            omega: axis * angle,
            axis,
            angle,
            c0,
            dc: end.centre() - c0,
        }
    }

    /// World-to-camera rotation at time `t`.
    #[inline]
    pub fn rotation(&self, t: f64) -> DMat3 {
        if self.angle == 0.0 {
            self.r0
        } else {
            DMat3::from_axis_angle(self.axis, self.angle * t) * self.r0
        }
    }

    /// Camera centre at time `t`.
    #[inline]
    pub fn centre(&self, t: f64) -> DVec3 {
        self.c0 + self.dc * t
    }

    /// World-to-camera pose at time `t`.
    pub fn pose(&self, t: f64) -> WorldToCamera {
        let r = self.rotation(t);
        WorldToCamera {
            rotation: r,
            translation: -(r * self.centre(t)),
        }
    }
}

/// A projection found by [`RollingProjector::solve`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RollingHit {
    /// Pixel coordinate.
    pub uv: DVec2,
    /// Time at which the camera saw the point.
    pub time: f64,
    /// The point in the camera's coordinates at that time (homogeneous: scaled by the
    /// point's `w`, see [`RollingProjector::solve`]).
    pub cam: DVec3,
    /// Projections evaluated.
    pub iterations: usize,
}

/// Projects points into a moving rolling-shutter camera (see the module docs).
#[derive(Clone, Copy, Debug)]
pub struct RollingProjector<'a> {
    intr: &'a Intrinsics,
    motion: Motion,
    time_origin: f64,
    grad: DVec2,
    /// `|grad|`, to turn time residuals into pixels.
    grad_len: f64,
    t_lo: f64,
    t_hi: f64,
    t_start: f64,
    max_r2: f64,
}

impl<'a> RollingProjector<'a> {
    /// The projector of `camera`, or `None` when its shutter does not move (project with
    /// its `pose` instead).
    pub fn new(camera: &'a Camera) -> Option<Self> {
        let rs = camera.moving_shutter()?;
        let k = &camera.intrinsics;
        let (t_lo, t_hi) = rs.time_range(k.width, k.height, RS_WINDOW_MARGIN);
        let centre = DVec2::new(0.5 * k.width as f64, 0.5 * k.height as f64);
        Some(Self {
            intr: k,
            motion: Motion::new(&rs.start, &rs.end),
            time_origin: rs.time_origin,
            grad: rs.time_per_pixel,
            grad_len: rs.time_per_pixel.length(),
            t_lo,
            t_hi,
            t_start: rs.time_at(centre),
            max_r2: k.distortion.map_or(f64::INFINITY, |d| d.max_radius2()),
        })
    }

    /// Projects the homogeneous world point `(p, w)`: the point `p / w` for `w > 0`, the
    /// direction `p` (a point at infinity) for `w = 0`. In camera coordinates at time `t`
    /// it is `q(t) = R(t) (p - w c(t))`. `None` when there is no defined projection (see
    /// the module docs).
    pub fn solve(&self, p: DVec3, w: f64) -> Option<RollingHit> {
        let k = self.intr;
        let eps2 = IN_FRONT_EPS * IN_FRONT_EPS;
        let tol = RS_ROW_TOL * self.grad_len;
        let mut t = self.t_start;
        let mut stuck = 0usize;
        for it in 1..=RS_MAX_ITERS {
            let r = self.motion.rotation(t);
            let q = r * (p - self.motion.centre(t) * w);
            if !(q.z > 0.0 && q.z * q.z > eps2 * q.length_squared()) {
                return None;
            }
            let inv_z = 1.0 / q.z;
            let n = DVec2::new(q.x * inv_z, q.y * inv_z);
            if n.length_squared() >= self.max_r2 {
                return None;
            }
            let uv = k.project_normalized(n);
            let residual = self.time_origin + self.grad.dot(uv) - t;
            if residual.abs() <= tol {
                return Some(RollingHit {
                    uv,
                    time: t,
                    cam: q,
                    iterations: it,
                });
            }
            // dq/dt = w x q - w R(t) (c1 - c0); dn/dt from the quotient rule.
            let dq = self.motion.omega.cross(q) - r * self.motion.dc * w;
            let dn = DVec2::new(dq.x - n.x * dq.z, dq.y - n.y * dq.z) * inv_z;
            let dn_d = match &k.distortion {
                Some(d) => d.jacobian(n) * dn,
                None => dn,
            };
            let duv = DVec2::new(k.fx * dn_d.x, k.fy * dn_d.y);
            let slope = self.grad.dot(duv) - 1.0;
            // Also rejects a NaN slope.
            if slope.abs().partial_cmp(&RS_MIN_SLOPE) != Some(std::cmp::Ordering::Greater) {
                return None;
            }
            let next = (t - residual / slope).clamp(self.t_lo, self.t_hi);
            if !next.is_finite() {
                return None;
            }
            // Pinned at the window's edge twice running: the solution is outside it.
            stuck = if next == t && (next == self.t_lo || next == self.t_hi) {
                stuck + 1
            } else {
                0
            };
            if stuck >= 2 {
                return None;
            }
            t = next;
        }
        None
    }
}

impl Camera {
    /// A global-shutter camera.
    pub fn global(intrinsics: Intrinsics, pose: WorldToCamera) -> Self {
        Self {
            intrinsics,
            pose,
            rolling_shutter: None,
        }
    }

    /// A rolling-shutter camera; its `pose` (what shutter-unaware code uses) is the pose
    /// at the time of the image centre, and exactly `shutter.start` when the start and end
    /// poses are equal.
    pub fn rolling(intrinsics: Intrinsics, shutter: RollingShutter) -> Self {
        let centre = DVec2::new(
            0.5 * intrinsics.width as f64,
            0.5 * intrinsics.height as f64,
        );
        Self {
            intrinsics,
            pose: shutter.pose_at(shutter.time_at(centre)),
            rolling_shutter: Some(shutter),
        }
    }

    /// The shutter when pixels see different poses (see [`RollingShutter::is_moving`]).
    pub fn moving_shutter(&self) -> Option<&RollingShutter> {
        self.rolling_shutter.as_ref().filter(|s| s.is_moving())
    }

    /// The same camera with its rolling shutter ignored: a global shutter at `pose`.
    pub fn without_rolling_shutter(&self) -> Self {
        Self {
            rolling_shutter: None,
            ..*self
        }
    }

    /// The pose of the pixel at coordinate `uv` (`pose` for a global shutter).
    pub fn pose_at_pixel(&self, uv: DVec2) -> WorldToCamera {
        match self.moving_shutter() {
            Some(rs) => rs.pose_at(rs.time_at(uv)),
            None => self.pose,
        }
    }

    /// Projects a world point to a pixel coordinate and its depth (camera z at the time
    /// the point was seen), rolling shutter included; `None` where
    /// [`RollingProjector::solve`] finds no projection. A global-shutter camera gives
    /// [`Camera::project`]'s result when the point is in front of it.
    pub fn project_rolling(&self, p_world: DVec3) -> Option<(DVec2, f64)> {
        match RollingProjector::new(self) {
            Some(proj) => proj.solve(p_world, 1.0).map(|h| (h.uv, h.cam.z)),
            None => {
                let (uv, z) = self.project(p_world);
                (z > 0.0).then_some((uv, z))
            }
        }
    }
}

#[cfg(test)]
mod tests;
