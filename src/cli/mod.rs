//! Command-line interface: argument parsing (clap), progress bars, human and JSON summaries,
//! exit codes. Thin by design: every command is one library call.
//!
//! Exit codes: 0 success, 1 failure (the message says what and where), 2 usage error.

mod bench;
mod calibrate;
mod calibrate_steps;
mod capture;
mod derive;
mod eval;
mod outcome;
mod progress;
mod report;
mod signals;
mod values;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use clap::{Args, Parser, Subcommand, ValueEnum};
use psscan::calibration::CalibrationChoice;
use psscan::maps::{MapOptions, NormalConvention, PngCompression};
use psscan::raw::{DevelopOptions, Resolution};
use psscan::region::{Background, RegionJob, Roi};
use psscan::rig::Rig;
use psscan::sets::{self, BatchOptions, BatchSummary, SolveJob};
use psscan::solve::{
    Estimator, KernelChoice, LightModel, Method, Precision, RobustOptions, SheenModel,
    SolveOptions, DEFAULT_TILE_TOLERANCE_DEG,
};
use psscan::synth::{self, DemoSummary, FrameEncoding, Sheen, SynthSpec};

use outcome::{
    exit_code, is_closed_pipe_message, panic_text, quiet_closed_pipe_panics, usage_error,
};
use progress::Bars;

#[derive(Parser)]
#[command(
    name = "psscan",
    version,
    about = "Photometric-stereo textile scanner: capture, calibrate, and solve RAW sets into albedo and normal maps"
)]
struct Cli {
    /// Print a JSON summary on stdout instead of the human one.
    #[arg(long, global = true)]
    json: bool,
    /// No progress bars.
    #[arg(long, short, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render the synthetic textile and solve it with the default rig, in one go.
    Demo(DemoArgs),
    /// Render a synthetic capture set (frames, manifest, ground truth).
    Synth(SynthArgs),
    /// Solve capture sets (psscan's, or the DiLiGenT benchmark layout) into maps and reports.
    Solve(SolveArgs),
    /// Shoot a capture set: a dark frame, then one frame per LED, through the LED controller
    /// and a camera; resumable.
    Capture(capture::CaptureArgs),
    /// Bench work on the LED controller: list ports, identify, test, switch LEDs.
    Lights(capture::LightsArgs),
    /// Calibrate the rig: without a subcommand, the wizard (camera, table, white sheet, flatness
    /// check; resumable); `calibrate camera|table|graychart|whitesheet` runs one step over
    /// photographs, `calibrate bundle` assembles their results.
    Calibrate(Box<calibrate::CalibrateArgs>),
    /// Benchmark every solver variant on standard synthetic scenes: run time against error,
    /// beside the memory-read floor and a NumPy peer.
    Bench(bench::BenchArgs),
    /// Rebuild a solve folder's report.html (one self-contained page), or render its relight
    /// on the CPU.
    Report(report::ReportArgs),
    /// Turn a solve into an engine-ready material: flattening, height, seamless tile,
    /// roughness mips, engine textures, DDS, glTF.
    Derive(derive::DeriveArgs),
    /// Measure the estimators against ground truth on DiLiGenT-layout sets (real captures),
    /// over deterministic light subsets, beside the trimmed and published anchors.
    Eval(eval::EvalArgs),
}

#[derive(Args)]
struct DemoArgs {
    /// Folder for the demo's capture set (`capture/`) and maps (`maps/`); replaced if present.
    #[arg(long, default_value = "psscan-demo")]
    out: PathBuf,
    #[command(flatten)]
    scene: SceneArgs,
    #[command(flatten)]
    solve: SolveFlags,
    /// Capture through the LED firmware running in its emulator (firmware/build) and the
    /// simulated camera, over psscan's real serial code, then solve.
    #[arg(long)]
    firmware_sim: bool,
}

