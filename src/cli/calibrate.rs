//! `psscan calibrate`: the interactive wizard (no subcommand) and each step over image files.
//! The prompts live here; the work is `psscan::calibration`'s.

use std::io::{BufRead, Write};
use std::path::PathBuf;

use clap::{Args, Subcommand, ValueEnum};
use psscan::calibration::camera::{self, Board, CameraOptions};
use psscan::calibration::capture::{self, Simulated};
use psscan::calibration::wizard::{Step, Wizard, VIEWS_NEEDED};

use super::calibrate_steps::{self as steps, BundleArgs, GraychartArgs, TableArgs, WhitesheetArgs};
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
pub(super) struct BoardArgs {
    /// Inner corners of the chessboard, COLSxROWS.
    #[arg(long, default_value = "9x6")]
    pub(super) board: String,
    /// Side of one square in millimetres.
    #[arg(long, default_value_t = 25.0)]
    pub(super) square_mm: f64,
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
    /// The LED controller and a tethered camera (not built yet).
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
    let board = Board::parse(&args.board.board, args.board.square_mm)?;
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

fn wizard(args: &WizardArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let hand = load_rig(&args.rig)?;
    let board = Board::parse(&args.wizard_board, args.wizard_square_mm)?;
    let dir = args.out.clone().unwrap_or_else(|| {
        PathBuf::from("calibration")
            .join(&hand.name)
            .join(&args.name)
    });
    let mut source = match args.source {
        SourceArg::Sim => Simulated::new(&hand, board, args.seed),
        SourceArg::Capture => capture::hardware_source()?,
    };
    let (mut wiz, resumed) = Wizard::open(&dir, hand, &args.name, board)?;
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
    let stopped = || {
        println!(
            "stopped; the state is saved in {}: run the same command to resume",
            dir.display()
        );
        Ok(())
    };
    while wiz.state.step == Step::CameraViews {
        let need = VIEWS_NEEDED - wiz.state.accepted.len();
        if !go_on(
            &format!("step 1/4 camera: hold the chessboard in view ({need} more views needed)"),
            args.yes,
        )? {
            return stopped();
        }
        let v = wiz.take_view(&mut source)?;
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
            "step 2/4 table: lay the chessboard flat at the table centre, rows along the image",
            args.yes,
        )? {
            return stopped();
        }
        let pose = wiz.take_table(&mut source)?;
        println!(
            "  camera at {:.4?} m, tilt {:.3?} deg, board RMS {:.3} px",
            pose.camera_position_m, pose.camera_rotation_deg, pose.rms_reprojection_px
        );
    }
    if wiz.state.step == Step::WhiteSheet {
        if !go_on("step 3/4 white sheet: lay the white sheet flat on the table (each LED lights it in turn)", args.yes)? {
            return stopped();
        }
        let fit = wiz.take_white_sheet(&mut source, args.sheet_reflectance, bars)?;
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
    }
    if wiz.state.step == Step::Flatness {
        if !go_on(
            "step 4/4 check: leave the white sheet in place; it is re-solved with the calibration",
            args.yes,
        )? {
            return stopped();
        }
        let (flat, index) = wiz.finish(&mut source, bars)?;
        if json {
            print_json(&serde_json::json!({
                "bundle": dir,
                "id": index.id,
                "sha256": index.sha256,
                "flatness": flat,
                "calibration": wiz.state.calibration,
            }));
            return Ok(());
        }
        println!(
            "  flatness: every one of {} normals within {:.3} deg of straight up (limit {}; {} exposures averaged; mean {:.3} deg): {}",
            flat.pixels,
            flat.max_deg,
            flat.tolerance_deg,
            flat.exposures,
            flat.mean_deg,
            if flat.flat { "FLAT" } else { "NOT FLAT" }
        );
        println!(
            "calibration bundle {} written to {}",
            index.id,
            dir.display()
        );
    } else if wiz.state.step == Step::Done {
        println!("{} is already complete", dir.display());
    }
    Ok(())
}
