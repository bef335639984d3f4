//! `psscan capture`, `psscan lights ...` and the firmware-emulator demo: argument parsing,
//! choosing the controller and camera, Ctrl-C, summaries. The work is the library's.

use std::path::{Path, PathBuf};
use std::time::Duration;

use clap::{Args, Subcommand};
use psscan::capture::camera::{self, Camera, CameraSpec};
use psscan::capture::lights::{
    describe_on, list_ports, resolve_port, test_leds, LedCheck, LedTest, SerialLights,
    SerialOptions, SharedLights,
};
use psscan::capture::{
    run_capture, CaptureOptions, CaptureReport, CaptureSet, FrameStatus, Interrupt,
};
use psscan::sim::emulated::{capture_synthetic, EmulatedController, FirmwareSimDemoSummary};
use serde::Serialize;

use super::progress::Bars;
use super::{load_rig, print_json, SceneArgs};

/// The stop token of a command that stops on its own: the first SIGINT or SIGTERM asks the
/// library to stop (the LED keepalive thread switches the LEDs off at once); a second one
/// exits on the spot (see `signals`).
pub fn interrupt_on_ctrl_c() -> anyhow::Result<Interrupt> {
    Ok(super::signals::cooperative())
}

/// How to reach the LED controller (shared by `capture` and `lights`).
#[derive(Args, Clone)]
pub struct PortArgs {
    /// Serial port of the LED controller, or `auto` (the one Arduino plugged in).
    // `global`: `psscan lights identify --port X` works as well as `psscan lights --port X
    // identify`.
    #[arg(long, default_value = "auto", global = true)]
    pub port: String,
    /// Run the LED firmware in its emulator (firmware/build/psscan-avr-sim) instead of a board.
    #[arg(long, conflicts_with = "port", global = true)]
    pub firmware_sim: bool,
    /// How long to wait for the board's READY banner after opening the port (default: 2500
    /// on a serial device, 0 on a pseudo-terminal).
    #[arg(long, global = true)]
    ready_wait_ms: Option<u64>,
}

impl PortArgs {
    /// The camera named on the command line, or the default for this port: the simulated
    /// camera with the firmware emulator, the tethered one on hardware.
    pub(super) fn camera_or_default(&self, camera: &Option<String>) -> String {
        camera
            .clone()
            .unwrap_or_else(|| if self.firmware_sim { "sim" } else { "gphoto2" }.to_string())
    }
}

impl PortArgs {
    fn serial_options(&self) -> SerialOptions {
        SerialOptions {
            ready_wait: self.ready_wait_ms.map(Duration::from_millis),
            ..SerialOptions::default()
        }
    }
}

/// An open controller, and the emulator behind it when there is one.
pub(super) struct Controller {
    pub lights: SharedLights,
    pub emulated: Option<EmulatedController>,
    _scratch: Option<ScratchFile>,
}

/// A pin log nobody asked to keep: removed when the controller closes.
struct ScratchFile(PathBuf);

impl Drop for ScratchFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// A port that could not be opened because it is not there: where to find the ports.
fn port_hint(e: psscan::Error) -> anyhow::Error {
    use psscan::error::{LinkError, PortProblem};
    let missing = matches!(
        &e,
        psscan::Error::Link {
            source: LinkError::Unopened {
                problem: PortProblem::NoDevice | PortProblem::NotFound,
                ..
            },
            ..
        }
    );
    let text = format!("{e}; `psscan lights ports` lists the ports");
    let e = anyhow::Error::from(e);
    if missing {
        e.context(text)
    } else {
        e
    }
}

impl Controller {
    /// Opens the controller. With `--firmware-sim` the emulator's pin log goes to `pin_log`
    /// when given, else to a scratch folder.
    pub(super) fn open(args: &PortArgs, pin_log: Option<&Path>) -> anyhow::Result<Controller> {
        if args.firmware_sim {
            let (scratch, path) = match pin_log {
                Some(p) => (None, p.to_path_buf()),
                None => {
                    let path = std::env::temp_dir()
                        .join(format!("psscan-{}-pins.log", std::process::id()));
                    (Some(ScratchFile(path.clone())), path)
                }
            };
            let emulated = EmulatedController::start(&path, args.serial_options())?;
            return Ok(Controller {
                lights: emulated.lights.clone(),
                emulated: Some(emulated),
                _scratch: scratch,
            });
        }
        let port = resolve_port(&args.port)?;
        let serial = SerialLights::open(&port, args.serial_options()).map_err(port_hint)?;
        Ok(Controller {
            lights: SharedLights::new(Box::new(serial)),
            emulated: None,
            _scratch: None,
        })
    }
}

