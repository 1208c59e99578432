//! [`upsample_crop`]: nearest upsampling by an integer factor and a crop in one pass.

use super::{on_cpu, plane_grad, slice, PlaneBackward};
use candle_core::{bail, CpuStorage, CustomOp1, Layout, Result, Shape, Tensor, WithDType};
use rayon::prelude::*;

/// `upsample_nearest(x, s)` cropped to rows `off .. off + h` and columns `off .. off + w`:
/// `[N, C, H, W]` -> `[N, C, h, w]`, `y[.., i, j] = x[.., (i + off) / s, (j + off) / s]`.
pub fn upsample_crop(x: &Tensor, s: usize, off: usize, h: usize, w: usize) -> Result<Tensor> {
    let (_, _, hi, wi) = x.dims4()?;
    if s == 0 || (off + h).div_ceil(s) > hi || (off + w).div_ceil(s) > wi {
        bail!("upsample_crop: {h}x{w} at {off} does not fit {hi}x{wi} upsampled by {s}");
    }
    if !on_cpu(&[x]) {
        return crate::model::upsample_nearest(x, s)?
            .narrow(2, off, h)?
            .narrow(3, off, w);
    }
    x.contiguous()?.apply_op1(UpsampleCrop { s, off, h, w })
}

#[derive(Clone, Copy)]
struct UpsampleCrop {
    s: usize,
    off: usize,
    h: usize,
    w: usize,
}

impl UpsampleCrop {
    /// Forward on one plane: `src` `[hi, wi]` -> `dst` `[h, w]`.
    fn plane<T: Copy>(&self, src: &[T], wi: usize, dst: &mut [T]) {
        for (i, row) in dst.chunks_exact_mut(self.w).enumerate() {
            let sr = &src[(i + self.off) / self.s * wi..];
            for (j, v) in row.iter_mut().enumerate() {
                *v = sr[(j + self.off) / self.s];
            }
        }
    }

    /// Backward on one plane: adds `dy` `[h, w]` into `dx` `[hi, wi]` (zeroed).
    fn plane_grad<T: WithDType>(&self, dy: &[T], wi: usize, dx: &mut [T]) {
        for (i, row) in dy.chunks_exact(self.w).enumerate() {
            let dr = &mut dx[(i + self.off) / self.s * wi..];
            for (j, &g) in row.iter().enumerate() {
                dr[(j + self.off) / self.s] += g;
            }
        }
    }

    fn fwd<T: WithDType>(&self, x: &[T], (n, c, hi, wi): (usize, usize, usize, usize)) -> Vec<T> {
        let mut y = vec![T::zero(); n * c * self.h * self.w];
        y.par_chunks_mut(self.h * self.w)
            .zip(x.par_chunks(hi * wi))
            .for_each(|(dst, src)| self.plane(src, wi, dst));
        y
    }
}

impl PlaneBackward for UpsampleCrop {
    fn dx<T: WithDType>(&self, dy: &[T], dims: (usize, usize, usize, usize)) -> Vec<T> {
        let (n, c, hi, wi) = dims;
        let mut dx = vec![T::zero(); n * c * hi * wi];
        dx.par_chunks_mut(hi * wi)
            .zip(dy.par_chunks(self.h * self.w))
            .for_each(|(dst, src)| self.plane_grad(src, wi, dst));
        dx
    }
}

impl CustomOp1 for UpsampleCrop {
    fn name(&self) -> &'static str {
        "deepstereo-upsample-crop"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, c, hi, wi) = l.shape().dims4()?;
        let shape = Shape::from((n, c, self.h, self.w));
        let y = match s {
            CpuStorage::F32(_) => CpuStorage::F32(self.fwd(slice::<f32>(s, l)?, (n, c, hi, wi))),
            CpuStorage::F64(_) => CpuStorage::F64(self.fwd(slice::<f64>(s, l)?, (n, c, hi, wi))),
            _ => bail!("upsample_crop: f32 or f64 only"),
        };
        Ok((y, shape))
    }

    fn bwd(&self, x: &Tensor, _y: &Tensor, dy: &Tensor) -> Result<Option<Tensor>> {
        plane_grad(self, x, dy)
    }
}
