//! The synthetic rig and scene: a woven textile rendered by the rig's camera under each LED,
//! through a sensor model, with exact ground truth. Every stage downstream is tested on these
//! inputs. Production paths use it only through `psscan demo` and `psscan synth`.

mod brdf;
pub mod demo;
mod render;
mod sensor;
pub mod set;
mod source;
pub mod targets;
pub mod textile;

use serde::{Deserialize, Serialize};

pub use brdf::Sheen;
pub use demo::{run_demo, DemoPaths, DemoSummary};
pub use render::{GroundTruth, Scene, SceneOptions};
pub use sensor::{expose, expose_mosaic, Noise};
pub use set::{
    write_synthetic_set, write_synthetic_set_from, write_synthetic_set_with, SynthOutcome,
};
pub use source::SceneSource;
pub use textile::{Textile, Weave};

use crate::plane::SensorWindow;
use crate::rig::Rig;

/// What to render: image size and where it sits on the rig's sensor, the textile, the
/// effects, the noise, and the exposure.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SynthSpec {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Sensor pixels per image pixel (1: full resolution; 8: every 8th pixel, covering
    /// 8x the field at 1/64 of the cost).
    pub step: f64,
    /// The textile rendered.
    pub textile: Textile,
    /// Which effects beyond Lambertian shading are rendered (cast shadows, sheen).
    pub scene: SceneOptions,
    /// `None`: rounding and clipping only.
    pub noise_seed: Option<u64>,
    /// Exposure relative to the rig's calibration exposure.
    pub exposure: f64,
    /// How the frames are stored.
    #[serde(default)]
    pub encoding: FrameEncoding,
}

/// How a synthetic set stores its frames.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FrameEncoding {
    /// 16-bit RGB PNGs of raw digital numbers: R, G and B at every pixel (an ideal camera).
    #[default]
    Dn16,
    /// DNG files of a Bayer (RGGB) mosaic, 14-bit lossless: each sensor pixel records only its
    /// own colour, and solving takes the real RAW decode path.
    Dng,
}

impl SynthSpec {
    /// The demo's default: a 2048 x 1536 (3.1 MP) crop of the centre of the sensor at full
    /// resolution, Lambertian twill, sensor noise on.
    pub fn demo() -> Self {
        SynthSpec {
            width: 2048,
            height: 1536,
            step: 1.0,
            textile: Textile::default(),
            scene: SceneOptions::default(),
            noise_seed: Some(1),
            exposure: 1.0,
            encoding: FrameEncoding::Dn16,
        }
    }

    /// The image's window on the rig's sensor, centred.
    pub fn window(&self, rig: &Rig) -> SensorWindow {
        SensorWindow::centred(
            rig.camera.width as usize,
            rig.camera.height as usize,
            self.width,
            self.height,
            self.step,
        )
    }

    /// The scene this spec describes under `rig`: the textile sampled at every pixel of its
    /// window (the expensive part of rendering, done once per set).
    pub fn scene<'r>(
        &self,
        rig: &'r Rig,
        progress: &dyn crate::progress::Progress,
    ) -> crate::error::Result<Scene<'r>> {
        Scene::build(
            rig,
            self.textile.clone(),
            self.width,
            self.height,
            self.window(rig),
            self.scene.clone(),
            progress,
        )
    }

    /// The sensor noise the spec asks for: seeded photon and read noise, or rounding and clipping
    /// only when `noise_seed` is `None`.
    pub fn noise(&self) -> Noise {
        match self.noise_seed {
            Some(seed) => Noise::Seeded(seed),
            None => Noise::Off,
        }
    }
}
