//! Geometry and plane-sweep cases: every volume must be finite with alpha in [0, 1] and
//! colours premultiplied (`0 <= rgb <= alpha` for images in [0, 1]); each is compared with
//! an f64 reference that goes through world points and `Camera::project` instead of the
//! sweep's relative pose and plane homography, and with exact answers where they exist.

use super::table::{fmt_err, row, row_text};
use deepstereo_core::camera::{Camera, Intrinsics, WorldToCamera};
use deepstereo_core::geometry::{apply_h, inverse_depths, plane_homography};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::sweep::{sample_bilinear, sweep, Region, Source, CHANNELS};
use glam::{DMat3, DVec2, DVec3};
use std::f64::consts::PI;

pub const W: u32 = 40;
pub const H: u32 = 32;
/// Largest accepted difference from the f64 reference (RGBA, images in [0, 1]).
const REF_TOL: f64 = 1e-5;

pub fn intr(f: f64) -> Intrinsics {
    Intrinsics::pinhole(f, f, W as f64 / 2.0, H as f64 / 2.0, W, H)
}

/// A camera at `centre` with world-to-camera rotation `r`.
pub fn cam(r: DMat3, centre: DVec3, k: Intrinsics) -> Camera {
    Camera {
        intrinsics: k,
        pose: WorldToCamera::new_checked(r, -(r * centre)).expect("valid pose"),
        rolling_shutter: None,
    }
}

/// A camera at `centre` looking along `forward`, image rows along `down` (OpenCV axes).
pub fn look(centre: DVec3, forward: DVec3, down: DVec3, k: Intrinsics) -> Camera {
    let z = forward.normalize();
    let x = down.cross(z).normalize();
    let y = z.cross(x);
    cam(DMat3::from_cols(x, y, z).transpose(), centre, k)
}

/// A deterministic noise image in [0, 1) (SplitMix64), so that any warp error shows.
pub fn noise(seed: u64) -> RgbImage {
    let mut s = seed;
    let mut img = RgbImage::new(W, H);
    for v in img.data.iter_mut() {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        *v = ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32;
    }
    img
}

/// The f64 reference of one volume sample: the target ray's point on the plane (or its
/// direction for `rho = 0`) in world coordinates, projected by the source camera; also
/// returns that pixel when the point is in front.
fn reference(
    target: &Camera,
    src: &Camera,
    img: &RgbImage,
    rho: f64,
    uv: DVec2,
) -> ([f32; 4], Option<DVec2>) {
    let n = target.intrinsics.unproject_pixel(uv).extend(1.0);
    let c2w = target.pose.inverse();
    let pc = if rho > 0.0 {
        src.pose
            .transform_point(c2w.rotation * (n / rho) + c2w.translation)
    } else {
        src.pose.rotation * (c2w.rotation * n)
    };
    if pc.z.is_nan() || pc.z <= 0.0 {
        return ([0.0; 4], None);
    }
    let p = src
        .intrinsics
        .project_normalized(DVec2::new(pc.x / pc.z, pc.y / pc.z));
    (sample_bilinear(img, p.x, p.y), Some(p))
}

/// The source pixel of a target ray on plane `rho` through the sweep's own geometry
/// (relative pose and plane homography in normalized coordinates).
fn homography_pixel(target: &Camera, src: &Camera, rho: f64, uv: DVec2) -> Option<DVec2> {
    let n = target.intrinsics.unproject_pixel(uv);
    let q = apply_h(
        &plane_homography(&target.pose.relative_to(&src.pose), rho),
        n.x,
        n.y,
    );
    (q.z > 0.0).then(|| {
        src.intrinsics
            .project_normalized(DVec2::new(q.x / q.z, q.y / q.z))
    })
}

/// A swept volume `[D, V, 4, H, W]` and what was measured on it.
pub struct Swept {
    pub vol: Vec<f32>,
    /// Worst |RGBA - f64 reference|.
    pub ref_err: f64,
    /// Worst distance (px) between the homography's and the reference's source pixel,
    /// over samples that land within a pixel of the source image.
    pub px_err: f64,
    /// Fraction of samples with alpha > 0.
    pub coverage: f64,
}

