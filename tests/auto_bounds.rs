//! Scenes without depth bounds: `inspect` on a NeRF-format procedural scene whose
//! `transforms.json` has no `near`/`far` finds them from the images and says so.

use deepstereo_tests::run_deepstereo;
use std::path::Path;

/// Writes one procedural scene with the binary and strips its `near`/`far`.
fn scene_without_bounds(out: &Path) -> std::path::PathBuf {
    let res = run_deepstereo([
        "synth",
        "--out",
        &out.to_string_lossy(),
        "--scenes",
        "1",
        "--seed",
        "3",
        "--size",
        "160x120",
    ]);
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    let dir = std::fs::read_dir(out)
        .expect("synth output")
        .flatten()
        .map(|e| e.path())
        .find(|p| p.join("transforms.json").is_file())
        .expect("a scene directory");
    let file = dir.join("transforms.json");
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&file).expect("read")).expect("JSON");
    let top = json.as_object_mut().expect("object");
    assert!(top.remove("near").is_some() && top.remove("far").is_some());
    std::fs::write(&file, serde_json::to_string_pretty(&json).expect("JSON")).expect("write");
    dir
}

#[test]
fn inspect_finds_bounds_of_a_nerf_scene_without_them() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = scene_without_bounds(tmp.path());
    let before: Vec<_> = walk(&dir);
    let scene = dir.to_string_lossy().into_owned();
    let res = run_deepstereo(["inspect", "--scene", &scene]);
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    assert!(res.stdout.contains("automatic, from"), "{}", res.stdout);
    let res = run_deepstereo(["inspect", "--json", "--scene", &scene]);
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    let json: serde_json::Value = serde_json::from_str(&res.stdout).expect("JSON");
    assert_eq!(json["bounds_source"], "auto");
    let near = json["near"].as_f64().expect("near");
    assert!(near > 0.0);
    // --near/--far override; nothing is written into the scene.
    let res = run_deepstereo([
        "inspect", "--json", "--scene", &scene, "--near", "0.5", "--far", "80",
    ]);
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    let json: serde_json::Value = serde_json::from_str(&res.stdout).expect("JSON");
    assert_eq!(json["bounds_source"], "user");
    assert_eq!(json["near"], 0.5);
    assert_eq!(walk(&dir), before);
}

#[test]
fn a_textureless_scene_without_bounds_is_refused_by_name() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let dir = scene_without_bounds(tmp.path());
    for e in std::fs::read_dir(dir.join("images"))
        .expect("images")
        .flatten()
    {
        let grey = image::RgbImage::from_pixel(160, 120, image::Rgb([128, 128, 128]));
        grey.save(e.path()).expect("write grey image");
    }
    let res = run_deepstereo(["inspect", "--scene", &dir.to_string_lossy()]);
    assert_ne!(res.code, Some(0));
    assert!(
        res.stderr.contains(&*dir.to_string_lossy()),
        "{}",
        res.stderr
    );
    assert!(
        res.stderr.contains("cannot find depth bounds"),
        "{}",
        res.stderr
    );
    assert!(
        res.stderr.contains("pass --near and --far"),
        "{}",
        res.stderr
    );
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}
