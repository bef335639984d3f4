//! `psscan calibrate`: the interactive wizard (no subcommand) and each step over image files.
//! The prompts live here; the work is `psscan::calibration`'s.

use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::time::Duration;

use clap::{Args, Subcommand, ValueEnum};
use psscan::calibration::camera::{self, CameraOptions};
use psscan::calibration::capture::Captured;
use psscan::calibration::wizard::{ChartVerdict, Step, TargetSource, Wizard, VIEWS_NEEDED};
use psscan::capture::camera::Camera;
use psscan::rig::Board;
use psscan::rig::ChartDescription;
use psscan::sim::operator::{simulated_camera, Simulated};

use super::calibrate_steps::{
    self as steps, BoardArgs, BundleArgs, GraychartArgs, TableArgs, WhitesheetArgs,
};
use super::capture::{interrupt_on_ctrl_c, open_camera, Controller, PortArgs};
use super::progress::Bars;
use super::{load_rig, print_json};

#[derive(Args)]
pub struct CalibrateArgs {
    #[command(subcommand)]
    step: Option<CalibrateStep>,
    #[command(flatten)]
    wizard: WizardArgs,
}

#[derive(Subcommand)]
enum CalibrateStep {
    /// Camera intrinsics and distortion from chessboard photographs in a folder (OpenCV).
    Camera(CameraArgs),
    /// The table's pose from one photograph of the chessboard lying on it (OpenCV).
    Table(TableArgs),
    /// Per-light white balance and linearity from RAW photographs of a gray chart.
    Graychart(GraychartArgs),
    /// Per-light intensity maps and each LED's fitted position from white-sheet photographs.
    Whitesheet(WhitesheetArgs),
    /// Assemble the steps' results into a calibration bundle that captures and solves cite.
    Bundle(BundleArgs),
}

