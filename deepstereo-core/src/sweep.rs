//! Plane-sweep volumes: every source image reprojected into the target camera at each
//! depth plane, as RGBA.
//!
//! Layout of a volume over a region of `h x w` target pixels:
//! `[D, V, 4, h, w]` f32 (plane-major, then source view, then R, G, B, A).
//!
//! Sampling is bilinear with zero padding, in the same convention as PyTorch's
//! `grid_sample(padding_mode="zeros", align_corners=False)`: a source pixel `(i, j)` has its
//! centre at `(i + 0.5, j + 0.5)`; taps outside the image contribute nothing. Alpha is the
//! bilinear weight of the taps inside the image, so it is 1 in the interior, fractional
//! within half a pixel of the border, and 0 outside; colours are the same zero-padded
//! bilinear sum, so at the border they are premultiplied by alpha. A plane point that is
//! not in front of the source camera gets RGBA = 0, and so does one beyond the range where
//! the source's lens distortion is monotonic ([`crate::camera::Distortion::max_radius2`]),
//! which the distortion polynomial would fold back into the image.

use crate::camera::{Camera, Intrinsics, WorldToCamera};
use crate::error::{Error, Result};
use crate::geometry::{apply_h, plane_homography};
use crate::imageio::RgbImage;
use glam::DVec2;
use rayon::prelude::*;

pub use crate::camera::IN_FRONT_EPS;
/// Channels per source view in a volume: R, G, B, A.
pub const CHANNELS: usize = 4;

/// A source view: its camera and its image at that camera's resolution.
#[derive(Clone, Copy)]
pub struct Source<'a> {
    pub camera: &'a Camera,
    pub image: &'a RgbImage,
}

/// A rectangle of target pixels; `x0`, `y0` may be negative or beyond the image (rays
/// through pixels outside the target image are as valid as those inside).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Region {
    pub x0: i64,
    pub y0: i64,
    pub width: usize,
    pub height: usize,
}

