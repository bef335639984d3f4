//! The light matrix, per pixel: for each light, the direction from the pixel's point on the
//! sample toward it and its intensity there. With near lights both change across the sample;
//! ignoring that (distant lights) is the low-frequency error of seed Figure 10.

use nalgebra::Vector3;

use crate::error::{Error, Result};
use crate::plane::SensorWindow;
use crate::rig::{LightSample, PlaneMapper, Rig};

/// How the solve models the LEDs of a rig.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum LightModel {
    /// Point sources: direction and inverse-square/beam falloff evaluated at every pixel.
    #[default]
    Near,
    /// One direction and one intensity per LED, those at the point seen by the centre pixel
    /// (as if the LEDs were infinitely far away): the seed's model, kept for comparison.
    Distant,
}

/// Where the lights come from.
#[derive(Clone, Copy, Debug)]
pub enum LightSource<'a> {
    /// A rig's LEDs and camera: each pixel's point on the sample plane is known.
    Rig(&'a Rig),
    /// Distant lights given directly (photometric-stereo benchmarks such as DiLiGenT): unit
    /// directions in the world frame and RGB intensities, one per light.
    Directions {
        /// Direction toward each light, world frame (normalised before use).
        directions: &'a [[f64; 3]],
        /// RGB intensity of each light, in the order of `directions`; every channel positive.
        intensities: &'a [[f64; 3]],
    },
    /// A calibrated rig (LED positions and powers fitted to the white sheet) and, per light,
    /// the sheet's measured intensity over the fitted model's on the table: what the point
    /// model misses (beam asymmetry, reflections in the rig) corrects the falloff.
    Calibrated {
        /// The rig, its LED positions and powers as fitted to the white sheet.
        rig: &'a Rig,
        /// One intensity correction per LED, in the rig's LED order.
        gains: &'a [GainGrid],
    },
}

/// A light's intensity correction over the table: a regular grid of factors in world x, y
/// (metres), bilinear between nodes, clamped at the edges.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GainGrid {
    /// World x of the first grid node, in metres.
    pub x0: f64,
    /// World y of the first grid node, in metres.
    pub y0: f64,
    /// Node spacing along world x, in metres.
    pub dx: f64,
    /// Node spacing along world y, in metres.
    pub dy: f64,
    /// Number of nodes along x.
    pub nx: usize,
    /// Number of nodes along y.
    pub ny: usize,
    /// Row-major, `nx * ny` factors.
    pub values: Vec<f64>,
}

impl GainGrid {
    /// The factor at world `(x, y)`.
    pub fn at(&self, x: f64, y: f64) -> f64 {
        let gx = ((x - self.x0) / self.dx).clamp(0.0, (self.nx - 1) as f64);
        let gy = ((y - self.y0) / self.dy).clamp(0.0, (self.ny - 1) as f64);
        let (i, j) = (
            (gx as usize).min(self.nx.saturating_sub(2)),
            (gy as usize).min(self.ny.saturating_sub(2)),
        );
        let (fx, fy) = (gx - i as f64, gy - j as f64);
        let v = |i: usize, j: usize| self.values[j * self.nx + i];
        if self.nx < 2 || self.ny < 2 {
            return self.values[0];
        }
        (1.0 - fy) * ((1.0 - fx) * v(i, j) + fx * v(i + 1, j))
            + fy * ((1.0 - fx) * v(i, j + 1) + fx * v(i + 1, j + 1))
    }
}

/// Everything the solve needs to know about the lights, precomputed once per solve.
pub struct Illumination<'a> {
    model: LightModel,
    leds: Vec<LedModel>,
    /// Per light: the white-surface signal per colour channel, over the falloff.
    rgb_scale: Vec<[f64; 3]>,
    /// For distant lights: each light's direction and falloff everywhere.
    distant: Vec<LightSample>,
    /// Pixel to sample-plane mapping (rigs only).
    mapper: Option<PlaneMapper<'a>>,
    window: SensorWindow,
    /// The camera's centre (rigs); `None`: an orthographic camera looking down +z.
    camera: Option<Vector3<f64>>,
    /// Per light intensity corrections of a calibrated rig (empty otherwise).
    gains: &'a [GainGrid],
}

struct LedModel {
    position: Vector3<f64>,
    axis: Vector3<f64>,
    beam_exponent: f64,
    power: f64,
}

