//! Each calibration step over photographs in files, as `psscan calibrate <step>` runs it, and
//! the bundle assembled from the steps' results. Every step's result is a plain value written
//! as TOML by the CLI; the bundle step reads them back, checks they fit together, and writes
//! the bundle once, whole (its checksum then never changes: captures cite it).

use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::bundle::{self, BundleIndex, Calibration, Parts};
use super::camera::CameraCalibration;
use super::files;
use super::graychart::{self, ChartReport, Shading};
use super::lights::{self, LightFit};
use super::table::{self, TablePose};
use super::whitesheet::{self, SheetLight};
use crate::error::{Conflict, Error, Result};
use crate::plane::{Frames, GrayImage, Plane};
use crate::progress::Progress;
use crate::raw::Levels;
use crate::rig::Board;
use crate::rig::Rig;
use crate::rig::{ChartDescription, ChartRect};
use crate::solve::{GainGrid, NoiseModel};

/// Reads a step's TOML result, naming the file in errors.
pub fn load_toml<T: serde::de::DeserializeOwned>(path: &Path, what: &str) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    toml::from_str(&text).map_err(|e| {
        Error::config(
            path,
            what,
            format!(
                "{} (expected the TOML `psscan calibrate {what} --out` writes)",
                e.message()
            ),
        )
    })
}

/// How far the table pose puts each detected board corner from where the board says it is
/// on the table: the pixel-to-world error of this photograph, in millimetres.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PixelToWorldCheck {
    /// Board corners detected and checked.
    pub corners: usize,
    /// Mean distance between where the pose maps a corner on the table and where it is (mm).
    pub mean_mm: f64,
    /// Largest such distance (mm); infinite when a corner's camera ray misses the table plane.
    pub max_mm: f64,
    /// Extent of the corner grid on the table (the area the check covers), mm.
    pub area_mm: [f64; 2],
}

/// The table step's result (`table.toml`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TableStep {
    /// The photograph of the board on the table.
    pub image: PathBuf,
    /// The chessboard photographed.
    pub board: Board,
    /// The camera's position and rotation over the table, found from the board's corners.
    pub pose: TablePose,
    /// How far the pose maps the board's corners from their places on the table.
    pub check: PixelToWorldCheck,
}

/// The board lying flat on the table, photographed with the camera the camera step
/// calibrated (same image size): the table's pose and its pixel-to-world check.
pub fn table_from_file(
    path: &Path,
    board: &Board,
    camera: &CameraCalibration,
) -> Result<TableStep> {
    let image = GrayImage::load(path)?;
    let intr = &camera.intrinsics;
    if (image.width, image.height) != (intr.width, intr.height) {
        return Err(Error::image(
            path,
            format!(
                "is {}x{} but the camera was calibrated on {}x{} photographs: photograph the \
                 table with the same camera settings",
                image.width, image.height, intr.width, intr.height
            ),
        ));
    }
    let corners = super::cv::find_corners(&image, super::cv::PatternSize::of(board), None)?
        .ok_or_else(|| {
            Error::image(
                path,
                format!(
                "the {}x{} board was not found: the whole board must be in the frame, flat and \
                 evenly lit (check --board, inner corners COLSxROWS)",
                board.cols, board.rows
            ),
            )
        })?;
    let pose = table::pose_from_corners(&corners, board, intr)?;
    let check = pixel_to_world_check(&corners, board, camera, &pose);
    Ok(TableStep {
        image: path.to_path_buf(),
        board: *board,
        pose,
        check,
    })
}

fn pixel_to_world_check(
    corners: &[[f64; 2]],
    board: &Board,
    camera: &CameraCalibration,
    pose: &TablePose,
) -> PixelToWorldCheck {
    let cam = table::camera(&camera.intrinsics, pose);
    let mapper = cam.plane_mapper(0.0);
    let [bx, by] = board.centre();
    let mut errors = Vec::with_capacity(corners.len());
    for (p, q) in board.object_points().iter().zip(corners) {
        // The board frame's rows run along world +x, its columns along world -y, centred.
        let truth = Vector3::new(p[0] - bx, -(p[1] - by), 0.0);
        let e = match mapper.map(q[0], q[1]) {
            Some(w) => (w - truth).norm() * 1e3,
            None => f64::INFINITY,
        };
        errors.push(e);
    }
    PixelToWorldCheck {
        corners: errors.len(),
        mean_mm: errors.iter().sum::<f64>() / errors.len().max(1) as f64,
        max_mm: errors.iter().copied().fold(0.0, f64::max),
        area_mm: [2.0 * bx * 1e3, 2.0 * by * 1e3],
    }
}

