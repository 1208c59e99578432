//! Full-image rendering: tiles compose without seams.

use anyhow::Result;
use candle_core::Device;
use deepstereo_core::config::Config;
use deepstereo_core::geometry::inverse_depths;
use deepstereo_core::inputs::PyramidSource;
use deepstereo_core::render::{render_view, CandleBackend};
use deepstereo_core::synth::{generate, SynthOptions, SynthScene};
use deepstereo_core::weights::{init, Trainable};

/// A synthetic scene of 6 views (`generate(seed)` at `width x height`), a `tiny` model
/// initialised as `init` does, and every view's pyramid.
fn synthetic(
    seed: u64,
    width: u32,
    height: u32,
) -> Result<(Config, SynthScene, Trainable, Vec<PyramidSource>)> {
    let cfg = Config::tiny();
    let opts = SynthOptions {
        views: 6,
        width,
        height,
        ..SynthOptions::default()
    };
    let s = generate(seed, &opts)?;
    let t = init(&cfg, &Device::Cpu)?;
    let pyr: Vec<PyramidSource> = (s.cameras.iter().zip(&s.images))
        .map(|(c, i)| PyramidSource::new(c, i, cfg.levels))
        .collect();
    Ok((cfg, s, t, pyr))
}

#[test]
fn tiled_render_equals_whole_image_render() -> Result<()> {
    let (cfg, s, t, pyr) = synthetic(21, 70, 52)?;
    let backend = CandleBackend {
        model: t.model,
        device: Device::Cpu,
    };
    let srcs: Vec<&PyramidSource> = pyr[1..=cfg.views].iter().collect();
    let inv = inverse_depths(s.near, s.far, 12);
    let whole = render_view(&backend, &s.cameras[0], &srcs, &inv, 80, &|_, _| {})?;
    let mut worst = 0f32;
    for tile in [2, 8, 14, 24] {
        let tiled = render_view(&backend, &s.cameras[0], &srcs, &inv, tile, &|_, _| {})?;
        for (a, b) in whole.image.data.iter().zip(&tiled.image.data) {
            worst = worst.max((a - b).abs());
        }
        for (a, b) in whole.depth.iter().zip(&tiled.depth) {
            assert!(
                (a - b).abs() <= 1e-4 * a.abs().max(1.0),
                "depth differs: {a} vs {b}"
            );
        }
    }
    println!("worst image difference tiled vs whole: {worst:e}");
    assert!(worst < 1e-5, "tiled render differs by {worst}");
    Ok(())
}

/// A synthetic scene, a tiny model, its sources for view 0 and 8 planes, and a prior of
/// log-weights falling with view 0's camera depth (a linear field, which trilinear
/// interpolation keeps exactly: nearer planes are favoured) over a box around everything
/// that camera sees on the planes.
struct PriorCase {
    cfg: Config,
    trainable: Trainable,
    scene: SynthScene,
    pyr: Vec<PyramidSource>,
    inv: Vec<f64>,
    zero: deepstereo_core::prior::PriorGrid,
    shell: deepstereo_core::prior::PriorGrid,
}

impl PriorCase {
    fn new() -> Result<Self> {
        use deepstereo_core::prior::PriorGrid;
        use glam::DVec3;
        let (cfg, s, t, pyr) = synthetic(5, 40, 32)?;
        let inv = inverse_depths(s.near, s.far, 8);
        let cam = &s.cameras[0];
        let c = cam.pose.centre();
        let (lo, hi) = (c - DVec3::splat(2.0 * s.far), c + DVec3::splat(2.0 * s.far));
        let zero = PriorGrid::zeros(lo, hi, 8)?;
        let mut shell = zero.clone();
        let [nx, ny, _] = shell.dims;
        for (i, v) in shell.values.iter_mut().enumerate() {
            let p = shell.origin
                + DVec3::new(
                    (i % nx) as f64,
                    ((i / nx) % ny) as f64,
                    (i / (nx * ny)) as f64,
                ) * shell.cell;
            let depth = cam.pose.transform_point(p).z;
            *v = (-4.0 * (depth - s.near) / (s.far - s.near)) as f32;
        }
        Ok(Self {
            cfg,
            trainable: t,
            scene: s,
            pyr,
            inv,
            zero,
            shell,
        })
    }

