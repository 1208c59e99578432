//! Unit tests of the plane sweep against analytic renderings and f64 references
//! (extreme geometry is in `tests_extreme.rs`).
use super::*;
use crate::camera::Distortion;
use crate::geometry::inverse_depths;
use glam::{DMat3, DVec3};

/// Deterministic pseudo-random numbers in [0, 1) (SplitMix64).
pub(super) struct Rng(pub(super) u64);
impl Rng {
    pub(super) fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    pub(super) fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.next()
    }
}

pub(super) fn cam(r: DMat3, centre: DVec3, intr: Intrinsics) -> Camera {
    Camera {
        intrinsics: intr,
        pose: WorldToCamera::new_checked(r, -(r * centre)).unwrap(),
        rolling_shutter: None,
    }
}

pub(super) fn noise_image(w: u32, h: u32, seed: u64) -> RgbImage {
    let mut rng = Rng(seed);
    let mut img = RgbImage::new(w, h);
    img.data.iter_mut().for_each(|v| *v = rng.next() as f32);
    img
}

/// Smooth colour texture of the plane point `(x, y)` (target camera coordinates).
fn texture(x: f64, y: f64) -> [f64; 3] {
    [
        0.5 + 0.2 * (6.0 * x + 2.6 * y).sin() + 0.1 * (4.2 * y).cos(),
        0.5 + 0.25 * (4.4 * x - 5.8 * y + 0.4).sin(),
        0.45 + 0.15 * (3.4 * x).cos() * (4.6 * y + 1.0).sin() + 0.1 * (6.2 * y).sin(),
    ]
}

/// Renders the plane `z = depth` of `target`'s camera frame, textured with
/// [`texture`], as seen by `cam` (ray-plane intersection, `ss x ss` supersampling).
/// A rolling-shutter `cam` sees each sub-sample from the pose of its own time.
pub(super) fn render_plane(
    cam: &Camera,
    target: &WorldToCamera,
    depth: f64,
    ss: usize,
) -> RgbImage {
    let k = &cam.intrinsics;
    let mut img = RgbImage::new(k.width, k.height);
    for j in 0..k.height {
        for i in 0..k.width {
            let mut acc = [0.0f64; 3];
            for (a, b) in (0..ss * ss).map(|s| (s % ss, s / ss)) {
                let uv = DVec2::new(
                    i as f64 + (a as f64 + 0.5) / ss as f64,
                    j as f64 + (b as f64 + 0.5) / ss as f64,
                );
                let c2w = cam.pose_at_pixel(uv).inverse();
                let origin = target.transform_point(c2w.translation);
                let dir = target.rotation
                    * (c2w.rotation * cam.intrinsics.unproject_pixel(uv).extend(1.0));
                let s = (depth - origin.z) / dir.z;
                assert!(s > 0.0, "the plane must fill every source view");
                let p = origin + dir * s;
                let t = texture(p.x, p.y);
                (0..3).for_each(|c| acc[c] += t[c] / (ss * ss) as f64);
            }
            let o = (j as usize * k.width as usize + i as usize) * 3;
            (0..3).for_each(|c| img.data[o + c] = acc[c] as f32);
        }
    }
    img
}

/// PSNR of slice `[4, h, w]` against `reference` over the pixels with alpha = 1,
/// and the fraction of such pixels.
pub(super) fn psnr_where_opaque(slice: &[f32], reference: &RgbImage) -> (f64, f64) {
    let hw = slice.len() / CHANNELS;
    let (mut se, mut n) = (0.0f64, 0usize);
    for p in 0..hw {
        if slice[3 * hw + p] >= 1.0 - 1e-6 {
            for c in 0..3 {
                let d = (slice[c * hw + p] - reference.data[p * 3 + c]) as f64;
                se += d * d;
            }
            n += 1;
        }
    }
    (
        10.0 * (1.0 / (se / (3 * n).max(1) as f64)).log10(),
        n as f64 / hw as f64,
    )
}