impl Swept {
    /// Slice `(plane d, view k, channel c)` as `[H * W]`.
    pub fn slice(&self, views: usize, d: usize, k: usize, c: usize) -> &[f32] {
        let hw = (W * H) as usize;
        let o = ((d * views + k) * CHANNELS + c) * hw;
        &self.vol[o..o + hw]
    }
}

/// Sweeps `sources` into `target` over the full image, asserting finiteness, alpha in
/// [0, 1] and premultiplied colours, and measuring the error against [`reference`].
pub fn sweep_checked(target: &Camera, sources: &[(Camera, RgbImage)], inv: &[f64]) -> Swept {
    let srcs: Vec<Source> = sources
        .iter()
        .map(|(c, i)| Source {
            camera: c,
            image: i,
        })
        .collect();
    let region = Region::full(&target.intrinsics);
    let vol = sweep(target, region, &srcs, inv);
    let (hw, v) = (region.len(), sources.len());
    let (mut ref_err, mut px_err, mut covered) = (0f64, 0f64, 0usize);
    for (d, &rho) in inv.iter().enumerate() {
        for (k, (src, img)) in sources.iter().enumerate() {
            let base = (d * v + k) * CHANNELS * hw;
            for p in 0..hw {
                let uv = DVec2::new((p % W as usize) as f64 + 0.5, (p / W as usize) as f64 + 0.5);
                let got: [f32; 4] = std::array::from_fn(|c| vol[base + c * hw + p]);
                assert!(
                    got.iter().all(|x| x.is_finite()),
                    "non-finite sample {got:?}"
                );
                let a = got[3];
                assert!((0.0..=1.0).contains(&a), "alpha {a} outside [0, 1]");
                assert!(
                    got[..3].iter().all(|&c| c >= 0.0 && c <= a + 1e-6),
                    "not premultiplied: {got:?}"
                );
                covered += (a > 0.0) as usize;
                let (want, at) = reference(target, src, img, rho, uv);
                let inside = |p: DVec2| {
                    p.x > -1.0 && p.y > -1.0 && p.x < W as f64 + 1.0 && p.y < H as f64 + 1.0
                };
                if let Some(p) = at.filter(|p| inside(*p)) {
                    let hp = homography_pixel(target, src, rho, uv).expect("in front for both");
                    px_err = px_err.max((hp - p).length());
                }
                for c in 0..4 {
                    ref_err = ref_err.max((got[c] as f64 - want[c] as f64).abs());
                }
            }
        }
    }
    let coverage = covered as f64 / (inv.len() * v * hw) as f64;
    Swept {
        vol,
        ref_err,
        px_err,
        coverage,
    }
}

/// Sweeps, checks, asserts the reference error and records the row.
fn case(
    name: &str,
    target: &Camera,
    sources: &[(Camera, RgbImage)],
    inv: &[f64],
    min_cover: f64,
) -> Swept {
    let s = sweep_checked(target, sources, inv);
    row_text(
        name,
        "finite, alpha in [0,1], premultiplied; vs f64 world-point reference: max abs RGBA error / max pixel error",
        &format!("{} / {} px", fmt_err(s.ref_err), fmt_err(s.px_err)),
    );
    assert!(
        s.ref_err <= REF_TOL,
        "{name}: error vs reference {:e}",
        s.ref_err
    );
    assert!(
        s.coverage >= min_cover,
        "{name}: coverage {} < {min_cover}",
        s.coverage
    );
    s
}

fn max_abs(a: &[f32]) -> f64 {
    a.iter().fold(0f64, |m, v| m.max(v.abs() as f64))
}

pub fn origin_target(f: f64) -> Camera {
    cam(DMat3::IDENTITY, DVec3::ZERO, intr(f))
}

