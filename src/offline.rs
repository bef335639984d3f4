//! The offline solve of saved sets, one or hundreds: psscan capture sets (`manifest.toml`) and
//! sets in the DiLiGenT benchmark layout, each into its own output folder, with one progress
//! bar over the whole batch. A set that fails is reported and skipped; the others finish.
//! Every output folder is built under a temporary name and renamed into place when complete
//! (`fsutil::StagedDir`), so a crash never leaves a half-written map or a half-complete folder
//! under an output's name.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use serde::Serialize;

use crate::capture::diligent::{self, DiligentSet};
use crate::capture::{manifest::MANIFEST_FILE, CaptureSet};
use crate::error::{Error, Result};
use crate::eval;
use crate::fsutil::{create_dir_all, StagedDir};
use crate::maps::{self, Report};
use crate::pipeline::{self, SolveJob};
use crate::progress::Progress;
use crate::raw::{DecodeInfo, Resolution};
use crate::solve::{self, LightSource, NoiseModel, SolveInput, SolveResult};
use crate::timing::StageClock;

/// What kind of set a folder holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SetKind {
    /// A psscan capture set (`manifest.toml`).
    Capture,
    /// The DiLiGenT benchmark layout (`filenames.txt`, `light_directions.txt`, ...).
    Diligent,
}

/// Tells what `dir` holds, or why it is not a set.
pub fn set_kind(dir: &Path) -> Result<SetKind> {
    let meta = match std::fs::metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(Error::capture_set(dir, "no such folder: not a capture set"))
        }
        other => other.map_err(|e| Error::io(dir, e))?,
    };
    if !meta.is_dir() {
        return Err(Error::capture_set(
            dir,
            "is a file, not a capture set folder",
        ));
    }
    if dir.join(MANIFEST_FILE).is_file() {
        Ok(SetKind::Capture)
    } else if DiligentSet::is_diligent(dir) {
        Ok(SetKind::Diligent)
    } else {
        Err(Error::capture_set(
            dir,
            format!(
                "not a capture set: no {MANIFEST_FILE} (psscan) and no {} with {} (DiLiGenT \
                 layout)",
                diligent::FILENAMES,
                diligent::LIGHT_DIRECTIONS
            ),
        ))
    }
}

