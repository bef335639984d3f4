//! Firmware in the loop: the real LED firmware (firmware/build/psscan_led.elf) in its simavr
//! harness, psscan's real serial code on the harness's pty, the simulated camera reading the
//! harness's pin log when it fires. Every capture here is checked against the pin log (which
//! LED pins were really high) and, where it completes, against the same scene captured
//! in-process.
//!
//! The harness is built by `make -C firmware all sim` (`make test` does it first); each test
//! starts its own instance (own pty, own pin log), so they run in parallel, and the instance
//! is stopped when the test ends (`--exit-with-parent` covers a killed test run).

use std::cell::RefCell;
use std::path::Path;
use std::rc::Rc;
use std::time::Duration;

use psscan::capture::camera::{Camera, Shot};
use psscan::capture::lights::{LightController, LineNoise, SerialLights, SerialOptions};
use psscan::capture::{
    run_capture, CameraSettings, CaptureOptions, CaptureReport, CaptureSet, ImageInfo, Interrupt,
};
use psscan::progress::Silent;
use psscan::rig::Rig;
use psscan::sets::{self, SolveJob};
use psscan::sim::emulated::{capture_synthetic, write_scene_truth, EmulatedController};
use psscan::sim::emulator::{PinHistory, PinLog};
use psscan::sim::SimCamera;
use psscan::synth::{self, SynthSpec};
use psscan::{Error, Result};

/// 64 x 48 pixels over most of the sensor (every 64th pixel): fast, and enough pixels for
/// the error statistics.
fn spec() -> SynthSpec {
    let mut spec = SynthSpec::demo();
    spec.width = 64;
    spec.height = 48;
    spec.step = 64.0;
    spec
}

fn options() -> CaptureOptions {
    CaptureOptions {
        settle: Duration::from_millis(5),
        ..CaptureOptions::default()
    }
}

fn start(dir: &Path) -> EmulatedController {
    EmulatedController::start(&dir.join("pins.log"), SerialOptions::default())
        .expect("the firmware emulator starts (make -C firmware all sim)")
}

/// The pin log agrees with the report at every shot: only the intended LED (none for the
/// dark frame) was high when the camera fired, and never two LEDs at once.
fn check_pin_log_against(report: &CaptureReport, history: &PinHistory) {
    for frame in report.frames.iter().filter(|f| f.fired_unix_us.is_some()) {
        let intended: Vec<usize> = frame.light.into_iter().collect();
        let at_fire = history.lit_at_unix_us(frame.fired_unix_us.unwrap());
        assert_eq!(at_fire, intended, "{}: pin log at the shot", frame.file);
        assert_eq!(
            frame.lit_at_fire.as_ref(),
            Some(&intended),
            "{}",
            frame.file
        );
    }
    assert!(history.max_lit_together() <= 1);
}

/// The frames of the set in `a` and `b` are byte for byte the same.
fn same_frames(a: &Path, b: &Path) {
    let a = CaptureSet::open(a, None).unwrap();
    let b = CaptureSet::open(b, None).unwrap();
    assert_eq!(a.manifest.frames.len(), 11);
    for entry in &a.manifest.frames {
        let other = b
            .manifest
            .frames
            .iter()
            .find(|f| f.kind == entry.kind && f.light == entry.light)
            .unwrap_or_else(|| panic!("{} missing", entry.file));
        assert_eq!(entry.sha256, other.sha256, "{}", entry.file);
    }
}

/// A camera around the simulated one that runs `hook(shot index)` before each shot, and
/// may claim a shorter shot time than it takes (a hung camera).
struct Hooked<'a> {
    inner: SimCamera<'a>,
    shots: usize,
    hook: Box<dyn FnMut(usize) -> Result<()> + 'a>,
    claimed_shot_time: Option<Duration>,
}

impl<'a> Hooked<'a> {
    fn new(inner: SimCamera<'a>, hook: impl FnMut(usize) -> Result<()> + 'a) -> Self {
        Hooked {
            inner,
            shots: 0,
            hook: Box::new(hook),
            claimed_shot_time: None,
        }
    }
}

