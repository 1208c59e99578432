//! What the commands write for people: camera-path videos (`render --path ... --video`,
//! MP4 through ffmpeg, checked with ffprobe, or the native GIF), `report`'s index.html
//! loaded in a real headless browser (every image on it must load), the one name of the
//! embedded model, poses from `inspect --json`, and failed commands leaving nothing behind.
//!
//! ffmpeg and Chromium are optional here: without them the checks that need them print
//! why they were skipped, unless `DEEPSTEREO_REQUIRE_FFMPEG=1` /
//! `DEEPSTEREO_REQUIRE_CHROMIUM=1` (as `tests/run-all.sh` sets), which makes them fail.

use deepstereo_tests::*;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Odd on purpose: the MP4 must still come out (padded to even dimensions).
const W: usize = 63;
const H: usize = 47;

fn scene(dir: &Path) -> PathBuf {
    synth_scene(dir, (W, H), 6, 7, &[])
}

fn fails(args: &[&str]) -> CmdOutput {
    let res = run_deepstereo(args);
    assert!(
        res.code.is_some_and(|c| c != 0),
        "deepstereo {} should fail:\n{}",
        args.join(" "),
        res.stderr
    );
    assert!(!res.stderr.contains("panicked"), "{}", res.stderr);
    let err = res
        .stderr
        .lines()
        .find(|l| l.starts_with("error"))
        .unwrap_or("");
    eprintln!("deepstereo {}: {err}", args[0]);
    res
}

fn runs(prog: &str) -> bool {
    Command::new(prog)
        .arg("-version")
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

fn gif_frames(path: &Path) -> (usize, u32, u32) {
    use image::AnimationDecoder;
    let f = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let dec = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(f)).expect("GIF");
    let frames = dec.into_frames().collect_frames().expect("GIF frames");
    let (w, h) = frames[0].buffer().dimensions();
    (frames.len(), w, h)
}

/// Every name in `dir` (recursively), relative to it.
fn listing(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).expect("read_dir") {
            let p = e.expect("entry").path();
            out.push(p.strip_prefix(dir).expect("prefix").display().to_string());
            if p.is_dir() {
                stack.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn path_video_is_a_decodable_mp4_or_gif_of_every_frame() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path()).to_string_lossy().into_owned();
    let out = tmp.path().join("frames");
    let video = tmp.path().join("x.mp4");
    let res = ok(&[
        "render",
        "--scene",
        &s,
        "--path",
        "circle",
        "--frames",
        "3",
        "--planes",
        "4",
        "--tile",
        "32",
        "--video",
        &video.to_string_lossy(),
        "--fps",
        "6",
        "--out",
        &out.to_string_lossy(),
    ]);
    for f in 0..3 {
        assert!(out.join(format!("frame_{f:04}.png")).is_file(), "frame {f}");
    }
    if runs("ffprobe") && runs("ffmpeg") {
        let probe = Command::new("ffprobe")
            .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
            .args([
                "-show_entries",
                "stream=codec_name,width,height,pix_fmt,nb_read_frames",
            ])
            .args(["-of", "default=noprint_wrappers=1"])
            .arg(&video)
            .output()
            .expect("ffprobe");
        let text = String::from_utf8_lossy(&probe.stdout).into_owned();
        assert!(probe.status.success(), "ffprobe: {text}");
        for want in [
            "codec_name=h264",
            "pix_fmt=yuv420p",
            "nb_read_frames=3",
            &format!("width={}", W + W % 2),
            &format!("height={}", H + H % 2),
        ] {
            assert!(text.contains(want), "{want} not in ffprobe's\n{text}");
        }
        eprintln!("ffprobe: {}", text.replace('\n', " "));
    } else {
        assert!(
            !required("DEEPSTEREO_REQUIRE_FFMPEG"),
            "ffmpeg/ffprobe are required (DEEPSTEREO_REQUIRE_FFMPEG=1) but do not run"
        );
        eprintln!(
            "SKIPPED the MP4 check: ffmpeg/ffprobe are not on the PATH (checked the GIF fallback)"
        );
        assert!(
            res.stderr.contains("ffmpeg is not on the PATH"),
            "{}",
            res.stderr
        );
        assert_eq!(
            gif_frames(&video.with_extension("gif")),
            (3, W as u32, H as u32)
        );
    }
    // The native GIF: asked for by name, and the fallback when ffmpeg does not run.
    let gif = tmp.path().join("y.gif");
    ok(&[
        "render",
        "--scene",
        &s,
        "--path",
        "line",
        "--frames",
        "3",
        "--planes",
        "4",
        "--video",
        &gif.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
    ]);
    assert_eq!(gif_frames(&gif), (3, W as u32, H as u32));
    let fallback = Command::new(deepstereo_bin())
        .env("DEEPSTEREO_FFMPEG", tmp.path().join("no-such-ffmpeg"))
        .args(["render", "--scene", &s, "--path", "spiral", "--frames", "2"])
        .args(["--planes", "4", "--out", &out.to_string_lossy(), "--video"])
        .arg(tmp.path().join("z.mp4"))
        .output()
        .expect("run deepstereo");
    let err = String::from_utf8_lossy(&fallback.stderr);
    assert!(fallback.status.success(), "{err}");
    assert!(err.contains("note: ffmpeg is not on the PATH"), "{err}");
    assert!(!tmp.path().join("z.mp4").exists());
    assert_eq!(gif_frames(&tmp.path().join("z.gif")).0, 2);
    let left: Vec<String> = listing(tmp.path())
        .into_iter()
        .filter(|n| n.contains(".tmp") || n.contains(".partial"))
        .collect();
    assert!(left.is_empty(), "left over: {left:?}");
}

