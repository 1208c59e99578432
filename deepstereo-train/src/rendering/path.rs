//! Camera paths through a scene's views, and rendering them frame by frame, for `render
//! --path` and `demo`.
//!
//! - `spiral`, `circle`, `line` (LLFF's): around the mean pose, for forward-facing captures.
//! - `orbit`: around the point the cameras look at ([`look_at_point`]), at their median
//!   distance and height, over the azimuths they cover (a full turn when they surround it).
//! - `interpolate`: a Catmull-Rom spline through the camera centres in capture order, the
//!   orientations slerped between them.
//! - `auto`: spiral for a forward-facing capture, orbit for one around an object
//!   ([`capture_kind`]).

use crate::rendering::{pick_planned_sources, render_camera, Prepared, RenderSettings};
use anyhow::{bail, Context, Result};
use deepstereo_core::camera::{Camera, Intrinsics, WorldToCamera};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use glam::{DMat3, DQuat, DVec3};
use std::path::Path;

/// The shape of a camera path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PathKind {
    Spiral,
    Circle,
    Line,
    Orbit,
    Interpolate,
    /// Spiral or orbit, whichever suits the capture.
    Auto,
}

impl PathKind {
    /// Every name [`Self::parse`] takes.
    pub const NAMES: &'static str = "auto, spiral, circle, line, orbit, interpolate";

    /// The kind of a name, `None` for any other.
    pub fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "spiral" => Self::Spiral,
            "circle" => Self::Circle,
            "line" => Self::Line,
            "orbit" => Self::Orbit,
            "interpolate" => Self::Interpolate,
            "auto" => Self::Auto,
            _ => return None,
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Spiral => "spiral",
            Self::Circle => "circle",
            Self::Line => "line",
            Self::Orbit => "orbit",
            Self::Interpolate => "interpolate",
            Self::Auto => "auto",
        }
    }
}

/// Viewing directions spread (90th percentile angle from their mean) beyond which a
/// capture is taken to be around an object rather than forward-facing, in degrees: LLFF's
/// forward-facing captures stay within about 4-18 degrees of one direction.
pub const FORWARD_SPREAD_DEG: f64 = 30.0;

/// How the cameras of a capture are laid out, as [`capture_kind`] finds it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CaptureKind {
    /// The 90th percentile angle between a view's direction and the mean, in degrees.
    pub spread_deg: f64,
    /// Whether it is forward-facing (`spread_deg` at most [`FORWARD_SPREAD_DEG`]).
    pub forward: bool,
}

/// Forward-facing or around an object, from the spread of the viewing directions.
pub fn capture_kind(cams: &[Camera]) -> CaptureKind {
    let dirs: Vec<DVec3> = cams.iter().map(|c| c.pose.rotation.row(2)).collect();
    let mean = dirs.iter().sum::<DVec3>().normalize_or_zero();
    let mut angles: Vec<f64> = dirs
        .iter()
        .map(|d| d.dot(mean).clamp(-1.0, 1.0).acos().to_degrees())
        .collect();
    angles.sort_by(f64::total_cmp);
    let spread_deg = match angles.len() {
        0 => 0.0,
        n => angles[(n * 9 / 10).min(n - 1)],
    };
    CaptureKind {
        spread_deg,
        forward: spread_deg <= FORWARD_SPREAD_DEG,
    }
}

/// Cameras along a path of `kind` through the scene's views, and the kind it was (`auto`
/// resolved) with a line saying why.
pub fn path_cameras(scene: &Scene, kind: PathKind, frames: usize) -> Result<Vec<Camera>> {
    Ok(resolved_path(scene, kind, frames)?.0)
}