impl Camera for Hooked<'_> {
    fn name(&self) -> String {
        self.inner.name()
    }
    fn settings(&mut self) -> Result<CameraSettings> {
        self.inner.settings()
    }
    fn image_info(&self, rig: &Rig) -> ImageInfo {
        self.inner.image_info(rig)
    }
    fn max_shot_time(&self) -> Duration {
        self.claimed_shot_time
            .unwrap_or_else(|| self.inner.max_shot_time())
    }
    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot> {
        let n = self.shots;
        self.shots += 1;
        (self.hook)(n)?;
        self.inner.capture(dest, interrupt)
    }
}

/// Frames of an interrupted set: exactly the first `k` of the plan, each intact.
fn kept_frames(dir: &Path) -> Vec<String> {
    let set = CaptureSet::open(dir, None).unwrap();
    for entry in &set.manifest.frames {
        set.read_frame_bytes(entry).expect("kept frames are intact");
    }
    set.manifest.frames.iter().map(|f| f.file.clone()).collect()
}

fn first_frames(k: usize) -> Vec<String> {
    std::iter::once("dark.png".to_string())
        .chain((0..10).map(|i| format!("L{i:02}.png")))
        .take(k)
        .collect()
}

/// Resumes the set in `dir` with a fresh emulator and checks the completed set equals the
/// in-process render of the same scene.
fn resume_and_compare(dir: &Path, scratch: &Path, reference: &Path, expect_shot: usize) {
    let rig = Rig::default_rig();
    let controller = start(scratch);
    let report = capture_synthetic(
        dir,
        &rig,
        &spec(),
        &controller.lights,
        Box::new(controller.pin_log()),
        &CaptureOptions {
            resume: true,
            ..options()
        },
        &Interrupt::new(),
        &Silent,
    )
    .expect("--resume completes the set");
    assert_eq!(report.shot, expect_shot);
    assert_eq!(report.kept, 11 - expect_shot);
    check_pin_log_against(&report, &controller.pin_log().read().unwrap());
    same_frames(dir, reference);
}

fn in_process_reference(dir: &Path) {
    synth::write_synthetic_set(&Rig::default_rig(), &spec(), dir, false, &Silent).unwrap();
}

#[test]
fn serial_link_drives_the_real_firmware_and_surfaces_its_refusals() {
    let tmp = tempfile::tempdir().unwrap();
    let controller = start(tmp.path());
    let pins = controller.pin_log();
    assert_eq!(controller.firmware.leds, 10);
    assert_eq!(controller.firmware.protocol, 1);
    // While one session holds the port, another cannot open it.
    let busy = SerialLights::open(controller.emulator.pty(), SerialOptions::default());
    let err = busy.err().unwrap().to_string();
    assert!(err.contains("in use"), "{err}");
    drop(controller.lights);
    let mut serial = SerialLights::open(controller.emulator.pty(), SerialOptions::default())
        .expect("a second session on the same port (the banner was read by the first)");

    serial.on(3).unwrap();
    assert_eq!(pins.lit().unwrap(), vec![3], "pin high before OK arrives");
    let state = serial.state().unwrap();
    assert_eq!((state.on, state.tripped), (Some(3), false));
    serial.on(7).unwrap();
    assert_eq!(pins.lit().unwrap(), vec![7]);
    serial.keepalive().unwrap();

    // Bad lines from the host: the firmware refuses each, psscan names the refusal, and
    // nothing changes on the pins.
    for (line, answer) in [
        (b"ON 12".to_vec(), "ERR 4 out of range"),
        (vec![b'O', b'N', b' ', 0xff, b'3'], "ERR 5 bad character"),
        (vec![b'X'; 40], "ERR 3 line too long"),
        (b"on 3".to_vec(), "ERR 1 unknown command"),
        (b"ON  3".to_vec(), "ERR 2 bad argument"),
        (b"TIMEOUT 50".to_vec(), "ERR 4 out of range"),
        (vec![0u8; 300], "ERR 3 line too long"),
    ] {
        let err = serial.send_raw(&line).unwrap_err().to_string();
        assert!(
            err.contains(answer) && err.contains("refused"),
            "{line:?}: {err}"
        );
        assert_eq!(pins.lit().unwrap(), vec![7], "{line:?} changed the LEDs");
    }
    assert_eq!(serial.send_raw(b"PING").unwrap(), "PONG");
    // The typed API refuses what it knows is wrong before sending it.
    assert!(serial
        .on(10)
        .unwrap_err()
        .to_string()
        .contains("does not exist"));
    assert!(serial
        .set_timeout(50)
        .unwrap_err()
        .to_string()
        .contains("100..60000"));

    serial.off().unwrap();
    assert!(pins.lit().unwrap().is_empty());
    serial.on(1).unwrap();
    drop(serial);
    assert!(
        pins.lit().unwrap().is_empty(),
        "dropping the controller switches the LEDs off"
    );
}

