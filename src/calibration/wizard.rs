//! The calibration wizard's logic (the CLI owns the prompts): the steps in order, what each
//! still needs, accepting or rejecting each photograph with a reason, and a state file in the
//! bundle folder so an interrupted session resumes where it stopped. Photographs come from a
//! [`TargetSource`]: the simulated rig (synthetic targets rendered through an as-built rig),
//! or the capture module (LED controller and camera, real or simulated; see `capture`).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::bundle::{self, Calibration};
use super::camera::{self, CameraOptions, DetectedView};
use super::graychart::{self, chart_rect, patch_noise, shading_uncertainty, ChartReport, Shading};
use super::whitesheet::{self, FLATNESS_TOLERANCE_DEG};
use super::{lights, table};
use crate::error::{Error, Result};
use crate::fsutil::write_atomic;
use crate::plane::{Frames, GrayImage, SensorWindow};
use crate::progress::Progress;
use crate::raw::Mosaic;
use crate::rig::Board;
use crate::rig::ChartDescription;
use crate::rig::Rig;
use crate::solve::NoiseModel;

/// The wizard's state file ([`State`] as TOML) in the bundle folder; a session that finds it there
/// resumes.
pub const STATE_FILE: &str = "wizard-state.toml";
/// Accepted chessboard views the camera step asks for.
pub const VIEWS_NEEDED: usize = 12;

/// Where the wizard's photographs come from.
pub trait TargetSource {
    /// A photograph of the chessboard as the operator holds it now (`attempt` counts every
    /// photograph taken, so a simulated operator moves between them).
    fn chessboard_view(&mut self, attempt: usize) -> Result<GrayImage>;
    /// The chessboard lying flat at the table centre.
    fn table_view(&mut self) -> Result<GrayImage>;
    /// The gray chart `chart` lying on the table with its patches filling the world rectangle
    /// `world` (`[x0, x1, y0, y1]`, metres), under every LED: one raw CFA mosaic per LED, and
    /// where the mosaics' samples sit on the sensor.
    fn gray_chart(
        &mut self,
        chart: &ChartDescription,
        world: [f64; 4],
        progress: &dyn Progress,
    ) -> Result<(Vec<Mosaic>, SensorWindow)>;
    /// The white sheet under every LED, `exposures` exposures averaged. `purpose` ("fit",
    /// "check") keeps the photographs of different uses apart where a source stores them.
    fn white_sheet(
        &mut self,
        purpose: &str,
        exposures: usize,
        progress: &dyn Progress,
    ) -> Result<Frames>;
    /// Where the chessboard photographs sit on the sensor (binned previews).
    fn view_window(&self) -> SensorWindow;
    /// Forgets a rejected gray chart's photographs, so the next [`Self::gray_chart`] takes
    /// new ones.
    fn forget_gray_chart(&mut self) -> Result<()> {
        Ok(())
    }
}

/// The steps, in order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Step {
    /// Taking chessboard photographs until [`VIEWS_NEEDED`] are accepted; then the camera is
    /// calibrated.
    CameraViews,
    /// Photographing the chessboard flat on the table for the table's pose.
    Table,
    /// Reading the gray chart under every LED: white balance and linearity.
    GrayChart,
    /// Photographing the white sheet under every LED and fitting the LED positions to it.
    WhiteSheet,
    /// The final check (the sheet re-solved with the calibration), after which the bundle is
    /// written.
    Flatness,
    /// Every step taken and the bundle written.
    Done,
}

/// Everything needed to resume.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct State {
    /// The step to take next.
    pub step: Step,
    /// Name of the rig being calibrated (the hand-measured rig's), the bundle id's first part.
    pub rig_name: String,
    /// The bundle's name, the bundle id's second part.
    pub name: String,
    /// The chessboard used for the camera and table steps.
    pub board: Board,
    /// Photographs taken so far (accepted or not).
    pub attempts: usize,
    /// Accepted chessboard views, saved as `views/<name>.png` in the bundle folder.
    pub accepted: Vec<String>,
    /// Rejected photographs and why.
    pub rejected: Vec<(String, String)>,
    /// The results of the steps finished so far.
    pub calibration: Calibration,
}

