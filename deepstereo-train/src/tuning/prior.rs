//! Fitting a scene's selection prior ([`deepstereo_core::prior`]) by leaving one view out:
//! the network renders each tuning view's layers from its other views once, and the
//! grid's log-weights are fitted so that the reweighed layers reproduce the photographs
//! (L1 and a small smoothness term, Adam). The network's weights
//! do not move, so the fit runs on stored layers, thousands of rays per step, without the
//! network in the loop.

mod need;
mod rays;

pub use need::PriorNeed;
use need::{fit_rays, FitTime};
pub use rays::{collect_view, Rays};

use crate::rendering::{Prepared, RenderSettings};
use crate::training::optim::{ADAM_BETAS, ADAM_EPS};
use anyhow::{bail, Result};
use deepstereo_core::prior::{PriorGrid, MAX_LOG_WEIGHT, SHARPNESS_RANGE};
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use deepstereo_core::synth::Rng;
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// How a prior is fitted.
#[derive(Clone, Debug)]
pub struct PriorOptions {
    /// Cells along the grid's longest side.
    pub cells: usize,
    /// Most rays kept per view (drawn at random, without repetition).
    pub rays_per_view: usize,
    /// Most rays kept in all (fewer per view when many views are read).
    pub max_rays: usize,
    /// Most views read.
    pub max_views: usize,
    /// Share of each view's tiles the network runs on when the view is read (at least
    /// one tile; rays are drawn from those tiles): below 1, more views are read in a
    /// time budget, each less densely.
    pub view_share: f64,
    /// Adam steps of the final fit.
    pub steps: usize,
    /// Rays per step.
    pub batch: usize,
    /// Adam's rate (log-weight units).
    pub lr: f32,
    /// Weight of the squared difference of neighbouring cells (1e-7: large enough that
    /// the views set aside stop peaking early, small enough not to blur; docs/results.md).
    pub smooth: f32,
    /// Whether the scene's sharpness (the selection's exponent) is fitted with the
    /// log-weights (Adam on its logarithm, at `lr`); otherwise it stays 1.
    pub sharpen: bool,
    /// Validation (on the views set aside) every this many steps.
    pub validate_every: usize,
    pub seed: u64,
    /// A grid to start the fit from, its box and log-weights and sharpness, instead of
    /// zeros over the rays' box (`tune --refit`: the prior fitted before the network's
    /// fine-tune, refitted on the tuned network).
    pub init: Option<PriorGrid>,
}

impl Default for PriorOptions {
    fn default() -> Self {
        Self {
            cells: 32,
            rays_per_view: 16384,
            max_rays: 600_000,
            max_views: 96,
            view_share: 1.0,
            steps: 1000,
            batch: 16384,
            lr: 0.05,
            smooth: 1e-7,
            sharpen: true,
            validate_every: 100,
            seed: 0,
            init: None,
        }
    }
}

impl PriorOptions {
    /// Refuses options no fit can run with (named by their `tune` flags), before any
    /// work: a grid of fewer than 2 cells, a negative or non-finite smoothness weight.
    pub fn check(&self) -> Result<()> {
        if self.cells < 2 {
            bail!("--prior-cells must be at least 2, got {}", self.cells);
        }
        if !(self.smooth.is_finite() && self.smooth >= 0.0) {
            bail!(
                "--prior-smooth must be a finite number >= 0, got {}",
                self.smooth
            );
        }
        Ok(())
    }

    /// Rays kept per view when `views` tuning views are read: `rays_per_view`, fewer when
    /// that many views would pass `max_rays`.
    pub fn rays_per_view_of(&self, views: usize) -> usize {
        self.rays_per_view.min(self.max_rays / views.max(1)).max(1)
    }
}

/// What a fit did.
#[derive(Clone, Debug)]
pub struct Fit {
    /// Steps taken.
    pub steps: usize,
    /// `(step, PSNR)` of each validation on the views set aside (step 0: the grid given).
    pub validation: Vec<(usize, f64)>,
    /// The step whose log-weights the grid ends with.
    pub best_step: usize,
    /// Whether `stop` ended it.
    pub interrupted: bool,
}

