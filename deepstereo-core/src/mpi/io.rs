//! The MPI directory format: `mpi.json` and one RGBA PNG per plane, converted here and
//! nowhere else.
//!
//! `mpi.json`: `version` 1, `width`, `height`, `fx`, `fy`, `cx`, `cy` (pixel centres at
//! `i + 0.5`), `R` (9 values, row-major) and `t` (3) with `p_cam = R p_world + t` (as
//! `inspect --json` writes a camera), `inverse_depths` (1/z along the camera's axis, near
//! to far, 0 for a plane at infinity) and `planes` (file names in the same order); and,
//! when the image extends beyond the view it was baked for (`mpi --margin`), `margin`:
//! the pixels added on every side (the view is the camera with `width - 2 margin`,
//! `height - 2 margin`, `cx - margin`, `cy - margin`).
//! Planes are 8-bit RGBA PNGs with straight alpha, colours encoded as the photographs.

use super::Mpi;
use crate::camera::{Camera, Intrinsics, WorldToCamera};
use crate::error::{Error, Result};
use crate::imageio::write_atomic;
use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The format's version.
pub const VERSION: u32 = 1;
/// The description's file name inside an MPI directory.
pub const JSON_NAME: &str = "mpi.json";

/// `mpi.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MpiJson {
    pub version: u32,
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(rename = "R")]
    pub r: Vec<f64>,
    pub t: Vec<f64>,
    pub inverse_depths: Vec<f64>,
    pub planes: Vec<String>,
    /// Pixels added on every side beyond the view it was baked for (absent: 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub margin: u32,
}

fn is_zero(m: &u32) -> bool {
    *m == 0
}

impl MpiJson {
    /// The description of `mpi` with plane files `plane_NN.png`.
    pub fn of(mpi: &Mpi) -> Self {
        let k = &mpi.camera.intrinsics;
        let r = mpi
            .camera
            .pose
            .rotation
            .transpose()
            .to_cols_array()
            .to_vec(); // row-major
        let t = mpi.camera.pose.translation.to_array().to_vec();
        Self {
            version: VERSION,
            width: k.width,
            height: k.height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            r,
            t,
            inverse_depths: mpi.inv_depths.clone(),
            planes: (0..mpi.planes().len())
                .map(|z| format!("plane_{z:02}.png"))
                .collect(),
            margin: mpi.margin,
        }
    }

    /// The reference camera, checked (finite, positive focal lengths and size, a rotation).
    pub fn camera(&self, file: &Path) -> Result<Camera> {
        let bad = |m: String| Error::format(file, m);
        if self.version != VERSION {
            return Err(bad(format!(
                "version {} (this reader knows {VERSION})",
                self.version
            )));
        }
        if self.r.len() != 9 || self.t.len() != 3 {
            return Err(bad("'R' needs 9 values and 't' 3".into()));
        }
        let k = Intrinsics::pinhole(self.fx, self.fy, self.cx, self.cy, self.width, self.height);
        k.validate().map_err(bad)?;
        if 2 * self.margin as u64 >= self.width.min(self.height) as u64 {
            return Err(bad(format!(
                "a margin of {} leaves nothing of a {}x{} image",
                self.margin, self.width, self.height
            )));
        }
        let mut cols = [0f64; 9];
        cols.copy_from_slice(&self.r);
        let rotation = DMat3::from_cols_array(&cols).transpose();
        let pose =
            WorldToCamera::new_checked(rotation, DVec3::new(self.t[0], self.t[1], self.t[2]))
                .map_err(|m| bad(format!("R, t: {m}")))?;
        Ok(Camera::global(k, pose))
    }
}

/// Writes `mpi` into `dir` (created if needed): `mpi.json` and the plane PNGs, each
/// atomically.
pub fn write(mpi: &Mpi, dir: &Path) -> Result<MpiJson> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let json = MpiJson::of(mpi);
    let (w, h) = (mpi.width() as u32, mpi.height() as u32);
    for (plane, name) in mpi.planes().iter().zip(&json.planes) {
        let path = dir.join(name);
        write_atomic(&path, &encode_rgba_png(&path, w, h, plane)?)?;
    }
    let text = serde_json::to_string_pretty(&json)
        .map_err(|e| Error::Invalid(format!("cannot serialize the MPI description: {e}")))?;
    write_atomic(&dir.join(JSON_NAME), text.as_bytes())?;
    Ok(json)
}

