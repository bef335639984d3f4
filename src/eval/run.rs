//! The real-data evaluation: each estimator on each light subset of a set with ground truth,
//! timed, beside the trimmed anchor and the published figures.

use std::time::Instant;

use nalgebra::Vector3;
use serde::Serialize;

use super::anchors::{self, Anchor};
use super::{angle_deg, compare_normals_over_mask, subsets, trimmed, Stats};
use crate::error::{Error, Result};
use crate::plane::{Frames, Mask, Plane};
use crate::progress::Progress;
use crate::solve::{self, Estimator, LightSource, NoiseModel, SolveInput, SolveOptions};

/// A set with ground truth, loaded: what the evaluation solves (the set sources build it).
pub struct EvalSet {
    /// The set's name in tables (its folder name).
    pub name: String,
    /// The images, one linear RGB frame per light, in the order of `directions`.
    pub frames: Frames,
    /// Unit directions toward the lights, world frame, one per frame.
    pub directions: Vec<[f64; 3]>,
    /// RGB intensities of the lights, one per frame.
    pub intensities: Vec<[f64; 3]>,
    /// The sensor noise model the solve weighs residuals with.
    pub noise: NoiseModel,
    /// The object's pixels, the only ones solved and scored; `None` for every pixel.
    pub mask: Option<Mask>,
    /// Ground-truth unit normals (zero where unknown).
    pub truth: [Plane; 3],
}

/// What to evaluate.
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Light counts; `None` is every light of the set. Counts at or above a set's total are
    /// evaluated once, as every light.
    pub lights: Vec<Option<usize>>,
    /// The estimators to run, each on every light subset.
    pub estimators: Vec<Estimator>,
    /// The solve options every estimator shares (the estimator field is replaced).
    pub solve: SolveOptions,
}

/// One estimator on one light subset of one set.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    /// The set's name (its [`EvalSet::name`]).
    pub set: String,
    /// How many lights the subset has (chosen spread out over the set's directions).
    pub lights: usize,
    /// An estimator name (`ls`, `adaptive`, ...) or `trimmed` (the anchor psscan computes).
    pub estimator: String,
    /// Over every mask pixel with a ground-truth normal (unsolved pixels count with (0, 0, 1)),
    /// as benchmark tables report it.
    pub error_deg: Stats,
    /// Mask pixels with a ground-truth normal, the count `error_deg` is over.
    pub mask_pixels: usize,
    /// Of those, the pixels solved (for `trimmed`, those it found a normal for).
    pub solved: usize,
    /// Pixels the robust fit ran on (estimators only).
    pub escalated: Option<usize>,
    /// Wall-clock time of the solve (for `trimmed`, of its normals), in seconds.
    pub seconds: f64,
}

/// The whole evaluation.
#[derive(Clone, Debug, Serialize)]
pub struct EvalReport {
    /// One row per estimator (and `trimmed`) per set and light count, in evaluation order.
    pub rows: Vec<Row>,
    /// Published figures for the (set, light count) pairs evaluated.
    pub anchors: Vec<Anchor>,
}

impl EvalReport {
    /// The row of `estimator` on `set` at `lights`, if evaluated.
    pub fn row(&self, set: &str, lights: usize, estimator: &str) -> Option<&Row> {
        self.rows
            .iter()
            .find(|r| r.set == set && r.lights == lights && r.estimator == estimator)
    }
}

/// The light counts `options` asks of a set of `total` lights: distinct, ascending, capped.
pub fn light_counts(options: &EvalOptions, total: usize) -> Result<Vec<usize>> {
    let mut counts = Vec::new();
    for k in &options.lights {
        let k = k.unwrap_or(total).min(total);
        if k < 3 {
            return Err(Error::Invalid(format!(
                "a subset of {k} lights: photometric stereo needs at least 3"
            )));
        }
        counts.push(k);
    }
    counts.sort_unstable();
    counts.dedup();
    Ok(counts)
}

/// Evaluates `set` with `options`, appending its rows and anchors to `report`.
pub fn evaluate(
    set: &EvalSet,
    options: &EvalOptions,
    progress: &dyn Progress,
    report: &mut EvalReport,
) -> Result<()> {
    for k in light_counts(options, set.directions.len())? {
        let chosen = subsets::farthest_point(&set.directions, k);
        let frames = Frames {
            width: set.frames.width,
            height: set.frames.height,
            window: set.frames.window,
            lights: chosen
                .iter()
                .map(|&i| set.frames.lights[i].clone())
                .collect(),
        };
        let directions: Vec<[f64; 3]> = chosen.iter().map(|&i| set.directions[i]).collect();
        let intensities: Vec<[f64; 3]> = chosen.iter().map(|&i| set.intensities[i]).collect();
        for &estimator in &options.estimators {
            let input = SolveInput {
                frames: &frames,
                lights: LightSource::Directions {
                    directions: &directions,
                    intensities: &intensities,
                },
                noise: set.noise,
                exposure: 1.0,
                mask: set.mask.as_ref(),
            };
            let solve_options = SolveOptions {
                kernel: options.solve.kernel.with_estimator(estimator)?,
                ..options.solve.clone()
            };
            let start = Instant::now();
            let result = solve::solve(&input, &solve_options, progress)?;
            let seconds = start.elapsed().as_secs_f64();
            let everywhere = Mask::new(frames.width, frames.height, true);
            let mask = set.mask.as_ref().unwrap_or(&everywhere);
            let cmp = compare_normals_over_mask(&result, &set.truth, mask);
            report.rows.push(Row {
                set: set.name.clone(),
                lights: k,
                estimator: estimator.name().into(),
                error_deg: cmp.normal_error_deg,
                mask_pixels: cmp.mask_pixels,
                solved: cmp.solved,
                escalated: Some(result.escalated),
                seconds,
            });
        }
        report
            .rows
            .push(trimmed_row(set, &frames, &directions, &intensities, k));
        report.anchors.extend(anchors::published(&set.name, k));
    }
    Ok(())
}

fn trimmed_row(
    set: &EvalSet,
    frames: &Frames,
    directions: &[[f64; 3]],
    intensities: &[[f64; 3]],
    k: usize,
) -> Row {
    let start = Instant::now();
    let normals = trimmed::trimmed_normals(frames, directions, intensities, set.mask.as_ref());
    let seconds = start.elapsed().as_secs_f64();
    let mut errors = Vec::new();
    let mut solved = 0;
    for (i, n) in normals.iter().enumerate() {
        if set.mask.as_ref().is_some_and(|m| !m.data[i]) {
            continue;
        }
        let t = Vector3::new(
            set.truth[0].data[i] as f64,
            set.truth[1].data[i] as f64,
            set.truth[2].data[i] as f64,
        );
        if t.norm().is_nan() || t.norm() <= 0.0 {
            continue;
        }
        solved += usize::from(n.is_some());
        errors.push(angle_deg(&n.unwrap_or_else(Vector3::z), &t));
    }
    Row {
        set: set.name.clone(),
        lights: k,
        estimator: "trimmed".into(),
        mask_pixels: errors.len(),
        error_deg: Stats::of(&mut errors),
        solved,
        escalated: None,
        seconds,
    }
}
