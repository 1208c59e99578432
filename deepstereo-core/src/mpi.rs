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
use glam::{DVec2, DVec3};
use rayon::prelude::*;
use std::sync::OnceLock;

pub mod agree;
pub mod fill;
pub mod io;
pub mod planned;
pub mod smooth;
mod texture;
mod tiles;
pub mod viewer;
pub mod warp;

#[cfg(test)]
use texture::{run, BLOCK_SHIFT};
use texture::{RowRuns, Texture};
pub(crate) use tiles::tile_layers;
pub use tiles::{layers, layers_of_tiles, TileGrid};

/// A multiplane image: straight-alpha RGBA planes in a pinhole reference camera.
#[derive(Clone, Debug)]
pub struct Mpi {
    /// The reference camera: a pinhole with a global shutter.
    pub camera: Camera,
    /// Inverse depths of the planes, near to far (camera z; 0 is a plane at infinity).
    pub inv_depths: Vec<f64>,
    /// Per plane, `[H, W, 4]` row-major RGBA in [0, 1], straight (not premultiplied).
    planes: Vec<Vec<f32>>,
    /// Per plane, what [`Self::render`] samples: built on the first render (a bake's
    /// intermediate MPIs and one only written to files never need them).
    textures: OnceLock<Vec<Texture>>,
    /// Pixels of its image on every side beyond the view it was baked for
    /// ([`with_margin`]; 0: none). The viewer's `?fit=native` leaves them out.
    pub margin: u32,
}

/// `camera` as an MPI's reference: its pinhole part at the mid-readout pose.
pub fn reference_camera(camera: &Camera) -> Camera {
    let k = &camera.intrinsics;
    Camera {
        intrinsics: Intrinsics::pinhole(k.fx, k.fy, k.cx, k.cy, k.width, k.height),
        ..camera.without_rolling_shutter()
    }
}

