//! A per-scene selection prior: a world-space grid of log-weights `b` that reweighs the
//! network's selection outside the network,
//!
//! `s'_z = s_z^g exp(b(x_z)) / sum_k s_k^g exp(b(x_k))`,
//!
//! where `x_z` is the world point of the pixel's ray on plane `z`, `b(x)` is the
//! grid's trilinear interpolation (points outside the grid take its nearest face's
//! values) and `g` the scene's sharpness, one exponent for the whole scene (above 1 the
//! selection is sharper than the network's, below 1 flatter). A grid of zeros with `g =
//! 1` changes nothing, so a prior fitted from there starts at the network's own render. Because `b` lives in the world, not in any camera, what one
//! view teaches about where surfaces are holds in every other view: it is the scene's
//! own depth evidence, learned by leaving one view out (`deepstereo tune`).
//!
//! The rendered colour is `C = sum_z s'_z c_z`, a softmax of the logits `l_z = g ln s_z +
//! b_z`; its derivatives are `dC/db_z = s'_z (c_z - C)` (the softmax's Jacobian) and
//! `dC/dg = sum_z s'_z (c_z - C) ln s_z`, which [`PriorGrid::ray_gradient`] uses. Geometry is f64; the grid and the layers are f32.

use crate::camera::Camera;
use crate::error::{Error, Result};
use glam::{DVec2, DVec3};
use rayon::prelude::*;

pub mod graph;
pub mod io;

/// The largest log-weight a cell may hold: `exp(12)` against `exp(-12)` is a ratio of
/// 2.6e10, past what f32 selections resolve, so nothing is lost by the bound and
/// `exp` never overflows.
pub const MAX_LOG_WEIGHT: f32 = 12.0;

/// The range a scene's sharpness `g` is held in: from a quarter of the network's
/// logit scale to eight times it (a selection of 0.5 against 0.25 becomes 256 to 1).
pub const SHARPNESS_RANGE: (f32, f32) = (0.25, 8.0);

/// An axis-aligned grid of log-weights over a box of the world.
#[derive(Clone, Debug, PartialEq)]
pub struct PriorGrid {
    /// The corner of the box with the smallest coordinates (the first cell's centre).
    pub origin: DVec3,
    /// The side of a cell (cells are cubes; cell centres are `origin + i * cell`).
    pub cell: f64,
    /// Cells along x, y, z (each at least 2).
    pub dims: [usize; 3],
    /// `dims[0] * dims[1] * dims[2]` log-weights, x fastest.
    pub values: Vec<f32>,
    /// The exponent `g` of the network's selection (1: as the network has it), within
    /// [`SHARPNESS_RANGE`].
    pub sharpness: f32,
}

/// Where a point falls in the grid: its cell's first corner and its fractions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cell {
    /// Index of the cell's corner with the smallest coordinates.
    pub base: u32,
    /// Position within the cell along x, y, z, each in [0, 1].
    pub frac: [f32; 3],
}

impl PriorGrid {
    /// A grid of zeros over the box `lo`..`hi` with `cells` cells along its longest side.
    pub fn zeros(lo: DVec3, hi: DVec3, cells: usize) -> Result<Self> {
        let size = hi - lo;
        if !(lo.is_finite() && hi.is_finite()) || size.min_element() < 0.0 || cells < 2 {
            return Err(Error::Invalid(format!(
                "a prior grid needs a finite box and at least 2 cells (box {lo} to {hi}, {cells} cells)"
            )));
        }
        let longest = size.max_element();
        let cell = if longest > 0.0 {
            longest / (cells - 1) as f64
        } else {
            1.0
        };
        let dim = |s: f64| ((s / cell).ceil() as usize + 1).clamp(2, cells);
        let dims = [dim(size.x), dim(size.y), dim(size.z)];
        Ok(Self {
            origin: lo,
            cell,
            dims,
            values: vec![0.0; dims[0] * dims[1] * dims[2]],
            sharpness: 1.0,
        })
    }

    /// Where `p` falls (clamped into the box).
    pub fn locate(&self, p: DVec3) -> Cell {
        let q = (p - self.origin) / self.cell;
        let mut base = [0usize; 3];
        let mut frac = [0f32; 3];
        for a in 0..3 {
            let top = (self.dims[a] - 1) as f64;
            let v = if q[a].is_finite() {
                q[a].clamp(0.0, top)
            } else if q[a] > 0.0 {
                top
            } else {
                0.0
            };
            let i = (v.floor() as usize).min(self.dims[a] - 2);
            base[a] = i;
            frac[a] = (v - i as f64) as f32;
        }
        Cell {
            base: (base[0] + self.dims[0] * (base[1] + self.dims[1] * base[2])) as u32,
            frac,
        }
    }

