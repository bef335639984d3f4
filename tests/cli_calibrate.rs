//! `psscan calibrate` from the outside: the camera step over photographs (`--json`), the clear
//! error of a build without OpenCV, the interactive wizard driven for real in tmux with
//! send-keys, stopped half-way and resumed; the steps over files (table, graychart,
//! whitesheet) on synthetic targets written to files, checked against the known truth; the
//! bundle they assemble; and its citation by capture manifests and solve reports.

use std::path::{Path, PathBuf};
#[cfg(feature = "opencv")]
use std::process::Command;
use std::process::Output;

mod common;

use common::{psscan, s};
use psscan::calibration::graychart::{self, Shading};
use psscan::calibration::steps::WhiteSheetStep;
use psscan::plane::{Frames, SensorWindow};
use psscan::raw::{encode_dng, DngStorage, RawMeta};
use psscan::rig::ChartDescription;
use psscan::rig::Rig;
use psscan::synth::targets;
#[cfg(feature = "opencv")]
use std::time::{Duration, Instant};

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
    let history = psscan::sim::emulator::PinLog::new(path).read().unwrap();
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

fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "psscan failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn fails(out: &Output) -> String {
    assert_eq!(
        out.status.code(),
        Some(1),
        "expected a failure: {}",
        String::from_utf8_lossy(&out.stdout)
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn json(out: &Output) -> serde_json::Value {
    serde_json::from_str(&ok(out)).expect("JSON on stdout")
}

fn distance_mm(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt() * 1e3
}

/// Writes each light's frame as a linear EXR `Lkk.exr` in `dir`.
fn write_exr_frames(frames: &Frames, dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    for (k, f) in frames.lights.iter().enumerate() {
        psscan::io::write_exr(
            &dir.join(format!("L{k:02}.exr")),
            &[("R", &f.rgb.r), ("G", &f.rgb.g), ("B", &f.rgb.b)],
        )
        .unwrap();
    }
}

/// The white-sheet step through the CLI: returns its result and stdout.
fn whitesheet_cli(images: &Path, extra: &[&str], out: &Path) -> (WhiteSheetStep, String) {
    let mut args = vec![
        "calibrate",
        "whitesheet",
        "--images",
        s(images),
        "--out",
        s(out),
        "-q",
    ];
    args.extend_from_slice(extra);
    let stdout = ok(&psscan(&args));
    let text = std::fs::read_to_string(out).unwrap();
    (toml::from_str(&text).unwrap(), stdout)
}

/// Every fitted LED within 5 mm of the as-built rig (the figure), from hand
/// measurements off by up to 3 cm; returns the worst hand and fitted errors (mm).
fn check_leds(result: &WhiteSheetStep, truth: &Rig) -> (f64, f64) {
    let (mut hand, mut fitted) = (0.0f64, 0.0f64);
    for (led, t) in result.lights.leds.iter().zip(&truth.leds) {
        hand = hand.max(distance_mm(led.start_m, t.position_m));
        fitted = fitted.max(distance_mm(led.position_m, t.position_m));
    }
    assert!(result.lights.converged);
    assert!(hand > 25.0, "the hand measurements were off by {hand} mm");
    assert!(fitted < 5.0, "worst fitted LED {fitted} mm from the truth");
    (hand, fitted)
}

const CHART_WORLD: [f64; 4] = [-0.06, 0.06, -0.025, 0.025];
const CHART_VIEW: (usize, usize, f64) = (1024, 512, 2.0);

/// The gray chart under each LED of `rig` as DNG files `Lkk.dng` in `dir`; returns the
/// mosaics and the chart's rectangle as `X,Y,W,H`.
fn write_chart_dngs(
    rig: &Rig,
    chart: &ChartDescription,
    exposure: f64,
    dir: &Path,
) -> (Vec<psscan::raw::Mosaic>, String) {
    std::fs::create_dir_all(dir).unwrap();
    let (mosaics, rect) =
        targets::gray_chart_mosaics(rig, chart, CHART_WORLD, CHART_VIEW, exposure, 7);
    let meta = RawMeta {
        make: "psscan".into(),
        model: "synthetic camera".into(),
        width: CHART_VIEW.0,
        height: CHART_VIEW.1,
        iso: Some(100),
        shutter_s: Some(0.1),
        aperture: Some(8.0),
    };
    for (k, m) in mosaics.iter().enumerate() {
        let bytes = encode_dng(
            m,
            &meta,
            rig.sensor.bits,
            rig.sensor.channel_gain,
            DngStorage::Lossless,
        )
        .unwrap();
        std::fs::write(dir.join(format!("L{k:02}.dng")), bytes).unwrap();
    }
    let xywh = format!(
        "{},{},{},{}",
        rect.x0,
        rect.y0,
        rect.x1 - rect.x0,
        rect.y1 - rect.y0
    );
    (mosaics, xywh)
}

#[test]
fn graychart_cli_over_dng_files_gives_the_sensor_gains_linearity_and_clipped_patches() {
    let tmp = tempfile::tempdir().unwrap();
    let rig = Rig::default_rig();
    let chart = ChartDescription::munsell_12();
    let chart_file = tmp.path().join("chart.toml");
    std::fs::write(&chart_file, toml::to_string(&chart).unwrap()).unwrap();
    let images = tmp.path().join("chart");
    let (mosaics, rect) = write_chart_dngs(&rig, &chart, 1.0, &images);
    let out_file = tmp.path().join("graychart.toml");
    let base = [
        "calibrate",
        "graychart",
        "--images",
        s(&images),
        "--chart",
        s(&chart_file),
        "--rect",
        &rect,
        "--step",
        "2",
    ];
    // A capture set's all-off frame among the photographs is left out, as the white-sheet
    // step does: still one photograph per LED.
    std::fs::copy(images.join("L00.dng"), images.join("dark.dng")).unwrap();
    let mut args = base.to_vec();
    args.extend(["--out", s(&out_file), "--json", "-q"]);
    let v = json(&psscan(&args));
    assert!(
        v["dark_frame_left_out"]
            .as_str()
            .is_some_and(|p| p.ends_with("dark.dng")),
        "{v}"
    );
    // The same numbers as the library on the mosaics in memory: the DNGs are lossless.
    let window = SensorWindow::centred(4928, 3264, CHART_VIEW.0, CHART_VIEW.1, CHART_VIEW.2);
    let (_, rect_lib) = targets::gray_chart_mosaics(&rig, &chart, CHART_WORLD, CHART_VIEW, 1.0, 7);
    let shading = Shading { rig: &rig, window };
    let lib = graychart::calibrate(&mosaics, &chart, &rect_lib, Some(&shading)).unwrap();
    let g = rig.sensor.channel_gain;
    let expected = [g[1] / g[0], 1.0, g[1] / g[2]];
    let lights = v["lights"].as_array().unwrap();
    assert_eq!(lights.len(), rig.leds.len());
    for (k, light) in lights.iter().enumerate() {
        let wb: Vec<f64> = light["white_balance"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let slope = light["linearity"]["slope"].as_f64().unwrap();
        for c in 0..3 {
            // Each patch averages over a thousand samples per channel: gains to 0.5 %.
            assert!(
                (wb[c] / expected[c] - 1.0).abs() < 0.005,
                "light {k}: {wb:?}"
            );
            assert!((wb[c] - lib.lights[k].white_balance[c]).abs() < 1e-9);
        }
        // Linear sensor, exact shading: the slope is the LED's green power.
        assert!((slope / rig.led_rgb_power(k)[1] - 1.0).abs() < 0.01);
        assert!(light["linearity"]["r_squared"].as_f64().unwrap() > 0.9999);
        assert!(light["linearity"]["clipped_patches"]
            .as_array()
            .unwrap()
            .is_empty());
    }
    let written: psscan::calibration::graychart::ChartReport =
        toml::from_str(&std::fs::read_to_string(&out_file).unwrap()).unwrap();
    assert_eq!(written.lights.len(), rig.leds.len());

    // Without --rect the chart is found in the photographs: close to the true rectangle
    // (the search works on 2x2 CFA cells) and the same gains.
    let mut args = base.to_vec();
    args.truncate(6);
    args.extend(["--step", "2", "--json", "-q"]);
    let found = json(&psscan(&args));
    let r = &found["rect"];
    let given: Vec<f64> = rect.split(',').map(|x| x.parse().unwrap()).collect();
    let patch_w = given[2] / chart.cols as f64;
    println!("chart found at {r} (given {given:?}, patch width {patch_w:.1} px)");
    assert_eq!(r["found"], true);
    for (key, want) in ["x", "y", "width", "height"].iter().zip(&given) {
        // Within a tenth of a patch: the sampled centre half of each patch stays inside it.
        assert!(
            (r[key].as_f64().unwrap() - want).abs() < 0.1 * patch_w,
            "{key}: {r}"
        );
    }
    for (k, light) in found["lights"].as_array().unwrap().iter().enumerate() {
        for c in 0..3 {
            let wb = light["white_balance"][c].as_f64().unwrap();
            assert!((wb / expected[c] - 1.0).abs() < 0.005, "light {k}: {wb}");
        }
    }

    // Overexposed: the brightest patch clips under the overhead LEDs; flagged, left out.
    let bright = tmp.path().join("bright");
    let (_, rect) = write_chart_dngs(&rig, &chart, 1.8, &bright);
    let mut args = base.to_vec();
    args[3] = s(&bright);
    args[7] = &rect;
    let text = ok(&psscan(&args));
    println!("{text}");
    // Under the four overhead LEDs (6-9) the brightest patch (11) clips.
    for k in 6..10 {
        let line = text
            .lines()
            .find(|l| l.contains(&format!("light {k} (L{k:02}.dng)")))
            .unwrap();
        assert!(
            line.contains("CLIPPED patches [") && line.contains("11] (left out of the fit)"),
            "{line}"
        );
    }

    // Bad input, each named: a missing light, a malformed chart, a missing folder.
    std::fs::remove_file(bright.join("L09.dng")).unwrap();
    let err = fails(&psscan(&args));
    assert!(
        err.contains("9 gray-chart photographs") && err.contains("10 LEDs"),
        "{err}"
    );
    let bad_chart = tmp.path().join("bad-chart.toml");
    std::fs::write(
        &bad_chart,
        "name = \"x\"\nrows = 2\ncols = 6\nreflectance = [0.5]\n",
    )
    .unwrap();
    let mut args = base.to_vec();
    args[5] = s(&bad_chart);
    let err = fails(&psscan(&args));
    assert!(
        err.contains("bad-chart.toml") && err.contains("reflectance"),
        "{err}"
    );
    let mut args = base.to_vec();
    args[3] = "/nonexistent/psscan-chart";
    assert!(fails(&psscan(&args)).contains("/nonexistent/psscan-chart"));
}

/// The hand-measured rig with the as-built camera (the camera and table steps' result, which
/// need OpenCV), and the as-built rig.
fn rigs(dir: &Path) -> (Rig, Rig, PathBuf, PathBuf) {
    let hand = Rig::default_rig();
    let truth = targets::as_built(&hand, 0.03, 5);
    let mut start = hand.clone();
    start.camera = truth.camera.clone();
    let (start_file, truth_file) = (dir.join("rig.toml"), dir.join("truth.toml"));
    start.save(&start_file).unwrap();
    truth.save(&truth_file).unwrap();
    (start, truth, start_file, truth_file)
}

#[test]
fn whitesheet_bundle_and_the_citation_in_captures_and_solves() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let (_, truth, rig_file, truth_file) = rigs(t);
    let sheet = t.join("sheet");
    write_exr_frames(
        &targets::white_sheet_frames(&truth, 8.0, 0.9, 0.02, 1, 3),
        &sheet,
    );
    let ws_file = t.join("whitesheet.toml");
    let (result, stdout) = whitesheet_cli(&sheet, &["--rig", s(&rig_file)], &ws_file);
    println!("{stdout}");
    assert!(
        stdout.contains("iteration  1: largest LED move") && stdout.contains("converged after")
    );
    let (hand, fitted) = check_leds(&result, &truth);
    println!("LEDs: hand measurements off by up to {hand:.1} mm, fitted within {fitted:.2} mm");
    assert!(t.join("whitesheet-maps/L09_intensity.exr").is_file());

    // Wrong count of light images: named.
    let short = t.join("short");
    std::fs::create_dir_all(&short).unwrap();
    std::fs::copy(sheet.join("L00.exr"), short.join("L00.exr")).unwrap();
    let err = fails(&psscan(&[
        "calibrate",
        "whitesheet",
        "--images",
        s(&short),
        "--rig",
        s(&rig_file),
    ]));
    assert!(
        err.contains("1 white-sheet photographs (L00.exr)") && err.contains("10 LEDs"),
        "{err}"
    );

    // The bundle.
    let bundle = t.join("bundle");
    let bundle_args = [
        "calibrate",
        "bundle",
        "--rig",
        s(&rig_file),
        "--whitesheet",
        s(&ws_file),
        "--name",
        "cli-test",
        "--out",
        s(&bundle),
        "--json",
    ];
    let b = json(&psscan(&bundle_args));
    let id = b["id"].as_str().unwrap().to_string();
    let sha = b["sha256"].as_str().unwrap().to_string();
    assert!(
        id.starts_with("default/cli-test/") && id.ends_with(&sha[..12]),
        "{id}"
    );
    let read = psscan::calibration::bundle::read(&bundle).unwrap();
    assert_eq!(read.gains.as_ref().unwrap().len(), 10);
    assert_eq!(read.rig, result.rig);
    assert!(read.index.files.contains_key("maps/L09_intensity.exr"));
    assert!(fails(&psscan(&bundle_args)).contains("already exists"));

    // A capture with the bundle (LED firmware in its emulator, simulated camera) cites it.
    let capture = t.join("capture");
    ok(&psscan(&[
        "capture",
        "--out",
        s(&capture),
        "--firmware-sim",
        "--calibration",
        s(&bundle),
        "--settle-ms",
        "0",
        "--width",
        "64",
        "--height",
        "48",
        "--step",
        "64",
        "-q",
    ]));
    let manifest = std::fs::read_to_string(capture.join("manifest.toml")).unwrap();
    println!("{manifest}");
    assert!(manifest.contains(&format!("id = \"{id}\"")) && manifest.contains(&sha));
    assert_eq!(Rig::load(&capture.join("rig.toml")).unwrap(), read.rig);

    // A synthetic capture of the as-built rig, recorded as a capture with the bundle would be.
    let set = t.join("set");
    ok(&psscan(&[
        "synth",
        "--out",
        s(&set),
        "--rig",
        s(&truth_file),
        "--calibration",
        s(&bundle),
        "--width",
        "616",
        "--height",
        "408",
        "--step",
        "8",
        "-q",
    ]));
    // Solved with the bundle it cites (found from the manifest) and with the true rig.
    let solve = |out: &str, extra: &[&str]| {
        let mut args = vec!["solve", s(&set), "--out", out, "--no-png", "--json", "-q"];
        args.extend_from_slice(extra);
        psscan(&args)
    };
    let out = |n: &str| t.join(n).to_str().unwrap().to_string();
    let cited = json(&solve(&out("m-cited"), &[]));
    assert_eq!(cited["calibration"]["id"], id.as_str());
    assert_eq!(cited["calibration"]["sha256"], sha.as_str());
    assert_eq!(
        cited["calibration"]["path"],
        s(&bundle.canonicalize().unwrap())
    );
    assert!(cited.get("calibration_cited_by_set").is_none());
    let true_rig = json(&solve(&out("m-truth"), &["--rig", s(&truth_file)]));
    assert!(true_rig.get("calibration").is_none());
    assert_eq!(true_rig["calibration_cited_by_set"]["id"], id.as_str());
    let err_of = |v: &serde_json::Value| v["truth"]["normal_error_deg"]["mean"].as_f64().unwrap();
    let ratio = err_of(&cited) / err_of(&true_rig);
    println!(
        "mean angular error: calibrated bundle {:.6} deg, true rig {:.6} deg (ratio {ratio:.4})",
        err_of(&cited),
        err_of(&true_rig)
    );
    assert!(ratio <= 1.2, "calibrated / true = {ratio}");
    // The hand-measured rig, for scale: what the calibration is worth.
    let hand = json(&solve(&out("m-hand"), &["--rig", s(&rig_file)]));
    println!("hand-measured LEDs: {:.6} deg", err_of(&hand));
    // The human summary names the bundle.
    let text = ok(&psscan(&[
        "solve",
        s(&set),
        "--out",
        &out("m-human"),
        "--no-png",
        "-q",
    ]));
    println!("{text}");
    assert!(
        text.contains(&format!("calibration: bundle {id} (sha256 {sha})")),
        "{text}"
    );

    // Another bundle than the one cited: refused, unless the mismatch is allowed.
    let other = t.join("other");
    let printed = ok(&psscan(&[
        "calibrate",
        "bundle",
        "--rig",
        s(&rig_file),
        "--whitesheet",
        s(&ws_file),
        "--name",
        "other",
        "--out",
        s(&other),
        "-q",
    ]));
    println!("{printed}");
    let err = fails(&solve(&out("m-other"), &["--calibration", s(&other)]));
    assert!(
        err.contains(&format!("was captured with calibration bundle {id}"))
            && err.contains("default/other/")
            && err.contains("--allow-calibration-mismatch"),
        "{err}"
    );
    let allowed = json(&solve(
        &out("m-allowed"),
        &["--calibration", s(&other), "--allow-calibration-mismatch"],
    ));
    assert!(allowed["calibration"]["id"]
        .as_str()
        .unwrap()
        .starts_with("default/other/"));
    assert_eq!(allowed["calibration_cited_by_set"]["id"], id.as_str());

    // A bundle file changed since: refused, naming the file.
    let rig_in_bundle = bundle.join("rig.toml");
    let text = std::fs::read_to_string(&rig_in_bundle).unwrap();
    std::fs::write(&rig_in_bundle, text + "\n# edited\n").unwrap();
    for extra in [&[][..], &["--calibration", s(&bundle)][..]] {
        let err = fails(&solve(&out("m-changed"), extra));
        assert!(
            err.contains("rig.toml") && err.contains("changed since the bundle was written"),
            "{err}"
        );
    }
    // --no-calibration solves with the set's rig copy, and the report still says what the set
    // cites.
    let none = json(&solve(&out("m-none"), &["--no-calibration"]));
    assert!(none.get("calibration").is_none());
    assert_eq!(none["calibration_cited_by_set"]["id"], id.as_str());
}

/// Every step over files, as a user runs them: chessboard photographs -> `calibrate camera`,
/// the board on the table -> `calibrate table`, the white sheet -> `calibrate whitesheet` with
/// that camera and table, then `calibrate bundle`; the synthetic textile captured with the
/// bundle and solved. Checked against the as-built rig: pixel-to-world error under 1 mm,
/// LEDs within 5 mm, the solve's mean angular error within 1.2x that of the true rig.
#[cfg(feature = "opencv")]
#[test]
fn opencv_every_step_over_files_then_bundle_capture_and_solve() {
    use psscan::calibration::camera::CameraCalibration;
    use psscan::calibration::steps::{self, TableStep};
    use psscan::calibration::table;
    use psscan::rig::Board;
    use psscan::synth::targets::Chessboard;

    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let hand = Rig::default_rig();
    let truth = targets::as_built(&hand, 0.03, 5);
    let (hand_file, truth_file) = (t.join("rig.toml"), t.join("truth.toml"));
    hand.save(&hand_file).unwrap();
    truth.save(&truth_file).unwrap();
    let chess = Chessboard {
        board: Board::parse("9x6", 15.0).unwrap(),
        border_squares: 1.0,
    };
    // Chessboard views binned 4x (a preview stream), with one board half out of the frame
    // and one bent: both must be rejected.
    let views = t.join("views");
    std::fs::create_dir_all(&views).unwrap();
    let set = targets::chessboard_views(&truth, &chess, 4.0, 12, true, 21);
    for (name, image) in &set.images {
        image.save_png(&views.join(format!("{name}.png"))).unwrap();
    }
    let cam_file = t.join("camera.toml");
    let board = ["--board", "9x6", "--square-mm", "15"];
    let mut args = vec![
        "calibrate",
        "camera",
        "--images",
        s(&views),
        "--out",
        s(&cam_file),
        "-q",
    ];
    args.extend(board);
    println!("{}", ok(&psscan(&args)));
    let cam: CameraCalibration = steps::load_toml(&cam_file, "camera").unwrap();
    assert_eq!(cam.views_rejected, 2);

    // The table.
    let photo = t.join("table.png");
    targets::table_view(&truth, &chess, 4.0, 77)
        .save_png(&photo)
        .unwrap();
    let table_file = t.join("table.toml");
    let mut args = vec![
        "calibrate",
        "table",
        "--image",
        s(&photo),
        "--camera",
        s(&cam_file),
        "--out",
        s(&table_file),
    ];
    args.extend(board);
    let text = ok(&psscan(&args));
    println!("{text}");
    assert!(text.contains("pixel-to-world check over 54 corners"));
    let table_step: TableStep = steps::load_toml(&table_file, "table").unwrap();
    let calibrated = steps::compose_rig(&hand, Some(&cam), Some(&table_step.pose)).unwrap();
    let (w, h) = (truth.camera.width as usize, truth.camera.height as usize);
    let (worst, mean) = table::pixel_to_world_error(
        &truth.camera,
        &calibrated.camera,
        0.0,
        SensorWindow::FULL,
        (w, h),
        41,
    );
    println!(
        "pixel-to-world error against the as-built camera over the whole field: max {:.3} mm, mean {:.3} mm; the table step's own check: max {:.3} mm over the board",
        worst * 1e3,
        mean * 1e3,
        table_step.check.max_mm
    );
    assert!(worst < 1e-3, "max pixel-to-world error {} mm", worst * 1e3);
    // The table step's own check sees the same camera at the board's corners.
    assert!(table_step.check.max_mm < 1.0);

    // Board not found, and a camera file that is not one: named.
    let mut args = vec![
        "calibrate",
        "table",
        "--image",
        s(&photo),
        "--camera",
        s(&cam_file),
    ];
    args.extend(["--board", "7x5", "--square-mm", "15"]);
    let err = fails(&psscan(&args));
    assert!(
        err.contains("table.png") && err.contains("7x5 board was not found"),
        "{err}"
    );
    let mut args = vec![
        "calibrate",
        "table",
        "--image",
        s(&photo),
        "--camera",
        s(&hand_file),
    ];
    args.extend(board);
    let err = fails(&psscan(&args));
    assert!(
        err.contains("rig.toml") && err.contains("calibrate camera --out"),
        "{err}"
    );

    // The white sheet with that camera and table, from the hand-measured LEDs.
    let sheet = t.join("sheet");
    write_exr_frames(
        &targets::white_sheet_frames(&truth, 8.0, 0.9, 0.02, 1, 31),
        &sheet,
    );
    let ws_file = t.join("whitesheet.toml");
    let rig_args = [
        "--rig",
        s(&hand_file),
        "--camera",
        s(&cam_file),
        "--table",
        s(&table_file),
    ];
    let (result, stdout) = whitesheet_cli(&sheet, &rig_args, &ws_file);
    println!("{stdout}");
    let (hand_mm, fitted_mm) = check_leds(&result, &truth);
    println!(
        "LEDs: hand measurements off by up to {hand_mm:.1} mm, fitted within {fitted_mm:.2} mm"
    );

    // The bundle: everything together.
    let bundle = t.join("bundle");
    let b = json(&psscan(&[
        "calibrate",
        "bundle",
        "--rig",
        s(&hand_file),
        "--camera",
        s(&cam_file),
        "--table",
        s(&table_file),
        "--whitesheet",
        s(&ws_file),
        "--name",
        "e2e",
        "--out",
        s(&bundle),
        "--json",
    ]));
    let id = b["id"].as_str().unwrap().to_string();
    let read = psscan::calibration::bundle::read(&bundle).unwrap();
    assert!(read.calibration.camera.is_some() && read.calibration.table.is_some());
    assert_eq!(read.rig.camera, calibrated.camera);
    // A white sheet fitted without this camera does not go with it. With the hand-measured
    // camera the fit itself may move LEDs beyond the rig's tolerance; then the step rejects
    // it (exit 1) and still writes it, marked rejected, for the record.
    let plain = psscan(&[
        "calibrate",
        "whitesheet",
        "--images",
        s(&sheet),
        "--out",
        s(&t.join("plain.toml")),
        "-q",
        "--rig",
        s(&hand_file),
    ]);
    assert!(plain.status.code() == Some(0) || plain.status.code() == Some(1));
    assert!(t.join("plain.toml").is_file());
    let err = fails(&psscan(&[
        "calibrate",
        "bundle",
        "--camera",
        s(&cam_file),
        "--table",
        s(&table_file),
        "--whitesheet",
        s(&t.join("plain.toml")),
        "--out",
        s(&t.join("mixed")),
    ]));
    assert!(
        err.contains("plain.toml") && (err.contains("another camera") || err.contains("rejected")),
        "{err}"
    );

    // The textile over the whole field (every 8th sensor pixel: the edges are where wrong
    // light positions show), captured as with the bundle, solved with it and with the truth.
    let set = t.join("set");
    ok(&psscan(&[
        "synth",
        "--out",
        s(&set),
        "--rig",
        s(&truth_file),
        "--calibration",
        s(&bundle),
        "--width",
        "616",
        "--height",
        "408",
        "--step",
        "8",
        "-q",
    ]));
    let solve = |out: &str, extra: &[&str]| {
        let mut args = vec!["solve", s(&set), "--out", out, "--no-png", "--json", "-q"];
        args.extend_from_slice(extra);
        json(&psscan(&args))
    };
    let out = |n: &str| t.join(n).to_str().unwrap().to_string();
    let cited = solve(&out("m-cited"), &[]);
    assert_eq!(cited["calibration"]["id"], id.as_str());
    let with_truth = solve(&out("m-truth"), &["--rig", s(&truth_file)]);
    let with_hand = solve(&out("m-hand"), &["--rig", s(&hand_file)]);
    let err_of = |v: &serde_json::Value| v["truth"]["normal_error_deg"]["mean"].as_f64().unwrap();
    let ratio = err_of(&cited) / err_of(&with_truth);
    println!(
        "mean angular error: bundle {:.4} deg, true rig {:.4} deg (ratio {ratio:.3}), hand-measured rig {:.4} deg",
        err_of(&cited),
        err_of(&with_truth),
        err_of(&with_hand)
    );
    assert!(ratio <= 1.2, "calibrated / true = {ratio}");
}
