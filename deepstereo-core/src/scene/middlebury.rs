//! Middlebury multi-view stereo scenes: `<name>_par.txt`.
//!
//! # Convention
//! The first line is the number of views; each further line is
//! `imgname k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3`
//! with a pixel projecting as `x = K [R | t] X`: `R`, `t` are already world-to-camera in
//! OpenCV axes, so the pose is taken as it is. `K`'s principal point is used as given
//! (the same cameras exported by COLMAP carry the same `cx`, `cy`). Image sizes come
//! from the image headers. Skew must be zero.
//!
//! # Bounds
//! The file gives none. When a `README.txt` beside it states the model's bounding box
//! (two lines of `(x y z)` after the words "bounding box", as the Middlebury archives
//! do), its eight corners serve as sparse points for the robust bounds.

use super::{make_view, RawScene, View, Within};
use crate::camera::{Intrinsics, WorldToCamera};
use crate::error::{Error, Result};
use glam::{DMat3, DVec3};
use std::path::{Path, PathBuf};

/// Number of numbers after the image name on a camera line.
const VALUES_PER_LINE: usize = 21;
/// Largest tolerated skew or non-unit `K[2][2]` deviation.
const K_TOLERANCE: f64 = 1e-9;

/// The `*_par.txt` file in `dir`, if there is exactly one.
pub fn par_file(dir: &Path) -> Option<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.file_name()
                    .is_some_and(|n| n.to_string_lossy().ends_with("_par.txt"))
        })
        .collect();
    found.sort();
    found.into_iter().next()
}

/// Reads a Middlebury scene directory; every image must resolve inside `within`.
pub fn read(dir: &Path, within: &Within) -> Result<RawScene> {
    let file = par_file(dir).ok_or_else(|| Error::format(dir, "no *_par.txt file"))?;
    within.check(dir, "the camera file", &file)?;
    let bytes = std::fs::read(&file).map_err(|e| Error::io(&file, e))?;
    parse_par(&file, &bytes, within)
}

/// Parses the bytes of a `*_par.txt` at `file` (images, and a `README.txt` with the
/// bounding box, are looked up in its folder; each must resolve inside `within`).
pub fn parse_par(file: &Path, bytes: &[u8], within: &Within) -> Result<RawScene> {
    let dir = file.parent().unwrap_or(Path::new("."));
    let text =
        std::str::from_utf8(bytes).map_err(|_| Error::parse(file, None, "not UTF-8 text"))?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let (_, first) = lines
        .next()
        .ok_or_else(|| Error::parse(file, None, "empty file"))?;
    let count: usize = first.trim().parse().map_err(|_| {
        Error::parse(
            file,
            Some(1),
            format!("expected the number of views, got '{}'", first.trim()),
        )
    })?;
    let mut views = Vec::new();
    for (i, line) in lines {
        views.push(parse_line((file, dir, within), i + 1, line)?);
    }
    if views.len() != count {
        return Err(Error::parse(
            file,
            Some(1),
            format!(
                "the header says {count} views but {} camera lines follow",
                views.len()
            ),
        ));
    }
    let mut notes = Vec::new();
    let points = readme_bbox(dir, within, &mut notes)?.unwrap_or_default();
    if !points.is_empty() {
        notes.push("depth bounds from the bounding box in README.txt".to_string());
    }
    Ok(RawScene {
        views,
        bounds: None,
        points,
        notes,
    })
}

