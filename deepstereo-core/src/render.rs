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
use crate::prior::PriorGrid;
use crate::prune::{Block, PruneStats, Pruner, TilePlan};
use candle_core::{Device, Tensor};
use std::time::Instant;

/// Runs the network on one tile's inputs.
pub trait Backend: Sync {
    /// Name for reports (`candle`, `ort`).
    fn name(&self) -> &str;
    fn config(&self) -> &Config;
    /// Returns the image `[3, th, tw]` and the selection `[D, th, tw]`, row-major.
    fn run(&self, inputs: &TileInputs, planes: usize) -> Result<(Vec<f32>, Vec<f32>)>;
    /// Returns every plane's colour `[D, 3, th, tw]` and the selection `[D, th, tw]`,
    /// row-major: the layers a multiplane image is baked from. Backends that run only
    /// the exported graph (image and selection) refuse.
    fn run_layers(&self, _inputs: &TileInputs, _planes: usize) -> Result<(Vec<f32>, Vec<f32>)> {
        Err(Error::Invalid(format!(
            "the {} backend returns no per-plane colours: bake multiplane images with candle",
            self.name()
        )))
    }
    /// Whether [`Backend::run_layers`] works.
    fn has_layers(&self) -> bool {
        false
    }
    /// The scene prior the renderers apply to the network's selection (a tuned model's;
    /// [`crate::prior`]): it needs [`Backend::run_layers`].
    fn prior(&self) -> Option<&PriorGrid> {
        None
    }
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
        self.infer(inputs, planes, |out| &out.image)
    }
    fn run_layers(&self, inputs: &TileInputs, planes: usize) -> Result<(Vec<f32>, Vec<f32>)> {
        self.infer(inputs, planes, |out| &out.colours)
    }
    fn has_layers(&self) -> bool {
        true
    }
    fn prior(&self) -> Option<&PriorGrid> {
        self.model.prior()
    }
}

impl CandleBackend {
    /// The network on one tile: `colour(output)` (the image or the per-plane colours) and
    /// the selection, flattened.
    fn infer(
        &self,
        inputs: &TileInputs,
        planes: usize,
        colour: impl Fn(&crate::model::Output) -> &candle_core::Tensor,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let tensors = inputs_to_tensors(self.config(), inputs, 1, planes, &self.device)?;
        let out = self.model.infer(&tensors)?;
        let c = colour(&out).flatten_all()?.to_vec1::<f32>()?;
        let selection = out.selection.flatten_all()?.to_vec1::<f32>()?;
        Ok((c, selection))
    }
}

/// Wraps per-level data `[B * D * V * 4 * h * w]` as the tensors the model `cfg` takes:
/// `[B, D, 4V, h, w]` or `[B, D, V, 4, h, w]` ([`Config::input_shape`]).
pub fn inputs_to_tensors(
    cfg: &Config,
    inputs: &TileInputs,
    b: usize,
    d: usize,
    device: &Device,
) -> Result<Vec<Tensor>> {
    inputs
        .levels
        .iter()
        .zip(&inputs.sizes)
        .map(|(data, &(h, w))| {
            let shape = cfg.input_shape(b, d, inputs.views, h, w);
            Ok(Tensor::from_slice(data, shape, device)?)
        })
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
    /// What pruning left out (`None`: rendered unpruned).
    pub prune: Option<PruneStats>,
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
    render_view_pruned(backend, target, sources, inv_depths, tile, None, progress)
}

