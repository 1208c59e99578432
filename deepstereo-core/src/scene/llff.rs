//! LLFF scenes: `poses_bounds.npy` plus a folder of images.
//!
//! # Convention
//! `poses_bounds.npy` is an `N x 17` array (`<f8` or `<f4`). Row `i` is a 3x5 matrix in
//! row-major order followed by `near_i, far_i`. The first three columns of the matrix are
//! the camera-to-world rotation with columns ordered **[down, right, backwards]**, the
//! fourth is the camera centre in world coordinates, the fifth is `[H, W, focal]` of the
//! FULL-resolution images.
//!
//! # Conversion (once, here)
//! The OpenCV camera axes are x = right = column 1, y = down = column 0 and
//! z = forward = -column 2; these give the OpenCV camera-to-world rotation, whose inverse
//! is the [`WorldToCamera`] pose. The images of the chosen folder may be downscaled
//! (`images_4/` holds 4x smaller images): `fx = fy = focal * W_actual / W_full` and
//! `cx = W_actual / 2`, `cy = H_actual / 2` (LLFF assumes a centred principal point), no
//! distortion. Per-view bounds are `(near_i, far_i)`, the scene's `(min near, max far)`.
//!
//! # Image folder
//! With `factor = Some(n)` the folder is `images_n/` (`images/` also serves for n = 1);
//! without a factor `images/` is used if present, else the smallest `n` among the
//! `images_n/` folders present. The choice is recorded in the scene's notes. Images are
//! the `.png`/`.jpg`/`.jpeg` files (any case) sorted by file name; their count must match
//! the rows. The size is read from the first image's header (every image's size is
//! checked when it is loaded).

use super::{make_view, RawScene, Within};
use crate::camera::{CameraToWorld, Intrinsics, WorldToCamera};
use crate::error::{Error, Result};
use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};

/// Columns of a `poses_bounds.npy` row: a 3x5 matrix plus near and far.
pub const POSES_BOUNDS_COLUMNS: usize = 17;
/// File name of the poses.
pub const POSES_FILE: &str = "poses_bounds.npy";
/// Relative aspect-ratio difference between the file's full-resolution size and the
/// image folder's size above which a note warns that the images are not a plain resize.
const ASPECT_NOTE_TOLERANCE: f64 = 0.01;
/// Extensions of image files, compared case-insensitively.
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Reads an LLFF scene directory; the poses file and every image must resolve inside
/// `within` (an image folder entry may be a symbolic link).
pub fn read(dir: &Path, factor: Option<u32>, within: &Within) -> Result<RawScene> {
    let file = dir.join(POSES_FILE);
    within.check(dir, "the poses file", &file)?;
    let arr = super::npy::read_npy(&file)?;
    let rows = poses_rows(&file, &arr)?;

    let (folder, folder_note) = choose_folder(dir, factor)?;
    let images = list_images(&folder)?;
    for p in &images {
        let name = p.file_name().unwrap_or_default().to_string_lossy();
        within.check(&folder, &format!("image '{name}'"), p)?;
    }
    if images.len() != rows {
        return Err(Error::format(
            &file,
            format!(
                "{rows} poses in {POSES_FILE} but {} images in {}",
                images.len(),
                folder.display()
            ),
        ));
    }
    let first = images
        .first()
        .ok_or_else(|| Error::format(&folder, "no images found"))?;
    let (w, h) = super::image_size(first)?;
    let mut raw = poses_to_views(&file, &arr, images, (w, h))?;
    raw.notes
        .insert(0, format!("{folder_note} ({rows} images of {w}x{h})"));
    Ok(raw)
}

/// Parses the bytes of `poses_bounds.npy` at `file` into one view per row for `images`
/// (in row order; only their names are used), all of `size` pixels: the part of [`read`]
/// after the image folder has been listed.
pub fn parse_poses_bounds(
    file: &Path,
    bytes: &[u8],
    images: Vec<PathBuf>,
    size: (u32, u32),
) -> Result<RawScene> {
    let arr = super::npy::parse_npy(file, bytes)?;
    let rows = poses_rows(file, &arr)?;
    if images.len() != rows {
        return Err(Error::format(
            file,
            format!("{rows} poses in {POSES_FILE} but {} images", images.len()),
        ));
    }
    poses_to_views(file, &arr, images, size)
}

/// The number of rows of a `poses_bounds` array, after checking its shape.
fn poses_rows(file: &Path, arr: &super::npy::NpyArray) -> Result<usize> {
    let (rows, cols) = match arr.shape.as_slice() {
        [r, c] => (*r, *c),
        other => {
            return Err(Error::parse(
                file,
                None,
                format!("expected a 2-D N x {POSES_BOUNDS_COLUMNS} array, got shape {other:?}"),
            ))
        }
    };
    if cols != POSES_BOUNDS_COLUMNS {
        return Err(Error::parse(
            file,
            None,
            format!("expected {POSES_BOUNDS_COLUMNS} columns (3x5 pose + near, far), got {cols}"),
        ));
    }
    if rows == 0 {
        return Err(Error::parse(
            file,
            None,
            "the file holds no cameras (0 rows)",
        ));
    }
    Ok(rows)
}

