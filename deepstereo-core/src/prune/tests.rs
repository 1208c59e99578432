//! Pruning against ground truth: the kept planes hold the true surface plane of the pixels
//! whose depth the images determine,
//! uncovered tiles skip the network, and pruning off is the unpruned renderer bit for bit.

use super::*;
use crate::camera::Camera;
use crate::config::{Config, Conv, TowerConfig};
use crate::geometry::inverse_depths;
use crate::inputs::{tile_inputs, PyramidSource};
use crate::render::{render_view, render_view_pruned, Backend, CandleBackend, Rendered};
use crate::synth::{generate, Rig, SynthOptions, SynthScene};
use crate::weights::init_seeded;
use candle_core::{DType, Device};

pub(super) type TestResult = std::result::Result<(), Box<dyn std::error::Error>>;

pub(super) fn nearest(cams: &[Camera], t: usize, k: usize) -> Vec<usize> {
    let c = cams[t].pose.centre();
    let mut idx: Vec<(f64, usize)> = (0..cams.len())
        .filter(|&i| i != t)
        .map(|i| (cams[i].pose.centre().distance_squared(c), i))
        .collect();
    idx.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    idx.into_iter().take(k).map(|(_, i)| i).collect()
}

pub(super) fn pyramids(s: &SynthScene, idx: &[usize], levels: usize) -> Vec<PyramidSource> {
    idx.iter()
        .map(|&i| PyramidSource::new(&s.cameras[i], &s.images[i], levels))
        .collect()
}

/// Index of the plane (of decreasing `inv`) nearest in inverse depth to `depth`.
pub(super) fn nearest_plane(inv: &[f64], depth: f64) -> usize {
    let r = 1.0 / depth;
    (0..inv.len())
        .min_by(|&a, &b| (inv[a] - r).abs().total_cmp(&(inv[b] - r).abs()))
        .unwrap_or(0)
}

/// A small model with the tiny preset's structure (2 levels, 3 depth convs).
pub(super) fn small_backend(views: usize) -> CandleBackend {
    let c = |k, ch| Conv {
        kernel: k,
        channels: ch,
    };
    let cfg = Config {
        name: "prune-test".into(),
        views,
        planes: 12,
        levels: 2,
        tile: 8,
        select: TowerConfig {
            levels: 2,
            level_convs: vec![c(3, 4)],
            merge_convs: vec![c(3, 4)],
        },
        depth_convs: vec![c(3, 4), c(3, 4), c(3, 1)],
        colour: TowerConfig {
            levels: 1,
            level_convs: vec![c(1, 4)],
            merge_convs: vec![c(1, 4)],
        },
        colour_skip: true,
        render_planes: None,
        pool: None,
    };
    let t = init_seeded(&cfg, DType::F32, &Device::Cpu, 7).expect("model");
    CandleBackend {
        model: t.model,
        device: Device::Cpu,
    }
}

/// The pixels of view `t` whose surface depth the images determine: the classical plane
/// sweep ([`crate::baseline::plane_sweep`], on the same sources and planes) finds their
/// true plane within one plane, and they are textured (the colour varies by at least
/// [`MIN_TEXTURE`] in their 5x5 neighbourhood).
/// Least colour range around a pixel for it to count as textured.
const MIN_TEXTURE: f32 = 0.1;

pub(super) fn known_pixels(s: &SynthScene, t: usize, sources: &[usize], inv: &[f64]) -> Vec<bool> {
    let srcs: Vec<crate::sweep::Source> = sources
        .iter()
        .map(|&k| crate::sweep::Source {
            camera: &s.cameras[k],
            image: &s.images[k],
        })
        .collect();
    let (_, planes) = crate::baseline::plane_sweep(&s.cameras[t], &srcs, inv);
    let img = &s.images[t];
    let (w, h) = (img.width as usize, img.height as usize);
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let z = nearest_plane(inv, s.depths[t][i] as f64);
            let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
            for yy in y.saturating_sub(2)..(y + 3).min(h) {
                for xx in x.saturating_sub(2)..(x + 3).min(w) {
                    let c = img.pixel(xx as u32, yy as u32);
                    for ch in 0..3 {
                        lo[ch] = lo[ch].min(c[ch]);
                        hi[ch] = hi[ch].max(c[ch]);
                    }
                }
            }
            (planes[i] as usize).abs_diff(z) <= 1 && (0..3).any(|ch| hi[ch] - lo[ch] >= MIN_TEXTURE)
        })
        .collect()
}

