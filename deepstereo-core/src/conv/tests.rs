//! Checks the kernels against candle's conv2d and against finite differences.

use super::Conv2d;
use candle_core::{DType, Device, Module, Result, Tensor, Var};

/// `(n, cin, h, w, cout, kh, kw)`: square and `(k, 1)` kernels, 1x1 grouped and in place,
/// images grouped into chunks and images cut into row chunks.
const SHAPES: [(usize, usize, usize, usize, usize, usize, usize); 17] = [
    (2, 12, 14, 17, 32, 5, 5),
    (1, 16, 10, 12, 48, 5, 5),
    (2, 5, 20, 21, 13, 3, 3),
    (2, 24, 12, 20, 7, 5, 5),
    (2, 24, 12, 26, 7, 5, 5),
    (2, 4, 22, 22, 7, 3, 3),
    (3, 7, 5, 9, 8, 1, 1),
    (3, 5, 9, 11, 7, 3, 3),
    (2, 4, 8, 8, 6, 5, 5),
    (1, 2, 30, 30, 3, 5, 5),
    (40, 3, 6, 6, 4, 3, 3),
    (2, 6, 10, 7, 4, 3, 1),
    (2, 6, 34, 64, 5, 3, 1),
    (1, 3, 40, 37, 5, 3, 3),
    (2, 8, 12, 5, 3, 1, 1),
    (1, 4, 30, 30, 3, 1, 1),
    (20, 4, 4, 4, 3, 1, 1),
];

fn conv(
    shape: (usize, usize, usize, usize, usize, usize, usize),
    dt: DType,
) -> Result<(Conv2d, Tensor)> {
    let (n, cin, h, w, cout, kh, kw) = shape;
    let dev = &Device::Cpu;
    let seed = [n, cin, h, w, cout, kh, kw]
        .iter()
        .fold(17u64, |s, &v| s.wrapping_mul(31).wrapping_add(v as u64));
    let weight = Var::from_tensor(&normal((cout, cin, kh, kw), seed, dev)?.to_dtype(dt)?)?;
    let bias = Var::from_tensor(&normal(cout, seed + 1, dev)?.to_dtype(dt)?)?;
    let x = normal((n, cin, h, w), seed + 2, dev)?.to_dtype(dt)?;
    let conv = Conv2d {
        weight: weight.as_tensor().clone(),
        bias: bias.as_tensor().clone(),
    };
    Ok((conv, x))
}

/// Standard normal values of `shape`, the same for the same `seed` (Box-Muller on a
/// 64-bit LCG; candle's CPU generator takes no seed). Fresh random data now and then put a
/// ReLU input within f32 rounding of 0, where the two convolutions' masks, and so their
/// gradients, can differ.
fn normal(shape: impl Into<candle_core::Shape>, seed: u64, dev: &Device) -> Result<Tensor> {
    let shape = shape.into();
    let mut s = seed;
    let mut uniform = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let v: Vec<f64> = (0..shape.elem_count())
        .map(|_| {
            let (u1, u2) = (uniform(), uniform());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        })
        .collect();
    Tensor::from_vec(v, shape, dev)
}

/// max |a - b| / max(max |b|, 1).
fn rel_err(a: &Tensor, b: &Tensor) -> Result<f64> {
    assert_eq!(a.dims(), b.dims());
    let diff = (a - b)?
        .abs()?
        .max_all()?
        .to_dtype(DType::F64)?
        .to_scalar::<f64>()?;
    let scale = b
        .abs()?
        .max_all()?
        .to_dtype(DType::F64)?
        .to_scalar::<f64>()?;
    Ok(diff / scale.max(1.0))
}

fn tol(dt: DType) -> f64 {
    if dt == DType::F32 {
        1e-4
    } else {
        1e-10
    }
}

#[test]
fn forward_matches_candle() -> Result<()> {
    for dt in [DType::F32, DType::F64] {
        for shape in SHAPES {
            let (conv, x) = conv(shape, dt)?;
            let want = conv.forward_reference(&x)?;
            let e = rel_err(&conv.forward(&x)?, &want)?;
            assert!(e < tol(dt), "{shape:?} {dt:?}: {e}");
            let e = rel_err(&conv.forward_relu(&x)?, &want.relu()?)?;
            assert!(e < tol(dt), "relu {shape:?} {dt:?}: {e}");
        }
    }
    Ok(())
}