/// The views of the rows of a `poses_bounds` array for `images` of size `(w, h)`.
fn poses_to_views(
    file: &Path,
    arr: &super::npy::NpyArray,
    images: Vec<PathBuf>,
    (w, h): (u32, u32),
) -> Result<RawScene> {
    let rows = images.len();
    let mut notes = Vec::new();
    let mut views = Vec::with_capacity(rows);
    let mut bounds: Option<(f64, f64)> = None;
    let mut aspect_noted = false;
    for (i, image_path) in images.into_iter().enumerate() {
        let row = arr.row(i).ok_or_else(|| {
            Error::parse(file, None, format!("row {i} is missing from the array"))
        })?;
        let name = image_path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| format!("{i}"));
        let row_err = |msg: String| Error::parse(file, None, format!("row {i} ({name}): {msg}"));
        if row.iter().any(|v| !v.is_finite()) {
            return Err(row_err("non-finite value".into()));
        }
        // m(r, c) of the row-major 3x5 matrix.
        let m = |r: usize, c: usize| row.get(r * 5 + c).copied().unwrap_or(f64::NAN);
        let col = |c: usize| DVec3::new(m(0, c), m(1, c), m(2, c));
        let (down, right, backwards, centre) = (col(0), col(1), col(2), col(3));
        let (h_full, w_full, focal) = (m(0, 4), m(1, 4), m(2, 4));
        if h_full <= 0.0 || w_full <= 0.0 || focal <= 0.0 {
            return Err(row_err(format!(
                "H, W and focal must be positive, got {h_full}, {w_full}, {focal}"
            )));
        }
        let near = row.get(15).copied().unwrap_or(f64::NAN);
        let far = row.get(16).copied().unwrap_or(f64::NAN);
        super::check_bounds(near, far).map_err(|m| row_err(format!("bounds: {m}")))?;
        let scale = w as f64 / w_full;
        let h_scale = h as f64 / h_full;
        if !aspect_noted && ((h_scale - scale) / scale).abs() > ASPECT_NOTE_TOLERANCE {
            aspect_noted = true;
            notes.push(format!(
                "warning: images are {w}x{h} but {POSES_FILE} gives {w_full}x{h_full}; \
                 the focal length is scaled by the width ratio {scale}"
            ));
        }
        let f = focal * scale;
        let intrinsics = Intrinsics::pinhole(f, f, w as f64 / 2.0, h as f64 / 2.0, w, h);
        let pose: std::result::Result<WorldToCamera, String> =
            CameraToWorld::new_checked(DMat3::from_cols(right, down, -backwards), centre)
                .map(|c2w| c2w.inverse());
        views.push(make_view(
            file,
            &name,
            image_path,
            intrinsics,
            pose,
            Some((near, far)),
        )?);
        bounds = Some(match bounds {
            None => (near, far),
            Some((n, f)) => (n.min(near), f.max(far)),
        });
    }
    Ok(RawScene {
        views,
        bounds,
        points: Vec::new(),
        notes,
    })
}

/// Picks the image folder; returns it and a note saying why.
fn choose_folder(dir: &Path, factor: Option<u32>) -> Result<(PathBuf, String)> {
    match factor {
        Some(0) => Err(Error::Invalid(
            "the LLFF image factor must be at least 1".into(),
        )),
        Some(n) => {
            let named = dir.join(format!("images_{n}"));
            if named.is_dir() {
                return Ok((
                    named,
                    format!("LLFF: using images_{n}/ (factor {n} requested)"),
                ));
            }
            if n == 1 && dir.join("images").is_dir() {
                return Ok((
                    dir.join("images"),
                    "LLFF: using images/ (factor 1 requested)".into(),
                ));
            }
            Err(Error::format(
                &named,
                format!("factor {n} requested but the folder images_{n}/ does not exist"),
            ))
        }
        None => {
            let plain = dir.join("images");
            if plain.is_dir() {
                return Ok((plain, "LLFF: using images/ (full resolution)".into()));
            }
            let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
            let mut best: Option<u32> = None;
            for entry in entries.flatten() {
                let name = entry.file_name();
                let n = name
                    .to_str()
                    .and_then(|s| s.strip_prefix("images_"))
                    .and_then(|s| s.parse::<u32>().ok())
                    .filter(|&n| n > 0);
                if let Some(n) = n {
                    if entry.path().is_dir() && best.is_none_or(|b| n < b) {
                        best = Some(n);
                    }
                }
            }
            match best {
                Some(n) => Ok((
                    dir.join(format!("images_{n}")),
                    format!("LLFF: no images/ folder, using images_{n}/ (smallest factor present)"),
                )),
                None => Err(Error::format(
                    dir,
                    "no images/ or images_<N>/ folder next to poses_bounds.npy",
                )),
            }
        }
    }
}

/// The image files of a folder, sorted by file name.
pub fn list_images(folder: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(folder).map_err(|e| Error::io(folder, e))?;
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(folder, e))?;
        let path = entry.path();
        let is_image = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)));
        // A symbolic link is listed whatever it points to, so that the scene's check
        // ([`Within`]) names one that leads outside instead of skipping it silently.
        if is_image && (path.is_file() || path.is_symlink()) {
            out.push(path);
        }
    }
    out.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(out)
}
