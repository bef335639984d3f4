//! The physical description of a scanner: where the LEDs are and how they shine, where the
//! camera is and how it images, what the sensor's levels and noise are. Read from and written
//! to `rig.toml`; validated with errors that name the offending field. No device I/O here.

mod citation;
mod geometry;
mod targets;

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

pub use citation::CalibrationRef;
pub use geometry::{LightSample, PlaneMapper};
pub use targets::{Board, ChartDescription, ChartRect};

/// The rig that ships with psscan (`calibration/default/rig.toml`), embedded in the binary so
/// `psscan demo` runs anywhere.
pub const DEFAULT_RIG_TOML: &str = include_str!("../../calibration/default/rig.toml");

/// The scanner as built (`rig.toml`): the camera, its sensor, where the sample lies, and the
/// LEDs in the order the controller numbers them. Lengths in metres, world frame of
/// DESIGN.md (origin at the table centre, +z toward the camera).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rig {
    /// The rig's name, as capture sets and reports record it.
    pub name: String,
    /// Free text: who measured it, when, how.
    #[serde(default)]
    pub description: String,
    /// The camera's optics and pose.
    pub camera: Camera,
    /// The sensor's levels and noise.
    pub sensor: Sensor,
    /// Where the sample's surface lies.
    #[serde(default)]
    pub sample: SamplePlane,
    /// The LEDs, index `k` being the controller's LED `k` and the capture set's frame `Lkk`.
    pub leds: Vec<Led>,
}

/// A pinhole camera with OpenCV-style distortion, placed in the world.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Sensor width in pixels.
    pub width: u32,
    /// Sensor height in pixels.
    pub height: u32,
    /// Focal length along columns, in pixels (pixel centres are at integer coordinates).
    pub fx: f64,
    /// Focal length along rows, in pixels.
    pub fy: f64,
    /// Principal point's column, in pixels.
    pub cx: f64,
    /// Principal point's row, in pixels.
    pub cy: f64,
    /// k1 k2 p1 p2 k3, OpenCV's order and model.
    #[serde(default)]
    pub distortion: [f64; 5],
    /// Centre of projection in world metres.
    pub position_m: [f64; 3],
    /// Rotations about world x, then y, then z (degrees) applied to a camera that looks
    /// straight down with image columns along +x and image rows toward -y.
    #[serde(default)]
    pub rotation_deg: [f64; 3],
}

/// The sensor's digital levels and noise, as the RAW files report them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sensor {
    /// Bits per RAW sample (12, 14, 16).
    pub bits: u32,
    /// The digital number of no light.
    pub black_level: f64,
    /// The digital number where the sensor clips.
    pub white_level: f64,
    /// Electrons per digital number (the inverse of the conversion gain) at the capture ISO.
    pub gain_e_per_dn: f64,
    /// Read noise in electrons RMS.
    pub read_noise_e: f64,
    /// Raw R, G, B response to the rig's white LEDs relative to green (what white balance
    /// undoes).
    #[serde(default = "unit_rgb")]
    pub channel_gain: [f64; 3],
}

/// Where the sample's surface lies: a plane parallel to the table at `z_m`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct SamplePlane {
    /// Height of the sample's surface above the table, metres.
    #[serde(default)]
    pub z_m: f64,
}

/// One LED: a point source with inverse-square falloff and a `cos^m` beam around its axis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Led {
    /// The LED's position, world metres.
    pub position_m: [f64; 3],
    /// The point the LED is aimed at; the table centre unless measured otherwise.
    #[serde(default)]
    pub aim_m: [f64; 3],
    /// Linear signal (1.0 = white level) a white Lambertian surface facing the LED gives at
    /// 1 m on its axis, at the calibration exposure.
    pub power: f64,
    /// The LED's colour as seen by the camera, relative (white = 1, 1, 1).
    #[serde(default = "unit_rgb")]
    pub color: [f64; 3],
    /// Angle off the axis where the intensity halves.
    #[serde(default = "default_half_angle")]
    pub beam_half_angle_deg: f64,
}

fn unit_rgb() -> [f64; 3] {
    [1.0, 1.0, 1.0]
}