impl<'a> Illumination<'a> {
    /// Prepares the lights for frames of `width x height` pixels at `window` on the sensor.
    pub fn new(
        source: &LightSource<'a>,
        model: LightModel,
        width: usize,
        height: usize,
        window: SensorWindow,
    ) -> Result<Self> {
        match *source {
            LightSource::Rig(rig) => Self::from_rig(rig, model, width, height, window),
            LightSource::Calibrated { rig, gains } => {
                if gains.len() != rig.leds.len() {
                    return Err(Error::Invalid(format!(
                        "{} light gain grids for a rig with {} LEDs",
                        gains.len(),
                        rig.leds.len()
                    )));
                }
                if let Some(k) = gains.iter().position(|g| {
                    g.nx * g.ny != g.values.len()
                        || g.values.is_empty()
                        || g.values.iter().any(|v| !(v.is_finite() && *v > 0.0))
                }) {
                    return Err(Error::Invalid(format!(
                        "light {k}: the gain grid is empty, the wrong size, or not positive"
                    )));
                }
                let mut ill = Self::from_rig(rig, model, width, height, window)?;
                ill.gains = gains;
                Ok(ill)
            }
            LightSource::Directions {
                directions,
                intensities,
            } => Self::from_directions(directions, intensities, window),
        }
    }

