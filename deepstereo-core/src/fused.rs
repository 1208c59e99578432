//! Fused CPU ops for the glue between the network's convolutions, where candle's generic
//! ops would copy through strided index arithmetic or allocate one tensor per step.
//!
//! - [`upsample_crop`]: nearest upsampling by an integer factor and a crop, in one pass
//!   (the towers' coarse levels), with its backward (sums over each source pixel's block);
//! - [`select_softmax`]: the selection tower's head, `softmax_D(tanh(x) exp(log_scale))`;
//! - [`composite`]: the rendered colour `sum_z s_z c_z`;
//! - [`pad_rows`]: zero rows above and below (the depth convolutions' padding) and
//!   optionally zero columns on the right, reading a transposed view directly (no
//!   separate transpose copy).
//!
//! Each op equals a composition of candle ops, which is also the fallback off the CPU or
//! for dtypes other than f32 / f64 (tests compare the two, values and gradients).

use crate::conv::SharedMut;
use candle_core::{
    bail, CpuStorage, CustomOp1, CustomOp2, DType, Layout, Result, Shape, Storage, Tensor,
    WithDType,
};
use num_traits::Float;
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
        plane_grad(
            x,
            dy,
            |g| self.bwd_typed(g, dims),
            |g| self.bwd_typed(g, dims),
        )
    }
}

/// `dx` of a one-input op from `dy`, computed on CPU slices by `f32` or `f64` (the same
/// generic function, once per type).
fn plane_grad(
    x: &Tensor,
    dy: &Tensor,
    f32: impl Fn(&[f32]) -> Vec<f32>,
    f64: impl Fn(&[f64]) -> Vec<f64>,
) -> Result<Option<Tensor>> {
    let dy = dy.contiguous()?;
    let (st, l) = dy.storage_and_layout();
    let dx = match x.dtype() {
        DType::F32 => Tensor::from_vec(f32(data::<f32>(&st, l)?), x.shape(), x.device())?,
        DType::F64 => Tensor::from_vec(f64(data::<f64>(&st, l)?), x.shape(), x.device())?,
        dt => bail!("fused op: f32 or f64 only, got {dt:?}"),
    };
    Ok(Some(dx))
}

/// The contiguous elements of a CPU tensor.
fn data<'a, T: WithDType>(s: &'a Storage, l: &Layout) -> Result<&'a [T]> {
    let Storage::Cpu(cpu) = s else {
        bail!("fused op: CPU tensor expected")
    };
    slice(cpu, l)
}

/// Whether the fused CPU kernels run these tensors (else: the candle composition).
fn on_cpu(ts: &[&Tensor]) -> bool {
    ts.iter()
        .all(|t| t.device().is_cpu() && matches!(t.dtype(), DType::F32 | DType::F64))
        && ts.windows(2).all(|p| p[0].dtype() == p[1].dtype())
}

/// Selection probabilities from the last depth layer: `x` `[B, D, P]`, `log_scale` `[1]`
/// -> `softmax over D of tanh(x) * exp(log_scale)`, `[B, D, P]`.
pub fn select_softmax(x: &Tensor, log_scale: &Tensor) -> Result<Tensor> {
    x.dims3()?;
    if log_scale.dims() != [1] {
        bail!(
            "select_softmax: log_scale must be [1], got {:?}",
            log_scale.dims()
        );
    }
    if !on_cpu(&[x, log_scale]) {
        let logits = x.tanh()?.broadcast_mul(&log_scale.exp()?)?;
        return candle_nn::ops::softmax(&logits, 1);
    }
    x.contiguous()?.apply_op2(log_scale, SelectSoftmax)
}

struct SelectSoftmax;

/// Columns (pixels) per parallel work item of the per-pixel ops.
const COLUMNS: usize = 512;

/// Runs `f(b, j0, j1)` on all threads over batch items and column ranges `j0..j1` of
/// [`COLUMNS`] pixels (`p` pixels per item).
fn par_columns(b: usize, p: usize, f: impl Fn(usize, usize, usize) + Sync) {
    let per = p.div_ceil(COLUMNS);
    (0..b * per).into_par_iter().for_each(|i| {
        f(
            i / per,
            (i % per) * COLUMNS,
            ((i % per + 1) * COLUMNS).min(p),
        )
    });
}

