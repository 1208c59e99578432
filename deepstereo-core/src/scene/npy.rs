//! A minimal reader and writer for NumPy `.npy` files of little-endian floats.
//!
//! # Convention
//! An `.npy` file is the magic `\x93NUMPY`, a version (1.0, 2.0 or 3.0), a header length
//! (u16 little-endian for 1.0, u32 for 2.0/3.0), a Python dict literal such as
//! `{'descr': '<f8', 'fortran_order': False, 'shape': (66, 17), }` and then the raw
//! array data. Only what scene files use is supported: dtype `<f8` or `<f4`, C order,
//! one or two dimensions. Values are returned as f64 in C (row-major) order; nothing
//! else is converted. Every malformed input (bad magic, truncated header or data, Fortran
//! order, big-endian or other dtypes, a shape whose size does not match the data) is an
//! [`Error::Parse`] naming the file. The shape is checked against the file's length
//! before anything is allocated, so a corrupt header cannot request a huge buffer.

use crate::error::{Error, Result};
use crate::imageio::write_atomic;
use std::path::Path;

/// The `.npy` magic string.
const MAGIC: &[u8] = b"\x93NUMPY";
/// Magic + version bytes.
const PREAMBLE_LEN: usize = MAGIC.len() + 2;
/// The data of an `.npy` file starts at a multiple of this many bytes.
const HEADER_ALIGN: usize = 64;
/// Longest header accepted (NumPy itself writes far less).
const MAX_HEADER_LEN: usize = 1 << 20;
/// Most dimensions accepted when reading (the readers need tables and vectors).
const MAX_DIMS: usize = 2;
/// Most dimensions written (images are `[H, W, 3]`, sweeps `[D, H, W, 4]`).
const MAX_WRITE_DIMS: usize = 8;

/// Element type of an `.npy` file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NpyDtype {
    F32,
    F64,
}

impl NpyDtype {
    fn size(self) -> usize {
        match self {
            NpyDtype::F32 => 4,
            NpyDtype::F64 => 8,
        }
    }
    fn descr(self) -> &'static str {
        match self {
            NpyDtype::F32 => "<f4",
            NpyDtype::F64 => "<f8",
        }
    }
}

/// A 1-D or 2-D array read from an `.npy` file, data in C order, widened to f64.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    pub dtype: NpyDtype,
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

impl NpyArray {
    /// Rows and columns of a 2-D array (a 1-D array of length `n` is one row of `n`).
    pub fn rows_cols(&self) -> (usize, usize) {
        match self.shape.as_slice() {
            [n] => (1, *n),
            [r, c] => (*r, *c),
            _ => (0, 0),
        }
    }

    /// Row `i` of a 2-D array, `None` out of range.
    pub fn row(&self, i: usize) -> Option<&[f64]> {
        let (_, c) = self.rows_cols();
        let start = i.checked_mul(c)?;
        self.data.get(start..start.checked_add(c)?)
    }
}

/// Reads an `.npy` file of `<f8` or `<f4` values.
pub fn read_npy(path: &Path) -> Result<NpyArray> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse_npy(path, &bytes)
}

