//! [`pad_rows`]: the depth convolutions' zero padding.

use super::{on_cpu, plane_grad, PlaneBackward};
use candle_core::{bail, CpuStorage, CustomOp1, Layout, Result, Shape, Tensor, WithDType};
use rayon::prelude::*;

/// `x` `[N, C, H, W]` (any strides) with `p` zero rows above and below and `extra` zero
/// columns on the right: `[N, C, H + 2p, W + extra]`, contiguous.
pub fn pad_rows(x: &Tensor, p: usize, extra: usize) -> Result<Tensor> {
    x.dims4()?;
    if !on_cpu(&[x]) {
        return x.pad_with_zeros(2, p, p)?.pad_with_zeros(3, 0, extra);
    }
    let x = if x.stride()[3] == 1 {
        x.clone()
    } else {
        x.contiguous()?
    };
    x.apply_op1(PadRows { p, extra })
}

struct PadRows {
    p: usize,
    extra: usize,
}

impl PadRows {
    fn fwd<T: WithDType>(&self, x: &[T], l: &Layout) -> Result<Vec<T>> {
        let (n, c, h, w) = l.shape().dims4()?;
        let st = l.stride();
        let (o, hp, wp) = (l.start_offset(), h + 2 * self.p, w + self.extra);
        let len = n * c * hp * wp;
        // Each plane is written whole below (zero rows, data rows with their zero tails),
        // in parallel: no serial zero fill of the buffer first.
        let mut y = Vec::<T>::with_capacity(len);
        y.spare_capacity_mut()[..len]
            .par_chunks_mut(hp * wp)
            .enumerate()
            .for_each(|(i, plane)| {
                let base = o + i / c * st[0] + i % c * st[1];
                for (r, row) in plane.chunks_exact_mut(wp).enumerate() {
                    let data = (self.p..self.p + h).contains(&r);
                    let (head, tail) = row.split_at_mut(if data { w } else { 0 });
                    if data {
                        let src = &x[base + (r - self.p) * st[2]..][..w];
                        for (d, &v) in head.iter_mut().zip(src) {
                            d.write(v);
                        }
                    }
                    for d in tail {
                        d.write(T::zero());
                    }
                }
            });
        // SAFETY: every plane's rows were written whole above, so all `len` values are
        // initialised.
        unsafe { y.set_len(len) };
        Ok(y)
    }
}

impl PlaneBackward for PadRows {
    fn dx<T: WithDType>(&self, dy: &[T], (n, c, h, w): (usize, usize, usize, usize)) -> Vec<T> {
        let (hp, wp) = (h + 2 * self.p, w + self.extra);
        let mut dx = vec![T::zero(); n * c * h * w];
        dx.par_chunks_mut(h * w)
            .zip(dy.par_chunks(hp * wp))
            .for_each(|(d, g)| {
                for (r, row) in d.chunks_exact_mut(w).enumerate() {
                    row.copy_from_slice(&g[(r + self.p) * wp..][..w]);
                }
            });
        dx
    }
}

impl CustomOp1 for PadRows {
    fn name(&self) -> &'static str {
        "deepstereo-pad-rows"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, c, h, w) = l.shape().dims4()?;
        let shape = Shape::from((n, c, h + 2 * self.p, w + self.extra));
        let y = match s {
            CpuStorage::F32(v) => CpuStorage::F32(self.fwd(v, l)?),
            CpuStorage::F64(v) => CpuStorage::F64(self.fwd(v, l)?),
            _ => bail!("pad_rows: f32 or f64 only"),
        };
        Ok((y, shape))
    }

    fn bwd(&self, x: &Tensor, _y: &Tensor, dy: &Tensor) -> Result<Option<Tensor>> {
        plane_grad(self, x, dy)
    }
}
