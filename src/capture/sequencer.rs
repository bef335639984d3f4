//! The capture session: an all-off dark frame, then one frame per LED. Before each shot the
//! controller is asked to confirm the LEDs (`STATE`) and the light settles; after it, the
//! controller is asked again, so a frame whose LED went off during the shot (silence timeout,
//! reset) is never kept. Each frame is moved into the set atomically, hashed and recorded,
//! and the manifest is rewritten after every frame: whatever stops the session, the frames
//! already taken stay valid and `resume` shoots only what is missing or damaged.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde::Serialize;

use super::camera::{Camera, Shot};
use super::exposure::{prepare_controller, settle_fire_confirm, switch_and_confirm};
use super::interrupt::Interrupt;
use super::lights::{FirmwareInfo, Keepalive, LightState, SharedLights};
use super::manifest::{CameraSettings, FrameKind, SyntheticInfo, MANIFEST_FILE};
use super::set::{light_file_name, CaptureSet, CaptureSetWriter, DroppedFrame};
use crate::error::{Error, Occupied, Result};
use crate::progress::Progress;
use crate::rig::Rig;

/// How to run a session.
#[derive(Clone, Debug)]
pub struct CaptureOptions {
    /// Wait between switching an LED and firing (LED warm-up, vibration).
    pub settle: Duration,
    /// Complete an interrupted set in the folder.
    pub resume: bool,
    /// Start over even if the folder holds a set.
    pub force: bool,
    /// Host-silence timeout to set on the controller; `None` keeps the firmware's.
    pub light_timeout_ms: Option<u32>,
    /// Ground truth of a synthetic scene, recorded in a new set's manifest.
    pub synthetic: Option<SyntheticInfo>,
    /// The calibration bundle the rig came from, recorded in a new set's manifest.
    pub calibration: Option<crate::rig::CalibrationRef>,
}

impl Default for CaptureOptions {
    fn default() -> Self {
        CaptureOptions {
            settle: Duration::from_millis(250),
            resume: false,
            force: false,
            light_timeout_ms: None,
            synthetic: None,
            calibration: None,
        }
    }
}

/// What happened to one frame in this session.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameStatus {
    /// Shot in this session.
    Shot,
    /// Already in the set and intact; not shot again.
    Kept,
}

/// One frame of the set as this session left it: shot now or kept from an earlier session, with
/// what the controller and camera said about it.
#[derive(Clone, Debug, Serialize)]
pub struct FrameRecord {
    /// The frame's file name inside the set (`dark.<ext>` or `Lkk.<ext>`).
    pub file: String,
    /// Dark frame or light frame.
    pub kind: FrameKind,
    /// The LED lit for a light frame; `None` for the dark frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub light: Option<usize>,
    /// Lower-case hex SHA-256 of the stored file, as the manifest records it.
    pub sha256: String,
    /// Whether the frame was shot in this session or kept from an earlier one.
    pub status: FrameStatus,
    /// The controller's `STATE` right before the shot.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state_before: Option<LightState>,
    /// The LEDs the camera saw lit when it fired (simulated camera: from the pin log or the
    /// mock).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lit_at_fire: Option<Vec<usize>>,
    /// When the shutter opened, Unix microseconds; `None` for a kept frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fired_unix_us: Option<u64>,
}

/// The session's summary (`psscan capture --json`).
#[derive(Clone, Debug, Serialize)]
pub struct CaptureReport {
    /// The capture set's folder.
    pub dir: PathBuf,
    /// The LED controller's name for messages (e.g. the serial device it is on).
    pub controller: String,
    /// What the controller's firmware reported about itself when the session began.
    pub firmware: FirmwareInfo,
    /// The camera's name.
    pub camera: String,
    /// The camera settings read from the camera at the start of the session.
    pub camera_settings: CameraSettings,
    /// Every frame of the set in shooting order (the dark frame first, then LED 0, 1, ...), shot or
    /// kept.
    pub frames: Vec<FrameRecord>,
    /// Frames shot in this session.
    pub shot: usize,
    /// Frames kept from an earlier session without shooting them again.
    pub kept: usize,
    /// Frames an earlier session left damaged or missing, shot again.
    pub dropped: Vec<DroppedFrame>,
    /// Keepalive pings sent to the controller while the session ran.
    pub keepalive_pings: u64,
    /// Wall-clock durations by stage name, seconds (today only `total`, the whole session).
    pub timings_s: BTreeMap<String, f64>,
}

/// One planned frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Planned {
    Dark,
    Light(usize),
}

impl Planned {
    fn kind(&self) -> FrameKind {
        match self {
            Planned::Dark => FrameKind::Dark,
            Planned::Light(_) => FrameKind::Light,
        }
    }

    fn light(&self) -> Option<usize> {
        match self {
            Planned::Dark => None,
            Planned::Light(k) => Some(*k),
        }
    }

    fn label(&self) -> String {
        match self {
            Planned::Dark => "the dark frame (all LEDs off)".into(),
            Planned::Light(k) => format!("frame L{k:02} (LED {k})"),
        }
    }