#[test]
fn g01_grazing_planes() {
    let t = origin_target(30.0);
    let inv = [1.0, 0.5, 0.25, 0.0];
    // Sources just in front of the plane z = 2, looking along +x tilted towards it by delta.
    for (delta, label) in [
        (0.3f64, "0.3"),
        (1e-3, "1e-3"),
        (1e-6, "1e-6"),
        (0.0, "0 (parallel)"),
    ] {
        let fwd = DVec3::new(delta.cos(), 0.0, delta.sin());
        let s = look(DVec3::new(-1.0, 0.0, 1.95), fwd, DVec3::Y, intr(30.0));
        case(
            &format!("plane at grazing angle {label} rad to a source's axis"),
            &t,
            &[(s, noise(1))],
            &inv,
            0.01,
        );
    }
}

#[test]
fn g02_plane_through_source_centre() {
    let t = origin_target(30.0);
    let inv = [1.0, 0.5, 0.25];
    let c = DVec3::new(0.5, 0.1, 2.0); // on the plane z = 2 (rho = 0.5)
    let edge_on = look(c, DVec3::X, DVec3::Y, intr(30.0));
    let oblique = look(c, DVec3::new(1.0, 0.0, 1.0), DVec3::Y, intr(30.0));
    case(
        "plane through a source centre, source edge-on",
        &t,
        &[(edge_on, noise(2))],
        &inv,
        0.0,
    );
    case(
        "plane through a source centre, source at 45 degrees",
        &t,
        &[(oblique, noise(3))],
        &inv,
        0.0,
    );
    // Looking along the plane normal: every point of the plane is sideways (z = 0).
    let normal = cam(DMat3::IDENTITY, c, intr(30.0));
    let s = case(
        "plane through a source centre, source along the normal",
        &t,
        &[(normal, noise(4))],
        &inv,
        0.0,
    );
    let alpha = max_abs(s.slice(1, 1, 0, 3));
    row(
        "plane through a source centre, source along the normal",
        "RGBA of that plane = 0 (exact)",
        alpha,
    );
    assert_eq!(alpha, 0.0);
}

