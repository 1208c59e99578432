//! Cameras as JSON: what `inspect --json` prints and `render --pose` reads.
//!
//! A scene is `{"format", "near", "far", "bounds_source", "views"}`, `far` being `null` for
//! a plane at infinity (files written before wrote the string `"inf"`, which
//! [`far_from_json`] reads too). A view is
//! `{"name", "width", "height", "fx", "fy", "cx", "cy", "distortion", "R", "t"}`, the pose
//! world-to-camera in OpenCV axes (`R` 9 numbers row-major, `t` 3), and a rolling shutter
//! adds `rolling_shutter: {"R_start", "t_start", "R_end", "t_end", "time_origin",
//! "time_per_pixel"}`, the time of pixel coordinate `(u, v)` being `time_origin +
//! time_per_pixel[0] u + time_per_pixel[1] v` (see `deepstereo_core::camera::rolling`);
//! `R`, `t` are then the pose at the image centre's time.

use anyhow::{bail, Context, Result};
use deepstereo_core::camera::{Camera, Intrinsics, RollingShutter, WorldToCamera};
use deepstereo_core::scene::{Scene, View};
use glam::{DMat3, DVec2, DVec3};
use serde_json::{json, Value};
use std::path::Path;

/// A scene as `inspect --json` prints it: `format`, `near`, `far` ([`far_json`]),
/// `bounds_source` and every view ([`view_json`]).
pub fn scene_json(scene: &Scene) -> Value {
    let views: Vec<Value> = scene.views.iter().map(view_json).collect();
    json!({
        "format": scene.format.name(), "near": scene.near, "far": far_json(scene.far),
        "bounds_source": scene.bounds_source, "views": views,
    })
}

/// A far bound as JSON: the number, or `null` for a plane at infinity (JSON has no
/// infinity).
pub fn far_json(far: f64) -> Value {
    if far.is_finite() {
        json!(far)
    } else {
        Value::Null
    }
}

/// A far bound read back from JSON: a number, or infinity for `null` (and for the string
/// `"inf"` that `inspect --json` wrote before); `None` for anything else.
pub fn far_from_json(v: &Value) -> Option<f64> {
    match v {
        Value::Null => Some(f64::INFINITY),
        Value::String(s) if s == "inf" => Some(f64::INFINITY),
        v => v.as_f64(),
    }
}

/// One view: `name`, `width`, `height`, `fx`, `fy`, `cx`, `cy`, `distortion` (`[k1, k2,
/// p1, p2]` or null), `R` (row-major), `t`, and `rolling_shutter` ([`shutter_to_json`])
/// for a rolling-shutter camera.
pub fn view_json(v: &View) -> Value {
    camera_json(&v.name, &v.camera)
}

/// A camera as one view of [`view_json`], named `name`.
pub fn camera_json(name: &str, camera: &Camera) -> Value {
    let k = &camera.intrinsics;
    let t = camera.pose.translation;
    let d = k.distortion;
    let mut view = json!({
        "name": name, "width": k.width, "height": k.height,
        "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
        "distortion": d.map(|d| [d.k1, d.k2, d.p1, d.p2]),
        "R": rows(camera.pose.rotation), "t": [t.x, t.y, t.z],
    });
    if let (Some(rs), Some(obj)) = (&camera.rolling_shutter, view.as_object_mut()) {
        obj.insert("rolling_shutter".into(), shutter_to_json(rs));
    }
    view
}

/// A camera path's cameras in `inspect --json`'s layout (`format` "camera path", the
/// scene's bounds, views named `frame_NNNN`): `render --path FILE` reads it back.
pub fn path_json(cams: &[Camera], scene: &Scene) -> Value {
    let views: Vec<Value> = cams
        .iter()
        .enumerate()
        .map(|(f, c)| camera_json(&format!("frame_{f:04}"), c))
        .collect();
    json!({
        "format": "camera path", "near": scene.near, "far": far_json(scene.far),
        "bounds_source": scene.bounds_source, "views": views,
    })
}

/// Every camera of a JSON file: each view of `inspect --json`'s output (or of a path's
/// `cameras.json`), or the one camera of a single view.
pub fn read_cameras(path: &Path) -> Result<Vec<Camera>> {
    let all = read_json(path)?;
    match all.get("views").and_then(|v| v.as_array()) {
        Some(views) if views.is_empty() => bail!("{}: 'views' is empty", path.display()),
        Some(views) => views
            .iter()
            .enumerate()
            .map(|(i, j)| camera_from_json(j, path).with_context(|| format!("view {i}")))
            .collect(),
        None => Ok(vec![camera_from_json(&all, path)?]),
    }
}

fn read_json(path: &Path) -> Result<Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: invalid JSON", path.display()))
}

/// Reads a camera from a JSON file (world-to-camera, OpenCV axes): one view, or with
/// `view` the view of that index in `inspect --json`'s output.
pub fn read_pose(path: &Path, view: Option<usize>) -> Result<Camera> {
    let all = read_json(path)?;
    let j = match (all.get("views").and_then(|v| v.as_array()), view) {
        (Some(views), Some(i)) => views.get(i).with_context(|| {
            format!(
                "{}: --view {i} is out of range: the file holds {} views",
                path.display(),
                views.len()
            )
        })?,
        (Some(views), None) => bail!(
            "{}: holds {} views (inspect --json's output); pick one with --view I",
            path.display(),
            views.len()
        ),
        (None, Some(_)) => bail!(
            "{}: --view needs a file with a 'views' list (inspect --json's output)",
            path.display()
        ),
        (None, None) => &all,
    };
    camera_from_json(j, path)
}