    fn file(&self, extension: &str) -> String {
        match self {
            Planned::Dark => format!("dark.{extension}"),
            Planned::Light(k) => light_file_name(*k, extension),
        }
    }
}

/// Runs a capture session into `dir` with `rig` (for a resumed set, the rig stored in the
/// set is used and must match). On any failure the LEDs are switched off and the error says
/// which frame failed, what is kept, and that `--resume` completes the set.
pub fn run_capture(
    dir: &Path,
    rig: &Rig,
    lights: &SharedLights,
    camera: &mut dyn Camera,
    options: &CaptureOptions,
    interrupt: &Interrupt,
    progress: &dyn Progress,
) -> Result<CaptureReport> {
    let total = Instant::now();
    // Read before the set is opened: a new set records them, a resumed one must match them.
    let camera_settings = camera.settings()?;
    let (mut writer, dropped) = open_set(dir, rig, camera, &camera_settings, options)?;
    let controller = lights.lock().name();
    let setup = prepare_controller(lights, rig.leds.len(), options.light_timeout_ms);
    let (firmware, timeout_ms) = match setup {
        Ok(v) => v,
        Err(e) => return Err(stopped(&writer, "setting up the LED controller", e, lights)),
    };
    let keepalive = Keepalive::start(
        lights.clone(),
        Duration::from_millis(timeout_ms as u64 / 3),
        interrupt.clone(),
    );

    let plan: Vec<Planned> = std::iter::once(Planned::Dark)
        .chain((0..rig.leds.len()).map(Planned::Light))
        .collect();
    let mut frames = Vec::new();
    let todo: Vec<Planned> = plan
        .iter()
        .copied()
        .filter(|p| existing(&writer, *p).is_none())
        .collect();
    progress.begin("capture", todo.len() as u64);
    for planned in &plan {
        if let Some(entry) = existing(&writer, *planned) {
            frames.push(FrameRecord {
                file: entry.file.clone(),
                kind: entry.kind,
                light: entry.light,
                sha256: entry.sha256.clone(),
                status: FrameStatus::Kept,
                state_before: None,
                lit_at_fire: None,
                fired_unix_us: None,
            });
            continue;
        }
        let result = shoot(
            *planned,
            &mut writer,
            lights,
            camera,
            &keepalive,
            options,
            interrupt,
        );
        match result {
            Ok(record) => frames.push(record),
            Err(e) => {
                progress.end();
                let what = planned.label();
                drop(keepalive);
                return Err(stopped(&writer, &what, e, lights));
            }
        }
        progress.advance(1);
    }
    progress.end();
    let pings = keepalive.pings();
    drop(keepalive);
    if let Err(e) = lights.lock().off() {
        return Err(stopped(
            &writer,
            "switching the LEDs off at the end",
            e,
            lights,
        ));
    }
    let shot = frames
        .iter()
        .filter(|f| f.status == FrameStatus::Shot)
        .count();
    let mut timings = BTreeMap::new();
    timings.insert("total".into(), total.elapsed().as_secs_f64());
    Ok(CaptureReport {
        dir: dir.to_path_buf(),
        controller,
        firmware,
        camera: camera.name(),
        camera_settings,
        kept: frames.len() - shot,
        shot,
        frames,
        dropped,
        keepalive_pings: pings,
        timings_s: timings,
    })
}

/// The writer for this session: a new set, or the interrupted one to complete.
fn open_set(
    dir: &Path,
    rig: &Rig,
    camera: &dyn Camera,
    settings: &CameraSettings,
    options: &CaptureOptions,
) -> Result<(CaptureSetWriter, Vec<DroppedFrame>)> {
    let image = camera.image_info(rig);
    let exists = dir.join(MANIFEST_FILE).is_file();
    if exists && options.resume && !options.force {
        let set = CaptureSet::open(dir, None)?;
        if set.rig != *rig {
            return Err(Error::SetOccupied {
                dir: dir.to_path_buf(),
                state: Occupied::OtherRig {
                    set_rig: set.rig.name.clone(),
                    session_rig: rig.name.clone(),
                },
            });
        }
        let had = &set.manifest.image;
        if had.encoding != image.encoding
            || had.width != image.width
            || had.height != image.height
            || had.window != image.window
            || had.exposure != image.exposure
        {
            return Err(Error::SetOccupied {
                dir: dir.to_path_buf(),
                state: Occupied::OtherFrames {
                    set_frames: format!("{} {}x{}", had.encoding, had.width, had.height),
                    camera_frames: format!("{} {}x{}", image.encoding, image.width, image.height),
                },
            });
        }
        if !set.manifest.camera.same_exposure(settings) {
            return Err(Error::SetOccupied {
                dir: dir.to_path_buf(),
                state: Occupied::OtherFrames {
                    set_frames: set.manifest.camera.exposure_text(),
                    camera_frames: settings.exposure_text(),
                },
            });
        }
        remove_scratch_files(dir);
        return CaptureSetWriter::resume(dir);
    }
    if exists && !options.force {
        let set = CaptureSet::open(dir, None)?;
        let complete = set.manifest.dark_frame().is_some()
            && (0..set.rig.leds.len()).all(|k| set.manifest.light_frame(k).is_some());
        let state = if complete {
            Occupied::Complete
        } else {
            Occupied::Unfinished {
                kept: set.manifest.frames.len(),
                total: set.rig.leds.len() + 1,
            }
        };
        return Err(Error::SetOccupied {
            dir: dir.to_path_buf(),
            state,
        });
    }
    // A new set: the folder must be new, empty or psscan's own (an old set, with --force);
    // the old set is removed as a whole, never mixed with the new one.
    crate::fsutil::claim_dir(dir, options.force, &[], &[])?;
    let mut writer = CaptureSetWriter::create(dir, rig, image, settings.clone(), true)?;
    if let Some(info) = &options.synthetic {
        writer.set_synthetic(info.clone())?;
    }
    if let Some(calibration) = &options.calibration {
        writer.set_calibration(calibration.clone())?;
    }
    Ok((writer, Vec::new()))
}