/// PNG bytes of `[H, W, 4]` values in [0, 1] (rounded to 8 bits).
pub fn encode_rgba_png(path: &Path, w: u32, h: u32, rgba: &[f32]) -> Result<Vec<u8>> {
    let bytes: Vec<u8> = (rgba.iter())
        .map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect();
    let mut buf = Vec::new();
    let enc = image::codecs::png::PngEncoder::new(&mut buf);
    image::ImageEncoder::write_image(enc, &bytes, w, h, image::ExtendedColorType::Rgba8)
        .map_err(|e| Error::image(path, format!("cannot encode PNG: {e}")))?;
    Ok(buf)
}

/// Reads an MPI directory, checking the description and every plane's size.
pub fn read(dir: &Path) -> Result<Mpi> {
    let file = dir.join(JSON_NAME);
    let text = std::fs::read_to_string(&file).map_err(|e| Error::io(&file, e))?;
    let json: MpiJson =
        serde_json::from_str(&text).map_err(|e| Error::format(&file, e.to_string()))?;
    let camera = json.camera(&file)?;
    if json.planes.is_empty() || json.planes.len() != json.inverse_depths.len() {
        return Err(Error::format(
            &file,
            format!(
                "{} planes but {} inverse depths (need one each, at least one)",
                json.planes.len(),
                json.inverse_depths.len()
            ),
        ));
    }
    if json
        .inverse_depths
        .iter()
        .any(|r| !(r.is_finite() && *r >= 0.0))
    {
        return Err(Error::format(
            &file,
            "inverse depths must be finite and not negative",
        ));
    }
    if let Some(i) = (1..json.inverse_depths.len())
        .find(|&i| json.inverse_depths[i] > json.inverse_depths[i - 1])
    {
        return Err(Error::format(
            &file,
            format!(
                "inverse depths must run near to far (not increasing): {} then {}",
                json.inverse_depths[i - 1],
                json.inverse_depths[i]
            ),
        ));
    }
    if let Some(name) = json.planes.iter().find(|n| !is_plain_file_name(n)) {
        return Err(Error::format(
            &file,
            format!("plane {name:?} is not a file name in the MPI's directory"),
        ));
    }
    let planes = (json.planes.iter())
        .map(|name| read_plane(&dir.join(name), json.width, json.height))
        .collect::<Result<Vec<_>>>()?;
    let mut mpi = Mpi::new(camera, json.inverse_depths, planes)
        .map_err(|e| Error::format(&file, e.to_string()))?;
    mpi.margin = json.margin;
    Ok(mpi)
}

/// The MPIs of a directory written by `deepstereo mpi`: the one in `dir` itself (its
/// `mpi.json`), else one per subdirectory holding an `mpi.json`, in name order.
pub fn read_dir(dir: &Path) -> Result<Vec<Mpi>> {
    if dir.join(JSON_NAME).is_file() {
        return Ok(vec![read(dir)?]);
    }
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut subs: Vec<_> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join(JSON_NAME).is_file())
        .collect();
    subs.sort();
    if subs.is_empty() {
        return Err(Error::format(
            dir,
            format!("no {JSON_NAME} in it or in its subdirectories: not an MPI directory"),
        ));
    }
    subs.iter().map(|p| read(p)).collect()
}

/// Whether `name` names a file directly in a directory: one normal path component (no
/// separator, `..`, root or prefix).
fn is_plain_file_name(name: &str) -> bool {
    let mut parts = Path::new(name).components();
    matches!(
        (parts.next(), parts.next()),
        (Some(std::path::Component::Normal(_)), None)
    ) && !name.contains(['/', '\\'])
}

fn read_plane(path: &Path, w: u32, h: u32) -> Result<Vec<f32>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let img = image::load_from_memory(&bytes)
        .map_err(|e| Error::image(path, format!("cannot decode: {e}")))?
        .to_rgba8();
    if img.dimensions() != (w, h) {
        let (iw, ih) = img.dimensions();
        return Err(Error::image(
            path,
            format!("plane is {iw}x{ih}, mpi.json says {w}x{h}"),
        ));
    }
    Ok(img.into_raw().iter().map(|&b| b as f32 / 255.0).collect())
}
