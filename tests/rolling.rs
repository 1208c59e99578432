//! Rolling-shutter cameras through the command line: `synth --rolling-shutter` writes
//! instant-ngp's keys, the reader gives back the generated cameras, `inspect --json`
//! prints the shutter and `render --pose` renders each row at its own pose.

use deepstereo_core::scene::{LoadOptions, Scene};
use deepstereo_core::synth::{generate, scene_seed, Rig, SynthOptions};
use deepstereo_tests::*;
use std::path::Path;

const W: u32 = 48;
const H: u32 = 36;

fn synth(out: &Path, share: &str) -> CmdOutput {
    run_deepstereo([
        "synth",
        "--out",
        &out.to_string_lossy(),
        "--scenes",
        "1",
        "--views",
        "5",
        "--seed",
        "3",
        "--rig",
        "handheld",
        "--size",
        &format!("{W}x{H}"),
        "--supersample",
        "1",
        "--rolling-shutter",
        share,
    ])
}

#[test]
fn synth_inspect_and_render_carry_the_rolling_shutter() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("scenes");
    let r = synth(&out, "0.8");
    assert_eq!(r.code, Some(0), "{}", r.stderr);
    let dir = out.join("scene_0000");
    let doc: serde_json::Value = serde_json::from_slice(
        &std::fs::read(dir.join("transforms.json")).expect("transforms.json"),
    )
    .expect("JSON");
    let f = &doc["frames"][0];
    for key in [
        "transform_matrix",
        "transform_matrix_start",
        "transform_matrix_end",
    ] {
        assert!(f[key].is_array(), "frame 0 lacks {key}");
    }
    let rs = f["rolling_shutter"].as_array().expect("rolling_shutter");
    assert_eq!(rs.len(), 4);
    assert!((rs[2].as_f64().expect("C") - 1.0).abs() < 1e-12, "{rs:?}");

    // The reader gives back the generated cameras, shutters included.
    let opts = SynthOptions {
        views: 5,
        width: W,
        height: H,
        rig: Rig::Handheld,
        supersample: 1,
        textures: Vec::new(),
        rolling_shutter: 0.8,
    };
    let want = generate(scene_seed(3, 0), &opts).expect("generate");
    let scene = Scene::load(&dir, &LoadOptions::default()).expect("load");
    for (v, c) in scene.views.iter().zip(&want.cameras) {
        let (got, exp) = (
            v.camera.moving_shutter().expect("a moving shutter"),
            c.rolling_shutter.expect("generated shutter"),
        );
        assert!(mat_diff(got.start.rotation, exp.start.rotation) < 1e-9);
        assert!(mat_diff(got.end.rotation, exp.end.rotation) < 1e-9);
        assert!((got.end.centre() - exp.end.centre()).length() < 1e-9);
        assert!((got.time_per_pixel - exp.time_per_pixel).length() < 1e-12);
        assert!(got.time_origin.abs() < 1e-12);
        assert_same_camera(&v.name, &v.camera, c, 1e-9);
    }
    let ignored = Scene::load(
        &dir,
        &LoadOptions {
            ignore_rolling_shutter: true,
            ..Default::default()
        },
    )
    .expect("load");
    assert!(ignored
        .views
        .iter()
        .all(|v| v.camera.rolling_shutter.is_none()));
    // At half resolution every point keeps its time.
    let half = Scene::load(
        &dir,
        &LoadOptions {
            downscale: Some(2),
            ..Default::default()
        },
    )
    .expect("load");
    let (full, small) = (
        scene.views[1].camera.rolling_shutter.expect("rs"),
        half.views[1].camera.rolling_shutter.expect("rs"),
    );
    let uv = glam::DVec2::new(30.0, 20.0);
    assert!((full.time_at(uv) - small.time_at(uv / 2.0)).abs() < 1e-12);

    // inspect prints it; render --pose reads it back, and it changes the rendering.
    let s = dir.to_string_lossy().into_owned();
    let text = ok(&["inspect", "--scene", &s]).stdout;
    assert!(text.contains("rolling shutter"), "{text}");
    let json = ok(&["inspect", "--json", "--scene", &s]).stdout;
    let v: serde_json::Value = serde_json::from_str(&json).expect("JSON");
    let view = &v["views"][2];
    for key in [
        "R_start",
        "t_start",
        "R_end",
        "t_end",
        "time_origin",
        "time_per_pixel",
    ] {
        assert!(
            !view["rolling_shutter"][key].is_null(),
            "inspect lacks {key}"
        );
    }
    let render = |name: &str, cam: &serde_json::Value| {
        let pose = tmp.path().join(format!("{name}.json"));
        std::fs::write(&pose, cam.to_string()).expect("write");
        let o = tmp.path().join(name);
        ok(&[
            "render",
            "--scene",
            &s,
            "--pose",
            &pose.to_string_lossy(),
            "--planes",
            "8",
            "--out",
            &o.to_string_lossy(),
        ]);
        image::open(o.join("image.png")).expect("image").to_rgb8()
    };
    let with = render("with", view);
    let mut plain = view.clone();
    plain.as_object_mut().map(|o| o.remove("rolling_shutter"));
    let without = render("without", &plain);
    assert_eq!((with.width(), with.height()), (W, H));
    let differ = with
        .pixels()
        .zip(without.pixels())
        .filter(|(a, b)| a != b)
        .count();
    assert!(
        differ > (W * H / 10) as usize,
        "only {differ} pixels differ"
    );

    // A malformed shutter in --pose is an error naming the file and the key.
    let mut bad = view.clone();
    bad["rolling_shutter"]["t_end"] = serde_json::json!([0.0, "x", 1.0]);
    let pose = tmp.path().join("bad.json");
    std::fs::write(&pose, bad.to_string()).expect("write");
    let e = run_deepstereo([
        "render",
        "--scene",
        &s,
        "--pose",
        &pose.to_string_lossy(),
        "--out",
        &tmp.path().join("bad").to_string_lossy(),
    ]);
    assert_ne!(e.code, Some(0));
    assert!(
        e.stderr.contains("bad.json") && e.stderr.contains("rolling_shutter.t_end"),
        "{}",
        e.stderr
    );
}

#[test]
fn synth_rejects_a_share_out_of_range() {
    let tmp = tempfile::tempdir().expect("tempdir");
    for share in ["1.5", "-0.1", "nan"] {
        let r = synth(&tmp.path().join("x"), share);
        assert_ne!(r.code, Some(0), "--rolling-shutter {share} accepted");
        assert!(
            r.stderr.contains("rolling-shutter"),
            "{share}: {}",
            r.stderr
        );
    }
}
