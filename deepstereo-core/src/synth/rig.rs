//! Camera rigs: random intrinsics and the poses of a scene's views.
//!
//! The world frame is that of a reference camera at the origin looking down +z (OpenCV
//! axes: x right, y down). Every rig keeps all of its rays pointing into the +z half
//! space (checked), so the backdrop plane `z = const` behind the content fills every view.
//! Baselines are chosen from a target disparity between neighbouring views at the nearest
//! content depth `d0`, a fraction [`NEIGHBOUR_DISPARITY`] of the image's larger side.

use super::rng::Rng;
use super::Rig;
use crate::camera::{Camera, CameraToWorld, Intrinsics};
use crate::error::{Error, Result};
use glam::{DMat3, DVec2, DVec3};

/// Focal length range, as a multiple of the image's larger side (its width for
/// landscape images).
pub const FOCAL_RANGE: (f64, f64) = (0.8, 1.4);
/// Largest offset of the principal point from the image centre, as a fraction of the size.
pub const PRINCIPAL_OFFSET: f64 = 0.05;
/// Largest relative difference between `fy` and `fx`.
const PIXEL_ASPECT_JITTER: f64 = 0.02;
/// Largest relative change of the focal length from one frame to another.
const FRAME_FOCAL_JITTER: f64 = 0.01;
/// Largest per-frame shift of the principal point, as a fraction of the size.
const FRAME_PRINCIPAL_JITTER: f64 = 0.005;
/// Disparity between neighbouring views at the nearest content, as a fraction of the
/// image's larger side.
pub const NEIGHBOUR_DISPARITY: (f64, f64) = (0.05, 0.15);
/// Log-uniform range of the nearest content depth, for rigs without a natural scale.
const SCENE_SCALE: (f64, f64) = (1.0, 10.0);
/// Rosette: distance between rig positions, in world units.
const ROSETTE_SPACING: (f64, f64) = (0.3, 3.0);
/// Rosette: yaw step between the cameras of one position, as a fraction of the FOV.
const ROSETTE_YAW_STEP: (f64, f64) = (0.08, 0.14);
/// Rosette: radius of the ring the cameras of one position sit on, times the spacing.
const ROSETTE_RADIUS: f64 = 0.05;
/// Rosette: largest angle of the direction of travel from the x axis (degrees).
const ROSETTE_TRAVEL_DEG: f64 = 35.0;
/// Ring: distance from the cameras to the cluster centre, times `d0`.
const RING_DISTANCE: (f64, f64) = (2.2, 3.0);
/// Ring: cluster radius, times the distance.
const RING_CLUSTER: (f64, f64) = (0.2, 0.3);
/// Ring: disparity at infinity between neighbours, times the target neighbour disparity
/// (content nearer than the cluster moves the other way, by more).
const RING_STEP_SCALE: f64 = 0.6;
/// Ring: largest angle of a camera on the arc from the central one (degrees).
const RING_MAX_HALF_SPAN_DEG: f64 = 35.0;
/// Handheld: step length range, times the neighbour baseline.
const HANDHELD_STEP: (f64, f64) = (0.5, 1.0);
/// Handheld: bounds of the yaw, pitch and roll random walks (degrees).
const HANDHELD_ANGLES_DEG: [f64; 3] = [8.0, 5.0, 3.0];
/// Every ray's world direction must be within this angle of +z (degrees).
const MAX_RAY_TILT_DEG: f64 = 85.0;

/// The cameras of a scene and the scale the content is built at.
pub(crate) struct RigLayout {
    pub cameras: Vec<Camera>,
    /// Nearest content depth, in world units.
    pub d0: f64,
    /// Ring: centre and radius of the object cluster the cameras look at.
    pub focus: Option<(DVec3, f64)>,
}

/// A camera-to-world rotation for yaw (about y, turning right), pitch and roll.
fn ypr(yaw: f64, pitch: f64, roll: f64) -> DMat3 {
    DMat3::from_rotation_y(yaw) * DMat3::from_rotation_x(pitch) * DMat3::from_rotation_z(roll)
}

/// A camera-to-world rotation looking from `c` at `target`, image y pointing down.
fn look_at(c: DVec3, target: DVec3, roll: f64) -> DMat3 {
    let z = (target - c).normalize();
    let x = DVec3::Y.cross(z).normalize();
    let y = z.cross(x);
    DMat3::from_cols(x, y, z) * DMat3::from_rotation_z(roll)
}

fn deg(d: f64) -> f64 {
    d.to_radians()
}

