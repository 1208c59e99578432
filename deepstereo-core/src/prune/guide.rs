//! The network's own coarse pass: the selection (and, where the backend gives them, the
//! per-plane colours) of a render at `1 / 2^level` resolution over the planes of the
//! depth range, telling each block of the full render which planes its image needs.

use crate::backend::Backend;
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::inputs::{level_camera, tile_inputs, PyramidSource};

/// The colour bound of [`needed_prefix`] stops only once the kept planes hold at least
/// this share of the selection (the most probable planes are always kept).
pub const COLOUR_MIN_MASS: f32 = 0.7;

/// Smallest side, in guide pixels, of a guide image (a smaller level is used otherwise).
const MIN_GUIDE_SIDE: usize = 8;

/// How many planes the coarse pass runs for a render of `planes` planes with a model of
/// `model_planes`: every second plane of the depth range (each standing for its
/// neighbours), and no more than the model's own count. The coarse pass only has to say
/// which planes a block needs; on every second plane it keeps the true plane of the known
/// pixels the tests check as well as on every plane, at half the cost.
pub fn guide_planes(model_planes: usize, planes: usize) -> usize {
    planes.div_ceil(2).min(model_planes).max(1)
}

/// Selection probabilities of a coarse render: `sel[(z * height + y) * width + x]` for
/// the guide planes `planes[z]` (planes of the full render, every `k`-th of the depth
/// range `first..=last` and its last, so that at most [`guide_planes`] are run).
#[derive(Clone, Debug)]
pub struct Guide {
    /// Pyramid level of the coarse render (its pixels are `2^level` full-resolution pixels).
    pub level: usize,
    pub width: usize,
    pub height: usize,
    /// The depth range, `first..=last` of the full render's planes.
    pub range: (usize, usize),
    /// The planes rendered (full-render indices, increasing, within `range`).
    pub planes: Vec<usize>,
    /// Full-render planes up to this many away from a guide plane are represented by it
    /// (`k / 2` for every `k`-th plane; 0 when every plane of the range was rendered).
    pub spread: usize,
    pub sel: Vec<f32>,
    /// Per-plane colours `rgb[((z * 3 + c) * height + y) * width + x]`, when the backend
    /// returns them ([`Backend::has_layers`]).
    pub rgb: Option<Vec<f32>>,
}

/// Renders the guide: the network on `target` at pyramid level `level` (clamped so that
/// the image keeps at least one aligned tile), on the planes `range` of `inv_depths`
/// (every `k`-th of them and the last, `k = ceil(planes / max_planes)`; `max_planes` 0:
/// all), from the sources' level-`level` images; with every plane's colour when `colours`
/// and the backend gives them. `None` when the target is too small for a coarse level.
#[allow(clippy::too_many_arguments)]
pub fn network_guide(
    backend: &dyn Backend,
    target: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    range: (usize, usize),
    level: usize,
    tile: usize,
    max_planes: usize,
    colours: bool,
) -> Result<Option<Guide>> {
    let cfg = backend.config();
    let a = cfg.tile_align();
    let Some(level) = coarse_level(target, level, a.max(MIN_GUIDE_SIDE)) else {
        return Ok(None);
    };
    let (w, h) = (
        (target.intrinsics.width >> level) as usize,
        (target.intrinsics.height >> level) as usize,
    );
    let cam = level_camera(target, level, w as u32, h as u32);
    let Some(pyr) = level_sources(sources, level, cfg.levels) else {
        return Ok(None);
    };
    // The features family's maps of the guide's images (small: computed again here).
    let pyr = match cfg.pool.as_ref().is_some_and(|p| p.features.is_some()) {
        true => (pyr.into_iter())
            .map(|s| s.with_features_from(|img| backend.source_features(img)))
            .collect::<Result<Vec<_>>>()?,
        false => pyr,
    };
    let srcs: Vec<&PyramidSource> = pyr.iter().collect();
    let (planes, k) = guide_plane_list(range, inv_depths.len(), max_planes)?;
    let band: Vec<f64> = planes.iter().map(|&z| inv_depths[z]).collect();
    let nz = band.len();
    // Tiles of twice the render's side (the guide runs at most half the planes per call,
    // see `guide_planes`) and no larger than the guide image needs: fewer calls, and
    // less computed outside the image.
    let tile = (2 * tile).max(1).div_ceil(a) * a;
    let (th, tw) = (tile.min(h.div_ceil(a) * a), tile.min(w.div_ceil(a) * a));
    let layers = colours && backend.has_layers();
    let mut sel = vec![0f32; nz * w * h];
    let mut rgb = vec![0f32; if layers { nz * 3 * w * h } else { 0 }];
    for y0 in (0..h).step_by(th) {
        for x0 in (0..w).step_by(tw) {
            let inputs = tile_inputs(cfg, &cam, &srcs, &band, (x0 as i64, y0 as i64), (th, tw))?;
            // s: [nz, th, tw]; c: [nz, 3, th, tw] with layers.
            let (c, mut s) = if layers {
                backend.run_layers(&inputs, nz)?
            } else {
                backend.run(&inputs, nz)?
            };
            if let Some(grid) = backend.prior() {
                // As the render applies it: the planes kept are then those the
                // reweighed selection needs.
                grid.reweigh_tile(&cam, &band, (x0, y0), (th, tw), &mut s);
            }
            let rgb = layers.then_some((c.as_slice(), rgb.as_mut_slice()));
            copy_tile((&s, &mut sel), rgb, (x0, y0, tw, th), (nz, w, h));
        }
    }
    Ok(Some(Guide {
        level,
        width: w,
        height: h,
        range,
        planes,
        spread: k / 2,
        sel,
        rgb: layers.then_some(rgb),
    }))
}

