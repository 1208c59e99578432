//! What `tune` decides by measuring the scene: how a time budget is split between
//! fine-tuning the network and fitting the scene prior, and how many depth planes the
//! tuned model renders at.
//!
//! - **The split.** The prior runs first: it reads every tuning view once (one render of
//!   its layers each) and then fits; its held-out gain flattens well before 10 minutes
//!   (297-524 s of 600 on the evaluation scenes; docs/results.md). It gets what it needs,
//!   `need` ([`PriorNeed::seconds`]: one view rendered and a few fit steps timed), at
//!   most [`MAX_PRIOR_SHARE`] of the budget less `reserve` (the time the planes choice
//!   below takes). The network then fine-tunes through the fitted prior, fixed, for the
//!   rest ([`crate::tuning::through`]); nothing when that is under
//!   [`MIN_NETWORK_SECONDS`].
//! - **The reading.** When reading its views whole would not end within the prior's
//!   time, it reads [`view_share`] of each view's tiles, so that every view is read,
//!   each less densely.
//! - **The planes.** A prior sharpens the selection, so pruning runs fewer planes and a
//!   tuned model can afford more of them at the cost of the model it started from. The
//!   work of a render is the planes times the pixels the network ran on and a fixed
//!   cost per block it ran ([`CALL_COST`]; both counted by the pruning's statistics, so
//!   the choice is deterministic). The choice is the most planes of [`plane_choices`]
//!   whose work on the views set aside for validation and a few tuning views (each
//!   rendered as a held-out view) stays within the starting model's at its own default;
//!   the fewest when none does.

use crate::rendering::{render_held_out, Prepared, RenderSettings};
use crate::tuning::prior::PriorNeed;
use anyhow::Result;
use deepstereo_core::render::Backend;
use deepstereo_core::scene::Scene;
use std::time::Instant;

/// The largest share of a time budget (less the planes choice's reserve) the prior
/// gets before the network's fine-tune through it.
pub const MAX_PRIOR_SHARE: f64 = 0.5;

/// The fewest seconds worth a network fine-tune after the prior (a few validations).
pub const MIN_NETWORK_SECONDS: f64 = 30.0;

/// Seconds the prior gets of `left` seconds when it needs `need` and `reserve` is kept
/// for the planes choice: `min(need, MAX_PRIOR_SHARE * (left - reserve))`, at least 0.
pub fn prior_seconds(left: f64, need: f64, reserve: f64) -> f64 {
    need.min(MAX_PRIOR_SHARE * (left - reserve)).max(0.0)
}

/// Seconds the network fine-tunes with `left` seconds of the budget when `reserve` is
/// kept: the rest, or 0 when that is under [`MIN_NETWORK_SECONDS`].
pub fn network_seconds(left: f64, reserve: f64) -> f64 {
    let rest = left - reserve;
    if rest >= MIN_NETWORK_SECONDS {
        rest
    } else {
        0.0
    }
}

/// The network's fixed cost per block run, in plane-pixels. On the 2-core VM the
/// network's seconds over the 24 renders of the side-by-side table in docs/results.md
/// (six scenes; embedded and tuned models at 32 and 48 planes) fit 0.45 us per
/// plane-pixel and 2.3 ms per block (within 9.5% on every render, against 19% for the
/// plane-pixels alone): a block costs as much as about 5,000 plane-pixels. Tuned models
/// run more, smaller blocks (up to 1.35x the blocks at equal plane-pixels).
pub const CALL_COST: f64 = 5000.0;

/// Renders of each of its views the planes choice may take (the start's and three
/// candidates' by bisection over seven counts), in units of one view's layers at the
/// network's planes (pruned renders at 1.5x the planes run 0.4-1.4x of those), for its
/// time reserve.
const CHOICE_RENDERS: f64 = 4.0;

/// The least share of each view's tiles [`view_share`] reads.
pub const MIN_VIEW_SHARE: f64 = 0.25;

