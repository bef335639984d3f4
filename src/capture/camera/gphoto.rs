//! A tethered camera through libgphoto2 (feature `gphoto2`): capture, download the file the
//! camera wrote to the path the sequencer gives, and read ISO, shutter and aperture back from
//! the camera's configuration for the manifest. Set the camera to RAW only (not RAW+JPEG) and
//! to manual exposure, so every frame has the same settings.

use std::path::Path;
use std::time::Duration;

use super::settings_text::{parse_aperture, parse_iso, parse_shutter};
use super::unix_now_us;
use super::{extension_of, raw_image_info, Camera, Shot};
use crate::capture::interrupt::Interrupt;
use crate::capture::manifest::{CameraSettings, ImageInfo};
use crate::error::{Error, Result};
use crate::rig::Rig;

/// A tethered camera driven through libgphoto2 (feature `gphoto2`): it reports its ISO,
/// shutter and aperture, and each shot's RAW file is downloaded into the capture set.
pub struct Gphoto2Camera {
    camera: gphoto2::Camera,
    model: String,
    timeout: Duration,
}

const DEVICE: &str = "camera (libgphoto2)";

impl Gphoto2Camera {
    /// Opens the first camera libgphoto2 finds. `timeout`: the longest one shot (exposure
    /// and download) may take.
    pub fn open(timeout: Duration) -> Result<Gphoto2Camera> {
        let context = gphoto2::Context::new().map_err(|e| gp_error("cannot start", e))?;
        let camera = context
            .autodetect_camera()
            .wait()
            .map_err(|e| gp_error("cannot open a camera", e))?;
        let model = camera.abilities().model().to_string();
        Ok(Gphoto2Camera {
            camera,
            model,
            timeout,
        })
    }

    /// A configuration value by the first of `keys` the camera has, as text.
    fn read_setting(&self, keys: &[&str]) -> Option<String> {
        keys.iter().find_map(|key| {
            let widget = self
                .camera
                .config_key::<gphoto2::widget::Widget>(key)
                .wait()
                .ok()?;
            Some(match widget {
                gphoto2::widget::Widget::Radio(w) => w.choice(),
                gphoto2::widget::Widget::Text(w) => w.value(),
                gphoto2::widget::Widget::Range(w) => w.value().to_string(),
                _ => return None,
            })
        })
    }
}

/// libgphoto2's error, with what it means for the operator.
pub fn gp_error(doing: &str, e: gphoto2::Error) -> Error {
    use gphoto2::error::ErrorKind;
    let hint = match e.kind() {
        ErrorKind::ModelNotFound | ErrorKind::UnknownPort | ErrorKind::IoUsbFind => {
            "no camera found: connect it by USB, switch it on, set it to PC/PTP mode"
        }
        ErrorKind::IoUsbClaim | ErrorKind::IoLock => {
            "the camera is in use by another program (a desktop photo importer or gvfs-gphoto2 \
             mount: unmount it, or stop gvfs-gphoto2-volume-monitor)"
        }
        ErrorKind::CameraBusy => "the camera is busy (still writing the last photograph?)",
        ErrorKind::Timeout => "the camera did not answer in time",
        _ => "",
    };
    let message = if hint.is_empty() {
        format!("{doing}: {e}")
    } else {
        format!("{doing}: {hint} (libgphoto2: {e})")
    };
    Error::device(DEVICE, message)
}

impl Camera for Gphoto2Camera {
    fn name(&self) -> String {
        format!("{DEVICE}: {}", self.model)
    }

    fn settings(&mut self) -> Result<CameraSettings> {
        Ok(CameraSettings {
            model: self.model.clone(),
            iso: self
                .read_setting(&["iso", "isospeed"])
                .and_then(|t| parse_iso(&t)),
            shutter_s: self
                .read_setting(&["shutterspeed", "shutterspeed2", "exposuretime"])
                .and_then(|t| parse_shutter(&t)),
            aperture: self
                .read_setting(&["aperture", "f-number", "fnumber"])
                .and_then(|t| parse_aperture(&t)),
        })
    }

    fn image_info(&self, rig: &Rig) -> ImageInfo {
        raw_image_info(rig)
    }

    fn max_shot_time(&self) -> Duration {
        self.timeout
    }

    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot> {
        if interrupt.is_set() {
            return Err(Error::Interrupted(format!(
                "{}: before firing",
                self.name()
            )));
        }
        let fired_unix_us = unix_now_us();
        let file = self
            .camera
            .capture_image()
            .wait()
            .map_err(|e| gp_error("capture failed", e))?;
        let (folder, name) = (file.folder().to_string(), file.name().to_string());
        self.camera
            .fs()
            .download_to(&folder, &name, dest)
            .wait()
            .map_err(|e| gp_error(&format!("download of {folder}/{name} failed"), e))?;
        Ok(Shot {
            extension: extension_of(&name).unwrap_or_else(|| "raw".into()),
            lit: None,
            fired_unix_us,
        })
    }
}
