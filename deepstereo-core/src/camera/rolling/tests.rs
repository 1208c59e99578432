//! The rolling-shutter projection against a brute-force search over the readout, and
//! its extreme cases.
use super::*;
use crate::camera::Distortion;
use glam::{DMat3, DVec2, DVec3};

fn pose(r: DMat3, centre: DVec3) -> WorldToCamera {
    WorldToCamera::new_checked(r, -(r * centre)).expect("pose")
}

/// Deterministic numbers in [0, 1) (SplitMix64).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn sym(&mut self, a: f64) -> f64 {
        a * (2.0 * self.next() - 1.0)
    }
}

/// The time residual `t(pi(t)) - t` of world point `p` in `cam` at time `t` (None when
/// the point is not in front).
fn residual(cam: &Camera, p: DVec3, t: f64) -> Option<(f64, DVec2)> {
    let rs = cam.rolling_shutter.expect("shutter");
    let at = Camera::global(cam.intrinsics, rs.pose_at(t));
    let (uv, z) = at.project(p);
    (z > 0.0).then(|| (rs.time_at(uv) - t, uv))
}

/// Every time in `[lo, hi]` where the residual changes sign, by a scan of `steps`
/// samples refined by bisection.
fn brute_force_roots(cam: &Camera, p: DVec3, lo: f64, hi: f64, steps: usize) -> Vec<f64> {
    let f = |t: f64| residual(cam, p, t).map(|r| r.0);
    let mut roots = Vec::new();
    let mut prev = (lo, f(lo));
    for i in 1..=steps {
        let t = lo + (hi - lo) * i as f64 / steps as f64;
        let ft = f(t);
        if let (Some(a), Some(b)) = (prev.1, ft) {
            if a == 0.0 {
                roots.push(prev.0);
            } else if a * b < 0.0 {
                let (mut x0, mut x1, mut f0) = (prev.0, t, a);
                for _ in 0..200 {
                    let m = 0.5 * (x0 + x1);
                    let fm = f(m).unwrap_or(f64::NAN);
                    if fm * f0 <= 0.0 {
                        x1 = m;
                    } else {
                        x0 = m;
                        f0 = fm;
                    }
                }
                roots.push(0.5 * (x0 + x1));
            }
        }
        prev = (t, ft);
    }
    roots
}

fn intrinsics(distorted: bool) -> Intrinsics {
    let mut k = Intrinsics::pinhole(180.0, 176.0, 81.3, 58.9, 160, 120);
    if distorted {
        k.distortion = Some(Distortion {
            k1: -0.12,
            k2: 0.03,
            p1: 0.002,
            p2: -0.001,
        });
    }
    k
}

#[test]
fn row_solver_matches_brute_force_over_rows() {
    let mut rng = Rng(7);
    let (mut worst_rows, mut worst_px, mut solved, mut max_iters) = (0.0f64, 0.0f64, 0, 0);
    for case in 0..40 {
        let k = intrinsics(case % 2 == 1);
        let r0 = DMat3::from_euler(
            glam::EulerRot::YXZ,
            rng.sym(0.2),
            rng.sym(0.2),
            rng.sym(0.1),
        );
        let r1 = DMat3::from_euler(
            glam::EulerRot::YXZ,
            rng.sym(0.1),
            rng.sym(0.1),
            rng.sym(0.05),
        ) * r0;
        let c0 = DVec3::new(rng.sym(0.5), rng.sym(0.5), rng.sym(0.2));
        let c1 = c0 + DVec3::new(rng.sym(0.6), rng.sym(0.6), rng.sym(0.3));
        // A vertical readout (rows), or one slanted across the columns too.
        let per = if case % 3 == 0 {
            DVec2::new(0.3 / 160.0, 0.8 / 120.0)
        } else {
            DVec2::new(0.0, 1.0 / 120.0)
        };
        let rs = RollingShutter::new_checked(pose(r0, c0), pose(r1, c1), 0.0, per).expect("rs");
        let cam = Camera::rolling(k, rs);
        for _ in 0..25 {
            // A point near the middle-time camera's view.
            let uv = DVec2::new(rng.next() * 160.0, rng.next() * 120.0);
            let p = cam.unproject(uv, 2.0 + 6.0 * rng.next());
            let (lo, hi) = rs.time_range(k.width, k.height, RS_WINDOW_MARGIN);
            let roots = brute_force_roots(&cam, p, lo, hi, 2000);
            let hit = RollingProjector::new(&cam).and_then(|pr| pr.solve(p, 1.0));
            match (roots.len(), hit) {
                (0, None) => {}
                (1, Some(h)) => {
                    // In rows: time difference over the time per row.
                    let rows = (h.time - roots[0]).abs() / per.length();
                    let (_, uv_bf) = residual(&cam, p, roots[0]).expect("in front");
                    worst_rows = worst_rows.max(rows);
                    worst_px = worst_px.max((h.uv - uv_bf).length());
                    max_iters = max_iters.max(h.iterations);
                    solved += 1;
                }
                (n, h) => panic!("case {case}: brute force {n} roots {roots:?}, solver {h:?}"),
            }
        }
    }
    println!(
        "{solved} points solved: worst {worst_rows:.2e} rows / {worst_px:.2e} px from brute force, \
         at most {max_iters} projections"
    );
    assert!(solved > 800, "only {solved} points inside the image");
    assert!(
        worst_rows < 1e-5 && worst_px < 1e-5,
        "{worst_rows} rows, {worst_px} px"
    );
    assert!(max_iters <= 6, "{max_iters} projections");
}

