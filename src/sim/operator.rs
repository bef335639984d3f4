//! The simulated operator of the calibration wizard: the synthetic rig as built (its LEDs
//! away from the hand measurements, a real lens), the poses at which the board is held, and
//! the two ways the wizard's photographs are simulated: [`Simulated`] renders the targets
//! directly (`--source sim`), and [`SimScene`] places them in front of the simulated
//! [`TargetCamera`] for a [`Captured`](crate::calibration::capture::Captured) source, which
//! photographs them through the LED controller.

use nalgebra::Vector3;

use super::camera::LitSource;
use super::target_camera::{Placement, Stage, Target, TargetCamera};
use crate::calibration::capture::{
    binned_window, view_led, view_window, Operator, Placing, CHART_STEP, SHEET_STEP, VIEW_STEP,
};
use crate::calibration::wizard::TargetSource;
use crate::error::Result;
use crate::plane::{Frames, GrayImage, SensorWindow};
use crate::progress::Progress;
use crate::raw::Mosaic;
use crate::rig::{Board, ChartDescription, Rig};
use crate::synth::targets::{self, BoardPose, Chessboard, RayGrid, ViewRender};

/// The simulated rig's white sheet: its true reflectance and fibre texture.
const SIM_SHEET_REFLECTANCE: f64 = 0.9;
const SIM_SHEET_TEXTURE: f64 = 0.02;
/// The simulated camera's exposure for the flat targets: the exposure captures use, so the
/// gray chart measures the linearity where the textile will be measured.
const SIM_FLAT_EXPOSURE: f64 = 1.0;

/// The simulated operator's hands: where the board is held for each photograph.
pub struct BoardPoses {
    /// The board held: its corners, square size and white border.
    pub chess: Chessboard,
    poses: Vec<BoardPose>,
}

impl BoardPoses {
    /// Poses sweeping the frame of `truth`'s camera, seen through the views' window.
    pub fn new(truth: &Rig, board: Board, seed: u64) -> BoardPoses {
        let chess = Chessboard {
            board,
            border_squares: 1.0,
        };
        let (w, h) = targets::binned_size(truth, VIEW_STEP);
        let distance = truth.camera.position_m[2] - truth.sample.z_m;
        let poses = targets::calibration_poses(
            &chess,
            &truth.camera,
            view_window(truth),
            (w, h),
            64,
            0.85 * distance,
            seed,
        );
        BoardPoses { chess, poses }
    }

    /// The board for photograph `attempt`: every fifth one the operator has it half out of
    /// the frame.
    pub fn pose(&self, attempt: usize) -> BoardPose {
        if attempt % 5 == 4 {
            BoardPose::facing_camera(&self.chess, Vector3::new(0.17, 0.0, 0.5), 0.1, -0.2, 0.1)
        } else {
            self.poses[attempt % self.poses.len()]
        }
    }
}

/// The `--source sim` photographs: the synthetic rig as built renders the targets directly,
/// with an operator who now and then holds the board half out of the frame. Quick; no LEDs,
/// no camera.
pub struct Simulated {
    /// The rig as built, whose camera and LEDs render the targets (not the hand-measured rig the
    /// wizard is given).
    pub truth: Rig,
    poses: BoardPoses,
    grid: RayGrid,
    window: SensorWindow,
    seed: u64,
    sheets: u64,
}

