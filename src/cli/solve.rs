//! `psscan solve`: its arguments (shared with the demo and batches), and the human summaries
//! of a solve and of a batch.

use super::hints::{with_hint, Resume};
use super::*;

#[derive(Args)]
pub(super) struct SolveArgs {
    /// Capture set folders (manifest.toml) or DiLiGenT-layout folders (filenames.txt,
    /// light_directions.txt, ...).
    #[arg(required = true)]
    pub(super) sets: Vec<PathBuf>,
    /// Folder for the maps and report.json; with several sets, each gets OUT/<set folder name>.
    #[arg(long)]
    pub(super) out: PathBuf,
    /// Rig description to use instead of the copy stored in each set (and instead of any
    /// calibration bundle the set cites).
    #[arg(long, conflicts_with_all = ["calibration", "no_calibration"])]
    pub(super) rig: Option<PathBuf>,
    /// Calibration bundle folder: solve with its calibrated rig and per-light gain grids.
    /// Default: the bundle each set's manifest cites, from the path recorded there. A set that
    /// cites another bundle, or this one before its files changed, is refused.
    #[arg(long, value_name = "BUNDLE_DIR")]
    pub(super) calibration: Option<PathBuf>,
    /// Use no calibration bundle, even one the set cites: solve with the set's rig copy.
    #[arg(long, conflicts_with = "calibration")]
    pub(super) no_calibration: bool,
    /// Use --calibration's bundle even where a set cites another one (the report records
    /// both).
    #[arg(long, requires = "calibration")]
    pub(super) allow_calibration_mismatch: bool,
    /// Replace existing solves in the output folders.
    #[arg(long)]
    pub(super) force: bool,
    /// Sets solved at the same time (each set is parallel inside; more sets at once need
    /// more memory).
    #[arg(long, default_value_t = BatchOptions::default().parallel_sets,
          value_parser = values::positive_count)]
    pub(super) parallel_sets: usize,
    #[command(flatten)]
    pub(super) solve: SolveFlags,
    /// Derived maps (`psscan derive`'s steps, written into OUT/derived/ and shown on the
    /// report page); none unless a step is named.
    #[command(flatten, next_help_heading = "Derive")]
    pub(super) derive: super::derive::DeriveFlags,
}

#[derive(Args, Clone)]
pub(super) struct SolveFlags {
    /// Per-pixel estimator: ls (least squares), robust (reject shadowed and highlighted
    /// lights everywhere), adaptive (least squares, robust only where the residual fails a
    /// chi-square test against the sensor noise).
    #[arg(long, value_enum, default_value_t = Estimator::Adaptive)]
    pub(super) estimator: Estimator,
    /// Fit the velvet sheen lobe of seed 004 (eqs. 21-23) where the Lambertian model fails;
    /// the lobe's shape: f0 (Fresnel at normal incidence), alpha (width), amplitude.
    #[arg(long, num_args = 3, value_names = ["F0", "ALPHA", "AMPLITUDE"])]
    pub(super) sheen_fit: Option<Vec<f64>>,
    /// How far real readings may depart from the surface model, as a fraction of the reading,
    /// added in quadrature to the sensor noise in the robust and adaptive tests (0: the noise
    /// model alone decides). For data whose noise model is rounding only, such as rendered
    /// benchmark sets.
    #[arg(long, default_value_t = 0.0, value_name = "FRACTION",
          value_parser = values::non_negative, allow_negative_numbers = true)]
    pub(super) model_error: f64,
    /// Least-squares method.
    #[arg(long, value_enum, default_value_t = MethodArg::Fast)]
    pub(super) method: MethodArg,
    /// Light model: near point lights (per-pixel directions and falloff) or distant lights.
    #[arg(long, value_enum, default_value_t = LightModelArg::Near)]
    pub(super) light_model: LightModelArg,
    /// Store normal maps DirectX-style (+Y down) instead of OpenGL-style (+Y up).
    #[arg(long)]
    pub(super) directx: bool,
    /// Do not write PNG maps.
    #[arg(long)]
    pub(super) no_png: bool,
    /// Do not write EXR normal and albedo maps (the confidence EXR is always written).
    #[arg(long)]
    pub(super) no_exr: bool,
    /// Do not write report.html (and frames_preview.jpg) beside the maps.
    #[arg(long)]
    pub(super) no_report_html: bool,
    /// RAW frames: full (bilinear demosaic) or half (2x2 CFA binning, 4x fewer pixels).
    #[arg(long, value_enum, default_value_t = ResolutionArg::Full)]
    pub(super) resolution: ResolutionArg,
    /// Do not subtract the set's all-off (dark) frame.
    #[arg(long)]
    pub(super) no_dark: bool,
    /// Kernel precision. Default (and f32 alone): the fast kernel, streaming f32 with tiles of
    /// 0.01 degrees (normals within 0.02 degrees plus single-precision round-off of the exact
    /// kernel's; the same pixels escalate to the robust fit) for the ls and adaptive
    /// estimators; robust and svd keep the exact kernel. f64: the exact per-pixel kernel.
    #[arg(long, value_enum)]
    pub(super) precision: Option<PrecisionArg>,
    /// Share light coefficients across tiles where that moves normals by at most this many
    /// degrees (streaming kernel; 0.01 with --precision f32 alone).
    #[arg(long, value_name = "DEG", value_parser = values::positive, allow_negative_numbers = true)]
    pub(super) tile_tolerance: Option<f64>,
    /// PNG deflate effort: fast (default) or best (smaller files for archives, much slower).
    #[arg(long, value_enum, default_value_t = PngCompressionArg::Fast)]
    pub(super) png_compression: PngCompressionArg,
    /// Print where the wall time went, stage by stage (also in report.json, "stages").
    #[arg(long)]
    pub(super) timings: bool,
    /// Solve the luminance alone: the normal map, with the luminance albedo in every channel.
    #[arg(long)]
    pub(super) normal_only: bool,
    /// Solve only this pixel rectangle of the frames: x,y,width,height.
    #[arg(long, value_name = "X,Y,W,H", value_parser = values::roi)]
    pub(super) roi: Option<Roi>,
    /// 2: solve 2x2-binned frames (a half-resolution preview, 4x fewer pixels).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
    pub(super) bin: u8,
    /// Background mask: none, auto (found from the frames), or an image file the size of
    /// the frames (non-zero = sample); no work is done outside it.
    #[arg(long, default_value = "none", value_name = "none|auto|FILE")]
    pub(super) background: String,
}

