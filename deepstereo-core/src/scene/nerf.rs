//! NeRF / instant-ngp / nerfstudio scenes: `transforms.json` (or `transforms_train.json`).
//!
//! # Convention
//! Each frame's `transform_matrix` is a 4x4 (or 3x4) camera-to-world matrix in the
//! OpenGL/NeRF camera axes: x right, y up, z backwards. Intrinsics come from `fl_x`/`fl_y`
//! or `camera_angle_x`/`camera_angle_y` (radians, full field of view), `cx`/`cy`
//! (default `w/2`, `h/2`), `w`/`h` (else read from the image header) and optional
//! OpenCV distortion `k1 k2 p1 p2`; each key may be at the top level or in a frame, the
//! frame's value winning (a frame's own focal key beats any top-level one). `cx`/`cy` are
//! continuous pixel coordinates with pixel centres at `i + 0.5` (instant-ngp's and
//! nerfstudio's convention; the original NeRF code's rays are half a pixel off that).
//!
//! # Conversion (once, here)
//! `R_cv = R_gl * diag(1, -1, -1)` (flip the y and z camera axes), the centre unchanged;
//! that camera-to-world pose is inverted to the [`crate::camera::WorldToCamera`] pose.
//!
//! # Rolling shutter (instant-ngp)
//! A frame may give `transform_matrix_start` and `transform_matrix_end` (the poses at the
//! start and end of its motion, `t = 0` and `t = 1`; the start defaults to
//! `transform_matrix`, the end to the start, as in instant-ngp, which then ignores
//! `transform_matrix`), and `rolling_shutter = [A, B, C]` or `[A, B, C, D]` (top level or,
//! overriding, per frame) gives each pixel its time `t = A + B u/W + C v/H + D/2`; see
//! [`crate::camera::rolling`] for what instant-ngp's loader does with these and how they
//! are converted. Such a frame's camera is a [`Camera::rolling`] camera; without any of
//! these keys it is a global shutter at `transform_matrix`.
//!
//! # Other keys
//! `file_path` is relative to the JSON file's folder; without an existing file at that
//! path, `.png`, `.jpg` and `.jpeg` are appended in turn (NeRF synthetic omits them);
//! every candidate must resolve inside the scene ([`Within`]) before it is looked at.
//! Optional top-level `near` and `far` give scene bounds; no bounds are invented.
//! instant-ngp's `aabb_scale`, `scale` and `offset` only place the scene in its own
//! training cube and do not change relative geometry, so they are ignored: the world
//! here is the file's world. Fisheye cameras and nonzero `k3`/`k4` are rejected.
//! Frames keep the file's order.

use super::{make_view, RawScene, Within};
use crate::camera::{Camera, CameraToWorld, Distortion, Intrinsics, RollingShutter, WorldToCamera};
use crate::error::{Error, Result};
use crate::imageio::MAX_IMAGE_SIDE;
use glam::{DMat3, DVec3};
use serde_json::{Map, Value};
use std::path::{Path, PathBuf};

/// File names tried, in order.
pub const TRANSFORMS_FILES: [&str; 2] = ["transforms.json", "transforms_train.json"];
/// Extensions appended to a `file_path` that names no existing file.
const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];
/// Largest tolerated deviation of a 4x4 matrix's last row from `[0, 0, 0, 1]`.
const LAST_ROW_TOLERANCE: f64 = 1e-6;
/// Camera models (nerfstudio `camera_model`) that this reader handles.
const SUPPORTED_MODELS: [&str; 3] = ["OPENCV", "PINHOLE", "SIMPLE_PINHOLE"];

/// Reads a NeRF-style scene directory; every image must resolve inside `within`.
pub fn read(dir: &Path, within: &Within) -> Result<RawScene> {
    let file = TRANSFORMS_FILES
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.is_file())
        .ok_or_else(|| Error::format(dir, "no transforms.json or transforms_train.json"))?;
    within.check(dir, "the scene file", &file)?;
    let bytes = std::fs::read(&file).map_err(|e| Error::io(&file, e))?;
    parse_transforms(&file, &bytes, within)
}

