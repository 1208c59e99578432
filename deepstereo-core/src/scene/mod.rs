//! Posed image sets ("scenes") and their readers.
//!
//! Every reader converts its file format's conventions into [`crate::camera`]'s (OpenCV
//! axes, world-to-camera, pixel centres at `i + 0.5`) exactly once; nothing downstream
//! knows which format a scene came from.

pub mod auto;
pub mod colmap;
pub mod discover;
pub mod llff;
pub mod middlebury;
pub mod nerf;
pub mod npy;
pub mod within;

pub use discover::scene_dirs;
pub use within::Within;

use crate::camera::{Camera, Intrinsics, WorldToCamera};
use crate::error::{Error, Result};
use crate::imageio::{RgbImage, MAX_IMAGE_SIDE};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Largest accepted `--downscale`.
pub const MAX_DOWNSCALE: u32 = 64;
/// The larger image side, in pixels, that the commands running the network read a scene
/// at when no `--downscale` is given ([`LoadOptions::max_side`]): camera photographs
/// (3000-6000 px) are read at 1/4 or 1/8, what the network was trained at.
pub const WORKING_SIDE: u32 = 1024;
/// Lower and upper percentiles of sparse-point depths used as near/far bounds.
pub const POINT_DEPTH_PERCENTILES: (f64, f64) = (0.01, 0.99);
/// Margin applied to percentile bounds: near is multiplied by `1 - m`, far by `1 + m`.
pub const POINT_DEPTH_MARGIN: f64 = 0.2;

/// The file formats a scene can be read from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneFormat {
    Llff,
    Colmap,
    Nerf,
    Middlebury,
}

impl SceneFormat {
    pub fn name(self) -> &'static str {
        match self {
            SceneFormat::Llff => "llff",
            SceneFormat::Colmap => "colmap",
            SceneFormat::Nerf => "nerf",
            SceneFormat::Middlebury => "middlebury",
        }
    }
}

impl std::str::FromStr for SceneFormat {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "llff" => Ok(Self::Llff),
            "colmap" => Ok(Self::Colmap),
            "nerf" | "instant-ngp" | "transforms" => Ok(Self::Nerf),
            "middlebury" => Ok(Self::Middlebury),
            other => Err(Error::Invalid(format!(
                "unknown scene format '{other}' (expected llff, colmap, nerf or middlebury)"
            ))),
        }
    }
}

/// One posed photograph of a scene.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    pub name: String,
    pub image_path: PathBuf,
    pub camera: Camera,
    /// Per-view depth bounds when the file gives them (LLFF).
    pub bounds: Option<(f64, f64)>,
}

/// What a reader returns before bounds are resolved.
#[derive(Clone, Debug, Default)]
pub struct RawScene {
    pub views: Vec<View>,
    /// Scene-wide bounds from the file (NeRF `near`/`far`, LLFF min/max of its bounds).
    pub bounds: Option<(f64, f64)>,
    /// Sparse 3D points (COLMAP `points3D`), used for bounds when the file gives none.
    pub points: Vec<DVec3>,
    /// A line for the user, such as which image folder was chosen.
    pub notes: Vec<String>,
}

/// Where a scene's near/far came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BoundsSource {
    File,
    Points,
    User,
    /// Estimated from the images themselves ([`auto`]).
    Auto,
}

impl BoundsSource {
    /// How `inspect` and the logs describe it.
    pub fn describe(self) -> &'static str {
        match self {
            BoundsSource::File => "from the scene's files",
            BoundsSource::Points => "from the scene's sparse points",
            BoundsSource::User => "given by --near/--far",
            BoundsSource::Auto => "automatic, from matched image points",
        }
    }
}

