//! The simulated camera: when it fires it asks a [`LitSource`] which LEDs are on *right
//! now* (the emulator's pin log, the mock's state, or the controller's own `STATE`), renders
//! the synthetic textile under exactly those LEDs (none: a dark frame; two: their sum), and
//! exposes it through the rig's sensor model. A wrong LED therefore gives a wrong image, which
//! the solve against ground truth shows.
//!
//! The noise of a frame depends only on the seed and on what was lit, so an emulated capture
//! is bit-identical to `psscan synth` of the same scene, and a re-shot frame equals the first.

use std::path::Path;
use std::time::Duration;

use super::emulator::PinLog;
use crate::capture::camera::{unix_now_us, Camera, Shot};
use crate::capture::interrupt::Interrupt;
use crate::capture::lights::{MockProbe, SharedLights};
use crate::capture::manifest::{CameraSettings, ImageInfo};
use crate::error::{Error, Result};
use crate::plane::RgbPlanes;
use crate::progress::Silent;
use crate::raw::{encode_png16, DnImage, Levels};
use crate::rig::Rig;
use crate::synth::{expose, Scene, SynthSpec};

/// Where the simulated camera learns which LEDs are on.
pub trait LitSource: Send {
    /// The LEDs on at this moment, by controller index (empty: all off).
    fn lit(&mut self) -> Result<Vec<usize>>;
    /// Names the source for the camera's name and messages, e.g. `pin log <path>`.
    fn name(&self) -> String;
}

impl LitSource for PinLog {
    fn lit(&mut self) -> Result<Vec<usize>> {
        PinLog::lit(self)
    }

    fn name(&self) -> String {
        format!("pin log {}", self.path().display())
    }
}

impl LitSource for MockProbe {
    fn lit(&mut self) -> Result<Vec<usize>> {
        Ok(MockProbe::lit(self))
    }

    fn name(&self) -> String {
        "mock controller state".into()
    }
}

/// The controller's own answer to `STATE` (for a real board with no pin log).
pub struct ControllerState(pub SharedLights);

impl LitSource for ControllerState {
    fn lit(&mut self) -> Result<Vec<usize>> {
        Ok(self.0.lock().state()?.on.into_iter().collect())
    }

    fn name(&self) -> String {
        "the controller's STATE answer".into()
    }
}

/// How the simulated camera stores a frame. One format today; the seam where a DNG writer
/// joins.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimOutput {
    /// 16-bit RGB PNG of raw digital numbers (`dn16`).
    Dn16Png,
}

impl SimOutput {
    /// The manifest's `image.encoding` for frames in this format.
    pub fn encoding(&self) -> &'static str {
        match self {
            SimOutput::Dn16Png => "dn16",
        }
    }

    /// The file extension of frames in this format, without the dot.
    pub fn extension(&self) -> &'static str {
        match self {
            SimOutput::Dn16Png => "png",
        }
    }

    fn encode(&self, image: &DnImage) -> Result<Vec<u8>> {
        match self {
            SimOutput::Dn16Png => encode_png16(image),
        }
    }
}

/// The simulated textile camera: renders the synthetic scene under whichever LEDs its [`LitSource`]
/// reports on when it fires, exposes it through the rig's sensor model, and stores the frame.
pub struct SimCamera<'a> {
    rig: &'a Rig,
    spec: SynthSpec,
    scene: Scene<'a>,
    source: Box<dyn LitSource>,
    output: SimOutput,
    /// Time between the trigger and the shutter (a slow camera, for fault tests).
    delay_before_fire: Duration,
}

impl<'a> SimCamera<'a> {
    /// Builds the scene `spec` describes under `rig` (the expensive part, done once).
    pub fn new(rig: &'a Rig, spec: &SynthSpec, source: Box<dyn LitSource>) -> Result<Self> {
        let scene = spec.scene(rig, &Silent)?;
        Ok(SimCamera {
            rig,
            spec: spec.clone(),
            scene,
            source,
            output: SimOutput::Dn16Png,
            delay_before_fire: Duration::ZERO,
        })
    }

    /// The camera waiting `delay` between the trigger and the shutter (a slow camera, for fault
    /// tests).
    pub fn with_delay_before_fire(mut self, delay: Duration) -> Self {
        self.delay_before_fire = delay;
        self
    }