/// Pixels within this many pixels of a depth edge are "at an edge".
const EDGE_RADIUS: usize = 4;
/// A depth edge: true planes differing by at least this many within [`EDGE_RADIUS`].
const EDGE_PLANES: usize = 3;

/// Whether pixel `(x, y)` (true plane `z`) lies within [`EDGE_RADIUS`] of a pixel whose
/// true plane differs by [`EDGE_PLANES`] or more: an occlusion edge, which coarse passes
/// blur (about a third of the known pixels of the test scenes).
fn near_depth_edge(s: &SynthScene, t: usize, inv: &[f64], x: usize, y: usize, z: usize) -> bool {
    let (w, h) = (s.images[t].width as usize, s.images[t].height as usize);
    (y.saturating_sub(EDGE_RADIUS)..(y + EDGE_RADIUS + 1).min(h)).any(|yy| {
        (x.saturating_sub(EDGE_RADIUS)..(x + EDGE_RADIUS + 1).min(w)).any(|xx| {
            nearest_plane(inv, s.depths[t][yy * w + xx] as f64).abs_diff(z) >= EDGE_PLANES
        })
    })
}

/// For every tile of `target`, the pixels of known depth (see [`known_pixels`]) whose true
/// surface plane the plan leaves out; returns (misses, identifiable pixels, plane-pixels
/// kept, plane-pixels in all). Asserts that every miss lies at a depth edge (see
/// [`near_depth_edge`]): away from occlusion edges pruning never drops the true plane.
pub(super) fn check_bands(
    s: &SynthScene,
    target: usize,
    planes: usize,
    tile: usize,
    opts: &PruneOptions,
) -> (usize, usize, usize, usize) {
    check_bands_guided(s, target, planes, tile, opts, None)
}

/// [`check_bands`], with the network's coarse pass of `guide` (a model) when given.
pub(super) fn check_bands_guided(
    s: &SynthScene,
    target: usize,
    planes: usize,
    tile: usize,
    opts: &PruneOptions,
    guide: Option<&dyn Backend>,
) -> (usize, usize, usize, usize) {
    let cfg = guide.map_or_else(Config::tiny, |b| b.config().clone());
    // The sources pruning picks (views that see the target).
    let cam = &s.cameras[target];
    let src = rank_views(&s.cameras, cam, cfg.views, Some(target), s.near, s.far).0;
    let pyr = pyramids(s, &src, cfg.levels);
    let refs: Vec<&PyramidSource> = pyr.iter().collect();
    let inv = inverse_depths(s.near, s.far, planes);
    let mut pruner = Pruner::new(&cfg, cam, &refs, &inv, None, opts);
    if let Some(b) = guide {
        let g = network_guide(
            b,
            cam,
            &refs,
            &inv,
            pruner.range(),
            opts.guide_level,
            tile,
            guide_planes(cfg.planes, inv.len()),
            opts.error > 0.0,
        )
        .expect("guide")
        .expect("image large enough for a guide");
        pruner = pruner.with_guide(g, 0.0);
    }
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let known = known_pixels(s, target, &src, &inv);
    let (mut misses, mut checked, mut kept, mut total, mut interior) = (0, 0, 0, 0, 0);
    for y0 in (0..h).step_by(tile) {
        for x0 in (0..w).step_by(tile) {
            for b in pruner.plan(x0, y0, tile) {
                let set = match b.plan {
                    TilePlan::Planes(set) => set,
                    TilePlan::Uncovered | TilePlan::Flat { .. } => continue,
                };
                for y in b.y0..(b.y0 + b.size).min(h) {
                    for x in b.x0..(b.x0 + b.size).min(w) {
                        kept += set.len();
                        total += planes;
                        if !known[y * w + x] {
                            continue;
                        }
                        let z = nearest_plane(&inv, s.depths[target][y * w + x] as f64);
                        checked += 1;
                        if !set.contains(&z) {
                            misses += 1;
                            if !near_depth_edge(s, target, &inv, x, y, z) {
                                interior += 1;
                            }
                        }
                    }
                }
            }
        }
    }
    assert_eq!(
        interior, 0,
        "{interior} known pixels away from depth edges lost their plane"
    );
    (misses, checked, kept, total)
}

