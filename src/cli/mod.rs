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
mod hints;
mod outcome;
mod progress;
mod report;
mod signals;
mod solve;
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
use solve::*;

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

    /// How a capture this command stopped is completed: the calibration wizard resumes by
    /// itself, `psscan capture` with `--resume`.
    fn resume(&self) -> hints::Resume {
        match self {
            Command::Calibrate(_) => hints::Resume::SameCommand,
            _ => hints::Resume::WithFlag,
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
