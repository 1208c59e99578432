//! Pinhole cameras and rigid poses, in f64.
//!
//! # Conventions (stated once, used everywhere)
//! - Camera axes are OpenCV's: x right, y down, z forward. Every reader converts its
//!   file's convention into this one; nothing downstream converts again.
//! - Pixel `(i, j)` (column `i`, row `j`) covers `[i, i+1) x [j, j+1)`; its centre is
//!   `(i + 0.5, j + 0.5)`. A pixel coordinate `u` therefore scales exactly with the image:
//!   at a level downsampled by `s`, the same point has coordinate `u / s`.
//! - Intrinsics map normalized camera coordinates to pixels: `u = fx * x + cx`,
//!   `v = fy * y + cy`, with `(x, y) = (X / Z, Y / Z)` after distortion.
//! - Distortion (OpenCV radial-tangential k1, k2, p1, p2) is modelled in projection, not
//!   removed from the images: [`Intrinsics::project_normalized`] applies it and
//!   [`Intrinsics::unproject_pixel`] inverts it iteratively.

pub mod rolling;

pub use rolling::{RollingShutter, RS_MAX_ITERS, RS_ROW_TOL};

use crate::imageio::MAX_IMAGE_SIDE;
use glam::{DMat2, DMat3, DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// Largest tolerated deviation of `R^T R` from identity before a pose is rejected.
pub const ROTATION_TOLERANCE: f64 = 1e-3;
/// Fixed-point iterations used to invert lens distortion.
const UNDISTORT_ITERATIONS: usize = 20;
/// A plane point counts as in front of a source camera when its homogeneous `z`
/// exceeds this fraction of its length (the ray is not behind or exactly sideways).
pub const IN_FRONT_EPS: f64 = 1e-9;
/// Smallest focal length, in units of the image's larger side: a field of view of about
/// 178 degrees across it (a pinhole model means nothing wider).
pub const MIN_FOCAL_RATIO: f64 = 0.01;
/// Largest focal length, in units of the image's larger side: a field of view of about
/// 0.06 degrees (beyond any lens; `fl_x = 1e300` is a corrupt file, not a telescope).
pub const MAX_FOCAL_RATIO: f64 = 1000.0;
/// How far outside the image the principal point may lie, in image sizes.
pub const MAX_CENTRE_OFFSET: f64 = 10.0;

/// OpenCV radial-tangential distortion of normalized coordinates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
}

impl Distortion {
    /// Distorts ideal normalized coordinates `(x, y)`.
    #[inline]
    pub fn apply(&self, p: DVec2) -> DVec2 {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * self.k2);
        DVec2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// The Jacobian `d apply(p) / d p` (columns: derivatives by `x` and by `y`).
    pub fn jacobian(&self, p: DVec2) -> DMat2 {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * self.k2);
        // d radial / d r2, times 2 for d r2 / dx = 2x.
        let dr = 2.0 * (self.k1 + 2.0 * self.k2 * r2);
        let (drx, dry) = (dr * x, dr * y);
        DMat2::from_cols(
            DVec2::new(
                radial + x * drx + 2.0 * self.p1 * y + 6.0 * self.p2 * x,
                y * drx + 2.0 * self.p1 * x + 2.0 * self.p2 * y,
            ),
            DVec2::new(
                x * dry + 2.0 * self.p1 * x + 2.0 * self.p2 * y,
                radial + y * dry + 6.0 * self.p1 * y + 2.0 * self.p2 * x,
            ),
        )
    }

    /// Inverts [`Distortion::apply`] by fixed-point iteration (exact for zero distortion).
    pub fn remove(&self, distorted: DVec2) -> DVec2 {
        let mut p = distorted;
        for _ in 0..UNDISTORT_ITERATIONS {
            let err = self.apply(p) - distorted;
            p -= err;
        }
        p
    }

    pub fn is_zero(&self) -> bool {
        self.k1 == 0.0 && self.k2 == 0.0 && self.p1 == 0.0 && self.p2 == 0.0
    }

    /// The largest `r^2 = x^2 + y^2` of ideal normalized coordinates up to which the
    /// radial part `r (1 + k1 r^2 + k2 r^4)` still grows with `r` (`f64::INFINITY` when it
    /// always does): the first positive root of `1 + 3 k1 s + 5 k2 s^2`. Beyond it the
    /// polynomial folds back, so a point there would be drawn onto pixels that belong to
    /// nearer rays; such points are treated as outside the image. (The small tangential
    /// terms are not included.)
    pub fn max_radius2(&self) -> f64 {
        let (a, b) = (5.0 * self.k2, 3.0 * self.k1);
        let roots = if a == 0.0 {
            [-1.0 / b, f64::NAN]
        } else {
            let disc = b * b - 4.0 * a;
            if disc < 0.0 {
                return f64::INFINITY;
            }
            // Stable quadratic roots of a s^2 + b s + 1 = 0.
            let q = -0.5 * (b + disc.sqrt().copysign(b));
            [q / a, 1.0 / q]
        };
        roots
            .into_iter()
            .filter(|s| s.is_finite() && *s > 0.0)
            .fold(f64::INFINITY, f64::min)
    }
}

