//! `psscan calibrate table|graychart|whitesheet|bundle`: the calibration steps over
//! photographs already taken, each writing its result as TOML (`--out`), and the bundle
//! assembled from those results. The work is `psscan::calibration::steps`'.
//!
//! Why a separate `bundle` step rather than each step writing into the bundle folder: a
//! bundle is what capture manifests cite by id and checksum, so it is written once, whole,
//! and never changes afterwards; the steps' own files can be redone one at a time (the table
//! after the camera was moved, the white sheet after an LED was re-aimed) and inspected
//! before anything cites them, and the bundle step checks they fit together (the white sheet
//! fitted with this camera and table, as many chart lights as LEDs).

use std::path::{Path, PathBuf};

use clap::Args;
use psscan::calibration::camera::CameraCalibration;
use psscan::calibration::files::{self, LINEAR_EXTENSIONS, RAW_EXTENSIONS};
use psscan::calibration::graychart::ChartReport;
use psscan::calibration::steps::{self, BundleInputs, TableStep, WhiteSheetStep};
use psscan::fsutil::{write_atomic, StagedDir};
use psscan::rig::Board;
use psscan::rig::{ChartDescription, ChartRect};

use super::progress::Bars;
use super::{load_rig, print_json};

/// The chessboard target's flags, shared by the wizard's camera step and the table step.
#[derive(Args)]
pub(super) struct BoardArgs {
    /// Inner corners of the chessboard, COLSxROWS.
    #[arg(long, default_value = "9x6")]
    pub(super) board: String,
    /// Side of one square in millimetres.
    #[arg(long, default_value_t = 25.0)]
    pub(super) square_mm: f64,
}

impl BoardArgs {
    /// The board the flags describe.
    pub(super) fn parse(&self) -> psscan::Result<Board> {
        Board::parse(&self.board, self.square_mm)
    }
}

#[derive(Args)]
pub struct TableArgs {
    /// Photograph of the chessboard lying flat at the table centre, its rows along the image
    /// rows, taken with the camera and settings of the camera step.
    #[arg(long)]
    image: PathBuf,
    /// The camera step's result (`psscan calibrate camera --out CAM.toml`).
    #[arg(long, value_name = "CAM.toml")]
    camera: PathBuf,
    #[command(flatten)]
    board: BoardArgs,
    /// Also write the result as TOML here.
    #[arg(long)]
    out: Option<PathBuf>,
}

/// Where the LEDs and camera come from for the steps that light the table.
#[derive(Args)]
pub struct RigArgs {
    /// Hand-measured rig description (default: the embedded default rig).
    #[arg(long)]
    rig: Option<PathBuf>,
    /// The camera step's result; with --table, replaces the rig's camera.
    #[arg(long, value_name = "CAM.toml")]
    camera: Option<PathBuf>,
    /// The table step's result (`psscan calibrate table --out TABLE.toml`).
    #[arg(long, value_name = "TABLE.toml")]
    table: Option<PathBuf>,
    /// Sensor pixels per image pixel of the photographs, which are taken as centred on the
    /// sensor (default: they cover the whole sensor, full size or binned).
    #[arg(long)]
    step: Option<f64>,
}

impl RigArgs {
    /// The files these options name (inputs of the step).
    fn paths(&self) -> impl Iterator<Item = &PathBuf> {
        self.rig.iter().chain(&self.camera).chain(&self.table)
    }

    fn rig(&self) -> anyhow::Result<psscan::rig::Rig> {
        let hand = load_rig(&self.rig)?;
        let camera: Option<CameraCalibration> = self
            .camera
            .as_deref()
            .map(|p| steps::load_toml(p, "camera"))
            .transpose()?;
        let table: Option<TableStep> = self
            .table
            .as_deref()
            .map(|p| steps::load_toml(p, "table"))
            .transpose()?;
        Ok(steps::compose_rig(
            &hand,
            camera.as_ref(),
            table.as_ref().map(|t| &t.pose),
        )?)
    }
}

