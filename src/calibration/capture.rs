//! Where the wizard's photographs come from when they are taken through the capture module
//! ([`Captured`]): the LED controller (a board on a serial port, or the real firmware in its
//! emulator) switches the LEDs, and a camera fires. Chessboard views are single shots; the gray
//! chart and the white sheet are capture sets shot by the sequencer into the bundle folder
//! (`captures/`), so an interrupted one is completed, not restarted, when the wizard runs
//! again. Whoever puts the targets in front of the camera is an [`Operator`]: a person at the
//! wizard's prompts (none given), or the simulated one in the `sim` module, which also has
//! the simulated source that renders the targets directly.

use std::path::{Path, PathBuf};
use std::time::Duration;

use nalgebra::Vector3;

use super::wizard::TargetSource;
use crate::capture::camera::Camera;
use crate::capture::exposure::prepare_controller;
use crate::capture::lights::SharedLights;
use crate::capture::{run_capture, shoot_one, CaptureOptions, CaptureSet, Interrupt};
use crate::error::{Error, Result};
use crate::plane::{Frames, GrayImage, LightFrame, Mask, Plane, RgbPlanes, SensorWindow};
use crate::progress::Progress;
use crate::raw::{
    decode_dn_image, decode_frame, decode_raw, develop_frames, DevelopOptions, Encoding, Levels,
    Mosaic, Resolution,
};
use crate::rig::{ChartDescription, Rig};
use crate::solve::LUMINANCE_WEIGHTS;

/// Chessboard views are the sensor binned 4x.
pub const VIEW_STEP: f64 = 4.0;
/// White-sheet frames: every 8th sensor pixel over the whole field.
pub const SHEET_STEP: f64 = 8.0;
/// The gray chart is read at the views' resolution (its patches need a few hundred samples).
pub const CHART_STEP: f64 = VIEW_STEP;
/// The chessboard views' window: the whole sensor binned by [`VIEW_STEP`].
pub fn view_window(rig: &Rig) -> SensorWindow {
    binned_window(rig, VIEW_STEP)
}

/// The whole sensor binned by `step`.
pub fn binned_window(rig: &Rig, step: f64) -> SensorWindow {
    let (w, h) = rig.camera.binned_size(step);
    SensorWindow::centred(
        rig.camera.width as usize,
        rig.camera.height as usize,
        w,
        h,
        step,
    )
}

/// The LED that lights the chessboard views and the board on the table: the one nearest the
/// camera's axis, seen from the table centre. The firmware lights one LED at a time, so one
/// must be chosen; light from beside the camera falls on a board facing the camera almost
/// head-on, so the whole board is lit nearly evenly (an LED low on one side would leave the far
/// squares several times darker, and the detector's thresholds struggle), and the operator's
/// hands and the board cast their shadows away from the camera's view.
pub fn view_led(rig: &Rig) -> usize {
    let centre = Vector3::new(0.0, 0.0, rig.sample.z_m);
    let axis = (rig.camera.centre() - centre).normalize();
    (0..rig.leds.len())
        .max_by(|&a, &b| {
            let cos = |k: usize| (rig.leds[k].position() - centre).normalize().dot(&axis);
            // Ties (a symmetric ring) go to the lowest index.
            cos(a).total_cmp(&cos(b)).then(b.cmp(&a))
        })
        .expect("a rig has LEDs")
}

/// What the wizard needs in front of the camera for its next photographs.
#[derive(Clone, Copy, Debug)]
pub enum Placing<'a> {
    /// The chessboard held up for chessboard view `attempt`.
    ChessboardView(usize),
    /// The chessboard lying flat on the table.
    ChessboardOnTable,
    /// The gray chart on the table, filling the world rectangle `[x0, x1, y0, y1]`.
    GrayChart {
        /// The chart's layout.
        chart: &'a ChartDescription,
        /// Where it lies on the table, in metres.
        world: [f64; 4],
    },
    /// The white sheet on the table, for exposure `exposure` of the capture `purpose`.
    WhiteSheet {
        /// Which white-sheet capture (its folder name's stem).
        purpose: &'a str,
        /// Which of the capture's exposures.
        exposure: usize,
    },
}

/// Who puts the targets in front of the camera when no person does so at the wizard's
/// prompts: the simulated operator, who places them where the simulated camera looks.
pub trait Operator {
    /// Puts `what` in front of the camera, to be photographed with frames binned by `step`.
    fn place(&self, what: Placing, step: f64);
}

/// Photographs through the LED controller and a camera.
pub struct Captured {
    dir: PathBuf,
    hand: Rig,
    lights: SharedLights,
    camera: Box<dyn Camera>,
    operator: Option<Box<dyn Operator>>,
    view_led: usize,
    settle: Duration,
    interrupt: Interrupt,
}