impl Fit {
    /// The validation PSNR of the grid kept (NaN without validation).
    pub fn best_psnr(&self) -> f64 {
        (self.validation.iter())
            .find(|v| v.0 == self.best_step)
            .map_or(f64::NAN, |v| v.1)
    }
}

/// Fits `grid` to `rays` (both located in it) with Adam on the L1 error, validating on
/// `val` (when it has rays) every `opts.validate_every` steps and at the end; the grid
/// ends with the log-weights that validated best (the grid given when none did better).
pub fn fit(
    grid: &mut PriorGrid,
    rays: &Rays,
    val: &Rays,
    opts: &PriorOptions,
    stop: &AtomicBool,
    mut on_validate: impl FnMut(usize, f64),
) -> Fit {
    let nr = rays.len();
    let mut adam: Vec<AdamScalar> = (0..grid.values.len()).map(|_| Default::default()).collect();
    let mut rng = Rng::new(opts.seed ^ 0xf17_9a1d);
    let batch = opts.batch.min(nr).max(1);
    let threads = rayon::current_num_threads().max(1);
    let validate = |g: &PriorGrid| {
        if val.is_empty() {
            f64::NAN
        } else {
            val.psnr(g)
        }
    };
    let first = validate(grid);
    on_validate(0, first);
    let mut out = Fit {
        steps: 0,
        validation: vec![(0, first)],
        best_step: 0,
        interrupted: false,
    };
    let mut best = (grid.values.clone(), grid.sharpness, first);
    let mut sharp = AdamScalar::default();
    for step in 1..=opts.steps {
        if nr == 0 {
            break;
        }
        if stop.load(Ordering::SeqCst) {
            out.interrupted = true;
            break;
        }
        let picks: Vec<usize> = (0..batch).map(|_| rng.below(nr)).collect();
        let (mut grad, grad_g) = batch_gradient(grid, rays, &picks, threads);
        smoothness_gradient(grid, opts.smooth, &mut grad);
        let c = AdamScalar::corrections(step as i32);
        for ((b, a), g) in grid.values.iter_mut().zip(&mut adam).zip(&grad) {
            *b = (*b - a.step(*g, c, opts.lr)).clamp(-MAX_LOG_WEIGHT, MAX_LOG_WEIGHT);
        }
        if opts.sharpen {
            // Adam on ln g: dL/d(ln g) = g dL/dg.
            let lg = grid.sharpness.ln() - sharp.step(grid.sharpness * grad_g, c, opts.lr);
            let (lo, hi) = SHARPNESS_RANGE;
            grid.sharpness = lg.exp().clamp(lo, hi);
        }
        out.steps = step;
        if step % opts.validate_every.max(1) == 0 || step == opts.steps {
            let psnr = validate(grid);
            on_validate(step, psnr);
            out.validation.push((step, psnr));
            // Without validation views the last step is kept.
            if psnr > best.2 || val.is_empty() {
                best = (grid.values.clone(), grid.sharpness, psnr);
                out.best_step = step;
            }
        }
    }
    (grid.values, grid.sharpness) = (best.0, best.1);
    out
}

/// The gradient of the mean L1 error of the rays `picks` to the grid's log-weights and
/// to its sharpness, summed over `threads` parts in parallel (in part order).
fn batch_gradient(
    grid: &PriorGrid,
    rays: &Rays,
    picks: &[usize],
    threads: usize,
) -> (Vec<f32>, f32) {
    let (d, batch) = (rays.planes, picks.len());
    let scale = 1.0 / (3.0 * batch as f32);
    let parts: Vec<(Vec<f32>, f32)> = picks
        .par_chunks(batch.div_ceil(threads))
        .map(|chunk| {
            let (mut grad, mut grad_g) = (vec![0f32; grid.values.len()], 0f32);
            for &r in chunk {
                let span = r * d..(r + 1) * d;
                grid.ray_gradient(
                    &rays.selection[span.clone()],
                    &rays.colours[span.clone()],
                    &rays.cells[span],
                    rays.truth[r],
                    scale,
                    &mut grad,
                    &mut grad_g,
                );
            }
            (grad, grad_g)
        })
        .collect();
    let (mut grad, mut grad_g) = (vec![0f32; grid.values.len()], 0f32);
    for (p, pg) in parts {
        grad.iter_mut().zip(p).for_each(|(a, b)| *a += b);
        grad_g += pg;
    }
    (grad, grad_g)
}

