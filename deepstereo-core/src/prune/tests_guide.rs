//! Tests of the network-guided coarse pass, plane thinning and constant tiles.

use super::tests::{
    assert_keeps_true_planes, known_pixels, nearest, pyramids, scene, small_backend, TestResult,
};
use super::*;
use crate::camera::Camera;
use crate::geometry::inverse_depths;
use crate::inputs::PyramidSource;
use crate::render::{render_view_pruned, Backend, CandleBackend};
use crate::synth::Rig;
use candle_core::Device;

/// The trained `tiny` model shipped with the command-line tool.
fn trained_tiny() -> CandleBackend {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deepstereo-train/assets/tiny.safetensors");
    let t = crate::weights::load(&path, &Device::Cpu).expect("trained tiny weights");
    CandleBackend {
        model: t.model,
        device: Device::Cpu,
    }
}

#[test]
fn prune_network_guide_keeps_the_true_surface_plane_of_known_pixels() {
    assert_keeps_true_planes(&PruneOptions::auto(), Some(&trained_tiny()), 32);
}

/// At twice the model's planes the guide runs on every second plane ([`guide_planes`]) and
/// each of its planes stands for its neighbours: the same guarantee holds.
#[test]
fn prune_thinned_network_guide_keeps_the_true_surface_plane_of_known_pixels() {
    let tiny = trained_tiny();
    let planes = 2 * tiny.config().planes;
    assert_keeps_true_planes(&PruneOptions::auto(), Some(&tiny), planes);
}

#[test]
fn prune_plane_step_is_focal_times_baseline_times_inverse_depth_step() {
    use crate::camera::{Intrinsics, WorldToCamera};
    use glam::{DMat3, DVec3};
    let (f, b, near, far, d) = (100.0, 0.3, 2.0, 50.0, 33);
    let k = Intrinsics::pinhole(f, f, 64.0, 48.0, 128, 96);
    let target = Camera {
        intrinsics: k,
        pose: WorldToCamera::new_checked(DMat3::IDENTITY, DVec3::ZERO).expect("pose"),
        rolling_shutter: None,
    };
    // p_cam = p_world - (b, 0, 0): the source sits b to the right of the target.
    let source = Camera {
        intrinsics: k,
        pose: WorldToCamera::new_checked(DMat3::IDENTITY, DVec3::new(-b, 0.0, 0.0)).expect("pose"),
        rolling_shutter: None,
    };
    let inv = inverse_depths(near, far, d);
    let want = f * b * (1.0 / near - 1.0 / far) / (d - 1) as f64;
    let got = max_plane_step(&target, &[&source], &inv);
    assert!((got - want).abs() < 1e-9 * want, "{got} vs {want}");
    // A source at the target's centre sees no disparity at all.
    assert_eq!(max_plane_step(&target, &[&target], &inv), 0.0);
}

/// `n` planes spread evenly over `0..d`, the first and last among them.
fn spread(d: usize, n: usize) -> Vec<usize> {
    (0..n)
        .map(|i| (i as f64 * (d - 1) as f64 / (n - 1) as f64).round() as usize)
        .collect()
}

#[test]
fn prune_thin_planes_spreads_the_fewest_planes_the_step_allows() {
    // 96 planes 0.25 px apart within 1 px: neighbours at most 4 grid steps apart, so
    // ceil(95 / 4) + 1 = 25 planes, whatever the floor.
    assert_eq!(thin_planes(96, 0.25, 1.0, 64), spread(96, 25));
    assert_eq!(thin_planes(96, 0.25, 1.0, 96), spread(96, 25));
    // Steps already at or above the limit, unknown steps and a zero limit keep all.
    for (step, max) in [
        (1.0, 1.0),
        (1.5, 1.0),
        (0.0, 1.0),
        (f64::NAN, 1.0),
        (0.1, 0.0),
    ] {
        assert_eq!(
            thin_planes(7, step, max, 1),
            (0..7).collect::<Vec<_>>(),
            "{step} {max}"
        );
    }
    assert_eq!(thin_planes(1, 0.01, 1.0, 1), vec![0]);
    assert!(thin_planes(0, 0.5, 1.0, 1).is_empty());
    // Beyond a pixel of disparity, thinning stops at the model's plane count, and goes
    // below it (to three quarters) only within 2 px: 64 planes 0.75 px apart within 3 px
    // could go to 17 but keep 32 (as every 2nd plane would be 1.5 px apart, every 3rd
    // 2.25); 32 planes 0.9 px apart keep 24 (1.8 px apart), 1.6 px apart all 32.
    assert_eq!(thin_planes(64, 0.75, 3.0, 32), spread(64, 32));
    assert_eq!(thin_planes(64, 0.75, 3.0, 40), spread(64, 33));
    assert_eq!(thin_planes(64, 0.75, 3.0, 20), spread(64, 20));
    assert_eq!(thin_planes(64, 0.75, 3.0, 8), spread(64, 17));
    assert_eq!(thin_planes(32, 0.9, 8.0, 32), spread(32, 24));
    assert_eq!(thin_planes(32, 1.6, 8.0, 32), (0..32).collect::<Vec<_>>());
    // Within a pixel the floor does not apply: 0.3 px apart, every 3rd plane (0.9 px).
    assert_eq!(thin_planes(64, 0.3, 8.0, 32), spread(64, 22));
    // Every result: increasing, first and last kept, neighbours within the step limit.
    for (d, step, max, model) in [(64, 0.75, 3.0, 32), (96, 0.3, 8.0, 32), (33, 0.9, 8.0, 32)] {
        let p = thin_planes(d, step, max, model);
        assert_eq!((p[0], *p.last().unwrap()), (0, d - 1));
        assert!(p
            .windows(2)
            .all(|w| w[0] < w[1] && (w[1] - w[0]) as f64 * step <= max));
    }
}

