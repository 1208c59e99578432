//! The user-facing commands end to end on a small generated scene, with the embedded
//! model: `render` (by view, along a path), `eval --json`, `report` and `demo` write what
//! their help and the README promise, with finite values of the documented shapes; and
//! `forward` refuses inputs without planes by name.

use deepstereo_tests::*;
use std::path::{Path, PathBuf};

const W: usize = 64;
const H: usize = 48;

/// A procedural scene of 6 views at W x H in `dir/scene_0000`.
fn scene(dir: &Path) -> PathBuf {
    let res = run_deepstereo([
        "synth",
        "--out",
        &dir.to_string_lossy(),
        "--scenes",
        "1",
        "--views",
        "6",
        "--seed",
        "31",
        "--size",
        &format!("{W}x{H}"),
        "--supersample",
        "1",
    ]);
    assert_eq!(res.code, Some(0), "synth failed: {}", res.stderr);
    dir.join("scene_0000")
}

/// `deepstereo eval --scene <scene> --holdout <holdout> <extra...> --json -`, parsed.
fn eval_json(scene: &Path, holdout: &str, extra: &[&str]) -> serde_json::Value {
    let sd = scene.to_string_lossy();
    let mut args = vec!["eval", "--scene", &sd, "--holdout", holdout];
    args.extend_from_slice(extra);
    args.extend_from_slice(&["--json", "-"]);
    let res = ok(&args);
    serde_json::from_str(&res.stdout).expect("JSON on stdout")
}

/// Shape and values of a little-endian f32 `.npy` file.
fn read_npy_f32(path: &Path) -> (Vec<usize>, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(
        &bytes[..6],
        b"\x93NUMPY",
        "{}: not an npy file",
        path.display()
    );
    let len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = String::from_utf8_lossy(&bytes[10..10 + len]).into_owned();
    assert!(header.contains("'<f4'"), "{header}");
    let inner = header
        .split("'shape': (")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .expect("shape");
    let shape: Vec<usize> = inner
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().expect("dimension"))
        .collect();
    let data: Vec<f32> = bytes[10 + len..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    assert_eq!(data.len(), shape.iter().product::<usize>(), "{header}");
    (shape, data)
}

fn png_size(path: &Path) -> (u32, u32) {
    let img = image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    (img.width(), img.height())
}

#[test]
fn render_by_view_writes_image_depth_confidence_and_coverage() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let out = tmp.path().join("render");
    let sd = s.to_string_lossy().into_owned();
    let od = out.to_string_lossy().into_owned();
    ok(&[
        "render", "--scene", &sd, "--target", "2", "--planes", "8", "--tile", "32", "--out", &od,
    ]);
    for png in ["image.png", "depth.png", "confidence.png", "coverage.png"] {
        assert_eq!(png_size(&out.join(png)), (W as u32, H as u32), "{png}");
    }
    let (shape, image) = read_npy_f32(&out.join("image.npy"));
    assert_eq!(shape, vec![H, W, 3]);
    assert!(image
        .iter()
        .all(|v| v.is_finite() && (-0.5..=1.5).contains(v)));
    let (shape, depth) = read_npy_f32(&out.join("depth.npy"));
    assert_eq!(shape, vec![H, W]);
    assert!(depth.iter().all(|v| v.is_finite() && *v > 0.0));
    // No temporary files left behind.
    for e in std::fs::read_dir(&out).expect("out dir") {
        let name = e.expect("entry").file_name().to_string_lossy().into_owned();
        assert!(!name.contains(".tmp"), "left over: {name}");
    }
    // A tile far larger than the image renders the same image (one tile covers it).
    let big = tmp.path().join("render_big_tile");
    let bd = big.to_string_lossy().into_owned();
    ok(&[
        "render", "--scene", &sd, "--target", "2", "--planes", "8", "--tile", "1000000", "--out",
        &bd,
    ]);
    let whole = tmp.path().join("render_whole");
    let wd = whole.to_string_lossy().into_owned();
    let side = W.max(H).to_string();
    ok(&[
        "render", "--scene", &sd, "--target", "2", "--planes", "8", "--tile", &side, "--out", &wd,
    ]);
    assert_eq!(
        read_npy_f32(&big.join("image.npy")),
        read_npy_f32(&whole.join("image.npy"))
    );
}

