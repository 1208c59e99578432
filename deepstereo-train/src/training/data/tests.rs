//! The sampler's unit tests.

use super::*;
use deepstereo_core::imageio::RgbImage;

fn scenes(cfg: &Config) -> Vec<SceneData> {
    let opts = SynthOptions {
        views: 6,
        width: 64,
        height: 48,
        ..SynthOptions::default()
    };
    synth_scenes(2, 11, &opts, cfg.levels).expect("scenes")
}

#[test]
fn batch_shapes_follow_the_config() -> anyhow::Result<()> {
    let cfg = Config::tiny();
    let b = make_batch(&cfg, &Sampling::fixed(&cfg), &scenes(&cfg), 1, 0, 3)?;
    assert_eq!(b.target_shape, [3, 3, cfg.tile, cfg.tile]);
    assert_eq!(b.target.len(), 3 * 3 * cfg.tile * cfg.tile);
    for l in 0..cfg.levels {
        let s = cfg.input_size(l, cfg.tile);
        assert_eq!(b.level_shapes[l], [3, cfg.planes, cfg.in_channels(), s, s]);
        assert_eq!(b.views, cfg.views);
        assert_eq!(
            b.levels[l].len(),
            b.level_shapes[l].iter().product::<usize>()
        );
    }
    assert!(b.target.iter().all(|v| (0.0..=1.0).contains(v)));
    Ok(())
}

#[test]
fn batches_are_deterministic_and_differ_between_indices() -> anyhow::Result<()> {
    let cfg = Config::tiny();
    let sc = scenes(&cfg);
    let fixed = Sampling::fixed(&cfg);
    let a = make_batch(&cfg, &fixed, &sc, 5, 7, 2)?;
    let b = make_batch(&cfg, &fixed, &sc, 5, 7, 2)?;
    let c = make_batch(&cfg, &fixed, &sc, 5, 8, 2)?;
    assert!(a.levels == b.levels && a.target == b.target);
    assert!(a.target != c.target);
    Ok(())
}

/// The coarse level covers an area twice as wide, so near the image border some of
/// its pixels fall outside every source: alpha 0 there, and never outside [0, 1].
#[test]
fn alpha_is_zero_where_sources_do_not_see() -> anyhow::Result<()> {
    let cfg = Config::tiny();
    let b = make_batch(&cfg, &Sampling::fixed(&cfg), &scenes(&cfg), 3, 0, 8)?;
    let l = cfg.levels - 1;
    let [_, d, c, h, w] = b.level_shapes[l][..] else {
        anyhow::bail!("expected a 5-d level shape");
    };
    let plane = h * w;
    let mut zeros = 0usize;
    for (i, chunk) in b.levels[l].chunks_exact(plane).enumerate() {
        if (i % c) % 4 == 3 {
            assert!(
                chunk.iter().all(|a| (0.0..=1.0).contains(a)),
                "alpha outside [0, 1]"
            );
            zeros += chunk.iter().filter(|&&a| a == 0.0).count();
        }
    }
    assert!(
        zeros > 0,
        "expected uncovered pixels at level {l} ({d} planes)"
    );
    Ok(())
}

/// The pooled family: the view count varies across batches within the range, shapes
/// carry it, and scenes with fewer views than asked are padded with empty views.
#[test]
fn pooled_batches_draw_their_view_count() -> anyhow::Result<()> {
    let cfg = Config::nviews();
    let sc = scenes(&cfg); // 6 views each: 5 sources at most
    let sampling = Sampling {
        views: (2, 8),
        ..Sampling::fixed(&cfg)
    };
    let mut seen = std::collections::BTreeSet::new();
    for b in 0..12 {
        let batch = make_batch(&cfg, &sampling, &sc, 9, b, 2)?;
        assert!((2..=8).contains(&batch.views));
        let s = cfg.input_size(0, cfg.tile);
        assert_eq!(batch.level_shapes[0], [2, cfg.planes, batch.views, 4, s, s]);
        seen.insert(batch.views);
        if batch.views > 5 {
            // The padded views' alpha is zero everywhere.
            let v = batch.views;
            let plane = s * s;
            for (i, chunk) in batch.levels[0].chunks_exact(plane).enumerate() {
                if (i / 4) % v >= 5 {
                    assert!(chunk.iter().all(|&x| x == 0.0));
                }
            }
        }
    }
    assert!(seen.len() >= 3, "view counts drawn: {seen:?}");
    let range = |lo, hi| Sampling {
        views: (lo, hi),
        ..Sampling::fixed(&cfg)
    };
    assert!(range(0, 3).check(&cfg).is_err());
    assert!(range(2, 8).check(&Config::tiny()).is_err());
    Ok(())
}

