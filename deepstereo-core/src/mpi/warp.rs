//! An MPI tile seen from another camera as differentiable tensor ops: the loss through
//! the MPI renderer that trains a network for MPIs (stereo magnification's), beside the
//! CPU renderer [`super::Mpi::render`], which it equals.
//!
//! The network's layers of a reference tile, selection `s_z` and colour `c_z` per plane
//! (near to far), become straight-alpha planes `a_z = s_z / sum_{k >= z} s_k` with colour
//! `clamp(c_z, 0, 1)` as [`super::Mpi::from_layers`] makes them. Each target pixel's ray
//! meets plane `z` at a reference pixel ([`super::plane_maps`], f64); its premultiplied
//! RGBA is sampled bilinearly there (texel centres at `i + 0.5`), and the planes are
//! composited front to back, `C += T a c`, `T *= 1 - a`. A target pixel counts only when
//! on every plane its four texels lie inside the tile and the point lies ahead of the
//! camera ([`WarpPlan::mask`]).

use super::plane_maps;
use crate::camera::Camera;
use candle_core::{DType, Result, Tensor};
use glam::{DVec2, DVec3};

/// Where each target pixel samples each plane of a reference tile: built on the CPU in
/// f64 by [`WarpPlan::new`], applied by [`render_warped`].
#[derive(Clone, Debug, PartialEq)]
pub struct WarpPlan {
    /// Planes `D`.
    pub planes: usize,
    /// Target pixels `N_t` (row-major in the target crop).
    pub pixels: usize,
    /// `[D, 4, N_t]`: the four texels (top-left, top-right, bottom-left, bottom-right) as
    /// indices into the reference tile's `th * tw` pixels (row-major); 0 where masked.
    pub index: Vec<u32>,
    /// `[D, 4, N_t]`: their bilinear weights; 0 where masked.
    pub weight: Vec<f32>,
    /// `[N_t]`: 1 where the pixel sees the tile on every plane, else 0.
    pub mask: Vec<f32>,
}

impl WarpPlan {
    /// The plan of the target crop `(x0, y0, w, h)` (pixels of `camera`) against the tile
    /// `(rx0, ry0, tw, th)` of `reference` (a pinhole; its planes at `inv_depths`, near
    /// to far, 0 for a plane at infinity).
    pub fn new(
        reference: &Camera,
        inv_depths: &[f64],
        (rx0, ry0, tw, th): (i64, i64, usize, usize),
        camera: &Camera,
        (x0, y0, w, h): (i64, i64, usize, usize),
    ) -> Self {
        let rel = camera.pose.relative_to(&reference.pose);
        let maps = plane_maps(&reference.intrinsics, inv_depths, rel.translation);
        let (d, n) = (inv_depths.len(), w * h);
        let mut plan = Self {
            planes: d,
            pixels: n,
            index: vec![0; d * 4 * n],
            weight: vec![0.0; d * 4 * n],
            mask: vec![1.0; n],
        };
        for p in 0..n {
            let uv = DVec2::new(
                (x0 + (p % w) as i64) as f64 + 0.5,
                (y0 + (p / w) as i64) as f64 + 0.5,
            );
            let nrm = camera.intrinsics.unproject_pixel(uv);
            let r = rel.rotation * DVec3::new(nrm.x, nrm.y, 1.0);
            let taps: Option<Vec<_>> = (maps.iter())
                .map(|m| {
                    let ahead = m[0] * r.z > 0.0;
                    let (u, v) = (m[1] * r.x / r.z + m[2], m[3] * r.y / r.z + m[4]);
                    ahead.then(|| taps((u - rx0 as f64, v - ry0 as f64), (tw, th)))?
                })
                .collect();
            match taps {
                Some(taps) => {
                    for (z, (idx, wgt)) in taps.into_iter().enumerate() {
                        for k in 0..4 {
                            plan.index[(z * 4 + k) * n + p] = idx[k];
                            plan.weight[(z * 4 + k) * n + p] = wgt[k];
                        }
                    }
                }
                None => plan.mask[p] = 0.0,
            }
        }
        plan
    }

    /// Target pixels that count.
    pub fn count(&self) -> usize {
        self.mask.iter().filter(|&&m| m > 0.0).count()
    }
}

/// The four bilinear texels of tile coordinate `(u, v)` (texel centres at `i + 0.5`) and
/// their weights, or `None` when one lies outside the `tw x th` tile.
fn taps((u, v): (f64, f64), (tw, th): (usize, usize)) -> Option<([u32; 4], [f32; 4])> {
    let (fx, fy) = (u - 0.5, v - 0.5);
    let (xi, yi) = (fx.floor(), fy.floor());
    if !(xi >= 0.0 && yi >= 0.0 && xi + 1.0 < tw as f64 && yi + 1.0 < th as f64) {
        return None;
    }
    let (ax, ay) = (fx - xi, fy - yi);
    let i = yi as usize * tw + xi as usize;
    let idx = [i, i + 1, i + tw, i + tw + 1].map(|k| k as u32);
    let wgt = [
        (1.0 - ax) * (1.0 - ay),
        ax * (1.0 - ay),
        (1.0 - ax) * ay,
        ax * ay,
    ];
    Some((idx, wgt.map(|x| x as f32)))
}