pub(super) fn scene(seed: u64, rig: Rig) -> SynthScene {
    scene_sized(seed, rig, 128, 96)
}

pub(super) fn scene_sized(seed: u64, rig: Rig, width: u32, height: u32) -> SynthScene {
    generate(
        seed,
        &SynthOptions {
            views: 8,
            width,
            height,
            rig,
            supersample: 2,
            textures: Vec::new(),
            rolling_shutter: 0.0,
        },
    )
    .expect("scene")
}

/// Depth margin the photo-consistency pass was tuned with.
const PHOTO_MARGIN: usize = 1;

/// Fewest known-depth pixels (of all rigs together) whose true plane pruning must keep.
pub(super) const MIN_KEPT_KNOWN: f64 = 0.995;

#[test]
fn prune_keeps_the_true_surface_plane_of_known_pixels() {
    // The photo-consistency pass at its tuned margin (the guided pass has its own test).
    let opts = PruneOptions {
        coarse: CoarsePass::Photo,
        margin: PHOTO_MARGIN,
        ..PruneOptions::auto()
    };
    assert_keeps_true_planes(&opts, None, 32);
}

/// Over a procedural scene of every rig (240x180, 32 planes, 64-pixel tiles): at least
/// [`MIN_KEPT_KNOWN`] of the known pixels keep their true plane (and those away from
/// depth edges all do, see [`check_bands_guided`]), while pruning leaves out at least
/// 10% of the planes x pixels. `guide`: the model of the network-guided pass.
pub(super) fn assert_keeps_true_planes(
    opts: &PruneOptions,
    guide: Option<&dyn Backend>,
    planes: usize,
) {
    let (mut misses, mut checked, mut kept, mut total) = (0, 0, 0, 0);
    for (i, rig) in Rig::CONCRETE.into_iter().enumerate() {
        let s = scene_sized(9100 + i as u64, rig, 240, 180);
        let target = s.cameras.len() / 2;
        let (m, n, k, t) = check_bands_guided(&s, target, planes, 64, opts, guide);
        println!(
            "{rig}: {m} of {n} known pixels lost their plane; {:.0}% of planes x pixels kept",
            100.0 * k as f64 / t as f64
        );
        assert!(n > 100, "{rig}: too few pixels of known depth ({n})");
        misses += m;
        checked += n;
        kept += k;
        total += t;
    }
    let frac = 1.0 - misses as f64 / checked as f64;
    println!("{:.2}% kept their plane", 100.0 * frac);
    assert!(
        frac >= MIN_KEPT_KNOWN,
        "only {:.1}% of known pixels keep their plane",
        100.0 * frac
    );
    // Pruning must also leave something out.
    assert!(
        (kept as f64) < 0.9 * total as f64,
        "kept {kept} of {total} plane-pixels"
    );
}

#[test]
fn prune_depth_range_from_points_keeps_the_points() {
    let s = scene(77, Rig::Forward);
    let cam = s.cameras[0];
    let inv = inverse_depths(s.near, s.far, 32);
    // Points on the true surfaces of the middle of the image.
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let pts: Vec<_> = (0..200)
        .map(|i| {
            let (x, y) = (w / 4 + (i * 37) % (w / 2), h / 4 + (i * 53) % (h / 2));
            cam.unproject(
                glam::DVec2::new(x as f64 + 0.5, y as f64 + 0.5),
                s.depths[0][y * w + x] as f64,
            )
        })
        .collect();
    let (first, last) = plane_range_from_points(&cam, &pts, &inv).expect("a range");
    for p in &pts {
        let z = nearest_plane(&inv, cam.pose.transform_point(*p).z);
        assert!(
            first <= z && z <= last,
            "plane {z} outside {first}..={last}"
        );
    }
    // Too few points say nothing; points behind the camera neither.
    assert_eq!(plane_range_from_points(&cam, &pts[..1], &inv), None);
    let behind: Vec<_> = (0..40)
        .map(|i| cam.unproject(glam::DVec2::new(10.0 + i as f64, 10.0), -1.0 - i as f64))
        .collect();
    assert_eq!(plane_range_from_points(&cam, &behind, &inv), None);
}