    fn from_rig(
        rig: &'a Rig,
        model: LightModel,
        width: usize,
        height: usize,
        window: SensorWindow,
    ) -> Result<Self> {
        let mapper = rig.camera.plane_mapper(rig.sample.z_m);
        let (cu, cv) = window.to_sensor((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
        let reference = mapper.map(cu, cv).ok_or_else(|| {
            Error::Invalid("the camera does not see the sample plane at the image centre".into())
        })?;
        let leds = rig
            .leds
            .iter()
            .map(|led| LedModel {
                position: led.position(),
                axis: led.axis(),
                beam_exponent: led.beam_exponent(),
                power: led.power,
            })
            .collect();
        let rgb_scale = (0..rig.leds.len())
            .map(|k| rig.led_rgb_power(k).map(|c| c / rig.leds[k].power))
            .collect();
        Ok(Illumination {
            model,
            leds,
            rgb_scale,
            distant: rig
                .leds
                .iter()
                .map(|led| led.sample_at(&reference))
                .collect(),
            mapper: Some(mapper),
            window,
            camera: Some(rig.camera.centre()),
            gains: &[],
        })
    }

    fn from_directions(
        directions: &[[f64; 3]],
        intensities: &[[f64; 3]],
        window: SensorWindow,
    ) -> Result<Self> {
        if directions.len() != intensities.len() {
            return Err(Error::Invalid(format!(
                "{} light directions but {} light intensities",
                directions.len(),
                intensities.len()
            )));
        }
        let mut distant = Vec::with_capacity(directions.len());
        for (k, d) in directions.iter().enumerate() {
            let v = Vector3::from(*d);
            let norm = v.norm();
            if !(norm.is_finite() && norm > 0.0) {
                return Err(Error::Invalid(format!(
                    "light {k}: direction {d:?} is not a direction"
                )));
            }
            if intensities[k].iter().any(|c| !(c.is_finite() && *c > 0.0)) {
                return Err(Error::Invalid(format!(
                    "light {k}: intensity {:?} must be positive",
                    intensities[k]
                )));
            }
            distant.push(LightSample {
                direction: v / norm,
                falloff: 1.0,
            });
        }
        Ok(Illumination {
            model: LightModel::Distant,
            leds: Vec::new(),
            rgb_scale: intensities.to_vec(),
            distant,
            mapper: None,
            window,
            camera: None,
            gains: &[],
        })
    }

    /// The number of lights.
    pub fn len(&self) -> usize {
        self.rgb_scale.len()
    }

    /// Whether there are no lights.
    pub fn is_empty(&self) -> bool {
        self.rgb_scale.is_empty()
    }

    /// How the lights are modelled: the model asked for with a rig, `Distant` for bare directions.
    pub fn model(&self) -> LightModel {
        self.model
    }

    /// The point on the sample seen by frame pixel `(x, y)`; `None` when its ray misses the
    /// sample plane. Lights given as bare directions need no point (the origin stands in).
    #[inline]
    pub fn point(&self, x: usize, y: usize) -> Option<Vector3<f64>> {
        self.point_at(x as f64, y as f64)
    }

    /// [`Illumination::point`] at a fractional pixel position.
    #[inline]
    pub fn point_at(&self, x: f64, y: f64) -> Option<Vector3<f64>> {
        match &self.mapper {
            None => Some(Vector3::zeros()),
            Some(mapper) => {
                let (u, v) = self.window.to_sensor(x, y);
                mapper.map(u, v)
            }
        }
    }

    /// Unit direction from `point` toward the camera (the view vector of a sheen model).
    #[inline]
    pub fn view(&self, point: &Vector3<f64>) -> Vector3<f64> {
        match self.camera {
            Some(centre) => (centre - point).normalize(),
            None => Vector3::z(),
        }
    }

    /// Per-channel factor that turns light `k`'s falloff into the white-surface signal.
    #[inline]
    pub fn rgb_scale(&self, k: usize) -> [f64; 3] {
        self.rgb_scale[k]
    }

    /// Direction toward light `k` and its falloff at `point`, under this solve's light model.
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
                let gain = match self.gains.get(k) {
                    Some(grid) => grid.at(point.x, point.y),
                    None => 1.0,
                };
                LightSample {
                    direction,
                    falloff: led.power * beam / r2 * gain,
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
        let window = SensorWindow::FULL;
        let (w, h) = (rig.camera.width as usize, rig.camera.height as usize);
        let source = LightSource::Rig(&rig);
        let near = Illumination::new(&source, LightModel::Near, w, h, window).unwrap();
        let distant = Illumination::new(&source, LightModel::Distant, w, h, window).unwrap();
        // The default rig's principal point is the sensor centre, straight above the origin.
        let centre = Vector3::zeros();
        let p = Vector3::new(0.15, -0.1, 0.0);
        for k in 0..rig.leds.len() {
            let expected = rig.leds[k].sample_at(&p);
            let got = near.sample(k, &p);
            assert!((got.direction - expected.direction).norm() < 1e-12);
            assert!((got.falloff - expected.falloff).abs() < 1e-12 * expected.falloff);
            let reference = rig.leds[k].sample_at(&centre);
            let d = distant.sample(k, &p);
            assert!((d.direction - reference.direction).norm() < 1e-12);
            assert!((d.falloff - reference.falloff).abs() < 1e-12);
        }
    }

    #[test]
    fn a_calibrated_rig_scales_each_light_by_its_gain_grid() {
        let rig = Rig::default_rig();
        let (w, h) = (rig.camera.width as usize, rig.camera.height as usize);
        let grid = |v: f64| GainGrid {
            x0: -0.2,
            y0: -0.1,
            dx: 0.2,
            dy: 0.2,
            nx: 3,
            ny: 2,
            values: vec![1.0, v, 1.0, 1.0, 1.0, 1.0],
        };
        let gains: Vec<GainGrid> = (0..rig.leds.len())
            .map(|k| grid(1.0 + 0.01 * k as f64))
            .collect();
        let plain = Illumination::new(
            &LightSource::Rig(&rig),
            LightModel::Near,
            w,
            h,
            SensorWindow::FULL,
        )
        .unwrap();
        let source = LightSource::Calibrated {
            rig: &rig,
            gains: &gains,
        };
        let calibrated =
            Illumination::new(&source, LightModel::Near, w, h, SensorWindow::FULL).unwrap();
        // At the node (0, -0.1) light k's factor is 1 + 0.01 k; halfway to (0, 0.1) half of that.
        for (p, f) in [
            (Vector3::new(0.0, -0.1, 0.0), 1.0),
            (Vector3::new(0.0, 0.0, 0.0), 0.5),
        ] {
            for k in 0..rig.leds.len() {
                let expected = 1.0 + f * 0.01 * k as f64;
                let ratio = calibrated.sample(k, &p).falloff / plain.sample(k, &p).falloff;
                assert!((ratio - expected).abs() < 1e-12, "{ratio} vs {expected}");
                assert_eq!(
                    calibrated.sample(k, &p).direction,
                    plain.sample(k, &p).direction
                );
            }
        }
        let short = &gains[..3];
        let source = LightSource::Calibrated {
            rig: &rig,
            gains: short,
        };
        assert!(Illumination::new(&source, LightModel::Near, w, h, SensorWindow::FULL).is_err());
    }

    #[test]
    fn bare_directions_are_normalised_and_checked() {
        let dirs = [[0.0, 0.0, 2.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]];
        let rgb = [[1.0; 3]; 3];
        let source = LightSource::Directions {
            directions: &dirs,
            intensities: &rgb,
        };
        let ill = Illumination::new(&source, LightModel::Near, 4, 4, SensorWindow::FULL).unwrap();
        assert_eq!(ill.model(), LightModel::Distant);
        assert!((ill.sample(0, &Vector3::zeros()).direction - Vector3::z()).norm() < 1e-15);
        let bad = [[0.0; 3], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]];
        let source = LightSource::Directions {
            directions: &bad,
            intensities: &rgb,
        };
        assert!(Illumination::new(&source, LightModel::Distant, 4, 4, SensorWindow::FULL).is_err());
    }
}
