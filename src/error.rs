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

    /// The LED controller's link failed; the kind says how, so a caller can act on it.
    #[error("{device}: {source}")]
    Link {
        /// The controller, for example `LED controller on /dev/ttyACM0`.
        device: String,
        /// How the request failed.
        #[source]
        source: LinkError,
    },

    /// A failure and what the recovery from it left behind (for example `all LEDs are off`).
    #[error("{source}; {aftermath}")]
    Aftermath {
        /// What the recovery left behind, in words.
        aftermath: String,
        /// The failure.
        #[source]
        source: Box<Error>,
    },

    /// The operator stopped the work (Ctrl-C); the message says what state was left behind.
    #[error("interrupted: {0}")]
    Interrupted(String),
}

/// How one request to the LED controller failed.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// No complete answer within the command timeout.
    #[error(
        "no answer to {what} within {timeout_ms} ms: is this the psscan LED controller \
         (firmware/), at {baud} baud?"
    )]
    Timeout {
        /// The request, quoted.
        what: String,
        /// How long the host waited.
        timeout_ms: u128,
        /// The link's baud rate.
        baud: u32,
    },
    /// The port went away (end of file, hang-up, I/O error).
    #[error(
        "the port vanished during {what} ({source}): USB cable unplugged, board without power, \
         or emulator stopped"
    )]
    Vanished {
        /// The request, quoted.
        what: String,
        /// What the port reported.
        #[source]
        source: std::io::Error,
    },
    /// A line that is not an answer to what was sent.
    #[error("bad answer to {what}: {message}")]
    Malformed {
        /// The request, quoted.
        what: String,
        /// What was wrong with the answer.
        message: String,
    },
    /// The port could not be opened.
    #[error("cannot open the port: {source}{}", problem.hint())]
    Unopened {
        /// Why, as far as the system says.
        problem: PortProblem,
        /// What the serial library reported.
        #[source]
        source: std::io::Error,
    },
    /// The firmware answered `ERR <code> <reason>`.
    #[error("the controller refused {what}: ERR {code} {reason}")]
    Refused {
        /// The request, quoted.
        what: String,
        /// The firmware's error code.
        code: u32,
        /// The firmware's reason.
        reason: String,
    },
}

/// Why a serial port could not be opened.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PortProblem {
    /// Another program holds the port's lock.
    InUse,
    /// The device is gone (board unplugged).
    NoDevice,
    /// No such port.
    NotFound,
    /// The user may not open it.
    PermissionDenied,
    /// Anything else.
    Other,
}

impl PortProblem {
    /// What the user can do about it (the CLI adds where to find the ports).
    pub fn hint(self) -> &'static str {
        match self {
            PortProblem::InUse => {
                " (the port is in use by another program, perhaps another psscan)"
            }
            PortProblem::NoDevice => " (no such device: is the board plugged in?)",
            PortProblem::NotFound => " (no such port)",
            PortProblem::PermissionDenied => {
                " (permission denied: add your user to the `dialout` group and log in again)"
            }
            PortProblem::Other => "",
        }
    }
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

    /// `self`, with what the recovery from it left behind.
    pub fn with_aftermath(self, aftermath: impl Into<String>) -> Self {
        Error::Aftermath {
            aftermath: aftermath.into(),
            source: Box::new(self),
        }
    }

    pub fn capture_set(dir: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::CaptureSet {
            dir: dir.as_ref().to_path_buf(),
            message: message.into(),
        }
    }
}