/// Parses the bytes of an `.npy` file; `path` only names the file in errors.
pub fn parse_npy(path: &Path, bytes: &[u8]) -> Result<NpyArray> {
    let err = |msg: String| Error::parse(path, None, format!("invalid .npy file: {msg}"));
    if bytes.len() < PREAMBLE_LEN || !bytes.starts_with(MAGIC) {
        return Err(err("missing the \\x93NUMPY magic (not a NumPy file)".into()));
    }
    let (major, minor) = (bytes[MAGIC.len()], bytes[MAGIC.len() + 1]);
    let len_bytes = match major {
        1 => 2,
        2 | 3 => 4,
        _ => return Err(err(format!("unsupported version {major}.{minor}"))),
    };
    let header_start = PREAMBLE_LEN + len_bytes;
    let len_field = bytes
        .get(PREAMBLE_LEN..header_start)
        .ok_or_else(|| err("truncated before the header length".into()))?;
    let header_len = len_field
        .iter()
        .rev()
        .fold(0usize, |acc, &b| (acc << 8) | b as usize);
    if header_len > MAX_HEADER_LEN {
        return Err(err(format!(
            "header length {header_len} is implausibly large"
        )));
    }
    let data_start = header_start + header_len;
    let header = bytes
        .get(header_start..data_start)
        .ok_or_else(|| err(format!("truncated header (needs {header_len} bytes)")))?;
    let header = std::str::from_utf8(header).map_err(|_| err("header is not text".into()))?;
    let (dtype, shape) = parse_header(header).map_err(err)?;

    let count = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| err(format!("shape {shape:?} overflows")))?;
    let data = bytes.get(data_start..).unwrap_or(&[]);
    let expected = count
        .checked_mul(dtype.size())
        .ok_or_else(|| err(format!("shape {shape:?} overflows")))?;
    if data.len() != expected {
        return Err(err(format!(
            "shape {shape:?} of {} needs {expected} data bytes but the file has {}{}",
            dtype.descr(),
            data.len(),
            if data.len() < expected {
                " (truncated)"
            } else {
                ""
            }
        )));
    }
    let data: Vec<f64> = match dtype {
        NpyDtype::F64 => data
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect(),
        NpyDtype::F32 => data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
            .collect(),
    };
    Ok(NpyArray { dtype, shape, data })
}

/// Parses the header dict; returns the dtype and shape.
fn parse_header(header: &str) -> std::result::Result<(NpyDtype, Vec<usize>), String> {
    let descr = dict_value(header, "descr")?;
    let descr = descr
        .trim()
        .strip_prefix(['\'', '"'])
        .and_then(|s| s.strip_suffix(['\'', '"']))
        .ok_or_else(|| format!("'descr' is not a string: {descr}"))?;
    let dtype = match descr {
        "<f8" => NpyDtype::F64,
        "<f4" => NpyDtype::F32,
        ">f8" | ">f4" => return Err(format!("big-endian dtype '{descr}' is not supported")),
        other => {
            return Err(format!(
                "dtype '{other}' is not supported (expected little-endian float '<f8' or '<f4')"
            ))
        }
    };
    match dict_value(header, "fortran_order")?.trim() {
        "False" => {}
        "True" => return Err("Fortran-order arrays are not supported".into()),
        other => return Err(format!("'fortran_order' is not a boolean: {other}")),
    }
    let shape_text = dict_value(header, "shape")?;
    let inner = shape_text
        .trim()
        .strip_prefix('(')
        .and_then(|s| s.strip_suffix(')'))
        .ok_or_else(|| format!("'shape' is not a tuple: {shape_text}"))?;
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| format!("bad dimension '{s}' in shape"))
        })
        .collect::<std::result::Result<Vec<_>, _>>()?;
    if shape.is_empty() || shape.len() > MAX_DIMS {
        return Err(format!(
            "shape ({inner}) has {} dimensions; only 1-D and 2-D arrays are supported",
            shape.len()
        ));
    }
    Ok((dtype, shape))
}

/// The raw text of the value of `key` in the header dict (up to the next top-level comma).
fn dict_value<'a>(header: &'a str, key: &str) -> std::result::Result<&'a str, String> {
    let needle_sq = format!("'{key}'");
    let needle_dq = format!("\"{key}\"");
    let pos = header
        .find(&needle_sq)
        .map(|p| p + needle_sq.len())
        .or_else(|| header.find(&needle_dq).map(|p| p + needle_dq.len()))
        .ok_or_else(|| format!("header has no '{key}' entry"))?;
    let rest = header
        .get(pos..)
        .and_then(|s| s.trim_start().strip_prefix(':'))
        .ok_or_else(|| format!("header entry '{key}' has no value"))?;
    let mut depth = 0i32;
    for (i, ch) in rest.char_indices() {
        match ch {
            '(' => depth += 1,
            ')' => depth -= 1,
            ',' | '}' if depth <= 0 => return Ok(rest.get(..i).unwrap_or(rest)),
            _ => {}
        }
    }
    Err(format!("header entry '{key}' is not terminated"))
}