/// [`render_view`], with the tiles planned by `pruner` (see [`crate::prune`]): the network
/// runs only on the planes each block of a tile keeps (the selection is 0 elsewhere), and not at all
/// on tiles no source covers or whose sources are constant there. `None`: every plane of
/// every tile, exactly [`render_view`].
pub fn render_view_pruned(
    backend: &dyn Backend,
    target: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    tile: usize,
    pruner: Option<&Pruner<'_>>,
    progress: &dyn Fn(usize, usize),
) -> Result<Rendered> {
    let (w, h) = (
        target.intrinsics.width as usize,
        target.intrinsics.height as usize,
    );
    let tile = backend.config().tile_side(tile, (w, h));
    let d = inv_depths.len();
    if d == 0 {
        return Err(Error::Invalid("at least one depth plane is needed".into()));
    }
    let mut out = Rendered::blank(w, h);
    let (ntx, nty) = (w.div_ceil(tile), h.div_ceil(tile));
    let total = ntx * nty;
    let mut stats = PruneStats {
        tiles: total,
        planes_total: total * tile * tile * d,
        ..PruneStats::default()
    };
    let mut empty: Option<(Vec<f32>, Vec<f32>)> = None;
    for ty in 0..nty {
        for tx in 0..ntx {
            let t0 = Instant::now();
            let blocks = plan_tile(pruner, tx * tile, ty * tile, tile, d);
            stats.coarse_seconds += t0.elapsed().as_secs_f64();
            for block in blocks {
                let area = Area::of(&block, w, h);
                match &block.plan {
                    TilePlan::Uncovered => {
                        stats.uncovered += 1;
                        if empty.is_none() {
                            empty = Some(empty_response(backend, d)?);
                        }
                        let (img, sel) = empty
                            .as_ref()
                            .map(|(i, s)| (i.as_slice(), s.as_slice()))
                            .unwrap_or_default();
                        fill_uncovered(&mut out, &area, inv_depths, img, sel);
                    }
                    TilePlan::Flat { colour, coverage } => {
                        stats.flat += 1;
                        let range = pruner.map_or((0, d - 1), |p| p.range());
                        fill_flat(&mut out, &area, inv_depths, range, colour, *coverage);
                    }
                    TilePlan::Planes(planes) => {
                        let job = BlockJob {
                            backend,
                            target,
                            sources,
                            inv_depths,
                        };
                        job.run(&mut out, &mut stats, &area, planes)?;
                    }
                }
            }
            progress(ty * ntx + tx + 1, total);
        }
    }
    if let Some(p) = pruner {
        stats.coarse_seconds += p.guide_seconds();
        stats.depth_range = Some(p.range()).filter(|&r| r != (0, d - 1));
        out.prune = Some(stats);
    }
    Ok(out)
}

impl Rendered {
    /// A `w` x `h` render with every value 0.
    fn blank(w: usize, h: usize) -> Self {
        Rendered {
            image: RgbImage::new(w as u32, h as u32),
            depth: vec![0.0; w * h],
            confidence: vec![0.0; w * h],
            coverage: vec![0.0; w * h],
            prune: None,
        }
    }
}

/// The blocks of the tile at `(x0, y0)`: the pruner's plan, or the whole tile on every plane.
fn plan_tile(
    pruner: Option<&Pruner<'_>>,
    x0: usize,
    y0: usize,
    tile: usize,
    d: usize,
) -> Vec<Block> {
    match pruner {
        Some(p) => p.plan(x0, y0, tile),
        None => vec![Block {
            x0,
            y0,
            size: tile,
            plan: TilePlan::Planes((0..d).collect()),
        }],
    }
}

/// A block's place in the image: its origin and side, and the rows and columns of it
/// inside the image (`w` pixels wide).
struct Area {
    x0: usize,
    y0: usize,
    size: usize,
    w: usize,
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
}

impl Area {
    fn of(b: &Block, w: usize, h: usize) -> Self {
        Area {
            x0: b.x0,
            y0: b.y0,
            size: b.size,
            w,
            rows: b.y0..(b.y0 + b.size).min(h),
            cols: b.x0..(b.x0 + b.size).min(w),
        }
    }

    /// Every pixel index of the area inside the image, row by row.
    fn pixels(&self) -> impl Iterator<Item = usize> + '_ {
        self.rows
            .clone()
            .flat_map(move |y| self.cols.clone().map(move |x| y * self.w + x))
    }
}

/// A block no source covers: the network's response to empty inputs, `img` and `sel`.
fn fill_uncovered(out: &mut Rendered, area: &Area, inv_depths: &[f64], img: &[f32], sel: &[f32]) {
    let d = inv_depths.len();
    for pix in area.pixels() {
        out.image.data[pix * 3..pix * 3 + 3].copy_from_slice(img);
        let (rho, best) = expectation(inv_depths, 0..d, sel.iter().copied());
        write_depth(out, pix, rho, best, 0.0);
    }
}

/// A block whose sources are constant: their colour, a uniform selection over `range`.
fn fill_flat(
    out: &mut Rendered,
    area: &Area,
    inv_depths: &[f64],
    (z0, z1): (usize, usize),
    colour: &[f32; 3],
    coverage: f32,
) {
    let p = 1.0 / (z1 + 1 - z0) as f32;
    for pix in area.pixels() {
        out.image.data[pix * 3..pix * 3 + 3].copy_from_slice(colour);
        let (rho, best) = expectation(inv_depths, z0..z1 + 1, (z0..=z1).map(|_| p));
        write_depth(out, pix, rho, best, coverage);
    }
}

/// What running the network on a block needs.
struct BlockJob<'a, 'b> {
    backend: &'a dyn Backend,
    target: &'a Camera,
    sources: &'a [&'b PyramidSource],
    inv_depths: &'a [f64],
}