/// Adam's moments for one value (the prior's own Adam: a plain loop over the grid's
/// values, which are not candle variables).
#[derive(Default)]
struct AdamScalar {
    m: f32,
    v: f32,
}

const BETAS: (f32, f32) = (ADAM_BETAS.0 as f32, ADAM_BETAS.1 as f32);

impl AdamScalar {
    /// The bias corrections `(1 - b1^t, 1 - b2^t)` of step `t` (from 1), the same for
    /// every value of a step.
    fn corrections(t: i32) -> (f32, f32) {
        (1.0 - BETAS.0.powi(t), 1.0 - BETAS.1.powi(t))
    }

    /// The update (to subtract) for gradient `g` with the step's `corrections` and rate
    /// `lr`.
    fn step(&mut self, g: f32, (c1, c2): (f32, f32), lr: f32) -> f32 {
        let (b1, b2) = BETAS;
        self.m = b1 * self.m + (1.0 - b1) * g;
        self.v = b2 * self.v + (1.0 - b2) * g * g;
        lr * (self.m / c1) / ((self.v / c2).sqrt() + ADAM_EPS as f32)
    }
}

/// Adds the gradient of `w * sum (b_i - b_j)^2` over neighbouring cells.
fn smoothness_gradient(grid: &PriorGrid, w: f32, grad: &mut [f32]) {
    if w == 0.0 {
        return;
    }
    let [nx, ny, nz] = grid.dims;
    let b = &grid.values;
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let i = x + nx * (y + ny * z);
                for (ok, j) in [
                    (x + 1 < nx, i + 1),
                    (y + 1 < ny, i + nx),
                    (z + 1 < nz, i + nx * ny),
                ] {
                    if ok {
                        let dlt = 2.0 * w * (b[i] - b[j]);
                        grad[i] += dlt;
                        grad[j] -= dlt;
                    }
                }
            }
        }
    }
}

/// How long fitting a scene's prior may take.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PriorBudget {
    /// Read every view (up to [`PriorOptions::max_views`]), then fit: the output depends
    /// only on the inputs and the seed.
    AllViews,
    /// Read views until the final fit would not end within this many seconds.
    Seconds(f64),
}

impl PriorBudget {
    /// Whether a time budget leaves too little, `elapsed` seconds in, for reading one more
    /// view and then fitting on `next` views (`reserve`: the fit's measured time).
    fn spent(self, elapsed: f64, reserve: Option<FitTime>, next: usize) -> bool {
        match self {
            PriorBudget::Seconds(b) => elapsed + reserve.map_or(0.0, |r| r.of(next)) >= b,
            PriorBudget::AllViews => false,
        }
    }

    /// The share of the budget used `elapsed` seconds in, with `collected` views read (of
    /// them `read` of the `total` fitting views); at most 1.
    fn share(
        self,
        (elapsed, reserve): (f64, Option<FitTime>),
        collected: usize,
        (read, total): (usize, usize),
    ) -> f64 {
        match self {
            PriorBudget::Seconds(b) => (elapsed + reserve.map_or(0.0, |r| r.of(collected))) / b,
            PriorBudget::AllViews => read as f64 / total.max(1) as f64,
        }
        .min(1.0)
    }
}

/// What fitting a scene's prior did.
#[derive(Default)]
pub struct SceneFit {
    /// The fitted grid (`None` when interrupted before any view was read).
    pub grid: Option<PriorGrid>,
    pub fit: Option<Fit>,
    /// Views read, and rays kept.
    pub views: usize,
    pub rays: usize,
    /// Seconds spent (the curve's snapshot fits excluded).
    pub seconds: f64,
    /// `(seconds, grid)`: the grid fitted on the views read by each snapshot time.
    pub snapshots: Vec<(f64, PriorGrid)>,
    pub interrupted: bool,
}

