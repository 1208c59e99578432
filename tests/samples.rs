//! `deepstereo samples`: the same seed gives the same shards (tensors and metadata), and a
//! rerun keeps complete shards and writes again only the missing or broken ones.

use deepstereo_tests::*;
use serde_json::Value;
use std::path::Path;

/// 5 samples in shards of 2: three shards (2, 2, 1).
const SHARDS: usize = 3;

/// `deepstereo samples` with this file's options (5 tiny samples in shards of 2, seed 3)
/// and `extra` ones, into `out`.
fn run_samples(out: &Path, extra: &[&str]) -> CmdOutput {
    let out = out.to_string_lossy();
    let mut args = vec![
        "samples",
        "--synthetic",
        "2",
        "--synth-size",
        "64x48",
        "--synth-views",
        "6",
        "--config",
        "tiny",
        "--count",
        "5",
        "--shard-size",
        "2",
        "--seed",
        "3",
        "--out",
        &out,
    ];
    args.extend_from_slice(extra);
    run_deepstereo(args)
}

fn samples(out: &Path) -> CmdOutput {
    let res = run_samples(out, &[]);
    assert_eq!(res.code, Some(0), "samples failed: {}", res.stderr);
    res
}

fn metadata(path: &Path) -> Value {
    let bytes = std::fs::read(path).expect("read shard");
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
    let header: Value = serde_json::from_slice(&bytes[8..8 + n]).expect("header JSON");
    header["__metadata__"].clone()
}

fn shard(dir: &Path, i: usize) -> std::path::PathBuf {
    dir.join(format!("shard-{i:05}.safetensors"))
}

fn assert_same_shards(a: &Path, b: &Path) {
    for i in 0..SHARDS {
        let (x, y) = (
            read_safetensors(&shard(a, i)),
            read_safetensors(&shard(b, i)),
        );
        assert_eq!(
            x.keys().collect::<Vec<_>>(),
            ["level0", "level1", "target"],
            "shard {i}"
        );
        for (name, t) in &x {
            assert_eq!(t.shape, y[name].shape, "shard {i} {name}");
            assert!(t.bytes == y[name].bytes, "shard {i}: '{name}' differs");
            assert_eq!(t.shape[0], if i + 1 < SHARDS { 2 } else { 1 });
        }
        assert_eq!(metadata(&shard(a, i)), metadata(&shard(b, i)), "shard {i}");
    }
}

#[test]
fn same_seed_same_shards_and_reruns_keep_complete_ones() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    samples(&a);
    samples(&b);
    assert_same_shards(&a, &b);
    let m = metadata(&shard(&a, 1));
    assert_eq!(m["format"], "deepstereo-samples-v1");
    assert_eq!(m["views"], "4");
    assert_eq!(m["shard"], "1");
    let cfg: Value = serde_json::from_str(m["deepstereo.config"].as_str().expect("config"))
        .expect("config JSON");
    assert_eq!(cfg["name"], "tiny");
    // Different shards hold different samples.
    let (s0, s1) = (
        read_safetensors(&shard(&a, 0)),
        read_safetensors(&shard(&a, 1)),
    );
    assert!(s0["target"].bytes != s1["target"].bytes);

    // A rerun with everything in place writes nothing.
    let before: Vec<_> = (0..SHARDS)
        .map(|i| {
            std::fs::metadata(shard(&a, i))
                .and_then(|m| m.modified())
                .expect("mtime")
        })
        .collect();
    let res = samples(&a);
    assert!(res.stderr.contains("all 3 shards"), "{}", res.stderr);
    for (i, t) in before.iter().enumerate() {
        let now = std::fs::metadata(shard(&a, i))
            .and_then(|m| m.modified())
            .expect("mtime");
        assert_eq!(*t, now, "shard {i} was rewritten");
    }

    // A missing and a truncated shard are written again; the complete one is kept.
    std::fs::remove_file(shard(&a, 0)).expect("remove");
    let bytes = std::fs::read(shard(&a, 2)).expect("read");
    std::fs::write(shard(&a, 2), &bytes[..bytes.len() / 2]).expect("truncate");
    let res = samples(&a);
    assert!(
        res.stderr.contains("writing 2 of 3 shards (1 complete)"),
        "{}",
        res.stderr
    );
    let kept = std::fs::metadata(shard(&a, 1))
        .and_then(|m| m.modified())
        .expect("mtime");
    assert_eq!(kept, before[1], "the complete shard was rewritten");
    assert_same_shards(&a, &b);
    for e in std::fs::read_dir(&a).expect("dir") {
        let name = e.expect("entry").file_name().to_string_lossy().into_owned();
        assert!(!name.contains(".tmp"), "left over: {name}");
    }
}

