//! Whole-network speed against onnxruntime and PyTorch, in one run on one machine and on
//! the same weights and inputs (issue 9's acceptance figures):
//!
//! - **forward** of one render tile (`B = 1`, the preset's planes, a 64-pixel tile for
//!   `tiny`, 32 for `paper`): candle (`DeepStereo::infer`, the renderer's path: this
//!   crate's conv kernels, the depth layers and a 1x1 colour tower fused), onnxruntime
//!   through `ort` on the exported graph (thread spinning off, as the renderer runs it),
//!   onnxruntime from Python on the same file (its defaults), and PyTorch
//!   (`python/deepstereo_ref.py`, `torch.no_grad`); the ratio printed takes the faster
//!   onnxruntime;
//! - **training step** on a training batch from procedural scenes (forward, L1 loss,
//!   backward, Adam update): candle against PyTorch.
//!
//! Threads: Rust uses all cores (rayon), PyTorch `torch.set_num_threads(cores)`,
//! onnxruntime its default (one per core). Times are the best of several runs (the machine
//! may be shared). GFLOP/s count 2 x multiply-adds of the convolutions as written (the
//! config's cost model, the same for every runtime) and are set against a 2048^2 f32
//! matmul measured in the same run; candle's Winograd layers do fewer products than that
//! count, so its figure can pass the matmul's (and the machine's peak). The
//! Python side also checks that its outputs match candle's (same model, same inputs).
//!
//! `cargo bench -p deepstereo-train --bench network`; `NET_BENCH_CONFIGS=tiny` picks
//! presets; without the workspace's `.venv` only the Rust side runs.

use anyhow::{bail, Context, Result};
use candle_core::{DType, Device, Tensor};
use deepstereo_core::config::Config;
use deepstereo_core::model::l1_loss;
use deepstereo_core::synth::SynthOptions;
use deepstereo_core::tensorio::{write_safetensors, NamedArray};
use deepstereo_core::weights::{init_seeded, named_vars, save, tensor_f32};
use deepstereo_export::export::{export_trainable, input_name, DEFAULT_OPSET};
use deepstereo_export::OrtBackend;
use deepstereo_train::data::{make_batch, synth_scenes};
use deepstereo_train::optim::{Optimizer, OptimizerKind};
use deepstereo_train::training::batch_tensors;
use std::path::Path;
use std::time::Instant;

/// Best seconds of `f`: one warm-up run, then 2..=12 runs within `budget_s`.
fn timed(budget_s: f64, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    let t = Instant::now();
    f()?;
    let first = t.elapsed().as_secs_f64();
    let reps = ((budget_s / first) as usize).clamp(2, 12);
    let mut best = f64::MAX;
    for _ in 0..reps {
        let t = Instant::now();
        f()?;
        best = best.min(t.elapsed().as_secs_f64());
    }
    Ok(best)
}

/// Best seconds of `a` and of `b`, run alternately (one warm-up each, then 3..=30
/// rounds within `budget_s`: the shared machine's times spread by +-30%, so the best of
/// many is the steadier figure).
fn interleaved(
    budget_s: f64,
    mut a: impl FnMut() -> Result<()>,
    mut b: impl FnMut() -> Result<()>,
) -> Result<(f64, f64)> {
    let t = Instant::now();
    a()?;
    b()?;
    let rounds = ((budget_s / t.elapsed().as_secs_f64()) as usize).clamp(3, 30);
    let (mut best_a, mut best_b) = (f64::MAX, f64::MAX);
    for _ in 0..rounds {
        let t = Instant::now();
        a()?;
        best_a = best_a.min(t.elapsed().as_secs_f64());
        let t = Instant::now();
        b()?;
        best_b = best_b.min(t.elapsed().as_secs_f64());
    }
    Ok((best_a, best_b))
}

fn matmul_gflops() -> Result<f64> {
    let a = Tensor::randn(0f32, 1., (2048, 2048), &Device::Cpu)?;
    let b = Tensor::randn(0f32, 1., (2048, 2048), &Device::Cpu)?;
    let s = timed(1.0, || Ok(a.matmul(&b).map(drop)?))?;
    Ok(2.0 * 2048f64.powi(3) / s * 1e-9)
}