    /// The 8 corner indices of a cell and their trilinear weights.
    pub fn corners(&self, c: Cell) -> [(usize, f32); 8] {
        let (sx, sy) = (1, self.dims[0]);
        let sz = self.dims[0] * self.dims[1];
        let [fx, fy, fz] = c.frac;
        let b = c.base as usize;
        let mut out = [(0usize, 0f32); 8];
        for (k, o) in out.iter_mut().enumerate() {
            let (ix, iy, iz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
            let w = [1.0 - fx, fx][ix] * [1.0 - fy, fy][iy] * [1.0 - fz, fz][iz];
            *o = (b + ix * sx + iy * sy + iz * sz, w);
        }
        out
    }

    /// `b` at a located point.
    pub fn value(&self, c: Cell) -> f32 {
        self.corners(c)
            .iter()
            .map(|&(i, w)| w * self.values[i])
            .sum()
    }

    /// Locates the world points of the rays of `camera` through the pixels `pixels`
    /// (`(x, y)`, centres at `+ 0.5`; pixels past the image are fine) on the planes
    /// `inv_depths` (camera z, near to far; 0 is a plane at infinity, located as a point
    /// far along the ray): `[pixels, D]`, pixel-major.
    pub fn locate_rays(
        &self,
        camera: &Camera,
        inv_depths: &[f64],
        pixels: &[(usize, usize)],
    ) -> Vec<Cell> {
        let d = inv_depths.len();
        let mut out = vec![
            Cell {
                base: 0,
                frac: [0.0; 3]
            };
            pixels.len() * d
        ];
        out.par_chunks_mut(d.max(1))
            .zip(pixels.par_iter())
            .for_each(|(row, &(x, y))| {
                let uv = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                let centre = camera.pose_at_pixel(uv).centre();
                let unit = camera.unproject(uv, 1.0) - centre;
                let far = self.far_distance(centre);
                for (z, cell) in row.iter_mut().enumerate() {
                    let rho = inv_depths[z];
                    let x = if rho > 0.0 {
                        centre + unit / rho
                    } else {
                        centre + unit.normalize_or_zero() * far
                    };
                    *cell = self.locate(x);
                }
            });
        out
    }

    /// [`Self::locate_rays`] of every pixel of the `th` x `tw` tile at `(x0, y0)`, row by
    /// row: `[th * tw, D]`.
    pub fn locate_tile(
        &self,
        camera: &Camera,
        inv_depths: &[f64],
        (x0, y0): (usize, usize),
        (th, tw): (usize, usize),
    ) -> Vec<Cell> {
        let pixels: Vec<(usize, usize)> =
            (0..th * tw).map(|q| (x0 + q % tw, y0 + q / tw)).collect();
        self.locate_rays(camera, inv_depths, &pixels)
    }

    /// Reweighs the selection `[D, th, tw]` (row-major, as a backend returns it) of the
    /// `th` x `tw` tile at `(x0, y0)` of `camera` on the planes `inv_depths`, in place.
    pub fn reweigh_tile(
        &self,
        camera: &Camera,
        inv_depths: &[f64],
        (x0, y0): (usize, usize),
        (th, tw): (usize, usize),
        selection: &mut [f32],
    ) {
        let (d, n) = (inv_depths.len(), th * tw);
        let cells = self.locate_tile(camera, inv_depths, (x0, y0), (th, tw));
        let columns: Vec<Vec<f32>> = (0..n)
            .into_par_iter()
            .map(|q| {
                let mut s: Vec<f32> = (0..d).map(|z| selection[z * n + q]).collect();
                self.reweigh(&mut s, &cells[q * d..(q + 1) * d]);
                s
            })
            .collect();
        for (q, s) in columns.into_iter().enumerate() {
            for (z, v) in s.into_iter().enumerate() {
                selection[z * n + q] = v;
            }
        }
    }

    /// Applies the prior to a tile's layers: `colours` `[D, 3, t, t]` and `selection`
    /// `[D, t, t]` (row-major, as a backend returns them) of the `t` x `t` tile at `(x0,
    /// y0)` of `camera` on the planes `inv_depths`. The selection is reweighed in place
    /// ([`Self::reweigh_tile`]); returns the colour `sum_z s'_z c_z`, `[3, t, t]`.
    pub fn apply_tile(
        &self,
        camera: &Camera,
        inv_depths: &[f64],
        (x0, y0): (usize, usize),
        tile: usize,
        colours: &[f32],
        selection: &mut [f32],
    ) -> Vec<f32> {
        self.reweigh_tile(camera, inv_depths, (x0, y0), (tile, tile), selection);
        let tt = tile * tile;
        let mut image = vec![0f32; 3 * tt];
        for (z, s) in selection.chunks_exact(tt).enumerate() {
            for (ch, out) in image.chunks_exact_mut(tt).enumerate() {
                let c = &colours[(z * 3 + ch) * tt..(z * 3 + ch + 1) * tt];
                for ((o, w), v) in out.iter_mut().zip(s).zip(c) {
                    *o += w * v;
                }
            }
        }
        image
    }

    /// A distance from `from` past the whole box.
    fn far_distance(&self, from: DVec3) -> f64 {
        let hi = self.origin
            + DVec3::new(
                (self.dims[0] - 1) as f64,
                (self.dims[1] - 1) as f64,
                (self.dims[2] - 1) as f64,
            ) * self.cell;
        2.0 * ((from - self.origin).length() + (hi - self.origin).length() + 1.0)
    }

    /// Reweighs one pixel's selection `s` (near to far) in place with the log-weights at
    /// its located plane points `cells`; a pixel whose selection is all zero stays zero.
    pub fn reweigh(&self, s: &mut [f32], cells: &[Cell]) {
        let b: Vec<f32> = cells.iter().map(|&c| self.value(c)).collect();
        reweigh_with(s, &b, self.sharpness);
    }

    /// One ray rendered with the prior: its reweighed selection `s'` and colour
    /// `sum_z s'_z c_z` (not clamped), from its selection `s`, colours `c` (`[D][3]`) and
    /// located plane points `cells`.
    pub fn render_ray(&self, s: &[f32], c: &[[f32; 3]], cells: &[Cell]) -> (Vec<f32>, [f32; 3]) {
        let mut sp = s.to_vec();
        self.reweigh(&mut sp, cells);
        let mut colour = [0f32; 3];
        for (w, cz) in sp.iter().zip(c) {
            for k in 0..3 {
                colour[k] += w * cz[k];
            }
        }
        (sp, colour)
    }

    /// One ray's L1 loss gradient by the log-weights of its plane points and by the
    /// sharpness: the rendered colour `C = sum_z s'_z c_z` of selection `s` and colours
    /// `c` (`[D][3]`) against `truth`, `e = sign(C - truth)`, `dL/db_z = s'_z (c_z - C) .
    /// e`, scattered onto the cells' corners with their trilinear weights (times `scale`)
    /// into `grad`, and `dL/dg = sum_z dL/db_z ln s_z` (times `scale`) added to
    /// `grad_sharpness`. Returns the ray's L1 error (summed over channels).
    #[allow(clippy::too_many_arguments)]
    pub fn ray_gradient(
        &self,
        s: &[f32],
        c: &[[f32; 3]],
        cells: &[Cell],
        truth: [f32; 3],
        scale: f32,
        grad: &mut [f32],
        grad_sharpness: &mut f32,
    ) -> f32 {
        let (sp, colour) = self.render_ray(s, c, cells);
        let e: [f32; 3] = std::array::from_fn(|k| (colour[k] - truth[k]).signum());
        for z in 0..sp.len() {
            let dz: f32 = (0..3).map(|k| (c[z][k] - colour[k]) * e[k]).sum::<f32>() * sp[z];
            if dz != 0.0 {
                for (i, w) in self.corners(cells[z]) {
                    grad[i] += scale * w * dz;
                }
                if s[z] > 0.0 {
                    *grad_sharpness += scale * dz * s[z].ln();
                }
            }
        }
        (0..3).map(|k| (colour[k] - truth[k]).abs()).sum()
    }
}

/// `s_z^g exp(b_z) / sum_k s_k^g exp(b_k)` in place, `g` the sharpness (`b` bounded by
/// [`MAX_LOG_WEIGHT`]; the logits `g ln s_z + b_z` shifted by their largest first, so
/// `exp` stays in range). Planes with `s_z = 0` stay 0.
pub fn reweigh_with(s: &mut [f32], b: &[f32], sharpness: f32) {
    let clamp = |x: f32| x.clamp(-MAX_LOG_WEIGHT, MAX_LOG_WEIGHT);
    if sharpness == 1.0 {
        // s_z exp(b_z - top): exact for the network's own sharpness.
        normalise_by(
            s,
            b,
            |v, x| (v > 0.0).then(|| clamp(x)),
            |v, x, top| v.max(0.0) * (clamp(x) - top).exp(),
        );
    } else {
        let logit = |v: f32, x: f32| (v > 0.0).then(|| sharpness * v.ln() + clamp(x));
        normalise_by(s, b, logit, |v, x, top| {
            logit(v, x).map_or(0.0, |l| (l - top).exp())
        });
    }
}

/// `s_z <- weight(s_z, b_z, top) / sum_k weight(s_k, b_k, top)`, `top` the largest
/// `key(s_z, b_z)` (planes without a key are not counted); unchanged when no plane has
/// a key, all zero when every weight is.
fn normalise_by(
    s: &mut [f32],
    b: &[f32],
    key: impl Fn(f32, f32) -> Option<f32>,
    weight: impl Fn(f32, f32, f32) -> f32,
) {
    let top = (s.iter().zip(b))
        .filter_map(|(&v, &x)| key(v, x))
        .fold(f32::NEG_INFINITY, f32::max);
    if !top.is_finite() {
        return;
    }
    let mut sum = 0f32;
    for (v, &x) in s.iter_mut().zip(b) {
        *v = weight(*v, x, top);
        sum += *v;
    }
    if sum > 0.0 {
        s.iter_mut().for_each(|v| *v /= sum);
    }
}

#[cfg(test)]
mod tests;
