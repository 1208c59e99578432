//! Per-view weights of the any-number-of-views family (config `pool.falloff`).
//!
//! The view pooling (`pool.rs`) averages the sources with their alpha as weights. With
//! every source weighing alike, adding views that are farther from the target than the
//! nearest few adds their occlusions and disagreements to the mean and the variance at
//! full weight: a model fed 8 views rendered worse than with 4 on most held-out scenes.
//! With a falloff, the sweep scales each source's alpha by
//!
//! `g_v = 1` when `d_v <= d_ref`, else `g_v = (d_ref / d_v)^power`,
//!
//! where `d_v` is the distance from source `v`'s camera centre to the target's and
//! `d_ref` the `full`-th smallest of them. The nearest `full` views are unchanged (a
//! model with `full = 4` sees exactly the unweighted input at 4 views or fewer), farther
//! ones still fill in where the nearest do not see (the pooled statistics are
//! normalised by the alpha sum), and their say elsewhere falls quickly (power 8: 0.23 at
//! 1.2 `d_ref`, 0.04 at 1.5 `d_ref`).
//!
//! With `full = 1` the weights are a soft proximity cue at any number of views: the
//! nearest source keeps 1 and every other weighs `(d_1 / d_v)^power`, so a source that
//! coincides with the target (`d_1 = 0`) takes over, and on a ring of cameras the views
//! on the far side count less than the neighbours. A model must be trained with the
//! weights it renders with (the shipped default's are `1:2`, run `runs/nviews-prox`):
//! fed to a model trained without them they help on some scenes and hurt on others.
//!
//! The weights depend only on the set of distances, so they do not change when views are
//! reordered, and empty views (no image: alpha 0 everywhere) are left out of the ranking,
//! so adding one changes nothing. Geometry only: f64, no tensors.

use crate::config::ViewFalloff;
use glam::DVec3;

/// Below this `d_ref` (camera centres that coincide with the target's), farther views
/// are measured against it instead, so that the weights stay finite.
pub const MIN_REF_DISTANCE: f64 = 1e-12;

/// The weights `g_v` of the module doc for sources at `centres` (`None`: an empty view,
/// weight 1, as its alpha is 0 anyway) seen from a target at `target`.
pub fn view_weights(falloff: ViewFalloff, target: DVec3, centres: &[Option<DVec3>]) -> Vec<f64> {
    let dist: Vec<Option<f64>> = centres
        .iter()
        .map(|c| c.map(|c| c.distance(target)))
        .collect();
    let mut sorted: Vec<f64> = dist.iter().flatten().copied().collect();
    if falloff.full == 0 || sorted.len() <= falloff.full {
        return vec![1.0; centres.len()];
    }
    sorted.sort_by(f64::total_cmp);
    let d_ref = sorted[falloff.full - 1].max(MIN_REF_DISTANCE);
    dist.iter()
        .map(|d| match d {
            Some(d) if *d > d_ref => (d_ref / d).powi(falloff.power as i32),
            _ => 1.0,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const F: ViewFalloff = ViewFalloff { full: 2, power: 4 };

    fn centres(xs: &[f64]) -> Vec<Option<DVec3>> {
        xs.iter().map(|&x| Some(DVec3::new(x, 0.0, 0.0))).collect()
    }

    #[test]
    fn the_nearest_keep_weight_one_and_the_others_fall_off() {
        let w = view_weights(F, DVec3::ZERO, &centres(&[2.0, 1.0, 4.0, -2.0]));
        // Distances 2, 1, 4, 2: d_ref = 2 (the second smallest); a tie keeps weight 1.
        assert_eq!(w, vec![1.0, 1.0, 0.5f64.powi(4), 1.0]);
        // At `full` views or fewer, every weight is 1.
        assert_eq!(
            view_weights(F, DVec3::ZERO, &centres(&[5.0, 1.0])),
            vec![1.0; 2]
        );
    }

    #[test]
    fn order_and_empty_views_change_nothing() {
        let mut c = centres(&[3.0, 1.0, 7.0, 2.0, 5.0]);
        let w = view_weights(F, DVec3::ZERO, &c);
        c.reverse();
        let mut r = view_weights(F, DVec3::ZERO, &c);
        r.reverse();
        assert_eq!(w, r);
        c.reverse();
        c.insert(1, None);
        c.push(None);
        let mut e = view_weights(F, DVec3::ZERO, &c);
        assert_eq!((e.remove(6), e.remove(1)), (1.0, 1.0));
        assert_eq!(w, e);
    }

    #[test]
    fn coinciding_centres_give_finite_weights() {
        let w = view_weights(F, DVec3::ZERO, &centres(&[0.0, 0.0, 1.0]));
        assert!(
            w.iter().all(|g| g.is_finite() && (0.0..=1.0).contains(g)),
            "{w:?}"
        );
    }
}
