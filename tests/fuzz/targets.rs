//! Fuzz targets shared by the cargo-fuzz binaries (`fuzz_targets/`), the stable-Rust
//! mutation driver (`driver/`) and the regression test
//! (`deepstereo-core/tests/fuzz_regressions.rs`), which include this file with `#[path]`.
//!
//! Each target feeds arbitrary bytes to one reader (or to the weights/config loader) and
//! returns `Ok` or the error message; any panic is a bug in the library. Readers that
//! look images up on disk get a [`Fixture`] folder holding small valid PNG images. Only
//! `deepstereo_core`, `candle_core`, `glam` and `serde_json` are used.
#![allow(dead_code)]

use deepstereo_core::config::{Config, Conv, TowerConfig};
use deepstereo_core::scene::{
    self, colmap, llff, middlebury, nerf, npy, LoadOptions, RawScene, Scene, SceneFormat, Within,
};
use std::path::{Path, PathBuf};

/// Every target, by name (also the folder names under `regressions/` and `corpus/`).
pub const TARGETS: [&str; 12] = [
    "npy",
    "llff_poses_bounds",
    "colmap_cameras_txt",
    "colmap_images_txt",
    "colmap_points3d_txt",
    "colmap_cameras_bin",
    "colmap_images_bin",
    "colmap_points3d_bin",
    "nerf_transforms",
    "middlebury_par",
    "weights",
    "config_json",
];

/// Image files in the fixture and their size.
const IMAGES: [&str; 3] = ["r_0.png", "r_1.png", "r_2.png"];
const IMAGE_SIZE: (u32, u32) = (8, 6);

/// A temporary folder with the images the scene readers look up; removed on drop.
pub struct Fixture {
    pub dir: PathBuf,
}