/// Builds the bytes of a version 1.0 (or 2.0 for huge headers) `.npy` file.
fn npy_bytes(dtype: NpyDtype, shape: &[usize], payload: &[u8]) -> Vec<u8> {
    let shape_text = match shape {
        [n] => format!("({n},)"),
        dims => format!(
            "({})",
            dims.iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {shape_text}, }}",
        dtype.descr()
    );
    let v1 = header.len() + 1 + PREAMBLE_LEN + 2 <= u16::MAX as usize;
    let prefix = PREAMBLE_LEN + if v1 { 2 } else { 4 };
    let total = prefix + header.len() + 1;
    let padded = total.div_ceil(HEADER_ALIGN) * HEADER_ALIGN;
    header.extend(std::iter::repeat_n(' ', padded - total));
    header.push('\n');
    let mut out = Vec::with_capacity(padded + payload.len());
    out.extend_from_slice(MAGIC);
    if v1 {
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&[2, 0]);
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(payload);
    out
}

fn check_shape(path: &Path, shape: &[usize], len: usize) -> Result<()> {
    let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
    if shape.is_empty() || shape.len() > MAX_WRITE_DIMS || count != Some(len) {
        return Err(Error::Invalid(format!(
            "{}: cannot write {len} values with shape {shape:?} (1 to {MAX_WRITE_DIMS} dimensions whose product is the value count)",
            path.display()
        )));
    }
    Ok(())
}

/// Writes a C-order `<f4` array atomically.
pub fn write_npy_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<()> {
    check_shape(path, shape, data.len())?;
    let payload: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    write_atomic(path, &npy_bytes(NpyDtype::F32, shape, &payload))
}

/// Writes a C-order `<f8` array atomically.
pub fn write_npy_f64(path: &Path, shape: &[usize], data: &[f64]) -> Result<()> {
    check_shape(path, shape, data.len())?;
    let payload: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    write_atomic(path, &npy_bytes(NpyDtype::F64, shape, &payload))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_round_trip() {
        let p = Path::new("x.npy");
        let bytes = npy_bytes(NpyDtype::F64, &[2, 3], &[0u8; 48]);
        assert_eq!(bytes.len() % HEADER_ALIGN, 48 % HEADER_ALIGN);
        let a = parse_npy(p, &bytes).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.row(1), Some(&[0.0; 3][..]));
        assert_eq!(a.row(2), None);
        let b = npy_bytes(NpyDtype::F32, &[5], &[0u8; 20]);
        assert_eq!(parse_npy(p, &b).unwrap().shape, vec![5]);
    }

    #[test]
    fn writes_images_of_three_dimensions() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("image.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32).collect();
        write_npy_f32(&p, &[2, 4, 3], &data).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let text = String::from_utf8_lossy(&bytes[..HEADER_ALIGN * 2]).into_owned();
        assert!(text.contains("'shape': (2, 4, 3)"), "{text}");
        assert_eq!(bytes.len() % HEADER_ALIGN, (24 * 4) % HEADER_ALIGN);
        let tail = &bytes[bytes.len() - 4..];
        assert_eq!(f32::from_le_bytes(tail.try_into().unwrap()), 23.0);
        // Counts that do not match the shape, and empty shapes, are refused.
        assert!(write_npy_f32(&p, &[2, 4, 4], &data).is_err());
        assert!(write_npy_f32(&p, &[], &data).is_err());
    }

    #[test]
    fn rejects_bad_headers() {
        let p = Path::new("x.npy");
        for h in [
            "{'descr': '>f8', 'fortran_order': False, 'shape': (1,), }",
            "{'descr': '<i4', 'fortran_order': False, 'shape': (1,), }",
            "{'descr': '<f8', 'fortran_order': True, 'shape': (1,), }",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 1, 1), }",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (99999999999999999999,), }",
            "{'descr': '<f8', 'fortran_order': False, }",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4611686018427387904, 4), }",
        ] {
            let mut b = MAGIC.to_vec();
            b.extend_from_slice(&[1, 0]);
            b.extend_from_slice(&(h.len() as u16).to_le_bytes());
            b.extend_from_slice(h.as_bytes());
            b.extend_from_slice(&[0; 8]);
            let e = parse_npy(p, &b).unwrap_err().to_string();
            assert!(e.contains("x.npy"), "{h}: {e}");
        }
    }
}
