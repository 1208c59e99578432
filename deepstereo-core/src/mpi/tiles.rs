//! The network's layers at a reference camera, run tile by tile (an MPI's planes:
//! [`Mpi::from_layers`](super::Mpi::from_layers)).

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::inputs::{tile_inputs, PyramidSource};
use crate::render::Backend;

/// The tiles of a `width` x `height` view at side `tile` (rounded up to the model's
/// alignment, as [`layers`] runs them), row-major: tile `i` covers the pixels
/// `[x0, x0 + side) x [y0, y0 + side)` clipped to the view, `x0 = (i % across) side`,
/// `y0 = (i / across) side`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    pub side: usize,
    pub across: usize,
    pub down: usize,
    pub width: usize,
    pub height: usize,
}

impl TileGrid {
    pub fn new(cfg: &crate::config::Config, (width, height): (usize, usize), tile: usize) -> Self {
        let side = cfg.tile_side(tile, (width, height));
        Self {
            side,
            across: width.div_ceil(side),
            down: height.div_ceil(side),
            width,
            height,
        }
    }

    pub fn len(&self) -> usize {
        self.across * self.down
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Tile `i`'s first pixel `(x0, y0)`.
    pub fn origin(&self, i: usize) -> (usize, usize) {
        ((i % self.across) * self.side, (i / self.across) * self.side)
    }

    /// The view's pixels (`y * width + x`) tile `i` covers, ascending.
    pub fn pixels(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        let (x0, y0) = self.origin(i);
        let (x1, y1) = (
            (x0 + self.side).min(self.width),
            (y0 + self.side).min(self.height),
        );
        (y0..y1).flat_map(move |y| (x0..x1).map(move |x| y * self.width + x))
    }
}

/// The network's layers at `camera` (a pinhole: [`reference_camera`]) from `sources` at
/// `inv_depths`, tile by tile: colours `[D, 3, H, W]` and the
/// selection `[D, H, W]`, row-major (finite, or an error), the selection reweighed by
/// the backend's scene prior when it has one.
pub fn layers(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    tile: usize,
    progress: &dyn Fn(usize, usize),
) -> Result<(Vec<f32>, Vec<f32>)> {
    let (w, h) = camera.intrinsics.size();
    let grid = TileGrid::new(backend.config(), (w, h), tile);
    let all: Vec<usize> = (0..grid.len()).collect();
    layers_of_tiles(backend, camera, sources, inv_depths, (grid, &all), progress)
}

/// [`layers`] on the tiles `tiles` of `grid` only (a grid of `camera`'s size): the
/// network runs on those tiles alone, and the values of every other pixel are 0.
/// Each tile's values are those [`layers`] gives it (tiles are run independently).
pub fn layers_of_tiles(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    (grid, tiles): (TileGrid, &[usize]),
    progress: &dyn Fn(usize, usize),
) -> Result<(Vec<f32>, Vec<f32>)> {
    let cfg = backend.config();
    let (w, h) = camera.intrinsics.size();
    if (grid.width, grid.height) != (w, h) || grid != TileGrid::new(cfg, (w, h), grid.side) {
        return Err(Error::Invalid(format!(
            "a tile grid of {}x{} pixels (side {}) for a {w}x{h} camera",
            grid.width, grid.height, grid.side
        )));
    }
    if let Some(&i) = tiles.iter().find(|&&i| i >= grid.len()) {
        return Err(Error::Invalid(format!("tile {i} of {}", grid.len())));
    }
    let d = inv_depths.len();
    if d == 0 {
        return Err(Error::Invalid("at least one depth plane is needed".into()));
    }
    let (n, tile) = (w * h, grid.side);
    let what = |c: usize| format!("MPI layers of {d} planes x {c} x {w}x{h}");
    let mut colours = crate::sweep::try_zeroed(&[d, 3, n], &what(3))?;
    let mut selection = crate::sweep::try_zeroed(&[d, n], &what(1))?;
    for (done, &i) in tiles.iter().enumerate() {
        let (x0, y0) = grid.origin(i);
        let (c, s) = tile_layers(backend, camera, sources, inv_depths, (x0, y0), tile)?;
        let tt = tile * tile;
        for p in grid.pixels(i) {
            let q = (p / w - y0) * tile + (p % w - x0);
            for z in 0..d {
                selection[z * n + p] = s[z * tt + q];
                for ch in 0..3 {
                    colours[(z * 3 + ch) * n + p] = c[(z * 3 + ch) * tt + q];
                }
            }
        }
        progress(done + 1, tiles.len());
    }
    Ok((colours, selection))
}

/// The network's colours `[D, 3, tile, tile]` and selection `[D, tile, tile]` on the
/// square of side `tile` at `(x0, y0)` of `camera` (the selection reweighed by the
/// backend's scene prior when it has one); an error when any value is not finite.
pub(crate) fn tile_layers(
    backend: &dyn Backend,
    camera: &Camera,
    sources: &[&PyramidSource],
    inv_depths: &[f64],
    (x0, y0): (usize, usize),
    tile: usize,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let inputs = tile_inputs(
        backend.config(),
        camera,
        sources,
        inv_depths,
        (x0 as i64, y0 as i64),
        (tile, tile),
    )?;
    let (c, mut s) = backend.run_layers(&inputs, inv_depths.len())?;
    if let Some(prior) = backend.prior() {
        prior.apply_tile(camera, inv_depths, (x0, y0), tile, &c, &mut s);
    }
    if c.iter().chain(&s).any(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!(
            "the network produced non-finite values in the tile at ({x0}, {y0})"
        )));
    }
    Ok((c, s))
}
