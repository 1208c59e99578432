//! Per-source features of the `features` family ([`crate::config::SourceFeatures`]): a 2D
//! CNN run once on each source image at each pyramid level, whose feature maps are then
//! warped into the plane sweep beside the source's RGBA.
//!
//! - **The network** ([`FeatureNet`], parameters `features.{i}.{weight,bias}`, weights
//!   shared across levels and views): `k x k` valid convolutions, ReLU after all but the
//!   last, on the image zero-padded by the network's radius `R = sum (k_i - 1) / 2`. So a
//!   feature at image pixel `p` is a function of the `(2R + 1)^2` window around `p` of the
//!   zero-padded image, and a crop of the image (padded the same way) gives exactly the
//!   features the whole image gives inside the crop.
//! - **The warp** ([`warp`], [`FeatureWarp`]): the sweep's zero-padded bilinear sampling
//!   ([`crate::sweep::sample_bilinear`]) of the feature map at the sweep's positions
//!   ([`crate::sweep::coords`]): `f(u, v) = sum_k w_k F[tap_k]` over the taps inside the
//!   image, so it is 0 where the view's alpha is 0 and premultiplied by alpha at the
//!   border, as the sweep's colours are. It is linear in `F`, and its gradient is the
//!   transposed sum `dF[tap_k] += w_k df`, so training reaches the CNN through the warp.

use crate::config::SourceFeatures;
use crate::conv::Conv2d;
use crate::imageio::RgbImage;
use candle_core::{bail, CpuStorage, CustomOp1, Device, Layout, Module, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;
use std::sync::Arc;

/// The per-source feature CNN (`features.*`).
#[derive(Debug, Clone)]
pub struct FeatureNet {
    convs: Vec<Conv2d>,
    radius: usize,
    channels: usize,
}

impl FeatureNet {
    pub fn new(cfg: &SourceFeatures, vb: VarBuilder) -> Result<Self> {
        let mut ch = 3;
        let mut convs = Vec::with_capacity(cfg.convs.len());
        for (i, c) in cfg.convs.iter().enumerate() {
            convs.push(Conv2d::new(ch, c.channels, (c.kernel, c.kernel), vb.pp(i))?);
            ch = c.channels;
        }
        Ok(Self {
            convs,
            radius: cfg.radius(),
            channels: cfg.channels(),
        })
    }

    /// Channels `F` of a feature map.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The border `R` each side that the valid convolutions consume.
    pub fn radius(&self) -> usize {
        self.radius
    }

    /// `x` `[N, 3, H + 2R, W + 2R]` (images zero-padded by `R`) -> `[N, C_f, H, W]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut x = x.clone();
        let last = self.convs.len().saturating_sub(1);
        for (i, conv) in self.convs.iter().enumerate() {
            x = match i < last {
                true => conv.forward_relu(&x)?,
                false => conv.forward(&x)?,
            };
        }
        Ok(x)
    }

    /// The features of the whole image `img`: `[C_f, H, W]` (no gradient).
    pub fn image_features(&self, img: &RgbImage, device: &Device) -> Result<FeatureMap> {
        let (w, h) = (img.width as usize, img.height as usize);
        let r = self.radius as i64;
        let window = Window {
            x0: -r,
            y0: -r,
            width: w + 2 * self.radius,
            height: h + 2 * self.radius,
        };
        let x = Tensor::from_vec(padded_crop(img, window), window.shape(), device)?;
        let f = self.forward(&x.unsqueeze(0)?)?.squeeze(0)?; // [C_f, H, W]
        let channels = f.dim(0)?;
        Ok(FeatureMap {
            channels,
            width: w,
            height: h,
            data: f.flatten_all()?.to_vec1::<f32>()?,
        })
    }
}

/// A rectangle of image pixels; `x0`, `y0` may be negative (outside the image: zeros).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Window {
    pub x0: i64,
    pub y0: i64,
    pub width: usize,
    pub height: usize,
}

impl Window {
    /// `(3, height, width)`.
    pub fn shape(&self) -> (usize, usize, usize) {
        (3, self.height, self.width)
    }
}

