//! Optimizers with state that can be saved and restored exactly: Adagrad (the paper's,
//! as PyTorch's `torch.optim.Adagrad` with `lr_decay = 0`, `initial_accumulator_value = 0`)
//! and Adam (PyTorch's `torch.optim.Adam`, no weight decay).

use anyhow::{bail, Result};
use candle_core::backprop::GradStore;
use candle_core::{Tensor, Var};
use serde::{Deserialize, Serialize};

/// Adagrad's epsilon (PyTorch's default).
pub const ADAGRAD_EPS: f64 = 1e-10;
/// Adam's epsilon and betas (PyTorch's defaults).
pub const ADAM_EPS: f64 = 1e-8;
pub const ADAM_BETAS: (f64, f64) = (0.9, 0.999);

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OptimizerKind {
    Adagrad,
    Adam,
}

/// An optimizer over a fixed, ordered list of variables.
pub struct Optimizer {
    pub kind: OptimizerKind,
    pub lr: f64,
    /// Steps taken (Adam's bias correction).
    pub steps: u64,
    vars: Vec<(String, Var)>,
    /// Adagrad: the accumulator; Adam: the first moment.
    first: Vec<Tensor>,
    /// Adam: the second moment (empty for Adagrad).
    second: Vec<Tensor>,
}

impl Optimizer {
    pub fn new(kind: OptimizerKind, lr: f64, vars: Vec<(String, Var)>) -> Result<Self> {
        if !(lr.is_finite() && lr > 0.0) {
            bail!("the learning rate must be finite and positive, got {lr}");
        }
        let zeros = |v: &Var| v.as_tensor().zeros_like();
        let first = vars
            .iter()
            .map(|(_, v)| zeros(v))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let second = match kind {
            OptimizerKind::Adam => vars
                .iter()
                .map(|(_, v)| zeros(v))
                .collect::<candle_core::Result<Vec<_>>>()?,
            OptimizerKind::Adagrad => Vec::new(),
        };
        Ok(Self {
            kind,
            lr,
            steps: 0,
            vars,
            first,
            second,
        })
    }

    /// The L2 norm of all gradients (NaN or infinite when any is).
    pub fn grad_norm(&self, grads: &GradStore) -> Result<f64> {
        let mut sq = 0f64;
        for (_, v) in &self.vars {
            if let Some(g) = grads.get(v.as_tensor()) {
                sq += g
                    .sqr()?
                    .sum_all()?
                    .to_dtype(candle_core::DType::F64)?
                    .to_scalar::<f64>()?;
            }
        }
        Ok(sq.sqrt())
    }

