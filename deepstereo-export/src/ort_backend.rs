//! Running an exported model through onnxruntime ([`ort`], loaded at run time).
//!
//! The library is found, in order, at `ORT_DYLIB_PATH`, else in the `onnxruntime` Python
//! package of the project's venv: `.venv/lib/python*/site-packages/onnxruntime/capi/`
//! `libonnxruntime.so*` in the current directory or one above it, or in a directory above
//! the running executable (so `target/release/deepstereo` finds the repository's `.venv`).

use crate::error::{Error, Result};
use crate::export::{
    config_of, export_features, export_trainable, features_path, input_name, model_weights,
    DEFAULT_OPSET,
};
use crate::onnx_proto::ModelProto;
use deepstereo_core::config::Config;
use deepstereo_core::features::{padded_crop, FeatureMap, Window};
use deepstereo_core::imageio::RgbImage;
use deepstereo_core::inputs::TileInputs;
use deepstereo_core::render::Backend;
use deepstereo_core::weights::Trainable;
use ort::environment::Environment;
use ort::session::Session;
use ort::value::TensorRef;
use prost::Message;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

/// What a forward pass returns: shapes and row-major data.
#[derive(Clone, Debug, PartialEq)]
pub struct Forward {
    /// `[B, 3, th, tw]`.
    pub image_shape: Vec<usize>,
    pub image: Vec<f32>,
    /// `[B, D, th, tw]`.
    pub selection_shape: Vec<usize>,
    pub selection: Vec<f32>,
}

/// The network run by onnxruntime on an exported ONNX model.
pub struct OrtBackend {
    cfg: Config,
    session: Mutex<Session>,
    /// The `features` family's feature graph ([`crate::export::build_features_model`]).
    features: Option<Mutex<Session>>,
    /// Where libonnxruntime was loaded from.
    library: PathBuf,
}

/// The libonnxruntime files of the `onnxruntime` package in `venv`, the versioned name first.
fn venv_libraries(venv: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let Ok(libdirs) = std::fs::read_dir(venv.join("lib")) else {
        return found;
    };
    let mut libdirs: Vec<PathBuf> = libdirs.filter_map(|e| e.ok().map(|e| e.path())).collect();
    libdirs.sort();
    for py in libdirs {
        let capi = py.join("site-packages").join("onnxruntime").join("capi");
        let Ok(entries) = std::fs::read_dir(&capi) else {
            continue;
        };
        let mut libs: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
                    n.starts_with("libonnxruntime.so") || n == "libonnxruntime.dylib"
                })
            })
            .collect();
        // The versioned name (`libonnxruntime.so.1.31.1`) is the real file in the wheel.
        libs.sort_by_key(|p| std::cmp::Reverse(p.as_os_str().len()));
        found.extend(libs);
    }
    found
}

/// Directories to look for `.venv` in: the current directory and its ancestors, then the
/// executable's directory and its ancestors.
fn search_roots() -> Vec<PathBuf> {
    let mut roots = Vec::new();
    if let Ok(cwd) = std::env::current_dir() {
        roots.extend(cwd.ancestors().map(Path::to_path_buf));
    }
    if let Ok(exe) = std::env::current_exe() {
        let exe = exe.canonicalize().unwrap_or(exe);
        if let Some(dir) = exe.parent() {
            roots.extend(dir.ancestors().map(Path::to_path_buf));
        }
    }
    let mut seen = std::collections::HashSet::new();
    roots.retain(|r| seen.insert(r.clone()));
    roots
}

/// Finds libonnxruntime (see the module documentation).
pub fn find_onnxruntime() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        if p.is_file() {
            return Ok(p);
        }
        return Err(Error::OrtLibrary(format!(
            "ORT_DYLIB_PATH={} is not a file: point it at libonnxruntime.so (for example the one in \
             .venv/lib/python3*/site-packages/onnxruntime/capi/)",
            p.display()
        )));
    }
    for root in search_roots() {
        let venv = root.join(".venv");
        if venv.is_dir() {
            if let Some(lib) = venv_libraries(&venv).into_iter().next() {
                return Ok(lib);
            }
        }
    }
    Err(Error::OrtLibrary(
        "libonnxruntime not found: set ORT_DYLIB_PATH to libonnxruntime.so, or run `bash tests/run-all.sh` once in \
         the repository to create .venv with the onnxruntime Python package (searched for .venv in the current \
         directory, the executable's directory and their parents)"
            .into(),
    ))
}

