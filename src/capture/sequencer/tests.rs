//! The sequencer on the in-process mock controller and the simulated camera.

use super::*;
use crate::capture::lights::{MockFault, MockLights};
use crate::error::Occupied;
use crate::progress::Silent;
use crate::sim::SimCamera;
use crate::synth::SynthSpec;

fn spec() -> SynthSpec {
    let mut spec = SynthSpec::demo();
    spec.width = 32;
    spec.height = 24;
    spec.step = 128.0;
    spec
}

fn options() -> CaptureOptions {
    CaptureOptions {
        settle: Duration::from_millis(1),
        ..Default::default()
    }
}

/// A camera that fails on its `n`-th shot (0-based), then works.
struct FailOnce<'a> {
    inner: SimCamera<'a>,
    shots: usize,
    fail_at: usize,
}

impl Camera for FailOnce<'_> {
    fn name(&self) -> String {
        self.inner.name()
    }
    fn settings(&mut self) -> Result<CameraSettings> {
        self.inner.settings()
    }
    fn image_info(&self, rig: &Rig) -> super::super::ImageInfo {
        self.inner.image_info(rig)
    }
    fn max_shot_time(&self) -> Duration {
        self.inner.max_shot_time()
    }
    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot> {
        self.shots += 1;
        if self.shots - 1 == self.fail_at {
            return Err(Error::device("test camera", "shutter jammed"));
        }
        self.inner.capture(dest, interrupt)
    }
}

/// A camera that reports `settings` (a DSLR tethered over gphoto2 reports its ISO, shutter
/// and aperture) and otherwise shoots as `inner`; at its `stop_at`-th shot it raises `stop`
/// (Ctrl-C while the shutter is open).
struct Reporting<'a> {
    inner: SimCamera<'a>,
    settings: CameraSettings,
    shots: usize,
    stop_at: usize,
    stop: Interrupt,
}

impl Camera for Reporting<'_> {
    fn name(&self) -> String {
        self.inner.name()
    }
    fn settings(&mut self) -> Result<CameraSettings> {
        Ok(self.settings.clone())
    }
    fn image_info(&self, rig: &Rig) -> super::super::ImageInfo {
        self.inner.image_info(rig)
    }
    fn max_shot_time(&self) -> Duration {
        self.inner.max_shot_time()
    }
    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot> {
        self.shots += 1;
        if self.shots == self.stop_at {
            self.stop.set();
        }
        self.inner.capture(dest, interrupt)
    }
}

#[test]
fn the_manifest_records_the_cameras_settings_and_resume_needs_the_same() {
    let rig = Rig::default_rig();
    let dir = tempfile::tempdir().unwrap();
    let mock = MockLights::new(10);
    let probe = mock.probe();
    let lights = SharedLights::new(Box::new(mock));
    let settings = CameraSettings {
        model: "Nikon D800E".into(),
        iso: Some(100),
        shutter_s: Some(1.0 / 60.0),
        aperture: Some(8.0),
    };
    let interrupt = Interrupt::new();
    let mut camera = Reporting {
        inner: SimCamera::new(&rig, &spec(), Box::new(probe.clone())).unwrap(),
        settings: settings.clone(),
        shots: 0,
        stop_at: 4,
        stop: interrupt.clone(),
    };
    let stopped = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &options(),
        &interrupt,
        &Silent,
    );
    assert!(stopped.is_err());
    let set = CaptureSet::open(dir.path(), None).unwrap();
    assert_eq!(set.manifest.camera, settings);
    // Resuming with the ISO changed would mix exposures in one set: refused, both named.
    camera.settings.iso = Some(400);
    let resume = CaptureOptions {
        resume: true,
        ..options()
    };
    let err = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &resume,
        &Interrupt::new(),
        &Silent,
    )
    .unwrap_err();
    let text = err.to_string();
    assert!(
        matches!(
            err,
            Error::SetOccupied {
                state: Occupied::OtherFrames { .. },
                ..
            }
        ),
        "{text}"
    );
    assert!(
        text.contains("ISO 100, 1/60 s, f/8") && text.contains("ISO 400"),
        "{text}"
    );
    // With the settings it was started with, it completes.
    camera.settings.iso = Some(100);
    let report = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &resume,
        &Interrupt::new(),
        &Silent,
    )
    .unwrap();
    assert_eq!(report.shot + report.kept, 11);
    assert_eq!(
        CaptureSet::open(dir.path(), None).unwrap().manifest.camera,
        settings
    );
}

