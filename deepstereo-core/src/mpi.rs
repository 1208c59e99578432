//! Multiplane images (MPIs) baked from the network, and their rendering on the CPU.
//!
//! For a reference camera the network gives, per pixel and plane `z` (near to far), a
//! colour `c_z` and a selection `s_z` with `sum_z s_z = 1`, and renders `sum_z s_z c_z`.
//! With the alpha `a_z = s_z / sum_{k >= z} s_k` (the farthest plane that selects
//! anything has alpha 1), compositing the planes back to front with "over",
//! `C <- a_z c_z + (1 - a_z) C`, gives `sum_z a_z c_z prod_{j < z} (1 - a_j)`, and the
//! product telescopes to `sum_{k >= z} s_k`, so the composite is exactly `sum_z s_z c_z`
//! at the reference camera. Seen from another camera each plane is warped by its
//! homography, which gives parallax near the reference: an MPI.
//!
//! Planes are fronto-parallel in the reference camera at the inverse depths `rho_z`
//! (camera z, `0` for a plane at infinity). For a ray `r` of another camera whose
//! coordinates map to the reference's as `p_ref = R p + t`, the point on plane `z` is, up
//! to the factor `rho_z` that the projection divides out,
//! `q = (1 - rho_z t_z) / (R r)_z * R r + rho_z t`, in front of that camera when the
//! factor `(1 - rho_z t_z) / (R r)_z` is positive. Pixel centres sit at `i + 0.5`.

use crate::camera::{Camera, Intrinsics};
use crate::error::{Error, Result};
use crate::imageio::RgbImage;
use crate::inputs::{tile_inputs, PyramidSource};
use crate::render::Backend;
use glam::{DVec2, DVec3};
use rayon::prelude::*;

pub mod io;
pub mod viewer;

/// A multiplane image: straight-alpha RGBA planes in a pinhole reference camera.
#[derive(Clone, Debug)]
pub struct Mpi {
    /// The reference camera: a pinhole with a global shutter.
    pub camera: Camera,
    /// Inverse depths of the planes, near to far (camera z; 0 is a plane at infinity).
    pub inv_depths: Vec<f64>,
    /// Per plane, `[H, W, 4]` row-major RGBA in [0, 1], straight (not premultiplied).
    pub planes: Vec<Vec<f32>>,
}

/// `camera` as an MPI's reference: its pinhole part at the mid-readout pose.
pub fn reference_camera(camera: &Camera) -> Camera {
    let k = &camera.intrinsics;
    Camera {
        intrinsics: Intrinsics::pinhole(k.fx, k.fy, k.cx, k.cy, k.width, k.height),
        ..camera.without_rolling_shutter()
    }
}

/// The alphas of one pixel's planes (near to far) from its selection `s` (near to far).
pub fn alphas(s: &[f32]) -> Vec<f32> {
    let mut out = vec![0f32; s.len()];
    let mut behind = 0f64;
    for z in (0..s.len()).rev() {
        let sz = s[z].max(0.0) as f64;
        behind += sz;
        out[z] = if behind > 0.0 {
            (sz / behind).clamp(0.0, 1.0) as f32
        } else {
            0.0
        };
    }
    out
}

impl Mpi {
    pub fn width(&self) -> usize {
        self.camera.intrinsics.width as usize
    }

    pub fn height(&self) -> usize {
        self.camera.intrinsics.height as usize
    }

    /// From the network's layers at `camera`: `colours` `[D, 3, H, W]`, `selection`
    /// `[D, H, W]` (colours clamped to [0, 1]).
    pub fn from_layers(
        camera: Camera,
        inv_depths: Vec<f64>,
        colours: &[f32],
        selection: &[f32],
    ) -> Result<Self> {
        let (w, h) = (
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
        );
        let (d, n) = (inv_depths.len(), w * h);
        if colours.len() != d * 3 * n || selection.len() != d * n {
            return Err(Error::Invalid(format!(
                "MPI layers of {} colour and {} selection values do not fit {d} planes of {w}x{h}",
                colours.len(),
                selection.len()
            )));
        }
        let mut planes = vec![vec![0f32; n * 4]; d];
        let mut s = vec![0f32; d];
        for p in 0..n {
            for (z, v) in s.iter_mut().enumerate() {
                *v = selection[z * n + p];
            }
            for (z, a) in alphas(&s).into_iter().enumerate() {
                let px = &mut planes[z][p * 4..p * 4 + 4];
                for c in 0..3 {
                    px[c] = colours[(z * 3 + c) * n + p].clamp(0.0, 1.0);
                }
                px[3] = a;
            }
        }
        Ok(Self {
            camera,
            inv_depths,
            planes,
        })
    }

