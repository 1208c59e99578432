//! The rays a prior is fitted to: each tuning view's layers rendered by the network
//! from its other views, sampled and stored ([`collect_view`]), and their error under a
//! grid.

use crate::rendering::{pick_sources, source_inputs, Prepared, RenderSettings};
use anyhow::{bail, Result};
use deepstereo_core::camera::Camera;
use deepstereo_core::mpi::{layers, layers_of_tiles, reference_camera, TileGrid};
use deepstereo_core::prior::{Cell, PriorGrid};
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use deepstereo_core::synth::Rng;
use glam::{DVec2, DVec3};
use rayon::prelude::*;

/// Stored rays: per ray its plane selection and colours, the photograph's colour, and
/// (once a grid exists) its plane points' cells.
pub struct Rays {
    pub planes: usize,
    pub selection: Vec<f32>,
    pub colours: Vec<[f32; 3]>,
    pub truth: Vec<[f32; 3]>,
    /// Per view read: its camera (as the layers were rendered), planes and first ray.
    pub(super) views: Vec<(Camera, Vec<f64>, usize)>,
    /// Each ray's pixel `(x, y)`.
    pub(super) pixels: Vec<(usize, usize)>,
    /// Expected surface point of each ray (the selection's mean inverse depth).
    pub(super) surface: Vec<DVec3>,
    pub(super) cells: Vec<Cell>,
}

impl Rays {
    pub fn new(planes: usize) -> Self {
        Self {
            planes,
            selection: Vec::new(),
            colours: Vec::new(),
            truth: Vec::new(),
            views: Vec::new(),
            pixels: Vec::new(),
            surface: Vec::new(),
            cells: Vec::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.truth.len()
    }

    pub fn is_empty(&self) -> bool {
        self.truth.is_empty()
    }

    /// Views read.
    pub fn views(&self) -> usize {
        self.views.len()
    }
}

/// Renders the layers of view `t` of `scene` from its nearest other views (none of
/// `exclude`) and keeps `count` random rays of it: of the whole view when `share` is 1
/// or more, else of `ceil(share * tiles)` of its tiles drawn at random (the network runs
/// on those alone).
#[allow(clippy::too_many_arguments)]
pub fn collect_view(
    backend: &dyn Backend,
    scene: &Scene,
    prepared: &mut Prepared,
    t: usize,
    exclude: &[usize],
    settings: &RenderSettings,
    (rng, count, share): (&mut Rng, usize, f64),
    rays: &mut Rays,
) -> Result<()> {
    let k = settings.source_count(backend.config())?;
    let cam = reference_camera(&scene.views[t].camera);
    let mut ex = exclude.to_vec();
    ex.push(t);
    let sources = pick_sources(scene, &cam, &ex, k, settings);
    let (srcs, inv) = source_inputs(backend.config(), scene, prepared, &sources, settings)?;
    if inv.len() != rays.planes {
        bail!(
            "{} planes where the prior expects {}",
            inv.len(),
            rays.planes
        );
    }
    let truth = scene.load_image(t)?;
    let (w, h) = (truth.width as usize, truth.height as usize);
    if (w, h)
        != (
            cam.intrinsics.width as usize,
            cam.intrinsics.height as usize,
        )
    {
        bail!("view {t}: its image is {w}x{h}, its camera another size");
    }
    let (c, s, pixels) = if share >= 1.0 {
        let (c, s) = layers(backend, &cam, &srcs, &inv, settings.tile, &|_, _| {})?;
        (c, s, pick_distinct(rng, w * h, count))
    } else {
        let grid = TileGrid::new(backend.config(), (w, h), settings.tile);
        let k = ((share.max(0.0) * grid.len() as f64).ceil() as usize).max(1);
        let tiles = pick_distinct(rng, grid.len(), k.min(grid.len()));
        let (c, s) = layers_of_tiles(backend, &cam, &srcs, &inv, (grid, &tiles), &|_, _| {})?;
        let covered: Vec<usize> = tiles.iter().flat_map(|&i| grid.pixels(i)).collect();
        let picked = pick_distinct(rng, covered.len(), count);
        let mut pixels: Vec<usize> = picked.into_iter().map(|i| covered[i]).collect();
        pixels.sort_unstable();
        (c, s, pixels)
    };
    rays.push(&cam, &inv, (&c, &s), &truth.data, &pixels);
    Ok(())
}

/// `count` distinct numbers of `0..n` (all when `count >= n`), ascending.
fn pick_distinct(rng: &mut Rng, n: usize, count: usize) -> Vec<usize> {
    if count >= n {
        return (0..n).collect();
    }
    let mut all: Vec<usize> = (0..n).collect();
    for i in 0..count {
        let j = i + rng.below(n - i);
        all.swap(i, j);
    }
    let mut out = all[..count].to_vec();
    out.sort_unstable();
    out
}

impl Rays {
    fn push(
        &mut self,
        cam: &Camera,
        inv: &[f64],
        (colours, selection): (&[f32], &[f32]),
        truth: &[f32],
        pixels: &[usize],
    ) {
        let d = inv.len();
        let w = cam.intrinsics.width as usize;
        let n = selection.len() / d;
        let centre = cam.pose.centre();
        self.views.push((*cam, inv.to_vec(), self.len()));
        for &p in pixels {
            let (x, y) = (p % w, p / w);
            let uv = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
            let unit = cam.unproject(uv, 1.0) - centre;
            let mut mean_rho = 0f64;
            for (z, &rho) in inv.iter().enumerate() {
                let s = selection[z * n + p];
                self.selection.push(s);
                self.colours.push(std::array::from_fn(|ch| {
                    colours[(z * 3 + ch) * n + p].clamp(0.0, 1.0)
                }));
                mean_rho += s as f64 * rho;
            }
            self.surface.push(match mean_rho > 0.0 {
                true => centre + unit / mean_rho,
                false => DVec3::NAN,
            });
            self.pixels.push((x, y));
            self.truth
                .push([truth[p * 3], truth[p * 3 + 1], truth[p * 3 + 2]]);
        }
    }

