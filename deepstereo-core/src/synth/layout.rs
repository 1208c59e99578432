//! Scene content: textured planar rectangles (fronto-parallel, slanted, grazing), thin
//! poles and bars, and an infinite backdrop plane, placed so that the rig's views see them.

use super::rig::RigLayout;
use super::rng::Rng;
use super::texture::{Role, Texture};
use crate::camera::Camera;
use crate::imageio::RgbImage;
use glam::{DMat3, DVec2, DVec3};

/// Number of rectangles per scene.
const PANELS: (usize, usize) = (5, 12);
/// Number of thin structures per scene.
const THIN: (usize, usize) = (1, 3);
/// Farthest rectangle centre depth, times the nearest content depth `d0`.
const DEPTH_RATIO: f64 = 10.0;
/// Farthest thin structure depth, times `d0`.
const THIN_DEPTH_RATIO: f64 = 6.0;
/// Backdrop depth range, times `d0`.
const BACKDROP_RATIO: (f64, f64) = (50.0, 200.0);
/// Every corner of every surface lies at least this deep (times `d0`) in every camera.
const MIN_CLEARANCE: f64 = 0.7;
/// Tries to place one surface before it is left out.
const MAX_ATTEMPTS: usize = 40;
/// Odds of fronto-parallel, slanted and grazing rectangles.
const SLANT_ODDS: [f64; 3] = [0.35, 0.4, 0.25];
/// Slant ranges of those classes (degrees from facing the camera).
const SLANT_DEG: [(f64, f64); 3] = [(0.0, 8.0), (15.0, 50.0), (55.0, 75.0)];
/// Half-size of a rectangle as a fraction of the view width at its depth.
const PANEL_SIZE: (f64, f64) = (0.05, 0.24);
/// Ratio of a rectangle's sides.
const PANEL_ASPECT: (f64, f64) = (0.4, 2.5);
/// Width of thin structures in pixels (of the view they are placed from).
const THIN_WIDTH_PX: (f64, f64) = (2.0, 6.0);
/// Ambient share of the Lambertian shading.
const AMBIENT: (f64, f64) = (0.5, 0.7);
/// Largest per-channel colour tint of a scene's light.
const TINT: f64 = 0.06;
/// Ring rig: share of rectangles placed in the central cluster.
const RING_CLUSTER_SHARE: f64 = 0.6;
/// Photo crops cover about this many times the pixels the surface covers on screen.
const PHOTO_CROP_SCALE: (f64, f64) = (0.75, 2.0);

/// A textured planar rectangle in world coordinates; infinite halves for the backdrop.
#[derive(Clone, Debug)]
pub(crate) struct Surface {
    pub centre: DVec3,
    pub axis_u: DVec3,
    pub axis_v: DVec3,
    pub normal: DVec3,
    pub half_u: f64,
    pub half_v: f64,
    /// World length of one texture unit.
    pub tex_scale: f64,
    pub texture: Texture,
    /// Lighting multiplier per channel.
    pub shade: [f32; 3],
}

/// Scene lighting: a light direction, the ambient share and a colour tint.
struct Light {
    dir: DVec3,
    ambient: f64,
    tint: [f64; 3],
}

impl Light {
    fn shade(&self, normal: DVec3) -> [f32; 3] {
        let l = self.ambient + (1.0 - self.ambient) * normal.dot(self.dir).abs();
        self.tint.map(|t| (t * l) as f32)
    }
}

