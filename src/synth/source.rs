//! A synthetic scene in memory as a set source: the frames a dn16 capture of the scene would
//! decode to (the sensor model's digital numbers over its levels), without writing them, and
//! the scene's exact ground truth. It goes through the same solve path as a set on disk.

use std::path::{Path, PathBuf};

use super::{expose, Noise, Scene, SynthSpec};
use crate::error::{Error, Result};
use crate::maps::report::LightRecord;
use crate::maps::Report;
use crate::plane::{Frames, SensorWindow};
use crate::progress::Progress;
use crate::raw::{DecodeInfo, DevelopOptions, Levels, Resolution};
use crate::rig::Rig;
use crate::sets::{decoded_noise_model, pixel_size_mm, undistortion_note, SetSource, Truth};
use crate::solve::{LightSource, NoiseModel};
use crate::timing::StageClock;

/// What the report records as the location of a scene that is not on disk.
pub const IN_MEMORY: &str = "synthetic scene (in memory)";

/// A rendered scene, ready to be solved as a set.
pub struct SceneSource<'r> {
    rig: &'r Rig,
    scene: Scene<'r>,
    noise: Noise,
    exposure: f64,
    location: PathBuf,
}

impl<'r> SceneSource<'r> {
    /// Builds the scene `spec` describes under `rig` (the frames are rendered when loaded).
    pub fn build(rig: &'r Rig, spec: &SynthSpec, progress: &dyn Progress) -> Result<Self> {
        let scene = spec.scene(rig, progress)?;
        Ok(SceneSource {
            rig,
            scene,
            noise: spec.noise(),
            exposure: spec.exposure,
            location: PathBuf::from(IN_MEMORY),
        })
    }

    /// The scene (its ground truth included).
    pub fn scene(&self) -> &Scene<'r> {
        &self.scene
    }

    fn levels(&self) -> Levels {
        Levels::from_sensor(&self.rig.sensor)
    }
}

impl SetSource for SceneSource<'_> {
    fn location(&self) -> &Path {
        &self.location
    }

    fn rig_name(&self) -> String {
        self.rig.name.clone()
    }

    /// Renders each light, exposes it through the sensor model (noise stream `k + 1`, as a
    /// synthetic set on disk) and reads the digital numbers back over the sensor's levels.
    fn load(
        &self,
        develop: &DevelopOptions,
        progress: &dyn Progress,
        clock: &mut StageClock,
    ) -> Result<(Frames, DecodeInfo)> {
        if develop.resolution != Resolution::Full {
            return Err(Error::Unsupported(
                "half resolution is 2x2 CFA binning of RAW frames; a scene in memory has RGB \
                 frames, solve it at full resolution"
                    .into(),
            ));
        }
        let levels = self.levels();
        let leds = self.rig.leds.len();
        let lights = clock.time("render", || {
            progress.begin("render", leds as u64);
            let lights = (0..leds)
                .map(|k| {
                    let linear = self.scene.render_light(k, self.exposure);
                    let frame = expose(&linear, &self.rig.sensor, self.noise, k as u64 + 1)
                        .to_light_frame(&levels);
                    progress.advance(1);
                    frame
                })
                .collect();
            progress.end();
            lights
        });
        let frames = Frames {
            width: self.scene.width,
            height: self.scene.height,
            window: self.scene.window,
            lights,
        };
        let decode = DecodeInfo {
            encoding: "synthetic (in memory)".into(),
            resolution: Resolution::Full,
            method: "none: the sensor model's digital numbers over its levels".into(),
            cfa_pattern: None,
            levels,
            camera: None,
            camera_to_srgb: None,
            backing: None,
            dark_frame: "none: the scene is rendered without one".into(),
            dark_subtracted: false,
            noise_channel_scale: [1.0; 3],
            noise_shared_cfa_sample: None,
            undistortion: undistortion_note(self.rig),
        };
        Ok((frames, decode))
    }

    fn lights(&self) -> LightSource<'_> {
        LightSource::Rig(self.rig)
    }

    fn noise(&self, decode: &DecodeInfo) -> NoiseModel {
        decoded_noise_model(self.rig, decode)
    }

    fn exposure(&self) -> f64 {
        self.exposure
    }

    fn truth(&self, _width: usize, _height: usize, _decode: &DecodeInfo) -> Result<Option<Truth>> {
        Ok(Some(Truth::Surface {
            normal: self.scene.truth.normal.clone(),
            albedo: self.scene.truth.albedo.clone(),
        }))
    }

    fn describe(&self, report: &mut Report, window: &SensorWindow) {
        report.lights = (self.rig.leds.iter())
            .map(|led| LightRecord {
                position_m: Some(led.position_m),
                ..LightRecord::toward(led.position_m)
            })
            .collect();
        report.pixel_size_mm = Some(pixel_size_mm(self.rig, window));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval;
    use crate::progress::Silent;
    use crate::sets::{solve_source, SolveJob};
    use crate::solve::{solve, SolveInput};

    /// The one path's figures for a scene in memory are those of the scene's frames solved
    /// directly and compared with the scene's truth: the path hands the solver the source's
    /// frames, lights, noise and exposure, and compares with the truth uncropped.
    #[test]
    fn a_scene_in_memory_solves_through_the_one_path() {
        let rig = Rig::default_rig();
        let spec = SynthSpec {
            width: 96,
            height: 64,
            step: 16.0,
            ..SynthSpec::demo()
        };
        let source = SceneSource::build(&rig, &spec, &Silent).unwrap();
        let out = tempfile::tempdir().unwrap();
        let job = SolveJob::default();
        let report = solve_source(&source, &out.path().join("maps"), &job, &Silent).unwrap();
        assert!(out.path().join("maps/report.json").is_file());
        assert_eq!((report.width, report.height), (96, 64));
        let via_path = report.truth.expect("a scene has ground truth");

        let (frames, decode) = source
            .load(
                &DevelopOptions::default(),
                &Silent,
                &mut StageClock::start(),
            )
            .unwrap();
        let input = SolveInput {
            frames: &frames,
            lights: source.lights(),
            noise: source.noise(&decode),
            exposure: source.exposure(),
            mask: None,
        };
        let direct = solve(&input, &job.options, &Silent).unwrap();
        let truth = &source.scene().truth;
        let expected = eval::compare(&direct, &truth.normal, &truth.albedo);
        assert_eq!(via_path.pixels, expected.pixels);
        assert_eq!(
            via_path.normal_error_deg.mean,
            expected.normal_error_deg.mean
        );
        assert_eq!(
            via_path.albedo_rel_error.mean,
            expected.albedo_rel_error.mean
        );
        assert!(via_path.pixels > 0);
    }
}
