//! psscan's error type. Every variant says what went wrong and, where a file is involved,
//! which file, so the CLI can print it as is and the operator knows what to fix.

use std::path::{Path, PathBuf};

/// psscan's result: `Ok`, or an [`Error`] that says what went wrong.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything that can go wrong in psscan; the text names the file, device or setting.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file or folder that cannot be read, written or created.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// What the system reported.
        #[source]
        source: std::io::Error,
    },

    /// A configuration or manifest file that does not parse or does not make sense; `field`
    /// names the offending key (for example `leds[3].position_m`).
    #[error("{path}: {field}: {message}")]
    Config {
        /// The file.
        path: PathBuf,
        /// The offending key.
        field: String,
        /// What is wrong with it.
        message: String,
    },

    /// An image file that cannot be read, decoded or written.
    #[error("{path}: {message}")]
    Image {
        /// The image file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },

    /// A capture set that is incomplete or inconsistent.
    #[error("capture set {dir}: {message}")]
    CaptureSet {
        /// The capture set's folder.
        dir: PathBuf,
        /// What is missing or inconsistent.
        message: String,
    },

    /// An output that already exists and would be overwritten; the caller may choose to
    /// replace it (the CLI names `--force`).
    #[error("{path} already exists")]
    Exists {
        /// The existing output (a file or a folder).
        path: PathBuf,
    },

    /// A capture folder already holding a set that this session may not simply write into;
    /// `state` says what it holds, so the caller can offer to complete or replace it.
    #[error("capture set {dir}: {state}")]
    SetOccupied {
        /// The capture set's folder.
        dir: PathBuf,
        /// What the folder holds.
        state: Occupied,
    },

    /// A capture that stopped part-way: the frames shot so far are kept in `dir`, so
    /// running the same capture again with resume on completes the set.
    #[error("{source}")]
    Resumable {
        /// The capture set's folder.
        dir: PathBuf,
        /// Why the capture stopped (its text says what the LEDs and the set were left as).
        #[source]
        source: Box<Error>,
    },

    /// No LED controller port could be chosen automatically; the kind says why, so a caller
    /// can ask for the port by its own means (the CLI names `--port PATH`).
    #[error("{0}")]
    NoPort(PortSearch),

    /// A capture set's calibration bundle that cannot be used as the set cites it; the kind
    /// says why, so a caller can offer another bundle, none, or to accept the mismatch.
    #[error("capture set {dir}: {problem}")]
    Bundle {
        /// The capture set's folder.
        dir: PathBuf,
        /// What is wrong with the bundle (boxed: it is large, and errors travel in every
        /// `Result`).
        problem: Box<BundleProblem>,
    },

    /// Settings that cannot be used together; the conflict says which, so a caller can name
    /// its own spelling of them (the CLI names the flags).
    #[error("{0}")]
    Incompatible(Conflict),

    /// Inputs that do not fit together (sizes, light counts, options).
    #[error("{0}")]
    Invalid(String),

    /// A value psscan could not work out from the data, which the caller can give instead;
    /// the kind says which, so a caller can name its own way of giving it (the CLI names the
    /// flag).
    #[error("{0}")]
    NeedsValue(Needed),

    /// A feature that is not built into this binary or not implemented yet.
    #[error("{0}")]
    Unsupported(String),

    /// A device (LED controller, camera, firmware emulator) that failed, answered wrongly or
    /// went away; `device` names it (for example `LED controller on /dev/ttyACM0`).
    #[error("{device}: {message}")]
    Device {
        /// The device, for example `LED controller on /dev/ttyACM0`.
        device: String,
        /// What went wrong.
        message: String,
    },

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

/// What a capture folder holds that a new session may not simply write into.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Occupied {
    /// A complete set: nothing is left to shoot.
    Complete,
    /// An unfinished set, `kept` of `total` frames shot (the dark frame counts as one).
    Unfinished {
        /// Frames in the set's manifest.
        kept: usize,
        /// Frames a complete set has: one per LED and the dark frame.
        total: usize,
    },
    /// An unfinished set started with another rig than this session's.
    OtherRig {
        /// The rig stored in the set.
        set_rig: String,
        /// This session's rig (same name or not, its values differ).
        session_rig: String,
    },
    /// An unfinished set whose frames differ from what this camera gives.
    OtherFrames {
        /// The set's frames: encoding and size, e.g. `dng 640x480`.
        set_frames: String,
        /// This camera's frames, in the same form.
        camera_frames: String,
    },
}

