//! The network's fine-tune through a fixed scene prior: each training and validation
//! tile's selection is reweighed by the prior's log-weights at the tile's plane points
//! ([`deepstereo_core::prior::graph`]), so the network learns what the prior leaves to
//! it, and its validation scores what the tuned model renders.

use crate::training::data::{Batch, TileRef};
use crate::training::{batch_tensors, psnr_of};
use anyhow::{bail, Result};
use candle_core::{Device, Tensor};
use deepstereo_core::model::DeepStereo;
use deepstereo_core::prior::graph::reweigh_graph;
use deepstereo_core::prior::PriorGrid;
use rayon::prelude::*;

/// The log-weights of `grid` at every tile of `tiles` on its planes, `[B, D, t, t]`,
/// mirrored left-right where augmentation mirrored the tile.
pub fn tile_bias(grid: &PriorGrid, tiles: &[TileRef], device: &Device) -> Result<Tensor> {
    let Some(first) = tiles.first() else {
        bail!("a batch without its tiles' places (MPI pairs) cannot go through a prior");
    };
    let (t, d) = (first.side, first.inv_depths.len());
    if tiles.iter().any(|r| r.side != t || r.inv_depths.len() != d) {
        bail!("a batch of tiles of different sides or planes");
    }
    let parts: Vec<Vec<f32>> = tiles
        .par_iter()
        .map(|r| {
            let mut b = grid.tile_log_weights(&r.camera, &r.inv_depths, r.origin, (t, t));
            if r.flipped {
                b.chunks_exact_mut(t).for_each(|row| row.reverse());
            }
            b
        })
        .collect();
    let flat: Vec<f32> = parts.concat();
    Ok(Tensor::from_vec(flat, (tiles.len(), d, t, t), device)?)
}

/// The rendered tiles of `batch`, `[B, 3, t, t]`, and its targets: the network's
/// training forward (`infer`: its rendering forward, no gradients), reweighed by `prior`
/// when there is one.
pub fn render_batch(
    model: &DeepStereo,
    batch: &Batch,
    prior: Option<&PriorGrid>,
    device: &Device,
    infer: bool,
) -> Result<(Tensor, Tensor)> {
    let (x, y) = batch_tensors(model, batch, device)?;
    let out = match infer {
        true => x.infer(model)?,
        false => x.forward(model)?,
    };
    let Some(grid) = prior else {
        return Ok((out.image, y));
    };
    let bias = tile_bias(grid, &batch.tiles, device)?;
    let (image, _) = reweigh_graph(&out.selection, &out.colours, &bias, grid.sharpness)?;
    Ok((image, y))
}

/// The PSNR of `batches` rendered by `model` through `prior` (clamped to [0, 1]), as
/// [`crate::training::validate`] scores them without one.
pub fn validate_through(
    model: &DeepStereo,
    batches: &[Batch],
    prior: Option<&PriorGrid>,
    device: &Device,
) -> Result<f64> {
    psnr_of(batches, |b| render_batch(model, b, prior, device, true))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::training::data::{make_batch, Sampling, SceneData};
    use glam::DVec3;

    /// A grid over the scene's box with log-weights that vary from cell to cell.
    fn grid() -> PriorGrid {
        let mut g = PriorGrid::zeros(DVec3::new(-3.0, -3.0, 0.5), DVec3::new(3.0, 3.0, 8.0), 6)
            .expect("grid");
        for (i, v) in g.values.iter_mut().enumerate() {
            *v = ((i * 29 % 13) as f32 - 6.0) * 0.5;
        }
        g.sharpness = 1.6;
        g
    }

    /// Each tile of a batch rendered through a prior is the renderer's `apply_tile` of
    /// the network's layers at that tile's camera, planes and offset; a grid of zeros at
    /// sharpness 1 changes nothing; a mirrored tile's log-weights are mirrored.
    #[test]
    fn tiles_through_a_prior_are_rendered_as_the_renderer_renders_them() -> anyhow::Result<()> {
        let dir = tempfile::tempdir()?;
        let (scene, cfg, backend, _) = crate::test_scene::tiny_case(dir.path(), 5, (64, 48), 32)?;
        let data = SceneData::from_scene(&scene, cfg.levels)?;
        let batch = make_batch(&cfg, &Sampling::fixed(&cfg), &[data], 3, 0, 3)?;
        let (model, dev) = (&backend.model, Device::Cpu);
        let g = grid();
        let (image, _) = render_batch(model, &batch, Some(&g), &dev, true)?;
        let (x, _) = batch_tensors(model, &batch, &dev)?;
        let out = x.infer(model)?;
        let t = cfg.tile;
        for (k, r) in batch.tiles.iter().enumerate() {
            let mut sel = out.selection.get(k)?.flatten_all()?.to_vec1::<f32>()?;
            let col = out.colours.get(k)?.flatten_all()?.to_vec1::<f32>()?;
            let want = g.apply_tile(&r.camera, &r.inv_depths, r.origin, t, &col, &mut sel);
            let got = image.get(k)?.flatten_all()?.to_vec1::<f32>()?;
            for (a, b) in got.iter().zip(&want) {
                assert!((a - b).abs() < 1e-5, "tile {k}: {a} vs {b}");
            }
        }
        let zeros = PriorGrid {
            values: vec![0.0; g.values.len()],
            sharpness: 1.0,
            ..g.clone()
        };
        let (same, _) = render_batch(model, &batch, Some(&zeros), &dev, true)?;
        let diff = (same - &out.image)?.abs()?.max_all()?.to_scalar::<f32>()?;
        assert!(diff < 1e-5, "{diff}");
        let mut flipped = batch.tiles[0].clone();
        flipped.flipped = true;
        let a = tile_bias(&g, &batch.tiles[..1], &dev)?;
        let b = tile_bias(&g, &[flipped], &dev)?;
        assert_eq!(
            a.flip(&[3])?.flatten_all()?.to_vec1::<f32>()?,
            b.flatten_all()?.to_vec1::<f32>()?
        );
        Ok(())
    }
}
