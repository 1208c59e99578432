//! Tests of the scene generator: determinism, the on-disk format, agreement of poses,
//! pixels and depths, options. The plane-sweep and overlap checks are in `tests_sweep`.

use super::*;
use crate::camera::Camera;
use crate::scene::{LoadOptions, Scene, SceneFormat};
use crate::sweep::sample_bilinear;
use glam::DVec2;
use std::path::Path;

pub(super) type TestResult = std::result::Result<(), Box<dyn std::error::Error>>;

pub(super) fn small(rig: Rig, views: usize, width: u32, height: u32) -> SynthOptions {
    SynthOptions {
        views,
        width,
        height,
        rig,
        supersample: 2,
        textures: Vec::new(),
        rolling_shutter: 0.0,
    }
}

/// Indices of the `k` cameras nearest to camera `t` by centre (ties by index).
pub(super) fn nearest(cams: &[Camera], t: usize, k: usize) -> Vec<usize> {
    let c = cams[t].pose.centre();
    let mut idx: Vec<(f64, usize)> = (0..cams.len())
        .filter(|&i| i != t)
        .map(|i| (cams[i].pose.centre().distance_squared(c), i))
        .collect();
    idx.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    idx.into_iter().take(k).map(|(_, i)| i).collect()
}

/// Pixel centre of pixel `p` of a `w`-wide image.
pub(super) fn centre(p: usize, w: usize) -> DVec2 {
    DVec2::new((p % w) as f64 + 0.5, (p / w) as f64 + 0.5)
}

fn files_under(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p.strip_prefix(dir).map(Path::to_path_buf).unwrap_or(p));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn synth_is_deterministic() -> TestResult {
    let opts = small(Rig::Mixed, 4, 48, 36);
    let (a, b) = (generate(11, &opts)?, generate(11, &opts)?);
    let bits = |s: &SynthScene| -> Vec<u32> {
        s.images
            .iter()
            .flat_map(|i| i.data.iter())
            .chain(s.depths.iter().flatten())
            .map(|v| v.to_bits())
            .collect()
    };
    assert_eq!(bits(&a), bits(&b));
    assert_eq!(a.cameras, b.cameras);
    assert_eq!(
        (a.near.to_bits(), a.far.to_bits(), a.rig),
        (b.near.to_bits(), b.far.to_bits(), b.rig)
    );
    assert_ne!(bits(&a), bits(&generate(12, &opts)?));
    let (d1, d2) = (tempfile::tempdir()?, tempfile::tempdir()?);
    write_scene(d1.path(), &a)?;
    write_scene(d2.path(), &b)?;
    let files = files_under(d1.path());
    assert_eq!(files, files_under(d2.path()));
    assert_eq!(files.len(), 2 * opts.views + 1);
    for f in &files {
        assert_eq!(
            std::fs::read(d1.path().join(f))?,
            std::fs::read(d2.path().join(f))?,
            "{}",
            f.display()
        );
    }
    Ok(())
}

#[test]
fn synth_round_trips_through_the_nerf_reader() -> TestResult {
    for rig in Rig::CONCRETE {
        let s = generate(5, &small(rig, 5, 40, 30))?;
        assert_eq!(s.rig, rig);
        let dir = tempfile::tempdir()?;
        write_scene(dir.path(), &s)?;
        let loaded = Scene::load(dir.path(), &LoadOptions::default())?;
        assert_eq!(loaded.format, SceneFormat::Nerf);
        assert_eq!((loaded.near, loaded.far), (s.near, s.far));
        assert_eq!(loaded.views.len(), s.cameras.len());
        for (v, c) in loaded.views.iter().zip(&s.cameras) {
            let (k, l) = (&c.intrinsics, &v.camera.intrinsics);
            assert_eq!((k.width, k.height), (l.width, l.height));
            for (x, y) in [(k.fx, l.fx), (k.fy, l.fy), (k.cx, l.cx), (k.cy, l.cy)] {
                assert!((x - y).abs() < 1e-9, "{rig}: intrinsics {x} vs {y}");
            }
            let (p, q) = (&c.pose, &v.camera.pose);
            let dr = (p.rotation - q.rotation)
                .to_cols_array()
                .iter()
                .fold(0.0f64, |m, d| m.max(d.abs()));
            assert!(
                dr < 1e-9 && (p.translation - q.translation).length() < 1e-9,
                "{rig}: pose"
            );
            let img = loaded.load_image(0)?;
            assert_eq!((img.width, img.height), (k.width, k.height));
        }
        let depth = crate::scene::npy::read_npy(&dir.path().join("depth/view_000.npy"))?;
        assert_eq!(depth.shape, vec![30, 40]);
        assert!(depth
            .data
            .iter()
            .zip(&s.depths[0])
            .all(|(a, b)| *a == *b as f64));
        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("transforms.json"))?)?;
        assert_eq!(json["rig"], rig.name());
        assert_eq!(json["seed"], 5);
    }
    Ok(())
}

