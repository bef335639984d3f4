//! The operator's commands end to end: `psscan capture` against the LED firmware in its
//! emulator (started by the test, opened by psscan by its pty path), Ctrl-C in the middle of
//! a capture, `--resume`, `psscan lights ...`, `psscan demo --firmware-sim`, and the errors a
//! missing camera or a failing camera command give.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use psscan::capture::CaptureSet;
use psscan::sim::emulator::{Emulator, EmulatorFiles};
mod common;

use common::{json, psscan, s, stderr};
use serde_json::Value;

fn emulator(dir: &Path) -> Emulator {
    let files = EmulatorFiles::locate().expect("make -C firmware all sim");
    Emulator::start(&files, &dir.join("pins.log")).unwrap()
}

const SCENE: [&str; 6] = ["--width", "64", "--height", "48", "--step", "64"];

fn capture_args<'a>(out: &'a Path, pty: &'a str, pins: &'a Path, settle: &'a str) -> Vec<&'a str> {
    let mut args = vec![
        "capture",
        "--out",
        s(out),
        "--port",
        pty,
        "--camera",
        "sim",
        "--pin-log",
        s(pins),
        "--settle-ms",
        settle,
    ];
    args.extend(SCENE);
    args
}

#[test]
fn capture_over_the_emulated_firmware_then_solve() {
    let tmp = tempfile::tempdir().unwrap();
    let emu = emulator(tmp.path());
    let pins = tmp.path().join("pins.log");
    let set = tmp.path().join("set");
    let mut args = capture_args(&set, emu.pty(), &pins, "5");
    args.push("--json");
    let report = json(&psscan(&args));
    assert_eq!(report["shot"], 11);
    assert_eq!(report["firmware"]["protocol"], 1);
    let frames = report["frames"].as_array().unwrap();
    assert_eq!(frames[0]["file"], "dark.png");
    assert_eq!(frames[0]["lit_at_fire"], serde_json::json!([]));
    for k in 0..10 {
        assert_eq!(frames[k + 1]["lit_at_fire"], serde_json::json!([k]));
    }
    assert!(emu.pin_log().lit().unwrap().is_empty());

    let solved = json(&psscan(&[
        "solve",
        s(&set),
        "--out",
        s(&tmp.path().join("maps")),
        "--json",
    ]));
    let measured = solved["truth"]["normal_error_deg"]["mean"]
        .as_f64()
        .unwrap();
    let predicted = solved["predicted_normal_error_deg"]["mean"]
        .as_f64()
        .unwrap();
    assert!(
        (measured / predicted - 1.0).abs() < 0.1,
        "{measured} vs {predicted}"
    );

    // A complete set is never overwritten without --force; the message names both ways on.
    let again = psscan(&capture_args(&set, emu.pty(), &pins, "5"));
    assert_eq!(again.status.code(), Some(1));
    let err = stderr(&again);
    assert!(err.contains("--force") && err.contains("--resume"), "{err}");
}