/// The pixels of `img` in `window` as `[3, h, w]` f32, zero outside the image.
pub fn padded_crop(img: &RgbImage, window: Window) -> Vec<f32> {
    let (w, h) = (window.width, window.height);
    let mut out = vec![0.0f32; 3 * w * h];
    let (iw, ih) = (img.width as i64, img.height as i64);
    for y in 0..h {
        let sy = window.y0 + y as i64;
        if sy < 0 || sy >= ih {
            continue;
        }
        for x in 0..w {
            let sx = window.x0 + x as i64;
            if sx < 0 || sx >= iw {
                continue;
            }
            let i = (sy as usize * iw as usize + sx as usize) * 3;
            for c in 0..3 {
                out[(c * h + y) * w + x] = img.data[i + c];
            }
        }
    }
    out
}

/// A source's feature map at one level: `[C, H, W]` f32 over the image's pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureMap {
    pub channels: usize,
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

/// The bilinear taps of one sampling position: up to four `(index into the feature
/// map's plane, weight)`; an unused tap has weight 0.
type Taps = [(u32, f32); 4];

/// The taps of position `(u, v)` in an image of `img_w x img_h` pixels whose feature map
/// covers `window` (sample_bilinear's weights, computed in f64; taps outside the image
/// have weight 0). `None`: a tap inside the image falls outside the window.
fn taps_of(u: f64, v: f64, (img_w, img_h): (i64, i64), window: Window) -> Option<Taps> {
    let mut taps = [(0u32, 0.0f32); 4];
    let (sx, sy) = (u - 0.5, v - 0.5);
    // Also rejects NaN (no projection).
    if !(sx > -1.0 && sy > -1.0 && sx < img_w as f64 && sy < img_h as f64) {
        return Some(taps);
    }
    let (x0, y0) = (sx.floor() as i64, sy.floor() as i64);
    let (ax, ay) = (sx - x0 as f64, sy - y0 as f64);
    let corners = [
        (x0, y0, (1.0 - ax) * (1.0 - ay)),
        (x0 + 1, y0, ax * (1.0 - ay)),
        (x0, y0 + 1, (1.0 - ax) * ay),
        (x0 + 1, y0 + 1, ax * ay),
    ];
    for (tap, (x, y, wt)) in taps.iter_mut().zip(corners) {
        if x < 0 || y < 0 || x >= img_w || y >= img_h || wt <= 0.0 {
            continue;
        }
        let (cx, cy) = (x - window.x0, y - window.y0);
        if cx < 0 || cy < 0 || cx >= window.width as i64 || cy >= window.height as i64 {
            return None;
        }
        *tap = ((cy as usize * window.width + cx as usize) as u32, wt as f32);
    }
    Some(taps)
}

/// The image pixels the taps of `coords` (`[D, 2, P]`: per plane all `u`, then all `v`)
/// read in an image of `img_w x img_h`: the smallest window holding them, `None` when they
/// read none.
pub fn tap_window(coords: &[f64], pixels: usize, (img_w, img_h): (usize, usize)) -> Option<Window> {
    let (iw, ih) = (img_w as i64, img_h as i64);
    let mut lo = (i64::MAX, i64::MAX);
    let mut hi = (i64::MIN, i64::MIN);
    for plane in coords.chunks_exact(2 * pixels.max(1)) {
        let (us, vs) = plane.split_at(pixels);
        for (&u, &v) in us.iter().zip(vs) {
            let (sx, sy) = (u - 0.5, v - 0.5);
            if !(sx > -1.0 && sy > -1.0 && sx < iw as f64 && sy < ih as f64) {
                continue;
            }
            let (x0, y0) = (sx.floor() as i64, sy.floor() as i64);
            lo = (lo.0.min(x0.max(0)), lo.1.min(y0.max(0)));
            hi = (
                hi.0.max((x0 + 1).min(iw - 1)),
                hi.1.max((y0 + 1).min(ih - 1)),
            );
        }
    }
    (lo.0 <= hi.0 && lo.1 <= hi.1).then(|| Window {
        x0: lo.0,
        y0: lo.1,
        width: (hi.0 - lo.0 + 1) as usize,
        height: (hi.1 - lo.1 + 1) as usize,
    })
}

