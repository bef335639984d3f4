//! The chi-square test of a luminance fit against the noise model, and the weighted fit whose
//! statistic it tests (the second link of the solve's chain: the sheen lobe, the robust fit and
//! the adaptive screen all decide with it).

use nalgebra::{Matrix3, Vector3};

use super::measure::{condition_of, Fit, Gram, Measurement};
use super::PixelFit;

/// The chi-square test of a luminance fit against the noise model.
pub(super) struct ChiSquare {
    sigma: f64,
    relative_model_error: f64,
    /// [`ChiSquare::threshold`] of each degree of freedom below [`TABULATED_DOF`], computed
    /// once: the robust fit tests after every light it drops.
    thresholds: [f64; TABULATED_DOF],
}

/// Degrees of freedom whose threshold is tabulated (rigs of up to 258 lights).
const TABULATED_DOF: usize = 256;

impl ChiSquare {
    /// The test at `significance_sigma`, with `relative_model_error` of the reading added in
    /// quadrature to the sensor noise (see `RobustOptions`).
    pub fn new(significance_sigma: f64, relative_model_error: f64) -> Self {
        let mut chi = ChiSquare {
            sigma: significance_sigma,
            relative_model_error,
            thresholds: [0.0; TABULATED_DOF],
        };
        chi.thresholds = std::array::from_fn(|dof| chi.threshold(dof));
        chi
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

    /// Whether a Lambertian surface explains the measurements within the noise (always,
    /// without redundant lights: three lights fit any normal exactly). `n_lum` is the
    /// least-squares fit: where its statistic passes, so does the minimum; otherwise the test
    /// is decided on the weighted fit, the one whose statistic follows the chi-square
    /// distribution. (The unweighted fit's statistic is inflated where the lights' variances
    /// differ, so tested on it far more clean pixels fail than the test's false-alarm rate:
    /// docs/solve.md.) A failing pixel's weighted fit comes back for the robust fit to start
    /// from.
    pub fn screen(&self, measurements: &[Measurement], n_lum: &Vector3<f64>) -> Screened {
        let lights = measurements.len();
        if lights <= 3 || self.accepts_statistic(self.statistic(measurements, n_lum), lights) {
            return Screened::Passes;
        }
        match weighted_fit(self, measurements) {
            Some(fit) if self.accepts_statistic(fit.chi2, lights) => Screened::Passes,
            weighted => Screened::Fails(weighted),
        }
    }

    /// True when `statistic` of a fit to `lights` lights is within the noise.
    pub fn accepts_statistic(&self, statistic: f64, lights: usize) -> bool {
        let dof = lights.saturating_sub(3);
        let threshold = match self.thresholds.get(dof) {
            Some(&tabulated) => tabulated,
            None => self.threshold(dof),
        };
        dof == 0 || statistic <= threshold
    }
}

/// The outcome of [`ChiSquare::screen`].
pub(super) enum Screened {
    Passes,
    /// The pixel fails the test; the weighted fit of all its lights, where it exists.
    Fails(Option<WeightedFit>),
}

/// Weighted least squares (`W = 1 / variance` of each light's luminance) on the luminance:
/// the maximum-likelihood fit under the noise model, whose residual is chi-square distributed.
#[derive(Clone)]
pub(super) struct WeightedFit {
    pub n_lum: Vector3<f64>,
    /// `(L^T W L)^-1`: the covariance of `n_lum`.
    pub cov: Matrix3<f64>,
    pub chi2: f64,
}

pub(super) fn weighted_fit(chi: &ChiSquare, measurements: &[Measurement]) -> Option<WeightedFit> {
    let mut a = Gram::default();
    let mut b = Vector3::zeros();
    for m in measurements {
        let w = 1.0 / chi.variance(m);
        a.add(&m.l, w);
        b += m.l * (m.lum * w);
    }
    let cov = a.matrix().try_inverse()?;
    let n_lum = cov * b;
    let chi2 = chi.statistic(measurements, &n_lum);
    Some(WeightedFit { n_lum, cov, chi2 })
}

impl WeightedFit {
    /// The colour solves with the same weights, in the kernel's shape.
    pub fn into_fit(
        self,
        chi: &ChiSquare,
        measurements: &[Measurement],
        condition: f64,
        rejected: bool,
    ) -> Fit {
        let mut b_rgb = [Vector3::zeros(); 3];
        for m in measurements {
            // The luminance weights serve the colour channels too: their noise is proportional.
            let w = 1.0 / chi.variance(m);
            for c in 0..3 {
                b_rgb[c] += m.l * (m.rgb[c] * w);
            }
        }
        let condition = if rejected {
            condition_of(measurements)
        } else {
            condition
        };
        Fit {
            n_lum: self.n_lum,
            n_rgb: b_rgb.map(|b| self.cov * b),
            a_inv: self.cov,
            weighted: true,
            condition,
            residual: None,
            kind: if rejected {
                PixelFit::Robust
            } else {
                PixelFit::LeastSquares
            },
        }
    }
}
