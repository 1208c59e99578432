//! Conv2d speed for every layer shape of `Config::tiny()` (4 tiles) and `Config::paper()`
//! (8 tiles): forward, and forward + backward (gradients of input, weight and bias), for
//! the crate's kernels and candle's built-in conv2d; with the workspace's `.venv`
//! present, also PyTorch and onnxruntime on the same shapes (`python/bench_conv.py`).
//!
//! GFLOP/s count the direct convolution's multiply-adds (x 2) for every runtime; the
//! crate's Winograd layers (`DEEPSTEREO_CONV=direct` turns them off) do fewer, so their
//! figure can pass the matmul's.
//!
//! `cargo bench -p deepstereo-core --bench conv`; `CONV_BENCH_REF=0` skips candle's conv2d,
//! `CONV_BENCH_PY=0` skips Python, `CONV_BENCH_CONFIGS=tiny` picks presets. Times are the
//! best of several runs (the machine is shared); Python times each shape right after Rust.

use candle_core::{DType, Device, Module, Result, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use deepstereo_core::config::Config;
use deepstereo_core::conv::Conv2d;
use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::Instant;

/// `(n, cin, h, w, cout, kh, kw)`.
type Shape = [usize; 7];

/// Best ms of `f`: one warm-up run, then repeats within `budget_s` (none if the warm-up
/// alone took longer).
fn timed(budget_s: f64, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    let t = Instant::now();
    f()?;
    let first = t.elapsed().as_secs_f64();
    if first > budget_s {
        return Ok(first * 1e3);
    }
    let reps = ((budget_s / first) as usize).clamp(2, 10);
    let mut times = Vec::with_capacity(reps);
    for _ in 0..reps {
        let t = Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64());
    }
    Ok(times.into_iter().fold(f64::MAX, f64::min) * 1e3)
}

/// Unique layer shapes of a preset, with the layer names sharing each.
fn shapes(cfg: &Config, batch: usize) -> Vec<(Shape, Vec<String>)> {
    let mut out: Vec<(Shape, Vec<String>)> = Vec::new();
    for l in cfg.layers() {
        let k = l.kernel;
        let shape = if l.name.starts_with("select.depth") {
            // [B, C, D + k - 1, t*t] zero-padded along depth, kernel (k, 1).
            [
                batch,
                l.in_channels,
                cfg.planes + k - 1,
                cfg.tile * cfg.tile,
                l.out_channels,
                k,
                1,
            ]
        } else {
            let s = l.out_size + k - 1;
            [
                batch * cfg.planes,
                l.in_channels,
                s,
                s,
                l.out_channels,
                k,
                k,
            ]
        };
        match out.iter_mut().find(|(s, _)| *s == shape) {
            Some((_, names)) => names.push(l.name),
            None => out.push((shape, vec![l.name])),
        }
    }
    out
}

fn gflop(s: &Shape) -> f64 {
    let [n, cin, h, w, cout, kh, kw] = *s;
    2.0 * (n * cout * (h - kh + 1) * (w - kw + 1) * cin * kh * kw) as f64 * 1e-9
}

#[derive(Default, Clone, Copy)]
struct Times {
    fwd: f64,
    fwd_bwd: f64,
}

/// Times our kernels and (when `reference`) candle's conv2d on one shape.
fn bench_shape(s: &Shape, reference: bool) -> Result<(Times, Option<Times>)> {
    let [n, cin, h, w, cout, kh, kw] = *s;
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let conv = Conv2d::new(
        cin,
        cout,
        (kh, kw),
        VarBuilder::from_varmap(&vm, DType::F32, &dev),
    )?;
    let x = Var::from_tensor(&Tensor::randn(0f32, 1., (n, cin, h, w), &dev)?)?;
    let run = |f: &dyn Fn(&Tensor) -> Result<Tensor>, budget: f64| -> Result<Times> {
        let fwd = timed(budget, || f(&x).map(drop))?;
        let fwd_bwd = timed(budget, || f(x.as_tensor())?.sum_all()?.backward().map(drop))?;
        Ok(Times { fwd, fwd_bwd })
    };
    let ours = run(&|x| conv.forward(x), 1.5)?;
    let theirs = reference
        .then(|| run(&|x| conv.forward_reference(x), 0.5))
        .transpose()?;
    Ok((ours, theirs))
}

/// Throughput of a 2048^2 f32 matmul (candle, all threads), measured next to each shape
/// because the load of the shared machine varies.
fn matmul_gflops() -> Result<f64> {
    let a = Tensor::randn(0f32, 1., (2048, 2048), &Device::Cpu)?;
    let b = Tensor::randn(0f32, 1., (2048, 2048), &Device::Cpu)?;
    let ms = timed(0.5, || a.matmul(&b).map(drop))?;
    Ok(2.0 * 2048f64.powi(3) / (ms * 1e-3) * 1e-9)
}

/// `python/bench_conv.py` running in the venv: PyTorch and onnxruntime times per shape.
struct Python {
    child: Child,
    out: BufReader<ChildStdout>,
}