    fn sources(&self) -> Vec<&PyramidSource> {
        self.pyr[1..=self.cfg.views].iter().collect()
    }

    fn backend(&self, prior: Option<deepstereo_core::prior::PriorGrid>) -> CandleBackend {
        CandleBackend {
            model: self.trainable.model.clone().with_prior(prior),
            device: Device::Cpu,
        }
    }
}

/// A scene prior applied by the renderer: a grid of zeros renders as the network does;
/// a grid favouring near points renders `sum_z s'_z c_z` of the network's layers with
/// the reweighed selection, tile by tile as the whole image; a model file carries the
/// prior through a save and a load.
#[test]
fn scene_prior_reweighs_the_render() -> Result<()> {
    use deepstereo_core::mpi::layers;
    let case = PriorCase::new()?;
    let (srcs, inv, cam) = (case.sources(), &case.inv, &case.scene.cameras[0]);
    let plain = case.backend(None);
    let reference = render_view(&plain, cam, &srcs, inv, 16, &|_, _| {})?;
    let r0 = render_view(
        &case.backend(Some(case.zero.clone())),
        cam,
        &srcs,
        inv,
        16,
        &|_, _| {},
    )?;
    let worst = (reference.image.data.iter().zip(&r0.image.data))
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-5, "a zero prior changed the render by {worst}");
    let shell = case.shell.clone();
    let favoured = render_view(
        &case.backend(Some(shell.clone())),
        cam,
        &srcs,
        inv,
        16,
        &|_, _| {},
    )?;
    let (cl, sl) = layers(&plain, cam, &srcs, inv, 16, &|_, _| {})?;
    let n = 40 * 32;
    let image = shell.apply_tile(
        cam,
        inv,
        (0, 0),
        40,
        &pad(&cl, 8 * 3, n),
        &mut pad(&sl, 8, n),
    );
    let mut differs = 0f32;
    for p in 0..n {
        let (x, y) = (p % 40, p / 40);
        for ch in 0..3 {
            let want = image[ch * 1600 + y * 40 + x].clamp(0.0, 1.0);
            let got = favoured.image.data[p * 3 + ch];
            assert!((want - got).abs() < 1e-4, "pixel {p}: {got} vs {want}");
            differs = differs.max((got - reference.image.data[p * 3 + ch]).abs());
        }
    }
    assert!(differs > 0.01, "the prior changed nothing ({differs})");
    // Through a file.
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("tuned.safetensors");
    let varmap = &case.trainable.varmap;
    deepstereo_core::weights::save_with_prior(&path, &case.cfg, varmap, Some(&shell), &[])?;
    let back = deepstereo_core::weights::load(&path, &Device::Cpu)?;
    let got = back.model.prior().expect("the prior read back");
    assert_eq!((got.dims, &got.values), (shell.dims, &shell.values));
    let moved = (got.origin - shell.origin).length() + (got.cell - shell.cell).abs();
    assert!(moved < 1e-9 * shell.cell, "placement moved by {moved}");
    Ok(())
}

