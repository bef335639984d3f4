//! `report.json`: the figures of one solve, for people and for scripts.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Serialize, Serializer};

use super::{MapOptions, NormalConvention, WrittenMaps};
use crate::error::Result;
use crate::eval::{Stats, TruthComparison};
use crate::fsutil::write_atomic;
use crate::math::select::select;
use crate::region::RegionInfo;
use crate::solve::{Estimator, PixelFit, PixelStatus, SolveOptions, SolveResult};
use crate::timing::{StageClock, StageTime};

/// Share of the solved pixels failing the adaptive estimator's model test above which the
/// summary warns: far above the test's false-alarm rate on clean data (a fraction of a
/// percent), so the frames hold something the Lambertian model and the noise model do not.
pub const MODEL_TEST_WARN_SHARE: f64 = 0.05;

/// The figures of one solve as `report.json` holds them: what was solved with which options, how
/// the pixels came out, where the time went and which files were written.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    /// The psscan version that made the solve.
    pub psscan_version: &'static str,
    /// Where the solved set is (its folder).
    pub capture: PathBuf,
    /// The rig's name (for a DiLiGenT set, a description of its light layout).
    pub rig: String,
    /// Width of the maps in pixels.
    pub width: usize,
    /// Height of the maps in pixels.
    pub height: usize,
    /// The options the solve ran with.
    pub options: SolveOptions,
    /// How the maps were written: the normal convention (`opengl`: +Y up, `directx`: +Y
    /// down), which formats, and the display colour matrix of `albedo.png`.
    pub maps: MapOptions,
    /// Pixel count per status (`solved`, `dark`, `saturated`, ...).
    pub pixels: BTreeMap<&'static str, usize>,
    /// Solved pixels per fit (`least_squares`, `robust`, `sheen`).
    pub fits: BTreeMap<&'static str, usize>,
    /// Pixels the estimator ran the robust fit on (adaptive: those that failed the chi-square
    /// test against the noise model).
    pub escalated: usize,
    /// The adaptive estimator found sheen and fitted the sheen model everywhere.
    pub sheen_everywhere: bool,
    /// Mean of the luminance fit's RMS residual over the solved pixels, in albedo units (0 when
    /// none was solved).
    pub residual_mean: f64,
    /// Mean predicted normal error from sensor noise over the solved pixels; `null` where it
    /// was not computed (the streaming kernel, `predict_error` off, or data without a noise
    /// model such as DiLiGenT sets).
    pub predicted_normal_error_deg: Mean,
    /// What the reader should know about these maps: most pixels failing the model test,
    /// errors the prediction does not cover. Each says what to try.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Errors against ground truth, when the capture set has it (synthetic sets); no albedo
    /// error for a `normal_only` solve.
    #[serde(
        skip_serializing_if = "Option::is_none",
        serialize_with = "truth_without_unknown_albedo"
    )]
    pub truth: Option<TruthComparison>,
    /// Crop, binning and background mask, when the solve did not cover every pixel.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub region: Option<crate::region::RegionInfo>,
    /// Coarse phases (`decode`, `solve`, `write`, `total`), for scripts that read them.
    pub timings_s: BTreeMap<String, f64>,
    /// Where the wall time went, stage by stage in the order they ran, ending with `other`
    /// (what no stage covers): the rows add up to `timings_s.total`. Stages that share the
    /// cores (reading, hashing and decoding frames; encoding maps) split their phase's wall
    /// time in proportion to their busy time, which they also give.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stages: Vec<StageTime>,
    /// The map files written.
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
    pub calibration: Option<crate::rig::CalibrationRef>,
    /// The bundle the capture set cites, when the solve did not use it (`--no-calibration`,
    /// `--rig`, or `--allow-calibration-mismatch` with another bundle).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration_cited_by_set: Option<crate::rig::CalibrationRef>,
    /// The lights in frame order, for the report page's view of the rig.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub lights: Vec<LightRecord>,
    /// The capture set's camera settings, as its manifest records them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<serde_json::Value>,
    /// Per-pixel normal errors against ground truth, binned (synthetic and benchmark sets).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_error_histogram: Option<Histogram>,
    /// Millimetres on the sample per map pixel (from the rig's camera), for `derive`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pixel_size_mm: Option<f64>,
    /// What the solve's derive step made in `derived/` (its `derive.json`), when the solve
    /// was asked for derived maps.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub derived: Option<serde_json::Value>,
}

