//! Automatic bounds on procedural scenes with exact depth.

use super::*;
use crate::scene::{nerf, BoundsSource, LoadOptions, RawScene, Scene, SceneFormat};
use crate::synth::{generate, write_scene, Rig, SynthOptions, SynthScene};

type TestResult = std::result::Result<(), Box<dyn std::error::Error>>;

/// Percentiles of the true depths taken as a scene's true range (a few pixels of a scene
/// are seen by one view only, or at grazing angles, and no matcher finds them).
const TRUE_PERCENTILES: (f64, f64) = (0.01, 0.99);
/// The automatic bounds may be at most this many times wider than the true range, in
/// inverse depth.
const MAX_WIDENING: f64 = 4.0;

fn opts(rig: Rig) -> SynthOptions {
    SynthOptions {
        views: 10,
        width: 160,
        height: 120,
        rig,
        supersample: 2,
        textures: Vec::new(),
        rolling_shutter: 0.0,
    }
}

/// The scene written to `dir` and read back without its `near`/`far`.
fn load_without_bounds(dir: &Path, scene: &SynthScene) -> Result<Scene> {
    write_scene(dir, scene)?;
    let mut raw = nerf::read(dir, &crate::scene::Within::anywhere())?;
    raw.bounds = None;
    Scene::from_raw(dir, SceneFormat::Nerf, raw, &LoadOptions::default())
}

/// The true depth range of the pixels an image matcher can see: the [`TRUE_PERCENTILES`]
/// of the true depths of textured pixels (grey standard deviation at least
/// [`MIN_TEXTURE_STD`] over the matching window). Untextured surfaces (the procedural
/// backdrop is smooth noise, flat patches) give no depth to any matcher.
fn true_range(scene: &SynthScene) -> (f64, f64) {
    let r = WINDOW_RADIUS;
    let nwin = ((2 * r + 1) * (2 * r + 1)) as f64;
    let mut z: Vec<f64> = Vec::new();
    for (img, depth) in scene.images.iter().zip(&scene.depths) {
        let (w, h) = (img.width as usize, img.height as usize);
        let g = grey(img);
        let s = box_sums(&g, w, h, r);
        let gg: Vec<f64> = g.iter().map(|v| v * v).collect();
        let ss = box_sums(&gg, w, h, r);
        for p in 0..w * h {
            if ss[p] - s[p] * s[p] / nwin >= nwin * MIN_TEXTURE_STD * MIN_TEXTURE_STD {
                z.push(depth[p] as f64);
            }
        }
    }
    z.sort_by(f64::total_cmp);
    let q = |f: f64| z[((z.len() - 1) as f64 * f).round() as usize];
    (q(TRUE_PERCENTILES.0), q(TRUE_PERCENTILES.1))
}

#[test]
fn automatic_bounds_contain_the_true_depths() -> TestResult {
    for (seed, rig) in [
        (1u64, Rig::Forward),
        (2, Rig::Rosette),
        (3, Rig::Ring),
        (4, Rig::Handheld),
        (5, Rig::Forward),
        (6, Rig::Ring),
        (11, Rig::Rosette),
    ] {
        let synth = generate(seed, &opts(rig))?;
        let dir = tempfile::tempdir()?;
        let t0 = std::time::Instant::now();
        let s = load_without_bounds(dir.path(), &synth)?;
        let secs = t0.elapsed().as_secs_f64();
        let (lo, hi) = true_range(&synth);
        let (rho_n, rho_f) = (
            1.0 / s.near,
            if s.far.is_finite() { 1.0 / s.far } else { 0.0 },
        );
        let widening = (rho_n - rho_f) / (1.0 / lo - 1.0 / hi);
        eprintln!(
            "seed {seed} {rig}: true {lo:.3}..{hi:.3} (file {:.3}..{:.3}), auto {:.3}..{:.3}, \
             {} points, {widening:.2}x in inverse depth, {secs:.2} s",
            synth.near,
            synth.far,
            s.near,
            s.far,
            s.points.len()
        );
        assert_eq!(s.bounds_source, BoundsSource::Auto);
        assert!(
            s.near <= lo && s.far >= hi,
            "seed {seed} {rig}: true range not inside"
        );
        assert!(
            widening <= MAX_WIDENING,
            "seed {seed} {rig}: {widening}x too wide"
        );
        assert!(!s.points.is_empty() && s.points.len() <= MAX_POINTS);
    }
    Ok(())
}