#[test]
fn textured_plane_is_reproduced_at_its_depth() {
    let intr = Intrinsics::pinhole(60.0, 62.0, 32.3, 23.8, 64, 48);
    let r_t = DMat3::from_rotation_y(0.1) * DMat3::from_rotation_x(-0.05);
    let target = cam(r_t, DVec3::new(0.2, -0.1, 0.3), intr);
    let depth = 3.0;
    let centre = target.pose.centre();
    let mut sources = Vec::new();
    for (k, (dx, dy, dz, ry)) in [
        (0.5, 0.0, 0.1, -0.1),
        (-0.4, 0.25, -0.3, 0.08),
        (0.05, -0.5, 0.4, 0.02),
    ]
    .into_iter()
    .enumerate()
    {
        let mut si = intr;
        si.fx *= 1.0 + 0.1 * k as f64;
        si.cx += 2.0 * k as f64;
        let r = DMat3::from_rotation_y(ry) * DMat3::from_rotation_z(0.03 * k as f64) * r_t;
        sources.push(cam(
            r,
            centre + r_t.transpose() * DVec3::new(dx, dy, dz),
            si,
        ));
    }
    let images: Vec<RgbImage> = sources
        .iter()
        .map(|c| render_plane(c, &target.pose, depth, 4))
        .collect();
    let reference = render_plane(&target, &target.pose, depth, 4);
    let srcs: Vec<Source> = sources
        .iter()
        .zip(&images)
        .map(|(camera, image)| Source { camera, image })
        .collect();
    let wrong = 1.0 / (1.5 * depth);
    let out = sweep(&target, Region::full(&intr), &srcs, &[1.0 / depth, wrong]);
    let n = CHANNELS * Region::full(&intr).len();
    for k in 0..srcs.len() {
        let (psnr, covered) = psnr_where_opaque(&out[k * n..(k + 1) * n], &reference);
        assert!(
            covered > 0.5,
            "source {k}: only {covered} of the target covered"
        );
        println!("source {k}: PSNR {psnr:.2} dB, covered {covered:.2}");
        // The issue asks for > 40 dB; the sweep gives 56-63 dB here, and a homography
        // whose depth is off by 2% still gives 41-43 dB, so hold it to 50.
        assert!(
            psnr > 50.0,
            "source {k}: PSNR {psnr:.2} dB at the plane's depth"
        );
        // The test discriminates: the wrong plane does not reproduce the target.
        let (bad, _) = psnr_where_opaque(
            &out[(srcs.len() + k) * n..(srcs.len() + k + 1) * n],
            &reference,
        );
        assert!(
            bad < psnr - 10.0,
            "source {k}: wrong plane PSNR {bad:.2} vs {psnr:.2}"
        );
    }
}

#[test]
fn target_swept_into_itself_is_identity() {
    let mut intr = Intrinsics::pinhole(45.0, 47.0, 20.7, 15.1, 41, 31);
    let pose = WorldToCamera::new_checked(DMat3::from_rotation_z(0.4), DVec3::new(1.0, 2.0, -3.0))
        .unwrap();
    let img = noise_image(41, 31, 7);
    for distortion in [
        None,
        Some(Distortion {
            k1: 0.058,
            k2: -0.081,
            p1: -0.001,
            p2: 0.0002,
        }),
    ] {
        intr.distortion = distortion;
        let camera = Camera::global(intr, pose);
        let src = [Source {
            camera: &camera,
            image: &img,
        }];
        let inv = [10.0, 1.0, 0.01, 0.0];
        let out = sweep(&camera, Region::full(&intr), &src, &inv);
        let hw = Region::full(&intr).len();
        let mut worst = 0.0f32;
        for d in 0..inv.len() {
            let s = &out[d * 4 * hw..(d + 1) * 4 * hw];
            for p in 0..hw {
                for c in 0..3 {
                    worst = worst.max((s[c * hw + p] - img.data[p * 3 + c]).abs());
                }
                worst = worst.max((s[3 * hw + p] - 1.0).abs());
            }
        }
        println!("identity sweep, distortion {distortion:?}: max |error| {worst:e}");
        // Unprojecting and projecting again (undistorting by fixed-point iteration and
        // distorting again) is exact to f64 rounding, which the f32 output does not show.
        assert_eq!(
            worst, 0.0,
            "{distortion:?}: the identity sweep is not exact"
        );
    }
}

/// The straightforward zero-padded bilinear sample (`floor`, every tap checked), the
/// reference for [`sample_bilinear`]'s faster paths.
fn reference_bilinear(img: &RgbImage, u: f64, v: f64) -> [f32; 4] {
    let (sx, sy) = (u - 0.5, v - 0.5);
    let (fx, fy) = (sx.floor(), sy.floor());
    let (ax, ay) = (sx - fx, sy - fy);
    let mut acc = [0.0f64; 4];
    let taps = [
        (fx, fy, (1.0 - ax) * (1.0 - ay)),
        (fx + 1.0, fy, ax * (1.0 - ay)),
        (fx, fy + 1.0, (1.0 - ax) * ay),
        (fx + 1.0, fy + 1.0, ax * ay),
    ];
    for (x, y, wt) in taps {
        if x >= 0.0 && y >= 0.0 && x < img.width as f64 && y < img.height as f64 {
            let i = (y as usize * img.width as usize + x as usize) * 3;
            (0..3).for_each(|c| acc[c] += wt * img.data[i + c] as f64);
            acc[3] += wt;
        }
    }
    acc.map(|v| v as f32)
}

