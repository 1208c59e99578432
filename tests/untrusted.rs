//! Untrusted input beyond the readers' corpus (`bad_input.rs`): interrupted runs leave no
//! staging folder, held-out views are named as such, `forward` refuses non-finite inputs, a
//! broken weights entry is named, and a README whose bounding box cannot be read is named
//! in a warning. Each case states what the command must print.

use deepstereo_tests::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Staging folders (`.<name>.partial-<pid>`) in `dir`.
fn stages(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .expect("ls")
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().contains(".partial-"))
        })
        .collect()
}

/// Starts a long path render into `out`, waits until its staging folder exists, sends
/// `signal` (a `kill` name) and returns the exit status and stderr.
fn interrupt_render(scene: &Path, out: &Path, signal: &str) -> (Option<i32>, String) {
    let err = tempfile::NamedTempFile::new().expect("temp");
    let mut child = Command::new(deepstereo_bin())
        .args(["render", "--scene"])
        .arg(scene)
        .args(["--path", "spiral", "--frames", "400", "--out"])
        .arg(out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(err.reopen().expect("reopen"))
        .spawn()
        .expect("spawn");
    let parent = out.parent().expect("parent");
    let start = Instant::now();
    while stages(parent).is_empty() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "no staging folder appeared"
        );
        assert!(
            child.try_wait().expect("wait").is_none(),
            "render ended early"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // Let it write a few frames into the stage.
    std::thread::sleep(Duration::from_millis(500));
    let ok = Command::new("kill")
        .args([format!("-{signal}"), child.id().to_string()])
        .status()
        .is_ok_and(|s| s.success());
    assert!(ok, "kill -{signal}");
    let status = child.wait().expect("wait");
    let stderr = std::fs::read_to_string(err.path()).unwrap_or_default();
    (status.code(), stderr)
}

#[test]
fn interrupted_renders_leave_no_staging_folder_and_stale_ones_are_removed() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = synth_scene(tmp.path(), (64, 48), 6, 3, &[]);
    let outs = tmp.path().join("outs");
    std::fs::create_dir_all(&outs).expect("mkdir");
    for signal in ["INT", "TERM"] {
        let out = outs.join(format!("render_{signal}"));
        let (code, stderr) = interrupt_render(&scene, &out, signal);
        assert_eq!(code, Some(130), "SIG{signal}: {stderr}");
        assert!(stderr.contains("interrupted"), "SIG{signal}: {stderr}");
        assert_eq!(
            stages(&outs),
            Vec::<PathBuf>::new(),
            "SIG{signal} left a stage"
        );
        assert!(!out.exists(), "SIG{signal} left a partial output");
    }
    // SIGKILL cannot be caught: the stage stays until the next run into the same output.
    let out = outs.join("render_KILL");
    let (code, _) = interrupt_render(&scene, &out, "KILL");
    assert_eq!(code, None, "killed");
    assert_eq!(stages(&outs).len(), 1, "SIGKILL leaves its stage");
    // A stage of a live process (this test's) is never touched.
    let live = outs.join(format!(".render_KILL.partial-{}", std::process::id()));
    std::fs::create_dir(&live).expect("mkdir");
    let res = ok(&[
        "render",
        "--scene",
        &scene.to_string_lossy(),
        "--target",
        "0",
        "--out",
        &out.to_string_lossy(),
    ]);
    assert!(
        res.stderr.contains("left by an interrupted run"),
        "{}",
        res.stderr
    );
    assert_eq!(
        stages(&outs),
        vec![live],
        "the stale stage stays or the live one went"
    );
    assert!(out.join("image.png").is_file());
}

#[test]
fn held_out_views_are_named_as_held_out_not_missing() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = synth_scene(tmp.path(), (48, 36), 6, 5, &[]);
    let s = scene.to_string_lossy();
    // Every view held out.
    let res = run_deepstereo(["eval", "--scene", &s, "--llffhold", "1"]);
    assert_ne!(res.code, Some(0));
    assert!(
        res.stderr
            .contains("--llffhold 1 holds out every one of the scene's 6 views"),
        "{}",
        res.stderr
    );
    assert!(!res.stderr.contains("has no views"), "{}", res.stderr);
    // Five of six held out: one source is left for each held-out target, and the hint
    // that names it works.
    let res = run_deepstereo(["eval", "--scene", &s, "--holdout", "0,1,2,3,4"]);
    assert_ne!(res.code, Some(0));
    assert!(
        res.stderr.contains(
            "4 source views are needed, 1 are left besides the target and any held-out views (try --views 1)"
        ),
        "{}",
        res.stderr
    );
    ok(&[
        "eval",
        "--scene",
        &s,
        "--holdout",
        "0,1,2,3,4",
        "--views",
        "1",
    ]);
}

