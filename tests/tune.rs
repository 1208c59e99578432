//! `deepstereo tune` end to end on a small generated scene: held-out photographs cannot
//! reach the tuner (noise in their place leaves a `--steps` tune bit-identical, while a
//! change to a tuning view does not), the same seed and steps give the same file, the
//! tuned model is taken by `eval --model`, and bad input is refused with nothing written.

use deepstereo_tests::*;
use std::path::{Path, PathBuf};

const W: u32 = 64;
const H: u32 = 48;

/// A procedural scene of 8 views at W x H ([`synth_scene`]). With `auto_bounds` its
/// transforms.json loses near/far, so the bounds are estimated from the images.
fn scene(dir: &Path, auto_bounds: bool) -> PathBuf {
    let s = synth_scene(dir, (W as usize, H as usize), 8, 5, &["--rig", "forward"]);
    if auto_bounds {
        let path = s.join("transforms.json");
        let mut json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).expect("read")).expect("json");
        let obj = json.as_object_mut().expect("an object");
        obj.remove("near");
        obj.remove("far");
        std::fs::write(&path, serde_json::to_string(&json).expect("json")).expect("write");
    }
    s
}

/// `tune` with a small budget; returns the command's output.
fn tune(scene: &Path, out: &Path, extra: &[&str]) -> CmdOutput {
    let (s, o) = (scene.to_string_lossy(), out.to_string_lossy());
    let mut args = vec![
        "tune",
        "--scene",
        &s,
        "--out",
        &o,
        "--batch",
        "2",
        "--val-batches",
        "1",
        "--validate-every",
        "2",
    ];
    args.extend_from_slice(extra);
    run_deepstereo(args)
}

fn tuned(scene: &Path, out: &Path) -> Vec<u8> {
    tuned_with(scene, out, &[])
}

/// A 4-step tune holding out every 4th view, with `extra` options.
fn tuned_with(scene: &Path, out: &Path, extra: &[&str]) -> Vec<u8> {
    let mut args = vec!["--llffhold", "4", "--steps", "4"];
    args.extend_from_slice(extra);
    let res = tune(scene, out, &args);
    assert_eq!(res.code, Some(0), "tune failed:\n{}", res.stderr);
    std::fs::read(out).expect("the tuned model")
}

/// The `__metadata__` of a safetensors file.
fn read_safetensors_metadata(path: &Path) -> serde_json::Map<String, serde_json::Value> {
    let bytes = std::fs::read(path).expect("read the model");
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).expect("header");
    header["__metadata__"]
        .as_object()
        .expect("metadata")
        .clone()
}

/// Both phases run: the prior's steps, then the network's through it.
fn held_out_noise_changes_nothing(auto_bounds: bool) {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), auto_bounds);
    let tuned = |s: &Path, out: &Path| tuned_with(s, out, &["--network-share", "0.5"]);
    let a = tuned(&s, &dir.path().join("a.safetensors"));
    assert!(
        a == tuned(&s, &dir.path().join("again.safetensors")),
        "same seed and steps, another file"
    );
    // --llffhold 4 of 8 views holds out views 0 and 4: noise in their place.
    for v in [0, 4] {
        write_png(&s.join(format!("images/view_{v:03}.png")), W, H, 99 + v);
    }
    let b = tuned(&s, &dir.path().join("b.safetensors"));
    assert!(
        a == b,
        "noise in the held-out photographs changed the tuned model"
    );
    // The test can fail: noise in a tuning view does change it.
    write_png(&s.join("images/view_002.png"), W, H, 7);
    let c = tuned(&s, &dir.path().join("c.safetensors"));
    assert!(
        a != c,
        "a tuning view's photograph did not change the tuned model"
    );
}

#[test]
fn held_out_photographs_cannot_reach_the_tuner() {
    held_out_noise_changes_nothing(false);
}

#[test]
fn held_out_photographs_cannot_move_estimated_bounds() {
    held_out_noise_changes_nothing(true);
}