fn default_half_angle() -> f64 {
    60.0
}

impl Rig {
    /// The rig embedded in the binary (the seed's scanner).
    pub fn default_rig() -> Rig {
        Rig::from_toml_str(DEFAULT_RIG_TOML, Path::new("calibration/default/rig.toml"))
            .expect("the embedded default rig is valid")
    }

    /// Parses and validates a rig; `origin` names the file in errors.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Rig> {
        let rig: Rig = toml::from_str(text).map_err(|e| {
            let field = e
                .span()
                .map(|span| {
                    let line = text[..span.start].lines().count().max(1);
                    format!("line {line}")
                })
                .unwrap_or_else(|| "syntax".into());
            Error::config(origin, field, e.message().to_string())
        })?;
        rig.validate()
            .map_err(|(field, message)| Error::config(origin, field, message))?;
        Ok(rig)
    }

    /// Reads and validates the rig file at `path`.
    pub fn load(path: &Path) -> Result<Rig> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Rig::from_toml_str(&text, path)
    }

    /// The rig as `rig.toml` text.
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).expect("a rig always serialises")
    }

    /// Writes the rig as TOML to `path`, atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        crate::fsutil::write_atomic(path, self.to_toml_string().as_bytes())
    }

    /// Checks every number a solve depends on; the error is `(field, reason)`.
    pub fn validate(&self) -> std::result::Result<(), (String, String)> {
        let fail = |field: &str, message: String| Err((field.to_string(), message));
        let c = &self.camera;
        if c.width == 0 || c.height == 0 {
            return fail(
                "camera.width",
                "the sensor size must be at least 1x1".into(),
            );
        }
        for (name, v) in [("camera.fx", c.fx), ("camera.fy", c.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return fail(name, format!("focal length must be positive, got {v}"));
            }
        }
        for (name, v) in [("camera.cx", c.cx), ("camera.cy", c.cy)] {
            if !v.is_finite() {
                return fail(name, format!("principal point must be finite, got {v}"));
            }
        }
        if let Some(v) = c.distortion.iter().find(|v| !v.is_finite()) {
            return fail(
                "camera.distortion",
                format!("coefficients must be finite, got {v}"),
            );
        }
        if !finite3(&c.position_m) || !finite3(&c.rotation_deg) {
            return fail("camera.position_m", "camera pose must be finite".into());
        }
        if c.position_m[2] <= self.sample.z_m {
            return fail(
                "camera.position_m",
                format!(
                    "the camera must be above the sample (z = {} m, sample at {} m)",
                    c.position_m[2], self.sample.z_m
                ),
            );
        }
        self.validate_sensor()?;
        if !self.sample.z_m.is_finite() {
            return fail("sample.z_m", "must be finite".into());
        }
        if self.leds.len() < 3 {
            return fail(
                "leds",
                format!(
                    "photometric stereo needs at least 3 LEDs, the rig has {}",
                    self.leds.len()
                ),
            );
        }
        for (k, led) in self.leds.iter().enumerate() {
            led.validate(self.sample.z_m)
                .map_err(|(field, message)| (format!("leds[{k}].{field}"), message))?;
        }
        Ok(())
    }

    fn validate_sensor(&self) -> std::result::Result<(), (String, String)> {
        let s = &self.sensor;
        let fail = |field: &str, message: String| Err((field.to_string(), message));
        if !(8..=16).contains(&s.bits) {
            return fail("sensor.bits", format!("must be 8..16, got {}", s.bits));
        }
        let max_dn = ((1u32 << s.bits) - 1) as f64;
        if !(s.black_level.is_finite() && s.black_level >= 0.0) {
            return fail(
                "sensor.black_level",
                format!("must be >= 0, got {}", s.black_level),
            );
        }
        if !(s.white_level > s.black_level && s.white_level <= max_dn) {
            return fail(
                "sensor.white_level",
                format!(
                    "must lie above the black level ({}) and at most {max_dn}, got {}",
                    s.black_level, s.white_level
                ),
            );
        }
        if !(s.gain_e_per_dn.is_finite() && s.gain_e_per_dn > 0.0) {
            return fail(
                "sensor.gain_e_per_dn",
                format!("must be positive, got {}", s.gain_e_per_dn),
            );
        }
        if !(s.read_noise_e.is_finite() && s.read_noise_e >= 0.0) {
            return fail(
                "sensor.read_noise_e",
                format!("must be >= 0, got {}", s.read_noise_e),
            );
        }
        if s.channel_gain.iter().any(|g| !(g.is_finite() && *g > 0.0)) {
            return fail(
                "sensor.channel_gain",
                format!(
                    "each channel's gain must be positive, got {:?}",
                    s.channel_gain
                ),
            );
        }
        Ok(())
    }

    /// The linear signal of a white Lambertian surface, per LED and channel, at 1 m on axis:
    /// the "light intensity" the solve divides by (seed eq. 25), before falloff.
    pub fn led_rgb_power(&self, k: usize) -> [f64; 3] {
        let led = &self.leds[k];
        std::array::from_fn(|c| led.power * led.color[c] * self.sensor.channel_gain[c])
    }
}