#[test]
fn global_shutter_and_zero_readout_project_like_a_pinhole() {
    let k = intrinsics(true);
    let a = pose(DMat3::from_rotation_y(0.1), DVec3::new(0.1, 0.2, -0.3));
    let b = pose(DMat3::from_rotation_x(0.2), DVec3::new(0.5, 0.0, 0.1));
    let p = DVec3::new(0.3, -0.2, 4.0);
    // Start = end: exactly the start pose, and the projection is the pinhole one.
    let same = Camera::rolling(
        k,
        RollingShutter::new_checked(a, a, 0.0, DVec2::new(0.0, 0.01)).expect("rs"),
    );
    assert_eq!(same.pose, a);
    assert!(same.moving_shutter().is_none());
    assert_eq!(same.project_rolling(p), Some(same.project(p)));
    // Zero readout: every pixel at time_origin, one pose.
    let zero = Camera::rolling(
        k,
        RollingShutter::new_checked(a, b, 0.25, DVec2::ZERO).expect("rs"),
    );
    assert!(zero.moving_shutter().is_none());
    let expect = Motion::new(&a, &b).pose(0.25);
    assert!((zero.pose.translation - expect.translation).length() < 1e-12);
    assert_eq!(zero.project_rolling(p), Some(zero.project(p)));
    // t = 0 and t = 1 are the start and end poses exactly.
    let rs = RollingShutter::new_checked(a, b, 0.0, DVec2::new(0.0, 0.01)).expect("rs");
    assert_eq!((rs.pose_at(0.0), rs.pose_at(1.0)), (a, b));
    let m = Motion::new(&a, &b).pose(1.0);
    assert!((m.rotation - b.rotation)
        .to_cols_array()
        .iter()
        .all(|v| v.abs() < 1e-12));
    assert!((m.centre() - b.centre()).length() < 1e-12);
}

#[test]
fn a_point_seen_by_two_rows_gets_one_of_them() {
    // The camera moves 0.9 forward during the readout, towards a point just below the
    // axis: its row runs down faster than the readout, and the readout catches it twice.
    let k = Intrinsics::pinhole(100.0, 100.0, 50.0, 50.0, 100, 100);
    let rs = RollingShutter::new_checked(
        pose(DMat3::IDENTITY, DVec3::ZERO),
        pose(DMat3::IDENTITY, DVec3::new(0.0, 0.0, 0.9)),
        0.0,
        DVec2::new(0.0, 0.01),
    )
    .expect("rs");
    let cam = Camera::rolling(k, rs);
    let p = DVec3::new(0.0, 0.06, 1.0);
    let roots = brute_force_roots(&cam, p, -0.02, 1.02, 4000);
    assert_eq!(roots.len(), 2, "{roots:?}");
    let hit = RollingProjector::new(&cam)
        .and_then(|pr| pr.solve(p, 1.0))
        .expect("a projection");
    let nearest = roots
        .iter()
        .map(|r| (hit.time - r).abs())
        .fold(f64::INFINITY, f64::min);
    println!(
        "roots {roots:?}, solver {:.9} ({} projections)",
        hit.time, hit.iterations
    );
    assert!(nearest * 100.0 < 1e-5, "{} vs {roots:?}", hit.time);
    assert!(hit.uv.is_finite());
}

