//! The simulated camera of the calibration wizard: it photographs whatever calibration target
//! the (simulated) operator has put in front of it — a chessboard held up or lying on the
//! table, the gray chart, the white sheet — lit by the LEDs that are on *when it fires*, which
//! it learns from a [`LitSource`] (the firmware emulator's pin log, the mock, or the
//! controller's `STATE`), as [`super::SimCamera`] does for the textile. No LED on: a black
//! frame; the wrong LED: a wrongly lit target, which the calibration then shows.
//!
//! The scene it renders is the rig *as built* (its LEDs away from the hand measurements, a
//! real lens), so the calibration has something to find.

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use super::camera::LitSource;
use crate::capture::camera::{unix_now_us, Camera, Shot};
use crate::capture::interrupt::Interrupt;
use crate::capture::manifest::{CameraSettings, ImageInfo};
use crate::error::{Error, Result};
use crate::plane::{RgbPlanes, SensorWindow};
use crate::raw::{encode_png16, DnImage, Levels};
use crate::rig::{ChartDescription, Rig};
use crate::synth::targets::{self, BoardPose, Chessboard, RayGrid, ViewRender};
use crate::synth::{expose, Noise};

/// What lies (or is held) in front of the camera.
#[derive(Clone, Debug, Default)]
pub enum Target {
    /// Nothing placed yet: the bare table.
    #[default]
    Table,
    /// The chessboard at a pose (held up, or lying flat on the table).
    Chessboard(BoardPose),
    /// The gray chart's patches filling the world rectangle `[x0, x1, y0, y1]` on the table.
    GrayChart {
        /// The chart: its patch grid and the patches' reflectances.
        chart: ChartDescription,
        /// Where its patches lie on the table, `[x0, x1, y0, y1]` in world metres.
        world: [f64; 4],
    },
    /// The white sheet on the table (reflectance, relative fibre texture, its seed).
    WhiteSheet {
        /// The sheet's mean diffuse reflectance, in (0, 1].
        reflectance: f64,
        /// Relative amplitude of the paper's fibre texture around the mean (0: perfectly uniform).
        texture: f64,
        /// Seed of the fibre pattern.
        seed: u64,
    },
}

/// The target and how the simulated camera is set for it.
#[derive(Clone, Debug)]
pub struct Placement {
    /// What is in front of the camera.
    pub target: Target,
    /// Frames are the whole sensor taken every `step` pixels (the simulation's stand-in for a
    /// full-resolution RAW, which the wizard would bin down to the same size).
    pub step: f64,
    /// Exposure: 1.0 puts a white Lambertian surface 1 m from an LED of power 1, on its axis,
    /// at the white level.
    pub exposure: f64,
    /// Which photograph of this placement: separates the sensor noise of repeated exposures
    /// while keeping a re-shot frame identical to the first.
    pub take: u64,
}

impl Default for Placement {
    fn default() -> Self {
        Placement {
            target: Target::Table,
            step: 8.0,
            exposure: 1.0,
            take: 0,
        }
    }
}

/// The operator's hands: what the wizard has placed in front of the simulated camera. Shared
/// between the wizard's source and the camera.
#[derive(Clone, Debug, Default)]
pub struct Stage(Arc<Mutex<Placement>>);

impl Stage {
    /// Puts `placement` in front of the camera, replacing what was there.
    pub fn place(&self, placement: Placement) {
        *self.0.lock().unwrap_or_else(|p| p.into_inner()) = placement;
    }

    /// What is in front of the camera now.
    pub fn current(&self) -> Placement {
        self.0.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }
}

/// The simulated calibration camera: renders the [`Stage`]'s current target through the rig as
/// built, lit by the LEDs its [`LitSource`] reports on when it fires, and stores 16-bit PNG frames.
pub struct TargetCamera {
    /// The rig as built.
    truth: Rig,
    chess: Chessboard,
    stage: Stage,
    source: Box<dyn LitSource>,
    seed: u64,
    /// Camera rays of the last step rendered (computing them is the slow part).
    grid: Option<(f64, RayGrid)>,
}

impl TargetCamera {
    /// A camera rendering through `truth` (the rig as built), photographing `chess` when the
    /// chessboard is placed, watching `stage` for the target, asking `source` which LEDs are lit,
    /// with sensor noise seeded by `seed`.
    pub fn new(
        truth: Rig,
        chess: Chessboard,
        stage: Stage,
        source: Box<dyn LitSource>,
        seed: u64,
    ) -> Self {
        TargetCamera {
            truth,
            chess,
            stage,
            source,
            seed,
            grid: None,
        }
    }

    fn frame_geometry(&self, step: f64) -> (usize, usize, SensorWindow) {
        let (w, h) = targets::binned_size(&self.truth, step);
        let window = SensorWindow::centred(
            self.truth.camera.width as usize,
            self.truth.camera.height as usize,
            w,
            h,
            step,
        );
        (w, h, window)
    }