/// The coarse pass of `--prune auto` sees the selection the render sees: with a scene
/// prior, each guide pixel's selection is the network's reweighed by the prior at that
/// pixel's plane points (of the guide level's camera).
#[test]
fn the_prune_guide_applies_the_scene_prior() -> Result<()> {
    use deepstereo_core::inputs::level_camera;
    use deepstereo_core::prune::network_guide;
    let case = PriorCase::new()?;
    let (srcs, inv, cam) = (case.sources(), &case.inv, &case.scene.cameras[0]);
    let guide = |prior| {
        network_guide(
            &case.backend(prior),
            cam,
            &srcs,
            inv,
            (0, 7),
            1,
            16,
            0,
            false,
        )
        .map(|g| g.expect("a guide at level 1"))
    };
    let (plain, tuned) = (guide(None)?, guide(Some(case.shell.clone()))?);
    let (w, h, d) = (plain.width, plain.height, inv.len());
    let lc = level_camera(cam, plain.level, w as u32, h as u32);
    let pixels: Vec<(usize, usize)> = (0..w * h).map(|q| (q % w, q / w)).collect();
    let cells = case.shell.locate_rays(&lc, inv, &pixels);
    let mut moved = 0f32;
    for q in 0..w * h {
        let mut s: Vec<f32> = (0..d).map(|z| plain.sel[z * w * h + q]).collect();
        case.shell.reweigh(&mut s, &cells[q * d..(q + 1) * d]);
        for (z, want) in s.iter().enumerate() {
            let got = tuned.sel[z * w * h + q];
            assert!(
                (got - want).abs() < 1e-5,
                "pixel {q} plane {z}: {got} vs {want}"
            );
            moved = moved.max((got - plain.sel[z * w * h + q]).abs());
        }
    }
    assert!(moved > 0.01, "the prior moved no guide selection ({moved})");
    Ok(())
}

/// `[planes, h*w]` layers of a 40 x 32 image laid out as one 40 x 40 tile.
fn pad(v: &[f32], planes: usize, n: usize) -> Vec<f32> {
    let mut out = vec![0f32; planes * 1600];
    for z in 0..planes {
        out[z * 1600..z * 1600 + n].copy_from_slice(&v[z * n..(z + 1) * n]);
    }
    out
}

/// The layers of chosen tiles equal those of the whole view on those tiles' pixels, and
/// are 0 on every other pixel; a grid of another size or a tile outside it is refused.
#[test]
fn layers_of_some_tiles_equal_the_whole_views_there() -> Result<()> {
    use deepstereo_core::mpi::{layers, layers_of_tiles, reference_camera, TileGrid};
    let (cfg, s, t, pyr) = synthetic(9, 70, 52)?;
    let backend = CandleBackend {
        model: t.model,
        device: Device::Cpu,
    };
    let srcs: Vec<&PyramidSource> = pyr[1..=cfg.views].iter().collect();
    let inv = inverse_depths(s.near, s.far, 6);
    let cam = reference_camera(&s.cameras[0]);
    let (w, h) = (70, 52);
    let grid = TileGrid::new(&cfg, (w, h), 24);
    assert_eq!((grid.across, grid.down), (3, 3));
    let (c, sel) = layers(&backend, &cam, &srcs, &inv, 24, &|_, _| {})?;
    let kept = [1, 5, 6];
    let (ck, sk) = layers_of_tiles(&backend, &cam, &srcs, &inv, (grid, &kept), &|_, _| {})?;
    let inside: Vec<usize> = kept.iter().flat_map(|&i| grid.pixels(i)).collect();
    assert_eq!(inside.len(), 24 * 24 + 22 * 24 + 24 * 4);
    let n = w * h;
    for p in 0..n {
        let kept = inside.contains(&p);
        for z in 0..inv.len() {
            let want = if kept { sel[z * n + p] } else { 0.0 };
            assert_eq!(
                sk[z * n + p].to_bits(),
                want.to_bits(),
                "selection at {p}, plane {z}"
            );
            for ch in 0..3 {
                let i = (z * 3 + ch) * n + p;
                let want = if kept { c[i] } else { 0.0 };
                assert_eq!(ck[i].to_bits(), want.to_bits(), "colour at {p}, plane {z}");
            }
        }
    }
    let other = TileGrid::new(&cfg, (w + 1, h), 24);
    assert!(layers_of_tiles(&backend, &cam, &srcs, &inv, (other, &kept), &|_, _| {}).is_err());
    assert!(layers_of_tiles(&backend, &cam, &srcs, &inv, (grid, &[9]), &|_, _| {}).is_err());
    Ok(())
}