/// Parses the bytes of a `transforms.json` at `file` (image paths are resolved, and
/// image headers read, relative to its folder; each must resolve inside `within` before
/// anything of it is touched).
pub fn parse_transforms(file: &Path, bytes: &[u8], within: &Within) -> Result<RawScene> {
    let file = file.to_path_buf();
    let dir = file.parent().unwrap_or(Path::new("."));
    let json: Value = serde_json::from_slice(bytes)
        .map_err(|e| Error::parse(&file, Some(e.line()), format!("invalid JSON: {e}")))?;
    let fname = file
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let top = json
        .as_object()
        .ok_or_else(|| Error::parse(&file, None, "the top level must be an object"))?;
    let frames = match top.get("frames") {
        Some(Value::Array(a)) if !a.is_empty() => a,
        Some(Value::Array(_)) => return Err(Error::parse(&file, None, "'frames' is empty")),
        Some(_) => return Err(Error::parse(&file, None, "'frames' must be an array")),
        None => return Err(Error::parse(&file, None, "missing 'frames'")),
    };
    let base = file.parent().unwrap_or(dir);

    let top_err = |msg: String| Error::parse(&file, None, msg);
    let near = number(top, "near").map_err(top_err)?;
    let far = number(top, "far").map_err(top_err)?;
    let bounds = match (near, far) {
        (Some(n), Some(f)) => {
            super::check_bounds(n, f).map_err(|m| top_err(format!("near/far: {m}")))?;
            Some((n, f))
        }
        (None, None) => None,
        _ => return Err(top_err("'near' and 'far' must be given together".into())),
    };

    let mut views = Vec::with_capacity(frames.len());
    for (i, frame) in frames.iter().enumerate() {
        let ferr = |msg: String| Error::parse(&file, None, format!("frame {i}: {msg}"));
        let frame = frame
            .as_object()
            .ok_or_else(|| ferr("must be an object".into()))?;
        let (rel, image_path) = frame_image((&file, base, within), i, frame)?;
        let intrinsics = intrinsics(top, frame, &image_path).map_err(ferr)?;
        let shutter = rolling_shutter(top, frame).map_err(ferr)?;
        let start_key = if frame.contains_key("transform_matrix_start") {
            "transform_matrix_start"
        } else {
            "transform_matrix"
        };
        let start = matrix(frame, start_key).map_err(ferr)?;
        let end = match frame.contains_key("transform_matrix_end") {
            true => Some(matrix(frame, "transform_matrix_end").map_err(ferr)?),
            false => None,
        };
        let pose = pose_of(start).map_err(|m| format!("'{start_key}': {m}"));
        let mut view = make_view(&file, rel, image_path, intrinsics, pose, None)?;
        if start_key != "transform_matrix" || end.is_some() || shutter.is_some() {
            let cam_err = |m: String| super::camera_err(&file, rel, m);
            let start = view.camera.pose;
            let end = match end {
                Some(m) => {
                    pose_of(m).map_err(|m| cam_err(format!("'transform_matrix_end': {m}")))?
                }
                None => start,
            };
            let (w, h) = (intrinsics.width, intrinsics.height);
            let abcd = shutter.unwrap_or([0.0; 4]);
            let rs = RollingShutter::from_instant_ngp(start, end, abcd, w, h).map_err(cam_err)?;
            view.camera = Camera::rolling(intrinsics, rs);
        }
        views.push(view);
    }
    Ok(RawScene {
        views,
        bounds,
        points: Vec::new(),
        notes: vec![format!("NeRF: cameras from {fname}")],
    })
}

/// A numeric key of an object: `Ok(None)` if absent, `Err` if not a finite number.
fn number(obj: &Map<String, Value>, key: &str) -> std::result::Result<Option<f64>, String> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => v
            .as_f64()
            .filter(|x| x.is_finite())
            .map(Some)
            .ok_or_else(|| format!("'{key}' must be a finite number")),
    }
}

/// A key looked up in the frame first, then at the top level.
fn either(
    top: &Map<String, Value>,
    frame: &Map<String, Value>,
    key: &str,
) -> std::result::Result<Option<f64>, String> {
    match number(frame, key)? {
        Some(v) => Ok(Some(v)),
        None => number(top, key),
    }
}