/// What happened to one chessboard photograph.
#[derive(Clone, Debug, Serialize)]
pub struct ViewVerdict {
    /// The photograph's name (`view-NNN`, numbered by attempt).
    pub name: String,
    /// Whether the view was kept for the camera calibration.
    pub accepted: bool,
    /// Why it was rejected, or what was found when it was accepted.
    pub reason: String,
    /// Views accepted so far, this one included.
    pub accepted_so_far: usize,
    /// Accepted views still to take before the camera can be calibrated.
    pub still_needed: usize,
    /// Regions of the frame no accepted view has covered yet.
    pub missing_regions: Vec<&'static str>,
}

/// The gray chart's step: its report, and whether it passed.
#[derive(Clone, Debug, Serialize)]
pub struct ChartVerdict {
    /// Whether the chart passed: no patch clipped and every light's worst patch within its
    /// `linearity_tolerance`.
    pub accepted: bool,
    /// Why not (empty when accepted).
    pub reasons: Vec<String>,
    /// Per light, the largest deviation from the linear fit that the shading model's
    /// uncertainty and the patches' sensor noise allow.
    pub linearity_tolerance: Vec<f64>,
    /// The chart's white balance and linearity per light; no lights when the chart could not
    /// be read at all (too few unclipped patches, say), with `reasons` saying why.
    pub report: ChartReport,
}

/// How far the LED positions may be off while the chart is read: the hand measurements (up
/// to 3 cm, the figure) before the white sheet, the fit (within 5 mm) after it.
pub use super::lights::{FITTED_LED_ERROR_M, HAND_LED_ERROR_M};

/// The default chart's place on the table: 120 x 50 mm centred under the camera.
pub const CHART_WORLD: [f64; 4] = [-0.06, 0.06, -0.025, 0.025];

/// The wizard over one bundle folder.
pub struct Wizard {
    /// The bundle folder: the state file, the accepted views (`views/`) and finally the bundle.
    pub dir: PathBuf,
    /// The rig as measured by hand, which each calibrated step refines.
    pub hand: Rig,
    /// Where the session stands; saved to [`STATE_FILE`] after every step.
    pub state: State,
    /// The gray chart and where on the table the operator lays it.
    pub chart: ChartDescription,
    /// Where the chart lies on the table, `[x0, x1, y0, y1]` in world metres.
    pub chart_world: [f64; 4],
}

impl Wizard {
    /// Starts a new session in `dir`, or resumes the one whose state file is there.
    pub fn open(dir: &Path, hand: Rig, name: &str, board: Board) -> Result<(Wizard, bool)> {
        let path = dir.join(STATE_FILE);
        let resumed = path.is_file();
        let state = if resumed {
            let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
            let state: State = toml::from_str(&text)
                .map_err(|e| Error::config(&path, "state", e.message().to_string()))?;
            // Resuming with another rig, name or board would mix two sessions' photographs.
            let (rig, saved_board) = (&state.rig_name, state.board);
            let square_mm = (saved_board.square_m * 1e6).round() / 1e3;
            if (rig.as_str(), state.name.as_str(), saved_board) != (&hand.name, name, board) {
                return Err(Error::Invalid(format!(
                    "{} holds the calibration session of rig `{rig}` named `{}` with a {}x{} \
                     board of {} mm squares; resume it with that rig, `--name {}`, \
                     `--wizard-board {}x{}` and `--wizard-square-mm {}`, or start another \
                     session in another folder (--out)",
                    dir.display(),
                    state.name,
                    saved_board.cols,
                    saved_board.rows,
                    square_mm,
                    state.name,
                    saved_board.cols,
                    saved_board.rows,
                    square_mm,
                )));
            }
            state
        } else {
            crate::fsutil::create_dir_all(&dir.join("views"))?;
            State {
                step: Step::CameraViews,
                rig_name: hand.name.clone(),
                name: name.to_string(),
                board,
                attempts: 0,
                accepted: Vec::new(),
                rejected: Vec::new(),
                calibration: Calibration::default(),
            }
        };
        let wizard = Wizard {
            dir: dir.to_path_buf(),
            hand,
            state,
            chart: ChartDescription::munsell_12(),
            chart_world: CHART_WORLD,
        };
        if !resumed {
            wizard.save()?;
        }
        Ok((wizard, resumed))
    }