#[test]
fn the_tuned_model_renders_and_names_its_tune() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), false);
    let model = dir.path().join("tuned.safetensors");
    tuned(&s, &model);
    let meta = read_safetensors_metadata(&model);
    let tune: serde_json::Value =
        serde_json::from_str(meta["deepstereo.tune"].as_str().expect("a string")).expect("json");
    assert_eq!(tune["holdout"], serde_json::json!([0, 4]));
    assert_eq!(tune["steps"], 4);
    // A model with a prior renders at the planes chosen on the views set aside and a
    // few tuning views: the most of 24, 28, ..., 48 whose work stays within the
    // embedded model's (24 when none does), found by bisection from 36; the network's
    // own plane count stays.
    let cfg: serde_json::Value =
        serde_json::from_str(meta["deepstereo.config"].as_str().expect("a string")).expect("json");
    assert_eq!(cfg["planes"], 32);
    assert_eq!(cfg["render_planes"], tune["render_planes"]);
    let chosen = cfg["render_planes"].as_u64().expect("render_planes");
    let tried: Vec<(u64, f64)> = tune["render_planes_work"]
        .as_array()
        .expect("the work of each count tried")
        .iter()
        .map(|t| {
            (
                t[0].as_u64().expect("planes"),
                t[1].as_f64().expect("ratio"),
            )
        })
        .collect();
    assert!(!tried.is_empty() && tried.iter().all(|t| t.1.is_finite() && t.1 > 0.0));
    // The bisection's path: each count tried follows from the ratio before it.
    let choices = [24u64, 28, 32, 36, 40, 44, 48];
    let (mut lo, mut hi, mut want) = (0usize, choices.len(), 24u64);
    for t in &tried {
        let mid = (lo + hi) / 2;
        assert_eq!(t.0, choices[mid], "{tried:?}");
        if t.1 <= 1.0 {
            want = t.0;
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    assert_eq!(lo, hi, "the bisection ended early: {tried:?}");
    assert_eq!(tune["render_planes_cut"], false, "--steps: no time limit");
    assert_eq!(chosen, want, "{tried:?}");
    assert_eq!(
        tune["network_share"], 0.0,
        "--steps without --network-share"
    );
    let (m, sc) = (model.to_string_lossy(), s.to_string_lossy());
    let eval = |extra: &[&str]| {
        let mut args = vec!["eval", "--scene", &sc, "--llffhold", "4", "--model", &m];
        args.extend_from_slice(extra);
        run_deepstereo(args)
    };
    let res = eval(&["--json", "-"]);
    assert_eq!(res.code, Some(0), "eval --model failed:\n{}", res.stderr);
    let json: serde_json::Value = serde_json::from_str(&res.stdout).expect("eval json");
    let psnr = json["mean"]["psnr"].as_f64().expect("a mean PSNR");
    assert!(psnr.is_finite() && psnr > 10.0, "PSNR {psnr}");
    // eval renders it at its render planes without being told, and at --planes when told.
    assert_eq!(json["planes"], chosen);
    let res = eval(&["--planes", "40", "--json", "-"]);
    assert_eq!(
        res.code,
        Some(0),
        "eval --planes 40 failed:\n{}",
        res.stderr
    );
    let json: serde_json::Value = serde_json::from_str(&res.stdout).expect("eval json");
    assert_eq!(json["planes"], 40);
    // The scene prior is in the file; onnxruntime cannot apply it and says so.
    assert!(
        meta.contains_key("deepstereo.prior"),
        "no scene prior in {meta:?}"
    );
    let res = eval(&["--backend", "ort"]);
    assert!(
        res.code != Some(0) && res.stderr.contains("scene prior"),
        "ort took a model with a prior:\n{}",
        res.stderr
    );
}

/// `--network-share`: 1 fine-tunes the network alone (no prior in the file), 0.5 both
/// (the prior's steps first, then the network's through it), and each moves what it
/// says.
#[test]
fn network_share_splits_the_steps() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), false);
    let start = dir.path().join("start.safetensors");
    let prior_only = tuned(&s, &start);
    for (share, prior) in [("1", false), ("0.5", true)] {
        let out = dir.path().join(format!("share{share}.safetensors"));
        let res = tune(
            &s,
            &out,
            &["--llffhold", "4", "--steps", "4", "--network-share", share],
        );
        assert_eq!(res.code, Some(0), "tune failed:\n{}", res.stderr);
        let meta = read_safetensors_metadata(&out);
        assert_eq!(
            meta.contains_key("deepstereo.prior"),
            prior,
            "share {share}"
        );
        let t: serde_json::Value =
            serde_json::from_str(meta["deepstereo.tune"].as_str().expect("a string"))
                .expect("json");
        assert_eq!(
            t["network_steps"],
            if share == "1" { 4 } else { 2 },
            "share {share}"
        );
        assert_eq!(t["network_through_prior"], prior, "share {share}: {t}");
        if prior {
            assert_eq!(t["prior_steps"], 2, "share {share}: {t}");
        }
        // Without a prior the model renders at the planes it started with; with one, at
        // the planes chosen.
        let cfg: serde_json::Value =
            serde_json::from_str(meta["deepstereo.config"].as_str().expect("a string"))
                .expect("json");
        let want = if prior {
            t["render_planes"].clone()
        } else {
            serde_json::Value::Null
        };
        assert!(!prior || want.is_u64(), "share {share}: {t}");
        assert_eq!(cfg["render_planes"], want, "share {share}");
        assert_eq!(cfg["planes"], 32, "share {share}");
        assert_ne!(
            std::fs::read(&out).expect("read"),
            prior_only,
            "share {share}"
        );
    }
}