#[test]
fn render_along_a_path_writes_a_numbered_sequence() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let out = tmp.path().join("path");
    ok(&[
        "render",
        "--scene",
        &s.to_string_lossy(),
        "--path",
        "circle",
        "--frames",
        "2",
        "--planes",
        "8",
        "--out",
        &out.to_string_lossy(),
    ]);
    let mut pngs: Vec<String> = std::fs::read_dir(&out)
        .expect("out dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".png"))
        .collect();
    pngs.sort();
    assert!(pngs.len() >= 2, "{pngs:?}");
}

#[test]
fn eval_json_has_the_documented_layout() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let v = eval_json(&s, "1,4", &["--planes", "8"]);
    for k in [
        "scene", "model", "backend", "planes", "views", "per_view", "mean",
    ] {
        assert!(v.get(k).is_some(), "missing key {k}: {v}");
    }
    let per_view = v["per_view"].as_array().expect("per_view");
    assert_eq!(per_view.len(), 2);
    for (pv, target) in per_view.iter().zip([1, 4]) {
        assert_eq!(pv["target"], target);
        for k in ["name", "psnr", "ssim", "seconds"] {
            assert!(pv.get(k).is_some(), "missing per_view.{k}");
        }
        let psnr = pv["psnr"].as_f64().expect("psnr");
        assert!(psnr.is_finite() && psnr > 5.0, "psnr {psnr}");
        let ssim = pv["ssim"].as_f64().expect("ssim");
        assert!((-1.0..=1.0).contains(&ssim));
        assert!(pv["baselines"]["nearest"]["psnr"].as_f64().is_some());
        assert!(pv["baselines"]["plane_sweep"]["seconds"].as_f64().is_some());
    }
    let mean = &v["mean"];
    let avg = (per_view[0]["psnr"].as_f64().unwrap() + per_view[1]["psnr"].as_f64().unwrap()) / 2.0;
    assert!((mean["psnr"].as_f64().expect("mean psnr") - avg).abs() < 1e-6);
    assert!(mean["baselines"]["plane_sweep"]["ssim"].as_f64().is_some());
    // Pruning is on by default; `--prune off` is the plain renderer, with no prune stats.
    assert_eq!(v["prune"], "auto");
    assert!(per_view[0].get("prune").is_some());
    let v = eval_json(&s, "1", &["--planes", "8", "--prune", "off"]);
    assert_eq!(v["prune"], "off");
    assert!(v["per_view"][0].get("prune").is_none(), "{v}");
}

#[test]
fn report_writes_csv_markdown_and_plot() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let out = tmp.path().join("report");
    ok(&[
        "report",
        "--scene",
        &s.to_string_lossy(),
        "--holdout",
        "2",
        "--planes-grid",
        "4,8",
        "--prune-grid",
        "off",
        "--downscale-grid",
        "1,2",
        "--out",
        &out.to_string_lossy(),
    ]);
    let csv = std::fs::read_to_string(out.join("report.csv")).expect("report.csv");
    let rows: Vec<&str> = csv.lines().collect();
    // Header; the network and the plane sweep at 2 plane counts x 2 scales; nearest.
    assert_eq!(rows.len(), 10, "{csv}");
    assert_eq!(
        rows.iter()
            .filter(|r| r.starts_with("deepstereo-candle-1/2,"))
            .count(),
        2,
        "{csv}"
    );
    let cols = rows[0].split(',').count();
    assert!(rows.iter().all(|r| r.split(',').count() == cols), "{csv}");
    let md = std::fs::read_to_string(out.join("report.md")).expect("report.md");
    assert!(md.contains("| method |"), "{md}");
    let (w, h) = png_size(&out.join("report.png"));
    assert!(w > 100 && h > 100);
}

#[test]
fn demo_scores_the_embedded_model_against_both_baselines() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("demo");
    let res = ok(&["demo", "--size", "96x72", "--out", &out.to_string_lossy()]);
    for k in ["DeepStereo", "plane sweep", "nearest source"] {
        assert!(res.stdout.contains(k), "missing {k}:\n{}", res.stdout);
    }
    for png in ["image.png", "depth.png", "comparison.png"] {
        assert!(out.join(png).is_file(), "{png}");
    }
    assert_eq!(png_size(&out.join("image.png")), (96, 72));
    // Five panels, 4 px apart, under one strip of titles (at the font's size: "nearest
    // view" is too wide for 96 px at twice it).
    assert_eq!(
        png_size(&out.join("comparison.png")),
        (5 * 96 + 16, 72 + 15)
    );
}

