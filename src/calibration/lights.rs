//! Each LED's 3-D position and intensity, fitted to the white sheet. The model is the one the
//! solve uses: a point source whose light on the flat sheet at `p` is
//! `power * beam(angle off the axis) * cos(incidence) / r^2`, the beam aimed at the LED's aim
//! point. Starting from the hand-measured positions in rig.toml, Levenberg-Marquardt moves
//! every LED (x, y, z, log power) to match the sheet's measured intensities block by block;
//! the intensity and the directions are refined together, each iteration's change reported,
//! until the positions stop moving. Colour comes last: per channel, the least-squares scale
//! of the fitted shape.

use nalgebra::{Matrix4, Vector3, Vector4};
use serde::{Deserialize, Serialize};

use super::whitesheet::SheetLight;
use crate::error::{Error, Result};
use crate::progress::Progress;
use crate::rig::{Led, Rig};

/// Positions that move less than this in an iteration have converged (m).
pub const CONVERGED_STEP_M: f64 = 1e-5;
const MAX_ITERATIONS: usize = 50;
/// How far a hand-measured LED position may lie from the LED (m): the rig's stated tolerance.
pub const HAND_LED_ERROR_M: f64 = 0.03;
/// How close the white-sheet fit puts each LED to where it is (m).
pub const FITTED_LED_ERROR_M: f64 = 0.005;
/// Relative accuracy of the point-source-and-beam model on a real sheet, which the gain grids
/// then correct: the LEDs' beams are not exactly `cos^m`, and a "near-perfect" diffuse sheet is
/// uniform to a few percent. A fit whose residual exceeds this (plus the sensor noise) is not
/// describing this rig and sheet.
pub const MODEL_RELATIVE_BUDGET: f64 = 0.05;
/// How many standard deviations of its own sampling spread an rms residual may exceed its
/// expectation by before the fit is called implausible.
const RESIDUAL_SIGMAS: f64 = 5.0;

/// One iteration of the joint fit.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Iteration {
    /// Which iteration this was, counting from 1.
    pub iteration: usize,
    /// Largest position change of any LED in this iteration (mm).
    pub max_step_mm: f64,
    /// Largest power change of any LED (relative).
    pub max_power_change: f64,
    /// RMS relative residual over all lights and blocks after the iteration.
    pub rms_relative_residual: f64,
}

/// One LED's result.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FittedLed {
    /// Where the fit started: the hand-measured position from rig.toml, world metres.
    pub start_m: [f64; 3],
    /// Where the fit put the LED, world metres.
    pub position_m: [f64; 3],
    /// Distance between the hand measurement and the fit (mm).
    pub moved_mm: f64,
    /// Linear signal of a white surface at 1 m on the axis, per channel (what the solve
    /// divides by).
    pub rgb_power: [f64; 3],
    /// RMS over this LED's usable sheet blocks of the measured over the modelled luminance, minus
    /// 1.
    pub rms_relative_residual: f64,
}

/// The white-sheet LED fit (the `lights` of `whitesheet.toml` and of a bundle): each LED's fitted
/// position and power, the history of the iterations, and whether the fit may be used.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LightFit {
    /// Per LED, in the rig's order, its fitted position and power.
    pub leds: Vec<FittedLed>,
    /// Each iteration's changes and residual, in order; its length is the number of iterations run.
    pub iterations: Vec<Iteration>,
    /// Whether every LED's position step fell below [`CONVERGED_STEP_M`] before the iteration
    /// limit.
    pub converged: bool,
    /// Why the fit cannot be used (empty: accepted). A fit that did not converge, moved an LED
    /// further from its hand measurement than the rig's tolerance allows, or leaves a residual
    /// beyond the noise and the model's accuracy is written with its reasons and refused by
    /// the bundle step and by every reader of a bundle.
    #[serde(default)]
    pub rejected_because: Vec<String>,
}

impl LightFit {
    /// Why this fit must not be used; empty when it may. A fit that did not converge is
    /// refused even when read from a file written before the reasons were recorded.
    pub fn problems(&self) -> Vec<String> {
        let mut problems = self.rejected_because.clone();
        if !self.converged && !problems.iter().any(|p| p.contains("converge")) {
            problems.push(format!(
                "the LED fit did not converge in {} iterations",
                self.iterations.len()
            ));
        }
        problems
    }

    /// `Ok` when the fit may be used; otherwise an error naming `source` and every reason.
    pub fn check_usable(&self, source: &std::path::Path) -> Result<()> {
        let problems = self.problems();
        if problems.is_empty() {
            return Ok(());
        }
        Err(Error::Invalid(format!(
            "{}: the white-sheet LED fit was rejected ({}); photograph the white sheet again, \
             one photograph per LED in LED order, and check the rig's hand-measured LED positions",
            source.display(),
            problems.join("; ")
        )))
    }

