//! The network's own coarse pass: the selection of a render at `1 / 2^level` resolution
//! over the planes of the depth range, telling each block of the full render which
//! planes carry its probability mass.

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::inputs::{level_camera, tile_inputs, PyramidSource};
use crate::render::Backend;

/// Smallest side, in guide pixels, of a guide image (a smaller level is used otherwise).
const MIN_GUIDE_SIDE: usize = 8;

/// Selection probabilities of a coarse render: `sel[(z * height + y) * width + x]` for
/// the planes `first..=last` of the full render (`z` counted from `first`).
#[derive(Clone, Debug)]
pub struct Guide {
    /// Pyramid level of the coarse render (its pixels are `2^level` full-resolution pixels).
    pub level: usize,
    pub width: usize,
    pub height: usize,
    /// The planes rendered, `first..=last` of the full render's planes.
    pub range: (usize, usize),
    pub sel: Vec<f32>,
}

/// Renders the guide: the network on `target` at pyramid level `level` (clamped so that
/// the image keeps at least one aligned tile), on the planes `range` of `inv_depths`,
/// from the sources' level-`level` images. `None` when the target is too small for a
/// coarse level.
pub fn network_guide(
    backend: &dyn Backend,
    target: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    range: (usize, usize),
    level: usize,
    tile: usize,
) -> Result<Option<Guide>> {
    let cfg = backend.config();
    let a = cfg.tile_align();
    let (w0, h0) = (target.intrinsics.width, target.intrinsics.height);
    let min_side = a.max(MIN_GUIDE_SIDE);
    let mut level = level;
    while level > 0 && (((w0 >> level) as usize) < min_side || ((h0 >> level) as usize) < min_side)
    {
        level -= 1;
    }
    if level == 0 {
        return Ok(None);
    }
    let (w, h) = ((w0 >> level) as usize, (h0 >> level) as usize);
    let cam = level_camera(target, level, w as u32, h as u32);
    // The sources' pyramids from their level-`level` image down (downsampling further
    // where their pyramids stop short of it).
    let mut pyr = Vec::with_capacity(sources.len());
    for s in sources {
        let Some(last) = s.images.len().checked_sub(1) else {
            return Ok(None);
        };
        let from = last.min(level);
        let mut img = s.images[from].clone();
        for _ in from..level {
            img = img.downsample2();
        }
        let camera = level_camera(&s.cameras[0], level, img.width, img.height);
        pyr.push(PyramidSource::new(&camera, &img, cfg.levels));
    }
    let srcs: Vec<&PyramidSource> = pyr.iter().collect();
    let (z0, z1) = range;
    if z0 > z1 || z1 >= inv_depths.len() {
        return Err(Error::Invalid(format!(
            "guide: plane range {z0}..={z1} outside {} planes",
            inv_depths.len()
        )));
    }
    let band = &inv_depths[z0..=z1];
    let nz = band.len();
    // Tiles no larger than the (small) guide image needs, so little is computed outside.
    let tile = tile.max(1).div_ceil(a) * a;
    let (th, tw) = (tile.min(h.div_ceil(a) * a), tile.min(w.div_ceil(a) * a));
    let mut sel = vec![0f32; nz * w * h];
    for y0 in (0..h).step_by(th) {
        for x0 in (0..w).step_by(tw) {
            let inputs = tile_inputs(cfg, &cam, &srcs, band, (x0 as i64, y0 as i64), (th, tw))?;
            let (_, s) = backend.run(&inputs, nz)?; // [nz, th, tw]
            for z in 0..nz {
                for y in y0..(y0 + th).min(h) {
                    for x in x0..(x0 + tw).min(w) {
                        let v = s[(z * th + y - y0) * tw + x - x0];
                        sel[(z * h + y) * w + x] = if v.is_finite() { v } else { 1.0 };
                    }
                }
            }
        }
    }
    Ok(Some(Guide {
        level,
        width: w,
        height: h,
        range,
        sel,
    }))
}

impl Guide {
    /// The planes (of the full render) the block at `(x0, y0)` of side `size` needs: for
    /// every guide pixel under the block (and `dilate` guide pixels around it), the most
    /// probable planes holding `mass` of its selection; their union. `None` when the block
    /// lies outside the guide.
    pub fn planes(
        &self,
        x0: usize,
        y0: usize,
        size: usize,
        dilate: usize,
        mass: f32,
    ) -> Option<Vec<bool>> {
        let l = self.level;
        let (gx0, gy0) = (
            (x0 >> l).saturating_sub(dilate),
            (y0 >> l).saturating_sub(dilate),
        );
        let gx1 = ((x0 + size).div_ceil(1 << l) + dilate).min(self.width);
        let gy1 = ((y0 + size).div_ceil(1 << l) + dilate).min(self.height);
        if gx0 >= gx1 || gy0 >= gy1 {
            return None;
        }
        let nz = self.range.1 + 1 - self.range.0;
        let mut want = vec![false; self.range.1 + 1];
        let mut probs: Vec<(f32, usize)> = Vec::with_capacity(nz);
        for y in gy0..gy1 {
            for x in gx0..gx1 {
                probs.clear();
                probs
                    .extend((0..nz).map(|z| (self.sel[(z * self.height + y) * self.width + x], z)));
                probs.sort_by(|a, b| b.0.total_cmp(&a.0));
                let total: f32 = probs.iter().map(|p| p.0).sum();
                let mut acc = 0f32;
                for &(p, z) in &probs {
                    want[self.range.0 + z] = true;
                    acc += p;
                    if acc >= mass * total {
                        break;
                    }
                }
            }
        }
        Some(want)
    }
}
