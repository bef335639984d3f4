//! The one way a set is solved: stage the output folder, open and decode the set, select the
//! region, solve, write the maps (reading the truth and comparing with it meanwhile), write
//! `report.json` and `report.html`, and commit the folder.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::{open, SetSource, SolveJob, Truth};
use crate::error::{Error, Result};
use crate::eval;
use crate::fsutil::{check_outside_inputs, write_atomic, StagedDir};
use crate::maps::derive::{self, DeriveSource, SolvedMaps};
use crate::maps::html::derived::DERIVED_DIR;
use crate::maps::html::MapFigures;
use crate::maps::report::Histogram;
use crate::maps::{self, MapOptions, Report, WrittenMaps};
use crate::plane::{FrameRelease, Frames, Mask, SensorWindow};
use crate::progress::Progress;
use crate::raw::DecodeInfo;
use crate::region::{region_truth, select_region, RegionInfo};
use crate::solve::consistency::{frame_consistency, BLOCKS};
use crate::solve::{self, LightSource, NoiseModel, SolveInput, SolveResult};
use crate::timing::{Busy, StageClock};

/// The stage of reading a set's ground truth (beside the maps' writing).
pub const TRUTH_READ_STAGE: &str = "read truth";

/// The stage of deriving the material from the solved maps (solve with derive options).
pub const DERIVE_STAGE: &str = "derive";

/// The stage of comparing the solve with the ground truth (beside the maps' writing).
pub const TRUTH_COMPARE_STAGE: &str = "compare with truth";

/// The stage of checking that the frames agree with one another.
pub const CONSISTENCY_STAGE: &str = "frame consistency";

/// The stage of building `report.html`.
pub const REPORT_PAGE_STAGE: &str = "report page";

/// The stage of building the page's map figures while the maps are written.
pub const PAGE_FIGURES_STAGE: &str = "report page figures";

