//! The synthetic camera sensor: turns linear light into digital numbers the way a RAW file
//! stores them. Photon noise (Gaussian with variance equal to the electron count, the
//! Poisson limit), read noise, the black level offset, rounding to whole DN, and clipping at
//! the white level. Seeded per row, so renders are deterministic whatever the thread count.

use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;
use rayon::prelude::*;

use super::textile::splitmix;
use crate::plane::RgbPlanes;
use crate::raw::DnImage;
use crate::rig::Sensor;

/// Whether the sensor adds noise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Noise {
    /// Rounding and clipping only.
    Off,
    /// Photon and read noise from this seed.
    Seeded(u64),
}

/// Exposes `planes` (1.0 = white level) on `sensor`. `stream` separates the noise of
/// different frames rendered with the same seed.
pub fn expose(planes: &RgbPlanes, sensor: &Sensor, noise: Noise, stream: u64) -> DnImage {
    let (width, height) = (planes.width(), planes.height());
    let mut data = vec![0u16; width * height * 3];
    let channels = planes.channels();
    data.par_chunks_mut(width * 3)
        .enumerate()
        .for_each(|(y, row)| {
            let mut rng = row_rng(noise, stream, y);
            for x in 0..width {
                for (c, plane) in channels.iter().enumerate() {
                    row[x * 3 + c] = to_dn(plane.data[y * width + x], sensor, rng.as_mut());
                }
            }
        });
    DnImage {
        width,
        height,
        data,
    }
}

/// Exposes `planes` on a sensor behind a Bayer colour filter array: the sample at `(x, y)`
/// records channel `pattern[y % 2][x % 2]` of that pixel, through the same noise, rounding
/// and clipping as [`expose`]. Returns the row-major CFA samples.
pub fn expose_mosaic(
    planes: &RgbPlanes,
    pattern: [[u8; 2]; 2],
    sensor: &Sensor,
    noise: Noise,
    stream: u64,
) -> Vec<u16> {
    let (width, height) = (planes.width(), planes.height());
    let mut data = vec![0u16; width * height];
    let channels = planes.channels();
    data.par_chunks_mut(width.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            let mut rng = row_rng(noise, stream, y);
            for (x, sample) in row.iter_mut().enumerate() {
                let plane = channels[pattern[y % 2][x % 2] as usize];
                *sample = to_dn(plane.data[y * width + x], sensor, rng.as_mut());
            }
        });
    data
}

fn row_rng(noise: Noise, stream: u64, y: usize) -> Option<Xoshiro256PlusPlus> {
    match noise {
        Noise::Off => None,
        Noise::Seeded(seed) => Some(Xoshiro256PlusPlus::seed_from_u64(splitmix(
            seed ^ splitmix(stream.wrapping_mul(0x1_0000_0001) ^ y as u64),
        ))),
    }
}

/// One linear value (1.0 = white level) as the sensor records it.
#[inline]
fn to_dn(value: f32, sensor: &Sensor, rng: Option<&mut Xoshiro256PlusPlus>) -> u16 {
    let gain = sensor.gain_e_per_dn;
    let electrons = value as f64 * (sensor.white_level - sensor.black_level) * gain;
    let noisy = match rng {
        None => electrons,
        Some(rng) => {
            let sigma = (electrons.max(0.0) + sensor.read_noise_e.powi(2)).sqrt();
            let z: f64 = StandardNormal.sample(rng);
            electrons + sigma * z
        }
    };
    let dn = (sensor.black_level + noisy / gain).round();
    dn.clamp(0.0, sensor.white_level) as u16
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plane::Plane;
    use crate::raw::Levels;
    use crate::rig::Rig;

    fn flat(value: f32) -> RgbPlanes {
        RgbPlanes {
            r: Plane::new(64, 64, value),
            g: Plane::new(64, 64, value),
            b: Plane::new(64, 64, value),
        }
    }

    #[test]
    fn noise_has_the_model_variance_and_is_deterministic() {
        let rig = Rig::default_rig();
        let planes = flat(0.4);
        let a = expose(&planes, &rig.sensor, Noise::Seeded(3), 1);
        let b = expose(&planes, &rig.sensor, Noise::Seeded(3), 1);
        let c = expose(&planes, &rig.sensor, Noise::Seeded(3), 2);
        assert_eq!(a.data, b.data);
        assert_ne!(a.data, c.data);
        let frame = a.to_light_frame(&Levels::from_sensor(&rig.sensor));
        let values = &frame.rgb.g.data;
        let mean = values.iter().map(|&v| v as f64).sum::<f64>() / values.len() as f64;
        let var = values
            .iter()
            .map(|&v| (v as f64 - mean).powi(2))
            .sum::<f64>()
            / (values.len() - 1) as f64;
        let model = crate::solve::NoiseModel::from_sensor(&rig.sensor).variance(0.4);
        assert!((mean - 0.4).abs() < 4.0 * (model / values.len() as f64).sqrt());
        // 4096 samples: the sample variance is within about 3 x sqrt(2/n) = 7 % of the truth.
        assert!((var / model - 1.0).abs() < 0.07, "var {var} model {model}");
    }

    #[test]
    fn values_clip_at_the_white_level_and_are_flagged() {
        let rig = Rig::default_rig();
        let dn = expose(&flat(1.5), &rig.sensor, Noise::Off, 0);
        assert!(dn.data.iter().all(|&v| v as f64 == rig.sensor.white_level));
        let frame = dn.to_light_frame(&Levels::from_sensor(&rig.sensor));
        assert_eq!(frame.saturated.unwrap().count(), 64 * 64);
        let dn = expose(&flat(0.25), &rig.sensor, Noise::Off, 0);
        let frame = dn.to_light_frame(&Levels::from_sensor(&rig.sensor));
        // A frame that clips nowhere gets no mask at all.
        assert!(frame.saturated.is_none());
        let step = 1.0 / (rig.sensor.white_level - rig.sensor.black_level);
        assert!((frame.rgb.r.data[0] as f64 - 0.25).abs() <= 0.5 * step + 1e-7);
    }
}
