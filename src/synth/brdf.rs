//! Reflectance models for the synthetic sample: Lambertian, and the cloth BRDF of seed 004
//! (eqs. 21-23): an inverted-Gaussian "velvet" distribution with an offset, Schlick Fresnel,
//! no geometry term and the smoothed denominator `4 (n.l + n.v - (n.l)(n.v))`.

use nalgebra::Vector3;

/// Parameters of the sheen lobe: the solver's model of the material, so that the renderer and
/// the sheen fit share one definition of the lobe (seed eq. 21-23).
pub type Sheen = crate::solve::SheenModel;

/// `pi * f * (n.l)` per channel for diffuse albedo `kd` under the sheen BRDF: the factor that
/// multiplies the light's white-surface signal (for a Lambertian surface this is `kd * n.l`).
pub fn sheen_shade(
    sheen: &Sheen,
    kd: [f64; 3],
    n: &Vector3<f64>,
    l: &Vector3<f64>,
    v: &Vector3<f64>,
) -> [f64; 3] {
    let nl = n.dot(l);
    if nl <= 0.0 {
        return [0.0; 3];
    }
    let nv = n.dot(v).max(0.0);
    let h = (l + v).normalize();
    let vh = v.dot(&h).clamp(0.0, 1.0);
    let d = sheen.distribution(n.dot(&h).clamp(-1.0, 1.0));
    let denominator = 4.0 * (nl + nv - nl * nv);
    std::array::from_fn(|c| {
        let f = sheen.f0[c] + (1.0 - sheen.f0[c]) * (1.0 - vh).powi(5);
        let brdf = (1.0 - f) * kd[c] / std::f64::consts::PI + f * d / denominator;
        std::f64::consts::PI * brdf * nl
    })
}

/// Lambertian shading: `kd * max(n.l, 0)`.
pub fn lambert(kd: [f64; 3], n: &Vector3<f64>, l: &Vector3<f64>) -> [f64; 3] {
    let nl = n.dot(l).max(0.0);
    kd.map(|c| c * nl)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn velvet_distribution_is_normalised_over_the_projected_hemisphere() {
        // Seed eq. 22 is normalised like Beckmann: integral of D cos(theta_h) dw = 1.
        let sheen = Sheen::default();
        let steps = 200_000;
        let mut sum = 0.0;
        for i in 0..steps {
            let theta = (i as f64 + 0.5) / steps as f64 * std::f64::consts::FRAC_PI_2;
            sum += sheen.distribution(theta.cos()) * theta.cos() * theta.sin();
        }
        let integral = sum * std::f64::consts::FRAC_PI_2 / steps as f64 * std::f64::consts::TAU;
        assert!((integral - 1.0).abs() < 1e-3, "{integral}");
    }

    #[test]
    fn sheen_peaks_toward_grazing_half_angles() {
        let sheen = Sheen::default();
        assert!(sheen.distribution(0.2) > 3.0 * sheen.distribution(0.95));
    }

    #[test]
    fn shading_is_zero_facing_away_and_close_to_lambert_with_no_fresnel() {
        let n = Vector3::z();
        let l = Vector3::new(0.0, -1.0, 0.2).normalize();
        let v = Vector3::z();
        assert_eq!(
            sheen_shade(
                &Sheen::default(),
                [0.5; 3],
                &n,
                &Vector3::new(0.0, 0.0, -1.0),
                &v
            ),
            [0.0; 3]
        );
        let no_sheen = Sheen {
            f0: [0.0; 3],
            ..Sheen::default()
        };
        let s = sheen_shade(&no_sheen, [0.5; 3], &n, &l, &v);
        // Schlick is not zero at grazing even with f0 = 0; it only lowers the diffuse part.
        assert!(s[0] <= lambert([0.5; 3], &n, &l)[0] + 1e-12);
    }
}
