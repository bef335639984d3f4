//! psscan's error type. Every variant says what went wrong and, where a file is involved,
//! which file, so the CLI can print it as is and the operator knows what to fix.

use std::path::{Path, PathBuf};

pub type Result<T, E = Error> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A configuration or manifest file that does not parse or does not make sense; `field`
    /// names the offending key (for example `leds[3].position_m`).
    #[error("{path}: {field}: {message}")]
    Config {
        path: PathBuf,
        field: String,
        message: String,
    },

    /// An image file that cannot be read, decoded or written.
    #[error("{path}: {message}")]
    Image { path: PathBuf, message: String },

    /// A capture set that is incomplete or inconsistent.
    #[error("capture set {dir}: {message}")]
    CaptureSet { dir: PathBuf, message: String },

    /// An output that already exists and would be overwritten.
    #[error("{path} already exists; pass --force to overwrite it")]
    Exists { path: PathBuf },

    /// Inputs that do not fit together (sizes, light counts, options).
    #[error("{0}")]
    Invalid(String),

    /// A feature that is not built into this binary or not implemented yet.
    #[error("{0}")]
    Unsupported(String),

    /// A device (LED controller, camera, firmware emulator) that failed, answered wrongly or
    /// went away; `device` names it (for example `LED controller on /dev/ttyACM0`).
    #[error("{device}: {message}")]
    Device { device: String, message: String },

    /// The operator stopped the work (Ctrl-C); the message says what state was left behind.
    #[error("interrupted: {0}")]
    Interrupted(String),
}

impl Error {
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    pub fn image(path: impl AsRef<Path>, message: impl std::fmt::Display) -> Self {
        Error::Image {
            path: path.as_ref().to_path_buf(),
            message: message.to_string(),
        }
    }

    pub fn config(
        path: impl AsRef<Path>,
        field: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        Error::Config {
            path: path.as_ref().to_path_buf(),
            field: field.into(),
            message: message.into(),
        }
    }

    pub fn device(device: impl Into<String>, message: impl Into<String>) -> Self {
        Error::Device {
            device: device.into(),
            message: message.into(),
        }
    }

    pub fn capture_set(dir: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::CaptureSet {
            dir: dir.as_ref().to_path_buf(),
            message: message.into(),
        }
    }
}