#[test]
fn forward_refuses_non_finite_inputs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = synth_scene(tmp.path(), (40, 32), 5, 7, &[]);
    let inputs = tmp.path().join("inputs.safetensors");
    ok(&[
        "sweep",
        "--scene",
        &scene.to_string_lossy(),
        "--target",
        "0",
        "--model",
        "embedded",
        "--planes",
        "4",
        "--out",
        &inputs.to_string_lossy(),
    ]);
    let out = tmp.path().join("out.safetensors");
    let forward = |file: &Path| {
        run_deepstereo([
            "forward",
            "--inputs",
            &file.to_string_lossy(),
            "--out",
            &out.to_string_lossy(),
        ])
    };
    assert_eq!(forward(&inputs).code, Some(0), "the clean inputs run");
    std::fs::remove_file(&out).expect("rm");
    // The first value of `level0` becomes NaN.
    let mut bytes = std::fs::read(&inputs).expect("read");
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).expect("header");
    let at = 8
        + n
        + header["level0"]["data_offsets"][0]
            .as_u64()
            .expect("level0") as usize;
    bytes[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let bad = tmp.path().join("nan.safetensors");
    std::fs::write(&bad, bytes).expect("write");
    let res = forward(&bad);
    assert_ne!(res.code, Some(0), "NaN inputs were run");
    assert!(
        res.stderr.contains("nan.safetensors") && res.stderr.contains("non-finite"),
        "{}",
        res.stderr
    );
    assert!(!out.exists(), "an output was written");
}

#[test]
fn an_unreadable_bounding_box_is_named_in_a_warning() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = synth_scene(tmp.path(), (40, 32), 4, 9, &[]);
    // Without bounds in transforms.json, the README's box would give them.
    let file = scene.join("transforms.json");
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&file).expect("read")).expect("json");
    let top = json.as_object_mut().expect("object");
    top.remove("near");
    top.remove("far");
    std::fs::write(&file, serde_json::to_vec(&json).expect("json")).expect("write");
    std::fs::write(
        scene.join("README.txt"),
        "The bounding box is\n(-1 -1 oops)\n(1 1 1)\n",
    )
    .expect("write");
    let res = ok(&["inspect", "--scene", &scene.to_string_lossy()]);
    assert!(
        res.stderr.contains("README.txt") && res.stderr.contains("bounding box"),
        "{}",
        res.stderr
    );
    assert!(res.stderr.contains("warning"), "{}", res.stderr);
}

/// A weights file whose header entry for `colour.out.bias` is broken (its data cut short,
/// leaving a gap before `colour.out.weight`) is refused naming the broken entry, not only
/// the tensor after it, and nothing is written.
#[test]
fn a_broken_weights_entry_is_named() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let scene = synth_scene(tmp.path(), (40, 32), 5, 13, &[]);
    let asset = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deepstereo-train/assets/nviews-disagree-scratch.safetensors");
    let bytes = std::fs::read(&asset).expect("the shipped weights");
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).expect("header");
    let bias = &mut header["colour.out.bias"];
    let begin = bias["data_offsets"][0].as_u64().expect("offset");
    bias["shape"] = serde_json::json!([2]);
    bias["data_offsets"] = serde_json::json!([begin, begin + 8]);
    let head = serde_json::to_vec(&header).expect("json");
    let mut broken = (head.len() as u64).to_le_bytes().to_vec();
    broken.extend(head);
    broken.extend(&bytes[8 + n..]);
    let model = tmp.path().join("broken.safetensors");
    std::fs::write(&model, broken).expect("write");
    let out = tmp.path().join("out");
    let res = run_deepstereo([
        "render",
        "--scene",
        &scene.to_string_lossy(),
        "--target",
        "0",
        "--model",
        &model.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
    ]);
    assert_ne!(res.code, Some(0));
    assert!(
        res.stderr.contains("broken.safetensors") && res.stderr.contains("'colour.out.bias'"),
        "{}",
        res.stderr
    );
    assert!(!out.exists(), "an output was written");
}