impl BlockJob<'_, '_> {
    /// Runs the network on the block's `planes` and writes its colour, expected depth,
    /// confidence and coverage.
    fn run(
        &self,
        out: &mut Rendered,
        stats: &mut PruneStats,
        area: &Area,
        planes: &[usize],
    ) -> Result<()> {
        let cfg = self.backend.config();
        let (x0, y0, tile) = (area.x0, area.y0, area.size);
        let band: Vec<f64> = planes.iter().map(|&z| self.inv_depths[z]).collect();
        let nb = band.len();
        stats.planes_run += nb * tile * tile;
        stats.calls += 1;
        let t1 = Instant::now();
        let inputs = tile_inputs(
            cfg,
            self.target,
            self.sources,
            &band,
            (x0 as i64, y0 as i64),
            (tile, tile),
        )?;
        let t2 = Instant::now();
        let (img, sel) = match self.backend.prior() {
            None => self.backend.run(&inputs, nb)?,
            Some(grid) => {
                let (c, mut s) = self.backend.run_layers(&inputs, nb)?;
                let img = grid.apply_tile(self.target, &band, (x0, y0), tile, &c, &mut s);
                (img, s)
            }
        };
        stats.warp_seconds += (t2 - t1).as_secs_f64();
        stats.network_seconds += t2.elapsed().as_secs_f64();
        if img.iter().chain(&sel).any(|x| !x.is_finite()) {
            return Err(Error::Invalid(format!(
                "the network produced non-finite values in the tile at ({x0}, {y0})"
            )));
        }
        write_block(out, area, &inputs, cfg.pad(0), &band, &img, &sel);
        Ok(())
    }
}

/// Writes a block's network output: colour (clamped), and from the selection over `band`
/// the expected depth, the confidence and the selection-weighted coverage of the sources
/// (their alpha in the level-0 inputs, `pad` pixels of border around the block).
fn write_block(
    out: &mut Rendered,
    area: &Area,
    inputs: &TileInputs,
    pad: usize,
    band: &[f64],
    img: &[f32],
    sel: &[f32],
) {
    let (tile, w) = (area.size, area.w);
    let v = inputs.views;
    let tt = tile * tile;
    for yy in 0..area.rows.len() {
        for xx in 0..area.cols.len() {
            let o = yy * tile + xx;
            let pix = (area.y0 + yy) * w + area.x0 + xx;
            for ch in 0..3 {
                out.image.data[pix * 3 + ch] = img[ch * tt + o].clamp(0.0, 1.0);
            }
            let (mut rho, mut best, mut cov) = (0.0f64, 0.0f32, 0.0f32);
            for (z, r) in band.iter().enumerate() {
                let s = sel[z * tt + o];
                rho += s as f64 * r;
                best = best.max(s);
                let mut alpha = 0.0;
                for k in 0..v {
                    alpha += inputs.levels[0][inputs.alpha_index(0, z, k, (xx + pad, yy + pad))];
                }
                cov += s * alpha / v as f32;
            }
            write_depth(out, pix, rho, best, cov);
        }
    }
}

/// Expected inverse depth and largest probability of a selection over `planes`.
fn expectation(
    inv_depths: &[f64],
    planes: std::ops::Range<usize>,
    sel: impl Iterator<Item = f32>,
) -> (f64, f32) {
    let (mut rho, mut best) = (0.0f64, 0.0f32);
    for (s, r) in sel.zip(&inv_depths[planes]) {
        rho += s as f64 * r;
        best = best.max(s);
    }
    (rho, best)
}

fn write_depth(out: &mut Rendered, pix: usize, rho: f64, best: f32, coverage: f32) {
    out.depth[pix] = if rho > 0.0 {
        (1.0 / rho) as f32
    } else {
        f32::INFINITY
    };
    out.confidence[pix] = best;
    out.coverage[pix] = coverage;
}

/// The network's colour and selection `[D]` for a pixel whose inputs are all empty (no
/// source covers it at any plane): every such pixel gets exactly these, so one minimal
/// tile gives them.
pub fn empty_response(backend: &dyn Backend, planes: usize) -> Result<(Vec<f32>, Vec<f32>)> {
    let cfg = backend.config();
    let a = cfg.tile_align();
    // One empty view is as empty as any number for the pooled family.
    let views = if cfg.pool.is_some() { 1 } else { cfg.views };
    let sizes: Vec<(usize, usize)> = (0..cfg.levels)
        .map(|l| (cfg.input_size(l, a), cfg.input_size(l, a)))
        .collect();
    let levels = sizes
        .iter()
        .map(|(h, w)| vec![0.0f32; planes * cfg.view_channels() * views * h * w])
        .collect();
    let inputs = TileInputs {
        levels,
        sizes,
        views,
        channels: cfg.view_channels(),
    };
    let (img, sel) = backend.run(&inputs, planes)?;
    let n = a * a;
    Ok((
        (0..3).map(|ch| img[ch * n].clamp(0.0, 1.0)).collect(),
        (0..planes).map(|z| sel[z * n]).collect(),
    ))
}