#[test]
fn prune_constant_tiles_take_their_colour_without_the_network() -> TestResult {
    // Sources of one colour everywhere: every tile is flat under both coarse passes, and
    // the render is that colour; a textured scene has textured tiles that are not.
    let backend = small_backend(3);
    let mut s = scene(31, Rig::Forward);
    let colour = [0.3f32, 0.5, 0.7];
    for img in &mut s.images {
        for px in img.data.chunks_exact_mut(3) {
            px.copy_from_slice(&colour);
        }
    }
    let t = 3;
    let src = nearest(&s.cameras, t, 3);
    let pyr = pyramids(&s, &src, 2);
    let refs: Vec<&PyramidSource> = pyr.iter().collect();
    let inv = inverse_depths(s.near, s.far, 12);
    let cam = s.cameras[t];
    for coarse in [CoarsePass::Photo, CoarsePass::Network] {
        let opts = PruneOptions {
            coarse,
            ..PruneOptions::auto()
        };
        let mut pruner = Pruner::new(backend.config(), &cam, &refs, &inv, None, &opts);
        if coarse == CoarsePass::Network {
            let g = network_guide(&backend, &cam, &refs, &inv, pruner.range(), 2, 32, 0, false)?
                .ok_or("no guide")?;
            pruner = pruner.with_guide(g, 0.0);
        }
        let got = render_view_pruned(&backend, &cam, &refs, &inv, 32, Some(&pruner), &|_, _| {})?;
        let st = got.prune.clone().ok_or("stats")?;
        // Tiles at the image border see beyond the sources for some planes (not flat).
        assert!(st.flat * 2 >= st.tiles, "{coarse:?}: {st:?}");
        assert!(
            st.planes_run + st.flat * 32 * 32 * 12 <= st.planes_total,
            "{st:?}"
        );
        let (w, h) = (
            cam.intrinsics.width as usize,
            cam.intrinsics.height as usize,
        );
        for y in 32..h.min(64) {
            for x in 32..w.min(64) {
                let p = got.image.pixel(x as u32, y as u32);
                for c in 0..3 {
                    assert!(
                        (p[c] - colour[c]).abs() < 1e-4,
                        "{coarse:?} ({x}, {y}): {p:?}"
                    );
                }
            }
        }
    }
    // A textured procedural scene: its textured tiles are never flat.
    let s = scene(31, Rig::Forward);
    let pyr = pyramids(&s, &src, 2);
    let refs: Vec<&PyramidSource> = pyr.iter().collect();
    let opts = PruneOptions::auto();
    let pruner = Pruner::new(backend.config(), &cam, &refs, &inv, None, &opts);
    let known = known_pixels(&s, t, &src, &inv);
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    for y0 in (0..h).step_by(32) {
        for x0 in (0..w).step_by(32) {
            if pruner.flat_probe_for_tests(x0, y0, 32) {
                let textured = (y0..(y0 + 32).min(h))
                    .flat_map(|y| (x0..(x0 + 32).min(w)).map(move |x| y * w + x))
                    .any(|i| known[i]);
                assert!(!textured, "textured tile ({x0}, {y0}) found flat");
            }
        }
    }
    Ok(())
}

