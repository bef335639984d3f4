//! The table's pose: a chessboard lying flat on the table, photographed by the calibrated
//! camera, gives (solvePnP) where the camera is relative to the table, and so where every
//! pixel's ray meets the table. The board defines the world frame (DESIGN.md): origin at the
//! centre of its corner grid, +x along its rows (image columns), +y toward the top of the
//! image, +z up; the operator lays it at the table centre where the LEDs were measured from.

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use super::camera::Intrinsics;
use super::cv;
use crate::error::{Error, Result};
use crate::plane::{GrayImage, SensorWindow};
use crate::rig::Board;
use crate::rig::{Camera, Rig};

/// Where the camera is in the table's world frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TablePose {
    /// Centre of projection (m).
    pub camera_position_m: [f64; 3],
    /// The rig's `camera.rotation_deg`: tilts about world x, y, z from looking straight down.
    pub camera_rotation_deg: [f64; 3],
    /// RMS distance between the detected corners and the board reprojected at this pose.
    pub rms_reprojection_px: f64,
}

/// Board frame (x along rows, y down columns, z into the board) to world axes: a half turn
/// about x. The same matrix is the camera's "looking straight down" orientation.
fn flip() -> Matrix3<f64> {
    Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
}

/// Finds the board in `image` (taken through `window` of the sensor) and solves the camera's
/// pose; `intrinsics` are in the image's pixels.
pub fn table_pose(image: &GrayImage, board: &Board, intrinsics: &Intrinsics) -> Result<TablePose> {
    if (image.width, image.height) != (intrinsics.width, intrinsics.height) {
        return Err(Error::Invalid(format!(
            "the table photograph is {}x{} but the camera was calibrated on {}x{} images",
            image.width, image.height, intrinsics.width, intrinsics.height
        )));
    }
    let corners = cv::find_corners(image, cv::PatternSize::of(board), None)?.ok_or_else(|| {
        Error::Invalid(
            "the board lying on the table was not found: the whole board must be in the frame, lit evenly"
                .into(),
        )
    })?;
    pose_from_corners(&corners, board, intrinsics)
}

/// The pose from already detected corners.
pub fn pose_from_corners(
    corners: &[[f64; 2]],
    board: &Board,
    intrinsics: &Intrinsics,
) -> Result<TablePose> {
    let object = board.object_points();
    let raw = cv::solve_pnp(
        &object,
        corners,
        &intrinsics.camera_matrix(),
        &intrinsics.distortion,
    )?;
    let r = Matrix3::from_fn(|i, j| raw.rotation[i][j]);
    let t = Vector3::from(raw.translation);
    let [bx, by] = board.centre();
    let c = Vector3::new(bx, by, 0.0);
    // Camera = R b + t, world = F (b - c): the camera centre is at world F(-R^T t - c).
    let camera_position = flip() * (-(r.transpose() * t) - c);
    let world_from_camera = flip() * r.transpose();
    let tilt = Rotation3::from_matrix(&(world_from_camera * flip()));
    let (roll, pitch, yaw) = tilt.euler_angles();
    let pose = TablePose {
        camera_position_m: camera_position.into(),
        camera_rotation_deg: [roll.to_degrees(), pitch.to_degrees(), yaw.to_degrees()],
        rms_reprojection_px: 0.0,
    };
    let rms = reprojection_rms(&pose, corners, board, intrinsics);
    Ok(TablePose {
        rms_reprojection_px: rms,
        ..pose
    })
}

/// The rig camera these intrinsics and this pose describe.
pub fn camera(intrinsics: &Intrinsics, pose: &TablePose) -> Camera {
    Camera {
        width: intrinsics.width as u32,
        height: intrinsics.height as u32,
        fx: intrinsics.fx,
        fy: intrinsics.fy,
        cx: intrinsics.cx,
        cy: intrinsics.cy,
        distortion: intrinsics.distortion,
        position_m: pose.camera_position_m,
        rotation_deg: pose.camera_rotation_deg,
    }
}

fn reprojection_rms(
    pose: &TablePose,
    corners: &[[f64; 2]],
    board: &Board,
    intr: &Intrinsics,
) -> f64 {
    let cam = camera(intr, pose);
    let [bx, by] = board.centre();
    let sum: f64 = board
        .object_points()
        .iter()
        .zip(corners)
        .map(|(p, q)| {
            let world = flip() * Vector3::new(p[0] - bx, p[1] - by, 0.0);
            match cam.project(&world) {
                Some((u, v)) => (u - q[0]).powi(2) + (v - q[1]).powi(2),
                None => f64::INFINITY,
            }
        })
        .sum();
    (sum / corners.len() as f64).sqrt()
}

/// `rig` with its camera replaced by the calibrated one (intrinsics in sensor pixels) and its
/// sample plane on the table.
pub fn calibrated_rig(rig: &Rig, sensor_intrinsics: &Intrinsics, pose: &TablePose) -> Rig {
    let mut out = rig.clone();
    out.camera = camera(sensor_intrinsics, pose);
    out
}

/// Largest and mean distance (m) between where two cameras put the same pixels on the table
/// plane, over an `n x n` grid of the sensor `window` of `width x height` image pixels.
pub fn pixel_to_world_error(
    a: &Camera,
    b: &Camera,
    plane_z: f64,
    window: SensorWindow,
    (width, height): (usize, usize),
    n: usize,
) -> (f64, f64) {
    let (ma, mb) = (a.plane_mapper(plane_z), b.plane_mapper(plane_z));
    let mut worst: f64 = 0.0;
    let mut sum = 0.0;
    for j in 0..n {
        for i in 0..n {
            let x = (width - 1) as f64 * i as f64 / (n - 1) as f64;
            let y = (height - 1) as f64 * j as f64 / (n - 1) as f64;
            let (u, v) = window.to_sensor(x, y);
            let d = match (ma.map(u, v), mb.map(u, v)) {
                (Some(p), Some(q)) => (p - q).norm(),
                _ => f64::INFINITY,
            };
            worst = worst.max(d);
            sum += d;
        }
    }
    (worst, sum / (n * n) as f64)
}