/// `rig` with the camera and table steps' results, when given (both or neither).
pub fn compose_rig(
    rig: &Rig,
    camera: Option<&CameraCalibration>,
    table: Option<&TablePose>,
) -> Result<Rig> {
    match (camera, table) {
        (Some(c), Some(t)) => files::rig_with_camera(rig, c, t),
        (None, None) => Ok(rig.clone()),
        (Some(_), None) => Err(Error::Incompatible(Conflict::CameraWithoutTable)),
        (None, Some(_)) => Err(Error::Incompatible(Conflict::TableWithoutCamera)),
    }
}

/// The gray chart step's inputs.
pub struct ChartInputs<'a> {
    /// The RAW photographs of the chart, one per LED in LED order.
    pub files: &'a [PathBuf],
    /// The chart: its patch grid and the patches' nominal reflectances.
    pub chart: &'a ChartDescription,
    /// The chart's rectangle in the photographs; `None`: found in the photographs.
    pub rect: Option<ChartRect>,
    /// The rig whose lights shade the chart (hand-measured or calibrated).
    pub rig: &'a Rig,
    /// Sensor pixels per image pixel (default: the images cover the sensor).
    pub step: Option<f64>,
}

/// Per light, white balance and linearity from RAW photographs of the chart, one per LED;
/// with the rectangle used (found in the photographs when none was given: `true`).
pub fn graychart_from_files(inputs: &ChartInputs) -> Result<(ChartReport, ChartRect, bool)> {
    files::check_light_count(inputs.files, inputs.rig, "gray-chart")?;
    let mut size = None;
    let mut mosaics = Vec::with_capacity(inputs.files.len());
    for path in inputs.files {
        let m = files::load_mosaic(path)?;
        files::check_size(path, (m.width, m.height), &mut size)?;
        mosaics.push(m);
    }
    let size = size.expect("one photograph per LED");
    let (rect, found) = match inputs.rect {
        Some(r) => (r, false),
        None => (super::chartfind::find(&mosaics, inputs.chart)?, true),
    };
    let window = files::image_window(inputs.rig, size, inputs.step)?;
    let shading = Shading {
        rig: inputs.rig,
        window,
    };
    let report = graychart::calibrate(&mosaics, inputs.chart, &rect, Some(&shading))?;
    Ok((report, rect, found))
}

/// The white sheet's flatness re-solved with the fitted lights, from the same photographs.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SheetCheck {
    /// Mean angle between a re-solved normal and straight up (degrees).
    pub mean_deg: f64,
    /// Largest angle between a re-solved normal and straight up (degrees).
    pub max_deg: f64,
    /// Largest angle from straight up of a 16x16-pixel block's mean normal (degrees): the
    /// calibration's own error with the noise averaged away.
    pub block_max_deg: f64,
    /// The level (degrees) the largest noise-only error stays under with probability 99.9 %, from
    /// each pixel's predicted error: what `max_deg` may reach through sensor noise alone.
    pub predicted_noise_max_deg: f64,
}

/// The white sheet step's result (`whitesheet.toml`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WhiteSheetStep {
    /// The RAW photographs of the sheet, one per LED in LED order.
    pub images: Vec<PathBuf>,
    /// A photograph with every LED off, subtracted from each of `images`; `None`: no dark frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dark: Option<PathBuf>,
    /// The sheet's diffuse reflectance, in (0, 1]; the measured intensities are divided by it.
    pub reflectance: f64,
    /// Side of the square pixel blocks the sheet's images are averaged over (pixels).
    pub block_px: usize,
    /// The LED fit: each LED's position and power, and whether the fit may be used.
    pub lights: LightFit,
    /// The sheet re-solved with the fitted lights (one exposure: sensor noise included).
    pub check: SheetCheck,
    /// Per light, the sheet's intensity over the fitted model's (the solve's correction).
    pub gains: Vec<GainGrid>,
    /// Folder of the per-light intensity maps (EXR), relative to this file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub maps_dir: Option<PathBuf>,
    /// The rig with the fitted LEDs: what the bundle stores.
    pub rig: Rig,
}

