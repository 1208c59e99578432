//! COLMAP sparse models, text (`*.txt`) and binary (`*.bin`).
//!
//! # Convention
//! `images.{txt,bin}` give per image `QW QX QY QZ TX TY TZ`: the world-to-camera rotation
//! as a (Hamilton, w first) quaternion and translation, `p_cam = R p_world + t`, in
//! COLMAP's camera axes, which are OpenCV's (x right, y down, z forward). COLMAP's pixel
//! convention is ours too (the top-left pixel's centre is at (0.5, 0.5)), so the
//! principal point is used as given.
//!
//! # Conversion (once, here)
//! The quaternion is normalized (a zero or non-finite one is an error) and turned into
//! `R`; `(R, t)` is the [`crate::camera::WorldToCamera`] pose unchanged. Camera models map
//! to [`Intrinsics`]: SIMPLE_PINHOLE `f cx cy`, PINHOLE `fx fy cx cy`, SIMPLE_RADIAL
//! `f cx cy k1`, RADIAL `f cx cy k1 k2`, OPENCV `fx fy cx cy k1 k2 p1 p2` (all-zero
//! distortion becomes `None`); any other model is an "unsupported camera model" error.
//!
//! # Files
//! [`model_dir`] is `sparse/0/` or `sparse/`, holding `cameras` and `images` in either
//! form (binary preferred when both exist, per file); `points3D` is optional and its
//! points (xyz only) go to [`RawScene::points`]. In `images.txt` each image is a line
//! followed by its 2D-points line, which may be blank (blank lines and `#` comments
//! between records are skipped). Image files are looked up in `images/` under the scene
//! directory, then in the scene directory itself. Views are sorted by image name. Binary
//! counts are checked against the bytes left in the file before anything is allocated.

use super::{make_view, RawScene, View, Within};
use crate::camera::{Distortion, Intrinsics, WorldToCamera};
use crate::error::{Error, Result};
use crate::imageio::MAX_IMAGE_SIDE;
use glam::{DMat3, DQuat, DVec3};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Quaternions with a norm below this are rejected rather than normalized.
const MIN_QUATERNION_NORM: f64 = 1e-8;
/// Smallest record of `images.bin`: id, 7 doubles, camera id, empty name, point count.
const MIN_IMAGE_RECORD: usize = 4 + 7 * 8 + 4 + 1 + 8;
/// Bytes of one 2D point in `images.bin`: x, y, point3D id.
const POINT2D_RECORD: usize = 8 + 8 + 8;
/// Smallest record of `cameras.bin`: id, model, width, height.
const MIN_CAMERA_RECORD: usize = 4 + 4 + 8 + 8;
/// Smallest record of `points3D.bin`: id, xyz, rgb, error, track length.
const MIN_POINT3D_RECORD: usize = 8 + 3 * 8 + 3 + 8 + 8;
/// Bytes of one track element in `points3D.bin`: image id, point2D index.
const TRACK_RECORD: usize = 4 + 4;

/// COLMAP camera model names by id.
const MODEL_NAMES: [&str; 12] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
];

/// The folder holding the model: `sparse/0/` or `sparse/` with cameras and images files.
pub fn model_dir(dir: &Path) -> Option<PathBuf> {
    let has = |d: &Path, stem: &str| {
        d.join(format!("{stem}.bin")).is_file() || d.join(format!("{stem}.txt")).is_file()
    };
    [dir.join("sparse").join("0"), dir.join("sparse")]
        .into_iter()
        .find(|d| has(d, "cameras") && has(d, "images"))
}