impl SelectSoftmax {
    /// Softmax over `d` of `tanh(x) a` for columns `j0..j1` of one batch item (`x`, `s`:
    /// `[d, p]`).
    ///
    /// # Safety
    /// `s` addresses `d * p` values of which no other thread touches these columns.
    unsafe fn columns<T: Float>(
        x: &[T],
        s: *mut T,
        a: T,
        (d, p): (usize, usize),
        j0: usize,
        j1: usize,
    ) {
        let mut m = vec![T::neg_infinity(); j1 - j0];
        for i in 0..d {
            for (j, mj) in (j0..j1).zip(m.iter_mut()) {
                let z = x[i * p + j].tanh() * a;
                *s.add(i * p + j) = z;
                *mj = mj.max(z);
            }
        }
        let mut sum = vec![T::zero(); j1 - j0];
        for i in 0..d {
            for ((j, &mj), sj) in (j0..j1).zip(&m).zip(sum.iter_mut()) {
                let e = (*s.add(i * p + j) - mj).exp();
                *s.add(i * p + j) = e;
                *sj = *sj + e;
            }
        }
        for i in 0..d {
            for (j, &sj) in (j0..j1).zip(&sum) {
                *s.add(i * p + j) = *s.add(i * p + j) / sj;
            }
        }
    }

    fn fwd<T: WithDType + Float>(x: &[T], a: T, (d, p): (usize, usize)) -> Vec<T> {
        let mut s = vec![T::zero(); x.len()];
        let sp = SharedMut(s.as_mut_ptr());
        par_columns(x.len() / (d * p), p, |b, j0, j1| {
            // SAFETY: items own disjoint columns of one batch item.
            unsafe {
                Self::columns(
                    &x[b * d * p..][..d * p],
                    sp.get().add(b * d * p),
                    a,
                    (d, p),
                    j0,
                    j1,
                )
            }
        });
        s
    }

    /// `(dx, d log_scale)` from the output `s` and its gradient `ds`.
    fn bwd_typed<T: WithDType + Float>(
        x: &[T],
        s: &[T],
        ds: &[T],
        a: T,
        (d, p): (usize, usize),
    ) -> (Vec<T>, T) {
        let mut dx = vec![T::zero(); x.len()];
        let dxp = SharedMut(dx.as_mut_ptr());
        let per = p.div_ceil(COLUMNS);
        let dls: Vec<T> = (0..x.len() / (d * p) * per)
            .into_par_iter()
            .map(|it| {
                let (b, j0) = (it / per, (it % per) * COLUMNS);
                let j1 = (j0 + COLUMNS).min(p);
                let o = b * d * p;
                let mut dls = T::zero();
                for j in j0..j1 {
                    let dot = (0..d).fold(T::zero(), |acc, i| {
                        acc + s[o + i * p + j] * ds[o + i * p + j]
                    });
                    for i in 0..d {
                        let k = o + i * p + j;
                        let dz = s[k] * (ds[k] - dot);
                        let t = x[k].tanh();
                        dls += dz * t * a;
                        // SAFETY: items own disjoint columns.
                        unsafe { *dxp.get().add(k) = dz * a * (T::one() - t * t) };
                    }
                }
                dls
            })
            .collect();
        (dx, dls.into_iter().fold(T::zero(), |acc, v| acc + v))
    }
}

impl CustomOp2 for SelectSoftmax {
    fn name(&self) -> &'static str {
        "deepstereo-select-softmax"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (_, d, p) = l1.shape().dims3()?;
        let y = match s1 {
            CpuStorage::F32(_) => {
                let a = slice::<f32>(s2, l2)?[0].exp();
                CpuStorage::F32(Self::fwd(slice::<f32>(s1, l1)?, a, (d, p)))
            }
            CpuStorage::F64(_) => {
                let a = slice::<f64>(s2, l2)?[0].exp();
                CpuStorage::F64(Self::fwd(slice::<f64>(s1, l1)?, a, (d, p)))
            }
            _ => bail!("select_softmax: f32 or f64 only"),
        };
        Ok((y, l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        ls: &Tensor,
        s: &Tensor,
        ds: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, d, p) = x.dims3()?;
        let ds = ds.contiguous()?;
        fn run<T: WithDType + Float>(
            x: &Tensor,
            ls: &Tensor,
            s: &Tensor,
            ds: &Tensor,
            dp: (usize, usize),
        ) -> Result<(Tensor, Tensor)> {
            let (dx, dls) = {
                let (xs, xl) = x.storage_and_layout();
                let (ss, sl) = s.storage_and_layout();
                let (gs, gl) = ds.storage_and_layout();
                let (ls_s, ls_l) = ls.storage_and_layout();
                let a = data::<T>(&ls_s, ls_l)?[0].exp();
                let (x, s, g) = (
                    data::<T>(&xs, xl)?,
                    data::<T>(&ss, sl)?,
                    data::<T>(&gs, gl)?,
                );
                SelectSoftmax::bwd_typed(x, s, g, a, dp)
            };
            Ok((
                Tensor::from_vec(dx, x.shape(), x.device())?,
                Tensor::from_vec(vec![dls], 1, x.device())?,
            ))
        }
        let (dx, dls) = match x.dtype() {
            DType::F32 => run::<f32>(x, ls, s, &ds, (d, p))?,
            DType::F64 => run::<f64>(x, ls, s, &ds, (d, p))?,
            dt => bail!("select_softmax: f32 or f64 only, got {dt:?}"),
        };
        Ok((Some(dx), Some(dls)))
    }
}