/// [`path_cameras`], with the kind `auto` chose and why.
pub fn resolved_path(
    scene: &Scene,
    kind: PathKind,
    frames: usize,
) -> Result<(Vec<Camera>, PathKind, String)> {
    let cams: Vec<Camera> = scene.views.iter().map(|v| v.camera).collect();
    let shape = capture_kind(&cams);
    let why = format!(
        "the viewing directions spread {:.0} degrees: {}",
        shape.spread_deg,
        if shape.forward {
            "a forward-facing capture"
        } else {
            "a capture around an object"
        }
    );
    let kind = match kind {
        PathKind::Auto if shape.forward => PathKind::Spiral,
        PathKind::Auto => PathKind::Orbit,
        k => k,
    };
    let intr = scene.views[0].camera.intrinsics;
    let out = match kind {
        PathKind::Orbit => orbit(&cams, intr, frames)?,
        PathKind::Interpolate => interpolate(&cams, intr, frames)?,
        k => llff_path(scene, k, frames)?,
    };
    Ok((out, kind, why))
}

/// The point nearest to every camera's optical axis (least squares), and whether the axes
/// converge on it (in front of the cameras, the system well conditioned).
pub fn look_at_point(cams: &[Camera]) -> Option<DVec3> {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for c in cams {
        let d = c.pose.rotation.row(2);
        let m = DMat3::IDENTITY - outer(d, d);
        a += m;
        b += m * c.pose.centre();
    }
    let n = cams.len() as f64;
    // Parallel axes leave a direction unconstrained: the smallest eigenvalue of `a / n`
    // is then near 0 (its determinant bounds it from above).
    if n < 2.0 || (a * (1.0 / n)).determinant() < 1e-3 {
        return None;
    }
    let p = a.inverse() * b;
    let in_front = cams
        .iter()
        .filter(|c| (p - c.pose.centre()).dot(c.pose.rotation.row(2)) > 0.0)
        .count();
    (p.is_finite() && 2 * in_front > cams.len()).then_some(p)
}

fn outer(u: DVec3, v: DVec3) -> DMat3 {
    DMat3::from_cols(u * v.x, u * v.y, u * v.z)
}