/// Options that change how a scene is read.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Force a format instead of detecting it.
    pub format: Option<SceneFormat>,
    /// LLFF: use `images_<factor>/`.
    pub factor: Option<u32>,
    pub near: Option<f64>,
    pub far: Option<f64>,
    /// Read images at `1 / downscale` resolution (a power of two; box-filtered, odd
    /// trailing rows and columns dropped), intrinsics scaled to match.
    pub downscale: Option<u32>,
    /// Without `downscale`: read the images at the smallest power-of-two factor that
    /// brings every view's larger side to at most this many pixels (the working
    /// resolution of the commands that run the network; a note says so). `None`: the
    /// files' resolution.
    pub max_side: Option<u32>,
    /// Treat rolling-shutter cameras as global shutters at their mid-readout pose
    /// ([`Camera::without_rolling_shutter`]), as a reader unaware of the shutter would.
    pub ignore_rolling_shutter: bool,
    /// Read images that the scene's files name outside the scene directory (after
    /// resolving `..` and symbolic links); by default they are refused unread
    /// ([`Within`]).
    pub allow_outside_paths: bool,
}

/// A posed image set with resolved depth bounds.
#[derive(Clone, Debug)]
pub struct Scene {
    pub root: PathBuf,
    pub format: SceneFormat,
    pub views: Vec<View>,
    pub near: f64,
    /// May be `f64::INFINITY`.
    pub far: f64,
    pub bounds_source: BoundsSource,
    pub points: Vec<DVec3>,
    pub notes: Vec<String>,
    /// Images are read at `1 / 2^downscale_levels` of their file resolution.
    pub downscale_levels: u32,
}

impl Scene {
    /// Reads a scene directory, detecting its format unless `opts.format` forces one.
    pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Scene> {
        Self::load_views(dir, opts, |n| Ok((0..n).collect()))
    }

    /// Reads a scene directory keeping only some of its views: `keep(n)` gets the number
    /// of views the files list and returns the indices to keep, ascending (an error
    /// message refuses the scene). Nothing of the other views is read but their cameras:
    /// their images are neither opened nor used to estimate depth bounds, so a held-out
    /// photograph cannot change the scene a tuner sees.
    pub fn load_views(
        dir: &Path,
        opts: &LoadOptions,
        keep: impl FnOnce(usize) -> std::result::Result<Vec<usize>, String>,
    ) -> Result<Scene> {
        if !dir.is_dir() {
            return Err(Error::format(
                dir,
                "not a directory (expected a scene directory)",
            ));
        }
        let format = match opts.format {
            Some(f) => f,
            None => detect(dir)?,
        };
        let within = match opts.allow_outside_paths {
            true => Within::anywhere(),
            false => Within::scene(dir)?,
        };
        let raw = match format {
            SceneFormat::Llff => llff::read(dir, opts.factor, &within)?,
            SceneFormat::Colmap => colmap::read(dir, &within)?,
            SceneFormat::Nerf => nerf::read(dir, &within)?,
            SceneFormat::Middlebury => middlebury::read(dir, &within)?,
        };
        let mut raw = raw;
        if raw.bounds.is_none() && raw.points.is_empty() && format != SceneFormat::Middlebury {
            if let Some(corners) = middlebury::readme_bbox(dir, &within, &mut raw.notes)? {
                raw.points = corners;
                raw.notes
                    .push("depth bounds from the bounding box in README.txt".to_string());
            }
        }
        let kept = keep(raw.views.len()).map_err(|m| Error::format(dir, m))?;
        if kept.windows(2).any(|w| w[0] >= w[1]) || kept.iter().any(|&i| i >= raw.views.len()) {
            return Err(Error::format(
                dir,
                "the views kept must be ascending view indices",
            ));
        }
        if kept.len() < raw.views.len() {
            let mut views = std::mem::take(&mut raw.views)
                .into_iter()
                .map(Some)
                .collect::<Vec<_>>();
            raw.views = kept.iter().filter_map(|&i| views[i].take()).collect();
        }
        check_image_headers(&raw.views)?;
        Self::from_raw(dir, format, raw, opts)
    }

