//! Calibration targets as the rig's camera photographs them, with known answers: a printed
//! chessboard at any pose (optionally bent), photographed through a camera with known
//! intrinsics and distortion, with supersampled edges, lens blur and sensor noise; and flat
//! targets lying on the table (the white sheet, the gray chart) lit by each LED.

use nalgebra::{Matrix3, Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;
use rayon::prelude::*;

mod blur;
mod flat;

use blur::gaussian_blur;

pub use flat::{
    flat_target_frames, gray_chart, gray_chart_mosaics, render_flat_target, white_sheet,
    white_sheet_frames,
};

use crate::plane::{GrayImage, RgbPlanes, SensorWindow};
use crate::rig::{Board, Camera, Rig};

/// A printed chessboard: the calibration's [`Board`] plus a white border of `border_squares`
/// squares around the pattern.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chessboard {
    /// The pattern: inner corners and square size.
    pub board: Board,
    /// Width of the white paper border around the squares, in squares.
    pub border_squares: f64,
}

impl Chessboard {
    /// The inner corners in the board frame (metres), row by row, as the calibration expects them.
    pub fn object_points(&self) -> Vec<[f64; 3]> {
        self.board.object_points()
    }

    /// Centre of the inner-corner grid in the board frame (metres).
    pub fn centre(&self) -> [f64; 2] {
        self.board.centre()
    }

    /// Print reflectance at board point `(x, y)`; `None` off the paper.
    fn reflectance(&self, x: f64, y: f64) -> Option<f64> {
        let s = self.board.square_m;
        let (cols, rows) = (self.board.cols as f64, self.board.rows as f64);
        let (a, b) = ((x / s).floor() + 1.0, (y / s).floor() + 1.0);
        let inside_squares = a >= 0.0 && b >= 0.0 && a <= cols && b <= rows;
        if inside_squares {
            let black = (a as i64 + b as i64) % 2 == 0;
            return Some(if black { 0.04 } else { 0.85 });
        }
        let m = self.border_squares * s;
        let on_paper = x >= -s - m && y >= -s - m && x <= cols * s + m && y <= rows * s + m;
        on_paper.then_some(0.85)
    }
}

/// Where a board is, seen from the camera: board-frame points `b` are at `rotation * b +
/// translation` in the camera frame (OpenCV's x right, y down, z forward). `bend` curves the
/// board about its y axis (1/m): the surface is at `z = -bend * (x - xc)^2 / 2`, a board that
/// is not flat.
#[derive(Clone, Copy, Debug)]
pub struct BoardPose {
    /// The board's orientation in the camera frame.
    pub rotation: Rotation3<f64>,
    /// Where the board frame's origin lies in the camera frame (metres).
    pub translation: Vector3<f64>,
    /// Curvature of the board about its y axis (1/m; 0: flat).
    pub bend: f64,
}

impl BoardPose {
    /// A board whose corner-grid centre is at `centre` (camera frame), tilted by `tilt_x`,
    /// `tilt_y` (radians, about the camera's x and y) and turned by `turn` about the view axis.
    pub fn facing_camera(
        board: &Chessboard,
        centre: Vector3<f64>,
        tilt_x: f64,
        tilt_y: f64,
        turn: f64,
    ) -> Self {
        let rotation = Rotation3::from_euler_angles(tilt_x, tilt_y, turn);
        let [cx, cy] = board.centre();
        let translation = centre - rotation * Vector3::new(cx, cy, 0.0);
        BoardPose {
            rotation,
            translation,
            bend: 0.0,
        }
    }

    /// The board lying flat on the table of `rig`, its corner grid centred on the world
    /// origin, its rows along world +x and its columns along world -y (so it reads the right
    /// way up in the image): the calibration's world frame is defined by this board.
    pub fn on_table(board: &Chessboard, rig: &Rig) -> Self {
        let world_from_board = board_to_world();
        let [cx, cy] = board.centre();
        let camera_from_world = rig.camera.world_from_camera().transpose();
        let world_origin_offset =
            world_from_board * Vector3::new(-cx, -cy, 0.0) + Vector3::new(0.0, 0.0, rig.sample.z_m);
        let rotation = camera_from_world * world_from_board;
        let translation = camera_from_world * (world_origin_offset - rig.camera.centre());
        BoardPose {
            rotation: Rotation3::from_matrix_unchecked(rotation),
            translation,
            bend: 0.0,
        }
    }
}