#[test]
fn emulated_capture_equals_the_in_process_render_and_solves_as_accurately() {
    let tmp = tempfile::tempdir().unwrap();
    let rig = Rig::default_rig();
    let emulated = tmp.path().join("emulated");
    let reference = tmp.path().join("reference");
    let controller = start(tmp.path());
    let report = capture_synthetic(
        &emulated,
        &rig,
        &spec(),
        &controller.lights,
        Box::new(controller.pin_log()),
        &options(),
        &Interrupt::new(),
        &Silent,
    )
    .unwrap();
    assert_eq!((report.shot, report.kept), (11, 0));
    let history = controller.pin_log().read().unwrap();
    check_pin_log_against(&report, &history);
    assert!(history.lit_now().is_empty(), "LEDs off at the end");
    // Every LED went on exactly once (the firmware's ON), in order.
    let ons: Vec<usize> = history
        .events
        .iter()
        .filter(|e| e.on)
        .map(|e| e.led)
        .collect();
    assert_eq!(ons, (0..10).collect::<Vec<_>>());

    in_process_reference(&reference);
    same_frames(&emulated, &reference);

    let job = SolveJob::default();
    let a = sets::solve_set(&emulated, &tmp.path().join("a"), &job, &Silent).unwrap();
    let b = sets::solve_set(&reference, &tmp.path().join("b"), &job, &Silent).unwrap();
    let (ta, tb) = (a.truth.unwrap(), b.truth.unwrap());
    assert_eq!(ta.normal_error_deg.mean, tb.normal_error_deg.mean);
    assert_eq!(ta.albedo_rel_error.mean, tb.albedo_rel_error.mean);
    // Against the noise model: 3072 pixels put the mean's sampling error near 1 %; the
    // model holds to 10 % (the same bound as the foundation's end-to-end test).
    let predicted = a.predicted_normal_error_deg.mean;
    let measured = ta.normal_error_deg.mean;
    println!(
        "emulated capture: normal error mean {measured:.4} deg, predicted {predicted:.4} deg, \
         albedo error mean {:.4} %",
        100.0 * ta.albedo_rel_error.mean
    );
    assert!(
        (measured / predicted - 1.0).abs() < 0.1,
        "measured {measured}, predicted {predicted}"
    );
}

#[test]
fn the_port_vanishing_mid_session_is_named_and_resume_completes_the_set() {
    let tmp = tempfile::tempdir().unwrap();
    let rig = Rig::default_rig();
    let dir = tmp.path().join("set");
    let first = tmp.path().join("first");
    std::fs::create_dir_all(&first).unwrap();
    let controller = start(&first);
    let lights = controller.lights.clone();
    let pins = controller.pin_log();
    let emulator = Rc::new(RefCell::new(controller.emulator));
    let k = 5; // dark, L00..L03 are taken; the emulator dies as L04 is shot
    let kill = emulator.clone();
    let scene = SimCamera::new(&rig, &spec(), Box::new(pins.clone())).unwrap();
    let truth = write_scene_truth(scene.scene(), &spec(), &dir).unwrap();
    let mut camera = Hooked::new(scene, move |n| {
        if n == k {
            kill.borrow_mut().kill();
        }
        Ok(())
    });
    let err = run_capture(
        &dir,
        &rig,
        &lights,
        &mut camera,
        &CaptureOptions {
            synthetic: Some(truth),
            ..options()
        },
        &Interrupt::new(),
        &Silent,
    )
    .unwrap_err();
    println!("{err}");
    // The set can be completed: the error says so by its kind (the CLI names --resume).
    assert!(matches!(err, Error::Resumable { .. }), "{err}");
    let err = err.to_string();
    assert!(
        err.contains("vanished") && err.contains("/dev/pts/"),
        "{err}"
    );
    assert!(err.contains("frame L04 (LED 4)"), "{err}");
    assert!(err.contains("could not switch the LEDs off"), "{err}");
    assert_eq!(kept_frames(&dir), first_frames(k));
    // The MCU died with the harness (on the rig: a board without power, every channel held
    // off by its gate pull-down); its log ends without an exit line.
    let history = pins.read().unwrap();
    assert!(history.markers.iter().all(|(m, _)| m != "exit"));
    assert!(history.max_lit_together() <= 1);

    let reference = tmp.path().join("reference");
    in_process_reference(&reference);
    resume_and_compare(&dir, tmp.path(), &reference, 11 - k);
}