    /// `rig` with its LEDs where the fit put them, with the fitted powers and colours.
    pub fn apply(&self, rig: &Rig) -> Rig {
        let mut out = rig.clone();
        for (led, fit) in out.leds.iter_mut().zip(&self.leds) {
            led.position_m = fit.position_m;
            // The rig stores power x colour x the sensor's channel gain; keep green's colour 1.
            let gain = rig.sensor.channel_gain;
            led.power = fit.rgb_power[1] / gain[1];
            led.color = std::array::from_fn(|c| fit.rgb_power[c] / (led.power * gain[c]));
        }
        out
    }
}

/// The white-surface luminance the point-source model predicts at `point`.
fn model(led: &Led, point: &Vector3<f64>) -> f64 {
    let s = led.sample_at(point);
    s.falloff * s.direction.z.max(0.0)
}

/// Sum of squared relative residuals of `led` (with `power` standing for the luminance
/// power) against the blocks' luminance.
fn cost(led: &Led, points: &[Vector3<f64>], values: &[f64]) -> f64 {
    points
        .iter()
        .zip(values)
        .map(|(p, v)| (model(led, p) / v - 1.0).powi(2))
        .sum()
}

fn with_params(base: &Led, q: &Vector4<f64>) -> Led {
    Led {
        position_m: [q[0], q[1], q[2]],
        power: q[3].exp(),
        ..base.clone()
    }
}

/// One Levenberg-Marquardt step for one LED; returns the new parameters and the new damping.
fn lm_step(
    base: &Led,
    q: &Vector4<f64>,
    lambda: f64,
    points: &[Vector3<f64>],
    values: &[f64],
) -> (Vector4<f64>, f64) {
    let led = with_params(base, q);
    let current = cost(&led, points, values);
    let mut jtj = Matrix4::zeros();
    let mut jtr = Vector4::zeros();
    let h = [1e-6, 1e-6, 1e-6, 1e-6];
    let shifted: Vec<Led> = (0..4)
        .map(|j| {
            let mut d = *q;
            d[j] += h[j];
            with_params(base, &d)
        })
        .collect();
    for (p, v) in points.iter().zip(values) {
        let m = model(&led, p);
        let r = m / v - 1.0;
        let g = Vector4::from_fn(|j, _| (model(&shifted[j], p) - m) / v / h[j]);
        jtj += g * g.transpose();
        jtr += g * r;
    }
    let mut lambda = lambda;
    for _ in 0..12 {
        let mut a = jtj;
        for j in 0..4 {
            a[(j, j)] *= 1.0 + lambda;
        }
        if let Some(step) = a.lu().solve(&(-jtr)) {
            let trial = q + step;
            if cost(&with_params(base, &trial), points, values) < current {
                return (trial, (lambda / 10.0).max(1e-9));
            }
        }
        lambda *= 10.0;
    }
    (*q, lambda)
}

