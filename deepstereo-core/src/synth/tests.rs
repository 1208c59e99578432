//! Tests of the scene generator: determinism, the on-disk format, agreement of poses,
//! pixels and depths, and that a classical plane sweep beats copying a neighbour.

use super::*;
use crate::camera::Camera;
use crate::geometry::inverse_depths;
use crate::scene::{LoadOptions, Scene, SceneFormat};
use crate::sweep::{sample_bilinear, sweep, Region, Source, CHANNELS};
use glam::DVec2;
use std::path::Path;

type TestResult = std::result::Result<(), Box<dyn std::error::Error>>;

fn small(rig: Rig, views: usize, width: u32, height: u32) -> SynthOptions {
    SynthOptions { views, width, height, rig, supersample: 2, textures: Vec::new() }
}

/// Indices of the `k` cameras nearest to camera `t` by centre (ties by index).
fn nearest(cams: &[Camera], t: usize, k: usize) -> Vec<usize> {
    let c = cams[t].pose.centre();
    let mut idx: Vec<(f64, usize)> = (0..cams.len())
        .filter(|&i| i != t)
        .map(|i| (cams[i].pose.centre().distance_squared(c), i))
        .collect();
    idx.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    idx.into_iter().take(k).map(|(_, i)| i).collect()
}

/// Pixel centre of pixel `p` of a `w`-wide image.
fn centre(p: usize, w: usize) -> DVec2 {
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
        s.images.iter().flat_map(|i| i.data.iter()).chain(s.depths.iter().flatten()).map(|v| v.to_bits()).collect()
    };
    assert_eq!(bits(&a), bits(&b));
    assert_eq!(a.cameras, b.cameras);
    assert_eq!((a.near.to_bits(), a.far.to_bits(), a.rig), (b.near.to_bits(), b.far.to_bits(), b.rig));
    assert_ne!(bits(&a), bits(&generate(12, &opts)?));
    let (d1, d2) = (tempfile::tempdir()?, tempfile::tempdir()?);
    write_scene(d1.path(), &a)?;
    write_scene(d2.path(), &b)?;
    let files = files_under(d1.path());
    assert_eq!(files, files_under(d2.path()));
    assert_eq!(files.len(), 2 * opts.views + 1);
    for f in &files {
        assert_eq!(std::fs::read(d1.path().join(f))?, std::fs::read(d2.path().join(f))?, "{}", f.display());
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
            let dr = (p.rotation - q.rotation).to_cols_array().iter().fold(0.0f64, |m, d| m.max(d.abs()));
            assert!(dr < 1e-9 && (p.translation - q.translation).length() < 1e-9, "{rig}: pose");
            let img = loaded.load_image(0)?;
            assert_eq!((img.width, img.height), (k.width, k.height));
        }
        let depth = crate::scene::npy::read_npy(&dir.path().join("depth/view_000.npy"))?;
        assert_eq!(depth.shape, vec![30, 40]);
        assert!(depth.data.iter().zip(&s.depths[0]).all(|(a, b)| *a == *b as f64));
        let json: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.path().join("transforms.json"))?)?;
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
        let s = generate(21, &SynthOptions { supersample: 3, ..small(rig, 6, 96, 72) })?;
        let lo = s.depths.iter().flatten().fold(f32::INFINITY, |m, &z| m.min(z)) as f64;
        let hi = s.depths.iter().flatten().fold(0.0f32, |m, &z| m.max(z)) as f64;
        assert!(s.near < lo && s.far > hi && s.near > 0.0, "{rig}: bounds");
        assert!(s.images.iter().flat_map(|i| &i.data).all(|v| (0.0..=1.0).contains(v)));
        for b in nearest(&s.cameras, 0, 2) {
            let (err, seen) = reprojection_error(&s, 0, b);
            println!("{rig}: view 0 -> {b}: mean abs diff {err:.4} over {:.0}% of pixels", 100.0 * seen);
            assert!(seen > 0.3, "{rig}: only {seen} of view 0 is visible in view {b}");
            assert!(err < 0.05, "{rig}: colours disagree ({err})");
        }
    }
    Ok(())
}

/// Half-size of the window the classical plane sweep aggregates its costs over.
const COST_WINDOW: usize = 2;