/// Board frame (x along rows, y down columns, z into the board) to world axes (x, y up the
/// image, z up): a half turn about x.
pub fn board_to_world() -> Matrix3<f64> {
    Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
}

/// How a chessboard photograph is rendered.
#[derive(Clone, Copy, Debug)]
pub struct ViewRender {
    /// Sub-samples per pixel side (anti-aliased edges as a real sensor integrates them).
    pub supersample: usize,
    /// Gaussian lens blur in pixels.
    pub blur_px: f64,
    /// Gaussian noise in 8-bit levels.
    pub noise_levels: f64,
    /// Seed of the sensor noise.
    pub seed: u64,
    /// 8-bit level of a white print.
    pub white: f64,
    /// 8-bit level where the camera sees past the board (the room, the table).
    pub background: f64,
}

impl Default for ViewRender {
    fn default() -> Self {
        ViewRender {
            supersample: 3,
            blur_px: 0.7,
            noise_levels: 2.0,
            seed: 1,
            white: 220.0,
            background: 90.0,
        }
    }
}

/// The camera ray (undistorted normalised coordinates) of every sub-sample of every pixel of
/// a `width x height` image through `window`: computed once, shared by all views of a set
/// (inverting the distortion is the expensive part of rendering).
pub struct RayGrid {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Sub-samples per pixel side; each pixel holds `supersample^2` rays.
    pub supersample: usize,
    rays: Vec<[f32; 2]>,
}

impl RayGrid {
    /// Computes the rays of every sub-sample of a `width x height` image that sits at `window` on
    /// `camera`'s sensor, undoing the lens distortion (`supersample` below 1 is taken as 1).
    pub fn new(
        camera: &Camera,
        window: SensorWindow,
        width: usize,
        height: usize,
        supersample: usize,
    ) -> Self {
        let n = supersample.max(1);
        let mut rays = vec![[0.0f32; 2]; width * height * n * n];
        rays.par_chunks_mut(width * n * n)
            .enumerate()
            .for_each(|(y, row)| {
                for x in 0..width {
                    for sy in 0..n {
                        for sx in 0..n {
                            let u = x as f64 + (sx as f64 + 0.5) / n as f64 - 0.5;
                            let v = y as f64 + (sy as f64 + 0.5) / n as f64 - 0.5;
                            let (su, sv) = window.to_sensor(u, v);
                            let (rx, ry) = camera.undistort_normalized(
                                (su - camera.cx) / camera.fx,
                                (sv - camera.cy) / camera.fy,
                            );
                            row[(x * n + sy) * n + sx] = [rx as f32, ry as f32];
                        }
                    }
                }
            });
        RayGrid {
            width,
            height,
            supersample: n,
            rays,
        }
    }
}

/// Renders the 8-bit grayscale photograph of `board` at `pose` through the camera rays of
/// `grid` (`render.supersample` is the grid's).
pub fn render_chessboard(
    grid: &RayGrid,
    board: &Chessboard,
    pose: &BoardPose,
    render: &ViewRender,
) -> GrayImage {
    let (width, height, n) = (grid.width, grid.height, grid.supersample);
    let mut linear = vec![0.0f32; width * height];
    linear
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, value) in row.iter_mut().enumerate() {
                let start = (y * width + x) * n * n;
                let sum: f64 = grid.rays[start..start + n * n]
                    .iter()
                    .map(|r| sample_board(board, pose, render, r[0] as f64, r[1] as f64))
                    .sum();
                *value = (sum / (n * n) as f64) as f32;
            }
        });
    let blurred = gaussian_blur(&linear, width, height, render.blur_px);
    let data = blurred
        .par_chunks(width)
        .enumerate()
        .flat_map_iter(|(y, row)| {
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(
                render.seed ^ (y as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
            );
            row.iter()
                .map(move |&v| {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    (v as f64 + render.noise_levels * z)
                        .round()
                        .clamp(0.0, 255.0) as u8
                })
                .collect::<Vec<_>>()
        })
        .collect();
    GrayImage {
        width,
        height,
        data,
    }
}

