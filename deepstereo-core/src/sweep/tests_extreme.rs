//! Unit tests of the plane sweep in extreme geometry: points behind a source, a plane at
//! infinity, extreme near/far, and lens distortion past its monotonic range.
use super::tests::{cam, noise_image, reference_slice};
use super::*;
use crate::camera::Distortion;
use crate::geometry::inverse_depths;
use glam::{DMat3, DVec3};

#[test]
fn points_behind_a_source_get_alpha_zero() {
    let intr = Intrinsics::pinhole(40.0, 40.0, 16.0, 12.0, 32, 24);
    let target = cam(DMat3::IDENTITY, DVec3::ZERO, intr);
    let img = noise_image(32, 24, 1);
    // A source beyond the plane z = 2, looking the same way: the plane is behind it,
    // and a projection that ignored the sign of z would land inside its image.
    let beyond = cam(DMat3::IDENTITY, DVec3::new(0.0, 0.0, 4.0), intr);
    // A source turned sideways at the plane: part of the plane is behind it.
    let sideways = cam(DMat3::from_rotation_y(1.3), DVec3::new(0.3, 0.0, 2.0), intr);
    for source in [beyond, sideways] {
        let src = [Source {
            camera: &source,
            image: &img,
        }];
        let out = sweep(&target, Region::full(&intr), &src, &[0.5]);
        let hw = Region::full(&intr).len();
        let (mut behind, mut naive_inside) = (0, 0);
        for p in 0..hw {
            let uv = DVec2::new((p % 32) as f64 + 0.5, (p / 32) as f64 + 0.5);
            let (uv_src, z) = source.project(target.unproject(uv, 2.0));
            let a = out[3 * hw + p];
            if z <= 0.0 {
                behind += 1;
                assert_eq!(a, 0.0, "pixel {p} behind the source has alpha {a}");
                assert!((0..3).all(|c| out[c * hw + p] == 0.0));
                // A projection that ignored the sign of z would have sampled here.
                naive_inside += usize::from(sample_bilinear(&img, uv_src.x, uv_src.y)[3] > 0.0);
            }
        }
        assert!(
            behind > 0 && naive_inside > 0,
            "behind {behind}, naive inside {naive_inside}"
        );
    }
}

#[test]
fn far_at_infinity_is_a_pure_rotation() {
    let intr = Intrinsics::pinhole(50.0, 50.0, 20.0, 15.0, 40, 30);
    let target = cam(DMat3::from_rotation_x(0.2), DVec3::new(0.0, 1.0, 0.0), intr);
    let img = noise_image(40, 30, 9);
    let r = DMat3::from_rotation_y(0.15) * DMat3::from_rotation_x(0.2);
    let near_src = cam(r, DVec3::new(0.0, 1.0, 0.0), intr);
    let far_src = cam(r, DVec3::new(5.0, -3.0, 2.0), intr);
    let inv = inverse_depths(1.0, f64::INFINITY, 4);
    assert_eq!(inv[3], 0.0);
    let a = sweep(
        &target,
        Region::full(&intr),
        &[Source {
            camera: &near_src,
            image: &img,
        }],
        &inv,
    );
    let b = sweep(
        &target,
        Region::full(&intr),
        &[Source {
            camera: &far_src,
            image: &img,
        }],
        &inv,
    );
    let n = 4 * Region::full(&intr).len();
    assert!(a.iter().chain(&b).all(|v| v.is_finite()));
    // At infinity the translation does not matter...
    assert_eq!(&a[3 * n..], &b[3 * n..]);
    // ...and the slice is the rotation-only reference.
    let want = reference_slice(
        &target,
        &Source {
            camera: &near_src,
            image: &img,
        },
        0.0,
        Region::full(&intr),
    );
    assert!(a[3 * n..]
        .iter()
        .zip(&want)
        .all(|(g, w)| (g - w).abs() < 1e-5));
    assert!(want.iter().skip(3 * n / 4).any(|&al| al > 0.99));
    // ...while at finite depth it does.
    assert_ne!(&a[..n], &b[..n]);
}

#[test]
fn extreme_near_and_far_stay_finite() {
    let intr = Intrinsics::pinhole(40.0, 40.0, 16.0, 12.0, 32, 24);
    let target = cam(DMat3::IDENTITY, DVec3::ZERO, intr);
    let source = cam(
        DMat3::from_rotation_y(0.1),
        DVec3::new(0.2, 0.05, -0.1),
        intr,
    );
    let img = noise_image(32, 24, 4);
    let inv = inverse_depths(1e-3, 1e6, 16);
    assert!(inv.iter().all(|r| r.is_finite() && *r > 0.0));
    let out = sweep(
        &target,
        Region::full(&intr),
        &[Source {
            camera: &source,
            image: &img,
        }],
        &inv,
    );
    assert!(out
        .iter()
        .all(|v| v.is_finite() && (0.0..=1.0 + 1e-6).contains(v)));
    let hw = Region::full(&intr).len();
    let last_alpha = &out[(15 * 4 + 3) * hw..(15 * 4 + 4) * hw];
    assert!(
        last_alpha.iter().any(|&a| a > 0.99),
        "the far plane must be visible"
    );
}

#[test]
fn distortion_never_folds_points_back_into_the_image() {
    let d = Distortion {
        k1: 0.058,
        k2: -0.081,
        p1: 0.0,
        p2: 0.0,
    };
    let s_max = d.max_radius2();
    let slope = |s: f64| 1.0 + 3.0 * d.k1 * s + 5.0 * d.k2 * s * s;
    assert!(
        slope(s_max * 0.999) > 0.0 && slope(s_max * 1.001) < 0.0,
        "{s_max}"
    );
    assert_eq!(
        Distortion {
            k1: 0.1,
            k2: 0.01,
            ..d
        }
        .max_radius2(),
        f64::INFINITY
    );
    assert!(
        (Distortion {
            k1: -0.2,
            k2: 0.0,
            ..d
        }
        .max_radius2()
            - 1.0 / 0.6)
            .abs()
            < 1e-12
    );
    // A source whose image reaches beyond the fold radius, seen from a wide pinhole
    // target at the same place: rays past the fold must not be sampled.
    let mut si = Intrinsics::pinhole(20.0, 20.0, 32.0, 24.0, 64, 48);
    si.distortion = Some(d);
    let ti = Intrinsics::pinhole(8.0, 8.0, 32.0, 24.0, 64, 48);
    let source = cam(DMat3::IDENTITY, DVec3::ZERO, si);
    let target = cam(DMat3::IDENTITY, DVec3::ZERO, ti);
    let img = noise_image(64, 48, 2);
    let out = sweep(
        &target,
        Region::full(&ti),
        &[Source {
            camera: &source,
            image: &img,
        }],
        &[0.5],
    );
    let hw = 64 * 48;
    let (mut beyond, mut seen) = (0, 0);
    for p in 0..hw {
        let ray = ti.unproject_pixel(DVec2::new((p % 64) as f64 + 0.5, (p / 64) as f64 + 0.5));
        let a = out[3 * hw + p];
        if ray.length_squared() > s_max {
            beyond += 1;
            assert_eq!(
                a,
                0.0,
                "pixel {p}: r^2 {} past the fold {s_max}",
                ray.length_squared()
            );
        } else if a > 0.99 {
            seen += 1;
        }
    }
    assert!(beyond > 100 && seen > 100, "beyond {beyond}, seen {seen}");
}