    /// Resolves bounds (user > file > sparse points > estimated from the images, see
    /// [`auto`]) and validates every camera.
    pub fn from_raw(
        dir: &Path,
        format: SceneFormat,
        mut raw: RawScene,
        opts: &LoadOptions,
    ) -> Result<Scene> {
        if raw.views.is_empty() {
            return Err(Error::format(dir, "the scene has no views"));
        }
        for v in &raw.views {
            v.camera
                .intrinsics
                .validate()
                .map_err(|msg| Error::Camera {
                    path: v.image_path.clone(),
                    view: v.name.clone(),
                    msg,
                })?;
        }
        let (near, far, bounds_source) = match (opts.near, opts.far) {
            (Some(n), Some(f)) => (n, f, BoundsSource::User),
            _ => {
                let (n, f, src) = if let Some((n, f)) = raw.bounds {
                    (n, f, BoundsSource::File)
                } else if let Some((n, f)) = bounds_from_points(&raw.views, &raw.points) {
                    (n, f, BoundsSource::Points)
                } else {
                    let est = auto::estimate(dir, &raw.views)?;
                    raw.notes.push(format!(
                        "depth bounds estimated from the images: {} matched points in {} reference views",
                        est.matched, est.references
                    ));
                    raw.points = est.points;
                    (est.near, est.far, BoundsSource::Auto)
                };
                (opts.near.unwrap_or(n), opts.far.unwrap_or(f), src)
            }
        };
        check_bounds(near, far).map_err(|m| Error::format(dir, m))?;
        if opts.ignore_rolling_shutter {
            for v in &mut raw.views {
                v.camera = v.camera.without_rolling_shutter();
            }
        }
        Scene {
            root: dir.to_path_buf(),
            format,
            views: raw.views,
            near,
            far,
            bounds_source,
            points: raw.points,
            notes: raw.notes,
            downscale_levels: 0,
        }
        .working(opts)
    }

    /// Applies `opts.downscale`, or else the factor `opts.max_side` asks for, with a note.
    fn working(mut self, opts: &LoadOptions) -> Result<Scene> {
        if let Some(f) = opts.downscale {
            return self.downscaled(f);
        }
        let Some(limit) = opts.max_side else {
            return self.downscaled(1);
        };
        let side = self.views.iter().map(|v| {
            let k = &v.camera.intrinsics;
            k.width.max(k.height)
        });
        let side = side.max().unwrap_or(0);
        let factor = working_factor(side, limit);
        if factor > 1 {
            self.notes.push(format!(
                "working resolution 1/{factor}: the images' larger side is {side} px, \
                 {} px read (at most {limit}); --downscale 1 reads them whole",
                side / factor
            ));
        }
        self.downscaled(factor)
    }

    /// Loads view `i`'s image, checking it has the size its camera expects.
    pub fn load_image(&self, i: usize) -> Result<RgbImage> {
        let v = self.views.get(i).ok_or_else(|| {
            Error::Invalid(format!(
                "view {i} out of range (scene has {})",
                self.views.len()
            ))
        })?;
        let k = self.downscale_levels;
        if k == 0 {
            return RgbImage::load_expecting(
                &v.image_path,
                v.camera.intrinsics.width,
                v.camera.intrinsics.height,
            );
        }
        if let Some(small) = self.prescaled(&v.image_path, k) {
            return RgbImage::load_expecting(
                &small,
                v.camera.intrinsics.width,
                v.camera.intrinsics.height,
            );
        }
        let mut img = RgbImage::load(&v.image_path)?;
        if img.width >> k != v.camera.intrinsics.width
            || img.height >> k != v.camera.intrinsics.height
        {
            return Err(Error::image(
                &v.image_path,
                format!(
                    "image is {}x{}, expected {}x{} before downscaling by {}",
                    img.width,
                    img.height,
                    v.camera.intrinsics.width << k,
                    v.camera.intrinsics.height << k,
                    1u32 << k
                ),
            ));
        }
        for _ in 0..k {
            img = img.downsample2();
        }
        Ok(img)
    }

