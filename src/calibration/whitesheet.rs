//! The white sheet: a near-perfect diffuse sheet flat on the table, photographed under each
//! LED. Block means of its images (which average the paper's fibre texture away) measure each
//! light's intensity across the field; they are the data the LED positions are fitted to
//! (the `lights` step) and, stored as maps, what the bundle keeps of the sheet. Re-solving the
//! sheet with the final calibration is the wizard's flatness check.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::plane::{Frames, Plane};
use crate::progress::Progress;
use crate::rig::Rig;
use crate::solve::{
    self, Estimator, LightSource, NoiseModel, PixelStatus, SolveInput, SolveOptions,
    LUMINANCE_WEIGHTS,
};

/// One light's intensity over the sheet: per block, the table point it sees and the linear
/// signal a white (reflectance 1) surface would give there, per channel.
#[derive(Clone, Debug)]
pub struct SheetLight {
    /// Per block, row by row, the table point (world metres) the block's centre sees; zero where
    /// its camera ray misses the table plane.
    pub points: Vec<Vector3<f64>>,
    /// Per block, the linear signal (R, G, B) a surface of reflectance 1 would give; NaN for a
    /// block with a saturated or non-finite pixel or whose ray misses the table.
    pub rgb: Vec<[f64; 3]>,
    /// Pixels averaged per block (their noise averages down by its square root).
    pub pixels_per_block: usize,
    /// Block-grid size, for writing the maps.
    pub grid: (usize, usize),
}

impl SheetLight {
    /// Luminance (Rec. 709 weights, as the solve uses) of each block.
    pub fn luminance(&self) -> Vec<f64> {
        self.rgb
            .iter()
            .map(|c| (0..3).map(|i| LUMINANCE_WEIGHTS[i] * c[i]).sum())
            .collect()
    }

    /// Channel `c` as a plane over the block grid.
    pub fn map(&self, c: usize) -> Plane {
        let (w, h) = self.grid;
        let mut plane = Plane::new(w, h, 0.0);
        for (i, v) in self.rgb.iter().enumerate() {
            plane.data[i] = v[c] as f32;
        }
        plane
    }
}

/// Block means of every light's sheet image, divided by the sheet's reflectance, at the table
/// points the blocks' centres see through `rig`'s (calibrated) camera. Blocks with a saturated
/// or non-finite pixel are left out.
pub fn measure(
    frames: &Frames,
    rig: &Rig,
    reflectance: f64,
    block: usize,
) -> Result<Vec<SheetLight>> {
    frames.validate()?;
    if !(reflectance.is_finite() && reflectance > 0.0 && reflectance <= 1.0) {
        return Err(Error::Invalid(format!(
            "white sheet reflectance must lie in (0, 1], got {reflectance}"
        )));
    }
    if frames.lights.len() != rig.leds.len() {
        return Err(Error::Invalid(format!(
            "{} white-sheet frames for a rig with {} LEDs",
            frames.lights.len(),
            rig.leds.len()
        )));
    }
    let block = block.max(1);
    let (bw, bh) = (frames.width / block, frames.height / block);
    if bw < 4 || bh < 4 {
        return Err(Error::Invalid(format!(
            "white-sheet frames of {}x{} give fewer than 4x4 blocks of {block} px",
            frames.width, frames.height
        )));
    }
    let mapper = rig.camera.plane_mapper(rig.sample.z_m);
    let mut out = Vec::with_capacity(frames.lights.len());
    for frame in &frames.lights {
        let mut points = Vec::new();
        let mut rgb = Vec::new();
        for by in 0..bh {
            for bx in 0..bw {
                let mut sum = [0.0f64; 3];
                let mut usable = true;
                for y in by * block..(by + 1) * block {
                    for x in bx * block..(bx + 1) * block {
                        let i = y * frames.width + x;
                        if frame.saturated.as_ref().is_some_and(|m| m.data[i]) {
                            usable = false;
                        }
                        for (c, plane) in frame.rgb.channels().iter().enumerate() {
                            let v = plane.data[i] as f64;
                            usable &= v.is_finite();
                            sum[c] += v;
                        }
                    }
                }
                let centre = (
                    (bx as f64 + 0.5) * block as f64 - 0.5,
                    (by as f64 + 0.5) * block as f64 - 0.5,
                );
                let (u, v) = frames.window.to_sensor(centre.0, centre.1);
                let point = mapper.map(u, v);
                let n = (block * block) as f64;
                points.push(point.unwrap_or_else(Vector3::zeros));
                rgb.push(if usable && point.is_some() {
                    sum.map(|s| s / n / reflectance)
                } else {
                    [f64::NAN; 3]
                });
            }
        }
        out.push(SheetLight {
            points,
            rgb,
            pixels_per_block: block * block,
            grid: (bw, bh),
        });
    }
    Ok(out)
}

