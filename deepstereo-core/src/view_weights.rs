//! Per-view weights of the any-number-of-views family (config `pool.falloff`), and the
//! colour gate of the views beyond the nearest (config `pool.agree`, [`agree_gate`]).
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

/// Each source's camera centre distance to `target` (`None`: an empty view) and the
/// `k`-th smallest of them, or `None` when there are `k` sources or fewer (or `k` is 0).
fn kth_distance(
    k: usize,
    target: DVec3,
    centres: &[Option<DVec3>],
) -> (Vec<Option<f64>>, Option<f64>) {
    let dist: Vec<Option<f64>> = centres
        .iter()
        .map(|c| c.map(|c| c.distance(target)))
        .collect();
    let mut sorted: Vec<f64> = dist.iter().flatten().copied().collect();
    if k == 0 || sorted.len() <= k {
        return (dist, None);
    }
    sorted.sort_by(f64::total_cmp);
    (dist, Some(sorted[k - 1]))
}

/// The weights `g_v` of the module doc for sources at `centres` (`None`: an empty view,
/// weight 1, as its alpha is 0 anyway) seen from a target at `target`.
pub fn view_weights(falloff: ViewFalloff, target: DVec3, centres: &[Option<DVec3>]) -> Vec<f64> {
    let (dist, Some(d_ref)) = kth_distance(falloff.full, target, centres) else {
        return vec![1.0; centres.len()];
    };
    let d_ref = d_ref.max(MIN_REF_DISTANCE);
    dist.iter()
        .map(|d| match d {
            Some(d) if *d > d_ref => (d_ref / d).powi(falloff.power as i32),
            _ => 1.0,
        })
        .collect()
}

/// Which sources are among the `near` nearest to the target (camera centre distance;
/// every source as near as the `near`-th counts, so ties do not depend on the order);
/// empty views (`None`) count as near, as their alpha is 0 anyway. With `near` sources
/// or fewer, all are near.
pub fn near_views(near: usize, target: DVec3, centres: &[Option<DVec3>]) -> Vec<bool> {
    let (dist, Some(d_ref)) = kth_distance(near, target, centres) else {
        return vec![true; centres.len()];
    };
    dist.iter().map(|d| d.is_none_or(|d| d <= d_ref)).collect()
}

/// Alpha at or above which a near source sees a plane point and its colour is a
/// reference of [`agree_gate`] (the sweep's alpha is 1 inside a source's image, 0
/// outside, fractional along its border).
pub const AGREE_SEES: f32 = 0.5;

/// The colour-agreement gate (config `pool.agree`) on a plane sweep `[D, V, 4, h, w]` of
/// `hw` pixels per plane, applied to the sweep's own alpha (before the falloff): at each
/// plane point, every source `v` that is not near (`near[v]` false) has its alpha scaled
/// by
///
/// `g_v = exp(-e_v / (2 sigma^2))`, `e_v = min_n |c_v - c_n|^2`,
///
/// the least squared RGB distance to the colour `c_n` of a near source `n` that sees the
/// point (alpha >= [`AGREE_SEES`]). Where no near source sees it, `g_v = 1`. A far
/// source then counts where it agrees with one of the nearest (the same surface seen
/// from farther) and hardly where it shows something else (another face of an object,
/// an occluder); near sources are unchanged, so a model sees its input unchanged at
/// `near` views or fewer. Depends on the colours and the set of near views only, so it
/// does not change when views are reordered; an empty view (alpha 0) stays empty and is
/// never a reference.
pub fn agree_gate(volume: &mut [f32], near: &[bool], sigma: f32, hw: usize) {
    use rayon::prelude::*;
    let v = near.len();
    if near.iter().all(|&n| n) {
        return;
    }
    let per = 4 * hw;
    let scale = -0.5 / (sigma * sigma);
    let (near_ix, far_ix): (Vec<usize>, Vec<usize>) = (0..v).partition(|&k| near[k]);
    volume.par_chunks_mut(v * per).for_each(|plane| {
        let mut e = vec![0f32; hw];
        for &f in &far_ix {
            closest_references(plane, hw, f, &near_ix, &mut e);
            let alpha = &mut plane[f * per + 3 * hw..][..hw];
            for (a, &e) in alpha.iter_mut().zip(&e) {
                if e.is_finite() && e > 0.0 {
                    *a *= (scale * e).exp();
                }
            }
        }
    });
}