#[derive(Args)]
struct CameraArgs {
    /// Folder of chessboard photographs (PNG, JPEG, TIFF), all from one camera.
    #[arg(long)]
    images: PathBuf,
    #[command(flatten)]
    board: BoardArgs,
    /// Keep fx = fy.
    #[arg(long)]
    fix_aspect_ratio: bool,
    /// Half size of the sub-pixel corner window in pixels (default: sized to the squares;
    /// OpenCV's sample uses 11).
    #[arg(long)]
    subpix_window: Option<usize>,
    /// Also write the result as TOML here.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Clone, Copy, ValueEnum)]
enum SourceArg {
    /// The simulated rig: synthetic targets through an as-built rig.
    Sim,
    /// Through the capture module: the LED controller (--port, or --firmware-sim) and a camera
    /// (--camera).
    Capture,
}

#[derive(Args)]
struct WizardArgs {
    /// Bundle folder (default calibration/<rig>/<name>); holds the wizard's state while it runs.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Bundle name.
    #[arg(long, default_value = "wizard")]
    name: String,
    /// Hand-measured rig description (default: the embedded default rig).
    #[arg(long)]
    rig: Option<PathBuf>,
    /// Where photographs come from.
    #[arg(long, value_enum, default_value_t = SourceArg::Sim)]
    source: SourceArg,
    /// Chessboard inner corners (the wizard's default board is 9x6 with 15 mm squares).
    #[arg(long, default_value = "9x6")]
    wizard_board: String,
    #[arg(long, default_value_t = 15.0)]
    wizard_square_mm: f64,
    /// Reflectance of the white sheet.
    #[arg(long, default_value_t = 0.9)]
    sheet_reflectance: f64,
    /// Seed of the simulated rig.
    #[arg(long, default_value_t = 5)]
    seed: u64,
    /// Do not wait for Enter before each photograph.
    #[arg(long)]
    yes: bool,
    /// Gray chart description (TOML: name, rows, cols, reflectance; default: the 12 Munsell
    /// neutrals N2..N9.5 in 2 rows of 6).
    #[arg(long)]
    chart: Option<PathBuf>,
    /// Size of the gray chart's patch area, WIDTHxHEIGHT in mm; it lies centred under the
    /// camera.
    #[arg(long, default_value = "120x50")]
    chart_mm: String,
    /// With --source capture: how to reach the LED controller.
    #[command(flatten)]
    port: PortArgs,
    /// With --source capture: `gphoto2` (tethered, needs the gphoto2 build feature), `sim`
    /// (photographs the simulated targets under whatever LEDs the controller has on), or
    /// `cmd:TEMPLATE`. Default: sim with --firmware-sim, else gphoto2.
    #[arg(long)]
    camera: Option<String>,
    /// With --source capture: wait after switching an LED before firing, ms.
    #[arg(long, default_value_t = 250)]
    settle_ms: u64,
    /// With --source capture: longest one shot (exposure + download) may take, s.
    #[arg(long, default_value_t = 60.0)]
    shot_timeout_s: f64,
    /// With --firmware-sim: where the emulator writes its pin log (kept afterwards).
    #[arg(long)]
    pin_log: Option<PathBuf>,
}

fn chart_world(text: &str) -> anyhow::Result<[f64; 4]> {
    let parsed: Option<Vec<f64>> = text.split('x').map(|v| v.trim().parse().ok()).collect();
    match parsed.as_deref() {
        Some(&[w, h]) if w > 0.0 && h > 0.0 => {
            let (w, h) = (w / 2000.0, h / 2000.0);
            Ok([-w, w, -h, h])
        }
        _ => Err(psscan::Error::Invalid(format!(
            "--chart-mm {text:?}: expected WIDTHxHEIGHT in millimetres, e.g. 120x50"
        ))
        .into()),
    }
}

pub fn calibrate(args: &CalibrateArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    match &args.step {
        Some(CalibrateStep::Camera(a)) => camera_step(a, json, bars),
        Some(CalibrateStep::Table(a)) => steps::table(a, json),
        Some(CalibrateStep::Graychart(a)) => steps::graychart(a, json),
        Some(CalibrateStep::Whitesheet(a)) => steps::whitesheet(a, json, bars),
        Some(CalibrateStep::Bundle(a)) => steps::bundle(a, json),
        None => wizard(&args.wizard, json, bars),
    }
}

fn camera_step(args: &CameraArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let board = args.board.parse()?;
    let files = camera::image_files(&args.images)?;
    let (views, size) = camera::detect_files(&files, &board, args.subpix_window, bars)?;
    let options = CameraOptions {
        fix_aspect_ratio: args.fix_aspect_ratio,
        ..CameraOptions::default()
    };
    let cal = camera::calibrate(&views, &board, size, &options)?;
    if let Some(out) = &args.out {
        let text = toml::to_string_pretty(&cal)?;
        psscan::fsutil::write_atomic(out, text.as_bytes())?;
    }
    if json {
        print_json(&cal);
        return Ok(());
    }
    let i = cal.intrinsics;
    println!(
        "camera: {}x{} px, fx {:.3} fy {:.3} (+/- {:.3} {:.3}), principal point {:.3} {:.3} (+/- {:.3} {:.3})",
        i.width, i.height, i.fx, i.fy, cal.std_dev[0], cal.std_dev[1], i.cx, i.cy, cal.std_dev[2], cal.std_dev[3]
    );
    println!("  distortion k1 k2 p1 p2 k3 = {:?}", i.distortion);
    println!(
        "  RMS reprojection error {:.4} px over {} views; {} rejected",
        cal.rms_reprojection_px, cal.views_used, cal.views_rejected
    );
    for v in cal.views.iter().filter(|v| !v.used) {
        println!(
            "  rejected {}: {}",
            v.name,
            v.rejected_because.as_deref().unwrap_or("")
        );
    }
    Ok(())
}

/// Waits for Enter; `false` when the operator typed q (or closed the input): stop here.
fn go_on(prompt: &str, yes: bool) -> anyhow::Result<bool> {
    println!("{prompt}");
    if yes {
        return Ok(true);
    }
    print!("  [Enter] take it, [q] stop (resume later with the same command) > ");
    std::io::stdout().flush()?;
    let mut line = String::new();
    let read = std::io::stdin().lock().read_line(&mut line)?;
    Ok(read > 0 && line.trim() != "q")
}

/// The photographs' source, and the controller (and emulator) behind it, kept alive with it.
struct Source {
    source: Box<dyn TargetSource>,
    /// Only dropped after `source`.
    controller: Option<Controller>,
    view_led: Option<usize>,
}

fn open_source(
    args: &WizardArgs,
    hand: &psscan::rig::Rig,
    board: Board,
    dir: &std::path::Path,
) -> anyhow::Result<Source> {
    if let SourceArg::Sim = args.source {
        if args.port.firmware_sim || args.camera.is_some() || args.pin_log.is_some() {
            anyhow::bail!(
                "--firmware-sim, --camera and --pin-log photograph through the capture module: \
                 add --source capture"
            );
        }
        return Ok(Source {
            source: Box::new(Simulated::new(hand, board, args.seed)),
            controller: None,
            view_led: None,
        });
    }
    let interrupt = interrupt_on_ctrl_c()?;
    let controller = Controller::open(&args.port, args.pin_log.as_deref())?;
    let camera = args.port.camera_or_default(&args.camera);
    type Operator = Option<Box<dyn psscan::calibration::capture::Operator>>;
    let (camera, operator): (Box<dyn Camera>, Operator) = if camera == "sim" {
        let lit = psscan::sim::lit_source(
            controller.emulated.as_ref(),
            args.pin_log.as_deref(),
            &controller.lights,
        );
        let (camera, scene) = simulated_camera(hand, board, args.seed, lit);
        (Box::new(camera), Some(Box::new(scene)))
    } else {
        let timeout = Duration::from_secs_f64(args.shot_timeout_s.max(0.1));
        (open_camera(&camera, None, timeout)?, None)
    };
    let captured = Captured::open(
        dir,
        hand,
        controller.lights.clone(),
        camera,
        operator,
        Duration::from_millis(args.settle_ms),
        interrupt,
    )?;
    Ok(Source {
        view_led: Some(captured.view_led()),
        source: Box::new(captured),
        controller: Some(controller),
    })
}

fn wizard(args: &WizardArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let hand = load_rig(&args.rig)?;
    let board = Board::parse(&args.wizard_board, args.wizard_square_mm)?;
    let dir = args.out.clone().unwrap_or_else(|| {
        PathBuf::from("calibration")
            .join(&hand.name)
            .join(&args.name)
    });
    let chart = match &args.chart {
        Some(path) => ChartDescription::load(path)?,
        None => ChartDescription::munsell_12(),
    };
    let chart_world = chart_world(&args.chart_mm)?;
    let (mut wiz, resumed) = Wizard::open(&dir, hand.clone(), &args.name, board)?;
    wiz.chart = chart;
    wiz.chart_world = chart_world;
    let mut source = open_source(args, &hand, board, &dir)?;
    let result = walk(&mut wiz, &mut source, resumed, args, json, bars);
    if let Err(e) = &result {
        let interrupted = e
            .downcast_ref::<psscan::Error>()
            .is_some_and(psscan::Error::is_interrupted);
        if interrupted {
            println!(
                "stopped; the state is saved in {}: run the same command to resume",
                dir.display()
            );
        }
    }
    let pins = pin_log_summary(&source);
    drop(source);
    let (flat, chart, index) = match result? {
        Some(done) => done,
        None => return Ok(()),
    };
    if json {
        print_json(&serde_json::json!({
            "bundle": dir,
            "id": index.id,
            "sha256": index.sha256,
            "flatness": flat,
            "gray_chart": chart,
            "calibration": wiz.state.calibration,
            "firmware_pin_log": pins,
        }));
        return Ok(());
    }
    if let Some(p) = pins {
        println!(
            "  firmware pin log: at most {} LED on at once; at the end {}",
            p["max_leds_on_together"], p["lit_at_end"]
        );
    }
    println!(
        "calibration bundle {} written to {}",
        index.id,
        dir.display()
    );
    Ok(())
}

/// With the firmware emulator: what its pin log says about the whole session.
fn pin_log_summary(source: &Source) -> Option<serde_json::Value> {
    let emulated = source.controller.as_ref()?.emulated.as_ref()?;
    let log = emulated.pin_log();
    let history = log.read().ok()?;
    Some(serde_json::json!({
        "path": log.path(),
        "max_leds_on_together": history.max_lit_together(),
        "lit_at_end": history.lit_now(),
    }))
}

type Finished = (
    psscan::calibration::whitesheet::Flatness,
    Option<ChartVerdict>,
    psscan::calibration::bundle::BundleIndex,
);

/// Walks the steps from where the state stands; `None` when the operator stopped (or the
/// bundle was already complete).
fn walk(
    wiz: &mut Wizard,
    source: &mut Source,
    resumed: bool,
    args: &WizardArgs,
    json: bool,
    bars: &Bars,
) -> anyhow::Result<Option<Finished>> {
    let dir = wiz.dir.clone();
    if resumed {
        println!(
            "resuming {} at step {:?}: {} of {VIEWS_NEEDED} chessboard views accepted",
            dir.display(),
            wiz.state.step,
            wiz.state.accepted.len()
        );
    } else {
        println!(
            "calibrating rig \"{}\" into {}",
            wiz.state.rig_name,
            dir.display()
        );
    }
    if let Some(k) = source.view_led {
        println!("  chessboard photographs are lit by LED {k}, the one nearest the camera axis");
    }
    let stopped = || {
        println!(
            "stopped; the state is saved in {}: run the same command to resume",
            dir.display()
        );
        Ok(None)
    };
    let source = source.source.as_mut();
    while wiz.state.step == Step::CameraViews {
        // Unattended, nobody can move the board or fix the light: stop instead of looping.
        if args.yes && wiz.state.rejected.len() >= 2 * VIEWS_NEEDED {
            let last = wiz
                .state
                .rejected
                .last()
                .map(|r| r.1.clone())
                .unwrap_or_default();
            anyhow::bail!(
                "{} chessboard photographs rejected, {} of {VIEWS_NEEDED} accepted (last: {last}); \
                 check the camera, the board and the light, then run the same command to resume",
                wiz.state.rejected.len(),
                wiz.state.accepted.len()
            );
        }
        let need = VIEWS_NEEDED - wiz.state.accepted.len();
        if !go_on(
            &format!("step 1/5 camera: hold the chessboard in view ({need} more views needed)"),
            args.yes,
        )? {
            return stopped();
        }
        let v = wiz.take_view(source)?;
        let verdict = if v.accepted { "accepted" } else { "REJECTED" };
        println!("  {} {verdict}: {}", v.name, v.reason);
        if !v.missing_regions.is_empty() && v.still_needed > 0 {
            println!(
                "  the board has not been at: {}",
                v.missing_regions.join(", ")
            );
        }
    }
    if let (Step::Table, Some(cam)) = (wiz.state.step, &wiz.state.calibration.camera) {
        println!(
            "  camera calibrated: fx {:.2} fy {:.2} px, RMS {:.4} px over {} views",
            cam.intrinsics.fx, cam.intrinsics.fy, cam.rms_reprojection_px, cam.views_used
        );
        if !go_on(
            "step 2/5 table: lay the chessboard flat at the table centre, rows along the image",
            args.yes,
        )? {
            return stopped();
        }
        let pose = wiz.take_table(source)?;
        println!(
            "  camera at {:.4?} m, tilt {:.3?} deg, board RMS {:.3} px",
            pose.camera_position_m, pose.camera_rotation_deg, pose.rms_reprojection_px
        );
    }
    while wiz.state.step == Step::GrayChart {
        let [x0, x1, y0, y1] = wiz.chart_world;
        let prompt = format!(
            "step 3/5 gray chart: lay the gray chart \"{}\" flat at the table centre, its {} x {} \
             patches filling {:.0} x {:.0} mm, rows along the image, the first patch at the top \
             left (each LED lights it in turn)",
            wiz.chart.name,
            wiz.chart.rows,
            wiz.chart.cols,
            (x1 - x0) * 1000.0,
            (y1 - y0) * 1000.0
        );
        if !go_on(&prompt, args.yes)? {
            return stopped();
        }
        let verdict = wiz.take_gray_chart(source, bars)?;
        print_chart(&verdict);
        if !verdict.accepted && args.yes {
            anyhow::bail!(
                "the gray chart was rejected ({}); fix it and run the same command again",
                verdict.reasons.join("; ")
            );
        }
    }
    if wiz.state.step == Step::WhiteSheet {
        if !go_on("step 4/5 white sheet: lay the white sheet flat on the table (each LED lights it in turn)", args.yes)? {
            return stopped();
        }
        let fit = wiz.take_white_sheet(source, args.sheet_reflectance, bars)?;
        for it in &fit.iterations {
            println!(
                "  LED fit iteration {}: largest move {:.3} mm, rms residual {:.2e}",
                it.iteration, it.max_step_mm, it.rms_relative_residual
            );
        }
        for (k, led) in fit.leds.iter().enumerate() {
            println!(
                "  LED {k}: moved {:.1} mm from the hand measurement",
                led.moved_mm
            );
        }
        let problems = fit.problems();
        if !problems.is_empty() {
            anyhow::bail!(
                "the white-sheet LED fit was rejected ({}); nothing was kept: check the rig's \
                 hand-measured LED positions and that each photograph is lit by its own LED, \
                 then run the same command again",
                problems.join("; ")
            );
        }
    }
    if wiz.state.step == Step::Flatness {
        if !go_on(
            "step 5/5 check: leave the white sheet in place; it is re-solved with the calibration",
            args.yes,
        )? {
            return stopped();
        }
        let (flat, chart, index) = wiz.finish(source, bars)?;
        if !json {
            println!(
                "  flatness: every one of {} normals within {:.3} deg of straight up (limit {}; {} exposures averaged; mean {:.3} deg): FLAT",
                flat.pixels,
                flat.max_deg,
                flat.tolerance_deg,
                flat.exposures,
                flat.mean_deg,
            );
            if let Some(chart) = &chart {
                println!("  gray chart read again with the fitted LED positions:");
                print_chart(chart);
            }
        }
        return Ok(Some((flat, chart, index)));
    }
    if wiz.state.step == Step::Done {
        println!("{} is already complete", dir.display());
    }
    Ok(None)
}

fn print_chart(v: &ChartVerdict) {
    for (k, light) in v.report.lights.iter().enumerate() {
        let l = &light.linearity;
        let wb = light.white_balance;
        println!(
            "  LED {k}: white balance R {:.4} G 1 B {:.4}; linearity slope {:.4} offset {:+.5} \
             R^2 {:.6}, worst patch {} at {:+.3} % (allowed {:.3} %){}",
            wb[0],
            wb[2],
            l.slope,
            l.offset,
            l.r_squared,
            l.worst_patch,
            100.0 * l.worst_deviation,
            100.0 * v.linearity_tolerance.get(k).copied().unwrap_or(f64::NAN),
            if l.clipped_patches.is_empty() {
                String::new()
            } else {
                format!(", clipped patches {:?}", l.clipped_patches)
            }
        );
    }
    if v.accepted {
        println!("  gray chart accepted");
    } else {
        for r in &v.reasons {
            println!("  gray chart REJECTED: {r}");
        }
    }
}