/// Averages several exposures of the same lights (the flatness check's noise budget).
pub fn average_exposures(exposures: &[Frames]) -> Result<Frames> {
    let first = exposures
        .first()
        .ok_or_else(|| Error::Invalid("no white-sheet exposures to average".into()))?;
    let mut out = first.clone();
    for other in &exposures[1..] {
        if other.width != first.width
            || other.height != first.height
            || other.lights.len() != first.lights.len()
        {
            return Err(Error::Invalid(
                "white-sheet exposures differ in size or light count".into(),
            ));
        }
        for (k, frame) in other.lights.iter().enumerate() {
            let target = &mut out.lights[k];
            for c in 0..3 {
                let (dst, src) = match c {
                    0 => (&mut target.rgb.r, &frame.rgb.r),
                    1 => (&mut target.rgb.g, &frame.rgb.g),
                    _ => (&mut target.rgb.b, &frame.rgb.b),
                };
                for (d, s) in dst.data.iter_mut().zip(&src.data) {
                    *d += s;
                }
            }
            if let (Some(m), Some(o)) = (target.saturated.as_mut(), frame.saturated.as_ref()) {
                for (d, s) in m.data.iter_mut().zip(&o.data) {
                    *d |= *s;
                }
            }
        }
    }
    let n = exposures.len() as f32;
    for frame in &mut out.lights {
        for v in frame
            .rgb
            .r
            .data
            .iter_mut()
            .chain(frame.rgb.g.data.iter_mut())
            .chain(frame.rgb.b.data.iter_mut())
        {
            *v /= n;
        }
    }
    Ok(out)
}

/// How flat the re-solved sheet came out, against what sensor noise alone predicts.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Flatness {
    /// Pixels solved (every one of them is checked).
    pub pixels: usize,
    /// Exposures averaged per light.
    pub exposures: usize,
    /// Mean angle between a solved normal and straight up (degrees).
    pub mean_deg: f64,
    /// The largest angle between a solved normal and straight up: "every normal".
    pub max_deg: f64,
    /// The largest angle of a block-mean normal (16x16 pixels): the calibration's own error
    /// with the noise averaged away.
    pub block_max_deg: f64,
    /// The solve's predicted mean angular error from sensor noise (Rayleigh mean).
    pub predicted_noise_mean_deg: f64,
    /// The level the largest of the pixels' noise-only errors stays under with probability
    /// 99.9 %, from each pixel's predicted error (see [`noise_max_of`]).
    pub predicted_noise_max_deg: f64,
    /// The tolerance `flat` was judged against ([`FLATNESS_TOLERANCE_DEG`]), degrees.
    pub tolerance_deg: f64,
    /// Whether every solved normal lies within `tolerance_deg` of straight up.
    pub flat: bool,
}

/// Tolerance of the flatness check: every normal within this of straight up.
pub const FLATNESS_TOLERANCE_DEG: f64 = 0.5;

/// Noise-only tail: the largest of `pixels` 2-D Gaussian angle errors with Rayleigh mean
/// `mean` stays below this with probability `1 - risk` (P(angle > a) = exp(-a^2 / 2 s^2) per
/// pixel, union bound over pixels).
pub fn noise_max(mean: f64, pixels: usize, risk: f64) -> f64 {
    let sigma = mean / (std::f64::consts::PI / 2.0).sqrt();
    sigma * (2.0 * (pixels.max(1) as f64 / risk).ln()).sqrt()
}

