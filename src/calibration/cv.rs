//! The OpenCV boundary: chessboard corner detection with sub-pixel refinement,
//! `calibrateCameraExtended` and `solvePnP`. Everything that touches OpenCV types is here;
//! without the `opencv` feature each call says the binary was built without it.

#[cfg(not(feature = "opencv"))]
use crate::error::{Error, Result};
#[cfg(not(feature = "opencv"))]
use crate::plane::GrayImage;

/// Inner-corner count of a chessboard target (`cols x rows`, OpenCV's pattern size).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PatternSize {
    pub cols: usize,
    pub rows: usize,
}

impl PatternSize {
    /// The inner-corner pattern of a chessboard target.
    pub fn of(board: &crate::rig::Board) -> PatternSize {
        PatternSize {
            cols: board.cols,
            rows: board.rows,
        }
    }
}

/// What `calibrateCameraExtended` returns, in plain numbers.
#[derive(Clone, Debug)]
pub struct RawCalibration {
    pub rms_px: f64,
    pub camera_matrix: [[f64; 3]; 3],
    pub distortion: [f64; 5],
    /// Standard deviations of fx, fy, cx, cy, k1, k2, p1, p2, k3.
    pub std_dev: [f64; 9],
    pub per_view_rms_px: Vec<f64>,
}

/// A board pose from `solvePnP`: board points `b` are at `R b + t` in the camera frame.
#[derive(Clone, Debug)]
pub struct RawPose {
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

#[cfg(not(feature = "opencv"))]
fn not_built() -> Error {
    Error::Unsupported(
        "this psscan was built without OpenCV; camera and table calibration need it: rebuild with \
         `cargo build --release --features opencv` (needs libopencv-dev, clang, libclang-dev)"
            .into(),
    )
}

#[cfg(not(feature = "opencv"))]
pub fn find_corners(
    _image: &GrayImage,
    _pattern: PatternSize,
    _half_window: Option<usize>,
) -> Result<Option<Vec<[f64; 2]>>> {
    Err(not_built())
}

#[cfg(not(feature = "opencv"))]
pub fn calibrate(
    _object: &[[f64; 3]],
    _views: &[Vec<[f64; 2]>],
    _size: (usize, usize),
    _fix_aspect_ratio: bool,
) -> Result<RawCalibration> {
    Err(not_built())
}

#[cfg(not(feature = "opencv"))]
pub fn solve_pnp(
    _object: &[[f64; 3]],
    _image: &[[f64; 2]],
    _camera_matrix: &[[f64; 3]; 3],
    _distortion: &[f64; 5],
) -> Result<RawPose> {
    Err(not_built())
}

/// True when this binary can calibrate cameras.
pub const AVAILABLE: bool = cfg!(feature = "opencv");

#[cfg(feature = "opencv")]
pub use with_opencv::{calibrate, find_corners, solve_pnp};

#[cfg(feature = "opencv")]
mod with_opencv {
    use opencv::calib3d;
    use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vector};
    use opencv::imgproc;
    use opencv::prelude::*;

    use super::{PatternSize, RawCalibration, RawPose};
    use crate::error::{Error, Result};
    use crate::plane::GrayImage;

