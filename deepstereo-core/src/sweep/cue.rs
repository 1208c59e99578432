//! The per-view geometric cue: how a source's ray to each plane point differs from the
//! target's (after IBRNet's ray-direction difference), in f64 beside the plane sweep.
//!
//! For a target pixel with normalized ray `r = (x, y, 1)` (target camera coordinates,
//! lens distortion removed) and a plane at inverse depth `rho` (1/z along the target's
//! axis), the plane point is `X = r / rho`. A source whose centre is `c` in target
//! coordinates sees it along `X - c = (r - rho c) / rho`, so with `s = r - rho c`:
//!
//! - `t = r / |r|`, `d = s / |s|` (unit rays of the target and the source; `d = t` when
//!   `s = 0`, and at `rho = 0`, the plane at infinity, `s = r`);
//! - `delta = d - t` and `n = |delta|` (about the angle between the rays, in radians);
//! - channels `[delta / (n + EPS_DIR), ln(n + EPS_DIR), clamp(ln(|s| / |r|), +-MAX_LOG_RATIO)]`:
//!   which side the source sees the point from (a unit vector, fading to 0 as the rays
//!   meet), how far apart the rays are (log scale: forward-facing captures differ by
//!   hundredths of a radian, rings of cameras by tenths), and the source's distance to
//!   the point relative to the target's (`|X - c| / |X|`: finer or coarser detail).
//!
//! Every channel is finite for every input, and invariant to the scene's scale and to
//! rotations and translations of the world (all in the target's frame, relative to
//! distances). Mirroring the target image horizontally negates channel 0 only. A view
//! that is not there has alpha 0, which the network's pooling and blend multiply by, so
//! its cue changes nothing.

use crate::camera::Camera;
use crate::config::CUE_CHANNELS;
use crate::cpu::fastmath::ln_f32;
use glam::{DVec2, DVec3};

/// Added to the angle before dividing and taking its logarithm (`ln(1e-3) ~ -6.9` where
/// the rays coincide).
pub const EPS_DIR: f64 = 1e-3;
/// Bound on the log distance ratio (a source 150 times nearer or farther than the target).
pub const MAX_LOG_RATIO: f64 = 5.0;

/// The centre of `source` in the coordinates of `target`.
pub fn centre_in(target: &Camera, source: &Camera) -> DVec3 {
    target.pose.transform_point(source.pose.centre())
}

/// The target rays of a region, prepared once for the cue of every (plane, view):
/// normalized coordinates `(x, y)` (as [`super::target_rays`] returns), `|r|^2` and
/// `1 / |r|` of `r = (x, y, 1)`.
pub struct CueRays {
    x: Vec<f64>,
    y: Vec<f64>,
    norm2: Vec<f64>,
    inv_norm: Vec<f64>,
}

impl CueRays {
    pub fn new(rays: &[DVec2]) -> Self {
        let norm2: Vec<f64> = rays.iter().map(|r| r.length_squared() + 1.0).collect();
        Self {
            x: rays.iter().map(|r| r.x).collect(),
            y: rays.iter().map(|r| r.y).collect(),
            inv_norm: norm2.iter().map(|n| 1.0 / n.sqrt()).collect(),
            norm2,
        }
    }

    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

/// The cue of one (plane, view) for the target rays `rays`, written as
/// `[CUE_CHANNELS, n]` into `out` (`n = rays.len()`). The geometry is [`cue`]'s in f64,
/// branch-free so that the loop vectorises; the logarithms are taken in f32 (the output's
/// precision) by [`ln_f32`] in a second pass. Agrees with [`cue`] within 1e-6 (tested).
pub fn cue_slice(rays: &CueRays, rho: f64, centre: DVec3, out: &mut [f32]) {
    let n = rays.len();
    debug_assert_eq!(out.len(), CUE_CHANNELS * n);
    let (o0, rest) = out.split_at_mut(n);
    let (o1, rest) = rest.split_at_mut(n);
    let (o2, rest) = rest.split_at_mut(n);
    let (o3, o4) = rest.split_at_mut(n);
    let c = rho * centre;
    #[cfg(target_arch = "x86_64")]
    if crate::cpu::avx2_fma_available() {
        // SAFETY: the CPU has AVX2 and FMA (checked).
        unsafe { geometry_avx2(rays, c, [o0, o1, o2, o3, o4]) };
        return logs(o3, o4);
    }
    geometry(rays, c, [o0, o1, o2, o3, o4]);
    logs(o3, o4);
}

/// [`geometry`] compiled for AVX2 + FMA (four f64 lanes).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn geometry_avx2(rays: &CueRays, c: DVec3, out: [&mut [f32]; CUE_CHANNELS]) {
    geometry(rays, c, out)
}