/// The rendered colour `sum over D of s c`: colours `[B, D, 3, P]`, selection `[B, D, P]`
/// -> `[B, 3, P]`.
pub fn composite(colours: &Tensor, selection: &Tensor) -> Result<Tensor> {
    let (b, d, _, p) = colours.dims4()?;
    if selection.dims() != [b, d, p] {
        bail!(
            "composite: selection {:?} does not match colours {:?}",
            selection.dims(),
            colours.dims()
        );
    }
    if !on_cpu(&[colours, selection]) {
        return colours.broadcast_mul(&selection.unsqueeze(2)?)?.sum(1);
    }
    colours
        .contiguous()?
        .apply_op2(&selection.contiguous()?, Composite)
}

struct Composite;

impl Composite {
    fn fwd<T: WithDType>(col: &[T], sel: &[T], (d, c, p): (usize, usize, usize)) -> Vec<T> {
        let mut out = vec![T::zero(); col.len() / d];
        let op = SharedMut(out.as_mut_ptr());
        par_columns(col.len() / (d * c * p), p, |b, j0, j1| {
            for z in 0..d {
                let s = &sel[(b * d + z) * p..][j0..j1];
                for ch in 0..c {
                    let cz = &col[((b * d + z) * c + ch) * p..][j0..j1];
                    // SAFETY: items own disjoint columns of the output.
                    let o = unsafe {
                        std::slice::from_raw_parts_mut(op.get().add((b * c + ch) * p + j0), j1 - j0)
                    };
                    for ((ov, &cv), &sv) in o.iter_mut().zip(cz).zip(s) {
                        *ov += cv * sv;
                    }
                }
            }
        });
        out
    }

    /// `(d colours, d selection)` from the output gradient `g` `[B, C, P]`.
    fn bwd_typed<T: WithDType>(
        col: &[T],
        sel: &[T],
        g: &[T],
        (d, c, p): (usize, usize, usize),
    ) -> (Vec<T>, Vec<T>) {
        let mut dcol = vec![T::zero(); col.len()];
        let mut dsel = vec![T::zero(); sel.len()];
        dcol.par_chunks_mut(c * p)
            .zip(dsel.par_chunks_mut(p))
            .enumerate()
            .for_each(|(bz, (dc, ds))| {
                let (b, s) = (bz / d, &sel[bz * p..][..p]);
                for ch in 0..c {
                    let gc = &g[(b * c + ch) * p..][..p];
                    let cz = &col[(bz * c + ch) * p..][..p];
                    let dcc = &mut dc[ch * p..][..p];
                    for j in 0..p {
                        dcc[j] = s[j] * gc[j];
                        ds[j] += cz[j] * gc[j];
                    }
                }
            });
        (dcol, dsel)
    }
}