#[test]
fn a_camera_failing_on_frame_k_leaves_leds_off_and_resume_completes_the_set() {
    let tmp = tempfile::tempdir().unwrap();
    let rig = Rig::default_rig();
    let dir = tmp.path().join("set");
    let first = tmp.path().join("first");
    std::fs::create_dir_all(&first).unwrap();
    let controller = start(&first);
    let pins = controller.pin_log();
    let k = 7; // L06 fails
    let scene = SimCamera::new(&rig, &spec(), Box::new(pins.clone())).unwrap();
    let truth = write_scene_truth(scene.scene(), &spec(), &dir).unwrap();
    let mut camera = Hooked::new(scene, |n| {
        if n == k {
            Err(Error::device("camera", "card full"))
        } else {
            Ok(())
        }
    });
    let err = run_capture(
        &dir,
        &rig,
        &controller.lights,
        &mut camera,
        &CaptureOptions {
            synthetic: Some(truth),
            ..options()
        },
        &Interrupt::new(),
        &Silent,
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("frame L06 (LED 6)") && err.contains("card full"),
        "{err}"
    );
    assert!(err.contains("all LEDs are off"), "{err}");
    let history = pins.read().unwrap();
    assert!(
        history.lit_now().is_empty(),
        "pin log: LEDs off after the error"
    );
    assert!(history.events.iter().any(|e| e.led == 6 && e.on));
    assert_eq!(kept_frames(&dir), first_frames(k));
    drop(controller);

    let reference = tmp.path().join("reference");
    in_process_reference(&reference);
    resume_and_compare(&dir, tmp.path(), &reference, 11 - k);
}

#[test]
fn garbage_on_the_line_is_retried_once_then_named_and_resume_completes_the_set() {
    let tmp = tempfile::tempdir().unwrap();
    let rig = Rig::default_rig();
    let reference = tmp.path().join("reference");
    in_process_reference(&reference);

    // Noise before "ON 2" once (a bad byte) and before "ON 5" once (an overlong line): the
    // firmware refuses the damaged lines, psscan resynchronises and retries, the set is
    // complete and right.
    let dir = tmp.path().join("noisy");
    let run = tmp.path().join("run1");
    std::fs::create_dir_all(&run).unwrap();
    let files = psscan::sim::emulator::EmulatorFiles::locate().unwrap();
    let emulator = psscan::sim::emulator::Emulator::start(&files, &run.join("pins.log")).unwrap();
    let mut serial = SerialLights::open(emulator.pty(), SerialOptions::default()).unwrap();
    serial.set_line_noise(Some(LineNoise {
        command: "ON 2".into(),
        times: 1,
        garbage: vec![0xff, 0x00, 0x07],
    }));
    let lights = psscan::capture::lights::SharedLights::new(Box::new(serial));
    let report = capture_synthetic(
        &dir,
        &rig,
        &spec(),
        &lights,
        Box::new(emulator.pin_log()),
        &options(),
        &Interrupt::new(),
        &Silent,
    )
    .unwrap();
    check_pin_log_against(&report, &emulator.pin_log().read().unwrap());
    same_frames(&dir, &reference);
    drop(lights);
    drop(emulator);

    // Overlong garbage before "ON 4", twice: the retry is refused too, and the session
    // stops with the firmware's answer, LEDs off, frames before it kept.
    let dir = tmp.path().join("broken");
    let run = tmp.path().join("run2");
    std::fs::create_dir_all(&run).unwrap();
    let emulator = psscan::sim::emulator::Emulator::start(&files, &run.join("pins.log")).unwrap();
    let mut serial = SerialLights::open(emulator.pty(), SerialOptions::default()).unwrap();
    serial.set_line_noise(Some(LineNoise {
        command: "ON 4".into(),
        times: 2,
        garbage: vec![b'#'; 40],
    }));
    let lights = psscan::capture::lights::SharedLights::new(Box::new(serial));
    let err = capture_synthetic(
        &dir,
        &rig,
        &spec(),
        &lights,
        Box::new(emulator.pin_log()),
        &options(),
        &Interrupt::new(),
        &Silent,
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("ERR 3 line too long") && err.contains("after one retry"),
        "{err}"
    );
    assert!(
        err.contains("frame L04 (LED 4)") && err.contains("all LEDs are off"),
        "{err}"
    );
    let history = emulator.pin_log().read().unwrap();
    assert!(history.lit_now().is_empty());
    assert!(
        !history.events.iter().any(|e| e.led == 4 && e.on),
        "the damaged ON 4 never lit LED 4"
    );
    assert_eq!(kept_frames(&dir), first_frames(5));
    drop(lights);
    drop(emulator);
    resume_and_compare(&dir, tmp.path(), &reference, 6);
}

