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
    DMat3::from_cols(
        rel.rotation.x_axis,
        rel.rotation.y_axis,
        rel.rotation.z_axis + t,
    )
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
        let a = WorldToCamera::new_checked(DMat3::from_rotation_y(0.2), DVec3::new(0.3, 0.0, 0.1))
            .unwrap();
        let b =
            WorldToCamera::new_checked(DMat3::from_rotation_x(-0.1), DVec3::new(-0.2, 0.1, 0.0))
                .unwrap();
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
            assert!((inv * h_ab - DMat3::IDENTITY)
                .to_cols_array()
                .iter()
                .all(|v| v.abs() < 1e-12));
        }
    }

    fn pose(rx: f64, ry: f64, rz: f64, t: [f64; 3]) -> WorldToCamera {
        let r = DMat3::from_euler(glam::EulerRot::XYZ, rx, ry, rz);
        WorldToCamera::new_checked(r, DVec3::from_array(t)).unwrap()
    }

    #[test]
    fn homography_inverse_is_the_reverse_plane_map() {
        // Derived independently: the plane rho * z_t = 1 is m^T X_s = 1 in the source with
        // m = rho R e3 / (1 + rho (R e3) . t), and X_t = R^T (I - t m^T) X_s.
        let cases = [
            (
                pose(0.1, -0.3, 0.2, [0.5, 0.1, -0.2]),
                pose(-0.2, 0.4, 0.0, [-0.3, 0.2, 0.6]),
            ),
            (
                pose(3.0, 0.1, -2.0, [1e3, -2e3, 5e2]),
                pose(0.0, 0.0, 0.0, [0.0, 0.0, 0.0]),
            ),
            (
                pose(0.0, 3.1, 0.0, [0.0, 0.0, 1.0]),
                pose(0.0, 0.0, 0.0, [1e-6, 0.0, 0.0]),
            ),
        ];
        for (target, source) in cases {
            let rel = target.relative_to(&source);
            let (r, t) = (rel.rotation, rel.translation);
            for rho in [0.0, 1e-6, 0.1, 1.0, 7.5, 1e3] {
                let h = plane_homography(&rel, rho);
                let n = r.z_axis;
                let m = n * (rho / (1.0 + rho * n.dot(t)));
                let outer = DMat3::from_cols(t * m.x, t * m.y, t * m.z);
                let back = r.transpose() * (DMat3::IDENTITY - outer);
                let prod = back * h;
                let scale = (prod.x_axis.x + prod.y_axis.y + prod.z_axis.z) / 3.0;
                let err = (prod * (1.0 / scale) - DMat3::IDENTITY)
                    .to_cols_array()
                    .iter()
                    .fold(0.0f64, |a, v| a.max(v.abs()));
                assert!(err < 1e-9, "rho {rho}: |H_st H_ts - I| = {err:e}");
                let num = (h.inverse() * h - DMat3::IDENTITY)
                    .to_cols_array()
                    .iter()
                    .fold(0.0f64, |a, v| a.max(v.abs()));
                assert!(num < 1e-9, "rho {rho}: |H^-1 H - I| = {num:e}");
            }
        }
    }

    #[test]
    fn homography_maps_plane_points_like_projection() {
        let target = pose(0.3, -0.1, 0.05, [0.2, -0.4, 1.0]);
        let source = pose(0.1, 0.25, -0.2, [-0.6, 0.3, 0.9]);
        let rel = target.relative_to(&source);
        let c2w = target.inverse();
        for rho in [0.05, 0.5, 2.0] {
            let h = plane_homography(&rel, rho);
            for (x, y) in [(0.0, 0.0), (0.3, -0.2), (-0.5, 0.4)] {
                let world = c2w.rotation * (DVec3::new(x, y, 1.0) / rho) + c2w.translation;
                let p = source.transform_point(world);
                let q = apply_h(&h, x, y);
                assert!(q.z > 0.0 && p.z > 0.0);
                assert!((q.truncate() / q.z - p.truncate() / p.z).length() < 1e-12);
            }
        }
        assert_eq!(plane_homography(&rel, 0.0), rel.rotation);
    }

    #[test]
    fn extreme_bounds_are_finite_and_uniform() {
        for (near, far, n) in [
            (1e-3, 1e6, 96),
            (1e-4, f64::INFINITY, 32),
            (1e-3, 1e6, 1),
            (5.0, 5.0 + 1e-9, 2),
        ] {
            let r = inverse_depths(near, far, n);
            assert_eq!(r.len(), n);
            assert!(
                r.iter().all(|v| v.is_finite() && *v >= 0.0),
                "{near} {far}: {r:?}"
            );
            assert!(r.windows(2).all(|w| w[0] > w[1]), "not decreasing: {r:?}");
            if n > 2 {
                let step = r[0] - r[1];
                assert!(r
                    .windows(2)
                    .all(|w| ((w[0] - w[1]) - step).abs() <= 1e-9 * r[0]));
            }
            assert!(depths_of(&r).iter().all(|d| *d > 0.0 && !d.is_nan()));
            let rel = pose(0.1, 0.2, 0.3, [0.5, -0.5, 0.25]);
            for rho in r {
                assert!(plane_homography(&rel, rho)
                    .to_cols_array()
                    .iter()
                    .all(|v| v.is_finite()));
            }
        }
        assert_eq!(inverse_depths(2.0, 4.0, 1), vec![0.375]);
        assert!(inverse_depths(2.0, 4.0, 0).is_empty());
    }
}
