//! Full-image rendering, tile by tile with bounded memory.
//!
//! Tiles start at multiples of the model's alignment, so the result is identical to
//! rendering the whole image as one tile (see `config.rs`). The network runs through a
//! [`Backend`], so candle and onnxruntime render through the same code.

pub use crate::backend::{inputs_to_tensors, Backend, CandleBackend};
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::imageio::RgbImage;
use crate::inputs::{tile_inputs, PyramidSource, TileInputs};
use crate::prune::{Block, PruneStats, Pruner, TilePlan};
use std::time::Instant;

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
    let computed = crate::backend::missing_features(backend, sources)?;
    let refs: Vec<&PyramidSource> = computed.iter().flatten().collect();
    let sources = if computed.is_some() {
        &refs[..]
    } else {
        sources
    };
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