/// Builds every surface of a scene for the rig's cameras.
pub(crate) fn build(rng: &mut Rng, rig: &RigLayout, photos: &[RgbImage]) -> Vec<Surface> {
    let d0 = rig.d0;
    let light = Light {
        dir: DVec3::new(rng.sym(0.7), -rng.range(0.3, 1.0), -rng.range(0.2, 1.0)).normalize(),
        ambient: rng.range(AMBIENT.0, AMBIENT.1),
        tint: [
            1.0 + rng.sym(TINT),
            1.0 + rng.sym(TINT),
            1.0 + rng.sym(TINT),
        ],
    };
    let mut out = Vec::new();
    let zb = d0 * rng.range(BACKDROP_RATIO.0, BACKDROP_RATIO.1);
    let fx = rig.cameras.first().map_or(1.0, |c| c.intrinsics.fx);
    let texture = if photos.is_empty() {
        Texture::procedural(rng, Role::Backdrop)
    } else {
        let crop = fx * rng.range(0.5, 1.5);
        Texture::photo(rng, photos, crop)
    };
    out.push(Surface {
        centre: DVec3::new(0.0, 0.0, zb),
        axis_u: DVec3::X,
        axis_v: DVec3::Y,
        normal: DVec3::NEG_Z,
        half_u: f64::INFINITY,
        half_v: f64::INFINITY,
        tex_scale: zb,
        texture,
        shade: light.tint.map(|t| (t * rng.range(0.85, 1.0)) as f32),
    });
    let panels = rng.int_in(PANELS.0, PANELS.1);
    for _ in 0..panels {
        let found = (0..MAX_ATTEMPTS).find_map(|_| {
            let g = match rig.focus {
                Some((f, r)) if rng.chance(RING_CLUSTER_SHARE) => cluster_panel(rng, rig, f, r),
                _ => view_panel(rng, rig),
            };
            clear(rig, &g, zb).then_some(g)
        });
        if let Some(g) = found {
            out.push(finish(rng, g, Role::Panel, &light, photos));
        }
    }
    let thin = rng.int_in(THIN.0, THIN.1);
    for _ in 0..thin {
        let found = (0..MAX_ATTEMPTS).find_map(|_| {
            let g = thin_structure(rng, rig);
            clear(rig, &g, zb).then_some(g)
        });
        if let Some(g) = found {
            out.push(finish(rng, g, Role::Thin, &light, photos));
        }
    }
    out
}

/// Geometry of a surface before it gets a texture, with the camera and depth it was
/// placed from (to size photo crops).
struct Geometry {
    centre: DVec3,
    axis_u: DVec3,
    axis_v: DVec3,
    half_u: f64,
    half_v: f64,
    /// Pixels per world unit at the surface in the camera it was placed from.
    px_per_unit: f64,
}

fn finish(rng: &mut Rng, g: Geometry, role: Role, light: &Light, photos: &[RgbImage]) -> Surface {
    let tex_scale = 2.0 * g.half_u.max(g.half_v);
    let texture = if photos.is_empty() {
        Texture::procedural(rng, role)
    } else {
        let crop = tex_scale * g.px_per_unit * rng.range(PHOTO_CROP_SCALE.0, PHOTO_CROP_SCALE.1);
        Texture::photo(rng, photos, crop)
    };
    let normal = g.axis_u.cross(g.axis_v).normalize();
    Surface {
        centre: g.centre,
        axis_u: g.axis_u,
        axis_v: g.axis_v,
        normal,
        half_u: g.half_u,
        half_v: g.half_v,
        tex_scale,
        texture,
        shade: light.shade(normal),
    }
}

/// Whether every corner is well in front of every camera and well before the backdrop.
fn clear(rig: &RigLayout, g: &Geometry, backdrop_z: f64) -> bool {
    let (u, v) = (g.axis_u * g.half_u, g.axis_v * g.half_v);
    let corners = [
        g.centre - u - v,
        g.centre + u - v,
        g.centre + u + v,
        g.centre - u + v,
    ];
    corners.iter().all(|p| {
        p.z < 0.5 * backdrop_z
            && rig
                .cameras
                .iter()
                .all(|c| c.pose.transform_point(*p).z >= MIN_CLEARANCE * rig.d0)
    })
}

/// A random camera, a random point of its view (with a margin) and its world axes.
fn view_point<'a>(
    rng: &mut Rng,
    rig: &'a RigLayout,
    margin: f64,
    depth: f64,
) -> (DVec3, DMat3, &'a Camera) {
    let cam = &rig.cameras[rng.below(rig.cameras.len())];
    let (w, h) = (cam.intrinsics.width as f64, cam.intrinsics.height as f64);
    let uv = DVec2::new(
        rng.range(-margin, 1.0 + margin) * w,
        rng.range(-margin, 1.0 + margin) * h,
    );
    (cam.unproject(uv, depth), cam.pose.rotation.transpose(), cam)
}

/// Depth between `d0` and `ratio * d0`: half the time uniform in inverse depth, else log.
fn content_depth(rng: &mut Rng, d0: f64, ratio: f64) -> f64 {
    if rng.chance(0.5) {
        1.0 / rng.range(1.0 / (ratio * d0), 1.0 / d0)
    } else {
        rng.log_range(d0, ratio * d0)
    }
}

