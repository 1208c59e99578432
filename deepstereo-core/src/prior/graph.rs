//! The prior inside a training graph: the network's selection reweighed by a fixed grid
//! with gradients to the network (`tune`'s fine-tune through a fitted prior).
//!
//! For a tile's selection `s` `[B, D, H, W]` and log-weights `b` of its plane points
//! ([`PriorGrid::tile_log_weights`]), the reweighed selection is
//! `s'_z = softmax_z(g ln(s_z + eps) + b_z)`, which is `s_z^g exp(b_z) / sum_k s_k^g
//! exp(b_k)` ([`super::reweigh_with`]) up to `eps` ([`LOG_FLOOR`]), and the colour
//! `C = sum_z s'_z c_z`. `eps` keeps `ln` and its derivative `1 / (s + eps)` finite where
//! a selection underflows to 0 (its gradient `ds` is then 0 as well).

use super::{PriorGrid, MAX_LOG_WEIGHT};
use crate::camera::Camera;
use candle_core::{Result, Tensor};

/// The floor added to the selection before its logarithm: `ln 1e-30 = -69`, far below
/// any plane a selection resolves, and `exp(g * -69)` is 0 beside them.
pub const LOG_FLOOR: f32 = 1e-30;

impl PriorGrid {
    /// The log-weights `b(x_z)` (within [`MAX_LOG_WEIGHT`]) of the `th` x `tw` tile at
    /// `(x0, y0)` of `camera` on the planes `inv_depths`: `[D, th * tw]`, plane-major,
    /// row-major within a plane (as a selection `[D, th, tw]` is laid out).
    pub fn tile_log_weights(
        &self,
        camera: &Camera,
        inv_depths: &[f64],
        origin: (usize, usize),
        (th, tw): (usize, usize),
    ) -> Vec<f32> {
        let (d, n) = (inv_depths.len(), th * tw);
        let cells = self.locate_tile(camera, inv_depths, origin, (th, tw));
        let mut out = vec![0f32; d * n];
        for (q, row) in cells.chunks_exact(d.max(1)).enumerate() {
            for (z, &c) in row.iter().enumerate() {
                out[z * n + q] = self.value(c).clamp(-MAX_LOG_WEIGHT, MAX_LOG_WEIGHT);
            }
        }
        out
    }
}