/// Reads a COLMAP scene directory.
pub fn read(dir: &Path, within: &Within) -> Result<RawScene> {
    let model = model_dir(dir).ok_or_else(|| {
        Error::format(
            dir,
            "no COLMAP model: expected sparse/0/ or sparse/ with cameras and images files",
        )
    })?;
    let pick = |stem: &str| {
        let bin = model.join(format!("{stem}.bin"));
        if bin.is_file() {
            (bin, true)
        } else {
            (model.join(format!("{stem}.txt")), false)
        }
    };
    let (cam_file, cam_bin) = pick("cameras");
    within.check(dir, "the camera file", &cam_file)?;
    let cam_bytes = read_file(&cam_file)?;
    let cameras = if cam_bin {
        parse_cameras_bin(&cam_file, &cam_bytes)?
    } else {
        parse_cameras_txt(&cam_file, &cam_bytes)?
    };
    let (img_file, img_bin) = pick("images");
    within.check(dir, "the image file", &img_file)?;
    let img_bytes = read_file(&img_file)?;
    let images = if img_bin {
        parse_images_bin(&img_file, &img_bytes)?
    } else {
        parse_images_txt(&img_file, &img_bytes)?
    };
    let (pts_file, pts_bin) = pick("points3D");
    within.check(dir, "the points file", &pts_file)?;
    let points = if !pts_file.is_file() {
        Vec::new()
    } else if pts_bin {
        parse_points3d_bin(&pts_file, &read_file(&pts_file)?)?
    } else {
        parse_points3d_txt(&pts_file, &read_file(&pts_file)?)?
    };

    let mut views = views_of((dir, within), (&img_file, &cam_file), images, &cameras)?;
    views.sort_by(|a, b| a.name.cmp(&b.name));
    if let Some(w) = views
        .windows(2)
        .find(|w| w.first().map(|v| &v.name) == w.get(1).map(|v| &v.name))
    {
        let name = w.first().map(|v| v.name.clone()).unwrap_or_default();
        return Err(Error::format(
            &img_file,
            format!("image '{name}' is listed twice"),
        ));
    }
    Ok(RawScene {
        views,
        bounds: None,
        points,
        notes: vec![format!("COLMAP: model in {}", model.display())],
    })
}

/// The views of `images`, their cameras from `cameras` and their images found (inside
/// `within`) in `images/` or the scene directory; errors name `img_file` and `cam_file`.
fn views_of(
    (dir, within): (&Path, &Within),
    (img_file, cam_file): (&Path, &Path),
    images: Vec<ImageEntry>,
    cameras: &HashMap<u32, Intrinsics>,
) -> Result<Vec<View>> {
    let mut views: Vec<View> = Vec::with_capacity(images.len());
    for img in images {
        let intrinsics = *cameras.get(&img.camera_id).ok_or_else(|| {
            Error::parse(
                img_file,
                img.line,
                format!(
                    "image '{}' uses camera {} which is not in {}",
                    img.name,
                    img.camera_id,
                    cam_file.display()
                ),
            )
        })?;
        let entry = match img.line {
            Some(l) => format!("line {l}: image '{}'", img.name),
            None => format!("image '{}'", img.name),
        };
        let image_path = find_image(dir, &img.name, |p| within.check(img_file, &entry, p))?
            .ok_or_else(|| {
                Error::image(
                    dir.join("images").join(&img.name),
                    format!(
                        "image '{}' listed in {} not found in images/ or the scene directory",
                        img.name,
                        img_file.display()
                    ),
                )
            })?;
        views.push(make_view(
            img_file, &img.name, image_path, intrinsics, img.pose, None,
        )?);
    }
    Ok(views)
}

/// The image `name` in `images/` or else in the scene directory; each candidate passes
/// `allowed` before it is looked at.
fn find_image(
    dir: &Path,
    name: &str,
    allowed: impl Fn(&Path) -> Result<()>,
) -> Result<Option<PathBuf>> {
    for p in [dir.join("images").join(name), dir.join(name)] {
        allowed(&p)?;
        if p.is_file() {
            return Ok(Some(p));
        }
    }
    Ok(None)
}

/// One entry of `images.{txt,bin}` before its camera is looked up.
pub struct ImageEntry {
    pub name: String,
    pub camera_id: u32,
    /// The pose, or why it is unusable (reported once the view is built).
    pub pose: std::result::Result<WorldToCamera, String>,
    /// Line in `images.txt` (none for the binary file).
    pub line: Option<usize>,
}

/// The pose from a COLMAP quaternion (w, x, y, z) and translation.
fn pose_from(q: [f64; 4], t: [f64; 3]) -> std::result::Result<WorldToCamera, String> {
    let [w, x, y, z] = q;
    let norm = (w * w + x * x + y * y + z * z).sqrt();
    if !norm.is_finite() || norm < MIN_QUATERNION_NORM {
        return Err(format!("invalid quaternion {q:?} (zero or non-finite)"));
    }
    let r = DMat3::from_quat(DQuat::from_xyzw(x / norm, y / norm, z / norm, w / norm));
    WorldToCamera::new_checked(r, DVec3::from_array(t))
}