/// Where the set to solve comes from.
enum SetRef<'a> {
    /// A folder of either kind, opened inside the solve's clock.
    Folder(&'a Path),
    /// A source already opened (a synthetic scene in memory).
    Opened(&'a dyn SetSource),
}

/// Solves the set in `dir` (a psscan capture set or a DiLiGenT-layout folder) and writes maps,
/// `report.json` and, when asked, `report.html` into `out`. The output is built beside `out`
/// and renamed into place when complete.
pub fn solve_set(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<Report> {
    solve_set_reusing(dir, out, job, progress, &mut None)
}

/// [`solve_set`], solving into `buffers` (a previous set's result, when it has the same size)
/// and leaving this set's result there: a batch of same-size sets then pays for fresh output
/// memory once, not per set (see `solve::solve_reusing`).
pub fn solve_set_reusing(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
    buffers: &mut Option<SolveResult>,
) -> Result<Report> {
    run(SetRef::Folder(dir), out, job, progress, buffers)
}

/// [`solve_set`] for a source already opened (its location is not read: only `job.inputs`
/// are the run's other inputs).
pub fn solve_source(
    source: &dyn SetSource,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<Report> {
    run(SetRef::Opened(source), out, job, progress, &mut None)
}

/// The figures of a solve against its set's ground truth.
struct TruthFigures {
    comparison: TruthComparisonKind,
    histogram: Histogram,
}

enum TruthComparisonKind {
    Surface(eval::TruthComparison),
    Normals(eval::MaskedNormalComparison),
}

/// What decoding and solving the set produced.
struct Solved {
    result: SolveResult,
    decode: DecodeInfo,
    window: SensorWindow,
    region: Option<RegionInfo>,
    /// The solve's mask (the region's, else the set's own), which the truth is compared over.
    mask: Option<Mask>,
    /// The frames' size before the region was cut out of them (the truth's size).
    frame_size: (usize, usize),
    maps: MapOptions,
    decode_s: f64,
}

/// What writing the maps produced.
struct Written<'a> {
    outputs: WrittenMaps,
    truth: Option<TruthFigures>,
    write_s: f64,
    /// The page's map figures, where they were built while the maps were written.
    figures: Option<MapFigures<'a>>,
}

fn run(
    set: SetRef,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
    buffers: &mut Option<SolveResult>,
) -> Result<Report> {
    let inputs = match set {
        SetRef::Folder(dir) => job.input_paths(dir),
        SetRef::Opened(_) => job.inputs.iter().map(PathBuf::as_path).collect(),
    };
    let mut clock = StageClock::start();
    let stage = StagedDir::create(out, job.force, &inputs)?;
    let opened;
    let source: &dyn SetSource = match set {
        SetRef::Opened(source) => source,
        SetRef::Folder(dir) => {
            opened = clock.time("open set", || -> Result<_> {
                let source = open(dir, job)?;
                let others = source.other_inputs();
                check_outside_inputs(
                    out,
                    &others.iter().map(PathBuf::as_path).collect::<Vec<_>>(),
                )?;
                Ok(source)
            })?;
            &*opened
        }
    };
    let solved = decode_and_solve(source, stage.path(), job, progress, buffers, &mut clock)?;
    let written = write_outputs(source, stage.path(), job, &solved, &mut clock)?;

    let report_start = clock.elapsed();
    let truth = written.truth;
    let mut report = clock.time("report", || {
        let outputs = relocate(written.outputs.clone(), out);
        let location = source.location();
        let mut report = Report::new(
            location,
            &source.rig_name(),
            &solved.result,
            &job.options,
            outputs,
            solved.decode.binned(),
        );
        report.maps = solved.maps.clone();
        source.describe(&mut report, &solved.window);
        if let Some(figures) = truth {
            match figures.comparison {
                TruthComparisonKind::Surface(c) => report.set_truth(c),
                TruthComparisonKind::Normals(c) => report.normal_truth = Some(c),
            }
            report.normal_error_histogram = Some(figures.histogram);
        }
        if let Some(region) = solved.region.clone() {
            report.set_region(region);
        }
        report
    });
    report.decode = Some(solved.decode.clone());
    let report_s = clock.elapsed() - report_start;
    if job.derive.is_some() {
        report.derived = Some(clock.time(DERIVE_STAGE, || {
            derive_into(
                stage.path(),
                out,
                &solved.result,
                &solved.maps,
                &report,
                job,
                progress,
            )
        })?);
    }
    report.timings_s = BTreeMap::from([
        ("decode".to_string(), solved.decode_s),
        ("solve".to_string(), clock.seconds("solve")),
        ("write".to_string(), written.write_s),
        ("report".to_string(), report_s),
    ]);
    report.set_stages(&clock);
    let report_path = stage.path().join(maps::REPORT_FILE);
    report.write(&report_path)?;
    if job.maps.report_html {
        // The page embeds the report as written above; its own build time is added to the
        // report afterwards (a page cannot hold the time it took to build itself).
        clock.time(REPORT_PAGE_STAGE, || {
            // With a derive, the figures are built now: they show its height and roughness.
            let figures = written.figures.unwrap_or_else(|| {
                MapFigures::of_solve(
                    stage.path(),
                    &solved.result,
                    solved.maps.display_matrix.as_ref(),
                )
            });
            maps::html::write_report_page_from(stage.path(), figures)
        })?;
        report.set_stages(&clock);
        report.write(&report_path)?;
    }
    stage.commit(job.force, &inputs)?;
    *buffers = Some(solved.result);
    Ok(report)
}

/// Decodes, selects the region and solves (the frame previews go into `dir`, the staged
/// folder).
fn decode_and_solve(
    source: &dyn SetSource,
    dir: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
    buffers: &mut Option<SolveResult>,
    clock: &mut StageClock,
) -> Result<Solved> {
    let (frames, decode) = source.load(&job.develop, progress, clock)?;
    let decode_s = clock.elapsed();
    let (width, height) = (frames.width, frames.height);
    let lights = source.lights();
    let noise = clock.time("noise model", || source.noise(&decode));
    let own_mask = source.mask(&frames)?;
    clock.time(CONSISTENCY_STAGE, || {
        check_consistency(source, &frames, &lights, &noise, own_mask.as_ref(), job)
    })?;
    let (mut frames, region_mask, noise, region_info) = clock.time("region", || {
        select_region(frames, &lights, noise, &job.region)
    })?;
    let mask = region_mask.or(own_mask);
    if job.maps.report_html {
        clock.time("frame previews", || {
            maps::html::write_frame_strip(&frames, dir)
        })?;
    }
    // Nothing reads the frames after the solve: it gives their rows back as it goes.
    let mut release = FrameRelease::new(&mut frames);
    let input = SolveInput {
        frames: &frames,
        lights,
        noise,
        exposure: source.exposure(),
        mask: mask.as_ref(),
    };
    let result = clock.time("solve", || {
        // SAFETY: the frames are this function's, lent to nothing but the solve.
        unsafe {
            solve::solve_releasing(&input, &job.options, progress, buffers.take(), &mut release)
        }
    })?;
    let window = frames.window;
    clock.time("free frames", || drop(frames));

    let maps = MapOptions {
        display_matrix: job.maps.display_matrix.or(decode.camera_to_srgb),
        ..job.maps.clone()
    };
    Ok(Solved {
        result,
        decode,
        window,
        region: (!job.region.is_full()).then_some(region_info),
        mask,
        frame_size: (width, height),
        maps,
        decode_s,
    })
}

/// Writes the maps into `dir` (the staged folder), reading the set's ground truth and
/// comparing with it meanwhile, and building the page's map figures when the page is asked
/// for and no derive is (the page shows a derive, which comes after the maps).
fn write_outputs<'a>(
    source: &dyn SetSource,
    dir: &Path,
    job: &SolveJob,
    solved: &'a Solved,
    clock: &mut StageClock,
) -> Result<Written<'a>> {
    let result = &solved.result;
    let figures_now = job.maps.report_html && job.derive.is_none();
    // Reading EXRs, comparing, building figures and writing share the cores better than each
    // alone: the map writers wait for the disk.
    let write_start = clock.elapsed();
    let mut stages = maps::MAP_STAGES.to_vec();
    stages.extend([TRUTH_READ_STAGE, TRUTH_COMPARE_STAGE, PAGE_FIGURES_STAGE]);
    let (outputs, (truth, figures)) = clock.time_shared(&stages, "write maps", |busy| {
        rayon::join(
            || maps::write_maps_timed(result, dir, &solved.maps, busy),
            || {
                rayon::join(
                    || truth_figures(source, solved, job, busy),
                    || {
                        figures_now.then(|| {
                            busy.time(PAGE_FIGURES_STAGE, || {
                                let matrix = solved.maps.display_matrix.as_ref();
                                MapFigures::of_solve(dir, result, matrix)
                            })
                        })
                    },
                )
            },
        )
    });
    Ok(Written {
        outputs: outputs?,
        truth: truth?,
        write_s: clock.elapsed() - write_start,
        figures,
    })
}

