//! Scene readers: the real scenes of `../shared/data` (skipped with a message when
//! absent), read through every format they come in, and synthetic round trips of random
//! cameras through every writer and reader.

use deepstereo_core::camera::{Camera, Intrinsics};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::scene::npy::read_npy;
use deepstereo_core::scene::{BoundsSource, LoadOptions, Scene, SceneFormat};
use deepstereo_tests::*;
use glam::DVec3;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::Path;

fn load(dir: &Path, format: Option<SceneFormat>, bounds: Option<(f64, f64)>) -> Scene {
    let opts = LoadOptions {
        format,
        factor: None,
        near: bounds.map(|b| b.0),
        far: bounds.map(|b| b.1),
        downscale: None,
        ignore_rolling_shutter: false,
        allow_outside_paths: false,
        max_side: None,
    };
    Scene::load(dir, &opts).unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
}

fn by_name(scene: &Scene) -> BTreeMap<String, Camera> {
    scene
        .views
        .iter()
        .map(|v| (v.name.clone(), v.camera))
        .collect()
}

#[test]
fn temple_ring_colmap_and_middlebury_agree() {
    let Some(data) = shared_data() else { return };
    let dir = data.join("templeRing");
    let colmap = load(&dir, Some(SceneFormat::Colmap), None);
    let midd = load(&dir, Some(SceneFormat::Middlebury), None);
    assert_eq!(colmap.format, SceneFormat::Colmap);
    assert_eq!(midd.format, SceneFormat::Middlebury);
    assert_eq!(colmap.views.len(), 47);
    assert_eq!(midd.views.len(), 47);
    let (a, b) = (by_name(&colmap), by_name(&midd));
    assert_eq!(
        a.keys().collect::<Vec<_>>(),
        b.keys().collect::<Vec<_>>(),
        "same image names"
    );
    let mut worst = (0.0f64, 0.0f64);
    for (name, ca) in &a {
        let cb = &b[name];
        assert_eq!(ca.intrinsics, cb.intrinsics, "{name}: intrinsics");
        let dr = mat_diff(ca.pose.rotation, cb.pose.rotation);
        let dt = (ca.pose.translation - cb.pose.translation)
            .abs()
            .max_element();
        worst = (worst.0.max(dr), worst.1.max(dt));
        assert!(dr < 1e-6 && dt < 1e-6, "{name}: |dR| {dr:e}, |dt| {dt:e}");
    }
    println!(
        "templeRing COLMAP vs Middlebury: max |dR| {:.2e}, max |dt| {:.2e}",
        worst.0, worst.1
    );
    // Detected as COLMAP (sparse/0 is checked before *_par.txt); both get their bounds
    // from the bounding box in README.txt, the same for both.
    assert_eq!(load(&dir, None, None).format, SceneFormat::Colmap);
    assert!((colmap.near - midd.near).abs() < 1e-9 && (colmap.far - midd.far).abs() < 1e-9);
    assert!(colmap.near > 0.0 && colmap.far > colmap.near && colmap.far.is_finite());
}

#[test]
fn ethiopian_head_llff() {
    let Some(data) = shared_data() else { return };
    let dir = data.join("ethiopianHead");
    let scene = load(&dir, None, None);
    assert_eq!(scene.format, SceneFormat::Llff);
    assert_eq!(scene.views.len(), 66);
    assert_eq!(scene.bounds_source, BoundsSource::File);
    assert!(
        scene.notes.iter().any(|n| n.contains("images_4")),
        "notes say which folder: {:?}",
        scene.notes
    );
    let rows = read_npy(&dir.join("poses_bounds.npy")).expect("npy");
    assert_eq!(rows.shape, vec![66, 17]);
    let first = RgbImage::load(&scene.views[0].image_path).expect("image");
    let (mut near, mut far) = (f64::INFINITY, 0.0f64);
    for (i, v) in scene.views.iter().enumerate() {
        assert_eq!(
            v.image_path.parent().and_then(|p| p.file_name()),
            Some("images_4".as_ref()),
            "{}",
            v.image_path.display()
        );
        let r = rows.row(i).expect("row");
        let (w_full, focal) = (r[9], r[14]);
        assert!(
            w_full == 4000.0 && (focal - 7543.57).abs() < 0.01,
            "{w_full} {focal}"
        );
        let k = &v.camera.intrinsics;
        assert_eq!((k.width, k.height), (first.width, first.height));
        let want_f = focal * first.width as f64 / w_full;
        assert!((k.fx - want_f).abs() < 1e-9 && (k.fy - want_f).abs() < 1e-9);
        assert_eq!(
            (k.cx, k.cy),
            (first.width as f64 / 2.0, first.height as f64 / 2.0)
        );
        // Camera centre and axes: [down, right, backwards] columns.
        let col = |c: usize| DVec3::new(r[c], r[5 + c], r[10 + c]);
        let c2w = v.camera.pose.inverse();
        assert!((c2w.translation - col(3)).length() < 1e-9);
        assert!((c2w.rotation.x_axis - col(1)).length() < 1e-6, "x = right");
        assert!((c2w.rotation.y_axis - col(0)).length() < 1e-6, "y = down");
        assert!(
            (c2w.rotation.z_axis + col(2)).length() < 1e-6,
            "z = -backwards"
        );
        assert_eq!(v.bounds, Some((r[15], r[16])));
        near = near.min(r[15]);
        far = far.max(r[16]);
    }
    assert_eq!((scene.near, scene.far), (near, far));
    assert_eq!(first.width, 1000);
}

