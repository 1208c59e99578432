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
use std::sync::OnceLock;

pub mod agree;
pub mod fill;
pub mod io;
pub mod planned;
pub mod smooth;
pub mod viewer;
pub mod warp;

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
        let (w, h) = (
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
        );
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
        let (w, h) = (
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
        );
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

/// A row of rays whose slopes `a` and `b` are each monotonic and finite and whose
/// `(R r)_z` share one sign: the rays that land inside a plane's image are one run.
struct RowRuns<'a> {
    a: &'a [f64],
    b: &'a [f64],
    /// Whether `a`, `b` ascend (else they descend).
    a_up: bool,
    b_up: bool,
    rz_sign: f64,
}

impl<'a> RowRuns<'a> {
    /// `None` when the row lacks that shape.
    fn of(a: &'a [f64], b: &'a [f64], rz: &[f64]) -> Option<Self> {
        let order = |v: &[f64]| -> Option<bool> {
            if v.iter().any(|x| !x.is_finite()) {
                return None;
            }
            let up = v.windows(2).all(|p| p[0] <= p[1]);
            let down = v.windows(2).all(|p| p[0] >= p[1]);
            (up || down).then_some(up)
        };
        let rz_sign = rz.first()?.signum();
        if rz.iter().any(|z| z.signum() != rz_sign || *z == 0.0) {
            return None;
        }
        Some(Self {
            a,
            b,
            a_up: order(a)?,
            b_up: order(b)?,
            rz_sign,
        })
    }

    /// The run of rays that may land inside the `w x h` image of the plane with map `m`
    /// ([`Mpi::plane_maps`]): a superset (its bounds widened by a millionth of a pixel)
    /// of those where `0 <= u <= w` and `0 <= v <= h`; empty when the plane lies behind.
    fn inside(&self, m: &[f64; 5], w: f64, h: f64) -> std::ops::Range<usize> {
        if m[0] * self.rz_sign <= 0.0 {
            return 0..0;
        }
        let ra = run(self.a, self.a_up, m[1], m[2], w);
        let rb = run(self.b, self.b_up, m[3], m[4], h);
        ra.start.max(rb.start)..ra.end.min(rb.end).max(ra.start.max(rb.start))
    }
}

/// The run of the monotonic `v` (ascending when `up`) where `0 <= s v + o <= side`,
/// widened by a millionth of a pixel.
fn run(v: &[f64], up: bool, s: f64, o: f64, side: f64) -> std::ops::Range<usize> {
    const SLACK: f64 = 1e-6;
    let (lo, hi) = (-SLACK, side + SLACK);
    if s == 0.0 {
        return match o >= lo && o <= hi {
            true => 0..v.len(),
            false => 0..0,
        };
    }
    // s v + o in [lo, hi]  <=>  v in [vlo, vhi] (the bounds swap when s < 0), widened
    // again for the division's rounding.
    let (p, q) = ((lo - o) / s, (hi - o) / s);
    let (vlo, vhi) = (p.min(q), p.max(q));
    let pad = 1e-12 * (1.0 + vlo.abs().max(vhi.abs()));
    let (vlo, vhi) = (vlo - pad, vhi + pad);
    let (start, end) = match up {
        true => (
            v.partition_point(|&x| x < vlo),
            v.partition_point(|&x| x <= vhi),
        ),
        false => (
            v.partition_point(|&x| x > vhi),
            v.partition_point(|&x| x >= vlo),
        ),
    };
    start..end.max(start)
}

/// A plane as [`Mpi::render`] samples it: the colour premultiplied by the alpha (so
/// bilinear sampling does not bleed the colour of transparent texels), and a border of
/// one texel that repeats the edge, so a sample never clamps: texel `(x, y)` of the
/// plane is `data[(y + 1) * stride + x + 1]`; and which blocks of it are empty, so that
/// sampling skips them (a baked plane is transparent over much of the image: on a
/// juicebox path, 45% of the samples were).
#[derive(Clone, Debug)]
struct Texture {
    width: usize,
    height: usize,
    stride: usize,
    data: Vec<[f32; 4]>,
    /// Per block of `data` (`1 << BLOCK_SHIFT` texels on a side; row-major, `blocks` per
    /// row): whether a bilinear sample whose top-left texel lies in the block can see a
    /// non-zero alpha (the block and the texel row and column after it).
    occupied: Vec<bool>,
    blocks: usize,
}

/// The side of [`Texture`]'s occupancy blocks, as a shift: 8 texels.
const BLOCK_SHIFT: usize = 3;