#[derive(Args)]
struct SynthArgs {
    /// Folder to write the capture set into.
    #[arg(long)]
    out: PathBuf,
    /// Rig description (default: the embedded default rig).
    #[arg(long)]
    rig: Option<PathBuf>,
    /// Replace an existing capture set in the folder.
    #[arg(long)]
    force: bool,
    /// Calibration bundle folder: the set is written as a capture with this bundle would be
    /// (its rig copy is the bundle's calibrated rig, its manifest cites the bundle), while the
    /// scene is rendered with --rig, the rig as built.
    #[arg(long, value_name = "BUNDLE_DIR")]
    calibration: Option<PathBuf>,
    #[command(flatten)]
    scene: SceneArgs,
}

#[derive(Args)]
struct SceneArgs {
    /// Image width in pixels (a centred crop of the rig's sensor).
    #[arg(long, default_value_t = 2048, value_parser = values::positive_count)]
    width: usize,
    /// Image height in pixels.
    #[arg(long, default_value_t = 1536, value_parser = values::positive_count)]
    height: usize,
    /// Sensor pixels per image pixel (e.g. 4 covers 4x the field at 1/16 of the pixels).
    #[arg(long, default_value_t = 1.0, value_parser = values::positive, allow_negative_numbers = true)]
    step: f64,
    /// Render cast shadows from the relief.
    #[arg(long)]
    shadows: bool,
    /// Add the cloth sheen lobe (seed eq. 23).
    #[arg(long)]
    sheen: bool,
    /// No photon or read noise (rounding and clipping remain).
    #[arg(long)]
    noise_free: bool,
    /// Seed of the sensor noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// How frames are stored: dn16 (16-bit RGB PNGs of raw numbers) or dng (Bayer RAW files,
    /// decoded like a camera's).
    #[arg(long, value_enum, default_value_t = EncodingArg::Dn16)]
    encoding: EncodingArg,
}

#[derive(Clone, Copy, ValueEnum)]
enum EncodingArg {
    Dn16,
    Dng,
}

impl SceneArgs {
    fn spec(&self) -> SynthSpec {
        let mut spec = SynthSpec::demo();
        spec.width = self.width;
        spec.height = self.height;
        spec.step = self.step;
        spec.scene.shadows = self.shadows;
        spec.scene.shadow_fill = if self.shadows { 0.15 } else { 0.0 };
        spec.scene.sheen = self.sheen.then(Sheen::default);
        spec.noise_seed = (!self.noise_free).then_some(self.seed);
        spec.encoding = match self.encoding {
            EncodingArg::Dn16 => FrameEncoding::Dn16,
            EncodingArg::Dng => FrameEncoding::Dng,
        };
        spec
    }
}

#[derive(Args)]
struct SolveArgs {
    /// Capture set folders (manifest.toml) or DiLiGenT-layout folders (filenames.txt,
    /// light_directions.txt, ...).
    #[arg(required = true)]
    sets: Vec<PathBuf>,
    /// Folder for the maps and report.json; with several sets, each gets OUT/<set folder name>.
    #[arg(long)]
    out: PathBuf,
    /// Rig description to use instead of the copy stored in each set (and instead of any
    /// calibration bundle the set cites).
    #[arg(long, conflicts_with_all = ["calibration", "no_calibration"])]
    rig: Option<PathBuf>,
    /// Calibration bundle folder: solve with its calibrated rig and per-light gain grids.
    /// Default: the bundle each set's manifest cites, from the path recorded there. A set that
    /// cites another bundle, or this one before its files changed, is refused.
    #[arg(long, value_name = "BUNDLE_DIR")]
    calibration: Option<PathBuf>,
    /// Use no calibration bundle, even one the set cites: solve with the set's rig copy.
    #[arg(long, conflicts_with = "calibration")]
    no_calibration: bool,
    /// Use --calibration's bundle even where a set cites another one (the report records
    /// both).
    #[arg(long, requires = "calibration")]
    allow_calibration_mismatch: bool,
    /// Replace existing solves in the output folders.
    #[arg(long)]
    force: bool,
    /// Sets solved at the same time (each set is parallel inside; more sets at once need
    /// more memory).
    #[arg(long, default_value_t = BatchOptions::default().parallel_sets,
          value_parser = values::positive_count)]
    parallel_sets: usize,
    #[command(flatten)]
    solve: SolveFlags,
}

