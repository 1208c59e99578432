//! A prior in a weights file: its log-weights as the F32 tensor [`TENSOR`], shaped
//! `[nz, ny, nx]` (x fastest, as [`PriorGrid::values`]), and its placement in the
//! metadata under [`META_KEY`] as JSON: `{"origin": [x, y, z], "cell": c, "sharpness":
//! g}` (world units, the first cell's centre and the cells' side; the selection's exponent,
//! 1 when absent).

use super::{PriorGrid, SHARPNESS_RANGE};
use crate::error::{Error, Result};
use crate::tensorio::{f32_values, NamedArray};
use glam::DVec3;
use safetensors::SafeTensors;
use std::path::Path;

/// Name of the log-weights tensor.
pub const TENSOR: &str = "prior.log_weights";
/// Metadata key of the grid's placement.
pub const META_KEY: &str = "deepstereo.prior";

#[derive(serde::Serialize, serde::Deserialize)]
struct Placement {
    origin: [f64; 3],
    cell: f64,
    #[serde(default = "one")]
    sharpness: f64,
}

fn one() -> f64 {
    1.0
}

/// The tensor and the metadata entry that store `grid`.
pub fn to_file(grid: &PriorGrid) -> (NamedArray, (&'static str, String)) {
    let [nx, ny, nz] = grid.dims;
    let place = Placement {
        origin: grid.origin.to_array(),
        cell: grid.cell,
        sharpness: grid.sharpness as f64,
    };
    let json = serde_json::to_string(&place).unwrap_or_default();
    (
        NamedArray::f32(TENSOR, &[nz, ny, nx], &grid.values),
        (META_KEY, json),
    )
}

/// The prior a weights file holds (`None` when it holds none), checked: a tensor without
/// its placement (or the reverse), a wrong shape or dtype, or a non-finite value is an
/// error naming `path`.
pub fn read(path: &Path, bytes: &[u8], st: &SafeTensors<'_>) -> Result<Option<PriorGrid>> {
    let (_, meta) = SafeTensors::read_metadata(bytes)
        .map_err(|e| Error::model(path, format!("not a safetensors file: {e}")))?;
    let place = meta.metadata().as_ref().and_then(|m| m.get(META_KEY));
    let tensor = st.tensor(TENSOR).ok();
    let (place, view) = match (place, tensor) {
        (None, None) => return Ok(None),
        (Some(p), Some(v)) => (p, v),
        _ => {
            return Err(Error::model(
                path,
                format!(
                    "a scene prior needs both the tensor '{TENSOR}' and the metadata '{META_KEY}'"
                ),
            ))
        }
    };
    let bad = |m: String| Error::model(path, format!("scene prior: {m}"));
    let place: Placement =
        serde_json::from_str(place).map_err(|e| bad(format!("'{META_KEY}' is not valid: {e}")))?;
    let origin = DVec3::from_array(place.origin);
    if !(origin.is_finite() && place.cell.is_finite() && place.cell > 0.0) {
        return Err(bad(
            "the origin and the cell side must be finite, the side positive".into(),
        ));
    }
    let (lo, hi) = SHARPNESS_RANGE;
    if !(place.sharpness >= lo as f64 && place.sharpness <= hi as f64) {
        return Err(bad(format!(
            "the sharpness must be within {lo} to {hi}, got {}",
            place.sharpness
        )));
    }
    let shape = view.shape();
    if view.dtype() != safetensors::Dtype::F32 || shape.len() != 3 || shape.iter().any(|&d| d < 2) {
        return Err(bad(format!(
            "'{TENSOR}' must be F32 of shape [nz, ny, nx], each at least 2, got {:?} {shape:?}",
            view.dtype()
        )));
    }
    let values = f32_values(&view);
    if values.iter().any(|v| !v.is_finite()) {
        return Err(bad(format!("'{TENSOR}' holds non-finite values")));
    }
    Ok(Some(PriorGrid {
        origin,
        cell: place.cell,
        dims: [shape[2], shape[1], shape[0]],
        values,
        sharpness: place.sharpness as f32,
    }))
}