/// Classical check: per pixel, the plane where the sources' colours vary least (variance
/// averaged over a small window, among the planes where the most sources see the pixel),
/// rendered as their mean there; pixels that fewer than two sources see at every plane
/// take what one source sees at the farthest such plane.
fn plane_sweep_render(target: &Camera, sources: &[Source<'_>], near: f64, far: f64, planes: usize) -> RgbImage {
    let inv = inverse_depths(near, far, planes);
    let region = Region::full(&target.intrinsics);
    let vol = sweep(target, region, sources, &inv);
    let (hw, nv, w, h) = (region.len(), sources.len(), region.width, region.height);
    let mut cost = vec![f32::INFINITY; inv.len() * hw];
    let mut mean = vec![0f32; inv.len() * hw * 3];
    let mut count = vec![0f32; inv.len() * hw];
    for d in 0..inv.len() {
        for p in 0..hw {
            let (mut sum, mut sq, mut n) = ([0f32; 3], [0f32; 3], 0.0f32);
            for k in 0..nv {
                let base = (d * nv + k) * CHANNELS * hw;
                let a = vol[base + 3 * hw + p];
                if a < 0.99 {
                    continue;
                }
                for c in 0..3 {
                    let x = vol[base + c * hw + p] / a;
                    sum[c] += x;
                    sq[c] += x * x;
                }
                n += 1.0;
            }
            count[d * hw + p] = n;
            if n >= 1.0 {
                for c in 0..3 {
                    mean[(d * hw + p) * 3 + c] = sum[c] / n;
                }
            }
            if n >= 2.0 {
                cost[d * hw + p] = (0..3).map(|c| sq[c] / n - (sum[c] / n).powi(2)).sum();
            }
        }
    }
    // A plane where some sources fall outside their images would win just by having
    // fewer colours to disagree: only planes where the most sources see the pixel count.
    for p in 0..hw {
        let most = (0..inv.len()).map(|d| count[d * hw + p]).fold(0.0f32, f32::max);
        for d in 0..inv.len() {
            if count[d * hw + p] < most {
                cost[d * hw + p] = f32::INFINITY;
            }
        }
    }
    let mut out = RgbImage::new(target.intrinsics.width, target.intrinsics.height);
    for p in 0..hw {
        let (x, y) = (p % w, p / w);
        let mut best = (f32::INFINITY, usize::MAX);
        for d in 0..inv.len() {
            if !cost[d * hw + p].is_finite() {
                continue;
            }
            let (mut acc, mut n) = (0.0f32, 0.0f32);
            for yy in y.saturating_sub(COST_WINDOW)..(y + COST_WINDOW + 1).min(h) {
                for xx in x.saturating_sub(COST_WINDOW)..(x + COST_WINDOW + 1).min(w) {
                    let c = cost[d * hw + yy * w + xx];
                    if c.is_finite() {
                        acc += c;
                        n += 1.0;
                    }
                }
            }
            if acc / n < best.0 {
                best = (acc / n, d);
            }
        }
        // Without a plane seen by two sources, the farthest plane any source sees.
        let plane = if best.1 < inv.len() { Some(best.1) } else { (0..inv.len()).rev().find(|&d| count[d * hw + p] > 0.0) };
        let c = match plane {
            Some(d) => {
                let i = (d * hw + p) * 3;
                [mean[i], mean[i + 1], mean[i + 2]]
            }
            None => sources[0].image.pixel(x as u32, y as u32),
        };
        out.data[3 * p..3 * p + 3].copy_from_slice(&c);
    }
    out
}

/// The view whose camera centre is nearest the centroid of all centres.
fn central_view(cams: &[Camera]) -> usize {
    let mean = cams.iter().map(|c| c.pose.centre()).sum::<glam::DVec3>() / cams.len() as f64;
    (0..cams.len())
        .min_by(|&a, &b| cams[a].pose.centre().distance(mean).total_cmp(&cams[b].pose.centre().distance(mean)))
        .unwrap_or(0)
}

fn psnr(a: &RgbImage, b: &RgbImage) -> f64 {
    let mse = a.data.iter().zip(&b.data).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>() / a.data.len() as f64;
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

#[test]
fn synth_plane_sweep_beats_nearest_source() -> TestResult {
    for rig in Rig::CONCRETE {
        let mut gains = Vec::new();
        for seed in [33, 34, 35] {
            let s = generate(seed, &small(rig, 9, 96, 72))?;
            let t = central_view(&s.cameras);
            let src = nearest(&s.cameras, t, 4);
            let sources: Vec<Source<'_>> =
                src.iter().map(|&i| Source { camera: &s.cameras[i], image: &s.images[i] }).collect();
            let swept = plane_sweep_render(&s.cameras[t], &sources, s.near, s.far, 32);
            let (p_sweep, p_copy) = (psnr(&swept, &s.images[t]), psnr(&s.images[src[0]], &s.images[t]));
            println!("{rig} seed {seed} view {t}: plane sweep {p_sweep:.2} dB, nearest source {p_copy:.2} dB");
            gains.push(p_sweep - p_copy);
        }
        let mean = gains.iter().sum::<f64>() / gains.len() as f64;
        let worst = gains.iter().fold(f64::INFINITY, |m, &g| m.min(g));
        assert!(mean > 4.0 && worst > 2.0, "{rig}: plane sweep gains only {gains:?} dB over the nearest source");
    }
    Ok(())
}

/// Fractions of view `t`'s pixels whose surface point falls inside at least one and at
/// least two of its 4 nearest views (occlusion ignored).
fn coverage(s: &SynthScene, t: usize) -> (f64, f64) {
    let cam = &s.cameras[t];
    let w = cam.intrinsics.width as usize;
    let nb = nearest(&s.cameras, t, 4);
    let (mut one, mut two, mut n) = (0usize, 0usize, 0usize);
    for p in (0..s.depths[t].len()).step_by(3) {
        let pt = cam.unproject(centre(p, w), s.depths[t][p] as f64);
        let seen = nb
            .iter()
            .filter(|&&i| {
                let k = &s.cameras[i].intrinsics;
                let (uv, z) = s.cameras[i].project(pt);
                z > 0.0 && uv.x >= 0.0 && uv.y >= 0.0 && uv.x < k.width as f64 && uv.y < k.height as f64
            })
            .count();
        one += usize::from(seen >= 1);
        two += usize::from(seen >= 2);
        n += 1;
    }
    (one as f64 / n as f64, two as f64 / n as f64)
}

#[test]
fn synth_every_rig_has_overlapping_neighbours() -> TestResult {
    let mut worst = Vec::new();
    for rig in Rig::CONCRETE {
        let (mut min1, mut min2) = (1.0f64, 1.0f64);
        for seed in 0..8 {
            let s = generate(scene_seed(99, seed), &SynthOptions { supersample: 1, ..small(rig, 10, 64, 48) })?;
            for t in 0..s.cameras.len() {
                let (one, two) = coverage(&s, t);
                min1 = min1.min(one);
                min2 = min2.min(two);
            }
        }
        println!("{rig}: worst view seen by >=1 neighbour {min1:.3}, by >=2 {min2:.3}");
        worst.push((rig, min1, min2));
    }
    for (rig, min1, min2) in worst {
        assert!(min1 > 0.8 && min2 > 0.6, "{rig}: neighbours overlap too little ({min1}, {min2})");
    }
    Ok(())
}

#[test]
fn synth_options_and_rigs_are_checked() {
    for rig in [Rig::Forward, Rig::Rosette, Rig::Ring, Rig::Handheld, Rig::Mixed] {
        assert_eq!(rig.to_string().parse::<Rig>().ok(), Some(rig));
    }
    assert!("orbit".parse::<Rig>().is_err());
    let base = small(Rig::Forward, 3, 16, 12);
    for bad in [
        SynthOptions { views: 1, ..base.clone() },
        SynthOptions { width: 0, ..base.clone() },
        SynthOptions { height: 0, ..base.clone() },
        SynthOptions { supersample: 0, ..base.clone() },
        SynthOptions { supersample: MAX_SUPERSAMPLE + 1, ..base.clone() },
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
    let e = load_textures(dir.path()).err().map(|e| e.to_string()).unwrap_or_default();
    assert!(e.contains("b.jpg"), "{e}");
    let s = generate(3, &SynthOptions { textures, ..small(Rig::Mixed, 3, 32, 24) })?;
    let (lo, hi) = s.images[0].data.iter().fold((1.0f32, 0.0f32), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(hi - lo > 0.1, "photo-textured view is flat");

    let out = tempfile::tempdir()?;
    let opts = small(Rig::Mixed, 3, 24, 18);
    write_scenes(out.path(), 3, 42, &opts)?;
    for i in 0..3 {
        let loaded = Scene::load(&scene_dir(out.path(), i), &LoadOptions::default())?;
        assert_eq!(loaded.views.len(), 3);
    }
    let scenes: Vec<SynthScene> = (0..2).map(|i| generate(scene_seed(42, i), &opts)).collect::<Result<_>>()?;
    let sheet = contact_sheet(&scenes, 2);
    assert_eq!((sheet.width, sheet.height), (2 + 4 * (24 + 2), 2 + 2 * (18 + 2)));
    Ok(())
}

#[test]
#[ignore]
fn synth_debug_dump() -> TestResult {
    let dir = std::path::PathBuf::from("/tmp/synth_debug");
    std::fs::create_dir_all(&dir)?;
    let mut scenes = Vec::new();
    for rig in Rig::CONCRETE {
        let seed = std::env::var("SYNTH_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(33);
        let s = generate(seed, &small(rig, 9, 96, 72))?;
        let t = central_view(&s.cameras);
        let src = nearest(&s.cameras, t, 4);
        let sources: Vec<Source<'_>> = src.iter().map(|&i| Source { camera: &s.cameras[i], image: &s.images[i] }).collect();
        let swept = plane_sweep_render(&s.cameras[t], &sources, s.near, s.far, 32);
        let mut diff = swept.clone();
        for (d, x) in diff.data.iter_mut().zip(&s.images[t].data) { *d = (*d - x).abs() * 4.0; }
        let parts = [&s.images[t], &swept, &s.images[src[0]], &diff];
        let z = 3usize;
        let mut big = RgbImage::new(96 * 4 * z as u32, 72 * z as u32);
        for (k, im) in parts.iter().enumerate() {
            for y in 0..72 * z { for x in 0..96 * z {
                let c = im.pixel((x / z) as u32, (y / z) as u32);
                let i = (y * 96 * 4 * z + k * 96 * z + x) * 3;
                big.data[i..i + 3].copy_from_slice(&c);
            }}
        }
        big.save_png(&dir.join(format!("{rig}_cmp.png")))?;
        scenes.push(s);
    }
    contact_sheet(&scenes, 4).save_png(&dir.join("sheet.png"))?;
    Ok(())
}

#[test]
#[ignore]
fn synth_debug_rosette() -> TestResult {
    for seed in 0..8 {
        let s = generate(scene_seed(99, seed), &SynthOptions { supersample: 1, ..small(Rig::Rosette, 10, 64, 48) })?;
        for t in 0..s.cameras.len() {
            let (one, two) = coverage(&s, t);
            if one < 0.9 || two < 0.75 {
                let nb = nearest(&s.cameras, t, 4);
                let c = s.cameras[t].pose.centre();
                let d: Vec<String> = nb.iter().map(|&i| format!("{i}:{:.3}", s.cameras[i].pose.centre().distance(c))).collect();
                let yaw = |i: usize| { let z = s.cameras[i].pose.rotation.row(2); z.x.atan2(z.z).to_degrees() };
                let ys: Vec<String> = (0..s.cameras.len()).map(|i| format!("{:.1}", yaw(i))).collect();
                println!("seed {seed} view {t}: {one:.3} {two:.3} nb {d:?} yaws {ys:?} fx {:.1}", s.cameras[t].intrinsics.fx);
            }
        }
    }
    Ok(())
}

#[test]
#[ignore]
fn synth_debug_many() -> TestResult {
    for rig in Rig::CONCRETE {
        let mut mins = Vec::new();
        let mut errs = 0;
        for seed in 0..300 {
            match generate(scene_seed(1234, seed), &SynthOptions { supersample: 1, ..small(rig, 10, 64, 48) }) {
                Ok(s) => {
                    let m = (0..s.cameras.len()).map(|t| coverage(&s, t)).fold((1.0f64, 1.0f64), |a, b| (a.0.min(b.0), a.1.min(b.1)));
                    mins.push(m);
                }
                Err(e) => { errs += 1; println!("{rig} seed {seed}: {e}"); }
            }
        }
        mins.sort_by(|a, b| a.1.total_cmp(&b.1));
        let n = mins.len();
        println!("{rig}: errors {errs}; >=2 coverage worst {:?} p5 {:?} p50 {:?}", mins[0], mins[n / 20], mins[n / 2]);
    }
    Ok(())
}

#[test]
#[ignore]
fn synth_debug_extremes() -> TestResult {
    for rig in Rig::CONCRETE {
        for (v, w, h) in [(2, 1, 1), (2, 17, 300), (40, 32, 24), (3, 300, 17)] {
            for seed in 0..20 {
                let s = generate(seed, &SynthOptions { supersample: 2, ..small(rig, v, w, h) })?;
                assert_eq!(s.cameras.len(), v);
                if v == 40 && seed == 0 {
                    let m = (0..s.cameras.len()).map(|t| coverage(&s, t)).fold((1.0f64, 1.0f64), |a, b| (a.0.min(b.0), a.1.min(b.1)));
                    println!("{rig} 40 views: {m:?} near {} far {}", s.near, s.far);
                }
            }
        }
    }
    Ok(())
}