#[derive(Clone, Copy, ValueEnum)]
pub(super) enum PngCompressionArg {
    Fast,
    Best,
}

#[derive(Clone, Copy, PartialEq, ValueEnum)]
pub(super) enum PrecisionArg {
    F64,
    F32,
}

#[derive(Clone, Copy, ValueEnum)]
pub(super) enum ResolutionArg {
    Full,
    Half,
}

#[derive(Clone, Copy, ValueEnum)]
pub(super) enum MethodArg {
    /// 3x3 normal equations, closed form.
    Fast,
    /// SVD of the light matrix (the seed's method).
    Svd,
}

#[derive(Clone, Copy, ValueEnum)]
pub(super) enum LightModelArg {
    Near,
    Distant,
}

impl SolveFlags {
    pub(super) fn job(&self) -> anyhow::Result<SolveJob> {
        let method = match self.method {
            MethodArg::Fast => Method::NormalEquations,
            MethodArg::Svd => Method::Svd,
        };
        let precision = match (self.precision, self.tile_tolerance) {
            (Some(PrecisionArg::F64), _) | (None, None) => Precision::F64,
            (Some(PrecisionArg::F32), _) | (None, Some(_)) => Precision::F32,
        };
        // `--precision f32` alone: the fast kernel, streaming f32 with tiles (within
        // solve::default_kernel_tolerance_deg of the exact kernel). The robust estimator and the
        // SVD method have no streaming form, so with them the flag is refused by name. No kernel
        // asked for: the fast kernel where the estimator and method have it (it predicts each
        // pixel's error and screens the same pixels as the exact kernel), else the exact one.
        let tiles = match (self.precision, self.tile_tolerance) {
            (Some(PrecisionArg::F32), None) => Some(DEFAULT_TILE_TOLERANCE_DEG),
            (_, tiles) => tiles,
        };
        let kernel = KernelChoice::new(self.estimator, method, precision, tiles, false)?;
        let kernel = match (self.precision, self.tile_tolerance) {
            (None, None) => kernel.fast_where_possible(),
            _ => kernel,
        };
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
            derive: None,
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

pub(super) fn solve(args: &SolveArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
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
    if args.derive.requested() {
        job.derive = Some(args.derive.options(args.solve.directx)?);
    }
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
    let mut summary = sets::solve_sets(&args.sets, &args.out, &job, options, bars);
    // The library names what failed; the flag that gets past it is the CLI's to name.
    for set in &mut summary.sets {
        if let (Some(text), Some(failure)) = (&mut set.error, &set.failure) {
            *text = with_hint(std::mem::take(text), failure, Resume::WithFlag);
        }
    }
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
pub(super) fn print_stage_table(report: &psscan::maps::Report) {
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
pub(super) static PROCESS_START: std::sync::OnceLock<std::time::Instant> =
    std::sync::OnceLock::new();

pub(super) fn print_batch(summary: &BatchSummary) {
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

pub(super) fn print_solve(set: &Path, out: &Path, report: &psscan::maps::Report) {
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
        if let Some(backing) = &decode.backing {
            let [r, g, b] = backing.albedo;
            println!(
                "  holes: {} isolated pixels showed one material through the weave (albedo \
                 {r:.3} {g:.3} {b:.3}) and took its colour",
                backing.pixels
            );
        }
    }
    if let Some(derived) = report
        .derived
        .as_ref()
        .and_then(|d| d["outputs"].as_object())
    {
        let names: Vec<&str> = derived.keys().map(String::as_str).collect();
        println!(
            "  derived into {}: {}",
            out.join("derived").display(),
            names.join(", ")
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
pub(super) fn albedo_error_text(error: &psscan::eval::Stats) -> String {
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

pub(super) fn print_warnings(warnings: &[String]) {
    for w in warnings {
        println!("  WARNING: {w}");
    }
}