#[derive(Args, Clone)]
struct SolveFlags {
    /// Per-pixel estimator: ls (least squares), robust (reject shadowed and highlighted
    /// lights everywhere), adaptive (least squares, robust only where the residual fails a
    /// chi-square test against the sensor noise).
    #[arg(long, value_enum, default_value_t = Estimator::Adaptive)]
    estimator: Estimator,
    /// Fit the velvet sheen lobe of seed 004 (eqs. 21-23) where the Lambertian model fails;
    /// the lobe's shape: f0 (Fresnel at normal incidence), alpha (width), amplitude.
    #[arg(long, num_args = 3, value_names = ["F0", "ALPHA", "AMPLITUDE"])]
    sheen_fit: Option<Vec<f64>>,
    /// How far real readings may depart from the surface model, as a fraction of the reading,
    /// added in quadrature to the sensor noise in the robust and adaptive tests (0: the noise
    /// model alone decides). For data whose noise model is rounding only, such as rendered
    /// benchmark sets.
    #[arg(long, default_value_t = 0.0, value_name = "FRACTION",
          value_parser = values::non_negative, allow_negative_numbers = true)]
    model_error: f64,
    /// Least-squares method.
    #[arg(long, value_enum, default_value_t = MethodArg::Fast)]
    method: MethodArg,
    /// Light model: near point lights (per-pixel directions and falloff) or distant lights.
    #[arg(long, value_enum, default_value_t = LightModelArg::Near)]
    light_model: LightModelArg,
    /// Store normal maps DirectX-style (+Y down) instead of OpenGL-style (+Y up).
    #[arg(long)]
    directx: bool,
    /// Do not write PNG maps.
    #[arg(long)]
    no_png: bool,
    /// Do not write EXR normal and albedo maps (the confidence EXR is always written).
    #[arg(long)]
    no_exr: bool,
    /// Do not write report.html (and frames_preview.jpg) beside the maps.
    #[arg(long)]
    no_report_html: bool,
    /// RAW frames: full (bilinear demosaic) or half (2x2 CFA binning, 4x fewer pixels).
    #[arg(long, value_enum, default_value_t = ResolutionArg::Full)]
    resolution: ResolutionArg,
    /// Do not subtract the set's all-off (dark) frame.
    #[arg(long)]
    no_dark: bool,
    /// Kernel precision. Default (and f64): the exact per-pixel kernel, which also predicts
    /// each pixel's error. f32 alone: the fast kernel, streaming f32 with tiles of 0.01
    /// degrees (normals within 0.02 degrees plus single-precision round-off of the exact
    /// kernel's) for the ls and adaptive estimators; robust and svd keep the exact kernel.
    #[arg(long, value_enum)]
    precision: Option<PrecisionArg>,
    /// Share light coefficients across tiles where that moves normals by at most this many
    /// degrees (streaming kernel; 0.01 with --precision f32 alone).
    #[arg(long, value_name = "DEG", value_parser = values::positive, allow_negative_numbers = true)]
    tile_tolerance: Option<f64>,
    /// PNG deflate effort: fast (default) or best (smaller files for archives, much slower).
    #[arg(long, value_enum, default_value_t = PngCompressionArg::Fast)]
    png_compression: PngCompressionArg,
    /// Print where the wall time went, stage by stage (also in report.json, "stages").
    #[arg(long)]
    timings: bool,
    /// Solve the luminance alone: the normal map, with the luminance albedo in every channel.
    #[arg(long)]
    normal_only: bool,
    /// Solve only this pixel rectangle of the frames: x,y,width,height.
    #[arg(long, value_name = "X,Y,W,H", value_parser = values::roi)]
    roi: Option<Roi>,
    /// 2: solve 2x2-binned frames (a half-resolution preview, 4x fewer pixels).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
    bin: u8,
    /// Background mask: none, auto (found from the frames), or an image file the size of
    /// the frames (non-zero = sample); no work is done outside it.
    #[arg(long, default_value = "none", value_name = "none|auto|FILE")]
    background: String,
}