#[test]
fn a_silent_host_lets_the_firmware_switch_off_and_the_frame_is_not_kept() {
    let tmp = tempfile::tempdir().unwrap();
    let rig = Rig::default_rig();
    let dir = tmp.path().join("set");
    let first = tmp.path().join("first");
    std::fs::create_dir_all(&first).unwrap();
    let controller = start(&first);
    let pins = controller.pin_log();
    let k = 4; // L03: the camera hangs far past the firmware's 300 ms silence timeout
    let scene = SimCamera::new(&rig, &spec(), Box::new(pins.clone())).unwrap();
    let truth = write_scene_truth(scene.scene(), &spec(), &dir).unwrap();
    let mut camera = Hooked::new(scene, |n| {
        if n == k {
            std::thread::sleep(Duration::from_millis(1200));
        }
        Ok(())
    });
    // The camera claims its shots take 100 ms: the keepalive covers that and then stops,
    // as it would for a camera that hung.
    camera.claimed_shot_time = Some(Duration::from_millis(100));
    let err = run_capture(
        &dir,
        &rig,
        &controller.lights,
        &mut camera,
        &CaptureOptions {
            synthetic: Some(truth),
            light_timeout_ms: Some(300),
            ..options()
        },
        &Interrupt::new(),
        &Silent,
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("frame L03 (LED 3)") && err.contains("tripped=1"),
        "{err}"
    );
    assert!(err.contains("all LEDs are off"), "{err}");
    // The pin log: LED 3 went off by itself, 300 ms (plus the 100 ms lease) after it went
    // on, long before the host spoke again at 1200 ms.
    let history = pins.read().unwrap();
    let on = history.events.iter().find(|e| e.led == 3 && e.on).unwrap();
    let off = history
        .events
        .iter()
        .find(|e| e.led == 3 && !e.on && e.sim_us > on.sim_us)
        .unwrap();
    let held_ms = (off.sim_us - on.sim_us) as f64 / 1000.0;
    assert!(
        (300.0..1100.0).contains(&held_ms),
        "LED 3 on for {held_ms} ms"
    );
    assert!(history.lit_now().is_empty());
    assert_eq!(kept_frames(&dir), first_frames(k));
    drop(controller);

    let reference = tmp.path().join("reference");
    in_process_reference(&reference);
    resume_and_compare(&dir, tmp.path(), &reference, 11 - k);
}

#[test]
fn a_pin_log_reader_sees_what_the_firmware_did() {
    // The reader against the live harness: a LED switched by the firmware shows at once.
    let tmp = tempfile::tempdir().unwrap();
    let controller = start(tmp.path());
    let log = PinLog::new(&tmp.path().join("pins.log"));
    controller.lights.lock().on(9).unwrap();
    assert_eq!(log.lit().unwrap(), vec![9]);
    let history = log.read().unwrap();
    assert!(history.start_unix_us > 0);
    assert_eq!(history.leds, 10);
    assert_eq!(history.markers[0].0, "power-on");
}