impl Captured {
    /// Opens the source: identifies the controller (it must drive every LED of `hand`) and
    /// switches all LEDs off. Shots and capture sets go under `dir` (the bundle folder).
    /// `operator` places the targets; none: a person does, at the wizard's prompts.
    pub fn open(
        dir: &Path,
        hand: &Rig,
        lights: SharedLights,
        camera: Box<dyn Camera>,
        operator: Option<Box<dyn Operator>>,
        settle: Duration,
        interrupt: Interrupt,
    ) -> Result<Captured> {
        prepare_controller(&lights, hand.leds.len(), None)?;
        crate::fsutil::create_dir_all(&dir.join("shots"))?;
        Ok(Captured {
            dir: dir.to_path_buf(),
            hand: hand.clone(),
            view_led: view_led(hand),
            lights,
            camera,
            operator,
            settle,
            interrupt,
        })
    }

    /// The LED that lights the chessboard photographs.
    pub fn view_led(&self) -> usize {
        self.view_led
    }

    /// The operator puts `what` in front of the camera (a person has done so at the wizard's
    /// prompt).
    fn place(&self, what: Placing, step: f64) {
        if let Some(operator) = &self.operator {
            operator.place(what, step);
        }
    }

    /// One photograph under the view LED, decoded to linear planes, and where it sits on the
    /// sensor. The file is scratch: the wizard keeps the 8-bit view it makes of it.
    fn shoot(&mut self, name: &str) -> Result<(LightFrame, SensorWindow)> {
        let dest = self.dir.join("shots").join(format!("{name}.shot"));
        shoot_one(
            &self.lights,
            self.camera.as_mut(),
            Some(self.view_led),
            &dest,
            self.settle,
            &self.interrupt,
        )?;
        let info = self.camera.image_info(&self.hand);
        let decoded = (|| {
            let encoding = Encoding::parse(&info.encoding).ok_or_else(|| {
                Error::Unsupported(format!("frame encoding \"{}\"", info.encoding))
            })?;
            let resolution = match encoding {
                Encoding::Raw => Resolution::Half,
                Encoding::Dn16 => Resolution::Full,
            };
            let bytes = std::fs::read(&dest).map_err(|e| Error::io(&dest, e))?;
            let frame = decode_frame(bytes, &dest, encoding, &info.levels)?;
            let mut frames = develop_frames(vec![frame], None, None, resolution)?;
            Ok((frames.remove(0), resolution.window(info.window)))
        })();
        let _ = std::fs::remove_file(&dest);
        decoded
    }

    /// A chessboard photograph as the 8-bit view the detector reads.
    fn view(&mut self, name: &str) -> Result<GrayImage> {
        let (frame, window) = self.shoot(name)?;
        let want = view_window(&self.hand);
        let (luma, window) = bin(&luminance(&frame.rgb), window, want.step)?;
        let (w, h) = self.hand.camera.binned_size(VIEW_STEP);
        if (luma.width, luma.height) != (w, h) || (window.x0 - want.x0).abs() > 1e-6 {
            return Err(Error::Invalid(format!(
                "the camera's photographs bin to {}x{} at sensor offset ({:.1}, {:.1}), rig \
                 \"{}\" expects {w}x{h} at ({:.1}, {:.1}): the rig's camera width and height \
                 must be the camera's RAW size",
                luma.width, luma.height, window.x0, window.y0, self.hand.name, want.x0, want.y0
            )));
        }
        Ok(to_gray(&luma))
    }

    /// A capture set of the target now on the table, in `captures/<name>` (completed when an
    /// earlier session left it unfinished).
    fn capture_set(&mut self, name: &str, progress: &dyn Progress) -> Result<CaptureSet> {
        let dir = self.dir.join("captures").join(name);
        let options = CaptureOptions {
            settle: self.settle,
            resume: true,
            ..CaptureOptions::default()
        };
        run_capture(
            &dir,
            &self.hand,
            &self.lights,
            self.camera.as_mut(),
            &options,
            &self.interrupt,
            progress,
        )?;
        CaptureSet::open(&dir, None)
    }
}

impl TargetSource for Captured {
    fn chessboard_view(&mut self, attempt: usize) -> Result<GrayImage> {
        self.place(Placing::ChessboardView(attempt), VIEW_STEP);
        self.view(&format!("view-{attempt:03}"))
    }

    fn table_view(&mut self) -> Result<GrayImage> {
        self.place(Placing::ChessboardOnTable, VIEW_STEP);
        self.view("table")
    }

