//! The ray tracer: `K x K` sub-pixel rays per pixel, nearest hit among the surfaces,
//! box-filtered; depth is the camera-space z of the pixel-centre ray's hit.
//!
//! Rays are traced in camera space with direction `d = (x, y, 1)` (normalized image
//! coordinates), so the ray parameter of a hit is its camera z. A camera with a moving
//! rolling shutter traces each row from the pose at the time of the row's pixel centres
//! (its depths are exact; the sub-pixel rays of a pixel share that pose, an error of
//! 1/H of the readout's motion within a pixel).

use super::layout::Surface;
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::imageio::RgbImage;
use glam::{DVec2, DVec3};

/// Rays closer to parallel with a plane than this (|n . d|) miss it.
const PARALLEL_EPS: f64 = 1e-12;
/// Hits nearer than this camera depth are ignored.
const MIN_DEPTH: f64 = 1e-9;
/// Corners shallower than this (camera z) make a surface's screen box the whole image.
const BEHIND_EPS: f64 = 1e-6;
/// Screen boxes grow by this many pixels on every side.
const BOX_MARGIN: f64 = 1.0;
/// Grazing incidence is clamped to this cosine when estimating the texture footprint.
const MIN_COS: f64 = 0.2;

/// A surface in one camera's coordinates, with its screen bounding box.
struct Local<'a> {
    c: DVec3,
    u: DVec3,
    v: DVec3,
    n: DVec3,
    nc: f64,
    hu: f64,
    hv: f64,
    /// `[x0, x1, y0, y1]` in pixels.
    bbox: [f64; 4],
    /// A lower bound of the depth of any of its points in the view.
    zmin: f64,
    surf: &'a Surface,
}

fn localize<'a>(cam: &Camera, s: &'a Surface) -> Option<Local<'a>> {
    let r = cam.pose.rotation;
    let c = cam.pose.transform_point(s.centre);
    let (u, v, n) = (r * s.axis_u, r * s.axis_v, r * s.normal);
    let k = &cam.intrinsics;
    let (w, h) = (k.width as f64, k.height as f64);
    let full = [
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
    ];
    // Rays through the image have |d| <= d_max, and hit the plane at distance >= |n . c|.
    let corner = |u: f64, v: f64| k.unproject_pixel(DVec2::new(u, v)).length_squared();
    let d_max = (1.0
        + corner(0.0, 0.0)
            .max(corner(w, 0.0))
            .max(corner(0.0, h))
            .max(corner(w, h)))
    .sqrt();
    let mut zmin = n.dot(c).abs() / d_max;
    let bbox = if s.half_u.is_finite() && s.half_v.is_finite() {
        let (du, dv) = (u * s.half_u, v * s.half_v);
        let corners = [c - du - dv, c + du - dv, c + du + dv, c - du + dv];
        if corners.iter().all(|p| p.z <= 0.0) {
            return None;
        }
        // Depth is linear over the rectangle: its smallest value is at a corner.
        zmin = zmin.max(corners.iter().fold(f64::INFINITY, |m, p| m.min(p.z)));
        if corners.iter().any(|p| p.z <= BEHIND_EPS) {
            full
        } else {
            let mut b = [
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::INFINITY,
                f64::NEG_INFINITY,
            ];
            for p in corners {
                let (x, y) = (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
                b = [b[0].min(x), b[1].max(x), b[2].min(y), b[3].max(y)];
            }
            [
                b[0] - BOX_MARGIN,
                b[1] + BOX_MARGIN,
                b[2] - BOX_MARGIN,
                b[3] + BOX_MARGIN,
            ]
        }
    } else {
        full
    };
    if bbox[1] < 0.0 || bbox[0] > w || bbox[3] < 0.0 || bbox[2] > h {
        return None;
    }
    Some(Local {
        c,
        u,
        v,
        n,
        nc: n.dot(c),
        hu: s.half_u,
        hv: s.half_v,
        bbox,
        zmin,
        surf: s,
    })
}

