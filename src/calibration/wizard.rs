//! The calibration wizard's logic (the CLI owns the prompts): the steps in order, what each
//! still needs, accepting or rejecting each photograph with a reason, and a state file in the
//! bundle folder so an interrupted session resumes where it stopped. Photographs come from a
//! [`TargetSource`]: the simulated rig (synthetic targets rendered through an as-built rig),
//! or the capture module on real hardware.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::bundle::{self, Calibration};
use super::camera::{self, Board, CameraOptions, DetectedView};
use super::whitesheet::{self, FLATNESS_TOLERANCE_DEG};
use super::{lights, table};
use crate::error::{Error, Result};
use crate::fsutil::write_atomic;
use crate::plane::{Frames, GrayImage, SensorWindow};
use crate::progress::Progress;
use crate::rig::Rig;
use crate::solve::NoiseModel;

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
    /// The white sheet under every LED, `exposures` exposures averaged.
    fn white_sheet(&mut self, exposures: usize) -> Result<Frames>;
    /// Where the chessboard photographs sit on the sensor (binned previews).
    fn view_window(&self) -> SensorWindow;
}

/// The steps, in order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Step {
    CameraViews,
    Table,
    WhiteSheet,
    Flatness,
    Done,
}

/// Everything needed to resume.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct State {
    pub step: Step,
    pub rig_name: String,
    pub name: String,
    pub board: Board,
    /// Photographs taken so far (accepted or not).
    pub attempts: usize,
    /// Accepted chessboard views, saved as `views/<name>.png` in the bundle folder.
    pub accepted: Vec<String>,
    /// Rejected photographs and why.
    pub rejected: Vec<(String, String)>,
    pub calibration: Calibration,
}

/// What happened to one chessboard photograph.
#[derive(Clone, Debug, Serialize)]
pub struct ViewVerdict {
    pub name: String,
    pub accepted: bool,
    pub reason: String,
    pub accepted_so_far: usize,
    pub still_needed: usize,
    /// Regions of the frame no accepted view has covered yet.
    pub missing_regions: Vec<&'static str>,
}

/// The wizard over one bundle folder.
pub struct Wizard {
    pub dir: PathBuf,
    pub hand: Rig,
    pub state: State,
}

impl Wizard {
    /// Starts a new session in `dir`, or resumes the one whose state file is there.
    pub fn open(dir: &Path, hand: Rig, name: &str, board: Board) -> Result<(Wizard, bool)> {
        let path = dir.join(STATE_FILE);
        if path.is_file() {
            let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
            let state: State = toml::from_str(&text)
                .map_err(|e| Error::config(&path, "state", e.message().to_string()))?;
            return Ok((
                Wizard {
                    dir: dir.to_path_buf(),
                    hand,
                    state,
                },
                true,
            ));
        }
        crate::fsutil::create_dir_all(&dir.join("views"))?;
        let state = State {
            step: Step::CameraViews,
            rig_name: hand.name.clone(),
            name: name.to_string(),
            board,
            attempts: 0,
            accepted: Vec::new(),
            rejected: Vec::new(),
            calibration: Calibration::default(),
        };
        let wizard = Wizard {
            dir: dir.to_path_buf(),
            hand,
            state,
        };
        wizard.save()?;
        Ok((wizard, false))
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
        self.state.step = Step::WhiteSheet;
        self.save()?;
        Ok(pose)
    }

    /// The white sheet: LED positions fitted from the hand measurements.
    pub fn take_white_sheet(
        &mut self,
        source: &mut dyn TargetSource,
        reflectance: f64,
        progress: &dyn Progress,
    ) -> Result<lights::LightFit> {
        let rig = self.current_rig(source.view_window());
        let frames = source.white_sheet(1)?;
        let sheet = whitesheet::measure(&frames, &rig, reflectance, 8)?;
        let fit = lights::fit(&rig, &sheet, progress)?;
        self.state.calibration.lights = Some(fit.clone());
        self.state.calibration.sheet_reflectance = Some(reflectance);
        self.state.step = Step::Flatness;
        self.save()?;
        Ok(fit)
    }

    /// The final check: the sheet re-solved with the calibration, as many exposures averaged
    /// as the noise model asks for; then the bundle is written.
    pub fn finish(
        &mut self,
        source: &mut dyn TargetSource,
        progress: &dyn Progress,
    ) -> Result<(whitesheet::Flatness, bundle::BundleIndex)> {
        let window = source.view_window();
        let rig = self.current_rig(window);
        let reflectance = self.state.calibration.sheet_reflectance.unwrap_or(0.9);
        let noise = NoiseModel::from_sensor(&rig.sensor);
        let one = source.white_sheet(1)?;
        let single = whitesheet::flatness(&one, &rig, noise, 1, progress)?;
        let n = whitesheet::exposures_needed(
            single.predicted_noise_max_deg,
            FLATNESS_TOLERANCE_DEG - single.block_max_deg,
        )
        .min(64);
        let frames = source.white_sheet(n)?;
        let check = whitesheet::flatness(&frames, &rig, noise, n, progress)?;
        let sheet = whitesheet::measure(&frames, &rig, reflectance, 8)?;
        self.state.calibration.flatness = Some(check.clone());
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
        Ok((check, index))
    }
}
