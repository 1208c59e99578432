//! Rolling-shutter scenes: the exact depths and the sweep agree with the images only
//! when the shutter is modelled.

use super::tests::{centre, nearest, small, TestResult};
use super::tests_sweep::{central_view, plane_sweep_render, psnr};
use super::*;
use crate::sweep::{sample_bilinear, Source};

/// Strong motion: the readout covers all of the motion from one view to the next.
const SHARE: f64 = 1.0;

fn rolling(rig: Rig, views: usize, w: u32, h: u32) -> SynthOptions {
    SynthOptions {
        rolling_shutter: SHARE,
        ..small(rig, views, w, h)
    }
}

/// PSNR of view `t`'s pixels against the colours its 4 nearest views show at the same
/// surface points (each pixel's exact depth, projected with `project_rolling`), over the
/// points a view sees unoccluded (its own depth there agrees within 2%); and how many.
fn reprojection_psnr(s: &SynthScene, cams: &[Camera], t: usize) -> (f64, usize) {
    let w = cams[t].intrinsics.width as usize;
    let (mut se, mut n) = (0.0f64, 0usize);
    for p in 0..s.depths[t].len() {
        let pt = cams[t].unproject(centre(p, w), s.depths[t][p] as f64);
        for &b in &nearest(cams, t, 4) {
            let Some((uv, z)) = cams[b].project_rolling(pt) else {
                continue;
            };
            let rgba = sample_bilinear(&s.images[b], uv.x, uv.y);
            let kb = &cams[b].intrinsics;
            let (x, y) = (uv.x.floor() as i64, uv.y.floor() as i64);
            if rgba[3] < 1.0 || x < 0 || y < 0 || x >= kb.width as i64 || y >= kb.height as i64 {
                continue;
            }
            let zb = s.depths[b][y as usize * kb.width as usize + x as usize] as f64;
            if (zb - z).abs() > 0.02 * z {
                continue;
            }
            for (a, b) in rgba.iter().zip(&s.images[t].data[3 * p..3 * p + 3]) {
                se += ((a - b) as f64).powi(2);
            }
            n += 1;
        }
    }
    (10.0 * (1.0 / (se / (3 * n.max(1)) as f64)).log10(), n)
}

#[test]
fn rolling_synth_is_global_for_share_zero_and_moves_otherwise() -> TestResult {
    let gs = generate(5, &small(Rig::Handheld, 5, 48, 36))?;
    assert!(gs.cameras.iter().all(|c| c.rolling_shutter.is_none()));
    let rs = generate(5, &rolling(Rig::Handheld, 5, 48, 36))?;
    for (a, b) in gs.cameras.iter().zip(&rs.cameras) {
        let shutter = b.moving_shutter().expect("a moving shutter");
        // The readout starts at the global-shutter pose.
        assert_eq!(shutter.start, a.pose);
        assert_eq!(shutter.time_at(glam::DVec2::new(3.0, 36.0)), 1.0);
    }
    assert!(SynthOptions {
        rolling_shutter: 1.5,
        ..small(Rig::Handheld, 5, 48, 36)
    }
    .validate()
    .is_err());
    Ok(())
}

#[test]
fn rolling_synth_reprojects_with_the_model_and_not_without() -> TestResult {
    for (rig, seed) in [(Rig::Forward, 21), (Rig::Handheld, 22), (Rig::Rosette, 23)] {
        let s = generate(seed, &rolling(rig, 8, 96, 72))?;
        let t = central_view(&s.cameras);
        let ignored: Vec<Camera> = s
            .cameras
            .iter()
            .map(|c| c.without_rolling_shutter())
            .collect();
        let (aware, n_aware) = reprojection_psnr(&s, &s.cameras, t);
        let (blind, n_blind) = reprojection_psnr(&s, &ignored, t);
        // The plane sweep over the 4 nearest views, as `synth_plane_sweep_beats_nearest_source`.
        let sweep_psnr = |cams: &[Camera]| {
            let src = nearest(cams, t, 4);
            let sources: Vec<Source<'_>> = src
                .iter()
                .map(|&i| Source {
                    camera: &cams[i],
                    image: &s.images[i],
                })
                .collect();
            psnr(
                &plane_sweep_render(&cams[t], &sources, s.near, s.far, 32),
                &s.images[t],
            )
        };
        let (sw_aware, sw_blind) = (sweep_psnr(&s.cameras), sweep_psnr(&ignored));
        println!(
            "{rig} seed {seed} view {t}: exact-depth reprojection {aware:.2} dB ({n_aware} samples) \
             with the model, {blind:.2} dB ({n_blind}) without; plane sweep {sw_aware:.2} vs {sw_blind:.2} dB"
        );
        assert!(aware > 27.0, "{rig}: {aware:.2} dB with the model");
        assert!(aware > blind + 6.0, "{rig}: {aware:.2} vs {blind:.2} dB");
        assert!(
            sw_aware > sw_blind + 1.0,
            "{rig}: sweep {sw_aware:.2} vs {sw_blind:.2} dB"
        );
    }
    Ok(())
}
