//! Plane-sweep speed: a 96-plane, 4-view, 512x384 volume built by
//! [`deepstereo_core::sweep::sweep_into`], against PyTorch `grid_sample` doing the same
//! warps (`python/bench_sweep.py`, 2 threads) on the same machine, with the ratio.
//!
//! `cargo bench -p deepstereo-core --bench sweep`. The Rust side writes the source images
//! and the per-(plane, view) pixel homographies (target -> source, pixel centres at
//! `i + 0.5`) to a temporary directory; the Python side, run with
//! `/work/main/.venv/bin/python` when it exists (or `$SWEEP_BENCH_PYTHON`), times the same
//! warps and writes three planes of its volume back, which are compared with ours.
//! `SWEEP_BENCH_PY=0` skips Python.

use deepstereo_core::camera::{Camera, Intrinsics, WorldToCamera};
use deepstereo_core::config::CUE_CHANNELS;
use deepstereo_core::geometry::{inverse_depths, plane_homography};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::scene::npy::{read_npy, write_npy_f32, write_npy_f64};
use deepstereo_core::sweep::cue::{centre_in, cue_slice, CueRays};
use deepstereo_core::sweep::{sweep_into, target_rays, Region, Source, CHANNELS};
use glam::{DMat3, DVec3};
use rayon::prelude::*;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

const PLANES: usize = 96;
const VIEWS: usize = 4;
const WIDTH: u32 = 512;
const HEIGHT: u32 = 384;
/// Planes whose slices the Python side writes back for comparison.
const CHECK_PLANES: [usize; 3] = [0, PLANES / 2, PLANES - 1];
const VENV_PYTHON: &str = "/work/main/.venv/bin/python";

/// A smooth random texture (sum of a few sinusoids per channel plus mild noise).
fn texture(w: u32, h: u32, seed: u64) -> RgbImage {
    let mut img = RgbImage::new(w, h);
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut rnd = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f32 / (1u64 << 53) as f32
    };
    let f: Vec<f32> = (0..18).map(|_| 0.02 + 0.2 * rnd()).collect();
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize * 3;
            for c in 0..3 {
                let (a, b, p) = (f[c * 6], f[c * 6 + 1], f[c * 6 + 2] * 30.0);
                let v = 0.5
                    + 0.2 * (a * x as f32 + b * y as f32 + p).sin()
                    + 0.15 * (f[c * 6 + 3] * x as f32 - f[c * 6 + 4] * y as f32).cos()
                    + 0.05 * (rnd() - 0.5);
                img.data[i + c] = v.clamp(0.0, 1.0);
            }
        }
    }
    img
}

/// CPU seconds (user + system, all threads) this process has used, from `/proc/self/stat`
/// (Linux; clock ticks of 10 ms); `None` elsewhere.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesized command name; utime and stime are fields 14 and 15.
    let rest = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Median wall seconds of `f` over `reps` runs after one warm-up, and the mean CPU
/// seconds per run (wall time is unreliable on a machine shared with other jobs).
fn timed(reps: usize, mut f: impl FnMut()) -> (f64, f64) {
    f();
    let cpu0 = cpu_seconds().unwrap_or(f64::NAN);
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    let cpu = (cpu_seconds().unwrap_or(f64::NAN) - cpu0) / reps as f64;
    t.sort_by(f64::total_cmp);
    (t[reps / 2], cpu)
}

fn camera(k: Intrinsics, r: DMat3, centre: DVec3) -> Camera {
    Camera {
        intrinsics: k,
        pose: WorldToCamera {
            rotation: r,
            translation: -(r * centre),
        },
        rolling_shutter: None,
    }
}

/// The source cameras: around the target's centre, turned slightly towards it.
fn source_cameras(k: Intrinsics) -> Vec<Camera> {
    (0..VIEWS)
        .map(|i| {
            let a = i as f64 * std::f64::consts::FRAC_PI_2;
            let r = DMat3::from_rotation_y(0.05 * a.cos()) * DMat3::from_rotation_x(0.04 * a.sin());
            camera(
                k,
                r,
                DVec3::new(0.3 * a.cos(), 0.2 * a.sin(), 0.05 * i as f64),
            )
        })
        .collect()
}

/// Times the per-view cue of the sweep's (plane, view) slices (`sweep::cue`), which models
/// with `pool.cue` compute beside the sweep, against the sweep's `rust_s` seconds.
fn bench_cue(target: &Camera, sources: &[Camera], region: Region, inv: &[f64], rust_s: f64) {
    let rays = CueRays::new(&target_rays(&target.intrinsics, region));
    let centres: Vec<DVec3> = sources.iter().map(|s| centre_in(target, s)).collect();
    let hw = region.len();
    let mut cue = vec![0.0f32; PLANES * VIEWS * CUE_CHANNELS * hw];
    let (cue_s, cue_cpu) = timed(5, || {
        cue.par_chunks_mut(CUE_CHANNELS * hw)
            .enumerate()
            .for_each(|(i, o)| cue_slice(&rays, inv[i / VIEWS], centres[i % VIEWS], o))
    });
    println!(
        "  rust cue_slice, the same slices: {:8.1} ms wall, {:8.1} ms CPU  ({:.2}x the sweep's wall time)",
        cue_s * 1e3,
        cue_cpu * 1e3,
        cue_s / rust_s
    );
}

