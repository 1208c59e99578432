//! The `deepstereo` command line on generated scenes: `sweep` writes the documented
//! tensors (and one PNG per plane), `inspect --json` prints the documented keys.

use deepstereo_core::camera::{Intrinsics, WorldToCamera};
use deepstereo_core::geometry::{depths_of, inverse_depths};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::scene::{LoadOptions, Scene};
use deepstereo_core::sweep::{sweep, Region, Source};
use deepstereo_tests::*;
use glam::{DMat3, DVec3};
use std::path::Path;

/// A forward-facing rig of `n` cameras 0.25 apart along x, slightly rotated.
fn rig(n: usize, w: u32, h: u32) -> Vec<NamedCamera> {
    let k = Intrinsics::pinhole(
        0.9 * w as f64,
        0.9 * w as f64,
        w as f64 / 2.0,
        h as f64 / 2.0,
        w,
        h,
    );
    (0..n)
        .map(|i| {
            let r = DMat3::from_rotation_y(0.02 * i as f64 - 0.03);
            let c = DVec3::new(0.25 * i as f64, 0.05 * (i % 2) as f64, 0.0);
            NamedCamera {
                name: format!("img_{i:03}.png"),
                camera: deepstereo_core::camera::Camera {
                    intrinsics: k,
                    pose: WorldToCamera::new_checked(r, -(r * c)).expect("rotation"),
                    rolling_shutter: None,
                },
            }
        })
        .collect()
}

fn sweep_args(scene: &Path, out: &Path, extra: &[&str]) -> Vec<String> {
    let mut a: Vec<String> = vec!["sweep".into(), "--scene".into()];
    a.push(scene.to_string_lossy().into_owned());
    a.push("--out".into());
    a.push(out.to_string_lossy().into_owned());
    a.extend(extra.iter().map(|s| s.to_string()));
    a
}

#[test]
fn sweep_writes_the_documented_tensors_and_pngs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene_dir = tmp.path().join("scene");
    let cams = rig(6, 24, 16);
    write_llff(&scene_dir, &cams, (1.5, 40.0), false);
    let out = tmp.path().join("psv.safetensors");
    let pngs = tmp.path().join("planes");
    let (target, views, planes) = (2usize, 3usize, 5usize);
    let res = run_deepstereo(sweep_args(
        &scene_dir,
        &out,
        &[
            "--target",
            &target.to_string(),
            "--views",
            &views.to_string(),
            "--planes",
            &planes.to_string(),
            "--png",
            &pngs.to_string_lossy(),
        ],
    ));
    assert_eq!(res.code, Some(0), "stderr: {}", res.stderr);
    let t = read_safetensors(&out);
    assert_eq!(
        t.keys().map(String::as_str).collect::<Vec<_>>(),
        ["depths", "psv", "sources", "target"]
    );
    let (h, w) = (16usize, 24usize);
    assert_eq!(t["psv"].dtype, "F32");
    assert_eq!(t["psv"].shape, vec![planes, views, 4, h, w]);
    assert_eq!(t["depths"].shape, vec![planes]);
    assert_eq!(t["target"].shape, vec![3, h, w]);
    assert_eq!(
        (t["sources"].dtype.as_str(), t["sources"].shape.clone()),
        ("I64", vec![views])
    );

    // Sources: the nearest camera centres, excluding the target, nearest first.
    let centre = |i: usize| cams[i].camera.pose.centre();
    let mut order: Vec<usize> = (0..cams.len()).filter(|&i| i != target).collect();
    order.sort_by(|&a, &b| {
        centre(a)
            .distance(centre(target))
            .total_cmp(&centre(b).distance(centre(target)))
    });
    let sources: Vec<i64> = order[..views].iter().map(|&i| i as i64).collect();
    assert_eq!(t["sources"].i64s(), sources);

    // Depths: uniform in inverse depth between the file's near and far.
    let want: Vec<f32> = depths_of(&inverse_depths(1.5, 40.0, planes))
        .iter()
        .map(|&d| d as f32)
        .collect();
    assert_eq!(t["depths"].f32s(), want);

    // Target: the real target image, planar, colours in [0, 1].
    let img = RgbImage::load(&scene_dir.join("images").join(&cams[target].name)).expect("image");
    let tgt = t["target"].f32s();
    for p in 0..h * w {
        for c in 0..3 {
            assert_eq!(tgt[c * h * w + p], img.data[p * 3 + c]);
        }
    }

    // The volume: finite, in [0, 1], partly opaque, and what the library computes.
    let psv = t["psv"].f32s();
    assert!(psv
        .iter()
        .all(|v| v.is_finite() && (0.0..=1.0 + 1e-6).contains(v)));
    let scene = Scene::load(&scene_dir, &LoadOptions::default()).expect("scene");
    let images: Vec<RgbImage> = sources
        .iter()
        .map(|&i| scene.load_image(i as usize).expect("image"))
        .collect();
    let srcs: Vec<Source> = sources
        .iter()
        .zip(&images)
        .map(|(&i, image)| Source {
            camera: &scene.views[i as usize].camera,
            image,
        })
        .collect();
    let cam = &scene.views[target].camera;
    let lib = sweep(
        cam,
        Region::full(&cam.intrinsics),
        &srcs,
        &inverse_depths(1.5, 40.0, planes),
    );
    assert_eq!(psv, lib, "the CLI's volume is the library's");
    let hw = h * w;
    let opaque = (0..planes * views)
        .map(|s| {
            psv[(s * 4 + 3) * hw..(s * 4 + 4) * hw]
                .iter()
                .filter(|&&a| a > 0.999)
                .count()
        })
        .sum::<usize>();
    assert!(opaque > planes * views * hw / 4, "mostly covered: {opaque}");

    // One PNG per plane, of the target's size.
    let mut files: Vec<_> = std::fs::read_dir(&pngs)
        .expect("png dir")
        .map(|e| e.expect("entry").path())
        .collect();
    files.sort();
    assert_eq!(files.len(), planes, "{files:?}");
    for f in &files {
        assert_eq!(f.extension().and_then(|e| e.to_str()), Some("png"));
        let img = RgbImage::load(f).expect("plane PNG");
        assert_eq!((img.width, img.height), (w as u32, h as u32));
    }
}