/// The level `a` the largest noise-only error of pixels with Rayleigh means `means` stays
/// under with probability `1 - risk`: the union bound `sum_i exp(-a^2 / 2 s_i^2) = risk`, with
/// `s_i = mean_i / sqrt(pi / 2)`, solved by bisection. Pixels near the field's edges, seen at
/// worse light geometry, dominate it.
pub fn noise_max_of(means: &[f64], risk: f64) -> f64 {
    let sigmas: Vec<f64> = means
        .iter()
        .map(|m| m / (std::f64::consts::PI / 2.0).sqrt())
        .filter(|s| *s > 0.0)
        .collect();
    let Some(largest) = sigmas.iter().copied().reduce(f64::max) else {
        return 0.0;
    };
    let tail = |a: f64| -> f64 { sigmas.iter().map(|s| (-a * a / (2.0 * s * s)).exp()).sum() };
    let (mut lo, mut hi) = (
        0.0,
        largest * (2.0 * (sigmas.len() as f64 / risk).ln()).sqrt(),
    );
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if tail(mid) > risk {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

/// How many exposures to average so that a single exposure's predicted noise tail
/// `single_tail_deg` shrinks (as 1/sqrt(n)) within `budget_deg`.
pub fn exposures_needed(single_tail_deg: f64, budget_deg: f64) -> usize {
    if budget_deg <= 0.0 {
        return usize::MAX;
    }
    ((single_tail_deg / budget_deg).powi(2)).ceil().max(1.0) as usize
}

/// Solves the white sheet with `rig` (the final calibration) and measures how far every
/// solved normal is from straight up.
pub fn flatness(
    frames: &Frames,
    rig: &Rig,
    noise: NoiseModel,
    exposures: usize,
    progress: &dyn Progress,
) -> Result<Flatness> {
    // Averaging n exposures divides the noise variance by n.
    let averaged = NoiseModel {
        photon: noise.photon / exposures as f64,
        floor: noise.floor / exposures as f64,
        ..noise
    };
    let input = SolveInput {
        frames,
        lights: LightSource::Rig(rig),
        noise: averaged,
        exposure: 1.0,
        mask: None,
    };
    // Plain least squares: a white sheet has no shadows or sheen to reject, and the noise
    // tail above is the least-squares estimate's.
    let options = SolveOptions::exact(Estimator::LeastSquares);
    let result = solve::solve(&input, &options, progress)?;
    let up = Vector3::z();
    let mut angles = Vec::new();
    let mut predicted = Vec::new();
    for i in 0..result.status.len() {
        if result.status[i] == PixelStatus::Solved {
            angles.push(result.normal_at(i).angle(&up).to_degrees());
            predicted.push(result.predicted_error_deg.data[i] as f64);
        }
    }
    if angles.is_empty() {
        return Err(Error::Invalid(
            "no pixel of the white sheet could be solved".into(),
        ));
    }
    let pixels = angles.len();
    let predicted_mean = predicted.iter().sum::<f64>() / pixels as f64;
    let max_deg = angles.iter().copied().fold(0.0, f64::max);
    let block_max_deg = block_mean_max(&result, 16);
    Ok(Flatness {
        pixels,
        exposures,
        mean_deg: angles.iter().sum::<f64>() / pixels as f64,
        max_deg,
        block_max_deg,
        predicted_noise_mean_deg: predicted_mean,
        predicted_noise_max_deg: noise_max_of(&predicted, 1e-3),
        tolerance_deg: FLATNESS_TOLERANCE_DEG,
        flat: max_deg <= FLATNESS_TOLERANCE_DEG,
    })
}

/// Largest angle from straight up of the mean normal of `block x block` pixel blocks.
fn block_mean_max(result: &solve::SolveResult, block: usize) -> f64 {
    let (w, h) = (result.width, result.height);
    let mut worst: f64 = 0.0;
    for by in 0..h / block {
        for bx in 0..w / block {
            let mut sum = Vector3::zeros();
            for y in by * block..(by + 1) * block {
                for x in bx * block..(bx + 1) * block {
                    let i = y * w + x;
                    if result.status[i] == PixelStatus::Solved {
                        sum += result.normal_at(i);
                    }
                }
            }
            if sum.norm() > 0.0 {
                worst = worst.max(sum.angle(&Vector3::z()).to_degrees());
            }
        }
    }
    worst
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_noise_tail_grows_with_the_pixel_count_and_exposures_shrink_it() {
        // Rayleigh mean 0.1 deg: sigma 0.0798; over 10^5 pixels at 0.1 % risk the tail is
        // sigma * sqrt(2 ln 1e8) = 0.0798 * 6.07.
        let tail = noise_max(0.1, 100_000, 1e-3);
        assert!((tail - 0.0798 * 6.070).abs() < 1e-3, "{tail}");
        assert!(noise_max(0.1, 1_000_000, 1e-3) > tail);
        // Four exposures halve the noise, so a budget of half the tail needs four.
        assert_eq!(exposures_needed(tail, tail / 2.0 + 1e-12), 4);
        assert_eq!(exposures_needed(0.01, 0.5), 1);
        // The per-pixel bound equals the uniform one when all pixels are alike, and is
        // dominated by the worst pixels otherwise.
        let uniform = noise_max_of(&vec![0.1; 100_000], 1e-3);
        assert!((uniform - tail).abs() < 1e-9 * tail);
        let mut mixed = vec![0.05; 100_000];
        mixed[..1000].fill(0.2);
        let m = noise_max_of(&mixed, 1e-3);
        assert!(m > noise_max(0.2, 1000, 1e-3) && m < noise_max(0.2, 100_000, 1e-3));
    }
}