    fn save(&self) -> Result<()> {
        let text = toml::to_string_pretty(&self.state)
            .map_err(|e| Error::Invalid(format!("wizard state does not serialise: {e}")))?;
        write_atomic(&self.dir.join(STATE_FILE), text.as_bytes())
    }

    fn accepted_views(&self) -> Result<Vec<DetectedView>> {
        self.state
            .accepted
            .iter()
            .map(|name| {
                let image = GrayImage::load(&self.dir.join("views").join(format!("{name}.png")))?;
                camera::detect(name, &image, &self.state.board, None)
            })
            .collect()
    }

    /// Takes one chessboard photograph and accepts it (board found, and consistent with the
    /// views so far once there are enough to calibrate) or rejects it with the reason.
    pub fn take_view(&mut self, source: &mut dyn TargetSource) -> Result<ViewVerdict> {
        let attempt = self.state.attempts;
        let name = format!("view-{attempt:03}");
        let image = source.chessboard_view(attempt)?;
        self.state.attempts += 1;
        let detected = camera::detect(&name, &image, &self.state.board, None)?;
        let size = (image.width, image.height);
        let mut reason = String::from("board found");
        let mut accepted = detected.corners.is_some();
        if !accepted {
            reason =
                "the whole board was not found: keep all of it in the frame, sharp and evenly lit"
                    .into();
        } else if self.state.accepted.len() >= camera::MIN_VIEWS {
            // Enough views to judge this one (outliers are only rejected above the minimum):
            // calibrate with it and see whether it stands out.
            let mut views = self.accepted_views()?;
            views.push(detected.clone());
            let cal =
                camera::calibrate(&views, &self.state.board, size, &CameraOptions::default())?;
            if let Some(v) = cal.views.iter().find(|v| v.name == name && !v.used) {
                accepted = false;
                reason = v.rejected_because.clone().unwrap_or_default();
            } else {
                reason = format!(
                    "board found, reprojection error {:.3} px",
                    cal.views
                        .iter()
                        .find(|v| v.name == name)
                        .and_then(|v| v.rms_px)
                        .unwrap_or(0.0)
                );
            }
        }
        if accepted {
            image.save_png(&self.dir.join("views").join(format!("{name}.png")))?;
            self.state.accepted.push(name.clone());
        } else {
            self.state.rejected.push((name.clone(), reason.clone()));
        }
        let views = self.accepted_views()?;
        let missing = camera::missing_regions(&camera::coverage(&views, size));
        if self.state.accepted.len() >= VIEWS_NEEDED {
            let cal =
                camera::calibrate(&views, &self.state.board, size, &CameraOptions::default())?;
            self.state.calibration.camera = Some(cal);
            self.state.step = Step::Table;
        }
        self.save()?;
        Ok(ViewVerdict {
            name,
            accepted,
            reason,
            accepted_so_far: self.state.accepted.len(),
            still_needed: VIEWS_NEEDED.saturating_sub(self.state.accepted.len()),
            missing_regions: missing,
        })
    }

    /// The rig with everything calibrated so far.
    pub fn current_rig(&self, window: SensorWindow) -> Rig {
        let cal = &self.state.calibration;
        let mut rig = self.hand.clone();
        if let (Some(cam), Some(pose)) = (&cal.camera, &cal.table) {
            let sensor = cam.intrinsics.to_sensor(
                window,
                (
                    self.hand.camera.width as usize,
                    self.hand.camera.height as usize,
                ),
            );
            rig = table::calibrated_rig(&rig, &sensor, pose);
        }
        if let Some(fit) = &cal.lights {
            rig = fit.apply(&rig);
        }
        rig
    }

