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

use candle_core::{bail, CpuStorage, DType, Layout, Result, Storage, Tensor, WithDType};
use rayon::prelude::*;

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