#[test]
fn report_rejects_impossible_grids_by_name() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let out = tmp.path().join("report");
    for (opt, val) in [
        ("--downscale-grid", "3"),
        ("--planes-grid", "0"),
        ("--backends", "gpu"),
        ("--prune-grid", "sometimes"),
    ] {
        let res = run_deepstereo([
            "report",
            "--scene",
            &s.to_string_lossy(),
            "--holdout",
            "2",
            opt,
            val,
            "--out",
            &out.to_string_lossy(),
        ]);
        assert_ne!(res.code, Some(0), "{opt} {val} was accepted");
        assert!(!res.timed_out && res.code.is_some(), "{opt} {val}: crashed");
        assert!(
            res.stderr.contains(opt),
            "{opt} {val}: message does not name the option: {}",
            res.stderr
        );
        assert!(!res.stderr.contains("panicked"), "{}", res.stderr);
    }
}

#[test]
fn eval_with_pruning_reports_what_it_left_out() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let v = eval_json(&s, "3", &["--planes", "96", "--prune", "auto"]);
    assert_eq!(v["prune"], "auto");
    let pv = &v["per_view"][0];
    assert!(pv["psnr"].as_f64().expect("psnr").is_finite());
    let st = &pv["prune"];
    let run = st["planes_run"].as_u64().expect("planes_run");
    let total = st["planes_total"].as_u64().expect("planes_total");
    assert!(run > 0 && run < total, "{st}");
    for k in ["coarse_seconds", "warp_seconds", "network_seconds", "calls"] {
        assert!(st.get(k).is_some(), "missing prune.{k}: {st}");
    }
}

#[test]
fn fewer_source_views_than_the_model_takes_work_and_more_are_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let sd = s.to_string_lossy().into_owned();
    let v = eval_json(&s, "2", &["--planes", "8", "--views", "2"]);
    assert_eq!(v["views"], 2);
    assert!(v["per_view"][0]["psnr"].as_f64().expect("psnr").is_finite());
    // The embedded model takes any number of views: all 5 sources of the scene work, 6
    // (more than the scene has beside the target) and 0 are refused by name; the paper
    // family's `tiny` takes exactly 4, so 5 is refused there.
    let v = eval_json(&s, "2", &["--planes", "8", "--views", "5"]);
    assert_eq!(v["views"], 5);
    let tiny = deepstereo_tests::tiny_asset()
        .to_string_lossy()
        .into_owned();
    for (bad, model) in [("6", "embedded"), ("0", "embedded"), ("5", tiny.as_str())] {
        let res = run_deepstereo([
            "eval",
            "--scene",
            &sd,
            "--holdout",
            "2",
            "--planes",
            "8",
            "--views",
            bad,
            "--model",
            model,
        ]);
        assert_ne!(res.code, Some(0), "--views {bad} accepted by {model}");
        assert!(res.stderr.contains("--views"), "{}", res.stderr);
        assert!(!res.stderr.contains("panicked"), "{}", res.stderr);
    }
    // The report's views axis.
    let out = tmp.path().join("report");
    ok(&[
        "report",
        "--scene",
        &sd,
        "--holdout",
        "2",
        "--planes-grid",
        "8",
        "--views-grid",
        "1,4",
        "--prune-grid",
        "off",
        "--out",
        &out.to_string_lossy(),
    ]);
    let csv = std::fs::read_to_string(out.join("report.csv")).expect("report.csv");
    assert!(csv.contains("deepstereo-candle-1views,8,1,"), "{csv}");
    assert!(csv.contains("deepstereo-candle-4views,8,4,"), "{csv}");
}

#[test]
fn forward_refuses_inputs_without_planes() {
    use deepstereo_core::tensorio::{write_safetensors, NamedArray};
    let tmp = tempfile::tempdir().expect("tempdir");
    let inputs = tmp.path().join("empty.safetensors");
    // The embedded model (`nviews`: 3 levels, any views): level sizes of a tile of its
    // alignment for 4 views, but no planes.
    let cfg = deepstereo_core::config::Config::nviews();
    let t = cfg.tile_align();
    let arrays: Vec<NamedArray> = (0..cfg.levels)
        .map(|l| {
            let n = cfg.input_size(l, t);
            NamedArray::f32(&format!("level{l}"), &cfg.input_shape(1, 0, 4, n, n), &[])
        })
        .collect();
    write_safetensors(&inputs, &arrays, None).expect("write inputs");
    let out = tmp.path().join("out.safetensors");
    let res = run_deepstereo([
        "forward",
        "--inputs",
        &inputs.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
    ]);
    assert_ne!(res.code, Some(0), "inputs without planes were accepted");
    assert!(!res.timed_out && res.code.is_some(), "crashed");
    assert!(
        res.stderr.contains("level0") && res.stderr.contains("at least 1"),
        "{}",
        res.stderr
    );
    assert!(!res.stderr.contains("panicked"), "{}", res.stderr);
    assert!(!out.exists(), "an output was written");
}