/// Reads the set's ground truth, where it has one, and compares the solve with it.
fn truth_figures(
    source: &dyn SetSource,
    solved: &Solved,
    job: &SolveJob,
    busy: &Busy,
) -> Result<Option<TruthFigures>> {
    let (width, height) = solved.frame_size;
    let truth = busy.time(TRUTH_READ_STAGE, || {
        source.truth(width, height, &solved.decode)
    })?;
    truth
        .map(|truth| {
            busy.time(TRUTH_COMPARE_STAGE, || {
                compare(&solved.result, truth, solved.mask.as_ref(), job)
            })
        })
        .transpose()
}

/// Refuses a set with a frame that disagrees with what the other frames say the surface is
/// (a frame decoded to in-range garbage), naming the frame's file.
fn check_consistency(
    source: &dyn SetSource,
    frames: &Frames,
    lights: &LightSource,
    noise: &NoiseModel,
    mask: Option<&Mask>,
    job: &SolveJob,
) -> Result<()> {
    let consistency = frame_consistency(frames, lights, job.options.light_model, noise, mask)?;
    let names = source.frame_names();
    let name = |k: usize| {
        names
            .get(k)
            .cloned()
            .unwrap_or_else(|| format!("light {k}"))
    };
    let problems: Vec<String> = (consistency.inconsistent().into_iter())
        .map(|k| {
            let f = &consistency.frames[k];
            format!(
                "{}: in the image block at column {}, row {} of {BLOCKS}x{BLOCKS} its residual from the \
                 other frames' fit is {:.1} times the median frame's there and {:.0} times its \
                 noise",
                name(k),
                f.worst_block.0,
                f.worst_block.1,
                f.worst_ratio,
                f.worst_scale
            )
        })
        .collect();
    if problems.is_empty() {
        return Ok(());
    }
    Err(Error::capture_set(
        source.location(),
        format!(
            "frames that disagree with the rest of the set (decoded to garbage: a damaged file \
             whose checksum was updated, or a fault in the camera): {}; re-shoot them",
            problems.join("; ")
        ),
    ))
}