/// Gradients of `sum(f(x) * r)` for x, weight and bias.
fn grads(x: &Var, conv: &Conv2d, f: impl Fn(&Tensor) -> Result<Tensor>) -> Result<[Tensor; 3]> {
    let y = f(x.as_tensor())?;
    let r = Tensor::ones_like(&y)?.cumsum(3)?.sin()?; // fixed, varied weights
    let g = (y * r)?.sum_all()?.backward()?;
    let get = |t: &Tensor| g.get(t).cloned().expect("missing gradient");
    Ok([get(x.as_tensor()), get(&conv.weight), get(&conv.bias)])
}

#[test]
fn gradients_match_candle() -> Result<()> {
    for dt in [DType::F32, DType::F64] {
        for shape in SHAPES {
            let (conv, x) = conv(shape, dt)?;
            let x = Var::from_tensor(&x)?;
            let want = grads(&x, &conv, |x| conv.forward_reference(x))?;
            let got = grads(&x, &conv, |x| conv.forward(x))?;
            let want_relu = grads(&x, &conv, |x| conv.forward_reference(x)?.relu())?;
            let got_relu = grads(&x, &conv, |x| conv.forward_relu(x))?;
            for (i, name) in ["x", "weight", "bias"].iter().enumerate() {
                let e = rel_err(&got[i], &want[i])?;
                assert!(e < tol(dt), "{name} {shape:?} {dt:?}: {e}");
                let e = rel_err(&got_relu[i], &want_relu[i])?;
                assert!(e < tol(dt), "relu {name} {shape:?} {dt:?}: {e}");
            }
        }
    }
    Ok(())
}

#[test]
fn input_without_gradient() -> Result<()> {
    let (conv, x) = conv((4, 3, 7, 7, 5, 3, 3), DType::F32)?;
    let w = Var::from_tensor(&conv.weight)?;
    let conv = Conv2d {
        weight: w.as_tensor().clone(),
        bias: conv.bias.clone(),
    };
    let g = conv.forward_relu(&x)?.sum_all()?.backward()?;
    assert!(g.get(&x).is_none());
    let gw = g.get(w.as_tensor()).expect("weight gradient");
    let want = conv.forward_reference(&x)?.relu()?.sum_all()?.backward()?;
    let e = rel_err(gw, want.get(w.as_tensor()).unwrap())?;
    assert!(e < 1e-4, "{e}");
    Ok(())
}

/// `loss(x, conv)` with argument `which` (0 input, 1 weight, 2 bias) replaced by `t`.
fn replaced(
    which: usize,
    t: Tensor,
    x: &Tensor,
    conv: &Conv2d,
    loss: impl Fn(&Tensor, &Conv2d) -> Result<f64>,
) -> Result<f64> {
    match which {
        0 => loss(&t, conv),
        1 => loss(
            x,
            &Conv2d {
                weight: t,
                bias: conv.bias.clone(),
            },
        ),
        _ => loss(
            x,
            &Conv2d {
                weight: conv.weight.clone(),
                bias: t,
            },
        ),
    }
}

#[test]
fn finite_differences_f64() -> Result<()> {
    for shape in [
        (2, 3, 6, 5, 2, 3, 3),
        (2, 3, 7, 4, 2, 3, 1),
        (2, 3, 3, 4, 2, 1, 1),
    ] {
        let (conv, x) = conv(shape, DType::F64)?;
        let x = Var::from_tensor(&x)?;
        let r = Tensor::randn(0f64, 1., conv.forward(&x)?.shape(), &Device::Cpu)?;
        let loss = |x: &Tensor, c: &Conv2d| -> Result<f64> {
            (c.forward(x)? * &r)?.sum_all()?.to_scalar::<f64>()
        };
        let g = (conv.forward(x.as_tensor())? * &r)?.sum_all()?.backward()?;
        let eps = 1e-4;
        // Perturbs element i of one of (x, weight, bias).
        for which in 0..3 {
            let base = [x.as_tensor(), &conv.weight, &conv.bias][which];
            let analytic: Vec<f64> = g.get(base).unwrap().flatten_all()?.to_vec1()?;
            let v: Vec<f64> = base.flatten_all()?.to_vec1()?;
            for i in 0..v.len() {
                let at = |d: f64| -> Result<f64> {
                    let mut p = v.clone();
                    p[i] += d;
                    let t = Tensor::from_vec(p, base.shape(), &Device::Cpu)?;
                    replaced(which, t, x.as_tensor(), &conv, loss)
                };
                let fd = (at(eps)? - at(-eps)?) / (2.0 * eps);
                let e = (fd - analytic[i]).abs() / analytic[i].abs().max(1.0);
                assert!(
                    e < 1e-7,
                    "{shape:?} arg {which} element {i}: fd {fd} vs {}",
                    analytic[i]
                );
            }
        }
    }
    Ok(())
}