/// Nearest hit of the ray `d = (x, y, 1)` among `locals[cands]` (sorted by `zmin`): its
/// depth and index.
#[inline]
fn trace(d: DVec3, locals: &[Local], cands: &[usize]) -> Option<(f64, usize)> {
    let mut best: Option<(f64, usize)> = None;
    for &i in cands {
        let l = &locals[i];
        if best.is_some_and(|(bt, _)| l.zmin >= bt) {
            break;
        }
        let denom = l.n.dot(d);
        if denom.abs() < PARALLEL_EPS {
            continue;
        }
        let t = l.nc / denom;
        if t <= MIN_DEPTH || best.is_some_and(|(bt, _)| t >= bt) {
            continue;
        }
        let q = d * t - l.c;
        if q.dot(l.u).abs() <= l.hu && q.dot(l.v).abs() <= l.hv {
            best = Some((t, i));
        }
    }
    best
}

/// Renders one view: its image (times the exposure `gain`, clamped to [0, 1]) and its
/// depth map, `[H * W]` camera z of the pixel-centre rays.
///
/// Every sub-pixel ray finds its nearest surface (exact coverage, box filtered).
/// Procedural textures are prefiltered by their footprint, so the sub-rays of a pixel
/// that hit the same surface share one texture lookup at their mean hit point with the
/// footprint of the whole pixel; photo textures are looked up per sub-ray.
pub(crate) fn render(
    cam: &Camera,
    surfaces: &[Surface],
    supersample: u32,
    gain: f32,
    photos: &[RgbImage],
) -> Result<(RgbImage, Vec<f32>)> {
    let k = &cam.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let localize_all = |c: &Camera| {
        let mut l: Vec<Local> = surfaces.iter().filter_map(|s| localize(c, s)).collect();
        l.sort_by(|a, b| a.zmin.total_cmp(&b.zmin));
        l
    };
    let moving = cam.moving_shutter().is_some();
    let mut locals = localize_all(cam);
    let ss = supersample.max(1) as usize;
    // Angle of one pixel and of one sub-pixel ray.
    let pixel_angle = 2.0 / (k.fx + k.fy);
    let sample_angle = pixel_angle / ss as f64;
    let weight = gain / (ss * ss) as f32;
    let mut image = RgbImage::new(k.width, k.height);
    let mut depth = vec![0f32; w * h];
    let mut row: Vec<usize> = Vec::with_capacity(locals.len());
    let mut cands: Vec<usize> = Vec::with_capacity(locals.len());
    // Per pixel: (surface, sum of hit points, count) of the prefiltered hits.
    let mut groups: Vec<(usize, DVec3, u32)> = Vec::with_capacity(ss * ss);
    let ray = |x: f64, y: f64| {
        let n = k.unproject_pixel(DVec2::new(x, y));
        DVec3::new(n.x, n.y, 1.0)
    };
    let missed = |px: usize, py: usize| {
        Error::Invalid(format!(
            "synth: a ray through pixel ({px}, {py}) hit nothing"
        ))
    };
    for py in 0..h {
        let (y0, y1) = (py as f64, py as f64 + 1.0);
        if moving {
            // A rolling shutter: the row is traced from the pose of its centre's time.
            let centre = DVec2::new(0.5 * w as f64, py as f64 + 0.5);
            locals = localize_all(&Camera::global(*k, cam.pose_at_pixel(centre)));
        }
        row.clear();
        row.extend(
            (0..locals.len()).filter(|&i| locals[i].bbox[2] <= y1 && locals[i].bbox[3] >= y0),
        );
        for px in 0..w {
            let (x0, x1) = (px as f64, px as f64 + 1.0);
            cands.clear();
            cands.extend(
                row.iter()
                    .copied()
                    .filter(|&i| locals[i].bbox[0] <= x1 && locals[i].bbox[1] >= x0),
            );
            let sampler = Sampler {
                ray: &ray,
                locals: &locals,
                cands: &cands,
                ss,
                angles: (pixel_angle, sample_angle),
                photos,
            };
            let (acc, t) = sampler
                .pixel((x0, y0), &mut groups)
                .ok_or_else(|| missed(px, py))?;
            depth[py * w + px] = t;
            let o = (py * w + px) * 3;
            for (out, a) in image.data[o..o + 3].iter_mut().zip(acc) {
                *out = (a * weight).clamp(0.0, 1.0);
            }
        }
    }
    Ok((image, depth))
}