/// Solves the set in `dir` (either kind) into `out`.
pub fn solve_set(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<Report> {
    solve_set_reusing(dir, out, job, progress, &mut None)
}

/// [`solve_set`] solving into, and leaving its result in, `buffers` (as
/// `pipeline::solve_capture_set_reusing`): what each batch worker does from set to set.
pub fn solve_set_reusing(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
    buffers: &mut Option<SolveResult>,
) -> Result<Report> {
    match set_kind(dir)? {
        SetKind::Capture => pipeline::solve_capture_set_reusing(dir, out, job, progress, buffers),
        SetKind::Diligent => solve_diligent_into(dir, out, job, progress, buffers),
    }
}

/// Solves a DiLiGenT-layout set: distant lights from `light_directions.txt` (divided by
/// `light_intensities.txt`), the object mask, and, when `Normal_gt.mat` is present, the mean
/// angular error over the mask in the report (`normal_truth`).
///
/// The images carry no sensor description, so the noise model is 16-bit quantisation only
/// (`1/12 DN^2`): the dark threshold drops exact zeros (shadows) and the predicted error is a
/// lower bound for real photographs.
pub fn solve_diligent_set(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<Report> {
    solve_diligent_into(dir, out, job, progress, &mut None)
}

fn solve_diligent_into(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
    buffers: &mut Option<SolveResult>,
) -> Result<Report> {
    if !job.region.is_full() {
        return Err(Error::Unsupported(format!(
            "{}: --roi, --bin and --background apply to psscan capture sets, not DiLiGenT sets",
            dir.display()
        )));
    }
    if job.develop.resolution != Resolution::Full {
        return Err(Error::Unsupported(format!(
            "{}: half resolution is 2x2 CFA binning of RAW frames; DiLiGenT sets store RGB \
             images, solve them at full resolution",
            dir.display()
        )));
    }
    let inputs = job.input_paths(dir);
    let mut clock = StageClock::start();
    let stage = StagedDir::create(out, job.force, &inputs)?;
    let (set, frames, mask) = clock.time("decode", || -> Result<_> {
        let set = DiligentSet::open(dir)?;
        let frames = set.load_frames(progress)?;
        let mask = set.mask(frames.width, frames.height)?;
        Ok((set, frames, mask))
    })?;

    let input = SolveInput {
        frames: &frames,
        lights: LightSource::Directions {
            directions: &set.directions,
            intensities: &set.intensities,
        },
        noise: diligent_noise(),
        exposure: 1.0,
        mask: mask.as_ref(),
    };
    let result = clock.time("solve", || {
        solve::solve_reusing(&input, &job.options, progress, buffers.take())
    })?;
    if job.maps.report_html {
        clock.time("frame previews", || {
            maps::html::write_frame_strip(&frames, stage.path())
        })?;
    }
    let outputs = clock.time_shared(&maps::MAP_STAGES, "write maps", |busy| {
        maps::write_maps_timed(&result, stage.path(), &job.maps, busy)
    })?;
    let write_s: f64 = maps::MAP_STAGES
        .iter()
        .map(|s| clock.seconds(s))
        .sum::<f64>()
        + clock.seconds("write maps");
    let rig = format!("DiLiGenT layout, {} distant lights", set.files.len());
    let mut report = Report::new(
        dir,
        &rig,
        &result,
        &job.options,
        pipeline::relocate(outputs, out),
    );
    report.maps = job.maps.clone();
    // The benchmark's sensor noise is not known (only its rounding is modelled above), so a
    // predicted error would be a figure for a noise-free camera: reported as unknown.
    report.predicted_normal_error_deg = crate::maps::report::Mean::UNKNOWN;
    report.normal_convention = job.maps.normal_convention;
    report.lights = (set.directions.iter().zip(&set.files))
        .map(|(d, file)| maps::report::LightRecord {
            frame: Some(file.clone()),
            ..maps::report::LightRecord::toward(*d)
        })
        .collect();
    report.decode = Some(DecodeInfo {
        encoding: "diligent-png16".into(),
        resolution: Resolution::Full,
        method: "none: 16-bit RGB PNGs, linear, 65535 = white".into(),
        cfa_pattern: None,
        levels: diligent::LEVELS,
        camera: None,
        camera_to_srgb: None,
        dark_frame: "none in the set".into(),
        dark_subtracted: false,
        noise_channel_scale: [1.0; 3],
        noise_shared_cfa_sample: None,
        undistortion: "none: the benchmark's images come with distant lights and no camera \
                       model; pixels are not resampled"
            .into(),
    });
    let truth = clock.time("report", || set.normal_truth(frames.width, frames.height))?;
    if let Some(truth) = truth {
        let everywhere = crate::plane::Mask::new(frames.width, frames.height, true);
        let mask = mask.as_ref().unwrap_or(&everywhere);
        report.normal_truth = Some(clock.time("report", || {
            eval::compare_normals_over_mask(&result, &truth, mask)
        }));
        let errors: Vec<f64> = (eval::normal_errors_deg(&result, &truth).into_iter())
            .zip(&mask.data)
            .filter_map(|(e, &inside)| e.filter(|_| inside))
            .collect();
        report.normal_error_histogram = Some(maps::report::Histogram::of_errors(&errors));
    }
    report.timings_s = BTreeMap::from([
        ("decode".to_string(), clock.seconds("decode")),
        ("solve".to_string(), clock.seconds("solve")),
        ("write".to_string(), write_s),
    ]);
    report.set_stages(&clock);
    report.write(&stage.path().join(maps::REPORT_FILE))?;
    if job.maps.report_html {
        maps::html::write_report_page(stage.path())?;
    }
    stage.commit(job.force, &inputs)?;
    *buffers = Some(result);
    Ok(report)
}

/// How a batch runs.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct BatchOptions {
    /// Sets solved at the same time (each set's decode and solve are parallel inside).
    pub parallel_sets: usize,
}

impl Default for BatchOptions {
    /// One set at a time, its pixels in parallel: measured as fast as two sets at once on
    /// two cores (benches/decode.rs), with half the memory.
    fn default() -> Self {
        BatchOptions { parallel_sets: 1 }
    }
}

/// One set's outcome.
#[derive(Clone, Debug, Serialize)]
pub struct SetOutcome {
    pub set: PathBuf,
    pub out: PathBuf,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kind: Option<SetKind>,
    /// `solved` or `failed`.
    pub status: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub summary: Option<SetSummary>,
}

/// The headline figures of a solved set (the full figures are in its `report.json`).
#[derive(Clone, Debug, Serialize)]
pub struct SetSummary {
    pub width: usize,
    pub height: usize,
    pub solved_pixels: usize,
    pub predicted_normal_error_deg: f64,
    /// Mean angular error against ground truth, when the set has it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_error_deg: Option<f64>,
    /// The solve's warnings (see `Report::warnings`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    pub seconds: f64,
    pub report: PathBuf,
}

impl SetSummary {
    fn of(report: &Report, out: &Path) -> Self {
        SetSummary {
            width: report.width,
            height: report.height,
            solved_pixels: report.pixels.get("solved").copied().unwrap_or(0),
            predicted_normal_error_deg: report.predicted_normal_error_deg.mean,
            normal_error_deg: report
                .truth
                .as_ref()
                .map(|t| t.normal_error_deg.mean)
                .or(report
                    .normal_truth
                    .as_ref()
                    .map(|t| t.normal_error_deg.mean)),
            warnings: report.warnings.clone(),
            seconds: report.timings_s.get("total").copied().unwrap_or(0.0),
            report: out.join(maps::REPORT_FILE),
        }
    }
}

/// What `psscan solve` with several sets prints with `--json`.
#[derive(Clone, Debug, Serialize)]
pub struct BatchSummary {
    pub sets: Vec<SetOutcome>,
    pub solved: usize,
    pub failed: usize,
    pub options: BatchOptions,
    pub seconds: f64,
}

/// The output folder of each set: `out` itself for a single set, `out/<set folder name>` for
/// several. Names that repeat are an error for every set but the first with that name.
pub fn output_dirs(sets: &[PathBuf], out: &Path) -> Vec<std::result::Result<PathBuf, String>> {
    if sets.len() == 1 {
        return vec![Ok(out.to_path_buf())];
    }
    let mut seen: HashMap<String, &Path> = HashMap::new();
    sets.iter()
        .map(|set| {
            let name = set_name(set)
                .ok_or_else(|| format!("cannot name an output folder after {}", set.display()))?;
            if let Some(first) = seen.get(&name) {
                return Err(format!(
                    "its output folder {} would also be that of {}; give the sets distinct \
                     folder names",
                    out.join(&name).display(),
                    first.display()
                ));
            }
            seen.insert(name.clone(), set);
            Ok(out.join(name))
        })
        .collect()
}

fn set_name(set: &Path) -> Option<String> {
    let named = set
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .filter(|n| !n.is_empty() && n != "." && n != "..");
    named.or_else(|| {
        set.canonicalize()
            .ok()?
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
    })
}

/// Solves every set in `sets` into its own folder under `out` (or into `out` itself for one
/// set). Failures are collected, never propagated: the caller looks at `failed`.
pub fn solve_sets(
    sets: &[PathBuf],
    out: &Path,
    job: &SolveJob,
    options: BatchOptions,
    progress: &dyn Progress,
) -> BatchSummary {
    let start = Instant::now();
    let outs = output_dirs(sets, out);
    let mut outcomes: Vec<Option<SetOutcome>> = vec![None; sets.len()];
    let mut planned = Vec::new();
    let failed = |set: &Path, out: PathBuf, kind, error: String| SetOutcome {
        set: set.to_path_buf(),
        out,
        kind,
        status: "failed",
        error: Some(error),
        summary: None,
    };
    if sets.len() > 1 {
        if let Err(e) = create_dir_all(out) {
            let message = e.to_string();
            let outcomes = sets
                .iter()
                .zip(outs)
                .map(|(set, o)| failed(set, o.unwrap_or_default(), None, message.clone()))
                .collect();
            return summarise(outcomes, options, start);
        }
    }
    for (i, (set, dir)) in sets.iter().zip(outs).enumerate() {
        let planned_set = dir
            .map_err(|m| m.to_string())
            .and_then(|dir| plan(set, job).map(|p| (dir, p)).map_err(|e| e.to_string()));
        match planned_set {
            Ok((dir, (kind, units))) => planned.push((i, dir, kind, units)),
            Err(message) => {
                let dir = out.join(set_name(set).unwrap_or_default());
                outcomes[i] = Some(failed(set, dir, None, message));
            }
        }
    }

    let total_units: u64 = planned.iter().map(|p| p.3).sum();
    progress.begin("solve sets", total_units);
    let next = AtomicUsize::new(0);
    let results = Mutex::new(Vec::new());
    let workers = options.parallel_sets.clamp(1, planned.len().max(1));
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| {
                // Each worker solves its sets into the previous one's outputs (same size: no
                // fresh pages to fault in and zero, the largest cost after reading the input).
                let mut buffers = None;
                loop {
                    let n = next.fetch_add(1, Ordering::Relaxed);
                    let Some((i, dir, kind, units)) = planned.get(n) else {
                        break;
                    };
                    let budget = Budget::new(progress, *units);
                    let outcome =
                        match solve_set_reusing(&sets[*i], dir, job, &budget, &mut buffers) {
                            Ok(report) => SetOutcome {
                                set: sets[*i].clone(),
                                out: dir.clone(),
                                kind: Some(*kind),
                                status: "solved",
                                error: None,
                                summary: Some(SetSummary::of(&report, dir)),
                            },
                            Err(e) => failed(&sets[*i], dir.clone(), Some(*kind), e.to_string()),
                        };
                    budget.finish();
                    results.lock().unwrap().push((*i, outcome));
                }
            });
        }
    });
    progress.end();
    for (i, outcome) in results.into_inner().unwrap() {
        outcomes[i] = Some(outcome);
    }
    summarise(outcomes.into_iter().flatten().collect(), options, start)
}

