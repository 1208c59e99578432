//! [`upsample_nearest`]: exact nearest upsampling as a candle composition (the training
//! path's and the fallback's); [`upsample_crop`]: nearest upsampling by an integer factor
//! and a crop in one pass;
//! [`upsample_cat`]: several of them concatenated along channels, written straight into
//! the concatenated buffer (rendering: the towers' level merge without a `cat` copy).

use super::{data, on_cpu, plane_grad, slice, PlaneBackward};
use candle_core::{bail, CpuStorage, CustomOp1, DType, Layout, Result, Shape, Tensor, WithDType};
use rayon::prelude::*;

/// Exact nearest upsampling by an integer factor through reshape and broadcast (candle's
/// `upsample_nearest2d` backward overwrites accumulated gradients). `[N, C, H, W]` ->
/// `[N, C, sH, sW]`.
pub fn upsample_nearest(x: &Tensor, s: usize) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    x.reshape((n, c, h, 1, w, 1))? // [N, C, H, 1, W, 1]
        .broadcast_as((n, c, h, s, w, s))? // [N, C, H, s, W, s]
        .contiguous()?
        .reshape((n, c, h * s, w * s)) // [N, C, sH, sW]
}

/// `upsample_nearest(x, s)` cropped to rows `off .. off + h` and columns `off .. off + w`:
/// `[N, C, H, W]` -> `[N, C, h, w]`, `y[.., i, j] = x[.., (i + off) / s, (j + off) / s]`.
pub fn upsample_crop(x: &Tensor, s: usize, off: usize, h: usize, w: usize) -> Result<Tensor> {
    let (_, _, hi, wi) = x.dims4()?;
    if s == 0 || (off + h).div_ceil(s) > hi || (off + w).div_ceil(s) > wi {
        bail!("upsample_crop: {h}x{w} at {off} does not fit {hi}x{wi} upsampled by {s}");
    }
    if !on_cpu(&[x]) {
        return upsample_nearest(x, s)?.narrow(2, off, h)?.narrow(3, off, w);
    }
    x.contiguous()?.apply_op1(UpsampleCrop { s, off, h, w })
}

/// [`upsample_crop`] of each part `(x_l [N, C_l, H_l, W_l], s_l, off_l)`, concatenated
/// along channels: `[N, sum C_l, h, w]`, each output value written once (no separate
/// crops and no `cat` copy). No gradient flows through it (rendering); `None` off the CPU.
pub fn upsample_cat(
    parts: &[(&Tensor, usize, usize)],
    h: usize,
    w: usize,
) -> Result<Option<Tensor>> {
    let mut n = None;
    for &(x, s, off) in parts {
        let (ni, _, hi, wi) = x.dims4()?;
        if s == 0 || (off + h).div_ceil(s) > hi || (off + w).div_ceil(s) > wi {
            bail!("upsample_cat: {h}x{w} at {off} does not fit {hi}x{wi} upsampled by {s}");
        }
        if n.is_some_and(|n| n != ni) {
            bail!("upsample_cat: parts of different batch sizes");
        }
        n = Some(ni);
    }
    let xs: Vec<&Tensor> = parts.iter().map(|p| p.0).collect();
    let Some(n) = n.filter(|_| on_cpu(&xs)) else {
        return Ok(None);
    };
    let xs = xs
        .iter()
        .map(|x| x.contiguous())
        .collect::<Result<Vec<_>>>()?;
    fn run<T: WithDType>(
        xs: &[Tensor],
        parts: &[(&Tensor, usize, usize)],
        (n, h, w): (usize, usize, usize),
    ) -> Result<Tensor> {
        let guards: Vec<_> = xs.iter().map(|x| x.storage_and_layout()).collect();
        // Per part: its data, channels, source width and height, and the op on a plane.
        let mut src = Vec::with_capacity(parts.len());
        for ((st, l), &(x, s, off)) in guards.iter().zip(parts) {
            let (_, c, hi, wi) = x.dims4()?;
            src.push((
                data::<T>(st, l)?,
                c,
                hi * wi,
                wi,
                UpsampleCrop { s, off, h, w },
            ));
        }
        let ctot: usize = src.iter().map(|p| p.1).sum();
        let mut y = vec![T::zero(); n * ctot * h * w];
        y.par_chunks_mut(h * w).enumerate().for_each(|(q, dst)| {
            let (ni, mut ch) = (q / ctot, q % ctot);
            for &(x, c, plane, wi, op) in &src {
                if ch < c {
                    op.plane(&x[(ni * c + ch) * plane..][..plane], wi, dst);
                    return;
                }
                ch -= c;
            }
        });
        Tensor::from_vec(y, (n, ctot, h, w), xs[0].device()) // [N, sum C_l, h, w]
    }
    match xs[0].dtype() {
        DType::F32 => run::<f32>(&xs, parts, (n, h, w)).map(Some),
        DType::F64 => run::<f64>(&xs, parts, (n, h, w)).map(Some),
        _ => Ok(None),
    }
}

#[derive(Clone, Copy)]
struct UpsampleCrop {
    s: usize,
    off: usize,
    h: usize,
    w: usize,
}

impl UpsampleCrop {
    /// Forward on one plane: `src` `[hi, wi]` -> `dst` `[h, w]`. An output row whose
    /// source row is the previous one's is a copy of it; `s = 1` rows are slice copies.
    fn plane<T: Copy>(&self, src: &[T], wi: usize, dst: &mut [T]) {
        let (s, off, w) = (self.s, self.off, self.w);
        // `j / s` as a shift where `s` is a power of two (the towers' levels).
        let shift = s.is_power_of_two().then(|| s.trailing_zeros());
        let div = |j: usize| shift.map_or(j / s, |sh| j >> sh);
        for i in 0..self.h {
            let (done, rest) = dst.split_at_mut(i * w);
            let row = &mut rest[..w];
            if i > 0 && div(i + off) == div(i - 1 + off) {
                row.copy_from_slice(&done[(i - 1) * w..]);
                continue;
            }
            let sr = &src[div(i + off) * wi..];
            if s == 1 {
                row.copy_from_slice(&sr[off..][..w]);
            } else {
                for (j, v) in row.iter_mut().enumerate() {
                    *v = sr[div(j + off)];
                }
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