impl Texture {
    /// From straight RGBA `[H, W, 4]` in [0, 1].
    fn of(plane: &[f32], w: usize, h: usize) -> Self {
        let stride = w + 2;
        let texel = |x: usize, y: usize| {
            let t = &plane[(y * w + x) * 4..][..4];
            let [r, g, b, a] = [t[0], t[1], t[2], t[3]];
            [r * a, g * a, b * a, a]
        };
        let mut data = Vec::with_capacity(stride * (h + 2));
        for y in 0..h + 2 {
            let sy = y.saturating_sub(1).min(h - 1);
            data.extend((0..stride).map(|x| texel(x.saturating_sub(1).min(w - 1), sy)));
        }
        let (blocks, occupied) = occupancy(&data, stride, h + 2);
        Self {
            width: w,
            height: h,
            stride,
            data,
            occupied,
            blocks,
        }
    }

    /// The bilinear premultiplied RGBA at pixel coordinate `(u, v)` (centres at
    /// `i + 0.5`; edge pixels extend half a pixel); `None` outside the image, and where
    /// the four texels lie in an empty block ([`occupancy`]; the sample would be zero).
    #[inline]
    fn sample(&self, u: f64, v: f64) -> Option<[f32; 4]> {
        if !(u >= 0.0 && v >= 0.0 && u <= self.width as f64 && v <= self.height as f64) {
            return None;
        }
        // In the bordered texture the texel centres sit at i - 0.5: fx, fy >= 0.5, so
        // truncating is the floor, and texels xi..=xi + 1, yi..=yi + 1 all exist.
        let (fx, fy) = (u + 0.5, v + 0.5);
        let (xi, yi) = (fx as usize, fy as usize);
        if !self.occupied[(yi >> BLOCK_SHIFT) * self.blocks + (xi >> BLOCK_SHIFT)] {
            return None;
        }
        let (ax, ay) = ((fx - xi as f64) as f32, (fy - yi as f64) as f32);
        let i = yi * self.stride + xi;
        let q = &self.data[i..i + self.stride + 2];
        let (bx, by) = (1.0 - ax, 1.0 - ay);
        let (wa, wb, wc, wd) = (bx * by, ax * by, bx * ay, ax * ay);
        let (pa, pb, pc, pd) = (q[0], q[1], q[self.stride], q[self.stride + 1]);
        let mut out = [0f32; 4];
        for (c, o) in out.iter_mut().enumerate() {
            *o = pa[c] * wa + pb[c] * wb + pc[c] * wc + pd[c] * wd;
        }
        Some(out)
    }
}

/// Blocks per row and, per block of `1 << BLOCK_SHIFT` texels on a side (row-major), whether
/// a texel of the block or of the row and column after it has a non-zero alpha: a
/// bilinear footprint whose top-left texel lies in a block that is not occupied samples
/// only zeros (premultiplied, so colour too).
fn occupancy(data: &[[f32; 4]], stride: usize, rows: usize) -> (usize, Vec<bool>) {
    let side = 1 << BLOCK_SHIFT;
    let (bw, bh) = (stride.div_ceil(side), rows.div_ceil(side));
    let mut occupied = vec![false; bw * bh];
    for (i, _) in data.iter().enumerate().filter(|(_, t)| t[3] > 0.0) {
        let (x, y) = (i % stride, i / stride);
        // Blocks whose footprints reach texel (x, y): its own, and the one before it in
        // x and y when the texel opens its block's row or column.
        for by in (y.saturating_sub(1) >> BLOCK_SHIFT)..=(y >> BLOCK_SHIFT) {
            for bx in (x.saturating_sub(1) >> BLOCK_SHIFT)..=(x >> BLOCK_SHIFT) {
                occupied[by * bw + bx] = true;
            }
        }
    }
    (bw, occupied)
}

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
    let (w, h) = (
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
    );
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
    let camera = reference_camera(camera);
    let (colours, selection) = layers(backend, &camera, sources, inv_depths, tile, progress)?;
    Mpi::from_layers(camera, inv_depths.to_vec(), &colours, &selection)
}

/// The tiles of a `width` x `height` view at side `tile` (rounded up to the model's
/// alignment, as [`layers`] runs them), row-major: tile `i` covers the pixels
/// `[x0, x0 + side) x [y0, y0 + side)` clipped to the view, `x0 = (i % across) side`,
/// `y0 = (i / across) side`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    pub side: usize,
    pub across: usize,
    pub down: usize,
    pub width: usize,
    pub height: usize,
}