/// Intrinsics from a model name and its parameters; `Err` is a message.
fn intrinsics_from(
    model: &str,
    width: u64,
    height: u64,
    p: &[f64],
) -> std::result::Result<Intrinsics, String> {
    let need = match model {
        "SIMPLE_PINHOLE" => 3,
        "PINHOLE" => 4,
        "SIMPLE_RADIAL" => 4,
        "RADIAL" => 5,
        "OPENCV" => 8,
        other => {
            return Err(format!(
                "unsupported camera model {other} (supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV)"
            ))
        }
    };
    if p.len() != need {
        return Err(format!(
            "camera model {model} needs {need} parameters, got {}",
            p.len()
        ));
    }
    if p.iter().any(|v| !v.is_finite()) {
        return Err(format!("non-finite camera parameters {p:?}"));
    }
    let side = |v: u64| {
        u32::try_from(v)
            .ok()
            .filter(|&s| s > 0 && s <= MAX_IMAGE_SIDE)
    };
    let (w, h) = match (side(width), side(height)) {
        (Some(w), Some(h)) => (w, h),
        _ => return Err(format!("unsupported image size {width}x{height}")),
    };
    let g = |i: usize| p.get(i).copied().unwrap_or(0.0);
    let (fx, fy, cx, cy, d) = match model {
        "SIMPLE_PINHOLE" => (g(0), g(0), g(1), g(2), [0.0; 4]),
        "PINHOLE" => (g(0), g(1), g(2), g(3), [0.0; 4]),
        "SIMPLE_RADIAL" => (g(0), g(0), g(1), g(2), [g(3), 0.0, 0.0, 0.0]),
        "RADIAL" => (g(0), g(0), g(1), g(2), [g(3), g(4), 0.0, 0.0]),
        _ => (g(0), g(1), g(2), g(3), [g(4), g(5), g(6), g(7)]),
    };
    let dist = Distortion {
        k1: d[0],
        k2: d[1],
        p1: d[2],
        p2: d[3],
    };
    let mut k = Intrinsics::pinhole(fx, fy, cx, cy, w, h);
    k.distortion = (!dist.is_zero()).then_some(dist);
    k.validate()?;
    Ok(k)
}

fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

/// The bytes of a text file as UTF-8, reporting the line of the first invalid byte.
pub(crate) fn utf8<'a>(path: &Path, bytes: &'a [u8]) -> Result<&'a str> {
    std::str::from_utf8(bytes).map_err(|e| {
        let at = e.valid_up_to();
        let line = bytes
            .get(..at)
            .unwrap_or(&[])
            .iter()
            .filter(|&&b| b == b'\n')
            .count()
            + 1;
        Error::parse(path, Some(line), "not valid UTF-8 text")
    })
}

fn parse_num<T: std::str::FromStr>(
    path: &Path,
    line: usize,
    tok: Option<&str>,
    what: &str,
) -> Result<T> {
    let tok = tok.ok_or_else(|| Error::parse(path, Some(line), format!("missing {what}")))?;
    tok.parse::<T>()
        .map_err(|_| Error::parse(path, Some(line), format!("bad {what} '{tok}'")))
}

fn is_skippable(line: &str) -> bool {
    let t = line.trim();
    t.is_empty() || t.starts_with('#')
}

/// Parses the bytes of `cameras.txt` (`path` names the file in errors): camera id to
/// intrinsics.
pub fn parse_cameras_txt(path: &Path, bytes: &[u8]) -> Result<HashMap<u32, Intrinsics>> {
    let text = utf8(path, bytes)?;
    let mut out = HashMap::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !is_skippable(l)) {
        let n = i + 1;
        let mut tok = line.split_whitespace();
        let id: u32 = parse_num(path, n, tok.next(), "camera id")?;
        let model = tok
            .next()
            .ok_or_else(|| Error::parse(path, Some(n), "missing camera model"))?;
        let width: u64 = parse_num(path, n, tok.next(), "width")?;
        let height: u64 = parse_num(path, n, tok.next(), "height")?;
        let params = tok
            .map(|t| {
                t.parse::<f64>()
                    .map_err(|_| Error::parse(path, Some(n), format!("bad camera parameter '{t}'")))
            })
            .collect::<Result<Vec<_>>>()?;
        let k = intrinsics_from(model, width, height, &params)
            .map_err(|m| Error::parse(path, Some(n), format!("camera {id}: {m}")))?;
        if out.insert(id, k).is_some() {
            return Err(Error::parse(
                path,
                Some(n),
                format!("camera id {id} appears twice"),
            ));
        }
    }
    Ok(out)
}

