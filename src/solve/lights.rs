//! The light matrix, per pixel: for each LED, the direction from the pixel's point on the
//! sample toward the LED and the LED's intensity there. With near lights both change across
//! the sample; ignoring that (distant lights) is the low-frequency error of seed Figure 10.

use nalgebra::Vector3;

use crate::rig::{LightSample, Rig};

/// How the solve models the LEDs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum LightModel {
    /// Point sources: direction and inverse-square/beam falloff evaluated at every pixel.
    #[default]
    Near,
    /// One direction and one intensity per LED, those at the reference point (as if the LEDs
    /// were infinitely far away): the seed's model, kept for comparison.
    Distant,
}

/// Everything the solve needs to know about the LEDs, precomputed once per solve.
pub struct Illumination {
    leds: Vec<LedModel>,
    model: LightModel,
    /// For `Distant`: each LED's direction and falloff at the reference point.
    distant: Vec<LightSample>,
}

struct LedModel {
    position: Vector3<f64>,
    axis: Vector3<f64>,
    beam_exponent: f64,
    power: f64,
    /// Linear signal per colour channel of a white surface at 1 m on axis, over `power`.
    rgb_scale: [f64; 3],
}

impl Illumination {
    /// `reference` is the point whose light the distant model uses everywhere (the sample
    /// point at the centre of the frames).
    pub fn new(rig: &Rig, model: LightModel, reference: Vector3<f64>) -> Self {
        let leds: Vec<LedModel> = rig
            .leds
            .iter()
            .enumerate()
            .map(|(k, led)| {
                let rgb = rig.led_rgb_power(k);
                LedModel {
                    position: led.position(),
                    axis: led.axis(),
                    beam_exponent: led.beam_exponent(),
                    power: led.power,
                    rgb_scale: rgb.map(|c| c / led.power),
                }
            })
            .collect();
        let distant = rig
            .leds
            .iter()
            .map(|led| led.sample_at(&reference))
            .collect();
        Illumination {
            leds,
            model,
            distant,
        }
    }

    pub fn len(&self) -> usize {
        self.leds.len()
    }

    pub fn is_empty(&self) -> bool {
        self.leds.is_empty()
    }

    pub fn model(&self) -> LightModel {
        self.model
    }

    /// Per-channel factor that turns LED `k`'s falloff into the white-surface signal.
    #[inline]
    pub fn rgb_scale(&self, k: usize) -> [f64; 3] {
        self.leds[k].rgb_scale
    }

    /// Direction toward LED `k` and its falloff at `point`, under this solve's light model.
    #[inline]
    pub fn sample(&self, k: usize, point: &Vector3<f64>) -> LightSample {
        match self.model {
            LightModel::Distant => self.distant[k],
            LightModel::Near => {
                let led = &self.leds[k];
                let to_led = led.position - point;
                let r2 = to_led.norm_squared();
                let direction = to_led / r2.sqrt();
                let cos_theta = -led.axis.dot(&direction);
                let beam = if cos_theta <= 0.0 {
                    0.0
                } else if led.beam_exponent == 1.0 {
                    cos_theta
                } else {
                    cos_theta.powf(led.beam_exponent)
                };
                LightSample {
                    direction,
                    falloff: led.power * beam / r2,
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_model_matches_the_rig_and_distant_model_is_constant() {
        let rig = Rig::default_rig();
        let reference = Vector3::zeros();
        let near = Illumination::new(&rig, LightModel::Near, reference);
        let distant = Illumination::new(&rig, LightModel::Distant, reference);
        let p = Vector3::new(0.15, -0.1, 0.0);
        for k in 0..rig.leds.len() {
            let expected = rig.leds[k].sample_at(&p);
            let got = near.sample(k, &p);
            assert!((got.direction - expected.direction).norm() < 1e-12);
            assert!((got.falloff - expected.falloff).abs() < 1e-12 * expected.falloff);
            assert_eq!(distant.sample(k, &p), rig.leds[k].sample_at(&reference));
        }
    }
}