#[derive(Args)]
pub struct CaptureArgs {
    /// Folder of the capture set (e.g. captures/NAME).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    port: PortArgs,
    /// Camera: `gphoto2` (tethered, needs the gphoto2 build feature), `sim` (renders the
    /// synthetic textile under whatever LEDs are on), or `cmd:TEMPLATE` (runs TEMPLATE with
    /// {out} replaced by the file to write, e.g.
    /// `cmd:gphoto2 --capture-image-and-download --filename {out}`). Default: gphoto2, or
    /// sim with --firmware-sim.
    #[arg(long)]
    camera: Option<String>,
    /// Complete an interrupted set: shoot only missing or damaged frames.
    #[arg(long)]
    resume: bool,
    /// Start over, replacing the set in the folder.
    #[arg(long, conflicts_with = "resume")]
    force: bool,
    /// Wait after switching an LED before firing (LED warm-up), ms.
    #[arg(long, default_value_t = 250)]
    settle_ms: u64,
    /// Host-silence timeout to set on the controller, ms (default: the firmware's, 3000).
    #[arg(long)]
    light_timeout_ms: Option<u32>,
    /// Longest one shot (exposure + download) may take with gphoto2 or a command camera, s.
    #[arg(long, default_value_t = 60.0)]
    shot_timeout_s: f64,
    /// File extension for frames from a command camera (default: png for PNG output, else raw).
    #[arg(long)]
    frame_ext: Option<String>,
    /// Rig description for a new set (default: the embedded default rig; a resumed set uses
    /// its own copy).
    #[arg(long, conflicts_with = "calibration")]
    rig: Option<PathBuf>,
    /// Calibration bundle folder for a new set: its calibrated rig is the set's rig, and the
    /// manifest cites the bundle (id, checksum, path), which solves then use and check.
    #[arg(long, value_name = "BUNDLE_DIR")]
    calibration: Option<PathBuf>,
    /// Simulated camera: read the lit LEDs from this emulator pin log (an emulator started
    /// by hand); with --firmware-sim, where the emulator writes its pin log.
    #[arg(long)]
    pin_log: Option<PathBuf>,
    #[command(flatten)]
    scene: SceneArgs,
}

pub fn capture(args: &CaptureArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let interrupt = interrupt_on_ctrl_c()?;
    // The set may not be written into or over the rig file or bundle it is shot with (the
    // rest of the rule is applied where the set is opened).
    let read: Vec<&Path> = args
        .rig
        .iter()
        .chain(&args.calibration)
        .map(PathBuf::as_path)
        .collect();
    psscan::fsutil::check_outside_inputs(&args.out, &read)?;
    let resuming = args.resume && args.out.join("manifest.toml").is_file();
    let bundle = match &args.calibration {
        Some(dir) if !resuming => Some(psscan::calibration::bundle::read(dir)?),
        _ => None,
    };
    let rig = if resuming {
        CaptureSet::open(&args.out, None)?.rig
    } else if let Some(b) = &bundle {
        b.rig.clone()
    } else {
        load_rig(&args.rig)?
    };
    let controller = Controller::open(&args.port, args.pin_log.as_deref())?;
    let options = CaptureOptions {
        settle: Duration::from_millis(args.settle_ms),
        resume: args.resume,
        force: args.force,
        light_timeout_ms: args.light_timeout_ms,
        synthetic: None,
        calibration: bundle.as_ref().map(|b| b.citation()),
    };
    let shot_timeout = Duration::from_secs_f64(args.shot_timeout_s.max(0.1));
    let camera = args.port.camera_or_default(&args.camera);
    let report = if camera == "sim" {
        let source = psscan::sim::lit_source(
            controller.emulated.as_ref(),
            args.pin_log.as_deref(),
            &controller.lights,
        );
        capture_synthetic(
            &args.out,
            &rig,
            &args.scene.spec(),
            &controller.lights,
            source,
            &options,
            &interrupt,
            bars,
        )?
    } else {
        let mut camera = open_camera(&camera, args.frame_ext.as_deref(), shot_timeout)?;
        run_capture(
            &args.out,
            &rig,
            &controller.lights,
            camera.as_mut(),
            &options,
            &interrupt,
            bars,
        )?
    };
    if json {
        print_json(&report);
    } else {
        print_capture(&report);
    }
    Ok(())
}