#[test]
fn g03_points_behind_source() {
    let t = origin_target(30.0);
    let inv = inverse_depths(1.0, 10.0, 10);
    let s = cam(
        DMat3::from_rotation_y(0.05),
        DVec3::new(0.3, -0.1, 4.0),
        intr(30.0),
    );
    let sw = case(
        "points behind a source (planes at depth 1..10, source at z = 4)",
        &t,
        &[(s, noise(5))],
        &inv,
        0.02,
    );
    let behind = inv.iter().enumerate().filter(|(_, r)| 1.0 / **r < 3.5);
    let worst = behind
        .map(|(d, _)| {
            (0..4)
                .map(|c| max_abs(sw.slice(1, d, 0, c)))
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max);
    row(
        "points behind a source (planes at depth 1..10, source at z = 4)",
        "RGBA of planes behind it = 0 (exact)",
        worst,
    );
    assert_eq!(worst, 0.0);
}

#[test]
fn g04_near_1e_4_far_infinity() {
    let t = origin_target(30.0);
    let inv = inverse_depths(1e-4, f64::INFINITY, 16);
    assert_eq!(inv[15], 0.0);
    let shifted = cam(DMat3::IDENTITY, DVec3::new(0.1, -0.05, 0.02), intr(30.0));
    let rotated = cam(
        DMat3::from_euler(glam::EulerRot::XYZ, 0.1, -0.2, 0.05),
        DVec3::new(-0.1, 0.0, 0.0),
        intr(30.0),
    );
    let img = noise(6);
    let s = case(
        "near = 1e-4, far = infinity (16 planes)",
        &t,
        &[(shifted, img.clone()), (rotated, noise(7))],
        &inv,
        0.05,
    );
    // At infinity a translated, unrotated source shows its image unchanged.
    let mut worst = 0f64;
    for c in 0..3 {
        let want = img.data.iter().skip(c).step_by(3);
        worst = s
            .slice(2, 15, 0, c)
            .iter()
            .zip(want)
            .fold(worst, |m, (a, b)| m.max((a - b).abs() as f64));
    }
    worst = s
        .slice(2, 15, 0, 3)
        .iter()
        .fold(worst, |m, a| m.max((a - 1.0).abs() as f64));
    row(
        "near = 1e-4, far = infinity (16 planes)",
        "plane at infinity of a translated source = its image",
        worst,
    );
    assert!(worst < 1e-6);
}

#[test]
fn g05_huge_and_tiny_focal_lengths() {
    let inv = inverse_depths(1.0, 10.0, 8);
    // f = 1e7: a 4e-6 rad field of view; baseline and rotation sized for pixel disparities.
    let t = origin_target(1e7);
    let s = cam(
        DMat3::from_rotation_y(2e-7),
        DVec3::new(1e-6, 2e-7, 0.0),
        intr(1e7),
    );
    case("focal length 1e7 px", &t, &[(s, noise(8))], &inv, 0.3);
    // f = 1e-3: the 40 px image spans almost a hemisphere.
    let t = origin_target(1e-3);
    let s = cam(
        DMat3::from_rotation_y(0.3),
        DVec3::new(0.5, 0.1, 0.0),
        intr(1e-3),
    );
    case("focal length 1e-3 px", &t, &[(s, noise(9))], &inv, 0.05);
    let t = origin_target(1e7);
    let s = cam(DMat3::IDENTITY, DVec3::new(0.0, 0.0, -1.0), intr(1e-3));
    case(
        "target focal 1e7 px, source focal 1e-3 px",
        &t,
        &[(s, noise(10))],
        &inv,
        0.0,
    );
    let t = origin_target(1e-3);
    let s = cam(DMat3::IDENTITY, DVec3::new(0.0, 0.0, -0.5), intr(1e7));
    case(
        "target focal 1e-3 px, source focal 1e7 px",
        &t,
        &[(s, noise(11))],
        &inv,
        0.0,
    );
}

#[test]
fn g06_principal_point_far_outside() {
    let inv = inverse_depths(1.0, 10.0, 8);
    // The target's principal point 1e4 px to the right: its rays look ~86 degrees left.
    let mut k = intr(30.0);
    k.cx = 1e4;
    k.cy = -5e3;
    let t = cam(DMat3::IDENTITY, DVec3::ZERO, k);
    let dir = t
        .intrinsics
        .unproject_pixel(DVec2::new(20.0, 16.0))
        .extend(1.0);
    let s = look(DVec3::new(0.2, 0.0, 0.0), dir, DVec3::Y, intr(30.0));
    let mut k2 = intr(30.0);
    k2.cx = -2e5;
    k2.cy = 3e5;
    let s2 = cam(DMat3::IDENTITY, DVec3::new(0.1, 0.0, 0.0), k2);
    case(
        "principal points 1e4 to 3e5 px outside the image",
        &t,
        &[(s, noise(12)), (s2, noise(13))],
        &inv,
        0.05,
    );
}

#[test]
fn g07_zero_baseline() {
    let inv = inverse_depths(0.5, 20.0, 8);
    let t = cam(
        DMat3::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 0.1),
        DVec3::new(1.0, 2.0, -3.0),
        intr(30.0),
    );
    let img = noise(14);
    let nudge = DMat3::from_rotation_z(1e-12) * t.pose.rotation;
    let near_twin = cam(nudge, t.pose.centre() + DVec3::splat(1e-12), intr(30.0));
    for (name, s) in [
        ("zero baseline (source = target)", t),
        ("near-zero baseline (1e-12 offset and rotation)", near_twin),
    ] {
        let sw = case(name, &t, &[(s, img.clone())], &inv, 0.99);
        let mut worst = 0f64;
        for d in 0..inv.len() {
            for c in 0..3 {
                let want = img.data.iter().skip(c).step_by(3);
                worst = sw
                    .slice(1, d, 0, c)
                    .iter()
                    .zip(want)
                    .fold(worst, |m, (a, b)| m.max((a - b).abs() as f64));
            }
            worst = sw
                .slice(1, d, 0, 3)
                .iter()
                .fold(worst, |m, a| m.max((a - 1.0).abs() as f64));
        }
        row(
            name,
            "every plane = the source image, alpha 1 (identity warp)",
            worst,
        );
        assert!(worst < 1e-6, "{name}: {worst:e}");
    }
}