#[test]
fn curve_plots_a_run_log_and_refuses_a_file_without_log_lines() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let log = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deepstereo-train/assets/readme/training_log.jsonl");
    let out = tmp.path().join("curve.png");
    ok(&[
        "curve",
        "--log",
        &log.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
    ]);
    let (w, h) = png_size(&out);
    assert!(w > 100 && h > 100);
    let bad = tmp.path().join("bad.jsonl");
    std::fs::write(&bad, "not a log\n{\"step\": \"x\"}\n").expect("write");
    let out2 = tmp.path().join("bad.png");
    let res = run_deepstereo([
        "curve",
        "--log",
        &bad.to_string_lossy(),
        "--out",
        &out2.to_string_lossy(),
    ]);
    assert_ne!(res.code, Some(0));
    assert!(
        res.stderr.contains("bad.jsonl") && res.stderr.contains("no training log lines"),
        "{}",
        res.stderr
    );
    assert!(!res.stderr.contains("panicked"), "{}", res.stderr);
    assert!(!out2.exists());
}

/// `train` refuses a missing --data directory, a --scene-weights name that is not one of
/// its scenes, an unreadable --init and a --resume without a checkpoint, by name, before
/// it creates --out.
#[test]
fn train_refuses_bad_data_before_writing_anything() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    ok(&[
        "synth",
        "--out",
        &data.to_string_lossy(),
        "--scenes",
        "1",
        "--size",
        "64x48",
        "--views",
        "6",
    ]);
    let out = tmp.path().join("run");
    let missing = tmp.path().join("missing");
    let init_missing = tmp
        .path()
        .join("absent.safetensors")
        .to_string_lossy()
        .to_string();
    let init_bad = tmp.path().join("bad.safetensors");
    std::fs::write(&init_bad, "not safetensors").expect("write");
    let init_bad = init_bad.to_string_lossy().to_string();
    for (data_dir, extra, says) in [
        (&missing, &[][..], vec!["missing", "not a directory"]),
        (
            &data,
            &["--scene-weights", "scene_9=2"][..],
            vec!["no training scene is named scene_9", "scene_0000"],
        ),
        (
            &data,
            &["--scene-weights", "scene_0000=-2"][..],
            vec!["must be above 0"],
        ),
        (
            &data,
            &["--init", &init_missing][..],
            vec!["--init", "cannot read"],
        ),
        (
            &data,
            &["--init", &init_bad][..],
            vec!["--init", "not a safetensors file"],
        ),
        (&data, &["--resume"][..], vec!["--resume", "cannot read"]),
        (&data, &["--mpi-loss", "0"][..], vec!["MPI loss weight"]),
        (&data, &["--mpi-loss", "nan"][..], vec!["MPI loss weight"]),
        (
            &data,
            &["--mpi-loss", "1", "--mpi-tile", "64x33"][..],
            vec!["MPI tile's sides must be multiples of"],
        ),
        (
            &data,
            &["--mpi-loss", "1", "--mpi-neighbours", "0"][..],
            vec!["nearest views"],
        ),
        (
            &data,
            &["--mpi-loss", "1", "--mpi-scale", "3"][..],
            vec!["scale is 1 or 2"],
        ),
        (
            &data,
            &[
                "--mpi-loss",
                "1",
                "--mpi-scale",
                "2",
                "--mpi-tile",
                "96x64",
                "--synthetic",
                "2",
                "--synth-size",
                "160x120",
            ][..],
            vec!["smaller than the 96x64 MPI tile at scale 2"],
        ),
        (
            &data,
            &["--mpi-loss", "1", "--augment"][..],
            vec!["MPI loss takes neither augmentation"],
        ),
        (
            &data,
            &[
                "--mpi-loss",
                "1",
                "--synthetic",
                "2",
                "--synth-size",
                "160x120",
            ][..],
            vec!["smaller than the 224x64 MPI tile"],
        ),
    ] {
        let mut args = vec![
            "train".to_string(),
            "--config".into(),
            "tiny".into(),
            "--data".into(),
            data_dir.to_string_lossy().into(),
            "--steps".into(),
            "1".into(),
            "--out".into(),
            out.to_string_lossy().into(),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        let res = run_deepstereo(&args);
        assert_eq!(res.code, Some(1), "{extra:?}: {}", res.stderr);
        for s in says {
            assert!(res.stderr.contains(s), "{extra:?}: {}", res.stderr);
        }
        assert!(!out.exists(), "{extra:?}: --out was created");
    }
}