/// A tensor used several times (conv inputs, one a strided view, and skip connections)
/// gets all its gradients added.
#[test]
fn gradient_accumulates_through_skip() -> Result<()> {
    let (c1, x) = conv((3, 4, 9, 9, 6, 3, 3), DType::F64)?;
    let (c2, _) = conv((3, 6, 7, 7, 6, 3, 3), DType::F64)?;
    let x = Var::from_tensor(&x)?;
    let run = |reference: bool| -> Result<Vec<Tensor>> {
        let f = |c: &Conv2d, t: &Tensor| {
            if reference {
                c.forward_reference(t)?.relu()
            } else {
                c.forward_relu(t)
            }
        };
        let a = f(&c1, x.as_tensor())?; // [3, 6, 7, 7]
        let b = (f(&c2, &a.narrow(3, 1, 6)?)? + a.narrow(2, 1, 5)?.narrow(3, 2, 4)?)?; // [3, 6, 5, 4]
        let skip = x
            .as_tensor()
            .narrow(1, 0, 1)?
            .narrow(2, 0, 1)?
            .narrow(3, 2, 5)?; // [3, 1, 1, 5]
        let out = c2.forward(&a)?.narrow(2, 0, 1)?.broadcast_add(&skip)?; // [3, 6, 1, 5]
        let loss = (b.sqr()?.sum_all()? + out.sin()?.sum_all()?)?;
        let g = loss.backward()?;
        Ok([x.as_tensor(), &c1.weight, &c1.bias, &c2.weight, &c2.bias]
            .iter()
            .map(|t| g.get(t).unwrap().clone())
            .collect())
    };
    for (got, want) in run(false)?.iter().zip(&run(true)?) {
        let e = rel_err(got, want)?;
        assert!(e < 1e-10, "{e}");
    }
    Ok(())
}

/// Gradients do not depend on which thread ran which chunk.
#[test]
fn gradients_are_deterministic() -> Result<()> {
    let (conv, x) = conv((64, 8, 20, 20, 8, 3, 3), DType::F32)?;
    let x = Var::from_tensor(&x)?;
    let first = grads(&x, &conv, |x| conv.forward_relu(x))?;
    for _ in 0..3 {
        let again = grads(&x, &conv, |x| conv.forward_relu(x))?;
        for (a, b) in first.iter().zip(&again) {
            assert_eq!(
                a.flatten_all()?.to_vec1::<f32>()?,
                b.flatten_all()?.to_vec1::<f32>()?
            );
        }
    }
    Ok(())
}