/// The white sheet step's inputs.
pub struct SheetInputs<'a> {
    /// The RAW photographs of the sheet, one per LED in LED order.
    pub files: &'a [PathBuf],
    /// A photograph with every LED off, subtracted from each photograph; `None`: no dark frame.
    pub dark: Option<&'a Path>,
    /// Hand-measured LEDs, with the calibrated camera when there is one.
    pub rig: &'a Rig,
    /// The sheet's diffuse reflectance, in (0, 1].
    pub reflectance: f64,
    /// Side of the square pixel blocks the sheet's images are averaged over (pixels).
    pub block_px: usize,
    /// Sensor pixels per image pixel (`None`: the photographs cover the whole sensor, full size or
    /// binned).
    pub step: Option<f64>,
}

/// Per-light intensity over the sheet, each LED's position fitted from the rig's hand
/// measurement, the gain grids, and the sheet re-solved with the result.
pub fn whitesheet_from_files(
    inputs: &SheetInputs,
    progress: &dyn Progress,
) -> Result<(WhiteSheetStep, Vec<SheetLight>)> {
    let rig = inputs.rig;
    files::check_light_count(inputs.files, rig, "white-sheet")?;
    let levels = Levels::from_sensor(&rig.sensor);
    let (lights, size) = files::load_frames(inputs.files, inputs.dark, &levels)?;
    let frames = Frames {
        width: size.0,
        height: size.1,
        window: files::image_window(rig, size, inputs.step)?,
        lights,
    };
    let sheet = whitesheet::measure(&frames, rig, inputs.reflectance, inputs.block_px)?;
    let fit = lights::fit(rig, &sheet, progress)?;
    let fitted = fit.apply(rig);
    let gains = lights::gain_grids(&fitted, &sheet)?;
    let noise = NoiseModel::from_sensor(&rig.sensor);
    let flat = whitesheet::flatness(&frames, &fitted, noise, 1, progress)?;
    let step = WhiteSheetStep {
        images: inputs.files.to_vec(),
        dark: inputs.dark.map(Path::to_path_buf),
        reflectance: inputs.reflectance,
        block_px: inputs.block_px,
        lights: fit,
        check: SheetCheck {
            mean_deg: flat.mean_deg,
            max_deg: flat.max_deg,
            block_max_deg: flat.block_max_deg,
            predicted_noise_max_deg: flat.predicted_noise_max_deg,
        },
        gains,
        maps_dir: None,
        rig: fitted,
    };
    Ok((step, sheet))
}

/// Writes the white sheet's per-light intensity maps into `dir` (`Lkk_intensity.exr`).
pub fn write_sheet_maps(dir: &Path, sheet: &[SheetLight]) -> Result<()> {
    crate::fsutil::create_dir_all(dir)?;
    for (k, light) in sheet.iter().enumerate() {
        let [r, g, b] = [light.map(0), light.map(1), light.map(2)];
        crate::io::write_exr(
            &dir.join(format!("L{k:02}_intensity.exr")),
            &[("R", &r), ("G", &g), ("B", &b)],
        )?;
    }
    Ok(())
}

fn read_sheet_maps(dir: &Path, lights: usize) -> Result<Vec<[Plane; 3]>> {
    (0..lights)
        .map(|k| {
            let path = dir.join(format!("L{k:02}_intensity.exr"));
            let mut planes = crate::io::read_exr(&path, &["R", "G", "B"])?.into_iter();
            let mut next = || planes.next().expect("three channels read");
            Ok([next(), next(), next()])
        })
        .collect()
}