#[derive(Clone, Copy, ValueEnum)]
enum PngCompressionArg {
    Fast,
    Best,
}

#[derive(Clone, Copy, PartialEq, ValueEnum)]
enum PrecisionArg {
    F64,
    F32,
}

#[derive(Clone, Copy, ValueEnum)]
enum ResolutionArg {
    Full,
    Half,
}

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    /// 3x3 normal equations, closed form.
    Fast,
    /// SVD of the light matrix (the seed's method).
    Svd,
}

#[derive(Clone, Copy, ValueEnum)]
enum LightModelArg {
    Near,
    Distant,
}

impl SolveFlags {
    fn job(&self) -> anyhow::Result<SolveJob> {
        let method = match self.method {
            MethodArg::Fast => Method::NormalEquations,
            MethodArg::Svd => Method::Svd,
        };
        let precision = match (self.precision, self.tile_tolerance) {
            (Some(PrecisionArg::F64), _) => Precision::F64,
            (Some(PrecisionArg::F32), _) | (None, Some(_)) => Precision::F32,
            (None, None) => Precision::F64,
        };
        // `--precision f32` alone: the fast kernel, streaming f32 with tiles (within
        // solve::default_kernel_tolerance_deg of the exact kernel). The robust estimator and the
        // SVD method have no streaming form, so with them the flag is refused by name. No kernel
        // asked for: the exact kernel, the one that predicts each pixel's error from the noise.
        let tiles = match (self.precision, self.tile_tolerance) {
            (Some(PrecisionArg::F32), None) => Some(DEFAULT_TILE_TOLERANCE_DEG),
            (_, tiles) => tiles,
        };
        let kernel = KernelChoice::new(self.estimator, method, precision, tiles, false)?;
        let options = SolveOptions {
            kernel,
            light_model: match self.light_model {
                LightModelArg::Near => LightModel::Near,
                LightModelArg::Distant => LightModel::Distant,
            },
            normal_only: self.normal_only,
            robust: RobustOptions {
                sheen: self.sheen_fit.as_deref().map(|v| SheenModel {
                    f0: [v[0]; 3],
                    alpha: v[1],
                    amplitude: v[2],
                }),
                relative_model_error: self.model_error,
                ..RobustOptions::default()
            },
            ..SolveOptions::default()
        };
        Ok(SolveJob {
            region: RegionJob {
                roi: self.roi,
                bin: self.bin as usize,
                background: Background::parse(&self.background),
            },
            options,
            maps: MapOptions {
                normal_convention: if self.directx {
                    NormalConvention::DirectX
                } else {
                    NormalConvention::OpenGl
                },
                png: !self.no_png,
                exr: !self.no_exr,
                // Set from the frames' own colour matrix when they are camera RAW files.
                display_matrix: None,
                report_html: !self.no_report_html,
                png_compression: match self.png_compression {
                    PngCompressionArg::Fast => PngCompression::Fast,
                    PngCompressionArg::Best => PngCompression::Best,
                },
            },
            rig: None,
            force: false,
            inputs: Vec::new(),
            calibration: Default::default(),
            allow_calibration_mismatch: false,
            develop: DevelopOptions {
                resolution: match self.resolution {
                    ResolutionArg::Full => Resolution::Full,
                    ResolutionArg::Half => Resolution::Half,
                },
                subtract_dark: !self.no_dark,
            },
        })
    }
}