#[test]
fn fox_nerf() {
    let Some(data) = shared_data() else { return };
    let dir = data.join("fox");
    let scene = load(&dir, None, Some((0.5, 30.0)));
    assert_eq!(scene.format, SceneFormat::Nerf);
    let json: Value =
        serde_json::from_slice(&std::fs::read(dir.join("transforms.json")).expect("read"))
            .expect("json");
    let frames = json["frames"].as_array().expect("frames");
    assert_eq!(scene.views.len(), frames.len());
    assert_eq!(frames.len(), 67);
    let num = |k: &str| json[k].as_f64().expect(k);
    for (v, f) in scene.views.iter().zip(frames) {
        let k = &v.camera.intrinsics;
        assert_eq!(v.name, f["file_path"].as_str().expect("file_path"));
        assert_eq!(
            (k.fx, k.fy, k.cx, k.cy),
            (num("fl_x"), num("fl_y"), num("cx"), num("cy"))
        );
        assert_eq!((k.width as f64, k.height as f64), (num("w"), num("h")));
        let d = k.distortion.expect("fox has distortion");
        assert_eq!(
            (d.k1, d.k2, d.p1, d.p2),
            (num("k1"), num("k2"), num("p1"), num("p2"))
        );
        let m = &f["transform_matrix"];
        let gl = |r: usize, c: usize| m[r][c].as_f64().expect("number");
        let gl_col = |c: usize| DVec3::new(gl(0, c), gl(1, c), gl(2, c));
        let c2w = v.camera.pose.inverse();
        assert!(
            (c2w.translation - gl_col(3)).length() < 1e-9,
            "{}: camera centre is the translation column",
            v.name
        );
        // OpenCV z (forward) is minus the GL z column, y (down) minus GL y, x the same;
        // the reader re-orthonormalizes, so compare to the normalized columns.
        assert!((c2w.rotation.z_axis + gl_col(2).normalize()).length() < 1e-4);
        assert!((c2w.rotation.y_axis + gl_col(1).normalize()).length() < 1e-4);
        assert!((c2w.rotation.x_axis - gl_col(0).normalize()).length() < 1e-4);
    }
}

#[test]
fn inspect_json_on_shared_scenes() {
    let Some(data) = shared_data() else { return };
    for (scene, format, extra) in [
        ("fox", "nerf", vec!["--near", "0.5", "--far", "30"]),
        ("templeRing", "colmap", vec![]),
        ("ethiopianHead", "llff", vec![]),
    ] {
        let dir = data.join(scene);
        let mut args = vec!["inspect".to_string(), "--json".into(), "--scene".into()];
        args.push(dir.to_string_lossy().into_owned());
        args.extend(extra.iter().map(|s| s.to_string()));
        let out = run_deepstereo(&args);
        assert_eq!(out.code, Some(0), "{scene}: {}", out.stderr);
        let json: Value = serde_json::from_str(&out.stdout).expect("inspect --json prints JSON");
        let user_bounds = (!extra.is_empty()).then_some((0.5, 30.0));
        check_inspect_json(&json, &load(&dir, None, user_bounds), format);
    }
}

/// Random cameras for every format, within LLFF's restrictions: one image size,
/// fx == fy, a centred principal point; focal lengths vary per view.
fn common_cameras(seed: u64, n: usize) -> Vec<NamedCamera> {
    let mut rng = Rng(seed);
    let intr: Vec<Intrinsics> = (0..n)
        .map(|_| {
            let f = rng.range(5.0, 40.0);
            Intrinsics::pinhole(f, f, 8.0, 6.0, 16, 12)
        })
        .collect();
    random_cameras(&mut rng, n, &intr)
}

fn assert_scene_has(scene: &Scene, cams: &[NamedCamera], name: impl Fn(&str) -> String, tol: f64) {
    assert_eq!(scene.views.len(), cams.len());
    let got = by_name(scene);
    for c in cams {
        let v = got
            .get(&name(&c.name))
            .unwrap_or_else(|| panic!("view {} missing; have {:?}", c.name, got.keys()));
        assert_same_camera(&c.name, v, &c.camera, tol);
    }
}