/// Random intrinsics for a `width x height` image.
fn base_intrinsics(rng: &mut Rng, width: u32, height: u32) -> Intrinsics {
    let (w, h) = (width as f64, height as f64);
    let fx = w.max(h) * rng.range(FOCAL_RANGE.0, FOCAL_RANGE.1);
    let fy = fx * (1.0 + rng.sym(PIXEL_ASPECT_JITTER));
    let cx = 0.5 * w + rng.sym(PRINCIPAL_OFFSET * w);
    let cy = 0.5 * h + rng.sym(PRINCIPAL_OFFSET * h);
    Intrinsics::pinhole(fx, fy, cx, cy, width, height)
}

/// The base intrinsics changed slightly for one frame.
fn frame_intrinsics(rng: &mut Rng, k: &Intrinsics) -> Intrinsics {
    let s = 1.0 + rng.sym(FRAME_FOCAL_JITTER);
    let (w, h) = (k.width as f64, k.height as f64);
    Intrinsics::pinhole(
        k.fx * s,
        k.fy * s,
        k.cx + rng.sym(FRAME_PRINCIPAL_JITTER * w),
        k.cy + rng.sym(FRAME_PRINCIPAL_JITTER * h),
        k.width,
        k.height,
    )
}

/// Builds the cameras of a concrete rig (the caller resolves [`Rig::Mixed`]; here it
/// falls back to handheld).
pub(crate) fn build(
    rig: Rig,
    rng: &mut Rng,
    views: usize,
    width: u32,
    height: u32,
) -> Result<RigLayout> {
    let base = base_intrinsics(rng, width, height);
    let disp = rng.range(NEIGHBOUR_DISPARITY.0, NEIGHBOUR_DISPARITY.1) * width.max(height) as f64;
    let f = base.fx;
    let hfov = 2.0 * (0.5 * width as f64 / f).atan();
    let (poses, d0, focus) = match rig {
        Rig::Forward => forward(rng, views, f, disp),
        Rig::Rosette => rosette(rng, views, f, disp, hfov),
        Rig::Ring => ring(rng, views, f, disp),
        Rig::Handheld | Rig::Mixed => handheld(rng, views, f, disp),
    };
    let mut cameras = Vec::with_capacity(views);
    for (i, (centre, r_c2w)) in poses.into_iter().enumerate() {
        let intrinsics = frame_intrinsics(rng, &base);
        let pose = CameraToWorld::new_checked(r_c2w, centre)
            .map_err(|m| {
                Error::Invalid(format!(
                    "synth: {rig} rig made a bad pose for view {i}: {m}"
                ))
            })?
            .inverse();
        let cam = Camera::global(intrinsics, pose);
        check_rays(&cam).map_err(|m| Error::Invalid(format!("synth: {rig} rig, view {i}: {m}")))?;
        cameras.push(cam);
    }
    Ok(RigLayout { cameras, d0, focus })
}

/// Checks that the rays through the image corners point into the +z half space.
pub(crate) fn check_rays(cam: &Camera) -> std::result::Result<(), String> {
    let k = &cam.intrinsics;
    let (w, h) = (k.width as f64, k.height as f64);
    let r_c2w = cam.pose.rotation.transpose();
    let min_z = deg(90.0 - MAX_RAY_TILT_DEG).sin();
    for uv in [
        DVec2::ZERO,
        DVec2::new(w, 0.0),
        DVec2::new(0.0, h),
        DVec2::new(w, h),
    ] {
        let n = k.unproject_pixel(uv);
        let d = (r_c2w * DVec3::new(n.x, n.y, 1.0)).normalize();
        if d.z < min_z {
            return Err(format!(
                "a corner ray points {:.1} deg away from +z",
                d.z.acos().to_degrees()
            ));
        }
    }
    Ok(())
}

type Poses = (Vec<(DVec3, DMat3)>, f64, Option<(DVec3, f64)>);

/// LLFF-like: a jittered grid on a plane, parallel or converging slightly.
fn forward(rng: &mut Rng, views: usize, f: f64, disp: f64) -> Poses {
    let d0 = rng.log_range(SCENE_SCALE.0, SCENE_SCALE.1);
    let b = d0 * disp / f;
    let cols = ((views as f64 * 4.0 / 3.0).sqrt().ceil() as usize).max(1);
    let rows = views.div_ceil(cols);
    let by = b * rng.range(0.8, 1.2);
    let converge = rng.chance(0.5).then(|| rng.range(3.0, 20.0) * d0);
    let poses = (0..views)
        .map(|i| {
            let (c, r) = ((i % cols) as f64, (i / cols) as f64);
            let centre = DVec3::new(
                (c - 0.5 * (cols - 1) as f64) * b + rng.sym(0.1 * b),
                (r - 0.5 * (rows - 1) as f64) * by + rng.sym(0.1 * b),
                rng.sym(0.05 * b),
            );
            let jitter = ypr(rng.sym(deg(1.5)), rng.sym(deg(1.5)), rng.sym(deg(1.0)));
            let rot = match converge {
                Some(z) => look_at(centre, DVec3::new(0.0, 0.0, z), 0.0) * jitter,
                None => jitter,
            };
            (centre, rot)
        })
        .collect();
    (poses, d0, None)
}