/// The world-to-camera pose (OpenCV axes) of a camera-to-world matrix's columns.
fn pose_of(c2w: [DVec3; 4]) -> std::result::Result<WorldToCamera, String> {
    let r_gl = DMat3::from_cols(c2w[0], c2w[1], c2w[2]);
    let r_cv = r_gl * DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));
    CameraToWorld::new_checked(r_cv, c2w[3]).map(|p| p.inverse())
}

/// instant-ngp's `rolling_shutter` `[A, B, C(, D)]` of a frame (its own, else the top
/// level's); `D` defaults to 0.
fn rolling_shutter(
    top: &Map<String, Value>,
    frame: &Map<String, Value>,
) -> std::result::Result<Option<[f64; 4]>, String> {
    let Some(v) = frame
        .get("rolling_shutter")
        .or_else(|| top.get("rolling_shutter"))
    else {
        return Ok(None);
    };
    const MSG: &str = "'rolling_shutter' must be an array of 3 or 4 finite numbers";
    let a = v
        .as_array()
        .filter(|a| a.len() == 3 || a.len() == 4)
        .ok_or(MSG)?;
    let mut out = [0.0; 4];
    for (slot, x) in out.iter_mut().zip(a) {
        *slot = x.as_f64().filter(|x| x.is_finite()).ok_or(MSG)?;
    }
    Ok(Some(out))
}

/// The camera-to-world matrix `key`'s columns: x, y, z axes and the centre.
fn matrix(frame: &Map<String, Value>, key: &str) -> std::result::Result<[DVec3; 4], String> {
    let msg = format!("'{key}' must be a 4x4 array of finite numbers");
    let msg = msg.as_str();
    let rows = frame
        .get(key)
        .ok_or_else(|| format!("missing '{key}'"))?
        .as_array()
        .filter(|r| r.len() == 3 || r.len() == 4)
        .ok_or(msg)?;
    let mut m = [[0.0f64; 4]; 4];
    m[3][3] = 1.0;
    for (r, row) in rows.iter().enumerate() {
        let vals = row.as_array().filter(|v| v.len() == 4).ok_or(msg)?;
        for (c, v) in vals.iter().enumerate() {
            let x = v.as_f64().filter(|x| x.is_finite()).ok_or(msg)?;
            if let Some(slot) = m.get_mut(r).and_then(|row| row.get_mut(c)) {
                *slot = x;
            }
        }
    }
    let last = [m[3][0], m[3][1], m[3][2], m[3][3] - 1.0];
    if last.iter().any(|v| v.abs() > LAST_ROW_TOLERANCE) {
        return Err(format!(
            "'{key}' last row must be [0, 0, 0, 1], got {:?}",
            m[3]
        ));
    }
    let col = |c: usize| DVec3::new(m[0][c], m[1][c], m[2][c]);
    Ok([col(0), col(1), col(2), col(3)])
}

/// An image side given as a JSON number (integer-valued, possibly written as a float).
fn side(
    top: &Map<String, Value>,
    frame: &Map<String, Value>,
    key: &str,
) -> std::result::Result<Option<u32>, String> {
    match either(top, frame, key)? {
        None => Ok(None),
        Some(v) if v.fract() == 0.0 && v >= 1.0 && v <= MAX_IMAGE_SIDE as f64 => Ok(Some(v as u32)),
        Some(v) => Err(format!(
            "'{key}' must be a positive whole number of pixels, got {v}"
        )),
    }
}

