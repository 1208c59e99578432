//! Writing scenes (NeRF / instant-ngp layout with depth maps), scene sets, user photo
//! textures and contact sheets.

use super::{generate, scene_seed, SynthOptions, SynthScene};
use crate::error::{Error, Result};
use crate::imageio::{write_atomic, RgbImage};
use crate::scene::npy::write_npy_f32;
use glam::{DMat3, DVec3};
use rayon::prelude::*;
use serde_json::json;
use std::path::{Path, PathBuf};

/// File extensions accepted as texture photos (case-insensitive).
const TEXTURE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];
/// Smallest side of a texture photo.
pub const MIN_TEXTURE_SIDE: u32 = 8;
/// Pixels between the cells of a contact sheet.
const SHEET_GAP: u32 = 2;
/// Grey level of a contact sheet's background.
const SHEET_BACKGROUND: f32 = 0.12;
/// Control points of the inverse-depth colour map (an inferno-like ramp, far = dark).
const DEPTH_COLOURS: [[f32; 3]; 5] = [
    [0.0015, 0.0005, 0.014],
    [0.34, 0.06, 0.43],
    [0.73, 0.21, 0.33],
    [0.98, 0.55, 0.04],
    [0.99, 1.0, 0.64],
];

/// The directory of scene `index` in a set written to `out`.
pub fn scene_dir(out: &Path, index: usize) -> PathBuf {
    out.join(format!("scene_{index:04}"))
}

/// Writes a scene to `dir`: `images/view_NNN.png`, `depth/view_NNN.npy` (float32
/// `[H, W]`) and, last, `transforms.json` (NeRF layout: OpenGL camera-to-world
/// matrices, `fl_x fl_y cx cy w h` per frame, top-level `near far rig seed`; a
/// rolling-shutter camera adds instant-ngp's `transform_matrix_start`,
/// `transform_matrix_end` and `rolling_shutter`, with `transform_matrix` its mid-readout
/// pose). Every file is written atomically.
pub fn write_scene(dir: &Path, scene: &SynthScene) -> Result<()> {
    let n = scene.cameras.len();
    if scene.images.len() != n || scene.depths.len() != n {
        return Err(Error::Invalid(format!(
            "{}: scene has {n} cameras, {} images and {} depth maps",
            dir.display(),
            scene.images.len(),
            scene.depths.len()
        )));
    }
    let gl_axes = DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));
    let mut frames = Vec::with_capacity(n);
    for (i, ((cam, img), depth)) in scene
        .cameras
        .iter()
        .zip(&scene.images)
        .zip(&scene.depths)
        .enumerate()
    {
        let k = &cam.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        if img.width != k.width || img.height != k.height || depth.len() != w * h {
            return Err(Error::Invalid(format!(
                "{}: view {i}: image {}x{} / depth of {} values do not match the camera's {w}x{h}",
                dir.display(),
                img.width,
                img.height,
                depth.len()
            )));
        }
        let image_rel = format!("images/view_{i:03}.png");
        let depth_rel = format!("depth/view_{i:03}.npy");
        img.save_png(&dir.join(&image_rel))?;
        write_npy_f32(&dir.join(&depth_rel), &[h, w], depth)?;
        let matrix = |pose: &crate::camera::WorldToCamera| {
            let c2w = pose.inverse();
            let r_gl = c2w.rotation * gl_axes;
            let t = c2w.translation;
            let row = |r: usize| {
                let v = r_gl.row(r);
                json!([v.x, v.y, v.z, t[r]])
            };
            json!([row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]])
        };
        let mut frame = json!({
            "file_path": image_rel,
            "depth_path": depth_rel,
            "transform_matrix": matrix(&cam.pose),
            "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height,
        });
        if let (Some(rs), Some(obj)) = (&cam.rolling_shutter, frame.as_object_mut()) {
            // instant-ngp's convention; `transform_matrix` is the mid-readout pose, the
            // one a reader that ignores the shutter should use.
            obj.insert("transform_matrix_start".into(), matrix(&rs.start));
            obj.insert("transform_matrix_end".into(), matrix(&rs.end));
            obj.insert(
                "rolling_shutter".into(),
                json!(rs.to_instant_ngp(k.width, k.height)),
            );
        }
        frames.push(frame);
    }
    let doc = json!({
        "camera_model": "PINHOLE",
        "near": scene.near,
        "far": scene.far,
        "rig": scene.rig.name(),
        "seed": scene.seed,
        "frames": frames,
    });
    let path = dir.join("transforms.json");
    let bytes = serde_json::to_vec_pretty(&doc)
        .map_err(|e| Error::Invalid(format!("{}: cannot encode JSON: {e}", path.display())))?;
    write_atomic(&path, &bytes)
}

/// Generates and writes `count` scenes to `out/scene_0000`, ... in parallel; scene `i`
/// uses the seed [`scene_seed`]`(base_seed, i)`.
pub fn write_scenes(out: &Path, count: usize, base_seed: u64, opts: &SynthOptions) -> Result<()> {
    write_scenes_progress(out, count, base_seed, opts, &|_| {})
}

