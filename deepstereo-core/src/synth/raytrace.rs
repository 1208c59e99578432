//! The ray tracer: `K x K` sub-pixel rays per pixel, nearest hit among the surfaces,
//! box-filtered; depth is the camera-space z of the pixel-centre ray's hit.
//!
//! Rays are traced in camera space with direction `d = (x, y, 1)` (normalized image
//! coordinates), so the ray parameter of a hit is its camera z.

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
    surf: &'a Surface,
}

fn localize<'a>(cam: &Camera, s: &'a Surface) -> Option<Local<'a>> {
    let r = cam.pose.rotation;
    let c = cam.pose.transform_point(s.centre);
    let (u, v, n) = (r * s.axis_u, r * s.axis_v, r * s.normal);
    let k = &cam.intrinsics;
    let (w, h) = (k.width as f64, k.height as f64);
    let full = [f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY];
    let bbox = if s.half_u.is_finite() && s.half_v.is_finite() {
        let (du, dv) = (u * s.half_u, v * s.half_v);
        let corners = [c - du - dv, c + du - dv, c + du + dv, c - du + dv];
        if corners.iter().all(|p| p.z <= 0.0) {
            return None;
        }
        if corners.iter().any(|p| p.z <= BEHIND_EPS) {
            full
        } else {
            let mut b = [f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY];
            for p in corners {
                let (x, y) = (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
                b = [b[0].min(x), b[1].max(x), b[2].min(y), b[3].max(y)];
            }
            [b[0] - BOX_MARGIN, b[1] + BOX_MARGIN, b[2] - BOX_MARGIN, b[3] + BOX_MARGIN]
        }
    } else {
        full
    };
    if bbox[1] < 0.0 || bbox[0] > w || bbox[3] < 0.0 || bbox[2] > h {
        return None;
    }
    Some(Local { c, u, v, n, nc: n.dot(c), hu: s.half_u, hv: s.half_v, bbox, surf: s })
}

/// Nearest hit of the ray `d = (x, y, 1)`: its depth and surface.
#[inline]
fn trace<'a, 'b>(d: DVec3, cands: &[&'b Local<'a>]) -> Option<(f64, &'b Local<'a>)> {
    let mut best: Option<(f64, &Local)> = None;
    for &l in cands {
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
            best = Some((t, l));
        }
    }
    best
}

/// Renders one view: its image (times the exposure `gain`, clamped to [0, 1]) and its
/// depth map, `[H * W]` camera z of the pixel-centre rays.
pub(crate) fn render(
    cam: &Camera,
    surfaces: &[Surface],
    supersample: u32,
    gain: f32,
    photos: &[RgbImage],
) -> Result<(RgbImage, Vec<f32>)> {
    let k = &cam.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let locals: Vec<Local> = surfaces.iter().filter_map(|s| localize(cam, s)).collect();
    let ss = supersample.max(1) as usize;
    let inv_ss = 1.0 / ss as f64;
    let f_mean = 0.5 * (k.fx + k.fy);
    // Footprint of one sub-sample ray per unit of ray length, in world units.
    let sample_angle = inv_ss / f_mean;
    let weight = gain / (ss * ss) as f32;
    let mut image = RgbImage::new(k.width, k.height);
    let mut depth = vec![0f32; w * h];
    let mut row: Vec<&Local> = Vec::with_capacity(locals.len());
    let mut cands: Vec<&Local> = Vec::with_capacity(locals.len());
    for py in 0..h {
        let (y0, y1) = (py as f64, py as f64 + 1.0);
        row.clear();
        row.extend(locals.iter().filter(|l| l.bbox[2] <= y1 && l.bbox[3] >= y0));
        for px in 0..w {
            let (x0, x1) = (px as f64, px as f64 + 1.0);
            cands.clear();
            cands.extend(row.iter().copied().filter(|l| l.bbox[0] <= x1 && l.bbox[1] >= x0));
            let ray = |x: f64, y: f64| {
                let n = k.unproject_pixel(DVec2::new(x, y));
                DVec3::new(n.x, n.y, 1.0)
            };
            let (t, _) = trace(ray(x0 + 0.5, y0 + 0.5), &cands).ok_or_else(|| {
                Error::Invalid(format!("synth: the ray through pixel ({px}, {py}) hit nothing"))
            })?;
            depth[py * w + px] = t as f32;
            let mut acc = [0f32; 3];
            for sy in 0..ss {
                for sx in 0..ss {
                    let d = ray(x0 + (sx as f64 + 0.5) * inv_ss, y0 + (sy as f64 + 0.5) * inv_ss);
                    let (t, l) = trace(d, &cands).ok_or_else(|| {
                        Error::Invalid(format!("synth: a sub-pixel ray of ({px}, {py}) hit nothing"))
                    })?;
                    let c = shade(d, t, l, sample_angle, photos);
                    for (a, v) in acc.iter_mut().zip(c) {
                        *a += v;
                    }
                }
            }
            let i = (py * w + px) * 3;
            for (o, a) in image.data[i..i + 3].iter_mut().zip(acc) {
                *o = (a * weight).clamp(0.0, 1.0);
            }
        }
    }
    Ok((image, depth))
}

/// Colour of the hit at depth `t` along `d` on `l`.
#[inline]
fn shade(d: DVec3, t: f64, l: &Local, sample_angle: f64, photos: &[RgbImage]) -> [f32; 3] {
    let s = l.surf;
    let q = d * t - l.c;
    let (a, b) = (q.dot(l.u), q.dot(l.v));
    let len2 = d.length_squared();
    let cos = (l.n.dot(d).abs() / len2.sqrt()).max(MIN_COS);
    let fp = t * len2.sqrt() * sample_angle / cos / s.tex_scale;
    let c = s.texture.eval(
        (a / s.tex_scale + 0.5) as f32,
        (b / s.tex_scale + 0.5) as f32,
        fp as f32,
        photos,
    );
    [c[0] * s.shade[0], c[1] * s.shade[1], c[2] * s.shade[2]]
}