#[test]
fn sweep_with_far_at_infinity() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene_dir = tmp.path().join("scene");
    write_nerf(&scene_dir, &rig(3, 16, 12), true, None);
    let out = tmp.path().join("psv.safetensors");
    let res = run_deepstereo(sweep_args(
        &scene_dir,
        &out,
        &[
            "--target", "0", "--views", "2", "--planes", "4", "--near", "1", "--far", "inf",
        ],
    ));
    assert_eq!(res.code, Some(0), "stderr: {}", res.stderr);
    let t = read_safetensors(&out);
    let depths = t["depths"].f32s();
    assert_eq!(depths[0], 1.0);
    assert_eq!(depths[3], f32::INFINITY);
    assert!(t["psv"].f32s().iter().all(|v| v.is_finite()));
}

#[test]
fn inspect_json_on_generated_scenes() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let cams = rig(4, 16, 12);
    let mut rng = Rng(4);
    let k = intrinsics_for_model(&mut rng, "OPENCV", 16, 12);
    let distorted = random_cameras(&mut rng, 3, &[k]);
    let points = [DVec3::new(0.0, 0.0, 4.0), DVec3::new(0.5, 0.2, 6.0)];
    write_llff(&tmp.path().join("llff"), &cams, (1.0, 9.0), false);
    write_colmap_bin(&tmp.path().join("colmap"), &distorted, &["OPENCV"], &points);
    write_nerf(&tmp.path().join("nerf"), &cams, false, Some((0.5, 5.0)));
    write_middlebury(&tmp.path().join("middlebury"), &cams);
    for (dir, format, user) in [
        ("llff", "llff", false),
        ("colmap", "colmap", true),
        ("nerf", "nerf", false),
        ("middlebury", "middlebury", true),
    ] {
        let scene_dir = tmp.path().join(dir);
        let mut args = vec!["inspect".to_string(), "--json".into(), "--scene".into()];
        args.push(scene_dir.to_string_lossy().into_owned());
        if user {
            args.extend(["--near", "0.25", "--far", "12"].map(String::from));
        }
        let res = run_deepstereo(&args);
        assert_eq!(res.code, Some(0), "{dir}: {}", res.stderr);
        let json: serde_json::Value = serde_json::from_str(&res.stdout).expect("JSON on stdout");
        let opts = LoadOptions {
            near: user.then_some(0.25),
            far: user.then_some(12.0),
            ..Default::default()
        };
        check_inspect_json(
            &json,
            &Scene::load(&scene_dir, &opts).expect("scene"),
            format,
        );
    }
    // Text mode names the format and every view.
    let res = run_deepstereo([
        "inspect",
        "--scene",
        &tmp.path().join("llff").to_string_lossy(),
    ]);
    assert_eq!(res.code, Some(0));
    assert!(res.stdout.contains("llff"));
    assert!(cams.iter().all(|c| res.stdout.contains(&c.name)));
}

#[test]
fn help_documents_every_option() {
    for (cmd, opts) in [
        (
            "inspect",
            &[
                "--scene", "--format", "--factor", "--near", "--far", "--json",
            ][..],
        ),
        (
            "sweep",
            &[
                "--scene", "--format", "--factor", "--near", "--far", "--target", "--views",
                "--planes", "--out", "--png",
            ][..],
        ),
    ] {
        let res = run_deepstereo([cmd, "--help"]);
        assert_eq!(res.code, Some(0));
        for o in opts {
            assert!(res.stdout.contains(o), "{cmd} --help lacks {o}");
        }
    }
}
