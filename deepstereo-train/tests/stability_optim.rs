//! Numerical stability of the optimizers (`deepstereo_train::training::optim`; issue 7, with the
//! geometry and network cases in deepstereo-core's `tests/stability.rs`): huge learning
//! rates, zero gradients on zero accumulators, and exploding gradients, which `grad_norm`
//! must flag as non-finite so that the trainer's guard (tested in `tests/guard.rs`) skips
//! them. Every check prints one markdown row into the same table, `target/stability.md`.
//! Reproduce with
//! `cargo test --release -p deepstereo-train --test stability_optim -- --nocapture`.

#[path = "../../deepstereo-core/tests/stability/fixtures.rs"]
mod fixtures;
#[path = "../../deepstereo-core/tests/stability/table.rs"]
mod table;

use anyhow::Result;
use candle_core::{DType, Device, Tensor, Var};
use deepstereo_core::model::l1_loss;
use deepstereo_core::weights::{init, named_vars};
use deepstereo_train::training::optim::{Optimizer, OptimizerKind, ADAGRAD_EPS, ADAM_EPS};
use fixtures::{inputs, small};
use table::{row, row_text};

fn flat(t: &Tensor) -> Result<Vec<f64>> {
    Ok(t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?)
}

#[test]
fn t01_large_learning_rates() -> Result<()> {
    let cfg = small();
    for (kind, name, eps) in [
        (OptimizerKind::Adagrad, "Adagrad", ADAGRAD_EPS),
        (OptimizerKind::Adam, "Adam", ADAM_EPS),
    ] {
        let lr = 1e3;
        let t = init(&cfg, &Device::Cpu)?;
        let vars = named_vars(&t.varmap);
        let mut opt = Optimizer::new(kind, lr, vars.clone())?;
        let x = inputs(&cfg, 2, 5, cfg.tile, 3, |_, u| u)?;
        let target = Tensor::full(0.25f32, (2, 3, cfg.tile, cfg.tile), &Device::Cpu)?;
        let case = format!("{name}, learning rate 1e3");
        let mut worst = 0f64;
        let mut flagged = 0;
        for step in 0..5 {
            let loss = l1_loss(&t.model.forward(&x)?.image, &target)?;
            let grads = loss.backward()?;
            let norm = opt.grad_norm(&grads)?;
            let loss_v = loss.to_scalar::<f32>()? as f64;
            if !(norm.is_finite() && loss_v.is_finite()) {
                flagged += 1; // the trainer's guard skips such a step
                continue;
            }
            let before: Vec<Vec<f64>> = vars
                .iter()
                .map(|(_, v)| flat(v.as_tensor()))
                .collect::<Result<_>>()?;
            opt.step(&grads)?;
            for ((_, v), w0) in vars.iter().zip(&before) {
                let w1 = flat(v.as_tensor())?;
                assert!(
                    w1.iter().all(|x| x.is_finite()),
                    "{case}: non-finite weight after step {step}"
                );
                if step == 0 {
                    // First step of both: w -= lr * g / (|g| + eps).
                    let g = flat(grads.get(v.as_tensor()).expect("gradient"))?;
                    for i in 0..g.len() {
                        let want = w0[i] - lr * g[i] / (g[i].abs() + eps);
                        let scale = (lr * g[i].abs() / (g[i].abs() + eps)).max(1e-3);
                        worst = worst.max((w1[i] - want).abs() / scale);
                    }
                }
            }
        }
        row(
            &case,
            "first step moves each weight by lr * g / (abs(g) + eps); relative error",
            worst,
        );
        row_text(
            &case,
            "5 steps: weights stay finite; non-finite loss or norm flagged",
            &format!("{flagged} of 5 steps flagged"),
        );
        assert!(worst < 1e-6, "{case}: {worst:e}");
    }
    Ok(())
}

/// A vector variable and an optimizer over it; the loss `sum(w * c)` has gradient `c`.
fn linear(kind: OptimizerKind, n: usize) -> Result<(Var, Optimizer)> {
    let w = Var::from_tensor(&Tensor::from_vec(
        (0..n).map(|i| 1.0 + i as f32).collect::<Vec<_>>(),
        n,
        &Device::Cpu,
    )?)?;
    let opt = Optimizer::new(kind, 0.1, vec![("w".into(), w.clone())])?;
    Ok((w, opt))
}

fn step_with(w: &Var, opt: &mut Optimizer, c: &[f32]) -> Result<f64> {
    let ct = Tensor::from_slice(c, c.len(), &Device::Cpu)?;
    let grads = (w.as_tensor() * ct)?.sum_all()?.backward()?;
    let norm = opt.grad_norm(&grads)?;
    opt.step(&grads)?;
    Ok(norm)
}

