//! Errors of the exporter and the ort backend.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An opset this exporter does not write.
    #[error("opset {got} is not supported: use {min}..={max}")]
    Opset { got: i64, min: i64, max: i64 },
    /// Weights that do not match the configuration (missing, unexpected, wrong shape).
    #[error("weights do not match the '{config}' config: {msg}")]
    Weights { config: String, msg: String },
    /// An invalid configuration.
    #[error("invalid config: {0}")]
    Config(String),
    /// An ONNX file that cannot be decoded or lacks what the backend needs.
    #[error("{what}: {msg}")]
    Onnx { what: String, msg: String },
    /// libonnxruntime could not be found or loaded.
    #[error("{0}")]
    OrtLibrary(String),
    /// An error reported by onnxruntime.
    #[error("onnxruntime: {0}")]
    Ort(String),
    /// Inputs with the wrong number, names or shapes.
    #[error("invalid input: {0}")]
    Input(String),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Core(#[from] deepstereo_core::Error),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub(crate) fn ort(e: impl std::fmt::Display) -> Self {
        Error::Ort(e.to_string())
    }
}

/// Converts to the core error, so the backend can implement
/// [`deepstereo_core::render::Backend`].
impl From<Error> for deepstereo_core::Error {
    fn from(e: Error) -> Self {
        match e {
            Error::Core(e) => e,
            Error::Candle(e) => deepstereo_core::Error::Candle(e),
            other => deepstereo_core::Error::Invalid(other.to_string()),
        }
    }
}