/// 8-bit level seen along the camera ray through normalised point `(x, y)`.
fn sample_board(board: &Chessboard, pose: &BoardPose, render: &ViewRender, x: f64, y: f64) -> f64 {
    let ray = Vector3::new(x, y, 1.0);
    let normal = pose.rotation * Vector3::z();
    let xc = board.centre()[0];
    // Fixed point on the bent surface: intersect the plane shifted to the current height.
    let mut bz = 0.0;
    let mut point = None;
    for _ in 0..4 {
        let origin = pose.translation + pose.rotation * Vector3::new(0.0, 0.0, bz);
        let denom = normal.dot(&ray);
        if denom.abs() < 1e-12 {
            return render.background;
        }
        let t = normal.dot(&origin) / denom;
        if t <= 0.0 {
            return render.background;
        }
        let b = pose.rotation.inverse() * (ray * t - pose.translation);
        point = Some(b);
        if pose.bend == 0.0 {
            break;
        }
        bz = -0.5 * pose.bend * (b.x - xc).powi(2);
    }
    let b = point.expect("at least one iteration");
    match board.reflectance(b.x, b.y) {
        Some(r) => render.white * r / 0.85,
        None => render.background,
    }
}

/// Reflectance of the table around a held or lying target (a mid-gray work surface).
pub const TABLE_REFLECTANCE: f64 = 0.3;

/// The chessboard at `pose` photographed through `grid` on `rig` (the rig as built) with LEDs
/// `lit` on: linear RGB, 1.0 = the white level at `exposure`. Each board point is lit by
/// every lit LED (inverse square, beam, incidence on the board); past the board the camera
/// sees the table, lit the same way (the board's shadow on it is not modelled: only the board
/// is measured). Lens blur as in [`render_chessboard`]; the sensor adds the noise. With no LED
/// on the frame is black, as a real one is.
pub fn render_chessboard_lit(
    rig: &Rig,
    grid: &RayGrid,
    board: &Chessboard,
    pose: &BoardPose,
    lit: &[usize],
    exposure: f64,
    blur_px: f64,
) -> RgbPlanes {
    let (width, height, n) = (grid.width, grid.height, grid.supersample);
    let world_from_camera = rig.camera.world_from_camera();
    let eye = rig.camera.centre();
    let scales: Vec<[f64; 3]> = lit
        .iter()
        .map(|&k| {
            rig.led_rgb_power(k)
                .map(|c| c / rig.leds[k].power * exposure)
        })
        .collect();
    // The radiance (times the exposure) of a Lambertian point with `normal` and `rho`.
    let shade = |point: &Vector3<f64>, normal: &Vector3<f64>, rho: f64| -> [f64; 3] {
        let mut out = [0.0; 3];
        for (&k, scale) in lit.iter().zip(&scales) {
            let s = rig.leds[k].sample_at(point);
            let cos = normal.dot(&s.direction).max(0.0);
            for c in 0..3 {
                out[c] += s.falloff * cos * scale[c] * rho;
            }
        }
        out
    };
    let table = Vector3::z();
    let mut planes = [
        vec![0.0f32; width * height],
        vec![0.0f32; width * height],
        vec![0.0f32; width * height],
    ];
    let [r, g, b] = &mut planes;
    r.par_chunks_mut(width)
        .zip(g.par_chunks_mut(width))
        .zip(b.par_chunks_mut(width))
        .enumerate()
        .for_each(|(y, ((r, g), b))| {
            for x in 0..width {
                let start = (y * width + x) * n * n;
                let mut sum = [0.0f64; 3];
                for ray in &grid.rays[start..start + n * n] {
                    let ray = Vector3::new(ray[0] as f64, ray[1] as f64, 1.0);
                    let world_ray = world_from_camera * ray;
                    let value = match board_hit(board, pose, &ray) {
                        Some((t, normal, Some(rho))) => {
                            let point = eye + world_ray * t;
                            // The face toward the camera.
                            let mut normal = world_from_camera * normal;
                            if normal.dot(&(eye - point)) < 0.0 {
                                normal = -normal;
                            }
                            shade(&point, &normal, rho)
                        }
                        _ if world_ray.z < 0.0 => {
                            let t = (rig.sample.z_m - eye.z) / world_ray.z;
                            shade(&(eye + world_ray * t), &table, TABLE_REFLECTANCE)
                        }
                        _ => [0.0; 3],
                    };
                    for c in 0..3 {
                        sum[c] += value[c];
                    }
                }
                let norm = 1.0 / (n * n) as f64;
                r[x] = (sum[0] * norm) as f32;
                g[x] = (sum[1] * norm) as f32;
                b[x] = (sum[2] * norm) as f32;
            }
        });
    let mut out = RgbPlanes::new(width, height);
    for (plane, data) in [&mut out.r, &mut out.g, &mut out.b].into_iter().zip(planes) {
        plane.data = gaussian_blur(&data, width, height, blur_px);
    }
    out
}