/// Pinhole intrinsics of an image of `width x height` pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    /// `None` for an ideal pinhole.
    pub distortion: Option<Distortion>,
}

impl Intrinsics {
    pub fn pinhole(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32) -> Self {
        Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            distortion: None,
        }
    }

    /// The same camera for an image resampled by `1 / factor` (pixel centres follow the
    /// `[i, i+1)` convention, so all four parameters divide by `factor`).
    pub fn downscaled(&self, factor: f64, width: u32, height: u32) -> Self {
        Self {
            fx: self.fx / factor,
            fy: self.fy / factor,
            cx: self.cx / factor,
            cy: self.cy / factor,
            width,
            height,
            distortion: self.distortion,
        }
    }

    /// The image's `(width, height)` in pixels.
    pub fn size(&self) -> (usize, usize) {
        (self.width as usize, self.height as usize)
    }

    /// `K` as a matrix (ignores distortion).
    pub fn k(&self) -> DMat3 {
        DMat3::from_cols(
            DVec3::new(self.fx, 0.0, 0.0),
            DVec3::new(0.0, self.fy, 0.0),
            DVec3::new(self.cx, self.cy, 1.0),
        )
    }

    /// Pixel of ideal (undistorted) normalized coordinates, applying distortion if any.
    #[inline]
    pub fn project_normalized(&self, p: DVec2) -> DVec2 {
        let d = match &self.distortion {
            Some(d) => d.apply(p),
            None => p,
        };
        DVec2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy)
    }

    /// Ideal normalized coordinates `(X/Z, Y/Z)` of the ray through pixel coordinate `uv`.
    #[inline]
    pub fn unproject_pixel(&self, uv: DVec2) -> DVec2 {
        let d = DVec2::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy);
        match &self.distortion {
            Some(dist) => dist.remove(d),
            None => d,
        }
    }

    /// Checks that every parameter is finite and the focal lengths and size are positive.
    pub fn validate(&self) -> Result<(), String> {
        let all = [self.fx, self.fy, self.cx, self.cy];
        if all.iter().any(|v| !v.is_finite()) {
            return Err(format!("non-finite intrinsics {all:?}"));
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(format!(
                "focal lengths must be positive, got fx={} fy={}",
                self.fx, self.fy
            ));
        }
        if self.width == 0
            || self.height == 0
            || self.width > MAX_IMAGE_SIDE
            || self.height > MAX_IMAGE_SIDE
        {
            return Err(format!(
                "unsupported image size {}x{} (each side must be 1 to {MAX_IMAGE_SIDE})",
                self.width, self.height
            ));
        }
        let side = self.width.max(self.height).max(1) as f64;
        for f in [self.fx, self.fy] {
            let ratio = f / side;
            if !(MIN_FOCAL_RATIO..=MAX_FOCAL_RATIO).contains(&ratio) {
                // Plain digits for a plausible focal length, an exponent for an absurd one.
                let f = match f.abs() < 1e7 {
                    true => f.to_string(),
                    false => format!("{f:e}"),
                };
                return Err(format!(
                    "focal length {f} is {:.3e} times the image's larger side ({side} px); \
                     a camera's must be {MIN_FOCAL_RATIO} to {MAX_FOCAL_RATIO} times it \
                     (a field of view between about 0.06 and 178 degrees)",
                    ratio
                ));
            }
        }
        let (w, h) = (self.width as f64, self.height as f64);
        let far_off =
            |c: f64, s: f64| c < -MAX_CENTRE_OFFSET * s || c > (1.0 + MAX_CENTRE_OFFSET) * s;
        if far_off(self.cx, w) || far_off(self.cy, h) {
            return Err(format!(
                "principal point ({}, {}) lies more than {MAX_CENTRE_OFFSET} image sizes outside the {}x{} image",
                self.cx, self.cy, self.width, self.height
            ));
        }
        if let Some(d) = &self.distortion {
            if [d.k1, d.k2, d.p1, d.p2].iter().any(|v| !v.is_finite()) {
                return Err("non-finite distortion coefficients".into());
            }
        }
        Ok(())
    }
}