/// In-plane axes of a rectangle whose normal is `n0` tilted by a random slant, rotated
/// by a random angle about the normal.
fn oriented_axes(rng: &mut Rng, n0: DVec3) -> (DVec3, DVec3) {
    let class = rng.weighted(&SLANT_ODDS);
    let (lo, hi) = SLANT_DEG[class];
    let slant = rng.range(lo, hi).to_radians();
    let a = n0.any_orthonormal_vector();
    let b = n0.cross(a);
    let phi = rng.range(0.0, std::f64::consts::TAU);
    let tilt_axis = a * phi.cos() + b * phi.sin();
    let n = DMat3::from_axis_angle(tilt_axis, slant) * n0;
    let p = n.any_orthonormal_vector();
    let q = n.cross(p);
    let psi = rng.range(0.0, std::f64::consts::TAU);
    let u = p * psi.cos() + q * psi.sin();
    (u, n.cross(u))
}

/// A rectangle placed from a random view: a random pixel at a random depth.
fn view_panel(rng: &mut Rng, rig: &RigLayout) -> Geometry {
    let z = content_depth(rng, rig.d0, DEPTH_RATIO);
    let (centre, r_c2w, cam) = view_point(rng, rig, 0.1, z);
    let k = &cam.intrinsics;
    let side = z * (k.width as f64 / k.fx);
    panel(
        rng,
        (centre, -r_c2w.z_axis),
        |rng| side * rng.range(PANEL_SIZE.0, PANEL_SIZE.1),
        k.fx / z,
    )
}

/// A rectangle at `centre` facing about `facing` (axes from [`oriented_axes`]), its half
/// width from `half(rng)`, its aspect random; `px_per_unit` as its texture's scale.
fn panel(
    rng: &mut Rng,
    (centre, facing): (DVec3, DVec3),
    half: impl FnOnce(&mut Rng) -> f64,
    px_per_unit: f64,
) -> Geometry {
    let (axis_u, axis_v) = oriented_axes(rng, facing);
    let half = half(rng);
    let aspect = rng.range(PANEL_ASPECT.0, PANEL_ASPECT.1);
    Geometry {
        centre,
        axis_u,
        axis_v,
        half_u: half,
        half_v: half * aspect,
        px_per_unit,
    }
}

/// A rectangle in the ring rig's central cluster, facing one of the cameras.
fn cluster_panel(rng: &mut Rng, rig: &RigLayout, focus: DVec3, radius: f64) -> Geometry {
    let centre = focus + DVec3::new(rng.sym(radius), rng.sym(0.6 * radius), rng.sym(radius));
    let cam = &rig.cameras[rng.below(rig.cameras.len())];
    let to_cam = (cam.pose.centre() - centre).normalize();
    let z = cam.pose.transform_point(centre).z.max(rig.d0);
    panel(
        rng,
        (centre, to_cam),
        |rng| radius * rng.range(0.15, 0.5),
        cam.intrinsics.fx / z,
    )
}

/// A pole (vertical) or bar (horizontal) a few pixels wide.
fn thin_structure(rng: &mut Rng, rig: &RigLayout) -> Geometry {
    let z = content_depth(rng, rig.d0, THIN_DEPTH_RATIO);
    let (centre, r_c2w, cam) = view_point(rng, rig, -0.05, z);
    let k = &cam.intrinsics;
    let (right, down, fwd) = (r_c2w.x_axis, r_c2w.y_axis, r_c2w.z_axis);
    let pole = rng.chance(0.6);
    let (long, half_len) = if pole {
        (down, z * (k.height as f64 / k.fy) * rng.range(0.6, 1.5))
    } else {
        (right, z * (k.width as f64 / k.fx) * rng.range(0.4, 1.2))
    };
    let axis_u = DMat3::from_axis_angle(fwd, rng.sym(12f64.to_radians())) * long;
    let normal = DMat3::from_axis_angle(axis_u, rng.sym(30f64.to_radians())) * -fwd;
    let axis_v = normal.cross(axis_u).normalize();
    let half_w = 0.5 * z * rng.range(THIN_WIDTH_PX.0, THIN_WIDTH_PX.1) / k.fx;
    Geometry {
        centre,
        axis_u,
        axis_v,
        half_u: half_len,
        half_v: half_w,
        px_per_unit: k.fx / z,
    }
}