/// One light of the solve.
#[derive(Clone, Debug, Serialize)]
pub struct LightRecord {
    /// Unit direction toward the light from the table centre (world frame).
    pub direction: [f64; 3],
    /// LED position (capture sets; DiLiGenT lights are distant).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub position_m: Option<[f64; 3]>,
    /// The light's frame file, relative to the capture set.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame: Option<String>,
    /// SHA-256 of the frame file in hex, as the capture set's manifest records it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
}

impl LightRecord {
    /// A light toward `towards` (any length).
    pub fn toward(towards: [f64; 3]) -> LightRecord {
        let len = towards
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
            .sqrt()
            .max(f64::MIN_POSITIVE);
        LightRecord {
            direction: towards.map(|v| v / len),
            position_m: None,
            frame: None,
            sha256: None,
        }
    }
}

/// Counts of values in bins of equal width from 0.
#[derive(Clone, Debug, Serialize)]
pub struct Histogram {
    /// Width of each bin, in degrees (rounded up to one significant digit).
    pub bin_deg: f64,
    /// How many values fall in each bin: bin `k` counts those in `[k, k + 1)` bin widths.
    pub counts: Vec<usize>,
    /// Values above the last bin.
    pub above: usize,
    /// Finite values counted (NaN and infinities are left out).
    pub pixels: usize,
}

impl Histogram {
    /// 40 bins up to the 99th percentile of the finite values (rounded up to a readable
    /// width); NaN and infinities are left out. On every core, without copying or reordering
    /// the values (16 M of them at 16 MP): the percentile is selected by
    /// [`crate::math::select`], the bins counted block by block.
    pub fn of_errors(values: &[f64]) -> Histogram {
        const BINS: usize = 40;
        const BLOCK: usize = 1 << 16;
        let finite = |i: usize| Some(values[i]).filter(|v| v.is_finite());
        let p99 = select(values.len(), finite, |n| [((n - 1) as f64 * 0.99) as usize])
            .map_or(1.0, |s| s.at[0])
            .max(1e-6);
        let step = 10f64.powf((p99 / BINS as f64).log10().floor());
        let bin_deg = ((p99 / BINS as f64) / step).ceil() * step;
        let tally = |block: &[f64]| {
            let (mut counts, mut above, mut pixels) = (vec![0; BINS], 0, 0);
            for v in block.iter().filter(|v| v.is_finite()) {
                pixels += 1;
                match counts.get_mut((v / bin_deg) as usize) {
                    Some(c) => *c += 1,
                    None => above += 1,
                }
            }
            (counts, above, pixels)
        };
        let (counts, above, pixels) = values.par_chunks(BLOCK).map(tally).reduce(
            || (vec![0; BINS], 0, 0),
            |(mut counts, above, pixels), (c, a, p)| {
                counts.iter_mut().zip(c).for_each(|(t, c)| *t += c);
                (counts, above + a, pixels + p)
            },
        );
        Histogram {
            bin_deg,
            counts,
            above,
            pixels,
        }
    }
}

/// A mean; NaN (JSON `null`, "n/a" in the CLI) when it could not be computed.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Mean {
    /// The mean, in the unit of what was averaged; NaN when unknown.
    pub mean: f64,
}

impl Mean {
    /// Not computed.
    pub const UNKNOWN: Mean = Mean { mean: f64::NAN };

    /// Whether the mean was computed (it is finite).
    pub fn is_known(&self) -> bool {
        self.mean.is_finite()
    }
}

/// Writes `truth` with `albedo_rel_error: null` where the albedo error is unknown (NaN).
fn truth_without_unknown_albedo<S: Serializer>(
    truth: &Option<TruthComparison>,
    serializer: S,
) -> std::result::Result<S::Ok, S::Error> {
    let mut value = serde_json::to_value(truth).map_err(serde::ser::Error::custom)?;
    if let Some(albedo) = value.get_mut("albedo_rel_error") {
        if albedo["mean"].is_null() {
            *albedo = serde_json::Value::Null;
        }
    }
    value.serialize(serializer)
}

/// The mean residual over the solved pixels (0 without any), summed in pixel order.
fn mean_residual(result: &SolveResult) -> f64 {
    // One pass over the pixels (a list of the solved pixels' indices was 128 MB at 16 MP).
    let (sum, solved) = result
        .status
        .iter()
        .zip(&result.residual.data)
        .filter(|(status, _)| **status == PixelStatus::Solved)
        .fold((0.0f64, 0usize), |(sum, n), (_, &r)| {
            (sum + r as f64, n + 1)
        });
    if solved == 0 {
        0.0
    } else {
        sum / solved as f64
    }
}