fn summarise(sets: Vec<SetOutcome>, options: BatchOptions, start: Instant) -> BatchSummary {
    let solved = sets.iter().filter(|o| o.status == "solved").count();
    BatchSummary {
        failed: sets.len() - solved,
        solved,
        sets,
        options,
        seconds: start.elapsed().as_secs_f64(),
    }
}

/// Opens a set far enough to know its kind and how many progress steps it will report
/// (frames decoded plus rows solved); a set that cannot be opened fails here, before any
/// work.
fn plan(dir: &Path, job: &SolveJob) -> Result<(SetKind, u64)> {
    let kind = set_kind(dir)?;
    let units = match kind {
        SetKind::Capture => {
            let set = CaptureSet::open(dir, job.rig.clone())?;
            let image = &set.manifest.image;
            let rows = job.develop.resolution.size(image.width, image.height).1;
            (set.manifest.frames.len() + rows) as u64
        }
        SetKind::Diligent => {
            let set = DiligentSet::open(dir)?;
            let first = dir.join(&set.files[0]);
            let (_, height) =
                image::image_dimensions(&first).map_err(|e| Error::image(&first, e))?;
            (set.files.len() + height as usize) as u64
        }
    };
    Ok((kind, units.max(1)))
}

/// One set's share of the batch's progress bar: its stages' steps count toward the bar, never
/// beyond the set's share, and whatever is left is added when the set ends (also on failure).
struct Budget<'a> {
    outer: &'a dyn Progress,
    budget: u64,
    used: AtomicU64,
}