/// Runs the CLI; returns the process exit code.
pub fn run() -> i32 {
    PROCESS_START.get_or_init(std::time::Instant::now);
    quiet_closed_pipe_panics();
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(err) => return usage_error(err),
    };
    // A corrupt RAW file makes some of rawler's decoders panic; psscan catches that and reports
    // the file, so the panic's own message is noise.
    psscan::raw::quiet_decoder_panics();
    let bars = Bars::new(cli.quiet);
    signals::install(cli.command.describe(), bars.slot());
    let finished = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let outcome = dispatch(&cli, &bars);
        exit_code(&cli, outcome)
    }));
    match finished {
        Ok(code) => code,
        // The reader of stdout went away (`| head`): the command has unwound, guards included.
        Err(payload) if is_closed_pipe_message(panic_text(payload.as_ref())) => 141,
        Err(payload) => std::panic::resume_unwind(payload),
    }
}

/// Runs the chosen command.
fn dispatch(cli: &Cli, bars: &Bars) -> anyhow::Result<()> {
    match &cli.command {
        Command::Demo(args) => demo(args, cli.json, bars),
        Command::Synth(args) => synth(args, cli.json, bars),
        Command::Solve(args) => solve(args, cli.json, bars),
        Command::Capture(args) => capture::capture(args, cli.json, bars),
        Command::Lights(args) => capture::lights(args, cli.json),
        Command::Calibrate(args) => calibrate::calibrate(args, cli.json, bars),
        Command::Bench(args) => bench::bench(args, cli.json, bars),
        Command::Report(args) => report::report(args, cli.json),
        Command::Derive(args) => derive::derive(args, cli.json, bars),
        Command::Eval(args) => eval::eval(args, cli.json, bars),
    }
}

/// Set once a command has printed its JSON object, so a failure after it adds no second one.
pub(super) static JSON_PRINTED: AtomicBool = AtomicBool::new(false);

impl Command {
    /// The command, for messages about the run ("stopped `psscan solve` ...").
    fn describe(&self) -> &'static str {
        match self {
            Command::Demo(_) => "`psscan demo`",
            Command::Synth(_) => "`psscan synth`",
            Command::Solve(_) => "`psscan solve`",
            Command::Capture(_) => "`psscan capture`",
            Command::Lights(_) => "`psscan lights`",
            Command::Calibrate(_) => "`psscan calibrate`",
            Command::Bench(_) => "`psscan bench`",
            Command::Report(_) => "`psscan report`",
            Command::Derive(_) => "`psscan derive`",
            Command::Eval(_) => "`psscan eval`",
        }
    }
}

fn load_rig(path: &Option<PathBuf>) -> psscan::Result<Rig> {
    match path {
        Some(p) => Rig::load(p),
        None => Ok(Rig::default_rig()),
    }
}

pub(super) fn print_json<T: serde::Serialize>(value: &T) {
    JSON_PRINTED.store(true, Ordering::Relaxed);
    println!(
        "{}",
        serde_json::to_string_pretty(value).expect("serialisable")
    );
}

fn demo(args: &DemoArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    if args.firmware_sim {
        return capture::demo_firmware_sim(&args.out, &args.scene, &args.solve.job()?, json, bars);
    }
    let spec = args.scene.spec();
    let summary = synth::run_demo(&args.out, &spec, &args.solve.job()?, bars)?;
    if json {
        print_json(&summary);
    } else {
        print_demo(&summary);
    }
    Ok(())
}