/// Mean predicted error over the solved pixels, or `None` when any of them has none (the
/// solvers leave 0 where they do not compute it; an exact 0 from a noise model needs a
/// sensor without noise, which no capture has).
fn mean_predicted_error_deg(result: &SolveResult) -> Option<f64> {
    let mut sum = 0.0;
    let mut n = 0usize;
    for (status, &e) in result.status.iter().zip(&result.predicted_error_deg.data) {
        if *status != PixelStatus::Solved {
            continue;
        }
        if !(e > 0.0 && e.is_finite()) {
            return None;
        }
        sum += e as f64;
        n += 1;
    }
    (n > 0).then(|| sum / n as f64)
}

/// The warning for a solve where many pixels failed the adaptive estimator's model test.
/// `binned`: the frames are 2x2-binned RAW (half resolution), whose own departure from the
/// model the warning names first.
fn model_test_warning(
    result: &SolveResult,
    options: &SolveOptions,
    solved: usize,
    binned: bool,
) -> Option<String> {
    if options.estimator() != Estimator::Adaptive || solved == 0 {
        return None;
    }
    let share = result.escalated as f64 / solved as f64;
    // A binned pixel sums four CFA sites with their own normals. Where some of them face a
    // light and some face away from it (an attached shadow inside the cell, common at thread
    // edges) the sum is not the response of any single normal, noise or not: a noise-free
    // synthetic set fails the test at a quarter of its binned pixels and at none of its
    // full-resolution ones.
    let (cause, first_remedy) = if binned {
        (
            "at half resolution each pixel sums a 2x2 cell of CFA sites, and where some of them \
             face a light and others face away from it (thread edges) no single normal explains \
             the sum; the frames may also hold cast shadows, sheen or highlights the Lambertian \
             model does not explain",
            "Solve at full resolution (--resolution full), which does not mix sites; try",
        )
    } else {
        (
            "the frames hold cast shadows, sheen or highlights the Lambertian model does not \
             explain, or the noise model is too tight for them",
            "Try",
        )
    };
    (share > MODEL_TEST_WARN_SHARE).then(|| {
        format!(
            "{:.1} % of the solved pixels fail the model test against the sensor noise: {cause}; \
             those pixels come from the robust fit, which leaves lights out and is less certain. \
             {first_remedy} --sheen-fit F0 ALPHA AMPLITUDE for cloth sheen, --model-error \
             FRACTION (e.g. 0.02) for frames that depart from the noise model, and check the \
             exposure and the dark frame",
            100.0 * share
        )
    })
}

impl Report {
    /// A report of `result` as solved from the set at `capture` with `rig`: pixel and fit counts,
    /// residual and predicted-error means, and the model-test warning (`binned`: the frames are
    /// 2x2-binned RAW); the caller fills in the rest (maps, truth, region, timings, provenance).
    pub fn new(
        capture: &Path,
        rig: &str,
        result: &SolveResult,
        options: &SolveOptions,
        outputs: WrittenMaps,
        binned: bool,
    ) -> Self {
        // The counts on every core; the two means (sums in pixel order) beside them.
        let ((statuses, fit_counts), (residual_mean, predicted)) = rayon::join(
            || result.class_counts(),
            || {
                rayon::join(
                    || mean_residual(result),
                    || mean_predicted_error_deg(result),
                )
            },
        );
        let pixels = PixelStatus::ALL
            .iter()
            .zip(statuses)
            .map(|(&s, count)| (s.name(), count))
            .collect();
        let fits = PixelFit::ALL
            .iter()
            .zip(fit_counts)
            .map(|(&f, count)| (f.name(), count))
            .collect();
        let solved = statuses[PixelStatus::Solved as usize];
        let warnings = model_test_warning(result, options, solved, binned)
            .into_iter()
            .collect();
        Report {
            psscan_version: env!("CARGO_PKG_VERSION"),
            capture: capture.to_path_buf(),
            rig: rig.to_string(),
            width: result.width,
            height: result.height,
            options: options.clone(),
            maps: MapOptions::default(),
            pixels,
            fits,
            escalated: result.escalated,
            sheen_everywhere: result.sheen_everywhere,
            residual_mean,
            predicted_normal_error_deg: predicted.map_or(Mean::UNKNOWN, |mean| Mean { mean }),
            warnings,
            truth: None,
            region: None,
            timings_s: BTreeMap::new(),
            stages: Vec::new(),
            outputs,
            decode: None,
            normal_truth: None,
            calibration: None,
            calibration_cited_by_set: None,
            lights: Vec::new(),
            camera: None,
            normal_error_histogram: None,
            pixel_size_mm: None,
            derived: None,
        }
    }