/// A stride `s` takes every `s`-th nearest view; a stride range of one value leaves
/// the batches exactly as they were (no extra random draw); a wider range changes
/// them; impossible ranges are refused.
#[test]
fn view_stride_takes_every_sth_nearest() -> anyhow::Result<()> {
    let cfg = Config::nviews();
    let sc = scenes(&cfg); // 6 views each
    let s = &sc[0];
    let nearest = s.sources(0, 5);
    assert_eq!(s.strided_sources(0, 2, 1), nearest[..2]);
    assert_eq!(s.strided_sources(0, 2, 2), [nearest[1], nearest[3]]);
    assert_eq!(s.strided_sources(0, 3, 2), [nearest[1], nearest[3]]); // only 5 others
    let fixed = Sampling::fixed(&cfg);
    let one = Sampling {
        view_stride: (1, 1),
        ..fixed.clone()
    };
    let wide = Sampling {
        view_stride: (2, 3),
        ..fixed.clone()
    };
    let a = make_batch(&cfg, &fixed, &sc, 5, 0, 2)?;
    assert_eq!(a.levels, make_batch(&cfg, &one, &sc, 5, 0, 2)?.levels);
    assert_ne!(a.levels, make_batch(&cfg, &wide, &sc, 5, 0, 2)?.levels);
    for bad in [(0, 1), (3, 2), (1, MAX_VIEW_STRIDE + 1)] {
        let s = Sampling {
            view_stride: bad,
            ..fixed.clone()
        };
        assert!(s.check(&cfg).is_err(), "{bad:?}");
    }
    Ok(())
}

/// The flat-tile test measures the luminance's spread; a threshold of 0 redraws
/// nothing (the batches of runs without it), one no tile reaches redraws (other
/// batches), and thresholds outside 0..=0.5 (or NaN) are refused.
#[test]
fn skip_flat_redraws_flat_tiles() -> anyhow::Result<()> {
    let mut img = RgbImage::new(4, 4);
    assert_eq!(luminance_std(&img, (0, 0), 4), 0.0);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = ((i / 3) % 2) as f32; // alternate black and white pixels
    }
    assert!((luminance_std(&img, (0, 0), 4) - 0.5).abs() < 1e-6);
    let cfg = Config::nviews();
    let sc = scenes(&cfg);
    let fixed = Sampling::fixed(&cfg);
    let with = |s: f32| Sampling {
        skip_flat: Some(s),
        ..fixed.clone()
    };
    let a = make_batch(&cfg, &fixed, &sc, 5, 0, 2)?;
    assert_eq!(a.levels, make_batch(&cfg, &with(0.0), &sc, 5, 0, 2)?.levels);
    assert_ne!(a.levels, make_batch(&cfg, &with(0.5), &sc, 5, 0, 2)?.levels);
    for bad in [-0.1, 0.6, f32::NAN] {
        assert!(with(bad).check(&cfg).is_err(), "{bad}");
    }
    Ok(())
}