impl<'a> Budget<'a> {
    fn new(outer: &'a dyn Progress, budget: u64) -> Self {
        Budget {
            outer,
            budget,
            used: AtomicU64::new(0),
        }
    }

    fn finish(&self) {
        let used = self.used.swap(self.budget, Ordering::Relaxed);
        if used < self.budget {
            self.outer.advance(self.budget - used);
        }
    }
}

impl Progress for Budget<'_> {
    fn advance(&self, steps: u64) {
        let before = self
            .used
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |u| {
                Some((u + steps).min(self.budget))
            })
            .unwrap_or(self.budget);
        let added = (before + steps).min(self.budget) - before;
        if added > 0 {
            self.outer.advance(added);
        }
    }
}

/// The noise model of a DiLiGenT-layout set: the images carry no sensor description, so
/// 16-bit quantisation only (`1/12 DN^2`).
fn diligent_noise() -> NoiseModel {
    let full_scale = diligent::LEVELS.white - diligent::LEVELS.black;
    NoiseModel {
        photon: 0.0,
        floor: 1.0 / 12.0 / (full_scale * full_scale),
        ..NoiseModel::NONE
    }
}

/// Loads a DiLiGenT-layout set with ground truth for `psscan eval`; a set without
/// `Normal_gt.mat` is an error that names it.
pub fn open_eval_set(dir: &Path, progress: &dyn Progress) -> Result<eval::EvalSet> {
    if set_kind(dir)? != SetKind::Diligent {
        return Err(Error::capture_set(
            dir,
            "psscan eval reads DiLiGenT-layout sets with ground truth; this is a psscan capture set",
        ));
    }
    let set = DiligentSet::open(dir)?;
    let frames = set.load_frames(progress)?;
    let mask = set.mask(frames.width, frames.height)?;
    let truth = set
        .normal_truth(frames.width, frames.height)?
        .ok_or_else(|| {
            Error::capture_set(
                dir,
                format!(
                    "has no {}: psscan eval needs ground-truth normals",
                    diligent::NORMAL_TRUTH
                ),
            )
        })?;
    let name = dir
        .canonicalize()
        .unwrap_or_else(|_| dir.to_path_buf())
        .file_name()
        .map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into());
    Ok(eval::EvalSet {
        name,
        frames,
        directions: set.directions,
        intensities: set.intensities,
        noise: diligent_noise(),
        mask,
        truth,
    })
}

/// `psscan eval`: every set in `dirs` (loaded one at a time) through [`eval::evaluate`].
pub fn evaluate_sets(
    dirs: &[PathBuf],
    options: &eval::EvalOptions,
    progress: &dyn Progress,
) -> Result<eval::EvalReport> {
    let mut report = eval::EvalReport {
        rows: Vec::new(),
        anchors: Vec::new(),
    };
    for dir in dirs {
        let set = open_eval_set(dir, progress)?;
        eval::evaluate(&set, options, progress, &mut report)?;
    }
    Ok(report)
}