    fn gray_chart(
        &mut self,
        chart: &ChartDescription,
        world: [f64; 4],
        progress: &dyn Progress,
    ) -> Result<(Vec<Mosaic>, SensorWindow)> {
        // Under every LED in turn, not the view LED: white balance and linearity are per
        // light (each LED has its own colour and brightness), so the chart is a capture set
        // shot by the sequencer, like the white sheet.
        self.place(Placing::GrayChart { chart, world }, CHART_STEP);
        let set = self.capture_set("graychart", progress)?;
        let info = &set.manifest.image;
        let mut window = info.window;
        let mosaics = set
            .light_entries()?
            .into_iter()
            .map(|entry| {
                let (path, bytes) = set.read_frame_bytes(entry)?;
                match Encoding::parse(&info.encoding) {
                    Some(Encoding::Dn16) => {
                        Ok(dn16_mosaic(&decode_dn_image(&bytes, &path)?, &info.levels))
                    }
                    Some(Encoding::Raw) => {
                        window = SensorWindow::FULL;
                        Ok(decode_raw(bytes, &path)?.mosaic)
                    }
                    None => Err(Error::Unsupported(format!(
                        "{}: frame encoding \"{}\"",
                        set.dir.display(),
                        info.encoding
                    ))),
                }
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((mosaics, window))
    }

    fn white_sheet(
        &mut self,
        purpose: &str,
        exposures: usize,
        progress: &dyn Progress,
    ) -> Result<Frames> {
        let mut sum: Option<Frames> = None;
        let n = exposures.max(1);
        for e in 0..n {
            self.place(
                Placing::WhiteSheet {
                    purpose,
                    exposure: e,
                },
                SHEET_STEP,
            );
            let set = self.capture_set(&format!("{purpose}-{e:02}"), progress)?;
            let resolution = if set.manifest.image.encoding == "raw" {
                Resolution::Half
            } else {
                Resolution::Full
            };
            let options = DevelopOptions {
                resolution,
                subtract_dark: true,
            };
            let frames = set.load_frames_with(&options, progress)?.frames;
            let frames = bin_frames(frames, SHEET_STEP)?;
            sum = Some(match sum {
                None => frames,
                Some(mut acc) => {
                    add_frames(&mut acc, &frames)?;
                    acc
                }
            });
        }
        let mut frames = sum.expect("at least one exposure");
        for f in &mut frames.lights {
            for p in [&mut f.rgb.r, &mut f.rgb.g, &mut f.rgb.b] {
                p.data.iter_mut().for_each(|v| *v /= n as f32);
            }
        }
        Ok(frames)
    }

    fn view_window(&self) -> SensorWindow {
        view_window(&self.hand)
    }

    fn forget_gray_chart(&mut self) -> Result<()> {
        let dir = self.dir.join("captures").join("graychart");
        match std::fs::remove_dir_all(&dir) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(Error::io(&dir, e)),
            _ => Ok(()),
        }
    }
}

/// The CFA samples a Bayer sensor (RGGB) records of a frame that has R, G and B at every
/// pixel: at each site, that site's channel.
fn dn16_mosaic(dn: &crate::raw::DnImage, levels: &Levels) -> Mosaic {
    let pattern = [[0u8, 1], [1, 2]];
    let samples = (0..dn.width * dn.height)
        .map(|i| {
            let (x, y) = (i % dn.width, i / dn.width);
            dn.data[i * 3 + pattern[y % 2][x % 2] as usize]
        })
        .collect();
    Mosaic {
        width: dn.width,
        height: dn.height,
        pattern,
        black: [[levels.black as f32; 2]; 2],
        white: levels.white as f32,
        samples,
    }
}

fn luminance(rgb: &RgbPlanes) -> Plane {
    let mut out = Plane::new(rgb.width(), rgb.height(), 0.0);
    for (i, v) in out.data.iter_mut().enumerate() {
        *v = LUMINANCE_WEIGHTS
            .iter()
            .zip(rgb.channels())
            .map(|(w, p)| *w as f32 * p.data[i])
            .sum();
    }
    out
}

/// Bins `plane` (at `window`) down to sensor step `step`: the mean of each block.
fn bin(plane: &Plane, window: SensorWindow, step: f64) -> Result<(Plane, SensorWindow)> {
    let f = factor(window.step, step)?;
    let (w, h) = (plane.width / f, plane.height / f);
    let mut out = Plane::new(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for dy in 0..f {
                for dx in 0..f {
                    s += plane.data[(y * f + dy) * plane.width + x * f + dx];
                }
            }
            out.data[y * w + x] = s / (f * f) as f32;
        }
    }
    Ok((out, binned(window, f)))
}

