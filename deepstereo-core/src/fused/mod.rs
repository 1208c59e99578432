//! Fused CPU ops for the glue between the network's convolutions, where candle's generic
//! ops would copy through strided index arithmetic or allocate one tensor per step.
//!
//! - [`upsample_crop`]: nearest upsampling by an integer factor and a crop, in one pass
//!   (the towers' coarse levels), with its backward (sums over each source pixel's block),
//!   and [`upsample_cat`], the levels' crops concatenated in one pass (rendering);
//! - [`select_softmax`]: the selection tower's head, `softmax_D(tanh(x) exp(log_scale))`;
//! - [`composite`]: the rendered colour `sum_z s_z c_z`;
//! - [`pool_front`], [`view_stats`], [`pooled_stats`], [`blend_colours`]: the
//!   any-number-of-views family's steps across views (`pool.rs` there), and
//!   [`encode_pool`] and [`blend_infer`], its per-view encoder with the pooling, and its
//!   whole colour blend, each in one pass when rendering, and [`weigh_views`], the cue's
//!   view weights (rendering);
//! - [`pad_rows`]: zero rows above and below (the depth convolutions' padding) and
//!   optionally zero columns on the right, reading a transposed view directly (no
//!   separate transpose copy).
//!
//! Each op equals a composition of candle ops, which is also the fallback off the CPU or
//! for dtypes other than f32 / f64 (tests compare the two, values and gradients).

mod blend;
mod blend_infer;
mod encode;
mod fastmath;
mod head;
mod pad;
mod pool;
#[cfg(test)]
mod tests;
mod upsample;
mod weigh;

pub use blend::{add_views_relu, blend_colours};
pub use blend_infer::{blend_infer, Dense};
pub use encode::encode_pool;
pub use head::{composite, select_softmax};
pub use pad::pad_rows;
pub use pool::{pool_front, pooled_stats, view_stats};
pub use upsample::{upsample_cat, upsample_crop, upsample_nearest};
pub use weigh::weigh_views;

use candle_core::{
    bail, CpuStorage, CustomOp2, DType, Layout, Result, Shape, Storage, Tensor, WithDType,
};
use num_traits::{AsPrimitive, Float, NumAssignOps};
use rayon::prelude::*;
use std::marker::PhantomData;

/// The float types the fused CPU kernels run on (f32 and f64), with what their loops use.
trait Real: WithDType + Float + NumAssignOps + AsPrimitive<f64> + Send + Sync {}
impl Real for f32 {}
impl Real for f64 {}

/// The contiguous elements of a CPU storage under `l`.
fn slice<'a, T: WithDType>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&s.as_slice::<T>()?[a..b]),
        None => bail!("fused op: expected a contiguous tensor"),
    }
}

/// A one-input op over `[N, C, H, W]` planes whose input gradient is computed on CPU
/// slices, for either float type.
trait PlaneBackward {
    /// `dx` (`x_dims` long) from the contiguous `dy`.
    fn dx<T: WithDType>(&self, dy: &[T], x_dims: (usize, usize, usize, usize)) -> Vec<T>;
}