    /// The linear image of `placement` with `lit` on (1.0 = white level).
    pub fn render(&mut self, placement: &Placement, lit: &[usize]) -> Result<RgbPlanes> {
        if let Some(&k) = lit.iter().find(|&&k| k >= self.truth.leds.len()) {
            return Err(Error::device(
                self.name(),
                format!(
                    "LED {k} is on, but the rig has only {} LEDs",
                    self.truth.leds.len()
                ),
            ));
        }
        let (w, h, window) = self.frame_geometry(placement.step);
        let flat = |reflectance: &(dyn Fn(f64, f64) -> [f64; 3] + Sync)| {
            let mut sum = RgbPlanes::new(w, h);
            for &k in lit {
                let one = targets::render_flat_target(
                    &self.truth,
                    window,
                    w,
                    h,
                    k,
                    placement.exposure,
                    reflectance,
                );
                for (s, a) in [
                    (&mut sum.r, &one.r),
                    (&mut sum.g, &one.g),
                    (&mut sum.b, &one.b),
                ] {
                    s.data.iter_mut().zip(&a.data).for_each(|(s, a)| *s += a);
                }
            }
            sum
        };
        Ok(match &placement.target {
            Target::Table => flat(&|_, _| [targets::TABLE_REFLECTANCE; 3]),
            Target::GrayChart { chart, world } => flat(&targets::gray_chart(chart, *world)),
            Target::WhiteSheet {
                reflectance,
                texture,
                seed,
            } => flat(&targets::white_sheet(*reflectance, *texture, *seed)),
            Target::Chessboard(pose) => {
                if self.grid.as_ref().map(|g| g.0) != Some(placement.step) {
                    let grid = RayGrid::new(
                        &self.truth.camera,
                        window,
                        w,
                        h,
                        ViewRender::default().supersample,
                    );
                    self.grid = Some((placement.step, grid));
                }
                let grid = &self.grid.as_ref().expect("just made").1;
                targets::render_chessboard_lit(
                    &self.truth,
                    grid,
                    &self.chess,
                    pose,
                    lit,
                    placement.exposure,
                    ViewRender::default().blur_px,
                )
            }
        })
    }

    /// The frame the sensor records for `placement` with `lit` on.
    pub fn photograph(&mut self, placement: &Placement, lit: &[usize]) -> Result<DnImage> {
        let linear = self.render(placement, lit)?;
        // The noise depends on the take and on what was lit, never on the wall clock.
        let lit_code = lit.iter().fold(0u64, |m, &k| m | 1 << k.min(62));
        let stream = placement.take.wrapping_mul(0x9e37_79b9) ^ lit_code.wrapping_add(1) << 40;
        Ok(expose(
            &linear,
            &self.truth.sensor,
            Noise::Seeded(self.seed),
            stream,
        ))
    }
}

impl Camera for TargetCamera {
    fn name(&self) -> String {
        format!(
            "simulated calibration camera (lit LEDs from {})",
            self.source.name()
        )
    }

    fn settings(&mut self) -> Result<CameraSettings> {
        Ok(CameraSettings {
            model: "psscan simulated camera".into(),
            ..Default::default()
        })
    }

    fn image_info(&self, rig: &Rig) -> ImageInfo {
        let placement = self.stage.current();
        let (width, height, window) = self.frame_geometry(placement.step);
        ImageInfo {
            width,
            height,
            window,
            levels: Levels::from_sensor(&rig.sensor),
            exposure: placement.exposure,
            encoding: "dn16".into(),
        }
    }

    fn max_shot_time(&self) -> Duration {
        // A supersampled chessboard view takes a few seconds on two busy cores.
        Duration::from_secs(30)
    }

    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot> {
        if interrupt.is_set() {
            return Err(Error::Interrupted(format!(
                "{}: before firing",
                self.name()
            )));
        }
        let placement = self.stage.current();
        let lit = self.source.lit()?;
        let fired_unix_us = unix_now_us();
        let image = self.photograph(&placement, &lit)?;
        let bytes = encode_png16(&image)?;
        std::fs::write(dest, bytes).map_err(|e| Error::io(dest, e))?;
        Ok(Shot {
            extension: "png".into(),
            lit: Some(lit),
            fired_unix_us,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::{LightController, MockLights};
    use crate::rig::Board;

    #[test]
    fn the_target_is_lit_by_the_leds_that_are_on() {
        let rig = Rig::default_rig();
        let chess = Chessboard {
            board: Board::parse("9x6", 15.0).unwrap(),
            border_squares: 1.0,
        };
        let mut mock = MockLights::new(10);
        let stage = Stage::default();
        let mut camera =
            TargetCamera::new(rig.clone(), chess, stage.clone(), Box::new(mock.probe()), 3);
        let sheet = Placement {
            target: Target::WhiteSheet {
                reflectance: 0.9,
                texture: 0.0,
                seed: 1,
            },
            step: 64.0,
            ..Placement::default()
        };
        stage.place(sheet.clone());
        let dir = tempfile::tempdir().unwrap();
        let dest = dir.path().join("f.png");
        let stop = Interrupt::new();
        let mean_g = |path: &Path| {
            let dn = crate::raw::read_dn_image(path).unwrap();
            let f = dn.to_light_frame(&Levels::from_sensor(&rig.sensor));
            f.rgb.g.data.iter().map(|&v| v as f64).sum::<f64>() / f.rgb.g.data.len() as f64
        };
        assert_eq!(camera.capture(&dest, &stop).unwrap().lit, Some(vec![]));
        assert!(mean_g(&dest).abs() < 0.002, "dark: {}", mean_g(&dest));
        mock.on(7).unwrap();
        camera.capture(&dest, &stop).unwrap();
        let seven = mean_g(&dest);
        // The frame is the renderer's sheet under LED 7 (the sensor adds only noise).
        let expected = camera.render(&sheet, &[7]).unwrap();
        let want =
            expected.g.data.iter().map(|&v| v as f64).sum::<f64>() / expected.g.data.len() as f64;
        assert!(
            want > 0.05 && (seven / want - 1.0).abs() < 0.01,
            "{seven} {want}"
        );
        // Another LED lights the sheet differently (LED 0 is low on one side).
        mock.on(0).unwrap();
        camera.capture(&dest, &stop).unwrap();
        assert!((mean_g(&dest) / seven - 1.0).abs() > 0.05);
    }
}