/// Opens the camera `--camera` names (not `sim`), turning the library's errors into the
/// flag's hints.
pub(super) fn open_camera(
    spec: &str,
    frame_ext: Option<&str>,
    shot_timeout: Duration,
) -> anyhow::Result<Box<dyn Camera>> {
    let spec = CameraSpec::parse(spec).map_err(|e| anyhow::anyhow!("--{e}"))?;
    match camera::open_camera(&spec, frame_ext, shot_timeout) {
        Err(psscan::Error::Unsupported(m)) if spec == CameraSpec::Gphoto2 => {
            Err(psscan::Error::Unsupported(format!(
                "--camera gphoto2: {m}, or use --camera 'cmd:gphoto2 \
                 --capture-image-and-download --filename {{out}}'"
            ))
            .into())
        }
        other => Ok(other?),
    }
}

fn print_capture(r: &CaptureReport) {
    println!(
        "captured {}: {} frames shot, {} kept from before ({} + {})",
        r.dir.display(),
        r.shot,
        r.kept,
        r.controller,
        r.camera
    );
    println!(
        "  firmware      {} fw={} proto={} ({} LEDs)",
        r.firmware.name, r.firmware.firmware_version, r.firmware.protocol, r.firmware.leds
    );
    for d in &r.dropped {
        println!("  re-shot       {} ({})", d.file, d.reason);
    }
    for f in &r.frames {
        let status = match f.status {
            FrameStatus::Shot => "shot",
            FrameStatus::Kept => "kept",
        };
        let lit = match &f.lit_at_fire {
            Some(lit) => format!("  (camera saw {})", lit_list(lit)),
            None => String::new(),
        };
        println!("  {:<12} {status}  sha256 {}{lit}", f.file, &f.sha256[..16]);
    }
    println!(
        "  time          {:.1} s, {} keepalive pings",
        r.timings_s.get("total").copied().unwrap_or(0.0),
        r.keepalive_pings
    );
}

#[derive(Args)]
pub struct LightsArgs {
    #[command(flatten)]
    port: PortArgs,
    #[command(subcommand)]
    command: LightsCommand,
}

#[derive(Subcommand)]
enum LightsCommand {
    /// List serial ports, marking Arduino boards.
    Ports,
    /// Ask the controller who it is (firmware, protocol, LED count) and its state.
    Identify,
    /// Light each LED in turn, checking the controller's state each time.
    Test {
        /// How long each LED stays on, ms.
        #[arg(long, default_value_t = 500)]
        dwell_ms: u64,
    },
    /// Light LED N (all others off) and hold it until Ctrl-C (or --for-s).
    On {
        led: usize,
        /// Hold for this many seconds, then switch off and exit.
        #[arg(long)]
        for_s: Option<f64>,
    },
    /// Switch all LEDs off.
    Off,
}

