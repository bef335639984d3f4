//! Camera intrinsics from chessboard photographs: corners found and refined by OpenCV,
//! `calibrateCamera` for the focal lengths, principal point and distortion, and automatic
//! rejection of views where the board is not found or whose reprojection error is an outlier
//! (a board that moved, bent, or was mis-detected), recalibrating after each rejection.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::cv::{self, PatternSize};
use crate::error::{Error, Result};
use crate::plane::{GrayImage, SensorWindow};
use crate::progress::Progress;
use crate::rig::Board;

/// A view whose RMS reprojection error is more than this many times the median of the views
/// is rejected: with every view seeing the same board through the same lens, errors differ
/// by noise and pose only, well within a factor of three (OpenCV's own sample set spans
/// 0.16-0.38 px around its one bad view at 1.18 px).
pub const OUTLIER_FACTOR: f64 = 3.0;

/// Fewer views than this cannot pin down focal length, principal point and distortion.
pub const MIN_VIEWS: usize = 4;

/// Pinhole intrinsics with OpenCV's distortion model, in the pixels of the images they were
/// measured on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Width of the images measured on, pixels.
    pub width: usize,
    /// Height of the images measured on, pixels.
    pub height: usize,
    /// Focal length along columns, pixels.
    pub fx: f64,
    /// Focal length along rows, pixels.
    pub fy: f64,
    /// Principal point's column, pixels.
    pub cx: f64,
    /// Principal point's row, pixels.
    pub cy: f64,
    /// k1 k2 p1 p2 k3.
    pub distortion: [f64; 5],
}

impl Intrinsics {
    /// The 3x3 camera matrix `K` in OpenCV's layout, rows outermost: `[[fx, 0, cx], [0, fy, cy],
    /// [0, 0, 1]]`.
    pub fn camera_matrix(&self) -> [[f64; 3]; 3] {
        [
            [self.fx, 0.0, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ]
    }

    /// The same lens in sensor pixels, for images that are `window` of a sensor (binned
    /// previews: image pixel `(x, y)` is sensor pixel `window.to_sensor(x, y)`). Distortion
    /// acts on normalised coordinates and is unchanged.
    pub fn to_sensor(&self, window: SensorWindow, sensor: (usize, usize)) -> Intrinsics {
        let (cx, cy) = window.to_sensor(self.cx, self.cy);
        Intrinsics {
            width: sensor.0,
            height: sensor.1,
            fx: self.fx * window.step,
            fy: self.fy * window.step,
            cx,
            cy,
            distortion: self.distortion,
        }
    }
}

/// One photograph's fate in the calibration.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewReport {
    /// The photograph's file name.
    pub name: String,
    /// Whether the final calibration used this view (`false`: no board found, or rejected as an
    /// outlier).
    pub used: bool,
    /// RMS reprojection error of this view in the last calibration that included it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rms_px: Option<f64>,
    /// Why the view was left out; `None` for a used view.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rejected_because: Option<String>,
}

/// The camera step's result.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CameraCalibration {
    /// The chessboard photographed.
    pub board: Board,
    /// The calibrated intrinsics, in the pixels of the photographs.
    pub intrinsics: Intrinsics,
    /// The 3x3 camera matrix as OpenCV returned it, rows outermost (the same numbers as
    /// `intrinsics`).
    pub camera_matrix: [[f64; 3]; 3],
    /// k1 k2 p1 p2 k3.
    pub distortion: [f64; 5],
    /// OpenCV's standard deviations of fx, fy, cx, cy, k1, k2, p1, p2, k3.
    pub std_dev: [f64; 9],
    /// RMS reprojection error over every corner of the used views (pixels).
    pub rms_reprojection_px: f64,
    /// Whether fx was held equal to fy.
    pub fix_aspect_ratio: bool,
    /// Views the final calibration used.
    pub views_used: usize,
    /// Views left out: no board found, or rejected as outliers.
    pub views_rejected: usize,
    /// Every photograph's fate, in the order given.
    pub views: Vec<ViewReport>,
}

/// A photograph with the corners found in it (`None`: no board).
#[derive(Clone, Debug)]
pub struct DetectedView {
    /// The photograph's file name.
    pub name: String,
    /// The board's inner corners in image pixels, row by row from the corner nearest the image's
    /// top left.
    pub corners: Option<Vec<[f64; 2]>>,
}

/// Finds the board in one photograph; `half_window` fixes the sub-pixel refinement's half
/// window (OpenCV's sample uses 11), `None` sizes it to the squares.
pub fn detect(
    name: &str,
    image: &GrayImage,
    board: &Board,
    half_window: Option<usize>,
) -> Result<DetectedView> {
    Ok(DetectedView {
        name: name.to_string(),
        corners: cv::find_corners(image, PatternSize::of(board), half_window)?,
    })
}