#[derive(Args)]
pub struct GraychartArgs {
    /// RAW photographs of the chart lying on the table, one per LED in LED order: a folder
    /// (its RAW files in name order) or the files. A file named `dark.*` (the all-off frame
    /// of a capture set) is left out: the linearity fit's offset takes the black level.
    #[arg(long, num_args = 1.., required = true)]
    images: Vec<PathBuf>,
    /// Chart description (TOML: name, rows, cols, reflectance row by row, sample_fraction),
    /// or `munsell-12` for the built-in Munsell N2-N9.5 scale.
    #[arg(long, value_name = "CHART.toml")]
    chart: PathBuf,
    /// The chart's outer rectangle in image pixels: left, top, width, height (default: found
    /// in the photographs; the chart must lie square to the image, its first row at the top).
    #[arg(long, value_name = "X,Y,W,H")]
    rect: Option<String>,
    #[command(flatten)]
    rig: RigArgs,
    /// Also write the result as TOML here.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Args)]
pub struct WhitesheetArgs {
    /// Photographs of the white sheet flat on the table, one per LED in LED order: a folder
    /// (EXR, 16-bit PNG/TIFF of raw numbers, or RAW files, in name order; a file named
    /// `dark.*` is the all-off frame and is subtracted) or the files.
    #[arg(long, num_args = 1.., required = true)]
    images: Vec<PathBuf>,
    #[command(flatten)]
    rig: RigArgs,
    /// Reflectance of the white sheet.
    #[arg(long, default_value_t = 0.9)]
    reflectance: f64,
    /// Side of the blocks the sheet is averaged over (pixels): averages the paper's texture
    /// and the noise away.
    #[arg(long, default_value_t = 8)]
    block: usize,
    /// Also write the result as TOML here, and the per-light intensity maps (EXR) into
    /// `<OUT stem>-maps/` beside it.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Args)]
pub struct BundleArgs {
    /// Hand-measured rig description (default: the embedded default rig); the white sheet
    /// step's fitted rig replaces it.
    #[arg(long)]
    rig: Option<PathBuf>,
    /// `calibrate camera --out` result.
    #[arg(long, value_name = "CAM.toml")]
    camera: Option<PathBuf>,
    /// `calibrate table --out` result.
    #[arg(long, value_name = "TABLE.toml")]
    table: Option<PathBuf>,
    /// `calibrate graychart --out` result.
    #[arg(long, value_name = "CHART.toml")]
    graychart: Option<PathBuf>,
    /// `calibrate whitesheet --out` result (its maps folder beside it).
    #[arg(long, value_name = "SHEET.toml")]
    whitesheet: Option<PathBuf>,
    /// Bundle name (default: today's date, YYYY-MM-DD).
    #[arg(long)]
    name: Option<String>,
    /// Bundle folder (default: calibration/<rig>/<name>).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Replace a bundle already in the folder (captures that cite it will no longer solve
    /// against it).
    #[arg(long)]
    force: bool,
}

fn write_toml<T: serde::Serialize>(path: &Path, value: &T) -> anyhow::Result<()> {
    let text = toml::to_string_pretty(value)?;
    write_atomic(path, text.as_bytes())?;
    Ok(())
}

pub fn table(args: &TableArgs, json: bool) -> anyhow::Result<()> {
    let board = args.board.parse()?;
    let camera: CameraCalibration = steps::load_toml(&args.camera, "camera")?;
    let result = steps::table_from_file(&args.image, &board, &camera)?;
    if let Some(out) = &args.out {
        write_toml(out, &result)?;
    }
    if json {
        print_json(&result);
        return Ok(());
    }
    let p = &result.pose;
    let c = &result.check;
    println!(
        "table: camera at x {:.2} y {:.2} z {:.2} mm above the board centre, tilted {:.3} {:.3} deg, turned {:.3} deg",
        p.camera_position_m[0] * 1e3,
        p.camera_position_m[1] * 1e3,
        p.camera_position_m[2] * 1e3,
        p.camera_rotation_deg[0],
        p.camera_rotation_deg[1],
        p.camera_rotation_deg[2]
    );
    println!(
        "  board reprojection RMS {:.3} px; pixel-to-world check over {} corners ({:.0} x {:.0} mm): mean {:.3} mm, max {:.3} mm",
        p.rms_reprojection_px, c.corners, c.area_mm[0], c.area_mm[1], c.mean_mm, c.max_mm
    );
    Ok(())
}

fn load_chart(path: &Path) -> anyhow::Result<ChartDescription> {
    if !path.exists() && path.as_os_str() == "munsell-12" {
        return Ok(ChartDescription::munsell_12());
    }
    Ok(ChartDescription::load(path)?)
}

/// `X,Y,W,H` (as `psscan solve --roi`) to the chart's corners.
fn parse_rect(text: &str) -> anyhow::Result<ChartRect> {
    let v: Vec<f64> = text
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .unwrap_or_default();
    match v.as_slice() {
        &[x, y, w, h] if w > 0.0 && h > 0.0 && x.is_finite() && y.is_finite() => Ok(ChartRect {
            x0: x,
            y0: y,
            x1: x + w,
            y1: y + h,
        }),
        _ => anyhow::bail!(
            "--rect {text:?}: expected X,Y,W,H in image pixels (left, top, width, height), \
             width and height positive"
        ),
    }
}

pub fn graychart(args: &GraychartArgs, json: bool) -> anyhow::Result<()> {
    let chart = load_chart(&args.chart)?;
    let rect = args.rect.as_deref().map(parse_rect).transpose()?;
    let rig = args.rig.rig()?;
    let listed = files::list_images(&args.images, &RAW_EXTENSIONS, "RAW photographs")?;
    let (files, dark) = files::split_dark(listed)?;
    let (report, rect, found) = steps::graychart_from_files(&steps::ChartInputs {
        files: &files,
        chart: &chart,
        rect,
        rig: &rig,
        step: args.rig.step,
    })?;
    if let Some(out) = &args.out {
        write_toml(out, &report)?;
    }
    let (w, h) = (rect.x1 - rect.x0, rect.y1 - rect.y0);
    if json {
        let mut v = serde_json::to_value(&report)?;
        v["rect"] = serde_json::json!({"x": rect.x0, "y": rect.y0, "width": w, "height": h, "found": found});
        v["dark_frame_left_out"] = serde_json::json!(dark);
        print_json(&v);
        return Ok(());
    }
    if let Some(dark) = &dark {
        println!(
            "dark frame {} left out (one photograph per LED)",
            dark.display()
        );
    }
    println!(
        "chart rectangle {:.1},{:.1},{w:.1},{h:.1} (X,Y,W,H in image pixels{})",
        rect.x0,
        rect.y0,
        if found {
            ", found in the photographs"
        } else {
            ""
        }
    );
    print_chart(&report, &files);
    Ok(())
}

fn print_chart(report: &ChartReport, files: &[PathBuf]) {
    println!(
        "gray chart \"{}\" under {} lights (white balance: multipliers of R, G, B; linearity: green against nominal reflectance)",
        report.chart,
        report.lights.len()
    );
    for (k, (light, file)) in report.lights.iter().zip(files).enumerate() {
        let l = &light.linearity;
        let wb = light.white_balance;
        let clipped = if l.clipped_patches.is_empty() {
            String::new()
        } else {
            format!(
                "; CLIPPED patches {:?} (left out of the fit)",
                l.clipped_patches
            )
        };
        println!(
            "  light {k} ({}): white balance {:.4} {:.4} {:.4}; slope {:.4}, offset {:+.5}, R^2 {:.6}, worst patch {} ({:+.2} %){clipped}",
            file.file_name().map(|n| n.to_string_lossy()).unwrap_or_default(),
            wb[0],
            wb[1],
            wb[2],
            l.slope,
            l.offset,
            l.r_squared,
            l.worst_patch,
            100.0 * l.worst_deviation
        );
    }
}

pub fn whitesheet(args: &WhitesheetArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let rig = args.rig.rig()?;
    let mut extensions: Vec<&str> = LINEAR_EXTENSIONS.to_vec();
    extensions.extend(RAW_EXTENSIONS);
    let listed = files::list_images(&args.images, &extensions, "white-sheet photographs")?;
    let (lights, dark) = files::split_dark(listed)?;
    let (mut result, sheet) = steps::whitesheet_from_files(
        &steps::SheetInputs {
            files: &lights,
            dark: dark.as_deref(),
            rig: &rig,
            reflectance: args.reflectance,
            block_px: args.block,
            step: args.rig.step,
        },
        bars,
    )?;
    if let Some(out) = &args.out {
        let stem = out
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "whitesheet".into());
        let maps = PathBuf::from(format!("{stem}-maps"));
        let base = out.parent().unwrap_or(Path::new("."));
        // The maps folder is this step's own (an earlier run's is replaced); it is staged,
        // and never a folder of other files nor one of the photographs' folders.
        let inputs: Vec<&Path> = args
            .images
            .iter()
            .chain(args.rig.paths())
            .map(|p| p.as_path())
            .collect();
        let stage = StagedDir::create(&base.join(&maps), true, &inputs)?;
        steps::write_sheet_maps(stage.path(), &sheet)?;
        stage.commit(true, &inputs)?;
        result.maps_dir = Some(maps);
        write_toml(out, &result)?;
    }
    if json {
        print_json(&result);
    } else {
        print_sheet(&result, &rig);
    }
    let problems = result.lights.problems();
    if !problems.is_empty() {
        let kept = match &args.out {
            Some(out) => format!(
                "; {} records it as rejected, and `calibrate bundle` refuses it",
                out.display()
            ),
            None => String::new(),
        };
        anyhow::bail!(
            "the white-sheet LED fit was rejected ({}){kept}",
            problems.join("; ")
        );
    }
    Ok(())
}

fn print_sheet(r: &WhiteSheetStep, start: &psscan::rig::Rig) {
    println!(
        "white sheet: {} lights{}, blocks of {} px, reflectance {}; LED positions fitted from rig \"{}\"",
        r.images.len(),
        if r.dark.is_some() { " (dark frame subtracted)" } else { "" },
        r.block_px,
        r.reflectance,
        start.name
    );
    for it in &r.lights.iterations {
        println!(
            "  iteration {:2}: largest LED move {:9.4} mm, largest power change {:+.2e}, rms relative residual {:.3e}",
            it.iteration, it.max_step_mm, it.max_power_change, it.rms_relative_residual
        );
    }
    let limit_mm = psscan::calibration::lights::CONVERGED_STEP_M * 1e3;
    if r.lights.converged {
        println!(
            "  converged after {} iterations (every LED moved less than {limit_mm} mm)",
            r.lights.iterations.len()
        );
    } else {
        println!(
            "  NOT converged after {} iterations: check the rig's hand measurements and that each photograph is lit by its own LED",
            r.lights.iterations.len()
        );
    }
    for reason in &r.lights.rejected_because {
        println!("  REJECTED: {reason}");
    }
    for (k, led) in r.lights.leds.iter().enumerate() {
        let p = led.position_m;
        println!(
            "  LED {k}: at {:.1} {:.1} {:.1} mm, {:.1} mm from the hand measurement, rms residual {:.2e}",
            p[0] * 1e3,
            p[1] * 1e3,
            p[2] * 1e3,
            led.moved_mm,
            led.rms_relative_residual
        );
    }
    println!(
        "  sheet re-solved with the fitted LEDs (one exposure): mean {:.3} deg, max {:.3} deg (sensor noise alone: up to {:.3}), 16x16-block max {:.3} deg",
        r.check.mean_deg, r.check.max_deg, r.check.predicted_noise_max_deg, r.check.block_max_deg
    );
}

pub fn bundle(args: &BundleArgs, json: bool) -> anyhow::Result<()> {
    let named = [
        &args.rig,
        &args.camera,
        &args.table,
        &args.graychart,
        &args.whitesheet,
    ];
    if let Some(out) = &args.out {
        // Refused before any step is read; checked again (with the sheet's maps) below.
        let read: Vec<&Path> = named
            .iter()
            .copied()
            .flatten()
            .map(|p| p.as_path())
            .collect();
        psscan::fsutil::check_replaceable(out, args.force, &read)?;
    }
    let rig = load_rig(&args.rig)?;
    let inputs = BundleInputs {
        rig,
        camera: load_step(&args.camera, "camera")?,
        table: load_step(&args.table, "table")?,
        graychart: load_step(&args.graychart, "graychart")?,
        whitesheet: load_step::<WhiteSheetStep>(&args.whitesheet, "whitesheet")?,
    };
    if inputs.camera.is_none()
        && inputs.table.is_none()
        && inputs.graychart.is_none()
        && inputs.whitesheet.is_none()
    {
        anyhow::bail!(
            "nothing to bundle: give at least one of --camera, --table, --graychart, --whitesheet"
        );
    }
    let name = args.name.clone().unwrap_or_else(steps::today);
    let rig_name = inputs
        .whitesheet
        .as_ref()
        .map_or(&inputs.rig.name, |w| &w.1.rig.name)
        .clone();
    let dir = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("calibration").join(&rig_name).join(&name));
    // Staged: a bundle appears whole or not at all, and replaces only a psscan bundle.
    let sheet_maps = inputs.whitesheet.as_ref().and_then(|(path, sheet)| {
        let base = path.parent().unwrap_or(Path::new("."));
        sheet.maps_dir.as_ref().map(|m| base.join(m))
    });
    let read: Vec<&Path> = [
        &args.rig,
        &args.camera,
        &args.table,
        &args.graychart,
        &args.whitesheet,
        &sheet_maps,
    ]
    .into_iter()
    .flatten()
    .map(|p| p.as_path())
    .collect();
    let stage = StagedDir::create(&dir, args.force, &read)?;
    let (index, _) = steps::assemble_bundle(&inputs, stage.path(), &name, true)?;
    stage.commit(args.force, &read)?;
    if json {
        print_json(&serde_json::json!({
            "bundle": dir,
            "id": index.id,
            "sha256": index.sha256,
            "files": index.files,
        }));
        return Ok(());
    }
    println!(
        "calibration bundle {} written to {}",
        index.id,
        dir.display()
    );
    println!("  sha256 {}", index.sha256);
    for file in index.files.keys() {
        println!("  {file}");
    }
    println!(
        "  cite it: psscan capture ... --calibration {0}; psscan solve ... --calibration {0}",
        dir.display()
    );
    Ok(())
}

fn load_step<T: serde::de::DeserializeOwned>(
    path: &Option<PathBuf>,
    what: &str,
) -> anyhow::Result<Option<(PathBuf, T)>> {
    Ok(match path {
        Some(p) => Some((p.clone(), steps::load_toml(p, what)?)),
        None => None,
    })
}