/// One pixel's rays: its sub-pixel rays against the candidate surfaces of its screen box.
struct Sampler<'a, R: Fn(f64, f64) -> DVec3> {
    /// The ray direction through an image point.
    ray: &'a R,
    locals: &'a [Local<'a>],
    cands: &'a [usize],
    /// Sub-pixel rays per side.
    ss: usize,
    /// Angle of one pixel and of one sub-pixel ray.
    angles: (f64, f64),
    photos: &'a [RgbImage],
}

impl<R: Fn(f64, f64) -> DVec3> Sampler<'_, R> {
    /// The sum of the shaded colours of the pixel at `(x0, y0)` (its corner) over its
    /// sub-rays, and the camera depth of its centre ray; `None` when a ray hits nothing.
    /// `groups` is scratch: per prefiltered surface hit, (surface, sum of hit points,
    /// count), shaded once at the mean hit point with the footprint of the whole pixel.
    fn pixel(
        &self,
        (x0, y0): (f64, f64),
        groups: &mut Vec<(usize, DVec3, u32)>,
    ) -> Option<([f32; 3], f32)> {
        let (ss, ssf) = (self.ss, self.ss as f64);
        let (locals, cands, photos) = (self.locals, self.cands, self.photos);
        let (pixel_angle, sample_angle) = self.angles;
        let mut depth = 0f32;
        if ss.is_multiple_of(2) {
            let (t, _) = trace((self.ray)(x0 + 0.5, y0 + 0.5), locals, cands)?;
            depth = t as f32;
        }
        let mut acc = [0f32; 3];
        groups.clear();
        for sy in 0..ss {
            for sx in 0..ss {
                // With odd `ss` the middle sub-ray is exactly the pixel-centre ray.
                let d = (self.ray)(x0 + (sx as f64 + 0.5) / ssf, y0 + (sy as f64 + 0.5) / ssf);
                let (t, i) = trace(d, locals, cands)?;
                if !ss.is_multiple_of(2) && sx == ss / 2 && sy == ss / 2 {
                    depth = t as f32;
                }
                let p = d * t;
                if locals[i].surf.texture.prefiltered() {
                    match groups.iter_mut().find(|g| g.0 == i) {
                        Some(g) => {
                            g.1 += p;
                            g.2 += 1;
                        }
                        None => groups.push((i, p, 1)),
                    }
                } else {
                    add(&mut acc, shade(p, &locals[i], sample_angle, photos), 1.0);
                }
            }
        }
        for &(i, sum, n) in groups.iter() {
            add(
                &mut acc,
                shade(sum / n as f64, &locals[i], pixel_angle, photos),
                n as f32,
            );
        }
        Some((acc, depth))
    }
}

#[inline]
fn add(acc: &mut [f32; 3], c: [f32; 3], n: f32) {
    for (a, v) in acc.iter_mut().zip(c) {
        *a += v * n;
    }
}

/// Colour of the point `p` (camera coordinates) of surface `l`, for a sample covering
/// `angle` radians.
#[inline]
fn shade(p: DVec3, l: &Local, angle: f64, photos: &[RgbImage]) -> [f32; 3] {
    let s = l.surf;
    let q = p - l.c;
    let (a, b) = (q.dot(l.u), q.dot(l.v));
    let dist = p.length();
    let cos = (l.n.dot(p).abs() / dist).max(MIN_COS);
    let fp = dist * angle / cos / s.tex_scale;
    let c = s.texture.eval(
        (a / s.tex_scale + 0.5) as f32,
        (b / s.tex_scale + 0.5) as f32,
        fp as f32,
        photos,
    );
    [c[0] * s.shade[0], c[1] * s.shade[1], c[2] * s.shade[2]]
}