fn print_demo(s: &DemoSummary) {
    let t = |k: &str| s.timings_s.get(k).copied().unwrap_or(0.0);
    println!(
        "psscan demo: {}x{} synthetic textile, rig \"{}\" ({} LEDs), {} pixels solved",
        s.width, s.height, s.rig, s.lights, s.solved_pixels
    );
    println!(
        "  normal error  mean {:.3} deg, median {:.3}, p95 {:.3} (sensor-noise model predicts mean {})",
        s.normal_error_deg.mean,
        s.normal_error_deg.median,
        s.normal_error_deg.p95,
        deg_or_na(s.predicted_normal_error_deg.mean)
    );
    println!("  albedo error  {}", albedo_error_text(&s.albedo_rel_error));
    println!(
        "  time          render+write {:.1} s, decode {:.1} s, solve {:.1} s, write maps {:.1} s, total {:.1} s",
        t("synth_scene") + t("synth_render_and_write"),
        t("solve_decode"),
        t("solve_solve"),
        t("solve_write"),
        t("total")
    );
    print_warnings(&s.warnings);
    println!("  capture set   {}", s.paths.capture.display());
    println!("  maps          {}", s.paths.maps.display());
}

fn synth(args: &SynthArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let rig = load_rig(&args.rig)?;
    let spec = args.scene.spec();
    let bundle = args
        .calibration
        .as_deref()
        .map(psscan::calibration::bundle::read)
        .transpose()?;
    let inputs: Vec<&Path> = args
        .rig
        .iter()
        .chain(&args.calibration)
        .map(|p| p.as_path())
        .collect();
    let outcome = synth::write_synthetic_set_from(
        &rig,
        &spec,
        &args.out,
        args.force,
        bundle.as_ref(),
        &inputs,
        bars,
    )?;
    if json {
        print_json(&outcome);
    } else {
        println!(
            "wrote synthetic capture set {} ({}x{}, {} lights + dark frame, ground truth in {}/truth)",
            outcome.dir.display(),
            outcome.width,
            outcome.height,
            outcome.lights,
            outcome.dir.display()
        );
    }
    Ok(())
}

fn solve(args: &SolveArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let mut job = args.solve.job()?;
    job.force = args.force;
    // Every set of the run is an input of every solve in it (one set's output may not be, or
    // sit inside, another set), and so is the rig file.
    job.inputs = args.sets.iter().chain(&args.rig).cloned().collect();
    job.rig = args.rig.as_ref().map(|p| Rig::load(p)).transpose()?;
    job.calibration = match (&args.calibration, args.no_calibration) {
        (Some(dir), _) => CalibrationChoice::Bundle(dir.clone()),
        (None, true) => CalibrationChoice::Ignore,
        (None, false) => CalibrationChoice::Cited,
    };
    job.allow_calibration_mismatch = args.allow_calibration_mismatch;
    if let [set] = args.sets.as_slice() {
        let report = sets::solve_set(set, &args.out, &job, bars)?;
        if json {
            print_json(&report);
        } else {
            print_solve(set, &args.out, &report);
            if args.solve.timings {
                print_stage_table(&report);
            }
        }
        return Ok(());
    }
    let options = BatchOptions {
        parallel_sets: args.parallel_sets,
    };
    let summary = sets::solve_sets(&args.sets, &args.out, &job, options, bars);
    if json {
        print_json(&summary);
    } else {
        print_batch(&summary);
    }
    if summary.failed > 0 {
        anyhow::bail!(
            "{} of {} sets failed (named above){}",
            summary.failed,
            summary.sets.len(),
            if summary.solved > 0 {
                "; the others were solved"
            } else {
                ""
            }
        );
    }
    Ok(())
}

/// The solve's stage table, and the whole process's wall time beside it.
fn print_stage_table(report: &psscan::maps::Report) {
    println!("  where the time went:");
    print!(
        "{}",
        psscan::timing::format_table(&report.stages, report.total_s())
    );
    if let Some(started) = PROCESS_START.get() {
        println!(
            "  {:<24} {:>8.3} s (the process so far, its start and the report's write included)",
            "process",
            started.elapsed().as_secs_f64()
        );
    }
}

/// When `run` started: the process's wall time for `--timings`.
static PROCESS_START: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();