/// World-to-camera rigid transform in OpenCV axes: `p_cam = R * p_world + t`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorldToCamera {
    pub rotation: DMat3,
    pub translation: DVec3,
}

/// Camera-to-world rigid transform in OpenCV axes: `p_world = R * p_cam + t`;
/// `t` is the camera centre in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraToWorld {
    pub rotation: DMat3,
    pub translation: DVec3,
}

impl WorldToCamera {
    /// Builds a pose after checking that it is finite and `R` is a proper rotation
    /// (within [`ROTATION_TOLERANCE`]); the rotation is then re-orthonormalized exactly.
    pub fn new_checked(rotation: DMat3, translation: DVec3) -> Result<Self, String> {
        let r = check_rotation(rotation)?;
        if !translation.is_finite() {
            return Err(format!("non-finite translation {translation:?}"));
        }
        Ok(Self {
            rotation: r,
            translation,
        })
    }

    pub fn identity() -> Self {
        Self {
            rotation: DMat3::IDENTITY,
            translation: DVec3::ZERO,
        }
    }

    #[inline]
    pub fn transform_point(&self, p_world: DVec3) -> DVec3 {
        self.rotation * p_world + self.translation
    }

    pub fn inverse(&self) -> CameraToWorld {
        let rt = self.rotation.transpose();
        CameraToWorld {
            rotation: rt,
            translation: -(rt * self.translation),
        }
    }

    /// Camera centre in world coordinates, `-R^T t`.
    pub fn centre(&self) -> DVec3 {
        -(self.rotation.transpose() * self.translation)
    }

    /// The pose of camera `other` relative to this one: maps this camera's coordinates to
    /// `other`'s, `p_other = R_rel * p_self + t_rel`.
    pub fn relative_to(&self, other: &WorldToCamera) -> WorldToCamera {
        let rt = self.rotation.transpose();
        let r = other.rotation * rt;
        WorldToCamera {
            rotation: r,
            translation: other.translation - r * self.translation,
        }
    }
}

impl CameraToWorld {
    /// Builds a pose after the same checks as [`WorldToCamera::new_checked`].
    pub fn new_checked(rotation: DMat3, translation: DVec3) -> Result<Self, String> {
        let r = check_rotation(rotation)?;
        if !translation.is_finite() {
            return Err(format!("non-finite camera centre {translation:?}"));
        }
        Ok(Self {
            rotation: r,
            translation,
        })
    }

    pub fn inverse(&self) -> WorldToCamera {
        let rt = self.rotation.transpose();
        WorldToCamera {
            rotation: rt,
            translation: -(rt * self.translation),
        }
    }
}

/// Validates a rotation and returns it re-orthonormalized (Gram-Schmidt on its columns).
fn check_rotation(r: DMat3) -> Result<DMat3, String> {
    let cols = [r.x_axis, r.y_axis, r.z_axis];
    if cols.iter().any(|c| !c.is_finite()) {
        return Err(format!("non-finite rotation {r:?}"));
    }
    let err = (r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    if err > ROTATION_TOLERANCE {
        return Err(format!(
            "rotation is not orthonormal (max |R^T R - I| = {err:.3e} > {ROTATION_TOLERANCE:e})"
        ));
    }
    if r.determinant() <= 0.0 {
        return Err("rotation has negative determinant (a reflection, not a rotation)".into());
    }
    let x = r.x_axis.normalize();
    let y = (r.y_axis - x * x.dot(r.y_axis)).normalize();
    let z = x.cross(y);
    Ok(DMat3::from_cols(x, y, z))
}

/// A posed camera: intrinsics plus world-to-camera pose, and optionally a rolling
/// shutter ([`rolling`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    /// The camera's pose; with a rolling shutter, the pose at the time of the image
    /// centre (build such cameras with [`Camera::rolling`]), which is what
    /// shutter-unaware code (view ranking, bounds, `inspect`'s `R`/`t`) uses.
    pub pose: WorldToCamera,
    /// `None` (and absent in JSON) for a global shutter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rolling_shutter: Option<RollingShutter>,
}

impl Camera {
    /// The same camera for an image resampled by `1 / factor` (intrinsics and the
    /// shutter's time per pixel; see [`Intrinsics::downscaled`]).
    pub fn downscaled(&self, factor: f64, width: u32, height: u32) -> Self {
        Self {
            intrinsics: self.intrinsics.downscaled(factor, width, height),
            pose: self.pose,
            rolling_shutter: self.rolling_shutter.map(|s| s.downscaled(factor)),
        }
    }