#[test]
fn sample_bilinear_matches_reference_everywhere() {
    let img = noise_image(13, 9, 5);
    let mut rng = Rng(17);
    let mut coords: Vec<(f64, f64)> = (0..20000)
        .map(|_| (rng.range(-2.0, 15.0), rng.range(-2.0, 11.0)))
        .collect();
    // Pixel centres, edges and corners exactly, and NaN / infinite coordinates.
    for (u, v) in [
        (0.5, 0.5),
        (0.0, 0.0),
        (-0.5, 4.5),
        (13.0, 9.0),
        (12.5, 8.5),
        (13.5, 2.0),
    ] {
        coords.push((u, v));
    }
    coords.extend([(f64::NAN, 1.0), (1.0, f64::INFINITY), (-1e300, 2.0)]);
    for (u, v) in coords {
        let (got, want) = (sample_bilinear(&img, u, v), reference_bilinear(&img, u, v));
        let want = if want.iter().all(|x| x.is_finite()) {
            want
        } else {
            [0.0; 4]
        };
        assert_eq!(got, want, "at ({u}, {v})");
        assert!(got[3] <= 1.0 && got[..3].iter().all(|&c| c <= got[3] + 1e-7));
    }
}

/// Per-pixel f64 reference: unproject the target pixel to the plane, project it into
/// the source, sample (alpha 0 behind the source).
pub(super) fn reference_slice(target: &Camera, src: &Source, rho: f64, region: Region) -> Vec<f32> {
    let hw = region.len();
    let mut out = vec![0.0f32; 4 * hw];
    let ct = target.pose.inverse();
    for p in 0..hw {
        let uv = DVec2::new(
            (region.x0 + (p % region.width) as i64) as f64 + 0.5,
            (region.y0 + (p / region.width) as i64) as f64 + 0.5,
        );
        let n = target.intrinsics.unproject_pixel(uv).extend(1.0);
        // Plane point in homogeneous form (x, y, 1, rho) handles rho = 0 too.
        let x_src = src.camera.pose.rotation * (ct.rotation * n)
            + (src.camera.pose.rotation * ct.translation + src.camera.pose.translation) * rho;
        if x_src.z > 1e-9 * x_src.length() {
            let uv = src
                .camera
                .intrinsics
                .project_normalized(DVec2::new(x_src.x / x_src.z, x_src.y / x_src.z));
            let s = reference_bilinear(src.image, uv.x, uv.y);
            (0..4).for_each(|c| out[c * hw + p] = s[c]);
        }
    }
    out
}

#[test]
fn sweep_matches_f64_point_projection() {
    let mut rng = Rng(3);
    let mut worst = 0.0f32;
    let region = Region {
        x0: -5,
        y0: 3,
        width: 37,
        height: 29,
    };
    for trial in 0..6 {
        let mut ti = Intrinsics::pinhole(
            rng.range(30.0, 80.0),
            rng.range(30.0, 80.0),
            20.0,
            16.0,
            40,
            32,
        );
        let mut si = Intrinsics::pinhole(
            rng.range(30.0, 80.0),
            rng.range(30.0, 80.0),
            18.0,
            14.0,
            36,
            28,
        );
        if trial % 2 == 1 {
            ti.distortion = Some(Distortion {
                k1: 0.05,
                k2: -0.02,
                p1: 0.001,
                p2: -0.001,
            });
            si.distortion = Some(Distortion {
                k1: -0.04,
                k2: 0.01,
                p1: 0.0,
                p2: 0.002,
            });
        }
        let rt = DMat3::from_euler(
            glam::EulerRot::XYZ,
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        );
        let target = cam(
            rt,
            DVec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), 0.0),
            ti,
        );
        let rs = DMat3::from_rotation_y(rng.range(-0.5, 0.5)) * rt;
        let source = cam(
            rs,
            target.pose.centre()
                + DVec3::new(
                    rng.range(-0.5, 0.5),
                    rng.range(-0.5, 0.5),
                    rng.range(-0.5, 0.5),
                ),
            si,
        );
        let img = noise_image(36, 28, trial);
        let src = [Source {
            camera: &source,
            image: &img,
        }];
        let inv = inverse_depths(0.5, f64::INFINITY, 5);
        let out = sweep(&target, region, &src, &inv);
        let mut opaque = 0;
        for (d, &rho) in inv.iter().enumerate() {
            let want = reference_slice(&target, &src[0], rho, region);
            let got = &out[d * want.len()..(d + 1) * want.len()];
            for (g, w) in got.iter().zip(&want) {
                worst = worst.max((g - w).abs());
                assert!((g - w).abs() < 1e-6, "trial {trial} plane {d}: {g} vs {w}");
            }
            opaque += want
                .iter()
                .skip(3 * region.len())
                .filter(|&&a| a > 0.99)
                .count();
        }
        assert!(
            opaque > 0,
            "trial {trial}: nothing visible, the test would be vacuous"
        );
    }
    println!("sweep vs f64 point projection: max |difference| {worst:e}");
}