/// `--render-planes P` is written as given, without the choice on the views set aside;
/// a time budget splits itself between the network and the prior and says how.
#[test]
fn render_planes_and_the_split_of_a_time_budget() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), false);
    let out = dir.path().join("p40.safetensors");
    let res = tune(
        &s,
        &out,
        &["--llffhold", "4", "--steps", "4", "--render-planes", "40"],
    );
    assert_eq!(res.code, Some(0), "tune failed:\n{}", res.stderr);
    let meta = read_safetensors_metadata(&out);
    let t: serde_json::Value =
        serde_json::from_str(meta["deepstereo.tune"].as_str().expect("a string")).expect("json");
    assert_eq!(t["render_planes"], 40);
    assert!(t["render_planes_work"].is_null(), "{t}");
    let out = dir.path().join("timed.safetensors");
    let res = tune(&s, &out, &["--llffhold", "4", "--minutes", "0.5"]);
    assert_eq!(res.code, Some(0), "tune failed:\n{}", res.stderr);
    assert!(
        res.stderr.contains("the prior needs about"),
        "{}",
        res.stderr
    );
    let meta = read_safetensors_metadata(&out);
    let t: serde_json::Value =
        serde_json::from_str(meta["deepstereo.tune"].as_str().expect("a string")).expect("json");
    let share = t["network_share"].as_f64().expect("a share");
    let need = t["prior_need_seconds"]
        .as_f64()
        .expect("the prior's estimated time");
    assert!((0.0..=1.0).contains(&share) && need > 0.0, "{t}");
    assert_eq!(t["network_share_given"], false);
    // The prior runs first; the network, when it runs, is tuned through its grid.
    assert!(t["prior_views"].as_u64().is_some_and(|v| v > 0), "{t}");
    let through = !t["prior_sharpness"].is_null();
    assert!(
        t["network_steps"].is_null() || t["network_through_prior"] == through,
        "{t}"
    );
    // The prior reads part of each view when whole views do not fit in its time.
    let view_share = t["prior_view_share"].as_f64().expect("a view share");
    assert!((0.25..=1.0).contains(&view_share), "{t}");
}