    /// Projects a world point to a pixel coordinate and its depth (camera z) with `pose`:
    /// a rolling shutter is ignored (see [`Camera::project_rolling`]).
    pub fn project(&self, p_world: DVec3) -> (DVec2, f64) {
        let pc = self.pose.transform_point(p_world);
        let uv = self
            .intrinsics
            .project_normalized(DVec2::new(pc.x / pc.z, pc.y / pc.z));
        (uv, pc.z)
    }

    /// World point at camera depth `depth` along the ray through pixel `uv`, with the
    /// pose of that pixel's time for a rolling shutter ([`Camera::pose_at_pixel`]).
    pub fn unproject(&self, uv: DVec2, depth: f64) -> DVec3 {
        let n = self.intrinsics.unproject_pixel(uv);
        let pc = DVec3::new(n.x * depth, n.y * depth, depth);
        let c2w = self.pose_at_pixel(uv).inverse();
        c2w.rotation * pc + c2w.translation
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distortion_round_trip() {
        let d = Distortion {
            k1: 0.058,
            k2: -0.081,
            p1: 0.001,
            p2: -0.002,
        };
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.4, 0.5)] {
            let p = DVec2::new(x, y);
            let back = d.remove(d.apply(p));
            assert!((back - p).length() < 1e-10, "{p:?} -> {back:?}");
        }
    }

    #[test]
    fn project_unproject_round_trip() {
        let r = DMat3::from_rotation_y(0.3) * DMat3::from_rotation_x(-0.2);
        let pose = WorldToCamera::new_checked(r, DVec3::new(0.1, -0.2, 0.5)).unwrap();
        let cam = Camera::global(
            Intrinsics::pinhole(500.0, 510.0, 320.5, 240.25, 640, 480),
            pose,
        );
        let uv = DVec2::new(100.5, 300.5);
        let p = cam.unproject(uv, 3.7);
        let (uv2, z) = cam.project(p);
        assert!((uv2 - uv).length() < 1e-9);
        assert!((z - 3.7).abs() < 1e-12);
        assert!((pose.inverse().inverse().translation - pose.translation).length() < 1e-12);
    }

    #[test]
    fn validate_rejects_impossible_intrinsics() {
        let ok = Intrinsics::pinhole(10.0, 10.0, 5.0, 5.0, 10, 10);
        assert!(ok.validate().is_ok());
        let huge = Intrinsics {
            width: MAX_IMAGE_SIDE + 1,
            ..ok
        };
        assert!(huge
            .validate()
            .unwrap_err()
            .contains("unsupported image size"));
        assert!(Intrinsics { height: 0, ..ok }.validate().is_err());
        assert!(Intrinsics { fx: -1.0, ..ok }.validate().is_err());
        assert!(Intrinsics { cy: f64::NAN, ..ok }.validate().is_err());
        // Focal lengths 0.01 to 1000 times the larger side; principal points within 10
        // image sizes of the image.
        assert!(Intrinsics { fx: 0.1, ..ok }.validate().is_ok());
        assert!(Intrinsics { fy: 1e4, ..ok }.validate().is_ok());
        let far = Intrinsics { fx: 1e300, ..ok }.validate().unwrap_err();
        assert!(far.contains("focal length 1e300"), "{far}");
        assert!(Intrinsics { fy: 0.09, ..ok }.validate().is_err());
        assert!(Intrinsics { cx: -100.0, ..ok }.validate().is_ok());
        assert!(Intrinsics { cx: -101.0, ..ok }.validate().is_err());
        assert!(Intrinsics { cy: 111.0, ..ok }.validate().is_err());
        let d = Distortion {
            k1: f64::INFINITY,
            ..Default::default()
        };
        assert!(Intrinsics {
            distortion: Some(d),
            ..ok
        }
        .validate()
        .is_err());
    }

    #[test]
    fn rejects_bad_rotations() {
        assert!(WorldToCamera::new_checked(
            DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0)),
            DVec3::ZERO
        )
        .is_err());
        assert!(
            WorldToCamera::new_checked(DMat3::from_diagonal(DVec3::splat(2.0)), DVec3::ZERO)
                .is_err()
        );
        let mut nan = DMat3::IDENTITY;
        nan.x_axis.x = f64::NAN;
        assert!(WorldToCamera::new_checked(nan, DVec3::ZERO).is_err());
        assert!(
            WorldToCamera::new_checked(DMat3::IDENTITY, DVec3::new(f64::INFINITY, 0.0, 0.0))
                .is_err()
        );
    }
}