/// The colour bound: the prefix `needed_prefix` returns is the shortest one that holds
/// `mass` of the selection, or holds `COLOUR_MIN_MASS` of it with its renormalized blend
/// within the bound of the full blend, computed here directly in f64.
#[test]
fn prune_needed_prefix_is_the_shortest_within_the_colour_bound() {
    // Equal colours: leaving planes out changes nothing once 70% is kept.
    let probs = [(0.5, 0), (0.3, 1), (0.2, 2)];
    assert_eq!(needed_prefix(&probs, &[[0.4; 3]; 3], 0.95, 0.01), 2);
    // Without colours only the mass decides.
    assert_eq!(needed_prefix(&probs, &[], 0.95, 0.01), 3);
    assert_eq!(needed_prefix(&probs, &[], 0.8, 0.01), 2);
    // The last plane differs: leaving it out moves the colour by 0.2 (> 0.01).
    let c = [[0.0; 3], [0.0; 3], [1.0, 0.0, 0.0]];
    assert_eq!(needed_prefix(&probs, &c, 0.95, 0.01), 3);
    assert_eq!(needed_prefix(&probs, &c, 0.95, 0.25), 2);
    let mut seed = 12345u64;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 33) as f32 / (1u64 << 31) as f32
    };
    for _ in 0..500 {
        let n = 1 + (rnd() * 12.0) as usize;
        let mut probs: Vec<(f32, usize)> = (0..n).map(|z| (rnd().powi(3), z)).collect();
        probs.sort_by(|a, b| b.0.total_cmp(&a.0));
        let colours: Vec<[f32; 3]> = (0..n).map(|_| [rnd(), rnd(), rnd()]).collect();
        let (mass, err) = (0.5 + 0.5 * rnd(), 0.05 * rnd());
        let total: f64 = probs.iter().map(|p| p.0 as f64).sum();
        let blend = |k: usize| -> [f64; 3] {
            let s: f64 = probs[..k].iter().map(|p| p.0 as f64).sum();
            [0, 1, 2].map(|ch| {
                (probs[..k].iter().zip(&colours))
                    .map(|(p, c)| p.0 as f64 * c[ch] as f64)
                    .sum::<f64>()
                    / s
            })
        };
        let all = blend(n);
        let ok = |k: usize| {
            let held: f64 = probs[..k].iter().map(|p| p.0 as f64).sum();
            let b = blend(k);
            held >= mass as f64 * total - 1e-6
                || (held >= COLOUR_MIN_MASS as f64 * total - 1e-6
                    && (0..3).all(|ch| (b[ch] - all[ch]).abs() <= err as f64 + 1e-6))
        };
        let k = needed_prefix(&probs, &colours, mass, err);
        assert!(k >= 1 && k <= n);
        assert!(k == n || ok(k), "prefix {k} of {n} outside the bound");
        // Nothing shorter would do (up to rounding at the thresholds).
        if k > 1 {
            let held: f64 = probs[..k - 1].iter().map(|p| p.0 as f64).sum();
            let b = blend(k - 1);
            let clearly = held >= mass as f64 * total + 1e-4
                || (held >= COLOUR_MIN_MASS as f64 * total + 1e-4
                    && (0..3).all(|ch| (b[ch] - all[ch]).abs() <= err as f64 - 1e-4));
            assert!(!clearly, "prefix {} of {n} would do", k - 1);
        }
    }
}

#[test]
fn prune_span_planes_spreads_the_grid_over_a_range() {
    let inv = inverse_depths(1.0, 10.0, 32);
    let (first, last) = (18, 30);
    let s = span_planes(&inv, (first, last));
    assert_eq!(s.len(), 32);
    // The range's ends exactly, and equal steps in inverse depth between them, nearest
    // first: 12 steps of the old grid become 31.
    assert_eq!((s[0], s[31]), (inv[first], inv[last]));
    let step = (inv[last] - inv[first]) / 31.0;
    for (i, w) in s.windows(2).enumerate() {
        assert!(
            ((w[1] - w[0]) - step).abs() < 1e-12,
            "step {i}: {}",
            w[1] - w[0]
        );
    }
    assert!((inv[first] - inv[last]) / (s[0] - s[1]) > 31.0 - 1e-9);
    // A plane at infinity stays the far end.
    let inf = inverse_depths(2.0, f64::INFINITY, 8);
    assert_eq!(span_planes(&inf, (3, 7))[7], 0.0);
    // The whole grid is itself; no range, or one plane, changes nothing.
    let whole = span_planes(&inv, (0, 31));
    assert!(whole.iter().zip(&inv).all(|(a, b)| (a - b).abs() < 1e-15));
    assert_eq!(span_planes(&inv, (5, 4)), inv);
    assert_eq!(span_planes(&inv, (5, 32)), inv);
    assert_eq!(span_planes(&[0.5], (0, 0)), vec![0.5]);
}