    /// A grid of zeros over the box of the rays' expected surface points (the 2nd to
    /// 98th percentile on each axis, grown by a tenth of its size on every side).
    pub fn grid(&self, cells: usize) -> Result<PriorGrid> {
        let mut lo = DVec3::ZERO;
        let mut hi = DVec3::ZERO;
        for a in 0..3 {
            let mut v: Vec<f64> = (self.surface.iter())
                .map(|p| p[a])
                .filter(|x| x.is_finite())
                .collect();
            if v.len() < 2 {
                bail!("the network saw no surface to place a prior grid around");
            }
            v.sort_by(f64::total_cmp);
            let top = v.len() - 1;
            let (a0, a1) = (v[top * 2 / 100], v[top * 98 / 100]);
            let pad = 0.1 * (a1 - a0).max(1e-6 * (1.0 + a0.abs()));
            lo[a] = a0 - pad;
            hi[a] = a1 + pad;
        }
        Ok(PriorGrid::zeros(lo, hi, cells)?)
    }

    /// Locates every ray's plane points in `grid`.
    pub fn locate(&mut self, grid: &PriorGrid) {
        let mut cells = Vec::with_capacity(self.len() * self.planes);
        for (i, (cam, inv, first)) in self.views.iter().enumerate() {
            let end = self.views.get(i + 1).map_or(self.len(), |v| v.2);
            cells.extend(grid.locate_rays(cam, inv, &self.pixels[*first..end]));
        }
        self.cells = cells;
    }

    /// The PSNR of the rays rendered with `grid` (located in it) against their
    /// photographs.
    pub fn psnr(&self, grid: &PriorGrid) -> f64 {
        let d = self.planes;
        let se: f64 = (0..self.len())
            .into_par_iter()
            .map(|r| {
                let span = r * d..(r + 1) * d;
                let (_, c) = grid.render_ray(
                    &self.selection[span.clone()],
                    &self.colours[span.clone()],
                    &self.cells[span],
                );
                (0..3)
                    .map(|k| ((c[k].clamp(0.0, 1.0) - self.truth[r][k]) as f64).powi(2))
                    .sum::<f64>()
            })
            .sum();
        let mse = se / (3 * self.len().max(1)) as f64;
        -10.0 * mse.max(1e-12).log10()
    }
}
