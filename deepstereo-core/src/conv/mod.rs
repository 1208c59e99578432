//! 2D convolution layer used by the model (valid padding, stride 1), with its own CPU
//! kernels for forward and backward.
//!
//! Weights `[C_out, C_in, kh, kw]` and bias `[C_out]`, PyTorch's layout.
//!
//! # Design
//! [`Conv2d::forward`] and [`Conv2d::forward_relu`] apply one candle `CustomOp3`
//! `(x, weight, bias) -> y` (`op.rs`); its backward calls the kernels directly instead of
//! composing candle ops, and candle's autograd adds the three gradients as for any op
//! (no second-order gradients). Off the CPU, or for dtypes other than f32 / f64, the layer
//! falls back to candle's `conv2d` ([`Conv2d::forward_reference`]).
//!
//! Three CPU paths, chosen per layer in `plan.rs`:
//! - **f32 with AVX2 and FMA** (checked at run time): implicit GEMM, no im2col buffer.
//!   `direct.rs` vectorises along output pixels (tiles of 6 output channels x 16 pixels,
//!   input read at a per-tap offset, bias and ReLU fused, taps blocked for L1);
//!   `direct_cv.rs` vectorises along output channels for wide layers (`Cout` a multiple of
//!   16, `K >= 256`: tiles of 16 channels x 6 pixels; rows' leftovers gathered into tiles
//!   of their own). `winograd.rs` runs the 3x3 and 5x5 layers with at least 32 output
//!   channels (a multiple of 16) as Winograd F(4x4, 3x3) / F(2x2, 5x5): 36 products per
//!   6x6 input tile instead of 144 / 100, the products on `direct_cv.rs`'s tile; its f32
//!   error is that of a direct sum (tested against im2col to 1e-5 of the outputs' scale,
//!   inputs of 1e4 included).
//!   `direct_grad.rs`: the input gradient is `direct.rs`'s forward on the zero-padded,
//!   ReLU-masked output gradient with flipped, transposed weights; the weight gradient a
//!   reduction vectorised along pixels (3 channels x 4 taps per tile), with accumulators
//!   summed in a fixed order (deterministic). `DEEPSTEREO_CONV=im2col`, `pixels` or
//!   `direct` turns these off (all; the channel-vectorised one and Winograd; Winograd) to
//!   compare paths in benchmarks.
//! - **otherwise (f64, other CPUs, layers too small for a tile)**: one product in "column
//!   space" (`im2col.rs`), described below.
//! - off the CPU: candle's `conv2d`.
//!
//! For rendering only (no gradients), `chain.rs` runs a whole chain of small layers per
//! block of 16 pixels on `direct.rs`'s tile, activations kept in a per-thread scratch:
//! [`depth_head`] (the depth convolutions and the selection softmax) and
//! [`pointwise_colours`] (a colour tower of 1x1 convolutions and its output layer);
//! `DeepStereo::infer` (`model.rs`) uses them.
//!
//! Column space: `Y [Cout, N*P] = W [Cout, K] x cols [K, N*P]`, `P = Ho*Wo`,
//! `K = Cin*kh*kw`. The
//! columns are cut into chunks (whole images, grouped when small, or balanced runs of
//! output rows of one image) whose im2col buffer is about 1 MiB (a core's L2), at least
//! 4 per thread. Rayon threads take chunks and run, each in its own reused buffers and
//! with a single-threaded `gemm` call (the crate candle's matmul uses):
//! - forward: im2col, `W x cols` written straight into `y` (NCHW) when the chunk lies in
//!   one image, else through a buffer; then bias and ReLU on the cache-hot rows;
//! - backward: the ReLU-masked output gradient `gy` of the chunk (summed into the bias
//!   gradient on the way), im2col again (columns are recomputed, not kept: memory stays that
//!   of the activations), `dW^T += cols x gy^T` into an accumulator per block of chunks
//!   (transposed so gemm reads the im2col buffer without repacking it; blocks are summed in
//!   a fixed order, so gradients are deterministic), then `dcols = W^T x gy` and col2im
//!   into `dx`. Row chunks of one image overlap in `dx` and run in two phases (even, odd).
//!   `dx` is only computed when `x` needs a gradient (not for the plane-sweep input).
//! - 1x1 kernels skip im2col / col2im: gemm reads `x` and writes `dx` in place.
//!
//! # Measurements behind the choices (2 cores of an AMD EPYC with AVX2, shared machine)
//! - The im2col path spent about a sixth of the `tiny` forward copying im2col runs (`perf`), and
//!   the `gemm` crate's f32 kernel vectorises along `Cout`, wasting a quarter of a 16-row
//!   tile at `Cout = 12`. The implicit-GEMM kernels took the `tiny` forward 1.2-1.3x and
//!   its training step 1.2-1.45x faster (`DEEPSTEREO_CONV=im2col` against the default in
//!   `examples/forward_probe.rs`, runs alternated; `paper`'s forward 1.1x). The `paper`
//!   backward stays on im2col + `gemm` (its direct backward was ~15% slower).
//! - Winograd took the `paper` forward 1.45-1.5x faster and its training step 1.1x
//!   (`target/release/examples/forward_probe paper 3`, and `... paper 3 32 step`, runs
//!   alternated with `DEEPSTEREO_CONV=direct`). Work units of 24 tiles keep a unit's
//!   transformed input and products in L2 (48 spilled out of L2 and ran slower); the
//!   input is split into `M x M` phase planes per image (per thread, into a reused buffer)
//!   so that the transforms read and write whole vectors. With 16 output channels the
//!   per-input-channel transform outweighs the saved products (the direct kernel was
//!   faster on `paper`'s 16-channel layers), and small outputs pad the tiles too much
//!   (`winograd::MIN_SAVING`).
//! - Rows whose byte stride is a multiple of 4 KiB (depth rows of a 64x64 tile) put all
//!   the taps of a tile in one L1 set; the model shifts them by a cache line.
//! - candle's own autograd over an im2col op plus `broadcast_matmul` (weights `[Cout, K]`
//!   against cols `[N, K, P]`) was slower even before counting im2col / col2im: for
//!   768x64x18x18 -> 96, 5x5 its matmul backward alone took about 2.2 s against 0.8 s for
//!   this whole backward (it loops over N small gemms and materialises `[N, Cout, K]`
//!   weight gradients), and it keeps cols (`[N, K, P]`, 0.74 GB for the paper's first
//!   layer) alive for the backward.
//! - A few huge chunks (in effect one big gemm per thread over the CNHW column space) were
//!   1.5-2x slower than L2-sized chunks; one image per chunk was about as fast as the
//!   chosen plan.
//! - On this VM a first touch of fresh memory costs about 1.5-2 ms per MB (page faults),
//!   comparable with the arithmetic of the small-channel layers. Every new tensor pays it
//!   (candle's gradient accumulation allocates several per op). Starting the process with
//!   `GLIBC_TUNABLES=glibc.malloc.hugetlb=1:glibc.malloc.mmap_threshold=4294967295:glibc.malloc.trim_threshold=4294967295`
//!   (transparent huge pages, freed memory kept for reuse, so the resident size stays at
//!   its peak) made the backward of the tiny preset's layers 2-3x faster back to back
//!   (e.g. 128x28x24x24 -> 3, 1x1: 12 ms -> 4.5 ms); it has to be set before the process
//!   starts (a binary can re-exec itself with it).

