//! Cameras the sequencer can fire: a tethered DSLR through libgphoto2 (feature `gphoto2`)
//! and any external command that takes a photograph into a file. The simulated cameras
//! implement the same [`Camera`] trait in the `sim` module, which the CLI wires in.

pub mod command;
#[cfg(feature = "gphoto2")]
pub mod gphoto;
pub mod settings_text;

use std::path::Path;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde::Serialize;

use super::interrupt::Interrupt;
use super::manifest::{CameraSettings, ImageInfo};
use crate::plane::SensorWindow;
use crate::raw::Levels;
use crate::rig::Rig;

pub use command::CommandCamera;

use crate::error::{Error, Result};

/// `image.encoding` of sets of camera RAW files (NEF, CR2, DNG, ...), decoded by `raw`.
pub const RAW_ENCODING: &str = "raw";

/// One photograph taken.
#[derive(Clone, Debug, Serialize)]
pub struct Shot {
    /// File extension for the stored frame (lower case, no dot), e.g. `nef` or `png`.
    pub extension: String,
    /// The LEDs the camera saw lit when it fired, where it can know (the simulated camera).
    pub lit: Option<Vec<usize>>,
    /// When the shutter opened, Unix microseconds.
    pub fired_unix_us: u64,
}

/// A camera the sequencer fires once per frame.
pub trait Camera {
    /// Names the camera for messages and the report.
    fn name(&self) -> String;
    /// Settings to record in the manifest, read back from the camera where it can.
    fn settings(&mut self) -> Result<CameraSettings>;
    /// How this camera's frames are described in the manifest.
    fn image_info(&self, rig: &Rig) -> ImageInfo;
    /// The longest one shot (exposure and download) may take. The LED keepalive covers the
    /// shot for this long and no longer, so a hung camera lets the firmware time out.
    fn max_shot_time(&self) -> Duration;
    /// Takes one photograph into `dest` (a scratch file in the set's folder; the sequencer
    /// hashes it and moves it into place). Returns early with an error when `interrupt` is
    /// set, where the backend can.
    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot>;
}

/// The manifest's image description for a camera whose frames are RAW files: the rig's
/// sensor, whole, at its levels. The RAW decoder checks the files against it.
pub fn raw_image_info(rig: &Rig) -> ImageInfo {
    ImageInfo {
        width: rig.camera.width as usize,
        height: rig.camera.height as usize,
        window: SensorWindow::FULL,
        levels: Levels::from_sensor(&rig.sensor),
        exposure: 1.0,
        encoding: RAW_ENCODING.into(),
    }
}

/// A file extension from a camera file name (`DSC_0001.NEF` -> `nef`).
pub fn extension_of(name: &str) -> Option<String> {
    let ext = Path::new(name).extension()?.to_str()?;
    (!ext.is_empty() && ext.chars().all(|c| c.is_ascii_alphanumeric()))
        .then(|| ext.to_ascii_lowercase())
}

/// Now, as Unix microseconds (the clock the pin log's `start_unix_us` uses).
pub fn unix_now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}

/// Which camera a command fires, as a user names it: `gphoto2`, `sim`, or `cmd:TEMPLATE`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CameraSpec {
    /// A tethered camera through libgphoto2 (feature `gphoto2`).
    Gphoto2,
    /// The simulated camera, which the simulation (`sim`) builds, not [`open_camera`].
    Sim,
    /// An external command; `{out}` in the template is the file it must write.
    Command(String),
}

impl CameraSpec {
    /// Parses a camera name: `gphoto2`, `sim`, or `cmd:TEMPLATE`.
    pub fn parse(spec: &str) -> Result<CameraSpec> {
        if let Some(template) = spec.strip_prefix("cmd:") {
            return Ok(CameraSpec::Command(template.to_string()));
        }
        match spec {
            "gphoto2" => Ok(CameraSpec::Gphoto2),
            "sim" => Ok(CameraSpec::Sim),
            other => Err(Error::Invalid(format!(
                "camera {other:?}: expected gphoto2, sim, or cmd:TEMPLATE"
            ))),
        }
    }
}

/// Opens a real camera. A command camera stores its frames with extension `frame_ext` when
/// given; every shot may take up to `shot_timeout`. [`CameraSpec::Sim`] is refused: the
/// simulated camera is built by the simulation, which the caller wires in.
pub fn open_camera(
    spec: &CameraSpec,
    frame_ext: Option<&str>,
    shot_timeout: Duration,
) -> Result<Box<dyn Camera>> {
    match spec {
        CameraSpec::Command(template) => Ok(Box::new(CommandCamera::new(
            template,
            frame_ext,
            shot_timeout,
        )?)),
        CameraSpec::Gphoto2 => open_gphoto2(shot_timeout),
        CameraSpec::Sim => Err(Error::Invalid(
            "the simulated camera is built by the simulation, not opened".into(),
        )),
    }
}

#[cfg(feature = "gphoto2")]
fn open_gphoto2(shot_timeout: Duration) -> Result<Box<dyn Camera>> {
    Ok(Box::new(gphoto::Gphoto2Camera::open(shot_timeout)?))
}

#[cfg(not(feature = "gphoto2"))]
fn open_gphoto2(_: Duration) -> Result<Box<dyn Camera>> {
    Err(Error::Unsupported(
        "this psscan was built without libgphoto2; rebuild with `cargo build --release \
         --features gphoto2` (needs libgphoto2-dev)"
            .into(),
    ))
}
