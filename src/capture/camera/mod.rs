//! Cameras the sequencer can fire: a tethered DSLR through libgphoto2 (feature `gphoto2`)
//! and any external command that takes a photograph into a file. The simulated cameras
//! implement the same [`Camera`] trait in the `sim` module, which the CLI wires in.

pub mod command;
#[cfg(feature = "gphoto2")]
pub mod gphoto;

use std::path::Path;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde::Serialize;

use super::interrupt::Interrupt;
use super::manifest::{CameraSettings, ImageInfo};
use crate::plane::SensorWindow;
use crate::raw::Levels;
use crate::rig::Rig;

pub use command::CommandCamera;

use crate::error::Result;

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