impl std::fmt::Display for Occupied {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Occupied::Complete => write!(
                f,
                "already holds a complete capture set, so resuming it has nothing left to shoot"
            ),
            Occupied::Unfinished { kept, total } => {
                write!(f, "holds an unfinished capture ({kept} of {total} frames)")
            }
            Occupied::OtherRig {
                set_rig,
                session_rig,
            } => write!(
                f,
                "was started with rig \"{set_rig}\" (stored in the set), this session uses rig \
                 \"{session_rig}\" with other values"
            ),
            Occupied::OtherFrames {
                set_frames,
                camera_frames,
            } => write!(
                f,
                "was started with other frames ({set_frames}), this camera gives {camera_frames}"
            ),
        }
    }
}

/// Why no LED controller port was chosen automatically.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PortSearch {
    /// The machine cannot list its serial ports (no sysfs, as in some containers).
    #[error("cannot list serial ports: /sys/class/tty is missing (no sysfs)")]
    NoSysfs,
    /// Several boards of the same rank could be the controller.
    #[error("several boards could be the LED controller ({candidates})")]
    Several {
        /// The candidates' ports and board names, comma-separated.
        candidates: String,
    },
    /// No Arduino-like board among the ports.
    #[error("no Arduino found ({seen})")]
    NoArduino {
        /// The ports seen, in words (`no serial ports at all`, `ports seen: ...`).
        seen: String,
    },
}

/// Why a capture set's calibration bundle cannot be used as cited.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BundleProblem {
    /// The bundle the set cites is not where the set says.
    #[error("cites calibration bundle {id} at {}, which is not there", path.display())]
    Missing {
        /// The cited bundle's id.
        id: String,
        /// Where the set says it is.
        path: PathBuf,
    },
    /// The bundle given is not the one the set was captured with.
    #[error(
        "was captured with calibration bundle {cited_id} (sha256 {cited_sha256}), but the \
         bundle at {} is {id} (sha256 {sha256})",
        path.display()
    )]
    Mismatch {
        /// The id the set cites.
        cited_id: String,
        /// The hash the set cites.
        cited_sha256: String,
        /// The bundle given.
        path: PathBuf,
        /// Its id.
        id: String,
        /// Its hash.
        sha256: String,
    },
}

/// Two settings that cannot be used together.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Conflict {
    /// The robust estimator with a streaming kernel (f32 precision or a tile tolerance).
    #[error(
        "the robust estimator fits every pixel with the exact kernel, not the streaming one \
         (f32 precision or a tile tolerance)"
    )]
    RobustStreaming,
    /// The SVD method with a streaming kernel (f32 precision or a tile tolerance).
    #[error("the SVD method is per pixel in f64 only, not in the streaming kernel")]
    SvdStreaming,
    /// A camera calibration without the table pose solved with it.
    #[error(
        "a camera calibration needs the table pose too: the camera's pose over the table \
         comes from the table step"
    )]
    CameraWithoutTable,
    /// A table pose without the camera calibration it was solved with.
    #[error(
        "a table pose needs the camera calibration too: the table's pose was solved with the \
         camera step's intrinsics"
    )]
    TableWithoutCamera,
    /// A crop, binning or background mask asked of a DiLiGenT set (they apply to psscan
    /// capture sets, whose frames are RAW).
    #[error("{}: crops, binning and background masks apply to psscan capture sets, not DiLiGenT sets", dir.display())]
    RegionOnDiligent {
        /// The DiLiGenT folder.
        dir: PathBuf,
    },
}

/// A value the data did not give (see [`Error::NeedsValue`]); its text says why.
#[derive(Debug, thiserror::Error)]
pub enum Needed {
    /// The gray chart's rectangle in its photographs: the chart search found none.
    #[error("{reason}")]
    ChartRect {
        /// Why the search found no rectangle.
        reason: String,
    },
    /// The sensor pixels per image pixel of photographs that are neither the whole sensor
    /// nor a whole-number binning of it.
    #[error("{reason}")]
    SensorStep {
        /// The photographs' size against the sensor's.
        reason: String,
    },
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
    /// An I/O failure on `path`.
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    /// An image file at `path` that cannot be read, decoded or written.
    pub fn image(path: impl AsRef<Path>, message: impl std::fmt::Display) -> Self {
        Error::Image {
            path: path.as_ref().to_path_buf(),
            message: message.to_string(),
        }
    }

    /// A configuration file at `path` whose key `field` is wrong.
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

    /// A device (named as in [`Error::Device`]) that failed.
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

    /// A capture set in `dir` that is incomplete or inconsistent.
    pub fn capture_set(dir: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::CaptureSet {
            dir: dir.as_ref().to_path_buf(),
            message: message.into(),
        }
    }

    /// Whether the operator stopped the work: this error or one it wraps is
    /// [`Error::Interrupted`].
    pub fn is_interrupted(&self) -> bool {
        match self {
            Error::Interrupted(_) => true,
            Error::Resumable { source, .. } => source.is_interrupted(),
            _ => false,
        }
    }
}