/// The process's one onnxruntime environment (ort allows one per process) and the library
/// it was loaded from.
fn environment() -> Result<&'static (Environment, PathBuf)> {
    static ENV: OnceLock<std::result::Result<(Environment, PathBuf), String>> = OnceLock::new();
    ENV.get_or_init(|| {
        let lib = find_onnxruntime().map_err(|e| e.to_string())?;
        let builder = ort::init_from(&lib)
            .map_err(|e| format!("cannot load onnxruntime from {}: {e}", lib.display()))?;
        let env = builder
            .with_name("deepstereo")
            .with_telemetry(false)
            .build()
            .map_err(|e| format!("cannot create the onnxruntime environment: {e}"))?;
        Ok((env, lib))
    })
    .as_ref()
    .map_err(|e| Error::OrtLibrary(e.clone()))
}

impl OrtBackend {
    /// Loads an ONNX model written by [`crate::export()`] (its config comes from the metadata).
    pub fn from_bytes(onnx: &[u8]) -> Result<Self> {
        let model = ModelProto::decode(onnx).map_err(|e| Error::Onnx {
            what: "ONNX model".into(),
            msg: format!("cannot decode: {e}"),
        })?;
        let cfg = config_of(&model)?;
        let (session, lib) = session_of(onnx)?;
        Ok(Self {
            cfg,
            session: Mutex::new(session),
            features: None,
            library: lib,
        })
    }

    /// This backend with the feature graph `onnx` (`deepstereo export` writes it beside
    /// the network's for the `features` family).
    pub fn with_features_graph(mut self, onnx: &[u8]) -> Result<Self> {
        self.features = Some(Mutex::new(session_of(onnx)?.0));
        Ok(self)
    }

    /// Loads an ONNX file written by `deepstereo export`.
    pub fn from_file(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let backend = Self::from_bytes(&bytes).map_err(|e| match e {
            Error::Onnx { msg, .. } => Error::Onnx {
                what: path.display().to_string(),
                msg,
            },
            other => other,
        })?;
        if backend
            .cfg
            .pool
            .as_ref()
            .is_none_or(|p| p.features.is_none())
        {
            return Ok(backend);
        }
        let fpath = features_path(path);
        let bytes = std::fs::read(&fpath).map_err(|source| Error::Io {
            path: fpath.clone(),
            source,
        })?;
        backend.with_features_graph(&bytes)
    }

    /// Exports `model` in memory (opset [`DEFAULT_OPSET`]) and loads it.
    pub fn from_model(model: &Trainable) -> Result<Self> {
        let backend = Self::from_bytes(&export_trainable(model, DEFAULT_OPSET)?)?;
        let weights = model_weights(model)?;
        match export_features(model.model.config(), &weights, DEFAULT_OPSET)? {
            Some(bytes) => backend.with_features_graph(&bytes),
            None => Ok(backend),
        }
    }

    /// The feature graph on one source image: `[F, H, W]`.
    fn image_features(&self, img: &RgbImage) -> Result<FeatureMap> {
        let (Some(session), Some(sf)) = (
            self.features.as_ref(),
            self.cfg.pool.as_ref().and_then(|p| p.features.as_ref()),
        ) else {
            return Err(Error::Input(format!(
                "the model '{}' reads no source features, or its feature graph is not loaded",
                self.cfg.name
            )));
        };
        let r = sf.radius();
        let (w, h) = (img.width as usize, img.height as usize);
        let window = Window {
            x0: -(r as i64),
            y0: -(r as i64),
            width: w + 2 * r,
            height: h + 2 * r,
        };
        let data = padded_crop(img, window);
        let shape = vec![1, 3, window.height, window.width];
        let t = TensorRef::from_array_view((shape, data.as_slice())).map_err(Error::ort)?;
        let mut session = session.lock().map_err(|_| {
            Error::Ort("the session's lock is poisoned (an earlier run panicked)".into())
        })?;
        let outputs = session.run(vec![("image", t)]).map_err(Error::ort)?;
        let v = outputs
            .get("features")
            .ok_or_else(|| Error::Ort("the feature graph has no output 'features'".into()))?;
        let (_, data) = v.try_extract_tensor::<f32>().map_err(Error::ort)?;
        Ok(FeatureMap {
            channels: sf.channels(),
            width: w,
            height: h,
            data: data.to_vec(),
        })
    }