fn existing(writer: &CaptureSetWriter, planned: Planned) -> Option<&super::FrameEntry> {
    match planned {
        Planned::Dark => writer.manifest().dark_frame(),
        Planned::Light(k) => writer.manifest().light_frame(k),
    }
}

/// The camera's scratch file for a frame (inside the set, so the move is a rename).
fn scratch_path(dir: &Path, planned: Planned) -> PathBuf {
    dir.join(format!(
        ".{}.shot",
        planned.file("x").trim_end_matches(".x")
    ))
}

/// Leftovers of a session that stopped mid-shot.
fn remove_scratch_files(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') && name.ends_with(".shot") {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// Switch, confirm, settle, fire, confirm again, store.
fn shoot(
    planned: Planned,
    writer: &mut CaptureSetWriter,
    lights: &SharedLights,
    camera: &mut dyn Camera,
    keepalive: &Keepalive,
    options: &CaptureOptions,
    interrupt: &Interrupt,
) -> Result<FrameRecord> {
    interrupt.check()?;
    let expected = planned.light();
    let state_before = switch_and_confirm(lights, expected)?;
    let scratch = scratch_path(writer.dir(), planned);
    let stored = (|| -> Result<(Shot, String)> {
        let shot = settle_fire_confirm(
            lights,
            keepalive,
            camera,
            expected,
            &scratch,
            options.settle,
            interrupt,
        )?;
        let bytes = std::fs::read(&scratch).map_err(|e| Error::io(&scratch, e))?;
        let file = planned.file(&shot.extension);
        check_frame(writer, &file, &bytes).map_err(|m| Error::device(camera.name(), m))?;
        writer.add_frame(planned.kind(), expected, &file, &bytes)?;
        Ok((shot, file))
    })();
    let _ = std::fs::remove_file(&scratch);
    let (shot, file) = stored?;
    let entry = existing(writer, planned).expect("just added");
    Ok(FrameRecord {
        file,
        kind: planned.kind(),
        light: expected,
        sha256: entry.sha256.clone(),
        status: FrameStatus::Shot,
        state_before: Some(state_before),
        lit_at_fire: shot.lit,
        fired_unix_us: Some(shot.fired_unix_us),
    })
}

/// The frame must be what the manifest records, as large as the set's earlier RAW frames and
/// no copy of one of them (`frame_check`); the set's first RAW frame is read back for its size.
fn check_frame(
    writer: &CaptureSetWriter,
    file: &str,
    bytes: &[u8],
) -> std::result::Result<(), String> {
    let manifest = writer.manifest();
    let others: Vec<super::FrameEntry> = manifest
        .frames
        .iter()
        .filter(|f| f.file != file)
        .cloned()
        .collect();
    let raw_size = if manifest.image.encoding == super::camera::RAW_ENCODING {
        others.first().and_then(|f| {
            let bytes = std::fs::read(writer.dir().join(&f.file)).ok()?;
            crate::raw::probe_raw(&bytes).ok().flatten()
        })
    } else {
        None
    };
    let sha = crate::fsutil::sha256_hex(bytes);
    super::frame_check::check(file, bytes, &sha, &manifest.image, &others, raw_size).map(|_| ())
}

/// The error for a session that stopped: LEDs off (or why not), what is kept, how to go on.
fn stopped(writer: &CaptureSetWriter, what: &str, cause: Error, lights: &SharedLights) -> Error {
    let leds = lights.off_and_report();
    let manifest = writer.manifest();
    let kept: Vec<&str> = manifest.frames.iter().map(|f| f.file.as_str()).collect();
    let kept = if kept.is_empty() {
        "no frames kept".to_string()
    } else {
        format!("{} frames kept ({})", kept.len(), kept.join(", "))
    };
    let dir = writer.dir().display();
    let stopped = if let Error::Interrupted(_) = cause {
        Error::Interrupted(format!(
            "capture into {dir} stopped at {what}; {leds}; {kept}"
        ))
    } else {
        Error::capture_set(
            writer.dir(),
            format!("capture stopped at {what}: {cause}; {leds}; {kept}"),
        )
    };
    Error::Resumable {
        dir: writer.dir().to_path_buf(),
        source: Box::new(stopped),
    }
}

#[cfg(test)]
mod tests;
