//! The benchmark's standard scenes: the synthetic textile under the default rig, with or
//! without cast shadows and sheen, rendered with sensor noise and decoded to linear planes
//! with saturation masks as a camera's RAW would be.

use serde::Serialize;

use crate::error::Result;
use crate::plane::{Frames, SensorWindow};
use crate::progress::Progress;
use crate::raw::Levels;
use crate::rig::Rig;
use crate::solve::NoiseModel;
use crate::synth::{expose, Noise, Scene, SceneOptions, Sheen, Textile};

/// The standard scenes.
#[derive(Clone, Copy, Debug, Serialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum SceneKind {
    /// Lambertian shading only: the reflectance every variant's model assumes.
    Lambertian,
    /// Cast shadows from the weave's height field, with 15 % of the direct light filling them.
    Shadows,
    /// Lambertian shading plus the cloth sheen lobe.
    Sheen,
    /// Cast shadows and sheen together: the hardest scene.
    ShadowsSheen,
}

impl SceneKind {
    /// Every scene, in the order the benchmark runs them.
    pub const ALL: [SceneKind; 4] = [
        SceneKind::Lambertian,
        SceneKind::Shadows,
        SceneKind::Sheen,
        SceneKind::ShadowsSheen,
    ];

    /// The scene's name in the benchmark's rows and tables (`lambertian`, `shadows`, `sheen`,
    /// `shadows+sheen`).
    pub fn name(self) -> &'static str {
        match self {
            SceneKind::Lambertian => "lambertian",
            SceneKind::Shadows => "shadows",
            SceneKind::Sheen => "sheen",
            SceneKind::ShadowsSheen => "shadows+sheen",
        }
    }

    fn options(self) -> SceneOptions {
        let shadows = matches!(self, SceneKind::Shadows | SceneKind::ShadowsSheen);
        SceneOptions {
            shadows,
            shadow_fill: if shadows { 0.15 } else { 0.0 },
            sheen: matches!(self, SceneKind::Sheen | SceneKind::ShadowsSheen).then(Sheen::default),
        }
    }
}

/// Renders `kind` at `mp` megapixels over the whole sensor field with sensor noise, as decoded
/// frames (with saturation masks), and its ground truth.
pub fn render_scene<'r>(
    rig: &'r Rig,
    kind: SceneKind,
    mp: f64,
    progress: &dyn Progress,
) -> Result<(Scene<'r>, Frames)> {
    let (sw, sh) = (rig.camera.width as usize, rig.camera.height as usize);
    let scale = (mp * 1e6 / (sw * sh) as f64).sqrt().min(1.0);
    let (w, h) = (
        ((sw as f64 * scale).round() as usize).max(1),
        ((sh as f64 * scale).round() as usize).max(1),
    );
    render_window(rig, kind, (w, h), sw as f64 / w as f64, progress)
}

/// Renders `kind` on a `w x h` window centred on the sensor, every `step` sensor pixels, with
/// sensor noise, as decoded frames (with saturation masks), and its ground truth.
pub fn render_window<'r>(
    rig: &'r Rig,
    kind: SceneKind,
    (w, h): (usize, usize),
    step: f64,
    progress: &dyn Progress,
) -> Result<(Scene<'r>, Frames)> {
    let (sw, sh) = (rig.camera.width as usize, rig.camera.height as usize);
    let window = SensorWindow::centred(sw, sh, w, h, step);
    let scene = Scene::build(
        rig,
        Textile::default(),
        w,
        h,
        window,
        kind.options(),
        progress,
    )?;
    let levels = Levels::from_sensor(&rig.sensor);
    progress.begin("render", rig.leds.len() as u64);
    let lights = (0..rig.leds.len())
        .map(|k| {
            let linear = scene.render_light(k, 1.0);
            let frame = expose(&linear, &rig.sensor, Noise::Seeded(7), k as u64 + 1)
                .to_light_frame(&levels);
            progress.advance(1);
            frame
        })
        .collect();
    progress.end();
    let frames = Frames {
        width: w,
        height: h,
        window,
        lights,
    };
    Ok((scene, frames))
}

/// The noise model the benchmark's frames were exposed with.
pub fn bench_noise(rig: &Rig) -> NoiseModel {
    crate::sets::noise_model(rig, &Levels::from_sensor(&rig.sensor))
}