/// Where the camera ray `ray` (camera frame, z = 1) meets the board: the ray parameter, the
/// board's normal there (camera frame) and the print's reflectance (`None` off the paper);
/// `None` when the ray misses the board's plane.
fn board_hit(
    board: &Chessboard,
    pose: &BoardPose,
    ray: &Vector3<f64>,
) -> Option<(f64, Vector3<f64>, Option<f64>)> {
    let normal = pose.rotation * Vector3::z();
    let xc = board.centre()[0];
    let mut bz = 0.0;
    let mut hit = None;
    for _ in 0..4 {
        let origin = pose.translation + pose.rotation * Vector3::new(0.0, 0.0, bz);
        let denom = normal.dot(ray);
        if denom.abs() < 1e-12 {
            return None;
        }
        let t = normal.dot(&origin) / denom;
        if t <= 0.0 {
            return None;
        }
        let b = pose.rotation.inverse() * (ray * t - pose.translation);
        hit = Some((t, b));
        if pose.bend == 0.0 {
            break;
        }
        bz = -0.5 * pose.bend * (b.x - xc).powi(2);
    }
    let (t, b) = hit?;
    // The bent surface's normal tilts by its slope -bend * (x - xc) along board x.
    let slope = -pose.bend * (b.x - xc);
    let local = Vector3::new(-slope, 0.0, 1.0).normalize();
    Some((t, pose.rotation * local, board.reflectance(b.x, b.y)))
}

/// A set of calibration views: the board held at varied distances, tilts and turns, its
/// centre swept over a grid of image positions so the corners cover the whole frame (what
/// the wizard asks the operator for). `distance_m` is the camera-to-board distance.
pub fn calibration_poses(
    board: &Chessboard,
    camera: &Camera,
    window: SensorWindow,
    (width, height): (usize, usize),
    count: usize,
    distance_m: f64,
    seed: u64,
) -> Vec<BoardPose> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    // Image positions on a 3 x 3 grid (then again with other tilts), inset from the edges.
    (0..count)
        .map(|i| {
            let cell = i % 9;
            let (gx, gy) = ((cell % 3) as f64, (cell / 3) as f64);
            let px = width as f64 * (0.27 + 0.23 * gx);
            let py = height as f64 * (0.3 + 0.2 * gy);
            let (su, sv) = window.to_sensor(px, py);
            let z = distance_m * rng.gen_range(0.85..1.05);
            let centre = Vector3::new(
                (su - camera.cx) / camera.fx * z,
                (sv - camera.cy) / camera.fy * z,
                z,
            );
            let tilt = 0.7f64;
            let tilt_x = rng.gen_range(-tilt..tilt);
            let tilt_y = rng.gen_range(-tilt..tilt);
            let turn = rng.gen_range(-0.3..0.3);
            BoardPose::facing_camera(board, centre, tilt_x, tilt_y, turn)
        })
        .collect()
}

/// Photographs of a chessboard for the camera step, as the wizard would collect them.
pub struct ViewSet {
    /// File-style names and images.
    pub images: Vec<(String, GrayImage)>,
    /// Where the images sit on the sensor (the whole sensor binned by the rendering step).
    pub window: SensorWindow,
    /// Image size in pixels, `(width, height)`.
    pub size: (usize, usize),
}