/// [`write_scenes`], calling `progress(index)` after each scene is written.
pub fn write_scenes_progress(
    out: &Path,
    count: usize,
    base_seed: u64,
    opts: &SynthOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<()> {
    opts.validate()?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    (0..count).into_par_iter().try_for_each(|i| {
        let scene = generate(scene_seed(base_seed, i), opts)?;
        write_scene(&scene_dir(out, i), &scene)?;
        progress(i);
        Ok(())
    })
}

/// Loads every PNG and JPEG in `dir` (sorted by name) as a texture photo. A file that
/// cannot be decoded or is smaller than `MIN_TEXTURE_SIDE` is an error naming it, and
/// so is a folder without any.
pub fn load_textures(dir: &Path) -> Result<Vec<RgbImage>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut paths = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| Error::io(dir, e))?.path();
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase());
        if path.is_file() && ext.is_some_and(|e| TEXTURE_EXTENSIONS.contains(&e.as_str())) {
            paths.push(path);
        }
    }
    if paths.is_empty() {
        return Err(Error::format(
            dir,
            "no PNG or JPEG texture images in this folder",
        ));
    }
    paths.sort();
    paths
        .iter()
        .map(|p| {
            let img = RgbImage::load(p)?;
            if img.width < MIN_TEXTURE_SIDE || img.height < MIN_TEXTURE_SIDE {
                return Err(Error::image(
                    p,
                    format!(
                        "texture is {}x{}, smaller than {MIN_TEXTURE_SIDE}x{MIN_TEXTURE_SIDE}",
                        img.width, img.height
                    ),
                ));
            }
            Ok(img)
        })
        .collect()
}

/// The inverse-depth colour of depth `z` for a scene spanning `[near, far]`.
fn depth_colour(z: f32, near: f64, far: f64) -> [f32; 3] {
    let (a, b) = (1.0 / far, 1.0 / near);
    let t = if z > 0.0 && b > a {
        ((1.0 / z as f64 - a) / (b - a)).clamp(0.0, 1.0) as f32
    } else {
        0.0
    };
    let x = t * (DEPTH_COLOURS.len() - 1) as f32;
    let i = (x as usize).min(DEPTH_COLOURS.len() - 2);
    let f = x - i as f32;
    let (c0, c1) = (DEPTH_COLOURS[i], DEPTH_COLOURS[i + 1]);
    [
        c0[0] + (c1[0] - c0[0]) * f,
        c0[1] + (c1[1] - c0[1]) * f,
        c0[2] + (c1[2] - c0[2]) * f,
    ]
}

/// Copies `w x h` pixels given by `colour(x, y)` into `sheet` at `(x0, y0)`.
fn blit(
    sheet: &mut RgbImage,
    x0: u32,
    y0: u32,
    w: u32,
    h: u32,
    colour: impl Fn(usize) -> [f32; 3],
) {
    for y in 0..h.min(sheet.height.saturating_sub(y0)) {
        for x in 0..w.min(sheet.width.saturating_sub(x0)) {
            let c = colour((y * w + x) as usize);
            let i = (((y0 + y) * sheet.width + x0 + x) * 3) as usize;
            sheet.data[i..i + 3].copy_from_slice(&c);
        }
    }
}

/// A grid with one row per scene: `per_scene` of its views (spread over the set), each
/// followed by its colour-mapped inverse depth (bright = near).
pub fn contact_sheet(scenes: &[SynthScene], per_scene: usize) -> RgbImage {
    let cw = scenes
        .iter()
        .flat_map(|s| &s.images)
        .map(|i| i.width)
        .max()
        .unwrap_or(0);
    let ch = scenes
        .iter()
        .flat_map(|s| &s.images)
        .map(|i| i.height)
        .max()
        .unwrap_or(0);
    let cols = (2 * per_scene) as u32;
    let width = SHEET_GAP + cols * (cw + SHEET_GAP);
    let height = SHEET_GAP + scenes.len() as u32 * (ch + SHEET_GAP);
    let mut sheet = RgbImage::new(width, height);
    sheet.data.fill(SHEET_BACKGROUND);
    for (r, s) in scenes.iter().enumerate() {
        let n = s.images.len().min(s.depths.len());
        let y0 = SHEET_GAP + r as u32 * (ch + SHEET_GAP);
        for j in 0..per_scene.min(n) {
            let v = j * n / per_scene.min(n);
            let (img, depth) = (&s.images[v], &s.depths[v]);
            let (w, h) = (img.width, img.height);
            let x0 = SHEET_GAP + 2 * j as u32 * (cw + SHEET_GAP);
            blit(&mut sheet, x0, y0, w, h, |p| {
                img.data
                    .get(3 * p..3 * p + 3)
                    .map_or([0.0; 3], |c| [c[0], c[1], c[2]])
            });
            blit(&mut sheet, x0 + cw + SHEET_GAP, y0, w, h, |p| {
                depth
                    .get(p)
                    .map_or([0.0; 3], |&z| depth_colour(z, s.near, s.far))
            });
        }
    }
    sheet
}