/// A line after an image line is its 2D points if blank or whole numeric triples.
fn is_points2d_line(line: &str) -> bool {
    let toks: Vec<&str> = line.split_whitespace().collect();
    toks.len().is_multiple_of(3) && toks.iter().all(|t| t.parse::<f64>().is_ok())
}

/// Parses the bytes of `images.txt` (`path` names the file in errors).
pub fn parse_images_txt(path: &Path, bytes: &[u8]) -> Result<Vec<ImageEntry>> {
    let text = utf8(path, bytes)?;
    let mut lines = text.lines().enumerate().peekable();
    let mut out = Vec::new();
    let mut ids = HashMap::new();
    while let Some((i, line)) = lines.next() {
        if is_skippable(line) {
            continue;
        }
        let n = i + 1;
        let mut tok = line.split_whitespace();
        let id: u64 = parse_num(path, n, tok.next(), "image id")?;
        if let Some(first) = ids.insert(id, n) {
            return Err(Error::parse(
                path,
                Some(n),
                format!("image id {id} appears twice (first on line {first})"),
            ));
        }
        let mut v = [0.0f64; 7];
        for (k, slot) in v.iter_mut().enumerate() {
            *slot = parse_num(path, n, tok.next(), &format!("pose value {}", k + 1))?;
        }
        let camera_id: u32 = parse_num(path, n, tok.next(), "camera id")?;
        let name = tok.collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(Error::parse(path, Some(n), "missing image name"));
        }
        if lines.peek().is_some_and(|(_, l)| is_points2d_line(l)) {
            lines.next();
        }
        out.push(ImageEntry {
            name,
            camera_id,
            pose: pose_from([v[0], v[1], v[2], v[3]], [v[4], v[5], v[6]]),
            line: Some(n),
        });
    }
    Ok(out)
}

/// Parses the bytes of `points3D.txt` (`path` names the file in errors): the points.
pub fn parse_points3d_txt(path: &Path, bytes: &[u8]) -> Result<Vec<DVec3>> {
    let text = utf8(path, bytes)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !is_skippable(l)) {
        let n = i + 1;
        let mut tok = line.split_whitespace();
        let _id: u64 = parse_num(path, n, tok.next(), "point id")?;
        let x: f64 = parse_num(path, n, tok.next(), "X")?;
        let y: f64 = parse_num(path, n, tok.next(), "Y")?;
        let z: f64 = parse_num(path, n, tok.next(), "Z")?;
        let p = DVec3::new(x, y, z);
        if !p.is_finite() {
            return Err(Error::parse(path, Some(n), "non-finite point"));
        }
        out.push(p);
    }
    Ok(out)
}

/// A bounds-checked little-endian reader over a binary model file.
struct Bin<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Bin<'a> {
    fn new(path: &'a Path, bytes: &'a [u8]) -> Self {
        Self {
            path,
            bytes,
            pos: 0,
        }
    }
    fn remaining(&self) -> usize {
        self.bytes.len().saturating_sub(self.pos)
    }
    fn err(&self, msg: String) -> Error {
        Error::parse(self.path, None, format!("at byte {}: {msg}", self.pos))
    }
    fn take<const N: usize>(&mut self, what: &str) -> Result<[u8; N]> {
        let arr = self
            .bytes
            .get(self.pos..self.pos.saturating_add(N))
            .and_then(|s| <[u8; N]>::try_from(s).ok())
            .ok_or_else(|| self.err(format!("file truncated while reading {what}")))?;
        self.pos += N;
        Ok(arr)
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        self.take::<4>(what).map(u32::from_le_bytes)
    }
    fn i32(&mut self, what: &str) -> Result<i32> {
        self.take::<4>(what).map(i32::from_le_bytes)
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        self.take::<8>(what).map(u64::from_le_bytes)
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        self.take::<8>(what).map(f64::from_le_bytes)
    }
    fn skip(&mut self, n: usize, what: &str) -> Result<()> {
        if n > self.remaining() {
            return Err(self.err(format!("file truncated while skipping {what}")));
        }
        self.pos += n;
        Ok(())
    }
    /// A count of records each at least `min_size` bytes, checked against what is left.
    fn count(&mut self, min_size: usize, what: &str) -> Result<usize> {
        let n = self.u64(what)?;
        let fits = usize::try_from(n).ok().filter(|&n| {
            n.checked_mul(min_size)
                .is_some_and(|b| b <= self.remaining())
        });
        fits.ok_or_else(|| {
            self.err(format!(
                "{what} {n} is larger than the rest of the file allows (corrupt or truncated)"
            ))
        })
    }
    fn cstring(&mut self, what: &str) -> Result<String> {
        let rest = self.bytes.get(self.pos..).unwrap_or(&[]);
        let end = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| self.err(format!("unterminated {what}")))?;
        let s = std::str::from_utf8(rest.get(..end).unwrap_or(&[]))
            .map_err(|_| self.err(format!("{what} is not valid UTF-8")))?
            .to_string();
        self.pos += end + 1;
        Ok(s)
    }
    fn finish(&self) -> Result<()> {
        if self.remaining() != 0 {
            return Err(self.err(format!("{} unexpected trailing bytes", self.remaining())));
        }
        Ok(())
    }
}