impl Python {
    fn start() -> Option<Self> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let python = root.join(".venv/bin/python");
        if !python.exists() || std::env::var("CONV_BENCH_PY").as_deref() == Ok("0") {
            println!(
                "(no PyTorch / onnxruntime: {} missing or CONV_BENCH_PY=0)",
                python.display()
            );
            return None;
        }
        let mut child = Command::new(python)
            .arg(root.join("python/bench_conv.py"))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .ok()?;
        let out = BufReader::new(child.stdout.take()?);
        Some(Self { child, out })
    }

    /// `[torch fwd, torch fwd+bwd, onnxruntime fwd]` in ms.
    fn times(&mut self, s: &Shape) -> Option<[f64; 3]> {
        let stdin = self.child.stdin.as_mut()?;
        writeln!(stdin, "{}", serde_json::to_string(s).ok()?).ok()?;
        stdin.flush().ok()?;
        let mut line = String::new();
        self.out.read_line(&mut line).ok()?;
        let r: serde_json::Value = serde_json::from_str(&line).ok()?;
        let f = |k: &str| r[k].as_f64();
        Some([f("torch_fwd_ms")?, f("torch_fwdbwd_ms")?, f("ort_fwd_ms")?])
    }
}

impl Drop for Python {
    fn drop(&mut self) {
        drop(self.child.stdin.take());
        let _ = self.child.wait();
    }
}

fn main() -> Result<()> {
    // As the `deepstereo` binary does: freed memory is reused instead of unmapped.
    deepstereo_core::alloc::tune_allocator();
    let reference = std::env::var("CONV_BENCH_REF").as_deref() != Ok("0");
    let wanted = std::env::var("CONV_BENCH_CONFIGS").unwrap_or_else(|_| "tiny,paper".into());
    let configs: Vec<(Config, usize)> = [(Config::tiny(), 4), (Config::paper(), 8)]
        .into_iter()
        .filter(|(c, _)| wanted.split(',').any(|w| w == c.name))
        .collect();
    let tunables = std::env::var("GLIBC_TUNABLES").unwrap_or_default();
    println!(
        "threads: {}, GLIBC_TUNABLES={tunables:?}",
        rayon::current_num_threads()
    );
    let mut py = Python::start();
    for (cfg, batch) in &configs {
        let shapes = shapes(cfg, *batch);
        println!(
            "\n## {} (batch {batch} tiles, {} planes)\n",
            cfg.name, cfg.planes
        );
        println!("| layers | N x Cin x H x W -> Cout, k | GFLOP | matmul GFLOP/s | fwd ms | GFLOP/s | of matmul | x candle | fwd+bwd ms | GFLOP/s | of matmul | x candle | / torch fwd | / torch f+b | / ort fwd |");
        println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
        let mut tot = [0f64; 7]; // ours fwd, fb, candle fwd, fb, torch fwd, fb, ort
        for (s, names) in &shapes {
            let mm = matmul_gflops()?;
            let (ours, theirs) = bench_shape(s, reference)?;
            let g = gflop(s);
            let reps = names.len() as f64;
            let ratio = |a: f64, b: Option<f64>| b.map_or("-".into(), |b| format!("{:.2}", a / b));
            let speedup =
                |a: f64, b: Option<f64>| b.map_or("-".into(), |b| format!("{:.1}", b / a));
            let pt = py.as_mut().and_then(|p| p.times(s));
            let [n, cin, h, w, cout, kh, kw] = *s;
            println!(
                "| {} | {n}x{cin}x{h}x{w} -> {cout}, {kh}x{kw} | {g:.2} | {mm:.0} | {:.1} | {:.0} | {:.2} | {} | {:.1} | {:.0} | {:.2} | {} | {} | {} | {} |",
                names.join(", "),
                ours.fwd,
                g / ours.fwd * 1e3,
                g / ours.fwd * 1e3 / mm,
                speedup(ours.fwd, theirs.map(|t| t.fwd)),
                ours.fwd_bwd,
                3.0 * g / ours.fwd_bwd * 1e3,
                3.0 * g / ours.fwd_bwd * 1e3 / mm,
                speedup(ours.fwd_bwd, theirs.map(|t| t.fwd_bwd)),
                ratio(ours.fwd, pt.map(|p| p[0])),
                ratio(ours.fwd_bwd, pt.map(|p| p[1])),
                ratio(ours.fwd, pt.map(|p| p[2])),
            );
            let t = theirs.unwrap_or_default();
            let p = pt.unwrap_or([0.0; 3]);
            for (acc, v) in
                tot.iter_mut()
                    .zip([ours.fwd, ours.fwd_bwd, t.fwd, t.fwd_bwd, p[0], p[1], p[2]])
            {
                *acc += reps * v;
            }
        }
        println!(
            "\nall {} layers: ours fwd {:.0} ms, fwd+bwd {:.0} ms; candle {:.0} / {:.0} ms; torch {:.0} / {:.0} ms; ort fwd {:.0} ms",
            cfg.layers().len(),
            tot[0],
            tot[1],
            tot[2],
            tot[3],
            tot[4],
            tot[5],
            tot[6]
        );
    }
    Ok(())
}