#[test]
fn report_page_loads_every_image_in_a_headless_browser() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path()).to_string_lossy().into_owned();
    let out = tmp.path().join("report");
    ok(&[
        "report",
        "--scene",
        &s,
        "--holdout",
        "1,4",
        "--planes-grid",
        "4,8",
        "--prune-grid",
        "off,auto",
        "--tile",
        "32",
        "--out",
        &out.to_string_lossy(),
    ]);
    let html = std::fs::read_to_string(out.join("index.html")).expect("index.html");
    assert!(html.contains("Pareto front") && html.contains("<table>"));
    assert!(
        !html.contains("http://") && !html.contains("https://"),
        "external link"
    );
    let srcs: Vec<&str> = html
        .split("src=\"")
        .skip(1)
        .filter_map(|s| s.split('"').next())
        .collect();
    // The plot, and per held-out view: photograph, network, plane sweep, nearest.
    assert_eq!(srcs.len(), 1 + 2 * 4, "{srcs:?}");
    for src in &srcs {
        assert!(!src.starts_with('/'), "absolute link {src}");
        assert!(out.join(src).is_file(), "{src} missing");
    }
    let Some(browser) = chromium() else {
        assert!(
            !required("DEEPSTEREO_REQUIRE_CHROMIUM"),
            "Chromium is required (DEEPSTEREO_REQUIRE_CHROMIUM=1) but does not run"
        );
        eprintln!(
            "SKIPPED the browser check: no chromium on the PATH (tests/run-all.sh installs it)"
        );
        return;
    };
    // The page itself has no script; a copy beside it gets one that counts loaded images.
    let check = "<script>window.addEventListener('load',()=>{const i=[...document.images];\
        const ok=i.filter(x=>x.complete&&x.naturalWidth>0).length;\
        document.body.setAttribute('data-images','LOADED '+ok+' OF '+i.length);});</script>";
    let probe = out.join("check.html");
    std::fs::write(&probe, html.replace("</body>", &format!("{check}</body>"))).expect("write");
    let profile = tmp.path().join("chromium-profile");
    let res = Command::new(browser)
        .args([
            "--headless",
            "--disable-gpu",
            "--no-sandbox",
            "--disable-dev-shm-usage",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(["--virtual-time-budget=10000", "--dump-dom"])
        .arg(format!("file://{}", probe.display()))
        .output()
        .expect("run chromium");
    let dom = String::from_utf8_lossy(&res.stdout);
    let want = format!("LOADED {0} OF {0}", srcs.len());
    assert!(
        dom.contains(&want),
        "{browser}: want '{want}' in the DOM:\n{}\n{}",
        dom.chars().take(400).collect::<String>(),
        String::from_utf8_lossy(&res.stderr)
    );
    eprintln!("{browser}: {want}");
}

#[test]
fn the_embedded_model_has_one_name_and_render_takes_inspect_json() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path()).to_string_lossy().into_owned();
    let res = ok(&[
        "eval",
        "--scene",
        &s,
        "--holdout",
        "2",
        "--planes",
        "4",
        "--model",
        "embedded",
        "--json",
        "-",
    ]);
    let j: serde_json::Value = serde_json::from_str(&res.stdout).expect("JSON");
    assert_eq!(j["model"], "embedded");
    let res = ok(&[
        "eval",
        "--scene",
        &s,
        "--holdout",
        "2",
        "--planes",
        "4",
        "--json",
        "-",
    ]);
    let j: serde_json::Value = serde_json::from_str(&res.stdout).expect("JSON");
    assert_eq!(j["model"], "embedded");
    let st = tmp.path().join("psv.safetensors");
    ok(&[
        "sweep",
        "--scene",
        &s,
        "--target",
        "1",
        "--planes",
        "4",
        "--model",
        "embedded",
        "--out",
        &st.to_string_lossy(),
    ]);
    let bytes = std::fs::read(&st).expect("safetensors");
    assert!(String::from_utf8_lossy(&bytes[..4096.min(bytes.len())]).contains("level0"));
    ok(&[
        "export",
        "--model",
        "embedded",
        "--out",
        &tmp.path().join("m.onnx").to_string_lossy(),
    ]);
    // Plain inspect prints R and t as the README says; --json feeds render --pose.
    let text = ok(&["inspect", "--scene", &s]).stdout;
    assert!(text.contains("R=[") && text.contains("t=("), "{text}");
    let json = ok(&["inspect", "--json", "--scene", &s]).stdout;
    let pose = tmp.path().join("inspect.json");
    std::fs::write(&pose, &json).expect("write");
    let out = tmp.path().join("posed");
    let (p, o) = (pose.to_string_lossy(), out.to_string_lossy());
    ok(&[
        "render", "--scene", &s, "--pose", &p, "--view", "3", "--planes", "4", "--out", &o,
    ]);
    let img = image::open(out.join("image.png")).expect("image.png");
    assert_eq!((img.width(), img.height()), (W as u32, H as u32));
    let v: serde_json::Value = serde_json::from_str(&json).expect("JSON");
    let one = tmp.path().join("one.json");
    std::fs::write(&one, v["views"][3].to_string()).expect("write");
    ok(&[
        "render",
        "--scene",
        &s,
        "--pose",
        &one.to_string_lossy(),
        "--planes",
        "4",
        "--out",
        &o,
    ]);
    let e = fails(&["render", "--scene", &s, "--pose", &p, "--out", &o]);
    assert!(e.stderr.contains("--view"), "{}", e.stderr);
    let e = fails(&[
        "render", "--scene", &s, "--pose", &p, "--view", "6", "--out", &o,
    ]);
    assert!(e.stderr.contains("out of range"), "{}", e.stderr);
}