impl TileGrid {
    pub fn new(cfg: &crate::config::Config, (width, height): (usize, usize), tile: usize) -> Self {
        let side = cfg.tile_side(tile, (width, height));
        Self {
            side,
            across: width.div_ceil(side),
            down: height.div_ceil(side),
            width,
            height,
        }
    }

    pub fn len(&self) -> usize {
        self.across * self.down
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Tile `i`'s first pixel `(x0, y0)`.
    pub fn origin(&self, i: usize) -> (usize, usize) {
        ((i % self.across) * self.side, (i / self.across) * self.side)
    }

    /// The view's pixels (`y * width + x`) tile `i` covers, ascending.
    pub fn pixels(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        let (x0, y0) = self.origin(i);
        let (x1, y1) = (
            (x0 + self.side).min(self.width),
            (y0 + self.side).min(self.height),
        );
        (y0..y1).flat_map(move |y| (x0..x1).map(move |x| y * self.width + x))
    }
}

/// The network's layers at `camera` (a pinhole: [`reference_camera`]) from `sources` at
/// `inv_depths`, tile by tile as [`bake`] runs them: colours `[D, 3, H, W]` and the
/// selection `[D, H, W]`, row-major (finite, or an error), the selection reweighed by
/// the backend's scene prior when it has one.
pub fn layers(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    tile: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<(Vec<f32>, Vec<f32>)> {
    let (w, h) = (
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
    );
    let grid = TileGrid::new(backend.config(), (w, h), tile);
    let all: Vec<usize> = (0..grid.len()).collect();
    layers_of_tiles(backend, camera, sources, inv_depths, (grid, &all), progress)
}

/// [`layers`] on the tiles `tiles` of `grid` only (a grid of `camera`'s size): the
/// network runs on those tiles alone, and the values of every other pixel are 0.
/// Each tile's values are those [`layers`] gives it (tiles are run independently).
pub fn layers_of_tiles(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    (grid, tiles): (TileGrid, &[usize]),
    progress: &dyn Fn(usize, usize),
) -> Result<(Vec<f32>, Vec<f32>)> {
    let cfg = backend.config();
    let (w, h) = (
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
    );
    if (grid.width, grid.height) != (w, h) || grid != TileGrid::new(cfg, (w, h), grid.side) {
        return Err(Error::Invalid(format!(
            "a tile grid of {}x{} pixels (side {}) for a {w}x{h} camera",
            grid.width, grid.height, grid.side
        )));
    }
    if let Some(&i) = tiles.iter().find(|&&i| i >= grid.len()) {
        return Err(Error::Invalid(format!("tile {i} of {}", grid.len())));
    }
    let d = inv_depths.len();
    if d == 0 {
        return Err(Error::Invalid("at least one depth plane is needed".into()));
    }
    let (n, tile) = (w * h, grid.side);
    let what = |c: usize| format!("MPI layers of {d} planes x {c} x {w}x{h}");
    let mut colours = crate::sweep::try_zeroed(&[d, 3, n], &what(3))?;
    let mut selection = crate::sweep::try_zeroed(&[d, n], &what(1))?;
    for (done, &i) in tiles.iter().enumerate() {
        let (x0, y0) = grid.origin(i);
        let (c, s) = tile_layers(backend, camera, sources, inv_depths, (x0, y0), tile)?;
        let tt = tile * tile;
        for p in grid.pixels(i) {
            let q = (p / w - y0) * tile + (p % w - x0);
            for z in 0..d {
                selection[z * n + p] = s[z * tt + q];
                for ch in 0..3 {
                    colours[(z * 3 + ch) * n + p] = c[(z * 3 + ch) * tt + q];
                }
            }
        }
        progress(done + 1, tiles.len());
    }
    Ok((colours, selection))
}

/// The network's colours `[D, 3, tile, tile]` and selection `[D, tile, tile]` on the
/// square of side `tile` at `(x0, y0)` of `camera` (the selection reweighed by the
/// backend's scene prior when it has one); an error when any value is not finite.
pub(crate) fn tile_layers(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    (x0, y0): (usize, usize),
    tile: usize,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let inputs = tile_inputs(
        backend.config(),
        camera,
        sources,
        inv_depths,
        (x0 as i64, y0 as i64),
        (tile, tile),
    )?;
    let (c, mut s) = backend.run_layers(&inputs, inv_depths.len())?;
    if let Some(prior) = backend.prior() {
        prior.apply_tile(camera, inv_depths, (x0, y0), tile, &c, &mut s);
    }
    if c.iter().chain(&s).any(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!(
            "the network produced non-finite values in the tile at ({x0}, {y0})"
        )));
    }
    Ok((c, s))
}

#[cfg(test)]
mod tests;