/// `dx` of a [`PlaneBackward`] op from `dy`.
fn plane_grad(op: &impl PlaneBackward, x: &Tensor, dy: &Tensor) -> Result<Option<Tensor>> {
    let dims = x.dims4()?;
    let dy = dy.contiguous()?;
    let (st, l) = dy.storage_and_layout();
    let dx = match x.dtype() {
        DType::F32 => Tensor::from_vec(op.dx(data::<f32>(&st, l)?, dims), x.shape(), x.device())?,
        DType::F64 => Tensor::from_vec(op.dx(data::<f64>(&st, l)?, dims), x.shape(), x.device())?,
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

/// The contiguous CPU data of the tensors `ts` as `T`, handed to `f` while their storages
/// are read-locked.
fn read<T: WithDType, R, const K: usize>(
    ts: [&Tensor; K],
    f: impl FnOnce([&[T]; K]) -> Result<R>,
) -> Result<R> {
    let guards = ts.map(|t| t.storage_and_layout());
    let mut slices: [&[T]; K] = [&[]; K];
    for (d, (st, l)) in slices.iter_mut().zip(&guards) {
        *d = data::<T>(st, l)?;
    }
    f(slices)
}

/// A fused two-input op's kernels on CPU slices, for either float type; [`fwd2`] and
/// [`bwd2`] dispatch on the dtype.
trait Kernels2: Send + Sync + 'static {
    /// The op's name in errors.
    const NAME: &'static str;

    /// The candle op's name.
    const OP: &'static str;

    /// The output's shape from the first input's (by default the same).
    fn out_shape(a: &Shape) -> Result<Shape> {
        Ok(a.clone())
    }

    /// The output from the inputs' contiguous data; `shape` is the first input's.
    fn forward<T: Real>(a: &[T], b: &[T], shape: &Shape) -> Result<Vec<T>>;

    /// The inputs' gradients from the inputs `a` and `b`, the output `y` and its
    /// contiguous gradient `g`.
    fn backward<T: Real>(
        a: &Tensor,
        b: &Tensor,
        y: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)>;
}

/// A [`Kernels2`] as a candle op.
struct Fused2<K>(PhantomData<K>);

/// The op `K` applied to `a` and `b` (with its backward).
fn apply2<K: Kernels2>(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    a.apply_op2(b, Fused2::<K>(PhantomData))
}

impl<K: Kernels2> CustomOp2 for Fused2<K> {
    fn name(&self) -> &'static str {
        K::OP
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        Ok((fwd2::<K>(s1, l1, s2, l2)?, K::out_shape(l1.shape())?))
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        y: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        bwd2::<K>(a, b, y, g)
    }
}

/// `v` as a tensor of `like`'s shape on its device.
fn shaped<T: WithDType>(v: Vec<T>, like: &Tensor) -> Result<Tensor> {
    Tensor::from_vec(v, like.shape(), like.device())
}

/// The sources' gradient `dx()` where the sources `x` carry one (their alphas weighed by
/// the cue), else `None`.
fn source_grad<T: WithDType>(x: &Tensor, dx: impl FnOnce() -> Vec<T>) -> Result<Option<Tensor>> {
    match x.track_op() {
        true => shaped(dx(), x).map(Some),
        false => Ok(None),
    }
}

/// [`Kernels2::forward`] on CPU storages of either float type.
fn fwd2<K: Kernels2>(
    s1: &CpuStorage,
    l1: &Layout,
    s2: &CpuStorage,
    l2: &Layout,
) -> Result<CpuStorage> {
    Ok(match s1 {
        CpuStorage::F32(_) => CpuStorage::F32(K::forward(
            slice::<f32>(s1, l1)?,
            slice::<f32>(s2, l2)?,
            l1.shape(),
        )?),
        CpuStorage::F64(_) => CpuStorage::F64(K::forward(
            slice::<f64>(s1, l1)?,
            slice::<f64>(s2, l2)?,
            l1.shape(),
        )?),
        _ => bail!("{}: f32 or f64 only", K::NAME),
    })
}

/// [`Kernels2::backward`] for `a`'s float type, with the output gradient made contiguous.
fn bwd2<K: Kernels2>(
    a: &Tensor,
    b: &Tensor,
    y: &Tensor,
    g: &Tensor,
) -> Result<(Option<Tensor>, Option<Tensor>)> {
    let g = g.contiguous()?;
    match a.dtype() {
        DType::F32 => K::backward::<f32>(a, b, y, &g),
        DType::F64 => K::backward::<f64>(a, b, y, &g),
        dt => bail!("{}: f32 or f64 only, got {dt:?}", K::NAME),
    }
}

/// Fails unless the sources `x` are `[N, V, 4, P]` with `(n, v, p)` those of `other` (the
/// op's `what`, e.g. its logits).
fn check_sources(
    op: &str,
    x: &Tensor,
    (n, v, p): (usize, usize, usize),
    (what, other): (&str, &Tensor),
) -> Result<()> {
    if x.dims() != [n, v, 4, p] {
        bail!(
            "{op}: sources {:?} do not match {what} {:?}",
            x.dims(),
            other.dims()
        );
    }
    Ok(())
}

/// Whether the fused CPU kernels run these tensors (else: the candle composition).
fn on_cpu(ts: &[&Tensor]) -> bool {
    ts.iter()
        .all(|t| t.device().is_cpu() && matches!(t.dtype(), DType::F32 | DType::F64))
        && ts.windows(2).all(|p| p[0].dtype() == p[1].dtype())
}

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