mod chain;
mod direct;
mod direct_cv;
mod direct_grad;
mod im2col;
mod kernels;
pub use chain::{depth_head, pointwise_chain, pointwise_colours};
mod op;
mod plan;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_chain;
mod winograd;

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

#[derive(Debug, Clone)]
pub struct Conv2d {
    weight: Tensor,
    bias: Tensor,
}

impl Conv2d {
    /// Kaiming-uniform initialisation as PyTorch's `nn.Conv2d` default.
    pub fn new(cin: usize, cout: usize, (kh, kw): (usize, usize), vb: VarBuilder) -> Result<Self> {
        let fan_in = (cin * kh * kw) as f64;
        let bound = 1.0 / fan_in.sqrt();
        let init = candle_nn::Init::Uniform {
            lo: -bound,
            up: bound,
        };
        let weight = vb.get_with_hints((cout, cin, kh, kw), "weight", init)?;
        let bias = vb.get_with_hints(cout, "bias", init)?;
        Ok(Self { weight, bias })
    }

    /// A layer whose weight and bias start at zero (its output is 0 until training moves it).
    pub fn zeros(
        cin: usize,
        cout: usize,
        (kh, kw): (usize, usize),
        vb: VarBuilder,
    ) -> Result<Self> {
        let init = candle_nn::Init::Const(0.0);
        let weight = vb.get_with_hints((cout, cin, kh, kw), "weight", init)?;
        let bias = vb.get_with_hints(cout, "bias", init)?;
        Ok(Self { weight, bias })
    }

    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    pub fn bias(&self) -> &Tensor {
        &self.bias
    }