#[test]
fn inspect_json_writes_an_infinite_far_bound_as_null() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path()).to_string_lossy().into_owned();
    let args = [
        "inspect", "--json", "--scene", &s, "--near", "0.5", "--far", "inf",
    ];
    let json = ok(&args).stdout;
    let v: serde_json::Value = serde_json::from_str(&json).expect("JSON");
    assert!(v["far"].is_null(), "far: {}", v["far"]);
    assert_eq!(inspect_far(&v["far"]), Some(f64::INFINITY));
    assert_eq!(v["near"].as_f64(), Some(0.5));
    let scene = deepstereo_core::scene::Scene::load(
        Path::new(&s),
        &deepstereo_core::scene::LoadOptions {
            near: Some(0.5),
            far: Some(f64::INFINITY),
            ..Default::default()
        },
    )
    .expect("scene");
    check_inspect_json(&v, &scene, "nerf");
    // render --pose reads the file back, and one written before (far "inf") alike.
    let old = json.replace("\"far\": null", "\"far\": \"inf\"");
    assert_ne!(old, json);
    for (name, text) in [("null.json", &json), ("inf.json", &old)] {
        let pose = tmp.path().join(name);
        std::fs::write(&pose, text).expect("write");
        let out = tmp.path().join(format!("{name}-out"));
        ok(&[
            "render",
            "--scene",
            &s,
            "--pose",
            &pose.to_string_lossy(),
            "--view",
            "2",
            "--planes",
            "4",
            "--far",
            "inf",
            "--near",
            "0.5",
            "--out",
            &out.to_string_lossy(),
        ]);
        assert!(out.join("image.png").is_file(), "{name}");
    }
}