    fn cv(context: &str) -> impl Fn(opencv::Error) -> Error + '_ {
        move |e| Error::Invalid(format!("OpenCV {context}: {e}"))
    }

    fn criteria(count: i32, eps: f64) -> Result<TermCriteria> {
        TermCriteria::new(
            i32::from(TermCriteria_Type::COUNT) + i32::from(TermCriteria_Type::EPS),
            count,
            eps,
        )
        .map_err(cv("TermCriteria"))
    }

    /// The chessboard's inner corners, refined to sub-pixel precision, row by row starting at
    /// the corner nearest the image's top left; `None` when the whole board is not found.
    pub fn find_corners(
        image: &GrayImage,
        pattern: PatternSize,
        half_window: Option<usize>,
    ) -> Result<Option<Vec<[f64; 2]>>> {
        let mat =
            Mat::new_rows_cols_with_data(image.height as i32, image.width as i32, &image.data)
                .map_err(cv("image"))?
                .try_clone()
                .map_err(cv("image"))?;
        let size = Size::new(pattern.cols as i32, pattern.rows as i32);
        // OpenCV's detector slows down sharply with image size (minutes for a 1-megapixel
        // photograph without a board): search a copy at most DETECT_SIZE px across, then
        // refine at full resolution.
        let scale = (DETECT_SIZE / image.width.max(image.height) as f64).min(1.0);
        let mut small = Mat::default();
        let search: &Mat = if scale < 1.0 {
            imgproc::resize(
                &mat,
                &mut small,
                Size::new(0, 0),
                scale,
                scale,
                imgproc::INTER_AREA,
            )
            .map_err(cv("resize"))?;
            &small
        } else {
            &mat
        };
        let mut corners = Vector::<Point2f>::new();
        // The flags and refinement of OpenCV's own calibration sample (calibration.cpp).
        let flags = calib3d::CALIB_CB_ADAPTIVE_THRESH
            | calib3d::CALIB_CB_NORMALIZE_IMAGE
            | calib3d::CALIB_CB_FAST_CHECK;
        let found = calib3d::find_chessboard_corners(search, size, &mut corners, flags)
            .map_err(cv("findChessboardCorners"))?;
        if !found || corners.len() != pattern.cols * pattern.rows {
            return Ok(None);
        }
        if scale < 1.0 {
            // Pixel centres at integer coordinates in both images.
            let back = |v: f32| ((v as f64 + 0.5) / scale - 0.5) as f32;
            corners = corners
                .iter()
                .map(|p| Point2f::new(back(p.x), back(p.y)))
                .collect();
        }
        // The refinement window (half size) must stay inside one square: 11 px as in OpenCV's
        // sample, less for small squares (a window that reaches the next corner pulls this one
        // toward it), unless the caller fixes it.
        let spacing = min_spacing(&corners);
        let half = ((0.4 * spacing).floor() as i32).clamp(2, 11);
        let half = half_window.map(|h| h as i32).unwrap_or(half);
        imgproc::corner_sub_pix(
            &mat,
            &mut corners,
            Size::new(half, half),
            Size::new(-1, -1),
            criteria(30, 1e-4)?,
        )
        .map_err(cv("cornerSubPix"))?;
        let mut points: Vec<[f64; 2]> = corners.iter().map(|p| [p.x as f64, p.y as f64]).collect();
        let (first, last) = (points[0], points[points.len() - 1]);
        if (last[0] - first[0]) + (last[1] - first[1]) < 0.0 {
            // OpenCV may start at either end; reversing a row-major grid turns it by 180 degrees.
            points.reverse();
        }
        Ok(Some(points))
    }

    /// Longest side of the image the detector searches.
    const DETECT_SIZE: f64 = 800.0;

    fn min_spacing(corners: &Vector<Point2f>) -> f64 {
        let pts: Vec<Point2f> = corners.iter().collect();
        pts.windows(2)
            .map(|w| ((w[1].x - w[0].x) as f64).hypot((w[1].y - w[0].y) as f64))
            .fold(f64::MAX, f64::min)
    }

    fn object_vector(object: &[[f64; 3]]) -> Vector<Point3f> {
        object
            .iter()
            .map(|p| Point3f::new(p[0] as f32, p[1] as f32, p[2] as f32))
            .collect()
    }

    fn image_vector(points: &[[f64; 2]]) -> Vector<Point2f> {
        points
            .iter()
            .map(|p| Point2f::new(p[0] as f32, p[1] as f32))
            .collect()
    }

    fn mat3(m: &Mat) -> Result<[[f64; 3]; 3]> {
        let mut out = [[0.0; 3]; 3];
        for (r, row) in out.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = *m.at_2d::<f64>(r as i32, c as i32).map_err(cv("matrix"))?;
            }
        }
        Ok(out)
    }

    fn column(m: &Mat, n: usize) -> Result<Vec<f64>> {
        let total = m.total();
        (0..n.min(total))
            .map(|i| m.at::<f64>(i as i32).copied().map_err(cv("vector")))
            .collect()
    }

    pub fn calibrate(
        object: &[[f64; 3]],
        views: &[Vec<[f64; 2]>],
        size: (usize, usize),
        fix_aspect_ratio: bool,
    ) -> Result<RawCalibration> {
        let object_points: Vector<Vector<Point3f>> =
            views.iter().map(|_| object_vector(object)).collect();
        let image_points: Vector<Vector<Point2f>> = views.iter().map(|v| image_vector(v)).collect();
        // With CALIB_FIX_ASPECT_RATIO OpenCV keeps the input's fx/fy: start from the identity.
        let mut camera_matrix = Mat::eye(3, 3, opencv::core::CV_64F)
            .map_err(cv("eye"))?
            .to_mat()
            .map_err(cv("eye"))?;
        let mut distortion = Mat::default();
        let mut rvecs = Vector::<Mat>::new();
        let mut tvecs = Vector::<Mat>::new();
        let mut std_intrinsics = Mat::default();
        let mut std_extrinsics = Mat::default();
        let mut per_view = Mat::default();
        let flags = if fix_aspect_ratio {
            calib3d::CALIB_FIX_ASPECT_RATIO
        } else {
            0
        };
        let rms = calib3d::calibrate_camera_extended(
            &object_points,
            &image_points,
            Size::new(size.0 as i32, size.1 as i32),
            &mut camera_matrix,
            &mut distortion,
            &mut rvecs,
            &mut tvecs,
            &mut std_intrinsics,
            &mut std_extrinsics,
            &mut per_view,
            flags,
            criteria(30, f64::EPSILON)?,
        )
        .map_err(cv("calibrateCameraExtended"))?;
        let dist = column(&distortion, 5)?;
        let std = column(&std_intrinsics, 9)?;
        Ok(RawCalibration {
            rms_px: rms,
            camera_matrix: mat3(&camera_matrix)?,
            distortion: std::array::from_fn(|i| dist.get(i).copied().unwrap_or(0.0)),
            std_dev: std::array::from_fn(|i| std.get(i).copied().unwrap_or(0.0)),
            per_view_rms_px: column(&per_view, views.len())?,
        })
    }

    pub fn solve_pnp(
        object: &[[f64; 3]],
        image: &[[f64; 2]],
        camera_matrix: &[[f64; 3]; 3],
        distortion: &[f64; 5],
    ) -> Result<RawPose> {
        let k = Mat::from_slice_2d(camera_matrix).map_err(cv("camera matrix"))?;
        let d = Mat::from_slice(distortion)
            .map_err(cv("distortion"))?
            .try_clone()
            .map_err(cv("distortion"))?;
        let mut rvec = Mat::default();
        let mut tvec = Mat::default();
        let ok = calib3d::solve_pnp(
            &object_vector(object),
            &image_vector(image),
            &k,
            &d,
            &mut rvec,
            &mut tvec,
            false,
            calib3d::SOLVEPNP_ITERATIVE,
        )
        .map_err(cv("solvePnP"))?;
        if !ok {
            return Err(Error::Invalid(
                "solvePnP found no pose for the board".into(),
            ));
        }
        let mut rotation = Mat::default();
        calib3d::rodrigues_def(&rvec, &mut rotation).map_err(cv("Rodrigues"))?;
        let t = column(&tvec, 3)?;
        Ok(RawPose {
            rotation: mat3(&rotation)?,
            translation: [t[0], t[1], t[2]],
        })
    }
}