/// The solve against the set's ground truth: surface truth cropped and binned as the frames
/// were, over every pixel; normal truth over the solve's mask.
fn compare(
    result: &SolveResult,
    truth: Truth,
    mask: Option<&Mask>,
    job: &SolveJob,
) -> Result<TruthFigures> {
    match truth {
        Truth::Surface { normal, albedo } => {
            let (normal, albedo) = region_truth((normal, albedo), &job.region)?;
            let errors = eval::solved_normal_errors_deg(result, &normal);
            let comparison = eval::compare_with_errors(result, &errors, &albedo);
            let histogram = Histogram::of_errors(&errors);
            Ok(TruthFigures {
                comparison: TruthComparisonKind::Surface(comparison),
                histogram,
            })
        }
        Truth::Normals(normal) => {
            let everywhere = Mask::new(result.width, result.height, true);
            let mask = mask.unwrap_or(&everywhere);
            let errors: Vec<f64> = (eval::normal_errors_deg(result, &normal).into_iter())
                .zip(&mask.data)
                .filter_map(|(e, &inside)| e.filter(|_| inside))
                .collect();
            Ok(TruthFigures {
                comparison: TruthComparisonKind::Normals(eval::compare_normals_over_mask(
                    result, &normal, mask,
                )),
                histogram: Histogram::of_errors(&errors),
            })
        }
    }
}

/// Runs `derive` on the solved maps into the staged folder's `derived/`, and returns its
/// report with the files named under the final folder (`out/derived/...`).
fn derive_into(
    stage: &Path,
    out: &Path,
    result: &SolveResult,
    map_options: &MapOptions,
    report: &Report,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<serde_json::Value> {
    let options = job
        .derive
        .as_ref()
        .expect("called only with derive options");
    let maps = SolvedMaps::from_result(
        result,
        map_options.display_matrix.as_ref(),
        report.pixel_size_mm,
        job.options.robust.sheen,
    );
    let dir = stage.join(DERIVED_DIR);
    let mut derived = derive::derive(
        DeriveSource::Maps(Box::new(maps)),
        &dir,
        options,
        false,
        progress,
    )?;
    let final_dir = out.join(DERIVED_DIR);
    for (name, path) in derived.outputs.iter_mut() {
        *path = final_dir.join(name);
    }
    // derive.json named the files where they were staged; name them where they will be.
    let json = serde_json::to_string_pretty(&derived).expect("a derive report serialises");
    write_atomic(&dir.join(derive::DERIVE_REPORT), json.as_bytes())?;
    Ok(serde_json::to_value(&derived).expect("a derive report serialises"))
}

/// The written maps' paths under their final folder name.
pub fn relocate(outputs: WrittenMaps, out: &Path) -> WrittenMaps {
    let moved = |p: PathBuf| out.join(p.file_name().expect("map files have names"));
    WrittenMaps {
        normal_png: outputs.normal_png.map(moved),
        normal_exr: outputs.normal_exr.map(moved),
        albedo_png: outputs.albedo_png.map(moved),
        albedo_exr: outputs.albedo_exr.map(moved),
        confidence_exr: moved(outputs.confidence_exr),
    }
}
