use super::*;
use crate::camera::{Intrinsics, WorldToCamera};
use crate::mpi::tests::values;
use crate::mpi::{Mpi, OPAQUE_T};
use candle_core::{Device, Var};
use glam::DMat3;

fn camera(w: u32, h: u32, centre: DVec3, angle: f64) -> Camera {
    let k = Intrinsics::pinhole(30.0, 31.0, w as f64 / 2.0 + 0.3, h as f64 / 2.0 - 0.2, w, h);
    let rotation = DMat3::from_rotation_y(angle) * DMat3::from_rotation_x(0.5 * angle);
    Camera::global(
        k,
        WorldToCamera {
            rotation,
            translation: -(rotation * centre),
        },
    )
}

/// Random layers: colours `[D, 3, N]` in [-0.1, 1.1) (some clamped) and a selection
/// `[D, N]` summing to 1 with some planes empty.
fn layers(d: usize, n: usize) -> (Vec<f32>, Vec<f32>) {
    let colours = values(d * 3 * n, 1).iter().map(|c| c * 1.2 - 0.1).collect();
    let mut sel = values(d * n, 2);
    for (i, s) in sel.iter_mut().enumerate() {
        if i % 5 == 0 {
            *s = 0.0;
        }
    }
    for p in 0..n {
        let sum: f32 = (0..d).map(|z| sel[z * n + p]).sum();
        (0..d).for_each(|z| sel[z * n + p] /= sum);
    }
    (colours, sel)
}

#[test]
fn the_warped_render_equals_the_cpu_renderer() -> Result<()> {
    let (w, h, d) = (24usize, 18usize, 6usize);
    let n = w * h;
    let (colours, sel) = layers(d, n);
    let inv = crate::geometry::inverse_depths(1.5, f64::INFINITY, d);
    let reference = camera(w as u32, h as u32, DVec3::ZERO, 0.0);
    let mpi = Mpi::from_layers(reference, inv.clone(), &colours, &sel)
        .map_err(candle_core::Error::msg)?;
    let dev = Device::Cpu;
    let s = Tensor::from_vec(sel.clone(), (1, d, n), &dev)?;
    let c = Tensor::from_vec(colours.clone(), (1, d, 3, n), &dev)?;
    for (centre, angle) in [
        (DVec3::new(0.1, -0.05, 0.02), 0.0),
        (DVec3::new(-0.15, 0.1, -0.1), 0.05),
    ] {
        let cam = camera(w as u32, h as u32, centre, angle);
        let plan = WarpPlan::new(&reference, &inv, (0, 0, w, h), &cam, (0, 0, w, h));
        assert!(
            plan.count() > n / 4 && plan.count() < n,
            "{} pixels count",
            plan.count()
        );
        let (index, weight, _) = plan_tensors(&[&plan], n, DType::F32, &dev)?;
        let out = render_warped(&s, &c, &index, &weight)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let (want, _) = mpi.render(&cam);
        for p in (0..n).filter(|&p| plan.mask[p] > 0.0) {
            for ch in 0..3 {
                let (a, b) = (out[ch * n + p], want.data[p * 3 + ch]);
                assert!(
                    (a - b).abs() < OPAQUE_T + 1e-5,
                    "pixel {p} channel {ch}: {a} vs {b}"
                );
            }
        }
    }
    Ok(())
}

#[test]
fn a_tile_inside_an_image_samples_its_own_pixels() -> Result<()> {
    // The reference tile at (5, 3) of a larger image: indices are the tile's.
    let (tw, th, d) = (8usize, 6usize, 3usize);
    let reference = camera(40, 30, DVec3::ZERO, 0.0);
    let inv = crate::geometry::inverse_depths(2.0, 10.0, d);
    let plan = WarpPlan::new(&reference, &inv, (5, 3, tw, th), &reference, (5, 3, tw, th));
    // At its own camera every pixel centre samples itself with weight 1, but the last
    // column and row have no right or lower texel inside the tile.
    assert_eq!(plan.count(), (tw - 1) * (th - 1));
    for p in (0..tw * th).filter(|&p| plan.mask[p] > 0.0) {
        for z in 0..d {
            assert_eq!(plan.index[(z * 4) * tw * th + p], p as u32);
            assert!((plan.weight[(z * 4) * tw * th + p] - 1.0).abs() < 1e-6);
        }
    }
    Ok(())
}