#[test]
fn same_cameras_through_every_format() {
    let cams = common_cameras(11, 7);
    let tmp = tempfile::tempdir().expect("tempdir");
    let root = tmp.path();
    let bounds = Some((0.25, 50.0));
    write_llff(&root.join("llff64"), &cams, (0.25, 50.0), false);
    write_colmap_text(&root.join("colmap_txt"), &cams, &["PINHOLE"], &[]);
    write_colmap_bin(&root.join("colmap_bin"), &cams, &["SIMPLE_PINHOLE"], &[]);
    write_nerf(&root.join("nerf"), &cams, false, bounds);
    write_middlebury(&root.join("middlebury"), &cams);
    let same = |s: &str| s.to_string();
    type ViewName<'a> = &'a dyn Fn(&str) -> String;
    let cases: [(&str, SceneFormat, ViewName); 5] = [
        ("llff64", SceneFormat::Llff, &same),
        ("colmap_txt", SceneFormat::Colmap, &same),
        ("colmap_bin", SceneFormat::Colmap, &same),
        ("nerf", SceneFormat::Nerf, &|s| format!("images/{s}")),
        ("middlebury", SceneFormat::Middlebury, &same),
    ];
    for (dir, format, name) in cases {
        let scene = load(&root.join(dir), None, bounds);
        assert_eq!(scene.format, format, "{dir} detected");
        assert_scene_has(&scene, &cams, name, 1e-9);
    }
}

#[test]
fn llff_round_trip_f32_and_images_folder_choice() {
    let cams = common_cameras(5, 4);
    let cams: Vec<NamedCamera> = cams
        .into_iter()
        .map(|mut c| {
            // One size for all: LLFF reads the size from the first image.
            c.camera.intrinsics = Intrinsics::pinhole(12.5, 12.5, 8.0, 6.0, 16, 12);
            c
        })
        .collect();
    let tmp = tempfile::tempdir().expect("tempdir");
    write_llff(tmp.path(), &cams, (0.5, 20.0), true);
    let scene = load(tmp.path(), None, None);
    assert_eq!((scene.near, scene.far), (0.5, 20.0));
    // f32 storage: values are exact to about 1e-7 relative; the reader re-orthonormalizes.
    assert_scene_has(&scene, &cams, |s| s.to_string(), 1e-5);

    // images_4/ holds 4x smaller images: intrinsics scale with the folder's image size.
    let images = tmp.path().join("images");
    let small = tmp.path().join("images_4");
    std::fs::create_dir_all(&small).expect("mkdir");
    for c in &cams {
        write_png(&small.join(&c.name), 4, 3, 1);
    }
    std::fs::rename(&images, tmp.path().join("moved")).expect("rename");
    let scene = load(tmp.path(), None, None);
    assert!(
        scene.notes.iter().any(|n| n.contains("images_4")),
        "{:?}",
        scene.notes
    );
    for v in &scene.views {
        let k = &v.camera.intrinsics;
        assert_eq!((k.width, k.height), (4, 3));
        assert!((k.fx - 12.5 / 4.0).abs() < 1e-6 && (k.cx - 2.0).abs() < 1e-12);
    }
    // Both folders: images/ wins unless --factor asks otherwise.
    std::fs::rename(tmp.path().join("moved"), &images).expect("rename");
    assert_eq!(
        load(tmp.path(), None, None).views[0]
            .camera
            .intrinsics
            .width,
        16
    );
    let opts = LoadOptions {
        factor: Some(4),
        ..Default::default()
    };
    let scene = Scene::load(tmp.path(), &opts).expect("factor 4");
    assert_eq!(scene.views[0].camera.intrinsics.width, 4);
}

/// Cameras whose intrinsics each COLMAP model can represent, cycling through the models.
fn colmap_cameras(seed: u64) -> (Vec<NamedCamera>, Vec<&'static str>) {
    let mut rng = Rng(seed);
    let models: Vec<&str> = COLMAP_MODELS.iter().map(|(m, _)| *m).collect();
    let n = 2 * models.len();
    let intr: Vec<Intrinsics> = (0..n)
        .map(|i| intrinsics_for_model(&mut rng, models[i % models.len()], 10 + i as u32, 8))
        .collect();
    (random_cameras(&mut rng, n, &intr), models)
}

