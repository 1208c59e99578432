//! 2D convolution layer used by the model (valid padding, stride 1), with its own CPU
//! kernels for forward and backward.
//!
//! Weights `[C_out, C_in, kh, kw]` and bias `[C_out]`, PyTorch's layout.
//!
//! # Design
//! DESIGN_PLACEHOLDER

mod im2col;
mod kernels;
mod op;
#[cfg(test)]
mod tests;

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
        let init = candle_nn::Init::Uniform { lo: -bound, up: bound };
        let weight = vb.get_with_hints((cout, cin, kh, kw), "weight", init)?;
        let bias = vb.get_with_hints(cout, "bias", init)?;
        Ok(Self { weight, bias })
    }

    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// `relu(conv(x) + bias)`, with the ReLU fused into the kernels (forward and backward).
    pub fn forward_relu(&self, x: &Tensor) -> Result<Tensor> {
        if op::supported(x, &self.weight) {
            op::conv2d(x, &self.weight, &self.bias, true)
        } else {
            self.forward_reference(x)?.relu()
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