/// `render`'s report of its sources: the network's, and those only pruning's coarse pass
/// read (empty when none).
fn render_sources(args: &[&str]) -> (Vec<usize>, Vec<usize>) {
    let res = ok(args);
    let list = |s: &str| -> Vec<usize> {
        let inner = s.split('[').nth(1).and_then(|s| s.split(']').next());
        let inner = inner.unwrap_or_else(|| panic!("no list in {s:?}"));
        inner
            .split(", ")
            .map(|v| v.parse().expect("index"))
            .collect()
    };
    let line = res.stderr.lines().find(|l| l.starts_with("rendered "));
    let line = line.unwrap_or_else(|| panic!("no render line: {}", res.stderr));
    let network = list(line.split("from views").nth(1).expect("views"));
    let plan = match line.split("chosen with views").nth(1) {
        Some(rest) => list(rest),
        None => Vec::new(),
    };
    (network, plan)
}

#[test]
fn pruning_chooses_the_planes_with_more_views_than_the_network_reads() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let sd = s.to_string_lossy().into_owned();
    let out = |name: &str| tmp.path().join(name).to_string_lossy().into_owned();
    let base = [
        "render", "--scene", &sd, "--target", "2", "--planes", "8", "--views", "2",
    ];
    let run = |name: &str, extra: &[&str]| {
        let o = out(name);
        let sources = render_sources(&[&base[..], extra, &["--out", &o]].concat());
        (
            sources,
            read_npy_f32(&tmp.path().join(name).join("image.npy")),
        )
    };
    // Every view but the target: the network's two, then the other three.
    let ((network, plan), more) = run("more", &["--prune-views", "8"]);
    assert_eq!((network.len(), plan.len()), (2, 3), "{network:?} {plan:?}");
    let mut all: Vec<usize> = network.iter().chain(&plan).copied().collect();
    all.sort();
    assert_eq!(all, vec![0, 1, 3, 4, 5]);
    assert!(more.1.iter().all(|v| v.is_finite()));
    // No more than the network's: the renderer that reads only them, to the bit.
    let ((n0, p0), none) = run("none", &["--prune-views", "0"]);
    let ((n2, p2), two) = run("two", &["--prune-views", "2"]);
    assert_eq!((&n0, &n2), (&network, &network));
    assert!(p0.is_empty() && p2.is_empty());
    assert!(none == two, "--prune-views 0 and 2 differ at 2 views");
    // The coarse pass's planes decide what the network runs: more views change them.
    assert!(
        more.1 != none.1,
        "the same image with and without more views"
    );
    // Without pruning there is no coarse pass.
    let ((_, off_plan), off_more) = run("off_more", &["--prune", "off", "--prune-views", "8"]);
    let (_, off) = run("off", &["--prune", "off"]);
    assert!(off_plan.is_empty());
    assert!(
        off_more == off,
        "--prune-views changed the render without pruning"
    );
    // eval never reads a held-out view, in the coarse pass either.
    let v = eval_json(
        &s,
        "1,4",
        &["--planes", "8", "--views", "2", "--prune-views", "8"],
    );
    for pv in v["per_view"].as_array().expect("per_view") {
        let ids = |k: &str| -> Vec<u64> {
            pv[k].as_array().map_or(Vec::new(), |a| {
                a.iter().filter_map(|x| x.as_u64()).collect()
            })
        };
        let (n, p) = (ids("sources"), ids("plan_sources"));
        assert_eq!((n.len(), p.len()), (2, 2), "{pv}");
        assert!(n.iter().chain(&p).all(|i| ![1, 4].contains(i)), "{pv}");
    }
    // Planes too close for the network's own views are thinned as without the others
    // (their wider baselines would keep more).
    let thinned = |plan: &str| -> Vec<serde_json::Value> {
        let v = eval_json(
            &s,
            "1,4",
            &["--planes", "96", "--views", "2", "--prune-views", plan],
        );
        let views = v["per_view"].as_array().expect("per_view").clone();
        views
            .iter()
            .map(|pv| pv["prune"]["thinned"].clone())
            .collect()
    };
    let own = thinned("0");
    assert!(own.iter().all(|t| t[1].as_u64() < Some(96)), "{own:?}");
    assert_eq!(thinned("8"), own);
}