#[test]
fn automatic_bounds_are_deterministic_and_write_nothing() -> TestResult {
    let synth = generate(7, &opts(Rig::Handheld))?;
    let dir = tempfile::tempdir()?;
    let a = load_without_bounds(dir.path(), &synth)?;
    let before: Vec<_> = std::fs::read_dir(dir.path())?
        .flatten()
        .map(|e| e.path())
        .collect();
    let mut raw = nerf::read(dir.path(), &crate::scene::Within::anywhere())?;
    raw.bounds = None;
    let b = Scene::from_raw(dir.path(), SceneFormat::Nerf, raw, &LoadOptions::default())?;
    let after: Vec<_> = std::fs::read_dir(dir.path())?
        .flatten()
        .map(|e| e.path())
        .collect();
    assert_eq!(before, after);
    assert_eq!((a.near, a.far), (b.near, b.far));
    assert_eq!(a.points, b.points);
    Ok(())
}

#[test]
fn user_bounds_override_and_one_given_bound_is_kept() -> TestResult {
    let synth = generate(8, &opts(Rig::Forward))?;
    let dir = tempfile::tempdir()?;
    write_scene(dir.path(), &synth)?;
    let raw = || -> Result<RawScene> {
        let mut r = nerf::read(dir.path(), &crate::scene::Within::anywhere())?;
        r.bounds = None;
        Ok(r)
    };
    let both = LoadOptions {
        near: Some(0.5),
        far: Some(50.0),
        ..Default::default()
    };
    let s = Scene::from_raw(dir.path(), SceneFormat::Nerf, raw()?, &both)?;
    assert_eq!(
        (s.near, s.far, s.bounds_source),
        (0.5, 50.0, BoundsSource::User)
    );
    assert!(s.points.is_empty());
    let near_only = LoadOptions {
        near: Some(0.25),
        ..Default::default()
    };
    let s = Scene::from_raw(dir.path(), SceneFormat::Nerf, raw()?, &near_only)?;
    assert_eq!((s.near, s.bounds_source), (0.25, BoundsSource::Auto));
    Ok(())
}

#[test]
fn a_textureless_scene_is_refused_by_name() -> TestResult {
    let mut synth = generate(9, &opts(Rig::Forward))?;
    for img in &mut synth.images {
        img.data.iter_mut().for_each(|v| *v = 0.5);
    }
    let dir = tempfile::tempdir()?;
    let err = match load_without_bounds(dir.path(), &synth) {
        Ok(s) => return Err(format!("accepted with bounds {}..{}", s.near, s.far).into()),
        Err(e) => e.to_string(),
    };
    eprintln!("{err}");
    assert!(err.contains(&dir.path().display().to_string()), "{err}");
    assert!(err.contains("cannot find depth bounds"), "{err}");
    assert!(err.contains("pass --near and --far"), "{err}");
    Ok(())
}

#[test]
fn a_single_view_is_refused() -> TestResult {
    let synth = generate(10, &opts(Rig::Forward))?;
    let dir = tempfile::tempdir()?;
    write_scene(dir.path(), &synth)?;
    let mut raw = nerf::read(dir.path(), &crate::scene::Within::anywhere())?;
    raw.views.truncate(1);
    let err = estimate(dir.path(), &raw.views)
        .err()
        .map(|e| e.to_string());
    assert!(err.is_some_and(|e| e.contains("single view")));
    Ok(())
}