impl CustomOp2 for Composite {
    fn name(&self) -> &'static str {
        "deepstereo-composite"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, d, c, p) = l1.shape().dims4()?;
        let y = match s1 {
            CpuStorage::F32(_) => CpuStorage::F32(Self::fwd(
                slice::<f32>(s1, l1)?,
                slice::<f32>(s2, l2)?,
                (d, c, p),
            )),
            CpuStorage::F64(_) => CpuStorage::F64(Self::fwd(
                slice::<f64>(s1, l1)?,
                slice::<f64>(s2, l2)?,
                (d, c, p),
            )),
            _ => bail!("composite: f32 or f64 only"),
        };
        Ok((y, Shape::from((b, c, p))))
    }

    fn bwd(
        &self,
        col: &Tensor,
        sel: &Tensor,
        _out: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, d, c, p) = col.dims4()?;
        let g = g.contiguous()?;
        fn run<T: WithDType>(
            col: &Tensor,
            sel: &Tensor,
            g: &Tensor,
            dcp: (usize, usize, usize),
        ) -> Result<(Tensor, Tensor)> {
            let (dc, ds) = {
                let (cs, cl) = col.storage_and_layout();
                let (ss, sl) = sel.storage_and_layout();
                let (gs, gl) = g.storage_and_layout();
                Composite::bwd_typed(
                    data::<T>(&cs, cl)?,
                    data::<T>(&ss, sl)?,
                    data::<T>(&gs, gl)?,
                    dcp,
                )
            };
            Ok((
                Tensor::from_vec(dc, col.shape(), col.device())?,
                Tensor::from_vec(ds, sel.shape(), sel.device())?,
            ))
        }
        let (dc, ds) = match col.dtype() {
            DType::F32 => run::<f32>(col, sel, &g, (d, c, p))?,
            DType::F64 => run::<f64>(col, sel, &g, (d, c, p))?,
            dt => bail!("composite: f32 or f64 only, got {dt:?}"),
        };
        Ok((Some(dc), Some(ds)))
    }
}

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
        let mut y = vec![T::zero(); n * c * hp * wp];
        y.par_chunks_mut(hp * wp)
            .enumerate()
            .for_each(|(i, plane)| {
                let base = o + i / c * st[0] + i % c * st[1];
                for r in 0..h {
                    let src = &x[base + r * st[2]..][..w];
                    plane[(r + self.p) * wp..][..w].copy_from_slice(src);
                }
            });
        Ok(y)
    }

    fn bwd_typed<T: WithDType>(
        &self,
        dy: &[T],
        (n, c, h, w): (usize, usize, usize, usize),
    ) -> Vec<T> {
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
        let dims = x.dims4()?;
        plane_grad(
            x,
            dy,
            |g| self.bwd_typed(g, dims),
            |g| self.bwd_typed(g, dims),
        )
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

    /// max |a - b| over two tensors.
    fn max_diff(a: &Tensor, b: &Tensor) -> Result<f64> {
        (a - b)?
            .abs()?
            .flatten_all()?
            .max(0)?
            .to_dtype(DType::F64)?
            .to_scalar::<f64>()
    }

    #[test]
    fn select_softmax_and_composite_match_composition() -> Result<()> {
        let dev = &Device::Cpu;
        for dt in [DType::F32, DType::F64] {
            let tol = if dt == DType::F32 { 1e-5 } else { 1e-12 };
            let x = Var::from_tensor(&Tensor::randn(0f64, 2., (2, 7, 11), dev)?.to_dtype(dt)?)?;
            let ls = Var::from_tensor(&Tensor::new(&[1.7f64], dev)?.to_dtype(dt)?)?;
            let col =
                Var::from_tensor(&Tensor::randn(0f64, 1., (2, 7, 3, 11), dev)?.to_dtype(dt)?)?;
            let r = Tensor::randn(0f64, 1., (2, 3, 11), dev)?.to_dtype(dt)?;
            let rs = Tensor::randn(0f64, 1., (2, 7, 11), dev)?.to_dtype(dt)?;
            let reference = |fused: bool| -> Result<Vec<Tensor>> {
                let (s, img) = if fused {
                    let s = select_softmax(x.as_tensor(), ls.as_tensor())?;
                    let img = composite(col.as_tensor(), &s)?;
                    (s, img)
                } else {
                    let logits = x
                        .as_tensor()
                        .tanh()?
                        .broadcast_mul(&ls.as_tensor().exp()?)?;
                    let s = candle_nn::ops::softmax(&logits, 1)?;
                    let img = col.as_tensor().broadcast_mul(&s.unsqueeze(2)?)?.sum(1)?;
                    (s, img)
                };
                let loss = ((img * &r)?.sum_all()? + (&s * &rs)?.sum_all()?)?;
                let g = loss.backward()?;
                let mut out = vec![s, loss];
                for v in [&x, &ls, &col] {
                    out.push(g.get(v.as_tensor()).expect("gradient").clone());
                }
                Ok(out)
            };
            let (got, want) = (reference(true)?, reference(false)?);
            for (i, (a, b)) in got.iter().zip(&want).enumerate() {
                let e = max_diff(a, b)?;
                assert!(e < tol, "{dt:?} output {i}: {e}");
            }
        }
        Ok(())
    }

    #[test]
    fn pad_rows_matches_pad_with_zeros() -> Result<()> {
        let dev = &Device::Cpu;
        for dt in [DType::F32, DType::F64] {
            let v = Var::from_tensor(&Tensor::randn(0f64, 1., (2, 5, 3, 7), dev)?.to_dtype(dt)?)?;
            let view = v.as_tensor().transpose(1, 2)?; // [2, 3, 5, 7], strided
            let r = Tensor::randn(0f64, 1., (2, 3, 9, 10), dev)?.to_dtype(dt)?;
            let got = pad_rows(&view, 2, 3)?;
            let want = view.pad_with_zeros(2, 2, 2)?.pad_with_zeros(3, 0, 3)?;
            assert_eq!(max_diff(&got, &want)?, 0.0);
            let gg = (got * &r)?.sum_all()?.backward()?;
            let gw = (want * &r)?.sum_all()?.backward()?;
            let e = max_diff(
                gg.get(v.as_tensor()).unwrap(),
                gw.get(v.as_tensor()).unwrap(),
            )?;
            assert_eq!(e, 0.0);
        }
        Ok(())
    }
}