#[test]
fn g08_rotations_of_180_degrees() {
    let inv = inverse_depths(1.0, 10.0, 8);
    let t = origin_target(30.0);
    let img = noise(15);
    // Roll by 180 degrees about the optical axis: the image turned upside down.
    let roll = cam(DMat3::from_rotation_z(PI), DVec3::ZERO, intr(30.0));
    let sw = case(
        "180-degree roll about the optical axis",
        &t,
        &[(roll, img.clone())],
        &inv,
        0.99,
    );
    let mut worst = 0f64;
    for d in 0..inv.len() {
        for p in 0..(W * H) as usize {
            let (x, y) = (p as u32 % W, p as u32 / W);
            let want = img.pixel(W - 1 - x, H - 1 - y);
            for (c, w) in want.iter().enumerate() {
                worst = worst.max((sw.slice(1, d, 0, c)[p] - w).abs() as f64);
            }
            worst = worst.max((sw.slice(1, d, 0, 3)[p] - 1.0).abs() as f64);
        }
    }
    row(
        "180-degree roll about the optical axis",
        "every plane = the source image turned by 180 degrees",
        worst,
    );
    assert!(worst < 1e-6);
    // Turned around at the same centre: every plane is behind the source.
    let back = cam(DMat3::from_rotation_y(PI), DVec3::ZERO, intr(30.0));
    let sw = case(
        "180-degree turn, same centre",
        &t,
        &[(back, noise(16))],
        &inv,
        0.0,
    );
    let worst = max_abs(&sw.vol);
    row(
        "180-degree turn, same centre",
        "RGBA = 0 everywhere (exact)",
        worst,
    );
    assert_eq!(worst, 0.0);
    // Turned around beyond the planes, looking back at them.
    let facing = cam(
        DMat3::from_rotation_y(PI),
        DVec3::new(0.2, 0.0, 12.0),
        intr(30.0),
    );
    case(
        "180-degree turn, source facing the target from z = 12",
        &t,
        &[(facing, noise(17))],
        &inv,
        0.05,
    );
}

/// A generic scene scaled by `s` and shifted by `offset`.
fn scene(s: f64, offset: DVec3) -> (Camera, Vec<(Camera, RgbImage)>, Vec<f64>) {
    let t = cam(
        DMat3::from_euler(glam::EulerRot::XYZ, 0.1, 0.2, -0.1),
        offset,
        intr(30.0),
    );
    let r1 = DMat3::from_euler(glam::EulerRot::XYZ, 0.15, 0.1, 0.0);
    let r2 = DMat3::from_euler(glam::EulerRot::XYZ, 0.05, 0.3, 0.02);
    let sources = vec![
        (
            cam(r1, offset + DVec3::new(0.3, -0.1, 0.05) * s, intr(30.0)),
            noise(18),
        ),
        (
            cam(r2, offset + DVec3::new(-0.25, 0.2, -0.1) * s, intr(28.0)),
            noise(19),
        ),
    ];
    let inv = inverse_depths(s, 10.0 * s, 8);
    (t, sources, inv)
}

#[test]
fn g09_scene_scale_and_offset() {
    let (t, srcs, inv) = scene(1.0, DVec3::ZERO);
    let base = sweep_checked(&t, &srcs, &inv);
    for (name, s, off) in [
        ("scene scale 1e6 (coordinates and depths)", 1e6, DVec3::ZERO),
        (
            "scene scale 1e-6 (coordinates and depths)",
            1e-6,
            DVec3::ZERO,
        ),
        (
            "scene 1e6 away from the origin (baseline 0.3)",
            1.0,
            DVec3::new(1e6, -1e6, 1e6),
        ),
    ] {
        let (t, srcs, inv) = scene(s, off);
        let sw = case(name, &t, &srcs, &inv, 0.3);
        let worst = sw
            .vol
            .iter()
            .zip(&base.vol)
            .fold(0f64, |m, (a, b)| m.max((a - b).abs() as f64));
        row(
            name,
            "same volume as at scale 1 at the origin (invariance)",
            worst,
        );
        assert!(worst < 1e-5, "{name}: {worst:e}");
    }
}