    /// The same image at `1 / 2^k` of `image`'s size in a prescaled folder, as LLFF's
    /// `imgs2poses` and nerfstudio write them: `images_F/NAME` beside `images/NAME`
    /// (`F = 2^k`), used when its header has the size the downscaled camera expects and it
    /// resolves inside the scene; `None` otherwise (the full image is then box-filtered).
    fn prescaled(&self, image: &Path, k: u32) -> Option<PathBuf> {
        let (name, folder) = (image.file_name()?, image.parent()?);
        if folder.file_name()? != "images" {
            return None;
        }
        let small = folder
            .parent()?
            .join(format!("images_{}", 1u32 << k))
            .join(name);
        let inside = within::resolve(&small)
            .zip(self.root.canonicalize().ok())
            .is_some_and(|(p, root)| p.starts_with(root));
        let view = self.views.iter().find(|v| v.image_path == image)?;
        let want = (view.camera.intrinsics.width, view.camera.intrinsics.height);
        (inside && small.is_file() && image_size(&small).ok()? == want).then_some(small)
    }

    /// The scene read at `1 / factor` resolution (`factor` a power of two).
    fn downscaled(mut self, factor: u32) -> Result<Scene> {
        if factor == 0 || !factor.is_power_of_two() || factor > MAX_DOWNSCALE {
            return Err(Error::Invalid(format!(
                "--downscale must be a power of two from 1 to {MAX_DOWNSCALE}, got {factor}"
            )));
        }
        let k = factor.trailing_zeros();
        for v in &mut self.views {
            let i = &v.camera.intrinsics;
            let (w, h) = (i.width >> k, i.height >> k);
            if w == 0 || h == 0 {
                return Err(camera_err(
                    &v.image_path,
                    &v.name,
                    format!(
                        "{}x{} is too small to downscale by {factor}",
                        i.width, i.height
                    ),
                ));
            }
            v.camera = v.camera.downscaled(factor as f64, w, h);
        }
        self.downscale_levels = k;
        Ok(self)
    }

    /// Indices of the `k` views whose camera centres are nearest to view `target`'s,
    /// excluding `target` itself, nearest first (ties broken by index); empty when `target`
    /// is out of range.
    pub fn nearest_views(&self, target: usize, k: usize) -> Vec<usize> {
        match self.views.get(target) {
            Some(v) => nearest_to_point(&self.views, v.camera.pose.centre(), k, Some(target)),
            None => Vec::new(),
        }
    }
}

/// The smallest power of two that brings `side` pixels to at most `limit` (1 when it fits,
/// at most [`MAX_DOWNSCALE`]).
pub fn working_factor(side: u32, limit: u32) -> u32 {
    let mut f = 1;
    while side / f > limit.max(1) && f < MAX_DOWNSCALE {
        f *= 2;
    }
    f
}

/// The `k` views whose centres are nearest to `c`, optionally excluding one index.
pub fn nearest_to_point(views: &[View], c: DVec3, k: usize, exclude: Option<usize>) -> Vec<usize> {
    let mut idx: Vec<(f64, usize)> = views
        .iter()
        .enumerate()
        .filter(|(i, _)| Some(*i) != exclude)
        .map(|(i, v)| (v.camera.pose.centre().distance_squared(c), i))
        .collect();
    idx.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    idx.into_iter().take(k).map(|(_, i)| i).collect()
}

/// Checks `0 < near < far` (far may be infinite).
pub fn check_bounds(near: f64, far: f64) -> Result<(), String> {
    if !near.is_finite() || near <= 0.0 {
        return Err(format!("near must be finite and positive, got {near}"));
    }
    if far.is_nan() || far <= near {
        return Err(format!("far must be greater than near ({near}), got {far}"));
    }
    Ok(())
}

/// Robust near/far from the depths of sparse points in every view that sees them.
pub fn bounds_from_points(views: &[View], points: &[DVec3]) -> Option<(f64, f64)> {
    let mut depths: Vec<f64> = Vec::new();
    for v in views {
        for p in points {
            let z = v.camera.pose.transform_point(*p).z;
            if z > 0.0 && z.is_finite() {
                depths.push(z);
            }
        }
    }
    if depths.len() < 2 {
        return None;
    }
    depths.sort_by(f64::total_cmp);
    let at = |q: f64| depths[((depths.len() - 1) as f64 * q).round() as usize];
    let near = at(POINT_DEPTH_PERCENTILES.0) * (1.0 - POINT_DEPTH_MARGIN);
    let far = at(POINT_DEPTH_PERCENTILES.1) * (1.0 + POINT_DEPTH_MARGIN);
    (near > 0.0 && far > near).then_some((near, far))
}