    /// Records the comparison with ground truth; a `normal_only` solve's albedo is the
    /// luminance in every channel, so its albedo error is not reported.
    pub fn set_truth(&mut self, mut truth: TruthComparison) {
        if self.options.normal_only {
            truth.albedo_rel_error = Stats {
                mean: f64::NAN,
                median: f64::NAN,
                p95: f64::NAN,
                max: f64::NAN,
            };
        }
        self.truth = Some(truth);
    }

    /// Records the crop, binning and mask; a binned solve notes what its prediction leaves
    /// out.
    pub fn set_region(&mut self, region: RegionInfo) {
        if region.bin > 1 {
            self.warnings.push(
                "binned 2x2: the predicted error covers the sensor noise of the binned pixels \
                 (a quarter of the variance) only. Where a 2x2 block straddles an edge of the \
                 relief (thread edges, gaps) its four normals do not add up to one Lambertian \
                 surface, and some lights graze part of the block: that error is not \
                 predicted, and it dominates the mean there. Use full resolution for the final \
                 maps"
                    .to_string(),
            );
        }
        self.region = Some(region);
    }

    /// Takes the stage table of `clock` as it stands now (the total is now).
    pub fn set_stages(&mut self, clock: &StageClock) {
        let (rows, total) = clock.table();
        self.stages = rows;
        self.timings_s.insert("total".into(), total);
    }

    /// The total wall time of the solve, seconds.
    pub fn total_s(&self) -> f64 {
        self.timings_s.get("total").copied().unwrap_or(0.0)
    }

    /// The report as pretty-printed JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a report always serialises")
    }

    /// Writes the report's JSON to `path`, atomically.
    pub fn write(&self, path: &Path) -> Result<()> {
        write_atomic(path, self.to_json().as_bytes())
    }
}

/// The orientation of the normal maps a report's solve wrote: `maps.normal_convention`
/// (reports written before it was recorded only there also carried a top-level copy, read as
/// a fallback); OpenGL when neither is present.
pub fn normal_convention_of(report: &serde_json::Value) -> NormalConvention {
    let recorded = report
        .pointer("/maps/normal_convention")
        .or_else(|| report.get("normal_convention"));
    recorded
        .and_then(|v| serde_json::from_value(v.clone()).ok())
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::Histogram;

    #[test]
    fn error_histogram_bins_up_to_the_99th_percentile_whatever_the_order() {
        // 0.00, 0.01, ... 9.99 degrees, shuffled, with non-finite values that are not counted.
        let mut values: Vec<f64> = (0..1000).map(|i| (i * 379 % 1000) as f64 * 0.01).collect();
        values.extend([f64::NAN, f64::INFINITY]);
        let h = Histogram::of_errors(&values);
        assert_eq!(h.pixels, 1000);
        // p99 = value at sorted position floor(999 * 0.99) = 989 -> 9.89 deg; 9.89 / 40 =
        // 0.247, rounded up at the 0.1 digit: 0.3 deg bins covering 0 .. 12 deg.
        assert!((h.bin_deg - 0.3).abs() < 1e-12, "{}", h.bin_deg);
        assert_eq!(h.above, 0);
        // Bin k holds the values in [k, k + 1) bin widths.
        for (k, &count) in h.counts.iter().enumerate() {
            let expected = values
                .iter()
                .filter(|v| v.is_finite() && (**v / h.bin_deg) as usize == k)
                .count();
            assert_eq!(count, expected, "bin {k}");
        }
        assert_eq!(h.counts.iter().sum::<usize>(), 1000);
        let empty = Histogram::of_errors(&[f64::NAN]);
        assert_eq!((empty.pixels, empty.above), (0, 0));
        assert!((empty.bin_deg - 0.03).abs() < 1e-12, "{}", empty.bin_deg);
        // With non-finite values among the finite ones, and over several blocks: the same
        // histogram.
        let mut mixed = values.clone();
        mixed.swap(0, 1000);
        let moved = Histogram::of_errors(&mixed);
        assert_eq!(
            (moved.bin_deg, &moved.counts, moved.above, moved.pixels),
            (h.bin_deg, &h.counts, h.above, h.pixels)
        );
        let many: Vec<f64> = (0..200_000).map(|i| values[i % 1000]).collect();
        let large = Histogram::of_errors(&many);
        let expected: Vec<usize> = h.counts.iter().map(|c| c * 200).collect();
        assert_eq!(
            (large.bin_deg, &large.counts, large.pixels),
            (h.bin_deg, &expected, 200_000)
        );
    }
}
