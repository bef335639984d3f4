//! The scanner without hardware: the LED firmware running in its emulator behind a
//! pseudo-terminal (opened with psscan's real serial code), the simulated camera reading the
//! emulator's pin log when it fires, a capture session through both, and the demo that then
//! solves the set as `psscan demo` does. A newcomer sees the whole loop; the tests use the
//! same pieces to put the firmware and the serial link in every capture test.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use super::camera::{ControllerState, LitSource, SimCamera};
use super::emulator::{Emulator, EmulatorFiles, PinLog};
use crate::capture::lights::{FirmwareInfo, SerialLights, SerialOptions, SharedLights};
use crate::capture::{run_capture, CaptureOptions, CaptureReport, Interrupt, SyntheticInfo};
use crate::error::Result;
use crate::maps::{self, report::Mean, WrittenMaps};
use crate::progress::Progress;
use crate::rig::Rig;
use crate::sets::{self, SolveJob};
use crate::synth::set::{write_truth, SPEC_FILE, TRUTH_DIR};
use crate::synth::{demo, DemoPaths, Scene, SynthSpec};

/// A running emulator with the serial link open on its pty.
pub struct EmulatedController {
    /// The firmware running in its emulator; it stops when this is dropped.
    pub emulator: Emulator,
    /// The serial link to the emulator's pty, shareable with the keepalive thread.
    pub lights: SharedLights,
    /// The identity the firmware gave at the handshake.
    pub firmware: FirmwareInfo,
}

impl EmulatedController {
    /// Starts the firmware emulator (pin log at `pin_log`) and opens its pty with the real
    /// serial code. Call from a thread that outlives the controller (the emulator stops when
    /// the thread that started it ends).
    pub fn start(pin_log: &Path, options: SerialOptions) -> Result<EmulatedController> {
        let files = EmulatorFiles::locate()?;
        let emulator = Emulator::start(&files, pin_log)?;
        let serial = SerialLights::open(emulator.pty(), options)?;
        let firmware = serial
            .info()
            .cloned()
            .expect("open identifies the firmware");
        Ok(EmulatedController {
            emulator,
            lights: SharedLights::new(Box::new(serial)),
            firmware,
        })
    }

    /// A reader of the emulator's pin log: which LEDs the firmware's pins had on, and when.
    pub fn pin_log(&self) -> PinLog {
        self.emulator.pin_log()
    }
}

/// Where a simulated camera learns which LEDs are on, chosen the same way by every command: the
/// emulator's pin log when the firmware runs in its emulator, else the pin log at `pin_log`
/// (a board whose pins are logged), else the controller's own answer to `STATE`.
pub fn lit_source(
    emulated: Option<&EmulatedController>,
    pin_log: Option<&Path>,
    lights: &SharedLights,
) -> Box<dyn LitSource> {
    match (emulated, pin_log) {
        (Some(emulated), _) => Box::new(emulated.pin_log()),
        (None, Some(path)) => Box::new(PinLog::new(path)),
        (None, None) => Box::new(ControllerState(lights.clone())),
    }
}

/// Writes the scene's ground truth into a capture set folder (for `psscan solve` to compare
/// against) and returns what the manifest records about it. The folder must be new, empty,
/// or already claimed by this run for a new set (see `fsutil::claim_dir`).
pub fn write_scene_truth(scene: &Scene, spec: &SynthSpec, dir: &Path) -> Result<SyntheticInfo> {
    crate::fsutil::claim_dir(dir, false, &[], &[])?;
    write_truth(scene, spec, dir)?;
    Ok(SyntheticInfo {
        truth_dir: TRUTH_DIR.into(),
        spec_file: SPEC_FILE.into(),
    })
}

/// Captures the synthetic scene `spec` into `dir` through `lights`, with the simulated
/// camera asking `source` what is lit; the set gets the scene's ground truth.
#[allow(clippy::too_many_arguments)]
pub fn capture_synthetic(
    dir: &Path,
    rig: &Rig,
    spec: &SynthSpec,
    lights: &SharedLights,
    source: Box<dyn LitSource>,
    options: &CaptureOptions,
    interrupt: &Interrupt,
    progress: &dyn Progress,
) -> Result<CaptureReport> {
    let mut camera = SimCamera::new(rig, spec, source)?;
    let mut options = options.clone();
    let exists = dir.join(crate::capture::manifest::MANIFEST_FILE).is_file();
    // A set being resumed has its truth already; one that must not be overwritten is
    // refused by the sequencer before anything is written.
    if !exists || options.force {
        // The sequencer claims the folder too; claimed once per run, the truth stays.
        crate::fsutil::claim_dir(dir, options.force, &[], &[])?;
        options.synthetic = Some(write_scene_truth(camera.scene(), spec, dir)?);
    }
    run_capture(dir, rig, lights, &mut camera, &options, interrupt, progress)
}

/// One frame of the firmware-in-the-loop demo: which LEDs the firmware had on (from its pin
/// log) when the camera fired.
#[derive(Clone, Debug, Serialize)]
pub struct DemoFrame {
    /// The frame's file name in the capture set.
    pub file: String,
    /// The LED the frame was meant to show; `None` for the dark frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub light: Option<usize>,
    /// The LEDs the simulated camera saw lit (from the pin log) when it fired; empty when it could
    /// not know.
    pub lit_at_fire: Vec<usize>,
    /// When the camera fired, Unix microseconds (0 when not known).
    pub fired_unix_us: u64,
}