/// Mean absolute colour difference between pixels of view `a` and their reprojections in
/// view `b` where `b` sees the same point, and the fraction of such pixels.
fn reprojection_error(s: &SynthScene, a: usize, b: usize) -> (f64, f64) {
    let (ca, cb) = (&s.cameras[a], &s.cameras[b]);
    let (w, h) = (ca.intrinsics.width as usize, ca.intrinsics.height as usize);
    let (wb, hb) = (cb.intrinsics.width as f64, cb.intrinsics.height as f64);
    let (mut err, mut n) = (0.0, 0usize);
    for p in 0..w * h {
        let pt = ca.unproject(centre(p, w), s.depths[a][p] as f64);
        let (uv, z) = cb.project(pt);
        if !(z > 0.0 && uv.x >= 1.0 && uv.y >= 1.0 && uv.x < wb - 1.0 && uv.y < hb - 1.0) {
            continue;
        }
        let zb = s.depths[b][uv.y as usize * wb as usize + uv.x as usize] as f64;
        if (zb - z).abs() > 0.01 * z {
            continue;
        }
        let c = sample_bilinear(&s.images[b], uv.x, uv.y);
        let px = s.images[a].pixel((p % w) as u32, (p / w) as u32);
        err += (0..3).map(|k| (c[k] - px[k]).abs() as f64).sum::<f64>() / 3.0;
        n += 1;
    }
    (err / n.max(1) as f64, n as f64 / (w * h) as f64)
}

#[test]
fn synth_depths_poses_and_pixels_agree() -> TestResult {
    for rig in Rig::CONCRETE {
        let s = generate(
            21,
            &SynthOptions {
                supersample: 3,
                ..small(rig, 6, 96, 72)
            },
        )?;
        let lo = s
            .depths
            .iter()
            .flatten()
            .fold(f32::INFINITY, |m, &z| m.min(z)) as f64;
        let hi = s.depths.iter().flatten().fold(0.0f32, |m, &z| m.max(z)) as f64;
        assert!(s.near < lo && s.far > hi && s.near > 0.0, "{rig}: bounds");
        assert!(s
            .images
            .iter()
            .flat_map(|i| &i.data)
            .all(|v| (0.0..=1.0).contains(v)));
        for b in nearest(&s.cameras, 0, 2) {
            let (err, seen) = reprojection_error(&s, 0, b);
            println!(
                "{rig}: view 0 -> {b}: mean abs diff {err:.4} over {:.0}% of pixels",
                100.0 * seen
            );
            assert!(
                seen > 0.3,
                "{rig}: only {seen} of view 0 is visible in view {b}"
            );
            assert!(err < 0.05, "{rig}: colours disagree ({err})");
        }
    }
    Ok(())
}

#[test]
fn synth_options_and_rigs_are_checked() {
    for rig in [
        Rig::Forward,
        Rig::Rosette,
        Rig::Ring,
        Rig::Handheld,
        Rig::Mixed,
    ] {
        assert_eq!(rig.to_string().parse::<Rig>().ok(), Some(rig));
    }
    assert!("orbit".parse::<Rig>().is_err());
    let base = small(Rig::Forward, 3, 16, 12);
    for bad in [
        SynthOptions {
            views: 1,
            ..base.clone()
        },
        SynthOptions {
            width: 0,
            ..base.clone()
        },
        SynthOptions {
            height: 0,
            ..base.clone()
        },
        SynthOptions {
            supersample: 0,
            ..base.clone()
        },
        SynthOptions {
            supersample: MAX_SUPERSAMPLE + 1,
            ..base.clone()
        },
    ] {
        assert!(generate(1, &bad).is_err(), "{bad:?}");
    }
    assert!(generate(1, &base).is_ok());
    let seeds: std::collections::HashSet<u64> = (0..1000).map(|i| scene_seed(7, i)).collect();
    assert_eq!(seeds.len(), 1000);
}

#[test]
fn synth_photo_textures_and_sets() -> TestResult {
    let dir = tempfile::tempdir()?;
    assert!(load_textures(dir.path()).is_err());
    let mut photo = RgbImage::new(40, 32);
    for (i, v) in photo.data.iter_mut().enumerate() {
        *v = ((i * 37) % 101) as f32 / 100.0;
    }
    photo.save_png(&dir.path().join("a.png"))?;
    let textures = load_textures(dir.path())?;
    assert_eq!(textures.len(), 1);
    std::fs::write(dir.path().join("b.jpg"), b"not a jpeg")?;
    let e = load_textures(dir.path())
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(e.contains("b.jpg"), "{e}");
    let s = generate(
        3,
        &SynthOptions {
            textures,
            ..small(Rig::Mixed, 3, 32, 24)
        },
    )?;
    let (lo, hi) = s.images[0]
        .data
        .iter()
        .fold((1.0f32, 0.0f32), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(hi - lo > 0.1, "photo-textured view is flat");

    let out = tempfile::tempdir()?;
    let opts = small(Rig::Mixed, 3, 24, 18);
    write_scenes(out.path(), 3, 42, &opts)?;
    for i in 0..3 {
        let loaded = Scene::load(&scene_dir(out.path(), i), &LoadOptions::default())?;
        assert_eq!(loaded.views.len(), 3);
    }
    let scenes: Vec<SynthScene> = (0..2)
        .map(|i| generate(scene_seed(42, i), &opts))
        .collect::<Result<_>>()?;
    let sheet = contact_sheet(&scenes, 2);
    assert_eq!(
        (sheet.width, sheet.height),
        (2 + 4 * (24 + 2), 2 + 2 * (18 + 2))
    );
    Ok(())
}

#[test]
fn synth_handles_extreme_options() -> TestResult {
    for rig in Rig::CONCRETE {
        for (views, w, h) in [(2, 1, 1), (2, 9, 200), (40, 32, 24), (3, 200, 9)] {
            for seed in 0..3 {
                let s = generate(
                    seed,
                    &SynthOptions {
                        supersample: 1,
                        ..small(rig, views, w, h)
                    },
                )?;
                assert_eq!(
                    (s.cameras.len(), s.images.len(), s.depths.len()),
                    (views, views, views)
                );
                assert!(s
                    .depths
                    .iter()
                    .flatten()
                    .all(|z| z.is_finite() && *z as f64 > s.near));
            }
        }
    }
    Ok(())
}