#[test]
fn a_mock_session_shoots_dark_then_each_led_and_checks_state() {
    let rig = Rig::default_rig();
    let dir = tempfile::tempdir().unwrap();
    let mock = MockLights::new(10);
    let probe = mock.probe();
    let lights = SharedLights::new(Box::new(mock));
    let mut camera = SimCamera::new(&rig, &spec(), Box::new(probe.clone())).unwrap();
    let report = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &options(),
        &Interrupt::new(),
        &Silent,
    )
    .unwrap();
    assert_eq!(report.shot, 11);
    assert_eq!(report.frames[0].lit_at_fire, Some(vec![]));
    for k in 0..10 {
        assert_eq!(report.frames[k + 1].lit_at_fire, Some(vec![k]));
        assert_eq!(report.frames[k + 1].file, format!("L{k:02}.png"));
    }
    let log = probe.log();
    // Each light: ON, STATE (confirm), STATE (after the shot).
    let on3 = log.iter().position(|l| l == "ON 3").unwrap();
    assert_eq!(&log[on3..on3 + 3], ["ON 3", "STATE", "STATE"]);
    assert!(probe.lit().is_empty());
    let set = CaptureSet::open(dir.path(), None).unwrap();
    assert_eq!(set.load_frames(&Silent).unwrap().lights.len(), 10);

    // A complete set is not overwritten without --force, and resume has nothing to do.
    let mut camera = SimCamera::new(&rig, &spec(), Box::new(probe.clone())).unwrap();
    let again = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &options(),
        &Interrupt::new(),
        &Silent,
    );
    let err = again.unwrap_err();
    assert!(
        matches!(
            err,
            Error::SetOccupied {
                state: Occupied::Complete,
                ..
            }
        ),
        "{err}"
    );
    let resumed = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &CaptureOptions {
            resume: true,
            ..options()
        },
        &Interrupt::new(),
        &Silent,
    )
    .unwrap();
    assert_eq!((resumed.shot, resumed.kept), (0, 11));
}

#[test]
fn a_failing_camera_keeps_earlier_frames_and_resume_reshoots_the_rest() {
    let rig = Rig::default_rig();
    let dir = tempfile::tempdir().unwrap();
    let mock = MockLights::new(10);
    let probe = mock.probe();
    let lights = SharedLights::new(Box::new(mock));
    let mut camera = FailOnce {
        inner: SimCamera::new(&rig, &spec(), Box::new(probe.clone())).unwrap(),
        shots: 0,
        fail_at: 4,
    };
    let err = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &options(),
        &Interrupt::new(),
        &Silent,
    )
    .unwrap_err();
    assert!(matches!(err, Error::Resumable { .. }), "{err}");
    let err = err.to_string();
    assert!(
        err.contains("LED 3") && err.contains("shutter jammed"),
        "{err}"
    );
    assert!(err.contains("all LEDs are off"), "{err}");
    assert!(probe.lit().is_empty());
    let set = CaptureSet::open(dir.path(), None).unwrap();
    assert_eq!(set.manifest.frames.len(), 4);
    // An incomplete set is not restarted by accident.
    let err = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &options(),
        &Interrupt::new(),
        &Silent,
    )
    .unwrap_err();
    assert!(
        matches!(
            err,
            Error::SetOccupied {
                state: Occupied::Unfinished { kept: 4, .. },
                ..
            }
        ),
        "{err}"
    );

    // Damage a kept frame: resume re-shoots it too.
    std::fs::write(dir.path().join("L01.png"), b"garbage").unwrap();
    let report = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &CaptureOptions {
            resume: true,
            ..options()
        },
        &Interrupt::new(),
        &Silent,
    )
    .unwrap();
    assert_eq!(report.kept, 3);
    assert_eq!(report.shot, 8);
    assert_eq!(report.dropped.len(), 1);
    assert!(report.dropped[0].reason.contains("SHA-256"));
    let set = CaptureSet::open(dir.path(), None).unwrap();
    assert_eq!(set.load_frames(&Silent).unwrap().lights.len(), 10);
}