    /// The board flat on the table: the table's pose.
    pub fn take_table(&mut self, source: &mut dyn TargetSource) -> Result<table::TablePose> {
        let cam = self.state.calibration.camera.clone().ok_or_else(|| {
            Error::Invalid("the table step needs the camera calibrated first".into())
        })?;
        let image = source.table_view()?;
        let pose = table::table_pose(&image, &self.state.board, &cam.intrinsics)?;
        self.state.calibration.table = Some(pose);
        self.state.step = Step::GrayChart;
        self.save()?;
        Ok(pose)
    }

    /// The gray chart under every LED: white-balance gains and the linearity report, read
    /// with the LEDs' shading as the rig stands now (hand-measured positions). Accepted when
    /// no patch clipped and every light's worst patch lies within what the shading's
    /// uncertainty and the sensor noise allow; a rejected chart is left out of the state and
    /// its reasons say what to change.
    pub fn take_gray_chart(
        &mut self,
        source: &mut dyn TargetSource,
        progress: &dyn Progress,
    ) -> Result<ChartVerdict> {
        let verdict = self.read_chart(source, HAND_LED_ERROR_M, progress)?;
        if verdict.accepted {
            self.state.calibration.gray_chart = Some(verdict.report.clone());
            self.state.step = Step::WhiteSheet;
            self.save()?;
        } else {
            source.forget_gray_chart()?;
        }
        Ok(verdict)
    }

    fn read_chart(
        &self,
        source: &mut dyn TargetSource,
        led_error_m: f64,
        progress: &dyn Progress,
    ) -> Result<ChartVerdict> {
        let rig = self.current_rig(source.view_window());
        let (mosaics, window) = source.gray_chart(&self.chart, self.chart_world, progress)?;
        let rect = chart_rect(&rig, window, self.chart_world)?;
        let shading = Shading { rig: &rig, window };
        let report = match graychart::calibrate(&mosaics, &self.chart, &rect, Some(&shading)) {
            Ok(report) => report,
            // Too few unclipped patches: a reason to reject, not a failure of the wizard.
            Err(Error::Invalid(reason)) => {
                return Ok(ChartVerdict {
                    accepted: false,
                    reasons: vec![reason],
                    linearity_tolerance: Vec::new(),
                    report: ChartReport {
                        chart: self.chart.name.clone(),
                        lights: Vec::new(),
                    },
                })
            }
            Err(e) => return Err(e),
        };
        let noise = NoiseModel::from_sensor(&rig.sensor);
        let mut reasons = Vec::new();
        let mut tolerances = Vec::new();
        for (k, light) in report.lights.iter().enumerate() {
            let l = &light.linearity;
            if !l.clipped_patches.is_empty() {
                reasons.push(format!(
                    "under LED {k} patches {:?} clipped at the white level: lower the exposure \
                     (the white sheet, brighter still, would clip too)",
                    l.clipped_patches
                ));
            }
            let tolerance = shading_uncertainty(&rig, k, &self.chart, &rect, window, led_error_m)?
                + 4.0 * patch_noise(&mosaics[k], &self.chart, &rect, &noise)?;
            tolerances.push(tolerance);
            if l.worst_deviation.abs() > tolerance {
                reasons.push(format!(
                    "under LED {k} patch {} lies {:+.2} % off the linear fit, more than the \
                     {:.2} % the shading model and the sensor noise allow: check that the chart \
                     lies flat where the wizard said and that nothing shades it",
                    l.worst_patch,
                    100.0 * l.worst_deviation,
                    100.0 * tolerance
                ));
            }
        }
        Ok(ChartVerdict {
            accepted: reasons.is_empty(),
            reasons,
            linearity_tolerance: tolerances,
            report,
        })
    }