#[test]
fn motion_larger_than_the_image_is_solved_or_rejected() {
    // During the readout the camera turns by 1.5 fields of view: points race across
    // rows faster than the readout (a fixed-point iteration would diverge here).
    let k = Intrinsics::pinhole(100.0, 100.0, 50.0, 50.0, 100, 100);
    let turn = 2.0 * 1.5 * (0.5f64).atan();
    let rs = RollingShutter::new_checked(
        pose(DMat3::IDENTITY, DVec3::ZERO),
        pose(DMat3::from_rotation_x(turn), DVec3::new(3.0, -2.0, 1.0)),
        0.0,
        DVec2::new(0.0, 0.01),
    )
    .expect("rs");
    let cam = Camera::rolling(k, rs);
    let proj = RollingProjector::new(&cam).expect("moving");
    let (mut some, mut none) = (0, 0);
    let mut rng = Rng(3);
    for _ in 0..2000 {
        let p = DVec3::new(rng.sym(6.0), rng.sym(6.0), 0.5 + 8.0 * rng.next());
        for w in [1.0, 0.0] {
            match proj.solve(if w == 0.0 { p.normalize() } else { p }, w) {
                Some(h) => {
                    // A solution is a true one: the pixel's time is the time it was seen.
                    assert!(h.uv.is_finite() && h.time.is_finite() && h.cam.is_finite());
                    let err = (rs.time_at(h.uv) - h.time).abs() / 0.01;
                    assert!(err <= RS_ROW_TOL * 1.0001, "{err} rows");
                    assert!(h.iterations <= RS_MAX_ITERS);
                    some += 1;
                }
                None => none += 1,
            }
        }
    }
    println!("{some} projected, {none} without a projection");
    assert!(some > 100 && none > 100);
    // Huge and degenerate inputs give a defined answer, never a panic or NaN.
    for p in [
        DVec3::new(1e300, -1e300, 1e300),
        DVec3::ZERO,
        DVec3::new(0.0, 0.0, -1.0),
        DVec3::new(f64::NAN, 0.0, 1.0),
    ] {
        if let Some(h) = proj.solve(p, 1.0) {
            assert!(h.uv.is_finite(), "{p:?}: {h:?}");
        }
    }
}

#[test]
fn instant_ngp_coefficients_convert_both_ways() {
    let a = pose(DMat3::IDENTITY, DVec3::ZERO);
    let b = pose(DMat3::IDENTITY, DVec3::X);
    let rs = RollingShutter::from_instant_ngp(a, b, [0.1, 0.2, 0.6, 0.4], 200, 100).expect("rs");
    assert!((rs.time_origin - 0.3).abs() < 1e-15);
    assert!((rs.time_per_pixel - DVec2::new(0.001, 0.006)).length() < 1e-15);
    // u/W = 0.5, v/H = 0.5: A + B/2 + C/2 + D/2.
    assert!((rs.time_at(DVec2::new(100.0, 50.0)) - 0.7).abs() < 1e-15);
    let back = rs.to_instant_ngp(200, 100);
    assert!((back[1] - 0.2).abs() < 1e-15 && (back[2] - 0.6).abs() < 1e-15);
    // Downscaling keeps every point's time.
    let half = rs.downscaled(2.0);
    assert!((half.time_at(DVec2::new(50.0, 25.0)) - 0.7).abs() < 1e-15);
    assert!(RollingShutter::from_instant_ngp(a, b, [0.0, f64::NAN, 1.0, 0.0], 2, 2).is_err());
    assert!(RollingShutter::new_checked(a, b, f64::INFINITY, DVec2::ZERO).is_err());
}

#[test]
fn camera_json_keeps_global_shutters_unchanged() {
    let k = intrinsics(false);
    let a = pose(DMat3::IDENTITY, DVec3::ZERO);
    let global = Camera::global(k, a);
    let text = serde_json::to_string(&global).expect("json");
    assert!(!text.contains("rolling_shutter"), "{text}");
    let back: Camera = serde_json::from_str(&text).expect("parse");
    assert_eq!(back, global);
    let b = pose(DMat3::from_rotation_z(0.1), DVec3::Y);
    let rolling = Camera::rolling(
        k,
        RollingShutter::new_checked(a, b, 0.0, DVec2::new(0.0, 1.0 / 120.0)).expect("rs"),
    );
    let back: Camera =
        serde_json::from_str(&serde_json::to_string(&rolling).expect("json")).expect("parse");
    // serde_json's float parsing may round the last bit.
    let (rs, rs0) = (
        back.rolling_shutter.expect("kept"),
        rolling.rolling_shutter.expect("rs"),
    );
    assert!((rs.end.translation - rs0.end.translation).length() < 1e-15);
    assert_eq!(rs.time_per_pixel, rs0.time_per_pixel);
    assert!((back.pose.rotation - rolling.pose.rotation)
        .to_cols_array()
        .iter()
        .all(|v| v.abs() < 1e-15));
}