/// `camera` with `margin` pixels added on every side of its image (the principal point
/// moves with them): the same rays through its pixels, and more around them. An MPI baked
/// at it covers what a camera moved away from the reference sees beyond the reference's
/// image, which the sources often do.
pub fn with_margin(camera: &Camera, margin: u32) -> Camera {
    let k = &camera.intrinsics;
    let m = margin as f64;
    Camera {
        intrinsics: Intrinsics::pinhole(
            k.fx,
            k.fy,
            k.cx + m,
            k.cy + m,
            k.width + 2 * margin,
            k.height + 2 * margin,
        ),
        ..*camera
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
    /// An MPI of `planes` (per plane `[H, W, 4]` straight RGBA in [0, 1], near to far)
    /// at the inverse depths `inv_depths` in the reference `camera`.
    pub fn new(camera: Camera, inv_depths: Vec<f64>, planes: Vec<Vec<f32>>) -> Result<Self> {
        let (w, h) = camera.intrinsics.size();
        if planes.len() != inv_depths.len() || planes.iter().any(|p| p.len() != w * h * 4) {
            return Err(Error::Invalid(format!(
                "an MPI of {w}x{h} needs one RGBA plane of that size per inverse depth ({} \
                 planes, {} inverse depths)",
                planes.len(),
                inv_depths.len()
            )));
        }
        Ok(Self {
            camera,
            inv_depths,
            planes,
            textures: OnceLock::new(),
            margin: 0,
        })
    }

    /// Per plane, `[H, W, 4]` row-major RGBA in [0, 1], straight (not premultiplied).
    pub fn planes(&self) -> &[Vec<f32>] {
        &self.planes
    }

    /// Per plane, what [`Self::render`] samples (built on the first call).
    fn textures(&self) -> &[Texture] {
        self.textures.get_or_init(|| {
            let (w, h) = (self.width(), self.height());
            (self.planes.par_iter())
                .map(|p| Texture::of(p, w, h))
                .collect()
        })
    }

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
        let (w, h) = camera.intrinsics.size();
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
        Self::new(camera, inv_depths, planes)
    }

    /// This MPI with its composite at the reference camera made `target` (`[H, W, 3]` in
    /// [0, 1], the MPI's size): at each pixel, every plane's straight colour moves by
    /// `(target - C) / A`, `C` the composite and `A` its coverage (`sum_z s_z`, 1 wherever
    /// a plane selects anything), so the composite becomes `C + A (target - C) / A =
    /// target`, exactly where no colour leaves [0, 1] (those are clamped); alphas, and so
    /// the planes' geometry, are unchanged. A pixel no plane covers stays as it is, and so
    /// does the margin ([`Self::margin`]): only the reference image is made `target`.
    pub fn with_composite(&self, target: &RgbImage) -> Result<Self> {
        let (w, h) = (self.width(), self.height());
        if (target.width as usize, target.height as usize) != (w, h) {
            return Err(Error::Invalid(format!(
                "a composite of {}x{} for an MPI of {w}x{h}",
                target.width, target.height
            )));
        }
        let (now, coverage) = self.composite_with_coverage();
        let mut planes = self.planes.clone();
        // A texel's centre inside the view the MPI was baked for.
        let inside = |p: usize| self.in_core((p % w) as f64 + 0.5, (p / w) as f64 + 0.5);
        for p in 0..w * h {
            if coverage[p] <= 0.0 || !inside(p) {
                continue;
            }
            for c in 0..3 {
                let shift = (target.data[p * 3 + c] - now.data[p * 3 + c]) / coverage[p];
                for plane in planes.iter_mut() {
                    let v = &mut plane[p * 4 + c];
                    *v = (*v + shift).clamp(0.0, 1.0);
                }
            }
        }
        let mut out = Self::new(self.camera, self.inv_depths.clone(), planes)?;
        out.margin = self.margin;
        Ok(out)
    }

    /// The planes composited back to front at the reference camera.
    pub fn composite(&self) -> RgbImage {
        self.composite_with_coverage().0
    }

    /// [`Self::composite`] and the accumulated alpha per pixel.
    fn composite_with_coverage(&self) -> (RgbImage, Vec<f32>) {
        let (w, h) = (self.width(), self.height());
        let mut img = RgbImage::new(w as u32, h as u32);
        let mut coverage = vec![0f32; w * h];
        for p in 0..w * h {
            let (mut c, mut a) = ([0f32; 3], 0f32);
            for plane in self.planes.iter().rev() {
                let px = &plane[p * 4..p * 4 + 4];
                for k in 0..3 {
                    c[k] = px[3] * px[k] + (1.0 - px[3]) * c[k];
                }
                a = px[3] + (1.0 - px[3]) * a;
            }
            img.data[p * 3..p * 3 + 3].copy_from_slice(&c);
            coverage[p] = a;
        }
        (img, coverage)
    }

    /// Renders the MPI at `camera` (any intrinsics and distortion; rolling shutter
    /// ignored): colour `[H, W, 3]` composited over black (so premultiplied by the
    /// coverage) and the accumulated alpha `[H, W]` (0 where no plane covers the ray:
    /// outside the reference image, or behind). Planes are composited front to back,
    /// `C += T a c`, `T *= 1 - a` (the same sum as "over" back to front), and a ray stops
    /// once its transmittance `T` is below [`OPAQUE_T`].
    pub fn render(&self, camera: &Camera) -> (RgbImage, Vec<f32>) {
        let (img, alpha, _) = self.render_parts(camera, false);
        (img, alpha)
    }

    /// [`Self::render`], and the render of the view the MPI was baked for alone, its
    /// margin left out (samples outside the view are absent, as for an MPI baked without
    /// a margin): `[H, W, 4]`, premultiplied colour and accumulated alpha per pixel (the
    /// same as [`Self::render`]'s without a margin).
    pub fn render_with_core(&self, camera: &Camera) -> (RgbImage, Vec<f32>, Vec<f32>) {
        let (img, alpha, core) = self.render_parts(camera, true);
        (img, alpha, core.unwrap_or_default())
    }

    fn render_parts(&self, camera: &Camera, core: bool) -> (RgbImage, Vec<f32>, Option<Vec<f32>>) {
        let (w, h) = camera.intrinsics.size();
        let rel = camera.pose.relative_to(&self.camera.pose);
        let maps = self.plane_maps(rel.translation);
        let mut img = RgbImage::new(w as u32, h as u32);
        let mut alpha = vec![0f32; w * h];
        let mut kept = vec![0f32; if core { w * h * 4 } else { 0 }];
        let mut krows: Vec<Option<&mut [f32]>> = match core {
            true => kept.chunks_mut(w * 4).map(Some).collect(),
            false => (0..h).map(|_| None).collect(),
        };
        img.data
            .par_chunks_mut(w * 3)
            .zip(alpha.par_chunks_mut(w))
            .zip(krows.par_iter_mut())
            .enumerate()
            .for_each(|(y, ((row, arow), krow))| {
                let rays: Vec<DVec3> = (0..w)
                    .map(|x| {
                        let uv = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                        let n = camera.intrinsics.unproject_pixel(uv);
                        rel.rotation * DVec3::new(n.x, n.y, 1.0)
                    })
                    .collect();
                self.row(&maps, &rays, true, row, arow, krow.as_deref_mut());
            });
        drop(krows);
        (img, alpha, core.then_some(kept))
    }

    /// Whether reference pixel coordinate `(u, v)` lies in the view the MPI was baked for
    /// (inside the margin; pixel edges, as [`Texture::sample`] bounds the image).
    #[inline]
    fn in_core(&self, u: f64, v: f64) -> bool {
        let m = self.margin as f64;
        let (w, h) = (self.width() as f64, self.height() as f64);
        u >= m && v >= m && u <= w - m && v <= h - m
    }

    /// One row of rays, `rays` their directions in the reference camera's coordinates,
    /// `maps` from [`Self::plane_maps`]: premultiplied colours into `row` (`[W, 3]`) and
    /// accumulated alphas into `arow` (`[W]`, both zero on entry). Plane by plane, near
    /// to far, so each pixel composites front to back; a ray stops once opaque. A plane is
    /// hit when `alpha_z / (R r)_z` is positive (the point lies ahead of the camera).
    ///
    /// With `bisect`, when the row's slopes `a` and `b` are each monotonic and finite and
    /// its `(R r)_z` share one sign (a pinhole row always), the rays that land inside a
    /// plane form one run, found by bisection, and only that run is visited. Otherwise
    /// every ray is (the same result). With `krow` (`[W, 4]`, zero on entry), also the
    /// composite of the samples inside the view the MPI was baked for ([`Self::in_core`]),
    /// premultiplied colour and alpha, with its own transmittance.
    fn row(
        &self,
        maps: &[[f64; 5]],
        rays: &[DVec3],
        bisect: bool,
        row: &mut [f32],
        arow: &mut [f32],
        mut krow: Option<&mut [f32]>,
    ) {
        let a: Vec<f64> = rays.iter().map(|r| r.x / r.z).collect();
        let b: Vec<f64> = rays.iter().map(|r| r.y / r.z).collect();
        let rz: Vec<f64> = rays.iter().map(|r| r.z).collect();
        let runs = RowRuns::of(&a, &b, &rz).filter(|_| bisect);
        let (w, h) = (self.width() as f64, self.height() as f64);
        let mut trans = vec![1f32; rays.len()];
        // The core's transmittance (all 0 without a core composite: never consulted).
        let mut core_t = vec![if krow.is_some() { 1f32 } else { 0.0 }; rays.len()];
        for (tex, m) in self.textures().iter().zip(maps) {
            let xs = match &runs {
                Some(r) => r.inside(m, w, h),
                None => 0..rays.len(),
            };
            for x in xs {
                if (trans[x] < OPAQUE_T && core_t[x] < OPAQUE_T) || m[0] * rz[x] <= 0.0 {
                    continue;
                }
                let (u, v) = (m[1] * a[x] + m[2], m[3] * b[x] + m[4]);
                let Some(px) = tex.sample(u, v) else {
                    continue;
                };
                if let Some(k) = krow.as_deref_mut().filter(|_| self.in_core(u, v)) {
                    for (c, v) in k[x * 4..x * 4 + 4].iter_mut().zip(px) {
                        *c += core_t[x] * v;
                    }
                    core_t[x] *= 1.0 - px[3];
                }
                if trans[x] < OPAQUE_T {
                    continue;
                }
                for (c, v) in row[x * 3..x * 3 + 3].iter_mut().zip(px) {
                    *c += trans[x] * v;
                }
                trans[x] *= 1.0 - px[3];
            }
        }
        for (a, t) in arow.iter_mut().zip(&trans) {
            *a = 1.0 - t;
        }
    }

    /// [`plane_maps`] of this MPI's planes.
    fn plane_maps(&self, t: DVec3) -> Vec<[f64; 5]> {
        plane_maps(&self.camera.intrinsics, &self.inv_depths, t)
    }
}

