//! The `features` family's part of a tile's inputs ([`crate::features`]): each source's
//! feature map of every level warped at the sweep's positions ([`crate::sweep::coords`])
//! and put after the view's RGBA and cue, `[D, V, C_v, h_l, w_l]` with the last `F`
//! channels the features.
//!
//! Rendering warps maps computed once per source image ([`append_warped`]); training
//! computes the maps inside its graph from crops of the sources, so that gradients reach
//! the CNN, and gets here only the crops and the warps ([`tile_warps`]).

use super::{level_camera, PyramidSource, TileInputs};
use crate::camera::Camera;
use crate::config::Config;
use crate::error::{Error, Result};
use crate::features::{padded_crop, sample_map, tap_window, warp, FeatureNet, FeatureWarp, Window};
use crate::sweep::coords::sweep_coords;
use crate::sweep::Region;
use candle_core::Tensor;

/// Level `l`'s region of a tile at `(x0, y0)` whose level input is `h x w`.
fn level_region(cfg: &Config, l: usize, (x0, y0): (i64, i64), (h, w): (usize, usize)) -> Region {
    Region {
        x0: cfg.input_origin(l, x0),
        y0: cfg.input_origin(l, y0),
        width: w,
        height: h,
    }
}

/// View `k`'s coordinates `[D, 2, P]` out of the sweep's `[D, V, 2, P]`.
fn view_coords(coords: &[f64], k: usize, views: usize, pixels: usize) -> Vec<f64> {
    if pixels == 0 || views == 0 {
        return Vec::new();
    }
    coords
        .chunks_exact(2 * pixels)
        .skip(k)
        .step_by(views)
        .flatten()
        .copied()
        .collect()
}

/// Level `l` of the target and the sources' level-`l` cameras.
fn level_cameras<'a>(
    target: &Camera,
    sources: &[&'a PyramidSource],
    l: usize,
) -> (Camera, Vec<&'a Camera>) {
    let (w, h) = (target.intrinsics.width >> l, target.intrinsics.height >> l);
    let cams = sources.iter().map(|s| &s.cameras[l]).collect();
    (level_camera(target, l, w, h), cams)
}

fn warp_error(e: candle_core::Error) -> Error {
    Error::Invalid(format!("source features: {e}"))
}

/// Appends every view's warped feature maps (`F` channels, the sources' `features`) to
/// `inputs` (built by [`super::tile_inputs_without_features`] for the tile at `origin`).
pub fn append_warped(
    cfg: &Config,
    inputs: &mut TileInputs,
    (target, sources, inv_depths): (&Camera, &[&PyramidSource], &[f64]),
    origin: (i64, i64),
    f: usize,
) -> Result<()> {
    let (v, d, cb) = (sources.len(), inv_depths.len(), inputs.channels);
    for (l, buf) in inputs.levels.iter_mut().enumerate() {
        let region = level_region(cfg, l, origin, inputs.sizes[l]);
        let hw = region.len();
        let (tcam, cams) = level_cameras(target, sources, l);
        let coords = sweep_coords(&tcam, region, &cams, inv_depths);
        let mut warped = Vec::with_capacity(v);
        for (k, s) in sources.iter().enumerate() {
            let img = &s.images[l];
            let (w, h) = (img.width as usize, img.height as usize);
            let map = match s.features.get(l) {
                Some(m) if (m.channels, m.width, m.height) == (f, w, h) => m,
                _ if w * h == 0 => {
                    warped.push(vec![0.0; d * f * hw]);
                    continue;
                }
                _ => {
                    return Err(Error::Invalid(format!(
                        "source {k} has no {f}-channel feature map of level {l} ({w}x{h})"
                    )))
                }
            };
            warped.push(sample_map(map, &view_coords(&coords, k, v, hw), d)); // [D, F, P]
        }
        let mut out = crate::sweep::try_zeroed(&[d, v, cb + f, hw], "a feature sweep")?;
        for (slice, dst) in out.chunks_exact_mut((cb + f) * hw).enumerate() {
            let (z, k) = (slice / v, slice % v);
            dst[..cb * hw].copy_from_slice(&buf[slice * cb * hw..][..cb * hw]);
            dst[cb * hw..].copy_from_slice(&warped[k][z * f * hw..][..f * hw]);
        }
        *buf = out;
    }
    inputs.channels = cb + f;
    Ok(())
}

/// One view's part of a training tile at one level: the CNN's input, a crop of the
/// source zero-padded by the CNN's radius `R` (`[3, h + 2R, w + 2R]`), and the warp of
/// its `h x w` features into the tile's sweep.
#[derive(Clone, Debug)]
pub struct ViewWarp {
    pub input: Vec<f32>,
    pub input_shape: (usize, usize, usize),
    pub op: FeatureWarp,
}