/// The whole map `map` sampled at `coords` (`[D, 2, P]`, one view's sweep positions):
/// `[D, F, P]`, what [`FeatureWarp::apply`] gives with the whole image as its window,
/// without building the taps (rendering).
pub fn sample_map(map: &FeatureMap, coords: &[f64], planes: usize) -> Vec<f32> {
    let (f, plane) = (map.channels, map.width * map.height);
    let p = coords.len() / (2 * planes.max(1));
    let size = (map.width as i64, map.height as i64);
    let whole = Window {
        x0: 0,
        y0: 0,
        width: map.width,
        height: map.height,
    };
    let mut out = vec![0.0f32; planes * f * p];
    if out.is_empty() || plane == 0 {
        return out;
    }
    out.par_chunks_mut(f * p)
        .zip(coords.par_chunks(2 * p))
        .for_each(|(dst, xy)| {
            let (us, vs) = xy.split_at(p);
            for (i, (&u, &v)) in us.iter().zip(vs).enumerate() {
                let Some(taps) = taps_of(u, v, size, whole) else {
                    continue;
                };
                for (c, o) in dst.iter_mut().skip(i).step_by(p).enumerate() {
                    let src = &map.data[c * plane..(c + 1) * plane];
                    *o = taps.iter().map(|&(j, w)| w * src[j as usize]).sum();
                }
            }
        });
    out
}

/// The warp of one source's feature map into the sweep, as a candle op on the map
/// `[C, h_f, w_f]` (covering `window` of the image): `[D, C, P]` for `D` planes of `P`
/// target pixels. Differentiable in the map.
#[derive(Clone, Debug)]
pub struct FeatureWarp {
    taps: Arc<Vec<Taps>>,
    planes: usize,
    window: Window,
}

impl FeatureWarp {
    /// `coords`: `[D, 2, P]` source pixel coordinates of one view
    /// ([`crate::sweep::coords`], NaN: none), in an image of `img_w x img_h` whose feature
    /// map covers `window` (the whole image, or a crop from [`tap_window`]).
    pub fn new(
        coords: &[f64],
        planes: usize,
        (img_w, img_h): (usize, usize),
        window: Window,
    ) -> Result<Self> {
        if planes == 0 || !coords.len().is_multiple_of(2 * planes) {
            bail!(
                "feature warp: {} coordinates for {planes} planes",
                coords.len()
            );
        }
        let p = coords.len() / (2 * planes);
        let size = (img_w as i64, img_h as i64);
        let mut taps = Vec::with_capacity(planes * p);
        for plane in coords.chunks_exact(2 * p.max(1)) {
            let (us, vs) = plane.split_at(p);
            for (&u, &v) in us.iter().zip(vs) {
                match taps_of(u, v, size, window) {
                    Some(t) => taps.push(t),
                    None => bail!("feature warp: a tap of ({u}, {v}) is outside the feature window {window:?}"),
                }
            }
        }
        Ok(Self {
            taps: Arc::new(taps),
            planes,
            window,
        })
    }

    /// The warp of [`Self::taps`]' arrays (`idx`, `wts`: `[D * P, 4]`) for a feature map of
    /// `h x w` pixels; indices outside the map are an error.
    pub fn from_taps(
        idx: &[i64],
        wts: &[f32],
        planes: usize,
        (h, w): (usize, usize),
    ) -> Result<Self> {
        if idx.len() != wts.len()
            || !idx.len().is_multiple_of(4)
            || planes == 0
            || !(idx.len() / 4).is_multiple_of(planes)
        {
            bail!(
                "feature warp: {} indices and {} weights for {planes} planes",
                idx.len(),
                wts.len()
            );
        }
        if let Some(i) = idx.iter().find(|&&i| i < 0 || i as usize >= h * w) {
            bail!("feature warp: tap index {i} outside a {h}x{w} map");
        }
        let taps = idx
            .chunks_exact(4)
            .zip(wts.chunks_exact(4))
            .map(|(i, wt)| std::array::from_fn(|k| (i[k] as u32, wt[k])))
            .collect();
        Ok(Self {
            taps: Arc::new(taps),
            planes,
            window: Window {
                x0: 0,
                y0: 0,
                width: w,
                height: h,
            },
        })
    }

