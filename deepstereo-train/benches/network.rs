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
//! onnxruntime its default (one per core). The runtimes take turns, round after round, each
//! turn two runs back to back (the Python side is a server process that waits 0.3 s after
//! each turn, so that spinning worker threads are idle when the next runtime starts), and
//! each figure is its best run: the machine's speed drifts over minutes, and turns make a
//! drift hit all of them alike. GFLOP/s count 2 x multiply-adds of the convolutions as written (the
//! config's cost model, the same for every runtime) and are set against a 2048^2 f32
//! matmul measured in the same run; candle's Winograd layers do fewer products than that
//! count, so its figure can pass the matmul's (and the machine's peak). The
//! Python side also checks that its outputs match candle's (same model, same inputs).
//!
//! `cargo bench -p deepstereo-train --bench network`; `NET_BENCH_CONFIGS=tiny,nviews` picks
//! presets; without the workspace's `.venv` only the Rust side runs.

use anyhow::{bail, Context, Result};
use candle_core::{DType, Device, Tensor};
use deepstereo_core::config::Config;
use deepstereo_core::model::l1_loss;
use deepstereo_core::tensorio::{write_safetensors, NamedArray};
use deepstereo_core::weights::{init_seeded, named_vars, save, tensor_f32, Trainable};
use deepstereo_export::export::{export_trainable, input_name, DEFAULT_OPSET};
use deepstereo_export::OrtBackend;
use deepstereo_train::training::data::Batch;
use deepstereo_train::training::optim::{Optimizer, OptimizerKind};
use deepstereo_train::training::{batch_tensors, procedural_batch};
use std::path::Path;
use std::time::Instant;

/// Calls per turn of a runtime, back to back (the best counts: the later calls run with
/// warm caches and awake worker threads, whatever ran before the turn).
const REPEAT: usize = 2;

/// Best seconds of [`REPEAT`] calls of `f` in a row.
fn seconds(mut f: impl FnMut() -> Result<()>) -> impl FnMut() -> Result<f64> {
    move || {
        let mut best = f64::MAX;
        for _ in 0..REPEAT {
            let t = Instant::now();
            f()?;
            best = best.min(t.elapsed().as_secs_f64());
        }
        Ok(best)
    }
}

/// Best seconds of each of `runs` (each returns its own time), run in turn round after
/// round: one warm-up round, then 3..=30 rounds within `budget_s`. The shared machine's
/// speed drifts by tens of percent over minutes; alternating makes a drift hit every
/// runtime alike, and the best of many rounds is the steadier figure.
fn alternate(budget_s: f64, runs: &mut [&mut dyn FnMut() -> Result<f64>]) -> Result<Vec<f64>> {
    let t = Instant::now();
    for r in runs.iter_mut() {
        r()?;
    }
    let rounds = ((budget_s / t.elapsed().as_secs_f64()) as usize).clamp(3, 30);
    let mut best = vec![f64::MAX; runs.len()];
    for _ in 0..rounds {
        for (r, b) in runs.iter_mut().zip(best.iter_mut()) {
            *b = b.min(r()?);
        }
    }
    Ok(best)
}

fn matmul_gflops() -> Result<f64> {
    let a = Tensor::randn(0f32, 1., (2048, 2048), &Device::Cpu)?;
    let b = Tensor::randn(0f32, 1., (2048, 2048), &Device::Cpu)?;
    let mut mm = seconds(|| Ok(a.matmul(&b).map(drop)?));
    let s = alternate(1.0, &mut [&mut mm])?[0];
    Ok(2.0 * 2048f64.powi(3) / s * 1e-9)
}