/// What the caller hears while a prior is fitted.
pub struct PriorProgress {
    /// Views read of those that will be read at most.
    pub views: (usize, usize),
    /// Share of the time budget used (views read without one).
    pub share: f64,
    /// The validation PSNR when the fit validated.
    pub val_psnr: Option<f64>,
}

/// The order views are read in: spread over the capture, so that the views read by any
/// time cover it (index `i` by the fractional part of `i` times the golden ratio).
pub fn spread_order(views: &[usize]) -> Vec<usize> {
    let mut v: Vec<(f64, usize)> = (views.iter().enumerate())
        .map(|(i, &x)| ((i as f64 * 0.618_033_988_749_895).fract(), x))
        .collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    v.into_iter().map(|(_, x)| x).collect()
}

/// Fits the prior of `scene` (every view of it may be a source) with the views `train`
/// as targets, validated on the views `validation`. `snapshots` are times (seconds of
/// the whole tune, which began `clock_offset` seconds before this call) at which a grid
/// fitted on the views read so far is kept, for a curve.
#[allow(clippy::too_many_arguments)]
pub fn fit_scene(
    backend: &dyn Backend,
    scene: &Scene,
    (train, validation): (&[usize], &[usize]),
    settings: &RenderSettings,
    opts: &PriorOptions,
    budget: PriorBudget,
    (snapshots, clock_offset): (&[f64], f64),
    stop: &AtomicBool,
    mut progress: impl FnMut(&PriorProgress),
) -> Result<SceneFit> {
    let t0 = Instant::now();
    let mut paused = 0f64;
    // The planes the network was trained at (not a tuned model's render_planes): the
    // grid is in world space and applies at any plane count.
    let planes = settings.planes.unwrap_or(backend.config().planes);
    let mut order = spread_order(train);
    order.truncate(opts.max_views);
    let total = order.len();
    let per_view = opts.rays_per_view_of(total);
    let mut prepared = Prepared::new(scene);
    let mut rng = Rng::new(opts.seed ^ 0x005e_ed0f_9a1d);
    let mut val = Rays::new(planes);
    for &v in validation {
        let r = (&mut rng, per_view, 1.0);
        collect_view(backend, scene, &mut prepared, v, &[], settings, r, &mut val)?;
    }
    let mut rays = Rays::new(planes);
    let mut out = SceneFit::default();
    let mut reserve = None;
    for &t in &order {
        let elapsed = t0.elapsed().as_secs_f64() - paused;
        if budget.spent(elapsed, reserve, rays.views() + val.views() + 1) {
            break;
        }
        if stop.load(Ordering::SeqCst) {
            out.interrupted = true;
            break;
        }
        let (r, p) = ((&mut rng, per_view, opts.view_share), &mut prepared);
        collect_view(backend, scene, p, t, &[], settings, r, &mut rays)?;
        let elapsed = t0.elapsed().as_secs_f64() - paused;
        if reserve.is_none() {
            reserve = Some(FitTime::measure(&mut rays, val.len(), opts)?);
        }
        let window = (clock_offset, clock_offset + elapsed);
        paused += snapshot_fits(snapshots, window, (&mut rays, &mut val), opts, &mut out)?;
        let collected = rays.views() + val.views();
        progress(&PriorProgress {
            views: (rays.views(), total),
            share: budget.share((elapsed, reserve), collected, (rays.views(), total)),
            val_psnr: None,
        });
    }
    if rays.is_empty() {
        out.interrupted |= stop.load(Ordering::SeqCst);
        out.seconds = t0.elapsed().as_secs_f64() - paused;
        return Ok(out);
    }
    let left = match budget {
        PriorBudget::Seconds(b) => Some(b - (t0.elapsed().as_secs_f64() - paused)),
        PriorBudget::AllViews => None,
    };
    // With a time budget, the fit takes the steps that end within it.
    let budget = (opts, left, reserve);
    let (grid, fit) = final_fit((&mut rays, &mut val), total, budget, stop, progress)?;
    out.interrupted |= fit.interrupted;
    out.views = rays.views();
    out.rays = rays.len();
    out.grid = Some(grid);
    out.fit = Some(fit);
    out.seconds = t0.elapsed().as_secs_f64() - paused;
    Ok(out)
}

