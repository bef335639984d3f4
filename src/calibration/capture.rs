//! Where the wizard's photographs come from. `Simulated`: the synthetic rig (an as-built rig
//! that differs from the hand measurements, as a real one does) renders the chessboard, the
//! board on the table and the white sheet, with an operator who now and then holds the board
//! half out of the frame. Capturing the targets through the LED controller and a tethered
//! camera is not built yet and says so.

use nalgebra::Vector3;

use super::camera::Board;
use super::wizard::TargetSource;
use crate::error::{Error, Result};
use crate::plane::{Frames, GrayImage, SensorWindow};
use crate::rig::Rig;
use crate::synth::targets::{self, BoardPose, Chessboard, RayGrid, ViewRender};

/// Chessboard previews are the sensor binned 4x.
pub const VIEW_STEP: f64 = 4.0;
/// White-sheet frames: every 8th sensor pixel over the whole field.
pub const SHEET_STEP: f64 = 8.0;

pub struct Simulated {
    pub truth: Rig,
    chess: Chessboard,
    grid: RayGrid,
    window: SensorWindow,
    poses: Vec<BoardPose>,
    seed: u64,
    sheets: u64,
}

impl Simulated {
    /// The rig as built: `hand` with its LEDs up to 3 cm off and a real lens (seeded).
    pub fn new(hand: &Rig, board: Board, seed: u64) -> Simulated {
        let truth = targets::as_built(hand, 0.03, seed);
        let chess = Chessboard {
            board,
            border_squares: 1.0,
        };
        let (w, h) = targets::binned_size(&truth, VIEW_STEP);
        let window = SensorWindow::centred(
            truth.camera.width as usize,
            truth.camera.height as usize,
            w,
            h,
            VIEW_STEP,
        );
        let grid = RayGrid::new(
            &truth.camera,
            window,
            w,
            h,
            ViewRender::default().supersample,
        );
        let distance = truth.camera.position_m[2] - truth.sample.z_m;
        let poses = targets::calibration_poses(
            &chess,
            &truth.camera,
            window,
            (w, h),
            64,
            0.85 * distance,
            seed,
        );
        Simulated {
            truth,
            chess,
            grid,
            window,
            poses,
            seed,
            sheets: 0,
        }
    }
}

impl TargetSource for Simulated {
    fn chessboard_view(&mut self, attempt: usize) -> Result<GrayImage> {
        let render = ViewRender {
            seed: self.seed.wrapping_add(attempt as u64),
            ..ViewRender::default()
        };
        // Every fifth photograph the operator has the board half out of the frame.
        let pose = if attempt % 5 == 4 {
            let z = 0.5;
            BoardPose::facing_camera(&self.chess, Vector3::new(0.17, 0.0, z), 0.1, -0.2, 0.1)
        } else {
            self.poses[attempt % self.poses.len()]
        };
        Ok(targets::render_chessboard(
            &self.grid,
            &self.chess,
            &pose,
            &render,
        ))
    }

    fn table_view(&mut self) -> Result<GrayImage> {
        Ok(targets::table_view(
            &self.truth,
            &self.chess,
            VIEW_STEP,
            self.seed ^ 0x7ab1e,
        ))
    }

    fn white_sheet(&mut self, exposures: usize) -> Result<Frames> {
        self.sheets += 1;
        Ok(targets::white_sheet_frames(
            &self.truth,
            SHEET_STEP,
            0.9,
            0.02,
            exposures,
            self.seed.wrapping_mul(31).wrapping_add(self.sheets),
        ))
    }

    fn view_window(&self) -> SensorWindow {
        self.window
    }
}

/// The real rig: not built yet.
pub fn hardware_source() -> Result<Simulated> {
    Err(Error::Unsupported(
        "capturing calibration targets through the LED controller and a tethered camera is not \
         built yet: run the wizard with --source sim, or each step over photographs you took \
         (psscan calibrate camera --images DIR ...)"
            .into(),
    ))
}
