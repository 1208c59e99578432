//! Which CPU algorithm runs a convolution: the one place the choice is made.
//!
//! Each kernel's module says which layers it can run (`applies`: the CPU has AVX2 and FMA
//! and the layer holds the kernel's tile); this module picks among those, in this order,
//! and applies the `DEEPSTEREO_CONV` override ([`Kernels`]):
//! - forward, f32 ([`forward`]): Winograd (`winograd/`) for wide 3x3 and 5x5 layers, then
//!   the channel-vectorised kernel (`direct_cv.rs`) for wide layers with many taps, then
//!   the pixel-vectorised kernel (`direct.rs`) for any layer with at least one tile, else
//!   im2col + gemm (`im2col.rs`, `kernels.rs`); f64 always takes im2col;
//! - backward, f32 ([`backward`]): the direct backward (`direct_grad.rs`) for layers with
//!   few taps, else for wide layers whose input gradient is a Winograd layer that gradient
//!   by Winograd and the weight gradient by im2col, else im2col for both;
//! - rendering's fused chains (`chain.rs`, [`chain`]): f32 on the CPU with the AVX2
//!   kernels allowed.
//!
//! The measurements behind the order are in the module doc of `conv`.

use super::im2col::Geom;
use super::{direct, direct_cv, kernels, winograd};
use crate::cpu::avx2_fma_available;
use candle_core::{DType, Tensor};

/// Which f32 kernels `DEEPSTEREO_CONV` allows (read once): `im2col` forces the im2col +
/// gemm path everywhere, `pixels` keeps the pixel-vectorised kernels but not the
/// channel-vectorised one (`direct_cv.rs`); anything else (or unset) lets each layer take
/// the kernel that suits it. For comparing the paths in benchmarks.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kernels {
    Auto,
    Direct,
    Pixels,
    Im2col,
}

pub(crate) fn kernels_allowed() -> Kernels {
    static K: std::sync::OnceLock<Kernels> = std::sync::OnceLock::new();
    *K.get_or_init(|| match std::env::var("DEEPSTEREO_CONV").as_deref() {
        Ok("im2col") => Kernels::Im2col,
        Ok("direct") => Kernels::Direct,
        Ok("pixels") => Kernels::Pixels,
        _ => Kernels::Auto,
    })
}

/// The f32 forward's algorithm.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Forward {
    Winograd,
    /// Channel-vectorised implicit GEMM (`direct_cv.rs`).
    DirectCv,
    /// Pixel-vectorised implicit GEMM (`direct.rs`).
    Direct,
    Im2col,
}

/// The f32 backward's algorithm.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Backward {
    /// [`direct_grad::backward`]: all three gradients.
    Direct,
    /// [`direct_grad::input_grad`] (Winograd) for the input gradient, im2col for the weight
    /// and bias gradients.
    InputByWinograd,
    Im2col,
}

/// The algorithm of an f32 forward of layer `g`.
pub(crate) fn forward(g: &Geom) -> Forward {
    let allowed = kernels_allowed();
    if allowed == Kernels::Im2col || !direct::applies(g) {
        Forward::Im2col
    } else if allowed == Kernels::Auto && winograd::applies(g) {
        Forward::Winograd
    } else if matches!(allowed, Kernels::Auto | Kernels::Direct) && direct_cv::applies(g) {
        Forward::DirectCv
    } else {
        Forward::Direct
    }
}

/// `y = act(conv(x, w) + b)` in f32 by the algorithm [`forward`] picks.
pub(crate) fn forward_f32(g: &Geom, x: &[f32], w: &[f32], b: &[f32], relu: bool) -> Vec<f32> {
    match forward(g) {
        Forward::Winograd => winograd::forward(g, x, w, b, relu),
        Forward::DirectCv => direct_cv::forward(g, x, w, b, relu),
        Forward::Direct => direct::forward(g, x, w, b, relu),
        Forward::Im2col => kernels::forward(g, x, w, b, relu),
    }
}

/// Most taps for [`backward`]: wider layers (the `paper` preset's) ran their training
/// step ~15% faster on the im2col + gemm backward (8 alternated runs of
/// `examples/forward_probe.rs paper 1 32 step`), narrow ones (`tiny`'s) on this one.
pub(crate) const MAX_DIRECT_GRAD_K: usize = 255;

/// Whether `direct_grad.rs`'s backward can run this layer: few taps (at most
/// [`MAX_DIRECT_GRAD_K`]), and the input gradient's convolution holds a tile.
pub(crate) fn direct_grad_applies(g: &Geom) -> bool {
    avx2_fma_available() && g.k() <= MAX_DIRECT_GRAD_K && direct::applies(&g.transposed())
}

/// The algorithm of an f32 backward of layer `g` (`need_dx`: the input's gradient is
/// asked for).
pub(crate) fn backward(g: &Geom, need_dx: bool) -> Backward {
    let allowed = kernels_allowed();
    if allowed != Kernels::Im2col && direct_grad_applies(g) {
        Backward::Direct
    } else if need_dx && allowed == Kernels::Auto && winograd::applies(&g.transposed()) {
        Backward::InputByWinograd
    } else {
        Backward::Im2col
    }
}

/// Whether the fused chains (`chain.rs`) run these tensors: f32 on the CPU, with the AVX2
/// kernels.
pub(crate) fn chain(ts: &[&Tensor]) -> bool {
    avx2_fma_available()
        && kernels_allowed() != Kernels::Im2col
        && ts
            .iter()
            .all(|t| t.device().is_cpu() && t.dtype() == DType::F32)
}