/// [`fit_scene`]'s fit of the rays collected from `total` views: with `left` seconds of a
/// time budget, the steps that end within it (as `reserve` measured them), else
/// `opts.steps`; progress after each validation.
fn final_fit(
    (rays, val): (&mut Rays, &mut Rays),
    total: usize,
    (opts, left, reserve): (&PriorOptions, Option<f64>, Option<FitTime>),
    stop: &AtomicBool,
    mut progress: impl FnMut(&PriorProgress),
) -> Result<(PriorGrid, Fit)> {
    let views = (rays.views(), total);
    let mut fo = opts.clone();
    if let (Some(left), Some(r)) = (left, reserve) {
        fo.steps = r.steps_within(left, rays.views() + val.views(), opts.steps);
    }
    fit_rays(rays, val, &fo, stop, |_, psnr| {
        progress(&PriorProgress {
            views,
            share: 1.0,
            val_psnr: Some(psnr),
        })
    })
}

/// The fits of the rays collected so far for each time of `snapshots` within `window`
/// (on the tune's clock: times before it belong to the network's fine-tune) not yet in
/// `out`'s snapshots, added there; the seconds they took.
fn snapshot_fits(
    snapshots: &[f64],
    (from, to): (f64, f64),
    (rays, val): (&mut Rays, &mut Rays),
    opts: &PriorOptions,
    out: &mut SceneFit,
) -> Result<f64> {
    let never = AtomicBool::new(false);
    let mut paused = 0.0;
    for &s in snapshots {
        let due = s >= from && s <= to;
        if due && !out.snapshots.iter().any(|(x, _)| *x == s) {
            let p0 = Instant::now();
            let (grid, _) = fit_rays(rays, val, opts, &never, |_, _| {})?;
            out.snapshots.push((s, grid));
            paused += p0.elapsed().as_secs_f64();
        }
    }
    Ok(paused)
}

#[cfg(test)]
mod tests {
    use super::*;
    use deepstereo_core::prior::Cell;
    use glam::DVec3;

    /// `n` rays of `d` planes with random selections and colours, located at random
    /// points of `grid`, whose photographs are their render with `truth`.
    fn rays_rendered_by(truth: &PriorGrid, grid: &PriorGrid, n: usize, seed: u64) -> Rays {
        let d = 6;
        let mut rng = Rng::new(seed);
        let mut rays = Rays::new(d);
        for _ in 0..n {
            let logits: Vec<f64> = (0..d).map(|_| rng.sym(3.0)).collect();
            let sum: f64 = logits.iter().map(|l| l.exp()).sum();
            let s: Vec<f32> = logits.iter().map(|l| (l.exp() / sum) as f32).collect();
            let c: Vec<[f32; 3]> = (0..d)
                .map(|_| std::array::from_fn(|_| rng.unit() as f32))
                .collect();
            let cells: Vec<Cell> = (0..d)
                .map(|_| {
                    let p = DVec3::new(rng.sym(1.0), rng.sym(1.0), rng.range(1.0, 3.0));
                    grid.locate(p)
                })
                .collect();
            let (_, colour) = truth.render_ray(&s, &c, &cells);
            rays.selection.extend(s);
            rays.colours.extend(c);
            rays.cells.extend(cells);
            rays.truth.push(colour);
        }
        rays
    }