#[test]
fn bad_input_is_refused_and_writes_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), false);
    let out = dir.path().join("out.safetensors");
    let tiny = tiny_asset();
    let tiny = tiny.to_string_lossy();
    let cases: [(&[&str], &str); 10] = [
        (
            &["--llffhold", "4", "--steps", "2", "--render-planes", "0"],
            "--render-planes",
        ),
        (
            &["--llffhold", "4", "--steps", "2", "--network-share", "1.5"],
            "--network-share",
        ),
        (&["--holdout", "0,1,2,3,4,5", "--steps", "2"], "at least 3"),
        (&["--holdout", "0,9", "--steps", "2"], "out of range"),
        (&["--llffhold", "4", "--minutes", "0"], "--minutes"),
        (&["--llffhold", "4", "--minutes=-2"], "--minutes"),
        (&["--llffhold", "4", "--steps", "0"], "--steps"),
        (
            &["--llffhold", "4", "--steps", "2", "--model", &tiny],
            "family",
        ),
        (&["--steps", "2", "--curve", "curve"], "held-out"),
        (&["--steps", "2", "--prior-smooth=-1"], "--prior-smooth"),
    ];
    for (args, want) in cases {
        let res = tune(&s, &out, args);
        assert_ne!(res.code, Some(0), "{args:?} was accepted");
        assert!(
            !res.timed_out && res.code.is_some(),
            "{args:?}: no clean exit"
        );
        assert!(
            res.stderr.contains(want),
            "{args:?}: expected '{want}' in:\n{}",
            res.stderr
        );
        assert!(!out.exists(), "{args:?} wrote {}", out.display());
    }
    // The split's flags are refused before the scene is read: a missing scene is not
    // what the error names.
    let nowhere = dir.path().join("no-scene");
    for (flag, value) in [
        ("--network-share", "2"),
        ("--prior-smooth", "-1"),
        ("--prior-cells", "1"),
    ] {
        let res = tune(
            &nowhere,
            &out,
            &["--steps", "2", &format!("{flag}={value}")],
        );
        assert!(
            res.code.is_some_and(|c| c != 0) && res.stderr.contains(flag),
            "{flag}={value} with a missing scene: {}",
            res.stderr
        );
    }
    // One rule across commands: the folders above an output are created.
    let missing = dir.path().join("no/such/dir/out.safetensors");
    let res = tune(&s, &missing, &["--llffhold", "4", "--steps", "2"]);
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    assert!(missing.is_file(), "no model in the created directory");
    std::fs::remove_dir_all(dir.path().join("no")).expect("rm");
    let res = tune(&s, dir.path(), &["--llffhold", "4", "--steps", "2"]);
    assert!(
        res.code != Some(0) && res.stderr.contains("directory"),
        "{}",
        res.stderr
    );
    assert_eq!(
        std::fs::read_dir(dir.path()).expect("ls").count(),
        1,
        "only the scene"
    );
}

/// `--curve` into a directory that does not exist yet: it is created, and the curve is
/// written there.
#[test]
fn the_curve_goes_into_a_new_directory() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), false);
    let curve = dir.path().join("out/curve");
    let c = curve.to_string_lossy();
    let out = dir.path().join("t.safetensors");
    let args = [
        "--llffhold",
        "4",
        "--steps",
        "2",
        "--curve",
        &c,
        "--curve-minutes",
        "0",
    ];
    let res = tune(&s, &out, &args);
    assert_eq!(res.code, Some(0), "tune --curve failed:\n{}", res.stderr);
    for f in ["curve.csv", "curve.json", "curve.png"] {
        assert!(curve.join(f).is_file(), "no {f} in {}", curve.display());
    }
}