/// The steps' results a bundle is assembled from; each is optional.
pub struct BundleInputs {
    /// The hand-measured rig (used when there is no white-sheet step).
    pub rig: Rig,
    /// The camera step's result and the file it was read from; `None`: the rig's own camera.
    pub camera: Option<(PathBuf, CameraCalibration)>,
    /// The table step's result and its file; given exactly when `camera` is.
    pub table: Option<(PathBuf, TableStep)>,
    /// The gray chart step's report and its file; `None`: the bundle has no gray-chart calibration.
    pub graychart: Option<(PathBuf, ChartReport)>,
    /// The white sheet step's result and its file; `None`: the rig's LEDs as measured by hand, and
    /// no intensity maps or gain grids.
    pub whitesheet: Option<(PathBuf, WhiteSheetStep)>,
}

/// Checks the steps fit together, then writes the bundle into `dir` (refusing an existing
/// bundle unless `force`: a bundle captures cite must not change under them).
pub fn assemble_bundle(
    inputs: &BundleInputs,
    dir: &Path,
    name: &str,
    force: bool,
) -> Result<(BundleIndex, Rig)> {
    let index_path = dir.join(bundle::INDEX_FILE);
    if index_path.exists() && !force {
        return Err(Error::Exists { path: index_path });
    }
    let composed = compose_rig(
        &inputs.rig,
        inputs.camera.as_ref().map(|c| &c.1),
        inputs.table.as_ref().map(|t| &t.1.pose),
    )?;
    let (rig, maps) = match &inputs.whitesheet {
        Some((path, sheet)) => {
            sheet.lights.check_usable(path)?;
            if inputs.camera.is_some() && !same_camera(&composed, &sheet.rig) {
                return Err(Error::Invalid(format!(
                    "{} was fitted with another camera or table pose than the camera and table \
                     steps given here: run the white sheet step again with these",
                    path.display()
                )));
            }
            let maps = match &sheet.maps_dir {
                Some(m) => {
                    let base = path.parent().unwrap_or(Path::new("."));
                    read_sheet_maps(&base.join(m), sheet.rig.leds.len())?
                }
                None => Vec::new(),
            };
            (sheet.rig.clone(), maps)
        }
        None => (composed, Vec::new()),
    };
    if let Some((path, chart)) = &inputs.graychart {
        if chart.lights.len() != rig.leds.len() {
            return Err(Error::Invalid(format!(
                "{}: gray chart results for {} lights, rig \"{}\" has {} LEDs",
                path.display(),
                chart.lights.len(),
                rig.name,
                rig.leds.len()
            )));
        }
    }
    let calibration = Calibration {
        camera: inputs.camera.as_ref().map(|c| c.1.clone()),
        table: inputs.table.as_ref().map(|t| t.1.pose),
        gray_chart: inputs.graychart.as_ref().map(|g| g.1.clone()),
        sheet_reflectance: inputs.whitesheet.as_ref().map(|w| w.1.reflectance),
        lights: inputs.whitesheet.as_ref().map(|w| w.1.lights.clone()),
        flatness: None,
    };
    let parts = Parts {
        calibration: &calibration,
        rig: &rig,
        maps: &maps,
        gains: inputs.whitesheet.as_ref().map(|w| w.1.gains.as_slice()),
    };
    let index = bundle::write_parts(dir, &rig.name, name, &parts)?;
    Ok((index, rig))
}

fn same_camera(a: &Rig, b: &Rig) -> bool {
    let (a, b) = (&a.camera, &b.camera);
    let close = |x: f64, y: f64| (x - y).abs() <= 1e-9 * (1.0 + x.abs().max(y.abs()));
    let all = |x: &[f64], y: &[f64]| x.iter().zip(y).all(|(p, q)| close(*p, *q));
    (a.width, a.height) == (b.width, b.height)
        && all(&[a.fx, a.fy, a.cx, a.cy], &[b.fx, b.fy, b.cx, b.cy])
        && all(&a.distortion, &b.distortion)
        && all(&a.position_m, &b.position_m)
        && all(&a.rotation_deg, &b.rotation_deg)
}

/// Today's date (UTC) as YYYY-MM-DD: the default bundle name.
pub fn today() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let (y, m, d) = civil_from_days((secs / 86_400) as i64);
    format!("{y:04}-{m:02}-{d:02}")
}

/// Days since 1970-01-01 to a proleptic Gregorian date (H. Hinnant's algorithm).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_from_days() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(11_016), (2000, 2, 29));
        assert_eq!(civil_from_days(20_454), (2026, 1, 1));
        assert_eq!(today().len(), 10);
    }
}