/// The f64 part of [`cue_slice`] for the scaled centre `c = rho * centre`: the direction
/// channels, `n + EPS_DIR` and `|s|^2 / |r|^2` (before their logarithms).
#[inline(always)]
fn geometry(rays: &CueRays, c: DVec3, [o0, o1, o2, o3, o4]: [&mut [f32]; CUE_CHANNELS]) {
    let rays_iter = rays
        .x
        .iter()
        .zip(&rays.y)
        .zip(&rays.norm2)
        .zip(&rays.inv_norm);
    for (i, (((&rx, &ry), &rn2), &inv_rn)) in rays_iter.enumerate() {
        let (tx, ty, tz) = (rx * inv_rn, ry * inv_rn, inv_rn);
        let (sx, sy, sz) = (rx - c.x, ry - c.y, 1.0 - c.z);
        let sn2 = sx * sx + sy * sy + sz * sz;
        // The source's ray is undefined where the point is its centre (`s = 0`) or
        // overflows: then the target's direction (`delta = 0`).
        let ok = sn2 > 0.0 && sn2 < f64::INFINITY;
        let inv_sn = if ok { 1.0 / sn2.sqrt() } else { 0.0 };
        let (dx, dy, dz) = match ok {
            true => (sx * inv_sn - tx, sy * inv_sn - ty, sz * inv_sn - tz),
            false => (0.0, 0.0, 0.0),
        };
        let nd = (dx * dx + dy * dy + dz * dz).sqrt() + EPS_DIR;
        let k = 1.0 / nd;
        o0[i] = (dx * k) as f32;
        o1[i] = (dy * k) as f32;
        o2[i] = (dz * k) as f32;
        o3[i] = nd as f32;
        // |s|^2 / |r|^2: 0 at the source's centre, infinite where `s` overflows.
        o4[i] = (sn2 / rn2) as f32;
    }
}

/// The logarithms of [`cue_slice`]'s channels 3 and 4, in place.
fn logs(o3: &mut [f32], o4: &mut [f32]) {
    let bound = MAX_LOG_RATIO as f32;
    for v in o3.iter_mut() {
        *v = ln_f32(*v);
    }
    // ln(|s| / |r|) = ln(|s|^2 / |r|^2) / 2 (ln_f32 maps 0 and infinity to about -87 and
    // 89: the bound's ends).
    for v in o4.iter_mut() {
        *v = (0.5 * ln_f32(*v)).clamp(-bound, bound);
    }
}

