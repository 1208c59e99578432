//! Fused CPU ops for the glue between the network's convolutions, where candle's generic
//! ops would copy through strided index arithmetic or allocate one tensor per step.
//!
//! - [`upsample_crop`]: nearest upsampling by an integer factor and a crop, in one pass
//!   (the towers' coarse levels), with its backward (sums over each source pixel's block).
//!
//! Each op equals a composition of candle ops, which is also the fallback off the CPU or
//! for dtypes other than f32 / f64 (tests compare the two, values and gradients).

use candle_core::{bail, CpuStorage, CustomOp1, DType, Layout, Result, Shape, Tensor, WithDType};
use rayon::prelude::*;

/// `upsample_nearest(x, s)` cropped to rows `off .. off + h` and columns `off .. off + w`:
/// `[N, C, H, W]` -> `[N, C, h, w]`, `y[.., i, j] = x[.., (i + off) / s, (j + off) / s]`.
pub fn upsample_crop(x: &Tensor, s: usize, off: usize, h: usize, w: usize) -> Result<Tensor> {
    let (_, _, hi, wi) = x.dims4()?;
    if s == 0 || (off + h).div_ceil(s) > hi || (off + w).div_ceil(s) > wi {
        bail!("upsample_crop: {h}x{w} at {off} does not fit {hi}x{wi} upsampled by {s}");
    }
    let cpu = x.device().is_cpu() && matches!(x.dtype(), DType::F32 | DType::F64);
    if !cpu {
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

    fn bwd_typed<T: WithDType>(&self, dy: &[T], dims: (usize, usize, usize, usize)) -> Vec<T> {
        let (n, c, hi, wi) = dims;
        let mut dx = vec![T::zero(); n * c * hi * wi];
        dx.par_chunks_mut(hi * wi)
            .zip(dy.par_chunks(self.h * self.w))
            .for_each(|(dst, src)| self.plane_grad(src, wi, dst));
        dx
    }
}

/// The contiguous elements of a CPU storage under `l`.
fn slice<'a, T: WithDType>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&s.as_slice::<T>()?[a..b]),
        None => bail!("fused op: expected a contiguous tensor"),
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
        let dims = x.dims4()?;
        let dy = dy.contiguous()?;
        let (st, l) = dy.storage_and_layout();
        let candle_core::Storage::Cpu(cpu) = &*st else {
            bail!("upsample_crop: CPU gradient expected")
        };
        let dx = match x.dtype() {
            DType::F32 => Tensor::from_vec(
                self.bwd_typed(slice::<f32>(cpu, l)?, dims),
                x.shape(),
                x.device(),
            )?,
            DType::F64 => Tensor::from_vec(
                self.bwd_typed(slice::<f64>(cpu, l)?, dims),
                x.shape(),
                x.device(),
            )?,
            dt => bail!("upsample_crop: f32 or f64 only, got {dt:?}"),
        };
        Ok(Some(dx))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    #[test]
    fn upsample_crop_matches_composition() -> Result<()> {
        for (s, off, h, w, hi, wi) in [(2, 3, 10, 12, 8, 9), (4, 0, 8, 8, 2, 2), (2, 1, 5, 3, 3, 2)]
        {
            for dt in [DType::F32, DType::F64] {
                let x = Var::from_tensor(
                    &Tensor::randn(0f64, 1., (2, 3, hi, wi), &Device::Cpu)?.to_dtype(dt)?,
                )?;
                let r = Tensor::randn(0f64, 1., (2, 3, h, w), &Device::Cpu)?.to_dtype(dt)?;
                let want = crate::model::upsample_nearest(x.as_tensor(), s)?
                    .narrow(2, off, h)?
                    .narrow(3, off, w)?;
                let got = upsample_crop(x.as_tensor(), s, off, h, w)?;
                let diff = (&got - &want)?.abs()?.max_all()?.to_dtype(DType::F64)?;
                assert_eq!(diff.to_scalar::<f64>()?, 0.0);
                let gw = (want * &r)?.sum_all()?.backward()?;
                let gg = (got * &r)?.sum_all()?.backward()?;
                let (a, b) = (
                    gw.get(x.as_tensor()).unwrap(),
                    gg.get(x.as_tensor()).unwrap(),
                );
                let e = (a - b)?
                    .abs()?
                    .max_all()?
                    .to_dtype(DType::F64)?
                    .to_scalar::<f64>()?;
                assert!(e < 1e-5, "{s} {off} {dt:?}: {e}");
            }
        }
        assert!(upsample_crop(
            &Tensor::zeros((1, 1, 2, 2), DType::F32, &Device::Cpu)?,
            2,
            1,
            4,
            4
        )
        .is_err());
        Ok(())
    }
}