#[test]
fn colmap_text_and_binary_round_trip_every_model() {
    let (cams, models) = colmap_cameras(21);
    let points = vec![
        DVec3::new(0.1, 0.2, 0.3),
        DVec3::new(-1.0, 2.0, 0.5),
        DVec3::new(1e-3, -2.5, 1.25),
    ];
    for binary in [false, true] {
        let tmp = tempfile::tempdir().expect("tempdir");
        if binary {
            write_colmap_bin(tmp.path(), &cams, &models, &points);
        } else {
            write_colmap_text(tmp.path(), &cams, &models, &points);
        }
        let scene = Scene::load(tmp.path(), &LoadOptions::default())
            .unwrap_or_else(|e| panic!("binary {binary}: {e}"));
        assert_scene_has(&scene, &cams, |s| s.to_string(), 1e-9);
        assert_eq!(scene.points, points, "points3D (binary {binary})");
        assert_eq!(scene.bounds_source, BoundsSource::Points);
        // Views come back sorted by name whatever the file order.
        let names: Vec<&str> = scene.views.iter().map(|v| v.name.as_str()).collect();
        assert!(names.windows(2).all(|w| w[0] < w[1]));
    }
}

#[test]
fn nerf_round_trip_shared_and_per_frame_intrinsics() {
    let mut rng = Rng(8);
    let k = intrinsics_for_model(&mut rng, "OPENCV", 18, 10);
    let shared = random_cameras(&mut rng, 5, &[k]);
    let per: Vec<Intrinsics> = (0..3)
        .map(|i| intrinsics_for_model(&mut rng, "OPENCV", 12 + i, 9))
        .collect();
    let per_frame = random_cameras(&mut rng, 6, &per);
    for (cams, is_shared) in [(shared, true), (per_frame, false)] {
        let tmp = tempfile::tempdir().expect("tempdir");
        write_nerf(tmp.path(), &cams, is_shared, Some((0.1, 9.0)));
        let scene = load(tmp.path(), None, None);
        assert_eq!((scene.near, scene.far), (0.1, 9.0));
        assert_scene_has(&scene, &cams, |s| format!("images/{s}"), 1e-9);
        // Frames keep the file's order.
        for (v, c) in scene.views.iter().zip(&cams) {
            assert_eq!(v.name, format!("images/{}", c.name));
        }
    }
}

#[test]
fn middlebury_round_trip_keeps_file_order() {
    let mut cams = common_cameras(31, 6);
    cams.reverse();
    let tmp = tempfile::tempdir().expect("tempdir");
    write_middlebury(tmp.path(), &cams);
    let scene = load(tmp.path(), None, Some((0.5, 5.0)));
    assert_eq!(scene.format, SceneFormat::Middlebury);
    for (v, c) in scene.views.iter().zip(&cams) {
        assert_eq!(v.name, c.name);
        assert_same_camera(&c.name, &v.camera, &c.camera, 1e-9);
    }
}

/// A scene read at 1/2 takes `images_2/NAME` beside `images/NAME` when it has the size
/// the downscaled camera expects (as LLFF's and nerfstudio's tools write them), and
/// box-filters the full image otherwise, or when the folder leads outside the scene.
#[test]
fn prescaled_folders_serve_a_downscaled_read() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = synth_scene(tmp.path(), (32, 24), 4, 2, &[]);
    let opts = LoadOptions {
        downscale: Some(2),
        ..Default::default()
    };
    let boxed = Scene::load(&scene, &opts)
        .expect("scene")
        .load_image(1)
        .expect("image");
    let small = scene.join("images_2");
    std::fs::create_dir(&small).expect("mkdir");
    // A prescaled view 1 of the right size (16x12): a different picture, so it shows.
    write_png(&small.join("view_001.png"), 16, 12, 77);
    // View 2's has the wrong size: the full image is filtered instead.
    write_png(&small.join("view_002.png"), 15, 12, 78);
    let s = Scene::load(&scene, &opts).expect("scene");
    let got = s.load_image(1).expect("image");
    let want = deepstereo_core::imageio::RgbImage::load(&small.join("view_001.png")).expect("png");
    assert_eq!(got, want, "the prescaled image");
    assert_ne!(got, boxed);
    let full = Scene::load(&scene, &LoadOptions::default()).expect("scene");
    assert_eq!(
        s.load_image(2).expect("image"),
        full.load_image(2).expect("image").downsample2()
    );
    // A prescaled folder that is a link outside the scene is not read.
    std::fs::remove_dir_all(&small).expect("rm");
    let outside = tmp.path().join("elsewhere");
    std::fs::create_dir(&outside).expect("mkdir");
    write_png(&outside.join("view_001.png"), 16, 12, 77);
    std::os::unix::fs::symlink(&outside, &small).expect("symlink");
    let s = Scene::load(&scene, &opts).expect("scene");
    assert_eq!(
        s.load_image(1).expect("image"),
        boxed,
        "read through a link outside"
    );
}