/// The cue of the module doc for ray `r`, inverse depth `rho` and source centre `c`.
pub fn cue(r: DVec3, rho: f64, c: DVec3) -> [f64; CUE_CHANNELS] {
    let rn = r.length();
    let t = r / rn;
    let s = r - rho * c;
    let sn = s.length();
    let d = if sn > 0.0 && sn.is_finite() {
        s / sn
    } else {
        t
    };
    let delta = d - t;
    let n = delta.length();
    let u = delta / (n + EPS_DIR);
    let ratio = if sn.is_finite() {
        sn / rn
    } else {
        f64::INFINITY
    };
    let log_ratio = match ratio {
        r if r > 0.0 => r.ln().clamp(-MAX_LOG_RATIO, MAX_LOG_RATIO),
        _ => -MAX_LOG_RATIO,
    };
    [u.x, u.y, u.z, (n + EPS_DIR).ln(), log_ratio]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Intrinsics, WorldToCamera};
    use glam::DMat3;

    fn camera(rotation: DMat3, centre: DVec3) -> Camera {
        let pose = WorldToCamera {
            rotation,
            translation: -(rotation * centre),
        };
        Camera {
            intrinsics: Intrinsics::pinhole(100.0, 100.0, 50.0, 40.0, 100, 80),
            pose,
            rolling_shutter: None,
        }
    }

    /// Against the definition in world coordinates: the angle between the rays from the
    /// two centres to the world point, and the ratio of the distances.
    #[test]
    fn matches_the_world_geometry() {
        let rt = DMat3::from_rotation_y(0.3) * DMat3::from_rotation_x(-0.2);
        let target = camera(rt, DVec3::new(1.0, -2.0, 0.5));
        let source = camera(DMat3::from_rotation_z(0.4), DVec3::new(1.7, -1.5, 0.9));
        let c = centre_in(&target, &source);
        for (ray, rho) in [
            (DVec3::new(0.1, -0.2, 1.0), 0.25),
            (DVec3::new(-0.4, 0.3, 1.0), 2.0),
            (DVec3::new(0.0, 0.0, 1.0), 0.01),
        ] {
            let cue = cue(ray, rho, c);
            // The world point and the two rays to it, in world coordinates.
            let cam_to_world = target.pose.inverse();
            let x = cam_to_world.rotation * (ray / rho) + cam_to_world.translation;
            let ct = target.pose.centre();
            let cs = source.pose.centre();
            let (dt, ds) = ((x - ct).normalize(), (x - cs).normalize());
            let n = (ds - dt).length();
            assert!(
                ((cue[3].exp() - EPS_DIR) - n).abs() < 1e-12,
                "{cue:?} vs {n}"
            );
            let ratio = (x - cs).length() / (x - ct).length();
            assert!((cue[4] - ratio.ln()).abs() < 1e-12);
            // The direction, back in world coordinates.
            let u = DVec3::new(cue[0], cue[1], cue[2]) * (n + EPS_DIR);
            let u_world = cam_to_world.rotation * u;
            assert!((u_world - (ds - dt)).length() < 1e-12);
        }
    }

    /// The plane at infinity, a source at the target's centre and a plane point at the
    /// source's centre: finite values at the limits.
    #[test]
    fn limits_are_finite() {
        let r = DVec3::new(0.2, 0.1, 1.0);
        let at_infinity = cue(r, 0.0, DVec3::new(3.0, 0.0, 0.0));
        assert_eq!(
            at_infinity,
            [0.0, 0.0, 0.0, EPS_DIR.ln(), 0.0],
            "plane at infinity"
        );
        assert_eq!(
            cue(r, 0.7, DVec3::ZERO),
            at_infinity,
            "source at the target"
        );
        let on_centre = cue(r, 2.0, r / 2.0);
        assert!(on_centre.iter().all(|v| v.is_finite()), "{on_centre:?}");
        assert_eq!(on_centre[4], -MAX_LOG_RATIO);
        let huge = cue(r, 1e300, DVec3::new(1e300, 0.0, 0.0));
        assert!(huge.iter().all(|v| v.is_finite()), "{huge:?}");
    }

    /// The per-slice path equals the reference within f32 rounding, including the limits.
    #[test]
    fn slice_matches_the_reference() {
        let rays: Vec<DVec2> = (0..60)
            .map(|i| DVec2::new(-0.8 + 0.027 * i as f64, 0.5 - 0.017 * i as f64))
            .collect();
        let centres = [
            DVec3::new(0.3, -0.1, 0.05),
            DVec3::new(-2.0, 0.4, 1.0),
            DVec3::ZERO,
            DVec3::new(1e-4, 0.0, 0.0),
        ];
        let mut out = vec![0f32; CUE_CHANNELS * rays.len()];
        let table = CueRays::new(&rays);
        for c in centres {
            for rho in [0.0, 1e-3, 0.3, 2.0, 40.0] {
                cue_slice(&table, rho, c, &mut out);
                for (i, ray) in rays.iter().enumerate() {
                    let want = cue(DVec3::new(ray.x, ray.y, 1.0), rho, c);
                    for (k, w) in want.iter().enumerate() {
                        let got = out[k * rays.len() + i] as f64;
                        assert!(
                            (got - w).abs() <= 1e-6 * w.abs().max(1.0),
                            "centre {c}, rho {rho}, ray {i}, channel {k}: {got} vs {w}"
                        );
                    }
                }
            }
        }
        // A plane point at the source's centre.
        let r = DVec2::new(0.2, 0.1);
        let mut one = [0f32; CUE_CHANNELS];
        cue_slice(
            &CueRays::new(&[r]),
            2.0,
            DVec3::new(0.1, 0.05, 0.5),
            &mut one,
        );
        assert_eq!(one[4], -MAX_LOG_RATIO as f32);
        assert!(one.iter().all(|v| v.is_finite()));
    }

    /// Scaling the scene (centres and depths) leaves the cue unchanged.
    #[test]
    fn scale_invariant() {
        let (r, c) = (DVec3::new(-0.3, 0.25, 1.0), DVec3::new(0.4, -0.1, 0.2));
        let a = cue(r, 0.5, c);
        let b = cue(r, 0.5 / 8.0, c * 8.0);
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-12, "{a:?} vs {b:?}");
        }
    }
}