pub fn lights(args: &LightsArgs, json: bool) -> anyhow::Result<()> {
    if let LightsCommand::Ports = args.command {
        let ports = list_ports()?;
        if json {
            print_json(&ports);
        } else if ports.is_empty() {
            println!("no serial ports found");
        } else {
            for p in &ports {
                let ids = match (p.vid, p.pid) {
                    (Some(v), Some(d)) => format!("{v:04x}:{d:04x}"),
                    _ => "-".into(),
                };
                let mark = if p.arduino_rank.is_some() { "*" } else { " " };
                println!(
                    "{mark} {:<16} {:<4} {ids:<9} {}",
                    p.path,
                    p.kind,
                    p.board
                        .clone()
                        .or_else(|| p.product.clone())
                        .unwrap_or_default()
                );
            }
            println!("(* = an Arduino or a USB-serial bridge used on Arduino clones)");
        }
        return Ok(());
    }
    let interrupt = interrupt_on_ctrl_c()?;
    let controller = Controller::open(&args.port, None)?;
    let lights = &controller.lights;
    match &args.command {
        LightsCommand::Ports => unreachable!(),
        LightsCommand::Identify => {
            let mut l = lights.lock();
            let info = l.identify()?;
            let state = l.state()?;
            #[derive(Serialize)]
            struct Identity {
                port: String,
                firmware: psscan::capture::lights::FirmwareInfo,
                state: psscan::capture::lights::LightState,
            }
            let out = Identity {
                port: l.name(),
                firmware: info,
                state,
            };
            if json {
                print_json(&out);
            } else {
                println!(
                    "{}: {} fw={} proto={}, {} LEDs; now {}, timeout {} ms{}",
                    out.port,
                    out.firmware.name,
                    out.firmware.firmware_version,
                    out.firmware.protocol,
                    out.firmware.leds,
                    describe_on(out.state.on),
                    out.state.timeout_ms,
                    if out.state.tripped {
                        ", tripped (the silence timeout switched an LED off)"
                    } else {
                        ""
                    }
                );
            }
        }
        LightsCommand::Test { dwell_ms } => {
            let mut show = |c: &LedCheck| {
                if !json {
                    let verdict = if c.ok { "ok" } else { "WRONG" };
                    println!("LED {}: {verdict}  ({})", c.led, c.state);
                }
            };
            let dwell = Duration::from_millis(*dwell_ms);
            let LedTest {
                checks,
                interrupted,
            } = test_leds(lights, dwell, &interrupt, &mut show)?;
            if json {
                print_json(&checks);
            }
            if interrupted {
                return Err(psscan::Error::Interrupted(
                    "LED test stopped; all LEDs are off".into(),
                )
                .into());
            }
            if checks.iter().any(|c| !c.ok) {
                anyhow::bail!("some LEDs did not report the expected state");
            }
        }
        LightsCommand::On { led, for_s } => {
            let timeout_ms = {
                let mut l = lights.lock();
                l.on(*led)?;
                l.state()?.timeout_ms
            };
            if !json {
                match for_s {
                    Some(s) => println!("LED {led} on for {s} s"),
                    None => println!("LED {led} on; Ctrl-C switches it off"),
                }
            }
            let keepalive = psscan::capture::lights::Keepalive::start(
                lights.clone(),
                Duration::from_millis(timeout_ms as u64 / 3),
                interrupt.clone(),
            );
            let hold = for_s.map_or(Duration::MAX, |s| Duration::from_secs_f64(s.max(0.0)));
            {
                let _lease = keepalive.lease(hold);
                interrupt.sleep(hold);
            }
            drop(keepalive);
            lights.lock().off()?;
            if json {
                print_json(&serde_json::json!({ "led": led, "held": true, "now": "off" }));
            }
        }
        LightsCommand::Off => {
            lights.lock().off()?;
            if json {
                print_json(&serde_json::json!({ "now": "off" }));
            } else {
                println!("all LEDs off");
            }
        }
    }
    Ok(())
}

fn lit_list(lit: &[usize]) -> String {
    match lit {
        [] => "all LEDs off".into(),
        [k] => format!("LED {k} on"),
        many => format!("LEDs {many:?} on together"),
    }
}

/// `psscan demo --firmware-sim`.
pub fn demo_firmware_sim(
    out: &Path,
    scene: &SceneArgs,
    job: &psscan::sets::SolveJob,
    json: bool,
    bars: &Bars,
) -> anyhow::Result<()> {
    let interrupt = interrupt_on_ctrl_c()?;
    let summary = psscan::sim::emulated::run_firmware_sim_demo(
        out,
        &scene.spec(),
        job,
        Duration::from_millis(20),
        &interrupt,
        bars,
    )?;
    if json {
        print_json(&summary);
    } else {
        print_firmware_sim_demo(&summary);
    }
    Ok(())
}

fn print_firmware_sim_demo(s: &FirmwareSimDemoSummary) {
    let t = |k: &str| s.timings_s.get(k).copied().unwrap_or(0.0);
    println!(
        "psscan demo --firmware-sim: {}x{} synthetic textile, rig \"{}\", firmware {} fw={} in \
         the emulator on {}",
        s.width, s.height, s.rig, s.firmware.name, s.firmware.firmware_version, s.port
    );
    for f in &s.frames {
        let want = match f.light {
            Some(k) => format!("LED {k}"),
            None => "dark".into(),
        };
        println!(
            "  {:<8} {want:<7} firmware had {} when the camera fired",
            f.file,
            lit_list(&f.lit_at_fire)
        );
    }
    println!(
        "  pin log       {} ({} shots with a wrong LED, at most {} LED on at once)",
        s.pin_log.display(),
        s.shots_with_wrong_leds,
        s.max_leds_on_together
    );
    println!(
        "  normal error  mean {:.3} deg, median {:.3}, p95 {:.3} (sensor-noise model predicts mean {})",
        s.normal_error_deg.mean,
        s.normal_error_deg.median,
        s.normal_error_deg.p95,
        super::deg_or_na(s.predicted_normal_error_deg.mean)
    );
    println!(
        "  albedo error  mean {:.2} %, median {:.2} %",
        100.0 * s.albedo_rel_error.mean,
        100.0 * s.albedo_rel_error.median
    );
    println!(
        "  time          capture {:.1} s, solve {:.1} s, total {:.1} s",
        t("capture"),
        t("solve_total"),
        t("total")
    );
    println!("  capture set   {}", s.paths.capture.display());
    println!("  maps          {}", s.paths.maps.display());
}
