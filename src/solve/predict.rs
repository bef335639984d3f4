//! The predicted-error model: how much sensor noise moves the solved normal.
//!
//! With measurements `I'_k = N . l_k + e_k`, `e_k ~ N(0, s_k^2)` independent, the least-squares
//! estimate has covariance `C_N = A^-1 (sum_k s_k^2 l_k l_k^T) A^-1` with `A = L^T L` (which is
//! `s^2 (L^T L)^-1` when all `s_k` are equal). The unit normal `n = N/|N|` moves, to first
//! order, by `J dN` with `J = (I - n n^T)/|N|`, a 2-D Gaussian in the tangent plane with
//! covariance eigenvalues `l1 >= l2`. The angle between the estimate and the truth is the
//! length of that 2-D vector, whose mean is `sqrt(2/pi) sqrt(l1) E(1 - l2/l1)` with `E` the
//! complete elliptic integral of the second kind (isotropic case: the Rayleigh mean
//! `s sqrt(pi/2)`).

use nalgebra::{Matrix3, Vector3};

use crate::rig::Sensor;

/// Variance of a linear measurement `I` (1.0 = white level): `photon * max(I, 0) + floor`,
/// times the channel's `channel_scale`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NoiseModel {
    /// Shot-noise variance per unit of signal.
    pub photon: f64,
    /// Signal-independent variance: read noise and quantisation.
    pub floor: f64,
    /// Variance of each colour channel (R, G, B) relative to one raw sample at the same signal:
    /// 1 where every pixel measures every channel (psscan's dn16 frames); less where a channel
    /// is a mean of several CFA samples (2x2 binning averages two greens), see
    /// `raw::Resolution::channel_variance_scale`.
    #[serde(default = "unit_channel_scale")]
    pub channel_scale: [f64; 3],
    /// Set for RAW frames developed at full resolution: each pixel's R, G and B are its own CFA
    /// sample times colour ratios that are the same in every frame, so all three carry that
    /// one sample's noise (fully correlated). The sample at pixel `(x, y)` is of channel
    /// `pattern[y % 2][x % 2]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shared_cfa_sample: Option<[[u8; 2]; 2]>,
}

fn unit_channel_scale() -> [f64; 3] {
    [1.0; 3]
}

impl NoiseModel {
    /// No noise at all (an ideal sensor): the predicted error is zero.
    pub const NONE: NoiseModel = NoiseModel {
        photon: 0.0,
        floor: 0.0,
        channel_scale: [1.0; 3],
        shared_cfa_sample: None,
    };

    /// The sensor's noise in linear units: photon noise (Poisson, variance = electrons),
    /// read noise, and the `1/12 DN^2` of rounding to whole digital numbers.
    pub fn from_sensor(sensor: &Sensor) -> Self {
        let full_scale_dn = sensor.white_level - sensor.black_level;
        let gain = sensor.gain_e_per_dn;
        NoiseModel {
            photon: 1.0 / (full_scale_dn * gain),
            floor: ((sensor.read_noise_e / gain).powi(2) + 1.0 / 12.0) / full_scale_dn.powi(2),
            channel_scale: [1.0; 3],
            shared_cfa_sample: None,
        }
    }

    /// The same sensor with each channel's variance scaled (see `channel_scale`).
    pub fn with_channel_scale(self, channel_scale: [f64; 3]) -> Self {
        NoiseModel {
            channel_scale,
            ..self
        }
    }

    /// Variance of one raw sample at `value`.
    #[inline]
    pub fn variance(&self, value: f64) -> f64 {
        self.photon * value.max(0.0) + self.floor
    }

    /// Variance of channel `c` (0 = R, 1 = G, 2 = B) at `value`.
    #[inline]
    pub fn channel_variance(&self, c: usize, value: f64) -> f64 {
        self.channel_scale[c] * self.variance(value)
    }

    /// Variance of a pixel's light-normalised luminance `lum = sum_c weights[c] * raw[c] *
    /// inv_intensity[c]`, from its channel values `raw` at pixel `(x, y)`: independent channels
    /// add their variances; channels sharing one CFA sample `v` (`shared_cfa_sample`) are all
    /// proportional to it, so `lum` is too and its relative variance is that of `v`.
    #[inline]
    pub fn luminance_variance(
        &self,
        raw: &[f64; 3],
        inv_intensity: &[f64; 3],
        weights: &[f64; 3],
        lum: f64,
        (x, y): (usize, usize),
    ) -> f64 {
        if let Some(pattern) = self.shared_cfa_sample {
            let v = raw[pattern[y % 2][x % 2] as usize];
            if v > 0.0 {
                return lum * lum * self.variance(v) / (v * v);
            }
        }
        (0..3)
            .map(|c| (weights[c] * inv_intensity[c]).powi(2) * self.channel_variance(c, raw[c]))
            .sum()
    }

