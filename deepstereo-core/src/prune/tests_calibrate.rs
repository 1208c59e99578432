//! Calibration tools, not checks (all ignored): how many planes pruning keeps, how often
//! it loses the true plane, what it costs a trained network, and what a network call
//! costs per block size. Run one with `cargo test --release -p deepstereo-core
//! prune_calibrate -- --ignored --nocapture`; the environment variables each reads are
//! in its doc.

use super::tests::{check_bands, nearest, nearest_plane, pyramids, scene, TestResult};
use super::*;
use crate::camera::Camera;
use crate::config::Config;
use crate::geometry::inverse_depths;
use crate::inputs::{tile_inputs, PyramidSource};
use crate::render::{render_view, render_view_pruned, Backend, CandleBackend};
use crate::synth::{generate, Rig, SynthOptions};
use crate::weights::init_seeded;
use candle_core::{DType, Device};

/// A grid point: `(mass, tolerance, stride, margin, window)`.
type GridPoint = (f32, f32, usize, usize, usize);

/// The rows of `PRUNE_GRID` (`a,b,c,d[,e];...`), each as numbers.
fn env_grid() -> Option<Vec<Vec<f64>>> {
    let g = std::env::var("PRUNE_GRID").ok()?;
    let row = |t: &str| t.split(',').map(|x| x.parse().unwrap()).collect();
    Some(g.split(';').map(row).collect())
}

/// The grid of `PRUNE_GRID` (`mass,tol,stride,margin[,window];...`), else `default` alone.
fn grid_from_env(default: GridPoint) -> Vec<GridPoint> {
    env_grid()
        .map(|rows| {
            rows.into_iter()
                .map(|v| {
                    (
                        v[0] as f32,
                        v[1] as f32,
                        v[2] as usize,
                        v[3] as usize,
                        v.get(4).map_or(1, |&x| x as usize),
                    )
                })
                .collect()
        })
        .unwrap_or_else(|| vec![default])
}

/// The pruning options of a grid point, with the contrast of `PRUNE_CONTRAST` if set.
fn options((mass, tol, stride, margin, window): GridPoint) -> PruneOptions {
    let contrast = std::env::var("PRUNE_CONTRAST")
        .ok()
        .and_then(|c| c.parse().ok())
        .unwrap_or(DEFAULT_CONTRAST);
    PruneOptions {
        mass,
        tolerance: tol,
        stride,
        margin,
        window,
        contrast,
        ..PruneOptions::auto()
    }
}

/// Calibration, not a check: per scene, how many planes pruning keeps and how many
/// pixels lose their true plane (`cargo test --release -p deepstereo-core prune_calibrate
/// -- --ignored --nocapture`).
#[test]
#[ignore]
fn prune_calibrate() {
    let planes = 32;
    for tile in [16usize, 32, 64] {
        let (mut k, mut t, mut k3) = (0, 0, 0);
        let mut union = [0usize; 4];
        let mut hist = [0usize; 9];
        for i in 0..8u64 {
            let s = scene(4242 + i, Rig::Mixed);
            let target = s.cameras.len() / 2;
            let inv = inverse_depths(s.near, s.far, planes);
            let (w, h) = (
                s.images[target].width as usize,
                s.images[target].height as usize,
            );
            for y0 in (0..h).step_by(tile) {
                for x0 in (0..w).step_by(tile) {
                    let (mut lo, mut hi) = (planes, 0);
                    let mut used = vec![false; planes];
                    for y in y0..(y0 + tile).min(h) {
                        for x in x0..(x0 + tile).min(w) {
                            let z = nearest_plane(&inv, s.depths[target][y * w + x] as f64);
                            used[z] = true;
                            lo = lo.min(z);
                            hi = hi.max(z);
                        }
                    }
                    for (m, u) in union.iter_mut().enumerate() {
                        *u += (0..planes)
                            .filter(|&z| {
                                (z.saturating_sub(m)..=(z + m).min(planes - 1)).any(|q| used[q])
                            })
                            .count();
                    }
                    k += hi + 1 - lo;
                    k3 += (hi + 3).min(planes - 1) + 1 - lo.saturating_sub(3);
                    t += planes;
                    hist[((hi + 1 - lo) * 8 / planes).min(8)] += 1;
                }
            }
        }
        println!(
            "tile {tile}: ground-truth union with margin 0..3 keeps {:?}%",
            union.map(|u| (1000 * u / t) as f64 / 10.0)
        );
        println!("tile {tile}: ground-truth hull keeps {:.1}%, with margin 3 {:.1}%; widths by eighths {hist:?}", 100.0 * k as f64 / t as f64, 100.0 * k3 as f64 / t as f64);
    }
    let grid = grid_from_env((1.0, 0.1, 2, 1, 1));
    for tile in [64usize] {
        for &(mass, tol, stride, margin, window) in &grid {
            let opts = options((mass, tol, stride, margin, window));
            let (mut m, mut n, mut k, mut t) = (0, 0, 0, 0);
            for i in 0..8u64 {
                let s = scene(4242 + i, Rig::Mixed);
                let r = check_bands(&s, s.cameras.len() / 2, planes, tile, &opts);
                m += r.0;
                n += r.1;
                k += r.2;
                t += r.3;
            }
            println!(
                "tile {tile} mass {mass} tol {tol} stride {stride} margin {margin} window {window}: kept {:.1}% of plane-pixels, {m} of {n} pixels miss",
                100.0 * k as f64 / t as f64
            );
        }
    }
}