/// Renders `good` well-posed views plus, when `with_bad` is set, one with the board half out of
/// the frame (`view-off-image`, which the detector cannot use) and one with the board bent
/// (`view-bent`, which must come out as an outlier). Images are the whole sensor binned by
/// `step`.
pub fn chessboard_views(
    rig: &Rig,
    board: &Chessboard,
    step: f64,
    good: usize,
    with_bad: bool,
    seed: u64,
) -> ViewSet {
    let (w, h) = binned_size(rig, step);
    let window = SensorWindow::centred(
        rig.camera.width as usize,
        rig.camera.height as usize,
        w,
        h,
        step,
    );
    let distance = rig.camera.position_m[2] - rig.sample.z_m;
    let mut poses: Vec<(String, BoardPose)> = calibration_poses(
        board,
        &rig.camera,
        window,
        (w, h),
        good,
        0.85 * distance,
        seed,
    )
    .into_iter()
    .enumerate()
    .map(|(i, p)| (format!("view-{i:02}"), p))
    .collect();
    if with_bad {
        let cam = &rig.camera;
        let z = 0.85 * distance;
        let (su, sv) = window.to_sensor(w as f64 * 0.97, h as f64 * 0.5);
        let edge = Vector3::new((su - cam.cx) / cam.fx * z, (sv - cam.cy) / cam.fy * z, z);
        poses.push((
            "view-off-image".into(),
            BoardPose::facing_camera(board, edge, 0.1, -0.2, 0.1),
        ));
        let (su, sv) = window.to_sensor(w as f64 * 0.5, h as f64 * 0.5);
        let centre = Vector3::new((su - cam.cx) / cam.fx * z, (sv - cam.cy) / cam.fy * z, z);
        let mut bent = BoardPose::facing_camera(board, centre, 0.3, -0.25, 0.2);
        bent.bend = 2.0;
        poses.push(("view-bent".into(), bent));
    }
    let grid = RayGrid::new(&rig.camera, window, w, h, ViewRender::default().supersample);
    let images = poses
        .iter()
        .enumerate()
        .map(|(i, (name, pose))| {
            let render = ViewRender {
                seed: seed.wrapping_add(1000 + i as u64),
                ..ViewRender::default()
            };
            (name.clone(), render_chessboard(&grid, board, pose, &render))
        })
        .collect();
    ViewSet {
        images,
        window,
        size: (w, h),
    }
}

/// The board lying on the table, photographed through the same binned window.
pub fn table_view(rig: &Rig, board: &Chessboard, step: f64, seed: u64) -> GrayImage {
    let (w, h) = binned_size(rig, step);
    let window = SensorWindow::centred(
        rig.camera.width as usize,
        rig.camera.height as usize,
        w,
        h,
        step,
    );
    let render = ViewRender {
        seed,
        ..ViewRender::default()
    };
    let grid = RayGrid::new(&rig.camera, window, w, h, render.supersample);
    render_chessboard(&grid, board, &BoardPose::on_table(board, rig), &render)
}

/// Image size of the whole sensor taken every `step` pixels.
pub fn binned_size(rig: &Rig, step: f64) -> (usize, usize) {
    rig.camera.binned_size(step)
}

/// The rig as it was actually built, for calibration tests: the lens's real focal lengths,
/// principal point and distortion, a camera slightly tilted and off centre, and every LED up
/// to `led_error_m` away from where `hand` (the hand measurements) puts it, each a little
/// brighter or dimmer. Seeded.
pub fn as_built(hand: &Rig, led_error_m: f64, seed: u64) -> Rig {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut rig = hand.clone();
    let c = &mut rig.camera;
    c.fx *= 1.004;
    c.fy *= 1.0025;
    c.cx += 14.3;
    c.cy -= 10.6;
    c.distortion = [-0.06, 0.09, 0.0004, -0.0003, 0.0];
    c.position_m = [0.0021, -0.0014, c.position_m[2] + 0.0035];
    c.rotation_deg = [0.35, -0.28, 0.9];
    for led in &mut rig.leds {
        // A random direction, and a length between 60 % and 100 % of the limit.
        let dir = loop {
            let v = Vector3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            );
            if v.norm() > 0.2 && v.norm() <= 1.0 {
                break v.normalize();
            }
        };
        let length = led_error_m * rng.gen_range(0.6..1.0);
        for i in 0..3 {
            led.position_m[i] += dir[i] * length;
        }
        led.power *= rng.gen_range(0.9..1.1);
    }
    rig
}

#[cfg(test)]
mod tests;