#[test]
fn ctrl_c_during_a_capture_switches_the_leds_off_and_resume_completes_the_set() {
    let tmp = tempfile::tempdir().unwrap();
    let emu = emulator(tmp.path());
    let pins = tmp.path().join("pins.log");
    let set = tmp.path().join("set");
    // 300 ms per LED: time to interrupt in the middle.
    let child = Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(capture_args(&set, emu.pty(), &pins, "300"))
        .arg("-q")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    loop {
        let frames = CaptureSet::open(&set, None)
            .map(|s| s.manifest.frames.len())
            .unwrap_or(0);
        if frames >= 4 {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "capture did not progress"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // SAFETY: signalling our own child.
    unsafe {
        libc::kill(child.id() as libc::pid_t, libc::SIGINT);
    }
    let out = child.wait_with_output().unwrap();
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(130), "{err}");
    assert!(
        err.contains("interrupted") && err.contains("--resume"),
        "{err}"
    );
    assert!(
        emu.pin_log().lit().unwrap().is_empty(),
        "LEDs off after Ctrl-C"
    );
    let set_now = CaptureSet::open(&set, None).unwrap();
    let kept = set_now.manifest.frames.len();
    assert!((4..11).contains(&kept), "{kept}");
    for entry in &set_now.manifest.frames {
        set_now.read_frame_bytes(entry).unwrap();
    }

    let mut args = capture_args(&set, emu.pty(), &pins, "5");
    args.extend(["--resume", "--json"]);
    let report = json(&psscan(&args));
    assert_eq!(report["kept"].as_u64().unwrap() as usize, kept);
    assert_eq!(report["shot"].as_u64().unwrap() as usize, 11 - kept);
    let complete = CaptureSet::open(&set, None).unwrap();
    assert_eq!(complete.manifest.frames.len(), 11);
    assert_eq!(
        complete
            .load_frames(&psscan::progress::Silent)
            .unwrap()
            .lights
            .len(),
        10
    );
}

#[test]
fn demo_firmware_sim_lists_the_lit_led_of_every_shot() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let mut args = vec!["demo", "--firmware-sim", "--out", s(&out), "--json"];
    args.extend(SCENE);
    let summary = json(&psscan(&args));
    let frames = summary["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 11);
    assert_eq!(frames[0]["lit_at_fire"], serde_json::json!([]));
    for k in 0..10 {
        assert_eq!(frames[k + 1]["light"], k);
        assert_eq!(frames[k + 1]["lit_at_fire"], serde_json::json!([k]));
    }
    assert_eq!(summary["shots_with_wrong_leds"], 0);
    assert_eq!(summary["max_leds_on_together"], 1);
    let measured = summary["normal_error_deg"]["mean"].as_f64().unwrap();
    let predicted = summary["predicted_normal_error_deg"]["mean"]
        .as_f64()
        .unwrap();
    assert!(
        (measured / predicted - 1.0).abs() < 0.1,
        "{measured} vs {predicted}"
    );
    assert!(Path::new(summary["pin_log"].as_str().unwrap()).is_file());
    assert!(out.join("maps/normal.png").is_file());
}

#[test]
fn lights_bench_commands_drive_the_emulated_firmware() {
    let tmp = tempfile::tempdir().unwrap();
    let emu = emulator(tmp.path());
    let pty = emu.pty().to_string();
    let ports = json(&psscan(&["lights", "ports", "--json"]));
    assert!(ports.is_array());

    let id = json(&psscan(&["lights", "--port", &pty, "identify", "--json"]));
    assert_eq!(id["firmware"]["name"], "psscan-led");
    assert_eq!(id["state"]["on"], Value::Null);

    let checks = json(&psscan(&[
        "lights",
        "--port",
        &pty,
        "test",
        "--dwell-ms",
        "10",
        "--json",
    ]));
    assert_eq!(checks.as_array().unwrap().len(), 10);
    assert!(checks.as_array().unwrap().iter().all(|c| c["ok"] == true));
    let history = emu.pin_log().read().unwrap();
    let ons: Vec<usize> = history
        .events
        .iter()
        .filter(|e| e.on)
        .map(|e| e.led)
        .collect();
    assert_eq!(ons, (0..10).collect::<Vec<_>>());
    assert!(history.lit_now().is_empty());

    // `on N` holds the LED with keepalives past the firmware's 3 s timeout... here briefly.
    json(&psscan(&[
        "lights", "--port", &pty, "on", "6", "--for-s", "0.3", "--json",
    ]));
    let history = emu.pin_log().read().unwrap();
    assert!(history.events.iter().any(|e| e.led == 6 && e.on));
    assert!(history.lit_now().is_empty());

    let bad = psscan(&["lights", "--port", &pty, "on", "12"]);
    assert_eq!(bad.status.code(), Some(1));
    assert!(
        stderr(&bad).contains("LED 12 does not exist"),
        "{}",
        stderr(&bad)
    );

    let gone = psscan(&["lights", "--port", "/dev/pts/999999", "identify"]);
    assert_eq!(gone.status.code(), Some(1));
    assert!(
        stderr(&gone).contains("/dev/pts/999999"),
        "{}",
        stderr(&gone)
    );
}

#[test]
fn a_failing_camera_command_is_named_and_leaves_the_leds_off() {
    let tmp = tempfile::tempdir().unwrap();
    let emu = emulator(tmp.path());
    let set = tmp.path().join("set");
    // Succeeds for the dark frame and L00 (two different RAW files), then reports a full card.
    let counter = tmp.path().join("count");
    for n in 0..2u16 {
        let (w, h) = (32, 24);
        let mosaic = psscan::raw::Mosaic {
            width: w,
            height: h,
            pattern: psscan::raw::Mosaic::parse_pattern("RGGB").unwrap(),
            black: [[600.0; 2]; 2],
            white: 15600.0,
            samples: vec![1000 + 100 * n; w * h],
        };
        let meta = psscan::raw::RawMeta {
            make: "psscan".into(),
            model: "test".into(),
            width: w,
            height: h,
            iso: Some(100),
            shutter_s: Some(0.1),
            aperture: Some(8.0),
        };
        let bytes = psscan::raw::encode_dng(
            &mosaic,
            &meta,
            14,
            [1.0; 3],
            psscan::raw::DngStorage::Lossless,
        )
        .unwrap();
        std::fs::write(tmp.path().join(format!("shot{n}.dng")), bytes).unwrap();
    }
    let template = format!(
        "cmd:sh -c 'n=$(cat {c} 2>/dev/null || echo 0); echo $((n+1)) > {c}; \
         if [ $n -ge 2 ]; then echo card full >&2; exit 5; fi; cp {d}/shot$n.dng \"$1\"' sh {{out}}",
        c = s(&counter),
        d = s(tmp.path())
    );
    let out = psscan(&[
        "capture",
        "--out",
        s(&set),
        "--port",
        emu.pty(),
        "--camera",
        &template,
        "--frame-ext",
        "nef",
        "--settle-ms",
        "5",
    ]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("frame L01 (LED 1)") && err.contains("card full"),
        "{err}"
    );
    assert!(err.contains("all LEDs are off"), "{err}");
    assert!(emu.pin_log().lit().unwrap().is_empty());
    let kept = CaptureSet::open(&set, None).unwrap();
    let files: Vec<&str> = kept
        .manifest
        .frames
        .iter()
        .map(|f| f.file.as_str())
        .collect();
    assert_eq!(files, ["dark.nef", "L00.nef"]);
    assert_eq!(kept.manifest.image.encoding, "raw");
}

#[test]
fn gphoto2_camera_without_hardware_gives_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let emu = emulator(tmp.path());
    let out = psscan(&[
        "capture",
        "--out",
        s(&tmp.path().join("set")),
        "--port",
        emu.pty(),
        "--camera",
        "gphoto2",
    ]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    if cfg!(feature = "gphoto2") {
        // libgphoto2 runs for real: on a machine without a camera (CI) the error is psscan's,
        // says no camera was found and carries libgphoto2's own text, not a bare code.
        assert!(err.contains("no camera found"), "{err}");
        assert!(err.contains("libgphoto2:"), "{err}");
    } else {
        assert!(err.contains("--features gphoto2"), "{err}");
    }
    assert!(emu.pin_log().lit().unwrap().is_empty());
}