    /// The white sheet: LED positions fitted from the hand measurements. A fit with problems
    /// (`LightFit::problems`) is returned but not kept: the wizard stays at this step.
    pub fn take_white_sheet(
        &mut self,
        source: &mut dyn TargetSource,
        reflectance: f64,
        progress: &dyn Progress,
    ) -> Result<lights::LightFit> {
        let rig = self.current_rig(source.view_window());
        let frames = source.white_sheet("fit", 1, progress)?;
        let sheet = whitesheet::measure(&frames, &rig, reflectance, 8)?;
        let fit = lights::fit(&rig, &sheet, progress)?;
        if !fit.problems().is_empty() {
            // A rejected fit stays out of the state: the step is taken again.
            return Ok(fit);
        }
        self.state.calibration.lights = Some(fit.clone());
        self.state.calibration.sheet_reflectance = Some(reflectance);
        self.state.step = Step::Flatness;
        self.save()?;
        Ok(fit)
    }

    /// The final check: the sheet re-solved with the calibration, as many exposures averaged
    /// as the noise model asks for; the gray chart read again with the fitted LEDs' shading;
    /// then the bundle is written. A sheet that does not come out flat is an error and writes
    /// no bundle (see `reject_flatness`).
    pub fn finish(
        &mut self,
        source: &mut dyn TargetSource,
        progress: &dyn Progress,
    ) -> Result<(
        whitesheet::Flatness,
        Option<ChartVerdict>,
        bundle::BundleIndex,
    )> {
        let window = source.view_window();
        let rig = self.current_rig(window);
        let reflectance = self.state.calibration.sheet_reflectance.unwrap_or(0.9);
        let noise = NoiseModel::from_sensor(&rig.sensor);
        let one = source.white_sheet("check", 1, progress)?;
        let single = whitesheet::flatness(&one, &rig, noise, 1, progress)?;
        let n = whitesheet::exposures_needed(
            single.predicted_noise_max_deg,
            FLATNESS_TOLERANCE_DEG - single.block_max_deg,
        )
        .min(64);
        let frames = source.white_sheet("check", n, progress)?;
        let check = whitesheet::flatness(&frames, &rig, noise, n, progress)?;
        self.state.calibration.flatness = Some(check.clone());
        if !check.flat {
            return Err(self.reject_flatness(&check));
        }
        let sheet = whitesheet::measure(&frames, &rig, reflectance, 8)?;
        // With the LEDs where the fit put them the chart's shading is known far better: its
        // linearity report is read again, and that one goes into the bundle.
        let chart = match self.state.calibration.gray_chart {
            Some(_) => {
                let verdict = self.read_chart(source, FITTED_LED_ERROR_M, progress)?;
                if !verdict.report.lights.is_empty() {
                    self.state.calibration.gray_chart = Some(verdict.report.clone());
                }
                Some(verdict)
            }
            None => None,
        };
        let index = bundle::write(
            &self.dir,
            &self.state.rig_name,
            &self.state.name,
            &self.state.calibration,
            &rig,
            Some(&sheet),
        )?;
        self.state.step = Step::Done;
        self.save()?;
        Ok((check, chart, index))
    }

    /// A sheet that does not come out flat means the calibration does not explain the
    /// photographs (LEDs fitted to a wrong minimum, a sheet that lifted or moved): no bundle
    /// is written. The failed check stays in the state as the record of why, the LED fit is
    /// dropped, and the session goes back to the white-sheet step, so the next run takes the
    /// sheet again and fits the LEDs from the hand measurements.
    fn reject_flatness(&mut self, check: &whitesheet::Flatness) -> Error {
        self.state.calibration.lights = None;
        self.state.step = Step::WhiteSheet;
        let saved = match self.save() {
            Ok(()) => String::new(),
            Err(e) => format!(" (and the state could not be saved: {e})"),
        };
        Error::Invalid(format!(
            "the flatness check failed: the white sheet re-solved with the calibration has a \
             normal {:.3} deg from straight up (limit {} deg; 16x16-block mean at most {:.3} \
             deg, noise alone predicts up to {:.3} deg with {} exposures averaged), so the \
             calibration does not explain the photographs and no bundle was written{saved}. \
             Check that the sheet lies flat and did not move, then run the same command again: \
             the white-sheet step is taken again and the LEDs are fitted afresh",
            check.max_deg,
            check.tolerance_deg,
            check.block_max_deg,
            check.predicted_noise_max_deg,
            check.exposures,
        ))
    }
}