    /// `relu(conv(x) + bias)`, with the ReLU fused into the kernels (forward and backward).
    pub fn forward_relu(&self, x: &Tensor) -> Result<Tensor> {
        if op::supported(x, &self.weight) {
            op::conv2d(x, &self.weight, &self.bias, true)
        } else {
            self.forward_reference(x)?.relu()
        }
    }

    /// The convolution of the channel concatenation `[a, b]` (`[N, Ca + Cb, H, W]`)
    /// without building it: `conv(a, w[:, ..Ca]) + conv(b, w[:, Ca..]) + bias`.
    pub fn forward_pair(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        let (ya, yb) = self.forward_split(a, b)?;
        ya + yb
    }

    /// The two parts of [`Self::forward_pair`] apart: `(conv(a, w[:, ..Ca]) + bias,
    /// conv(b, w[:, Ca..]))`; `a` and `b` may have different batch sizes.
    pub fn forward_split(&self, a: &Tensor, b: &Tensor) -> Result<(Tensor, Tensor)> {
        let ca = a.dim(1)?;
        let cin = self.weight.dim(1)?;
        if ca + b.dim(1)? != cin {
            candle_core::bail!(
                "conv2d: inputs with {ca} + {} channels for a weight of {cin}",
                b.dim(1)?
            );
        }
        let wa = self.weight.narrow(1, 0, ca)?.contiguous()?;
        let wb = self.weight.narrow(1, ca, cin - ca)?.contiguous()?;
        let zero = self.bias.zeros_like()?;
        if op::supported(a, &self.weight) && op::supported(b, &self.weight) {
            Ok((
                op::conv2d(a, &wa, &self.bias, false)?,
                op::conv2d(b, &wb, &zero, false)?,
            ))
        } else {
            let ya = a.conv2d(&wa, 0, 1, 1, 1)?;
            let c = self.bias.dim(0)?;
            Ok((
                ya.broadcast_add(&self.bias.reshape((1, c, 1, 1))?)?,
                b.conv2d(&wb, 0, 1, 1, 1)?,
            ))
        }
    }

    /// The same convolution through candle's built-in `conv2d` (for tests and benchmarks;
    /// also the fallback off the CPU or for dtypes other than f32 and f64).
    pub fn forward_reference(&self, x: &Tensor) -> Result<Tensor> {
        let y = x.conv2d(&self.weight, 0, 1, 1, 1)?;
        let c = self.bias.dim(0)?;
        y.broadcast_add(&self.bias.reshape((1, c, 1, 1))?)
    }
}

impl Module for Conv2d {
    /// `[N, C_in, H, W]` -> `[N, C_out, H - kh + 1, W - kw + 1]`.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if op::supported(x, &self.weight) {
            op::conv2d(x, &self.weight, &self.bias, false)
        } else {
            self.forward_reference(x)
        }
    }
}