    /// The planes composited back to front at the reference camera.
    pub fn composite(&self) -> RgbImage {
        let (w, h) = (self.width(), self.height());
        let mut img = RgbImage::new(w as u32, h as u32);
        for p in 0..w * h {
            let mut c = [0f32; 3];
            for plane in self.planes.iter().rev() {
                let px = &plane[p * 4..p * 4 + 4];
                for k in 0..3 {
                    c[k] = px[3] * px[k] + (1.0 - px[3]) * c[k];
                }
            }
            img.data[p * 3..p * 3 + 3].copy_from_slice(&c);
        }
        img
    }

    /// Renders the MPI at `camera` (any intrinsics and distortion; rolling shutter
    /// ignored): colour `[H, W, 3]` composited over black (so premultiplied by the
    /// coverage) and the accumulated alpha `[H, W]` (0 where no plane covers the ray:
    /// outside the reference image, or behind). Planes are composited front to back,
    /// `C += T a c`, `T *= 1 - a` (the same sum as "over" back to front), and a ray stops
    /// once its transmittance `T` is below [`OPAQUE_T`].
    pub fn render(&self, camera: &Camera) -> (RgbImage, Vec<f32>) {
        let (w, h) = (
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
        );
        let rel = camera.pose.relative_to(&self.camera.pose);
        let planes = self.plane_maps(rel.translation);
        let mut img = RgbImage::new(w as u32, h as u32);
        let mut alpha = vec![0f32; w * h];
        img.data
            .par_chunks_mut(w * 3)
            .zip(alpha.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, (row, arow))| {
                for x in 0..w {
                    let uv = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                    let n = camera.intrinsics.unproject_pixel(uv);
                    let rr = rel.rotation * DVec3::new(n.x, n.y, 1.0);
                    let (c, a) = self.ray(&planes, rr);
                    row[x * 3..x * 3 + 3].copy_from_slice(&c);
                    arow[x] = a;
                }
            });
        (img, alpha)
    }

    /// Per plane, for a camera whose centre is `t` in the reference's coordinates: the
    /// factor `alpha_z = 1 - rho_z t_z` and the affine map from a ray's slopes
    /// `(a, b) = ((R r)_x, (R r)_y) / (R r)_z` to the plane point's reference pixel,
    /// `u = fx (alpha_z a + rho_z t_x) + cx`, `v = fy (alpha_z b + rho_z t_y) + cy` (the
    /// point `q` of the module docs has `q_z = 1`): `[alpha, su, ou, sv, ov]`.
    fn plane_maps(&self, t: DVec3) -> Vec<[f64; 5]> {
        let k = &self.camera.intrinsics;
        (self.inv_depths.iter())
            .map(|&rho| {
                let al = 1.0 - rho * t.z;
                [
                    al,
                    k.fx * al,
                    k.fx * rho * t.x + k.cx,
                    k.fy * al,
                    k.fy * rho * t.y + k.cy,
                ]
            })
            .collect()
    }

    /// One ray, `rr` its direction in the reference camera's coordinates, `maps` from
    /// [`Self::plane_maps`]: premultiplied colour and accumulated alpha. A plane is hit
    /// when `alpha_z / (R r)_z` is positive (the point lies ahead of the camera; both are
    /// finite here).
    fn ray(&self, maps: &[[f64; 5]], rr: DVec3) -> ([f32; 3], f32) {
        let (mut c, mut trans) = ([0f32; 3], 1f32);
        let (a, b) = (rr.x / rr.z, rr.y / rr.z);
        if !(a.is_finite() && b.is_finite()) {
            return (c, 0.0);
        }
        let (w, h) = (self.width(), self.height());
        for (plane, m) in self.planes.iter().zip(maps) {
            if m[0] * rr.z <= 0.0 {
                continue;
            }
            let px = sample(plane, w, h, m[1] * a + m[2], m[3] * b + m[4]);
            let wgt = trans * px[3];
            for ch in 0..3 {
                c[ch] += wgt * px[ch];
            }
            trans *= 1.0 - px[3];
            if trans < OPAQUE_T {
                break;
            }
        }
        (c, 1.0 - trans)
    }
}

/// Transmittance below which a ray is opaque: what is behind moves its colour by less
/// than a tenth of an 8-bit step.
pub const OPAQUE_T: f32 = 1.0 / 2560.0;