/// One camera line of a `*_par.txt` (`lineno` counting from 1): its view, the image checked
/// to lie inside `within` before its header is read.
fn parse_line(
    (file, dir, within): (&Path, &Path, &Within),
    lineno: usize,
    line: &str,
) -> Result<View> {
    let mut parts = line.split_whitespace();
    let name = parts.next().unwrap_or_default().to_string();
    let vals: Vec<f64> = parts
        .map(|s| {
            s.parse::<f64>()
                .map_err(|_| Error::parse(file, Some(lineno), format!("'{s}' is not a number")))
        })
        .collect::<Result<_>>()?;
    if vals.len() != VALUES_PER_LINE {
        return Err(Error::parse(
            file,
            Some(lineno),
            format!(
                "expected a name and {VALUES_PER_LINE} numbers, got {} numbers",
                vals.len()
            ),
        ));
    }
    if vals.iter().any(|v| !v.is_finite()) {
        return Err(Error::parse(file, Some(lineno), "non-finite value"));
    }
    let k = &vals[0..9];
    if k[1].abs() > K_TOLERANCE
        || k[3].abs() > K_TOLERANCE
        || k[6].abs() > K_TOLERANCE
        || k[7].abs() > K_TOLERANCE
        || (k[8] - 1.0).abs() > K_TOLERANCE
    {
        return Err(Error::parse(
            file,
            Some(lineno),
            "K must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew)",
        ));
    }
    let image_path = dir.join(&name);
    within.check(file, &format!("line {lineno}: image '{name}'"), &image_path)?;
    let (w, h) = super::image_size(&image_path)?;
    let intrinsics = Intrinsics::pinhole(k[0], k[4], k[2], k[5], w, h);
    let r = &vals[9..18];
    let rot = DMat3::from_cols(
        DVec3::new(r[0], r[3], r[6]),
        DVec3::new(r[1], r[4], r[7]),
        DVec3::new(r[2], r[5], r[8]),
    );
    let t = DVec3::new(vals[18], vals[19], vals[20]);
    make_view(
        file,
        &name,
        image_path,
        intrinsics,
        WorldToCamera::new_checked(rot, t),
        None,
    )
}

/// The eight corners of the bounding box stated in `dir/README.txt`, if it states one. A
/// README that mentions a bounding box whose corners cannot be read adds a warning to
/// `notes` and gives none; a README outside the scene is refused.
pub(crate) fn readme_bbox(
    dir: &Path,
    within: &Within,
    notes: &mut Vec<String>,
) -> Result<Option<Vec<DVec3>>> {
    let path = dir.join("README.txt");
    if !path.is_file() {
        return Ok(None);
    }
    within.check(dir, "README.txt", &path)?;
    let Ok(text) = std::fs::read_to_string(&path) else {
        notes.push(format!(
            "warning: {}: not readable UTF-8 text; no bounding box read from it",
            path.display()
        ));
        return Ok(None);
    };
    let Some(start) = text.to_ascii_lowercase().find("bounding box") else {
        return Ok(None);
    };
    let corners = bbox_corners(&text[start..]);
    if corners.is_none() {
        notes.push(format!(
            "warning: {}: it mentions a bounding box but not as two lines '(x y z)' of finite numbers; the box is ignored",
            path.display()
        ));
    }
    Ok(corners)
}

/// The eight corners of the box whose two corners are the first two `(x y z)` of `text`.
fn bbox_corners(text: &str) -> Option<Vec<DVec3>> {
    let start = 0;
    let triples: Vec<DVec3> = text[start..]
        .split('(')
        .skip(1)
        .filter_map(|chunk| {
            let inner = chunk.split(')').next()?;
            let v: Vec<f64> = inner
                .split_whitespace()
                .filter_map(|s| s.parse().ok())
                .collect();
            (v.len() == 3 && v.iter().all(|x| x.is_finite())).then(|| DVec3::new(v[0], v[1], v[2]))
        })
        .take(2)
        .collect();
    let [lo, hi] = <[DVec3; 2]>::try_from(triples).ok()?;
    Some(
        (0..8)
            .map(|i| {
                DVec3::new(
                    if i & 1 == 0 { lo.x } else { hi.x },
                    if i & 2 == 0 { lo.y } else { hi.y },
                    if i & 4 == 0 { lo.z } else { hi.z },
                )
            })
            .collect(),
    )
}