/// The intrinsics of one frame.
fn intrinsics(
    top: &Map<String, Value>,
    frame: &Map<String, Value>,
    image: &Path,
) -> std::result::Result<Intrinsics, String> {
    if let Some(v) = frame
        .get("camera_model")
        .or_else(|| top.get("camera_model"))
    {
        let name = v.as_str().ok_or("'camera_model' must be a string")?;
        if !SUPPORTED_MODELS.contains(&name) {
            return Err(format!("unsupported camera model {name}"));
        }
    }
    let fisheye = frame.get("is_fisheye").or_else(|| top.get("is_fisheye"));
    if fisheye.and_then(Value::as_bool) == Some(true) {
        return Err("fisheye cameras are not supported".into());
    }
    for key in ["k3", "k4"] {
        if either(top, frame, key)?.is_some_and(|v| v != 0.0) {
            return Err(format!(
                "nonzero '{key}' is not supported (only k1 k2 p1 p2)"
            ));
        }
    }
    let (w, h) = match (side(top, frame, "w")?, side(top, frame, "h")?) {
        (Some(w), Some(h)) => (w, h),
        _ => super::image_size(image).map_err(|e| format!("no 'w'/'h' and {e}"))?,
    };
    let from_angle = |obj: &Map<String, Value>,
                      key: &str,
                      size: u32|
     -> std::result::Result<Option<f64>, String> {
        match number(obj, key)? {
            Some(a) if a > 0.0 && a < std::f64::consts::PI => {
                Ok(Some(0.5 * size as f64 / (0.5 * a).tan()))
            }
            Some(a) => Err(format!(
                "'{key}' must be an angle in (0, pi) radians, got {a}"
            )),
            None => Ok(None),
        }
    };
    let focal = |fl: &str, angle: &str, size: u32| -> std::result::Result<Option<f64>, String> {
        for obj in [frame, top] {
            if let Some(f) = number(obj, fl)? {
                return Ok(Some(f));
            }
            if let Some(f) = from_angle(obj, angle, size)? {
                return Ok(Some(f));
            }
        }
        Ok(None)
    };
    let fx = focal("fl_x", "camera_angle_x", w)?;
    let fy = focal("fl_y", "camera_angle_y", h)?;
    let (fx, fy) = match (fx, fy) {
        (Some(x), Some(y)) => (x, y),
        (Some(x), None) => (x, x),
        (None, Some(y)) => (y, y),
        (None, None) => return Err("no focal length: need 'fl_x' or 'camera_angle_x'".into()),
    };
    let cx = either(top, frame, "cx")?.unwrap_or(w as f64 / 2.0);
    let cy = either(top, frame, "cy")?.unwrap_or(h as f64 / 2.0);
    let d = Distortion {
        k1: either(top, frame, "k1")?.unwrap_or(0.0),
        k2: either(top, frame, "k2")?.unwrap_or(0.0),
        p1: either(top, frame, "p1")?.unwrap_or(0.0),
        p2: either(top, frame, "p2")?.unwrap_or(0.0),
    };
    let mut k = Intrinsics::pinhole(fx, fy, cx, cy, w, h);
    k.distortion = (!d.is_zero()).then_some(d);
    Ok(k)
}

/// Frame `i`'s `file_path` and the image it names (relative to `base`, the folder of the
/// JSON `file`; it must resolve inside `within`).
fn frame_image<'a>(
    (file, base, within): (&Path, &Path, &Within),
    i: usize,
    frame: &'a Map<String, Value>,
) -> Result<(&'a str, PathBuf)> {
    let ferr = |msg: &str| Error::parse(file, None, format!("frame {i}: {msg}"));
    let rel = match frame.get("file_path") {
        Some(Value::String(s)) if !s.is_empty() => s.as_str(),
        Some(_) => return Err(ferr("'file_path' must be a non-empty string")),
        None => return Err(ferr("missing 'file_path'")),
    };
    let entry = format!("frame {i}: file_path '{rel}'");
    let fname = file.file_name().unwrap_or_default().to_string_lossy();
    let image = find_image(base, rel, |p| within.check(file, &entry, p))?.ok_or_else(|| {
        Error::image(
            base.join(rel),
            format!("{fname}: frame {i}: image not found (also tried .png/.jpg/.jpeg)"),
        )
    })?;
    Ok((rel, image))
}

/// The image of a `file_path`, trying the usual extensions when it names no file; each
/// candidate passes `allowed` before it is looked at.
fn find_image(
    base: &Path,
    rel: &str,
    allowed: impl Fn(&Path) -> Result<()>,
) -> Result<Option<PathBuf>> {
    let candidates = std::iter::once(base.join(rel)).chain(
        IMAGE_EXTENSIONS
            .iter()
            .map(|ext| base.join(format!("{rel}.{ext}"))),
    );
    for p in candidates {
        allowed(&p)?;
        if p.is_file() {
            return Ok(Some(p));
        }
    }
    Ok(None)
}