/// Per plane of inverse depth `rho_z` in a reference camera of intrinsics `k`, for a
/// camera whose centre is `t` in the reference's coordinates: the factor
/// `alpha_z = 1 - rho_z t_z` and the affine map from a ray's slopes
/// `(a, b) = ((R r)_x, (R r)_y) / (R r)_z` to the plane point's reference pixel,
/// `u = fx (alpha_z a + rho_z t_x) + cx`, `v = fy (alpha_z b + rho_z t_y) + cy` (the point
/// `q` of the module docs has `q_z = 1`): `[alpha, su, ou, sv, ov]`. The ray hits the
/// plane ahead of that camera when `alpha_z (R r)_z > 0`.
pub fn plane_maps(k: &Intrinsics, inv_depths: &[f64], t: DVec3) -> Vec<[f64; 5]> {
    (inv_depths.iter())
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

/// Transmittance below which a ray is opaque: what is behind moves its colour by less
/// than a tenth of an 8-bit step.
pub const OPAQUE_T: f32 = 1.0 / 2560.0;

/// The weight of a blended MPI's margin against the views the MPIs were baked for
/// ([`render_blend`]'s `delta`; chosen on training scenes, 0.25 over 0.05: +0.1 dB).
pub const MARGIN_BLEND_WEIGHT: f64 = 0.25;

/// Renders several MPIs of one scene at `camera`, blended as LLFF does, each MPI's
/// margin weighed down against the views the MPIs were baked for:
/// `C = sum_i w_i (C'_i + delta C_i) / sum_i w_i (A'_i + delta A_i)`, with `C_i` MPI
/// `i`'s render (composited over black, so premultiplied by its accumulated alpha `A_i`),
/// `C'_i`, `A'_i` the render of the view it was baked for alone, its margin left out
/// ([`Mpi::render_with_core`]), `w_i = 1 / (d_i + eps)^2`, `d_i` the distance of its
/// reference camera's centre to `camera`'s (`eps`: a thousandth of the largest) and
/// `delta` [`MARGIN_BLEND_WEIGHT`]. A margin is the network's extrapolation: where a
/// farther MPI photographed what a nearer one's margin shows, the farther one counts
/// `(1 + delta) / delta` times as much at equal distance.
/// Without margins `C' = C`, LLFF's blend. Where no MPI covers the ray (a camera moved
/// beyond their images), the colour is filled from the covered pixels around it
/// ([`fill::fill_holes`]).
pub fn render_blend(mpis: &[Mpi], camera: &Camera) -> RgbImage {
    let centre = camera.pose.centre();
    let dists: Vec<f64> = (mpis.iter())
        .map(|m| (m.camera.pose.centre() - centre).length())
        .collect();
    let eps = 1e-3 * dists.iter().cloned().fold(1e-9, f64::max);
    // One MPI, or none with a margin: C' = C (and `render` is faster).
    let core = mpis.len() > 1 && mpis.iter().any(|m| m.margin > 0);
    let renders: Vec<(RgbImage, Vec<f32>, Vec<f32>)> = (mpis.iter())
        .map(|m| match core {
            true => m.render_with_core(camera),
            false => {
                let (img, a) = m.render(camera);
                (img, a, Vec::new())
            }
        })
        .collect();
    let (w, h) = camera.intrinsics.size();
    let mut img = RgbImage::new(w as u32, h as u32);
    img.data.par_chunks_mut(3).enumerate().for_each(|(p, out)| {
        let (mut c, mut total) = ([0f64; 3], 0f64);
        for ((r, a, k), d) in renders.iter().zip(&dists) {
            let wgt = 1.0 / (d + eps).powi(2);
            let (own, own_a) = match core {
                true => (&k[p * 4..p * 4 + 3], k[p * 4 + 3] as f64),
                false => (&r.data[p * 3..p * 3 + 3], a[p] as f64),
            };
            let full = &r.data[p * 3..p * 3 + 3];
            for ((ck, &o), &f) in c.iter_mut().zip(own).zip(full) {
                *ck += wgt * (o as f64 + MARGIN_BLEND_WEIGHT * f as f64);
            }
            total += wgt * (own_a + MARGIN_BLEND_WEIGHT * a[p] as f64);
        }
        if total > 1e-12 {
            for (o, ck) in out.iter_mut().zip(c) {
                *o = (ck / total) as f32;
            }
        }
    });
    let covered: Vec<bool> = (0..w * h)
        .map(|p| renders.iter().any(|(_, a, _)| a[p] > 0.0))
        .collect();
    fill::fill_holes(&mut img, &covered);
    img
}

#[cfg(test)]
mod tests;