#[test]
fn failed_commands_leave_nothing_behind() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path()).to_string_lossy().into_owned();
    let before = listing(tmp.path());
    let new = |n: &str| {
        tmp.path()
            .join("new")
            .join(n)
            .to_string_lossy()
            .into_owned()
    };
    let cases: Vec<Vec<String>> = vec![
        // Fails after the frames are rendered: the video cannot be written.
        vec![
            "render",
            "--scene",
            &s,
            "--path",
            "circle",
            "--frames",
            "2",
            "--planes",
            "4",
            "--video",
            "/dev/null/x.mp4",
            "--out",
            &new("render"),
        ],
        vec![
            "render",
            "--scene",
            &s,
            "--target",
            "9",
            "--out",
            &new("render"),
        ],
        // Fails on the second held-out view, after the first one's image.
        vec![
            "eval",
            "--scene",
            &s,
            "--holdout",
            "1,9",
            "--planes",
            "4",
            "--images",
            &new("eval"),
            "--json",
            &new("eval.json"),
        ],
        vec![
            "report",
            "--scene",
            &s,
            "--holdout",
            "1,9",
            "--planes-grid",
            "4",
            "--out",
            &new("report"),
        ],
        vec![
            "synth",
            "--out",
            &new("synth"),
            "--scenes",
            "1",
            "--views",
            "3",
            "--size",
            "32x24",
            "--supersample",
            "1",
            "--sheet",
            "/dev/null/sheet.png",
        ],
        vec![
            "export",
            "--model",
            &new("missing.safetensors"),
            "--out",
            &new("m.onnx"),
        ],
        vec![
            "sweep",
            "--scene",
            &s,
            "--target",
            "1",
            "--planes",
            "4",
            "--png",
            &new("planes"),
            "--out",
            "/dev/null/psv.safetensors",
        ],
    ]
    .into_iter()
    .map(|c| c.into_iter().map(String::from).collect())
    .collect();
    for args in &cases {
        let a: Vec<&str> = args.iter().map(String::as_str).collect();
        fails(&a);
        assert_eq!(
            listing(tmp.path()),
            before,
            "deepstereo {} left files",
            a.join(" ")
        );
    }
}

/// A path's cameras come back from its `cameras.json`: rendering the file gives the same
/// frames, byte for byte, and the file holds every camera in `inspect --json`'s layout; a
/// bare `--path` picks the spiral for a forward-facing rig and says so.
#[test]
fn a_paths_cameras_json_renders_the_same_frames_again() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = synth_scene(tmp.path(), (48, 36), 8, 11, &["--rig", "forward"]);
    let s = s.to_string_lossy().into_owned();
    let first = tmp.path().join("first");
    let res = ok(&[
        "render",
        "--scene",
        &s,
        "--path",
        "--frames",
        "3",
        "--planes",
        "8",
        "--out",
        &first.to_string_lossy(),
    ]);
    assert!(
        res.stderr.contains("path: spiral") && res.stderr.contains("forward-facing"),
        "{}",
        res.stderr
    );
    let cams = first.join("cameras.json");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&cams).expect("cameras.json")).expect("json");
    let views = json["views"].as_array().expect("views");
    assert_eq!(views.len(), 3);
    for (i, v) in views.iter().enumerate() {
        assert_eq!(v["name"], format!("frame_{i:04}"));
        assert_eq!(v["R"].as_array().map(Vec::len), Some(9));
        assert_eq!(
            (v["width"].as_u64(), v["height"].as_u64()),
            (Some(48), Some(36))
        );
    }
    let again = tmp.path().join("again");
    let res = ok(&[
        "render",
        "--scene",
        &s,
        "--path",
        &cams.to_string_lossy(),
        "--planes",
        "8",
        "--out",
        &again.to_string_lossy(),
    ]);
    assert!(res.stderr.contains("the 3 cameras of"), "{}", res.stderr);
    for f in 0..3 {
        let name = format!("frame_{f:04}.png");
        assert_eq!(
            std::fs::read(first.join(&name)).expect("first"),
            std::fs::read(again.join(&name)).expect("again"),
            "{name}"
        );
    }
    // Written back, the cameras are the same to rounding (a pose read is orthonormalized).
    let back: serde_json::Value =
        serde_json::from_slice(&std::fs::read(again.join("cameras.json")).expect("again"))
            .expect("json");
    for (a, b) in views.iter().zip(back["views"].as_array().expect("views")) {
        for key in ["R", "t"] {
            let (a, b) = (a[key].as_array().expect(key), b[key].as_array().expect(key));
            for (x, y) in a.iter().zip(b) {
                let (x, y) = (x.as_f64().expect("x"), y.as_f64().expect("y"));
                assert!((x - y).abs() < 1e-12, "{key}: {x} against {y}");
            }
        }
    }
    // One camera of the file with --pose --view renders that frame.
    let one = tmp.path().join("one");
    ok(&[
        "render",
        "--scene",
        &s,
        "--pose",
        &cams.to_string_lossy(),
        "--view",
        "1",
        "--planes",
        "8",
        "--out",
        &one.to_string_lossy(),
    ]);
    assert!(one.join("image.png").is_file());
    let bad = fails(&[
        "render",
        "--scene",
        &s,
        "--path",
        "nowhere",
        "--out",
        &one.to_string_lossy(),
    ]);
    assert!(bad.stderr.contains("neither a path kind"), "{}", bad.stderr);
}
