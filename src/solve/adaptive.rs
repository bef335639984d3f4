//! Adaptive escalation: least squares everywhere, the robust fit only where it is needed.
//!
//! A pixel escalates when its least-squares luminance residual is larger than the noise model
//! allows: the weighted sum of squared residuals `X = sum_k r_k^2 / s_k^2` of a Lambertian
//! pixel with independent Gaussian noise follows a chi-square distribution with `m - 3`
//! degrees of freedom (`m` lights used), and the test rejects at `significance_sigma` of
//! that distribution. The threshold therefore comes from the noise model, not from tuning: on
//! clean data a known small fraction escalates (0.13 % at 3 sigma), and escalating a clean
//! pixel is harmless because the robust fit keeps all lights that agree. Lights that were
//! dark or saturated are already out of the least-squares fit; a pixel with exactly three
//! lights left cannot be tested (any normal fits three lights) and stays least squares.

use nalgebra::Vector3;

use super::kernel::Measurement;
use super::robust::RobustOptions;

/// The chi-square test of a luminance fit against the noise model.
pub(super) struct ChiSquare {
    sigma: f64,
    relative_model_error: f64,
}

impl ChiSquare {
    pub fn new(options: &RobustOptions) -> Self {
        ChiSquare {
            sigma: options.significance_sigma,
            relative_model_error: options.relative_model_error,
        }
    }

    /// Sets each measurement's test variance: sensor noise, model error, and the f32
    /// precision of the stored planes relative to the pixel's brightest reading (so that
    /// noise-free inputs have a finite test, and no reading's weight outruns the precision
    /// the solve's inputs have).
    pub fn prepare(&self, measurements: &mut [Measurement]) {
        let brightest = measurements.iter().fold(0.0f64, |a, m| a.max(m.lum.abs()));
        let precision = (brightest * f32::EPSILON as f64).powi(2) / 12.0 + f64::MIN_POSITIVE;
        for m in measurements {
            m.test_var = m.var + (self.relative_model_error * m.lum).powi(2) + precision;
        }
    }

    /// The test variance of `m` (set by `prepare`).
    #[inline]
    pub fn variance(&self, m: &Measurement) -> f64 {
        m.test_var
    }

    /// `sum_k r_k^2 / s_k^2` for the luminance fit `n_lum`.
    pub fn statistic(&self, measurements: &[Measurement], n_lum: &Vector3<f64>) -> f64 {
        measurements
            .iter()
            .map(|m| (m.lum - n_lum.dot(&m.l)).powi(2) / self.variance(m))
            .sum()
    }

    /// The statistic's upper limit for `dof` degrees of freedom at `sigma` (Wilson-Hilferty:
    /// `(X/k)^(1/3)` is nearly normal with mean `1 - 2/(9k)` and variance `2/(9k)`).
    pub fn threshold(&self, dof: usize) -> f64 {
        let k = dof as f64;
        let v = 2.0 / (9.0 * k);
        k * (1.0 - v + self.sigma * v.sqrt()).powi(3)
    }

    /// True when the fit explains the measurements within the noise (always, without
    /// redundant lights: three lights fit any normal exactly).
    pub fn accepts(&self, measurements: &[Measurement], n_lum: &Vector3<f64>) -> bool {
        measurements.len() <= 3
            || self.accepts_statistic(self.statistic(measurements, n_lum), measurements.len())
    }

    /// True when `statistic` of a fit to `lights` lights is within the noise.
    pub fn accepts_statistic(&self, statistic: f64, lights: usize) -> bool {
        let dof = lights.saturating_sub(3);
        dof == 0 || statistic <= self.threshold(dof)
    }
}
