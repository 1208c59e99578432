//! Writing named f32 / i64 arrays as a safetensors file, atomically.

use crate::error::{Error, Result};
use crate::imageio::write_atomic;
use safetensors::tensor::{Dtype, TensorView};
use std::collections::HashMap;
use std::path::Path;

/// One named array to write: little-endian bytes of `dtype` with `shape`.
pub struct NamedArray {
    pub name: String,
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub bytes: Vec<u8>,
}

impl NamedArray {
    pub fn f32(name: &str, shape: &[usize], data: &[f32]) -> Self {
        Self {
            name: name.to_string(),
            dtype: Dtype::F32,
            shape: shape.to_vec(),
            bytes: data.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }
    pub fn i64(name: &str, shape: &[usize], data: &[i64]) -> Self {
        Self {
            name: name.to_string(),
            dtype: Dtype::I64,
            shape: shape.to_vec(),
            bytes: data.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }
}

/// A tensor's data as little-endian f32 values (its dtype is not checked).
pub fn f32_values(view: &TensorView<'_>) -> Vec<f32> {
    (view.data().chunks_exact(4))
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// Serializes `arrays` with `metadata` and writes them to `path` atomically.
pub fn write_safetensors(
    path: &Path,
    arrays: &[NamedArray],
    metadata: Option<HashMap<String, String>>,
) -> Result<()> {
    let views: Vec<(String, TensorView<'_>)> = arrays
        .iter()
        .map(|a| {
            TensorView::new(a.dtype, a.shape.clone(), &a.bytes)
                .map(|v| (a.name.clone(), v))
                .map_err(|e| Error::format(path, format!("tensor '{}': {e}", a.name)))
        })
        .collect::<Result<_>>()?;
    let mut bytes = safetensors::serialize(views, metadata)
        .map_err(|e| Error::format(path, format!("cannot serialize safetensors: {e}")))?;
    sort_header(&mut bytes);
    write_atomic(path, &bytes)
}

/// Rewrites a serialized file's JSON header with its keys sorted (the metadata comes as a
/// `HashMap`, whose order changes from one process to the next), so the same tensors
/// and metadata always give the same bytes. The header keeps its length: the same keys
/// and values, compact, in another order.
fn sort_header(bytes: &mut [u8]) {
    let Some(len) = bytes
        .get(..8)
        .map(|b| u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as usize)
    else {
        return;
    };
    let Some(header) = bytes.get(8..8 + len) else {
        return;
    };
    let text = String::from_utf8_lossy(header);
    let trimmed = text.trim_end();
    // serde_json's map is a BTreeMap here: serializing sorts every object's keys.
    let sorted = serde_json::from_str::<serde_json::Value>(trimmed)
        .ok()
        .and_then(|v| serde_json::to_string(&v).ok());
    if let Some(sorted) = sorted.filter(|s| s.len() == trimmed.len()) {
        bytes[8..8 + sorted.len()].copy_from_slice(sorted.as_bytes());
    }
}