/// The pyramid level of the coarse render: `level`, lowered until the target's image
/// there keeps `min_side` pixels on each side; `None` at level 0.
fn coarse_level(target: &Camera, level: usize, min_side: usize) -> Option<usize> {
    let (w0, h0) = (target.intrinsics.width, target.intrinsics.height);
    let mut level = level;
    while level > 0 && (((w0 >> level) as usize) < min_side || ((h0 >> level) as usize) < min_side)
    {
        level -= 1;
    }
    (level > 0).then_some(level)
}

/// The sources' pyramids from their level-`level` image down (downsampling further
/// where their pyramids stop short of it); `None` where a source has no image.
fn level_sources(
    sources: &[&PyramidSource],
    level: usize,
    levels: usize,
) -> Option<Vec<PyramidSource>> {
    let mut pyr = Vec::with_capacity(sources.len());
    for s in sources {
        let last = s.images.len().checked_sub(1)?;
        let from = last.min(level);
        let mut img = s.images[from].clone();
        for _ in from..level {
            img = img.downsample2();
        }
        let camera = level_camera(&s.cameras[0], level, img.width, img.height);
        pyr.push(PyramidSource::new(&camera, &img, levels));
    }
    Some(pyr)
}

/// The guide planes of the range `z0..=z1` of `n` planes: every `k`-th and the last,
/// `k = ceil(planes / max_planes)` (`max_planes` 0: all); with `k`.
fn guide_plane_list(
    (z0, z1): (usize, usize),
    n: usize,
    max_planes: usize,
) -> Result<(Vec<usize>, usize)> {
    if z0 > z1 || z1 >= n {
        return Err(Error::Invalid(format!(
            "guide: plane range {z0}..={z1} outside {n} planes"
        )));
    }
    let all = z1 + 1 - z0;
    let k = if max_planes == 0 {
        1
    } else {
        all.div_ceil(max_planes).max(1)
    };
    let mut planes: Vec<usize> = (z0..=z1).step_by(k).collect();
    if planes.last() != Some(&z1) {
        planes.push(z1);
    }
    Ok((planes, k))
}

/// One tile's selection `s` `[nz, th, tw]` at `(x0, y0)` into the guide's `sel`
/// `[nz, h, w]` (non-finite values as 1), and with `rgb` its colours `[nz, 3, th, tw]`
/// into the guide's (non-finite values as 0.5).
fn copy_tile(
    (s, sel): (&[f32], &mut [f32]),
    mut rgb: Option<(&[f32], &mut [f32])>,
    (x0, y0, tw, th): (usize, usize, usize, usize),
    (nz, w, h): (usize, usize, usize),
) {
    for z in 0..nz {
        for y in y0..(y0 + th).min(h) {
            for x in x0..(x0 + tw).min(w) {
                let v = s[(z * th + y - y0) * tw + x - x0];
                sel[(z * h + y) * w + x] = if v.is_finite() { v } else { 1.0 };
                if let Some((c, rgb)) = rgb.as_mut() {
                    for ch in 0..3 {
                        let v = c[((z * 3 + ch) * th + y - y0) * tw + x - x0];
                        rgb[((z * 3 + ch) * h + y) * w + x] = if v.is_finite() { v } else { 0.5 };
                    }
                }
            }
        }
    }
}