/// Calibration against a trained network (`PRUNE_MODEL=path.safetensors`): per scene,
/// the selection mass the plans leave out, the fraction of planes x pixels run, and the
/// PSNR of the pruned and unpruned renders against the truth.
#[test]
#[ignore]
fn prune_calibrate_network() -> TestResult {
    let Ok(path) = std::env::var("PRUNE_MODEL") else {
        return Ok(());
    };
    let t = crate::weights::load(std::path::Path::new(&path), &Device::Cpu)?;
    let backend = CandleBackend {
        model: t.model,
        device: Device::Cpu,
    };
    let cfg = backend.config().clone();
    let grid = grid_from_env((1.0, 0.05, 2, 1, 1));
    let scenes: usize = std::env::var("PRUNE_SCENES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3);
    let mut sums = vec![(0.0f64, 0.0f64, 0.0f64, 0.0f64); grid.len()];
    let mut off_sum = 0.0;
    let mut mass_need = [0.0f64; 3];
    let mut npix = 0.0;
    for i in 0..scenes as u64 {
        let s = generate(
            4242 + i,
            &SynthOptions {
                views: 10,
                width: 160,
                height: 120,
                rig: Rig::Mixed,
                supersample: 2,
                textures: Vec::new(),
                rolling_shutter: 0.0,
            },
        )?;
        let target = s.cameras.len() / 2;
        let src = nearest(&s.cameras, target, cfg.views);
        let pyr = pyramids(&s, &src, cfg.levels);
        let refs: Vec<&PyramidSource> = pyr.iter().collect();
        let inv = inverse_depths(s.near, s.far, cfg.planes);
        let cam = &s.cameras[target];
        let (w, h) = (
            cam.intrinsics.width as usize,
            cam.intrinsics.height as usize,
        );
        // Full selections per pixel.
        let d = inv.len();
        let mut sel_full = vec![0f32; w * h * d];
        let tile = 64;
        for y0 in (0..h).step_by(tile) {
            for x0 in (0..w).step_by(tile) {
                let inputs =
                    tile_inputs(&cfg, cam, &refs, &inv, (x0 as i64, y0 as i64), (tile, tile))?;
                let (_, sel) = backend.run(&inputs, d)?;
                for y in y0..(y0 + tile).min(h) {
                    for x in x0..(x0 + tile).min(w) {
                        let o = (y - y0) * tile + x - x0;
                        for z in 0..d {
                            sel_full[(y * w + x) * d + z] = sel[z * tile * tile + o];
                        }
                        let mut v: Vec<f32> = (0..d).map(|z| sel[z * tile * tile + o]).collect();
                        v.sort_by(|a, b| b.total_cmp(a));
                        for (k, q) in [0.9f32, 0.95, 0.99].iter().enumerate() {
                            let mut acc = 0.0;
                            let n = v.iter().take_while(|&&x| {
                                let before = acc;
                                acc += x;
                                before < *q
                            });
                            mass_need[k] += n.count() as f64;
                        }
                        npix += 1.0;
                    }
                }
            }
        }
        let off = render_view(&backend, cam, &refs, &inv, tile, &|_, _| {})?;
        let off_psnr = crate::metrics::psnr(&off.image, &s.images[target]);
        off_sum += off_psnr;
        for (g, &(mass, tol, stride, margin, window)) in grid.iter().enumerate() {
            let opts = options((mass, tol, stride, margin, window));
            let pruner = Pruner::new(&cfg, cam, &refs, &inv, None, &opts);
            let mut lost = 0.0f64;
            for y0 in (0..h).step_by(tile) {
                for x0 in (0..w).step_by(tile) {
                    for b in pruner.plan(x0, y0, tile) {
                        let keep = match &b.plan {
                            TilePlan::Planes(p) => p.clone(),
                            _ => Vec::new(),
                        };
                        for y in b.y0..(b.y0 + b.size).min(h) {
                            for x in b.x0..(b.x0 + b.size).min(w) {
                                let m: f32 = (0..d)
                                    .filter(|z| !keep.contains(z))
                                    .map(|z| sel_full[(y * w + x) * d + z])
                                    .sum();
                                lost += m as f64;
                            }
                        }
                    }
                }
            }
            let r =
                render_view_pruned(&backend, cam, &refs, &inv, tile, Some(&pruner), &|_, _| {})?;
            let p = crate::metrics::psnr(&r.image, &s.images[target]);
            let vs_off = crate::metrics::psnr(&r.image, &off.image);
            let st = r.prune.expect("stats");
            sums[g].0 += p - off_psnr;
            sums[g].1 += st.planes_fraction();
            sums[g].2 += lost / (w * h) as f64;
            sums[g].3 += vs_off;
            println!("scene {i} {:?}: off {off_psnr:.2} pruned {p:.2} (vs off {vs_off:.1} dB), planes {:.1}%, lost mass {:.3}", (mass, tol, stride, margin, window), 100.0 * st.planes_fraction(), lost / (w * h) as f64);
        }
    }
    let n = scenes as f64;
    println!(
        "network needs planes for 90/95/99% mass: {:?} of {}",
        mass_need.map(|m| (m / npix * 10.0).round() / 10.0),
        cfg.planes
    );
    println!("off mean PSNR {:.2}", off_sum / n);
    for (g, s) in grid.iter().zip(&sums) {
        println!(
            "{g:?}: PSNR change {:+.3} dB, planes {:.1}%, lost mass {:.3}, vs off {:.1} dB",
            s.0 / n,
            100.0 * s.1 / n,
            s.2 / n,
            s.3 / n
        );
    }
    Ok(())
}

/// Timing of one network call per block size and plane count (for the split cost model).
#[test]
#[ignore]
fn prune_time_blocks() -> TestResult {
    let cfg = Config::tiny();
    let t = init_seeded(&cfg, DType::F32, &Device::Cpu, 1)?;
    let backend = CandleBackend {
        model: t.model,
        device: Device::Cpu,
    };
    let s = generate(
        3,
        &SynthOptions {
            views: 6,
            width: 128,
            height: 128,
            rig: Rig::Forward,
            supersample: 1,
            textures: Vec::new(),
            rolling_shutter: 0.0,
        },
    )?;
    let src = nearest(&s.cameras, 0, cfg.views);
    let pyr = pyramids(&s, &src, cfg.levels);
    let refs: Vec<&PyramidSource> = pyr.iter().collect();
    let inv = inverse_depths(s.near, s.far, 32);
    for size in [16usize, 32, 64] {
        for planes in [1usize, 4, 8, 16, 32] {
            let reps = (4096 / (size * size)).max(1) * 2;
            let t0 = std::time::Instant::now();
            let mut warp = 0.0;
            for r in 0..reps {
                let w0 = std::time::Instant::now();
                let inputs = tile_inputs(
                    &cfg,
                    &s.cameras[0],
                    &refs,
                    &inv[..planes],
                    ((r % 2 * size) as i64, 0),
                    (size, size),
                )?;
                warp += w0.elapsed().as_secs_f64();
                backend.run(&inputs, planes)?;
            }
            let per = t0.elapsed().as_secs_f64() / reps as f64;
            println!("block {size:2} planes {planes:2}: {:.2} ms per call ({:.2} ms warping), {:.1} us per plane x pixel", per * 1e3, warp / reps as f64 * 1e3, per * 1e6 / (planes * size * size) as f64 * 1e3 / 1e3);
        }
    }
    Ok(())
}

/// A crop of a real scene's held-out view, rendered off and pruned
/// (`PRUNE_MODEL=... PRUNE_SCENE=dir PRUNE_CROP=target,x0,y0,size`).
#[test]
#[ignore]
fn prune_real_crop() -> TestResult {
    let (Ok(path), Ok(dir), Ok(crop)) = (
        std::env::var("PRUNE_MODEL"),
        std::env::var("PRUNE_SCENE"),
        std::env::var("PRUNE_CROP"),
    ) else {
        return Ok(());
    };
    let c: Vec<usize> = crop.split(',').map(|x| x.parse().unwrap()).collect();
    let (t, x0, y0, size) = (c[0], c[1], c[2], c[3]);
    let tr = crate::weights::load(std::path::Path::new(&path), &Device::Cpu)?;
    let backend = CandleBackend {
        model: tr.model,
        device: Device::Cpu,
    };
    let cfg = backend.config().clone();
    let scene = crate::scene::Scene::load(std::path::Path::new(&dir), &Default::default())?;
    let truth = scene.load_image(t)?;
    let mut cam = scene.views[t].camera;
    cam.intrinsics.cx -= x0 as f64;
    cam.intrinsics.cy -= y0 as f64;
    cam.intrinsics.width = size as u32;
    cam.intrinsics.height = size as u32;
    if let Some(rs) = &mut cam.rolling_shutter {
        // Pixel (x, y) of the crop is (x0 + x, y0 + y) of the view: same time.
        rs.time_origin += rs
            .time_per_pixel
            .dot(glam::DVec2::new(x0 as f64, y0 as f64));
    }
    let mut want = crate::imageio::RgbImage::new(size as u32, size as u32);
    for y in 0..size {
        for x in 0..size {
            let p = truth.pixel((x0 + x) as u32, (y0 + y) as u32);
            want.data[(y * size + x) * 3..(y * size + x) * 3 + 3].copy_from_slice(&p);
        }
    }
    let inv = inverse_depths(scene.near, scene.far, cfg.planes);
    let grid: Vec<(f32, f32, usize, usize, f32)> = env_grid()
        .map(|rows| {
            rows.into_iter()
                .map(|v| {
                    (
                        v[0] as f32,
                        v[1] as f32,
                        v[2] as usize,
                        v[3] as usize,
                        v.get(4).map_or(DEFAULT_CONTRAST, |&x| x as f32),
                    )
                })
                .collect()
        })
        .unwrap_or_else(|| {
            vec![(
                DEFAULT_MASS,
                DEFAULT_TOLERANCE,
                DEFAULT_MARGIN,
                DEFAULT_WINDOW,
                DEFAULT_CONTRAST,
            )]
        });
    for ranked in [false, true] {
        let src = if ranked {
            let cams: Vec<Camera> = scene.views.iter().map(|v| v.camera).collect();
            rank_views(&cams, &cam, cfg.views, Some(t), scene.near, scene.far).0
        } else {
            scene.nearest_views(t, cfg.views)
        };
        let pyr: Vec<PyramidSource> = src
            .iter()
            .map(|&i| {
                PyramidSource::new(
                    &scene.views[i].camera,
                    &scene.load_image(i).unwrap(),
                    cfg.levels,
                )
            })
            .collect();
        let refs: Vec<&PyramidSource> = pyr.iter().collect();
        let t0 = std::time::Instant::now();
        let off = render_view(&backend, &cam, &refs, &inv, 64, &|_, _| {})?;
        let toff = t0.elapsed().as_secs_f64();
        println!(
            "sources {src:?}: off {:.2} dB {toff:.2} s",
            crate::metrics::psnr(&off.image, &want)
        );
        for &(mass, tolerance, margin, window, contrast) in &grid {
            let opts = PruneOptions {
                mass,
                tolerance,
                margin,
                window,
                contrast,
                ..PruneOptions::auto()
            };
            let range = std::env::var("PRUNE_RANGE")
                .ok()
                .map(|r| {
                    let v: Vec<usize> = r.split(',').map(|x| x.parse().unwrap()).collect();
                    (v[0], v[1])
                })
                .or_else(|| plane_range_from_points(&cam, &scene.points, &inv))
                .or_else(|| {
                    let b: Vec<_> = src.iter().map(|&i| scene.views[i].bounds).collect();
                    plane_range_from_bounds(&b, &inv)
                });
            let pruner = Pruner::new(&cfg, &cam, &refs, &inv, range, &opts);
            let t0 = std::time::Instant::now();
            let r = render_view_pruned(&backend, &cam, &refs, &inv, 64, Some(&pruner), &|_, _| {})?;
            let st = r.prune.clone().unwrap();
            println!(
                "  {:?} range {range:?}: {:.2} dB {:.2} s ({:.1}x), planes {:.1}%, coarse {:.2} s",
                (mass, tolerance, margin, window, contrast),
                crate::metrics::psnr(&r.image, &want),
                t0.elapsed().as_secs_f64(),
                toff / t0.elapsed().as_secs_f64(),
                100.0 * st.planes_fraction(),
                st.coarse_seconds
            );
        }
    }
    Ok(())
}