/// Bilinear RGBA at pixel coordinate `(u, v)` (centres at `i + 0.5`); transparent
/// outside the image (edge pixels extend half a pixel).
#[inline]
fn sample(plane: &[f32], w: usize, h: usize, u: f64, v: f64) -> [f32; 4] {
    if !(u >= 0.0 && v >= 0.0 && u <= w as f64 && v <= h as f64) {
        return [0.0; 4];
    }
    let (fx, fy) = (u - 0.5, v - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (ax, ay) = ((fx - x0) as f32, (fy - y0) as f32);
    // x0 >= -1 and x0 + 1 <= w here, so only the two edges clamp.
    let (xi, yi) = (x0 as isize, y0 as isize);
    let xa = xi.max(0) as usize;
    let xb = ((xi + 1) as usize).min(w - 1);
    let ya = yi.max(0) as usize;
    let yb = ((yi + 1) as usize).min(h - 1);
    let (ra, rb) = (
        &plane[ya * w * 4..(ya + 1) * w * 4],
        &plane[yb * w * 4..(yb + 1) * w * 4],
    );
    let (p00, p01) = (&ra[xa * 4..xa * 4 + 4], &ra[xb * 4..xb * 4 + 4]);
    let (p10, p11) = (&rb[xa * 4..xa * 4 + 4], &rb[xb * 4..xb * 4 + 4]);
    let mut out = [0f32; 4];
    for (ch, o) in out.iter_mut().enumerate() {
        let top = p00[ch] + (p01[ch] - p00[ch]) * ax;
        let bottom = p10[ch] + (p11[ch] - p10[ch]) * ax;
        *o = top + (bottom - top) * ay;
    }
    out
}

/// Renders several MPIs of one scene at `camera`, blended as LLFF does:
/// `C = sum_i w_i C_i / sum_i w_i A_i`, with `C_i` MPI `i`'s render (composited over
/// black, so premultiplied by its accumulated alpha `A_i`) and `w_i = 1 / (d_i + eps)^2`,
/// `d_i` the distance of its reference camera's centre to `camera`'s (`eps`: a
/// thousandth of the largest). Black where no MPI covers the ray.
pub fn render_blend(mpis: &[Mpi], camera: &Camera) -> RgbImage {
    let centre = camera.pose.centre();
    let dists: Vec<f64> = (mpis.iter())
        .map(|m| (m.camera.pose.centre() - centre).length())
        .collect();
    let eps = 1e-3 * dists.iter().cloned().fold(1e-9, f64::max);
    let renders: Vec<(RgbImage, Vec<f32>)> = mpis.iter().map(|m| m.render(camera)).collect();
    let (w, h) = (
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
    );
    let mut img = RgbImage::new(w as u32, h as u32);
    for p in 0..w * h {
        let (mut c, mut total) = ([0f64; 3], 0f64);
        for ((r, a), d) in renders.iter().zip(&dists) {
            let wgt = 1.0 / (d + eps).powi(2);
            for (ck, &rk) in c.iter_mut().zip(&r.data[p * 3..p * 3 + 3]) {
                *ck += wgt * rk as f64;
            }
            total += wgt * a[p] as f64;
        }
        if total > 1e-12 {
            for (out, ck) in img.data[p * 3..p * 3 + 3].iter_mut().zip(c) {
                *out = (ck / total) as f32;
            }
        }
    }
    img
}

/// Bakes the MPI of `camera` (made a pinhole, [`reference_camera`]) from `sources` at
/// `inv_depths` (near to far), tile by tile (`tile` rounded up to the model's
/// alignment); `progress(done, total)` after each tile.
pub fn bake(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    tile: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<Mpi> {
    let cfg = backend.config();
    let camera = reference_camera(camera);
    let a = cfg.tile_align();
    let tile = tile.max(1).div_ceil(a) * a;
    let (w, h) = (
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
    );
    let d = inv_depths.len();
    if d == 0 {
        return Err(Error::Invalid("at least one depth plane is needed".into()));
    }
    let n = w * h;
    let (mut colours, mut selection) = (vec![0f32; d * 3 * n], vec![0f32; d * n]);
    let (ntx, nty) = (w.div_ceil(tile), h.div_ceil(tile));
    for ty in 0..nty {
        for tx in 0..ntx {
            let (x0, y0) = (tx * tile, ty * tile);
            let inputs = tile_inputs(
                cfg,
                &camera,
                sources,
                inv_depths,
                (x0 as i64, y0 as i64),
                (tile, tile),
            )?;
            let (c, s) = backend.run_layers(&inputs, d)?;
            if c.iter().chain(&s).any(|v| !v.is_finite()) {
                return Err(Error::Invalid(format!(
                    "the network produced non-finite values in the tile at ({x0}, {y0})"
                )));
            }
            let tt = tile * tile;
            for y in y0..(y0 + tile).min(h) {
                for x in x0..(x0 + tile).min(w) {
                    let (p, q) = (y * w + x, (y - y0) * tile + (x - x0));
                    for z in 0..d {
                        selection[z * n + p] = s[z * tt + q];
                        for ch in 0..3 {
                            colours[(z * 3 + ch) * n + p] = c[(z * 3 + ch) * tt + q];
                        }
                    }
                }
            }
            progress(ty * ntx + tx + 1, ntx * nty);
        }
    }
    Mpi::from_layers(camera, inv_depths.to_vec(), &colours, &selection)
}

#[cfg(test)]
mod tests;