#[test]
fn a_controller_that_vanishes_or_refuses_stops_the_session_clearly() {
    let rig = Rig::default_rig();
    for (fault, needle) in [
        (MockFault::VanishAt("ON 5".into()), "vanished"),
        (MockFault::Refuse("ON 2".into(), 4), "ERR 4"),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let mock = MockLights::new(10).with_fault(fault);
        let probe = mock.probe();
        let lights = SharedLights::new(Box::new(mock));
        let mut camera = SimCamera::new(&rig, &spec(), Box::new(probe.clone())).unwrap();
        let options = CaptureOptions {
            light_timeout_ms: Some(100),
            ..options()
        };
        let err = run_capture(
            dir.path(),
            &rig,
            &lights,
            &mut camera,
            &options,
            &Interrupt::new(),
            &Silent,
        )
        .unwrap_err();
        assert!(matches!(err, Error::Resumable { .. }), "{err}");
        let err = err.to_string();
        assert!(err.contains(needle), "{err}");
        // A vanished controller cannot be told; its silence timeout switches off.
        std::thread::sleep(Duration::from_millis(150));
        assert!(probe.lit().is_empty(), "{err}");
    }
}

#[test]
fn an_interrupt_stops_before_the_next_frame_and_keeps_the_set_resumable() {
    let rig = Rig::default_rig();
    let dir = tempfile::tempdir().unwrap();
    let mock = MockLights::new(10);
    let probe = mock.probe();
    let lights = SharedLights::new(Box::new(mock));
    let stop = Interrupt::new();
    struct StopAt<'a> {
        inner: SimCamera<'a>,
        shots: usize,
        stop: Interrupt,
    }
    impl Camera for StopAt<'_> {
        fn name(&self) -> String {
            "stopper".into()
        }
        fn settings(&mut self) -> Result<CameraSettings> {
            self.inner.settings()
        }
        fn image_info(&self, rig: &Rig) -> super::super::ImageInfo {
            self.inner.image_info(rig)
        }
        fn max_shot_time(&self) -> Duration {
            Duration::from_secs(5)
        }
        fn capture(&mut self, dest: &Path, i: &Interrupt) -> Result<Shot> {
            self.shots += 1;
            if self.shots == 6 {
                // Ctrl-C while the shutter is open: this frame is not kept.
                self.stop.set();
            }
            self.inner.capture(dest, i)
        }
    }
    let mut camera = StopAt {
        inner: SimCamera::new(&rig, &spec(), Box::new(probe.clone())).unwrap(),
        shots: 0,
        stop: stop.clone(),
    };
    let err = run_capture(
        dir.path(),
        &rig,
        &lights,
        &mut camera,
        &options(),
        &stop,
        &Silent,
    )
    .unwrap_err();
    assert!(matches!(err, Error::Resumable { .. }), "{err}");
    assert!(err.is_interrupted(), "{err}");
    assert!(probe.lit().is_empty());
    let set = CaptureSet::open(dir.path(), None).unwrap();
    assert_eq!(set.manifest.frames.len(), 5);
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.contains(".shot")), "{names:?}");
}
