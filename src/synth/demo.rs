//! `psscan demo`: the synthetic textile rendered with the default rig as a capture set on
//! disk, solved through the one solve path, and compared with its ground truth.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use super::set::write_synthetic_set;
use super::SynthSpec;
use crate::error::Result;
use crate::eval::Stats;
use crate::fsutil::claim_dir;
use crate::maps::{self, report::Mean, WrittenMaps};
use crate::progress::Progress;
use crate::rig::Rig;
use crate::sets::{solve_set, SolveJob};

/// The figures `psscan demo --json` prints.
#[derive(Clone, Debug, Serialize)]
pub struct DemoSummary {
    /// The rig's name.
    pub rig: String,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// LEDs (frames).
    pub lights: usize,
    /// Normal error against the ground truth, degrees.
    pub normal_error_deg: Stats,
    /// Mean normal error the sensor-noise model predicts.
    pub predicted_normal_error_deg: Mean,
    /// Relative albedo error against the ground truth.
    pub albedo_rel_error: Stats,
    /// Pixels with a solution.
    pub solved_pixels: usize,
    /// The solve's warnings (see `Report::warnings`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Phases of the demo, seconds (`synth_*`, `solve_*`, `total`).
    pub timings_s: BTreeMap<String, f64>,
    /// Where the demo wrote.
    pub paths: DemoPaths,
}

/// Where `psscan demo` wrote.
#[derive(Clone, Debug, Serialize)]
pub struct DemoPaths {
    /// The synthetic capture set.
    pub capture: PathBuf,
    /// The solve's output folder.
    pub maps: PathBuf,
    /// The solve's `report.json`.
    pub report: PathBuf,
    /// The maps written.
    pub outputs: WrittenMaps,
}

/// The demo folder's entries, as its ownership record lists them (sub-folders with records
/// of their own).
pub const DEMO_CAPTURE: &str = "capture/";
/// The demo's solve output folder (see [`DEMO_CAPTURE`]).
pub const DEMO_MAPS: &str = "maps/";

/// Renders the synthetic textile with the embedded default rig into `out/capture`, solves it
/// into `out/maps`, and compares with the ground truth. The demo's folder is its own scratch
/// space: an earlier demo's output there is replaced as a whole (first removed, so an
/// interrupted demo never leaves new frames beside old maps); any other folder is refused.
pub fn run_demo(
    out: &Path,
    spec: &SynthSpec,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<DemoSummary> {
    let total = Instant::now();
    let rig = Rig::default_rig();
    let capture = out.join("capture");
    let maps_dir = out.join("maps");
    claim_dir(out, true, &[], &[DEMO_CAPTURE, DEMO_MAPS])?;
    let synth = write_synthetic_set(&rig, spec, &capture, true, progress)?;
    let job = SolveJob {
        force: true,
        ..job.clone()
    };
    let report = solve_set(&capture, &maps_dir, &job, progress)?;
    let truth = report
        .truth
        .clone()
        .expect("a synthetic set always has ground truth");
    let mut timings = BTreeMap::new();
    for (k, v) in &synth.timings_s {
        timings.insert(format!("synth_{k}"), *v);
    }
    for (k, v) in &report.timings_s {
        timings.insert(format!("solve_{k}"), *v);
    }
    timings.insert("total".into(), total.elapsed().as_secs_f64());
    Ok(DemoSummary {
        rig: rig.name.clone(),
        width: spec.width,
        height: spec.height,
        lights: rig.leds.len(),
        normal_error_deg: truth.normal_error_deg,
        predicted_normal_error_deg: report.predicted_normal_error_deg,
        albedo_rel_error: truth.albedo_rel_error,
        solved_pixels: truth.pixels,
        warnings: report.warnings.clone(),
        timings_s: timings,
        paths: DemoPaths {
            capture,
            report: maps_dir.join(maps::REPORT_FILE),
            maps: maps_dir,
            outputs: report.outputs.clone(),
        },
    })
}