fn factor(have: f64, want: f64) -> Result<usize> {
    let f = want / have;
    if f < 1.0 - 1e-9 || (f - f.round()).abs() > 1e-9 {
        return Err(Error::Invalid(format!(
            "frames every {have} sensor pixels cannot be binned to every {want}"
        )));
    }
    Ok(f.round() as usize)
}

fn binned(window: SensorWindow, f: usize) -> SensorWindow {
    SensorWindow {
        x0: window.x0 + 0.5 * (f as f64 - 1.0) * window.step,
        y0: window.y0 + 0.5 * (f as f64 - 1.0) * window.step,
        step: window.step * f as f64,
    }
}

/// Bins every frame to sensor step `step`; a bin with a saturated pixel is saturated.
fn bin_frames(frames: Frames, step: f64) -> Result<Frames> {
    let f = factor(frames.window.step, step)?;
    if f == 1 {
        return Ok(frames);
    }
    let window = frames.window;
    let lights = frames
        .lights
        .iter()
        .map(|frame| {
            let [r, g, b] = frame
                .rgb
                .channels()
                .map(|p| bin(p, window, step).map(|b| b.0));
            let (r, g, b) = (r?, g?, b?);
            let saturated = frame.saturated.as_ref().map(|m| {
                let (w, h) = (m.width / f, m.height / f);
                let mut out = Mask::new(w, h, false);
                for y in 0..h {
                    for x in 0..w {
                        out.data[y * w + x] =
                            (0..f * f).any(|i| m.data[(y * f + i / f) * m.width + x * f + i % f]);
                    }
                }
                out
            });
            Ok(LightFrame {
                rgb: RgbPlanes { r, g, b },
                saturated,
                cfa: None,
                dn: None,
                cfa_dn: None,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Frames {
        width: frames.width / f,
        height: frames.height / f,
        window: binned(window, f),
        lights,
    })
}

fn add_frames(acc: &mut Frames, more: &Frames) -> Result<()> {
    if (acc.width, acc.height, acc.lights.len()) != (more.width, more.height, more.lights.len()) {
        return Err(Error::Invalid(
            "white-sheet exposures differ in size or light count".into(),
        ));
    }
    for (a, m) in acc.lights.iter_mut().zip(&more.lights) {
        for (dst, src) in [
            (&mut a.rgb.r, &m.rgb.r),
            (&mut a.rgb.g, &m.rgb.g),
            (&mut a.rgb.b, &m.rgb.b),
        ] {
            dst.data
                .iter_mut()
                .zip(&src.data)
                .for_each(|(d, s)| *d += s);
        }
        if let (Some(d), Some(s)) = (a.saturated.as_mut(), m.saturated.as_ref()) {
            d.data.iter_mut().zip(&s.data).for_each(|(d, s)| *d |= *s);
        }
    }
    Ok(())
}

/// Linear luminance to the 8-bit view the chessboard detector reads: the 99th percentile
/// (the white print, whatever the exposure) at level 220. A black frame (no LED on) stays
/// black, so the board is not found.
fn to_gray(luma: &Plane) -> GrayImage {
    let mut sorted: Vec<f32> = luma
        .data
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    sorted.sort_by(f32::total_cmp);
    let p99 = sorted
        .get(sorted.len().saturating_sub(1) * 99 / 100)
        .copied()
        .unwrap_or(0.0);
    // Below 1 % of the white level there is no lit target to see, only sensor noise.
    let scale = if p99 > 0.01 { 220.0 / p99 } else { 0.0 };
    GrayImage {
        width: luma.width,
        height: luma.height,
        data: luma
            .data
            .iter()
            .map(|v| (v * scale).round().clamp(0.0, 255.0) as u8)
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_view_led_is_the_one_nearest_the_camera_axis() {
        let rig = Rig::default_rig();
        // LEDs 6..9 sit at 60 degrees elevation, 0..5 at 30: the first high one.
        assert_eq!(view_led(&rig), 6);
        let mut moved = rig.clone();
        moved.leds[8].position_m = [0.05, 0.0, 0.55];
        assert_eq!(view_led(&moved), 8);
    }

    #[test]
    fn binning_keeps_the_sensor_positions() {
        let w = SensorWindow::centred(4928, 3264, 2464, 1632, 2.0);
        let plane = Plane::new(2464, 1632, 0.5);
        let (b, bw) = bin(&plane, w, 8.0).unwrap();
        assert_eq!((b.width, b.height), (616, 408));
        assert_eq!(bw, SensorWindow::centred(4928, 3264, 616, 408, 8.0));
        assert!(bin(&plane, w, 3.0).is_err());
    }
}
