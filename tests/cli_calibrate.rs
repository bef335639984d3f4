//! `psscan calibrate` from the outside: the camera step over photographs (`--json`), the clear
//! error of a build without OpenCV, and the interactive wizard driven for real in tmux with
//! send-keys, stopped half-way and resumed.

#[cfg(feature = "opencv")]
use std::path::Path;
use std::process::{Command, Output};
#[cfg(feature = "opencv")]
use std::time::{Duration, Instant};

fn psscan(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_psscan"))
        .args(args)
        .output()
        .expect("psscan runs")
}

#[cfg(not(feature = "opencv"))]
#[test]
fn calibrate_camera_without_opencv_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    psscan::plane::GrayImage {
        width: 8,
        height: 8,
        data: vec![0; 64],
    }
    .save_png(&tmp.path().join("a.png"))
    .unwrap();
    let out = psscan(&[
        "calibrate",
        "camera",
        "--images",
        tmp.path().to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("built without OpenCV") && err.contains("--features opencv"),
        "{err}"
    );
}

#[test]
fn calibrate_camera_names_a_missing_folder() {
    let out = psscan(&[
        "calibrate",
        "camera",
        "--images",
        "/nonexistent/psscan-views",
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/psscan-views"));
}

#[cfg(feature = "opencv")]
#[test]
fn opencv_calibrate_camera_cli_json_on_real_photographs() {
    let tmp = tempfile::tempdir().unwrap();
    let data = Path::new("/usr/share/doc/opencv-doc/examples/data");
    for i in [1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14] {
        let name = format!("left{i:02}.jpg");
        std::fs::copy(data.join(&name), tmp.path().join(&name))
            .expect("opencv-doc's sample photographs");
    }
    let out = psscan(&[
        "calibrate",
        "camera",
        "--images",
        tmp.path().to_str().unwrap(),
        "--board",
        "9x6",
        "--square-mm",
        "25",
        "--fix-aspect-ratio",
        "--json",
        "-q",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let k = v["camera_matrix"].as_array().unwrap();
    assert_eq!(k.len(), 3);
    assert_eq!(k[0][0], k[1][1], "fixed aspect ratio");
    assert_eq!(v["distortion"].as_array().unwrap().len(), 5);
    assert!(v["rms_reprojection_px"].as_f64().unwrap() < 0.5);
    assert_eq!(
        v["views_used"].as_u64().unwrap() + v["views_rejected"].as_u64().unwrap(),
        13
    );
}

#[cfg(feature = "opencv")]
struct Tmux {
    /// A private tmux server (`-L`), so the test touches no one else's sessions.
    socket: String,
    session: String,
}

#[cfg(feature = "opencv")]
impl Tmux {
    fn start(socket: &str, session: &str, command: &str) -> Tmux {
        let status = Command::new("tmux")
            .args([
                "-L",
                socket,
                "new-session",
                "-d",
                "-s",
                session,
                "-x",
                "200",
                "-y",
                "50",
                command,
            ])
            .status()
            .expect("tmux is installed (.ci/install-deps)");
        assert!(status.success());
        Tmux {
            socket: socket.into(),
            session: session.into(),
        }
    }

    fn screen(&self) -> String {
        let out = Command::new("tmux")
            .args([
                "-L",
                &self.socket,
                "capture-pane",
                "-p",
                "-J",
                "-S",
                "-10000",
                "-t",
                &self.session,
            ])
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    fn keys(&self, keys: &[&str]) {
        let mut args = vec!["-L", &self.socket, "send-keys", "-t", &self.session];
        args.extend_from_slice(keys);
        assert!(Command::new("tmux").args(&args).status().unwrap().success());
    }

    /// Answers prompts one at a time until `until` appears on the screen; `limit` prompts at
    /// most (then returns with the prompt waiting).
    fn answer_until(&self, until: &str, limit: usize, timeout: Duration) -> String {
        let start = Instant::now();
        let mut answered = 0;
        loop {
            let screen = self.screen();
            if screen.contains(until) || start.elapsed() > timeout {
                return screen;
            }
            let prompts = screen.matches("[Enter] take it").count();
            if prompts > answered && answered < limit && screen.trim_end().ends_with('>') {
                self.keys(&["Enter"]);
                answered += 1;
            } else if answered >= limit && prompts > answered {
                return screen;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

#[cfg(feature = "opencv")]
impl Drop for Tmux {
    fn drop(&mut self) {
        let _ = Command::new("tmux")
            .args(["-L", &self.socket, "kill-session", "-t", &self.session])
            .status();
    }
}

#[cfg(feature = "opencv")]
#[test]
fn opencv_wizard_in_tmux_stops_and_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("bundle");
    let command = format!(
        "{} calibrate --out {} -q; echo WIZARD-EXIT-$?; sleep 60",
        env!("CARGO_BIN_EXE_psscan"),
        dir.display()
    );
    let socket = format!("psscan-wizard-{}", std::process::id());
    let first = Tmux::start(&socket, "first", &command);
    // Five photographs (the simulated operator's fifth has the board half out of the frame),
    // then q at the sixth prompt.
    let screen = first.answer_until("never", 5, Duration::from_secs(120));
    first.keys(&["q", "Enter"]);
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut screen_after = screen.clone();
    while !screen_after.contains("WIZARD-EXIT-") && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(200));
        screen_after = first.screen();
    }
    println!("--- first session ---\n{screen_after}");
    assert!(screen_after.contains("view-000 accepted"));
    assert!(screen_after.contains("view-004 REJECTED: the whole board was not found"));
    assert!(screen_after.contains("the board has not been at:"));
    assert!(
        screen_after.contains("stopped; the state is saved")
            && screen_after.contains("WIZARD-EXIT-0")
    );
    let state = std::fs::read_to_string(dir.join("wizard-state.toml")).unwrap();
    assert!(
        state.contains("attempts = 5") && state.contains("step = \"camera-views\""),
        "{state}"
    );

    // The same command resumes at the sixth photograph and goes to the end.
    let second = Tmux::start(&socket, "second", &command);
    let screen = second.answer_until("WIZARD-EXIT-", 100, Duration::from_secs(400));
    println!("--- second session ---\n{screen}");
    assert!(screen.contains("resuming") && screen.contains("4 of 12 chessboard views accepted"));
    assert!(screen.contains("view-005") && !screen.contains("view-000 "));
    assert!(screen.contains("LED fit iteration 1") && screen.contains("FLAT"));
    assert!(screen.contains("WIZARD-EXIT-0"));
    let bundle = psscan::calibration::bundle::read(&dir).unwrap();
    let flat = bundle.calibration.flatness.unwrap();
    assert!(flat.flat && flat.max_deg <= 0.5);
    assert!(bundle.index.id.starts_with("default/wizard/"));
    drop(second);
    drop(first);
}

/// The truth of the simulated rig the wizard calibrates (`--seed` 5, the default): LED `k`'s
/// distance from where the bundle's rig puts it, metres.
#[cfg(feature = "opencv")]
fn led_errors_m(bundle: &psscan::calibration::bundle::Bundle) -> Vec<f64> {
    let truth = psscan::synth::targets::as_built(&psscan::rig::Rig::default_rig(), 0.03, 5);
    bundle
        .rig
        .leds
        .iter()
        .zip(&truth.leds)
        .map(|(got, want)| {
            (0..3)
                .map(|i| (got.position_m[i] - want.position_m[i]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect()
}

/// What the firmware emulator's pin log says: the most LEDs ever on together, and those on
/// at its end.
#[cfg(feature = "opencv")]
fn pins(path: &Path) -> (usize, Vec<usize>) {
    let history = psscan::capture::emulator::PinLog::new(path).read().unwrap();
    (history.max_lit_together(), history.lit_now())
}

#[cfg(feature = "opencv")]
#[test]
fn opencv_wizard_through_the_firmware_emulator_json() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("bundle");
    let pin_log = tmp.path().join("pins.log");
    let out = psscan(&[
        "calibrate",
        "--source",
        "capture",
        "--firmware-sim",
        "--yes",
        "--json",
        "-q",
        "--settle-ms",
        "20",
        "--out",
        dir.to_str().unwrap(),
        "--pin-log",
        pin_log.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let json_start = stdout.find("{\n").expect("the JSON summary");
    let v: serde_json::Value = serde_json::from_str(&stdout[json_start..]).unwrap();
    println!("{}", &stdout[..json_start]);
    // The pin log: never two LEDs at once, all off at the end (the JSON says the same).
    assert_eq!(pins(&pin_log), (1, vec![]));
    assert_eq!(v["firmware_pin_log"]["max_leds_on_together"], 1);
    assert_eq!(v["firmware_pin_log"]["lit_at_end"], serde_json::json!([]));

    let bundle = psscan::calibration::bundle::read(&dir).unwrap();
    assert_eq!(v["id"].as_str().unwrap(), bundle.index.id);
    // The figures: the white sheet re-solved flat (every normal within 0.5 deg), the
    // LEDs within 5 mm of where the simulated rig has them (the hand rig is up to 3 cm off).
    let flat = bundle.calibration.flatness.clone().unwrap();
    println!(
        "flatness: max {:.3} deg over {} normals, {} exposures",
        flat.max_deg, flat.pixels, flat.exposures
    );
    assert!(flat.flat && flat.max_deg <= 0.5);
    let errors = led_errors_m(&bundle);
    println!(
        "LED position errors (mm): {:.2?}",
        errors.iter().map(|e| e * 1e3).collect::<Vec<_>>()
    );
    assert!(errors.iter().all(|&e| e < 5e-3));
    // The gray chart: its gains are the sensor's inverse channel gains (the LEDs are white);
    // each patch averages a few hundred green samples, so 0.5 % holds.
    let chart = bundle.calibration.gray_chart.clone().unwrap();
    assert_eq!(chart.lights.len(), 10);
    let g = psscan::rig::Rig::default_rig().sensor.channel_gain;
    for light in &chart.lights {
        let want = [g[1] / g[0], 1.0, g[1] / g[2]];
        for (got, want) in light.white_balance.iter().zip(want) {
            assert!((got / want - 1.0).abs() < 0.005, "{got} vs {want}");
        }
        assert!(light.linearity.clipped_patches.is_empty());
    }
    assert_eq!(v["gray_chart"]["accepted"], true);
    // The photographs went through the sequencer: capture sets with manifests in the bundle.
    for set in ["graychart", "fit-00", "check-00"] {
        let set = psscan::capture::CaptureSet::open(&dir.join("captures").join(set), None).unwrap();
        assert_eq!(set.manifest.frames.len(), 11, "dark + 10 LEDs");
    }
}

#[cfg(feature = "opencv")]
fn frames_of(set: &Path) -> Vec<(String, String)> {
    match psscan::capture::CaptureSet::open(set, None) {
        Ok(s) => s
            .manifest
            .frames
            .iter()
            .map(|f| (f.file.clone(), f.sha256.clone()))
            .collect(),
        Err(_) => Vec::new(),
    }
}

#[cfg(feature = "opencv")]
#[test]
fn opencv_wizard_capture_in_tmux_ctrl_c_in_the_white_sheet_then_resume() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("bundle");
    let pin_log = tmp.path().join("pins.log");
    let command = format!(
        "{} calibrate --source capture --firmware-sim --settle-ms 100 --out {} --pin-log {} -q; \
         echo WIZARD-EXIT-$?; sleep 60",
        env!("CARGO_BIN_EXE_psscan"),
        dir.display(),
        pin_log.display()
    );
    let socket = format!("psscan-wizard-capture-{}", std::process::id());
    let first = Tmux::start(&socket, "first", &command);
    // Every prompt answered up to the white sheet's.
    let screen = first.answer_until("step 4/5 white sheet", 100, Duration::from_secs(300));
    assert!(screen.contains("step 4/5 white sheet"), "{screen}");
    first.keys(&["Enter"]);
    // Ctrl-C on the terminal once the sequencer has kept a few of the sheet's frames.
    let set = dir.join("captures/fit-00");
    let deadline = Instant::now() + Duration::from_secs(120);
    while frames_of(&set).len() < 4 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    first.keys(&["C-c"]);
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut screen = first.screen();
    while !screen.contains("WIZARD-EXIT-") && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(200));
        screen = first.screen();
    }
    println!("--- first session ---\n{screen}");
    assert!(screen.contains("lit by LED 6, the one nearest the camera axis"));
    assert!(screen.contains("view-004 REJECTED: the whole board was not found"));
    assert!(screen.contains("gray chart accepted"));
    assert!(
        screen.contains("all LEDs are off") && screen.contains("stopped; the state is saved"),
        "{screen}"
    );
    assert!(screen.contains("WIZARD-EXIT-130"), "{screen}");
    let (most, lit) = pins(&pin_log);
    assert_eq!((most, lit), (1, vec![]), "LEDs off after Ctrl-C");
    let kept = frames_of(&set);
    assert!(kept.len() >= 4 && kept.len() < 11, "{kept:?}");
    let state = std::fs::read_to_string(dir.join("wizard-state.toml")).unwrap();
    assert!(state.contains("step = \"white-sheet\""), "{state}");

    // The same command resumes at the white sheet, keeps its frames and goes to the end.
    let second = Tmux::start(&socket, "second", &command);
    let screen = second.answer_until("WIZARD-EXIT-", 100, Duration::from_secs(400));
    println!("--- second session ---\n{screen}");
    assert!(screen.contains("resuming") && screen.contains("at step WhiteSheet"));
    assert!(!screen.contains("step 1/5") && !screen.contains("step 3/5"));
    assert!(screen.contains("LED fit iteration 1") && screen.contains("FLAT"));
    assert!(screen.contains("at most 1 LED on at once; at the end []"));
    assert!(screen.contains("WIZARD-EXIT-0"));
    let after = frames_of(&set);
    assert_eq!(after.len(), 11);
    for frame in &kept {
        assert!(after.contains(frame), "{frame:?} was kept, not re-shot");
    }
    assert_eq!(pins(&pin_log), (1, vec![]));
    let bundle = psscan::calibration::bundle::read(&dir).unwrap();
    assert!(bundle.calibration.flatness.as_ref().unwrap().flat);
    assert!(led_errors_m(&bundle).iter().all(|&e| e < 5e-3));
    drop(second);
    drop(first);
}

#[test]
fn the_wizard_asks_for_source_capture_before_driving_hardware() {
    let tmp = tempfile::tempdir().unwrap();
    let out = psscan(&[
        "calibrate",
        "--firmware-sim",
        "--yes",
        "--out",
        tmp.path().join("b").to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("add --source capture"), "{err}");
}

/// The capture source with a tethered camera, on this machine (no camera attached, or no
/// libgphoto2 in the build): a clear error naming what to do, after the LEDs were reached.
#[test]
fn gphoto_wizard_capture_without_a_camera_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let out = psscan(&[
        "calibrate",
        "--source",
        "capture",
        "--firmware-sim",
        "--camera",
        "gphoto2",
        "--yes",
        "--out",
        tmp.path().join("b").to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    println!("{err}");
    if cfg!(feature = "gphoto2") {
        assert!(
            err.contains("no camera found") || err.contains("cannot open a camera"),
            "{err}"
        );
    } else {
        assert!(
            err.contains("built without libgphoto2") && err.contains("--features gphoto2"),
            "{err}"
        );
    }
}