/// Fits every LED of `rig` (positions as measured by hand, aims and beams as given) to the
/// white sheet's measured intensities.
pub fn fit(rig: &Rig, sheet: &[SheetLight], progress: &dyn Progress) -> Result<LightFit> {
    if sheet.len() != rig.leds.len() {
        return Err(Error::Invalid(format!(
            "{} white-sheet lights for {} LEDs",
            sheet.len(),
            rig.leds.len()
        )));
    }
    // Per LED: the usable blocks' points and luminances.
    let data: Vec<(Vec<Vector3<f64>>, Vec<f64>)> = sheet
        .iter()
        .map(|s| {
            let lum = s.luminance();
            s.points
                .iter()
                .zip(lum)
                .filter(|(_, l)| l.is_finite() && *l > 0.0)
                .map(|(p, l)| (*p, l))
                .unzip()
        })
        .collect();
    for (k, (points, _)) in data.iter().enumerate() {
        if points.len() < 16 {
            return Err(Error::Invalid(format!(
                "LED {k}: only {} usable white-sheet blocks (saturated or dark); need 16",
                points.len()
            )));
        }
    }
    // Start: hand positions, and the power that matches the sheet's mean with them.
    let mut params: Vec<Vector4<f64>> = rig
        .leds
        .iter()
        .zip(&data)
        .map(|(led, (points, values))| {
            let unit = Led {
                power: 1.0,
                ..led.clone()
            };
            let ratio: f64 = points
                .iter()
                .zip(values)
                .map(|(p, v)| v / model(&unit, p))
                .sum::<f64>()
                / points.len() as f64;
            Vector4::new(
                led.position_m[0],
                led.position_m[1],
                led.position_m[2],
                ratio.ln(),
            )
        })
        .collect();
    let mut lambdas = vec![1e-3; rig.leds.len()];
    let mut iterations = Vec::new();
    let mut converged = false;
    progress.begin("lights", MAX_ITERATIONS as u64);
    for iteration in 1..=MAX_ITERATIONS {
        let mut max_step: f64 = 0.0;
        let mut max_power: f64 = 0.0;
        for k in 0..rig.leds.len() {
            let (points, values) = &data[k];
            let (next, lambda) = lm_step(&rig.leds[k], &params[k], lambdas[k], points, values);
            let step = (next.fixed_rows::<3>(0) - params[k].fixed_rows::<3>(0)).norm();
            max_step = max_step.max(step);
            max_power = max_power.max((next[3] - params[k][3]).abs());
            params[k] = next;
            lambdas[k] = lambda;
        }
        let rms = rms_residual(rig, &params, &data);
        iterations.push(Iteration {
            iteration,
            max_step_mm: max_step * 1e3,
            max_power_change: max_power.exp_m1(),
            rms_relative_residual: rms,
        });
        progress.advance(1);
        if max_step < CONVERGED_STEP_M {
            converged = true;
            break;
        }
    }
    progress.end();
    let leds = rig
        .leds
        .iter()
        .zip(&params)
        .zip(sheet)
        .zip(&data)
        .map(|(((led, q), s), (points, values))| {
            let fitted = with_params(led, q);
            FittedLed {
                start_m: led.position_m,
                position_m: fitted.position_m,
                moved_mm: (fitted.position() - led.position()).norm() * 1e3,
                rgb_power: channel_powers(&fitted, s),
                rms_relative_residual: (cost(&fitted, points, values) / points.len() as f64).sqrt(),
            }
        })
        .collect::<Vec<FittedLed>>();
    let expected = expected_residual(rig, &data, sheet);
    let rms = iterations
        .last()
        .map_or(f64::NAN, |i| i.rms_relative_residual);
    let blocks: usize = data.iter().map(|(p, _)| p.len()).sum();
    let rejected_because = verdict(converged, iterations.len(), &leds, rms, expected, blocks);
    Ok(LightFit {
        leds,
        iterations,
        converged,
        rejected_because,
    })
}

/// The rms relative residual a right fit leaves: per block, the sensor noise of its mean
/// (`NoiseModel::from_sensor` at the block's signal over the pixels averaged) and the model's
/// accuracy budget, added in quadrature and averaged over the blocks.
fn expected_residual(
    rig: &Rig,
    data: &[(Vec<Vector3<f64>>, Vec<f64>)],
    sheet: &[SheetLight],
) -> f64 {
    let noise = crate::solve::NoiseModel::from_sensor(&rig.sensor);
    let (mut sum, mut n) = (0.0, 0usize);
    for ((_, values), light) in data.iter().zip(sheet) {
        let pixels = light.pixels_per_block.max(1) as f64;
        for &v in values {
            // The luminance as one sample's noise: three channels average some of it away, so
            // this overstates the noise slightly, never the other way.
            sum += noise.variance(v) / (v * v) / pixels + MODEL_RELATIVE_BUDGET.powi(2);
            n += 1;
        }
    }
    (sum / n.max(1) as f64).sqrt()
}

/// The reasons a fit is implausible. The rms of `blocks` residuals of expected size `expected`
/// scatters by about `expected / sqrt(2 blocks)`; beyond `RESIDUAL_SIGMAS` of that the model
/// does not describe the photographs. An LED the fit moved further than the hand measurement's
/// tolerance plus the fit's own accuracy is somewhere the rig says it cannot be.
fn verdict(
    converged: bool,
    iterations: usize,
    leds: &[FittedLed],
    rms: f64,
    expected: f64,
    blocks: usize,
) -> Vec<String> {
    let mut reasons = Vec::new();
    if !converged {
        reasons.push(format!(
            "the LED fit did not converge in {iterations} iterations (an LED still moved more \
             than {} mm in the last one)",
            CONVERGED_STEP_M * 1e3
        ));
    }
    let limit_mm = (HAND_LED_ERROR_M + FITTED_LED_ERROR_M) * 1e3;
    let far: Vec<String> = leds
        .iter()
        .enumerate()
        .filter(|(_, l)| l.moved_mm.is_nan() || l.moved_mm > limit_mm)
        .map(|(k, l)| format!("LED {k} {:.0} mm", l.moved_mm))
        .collect();
    if !far.is_empty() {
        reasons.push(format!(
            "the fit moved {} from the hand measurement, more than the {limit_mm:.0} mm the \
             rig's tolerance ({:.0} mm) and the fit's accuracy allow",
            far.join(", "),
            HAND_LED_ERROR_M * 1e3
        ));
    }
    let limit = expected * (1.0 + RESIDUAL_SIGMAS / (2.0 * blocks.max(1) as f64).sqrt());
    if rms.is_nan() || rms > limit {
        reasons.push(format!(
            "the rms relative residual {rms:.3} exceeds the {limit:.3} that sensor noise and \
             the model's {:.0} % accuracy allow",
            100.0 * MODEL_RELATIVE_BUDGET
        ));
    }
    reasons
}