/// The selection `selection` `[B, D, H, W]` reweighed by the log-weights `bias` (same
/// shape) at sharpness `sharpness`, and the colour it composites from `colours` `[B, D,
/// 3, H, W]`: `(image [B, 3, H, W], selection [B, D, H, W])`, differentiable in
/// `selection` and `colours`.
pub fn reweigh_graph(
    selection: &Tensor,
    colours: &Tensor,
    bias: &Tensor,
    sharpness: f32,
) -> Result<(Tensor, Tensor)> {
    let (b, d, h, w) = selection.dims4()?;
    if bias.dims() != selection.dims() || colours.dims() != [b, d, 3, h, w] {
        candle_core::bail!(
            "a prior's log-weights {:?} and colours {:?} against a selection {:?}",
            bias.dims(),
            colours.dims(),
            selection.dims()
        );
    }
    let logits = ((selection + LOG_FLOOR as f64)?.log()? * sharpness as f64)?.add(bias)?;
    let s = candle_nn::ops::softmax(&logits, 1)?; // [B, D, H, W]
    let image = colours
        .broadcast_mul(&s.unsqueeze(2)?)? // [B, D, 3, H, W]
        .sum(1)?; // [B, 3, H, W]
    Ok((image, s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Intrinsics, WorldToCamera};
    use candle_core::{Device, Var};
    use glam::{DMat3, DVec3};

    fn grid() -> PriorGrid {
        let mut g = PriorGrid::zeros(DVec3::new(-2.0, -2.0, 1.0), DVec3::new(2.0, 2.0, 5.0), 5)
            .expect("grid");
        for (i, v) in g.values.iter_mut().enumerate() {
            *v = ((i * 37 % 11) as f32 - 5.0) * 0.6;
        }
        g.sharpness = 1.7;
        g
    }

    fn camera() -> Camera {
        let pose =
            WorldToCamera::new_checked(DMat3::from_rotation_y(0.2), DVec3::new(0.1, -0.2, 0.0))
                .expect("pose");
        Camera::global(Intrinsics::pinhole(20.0, 20.0, 6.0, 5.0, 12, 10), pose)
    }

    /// The graph's image and selection equal the renderer's `apply_tile` on the same
    /// tile (a selection with underflowed planes included).
    #[test]
    fn the_graph_reweighs_as_the_renderer_does() -> anyhow::Result<()> {
        let (g, cam) = (grid(), camera());
        let inv = crate::geometry::inverse_depths(1.5, 4.5, 6);
        let (d, t, origin) = (inv.len(), 4, (3, 2));
        let mut rng = crate::synth::Rng::new(3);
        let mut sel = vec![0f32; d * t * t];
        for q in 0..t * t {
            let l: Vec<f64> = (0..d).map(|_| rng.sym(4.0)).collect();
            let sum: f64 = l.iter().map(|x| x.exp()).sum();
            for z in 0..d {
                sel[z * t * t + q] = (l[z].exp() / sum) as f32;
            }
        }
        sel[5] = 0.0; // an underflowed plane
        let col: Vec<f32> = (0..d * 3 * t * t).map(|_| rng.unit() as f32).collect();
        let mut want_s = sel.clone();
        let want = g.apply_tile(&cam, &inv, origin, t, &col, &mut want_s);
        let bias = g.tile_log_weights(&cam, &inv, origin, (t, t));
        let dev = Device::Cpu;
        let (image, s) = reweigh_graph(
            &Tensor::from_slice(&sel, (1, d, t, t), &dev)?,
            &Tensor::from_slice(&col, (1, d, 3, t, t), &dev)?,
            &Tensor::from_slice(&bias, (1, d, t, t), &dev)?,
            g.sharpness,
        )?;
        let got = image.flatten_all()?.to_vec1::<f32>()?;
        let got_s = s.flatten_all()?.to_vec1::<f32>()?;
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() < 2e-6, "{a} vs {b}");
        }
        for (a, b) in got_s.iter().zip(&want_s) {
            assert!((a - b).abs() < 2e-6, "{a} vs {b}");
        }
        Ok(())
    }

    /// The gradient of `sum(image * w)` by the selection's logits matches central
    /// differences (f64 graph), through the softmax, the floor and the reweighing.
    #[test]
    fn the_gradient_matches_finite_differences() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let (b, d, h, w) = (1, 5, 2, 3);
        let mut rng = crate::synth::Rng::new(9);
        let mut vals = |n: usize, s: f64| -> Vec<f64> { (0..n).map(|_| rng.sym(s)).collect() };
        let logits = Var::from_vec(vals(b * d * h * w, 3.0), (b, d, h, w), &dev)?;
        let colours = Tensor::from_vec(vals(b * d * 3 * h * w, 1.0), (b, d, 3, h, w), &dev)?;
        let bias = Tensor::from_vec(vals(b * d * h * w, 2.0), (b, d, h, w), &dev)?;
        let weight = Tensor::from_vec(vals(b * 3 * h * w, 1.0), (b, 3, h, w), &dev)?;
        let loss = |l: &Tensor| -> candle_core::Result<Tensor> {
            let s = candle_nn::ops::softmax(l, 1)?;
            let (image, _) = reweigh_graph(&s, &colours, &bias, 1.7)?;
            (image * &weight)?.sum_all()
        };
        let grads = loss(logits.as_tensor())?.backward()?;
        let g = grads.get(&logits).expect("gradient").flatten_all()?;
        let g = g.to_vec1::<f64>()?;
        let x0 = logits.as_tensor().flatten_all()?.to_vec1::<f64>()?;
        let eps = 1e-5;
        for i in 0..x0.len() {
            let at = |dx: f64| -> candle_core::Result<f64> {
                let mut x = x0.clone();
                x[i] += dx;
                loss(&Tensor::from_vec(x, (b, d, h, w), &dev)?)?.to_scalar::<f64>()
            };
            let fd = (at(eps)? - at(-eps)?) / (2.0 * eps);
            assert!(
                (fd - g[i]).abs() < 1e-6 * (1.0 + fd.abs()),
                "{i}: {fd} vs {}",
                g[i]
            );
        }
        Ok(())
    }
}