/// Detects the format of a scene directory from the files it holds.
pub fn detect(dir: &Path) -> Result<SceneFormat> {
    if dir.join("poses_bounds.npy").is_file() {
        return Ok(SceneFormat::Llff);
    }
    if dir.join("transforms.json").is_file() || dir.join("transforms_train.json").is_file() {
        return Ok(SceneFormat::Nerf);
    }
    if colmap::model_dir(dir).is_some() {
        return Ok(SceneFormat::Colmap);
    }
    if middlebury::par_file(dir).is_some() {
        return Ok(SceneFormat::Middlebury);
    }
    // A marker that is there but no regular file (a FIFO, a device, a directory) is named
    // as such, not taken for a missing one; it is never opened.
    for name in [
        "poses_bounds.npy",
        "transforms.json",
        "transforms_train.json",
    ] {
        let p = dir.join(name);
        if p.symlink_metadata().is_ok() {
            return Err(Error::format(
                p,
                "exists but is not a regular file (a FIFO, device, directory or dangling link); it is not read",
            ));
        }
    }
    Err(Error::format(
        dir,
        "unknown scene format: expected poses_bounds.npy (LLFF), transforms.json (NeRF), \
         sparse/0/ or sparse/ (COLMAP) or *_par.txt (Middlebury); use --format to force one",
    ))
}

/// The size in an image file's header (PNG or JPEG, detected from the content, else the
/// extension), without decoding the pixels. The decoder's memory limit is lifted for the
/// header only, so that a header claiming a huge size is reported as such; sides must be
/// within `1..=MAX_IMAGE_SIDE`.
pub fn image_size(path: &Path) -> Result<(u32, u32)> {
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::image(path, format!("cannot open the image: {e}")))?;
    let mut reader = reader
        .with_guessed_format()
        .map_err(|e| Error::image(path, format!("cannot read the image: {e}")))?;
    reader.no_limits();
    let (w, h) = reader
        .into_dimensions()
        .map_err(|e| Error::image(path, format!("cannot read the image header: {e}")))?;
    if w == 0 || h == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
        return Err(Error::image(
            path,
            format!("unsupported image size {w}x{h} (each side must be 1 to {MAX_IMAGE_SIDE})"),
        ));
    }
    Ok((w, h))
}

/// Checks that every view's image exists, has a readable header and the size its camera
/// expects, so that a scene that loads has usable images (the pixels are decoded, and
/// checked again, only when an image is loaded).
pub fn check_image_headers(views: &[View]) -> Result<()> {
    for v in views {
        let (w, h) = image_size(&v.image_path)?;
        let k = &v.camera.intrinsics;
        if (w, h) != (k.width, k.height) {
            return Err(Error::image(
                &v.image_path,
                format!(
                    "image is {w}x{h} but the camera of view '{}' expects {}x{}",
                    v.name, k.width, k.height
                ),
            ));
        }
    }
    Ok(())
}

/// Helper for readers: a pose error attributed to a file and view.
pub(crate) fn camera_err(path: &Path, view: &str, msg: String) -> Error {
    Error::Camera {
        path: path.to_path_buf(),
        view: view.to_string(),
        msg,
    }
}

/// Helper for readers: builds a view after validating its pose.
pub(crate) fn make_view(
    file: &Path,
    name: &str,
    image_path: PathBuf,
    intrinsics: Intrinsics,
    pose: Result<WorldToCamera, String>,
    bounds: Option<(f64, f64)>,
) -> Result<View> {
    let pose = pose.map_err(|m| camera_err(file, name, m))?;
    intrinsics
        .validate()
        .map_err(|m| camera_err(file, name, m))?;
    Ok(View {
        name: name.to_string(),
        image_path,
        camera: Camera::global(intrinsics, pose),
        bounds,
    })
}