#[test]
fn gradients_match_finite_differences() -> Result<()> {
    let (w, h, d) = (6usize, 5usize, 4usize);
    let n = w * h;
    let dev = Device::Cpu;
    let logits: Vec<f64> = values(d * n, 7).iter().map(|&v| 3.0 * v as f64).collect();
    let cols: Vec<f64> = values(d * 3 * n, 8)
        .iter()
        .map(|&v| 0.05 + 0.9 * v as f64)
        .collect();
    let reference = camera(w as u32, h as u32, DVec3::ZERO, 0.0);
    let inv = crate::geometry::inverse_depths(1.0, 8.0, d);
    let cam = camera(w as u32, h as u32, DVec3::new(0.04, 0.03, 0.0), 0.0);
    let plan = WarpPlan::new(&reference, &inv, (0, 0, w, h), &cam, (0, 0, w, h));
    assert!(plan.count() > 0);
    let (index, weight, mask) = plan_tensors(&[&plan], n, DType::F64, &dev)?;
    let probe = Tensor::from_vec(
        values(3 * n, 9)
            .iter()
            .map(|&v| v as f64)
            .collect::<Vec<_>>(),
        (1, 3, n),
        &dev,
    )?;
    let loss = |l: &Tensor, c: &Tensor| -> Result<Tensor> {
        let s = candle_nn::ops::softmax(l, 1)?;
        let out = render_warped(&s, c, &index, &weight)?;
        out.mul(&probe)?
            .broadcast_mul(&mask.unsqueeze(1)?)?
            .sum_all()
    };
    let lv = Var::from_vec(logits.clone(), (1, d, n), &dev)?;
    let cv = Var::from_vec(cols.clone(), (1, d, 3, n), &dev)?;
    let grads = loss(lv.as_tensor(), cv.as_tensor())?.backward()?;
    let gl = grads
        .get(lv.as_tensor())
        .expect("logit gradient")
        .flatten_all()?
        .to_vec1::<f64>()?;
    let gc = grads
        .get(cv.as_tensor())
        .expect("colour gradient")
        .flatten_all()?
        .to_vec1::<f64>()?;
    let eval = |l: &[f64], c: &[f64]| -> Result<f64> {
        let l = Tensor::from_vec(l.to_vec(), (1, d, n), &dev)?;
        let c = Tensor::from_vec(c.to_vec(), (1, d, 3, n), &dev)?;
        loss(&l, &c)?.to_scalar::<f64>()
    };
    // Central differences of every `step`-th entry of `base` against `grad`; returns
    // how many were checked and how many are non-zero.
    let check = |name: &str,
                 base: &[f64],
                 grad: &[f64],
                 step: usize,
                 eval_at: &dyn Fn(&[f64]) -> Result<f64>|
     -> Result<(usize, usize)> {
        let eps = 1e-6;
        let (mut checked, mut nonzero) = (0, 0);
        for i in (0..base.len()).step_by(step) {
            let (mut up, mut down) = (base.to_vec(), base.to_vec());
            up[i] += eps;
            down[i] -= eps;
            let fd = (eval_at(&up)? - eval_at(&down)?) / (2.0 * eps);
            assert!(
                (fd - grad[i]).abs() < 1e-6 + 1e-5 * fd.abs(),
                "{name} {i}: {fd} vs {}",
                grad[i]
            );
            checked += 1;
            nonzero += usize::from(fd.abs() > 1e-4);
        }
        Ok((checked, nonzero))
    };
    let (c1, n1) = check("logit", &logits, &gl, 7, &|l| eval(l, &cols))?;
    let (c2, n2) = check("colour", &cols, &gc, 11, &|c| eval(&logits, c))?;
    let (checked, nonzero) = (c1 + c2, n1 + n2);
    assert!(
        nonzero > checked / 4,
        "{nonzero} of {checked} derivatives are non-zero"
    );
    Ok(())
}

#[test]
fn the_masked_loss_counts_only_masked_pixels() -> Result<()> {
    let dev = Device::Cpu;
    let pred = Tensor::from_vec(vec![0.5f32, 1.0, 0.5, 1.0, 0.5, 1.0], (1, 3, 2), &dev)?;
    let target = Tensor::zeros((1, 3, 2), DType::F32, &dev)?;
    let mask = Tensor::from_vec(vec![1f32, 0.0], (1, 2), &dev)?;
    assert!((masked_l1(&pred, &target, &mask)?.to_scalar::<f32>()? - 0.5).abs() < 1e-7);
    let none = Tensor::zeros((1, 2), DType::F32, &dev)?;
    assert_eq!(masked_l1(&pred, &target, &none)?.to_scalar::<f32>()?, 0.0);
    Ok(())
}
