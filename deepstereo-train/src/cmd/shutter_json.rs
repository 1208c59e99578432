//! A rolling shutter as `inspect --json` prints it and `render --pose` reads it:
//! `{"R_start", "t_start", "R_end", "t_end", "time_origin", "time_per_pixel"}`, the poses
//! world-to-camera in OpenCV axes (`R` 9 numbers row-major, `t` 3), the time of pixel
//! coordinate `(u, v)` being `time_origin + time_per_pixel[0] u + time_per_pixel[1] v`
//! (see `deepstereo_core::camera::rolling`).

use anyhow::{bail, Context, Result};
use deepstereo_core::camera::{RollingShutter, WorldToCamera};
use glam::{DMat3, DVec2, DVec3};
use serde_json::{json, Value};
use std::path::Path;

/// `R` row-major.
pub fn rows(r: DMat3) -> Vec<f64> {
    (0..3)
        .flat_map(|i| [r.x_axis[i], r.y_axis[i], r.z_axis[i]])
        .collect()
}

pub fn to_json(rs: &RollingShutter) -> Value {
    let t = |p: &WorldToCamera| [p.translation.x, p.translation.y, p.translation.z];
    json!({
        "R_start": rows(rs.start.rotation), "t_start": t(&rs.start),
        "R_end": rows(rs.end.rotation), "t_end": t(&rs.end),
        "time_origin": rs.time_origin,
        "time_per_pixel": [rs.time_per_pixel.x, rs.time_per_pixel.y],
    })
}

/// The `rolling_shutter` of camera JSON `j` read from `path`: `None` when absent or null.
pub fn from_json(j: &Value, path: &Path) -> Result<Option<RollingShutter>> {
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
        let rot = DMat3::from_cols(
            DVec3::new(r[0], r[3], r[6]),
            DVec3::new(r[1], r[4], r[7]),
            DVec3::new(r[2], r[5], r[8]),
        );
        WorldToCamera::new_checked(rot, DVec3::new(t[0], t[1], t[2]))
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