/// The model's own layer shapes (both presets, 2 planes, batch 1, render tile sizes) run
/// the AVX2 kernels on a CPU that has them, and agree with the im2col + gemm path:
/// forward (with and without ReLU) and all three gradients.
#[test]
fn direct_kernels_match_im2col_on_model_layers() {
    use super::im2col::Geom;
    use super::{direct, direct_cv, direct_grad, kernels, plan, winograd};
    use crate::config::Config;
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut rand = |len: usize| -> Vec<f32> {
        (0..len)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 40) as f32 / (1u64 << 23) as f32 - 1.0
            })
            .collect()
    };
    let max_rel = |a: &[f32], b: &[f32]| {
        let scale = b.iter().fold(1f32, |m, v| m.max(v.abs()));
        a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale
    };
    let (mut ran, mut ran_cv, mut ran_wino, mut ran_split) = (0, 0, 0, 0);
    for cfg in [Config::tiny(), Config::paper()] {
        let tile = if cfg.name == "paper" { 16 } else { 24 };
        for l in cfg.layers() {
            let k = l.kernel;
            let g = if l.name.starts_with("select.depth") {
                let (h, w) = (2 + k - 1, tile * tile);
                Geom {
                    n: 1,
                    cin: l.in_channels,
                    h,
                    w,
                    cout: l.out_channels,
                    kh: k,
                    kw: 1,
                }
            } else {
                let s = (l.out_size * tile / cfg.tile).max(1) + k - 1;
                Geom {
                    n: 2,
                    cin: l.in_channels,
                    h: s,
                    w: s,
                    cout: l.out_channels,
                    kh: k,
                    kw: k,
                }
            };
            let x = rand(g.n * g.cin * g.hw());
            let w = rand(g.cout * g.k());
            let b = rand(g.cout);
            for relu in [false, true] {
                if direct::applies(&g) {
                    ran += 1;
                    ran_cv += usize::from(direct_cv::applies(&g));
                    let want = kernels::forward(&g, &x, &w, &b, relu);
                    // The dispatched kernel, and each kernel that takes the layer.
                    let mut paths = vec![
                        ("best", plan::forward_f32(&g, &x, &w, &b, relu)),
                        ("pixels", direct::forward(&g, &x, &w, &b, relu)),
                    ];
                    if direct_cv::applies(&g) {
                        paths.push(("channels", direct_cv::forward(&g, &x, &w, &b, relu)));
                    }
                    if winograd::applies(&g) {
                        ran_wino += 1;
                        paths.push(("winograd", winograd::forward(&g, &x, &w, &b, relu)));
                    }
                    for (path, got) in paths {
                        let e = max_rel(&got, &want);
                        assert!(e < 1e-5, "{} forward ({path}) {g:?}: {e}", l.name);
                    }
                }
                if plan::backward(&g, true) == plan::Backward::InputByWinograd {
                    ran_split += 1;
                    let y = kernels::forward(&g, &x, &w, &b, relu);
                    let dy = rand(y.len());
                    let got = direct_grad::input_grad(&g, &w, &y, &dy, relu);
                    let want = kernels::backward(&g, &x, &w, &y, &dy, relu, true, false);
                    let e = max_rel(&got, want.dx.as_ref().expect("dx"));
                    assert!(e < 1e-5, "{} dx (Winograd) {g:?} relu {relu}: {e}", l.name);
                }
                if plan::direct_grad_applies(&g) {
                    let y = kernels::forward(&g, &x, &w, &b, relu);
                    let dy = rand(y.len());
                    let (dx, dw, db) = direct_grad::backward(&g, &x, &w, &y, &dy, relu, true);
                    let want = kernels::backward(&g, &x, &w, &y, &dy, relu, true, true);
                    let dx = dx.expect("dx asked for");
                    for (name, a, b) in [
                        ("dx", &dx, want.dx.as_ref().expect("dx")),
                        ("dw", &dw, &want.dw),
                        ("db", &db, &want.db),
                    ] {
                        let e = max_rel(a, b);
                        assert!(e < 1e-5, "{} {name} {g:?} relu {relu}: {e}", l.name);
                    }
                }
            }
        }
    }
    if crate::cpu::avx2_fma_available() {
        assert!(
            ran >= 40 && ran_cv >= 10 && ran_wino >= 10 && ran_split >= 10,
            "AVX2 kernels ran on {ran} layers ({ran_cv} channel-vectorised, {ran_wino} Winograd, \
             {ran_split} Winograd input gradients)"
        );
    }
}