    /// One update from `grads` (variables without a gradient are left unchanged).
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.steps += 1;
        let t = self.steps as i32;
        for (i, (_, v)) in self.vars.iter().enumerate() {
            let Some(g) = grads.get(v.as_tensor()) else {
                continue;
            };
            let w = v.as_tensor();
            match self.kind {
                OptimizerKind::Adagrad => {
                    let acc = (&self.first[i] + g.sqr()?)?;
                    let upd = (g / (acc.sqrt()? + ADAGRAD_EPS)?)?;
                    v.set(&(w - (upd * self.lr)?)?)?;
                    self.first[i] = acc;
                }
                OptimizerKind::Adam => {
                    let (b1, b2) = ADAM_BETAS;
                    let m = ((&self.first[i] * b1)? + (g * (1.0 - b1))?)?;
                    let s = ((&self.second[i] * b2)? + (g.sqr()? * (1.0 - b2))?)?;
                    let mhat = (&m / (1.0 - b1.powi(t)))?;
                    let shat = (&s / (1.0 - b2.powi(t)))?;
                    let upd = (mhat / (shat.sqrt()? + ADAM_EPS)?)?;
                    v.set(&(w - (upd * self.lr)?)?)?;
                    self.first[i] = m;
                    self.second[i] = s;
                }
            }
        }
        Ok(())
    }

    /// State tensors by name (`optim.first.<var>`, `optim.second.<var>`) for checkpoints.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        for (i, (name, _)) in self.vars.iter().enumerate() {
            out.push((format!("optim.first.{name}"), self.first[i].clone()));
            if let Some(s) = self.second.get(i) {
                out.push((format!("optim.second.{name}"), s.clone()));
            }
        }
        out
    }

    /// Restores state saved by [`Self::state`]; `get` looks a tensor up by name.
    pub fn restore(&mut self, steps: u64, get: impl Fn(&str) -> Result<Tensor>) -> Result<()> {
        for (i, (name, _)) in self.vars.iter().enumerate() {
            self.first[i] = get(&format!("optim.first.{name}"))?;
            if i < self.second.len() {
                self.second[i] = get(&format!("optim.second.{name}"))?;
            }
        }
        self.steps = steps;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Tensor};

    /// Adagrad on f(w) = sum(c * w^2) for three steps, against values computed by hand
    /// from the update `acc += g^2; w -= lr * g / (sqrt(acc) + eps)`.
    #[test]
    fn adagrad_matches_hand_computed_reference() -> Result<()> {
        let dev = Device::Cpu;
        let w0 = [1.0f64, -2.0, 0.5];
        let c = [1.0f64, 0.5, 3.0];
        let var = Var::from_tensor(&Tensor::new(&w0, &dev)?)?;
        let ct = Tensor::new(&c, &dev)?;
        let lr = 0.1;
        let mut opt = Optimizer::new(OptimizerKind::Adagrad, lr, vec![("w".into(), var.clone())])?;
        let (mut w, mut acc) = (w0, [0f64; 3]);
        for _ in 0..3 {
            let loss = (var.as_tensor().sqr()? * &ct)?.sum_all()?;
            opt.step(&loss.backward()?)?;
            for i in 0..3 {
                let g = 2.0 * c[i] * w[i];
                acc[i] += g * g;
                w[i] -= lr * g / (acc[i].sqrt() + ADAGRAD_EPS);
            }
            let got = var.as_tensor().to_vec1::<f64>()?;
            for i in 0..3 {
                assert!((got[i] - w[i]).abs() < 1e-12, "{got:?} vs {w:?}");
            }
        }
        Ok(())
    }

    /// A zero gradient on a zero accumulator must not produce NaN (0 / (0 + eps) = 0).
    #[test]
    fn adagrad_zero_gradient_stays_finite() -> Result<()> {
        let dev = Device::Cpu;
        let var = Var::from_tensor(&Tensor::new(&[1.0f32, 2.0], &dev)?)?;
        let mut opt = Optimizer::new(OptimizerKind::Adagrad, 0.5, vec![("w".into(), var.clone())])?;
        let loss = (var.as_tensor() * 0.0)?.sum_all()?;
        opt.step(&loss.backward()?)?;
        assert_eq!(var.as_tensor().to_vec1::<f32>()?, vec![1.0, 2.0]);
        Ok(())
    }

    /// Adam against the first steps computed by hand.
    #[test]
    fn adam_matches_hand_computed_reference() -> Result<()> {
        let dev = Device::Cpu;
        let var = Var::from_tensor(&Tensor::new(&[1.5f64, -0.5], &dev)?)?;
        let lr = 0.01;
        let mut opt = Optimizer::new(OptimizerKind::Adam, lr, vec![("w".into(), var.clone())])?;
        let (mut w, mut m, mut s) = ([1.5f64, -0.5], [0f64; 2], [0f64; 2]);
        let (b1, b2) = ADAM_BETAS;
        for t in 1..=4 {
            let loss = var.as_tensor().powf(3.0)?.sum_all()?;
            opt.step(&loss.backward()?)?;
            for i in 0..2 {
                let g = 3.0 * w[i] * w[i];
                m[i] = b1 * m[i] + (1.0 - b1) * g;
                s[i] = b2 * s[i] + (1.0 - b2) * g * g;
                let mh = m[i] / (1.0 - b1.powi(t));
                let sh = s[i] / (1.0 - b2.powi(t));
                w[i] -= lr * mh / (sh.sqrt() + ADAM_EPS);
            }
            let got = var.as_tensor().to_vec1::<f64>()?;
            for i in 0..2 {
                assert!((got[i] - w[i]).abs() < 1e-12, "{got:?} vs {w:?}");
            }
        }
        Ok(())
    }
}