impl Region {
    pub fn full(intr: &Intrinsics) -> Self {
        Self {
            x0: 0,
            y0: 0,
            width: intr.width as usize,
            height: intr.height as usize,
        }
    }
    pub fn len(&self) -> usize {
        self.width * self.height
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Normalized coordinates of the centres of the region's pixels in the target camera.
pub fn target_rays(target: &Intrinsics, region: Region) -> Vec<DVec2> {
    let mut rays = Vec::with_capacity(region.len());
    for y in 0..region.height {
        for x in 0..region.width {
            let uv = DVec2::new(
                (region.x0 + x as i64) as f64 + 0.5,
                (region.y0 + y as i64) as f64 + 0.5,
            );
            rays.push(target.unproject_pixel(uv));
        }
    }
    rays
}

/// Fills `out` (`[D, V, 4, h, w]`, length `D * V * 4 * h * w`) with the plane-sweep volume
/// of `sources` seen from `target` over `region`, for planes at `inv_depths`.
///
/// Parallel over (plane, view) slices; no allocation per pixel. When the target or a
/// source has a moving rolling shutter, [`rolling`] projects per pixel instead (only
/// the slices that involve one; the others are unchanged).
pub fn sweep_into(
    target: &Camera,
    region: Region,
    sources: &[Source<'_>],
    inv_depths: &[f64],
    out: &mut [f32],
) {
    let hw = region.len();
    let v = sources.len();
    debug_assert_eq!(out.len(), inv_depths.len() * v * CHANNELS * hw);
    if hw == 0 || v == 0 {
        return;
    }
    let target_moves = target.moving_shutter().is_some();
    let moves = |s: &Source<'_>| target_moves || s.camera.moving_shutter().is_some();
    // The world rays of the pixels, only when some slice projects per pixel.
    let world = match sources.iter().any(moves) {
        true => rolling::target_world_rays(target, region),
        false => Vec::new(),
    };
    let rays = target_rays(&target.intrinsics, region);
    let rels: Vec<WorldToCamera> = sources
        .iter()
        .map(|s| target.pose.relative_to(&s.camera.pose))
        .collect();
    out.par_chunks_mut(CHANNELS * hw)
        .enumerate()
        .for_each(|(slice, chunk)| {
            let (d, k) = (slice / v, slice % v);
            if moves(&sources[k]) {
                rolling::rolling_slice(&world, inv_depths[d], &sources[k], chunk);
            } else {
                let h = plane_homography(&rels[k], inv_depths[d]);
                warp_slice(&h, &rays, &sources[k], chunk);
            }
        });
}

/// A zeroed `[D, V, 4, h, w]` buffer for [`sweep_into`], or an error naming the size when
/// it overflows or cannot be allocated (a huge `--planes` must not abort the process).
pub fn alloc_volume(planes: usize, views: usize, region: Region) -> Result<Vec<f32>> {
    try_zeroed(
        &[planes, views, CHANNELS, region.width, region.height],
        &format!(
            "a plane-sweep volume of {planes} planes x {views} views x {CHANNELS} x {}x{}",
            region.width, region.height
        ),
    )
}

/// A zeroed buffer of the product of `dims` f32s, or an error naming `what` and the size
/// when the product overflows or the memory cannot be had: a huge `--planes`, `--tile` or
/// image must give an error, not abort the process.
pub fn try_zeroed(dims: &[usize], what: &str) -> Result<Vec<f32>> {
    let len = dims.iter().try_fold(1usize, |a, &b| a.checked_mul(b));
    let too_big = |detail: String| Error::Invalid(format!("{what} f32 {detail}"));
    let len = len.ok_or_else(|| too_big("overflows the address space".into()))?;
    let mut v = Vec::new();
    v.try_reserve_exact(len).map_err(|_| {
        too_big(format!(
            "({:.1} GiB) cannot be allocated",
            len as f64 * 4.0 / (1u64 << 30) as f64
        ))
    })?;
    v.resize(len, 0.0);
    Ok(v)
}

/// Allocating wrapper of [`sweep_into`].
pub fn sweep(
    target: &Camera,
    region: Region,
    sources: &[Source<'_>],
    inv_depths: &[f64],
) -> Vec<f32> {
    let mut out = vec![0.0; inv_depths.len() * sources.len() * CHANNELS * region.len()];
    sweep_into(target, region, sources, inv_depths, &mut out);
    out
}

/// Warps one source through one plane homography into `out` (`[4, h, w]`).
///
/// Per pixel: the homography in f64, the in-front test without a square root, one
/// reciprocal instead of two divisions, and [`sample_bilinear`]'s branch-free interior
/// path; the results equal the straightforward per-pixel formulas to about 1e-13 pixels.
fn warp_slice(h: &glam::DMat3, rays: &[DVec2], src: &Source<'_>, out: &mut [f32]) {
    let hw = rays.len();
    let (r_out, rest) = out.split_at_mut(hw);
    let (g_out, rest) = rest.split_at_mut(hw);
    let (b_out, a_out) = rest.split_at_mut(hw);
    project_slice(h, rays, &src.camera.intrinsics, |i, uv| {
        let rgba = uv.map_or([0.0; 4], |uv| sample_bilinear(src.image, uv.x, uv.y));
        r_out[i] = rgba[0];
        g_out[i] = rgba[1];
        b_out[i] = rgba[2];
        a_out[i] = rgba[3];
    });
}

/// Calls `each(i, uv)` for every ray `rays[i]` (normalized target coordinates) with the
/// source pixel coordinate `uv` its point on the plane of homography `h` projects to, or
/// `None` where the point is not in front of the source (`q.z > IN_FRONT_EPS |q|`) or lies
/// beyond the range where the lens distortion is monotonic.
#[inline(always)]
pub(crate) fn project_slice(
    h: &glam::DMat3,
    rays: &[DVec2],
    intr: &Intrinsics,
    mut each: impl FnMut(usize, Option<DVec2>),
) {
    let max_r2 = intr.distortion.map_or(f64::INFINITY, |d| d.max_radius2());
    let eps2 = IN_FRONT_EPS * IN_FRONT_EPS;
    for (i, ray) in rays.iter().enumerate() {
        let q = apply_h(h, ray.x, ray.y);
        // In front: q.z > IN_FRONT_EPS * |q|, compared squared.
        let uv = if q.z > 0.0 && q.z * q.z > eps2 * q.length_squared() {
            let inv_z = 1.0 / q.z;
            let n = DVec2::new(q.x * inv_z, q.y * inv_z);
            (n.length_squared() < max_r2).then(|| match &intr.distortion {
                None => DVec2::new(intr.fx * n.x + intr.cx, intr.fy * n.y + intr.cy),
                Some(_) => intr.project_normalized(n),
            })
        } else {
            None
        };
        each(i, uv);
    }
}

/// `floor(s)` as an integer without a libm call; exact for `|s| < 2^63`.
#[inline]
fn floor_i64(s: f64) -> i64 {
    let t = s as i64;
    if (t as f64) > s {
        t - 1
    } else {
        t
    }
}

/// Zero-padded bilinear sample at pixel coordinate `(u, v)` (pixel centres at `i + 0.5`);
/// returns RGB and the coverage alpha.
#[inline]
pub fn sample_bilinear(img: &RgbImage, u: f64, v: f64) -> [f32; 4] {
    let (w, h) = (img.width as i64, img.height as i64);
    let (sx, sy) = (u - 0.5, v - 0.5);
    // Also rejects NaN: comparisons with NaN are false.
    if !(sx > -1.0 && sy > -1.0 && sx < w as f64 && sy < h as f64) {
        return [0.0; 4];
    }
    let (x0, y0) = (floor_i64(sx), floor_i64(sy));
    // Weights and sums in f64, rounded once: in f32 the four weights can sum to
    // 1.0000001, giving alpha > 1 and colours above alpha.
    let (ax, ay) = (sx - x0 as f64, sy - y0 as f64);
    let weights = [
        (1.0 - ax) * (1.0 - ay),
        ax * (1.0 - ay),
        (1.0 - ax) * ay,
        ax * ay,
    ];
    let mut acc = [0.0f64; 4];
    if x0 >= 0 && y0 >= 0 && x0 + 1 < w && y0 + 1 < h {
        // Interior: all four taps exist. The same sums in the same order as below (a zero
        // weight adds an exact zero), so both paths give identical results.
        let stride = img.width as usize * 3;
        let i = y0 as usize * stride + x0 as usize * 3;
        let rows = (
            img.data.get(i..i + 6),
            img.data.get(i + stride..i + stride + 6),
        );
        if let (Some(r0), Some(r1)) = rows {
            let px = [&r0[..3], &r0[3..], &r1[..3], &r1[3..]];
            for (p, wt) in px.iter().zip(weights) {
                acc[0] += wt * p[0] as f64;
                acc[1] += wt * p[1] as f64;
                acc[2] += wt * p[2] as f64;
                acc[3] += wt;
            }
            return acc.map(|v| v as f32);
        }
    }
    let taps = [(x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1)];
    for ((x, y), wt) in taps.into_iter().zip(weights) {
        if x >= 0 && y >= 0 && x < w && y < h && wt > 0.0 {
            let i = (y as usize * img.width as usize + x as usize) * 3;
            if let Some(p) = img.data.get(i..i + 3) {
                acc[0] += wt * p[0] as f64;
                acc[1] += wt * p[1] as f64;
                acc[2] += wt * p[2] as f64;
                acc[3] += wt;
            }
        }
    }
    acc.map(|v| v as f32)
}

pub mod coords;
pub mod cue;
pub mod rolling;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_extreme;
#[cfg(test)]
mod tests_rolling;