/// Finite differences on the AVX2 path itself (f32): directional derivatives of
/// `sum(conv(x) * r)` along random directions of x, weight and bias against the
/// gradients' dot products, for a pixel-vectorised and a channel-vectorised layer (the
/// ReLU's mask is checked against candle above; its kinks would blur differences here).
#[test]
fn direct_path_finite_differences_f32() -> Result<()> {
    use super::{direct, direct_cv, im2col::Geom, plan};
    for shape in [(2, 5, 9, 20, 7, 3, 3), (1, 16, 10, 12, 32, 5, 5)] {
        let (n, cin, h, w, cout, kh, kw) = shape;
        let g = Geom {
            n,
            cin,
            h,
            w,
            cout,
            kh,
            kw,
        };
        if !direct::applies(&g) {
            return Ok(()); // a CPU without AVX2 / FMA: the im2col path is tested above
        }
        assert!(
            plan::direct_grad_applies(&g) || direct_cv::applies(&g),
            "{shape:?}"
        );
        let (conv, x) = conv(shape, DType::F32)?;
        let x = Var::from_tensor(&x)?;
        let r = Tensor::randn(0f32, 1., conv.forward(&x)?.shape(), &Device::Cpu)?;
        // The loss is linear in each argument, so a large step has no truncation error;
        // it is summed in f64 so that only the convolution's own f32 rounding remains.
        let r64 = r.to_dtype(DType::F64)?;
        let loss = |x: &Tensor, c: &Conv2d| -> Result<f64> {
            (c.forward(x)?.to_dtype(DType::F64)? * &r64)?
                .sum_all()?
                .to_scalar::<f64>()
        };
        let g = (conv.forward(x.as_tensor())? * &r)?.sum_all()?.backward()?;
        let eps = 0.1;
        for which in 0..3 {
            let base = [x.as_tensor(), &conv.weight, &conv.bias][which];
            let v = Tensor::randn(0f32, 1., base.shape(), &Device::Cpu)?;
            let grad = g.get(base).unwrap().to_dtype(DType::F64)?;
            let analytic = (&grad * v.to_dtype(DType::F64)?)?
                .sum_all()?
                .to_scalar::<f64>()?;
            let at = |d: f64| -> Result<f64> {
                replaced(which, (base + (&v * d)?)?, x.as_tensor(), &conv, loss)
            };
            let fd = (at(eps)? - at(-eps)?) / (2.0 * eps);
            // Relative to the derivative's typical size: for a random direction `v`,
            // `grad . v` has standard deviation `|grad|`, and a draw where the sum cancels
            // to near zero (a few in a thousand) must not turn the loss's own f32
            // rounding into a failure (the direction is drawn unseeded).
            let scale = grad.sqr()?.sum_all()?.sqrt()?.to_scalar::<f64>()?;
            let e = (fd - analytic).abs() / analytic.abs().max(scale).max(1.0);
            assert!(e < 2e-3, "{shape:?} arg {which}: fd {fd} vs {analytic}");
        }
    }
    Ok(())
}

/// Winograd on shapes the model's layers miss: sizes that leave partial tiles on both
/// edges, images of several work units, more input channels than a tap block (128), both
/// kernel sizes, with and without ReLU, against the im2col path; large inputs (1e4) too,
/// with the error relative to the outputs' scale.
#[test]
fn winograd_matches_im2col_on_edge_shapes() {
    use super::im2col::Geom;
    use super::{kernels, winograd};
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut rand = |len: usize, scale: f32| -> Vec<f32> {
        (0..len)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                ((state >> 40) as f32 / (1u64 << 23) as f32 - 1.0) * scale
            })
            .collect()
    };
    let shapes = [
        // (n, cin, h, w, cout, k)
        (2, 9, 8, 13, 32, 3),
        (1, 8, 7, 7, 32, 5),
        (1, 130, 12, 11, 32, 5),
        (1, 16, 40, 37, 48, 3),
        (3, 20, 29, 26, 96, 5),
        (1, 24, 6, 50, 32, 3),
    ];
    let mut ran = 0;
    for (n, cin, h, w, cout, k) in shapes {
        let g = Geom {
            n,
            cin,
            h,
            w,
            cout,
            kh: k,
            kw: k,
        };
        // Called directly: some of these shapes save too little for `applies` to pick it.
        if !crate::cpu::avx2_fma_available() {
            return;
        }
        for (scale, relu) in [(1.0, false), (1.0, true), (1e4, false)] {
            ran += 1;
            let x = rand(g.n * g.cin * g.hw(), scale);
            let wt = rand(g.cout * g.k(), 0.3);
            let b = rand(g.cout, 0.1);
            let want = kernels::forward(&g, &x, &wt, &b, relu);
            let got = winograd::forward(&g, &x, &wt, &b, relu);
            let top = want.iter().fold(1f32, |m, v| m.max(v.abs()));
            let e = got
                .iter()
                .zip(&want)
                .fold(0f32, |m, (a, b)| m.max((a - b).abs()))
                / top;
            assert!(e < 1e-5, "{g:?} scale {scale} relu {relu}: {e}");
        }
    }
    assert_eq!(ran, 3 * shapes.len());
}