/// A world-to-camera pose at `c` looking at `p` with `up` (world) up in the picture.
pub fn looking_at(c: DVec3, p: DVec3, up: DVec3) -> Result<WorldToCamera> {
    let z = (p - c).normalize_or_zero();
    let x = (-up).cross(z).normalize_or_zero();
    let y = z.cross(x);
    if x.length() < 0.5 || z.length() < 0.5 {
        bail!("cannot aim a camera: it stands on its target or looks straight along up");
    }
    let rot = DMat3::from_cols(x, y, z).transpose();
    WorldToCamera::new_checked(rot, -(rot * c)).map_err(anyhow::Error::msg)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// An orbit around the point the cameras look at, at their median distance and height
/// (along their mean up direction), over the azimuths they cover: a full turn when no gap
/// between neighbouring cameras exceeds 90 degrees, else there and back over their arc.
fn orbit(cams: &[Camera], intr: Intrinsics, frames: usize) -> Result<Vec<Camera>> {
    let p = look_at_point(cams).context(
        "--path orbit: the cameras' axes meet at no point in front of them (a forward-facing capture? try --path spiral)",
    )?;
    // Rows of R: x right, y down; up is minus the mean down.
    let up = -cams.iter().map(|c| c.pose.rotation.row(1)).sum::<DVec3>();
    let up = up.normalize_or_zero();
    if up.length() < 0.5 {
        bail!("--path orbit: the cameras' up directions average to nothing");
    }
    let e1 = any_perpendicular(up);
    let e2 = up.cross(e1);
    let rel: Vec<DVec3> = cams.iter().map(|c| c.pose.centre() - p).collect();
    let radius = median(rel.iter().map(|r| (*r - up * r.dot(up)).length()).collect());
    let height = median(rel.iter().map(|r| r.dot(up)).collect());
    let mut az: Vec<f64> = rel.iter().map(|r| r.dot(e2).atan2(r.dot(e1))).collect();
    az.sort_by(f64::total_cmp);
    let (start, span) = covered_arc(&az);
    let full = span >= std::f64::consts::TAU - 1e-9;
    (0..frames)
        .map(|f| {
            let s = f as f64 / frames as f64;
            let a = match full {
                true => start + s * span,
                // There and back, slowing at the ends.
                false => start + span * 0.5 * (1.0 - (s * std::f64::consts::TAU).cos()),
            };
            let c = p + (e1 * a.cos() + e2 * a.sin()) * radius + up * height;
            Ok(Camera::global(intr, looking_at(c, p, up)?))
        })
        .collect()
}

/// A unit vector perpendicular to the unit vector `u`.
fn any_perpendicular(u: DVec3) -> DVec3 {
    let a = if u.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
    u.cross(a).normalize()
}

/// The arc sorted azimuths `az` cover: its start and length, the largest gap between
/// neighbours left out (a full turn when that gap is under 90 degrees).
fn covered_arc(az: &[f64]) -> (f64, f64) {
    let tau = std::f64::consts::TAU;
    let Some((&first, &last)) = az.first().zip(az.last()) else {
        return (0.0, tau);
    };
    let (mut gap, mut after) = (first + tau - last, first);
    for w in az.windows(2) {
        if w[1] - w[0] > gap {
            (gap, after) = (w[1] - w[0], w[1]);
        }
    }
    if gap < tau / 4.0 {
        return (after, tau);
    }
    (after, tau - gap)
}

/// A Catmull-Rom spline through the camera centres in capture order, orientations slerped
/// between neighbouring cameras; `frames` frames from the first camera to the last.
fn interpolate(cams: &[Camera], intr: Intrinsics, frames: usize) -> Result<Vec<Camera>> {
    let n = cams.len();
    if n < 2 {
        bail!("--path interpolate needs at least 2 views");
    }
    let c: Vec<DVec3> = cams.iter().map(|k| k.pose.centre()).collect();
    let q: Vec<DQuat> = cams
        .iter()
        .map(|k| DQuat::from_mat3(&k.pose.rotation))
        .collect();
    let at = |i: isize| c[i.clamp(0, n as isize - 1) as usize];
    (0..frames)
        .map(|f| {
            let u = f as f64 / (frames.max(2) - 1) as f64 * (n - 1) as f64;
            let i = (u.floor() as usize).min(n - 2);
            let t = u - i as f64;
            let ii = i as isize;
            let (p0, p1, p2, p3) = (at(ii - 1), at(ii), at(ii + 1), at(ii + 2));
            let centre = 0.5
                * (2.0 * p1
                    + (p2 - p0) * t
                    + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * t * t
                    + (3.0 * p1 - p0 - 3.0 * p2 + p3) * t * t * t);
            let (qa, qb) = (q[i], q[i + 1]);
            let qb = if qa.dot(qb) < 0.0 { -qb } else { qb };
            let rot = DMat3::from_quat(qa.slerp(qb, t).normalize());
            let pose =
                WorldToCamera::new_checked(rot, -(rot * centre)).map_err(anyhow::Error::msg)?;
            Ok(Camera::global(intr, pose))
        })
        .collect()
}

/// LLFF's paths (spiral, circle, line) around the views' mean pose: the mean orientation
/// of the views, centres offset from the mean centre in that frame by the spread of the
/// views.
fn llff_path(scene: &Scene, kind: PathKind, frames: usize) -> Result<Vec<Camera>> {
    let n = scene.views.len() as f64;
    let centre = scene
        .views
        .iter()
        .map(|v| v.camera.pose.centre())
        .sum::<DVec3>()
        / n;
    // Mean camera axes (rows of R are the camera axes in world coordinates).
    let axis = |i: usize| {
        scene
            .views
            .iter()
            .map(|v| v.camera.pose.rotation.row(i))
            .sum::<DVec3>()
            .normalize_or_zero()
    };
    let (x, z0) = (axis(0), axis(2));
    let z = z0;
    let y = z.cross(x).normalize_or_zero();
    let x = y.cross(z).normalize_or_zero();
    if !(x.is_finite() && y.is_finite() && z.is_finite()) || x.length() < 0.5 {
        bail!("cannot build a path: the views' orientations average to nothing");
    }
    let mut d: Vec<f64> = scene
        .views
        .iter()
        .map(|v| (v.camera.pose.centre() - centre).length())
        .collect();
    d.sort_by(f64::total_cmp);
    let radius = d[(d.len() * 9 / 10).min(d.len() - 1)].max(1e-9) * 0.5;
    let rot = DMat3::from_cols(x, y, z).transpose(); // world-to-camera: rows are axes
    let intr = scene.views[0].camera.intrinsics;
    (0..frames)
        .map(|f| {
            let s = f as f64 / frames as f64;
            let th = s * std::f64::consts::TAU;
            let off = match kind {
                PathKind::Circle => x * th.cos() + y * th.sin(),
                PathKind::Spiral => x * th.cos() - y * th.sin() - z * (0.5 * th).sin() * 0.5,
                _ => x * (2.0 * (f as f64 / (frames.max(2) - 1) as f64) - 1.0),
            };
            let c = centre + off * radius;
            let pose = WorldToCamera::new_checked(rot, -(rot * c)).map_err(anyhow::Error::msg)?;
            Ok(Camera::global(intr, pose))
        })
        .collect()
}

/// Steps of the path progress bar per frame (the bar advances tile by tile).
const BAR_STEPS_PER_FRAME: u64 = 1000;

/// Renders `cams` in order, saving each as `dir/frame_NNNN.png` (`dir`: a staged
/// directory, put in place once complete; see [`RgbImage::save_frame_png`]), with a
/// progress bar (frames done, time left); returns the frames.
pub fn render_path(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    cams: &[Camera],
    views: usize,
    settings: &RenderSettings,
    dir: &Path,
) -> Result<Vec<RgbImage>> {
    let n = cams.len() as u64;
    let bar = indicatif::ProgressBar::new(n * BAR_STEPS_PER_FRAME);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {msg}, {eta} left",
        )
        .context("progress bar template")?,
    );
    let mut frames = Vec::with_capacity(cams.len());
    for (f, cam) in cams.iter().enumerate() {
        bar.set_message(format!("frame {}/{n}", f + 1));
        let base = f as u64 * BAR_STEPS_PER_FRAME;
        let progress = |done: usize, total: usize| {
            let part = done as u64 * BAR_STEPS_PER_FRAME / total.max(1) as u64;
            bar.set_position(base + part);
        };
        let srcs = pick_planned_sources(scene, cam, &[], (views, backend.config()), settings);
        let (r, _) = render_camera(backend, scene, prepared, cam, &srcs, settings, &progress)?;
        r.image
            .save_frame_png(&dir.join(format!("frame_{f:04}.png")))?;
        bar.set_position(base + BAR_STEPS_PER_FRAME);
        if bar.is_hidden() {
            eprintln!("frame {}/{n}", f + 1);
        }
        frames.push(r.image);
    }
    bar.finish_and_clear();
    Ok(frames)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn intr() -> Intrinsics {
        Intrinsics::pinhole(50.0, 50.0, 32.0, 24.0, 64, 48)
    }

    /// `n` cameras on a ring of radius 4 at height 1 around (1, 0, 2) (world y down, as
    /// OpenCV), each looking at it; `arc` radians of the ring.
    fn ring(n: usize, arc: f64) -> (Vec<Camera>, DVec3) {
        let p = DVec3::new(1.0, 0.0, 2.0);
        let up = DVec3::new(0.0, -1.0, 0.0);
        let cams = (0..n)
            .map(|i| {
                let a = arc * i as f64 / n as f64;
                let c = p + DVec3::new(4.0 * a.cos(), -1.0, 4.0 * a.sin());
                Camera::global(intr(), looking_at(c, p, up).expect("pose"))
            })
            .collect();
        (cams, p)
    }

    /// A 4x3 grid of forward-facing cameras in the plane z = 0, looking along +z, their
    /// directions tilted by up to 5 degrees.
    fn grid() -> Vec<Camera> {
        (0..12)
            .map(|i| {
                let (gx, gy) = ((i % 4) as f64, (i / 4) as f64);
                let c = DVec3::new(0.3 * gx, 0.3 * gy, 0.0);
                let rot = DMat3::from_rotation_y(0.02 * (gx - 1.5))
                    * DMat3::from_rotation_x(0.02 * (gy - 1.0));
                let pose = WorldToCamera::new_checked(rot, -(rot * c)).expect("pose");
                Camera::global(intr(), pose)
            })
            .collect()
    }

    /// Each camera's distance to `p` relative to the median of `rig`'s, and how far (in
    /// degrees) its axis points away from `p`.
    fn check_facing(cams: &[Camera], rig: &[Camera], p: DVec3) {
        let med = median(rig.iter().map(|c| (c.pose.centre() - p).length()).collect());
        for c in cams {
            let d = c.pose.centre() - p;
            let ratio = d.length() / med;
            assert!(
                (0.6..=1.5).contains(&ratio),
                "distance {ratio} x the median"
            );
            let cos = (-d).normalize().dot(c.pose.rotation.row(2));
            let off = cos.clamp(-1.0, 1.0).acos().to_degrees();
            assert!(off < 1.0, "looks {off} degrees away from the point");
        }
    }

    #[test]
    fn a_ring_is_around_an_object_and_its_orbit_circles_the_point_it_looks_at() {
        let (rig, p) = ring(24, std::f64::consts::TAU);
        let kind = capture_kind(&rig);
        assert!(!kind.forward && kind.spread_deg > 60.0, "{kind:?}");
        let found = look_at_point(&rig).expect("the axes meet");
        assert!((found - p).length() < 1e-6, "{found}");
        let cams = orbit(&rig, intr(), 16).expect("orbit");
        check_facing(&cams, &rig, p);
        // A full turn: the frames' azimuths cover the circle in even steps.
        let az: Vec<f64> = cams
            .iter()
            .map(|c| {
                let d = c.pose.centre() - p;
                d.z.atan2(d.x)
            })
            .collect();
        for w in az.windows(2) {
            let step = (w[1] - w[0]).rem_euclid(std::f64::consts::TAU);
            assert!((step - std::f64::consts::TAU / 16.0).abs() < 1e-9, "{step}");
        }
        // Upright: the picture's down is the world's down (y).
        for c in &cams {
            assert!(c.pose.rotation.row(1).dot(DVec3::Y) > 0.9);
        }
    }

    #[test]
    fn an_arc_is_orbited_within_its_azimuths_and_auto_picks_the_orbit() {
        let (rig, p) = ring(12, 100f64.to_radians());
        let cams = orbit(&rig, intr(), 20).expect("orbit");
        check_facing(&cams, &rig, p);
        let span = 100f64.to_radians() * 11.0 / 12.0;
        for c in &cams {
            let d = c.pose.centre() - p;
            let a = d.z.atan2(d.x);
            assert!(
                (-1e-9..=span + 1e-9).contains(&a),
                "azimuth {a} outside the arc"
            );
        }
        assert!(!capture_kind(&rig).forward);
    }

    #[test]
    fn a_forward_grid_is_forward_facing_and_has_no_orbit() {
        let rig = grid();
        let kind = capture_kind(&rig);
        assert!(kind.forward && kind.spread_deg < 5.0, "{kind:?}");
        assert!(
            look_at_point(&rig).is_none(),
            "near-parallel axes meet nowhere"
        );
        assert!(orbit(&rig, intr(), 4).is_err());
    }

    #[test]
    fn interpolation_passes_through_the_cameras_in_order() {
        let rig = grid();
        // 12 cameras, 23 frames: frame 2i is camera i.
        let cams = interpolate(&rig, intr(), 23).expect("interpolate");
        for (i, c) in rig.iter().enumerate() {
            let f = &cams[2 * i];
            assert!(
                (f.pose.centre() - c.pose.centre()).length() < 1e-9,
                "frame {}",
                2 * i
            );
            let r = f.pose.rotation - c.pose.rotation;
            assert!(r.to_cols_array().iter().all(|v| v.abs() < 1e-9));
        }
        // In between, on the spline: within the grid's bounding box (plus a margin).
        for f in &cams {
            let c = f.pose.centre();
            assert!(c.x > -0.1 && c.x < 1.0 && c.y > -0.1 && c.y < 0.7 && c.z.abs() < 1e-9);
        }
        assert!(interpolate(&rig[..1], intr(), 5).is_err());
    }
}
