//! What a prior fit takes: the estimate before it ([`PriorNeed`]), the fit of the rays
//! read ([`fit_rays`]) and its measured time ([`FitTime`]).

use super::*;

/// What reading a scene's views and fitting its prior will take, estimated before it
/// runs (for a tune that splits its time between the network and the prior).
#[derive(Clone, Copy, Debug)]
pub struct PriorNeed {
    /// Views [`fit_scene`] would read (validation views included).
    pub views: usize,
    /// Seconds to render one view's layers (measured on one validation view).
    pub per_view: f64,
    pub(super) fit: FitTime,
}

impl PriorNeed {
    /// The factor the measured time per view is scaled by.
    const MARGIN: f64 = 1.15;

    /// Renders the layers of the first validation view (or the first training view) with
    /// `backend` and times it, then times a few fit steps on its rays.
    pub fn measure(
        backend: &dyn Backend,
        scene: &Scene,
        (train, validation): (&[usize], &[usize]),
        settings: &RenderSettings,
        opts: &PriorOptions,
    ) -> Result<Self> {
        let Some(&probe) = validation.first().or(train.first()) else {
            bail!("no view to measure the prior's time on");
        };
        let planes = settings.planes.unwrap_or(backend.config().planes);
        let read = train.len().min(opts.max_views);
        let views = read + validation.len();
        let per_ray = opts.rays_per_view_of(read);
        let mut rays = Rays::new(planes);
        let mut prepared = Prepared::new(scene);
        let mut rng = Rng::new(opts.seed);
        let t0 = Instant::now();
        let r = (&mut rng, per_ray, 1.0);
        collect_view(
            backend,
            scene,
            &mut prepared,
            probe,
            &[],
            settings,
            r,
            &mut rays,
        )?;
        let per_view = t0.elapsed().as_secs_f64();
        let fit = FitTime::measure(&mut rays, validation.len() * per_ray, opts)?;
        Ok(Self {
            views,
            per_view,
            fit,
        })
    }

    /// Seconds to read every view and fit: `views * per_view` (with a margin) and the fit.
    pub fn seconds(&self) -> f64 {
        self.seconds_at(1.0)
    }

    /// Seconds to read every view whole: `views * per_view`, with a margin.
    fn reading(&self) -> f64 {
        Self::MARGIN * self.per_view * self.views as f64
    }

    /// Seconds to read every view at `share` of its tiles (the reading taken to scale with
    /// them) and fit.
    pub fn seconds_at(&self, share: f64) -> f64 {
        self.reading() * share + self.fit.of(self.views)
    }

    /// The share of each view's tiles at which reading every view and fitting take
    /// `seconds` (at most 1, at least `least`).
    pub fn share_within(&self, seconds: f64, least: f64) -> f64 {
        let share = (seconds - self.fit.of(self.views)) / self.reading().max(1e-9);
        share.clamp(least.min(1.0), 1.0)
    }
}

/// A grid over `rays` (or [`PriorOptions::init`]), fitted to them.
pub(super) fn fit_rays(
    rays: &mut Rays,
    val: &mut Rays,
    opts: &PriorOptions,
    stop: &AtomicBool,
    on_validate: impl FnMut(usize, f64),
) -> Result<(PriorGrid, Fit)> {
    let mut grid = match &opts.init {
        Some(g) => g.clone(),
        None => rays.grid(opts.cells)?,
    };
    rays.locate(&grid);
    val.locate(&grid);
    let fit = fit(&mut grid, rays, val, opts, stop, on_validate);
    Ok((grid, fit))
}

/// How long the final fit will take: `fixed + per_view * views` seconds for `views`
/// views read (placing their rays in the grid grows with them), with
/// [`FitTime::MARGIN`] more for safety and [`FitTime::SLACK`] seconds besides.
#[derive(Clone, Copy, Debug)]
pub(super) struct FitTime {
    pub(super) fixed: f64,
    pub(super) per_view: f64,
    /// Seconds per step, its share of the validations included.
    pub(super) per_step: f64,
}

impl FitTime {
    /// The factor every measured time is scaled by.
    const MARGIN: f64 = 1.2;
    /// Seconds added to the fit's time.
    const SLACK: f64 = 2.0;

    /// Estimated from a few steps on `rays` (one view's; the grid is thrown away, and
    /// the rays are placed in the final grid again before the fit), with `val_rays`
    /// validation rays.
    pub(super) fn measure(rays: &mut Rays, val_rays: usize, opts: &PriorOptions) -> Result<Self> {
        let t0 = Instant::now();
        let mut grid = match &opts.init {
            Some(g) => g.clone(),
            None => rays.grid(opts.cells)?,
        };
        rays.locate(&grid);
        let per_view = t0.elapsed().as_secs_f64() / rays.views().max(1) as f64;
        let steps = 5;
        let o = PriorOptions {
            steps,
            validate_every: usize::MAX,
            ..opts.clone()
        };
        let never = AtomicBool::new(false);
        let t1 = Instant::now();
        fit(
            &mut grid,
            rays,
            &Rays::new(rays.planes),
            &o,
            &never,
            |_, _| {},
        );
        // A step renders `batch` rays however many there are: scale the probe's up.
        let probed = opts.batch.min(rays.len()).max(1) as f64;
        let per_step = t1.elapsed().as_secs_f64() / steps as f64 * opts.batch as f64 / probed;
        // A validation renders every validation ray once, about as a step renders its batch.
        let validations = (opts.steps / opts.validate_every.max(1) + 2) as f64;
        let per_val = per_step * val_rays as f64 / opts.batch.max(1) as f64;
        let total = per_step * opts.steps as f64 + per_val * validations;
        Ok(Self {
            fixed: Self::MARGIN * total + Self::SLACK,
            per_view: Self::MARGIN * per_view,
            per_step: total / opts.steps.max(1) as f64,
        })
    }

    /// The most steps (at least 1, at most `steps`) that end within `left` seconds once
    /// `views` views' rays are placed in the grid.
    pub(super) fn steps_within(&self, left: f64, views: usize, steps: usize) -> usize {
        let room =
            (left - Self::SLACK - self.per_view * views as f64) / (Self::MARGIN * self.per_step);
        (room.max(1.0) as usize).min(steps)
    }

    /// Seconds for the final fit once `views` views (validation views included) are read.
    pub(super) fn of(&self, views: usize) -> f64 {
        self.fixed + self.per_view * views as f64
    }
}