/// A training tile's feature warps: `levels[l][k]`, `None` where view `k` is not seen
/// at any plane (its features are zeros there).
#[derive(Clone, Debug)]
pub struct TileWarps {
    pub levels: Vec<Vec<Option<ViewWarp>>>,
    /// `(h_l, w_l)` per level, as [`TileInputs::sizes`].
    pub sizes: Vec<(usize, usize)>,
    pub planes: usize,
}

impl TileWarps {
    /// Multiplies each view's crop channel `c` by `gains[c]` (training's photometric
    /// augmentation, applied to the sweep's colours alike).
    pub fn scale_colours(&mut self, gains: &[f32]) {
        for vw in self.levels.iter_mut().flatten().flatten() {
            let plane = vw.input_shape.1 * vw.input_shape.2;
            for (c, chunk) in vw.input.chunks_exact_mut(plane).enumerate() {
                chunk.iter_mut().for_each(|x| *x *= gains[c % gains.len()]);
            }
        }
    }
}

/// The crops and warps of the tile at `origin` whose level inputs are `sizes`
/// ([`TileInputs::sizes`]), for a feature CNN of radius `radius`.
pub fn tile_warps(
    cfg: &Config,
    (target, sources, inv_depths): (&Camera, &[&PyramidSource], &[f64]),
    origin: (i64, i64),
    sizes: &[(usize, usize)],
    radius: usize,
) -> Result<TileWarps> {
    let (v, d) = (sources.len(), inv_depths.len());
    let mut levels = Vec::with_capacity(sizes.len());
    for (l, &size) in sizes.iter().enumerate() {
        let region = level_region(cfg, l, origin, size);
        let hw = region.len();
        let (tcam, cams) = level_cameras(target, sources, l);
        let coords = sweep_coords(&tcam, region, &cams, inv_depths);
        let mut views = Vec::with_capacity(v);
        for (k, s) in sources.iter().enumerate() {
            let img = &s.images[l];
            let dims = (img.width as usize, img.height as usize);
            let ck = view_coords(&coords, k, v, hw);
            let Some(window) = tap_window(&ck, hw, dims) else {
                views.push(None);
                continue;
            };
            let op = FeatureWarp::new(&ck, d, dims, window).map_err(warp_error)?;
            let r = radius as i64;
            let padded = Window {
                x0: window.x0 - r,
                y0: window.y0 - r,
                width: window.width + 2 * radius,
                height: window.height + 2 * radius,
            };
            views.push(Some(ViewWarp {
                input: padded_crop(img, padded),
                input_shape: padded.shape(),
                op,
            }));
        }
        levels.push(views);
    }
    Ok(TileWarps {
        levels,
        sizes: sizes.to_vec(),
        planes: d,
    })
}

/// Training's warped maps, computed in the graph: `[B, D, V, F, h_l, w_l]` per level for
/// inputs `base[l]` `[B, D, V, C_v - F, h_l, w_l]` (from
/// [`super::tile_inputs_without_features`]), differentiable in the CNN's weights.
/// `tiles[b]`: sample `b`'s warps. The model takes them apart from `base`
/// ([`crate::model::DeepStereo::forward_parts`]).
pub fn warped_features(
    net: &FeatureNet,
    base: &[Tensor],
    tiles: &[TileWarps],
) -> candle_core::Result<Vec<Tensor>> {
    let f = net.channels();
    let mut out = Vec::with_capacity(base.len());
    for (l, x) in base.iter().enumerate() {
        let &[b, d, v, _, h, w] = x.dims() else {
            candle_core::bail!(
                "input level {l}: expected [B, D, V, C, H, W], got {:?}",
                x.dims()
            );
        };
        let mut samples = Vec::with_capacity(b);
        for tile in tiles.iter().take(b) {
            let mut views = Vec::with_capacity(v);
            for vw in tile.levels[l].iter().take(v) {
                views.push(match vw {
                    Some(vw) => {
                        let input = Tensor::from_vec(vw.input.clone(), vw.input_shape, x.device())?;
                        let fm = net.forward(&input.unsqueeze(0)?)?.squeeze(0)?; // [F, h_f, w_f]
                        warp(&fm, &vw.op)? // [D, F, P]
                    }
                    None => Tensor::zeros((d, f, h * w), x.dtype(), x.device())?,
                });
            }
            samples.push(Tensor::stack(&views, 1)?); // [D, V, F, P]
        }
        out.push(Tensor::stack(&samples, 0)?.reshape((b, d, v, f, h, w))?);
    }
    Ok(out)
}

/// [`warped_features`] appended to `base` on dim 3: `[B, D, V, C_v, h_l, w_l]`, the
/// inputs rendering builds (for tests and checks; training keeps them apart).
pub fn with_warped_features(
    net: &FeatureNet,
    base: &[Tensor],
    tiles: &[TileWarps],
) -> candle_core::Result<Vec<Tensor>> {
    (base.iter().zip(warped_features(net, base, tiles)?))
        .map(|(x, f)| Tensor::cat(&[x, &f], 3))
        .collect()
}