/// Deterministic inputs in [0, 1) of the render tile: `[1, D, 4V, H_l, W_l]` (or
/// `[1, D, V, 4, H_l, W_l]`) per level, with the config's default views.
fn tile_inputs(cfg: &Config, tile: usize) -> Vec<(Vec<usize>, Vec<f32>)> {
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    (0..cfg.levels)
        .map(|l| {
            let s = cfg.input_size(l, tile);
            let shape = cfg.input_shape(1, cfg.planes, cfg.views, s, s);
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

/// A training batch's inputs per level and its target, named as the Python side reads
/// them.
fn batch_arrays(b: &Batch) -> Vec<NamedArray> {
    let mut out: Vec<NamedArray> = b
        .levels
        .iter()
        .zip(&b.level_shapes)
        .enumerate()
        .map(|(l, (d, s))| NamedArray::f32(&input_name(l), s, d))
        .collect();
    out.push(NamedArray::f32("target", &b.target_shape, &b.target));
    out
}

fn arrays(levels: &[(Vec<usize>, Vec<f32>)]) -> Vec<NamedArray> {
    levels
        .iter()
        .enumerate()
        .map(|(l, (s, d))| NamedArray::f32(&input_name(l), s, d))
        .collect()
}

/// `python/bench_network.py` serving timed PyTorch and onnxruntime runs on the files in
/// a directory (see its documentation).
struct Python {
    child: std::process::Child,
    input: std::process::ChildStdin,
    output: std::io::BufReader<std::process::ChildStdout>,
    /// Largest difference of PyTorch's and onnxruntime's images from candle's.
    max_diff: f64,
}

impl Python {
    /// Starts the server, or `None` without the workspace's venv.
    fn start(dir: &Path, threads: usize) -> Result<Option<Self>> {
        use std::process::{Command, Stdio};
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let py = root.join(".venv/bin/python");
        if !py.is_file() {
            eprintln!("note: no .venv (run `bash tests/run-all.sh` once): PyTorch and Python onnxruntime skipped");
            return Ok(None);
        }
        let mut child = Command::new(py)
            .arg(root.join("python/bench_network.py"))
            .arg(dir)
            .arg(threads.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .context("running python/bench_network.py")?;
        let (Some(input), Some(out)) = (child.stdin.take(), child.stdout.take()) else {
            bail!("python/bench_network.py: no pipes");
        };
        let mut py = Self {
            child,
            input,
            output: std::io::BufReader::new(out),
            max_diff: f64::NAN,
        };
        let v: serde_json::Value = serde_json::from_str(&py.line()?)
            .context("python/bench_network.py: first line is not JSON")?;
        py.max_diff = v["max_abs_diff"]
            .as_f64()
            .context("python/bench_network.py: no max_abs_diff")?;
        Ok(Some(py))
    }

    fn line(&mut self) -> Result<String> {
        use std::io::BufRead;
        let mut s = String::new();
        if self.output.read_line(&mut s)? == 0 {
            bail!("python/bench_network.py ended early (its error is above)");
        }
        Ok(s)
    }

    /// Best seconds of [`REPEAT`] `cmd` runs in a row on the Python side.
    fn time(&mut self, cmd: &str) -> Result<f64> {
        use std::io::Write;
        writeln!(self.input, "{cmd} {REPEAT}")?;
        self.input.flush()?;
        let s = self.line()?;
        s.trim()
            .parse()
            .with_context(|| format!("bench_network.py answered {s:?} to {cmd}"))
    }
}

impl Drop for Python {
    fn drop(&mut self) {
        use std::io::Write;
        let _ = writeln!(self.input, "quit");
        let _ = self.input.flush();
        let _ = self.child.wait();
    }
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
    let xs = write_tile(dir.path(), &t, &levels)?;
    let ort = OrtBackend::from_bytes(&onnx)?;
    let views: Vec<(&[usize], &[f32])> = levels
        .iter()
        .map(|(s, d)| (s.as_slice(), d.as_slice()))
        .collect();

    // One training step on a batch of procedural patches.
    let b = procedural_batch(&cfg, batch)?;
    let (x, y) = batch_tensors(&t.model, &b, &Device::Cpu)?;
    write_safetensors(
        &dir.path().join("batch.safetensors"),
        &batch_arrays(&b),
        None,
    )?;
    let mut opt = Optimizer::new(OptimizerKind::Adam, 1e-4, named_vars(&t.varmap))?;

    // Every runtime in turn, round after round (see `alternate`).
    let mut py = Python::start(dir.path(), threads)?;
    let mut candle_fwd = seconds(|| {
        Ok(t.model
            .infer(&xs)?
            .image
            .flatten_all()?
            .to_vec1::<f32>()
            .map(drop)?)
    });
    let mut ort_fwd = seconds(|| Ok(ort.forward(&views).map(drop)?));
    let mut candle_step = seconds(|| {
        let loss = l1_loss(&x.forward(&t.model)?.image, &y)?;
        let grads = loss.backward()?;
        opt.step(&grads)
    });
    let (fwd, ort_fwd, py_fwd, step, py_step) = match py.as_mut() {
        Some(p) => {
            let p = std::cell::RefCell::new(p);
            let mut ort_py = || p.borrow_mut().time("ort_fwd");
            let mut torch_fwd = || p.borrow_mut().time("torch_fwd");
            let f = alternate(
                12.0,
                &mut [&mut candle_fwd, &mut ort_fwd, &mut ort_py, &mut torch_fwd],
            )?;
            let mut torch_step = || p.borrow_mut().time("torch_step");
            let s = alternate(12.0, &mut [&mut candle_step, &mut torch_step])?;
            (f[0], f[1], Some((f[2], f[3])), s[0], Some(s[1]))
        }
        None => {
            let f = alternate(12.0, &mut [&mut candle_fwd, &mut ort_fwd])?;
            let s = alternate(8.0, &mut [&mut candle_step])?;
            (f[0], f[1], None, s[0], None)
        }
    };

    let max_diff = py.as_ref().map(|p| p.max_diff);
    let times = Times {
        fwd,
        ort_fwd,
        py_fwd,
        step,
        py_step,
    };
    print_table(name, &cfg, (tile, batch), mm, &times, max_diff);
    Ok(())
}

/// Writes the tile's inputs `levels` and candle's image of them into `dir` (for the
/// Python side); the inputs as tensors.
fn write_tile(dir: &Path, t: &Trainable, levels: &[(Vec<usize>, Vec<f32>)]) -> Result<Vec<Tensor>> {
    write_safetensors(&dir.join("tile.safetensors"), &arrays(levels), None)?;
    let xs: Vec<Tensor> = levels
        .iter()
        .map(|(s, d)| Tensor::from_slice(d, s.as_slice(), &Device::Cpu))
        .collect::<candle_core::Result<_>>()?;
    let image = t.model.infer(&xs)?.image;
    let shape = image.dims().to_vec();
    let out = vec![NamedArray::f32("image", &shape, &tensor_f32(&image)?)];
    write_safetensors(&dir.join("candle.safetensors"), &out, None)?;
    Ok(xs)
}

/// Best seconds of each runtime: candle's forward, onnxruntime's (Rust), onnxruntime's
/// (Python) and PyTorch's forward, candle's training step and PyTorch's.
struct Times {
    fwd: f64,
    ort_fwd: f64,
    py_fwd: Option<(f64, f64)>,
    step: f64,
    py_step: Option<f64>,
}

/// Prints preset `name`'s table: each runtime's time, GFLOP/s, share of the matmul's
/// `mm` GFLOP/s and time against candle's (`max_diff`: the Python side's outputs
/// against candle's, when it ran).
fn print_table(
    name: &str,
    cfg: &Config,
    (tile, batch): (usize, usize),
    mm: f64,
    times: &Times,
    max_diff: Option<f64>,
) {
    let &Times {
        fwd,
        ort_fwd,
        py_fwd,
        step,
        py_step,
    } = times;
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
    if let Some((ort_py, torch)) = py_fwd {
        row("forward", "onnxruntime (Python)", ort_py, fwd_flop, fwd);
        row("forward", "PyTorch", torch, fwd_flop, fwd);
    }
    row("training step", "candle", step, step_flop, step);
    if let (Some(torch_step), Some((ort_py, _)), Some(max_diff)) = (py_step, py_fwd, max_diff) {
        row("training step", "PyTorch", torch_step, step_flop, step);
        println!(
            "outputs: PyTorch and onnxruntime vs candle, max abs difference {:.1e}",
            max_diff
        );
        println!(
            "RATIO {name}: candle's speed relative to onnxruntime's forward {:.2}, to PyTorch's training step {:.2} (issue 9 asks for >= 1)",
            ort_fwd.min(ort_py) / fwd,
            torch_step / step
        );
    }
}

fn main() -> Result<()> {
    // As the `deepstereo` binary does (PyTorch and onnxruntime keep their own pools).
    deepstereo_train::alloc::tune_allocator();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let configs = std::env::var("NET_BENCH_CONFIGS").unwrap_or_else(|_| "tiny,nviews,paper".into());
    let mm = matmul_gflops()?;
    println!("{threads} threads; candle 2048^2 f32 matmul {mm:.1} GFLOP/s");
    for name in configs.split(',') {
        bench(name.trim(), mm, threads)?;
    }
    Ok(())
}