/// Deterministic inputs in [0, 1) of the render tile: `[1, D, 4V, H_l, W_l]` per level.
fn tile_inputs(cfg: &Config, tile: usize) -> Vec<(Vec<usize>, Vec<f32>)> {
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    (0..cfg.levels)
        .map(|l| {
            let s = cfg.input_size(l, tile);
            let shape = vec![1, cfg.planes, cfg.in_channels(), s, s];
            let data = (0..shape.iter().product::<usize>())
                .map(|_| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    (state >> 40) as f32 / (1u64 << 24) as f32
                })
                .collect();
            (shape, data)
        })
        .collect()
}

fn arrays(levels: &[(Vec<usize>, Vec<f32>)]) -> Vec<NamedArray> {
    levels
        .iter()
        .enumerate()
        .map(|(l, (s, d))| NamedArray::f32(&input_name(l), s, d))
        .collect()
}

struct PyTimes {
    torch_fwd: f64,
    torch_step: f64,
    ort_py_fwd: f64,
    max_diff: f64,
}

/// `python/bench_network.py` on the files in `dir`, or `None` without the venv.
fn python(dir: &Path, threads: usize) -> Result<Option<PyTimes>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let py = root.join(".venv/bin/python");
    if !py.is_file() {
        eprintln!("note: no .venv (run `bash tests/run-all.sh` once): PyTorch and Python onnxruntime skipped");
        return Ok(None);
    }
    let out = std::process::Command::new(py)
        .arg(root.join("python/bench_network.py"))
        .arg(dir)
        .arg(threads.to_string())
        .output()
        .context("running python/bench_network.py")?;
    if !out.status.success() {
        bail!(
            "python/bench_network.py failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout)
        .with_context(|| format!("bench_network.py: {}", String::from_utf8_lossy(&out.stdout)))?;
    let get = |k: &str| {
        v[k].as_f64()
            .with_context(|| format!("bench_network.py: no {k}"))
    };
    Ok(Some(PyTimes {
        torch_fwd: get("torch_fwd_s")?,
        torch_step: get("torch_step_s")?,
        ort_py_fwd: get("ort_fwd_s")?,
        max_diff: get("max_abs_diff")?,
    }))
}

fn bench(name: &str, mm: f64, threads: usize) -> Result<()> {
    let cfg = Config::preset(name).with_context(|| format!("unknown preset {name}"))?;
    let (tile, batch) = if name == "paper" { (32, 1) } else { (64, 8) };
    let dir = tempfile::tempdir()?;
    let t = init_seeded(&cfg, DType::F32, &Device::Cpu, 0)?;
    save(&dir.path().join("weights.safetensors"), &cfg, &t.varmap)?;
    let onnx = export_trainable(&t, DEFAULT_OPSET)?;
    std::fs::write(dir.path().join("model.onnx"), &onnx)?;

    // Forward of one render tile.
    let levels = tile_inputs(&cfg, tile);
    write_safetensors(&dir.path().join("tile.safetensors"), &arrays(&levels), None)?;
    let xs: Vec<Tensor> = levels
        .iter()
        .map(|(s, d)| Tensor::from_slice(d, s.as_slice(), &Device::Cpu))
        .collect::<candle_core::Result<_>>()?;
    let image = t.model.infer(&xs)?.image;
    let shape = image.dims().to_vec();
    let out = vec![NamedArray::f32("image", &shape, &tensor_f32(&image)?)];
    write_safetensors(&dir.path().join("candle.safetensors"), &out, None)?;
    let ort = OrtBackend::from_bytes(&onnx)?;
    let views: Vec<(&[usize], &[f32])> = levels
        .iter()
        .map(|(s, d)| (s.as_slice(), d.as_slice()))
        .collect();
    // Candle and ort alternate, so that a change in the shared machine's load hits both.
    let (fwd, ort_fwd) = interleaved(
        12.0,
        || {
            Ok(t.model
                .infer(&xs)?
                .image
                .flatten_all()?
                .to_vec1::<f32>()
                .map(drop)?)
        },
        || Ok(ort.forward(&views).map(drop)?),
    )?;

    // One training step on a batch of procedural patches.
    let opts = SynthOptions {
        views: 8,
        width: 160,
        height: 120,
        ..SynthOptions::default()
    };
    let scenes = synth_scenes(4, 1, &opts, cfg.levels)?;
    let b = make_batch(&cfg, &scenes, 9, 0, batch)?;
    let (x, y) = batch_tensors(&b, &Device::Cpu)?;
    let mut train_arrays: Vec<NamedArray> = b
        .levels
        .iter()
        .zip(&b.level_shapes)
        .enumerate()
        .map(|(l, (d, s))| NamedArray::f32(&input_name(l), s, d))
        .collect();
    train_arrays.push(NamedArray::f32("target", &b.target_shape, &b.target));
    write_safetensors(&dir.path().join("batch.safetensors"), &train_arrays, None)?;
    let mut opt = Optimizer::new(OptimizerKind::Adam, 1e-4, named_vars(&t.varmap))?;
    let step = timed(8.0, || {
        let loss = l1_loss(&t.model.forward(&x)?.image, &y)?;
        let grads = loss.backward()?;
        opt.step(&grads)
    })?;

    let py = python(dir.path(), threads)?;
    // The config's cost model counts multiply-adds per output pixel of a `cfg.tile` tile
    // (the borders the convolutions need included); the render tile has its own.
    let at_tile = Config {
        tile,
        ..cfg.clone()
    };
    let fwd_flop = 2.0 * at_tile.macs_per_pixel() * (tile * tile) as f64;
    let step_flop = 3.0 * 2.0 * cfg.macs_per_pixel() * (cfg.tile * cfg.tile * batch) as f64;
    let gf = |flop: f64, s: f64| flop / s * 1e-9;
    println!(
        "\n{name}: forward of a {tile}x{tile} tile, {} planes, {} views ({:.2} GFLOP); training step: batch {batch}, {}x{} patches (~{:.2} GFLOP)",
        cfg.planes, cfg.views, fwd_flop * 1e-9, cfg.tile, cfg.tile, step_flop * 1e-9
    );
    println!(
        "| what | runtime | ms | GFLOP/s | of matmul ({mm:.0} GFLOP/s) | its time / candle's |"
    );
    println!("|---|---|---|---|---|---|");
    let row = |what: &str, rt: &str, s: f64, flop: f64, ours: f64| {
        println!(
            "| {what} | {rt} | {:.1} | {:.1} | {:.0}% | {:.2}x |",
            s * 1e3,
            gf(flop, s),
            100.0 * gf(flop, s) / mm,
            s / ours
        );
    };
    row("forward", "candle", fwd, fwd_flop, fwd);
    row("forward", "onnxruntime (ort, Rust)", ort_fwd, fwd_flop, fwd);
    if let Some(p) = &py {
        row(
            "forward",
            "onnxruntime (Python)",
            p.ort_py_fwd,
            fwd_flop,
            fwd,
        );
        row("forward", "PyTorch", p.torch_fwd, fwd_flop, fwd);
    }
    row("training step", "candle", step, step_flop, step);
    if let Some(p) = &py {
        row("training step", "PyTorch", p.torch_step, step_flop, step);
        println!(
            "outputs: PyTorch and onnxruntime vs candle, max abs difference {:.1e}",
            p.max_diff
        );
        println!(
            "RATIO {name}: candle's speed relative to onnxruntime's forward {:.2}, to PyTorch's training step {:.2} (issue 9 asks for >= 1)",
            ort_fwd.min(p.ort_py_fwd) / fwd,
            p.torch_step / step
        );
    }
    Ok(())
}

fn main() -> Result<()> {
    // As the `deepstereo` binary does (PyTorch and onnxruntime keep their own pools).
    deepstereo_train::alloc::tune_allocator();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let configs = std::env::var("NET_BENCH_CONFIGS").unwrap_or_else(|_| "tiny,paper".into());
    let mm = matmul_gflops()?;
    println!("{threads} threads; candle 2048^2 f32 matmul {mm:.1} GFLOP/s");
    for name in configs.split(',') {
        bench(name.trim(), mm, threads)?;
    }
    Ok(())
}