    pub fn library(&self) -> &Path {
        &self.library
    }

    /// Runs the network on `levels[l]` = (shape `[B, D, 4V, H_l, W_l]`, or
    /// `[B, D, V, C_v, H_l, W_l]` for the any-number-of-views family, `C_v` =
    /// `Config::view_channels`, data).
    pub fn forward(&self, levels: &[(&[usize], &[f32])]) -> Result<Forward> {
        let cfg = &self.cfg;
        if levels.len() != cfg.levels {
            return Err(Error::Input(format!(
                "expected {} input levels, got {}",
                cfg.levels,
                levels.len()
            )));
        }
        let mut inputs = Vec::with_capacity(levels.len());
        let cv = cfg.view_channels();
        for (l, (shape, data)) in levels.iter().enumerate() {
            let ok = match cfg.pool {
                Some(_) => shape.len() == 6 && shape[3] == cv && !shape[..3].contains(&0),
                None => {
                    shape.len() == 5 && shape[2] == cfg.in_channels() && !shape[..2].contains(&0)
                }
            };
            if !ok {
                let want = match cfg.pool {
                    Some(_) => format!("[B, D, V, {cv}, H, W] with B, D and V at least 1"),
                    None => format!(
                        "[B, D, {}, H, W] with B and D at least 1",
                        cfg.in_channels()
                    ),
                };
                return Err(Error::Input(format!(
                    "level {l}: expected shape {want}, got {shape:?}"
                )));
            }
            if shape.iter().product::<usize>() != data.len() {
                return Err(Error::Input(format!(
                    "level {l}: shape {shape:?} does not match {} values",
                    data.len()
                )));
            }
            let t = TensorRef::from_array_view((shape.to_vec(), *data)).map_err(Error::ort)?;
            inputs.push((input_name(l), t));
        }
        let mut session = self.session.lock().map_err(|_| {
            Error::Ort("the session's lock is poisoned (an earlier run panicked)".into())
        })?;
        let outputs = session.run(inputs).map_err(Error::ort)?;
        let get = |name: &str| -> Result<(Vec<usize>, Vec<f32>)> {
            let v = outputs
                .get(name)
                .ok_or_else(|| Error::Ort(format!("the model has no output '{name}'")))?;
            let (shape, data) = v.try_extract_tensor::<f32>().map_err(Error::ort)?;
            Ok((shape.iter().map(|&d| d as usize).collect(), data.to_vec()))
        };
        let (image_shape, image) = get("image")?;
        let (selection_shape, selection) = get("selection")?;
        Ok(Forward {
            image_shape,
            image,
            selection_shape,
            selection,
        })
    }
}

impl Backend for OrtBackend {
    fn name(&self) -> &str {
        "ort"
    }
    fn config(&self) -> &Config {
        &self.cfg
    }
    fn run(
        &self,
        inputs: &TileInputs,
        planes: usize,
    ) -> deepstereo_core::Result<(Vec<f32>, Vec<f32>)> {
        let shapes: Vec<Vec<usize>> = inputs
            .sizes
            .iter()
            .map(|&(h, w)| self.cfg.input_shape(1, planes, inputs.views, h, w))
            .collect();
        let levels: Vec<(&[usize], &[f32])> = shapes
            .iter()
            .zip(&inputs.levels)
            .map(|(s, d)| (s.as_slice(), d.as_slice()))
            .collect();
        let out = self.forward(&levels)?;
        Ok((out.image, out.selection))
    }
    fn source_features(&self, image: &RgbImage) -> deepstereo_core::Result<FeatureMap> {
        self.image_features(image)
            .map_err(|e| deepstereo_core::Error::Invalid(e.to_string()))
    }
}

/// An onnxruntime session of `onnx` (no spinning: the threads of onnxruntime's pool would
/// otherwise busy-wait after each call, taking the cores from the renderer's own threads,
/// warping and candle) and where the library was loaded from.
fn session_of(onnx: &[u8]) -> Result<(Session, PathBuf)> {
    let (env, lib) = environment()?;
    let session = Session::builder(env)
        .map_err(Error::ort)?
        .with_intra_op_spinning(false)
        .map_err(Error::ort)?
        .with_inter_op_spinning(false)
        .map_err(Error::ort)?
        .commit_from_memory(onnx)
        .map_err(Error::ort)?;
    Ok((session, lib.clone()))
}