/// The renderer as it was before pruning, kept here as the reference.
fn reference_render(
    backend: &dyn Backend,
    target: &Camera,
    sources: &[&PyramidSource],
    inv: &[f64],
    tile: usize,
) -> Rendered {
    let cfg = backend.config();
    let a = cfg.tile_align();
    let tile = tile.max(1).div_ceil(a) * a;
    let (w, h) = (
        target.intrinsics.width as usize,
        target.intrinsics.height as usize,
    );
    let mut out = Rendered {
        image: crate::imageio::RgbImage::new(w as u32, h as u32),
        depth: vec![0.0; w * h],
        confidence: vec![0.0; w * h],
        coverage: vec![0.0; w * h],
        prune: None,
    };
    let v = cfg.views;
    for y0 in (0..h).step_by(tile) {
        for x0 in (0..w).step_by(tile) {
            let inputs = tile_inputs(
                cfg,
                target,
                sources,
                inv,
                (x0 as i64, y0 as i64),
                (tile, tile),
            )
            .unwrap();
            let (img, sel) = backend.run(&inputs, inv.len()).unwrap();
            let p = cfg.pad(0);
            let tt = tile * tile;
            for yy in 0..tile.min(h - y0) {
                for xx in 0..tile.min(w - x0) {
                    let o = yy * tile + xx;
                    let pix = (y0 + yy) * w + x0 + xx;
                    for ch in 0..3 {
                        out.image.data[pix * 3 + ch] = img[ch * tt + o].clamp(0.0, 1.0);
                    }
                    let (mut rho, mut best, mut cov) = (0.0f64, 0.0f32, 0.0f32);
                    for (z, r) in inv.iter().enumerate() {
                        let s = sel[z * tt + o];
                        rho += s as f64 * r;
                        best = best.max(s);
                        let mut alpha = 0.0;
                        for k in 0..v {
                            alpha +=
                                inputs.levels[0][inputs.alpha_index(0, z, k, (xx + p, yy + p))];
                        }
                        cov += s * alpha / v as f32;
                    }
                    out.depth[pix] = if rho > 0.0 {
                        (1.0 / rho) as f32
                    } else {
                        f32::INFINITY
                    };
                    out.confidence[pix] = best;
                    out.coverage[pix] = cov;
                }
            }
        }
    }
    out
}

fn bits(r: &Rendered) -> Vec<u32> {
    r.image
        .data
        .iter()
        .chain(&r.depth)
        .chain(&r.confidence)
        .chain(&r.coverage)
        .map(|x| x.to_bits())
        .collect()
}

#[test]
fn prune_off_is_bit_identical_to_the_unpruned_renderer() -> TestResult {
    let backend = small_backend(3);
    let s = generate(
        5,
        &SynthOptions {
            views: 5,
            width: 44,
            height: 30,
            rig: Rig::Forward,
            supersample: 1,
            textures: Vec::new(),
            rolling_shutter: 0.0,
        },
    )?;
    let src = nearest(&s.cameras, 2, 3);
    let pyr = pyramids(&s, &src, 2);
    let refs: Vec<&PyramidSource> = pyr.iter().collect();
    let inv = inverse_depths(s.near, s.far, 9);
    let want = reference_render(&backend, &s.cameras[2], &refs, &inv, 16);
    let got = render_view(&backend, &s.cameras[2], &refs, &inv, 16, &|_, _| {})?;
    assert_eq!(bits(&got), bits(&want));
    assert!(got.prune.is_none());
    let got = render_view_pruned(&backend, &s.cameras[2], &refs, &inv, 16, None, &|_, _| {})?;
    assert_eq!(bits(&got), bits(&want));
    Ok(())
}

