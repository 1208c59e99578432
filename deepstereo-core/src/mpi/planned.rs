//! MPIs baked with pruning's plan ([`crate::prune::Pruner`]): the network runs per block
//! on the planes the coarse pass keeps there, as [`crate::render::render_view_pruned`]
//! runs it, and every other plane of the block gets selection 0, so alpha 0. The
//! composite at the reference camera is then the pruned render of that camera (the same
//! colours and selections), and the planes hold colour only near the depths the coarse
//! pass finds surfaces at.

use super::{tile_layers, TileGrid};
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::inputs::PyramidSource;
use crate::prune::{Block, Pruner, TilePlan};
use crate::render::{empty_response, Backend};

/// Layers `[D, 3, H, W]` and `[D, H, W]` being filled block by block.
struct Layers {
    w: usize,
    h: usize,
    colours: Vec<f32>,
    selection: Vec<f32>,
}

impl Layers {
    /// The pixels of `b` inside the image, as `(pixel index, index in the block)`.
    fn pixels(&self, b: &Block) -> Vec<(usize, usize)> {
        let (x1, y1) = ((b.x0 + b.size).min(self.w), (b.y0 + b.size).min(self.h));
        (b.y0..y1)
            .flat_map(|y| (b.x0..x1).map(move |x| (y * self.w + x, (y - b.y0) * b.size + x - b.x0)))
            .collect()
    }

    /// Writes plane `z`'s colour and selection at pixel `p`.
    fn set(&mut self, z: usize, p: usize, rgb: [f32; 3], s: f32) {
        let n = self.w * self.h;
        self.selection[z * n + p] = s;
        for (ch, v) in rgb.into_iter().enumerate() {
            self.colours[(z * 3 + ch) * n + p] = v;
        }
    }
}

/// The network's layers at `camera` (a pinhole) from `sources` at `inv_depths`, run as
/// `pruner` plans each tile of side `tile` (rounded up to the model's alignment): on a
/// block's kept planes the network's colours and selection (reweighed by the backend's
/// scene prior when it has one), 0 on the others; on a block no source covers, the
/// network's response to empty input on every plane (its image as every plane's colour);
/// on a constant block, its colour with a uniform selection over the pruner's depth range.
pub fn layers_planned(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    tile: usize,
    pruner: &Pruner<'_>,
    progress: &dyn Fn(usize, usize),
) -> Result<(Vec<f32>, Vec<f32>)> {
    let cfg = backend.config();
    let (w, h) = camera.intrinsics.size();
    let d = inv_depths.len();
    if d == 0 {
        return Err(Error::Invalid("at least one depth plane is needed".into()));
    }
    let grid = TileGrid::new(cfg, (w, h), tile);
    let mut out = Layers {
        w,
        h,
        colours: vec![0f32; d * 3 * w * h],
        selection: vec![0f32; d * w * h],
    };
    // The network's response to empty input, computed on the first block that needs it.
    let mut empty: Option<([f32; 3], Vec<f32>)> = None;
    for i in 0..grid.len() {
        let (x0, y0) = grid.origin(i);
        for block in pruner.plan(x0, y0, grid.side) {
            match &block.plan {
                TilePlan::Uncovered => {
                    if empty.is_none() {
                        let (img, sel) = empty_response(backend, d)?;
                        empty = Some(([img[0], img[1], img[2]], sel));
                    }
                    if let Some((rgb, sel)) = &empty {
                        for (p, _) in out.pixels(&block) {
                            for (z, &s) in sel.iter().enumerate() {
                                out.set(z, p, *rgb, s);
                            }
                        }
                    }
                }
                TilePlan::Flat { colour, .. } => {
                    let (z0, z1) = pruner.range();
                    let s = 1.0 / (z1 + 1 - z0) as f32;
                    for (p, _) in out.pixels(&block) {
                        for z in z0..=z1 {
                            out.set(z, p, *colour, s);
                        }
                    }
                }
                TilePlan::Planes(planes) => run_block(
                    backend, camera, sources, inv_depths, &block, planes, &mut out,
                )?,
            }
        }
        progress(i + 1, grid.len());
    }
    Ok((out.colours, out.selection))
}

/// The network's layers on `planes` of `block`, written at those planes.
fn run_block(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    block: &Block,
    planes: &[usize],
    out: &mut Layers,
) -> Result<()> {
    let band: Vec<f64> = planes.iter().map(|&z| inv_depths[z]).collect();
    let (x0, y0, size) = (block.x0, block.y0, block.size);
    let (c, s) = tile_layers(backend, camera, sources, &band, (x0, y0), size)?;
    let tt = size * size;
    for (p, q) in out.pixels(block) {
        for (j, &z) in planes.iter().enumerate() {
            let rgb = [
                c[j * 3 * tt + q],
                c[(j * 3 + 1) * tt + q],
                c[(j * 3 + 2) * tt + q],
            ];
            out.set(z, p, rgb, s[j * tt + q]);
        }
    }
    Ok(())
}