fn print_batch(summary: &BatchSummary) {
    for o in &summary.sets {
        match (&o.summary, &o.error) {
            (Some(s), _) => {
                let truth = s
                    .normal_error_deg
                    .map(|e| format!(", normal error {e:.3} deg against truth"))
                    .unwrap_or_default();
                println!(
                    "solved  {} -> {} ({}x{}, {} pixels, predicted {}{truth}, {:.1} s)",
                    o.set.display(),
                    o.out.display(),
                    s.width,
                    s.height,
                    s.solved_pixels,
                    deg_or_na(s.predicted_normal_error_deg),
                    s.seconds
                );
                print_warnings(&s.warnings);
            }
            (None, error) => eprintln!(
                "FAILED  {}: {}",
                o.set.display(),
                error.as_deref().unwrap_or("unknown error")
            ),
        }
    }
    println!(
        "{} solved, {} failed, {:.1} s",
        summary.solved, summary.failed, summary.seconds
    );
}

fn print_solve(set: &Path, out: &Path, report: &psscan::maps::Report) {
    let solved = report.pixels.get("solved").copied().unwrap_or(0);
    let total = report.width * report.height;
    println!(
        "solved {}: {}x{}, {} of {} pixels ({:.2} %), predicted normal error {}",
        set.display(),
        report.width,
        report.height,
        solved,
        total,
        100.0 * solved as f64 / total.max(1) as f64,
        deg_or_na(report.predicted_normal_error_deg.mean)
    );
    for (name, count) in &report.pixels {
        if *name != "solved" && *count > 0 {
            println!("  {name}: {count} pixels");
        }
    }
    if let Some(truth) = &report.truth {
        println!(
            "  against ground truth: normal error mean {:.3} deg (p95 {:.3}), albedo error {}",
            truth.normal_error_deg.mean,
            truth.normal_error_deg.p95,
            albedo_error_text(&truth.albedo_rel_error)
        );
    }
    if let Some(truth) = &report.normal_truth {
        println!(
            "  against ground-truth normals over the mask ({} pixels, {} solved): mean {:.3} deg, median {:.3}",
            truth.mask_pixels,
            truth.solved,
            truth.normal_error_deg.mean,
            truth.normal_error_deg.median
        );
    }
    match (&report.calibration, &report.calibration_cited_by_set) {
        (Some(c), _) => println!(
            "  calibration: bundle {} (sha256 {}) at {}",
            c.id,
            c.sha256,
            c.path.display()
        ),
        (None, Some(c)) => println!(
            "  calibration: none used; the set cites bundle {} (sha256 {})",
            c.id, c.sha256
        ),
        (None, None) => println!("  calibration: none (the set's rig copy)"),
    }
    if let Some(c) = report
        .calibration_cited_by_set
        .as_ref()
        .filter(|_| report.calibration.is_some())
    {
        println!(
            "  WARNING: the set cites another bundle, {} (sha256 {})",
            c.id, c.sha256
        );
    }
    if let Some(decode) = &report.decode {
        println!(
            "  frames: {} ({}); dark frame: {}",
            decode.encoding, decode.method, decode.dark_frame
        );
    }
    print_warnings(&report.warnings);
    println!(
        "  wrote {} in {:.1} s",
        out.display(),
        report.timings_s.get("total").copied().unwrap_or(0.0)
    );
}

/// A predicted error in degrees, or `n/a` where it was not computed (NaN).
pub(crate) fn deg_or_na(value: f64) -> String {
    if value.is_finite() {
        format!("{value:.3} deg")
    } else {
        "n/a".to_string()
    }
}

/// Mean and median relative albedo error, or why there is none.
fn albedo_error_text(error: &psscan::eval::Stats) -> String {
    if error.mean.is_finite() {
        format!(
            "mean {:.2} %, median {:.2} %",
            100.0 * error.mean,
            100.0 * error.median
        )
    } else {
        "n/a (--normal-only: the albedo is the luminance, not solved per channel)".to_string()
    }
}

fn print_warnings(warnings: &[String]) {
    for w in warnings {
        println!("  WARNING: {w}");
    }
}
