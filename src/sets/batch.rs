//! Batches: many saved sets, each solved through the one path into its own output folder,
//! with one progress bar over the whole batch. A set that fails is reported and skipped; the
//! others finish.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::Serialize;

use super::{set_kind, solve_set_reusing, SetKind, SolveJob};
use crate::capture::diligent::DiligentSet;
use crate::capture::CaptureSet;
use crate::error::{Error, Result};
use crate::fsutil::create_dir_all;
use crate::maps::{self, Report};
use crate::progress::Progress;

/// How a batch runs.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct BatchOptions {
    /// Sets solved at the same time (each set's decode and solve are parallel inside).
    pub parallel_sets: usize,
}

impl Default for BatchOptions {
    /// One set at a time, its pixels in parallel: each set's decode and solve already use
    /// every core, and one set's frames are held instead of several (benches/decode.rs
    /// times one set at a time against several).
    fn default() -> Self {
        BatchOptions { parallel_sets: 1 }
    }
}

/// One set's outcome.
#[derive(Clone, Debug, Serialize)]
pub struct SetOutcome {
    /// The set's folder, as given.
    pub set: PathBuf,
    /// Its output folder.
    pub out: PathBuf,
    /// What the folder holds; `None` when the set failed before its kind was known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kind: Option<SetKind>,
    /// `solved` or `failed`.
    pub status: &'static str,
    /// Why the set failed, as the error's message; `None` when it was solved.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The failure behind `error`, for a caller that acts on its kind (the CLI adds the flag
    /// that gets past it); `None` for failures found before the set was opened.
    #[serde(skip)]
    pub failure: Option<Arc<Error>>,
    /// The solve's headline figures; `None` when the set failed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub summary: Option<SetSummary>,
}

/// The headline figures of a solved set (the full figures are in its `report.json`).
#[derive(Clone, Debug, Serialize)]
pub struct SetSummary {
    /// Map width in pixels.
    pub width: usize,
    /// Map height in pixels.
    pub height: usize,
    /// Pixels with a solution.
    pub solved_pixels: usize,
    /// Mean predicted normal error from sensor noise (NaN: not computed).
    pub predicted_normal_error_deg: f64,
    /// Mean angular error against ground truth, when the set has it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_error_deg: Option<f64>,
    /// The solve's warnings (see `Report::warnings`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Wall time, seconds.
    pub seconds: f64,
    /// The set's `report.json`.
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
    /// Every set's outcome, in the order given.
    pub sets: Vec<SetOutcome>,
    /// Sets solved.
    pub solved: usize,
    /// Sets that failed.
    pub failed: usize,
    /// How the batch ran.
    pub options: BatchOptions,
    /// Wall time, seconds.
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
        failure: None,
        summary: None,
    };
    let failed_with = |set: &Path, out: PathBuf, kind, error: Error| {
        let text = error.to_string();
        SetOutcome {
            failure: Some(Arc::new(error)),
            ..failed(set, out, kind, text)
        }
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
        let fallback = || out.join(set_name(set).unwrap_or_default());
        match dir {
            Err(message) => outcomes[i] = Some(failed(set, fallback(), None, message)),
            Ok(dir) => match plan(set, job) {
                Ok((kind, units)) => planned.push((i, dir, kind, units)),
                Err(e) => outcomes[i] = Some(failed_with(set, fallback(), None, e)),
            },
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
                                failure: None,
                                summary: Some(SetSummary::of(&report, dir)),
                            },
                            Err(e) => failed_with(&sets[*i], dir.clone(), Some(*kind), e),
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
