//! `report.json`: the figures of one solve, for people and for scripts.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::WrittenMaps;
use crate::error::Result;
use crate::eval::TruthComparison;
use crate::fsutil::write_atomic;
use crate::solve::{PixelFit, PixelStatus, SolveOptions, SolveResult};

#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub psscan_version: &'static str,
    pub capture: PathBuf,
    pub rig: String,
    pub width: usize,
    pub height: usize,
    pub options: SolveOptions,
    /// Pixel count per status (`solved`, `dark`, `saturated`, ...).
    pub pixels: BTreeMap<&'static str, usize>,
    /// Solved pixels per fit (`least_squares`, `robust`, `sheen`).
    pub fits: BTreeMap<&'static str, usize>,
    /// Pixels the estimator ran the robust fit on (adaptive: those that failed the chi-square
    /// test against the noise model).
    pub escalated: usize,
    /// The adaptive estimator found sheen and fitted the sheen model everywhere.
    pub sheen_everywhere: bool,
    pub residual_mean: f64,
    pub predicted_normal_error_deg: Mean,
    /// Errors against ground truth, when the capture set has it (synthetic sets).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthComparison>,
    /// Crop, binning and background mask, when the solve did not cover every pixel.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub region: Option<crate::region::RegionInfo>,
    pub timings_s: BTreeMap<String, f64>,
    pub outputs: WrittenMaps,
    /// How the frames were decoded and prepared (capture sets).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub decode: Option<crate::raw::DecodeInfo>,
    /// Normals against a ground-truth normal map over an object mask (benchmark sets such as
    /// DiLiGenT, which have no albedo truth).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_truth: Option<crate::eval::MaskedNormalComparison>,
    /// The calibration bundle whose rig (and gain grids) the solve used.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::calibration::bundle::CalibrationRef>,
    /// The bundle the capture set cites, when the solve did not use it (`--no-calibration`,
    /// `--rig`, or `--allow-calibration-mismatch` with another bundle).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration_cited_by_set: Option<crate::calibration::bundle::CalibrationRef>,
    /// Millimetres on the sample per map pixel (from the rig's camera), for `derive`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pixel_size_mm: Option<f64>,
    /// How the normal maps store Y (`derive` reads normal.exr back through it).
    pub normal_convention: super::NormalConvention,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub struct Mean {
    pub mean: f64,
}

impl Report {
    pub fn new(
        capture: &Path,
        rig: &str,
        result: &SolveResult,
        options: &SolveOptions,
        outputs: WrittenMaps,
    ) -> Self {
        let pixels = PixelStatus::ALL
            .iter()
            .map(|&s| (s.name(), result.count(s)))
            .collect();
        let fits = PixelFit::ALL
            .iter()
            .map(|&f| (f.name(), result.count_fit(f)))
            .collect();
        let solved: Vec<usize> = (0..result.status.len())
            .filter(|&i| result.status[i] == PixelStatus::Solved)
            .collect();
        let residual_mean = if solved.is_empty() {
            0.0
        } else {
            solved
                .iter()
                .map(|&i| result.residual.data[i] as f64)
                .sum::<f64>()
                / solved.len() as f64
        };
        Report {
            psscan_version: env!("CARGO_PKG_VERSION"),
            capture: capture.to_path_buf(),
            rig: rig.to_string(),
            width: result.width,
            height: result.height,
            options: options.clone(),
            pixels,
            fits,
            escalated: result.escalated,
            sheen_everywhere: result.sheen_everywhere,
            residual_mean,
            predicted_normal_error_deg: Mean {
                mean: result.mean_predicted_error_deg(),
            },
            truth: None,
            region: None,
            timings_s: BTreeMap::new(),
            outputs,
            decode: None,
            normal_truth: None,
            calibration: None,
            calibration_cited_by_set: None,
            pixel_size_mm: None,
            normal_convention: super::NormalConvention::default(),
        }
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a report always serialises")
    }

    pub fn write(&self, path: &Path) -> Result<()> {
        write_atomic(path, self.to_json().as_bytes())
    }
}