/// Parses the bytes of `cameras.bin` (`path` names the file in errors).
pub fn parse_cameras_bin(path: &Path, bytes: &[u8]) -> Result<HashMap<u32, Intrinsics>> {
    let mut b = Bin::new(path, bytes);
    let n = b.count(MIN_CAMERA_RECORD, "camera count")?;
    let mut out = HashMap::with_capacity(n);
    for _ in 0..n {
        let id = b.u32("camera id")?;
        let model_id = b.i32("camera model")?;
        let width = b.u64("width")?;
        let height = b.u64("height")?;
        let name = usize::try_from(model_id)
            .ok()
            .and_then(|i| MODEL_NAMES.get(i))
            .copied();
        let Some(name) = name else {
            return Err(b.err(format!(
                "camera {id}: unsupported camera model id {model_id}"
            )));
        };
        let nparams = match name {
            "SIMPLE_PINHOLE" => 3,
            "PINHOLE" | "SIMPLE_RADIAL" => 4,
            "RADIAL" => 5,
            "OPENCV" => 8,
            _ => 0,
        };
        let mut params = Vec::with_capacity(nparams);
        for _ in 0..nparams {
            params.push(b.f64("camera parameter")?);
        }
        let k = intrinsics_from(name, width, height, &params)
            .map_err(|m| b.err(format!("camera {id}: {m}")))?;
        if out.insert(id, k).is_some() {
            return Err(b.err(format!("camera id {id} appears twice")));
        }
    }
    b.finish()?;
    Ok(out)
}

/// Parses the bytes of `images.bin` (`path` names the file in errors).
pub fn parse_images_bin(path: &Path, bytes: &[u8]) -> Result<Vec<ImageEntry>> {
    let mut b = Bin::new(path, bytes);
    let n = b.count(MIN_IMAGE_RECORD, "image count")?;
    let mut out = Vec::with_capacity(n);
    let mut ids = std::collections::HashSet::new();
    for _ in 0..n {
        let id = b.u32("image id")?;
        if !ids.insert(id) {
            return Err(b.err(format!("image id {id} appears twice")));
        }
        let mut v = [0.0f64; 7];
        for slot in v.iter_mut() {
            *slot = b.f64("pose")?;
        }
        let camera_id = b.u32("camera id")?;
        let name = b.cstring("image name")?;
        let npts = b.count(POINT2D_RECORD, "2D point count")?;
        b.skip(npts * POINT2D_RECORD, "2D points")?;
        out.push(ImageEntry {
            name,
            camera_id,
            pose: pose_from([v[0], v[1], v[2], v[3]], [v[4], v[5], v[6]]),
            line: None,
        });
    }
    b.finish()?;
    Ok(out)
}

/// Parses the bytes of `points3D.bin` (`path` names the file in errors).
pub fn parse_points3d_bin(path: &Path, bytes: &[u8]) -> Result<Vec<DVec3>> {
    let mut b = Bin::new(path, bytes);
    let n = b.count(MIN_POINT3D_RECORD, "point count")?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let _id = b.u64("point id")?;
        let p = DVec3::new(b.f64("X")?, b.f64("Y")?, b.f64("Z")?);
        b.skip(3, "colour")?;
        let _error = b.f64("error")?;
        let track = b.count(TRACK_RECORD, "track length")?;
        b.skip(track * TRACK_RECORD, "track")?;
        if !p.is_finite() {
            return Err(b.err("non-finite point".into()));
        }
        out.push(p);
    }
    b.finish()?;
    Ok(out)
}