    /// The taps as two `[D * P, 4]` arrays: indices into a plane of the feature map
    /// (row-major over its window) and weights (0 for an unused tap), so another runtime
    /// warps the map as `sum_k w[:, k] F[:, i[:, k]]` (`python/train_ddp.py`).
    pub fn taps(&self) -> (Vec<i64>, Vec<f32>) {
        let idx = self
            .taps
            .iter()
            .flat_map(|t| t.map(|(i, _)| i as i64))
            .collect();
        let wts = self.taps.iter().flat_map(|t| t.map(|(_, w)| w)).collect();
        (idx, wts)
    }

    /// Planes `D` of the warp.
    pub fn planes(&self) -> usize {
        self.planes
    }

    /// Target pixels per plane.
    pub fn pixels(&self) -> usize {
        self.taps.len() / self.planes
    }

    /// `f` `[C, h_f * w_f]` (one plane per channel) -> `[D, C, P]`.
    pub fn apply(&self, f: &[f32], channels: usize) -> Vec<f32> {
        let (p, plane) = (self.pixels(), self.window.width * self.window.height);
        let mut out = vec![0.0f32; self.planes * channels * p];
        if out.is_empty() || plane == 0 {
            return out;
        }
        out.par_chunks_mut(p).enumerate().for_each(|(dc, dst)| {
            let (d, c) = (dc / channels, dc % channels);
            let src = &f[c * plane..(c + 1) * plane];
            let taps = &self.taps[d * p..(d + 1) * p];
            for (o, t) in dst.iter_mut().zip(taps) {
                *o = t.iter().map(|&(i, w)| w * src[i as usize]).sum();
            }
        });
        out
    }

    /// The gradient of [`Self::apply`]: `dy` `[D, C, P]` -> `[C, h_f * w_f]`.
    fn transpose(&self, dy: &[f32], channels: usize) -> Vec<f32> {
        let (p, plane) = (self.pixels(), self.window.width * self.window.height);
        let mut dx = vec![0.0f32; channels * plane];
        if dx.is_empty() || p == 0 {
            return dx;
        }
        dx.par_chunks_mut(plane).enumerate().for_each(|(c, dst)| {
            for d in 0..self.planes {
                let g = &dy[(d * channels + c) * p..][..p];
                let taps = &self.taps[d * p..(d + 1) * p];
                for (&gv, t) in g.iter().zip(taps) {
                    for &(i, w) in t {
                        dst[i as usize] += w * gv;
                    }
                }
            }
        });
        dx
    }
}

impl CustomOp1 for FeatureWarp {
    fn name(&self) -> &'static str {
        "deepstereo-feature-warp"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (c, h, w) = l.shape().dims3()?;
        if (h, w) != (self.window.height, self.window.width) {
            bail!(
                "feature warp: a map of {h}x{w} for a window of {:?}",
                self.window
            );
        }
        let f = match (s, l.contiguous_offsets()) {
            (CpuStorage::F32(v), Some((a, b))) => &v[a..b],
            _ => bail!("feature warp: a contiguous f32 map only"),
        };
        let y = self.apply(f, c);
        Ok((
            CpuStorage::F32(y),
            Shape::from((self.planes, c, self.pixels())),
        ))
    }

    fn bwd(&self, x: &Tensor, _y: &Tensor, dy: &Tensor) -> Result<Option<Tensor>> {
        let (c, h, w) = x.dims3()?;
        let dy = dy.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
        let dx = self.transpose(&dy, c);
        Ok(Some(Tensor::from_vec(dx, (c, h, w), x.device())?))
    }
}

/// Warps the feature map `f` `[C, h_f, w_f]` with `op`: `[D, C, P]`, differentiable in `f`.
pub fn warp(f: &Tensor, op: &FeatureWarp) -> Result<Tensor> {
    f.contiguous()?.apply_op1(op.clone())
}

#[cfg(test)]
mod tests;