impl Simulated {
    /// The rig as built: `hand` with its LEDs up to 3 cm off and a real lens (seeded).
    pub fn new(hand: &Rig, board: Board, seed: u64) -> Simulated {
        let truth = targets::as_built(hand, 0.03, seed);
        let (w, h) = targets::binned_size(&truth, VIEW_STEP);
        let window = view_window(&truth);
        let grid = RayGrid::new(
            &truth.camera,
            window,
            w,
            h,
            ViewRender::default().supersample,
        );
        Simulated {
            poses: BoardPoses::new(&truth, board, seed),
            truth,
            grid,
            window,
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
        Ok(targets::render_chessboard(
            &self.grid,
            &self.poses.chess,
            &self.poses.pose(attempt),
            &render,
        ))
    }

    fn table_view(&mut self) -> Result<GrayImage> {
        Ok(targets::table_view(
            &self.truth,
            &self.poses.chess,
            VIEW_STEP,
            self.seed ^ 0x7ab1e,
        ))
    }

    fn gray_chart(
        &mut self,
        chart: &ChartDescription,
        world: [f64; 4],
        _progress: &dyn Progress,
    ) -> Result<(Vec<Mosaic>, SensorWindow)> {
        let (w, h) = targets::binned_size(&self.truth, CHART_STEP);
        let (mosaics, _) = targets::gray_chart_mosaics(
            &self.truth,
            chart,
            world,
            (w, h, CHART_STEP),
            SIM_FLAT_EXPOSURE,
            self.seed ^ 0xc4a7,
        );
        Ok((mosaics, binned_window(&self.truth, CHART_STEP)))
    }

    fn white_sheet(
        &mut self,
        _purpose: &str,
        exposures: usize,
        _progress: &dyn Progress,
    ) -> Result<Frames> {
        self.sheets += 1;
        Ok(targets::white_sheet_frames(
            &self.truth,
            SHEET_STEP,
            SIM_SHEET_REFLECTANCE,
            SIM_SHEET_TEXTURE,
            exposures,
            self.seed.wrapping_mul(31).wrapping_add(self.sheets),
        ))
    }

    fn view_window(&self) -> SensorWindow {
        self.window
    }
}

/// The simulated side of a [`Captured`](crate::calibration::capture::Captured) source: the
/// operator (an [`Operator`]) and the stage the simulated camera photographs.
pub struct SimScene {
    /// The rig as built that the simulated camera renders through.
    pub truth: Rig,
    /// Where the operator places each target for the simulated camera to photograph.
    pub stage: Stage,
    poses: BoardPoses,
    /// Exposure of the chessboard views: a white print at the table centre under the view LED
    /// at 40 % of the white level, so a board held nearer the LEDs does not clip.
    view_exposure: f64,
    seed: u64,
}

/// The simulated camera for a [`Captured`](crate::calibration::capture::Captured) source on
/// `hand`'s rig as built (seeded, the same as-built rig [`Simulated`] has), reading the lit
/// LEDs from `lit`; the scene is the operator to pass to the source.
pub fn simulated_camera(
    hand: &Rig,
    board: Board,
    seed: u64,
    lit: Box<dyn LitSource>,
) -> (TargetCamera, SimScene) {
    let truth = targets::as_built(hand, 0.03, seed);
    let poses = BoardPoses::new(&truth, board, seed);
    let stage = Stage::default();
    let k = view_led(hand);
    let centre = Vector3::new(0.0, 0.0, truth.sample.z_m);
    let s = truth.leds[k].sample_at(&centre);
    let white = s.falloff * s.direction.z * truth.led_rgb_power(k)[1] / truth.leds[k].power * 0.85;
    let camera = TargetCamera::new(
        truth.clone(),
        poses.chess,
        stage.clone(),
        lit,
        seed ^ 0xca11,
    );
    let scene = SimScene {
        truth,
        stage,
        poses,
        view_exposure: 0.4 / white,
        seed,
    };
    (camera, scene)
}

impl Operator for SimScene {
    fn place(&self, what: Placing, step: f64) {
        let (target, exposure, take) = match what {
            Placing::ChessboardView(attempt) => (
                Target::Chessboard(self.poses.pose(attempt)),
                self.view_exposure,
                attempt as u64,
            ),
            Placing::ChessboardOnTable => (
                Target::Chessboard(BoardPose::on_table(&self.poses.chess, &self.truth)),
                self.view_exposure,
                1 << 20,
            ),
            Placing::GrayChart { chart, world } => (
                Target::GrayChart {
                    chart: chart.clone(),
                    world,
                },
                SIM_FLAT_EXPOSURE,
                2 << 20,
            ),
            Placing::WhiteSheet { purpose, exposure } => {
                // Each exposure of each purpose its own noise (a re-shot frame its old noise).
                let purpose_code = purpose
                    .bytes()
                    .fold(0u64, |h, b| h.wrapping_mul(31) + b as u64);
                (
                    Target::WhiteSheet {
                        reflectance: SIM_SHEET_REFLECTANCE,
                        texture: SIM_SHEET_TEXTURE,
                        seed: self.seed,
                    },
                    SIM_FLAT_EXPOSURE,
                    (3 << 20) + (purpose_code << 8) + exposure as u64,
                )
            }
        };
        self.stage.place(Placement {
            target,
            step,
            exposure,
            take,
        });
    }
}