/// The least squared RGB distance from the colour of source `k` to that of a source in
/// `refs` other than `k` that sees the point (alpha >= [`AGREE_SEES`]), at every pixel
/// of one plane `[V, 4, hw]`, into `e` (`hw`): `e_v` of [`agree_gate`], `q_v^2` of
/// [`disagreement`]; infinite where no such source sees it. Runs over rows of pixels
/// (contiguous, so the compiler vectorises it).
fn closest_references(plane: &[f32], hw: usize, k: usize, refs: &[usize], e: &mut [f32]) {
    let channel = |n: usize, c: usize| &plane[n * 4 * hw + c * hw..][..hw];
    let (r, g, b) = (channel(k, 0), channel(k, 1), channel(k, 2));
    e.fill(f32::INFINITY);
    for &n in refs.iter().filter(|&&n| n != k) {
        let (rn, gn, bn, an) = (channel(n, 0), channel(n, 1), channel(n, 2), channel(n, 3));
        for p in 0..hw {
            let d = (r[p] - rn[p]).powi(2) + (g[p] - gn[p]).powi(2) + (b[p] - bn[p]).powi(2);
            if an[p] >= AGREE_SEES {
                e[p] = e[p].min(d);
            }
        }
    }
}

/// The cue's disagreement channel (config `pool.disagree`) of a plane sweep
/// `[D, V, 4, h, w]` of `hw` pixels per plane, from the sweep's own alpha: `[D, V, hw]`
/// with, at each plane point, for every source `v`,
///
/// `q_v = sqrt(min_n |c_v - c_n|^2)`
///
/// over the near sources `n != v` (`near[n]`) that see the point (alpha >=
/// [`AGREE_SEES`]); `q_v = 0` where none does. Colours are 0-1, so `q_v` is in
/// `[0, sqrt 3]`: how far the source's colour is from the nearest sources' at that depth
/// (small where it sees the surface they see, large where it shows another face or an
/// occluder). Depends on the colours and the set of near views only: reordering the
/// views reorders `q`; an empty view (alpha 0) is never a reference, and its own `q`
/// multiplies its alpha 0 in the view weights.
pub fn disagreement(volume: &[f32], near: &[bool], hw: usize) -> Vec<f32> {
    use rayon::prelude::*;
    let v = near.len();
    let per = 4 * hw;
    let near_ix: Vec<usize> = (0..v).filter(|&k| near[k]).collect();
    let mut out = vec![0f32; volume.len() / 4];
    out.par_chunks_mut(v * hw)
        .zip(volume.par_chunks(v * per))
        .for_each(|(q, plane)| {
            for (k, qk) in q.chunks_mut(hw).enumerate() {
                closest_references(plane, hw, k, &near_ix, qk);
                for x in qk.iter_mut() {
                    *x = if x.is_finite() { x.sqrt() } else { 0.0 };
                }
            }
        });
    out
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

    /// A sweep `[1, V, 4, 1, 2]` of the given RGBA per view and pixel.
    fn volume(views: &[[[f32; 4]; 2]]) -> Vec<f32> {
        let mut v = Vec::new();
        for view in views {
            for c in 0..4 {
                v.extend(view.iter().map(|px| px[c]));
            }
        }
        v
    }

    fn alphas(vol: &[f32]) -> Vec<[f32; 2]> {
        vol.chunks_exact(8).map(|v| [v[6], v[7]]).collect()
    }

    #[test]
    fn far_views_are_gated_by_the_nearest_agreeing_colour() {
        let sigma = 0.1f32;
        let views = [
            // near: seen at pixel 0, barely (alpha under AGREE_SEES) at pixel 1
            [[0.2, 0.2, 0.2, 1.0], [0.5, 0.5, 0.5, 0.4]],
            [[0.8, 0.8, 0.8, 1.0], [0.5, 0.5, 0.5, 0.0]],
            // far
            [[0.3, 0.2, 0.2, 1.0], [0.9, 0.1, 0.1, 0.7]],
        ];
        let mut vol = volume(&views);
        agree_gate(&mut vol, &[true, true, false], sigma, 2);
        let a = alphas(&vol);
        // Pixel 0: the closest near colour is (0.2, 0.2, 0.2), e = 0.01.
        let want = (-0.01f32 / (2.0 * sigma * sigma)).exp();
        assert!((a[2][0] - want).abs() < 1e-6, "{} against {want}", a[2][0]);
        // Pixel 1: no near view sees it, so the far view keeps its alpha; near views
        // are never changed.
        assert_eq!(a[2][1], 0.7);
        assert_eq!((a[0], a[1]), ([1.0, 0.4], [1.0, 0.0]));
        // Every view near: nothing changes.
        let mut same = volume(&views);
        agree_gate(&mut same, &[true; 3], sigma, 2);
        assert_eq!(same, volume(&views));
    }

    #[test]
    fn the_gate_ignores_order_and_empty_views() {
        let views = [
            [[0.2, 0.4, 0.2, 1.0], [0.5, 0.5, 0.5, 1.0]],
            [[0.8, 0.1, 0.8, 1.0], [0.1, 0.5, 0.9, 0.6]],
            [[0.3, 0.2, 0.2, 1.0], [0.9, 0.1, 0.1, 0.7]],
            [[0.7, 0.2, 0.7, 0.9], [0.4, 0.5, 0.5, 1.0]],
        ];
        let near = [true, false, true, false];
        let mut vol = volume(&views);
        agree_gate(&mut vol, &near, 0.2, 2);
        let a = alphas(&vol);
        assert!(a[1][0] < 1.0 && a[3][1] < 1.0, "nothing was gated: {a:?}");
        let order = [2, 3, 0, 1];
        let mut vp = volume(&order.map(|i| views[i]));
        agree_gate(&mut vp, &order.map(|i| near[i]), 0.2, 2);
        let ap = alphas(&vp);
        for (k, &i) in order.iter().enumerate() {
            assert_eq!(ap[k], a[i]);
        }
        // An empty view (alpha 0), near or far, changes nothing and stays empty.
        for empty_near in [false, true] {
            let mut ve = views.to_vec();
            ve.insert(1, [[0.0; 4]; 2]);
            let mut ne = near.to_vec();
            ne.insert(1, empty_near);
            let mut vol = volume(&ve);
            agree_gate(&mut vol, &ne, 0.2, 2);
            let mut ae = alphas(&vol);
            assert_eq!(ae.remove(1), [0.0, 0.0]);
            assert_eq!(ae, a);
        }
    }

    /// Each view's distance to the closest other near colour that sees the point; 0
    /// where no other near view sees it.
    #[test]
    fn disagreement_is_the_distance_to_the_closest_other_near_colour() {
        let views = [
            // near: seen at pixel 0, barely (alpha under AGREE_SEES) at pixel 1
            [[0.2, 0.2, 0.2, 1.0], [0.5, 0.5, 0.5, 0.4]],
            [[0.8, 0.8, 0.8, 1.0], [0.5, 0.5, 0.5, 1.0]],
            // far
            [[0.3, 0.2, 0.2, 1.0], [0.9, 0.1, 0.1, 0.7]],
        ];
        let q = disagreement(&volume(&views), &[true, true, false], 2);
        let want = [
            [(3.0f32 * 0.36).sqrt(), 0.0], // pixel 1: view 1's colour, equal
            [(3.0f32 * 0.36).sqrt(), 0.0], // pixel 1: no other near view sees it
            [0.1, (0.16f32 + 0.16 + 0.16).sqrt()],
        ];
        for (k, w) in want.iter().enumerate() {
            for p in 0..2 {
                assert!(
                    (q[k * 2 + p] - w[p]).abs() < 1e-6,
                    "view {k} pixel {p}: {q:?}"
                );
            }
        }
        // Reordered views give reordered values; an empty view changes nothing.
        let order = [2, 0, 1];
        let qp = disagreement(&volume(&order.map(|i| views[i])), &[false, true, true], 2);
        for (k, &i) in order.iter().enumerate() {
            assert_eq!(qp[k * 2..k * 2 + 2], q[i * 2..i * 2 + 2]);
        }
        for empty_near in [false, true] {
            let mut ve = views.to_vec();
            ve.insert(1, [[0.0; 4]; 2]);
            let qe = disagreement(&volume(&ve), &[true, empty_near, true, false], 2);
            let mut qe: Vec<f32> = qe.to_vec();
            qe.drain(2..4);
            assert_eq!(qe, q);
        }
    }

    #[test]
    fn near_views_keep_ties_and_empty_views() {
        let c = centres(&[3.0, 1.0, 2.0, -2.0, 5.0]);
        // The 2nd nearest distance is 2, shared by two views: both are near.
        assert_eq!(
            near_views(2, DVec3::ZERO, &c),
            vec![false, true, true, true, false]
        );
        let mut ce = c.clone();
        ce.push(None);
        assert_eq!(
            near_views(2, DVec3::ZERO, &ce),
            vec![false, true, true, true, false, true]
        );
        // At `near` views or fewer (empty ones not counted), every view is near.
        assert_eq!(near_views(4, DVec3::ZERO, &c[..4]), vec![true; 4]);
        assert_eq!(
            near_views(2, DVec3::ZERO, &[c[0], None, c[1]]),
            vec![true; 3]
        );
    }

    /// The definition, pixel by pixel: the least squared RGB distance from the colour of
    /// source `k` at pixel `p` of one plane `[V, 4, hw]` to that of a source in `refs`
    /// other than `k` that sees the point; `None` where none does.
    fn closest_reference(
        plane: &[f32],
        hw: usize,
        p: usize,
        k: usize,
        refs: &[usize],
    ) -> Option<f32> {
        let per = 4 * hw;
        let colour = |k: usize| [0, 1, 2].map(|c| plane[k * per + c * hw + p]);
        let ck = colour(k);
        (refs.iter().copied())
            .filter(|&n| n != k && plane[n * per + 3 * hw + p] >= AGREE_SEES)
            .map(|n| {
                let cn = colour(n);
                (0..3).map(|c| (ck[c] - cn[c]).powi(2)).sum::<f32>()
            })
            .reduce(f32::min)
    }

    /// The row-wise `disagreement` and `agree_gate` against `closest_reference` pixel by
    /// pixel, on a pseudo-random sweep of 3 planes, 6 views (4 near), half of the alphas
    /// below `AGREE_SEES`: the same values, bit for bit.
    #[test]
    fn disagreement_and_gate_equal_the_closest_reference_at_every_pixel() {
        let (d, v, hw) = (3, 6, 37);
        let mut state = 12345u64;
        let volume: Vec<f32> = (0..d * v * 4 * hw)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 40) as f32 / (1u64 << 24) as f32
            })
            .collect();
        let near = [true, false, true, true, false, true];
        let near_ix: Vec<usize> = (0..v).filter(|&k| near[k]).collect();
        let q = disagreement(&volume, &near, hw);
        let mut seen = 0;
        for z in 0..d {
            let plane = &volume[z * v * 4 * hw..][..v * 4 * hw];
            for k in 0..v {
                for p in 0..hw {
                    let e = closest_reference(plane, hw, p, k, &near_ix);
                    seen += usize::from(e.is_some());
                    let want = e.map_or(0.0, f32::sqrt);
                    assert_eq!(
                        q[(z * v + k) * hw + p].to_bits(),
                        want.to_bits(),
                        "{z} {k} {p}"
                    );
                }
            }
        }
        // Both cases occur: some points with a seeing reference, some with none.
        assert!(seen > 0 && seen < d * v * hw, "{seen}");
        let sigma = 0.1f32;
        let mut gated = volume.clone();
        agree_gate(&mut gated, &near, sigma, hw);
        for z in 0..d {
            let plane = &volume[z * v * 4 * hw..][..v * 4 * hw];
            for (k, &is_near) in near.iter().enumerate() {
                for p in 0..hw {
                    let i = z * v * 4 * hw + k * 4 * hw + 3 * hw + p;
                    let e = closest_reference(plane, hw, p, k, &near_ix);
                    let want = match e.filter(|&e| !is_near && e > 0.0) {
                        Some(e) => volume[i] * (-0.5 / (sigma * sigma) * e).exp(),
                        None => volume[i],
                    };
                    assert_eq!(gated[i].to_bits(), want.to_bits(), "gate {z} {k} {p}");
                }
            }
        }
        assert_ne!(gated, volume);
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