impl Led {
    fn validate(&self, sample_z: f64) -> std::result::Result<(), (String, String)> {
        let fail = |field: &str, message: String| Err((field.to_string(), message));
        if !finite3(&self.position_m) {
            return fail("position_m", "must be finite".into());
        }
        if self.position_m[2] <= sample_z {
            return fail(
                "position_m",
                format!(
                    "the LED must be above the sample (z = {} m, sample at {} m)",
                    self.position_m[2], sample_z
                ),
            );
        }
        if !finite3(&self.aim_m) {
            return fail("aim_m", "must be finite".into());
        }
        let axis: f64 = (0..3)
            .map(|i| (self.aim_m[i] - self.position_m[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        if axis < 1e-6 {
            return fail("aim_m", "the aim point coincides with the LED".into());
        }
        if !(self.power.is_finite() && self.power > 0.0) {
            return fail("power", format!("must be positive, got {}", self.power));
        }
        if self.color.iter().any(|c| !(c.is_finite() && *c > 0.0)) {
            return fail(
                "color",
                format!("each channel must be positive, got {:?}", self.color),
            );
        }
        if !(self.beam_half_angle_deg > 0.0 && self.beam_half_angle_deg < 90.0) {
            return fail(
                "beam_half_angle_deg",
                format!("must lie in (0, 90), got {}", self.beam_half_angle_deg),
            );
        }
        Ok(())
    }
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_default_rig_is_the_seed_rig() {
        let rig = Rig::default_rig();
        assert_eq!(rig.leds.len(), 10);
        assert!((rig.camera.position_m[2] - 0.6).abs() < 1e-12);
        for led in &rig.leds {
            let r = led.position_m.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!((r - 0.6).abs() < 1e-3, "LED at {r} m from the centre");
        }
    }

    #[test]
    fn toml_round_trip_keeps_every_field() {
        let rig = Rig::default_rig();
        let text = rig.to_toml_string();
        let back = Rig::from_toml_str(&text, Path::new("x.toml")).unwrap();
        assert_eq!(rig, back);
    }

    #[test]
    fn validation_errors_name_the_field() {
        let mut rig = Rig::default_rig();
        rig.leds[3].position_m[2] = -0.1;
        let text = rig.to_toml_string();
        let err = Rig::from_toml_str(&text, Path::new("bad.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("bad.toml") && err.contains("leds[3].position_m"),
            "{err}"
        );

        let mut rig = Rig::default_rig();
        rig.sensor.white_level = 100.0;
        let err = Rig::from_toml_str(&rig.to_toml_string(), Path::new("bad.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("sensor.white_level"), "{err}");

        let mut rig = Rig::default_rig();
        rig.leds.truncate(2);
        let err = Rig::from_toml_str(&rig.to_toml_string(), Path::new("bad.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("leds") && err.contains("at least 3"), "{err}");
    }

    #[test]
    fn unknown_and_missing_keys_are_reported() {
        let text = DEFAULT_RIG_TOML.replace("fx = 7322.0", "fxx = 7322.0");
        let err = Rig::from_toml_str(&text, Path::new("typo.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("typo.toml") && err.contains("fxx"), "{err}");
    }
}