/// The per-sample plans of a batch as tensors on `device`: the flat texel index
/// `[B*D*4*N_t]` (u32, into `[B*D*N_r]` with `N_r` the tile's pixels), the weights
/// `[B, D, 4, N_t]` and the mask `[B, N_t]` (in `dtype`). Every plan must share `D` and
/// `N_t`.
pub fn plan_tensors(
    plans: &[&WarpPlan],
    tile_pixels: usize,
    dtype: DType,
    device: &candle_core::Device,
) -> Result<(Tensor, Tensor, Tensor)> {
    let Some(first) = plans.first() else {
        candle_core::bail!("no warp plans");
    };
    let (d, n) = (first.planes, first.pixels);
    if plans.iter().any(|p| p.planes != d || p.pixels != n) {
        candle_core::bail!("warp plans of one batch must share their planes and pixels");
    }
    let b = plans.len();
    let mut index = Vec::with_capacity(b * d * 4 * n);
    for (s, plan) in plans.iter().enumerate() {
        for z in 0..d {
            let base = ((s * d + z) * tile_pixels) as u32;
            let row = &plan.index[z * 4 * n..(z + 1) * 4 * n];
            index.extend(row.iter().map(|&i| base + i));
        }
    }
    let weight: Vec<f32> = plans
        .iter()
        .flat_map(|p| p.weight.iter().copied())
        .collect();
    let mask: Vec<f32> = plans.iter().flat_map(|p| p.mask.iter().copied()).collect();
    Ok((
        Tensor::from_vec(index, b * d * 4 * n, device)?,
        Tensor::from_vec(weight, (b, d, 4, n), device)?.to_dtype(dtype)?,
        Tensor::from_vec(mask, (b, n), device)?.to_dtype(dtype)?,
    ))
}

/// The MPI of the network's layers, `selection` `[B, D, N_r]` and `colours`
/// `[B, D, 3, N_r]` of a reference tile, rendered at the target pixels of
/// [`plan_tensors`]' `index` `[B*D*4*N_t]` and `weight` `[B, D, 4, N_t]`: `[B, 3, N_t]`,
/// composited over black. Differentiable in both layers.
pub fn render_warped(
    selection: &Tensor,
    colours: &Tensor,
    index: &Tensor,
    weight: &Tensor,
) -> Result<Tensor> {
    let (b, d, n_r) = selection.dims3()?;
    let n_t = weight.dim(3)?;
    // behind_z = sum_{k >= z} s_k: an upper-triangular matrix of ones times s.
    let upper: Vec<f32> = (0..d * d)
        .map(|i| f32::from(u8::from(i % d >= i / d)))
        .collect();
    let upper = Tensor::from_vec(upper, (d, d), selection.device())?.to_dtype(selection.dtype())?;
    let behind = upper.broadcast_matmul(selection)?; // [B, D, N_r]
    let alpha = selection
        .div(&behind.clamp(1e-12, f64::MAX)?)?
        .unsqueeze(2)?; // [B, D, 1, N_r]
    let premult = colours.clamp(0.0, 1.0)?.broadcast_mul(&alpha)?; // [B, D, 3, N_r]
    let rgba = Tensor::cat(&[&premult, &alpha], 2)? // [B, D, 4, N_r]
        .transpose(2, 3)?
        .contiguous()?
        .reshape((b * d * n_r, 4))?; // [B*D*N_r, 4]
    let warped = rgba
        .index_select(index, 0)? // [B*D*4*N_t, 4]
        .reshape((b, d, 4, n_t, 4))?
        .broadcast_mul(&weight.unsqueeze(4)?)?
        .sum(2)?; // [B, D, N_t, 4]
    let mut colour = Tensor::zeros((b, n_t, 3), selection.dtype(), selection.device())?;
    let mut trans = Tensor::ones((b, n_t, 1), selection.dtype(), selection.device())?;
    for z in 0..d {
        let p = warped.narrow(1, z, 1)?.squeeze(1)?; // [B, N_t, 4]
        colour = (colour + p.narrow(2, 0, 3)?.broadcast_mul(&trans)?)?;
        trans = (&trans * (1.0 - p.narrow(2, 3, 1)?)?)?;
    }
    colour.transpose(1, 2) // [B, 3, N_t]
}

/// Mean absolute error of `pred` `[B, 3, N_t]` against `target` `[B, 3, N_t]` over the
/// pixels of `mask` `[B, N_t]` (0 when none counts).
pub fn masked_l1(pred: &Tensor, target: &Tensor, mask: &Tensor) -> Result<Tensor> {
    let m = mask.unsqueeze(1)?; // [B, 1, N_t]
    let sum = pred.sub(target)?.abs()?.broadcast_mul(&m)?.sum_all()?;
    let count = (m.sum_all()? * 3.0)?.clamp(1.0, f64::MAX)?;
    sum.div(&count)
}

#[cfg(test)]
mod tests;