    /// The test that leaves a dark light (attached or cast shadow) out of a pixel's fit, at
    /// `sigmas` deviations of the noise floor of the luminance (`weights`) or, where the
    /// channels share one CFA sample, of that sample (see `DarkTest`).
    pub fn dark_test(&self, weights: &[f64; 3], sigmas: f64) -> DarkTest {
        DarkTest {
            weights: *weights,
            luminance: sigmas * self.luminance_floor_variance(weights).sqrt(),
            sample: (self.shared_cfa_sample).map(|pattern| (pattern, sigmas * self.floor.sqrt())),
        }
    }

    /// Signal-independent variance of the luminance (`weights` per channel).
    pub fn luminance_floor_variance(&self, weights: &[f64; 3]) -> f64 {
        (0..3)
            .map(|c| weights[c] * weights[c] * self.channel_scale[c] * self.floor)
            .sum()
    }
}

/// When a pixel's reading under a light is dark: at or below a number of deviations of the
/// noise floor ([`NoiseModel::dark_test`]). Where the channels share one CFA sample, the
/// pixel's luminance is that sample times a factor of its colour ratios, and so is the
/// luminance's noise, so the sample is tested against its own floor. Tested as three
/// independent channels' luminance, the bar sat at a fraction of a deviation where the
/// missing channels are much brighter than the own one (a green site of a red thread), and a
/// light in attached shadow passed it often enough to send 2.2 % of a clean 3 MP Lambertian
/// DNG set's pixels to the robust fit (the same scene's dn16 set: 0.09 %).
#[derive(Clone, Copy, Debug)]
pub struct DarkTest {
    /// The luminance's weights per channel.
    pub weights: [f64; 3],
    /// The luminance at or below which a light is dark.
    pub luminance: f64,
    /// Where the channels share one CFA sample: its pattern (`pattern[y % 2][x % 2]` is the
    /// sample's channel) and the sample's threshold, tested instead of `luminance`.
    pub sample: Option<([[u8; 2]; 2], f64)>,
}

impl DarkTest {
    /// Whether pixel `(x, y)`'s channel values `raw` under one light are dark.
    pub fn is_dark(&self, raw: &[f64; 3], (x, y): (usize, usize)) -> bool {
        match self.sample {
            Some((pattern, threshold)) => raw[pattern[y % 2][x % 2] as usize] <= threshold,
            None => {
                let lum: f64 = (0..3).map(|c| self.weights[c] * raw[c]).sum();
                lum <= self.luminance
            }
        }
    }
}

/// Mean angular error (radians) of a normal estimated as `N` with covariance `cov_n`.
pub fn expected_angle_error(n_scaled: &Vector3<f64>, cov_n: &Matrix3<f64>) -> f64 {
    let length = n_scaled.norm();
    if length <= 0.0 || !length.is_finite() {
        return 0.0;
    }
    let n = n_scaled / length;
    let (t1, t2) = tangent_basis(&n);
    // Tangent-plane covariance of the unit normal.
    let a = t1.dot(&(cov_n * t1)) / (length * length);
    let b = t1.dot(&(cov_n * t2)) / (length * length);
    let d = t2.dot(&(cov_n * t2)) / (length * length);
    let mean = 0.5 * (a + d);
    let spread = (0.25 * (a - d) * (a - d) + b * b).sqrt();
    let l1 = (mean + spread).max(0.0);
    let l2 = (mean - spread).max(0.0);
    if l1 <= 0.0 {
        return 0.0;
    }
    (2.0 / std::f64::consts::PI).sqrt() * l1.sqrt() * elliptic_e(1.0 - l2 / l1)
}

/// Two unit vectors completing `n` to an orthonormal basis.
pub(crate) fn tangent_basis(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let t1 = n.cross(&helper).normalize();
    let t2 = n.cross(&t1);
    (t1, t2)
}

