//! Full-image rendering, tile by tile with bounded memory.
//!
//! Tiles start at multiples of the model's alignment, so the result is identical to
//! rendering the whole image as one tile (see `config.rs`). The network runs through a
//! [`Backend`], so candle and onnxruntime render through the same code.

use crate::camera::Camera;
use crate::config::Config;
use crate::error::{Error, Result};
use crate::imageio::RgbImage;
use crate::inputs::{tile_inputs, PyramidSource, TileInputs};
use crate::model::DeepStereo;
use crate::sweep::CHANNELS;
use candle_core::{Device, Tensor};

/// Runs the network on one tile's inputs.
pub trait Backend: Sync {
    /// Name for reports (`candle`, `ort`).
    fn name(&self) -> &str;
    fn config(&self) -> &Config;
    /// Returns the image `[3, th, tw]` and the selection `[D, th, tw]`, row-major.
    fn run(&self, inputs: &TileInputs, planes: usize) -> Result<(Vec<f32>, Vec<f32>)>;
}

/// The candle backend (CPU, f32).
pub struct CandleBackend {
    pub model: DeepStereo,
    pub device: Device,
}

impl Backend for CandleBackend {
    fn name(&self) -> &str {
        "candle"
    }
    fn config(&self) -> &Config {
        self.model.config()
    }
    fn run(&self, inputs: &TileInputs, planes: usize) -> Result<(Vec<f32>, Vec<f32>)> {
        let c = self.config().in_channels();
        let tensors = inputs_to_tensors(inputs, 1, planes, c, &self.device)?;
        let out = self.model.forward(&tensors)?;
        let image = out.image.flatten_all()?.to_vec1::<f32>()?;
        let selection = out.selection.flatten_all()?.to_vec1::<f32>()?;
        Ok((image, selection))
    }
}

/// Wraps per-level data `[B * D * C * h * w]` as tensors `[B, D, C, h, w]`.
pub fn inputs_to_tensors(inputs: &TileInputs, b: usize, d: usize, c: usize, device: &Device) -> Result<Vec<Tensor>> {
    inputs
        .levels
        .iter()
        .zip(&inputs.sizes)
        .map(|(data, &(h, w))| Ok(Tensor::from_slice(data, (b, d, c, h, w), device)?))
        .collect()
}

/// A rendered view and what the selection says about it.
#[derive(Clone, Debug)]
pub struct Rendered {
    pub image: RgbImage,
    /// Expected depth per pixel, `[H, W]` (from the expected inverse depth).
    pub depth: Vec<f32>,
    /// Largest selection probability per pixel, `[H, W]`.
    pub confidence: Vec<f32>,
    /// Selection-weighted fraction of sources that see the pixel, `[H, W]`.
    pub coverage: Vec<f32>,
}

/// Renders the full `target` image tile by tile. `tile` is rounded up to the model's
/// alignment; `progress(done, total)` is called after each tile.
pub fn render_view(
    backend: &dyn Backend,
    target: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    tile: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<Rendered> {
    let cfg = backend.config();
    let a = cfg.tile_align();
    let tile = tile.max(1).div_ceil(a) * a;
    let (w, h) = (target.intrinsics.width as usize, target.intrinsics.height as usize);
    let d = inv_depths.len();
    if d == 0 {
        return Err(Error::Invalid("at least one depth plane is needed".into()));
    }
    let mut out = Rendered {
        image: RgbImage::new(w as u32, h as u32),
        depth: vec![0.0; w * h],
        confidence: vec![0.0; w * h],
        coverage: vec![0.0; w * h],
    };
    let (ntx, nty) = (w.div_ceil(tile), h.div_ceil(tile));
    let total = ntx * nty;
    let v = cfg.views;
    for ty in 0..nty {
        for tx in 0..ntx {
            let (x0, y0) = (tx * tile, ty * tile);
            let inputs = tile_inputs(cfg, target, sources, inv_depths, (x0 as i64, y0 as i64), (tile, tile))?;
            let (img, sel) = backend.run(&inputs, d)?;
            if img.iter().chain(&sel).any(|x| !x.is_finite()) {
                return Err(Error::Invalid(format!(
                    "the network produced non-finite values in the tile at ({x0}, {y0})"
                )));
            }
            let (ih, iw) = inputs.sizes[0];
            let p = cfg.pad(0);
            let tt = tile * tile;
            for yy in 0..tile.min(h - y0) {
                for xx in 0..tile.min(w - x0) {
                    let o = yy * tile + xx;
                    let pix = (y0 + yy) * w + x0 + xx;
                    for ch in 0..3 {
                        out.image.data[pix * 3 + ch] = img[ch * tt + o].clamp(0.0, 1.0);
                    }
                    let (mut rho, mut best, mut cov) = (0.0f64, 0.0f32, 0.0f32);
                    for (z, r) in inv_depths.iter().enumerate() {
                        let s = sel[z * tt + o];
                        rho += s as f64 * r;
                        best = best.max(s);
                        let mut alpha = 0.0;
                        for k in 0..v {
                            let base = ((z * v + k) * CHANNELS + 3) * ih * iw;
                            alpha += inputs.levels[0][base + (yy + p) * iw + xx + p];
                        }
                        cov += s * alpha / v as f32;
                    }
                    out.depth[pix] = if rho > 0.0 { (1.0 / rho) as f32 } else { f32::INFINITY };
                    out.confidence[pix] = best;
                    out.coverage[pix] = cov;
                }
            }
            progress(ty * ntx + tx + 1, total);
        }
    }
    Ok(out)
}
