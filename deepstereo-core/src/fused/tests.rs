//! The fused ops against the candle compositions they replace (values and gradients).

use super::*;
use candle_core::DType;
use candle_core::{Device, Var};

#[test]
fn upsample_crop_matches_composition() -> Result<()> {
    for (s, off, h, w, hi, wi) in [(2, 3, 10, 12, 8, 9), (4, 0, 8, 8, 2, 2), (2, 1, 5, 3, 3, 2)] {
        for dt in [DType::F32, DType::F64] {
            let x = Var::from_tensor(
                &Tensor::randn(0f64, 1., (2, 3, hi, wi), &Device::Cpu)?.to_dtype(dt)?,
            )?;
            let r = Tensor::randn(0f64, 1., (2, 3, h, w), &Device::Cpu)?.to_dtype(dt)?;
            let want = super::upsample_nearest(x.as_tensor(), s)?
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
        let col = Var::from_tensor(&Tensor::randn(0f64, 1., (2, 7, 3, 11), dev)?.to_dtype(dt)?)?;
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

#[test]
fn upsample_cat_equals_the_crops_concatenated() -> Result<()> {
    let dev = &Device::Cpu;
    for dt in [DType::F32, DType::F64] {
        let x0 = Tensor::randn(0f64, 1., (2, 3, 12, 13), dev)?.to_dtype(dt)?;
        let x1 = Tensor::randn(0f64, 1., (2, 2, 7, 7), dev)?.to_dtype(dt)?;
        let x2 = Tensor::randn(0f64, 1., (2, 4, 4, 4), dev)?.to_dtype(dt)?;
        let (h, w) = (10, 11);
        let got = upsample_cat(&[(&x0, 1, 1), (&x1, 2, 3), (&x2, 4, 2)], h, w)?
            .ok_or_else(|| candle_core::Error::msg("upsample_cat did not run"))?;
        let want = Tensor::cat(
            &[
                x0.narrow(2, 1, h)?.narrow(3, 1, w)?,
                upsample_crop(&x1, 2, 3, h, w)?,
                upsample_crop(&x2, 4, 2, h, w)?,
            ],
            1,
        )?; // [2, 9, h, w]
        assert_eq!(got.dims(), want.dims());
        assert_eq!(max_diff(&got, &want)?, 0.0);
    }
    let x = Tensor::zeros((1, 1, 2, 2), DType::F32, &Device::Cpu)?;
    assert!(upsample_cat(&[(&x, 2, 1), (&x, 1, 0)], 4, 4).is_err());
    Ok(())
}

#[test]
fn pooled_stats_equals_front_then_view_stats() -> Result<()> {
    let dev = &Device::Cpu;
    for dt in [DType::F32, DType::F64] {
        let (n, v, c, p) = (3, 4, 5, 37);
        let x = Tensor::rand(0f64, 1., (n, v, 4, p), dev)?.to_dtype(dt)?;
        let e = Tensor::randn(0f64, 1., (n, v, c, p), dev)?.to_dtype(dt)?;
        let Some((_, front)) = pool_front(&x)? else {
            candle_core::bail!("pool_front did not run");
        };
        let got = pooled_stats(&front, &e, &x)?
            .ok_or_else(|| candle_core::Error::msg("pooled_stats did not run"))?;
        let moments =
            view_stats(&e, &x)?.ok_or_else(|| candle_core::Error::msg("view_stats did not run"))?;
        let want = Tensor::cat(&[&front, &moments], 1)?; // [N, 4 + 2C, P]
        assert_eq!(got.dims(), [n, 4 + 2 * c, p]);
        assert_eq!(max_diff(&got, &want)?, 0.0);
        assert!(pooled_stats(&front, &e, &x.narrow(1, 0, 3)?).is_err());
    }
    Ok(())
}

/// [`pool_front`] as candle ops: `(enc [N*V, 7, P], front [N, 4, P])`.
fn pool_front_ops(x: &Tensor) -> Result<(Tensor, Tensor)> {
    let (n, v, _, p) = x.dims4()?;
    let (rgb, a) = (x.narrow(2, 0, 3)?, x.narrow(2, 3, 1)?); // [N, V, 3, P], [N, V, 1, P]
    let asum = a.sum_keepdim(1)?; // [N, 1, 1, P]
    let mean = rgb
        .broadcast_mul(&a)?
        .sum_keepdim(1)?
        .broadcast_div(&(&asum + crate::config::POOL_EPS)?)?; // [N, 1, 3, P]
    let enc = Tensor::cat(&[x, &rgb.broadcast_sub(&mean)?], 2)?.reshape((n * v, 7, p))?;
    let cover = asum.div(&(&asum + 1.0)?)?; // [N, 1, 1, P]
    let front = Tensor::cat(&[&mean, &cover], 2)?.reshape((n, 4, p))?;
    Ok((enc, front))
}

#[test]
fn pool_front_matches_composition_and_its_gradient() -> Result<()> {
    let dev = &Device::Cpu;
    for dt in [DType::F32, DType::F64] {
        let tol = if dt == DType::F32 { 1e-5 } else { 1e-12 };
        let (n, v, p) = (3, 4, 37);
        // Alphas in [0, 2] (weighed by the cue), one view empty at some pixels.
        let mut flat = Tensor::rand(0f64, 2., (n, v, 4, p), dev)?
            .flatten_all()?
            .to_vec1::<f64>()?;
        for i in 0..n {
            flat[((i * v + 1) * 4 + 3) * p..][..5].fill(0.0);
        }
        let x = Var::from_tensor(&Tensor::from_vec(flat, (n, v, 4, p), dev)?.to_dtype(dt)?)?;
        let (r1, r2) = (
            Tensor::randn(0f64, 1., (n * v, 7, p), dev)?.to_dtype(dt)?,
            Tensor::randn(0f64, 1., (n, 4, p), dev)?.to_dtype(dt)?,
        );
        let Some((enc, front)) = pool_front(x.as_tensor())? else {
            candle_core::bail!("pool_front did not run");
        };
        let (enc_w, front_w) = pool_front_ops(x.as_tensor())?;
        assert!(max_diff(&enc, &enc_w)? < tol && max_diff(&front, &front_w)? < tol);
        let Some((enc_u, front_u)) = pool_front(&x.as_tensor().detach())? else {
            candle_core::bail!("pool_front did not run");
        };
        assert_eq!(max_diff(&enc, &enc_u)?, 0.0);
        assert_eq!(max_diff(&front, &front_u)?, 0.0);
        let loss = |e: &Tensor, f: &Tensor| -> Result<Tensor> {
            (e * &r1)?.sum_all()? + (f * &r2)?.sum_all()?
        };
        let got = loss(&enc, &front)?.backward()?;
        let want = loss(&enc_w, &front_w)?.backward()?;
        let (g, w) = (
            got.get(x.as_tensor()).expect("a gradient"),
            want.get(x.as_tensor()).expect("a gradient"),
        );
        let scale = w
            .abs()?
            .max_all()?
            .to_dtype(DType::F64)?
            .to_scalar::<f64>()?;
        let e = max_diff(g, w)?;
        assert!(e < tol * scale.max(1.0), "{dt:?}: gradient differs by {e}");
    }
    Ok(())
}