#[test]
fn prune_skips_uncovered_tiles_with_the_networks_own_output() -> TestResult {
    let backend = small_backend(2);
    let s = generate(
        8,
        &SynthOptions {
            views: 3,
            width: 64,
            height: 48,
            rig: Rig::Forward,
            supersample: 1,
            textures: Vec::new(),
            rolling_shutter: 0.0,
        },
    )?;
    let src = [1usize, 2];
    let pyr = pyramids(&s, &src, 2);
    let refs: Vec<&PyramidSource> = pyr.iter().collect();
    let inv = inverse_depths(s.near, s.far, 6);
    // A target that looks far to the side of the sources sees nothing they see on its
    // left; widen its image so whole tiles lie outside every source.
    let mut cam = s.cameras[0];
    cam.intrinsics.width = 192;
    cam.intrinsics.cx += 128.0;
    let opts = PruneOptions {
        margin: 100,
        ..PruneOptions::auto()
    };
    let pruner = Pruner::new(backend.config(), &cam, &refs, &inv, None, &opts);
    let got = render_view_pruned(&backend, &cam, &refs, &inv, 16, Some(&pruner), &|_, _| {})?;
    let stats = got.prune.clone().expect("stats");
    assert!(stats.uncovered > 0, "{stats:?}");
    assert!(got
        .image
        .data
        .iter()
        .chain(&got.confidence)
        .chain(&got.coverage)
        .all(|x| x.is_finite()));
    assert!(got.depth.iter().all(|x| !x.is_nan()));
    // The skipped tiles hold exactly what the network gives there (the kept planes, with a
    // margin covering every plane, leaves the others equal too).
    let want = render_view(&backend, &cam, &refs, &inv, 16, &|_, _| {})?;
    let diff = got
        .image
        .data
        .iter()
        .zip(&want.image.data)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff < 1e-5, "max difference {diff}");
    let (w, tile) = (192usize, 16usize);
    let mut skipped_pixels = 0;
    for y in 0..48 {
        for x in 0..w {
            if !pruner.covered(x / tile * tile, y / tile * tile, tile) {
                skipped_pixels += 1;
                let p = y * w + x;
                assert_eq!(
                    got.image.data[p * 3..p * 3 + 3],
                    want.image.data[p * 3..p * 3 + 3]
                );
                assert_eq!(got.coverage[p], 0.0);
            }
        }
    }
    assert!(skipped_pixels > 0);
    Ok(())
}

#[test]
fn prune_views_prefer_views_that_see_the_target() {
    let s = scene(31, Rig::Rosette);
    let t = 0;
    let k = 3;
    let cams = &s.cameras;
    let (chosen, ranks) = rank_views(cams, &cams[t], k, Some(t), s.near, s.far);
    assert_eq!(chosen.len(), k);
    assert!(!chosen.contains(&t));
    let useful = ranks
        .iter()
        .filter(|r| r.coverage >= MIN_VIEW_COVERAGE)
        .count();
    for &c in &chosen {
        let r = ranks.iter().find(|r| r.index == c).expect("ranked");
        assert!(
            r.coverage >= MIN_VIEW_COVERAGE || useful < k,
            "view {c} sees {:.2}",
            r.coverage
        );
    }
    // A view looking the opposite way sees nothing of the frustum.
    let mut back = cams[t];
    back.pose.rotation = glam::DMat3::from_rotation_y(std::f64::consts::PI) * back.pose.rotation;
    back.pose.translation =
        glam::DMat3::from_rotation_y(std::f64::consts::PI) * back.pose.translation;
    assert_eq!(view_coverage(&cams[t], &back, s.near, s.far), 0.0);
    assert!(view_coverage(&cams[t], &cams[t], s.near, s.far) > 0.99);
}

#[test]
fn prune_depth_range_from_bounds_covers_the_sources_bounds() {
    let inv = inverse_depths(2.0, 10.0, 33);
    let (first, last) =
        plane_range_from_bounds(&[Some((3.0, 5.0)), Some((2.5, 4.0))], &inv).expect("a range");
    // Every depth in [2.5, 5] lies between two kept planes.
    for d in [2.5, 3.0, 4.0, 5.0] {
        let r = 1.0 / d;
        assert!(
            inv[first] >= r && inv[last] <= r,
            "depth {d} outside planes {first}..={last}"
        );
    }
    assert!(first > 0 && last < 32, "nothing left out: {first}..={last}");
    assert_eq!(
        plane_range_from_bounds(&[Some((3.0, 5.0)), None], &inv),
        None
    );
    assert_eq!(plane_range_from_bounds(&[], &inv), None);
    // Bounds beyond the planes keep the end planes.
    assert_eq!(
        plane_range_from_bounds(&[Some((1.0, 20.0))], &inv),
        Some((0, 32))
    );
}