impl Guide {
    /// The planes (of the full render) the block at `(x0, y0)` of side `size` needs: for
    /// every guide pixel under the block (and `dilate` guide pixels around it), the most
    /// probable planes, as few as hold `mass` of its selection or leave its colour within
    /// `max_error` of the colour of all planes (see [`needed_prefix`]); their union.
    /// `None` when the block lies outside the guide.
    pub fn planes(
        &self,
        x0: usize,
        y0: usize,
        size: usize,
        dilate: usize,
        mass: f32,
        max_error: f32,
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
        let nz = self.planes.len();
        let mut want = vec![false; self.range.1 + 1];
        let mut probs: Vec<(f32, usize)> = Vec::with_capacity(nz);
        let mut colours: Vec<[f32; 3]> = Vec::with_capacity(nz);
        let plane = self.height * self.width;
        for y in gy0..gy1 {
            for x in gx0..gx1 {
                let px = y * self.width + x;
                probs.clear();
                probs.extend((0..nz).map(|z| (self.sel[z * plane + px], z)));
                probs.sort_by(|a, b| b.0.total_cmp(&a.0));
                colours.clear();
                if let Some(rgb) = self.rgb.as_ref().filter(|_| max_error > 0.0) {
                    colours.extend(
                        probs
                            .iter()
                            .map(|&(_, z)| [0, 1, 2].map(|c| rgb[(z * 3 + c) * plane + px])),
                    );
                }
                let k = needed_prefix(&probs, &colours, mass, max_error);
                for &(_, z) in &probs[..k] {
                    let g = self.planes[z];
                    let lo = g.saturating_sub(self.spread).max(self.range.0);
                    for w in &mut want[lo..=(g + self.spread).min(self.range.1)] {
                        *w = true;
                    }
                }
            }
        }
        Some(want)
    }
}

/// How many of the planes `probs` (selection probability and plane, most probable
/// first; `colours` their colours in the same order, or empty) one pixel needs: the
/// shortest prefix that holds `mass` of the total probability, or (with colours) that
/// holds [`COLOUR_MIN_MASS`] of it and whose renormalized blend
/// `sum_kept s_z c_z / sum_kept s_z` is within `max_error` (in every channel) of the
/// blend of all planes `sum_z s_z c_z / sum_z s_z`. Leaving out planes of
/// mass `m` moves the colour by `m (c_kept - c_left)`, the difference of the two groups'
/// mean colours: planes may be left out when they are improbable or when they agree with
/// the rest.
pub fn needed_prefix(
    probs: &[(f32, usize)],
    colours: &[[f32; 3]],
    mass: f32,
    max_error: f32,
) -> usize {
    let total: f32 = probs.iter().map(|p| p.0).sum();
    let use_colour = colours.len() == probs.len() && total > 0.0;
    let mut all = [0f64; 3];
    if use_colour {
        for (&(p, _), c) in probs.iter().zip(colours) {
            for ch in 0..3 {
                all[ch] += p as f64 * c[ch] as f64;
            }
        }
        all = all.map(|v| v / total as f64);
    }
    let (mut acc, mut kept) = (0f32, [0f64; 3]);
    for (k, &(p, _)) in probs.iter().enumerate() {
        acc += p;
        if acc >= mass * total {
            return k + 1;
        }
        if !use_colour {
            continue;
        }
        for ch in 0..3 {
            kept[ch] += p as f64 * colours[k][ch] as f64;
        }
        if acc >= COLOUR_MIN_MASS * total {
            let worst = (0..3)
                .map(|ch| (kept[ch] / acc as f64 - all[ch]).abs())
                .fold(0f64, f64::max);
            if worst <= max_error as f64 {
                return k + 1;
            }
        }
    }
    probs.len()
}