/// The photographs in `dir` (PNG, JPEG, TIFF), in name order.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let ext = p
                .extension()
                .and_then(|e| e.to_str())
                .unwrap_or("")
                .to_ascii_lowercase();
            matches!(ext.as_str(), "png" | "jpg" | "jpeg" | "tif" | "tiff")
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(Error::Invalid(format!(
            "{}: no PNG, JPEG or TIFF photographs in this folder",
            dir.display()
        )));
    }
    Ok(files)
}

/// Loads and searches every photograph; all must have the same size.
pub fn detect_files(
    files: &[PathBuf],
    board: &Board,
    half_window: Option<usize>,
    progress: &dyn Progress,
) -> Result<(Vec<DetectedView>, (usize, usize))> {
    // Fail on a build without OpenCV before decoding anything.
    if !cv::AVAILABLE {
        cv::find_corners(
            &GrayImage {
                width: 1,
                height: 1,
                data: vec![0],
            },
            PatternSize::of(board),
            None,
        )?;
    }
    progress.begin("corners", files.len() as u64);
    let mut size = None;
    let mut views = Vec::with_capacity(files.len());
    for path in files {
        let image = GrayImage::load(path)?;
        match size {
            None => size = Some((image.width, image.height)),
            Some(s) if s != (image.width, image.height) => {
                return Err(Error::image(
                    path,
                    format!(
                        "is {}x{} but the first photograph is {}x{}: one camera, one size",
                        image.width, image.height, s.0, s.1
                    ),
                ))
            }
            Some(_) => {}
        }
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        views.push(detect(&name, &image, board, half_window)?);
        progress.advance(1);
    }
    progress.end();
    Ok((views, size.expect("at least one file")))
}

/// How the camera is calibrated.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraOptions {
    /// Keep fx = fy (OpenCV's CALIB_FIX_ASPECT_RATIO with a unit ratio).
    pub fix_aspect_ratio: bool,
    /// Views worse than this many times the median error are rejected (infinity: never).
    pub outlier_factor: f64,
}

impl Default for CameraOptions {
    fn default() -> Self {
        CameraOptions {
            fix_aspect_ratio: false,
            outlier_factor: OUTLIER_FACTOR,
        }
    }
}

/// Calibrates from the views that show the board, rejecting outliers one at a time (the
/// worst first) and recalibrating, until every remaining view is within
/// `options.outlier_factor` of the median.
pub fn calibrate(
    views: &[DetectedView],
    board: &Board,
    size: (usize, usize),
    options: &CameraOptions,
) -> Result<CameraCalibration> {
    let fix_aspect_ratio = options.fix_aspect_ratio;
    let mut reports: Vec<ViewReport> = views
        .iter()
        .map(|v| ViewReport {
            name: v.name.clone(),
            used: v.corners.is_some(),
            rms_px: None,
            rejected_because: v.corners.is_none().then(|| {
                "the whole board was not found (out of frame, blurred, or too oblique)".to_string()
            }),
        })
        .collect();
    let object = board.object_points();
    loop {
        let used: Vec<usize> = (0..views.len()).filter(|&i| reports[i].used).collect();
        if used.len() < MIN_VIEWS {
            return Err(Error::Invalid(format!(
                "only {} of {} photographs are usable; calibration needs at least {MIN_VIEWS} views of the whole board",
                used.len(),
                views.len()
            )));
        }
        let corners: Vec<Vec<[f64; 2]>> = used
            .iter()
            .map(|&i| views[i].corners.clone().expect("used views have corners"))
            .collect();
        let raw = cv::calibrate(&object, &corners, size, fix_aspect_ratio)?;
        for (j, &i) in used.iter().enumerate() {
            reports[i].rms_px = raw.per_view_rms_px.get(j).copied();
        }
        if let Some((i, reason)) =
            worst_outlier(&used, &raw.per_view_rms_px, options.outlier_factor)
        {
            reports[i].used = false;
            reports[i].rejected_because = Some(reason);
            continue;
        }
        let k = raw.camera_matrix;
        let intrinsics = Intrinsics {
            width: size.0,
            height: size.1,
            fx: k[0][0],
            fy: k[1][1],
            cx: k[0][2],
            cy: k[1][2],
            distortion: raw.distortion,
        };
        return Ok(CameraCalibration {
            board: *board,
            intrinsics,
            camera_matrix: k,
            distortion: raw.distortion,
            std_dev: raw.std_dev,
            rms_reprojection_px: raw.rms_px,
            fix_aspect_ratio,
            views_used: used.len(),
            views_rejected: views.len() - used.len(),
            views: reports,
        });
    }
}