#[test]
fn other_options_into_the_same_directory_are_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let a = tmp.path().join("a");
    samples(&a);
    let res = run_deepstereo([
        "samples",
        "--synthetic",
        "2",
        "--synth-size",
        "64x48",
        "--synth-views",
        "6",
        "--count",
        "5",
        "--shard-size",
        "2",
        "--seed",
        "4",
        "--out",
        &a.to_string_lossy(),
    ]);
    assert_eq!(res.code, Some(1), "{}", res.stderr);
    assert!(res.stderr.contains("other options"), "{}", res.stderr);
}

/// `--view-stride` is part of what a shard is made with (a rerun with another stride into
/// the same directory is refused), and impossible strides and flat-tile thresholds are
/// refused by name.
#[test]
fn view_stride_is_an_option_of_the_shards() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let a = tmp.path().join("a");
    samples(&a);
    let with_stride = |stride: &str, out: &Path| run_samples(out, &["--view-stride", stride]);
    let res = with_stride("2", &a);
    assert_eq!(res.code, Some(1), "{}", res.stderr);
    assert!(res.stderr.contains("other options"), "{}", res.stderr);
    let b = tmp.path().join("b");
    assert_eq!(with_stride("1", &b).code, Some(0));
    assert_same_shards(&a, &b);
    for bad in ["-1", "0.9", "nan"] {
        let res = run_deepstereo([
            "samples",
            "--synthetic",
            "1",
            "--count",
            "1",
            &format!("--skip-flat={bad}"),
            "--out",
            &tmp.path().join("d").to_string_lossy(),
        ]);
        assert_eq!(res.code, Some(1), "{bad}: {}", res.stderr);
        assert!(res.stderr.contains("flat"), "{bad}: {}", res.stderr);
    }
    for bad in ["0", "3-2", "x", "1-99"] {
        let res = with_stride(bad, &tmp.path().join("c"));
        assert_eq!(res.code, Some(1), "{bad}: {}", res.stderr);
        assert!(
            res.stderr.contains("view stride") || res.stderr.contains("--view-stride"),
            "{bad}: {}",
            res.stderr
        );
    }
}

/// `--scene-weights` is part of what a shard is made with; names that are not scenes of
/// `--data`, and impossible weights, are refused by name before anything is written.
#[test]
fn scene_weights_are_an_option_of_the_shards() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let res = run_deepstereo([
        "synth",
        "--out",
        &data.to_string_lossy(),
        "--scenes",
        "2",
        "--size",
        "64x48",
        "--views",
        "6",
    ]);
    assert_eq!(res.code, Some(0), "synth failed: {}", res.stderr);
    let data_arg = data.to_string_lossy().to_string();
    let with = |weights: &str, out: &Path| {
        run_samples(
            out,
            &[
                "--data",
                &data_arg,
                "--scene-weights",
                weights,
                "--synthetic-percent",
                "50",
            ],
        )
    };
    let a = tmp.path().join("a");
    let res = with("scene_0001=4", &a);
    assert_eq!(res.code, Some(0), "{}", res.stderr);
    let opts: Value = serde_json::from_str(
        metadata(&shard(&a, 0))["deepstereo.samples"]
            .as_str()
            .expect("sample options in the metadata"),
    )
    .expect("options JSON");
    assert_eq!(
        opts["scene_weights"],
        serde_json::json!([["scene_0001", 4.0]])
    );
    let res = with("scene_0001=2", &a);
    assert_eq!(res.code, Some(1), "{}", res.stderr);
    assert!(res.stderr.contains("other options"), "{}", res.stderr);
    for (bad, says) in [
        ("nope=2", "no training scene is named nope"),
        ("scene_0001=0", "must be above 0"),
        ("scene_0001", "NAME=WEIGHT"),
    ] {
        let out = tmp.path().join("bad");
        let res = with(bad, &out);
        assert_eq!(res.code, Some(1), "{bad}: {}", res.stderr);
        assert!(res.stderr.contains(says), "{bad}: {}", res.stderr);
        assert!(!shard(&out, 0).exists(), "{bad}: a shard was written");
    }
}