impl Fixture {
    pub fn new() -> Self {
        let n = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let dir = std::env::temp_dir().join(format!("deepstereo-fuzz-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("create the fixture folder");
        let (w, h) = IMAGE_SIZE;
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 37 % 251) as u8).collect();
        for name in IMAGES {
            deepstereo_core::imageio::save_rgb8_png(&dir.join(name), w, h, &rgb)
                .expect("write a fixture image");
        }
        Self { dir }
    }
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn msg<T, E: std::fmt::Display>(r: Result<T, E>) -> Result<T, String> {
    r.map_err(|e| e.to_string())
}

/// Resolves a scene like `Scene::load` does after reading (user bounds fill in when the
/// file gives none), then exercises what callers do next.
fn finish(fx: &Fixture, format: SceneFormat, raw: RawScene) -> Result<(), String> {
    let _ = scene::bounds_from_points(&raw.views, &raw.points);
    let opts = LoadOptions {
        near: Some(0.5),
        far: Some(100.0),
        ..Default::default()
    };
    let s = msg(Scene::from_raw(&fx.dir, format, raw, &opts))?;
    for i in 0..s.views.len().min(4) {
        let _ = s.nearest_views(i, 4);
    }
    Ok(())
}

/// Runs target `name` on `data`.
pub fn run(name: &str, data: &[u8], fx: &Fixture) -> Result<(), String> {
    let p = |f: &str| fx.dir.join(f);
    match name {
        "npy" => {
            let a = msg(npy::parse_npy(&p("a.npy"), data))?;
            let (r, _) = a.rows_cols();
            let _sum: f64 = (0..r.min(8)).filter_map(|i| a.row(i)).flatten().sum();
            Ok(())
        }
        "llff_poses_bounds" => {
            let rows =
                npy::parse_npy(&p("poses_bounds.npy"), data).map_or(2, |a| a.rows_cols().0.min(64));
            let images = (0..rows).map(|i| p(&format!("{i:03}.png"))).collect();
            let raw = msg(llff::parse_poses_bounds(
                &p("poses_bounds.npy"),
                data,
                images,
                IMAGE_SIZE,
            ))?;
            finish(fx, SceneFormat::Llff, raw)
        }
        "colmap_cameras_txt" => msg(colmap::parse_cameras_txt(&p("cameras.txt"), data)).map(drop),
        "colmap_images_txt" => msg(colmap::parse_images_txt(&p("images.txt"), data)).map(drop),
        "colmap_points3d_txt" => {
            msg(colmap::parse_points3d_txt(&p("points3D.txt"), data)).map(drop)
        }
        "colmap_cameras_bin" => msg(colmap::parse_cameras_bin(&p("cameras.bin"), data)).map(drop),
        "colmap_images_bin" => msg(colmap::parse_images_bin(&p("images.bin"), data)).map(drop),
        "colmap_points3d_bin" => {
            msg(colmap::parse_points3d_bin(&p("points3D.bin"), data)).map(drop)
        }
        "nerf_transforms" => {
            let raw = msg(nerf::parse_transforms(
                &p("transforms.json"),
                data,
                &Within::anywhere(),
            ))?;
            finish(fx, SceneFormat::Nerf, raw)
        }
        "middlebury_par" => {
            let raw = msg(middlebury::parse_par(
                &p("scene_par.txt"),
                data,
                &Within::anywhere(),
            ))?;
            finish(fx, SceneFormat::Middlebury, raw)
        }
        "weights" => {
            let dev = candle_core::Device::Cpu;
            let t = msg(deepstereo_core::weights::load_bytes(
                &p("model.safetensors"),
                data,
                &dev,
            ))?;
            forward_once(&t.model).map_err(|e| format!("forward: {e}"))
        }
        "config_json" => {
            let cfg: Config = msg(serde_json::from_slice(data))?;
            cfg.validate()?;
            let _ = (
                cfg.parameters(),
                cfg.macs_per_pixel(),
                cfg.receptive_field(),
                cfg.layers(),
            );
            for l in 0..cfg.levels {
                let _ = (
                    cfg.input_size(l, cfg.tile),
                    cfg.input_origin(l, -(cfg.tile as i64)),
                );
            }
            Ok(())
        }
        other => Err(format!("unknown target {other}")),
    }
}

/// One forward pass of a loaded model on a one-plane tile of the smallest size, when the
/// model is small enough to be quick.
fn forward_once(m: &deepstereo_core::model::DeepStereo) -> candle_core::Result<()> {
    let cfg = m.config();
    if cfg.parameters() > 200_000 || cfg.receptive_field() > 256 {
        return Ok(());
    }
    let th = cfg.tile_align();
    let inputs = (0..cfg.levels)
        .map(|l| {
            let s = cfg.input_size(l, th);
            candle_core::Tensor::full(
                0.5f32,
                (1, 1, cfg.in_channels(), s, s),
                &candle_core::Device::Cpu,
            )
        })
        .collect::<candle_core::Result<Vec<_>>>()?;
    let o = m.forward(&inputs)?;
    let v = o.image.flatten_all()?.to_vec1::<f32>()?;
    if v.iter().any(|x| !x.is_finite()) {
        candle_core::bail!("non-finite output from finite weights");
    }
    Ok(())
}

// ---- Seeds: small valid inputs for every target --------------------------------------

fn npy_bytes(fx: &Fixture, shape: &[usize], data: &[f64], f32: bool) -> Vec<u8> {
    let path = fx.dir.join("seed.npy");
    if f32 {
        let d: Vec<f32> = data.iter().map(|&v| v as f32).collect();
        npy::write_npy_f32(&path, shape, &d).expect("write npy");
    } else {
        npy::write_npy_f64(&path, shape, data).expect("write npy");
    }
    std::fs::read(&path).expect("read npy")
}

/// `n` LLFF rows: cameras along x looking down -z in LLFF's [down, right, backwards].
fn llff_rows(n: usize) -> Vec<f64> {
    (0..n)
        .flat_map(|i| {
            let c = [0.1 * i as f64, 0.0, 0.0];
            let (h, w, f) = (6.0, 8.0, 7.5);
            [
                0.0, 1.0, 0.0, c[0], h, 1.0, 0.0, 0.0, c[1], w, 0.0, 0.0, -1.0, c[2], f, 1.5, 20.0,
            ]
        })
        .collect()
}

fn le(out: &mut Vec<u8>, parts: &[&[u8]]) {
    parts.iter().for_each(|p| out.extend_from_slice(p));
}

fn small_config(levels: usize, skip: bool) -> Config {
    let c = |k, ch| Conv {
        kernel: k,
        channels: ch,
    };
    Config {
        name: "fuzz".into(),
        views: 2,
        planes: 4,
        levels,
        tile: 4,
        select: TowerConfig {
            levels,
            level_convs: vec![c(3, 3)],
            merge_convs: vec![c(3, 3)],
        },
        depth_convs: vec![c(3, 2), c(3, 1)],
        colour: TowerConfig {
            levels: 1,
            level_convs: vec![c(1, 3)],
            merge_convs: vec![],
        },
        colour_skip: skip,
        pool: None,
        render_planes: None,
    }
}

/// Valid inputs of target `name` (the seed corpus).
pub fn seeds(name: &str, fx: &Fixture) -> Vec<Vec<u8>> {
    let s = |t: &str| t.as_bytes().to_vec();
    match name {
        "npy" => vec![
            npy_bytes(fx, &[2, 17], &llff_rows(2), false),
            npy_bytes(fx, &[5], &[1.0, -2.0, 0.5, 1e300, 0.0], true),
        ],
        "llff_poses_bounds" => vec![npy_bytes(fx, &[3, 17], &llff_rows(3), false), npy_bytes(fx, &[2, 17], &llff_rows(2), true)],
        "colmap_cameras_txt" => vec![s(
            "# Camera list\n1 PINHOLE 8 6 7.5 7.4 4 3\n2 OPENCV 8 6 7 7 4.1 2.9 0.01 -0.02 0.001 0.002\n3 SIMPLE_RADIAL 8 6 7 4 3 0.05\n",
        )],
        "colmap_images_txt" => vec![s(
            "# Image list\n1 1 0 0 0 0 0 0 1 r_0.png\n10.5 2.5 -1 4 3.5 7\n2 0.9950042 0 0.0998334 0 -0.1 0 0 2 r_1.png\n\n",
        )],
        "colmap_points3d_txt" => vec![s("# 3D points\n1 0.1 0.2 3 255 0 0 0.5 1 0 2 1\n2 -1 0.5 7.5 0 255 0 0.1 1 1\n")],
        "colmap_cameras_bin" => {
            let mut b = 2u64.to_le_bytes().to_vec();
            le(&mut b, &[&1u32.to_le_bytes(), &1i32.to_le_bytes(), &8u64.to_le_bytes(), &6u64.to_le_bytes()]);
            [7.5f64, 7.4, 4.0, 3.0].iter().for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
            le(&mut b, &[&2u32.to_le_bytes(), &4i32.to_le_bytes(), &8u64.to_le_bytes(), &6u64.to_le_bytes()]);
            [7.0f64, 7.0, 4.0, 3.0, 0.01, -0.02, 0.001, 0.002].iter().for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
            vec![b]
        }
        "colmap_images_bin" => {
            let mut b = 2u64.to_le_bytes().to_vec();
            for (id, q, name, pts) in [(1u32, [1.0f64, 0.0, 0.0, 0.0], "r_0.png", 1u64), (2, [0.995, 0.0, 0.0998, 0.0], "r_1.png", 0)] {
                b.extend_from_slice(&id.to_le_bytes());
                q.iter().chain(&[0.1, 0.0, 0.0]).for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
                b.extend_from_slice(&1u32.to_le_bytes());
                le(&mut b, &[name.as_bytes(), &[0], &pts.to_le_bytes()]);
                for _ in 0..pts {
                    le(&mut b, &[&1.5f64.to_le_bytes(), &2.5f64.to_le_bytes(), &(-1i64).to_le_bytes()]);
                }
            }
            vec![b]
        }
        "colmap_points3d_bin" => {
            let mut b = 1u64.to_le_bytes().to_vec();
            b.extend_from_slice(&7u64.to_le_bytes());
            [0.1f64, 0.2, 3.0].iter().for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
            le(&mut b, &[&[255, 0, 0], &0.5f64.to_le_bytes(), &1u64.to_le_bytes(), &1u32.to_le_bytes(), &0u32.to_le_bytes()]);
            vec![b]
        }
        "nerf_transforms" => vec![
            s(r#"{"camera_angle_x": 0.69, "near": 2.0, "far": 6.0, "frames": [
  {"file_path": "r_0", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]},
  {"file_path": "r_1.png", "transform_matrix": [[0.995,0,0.0998,0.4],[0,1,0,0],[-0.0998,0,0.995,4],[0,0,0,1]]}]}"#),
            s(r#"{"fl_x": 7.5, "fl_y": 7.4, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "k1": 0.01, "p2": 0.001, "camera_model": "OPENCV",
  "frames": [{"file_path": "r_2.png", "fl_x": 7.0, "transform_matrix": [[1,0,0,0.1],[0,1,0,0],[0,0,1,3]]}]}"#),
        ],
        "middlebury_par" => vec![s(
            "2\nr_0.png 7.5 0 4 0 7.4 3 0 0 1 1 0 0 0 1 0 0 0 1 0 0 2\nr_1.png 7.5 0 4 0 7.4 3 0 0 1 1 0 0 0 1 0 0 0 1 -0.1 0 2\n",
        )],
        "weights" => [small_config(2, true), small_config(1, false)]
            .iter()
            .map(|cfg| {
                let t = deepstereo_core::weights::init(cfg, &candle_core::Device::Cpu).expect("init");
                let path = fx.dir.join("seed.safetensors");
                deepstereo_core::weights::save(&path, cfg, &t.varmap).expect("save");
                std::fs::read(&path).expect("read weights")
            })
            .collect(),
        "config_json" => [Config::tiny(), Config::paper(), small_config(2, true)]
            .iter()
            .map(|c| serde_json::to_vec_pretty(c).expect("config json"))
            .collect(),
        _ => Vec::new(),
    }
}

/// The regression inputs kept for `name` under `root` (`regressions/<name>/*`), sorted.
pub fn regressions(root: &Path, name: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(root.join(name))
        .map(|d| {
            d.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_file())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}