/// The worst view if it is an outlier, with the reason, as an index into the views.
fn worst_outlier(used: &[usize], errors: &[f64], factor: f64) -> Option<(usize, String)> {
    if used.len() <= MIN_VIEWS || errors.len() != used.len() {
        return None;
    }
    let median = median(errors);
    let (j, worst) = errors
        .iter()
        .copied()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    (worst > factor * median).then(|| {
        (
            used[j],
            format!(
                "reprojection error {worst:.3} px is {:.1}x the median {median:.3} px (limit {factor}x): the board moved, bent or was mis-detected",
                worst / median
            ),
        )
    })
}

fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Where in the frame the accepted views put corners: a `3 x 3` grid of the image, `true`
/// where some view had a corner. The wizard asks for the cells still empty.
pub fn coverage(views: &[DetectedView], size: (usize, usize)) -> [[bool; 3]; 3] {
    let mut cells = [[false; 3]; 3];
    for corners in views.iter().filter_map(|v| v.corners.as_ref()) {
        for p in corners {
            let cx = ((p[0] / size.0 as f64) * 3.0).clamp(0.0, 2.999) as usize;
            let cy = ((p[1] / size.1 as f64) * 3.0).clamp(0.0, 2.999) as usize;
            cells[cy][cx] = true;
        }
    }
    cells
}

/// Names of the uncovered cells ("top left", "centre", ...).
pub fn missing_regions(cells: &[[bool; 3]; 3]) -> Vec<&'static str> {
    const NAMES: [[&str; 3]; 3] = [
        ["top left", "top", "top right"],
        ["left", "centre", "right"],
        ["bottom left", "bottom", "bottom right"],
    ];
    let mut out = Vec::new();
    for y in 0..3 {
        for x in 0..3 {
            if !cells[y][x] {
                out.push(NAMES[y][x]);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn board_parsing_and_errors() {
        let b = Board::parse("9x6", 25.0).unwrap();
        assert_eq!((b.cols, b.rows), (9, 6));
        assert!((b.square_m - 0.025).abs() < 1e-15);
        assert_eq!(b.object_points().len(), 54);
        assert_eq!(b.object_points()[9], [0.0, 0.025, 0.0]);
        assert!(Board::parse("9by6", 25.0)
            .unwrap_err()
            .to_string()
            .contains("COLSxROWS"));
        assert!(Board::parse("2x6", 25.0).is_err());
        assert!(Board::parse("9x6", f64::NAN)
            .unwrap_err()
            .to_string()
            .contains("square size"));
    }

    #[test]
    fn the_worst_view_is_rejected_only_when_it_is_an_outlier() {
        let used = [0, 2, 3, 5, 7, 8];
        let calm = [0.2, 0.25, 0.18, 0.3, 0.22, 0.5];
        assert!(worst_outlier(&used, &calm, OUTLIER_FACTOR).is_none());
        let bad = [0.2, 0.25, 0.18, 1.2, 0.22, 0.21];
        let (i, reason) = worst_outlier(&used, &bad, OUTLIER_FACTOR).unwrap();
        assert_eq!(i, 5);
        assert!(reason.contains("1.200 px"), "{reason}");
        // With only the minimum number of views left nothing more is rejected.
        assert!(worst_outlier(&used[..4], &bad[..4], OUTLIER_FACTOR).is_none());
    }

    #[test]
    fn coverage_names_the_empty_regions() {
        let view = DetectedView {
            name: "a".into(),
            corners: Some(vec![[10.0, 10.0], [50.0, 50.0], [95.0, 95.0]]),
        };
        let cells = coverage(&[view], (100, 100));
        let missing = missing_regions(&cells);
        assert_eq!(missing.len(), 6);
        assert!(missing.contains(&"top right") && !missing.contains(&"centre"));
    }

    #[test]
    fn sensor_intrinsics_of_a_binned_preview() {
        let i = Intrinsics {
            width: 616,
            height: 408,
            fx: 915.0,
            fy: 916.0,
            cx: 307.5,
            cy: 203.5,
            distortion: [0.1, 0.0, 0.0, 0.0, 0.0],
        };
        let w = SensorWindow::centred(4928, 3264, 616, 408, 8.0);
        let s = i.to_sensor(w, (4928, 3264));
        assert_eq!((s.fx, s.fy), (7320.0, 7328.0));
        assert!((s.cx - 2463.5).abs() < 1e-9 && (s.cy - 1631.5).abs() < 1e-9);
    }

    #[cfg(not(feature = "opencv"))]
    #[test]
    fn without_opencv_the_camera_step_says_so() {
        let image = GrayImage {
            width: 4,
            height: 4,
            data: vec![0; 16],
        };
        let board = Board::parse("9x6", 25.0).unwrap();
        let err = detect("x", &image, &board, None).unwrap_err().to_string();
        assert!(
            err.contains("without OpenCV") && err.contains("--features opencv"),
            "{err}"
        );
    }
}