/// `psscan demo --firmware-sim --json`.
#[derive(Clone, Debug, Serialize)]
pub struct FirmwareSimDemoSummary {
    /// The rig's name (the default rig).
    pub rig: String,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// LEDs in the rig, one light frame each.
    pub lights: usize,
    /// Angle between solved and true normals over the solved pixels (degrees).
    pub normal_error_deg: crate::eval::Stats,
    /// Mean normal error the solve predicts from sensor noise (degrees; NaN when not computed).
    pub predicted_normal_error_deg: Mean,
    /// `|albedo - true| / true` per channel over the solved pixels.
    pub albedo_rel_error: crate::eval::Stats,
    /// Solved pixels compared with the ground truth.
    pub solved_pixels: usize,
    /// The identity the emulated firmware gave.
    pub firmware: FirmwareInfo,
    /// The emulator's pseudo-terminal the serial link used.
    pub port: String,
    /// The pin log the emulator wrote, `<out>/firmware-sim/pins.log`.
    pub pin_log: PathBuf,
    /// Every frame of the capture, with the LEDs lit when it was shot.
    pub frames: Vec<DemoFrame>,
    /// Shots at which the pin log shows anything but the one intended LED (or, for the dark
    /// frame, any LED): 0 in a correct run.
    pub shots_with_wrong_leds: usize,
    /// The most LEDs the pin log ever shows on together (1 in a correct run).
    pub max_leds_on_together: usize,
    /// Keepalive pings sent to the firmware during the capture.
    pub keepalive_pings: u64,
    /// Wall-clock durations by stage, seconds: `capture`, the solve's stages as `solve_<stage>`,
    /// and `total`.
    pub timings_s: BTreeMap<String, f64>,
    /// Where the demo wrote the capture set, the maps and the report.
    pub paths: DemoPaths,
}

/// The demo through the emulated firmware: start the emulator, open its pty, capture the
/// synthetic textile into `out/capture` with the simulated camera, solve into `out/maps`,
/// compare with the ground truth. The demo's folder is scratch space (replaced).
pub fn run_firmware_sim_demo(
    out: &Path,
    spec: &SynthSpec,
    job: &SolveJob,
    settle: std::time::Duration,
    interrupt: &Interrupt,
    progress: &dyn Progress,
) -> Result<FirmwareSimDemoSummary> {
    let total = Instant::now();
    let rig = Rig::default_rig();
    let capture_dir = out.join("capture");
    let maps_dir = out.join("maps");
    let sim_dir = out.join("firmware-sim");
    crate::fsutil::claim_dir(
        out,
        true,
        &[],
        &[demo::DEMO_CAPTURE, demo::DEMO_MAPS, "firmware-sim/"],
    )?;
    crate::fsutil::claim_dir(&sim_dir, true, &[], &["pins.log"])?;
    let pin_log_path = sim_dir.join("pins.log");
    let controller = EmulatedController::start(&pin_log_path, SerialOptions::default())?;
    let options = CaptureOptions {
        settle,
        force: true,
        ..CaptureOptions::default()
    };
    let start = Instant::now();
    let capture = capture_synthetic(
        &capture_dir,
        &rig,
        spec,
        &controller.lights,
        Box::new(controller.pin_log()),
        &options,
        interrupt,
        progress,
    )?;
    let capture_s = start.elapsed().as_secs_f64();
    let history = controller.pin_log().read()?;
    let port = controller.emulator.pty().to_string();
    let firmware = controller.firmware.clone();
    drop(controller);

    let frames: Vec<DemoFrame> = capture
        .frames
        .iter()
        .map(|f| DemoFrame {
            file: f.file.clone(),
            light: f.light,
            lit_at_fire: f.lit_at_fire.clone().unwrap_or_default(),
            fired_unix_us: f.fired_unix_us.unwrap_or_default(),
        })
        .collect();
    let shots_with_wrong_leds = frames
        .iter()
        .filter(|f| {
            let intended: Vec<usize> = f.light.into_iter().collect();
            f.lit_at_fire != intended || history.lit_at_unix_us(f.fired_unix_us) != intended
        })
        .count();

    let job = SolveJob {
        force: true,
        ..job.clone()
    };
    let report = sets::solve_set(&capture_dir, &maps_dir, &job, progress)?;
    let truth = report
        .truth
        .clone()
        .expect("the emulated capture records the scene's ground truth");
    let mut timings = BTreeMap::new();
    timings.insert("capture".into(), capture_s);
    for (k, v) in &report.timings_s {
        timings.insert(format!("solve_{k}"), *v);
    }
    timings.insert("total".into(), total.elapsed().as_secs_f64());
    let outputs: WrittenMaps = report.outputs.clone();
    Ok(FirmwareSimDemoSummary {
        rig: rig.name.clone(),
        width: spec.width,
        height: spec.height,
        lights: rig.leds.len(),
        normal_error_deg: truth.normal_error_deg,
        predicted_normal_error_deg: report.predicted_normal_error_deg,
        albedo_rel_error: truth.albedo_rel_error,
        solved_pixels: truth.pixels,
        firmware,
        port,
        pin_log: pin_log_path,
        frames,
        shots_with_wrong_leds,
        max_leds_on_together: history.max_lit_together(),
        keepalive_pings: capture.keepalive_pings,
        timings_s: timings,
        paths: DemoPaths {
            capture: capture_dir,
            report: maps_dir.join(maps::REPORT_FILE),
            maps: maps_dir,
            outputs,
        },
    })
}
