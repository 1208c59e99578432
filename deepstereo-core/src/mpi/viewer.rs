//! The browser viewer written beside MPIs: `index.html` (plain WebGL2, no library, no
//! network) and `mpi.js`, which holds every MPI's description with its planes inlined as
//! `data:` URIs so that the page opens from the file system without a server.

use super::io::{MpiJson, JSON_NAME};
use crate::error::{Error, Result};
use crate::imageio::write_atomic;
use serde::Serialize;
use std::path::Path;

/// The viewer page (see its header for the controls, `?fit=native` and `?bench=N`).
pub const INDEX_HTML: &str = include_str!("viewer.html");
/// The most MPIs the viewer blends.
pub const MAX_MPIS: usize = 8;

#[derive(Serialize)]
struct ViewerMpi<'a> {
    /// The MPI's directory, relative to the viewer's.
    name: &'a str,
    #[serde(flatten)]
    json: MpiJson,
}

#[derive(Serialize)]
struct ViewerData<'a> {
    /// How far (world units) the viewer may move from the first MPI's reference.
    range: f64,
    mpis: Vec<ViewerMpi<'a>>,
}

/// Writes `index.html` and `mpi.js` into `dir` for the MPIs in its subdirectories
/// `names` (`"."` for an MPI in `dir` itself), each holding `mpi.json` and its planes.
/// `range`: how far the viewer may move from the first MPI's reference camera.
pub fn write(dir: &Path, names: &[&str], range: f64) -> Result<()> {
    if names.is_empty() || names.len() > MAX_MPIS {
        return Err(Error::Invalid(format!(
            "the viewer shows 1 to {MAX_MPIS} MPIs, not {}",
            names.len()
        )));
    }
    let mut mpis = Vec::new();
    for name in names {
        let sub = dir.join(name);
        let file = sub.join(JSON_NAME);
        let text = std::fs::read_to_string(&file).map_err(|e| Error::io(&file, e))?;
        let mut json: MpiJson =
            serde_json::from_str(&text).map_err(|e| Error::format(&file, e.to_string()))?;
        for plane in json.planes.iter_mut() {
            let path = sub.join(&*plane);
            let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
            *plane = format!("data:image/png;base64,{}", base64(&bytes));
        }
        mpis.push(ViewerMpi { name, json });
    }
    let data = ViewerData {
        range: if range.is_finite() && range > 0.0 {
            range
        } else {
            1.0
        },
        mpis,
    };
    let js = serde_json::to_string(&data)
        .map_err(|e| Error::Invalid(format!("cannot serialize the viewer's data: {e}")))?;
    write_atomic(
        &dir.join("mpi.js"),
        format!("window.DEEPSTEREO_MPIS = {js};\n").as_bytes(),
    )?;
    write_atomic(&dir.join("index.html"), INDEX_HTML.as_bytes())
}

/// Standard base64 (RFC 4648, with padding).
pub fn base64(bytes: &[u8]) -> String {
    const ABC: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(ABC[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}