    /// Reading a share of a view keeps rays of that many of its tiles only, each with the
    /// layers the whole view has at its pixel.
    #[test]
    fn a_share_of_a_view_reads_rays_of_its_tiles_only() -> Result<()> {
        let dir = tempfile::tempdir()?;
        let (w, h) = (96, 64);
        let (scene, cfg, backend, settings) =
            crate::test_scene::tiny_case(dir.path(), 4, (w as u32, h as u32), 32)?;
        let d = cfg.planes;
        let mut prepared = Prepared::new(&scene);
        let mut read = |count: usize, share: f64| -> Result<Rays> {
            let mut rays = Rays::new(d);
            let r = (&mut Rng::new(7), count, share);
            collect_view(
                &backend,
                &scene,
                &mut prepared,
                2,
                &[],
                &settings,
                r,
                &mut rays,
            )?;
            Ok(rays)
        };
        let part = read(300, 0.5)?;
        let whole = read(w * h, 1.0)?;
        assert_eq!((part.len(), whole.len()), (300, w * h));
        // 0.5 of the 3 x 2 tiles of 32 pixels.
        let tiles: std::collections::BTreeSet<usize> = (part.pixels.iter())
            .map(|&(x, y)| (y / 32) * 3 + x / 32)
            .collect();
        assert_eq!(tiles.len(), 3, "{tiles:?}");
        for (r, &(x, y)) in part.pixels.iter().enumerate() {
            let q = y * w + x;
            assert_eq!(whole.pixels[q], (x, y));
            assert_eq!(part.truth[r], whole.truth[q]);
            for z in 0..d {
                let (a, b) = (part.selection[r * d + z], whole.selection[q * d + z]);
                assert_eq!(a.to_bits(), b.to_bits(), "ray {r}, plane {z}");
                assert_eq!(part.colours[r * d + z], whole.colours[q * d + z]);
            }
        }
        Ok(())
    }

    #[test]
    fn the_view_share_fits_the_reading_in_the_time_left() {
        let fit = FitTime {
            fixed: 20.0,
            per_view: 0.1,
            per_step: 0.01,
        };
        let need = PriorNeed {
            views: 100,
            per_view: 2.0,
            fit,
        };
        // 1.15 * 2 s * 100 views of reading, 20 + 0.1 * 100 s of fit.
        assert!((need.seconds() - 260.0).abs() < 1e-9);
        assert_eq!(need.share_within(300.0, 0.25), 1.0);
        let share = need.share_within(145.0, 0.25);
        assert!((share - 0.5).abs() < 1e-12, "{share}");
        assert!((need.seconds_at(share) - 145.0).abs() < 1e-9);
        assert_eq!(need.share_within(10.0, 0.25), 0.25);
        assert_eq!(need.share_within(-5.0, 2.0), 1.0);
    }

    /// Photographs rendered at sharpness 2.5 (and no log-weights): the fit finds the
    /// exponent, and the views set aside score higher; without `sharpen` it stays 1.
    #[test]
    fn the_fit_finds_the_scenes_sharpness() {
        let grid = PriorGrid::zeros(DVec3::new(-1.0, -1.0, 1.0), DVec3::new(1.0, 1.0, 3.0), 4)
            .expect("grid");
        let truth = PriorGrid {
            sharpness: 2.5,
            ..grid.clone()
        };
        let rays = rays_rendered_by(&truth, &grid, 4000, 1);
        let val = rays_rendered_by(&truth, &grid, 1000, 2);
        let opts = PriorOptions {
            steps: 300,
            batch: 1024,
            validate_every: 50,
            ..PriorOptions::default()
        };
        let never = AtomicBool::new(false);
        let mut g = grid.clone();
        let f = fit(&mut g, &rays, &val, &opts, &never, |_, _| {});
        assert!(
            (g.sharpness - 2.5).abs() < 0.25,
            "sharpness {}",
            g.sharpness
        );
        assert!(
            f.best_psnr() > f.validation[0].1 + 10.0,
            "{:?}",
            f.validation
        );
        let mut flat = grid.clone();
        let plain = PriorOptions {
            sharpen: false,
            ..opts
        };
        fit(&mut flat, &rays, &val, &plain, &never, |_, _| {});
        assert_eq!(flat.sharpness, 1.0);
    }
}
