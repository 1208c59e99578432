//! The library's one error type. Every variant that concerns a file names it.

use std::path::PathBuf;

/// Errors of `deepstereo-core`. Binaries wrap them with `anyhow`; the library never panics on bad input.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file whose contents do not follow its format.
    #[error("{path}{}: {msg}", line.map(|l| format!(":{l}")).unwrap_or_default())]
    Parse {
        path: PathBuf,
        line: Option<usize>,
        msg: String,
    },
    /// An image that cannot be decoded or has an unexpected size or channel count.
    #[error("{path}: {msg}")]
    Image { path: PathBuf, msg: String },
    /// A camera whose pose or intrinsics are unusable (non-finite, not a rotation, ...).
    #[error("{path}: view '{view}': {msg}")]
    Camera {
        path: PathBuf,
        view: String,
        msg: String,
    },
    /// A directory that matches no known scene format.
    #[error("{path}: {msg}")]
    Format { path: PathBuf, msg: String },
    /// A scene file naming a path that resolves outside the scene directory.
    #[error("{file}: {entry}: {path} is outside the scene directory {root}; it is not read (--allow-outside-paths reads it)")]
    Outside {
        file: PathBuf,
        entry: String,
        path: PathBuf,
        root: PathBuf,
    },
    /// An impossible option or argument combination.
    #[error("invalid argument: {0}")]
    Invalid(String),
    /// A model file or configuration that does not match what is expected.
    #[error("{path}: {msg}")]
    Model { path: PathBuf, msg: String },
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
    pub fn parse(path: impl Into<PathBuf>, line: Option<usize>, msg: impl Into<String>) -> Self {
        Error::Parse {
            path: path.into(),
            line,
            msg: msg.into(),
        }
    }
    pub fn image(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        Error::Image {
            path: path.into(),
            msg: msg.into(),
        }
    }
    pub fn format(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            msg: msg.into(),
        }
    }
    pub fn model(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        Error::Model {
            path: path.into(),
            msg: msg.into(),
        }
    }
}