/// A time budget holds whatever the images' size: when one view's read would take over a
/// quarter of it, the scene is read at a lower resolution (halved until it fits), with a
/// note; `--downscale` does not override it. Without a time budget nothing changes.
#[test]
fn a_short_budget_reads_a_large_scene_at_a_lower_resolution() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = synth_scene(dir.path(), (512, 384), 8, 4, &[]);
    let out = dir.path().join("m.safetensors");
    // 0.2 megapixels: about 5.9 s a view at the bound, against 0.75 s for a 3 s budget.
    let res = tune(
        &s,
        &out,
        &["--llffhold", "4", "--minutes", "0.05", "--downscale", "1"],
    );
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    for want in ["reading the scene at 1/2", "reading the scene at 1/4"] {
        assert!(res.stderr.contains(want), "no '{want}':\n{}", res.stderr);
    }
    assert!(!res.stderr.contains("at 1/8"), "{}", res.stderr);
    assert!(out.is_file());
    let res = tune(&s, &out, &["--llffhold", "4", "--steps", "2"]);
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    assert!(
        !res.stderr.contains("reading the scene at"),
        "{}",
        res.stderr
    );
}

/// Ctrl-C while the network is tuned through the prior writes the best model so far:
/// the fitted prior and the network's best weights, exit 0, nothing else in the folder.
#[test]
fn ctrl_c_in_the_networks_phase_writes_the_best_model() {
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), false);
    let outdir = dir.path().join("out");
    std::fs::create_dir(&outdir).expect("mkdir");
    let out = outdir.join("tuned.safetensors");
    let mut child = Command::new(deepstereo_bin())
        .args(["tune", "--scene"])
        .arg(&s)
        .args([
            "--llffhold",
            "4",
            "--minutes",
            "5",
            "--network-share",
            "0.9",
        ])
        .args([
            "--batch",
            "2",
            "--val-batches",
            "1",
            "--validate-every",
            "2",
        ])
        .args(["--no-progress", "--out"])
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let mut lines = BufReader::new(child.stderr.take().expect("stderr")).lines();
    let mut seen = String::new();
    // The network's phase validates every 2 steps: interrupt at its second validation.
    let mut steps = 0;
    for line in lines.by_ref() {
        let line = line.expect("a line");
        seen += &line;
        seen.push('\n');
        if line.starts_with("step ") {
            steps += 1;
            if steps == 2 {
                break;
            }
        }
    }
    assert_eq!(steps, 2, "the network's phase never validated:\n{seen}");
    let ok = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .is_ok_and(|st| st.success());
    assert!(ok, "kill -INT");
    for line in lines {
        seen += &line.expect("a line");
        seen.push('\n');
    }
    let status = child.wait().expect("wait");
    assert_eq!(status.code(), Some(0), "{seen}");
    assert!(
        seen.contains("interrupted: network through the prior"),
        "{seen}"
    );
    let meta = read_safetensors_metadata(&out);
    assert!(meta.contains_key("deepstereo.prior"), "no prior written");
    let t: serde_json::Value =
        serde_json::from_str(meta["deepstereo.tune"].as_str().expect("a string")).expect("json");
    assert_eq!(t["network_through_prior"], true, "{t}");
    let left: Vec<_> = std::fs::read_dir(&outdir)
        .expect("ls")
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
}

/// `--refit` reads the views again after the network's phase and refits the prior from
/// the one fitted before: the file says so, and it differs from the tune without it.
#[test]
fn refit_refits_the_prior_on_the_tuned_network() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = scene(dir.path(), false);
    let both = &["--network-share", "0.5"];
    let without = tuned_with(&s, &dir.path().join("a.safetensors"), both);
    let out = dir.path().join("refit.safetensors");
    let with = tuned_with(&s, &out, &["--network-share", "0.5", "--refit"]);
    let meta = read_safetensors_metadata(&out);
    let t: serde_json::Value =
        serde_json::from_str(meta["deepstereo.tune"].as_str().expect("a string")).expect("json");
    assert!(t["refit_views"].as_u64().is_some_and(|v| v > 0), "{t}");
    assert!(meta.contains_key("deepstereo.prior"), "{t}");
    assert_ne!(with, without);
}