fn rms_residual(rig: &Rig, params: &[Vector4<f64>], data: &[(Vec<Vector3<f64>>, Vec<f64>)]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for (k, (points, values)) in data.iter().enumerate() {
        sum += cost(&with_params(&rig.leds[k], &params[k]), points, values);
        n += points.len();
    }
    (sum / n as f64).sqrt()
}

/// Per channel, the power that best scales the fitted LED's shape to the sheet (least
/// squares), in the rig's units (signal of a white surface at 1 m on axis).
fn channel_powers(led: &Led, sheet: &SheetLight) -> [f64; 3] {
    let unit = Led {
        power: 1.0,
        ..led.clone()
    };
    std::array::from_fn(|c| {
        let (mut num, mut den) = (0.0, 0.0);
        for (p, v) in sheet.points.iter().zip(&sheet.rgb) {
            if v[c].is_finite() {
                let m = model(&unit, p);
                num += m * v[c];
                den += m * m;
            }
        }
        num / den
    })
}

/// Blocks averaged per gain-grid cell side: the paper's texture and the sensor noise average
/// out over 64 blocks (a per-block correction would put them into every light's intensity).
pub const GAIN_CELL_BLOCKS: usize = 8;

/// Per light, what the white sheet measured over what the fitted model predicts, averaged over
/// cells of `GAIN_CELL_BLOCKS x GAIN_CELL_BLOCKS` blocks on a regular world grid: the
/// calibrated light source's correction ([`crate::solve::LightSource::Calibrated`]).
pub fn gain_grids(fitted: &Rig, sheet: &[SheetLight]) -> Result<Vec<crate::solve::GainGrid>> {
    let first = sheet
        .first()
        .ok_or_else(|| Error::Invalid("no white-sheet lights".into()))?;
    let (mut xmin, mut xmax, mut ymin, mut ymax) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in &first.points {
        (xmin, xmax, ymin, ymax) = (xmin.min(p.x), xmax.max(p.x), ymin.min(p.y), ymax.max(p.y));
    }
    let (bw, bh) = first.grid;
    let nx = (bw / GAIN_CELL_BLOCKS).max(2);
    let ny = (bh / GAIN_CELL_BLOCKS).max(2);
    // Nodes at the cell centres; cells tile the sheet's extent.
    let (cw, ch) = ((xmax - xmin) / nx as f64, (ymax - ymin) / ny as f64);
    sheet
        .iter()
        .enumerate()
        .map(|(k, light)| {
            let led = &fitted.leds[k];
            let luminance_power: f64 = (0..3)
                .map(|c| crate::solve::LUMINANCE_WEIGHTS[c] * fitted.led_rgb_power(k)[c])
                .sum::<f64>()
                / led.power;
            let mut sum = vec![0.0; nx * ny];
            let mut count = vec![0usize; nx * ny];
            for (p, m) in light.points.iter().zip(light.luminance()) {
                let predicted = model(led, p) * luminance_power;
                if !(m.is_finite() && m > 0.0 && predicted > 0.0) {
                    continue;
                }
                let i = (((p.x - xmin) / cw) as usize).min(nx - 1);
                let j = (((p.y - ymin) / ch) as usize).min(ny - 1);
                sum[j * nx + i] += m / predicted;
                count[j * nx + i] += 1;
            }
            let values = sum
                .iter()
                .zip(&count)
                .map(|(s, &n)| if n > 0 { s / n as f64 } else { 1.0 })
                .collect();
            Ok(crate::solve::GainGrid {
                x0: xmin + 0.5 * cw,
                y0: ymin + 0.5 * ch,
                dx: cw,
                dy: ch,
                nx,
                ny,
                values,
            })
        })
        .collect()
}