/// The share of each view's tiles the prior reads in `seconds`: 1 when reading every
/// view whole and fitting fit in them, else the share at which they
/// do (at least [`MIN_VIEW_SHARE`]). The prior keeps a few thousand rays of a view of
/// hundreds of thousands of pixels, so a part of each view serves it: on moldgoldcape
/// (99 views at 7.5 s for 10 minutes) it read all 96 of its views at 44% instead of 55
/// whole, and its held-out views scored the same (docs/results.md), the scene covered by
/// every view.
pub fn view_share(need: &PriorNeed, seconds: f64) -> f64 {
    match seconds >= need.seconds() {
        true => 1.0,
        false => need.share_within(seconds, MIN_VIEW_SHARE),
    }
}

/// Tuning views the planes choice renders besides the views set aside, each from the
/// others as a held-out view is: three views set aside alone misjudged the work of the
/// held-out views by up to 16% (fox: 1.07x against 0.91x; docs/results.md).
pub const CHOICE_TUNING_VIEWS: usize = 3;

/// The views the planes choice renders: those set aside and [`CHOICE_TUNING_VIEWS`] of
/// `tuning` spread over it.
pub fn choice_targets(tuning: &[usize], validation: &[usize]) -> Vec<usize> {
    let (n, k) = (tuning.len(), CHOICE_TUNING_VIEWS.min(tuning.len()));
    let spread = (0..k).map(|i| tuning[(2 * i + 1) * n / (2 * k)]);
    validation.iter().copied().chain(spread).collect()
}

/// The largest share of a time budget kept for [`choose_render_planes`]; past it the
/// choice stops its bisection when its next count would end after the budget.
pub const MAX_RESERVE_SHARE: f64 = 0.25;

/// Seconds to keep for [`choose_render_planes`] on `views` views within a budget of
/// `budget` seconds: [`CHOICE_RENDERS`] renders of each, at most [`MAX_RESERVE_SHARE`]
/// of the budget.
pub fn choice_reserve(need: &PriorNeed, views: usize, budget: f64) -> f64 {
    (CHOICE_RENDERS * need.per_view * views as f64).min(MAX_RESERVE_SHARE * budget)
}

/// The plane counts the choice is among, fewest first: 0.75 to 1.5 times the network's
/// `planes` in steps of an eighth (24, 28, ..., 48). Fewer planes than the network's
/// keep a tuned model whose prior flattens the selection (so that pruning thins fewer
/// planes) within the starting model's time.
pub fn plane_choices(planes: usize) -> Vec<usize> {
    let mut v: Vec<usize> = (6..=12).map(|k| (planes * k / 8).max(1)).collect();
    v.dedup();
    v
}

/// What [`choose_render_planes`] found.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PlanesChoice {
    pub planes: usize,
    /// `(planes, work / the start's work)` of each count tried, in the order tried.
    pub work: Vec<(usize, f64)>,
    pub seconds: f64,
    /// Whether the bisection stopped early to end within its time.
    pub cut: bool,
}