    /// The synthetic scene the camera photographs, with its ground truth.
    pub fn scene(&self) -> &Scene<'a> {
        &self.scene
    }

    /// The frame the sensor records with `lit` on.
    pub fn render(&self, lit: &[usize]) -> Result<DnImage> {
        let mut planes = RgbPlanes::new(self.spec.width, self.spec.height);
        for &k in lit {
            if k >= self.rig.leds.len() {
                return Err(Error::device(
                    self.name(),
                    format!(
                        "LED {k} is on, but the rig has only {} LEDs",
                        self.rig.leds.len()
                    ),
                ));
            }
            let light = self.scene.render_light(k, self.spec.exposure);
            for (sum, add) in [
                (&mut planes.r, &light.r),
                (&mut planes.g, &light.g),
                (&mut planes.b, &light.b),
            ] {
                sum.data
                    .iter_mut()
                    .zip(&add.data)
                    .for_each(|(s, a)| *s += a);
            }
        }
        Ok(expose(
            &planes,
            &self.rig.sensor,
            self.spec.noise(),
            noise_stream(lit),
        ))
    }
}

/// The sensor-noise stream for a frame with `lit` on: the same numbering `psscan synth`
/// uses (0 dark, k + 1 for LED k), and distinct streams for mixtures.
fn noise_stream(lit: &[usize]) -> u64 {
    match lit {
        [] => 0,
        [k] => *k as u64 + 1,
        many => 1 << 32 | many.iter().fold(0u64, |m, &k| m | 1 << k.min(31)),
    }
}

impl Camera for SimCamera<'_> {
    fn name(&self) -> String {
        format!("simulated camera (lit LEDs from {})", self.source.name())
    }

    fn settings(&mut self) -> Result<CameraSettings> {
        Ok(CameraSettings {
            model: "psscan simulated camera".into(),
            ..Default::default()
        })
    }

    fn image_info(&self, rig: &Rig) -> ImageInfo {
        ImageInfo {
            width: self.spec.width,
            height: self.spec.height,
            window: self.spec.window(rig),
            levels: Levels::from_sensor(&rig.sensor),
            exposure: self.spec.exposure,
            encoding: self.output.encoding().into(),
        }
    }

    fn max_shot_time(&self) -> Duration {
        // Rendering a full-sensor frame on two cores takes a few seconds.
        Duration::from_secs(30)
    }

    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot> {
        if !interrupt.sleep(self.delay_before_fire) {
            return Err(Error::Interrupted(format!(
                "{}: before firing",
                self.name()
            )));
        }
        let lit = self.source.lit()?;
        let fired_unix_us = unix_now_us();
        let image = self.render(&lit)?;
        let bytes = self.output.encode(&image)?;
        std::fs::write(dest, bytes).map_err(|e| Error::io(dest, e))?;
        Ok(Shot {
            extension: self.output.extension().into(),
            lit: Some(lit),
            fired_unix_us,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::{LightController, MockLights};

    fn small_spec() -> SynthSpec {
        let mut spec = SynthSpec::demo();
        spec.width = 32;
        spec.height = 24;
        spec.step = 128.0;
        spec
    }

    #[test]
    fn the_image_follows_the_lit_leds() {
        let rig = Rig::default_rig();
        let spec = small_spec();
        let mut mock = MockLights::new(10);
        let mut camera = SimCamera::new(&rig, &spec, Box::new(mock.probe())).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let dest = dir.path().join("f.png");
        let stop = Interrupt::new();
        let mean = |path: &Path| {
            let dn = crate::raw::read_dn_image(path).unwrap();
            dn.data.iter().map(|&v| v as f64).sum::<f64>() / dn.data.len() as f64
        };

        let shot = camera.capture(&dest, &stop).unwrap();
        assert_eq!(shot.lit, Some(vec![]));
        let dark = mean(&dest);
        assert!((dark - rig.sensor.black_level).abs() < 5.0, "{dark}");

        mock.on(2).unwrap();
        camera.capture(&dest, &stop).unwrap();
        let two = mean(&dest);
        assert!(two > dark + 100.0);
        // Exactly the frame `psscan synth` renders for LED 2.
        let expected = crate::synth::expose(
            &camera.scene().render_light(2, spec.exposure),
            &rig.sensor,
            spec.noise(),
            3,
        );
        assert_eq!(crate::raw::read_dn_image(&dest).unwrap(), expected);

        mock.on(5).unwrap();
        camera.capture(&dest, &stop).unwrap();
        assert_ne!(
            crate::raw::read_dn_image(&dest).unwrap(),
            expected,
            "another LED, another image"
        );

        // Two LEDs at once (impossible with the firmware): their sum.
        let both = camera.render(&[2, 5]).unwrap();
        let five = camera.render(&[5]).unwrap();
        let m = |d: &DnImage| d.data.iter().map(|&v| v as f64).sum::<f64>() / d.data.len() as f64;
        let black = rig.sensor.black_level;
        let sum = (m(&expected) - black) + (m(&five) - black);
        assert!(((m(&both) - black) / sum - 1.0).abs() < 0.01);
    }
}
