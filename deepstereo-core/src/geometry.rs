//! Plane-sweep geometry in f64: depth planes and plane-induced homographies.
//!
//! Planes are fronto-parallel to the target camera. A plane at depth `d` (inverse depth
//! `rho = 1 / d`) induces, between the target's and a source's *normalized* coordinates,
//! the homography (target -> source)
//!
//! `H(rho) = R_rel + rho * t_rel * e3^T`,
//!
//! where `p_src = R_rel * p_tgt + t_rel` maps target camera coordinates to the source's.
//! Working in normalized coordinates keeps `H` well conditioned whatever the focal
//! lengths; `rho = 0` (far = infinity) gives the pure-rotation homography.

use crate::camera::WorldToCamera;
use glam::{DMat3, DVec3};

/// `D` inverse depths uniform between `1 / near` (plane 0) and `1 / far` (plane `D - 1`).
/// `far` may be infinite (inverse depth 0). With `D == 1` the single plane sits at the
/// middle inverse depth.
pub fn inverse_depths(near: f64, far: f64, planes: usize) -> Vec<f64> {
    let (a, b) = (1.0 / near, if far.is_infinite() { 0.0 } else { 1.0 / far });
    match planes {
        0 => Vec::new(),
        1 => vec![0.5 * (a + b)],
        n => (0..n)
            .map(|i| a + (b - a) * i as f64 / (n - 1) as f64)
            .collect(),
    }
}

/// Depths of the planes (`f64::INFINITY` for inverse depth 0).
pub fn depths_of(inv_depths: &[f64]) -> Vec<f64> {
    inv_depths
        .iter()
        .map(|&r| if r > 0.0 { 1.0 / r } else { f64::INFINITY })
        .collect()
}

/// Homography from target to source normalized coordinates for the plane at inverse
/// depth `rho` (see the module docs). `rel` maps target camera coordinates to source's.
pub fn plane_homography(rel: &WorldToCamera, rho: f64) -> DMat3 {
    let t = rel.translation * rho;
    // Adding t * e3^T changes only the third column.
    DMat3::from_cols(rel.rotation.x_axis, rel.rotation.y_axis, rel.rotation.z_axis + t)
}

/// Applies a homography to normalized coordinates `(x, y, 1)`; returns the homogeneous
/// result, whose `z` is positive exactly when the plane point lies in front of the source.
#[inline]
pub fn apply_h(h: &DMat3, x: f64, y: f64) -> DVec3 {
    h.x_axis * x + h.y_axis * y + h.z_axis
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_depths_endpoints() {
        let r = inverse_depths(2.0, 10.0, 5);
        assert!((r[0] - 0.5).abs() < 1e-15 && (r[4] - 0.1).abs() < 1e-15);
        let r = inverse_depths(1.0, f64::INFINITY, 3);
        assert_eq!(r, vec![1.0, 0.5, 0.0]);
        assert_eq!(depths_of(&r)[2], f64::INFINITY);
    }

    #[test]
    fn homography_times_inverse_is_identity() {
        let a = WorldToCamera::new_checked(DMat3::from_rotation_y(0.2), DVec3::new(0.3, 0.0, 0.1)).unwrap();
        let b = WorldToCamera::new_checked(DMat3::from_rotation_x(-0.1), DVec3::new(-0.2, 0.1, 0.0)).unwrap();
        for rho in [0.0, 0.1, 2.0, 1e3] {
            let h_ab = plane_homography(&a.relative_to(&b), rho);
            // The plane z = 1/rho in a, expressed in b, is not fronto-parallel in b, so go
            // through the point map instead: a point of the plane maps back exactly.
            let p_a = DVec3::new(0.1, -0.2, 1.0);
            let q = apply_h(&h_ab, p_a.x, p_a.y);
            if rho > 0.0 {
                let x_b = q / rho; // the 3D point in b's coordinates
                let back = b.relative_to(&a).transform_point(x_b);
                assert!((back * rho - p_a).length() < 1e-9, "rho {rho}");
            }
            let inv = h_ab.inverse();
            assert!((inv * h_ab - DMat3::IDENTITY).to_cols_array().iter().all(|v| v.abs() < 1e-12));
        }
    }
}