#[test]
fn t02_zero_gradients_in_accumulators() -> Result<()> {
    for (kind, name) in [
        (OptimizerKind::Adagrad, "Adagrad"),
        (OptimizerKind::Adam, "Adam"),
    ] {
        let (w, mut opt) = linear(kind, 4)?;
        let w0 = flat(w.as_tensor())?;
        let mut worst = 0f64;
        for _ in 0..3 {
            step_with(&w, &mut opt, &[0.0; 4])?;
            let w1 = flat(w.as_tensor())?;
            worst = w1
                .iter()
                .zip(&w0)
                .fold(worst, |m, (a, b)| m.max((a - b).abs()));
        }
        let state = opt.state();
        assert!(
            state
                .iter()
                .all(|(_, t)| flat(t).unwrap().iter().all(|v| *v == 0.0)),
            "{name}: state moved"
        );
        row(
            &format!("{name}, zero gradients on zero accumulators (3 steps)"),
            "weights unchanged, state stays 0 (exact)",
            worst,
        );
        assert_eq!(worst, 0.0);
        // Gradients whose square underflows f32 (1e-30, a subnormal 1e-45) and a mix with 0.
        let before = flat(w.as_tensor())?;
        step_with(&w, &mut opt, &[1e-30, 1e-45, 0.0, 1.0])?;
        let after = flat(w.as_tensor())?;
        assert!(after.iter().all(|v| v.is_finite()), "{name}: {after:?}");
        let moved = (before[3] - after[3]).abs();
        let case = format!("{name}, gradients 1e-30 and 1e-45 (square underflows f32)");
        let err = after
            .iter()
            .zip(&before)
            .take(3)
            .fold(0f64, |m, (a, b)| m.max((a - b).abs()));
        row(
            &case,
            "finite; weights with g below 1e-29 move by at most lr * 1e-20",
            err,
        );
        // The weight with g = 1: Adagrad's accumulator was 0 (step = lr); Adam is at t = 4.
        let want = match kind {
            OptimizerKind::Adagrad => 0.1,
            OptimizerKind::Adam => {
                0.1 * (0.1 / (1.0 - 0.9f64.powi(4)))
                    / ((1e-3 / (1.0 - 0.999f64.powi(4))).sqrt() + ADAM_EPS)
            }
        };
        assert!(
            err <= 0.1 * 1e-20 * 1.01 && (moved - want).abs() < 2e-6,
            "{name}: {err:e} {moved} vs {want}"
        );
    }
    Ok(())
}

#[test]
fn t03_exploding_gradients() -> Result<()> {
    for (kind, name) in [
        (OptimizerKind::Adagrad, "Adagrad"),
        (OptimizerKind::Adam, "Adam"),
    ] {
        let mut flagged = 0;
        let cases: [(f32, &str); 3] = [(1e20, "1e20"), (f32::INFINITY, "inf"), (f32::NAN, "NaN")];
        for (g, _) in cases {
            let (w, opt) = linear(kind, 3)?;
            let ct = Tensor::from_slice(&[1.0, g, 1.0], 3, &Device::Cpu)?;
            let grads = (w.as_tensor() * ct)?.sum_all()?.backward()?;
            flagged += !opt.grad_norm(&grads)?.is_finite() as usize;
        }
        row_text(
            &format!("{name}, exploding gradients (1e20, inf, NaN)"),
            "grad_norm is non-finite, so the trainer's guard skips the step",
            &format!("{flagged} of 3 flagged"),
        );
        assert_eq!(flagged, 3, "{name}");
        // What the guard prevents: stepping on a finite 1e20 gradient (its square is inf
        // in f32) leaves an infinite accumulator that freezes the weight for good.
        let (w, mut opt) = linear(kind, 3)?;
        step_with(&w, &mut opt, &[1.0, 1e20, 1.0])?;
        let before = flat(w.as_tensor())?;
        step_with(&w, &mut opt, &[1.0, 1.0, 1.0])?;
        let after = flat(w.as_tensor())?;
        assert!(after.iter().all(|v| v.is_finite()));
        let frozen = before[1] == after[1];
        row_text(
            &format!("{name}, one unguarded step on a 1e20 gradient"),
            "weights stay finite; does that weight still move on the next step?",
            if frozen {
                "no: frozen (infinite second moment)"
            } else {
                "yes"
            },
        );
    }
    Ok(())
}