/// Complete elliptic integral of the second kind, `E(m) = int_0^{pi/2} sqrt(1 - m sin^2 t) dt`,
/// by the arithmetic-geometric mean (converges quadratically).
pub fn elliptic_e(m: f64) -> f64 {
    let m = m.clamp(0.0, 1.0);
    if m >= 1.0 - 1e-15 {
        return 1.0;
    }
    let (mut a, mut b) = (1.0f64, (1.0 - m).sqrt());
    let mut sum = 0.5 * m;
    let mut weight = 0.5;
    for _ in 0..40 {
        let c = 0.5 * (a - b);
        (a, b) = (0.5 * (a + b), (a * b).sqrt());
        weight *= 2.0;
        sum += weight * c * c;
        if c.abs() < 1e-16 {
            break;
        }
    }
    std::f64::consts::PI / (2.0 * a) * (1.0 - sum)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    #[test]
    fn elliptic_e_known_values() {
        assert!((elliptic_e(0.0) - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
        assert!((elliptic_e(0.5) - 1.350_643_881_047_675_5).abs() < 1e-13);
        assert!((elliptic_e(0.9) - 1.104_774_732_704_073).abs() < 1e-12);
        assert!((elliptic_e(1.0) - 1.0).abs() < 1e-15);
    }

    #[test]
    fn expected_angle_matches_monte_carlo_for_anisotropic_noise() {
        let n = Vector3::new(0.3, -0.2, 0.9).normalize() * 0.7;
        let cov = Matrix3::new(4e-6, 1e-6, 0.0, 1e-6, 1e-6, 0.0, 0.0, 0.0, 2e-6);
        let predicted = expected_angle_error(&n, &cov);
        let chol = cov.cholesky().unwrap().l();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        let trials = 200_000;
        let mut sum = 0.0;
        for _ in 0..trials {
            let z = Vector3::from_fn(|_, _| StandardNormal.sample(&mut rng));
            let noisy = n + chol * z;
            sum += noisy
                .normalize()
                .dot(&n.normalize())
                .clamp(-1.0, 1.0)
                .acos();
        }
        let measured = sum / trials as f64;
        // Monte Carlo standard error is about 0.5 % here; the first-order model is exact to
        // well under that at this noise level.
        assert!(
            (measured / predicted - 1.0).abs() < 0.01,
            "measured {measured}, predicted {predicted}"
        );
    }

    #[test]
    fn luminance_variance_of_independent_and_of_shared_channels() {
        let rig = crate::rig::Rig::default_rig();
        let noise = NoiseModel::from_sensor(&rig.sensor).with_channel_scale([1.0, 0.5, 1.0]);
        let w = [0.2, 0.7, 0.1];
        let inv = [2.0, 1.0, 1.5];
        let raw = [0.1, 0.4, 0.2];
        let lum: f64 = (0..3).map(|c| w[c] * inv[c] * raw[c]).sum();
        let independent: f64 = (0..3)
            .map(|c| (w[c] * inv[c]).powi(2) * noise.channel_scale[c] * noise.variance(raw[c]))
            .sum();
        assert_eq!(
            noise.luminance_variance(&raw, &inv, &w, lum, (3, 5)),
            independent
        );
        // Sharing pixel (3, 5)'s CFA sample: in GBRG that is row 1, column 1, a G sample.
        let shared = NoiseModel {
            shared_cfa_sample: Some([[1, 2], [0, 1]]),
            ..noise
        };
        let v = raw[1];
        let expected = lum * lum * noise.variance(v) / (v * v);
        assert!((shared.luminance_variance(&raw, &inv, &w, lum, (3, 5)) - expected).abs() < 1e-18);
        // Pixel (2, 5) holds the R sample.
        let v = raw[0];
        let expected = lum * lum * noise.variance(v) / (v * v);
        assert!((shared.luminance_variance(&raw, &inv, &w, lum, (2, 5)) - expected).abs() < 1e-18);
    }

    #[test]
    fn sensor_noise_model_in_linear_units() {
        let rig = crate::rig::Rig::default_rig();
        let noise = NoiseModel::from_sensor(&rig.sensor);
        let fs = rig.sensor.white_level - rig.sensor.black_level;
        // Half scale: 7500 DN * 2.6 e/DN = 19500 electrons of shot noise.
        let electrons = 0.5 * fs * rig.sensor.gain_e_per_dn;
        let expected_dn2 = electrons / rig.sensor.gain_e_per_dn.powi(2)
            + (rig.sensor.read_noise_e / rig.sensor.gain_e_per_dn).powi(2)
            + 1.0 / 12.0;
        assert!((noise.variance(0.5) * fs * fs - expected_dn2).abs() < 1e-9 * expected_dn2);
    }
}