/// Scene weights draw a named real scene that many times as often as the others,
/// leave the procedural share alone, and are checked like the other options.
#[test]
fn scene_weights_draw_named_scenes_more_often() {
    let stub = |name: &str, synthetic| SceneData {
        name: name.into(),
        synthetic,
        cameras: Vec::new(),
        pyramids: Vec::new(),
        near: 1.0,
        far: 2.0,
        targets: None,
    };
    let sc = [stub("/d/a", false), stub("/d/b", false), stub("p0", true)];
    let cfg = Config::nviews();
    let count = |s: &Sampling| {
        let mut c = [0usize; 3];
        for k in 0..40_000u64 {
            let p = pick_scene(&sc, s, mix(k), mix(k ^ 0xabcd));
            c[sc.iter().position(|x| std::ptr::eq(x, p)).unwrap_or(0)] += 1;
        }
        c
    };
    let weights = SceneWeights(vec![("b".into(), 3.0)]);
    for percent in [Some(50), None] {
        let base = Sampling {
            synthetic_percent: percent,
            ..Sampling::fixed(&cfg)
        };
        let weighted = Sampling {
            scene_weights: weights.clone(),
            ..base.clone()
        };
        let (u, w) = (count(&base), count(&weighted));
        let ratio = |c: [usize; 3], i: usize| c[i] as f64 / c[0] as f64;
        assert!((ratio(u, 1) - 1.0).abs() < 0.1, "{percent:?} {u:?}");
        assert!((ratio(w, 1) - 3.0).abs() < 0.25, "{percent:?} {w:?}");
        match percent {
            // The share of procedural samples is drawn first, and weights keep it.
            Some(_) => assert_eq!(u[2], w[2]),
            // Without a share, a procedural scene weighs 1 like an unnamed real one.
            None => assert!((ratio(w, 2) - 1.0).abs() < 0.1, "{w:?}"),
        }
        let bad = Sampling {
            scene_weights: SceneWeights(vec![("b".into(), -1.0)]),
            ..base
        };
        assert!(bad.check(&cfg).is_err());
    }
}

/// Augmentation scales colours (not alpha) by one gain per channel for the sources
/// and the target alike, and flips them together.
#[test]
fn augmentation_scales_colours_and_flips_consistently() {
    let (plane, w) = (6, 3);
    let mut vol: Vec<f32> = (0..8 * plane).map(|i| i as f32).collect(); // 2 views
    let orig = vol.clone();
    augment_planes(&mut vol, (plane, w, 4), &[2.0, 3.0, 4.0], true);
    for (i, (a, o)) in vol
        .chunks_exact(plane)
        .zip(orig.chunks_exact(plane))
        .enumerate()
    {
        let g = [2.0, 3.0, 4.0, 1.0][i % 4];
        assert_eq!(
            a[0],
            o[2] * g,
            "plane {i}: first value is the mirrored row's last"
        );
        assert_eq!(a[3], o[5] * g);
    }
    let mut target: Vec<f32> = (0..3 * plane).map(|i| i as f32).collect();
    augment_planes(&mut target, (plane, w, 3), &[2.0, 3.0, 4.0], false);
    assert_eq!(target[2 * plane + 1], (2 * plane + 1) as f32 * 4.0);
}

/// With the per-view cue (9 channels per view): the gains touch R, G, B only, and a flip
/// mirrors every channel and negates the cue's horizontal direction (channel 4) alone.
#[test]
fn augmentation_flips_the_cue_direction() {
    let (plane, w, cycle) = (6, 3, 9);
    let mut vol: Vec<f32> = (0..2 * cycle * plane).map(|i| i as f32 + 1.0).collect();
    let orig = vol.clone();
    augment_planes(&mut vol, (plane, w, cycle), &[2.0, 3.0, 4.0], true);
    for (i, (a, o)) in vol
        .chunks_exact(plane)
        .zip(orig.chunks_exact(plane))
        .enumerate()
    {
        let g = match i % cycle {
            c @ 0..=2 => [2.0, 3.0, 4.0][c],
            4 => -1.0,
            _ => 1.0,
        };
        assert_eq!(a[0], o[2] * g, "plane {i} (channel {})", i % cycle);
        assert_eq!(a[5], o[3] * g, "plane {i} (channel {})", i % cycle);
    }
    let mut again = orig.clone();
    augment_planes(&mut again, (plane, w, cycle), &[1.0, 1.0, 1.0], false);
    assert_eq!(again, orig, "unit gains without a flip change nothing");
}