/// One view's camera (`path` names the file in errors).
fn camera_from_json(j: &Value, path: &Path) -> Result<Camera> {
    let num = |k: &str| -> Result<f64> {
        j.get(k)
            .and_then(|v| v.as_f64())
            .with_context(|| format!("{}: missing or non-numeric '{k}'", path.display()))
    };
    let arr = |k: &str, n: usize| -> Result<Vec<f64>> {
        let a: Vec<f64> = j
            .get(k)
            .and_then(|v| v.as_array())
            .map(|a| a.iter().filter_map(|x| x.as_f64()).collect())
            .unwrap_or_default();
        if a.len() != n {
            bail!("{}: '{k}' must be an array of {n} numbers", path.display());
        }
        Ok(a)
    };
    let (w, h) = (num("width")?, num("height")?);
    if !(w >= 1.0 && h >= 1.0 && w <= 32768.0 && h <= 32768.0) {
        bail!("{}: width and height must be 1..=32768", path.display());
    }
    let intr = Intrinsics::pinhole(
        num("fx")?,
        num("fy")?,
        num("cx")?,
        num("cy")?,
        w as u32,
        h as u32,
    );
    intr.validate()
        .map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
    let r = arr("R", 9)?;
    let t = arr("t", 3)?;
    let pose = WorldToCamera::new_checked(from_rows(&r), DVec3::new(t[0], t[1], t[2]))
        .map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
    // With a rolling shutter, each row is rendered at its own pose; `R`/`t` (the pose at
    // the image centre's time, as `inspect` prints it) are then not used.
    Ok(match shutter_from_json(j, path)? {
        Some(rs) => Camera::rolling(intr, rs),
        None => Camera::global(intr, pose),
    })
}

/// `R` row-major.
pub fn rows(r: DMat3) -> Vec<f64> {
    (0..3)
        .flat_map(|i| [r.x_axis[i], r.y_axis[i], r.z_axis[i]])
        .collect()
}

/// The matrix of 9 numbers `r`, row-major (the inverse of [`rows`]).
fn from_rows(r: &[f64]) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(r[0], r[3], r[6]),
        DVec3::new(r[1], r[4], r[7]),
        DVec3::new(r[2], r[5], r[8]),
    )
}

/// A rolling shutter's poses and timing.
pub fn shutter_to_json(rs: &RollingShutter) -> Value {
    let t = |p: &WorldToCamera| [p.translation.x, p.translation.y, p.translation.z];
    json!({
        "R_start": rows(rs.start.rotation), "t_start": t(&rs.start),
        "R_end": rows(rs.end.rotation), "t_end": t(&rs.end),
        "time_origin": rs.time_origin,
        "time_per_pixel": [rs.time_per_pixel.x, rs.time_per_pixel.y],
    })
}

/// The `rolling_shutter` of camera JSON `j` read from `path`: `None` when absent or null.
pub fn shutter_from_json(j: &Value, path: &Path) -> Result<Option<RollingShutter>> {
    let Some(rs) = j.get("rolling_shutter").filter(|v| !v.is_null()) else {
        return Ok(None);
    };
    let p = path.display();
    let arr = |k: &str, n: usize| -> Result<Vec<f64>> {
        let a: Vec<f64> = rs
            .get(k)
            .and_then(|v| v.as_array())
            .map(|a| a.iter().filter_map(|x| x.as_f64()).collect())
            .unwrap_or_default();
        if a.len() != n || a.iter().any(|x| !x.is_finite()) {
            bail!("{p}: 'rolling_shutter.{k}' must be an array of {n} finite numbers");
        }
        Ok(a)
    };
    let pose = |r: &str, t: &str| -> Result<WorldToCamera> {
        let (r, t) = (arr(r, 9)?, arr(t, 3)?);
        WorldToCamera::new_checked(from_rows(&r), DVec3::new(t[0], t[1], t[2]))
            .map_err(|m| anyhow::anyhow!("{p}: rolling_shutter: {m}"))
    };
    let origin = rs
        .get("time_origin")
        .and_then(|v| v.as_f64())
        .with_context(|| format!("{p}: missing or non-numeric 'rolling_shutter.time_origin'"))?;
    let per = arr("time_per_pixel", 2)?;
    let shutter = RollingShutter::new_checked(
        pose("R_start", "t_start")?,
        pose("R_end", "t_end")?,
        origin,
        DVec2::new(per[0], per[1]),
    )
    .map_err(|m| anyhow::anyhow!("{p}: {m}"))?;
    Ok(Some(shutter))
}

#[cfg(test)]
mod tests {
    use super::{far_from_json, far_json};
    use serde_json::json;

    #[test]
    fn an_infinite_far_bound_is_null_and_reads_back() {
        assert_eq!(far_json(f64::INFINITY), serde_json::Value::Null);
        assert_eq!(far_json(12.5), json!(12.5));
        for far in [0.25, 12.5, f64::INFINITY] {
            assert_eq!(far_from_json(&far_json(far)), Some(far));
        }
        assert_eq!(far_from_json(&json!("inf")), Some(f64::INFINITY));
        assert_eq!(far_from_json(&json!("far")), None);
        assert_eq!(far_from_json(&json!([1.0])), None);
    }
}