/// Street-View-like: a few rig positions along a path, each with cameras at several yaws.
fn rosette(rng: &mut Rng, views: usize, f: f64, disp: f64, hfov: f64) -> Poses {
    let s = rng.range(ROSETTE_SPACING.0, ROSETTE_SPACING.1);
    let d0 = f * s / disp;
    let per = rng.int_in(2, 3).min(views);
    let positions = views.div_ceil(per);
    let step = hfov * rng.range(ROSETTE_YAW_STEP.0, ROSETTE_YAW_STEP.1);
    let a = rng.sym(deg(ROSETTE_TRAVEL_DEG));
    let dir = DVec3::new(a.cos(), rng.sym(0.1), a.sin()).normalize();
    let heading0 = rng.sym(deg(10.0));
    let mut poses = Vec::with_capacity(views);
    for k in 0..positions {
        let jitter = DVec3::new(rng.sym(0.1 * s), rng.sym(0.1 * s), rng.sym(0.1 * s));
        let p = dir * ((k as f64 - 0.5 * (positions - 1) as f64) * s) + jitter;
        let heading = heading0 + rng.sym(deg(2.0));
        let pitch = rng.sym(deg(3.0));
        for j in 0..per {
            if poses.len() == views {
                break;
            }
            let yaw = heading + (j as f64 - 0.5 * (per - 1) as f64) * step;
            let fwd = DVec3::new(yaw.sin(), 0.0, yaw.cos());
            let rot = ypr(yaw, pitch + rng.sym(deg(1.0)), rng.sym(deg(1.0)));
            poses.push((p + fwd * (ROSETTE_RADIUS * s), rot));
        }
    }
    (poses, d0, None)
}

/// An arc of cameras around a central object cluster, all looking at it.
fn ring(rng: &mut Rng, views: usize, f: f64, disp: f64) -> Poses {
    let d0 = rng.log_range(SCENE_SCALE.0, SCENE_SCALE.1);
    let dist = d0 * rng.range(RING_DISTANCE.0, RING_DISTANCE.1);
    let radius = dist * rng.range(RING_CLUSTER.0, RING_CLUSTER.1);
    let focus = DVec3::new(0.0, 0.0, dist);
    let span = 2.0 * deg(RING_MAX_HALF_SPAN_DEG) * 0.9;
    let dtheta = (RING_STEP_SCALE * disp / f).min(span / (views.max(2) - 1) as f64);
    let elev0 = rng.sym(deg(5.0));
    let poses = (0..views)
        .map(|i| {
            let theta = (i as f64 - 0.5 * (views - 1) as f64) * dtheta + rng.sym(0.05 * dtheta);
            let phi = elev0 + rng.sym(deg(2.0));
            let offset = DVec3::new(theta.sin() * phi.cos(), phi.sin(), theta.cos() * phi.cos());
            let centre = focus - offset * dist;
            let aim = focus + DVec3::new(rng.sym(0.05), rng.sym(0.05), rng.sym(0.05)) * radius;
            (centre, look_at(centre, aim, rng.sym(deg(1.5))))
        })
        .collect();
    (poses, d0, Some((focus, radius)))
}

/// A jittered random-walk path with small, bounded rotations.
fn handheld(rng: &mut Rng, views: usize, f: f64, disp: f64) -> Poses {
    let d0 = rng.log_range(SCENE_SCALE.0, SCENE_SCALE.1);
    let b = d0 * disp / f;
    let lim = HANDHELD_ANGLES_DEG.map(deg);
    let mut heading = rng.range(0.0, std::f64::consts::TAU);
    let mut angles = [
        rng.sym(lim[0] * 0.6),
        rng.sym(lim[1] * 0.6),
        rng.sym(lim[2] * 0.6),
    ];
    let mut pos = DVec3::ZERO;
    let mut poses = Vec::with_capacity(views);
    for _ in 0..views {
        poses.push((pos, ypr(angles[0], angles[1], angles[2])));
        heading += 0.5 * rng.normal();
        let step = b * rng.range(HANDHELD_STEP.0, HANDHELD_STEP.1);
        pos += DVec3::new(heading.cos(), 0.6 * heading.sin(), rng.sym(0.3)) * step;
        for (a, l) in angles.iter_mut().zip(lim) {
            *a = (*a + deg(0.6) * rng.normal()).clamp(-l, l);
        }
    }
    let mean = poses.iter().map(|p| p.0).sum::<DVec3>() / views.max(1) as f64;
    for p in &mut poses {
        p.0 -= mean;
    }
    (poses, d0, None)
}