/// Writes the Python side's inputs into `dir`: the pixel homographies (target pixel ->
/// source pixel, `K_s H(rho) K_t^-1`, row-major), the source images and `meta.json`.
fn write_python_inputs(
    dir: &Path,
    target: &Camera,
    sources: &[Camera],
    images: &[RgbImage],
    inv: &[f64],
) -> Result<(), Box<dyn std::error::Error>> {
    let kt_inv = target.intrinsics.k().inverse();
    let mut hs = Vec::with_capacity(PLANES * VIEWS * 9);
    for &rho in inv {
        for s in sources {
            let rel = target.pose.relative_to(&s.pose);
            let h = s.intrinsics.k() * plane_homography(&rel, rho) * kt_inv;
            for r in 0..3 {
                hs.extend([h.x_axis[r], h.y_axis[r], h.z_axis[r]]);
            }
        }
    }
    write_npy_f64(&dir.join("homographies.npy"), &[PLANES * VIEWS, 9], &hs)?;
    let pixels: Vec<f32> = images.iter().flat_map(|i| i.data.iter().copied()).collect();
    write_npy_f32(
        &dir.join("images.npy"),
        &[VIEWS * HEIGHT as usize, WIDTH as usize * 3],
        &pixels,
    )?;
    let meta = serde_json::json!({
        "planes": PLANES, "views": VIEWS, "height": HEIGHT, "width": WIDTH, "threads": 2,
        "check_planes": CHECK_PLANES, "dir": dir,
    });
    std::fs::write(dir.join("meta.json"), meta.to_string())?;
    Ok(())
}

/// Prints the Python side's `report` against the sweep's `rust_s` wall and `rust_cpu`
/// CPU seconds.
fn print_python(report: &serde_json::Value, rust_s: f64, rust_cpu: f64) {
    let torch_ms = report["median_ms"].as_f64().unwrap_or(f64::NAN);
    let torch_cpu_ms = report["cpu_ms"].as_f64().unwrap_or(f64::NAN);
    println!(
        "  pytorch grid_sample ({} threads, torch {}): {torch_ms:8.1} ms wall, {torch_cpu_ms:8.1} ms CPU",
        report["threads"], report["torch"]
    );
    let ratio = torch_ms / (rust_s * 1e3);
    println!(
        "  ratio pytorch / rust: {ratio:.2}x wall, {:.2}x CPU ({})",
        torch_cpu_ms / (rust_cpu * 1e3),
        if ratio > 1.0 {
            "rust faster"
        } else {
            "pytorch faster"
        }
    );
}

/// Compares the planes PyTorch wrote back (`check`) with ours in `out` (same warps).
fn compare_planes(out: &[f32], check: &Path, hw: usize) -> Result<(), Box<dyn std::error::Error>> {
    let theirs = read_npy(check)?;
    let slice = VIEWS * CHANNELS * hw;
    let (mut max, mut sum, mut n) = (0.0f64, 0.0f64, 0usize);
    for (i, &d) in CHECK_PLANES.iter().enumerate() {
        let ours = &out[d * slice..(d + 1) * slice];
        for (a, b) in ours.iter().zip(&theirs.data[i * slice..(i + 1) * slice]) {
            let e = (*a as f64 - b).abs();
            max = max.max(e);
            sum += e;
            n += 1;
        }
    }
    println!(
        "  same warps: max |rust - pytorch| = {max:.2e}, mean {:.2e} over planes {CHECK_PLANES:?}",
        sum / n.max(1) as f64
    );
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let k = Intrinsics::pinhole(450.0, 450.0, 256.0, 192.0, WIDTH, HEIGHT);
    let target = camera(k, DMat3::IDENTITY, DVec3::ZERO);
    let sources = source_cameras(k);
    let images: Vec<RgbImage> = (0..VIEWS)
        .map(|i| texture(WIDTH, HEIGHT, i as u64 + 1))
        .collect();
    let srcs: Vec<Source> = sources
        .iter()
        .zip(&images)
        .map(|(camera, image)| Source { camera, image })
        .collect();
    let inv = inverse_depths(1.0, 100.0, PLANES);
    let region = Region::full(&k);
    let hw = region.len();
    let mut out = vec![0.0f32; PLANES * VIEWS * CHANNELS * hw];

    let threads = rayon::current_num_threads();
    let (rust_s, rust_cpu) = timed(5, || sweep_into(&target, region, &srcs, &inv, &mut out));
    println!(
        "plane sweep {PLANES} planes x {VIEWS} views x {WIDTH}x{HEIGHT} ({:.1} M samples)",
        (PLANES * VIEWS * hw) as f64 / 1e6
    );
    println!(
        "  rust sweep_into ({threads} rayon threads): {:8.1} ms wall, {:8.1} ms CPU  ({:.2} ns/sample wall)",
        rust_s * 1e3,
        rust_cpu * 1e3,
        rust_s * 1e9 / (PLANES * VIEWS * hw) as f64
    );

    bench_cue(&target, &sources, region, &inv, rust_s);

    if std::env::var("SWEEP_BENCH_PY").as_deref() == Ok("0") {
        return Ok(());
    }
    let python = std::env::var("SWEEP_BENCH_PYTHON").unwrap_or_else(|_| VENV_PYTHON.to_string());
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../python/bench_sweep.py");
    if !Path::new(&python).exists() || !script.is_file() {
        println!(
            "  pytorch: skipped ({python} or {} missing)",
            script.display()
        );
        return Ok(());
    }
    let dir = tempfile::tempdir()?;
    write_python_inputs(dir.path(), &target, &sources, &images, &inv)?;
    let res = Command::new(&python)
        .arg(&script)
        .arg(dir.path().join("meta.json"))
        .output()?;
    if !res.status.success() {
        println!(
            "  pytorch: failed:\n{}",
            String::from_utf8_lossy(&res.stderr)
        );
        return Ok(());
    }
    let report: serde_json::Value = serde_json::from_slice(&res.stdout)?;
    print_python(&report, rust_s, rust_cpu);
    compare_planes(&out, &dir.path().join("check.npy"), hw)?;
    Ok(())
}