#[test]
fn the_target_is_never_a_source() {
    let cfg = Config::tiny();
    let sc = scenes(&cfg);
    for s in &sc {
        for t in 0..s.cameras.len() {
            let src = s.sources(t, cfg.views);
            assert_eq!(src.len(), cfg.views);
            assert!(!src.contains(&t));
        }
    }
}

/// Pair samples for the loss through the MPI ([`pairs`]): every view of a scene one flat
/// colour of its own, so a sample's colours tell which views it read. Neither the
/// reference (the tile's target) nor the neighbouring view (the MPI's target) is ever a
/// source, and the warps count pixels, at full and at half resolution (`scale` 2).
#[test]
fn pair_samples_leave_the_reference_and_its_neighbour_out() -> anyhow::Result<()> {
    let cfg = Config::nviews();
    let mut sc = scenes(&cfg);
    for s in &mut sc {
        for (i, cam) in s.cameras.iter().enumerate() {
            let k = &cam.intrinsics;
            let mut img = RgbImage::new(k.width, k.height);
            img.data.iter_mut().for_each(|v| *v = 0.1 + 0.1 * i as f32);
            s.pyramids[i] = PyramidSource::new(cam, &img, cfg.levels);
        }
    }
    // At scale 2 the pairs come from pyramid level 1 (flat colours too).
    for (scale, (tw, th)) in [(1, (40, 24)), (2, (24, 16))] {
        let pairs = MpiPairs {
            weight: 1.0,
            tile: (tw, th),
            neighbours: 2,
            scale,
        };
        let sampling = Sampling {
            views: (3, 3),
            mpi: Some(pairs),
            ..Sampling::fixed(&cfg)
        };
        let (mut counted, mut samples) = (0, 0);
        for b in 0..6 {
            let batch = make_batch(&cfg, &sampling, &sc, 4, b, 2)?;
            let again = make_batch(&cfg, &sampling, &sc, 4, b, 2)?;
            let Some(p) = &batch.mpi else {
                anyhow::bail!("a pair batch without its MPI part");
            };
            assert!(batch.levels == again.levels && again.mpi.is_some_and(|q| q.plans == p.plans));
            let (h, w) = (cfg.input_size(0, th), cfg.input_size(0, tw));
            let c = cfg.view_channels();
            assert_eq!(batch.level_shapes[0], [2, cfg.planes, 3, c, h, w]);
            assert_eq!(p.pixels, tw * th);
            let per_sample = batch.levels[0].len() / 2;
            for k in 0..2 {
                let own = batch.target[k * 3 * p.pixels];
                let neighbour = p.target[k * 3 * p.pixels];
                assert!(
                    own != neighbour,
                    "the reference and its neighbour are two views"
                );
                let input = &batch.levels[0][k * per_sample..(k + 1) * per_sample];
                let plane = h * w;
                let chunks: Vec<&[f32]> = input.chunks_exact(plane).collect();
                for i in (0..chunks.len()).step_by(c) {
                    // Red of some view on some plane where it sees the pixel fully (at its
                    // border, bilinear sampling blends its colour with black).
                    for (&v, &a) in chunks[i].iter().zip(chunks[i + 3]) {
                        assert!(
                            a < 1.0 || ((v - own).abs() > 1e-4 && (v - neighbour).abs() > 1e-4),
                            "a source holds the colour {v} of the reference or its neighbour"
                        );
                    }
                }
                counted += p.plans[k].count();
                samples += 1;
            }
        }
        assert!(
            counted > 0,
            "no target pixel sees its tile in {samples} samples"
        );
    }
    let pairs = MpiPairs {
        weight: 1.0,
        tile: (40, 24),
        neighbours: 2,
        scale: 1,
    };
    let sampling = Sampling {
        views: (3, 3),
        mpi: Some(pairs),
        ..Sampling::fixed(&cfg)
    };
    let augmented = Sampling {
        augment: true,
        ..sampling
    };
    assert!(make_batch(&cfg, &augmented, &sc, 4, 0, 2).is_err());
    Ok(())
}