/// The most planes of `choices` (fewest first) at which `tuned` does no more work on the
/// views `targets` of `scene` than `start` at its own default planes (found by
/// bisection, taking the work to grow with the planes); the first (fewest) when none
/// does. Each target is rendered from the views that are neither it nor in
/// `exclude`, as `eval` renders a held-out view. `settings.planes` is ignored. The
/// bisection stops (with the most planes found to fit so far) before a count whose
/// renders, taken to last as long as the previous count's, would end after `seconds`.
pub fn choose_render_planes(
    (start, tuned): (&dyn Backend, &dyn Backend),
    scene: &Scene,
    (targets, exclude): (&[usize], &[usize]),
    settings: &RenderSettings,
    (choices, seconds): (&[usize], f64),
) -> Result<PlanesChoice> {
    let t0 = Instant::now();
    let mut prepared = Prepared::new(scene);
    let mut work = |backend: &dyn Backend, planes: Option<usize>| -> Result<f64> {
        let s = RenderSettings {
            planes,
            ..settings.clone()
        };
        let k = s.source_count(backend.config())?;
        let mut sum = 0f64;
        for &t in targets {
            let mut out = exclude.to_vec();
            out.push(t);
            let h = render_held_out(backend, scene, &mut prepared, t, &out, k, &s)?;
            let (w, hgt) = (h.rendered.image.width, h.rendered.image.height);
            sum += match &h.rendered.prune {
                Some(p) => p.planes_run as f64 + CALL_COST * p.calls as f64,
                None => (h.inv_depths.len() * w as usize * hgt as usize) as f64,
            };
        }
        Ok(sum)
    };
    let base = work(start, None)?.max(1.0);
    let mut last = t0.elapsed().as_secs_f64();
    let mut tried = Vec::new();
    let mut planes = *choices.first().unwrap_or(&start.config().planes);
    let mut cut = false;
    // Bisection over the counts (work grows with them): [lo, hi) holds the unknown.
    let (mut lo, mut hi) = (0, choices.len());
    while lo < hi {
        let begun = t0.elapsed().as_secs_f64();
        if begun + last > seconds {
            cut = true;
            break;
        }
        let mid = (lo + hi) / 2;
        let ratio = work(tuned, Some(choices[mid]))? / base;
        last = t0.elapsed().as_secs_f64() - begun;
        tried.push((choices[mid], ratio));
        if ratio <= 1.0 {
            planes = choices[mid];
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    Ok(PlanesChoice {
        planes,
        work: tried,
        seconds: t0.elapsed().as_secs_f64(),
        cut,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_prior_gets_its_need_up_to_half_and_the_network_the_rest() {
        assert_eq!(prior_seconds(600.0, 100.0, 20.0), 100.0);
        assert_eq!(prior_seconds(600.0, 900.0, 20.0), 290.0);
        assert_eq!(prior_seconds(10.0, 100.0, 20.0), 0.0);
        assert_eq!(network_seconds(480.0, 20.0), 460.0);
        // Under MIN_NETWORK_SECONDS left: no fine-tune.
        assert_eq!(network_seconds(45.0, 20.0), 0.0);
        assert_eq!(network_seconds(10.0, 20.0), 0.0);
    }

    #[test]
    fn the_choice_renders_the_views_set_aside_and_tuning_views_spread() {
        let tuning: Vec<usize> = (0..20).filter(|i| i % 7 != 3).collect();
        let t = choice_targets(&tuning, &[3, 10, 17]);
        assert_eq!(t.len(), 3 + CHOICE_TUNING_VIEWS);
        assert_eq!(&t[..3], &[3, 10, 17]);
        assert!(t[3..].iter().all(|v| tuning.contains(v)));
        assert!(t[3..].windows(2).all(|w| w[0] < w[1]));
        assert_eq!(choice_targets(&[4], &[1]), vec![1, 4]);
    }

    /// The choice renders every count of its bisection with time enough, and none (taking
    /// the fewest planes) when its time is spent.
    #[test]
    fn the_choice_stops_at_its_time() -> Result<()> {
        let dir = tempfile::tempdir()?;
        let (scene, cfg, backend, settings) =
            crate::test_scene::tiny_case(dir.path(), 3, (40, 32), 64)?;
        let choices = plane_choices(cfg.planes);
        let pair = (&backend as &dyn Backend, &backend as &dyn Backend);
        let targets = (&[0, 3][..], &[5][..]);
        let all =
            choose_render_planes(pair, &scene, targets, &settings, (&choices, f64::INFINITY))?;
        assert!(!all.cut, "{all:?}");
        assert_eq!(
            all.work.len(),
            3,
            "seven counts take three renders: {all:?}"
        );
        let none = choose_render_planes(pair, &scene, targets, &settings, (&choices, 0.0))?;
        assert!(none.cut && none.work.is_empty(), "{none:?}");
        assert_eq!(none.planes, choices[0]);
        Ok(())
    }

    #[test]
    fn plane_choices_scale_the_networks_planes() {
        assert_eq!(plane_choices(32), [24, 28, 32, 36, 40, 44, 48]);
        assert_eq!(plane_choices(8), [6, 7, 8, 9, 10, 11, 12]);
        assert_eq!(plane_choices(2), [1, 2, 3]);
    }
}
