//! The calibration steps' photographs, read from files: which files a step takes from a folder,
//! how each format becomes linear values, and where the images sit on the rig's sensor.
//!
//! Formats: the gray chart needs the raw CFA values, so camera RAW files (NEF, CR2, ARW, DNG,
//! ... through rawler). The white sheet takes linear RGB: OpenEXR (linear floats, 1.0 = the
//! white level; values within 1 % of it are taken as clipped), 16-bit RGB PNG or TIFF of raw digital numbers (psscan's `dn16` frames,
//! linearised with the rig's sensor levels), or camera RAW files (demosaiced at full
//! resolution, as a capture set's RAW frames are). Chessboard photographs (camera and table
//! steps) are any 8-bit image the `image` crate reads (PNG, JPEG, TIFF).

use std::path::{Path, PathBuf};

use crate::error::{Error, Needed, Result};
use crate::io::read_exr;
use crate::plane::{LightFrame, Mask, RgbPlanes, SensorWindow};
use crate::raw::{
    read_dn_image, read_raw, subtract_dark, DarkFrame, Levels, Mosaic, Resolution,
    SATURATION_MARGIN,
};
use crate::rig::Rig;

/// Camera RAW extensions a folder listing picks up (explicitly named files may have any).
pub const RAW_EXTENSIONS: [&str; 14] = [
    "dng", "nef", "nrw", "cr2", "cr3", "crw", "arw", "srf", "sr2", "raf", "orf", "rw2", "pef",
    "srw",
];
/// Linear and 16-bit image extensions.
pub const LINEAR_EXTENSIONS: [&str; 4] = ["exr", "png", "tif", "tiff"];

/// The name stem of a dark (all LEDs off) frame in a white-sheet folder.
pub const DARK_STEM: &str = "dark";

fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}

/// The files of a step: `inputs` is one folder (its files with one of `extensions`, in name
/// order) or a list of files (in the order given). A path that is not there is an error naming
/// it.
pub fn list_images(inputs: &[PathBuf], extensions: &[&str], what: &str) -> Result<Vec<PathBuf>> {
    for p in inputs {
        if !p.exists() {
            return Err(Error::io(
                p,
                std::io::Error::new(std::io::ErrorKind::NotFound, "no such file or folder"),
            ));
        }
    }
    let files = match inputs {
        [dir] if dir.is_dir() => {
            let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
            let mut files: Vec<PathBuf> = entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_file() && extensions.contains(&extension(p).as_str()))
                .collect();
            files.sort();
            if files.is_empty() {
                return Err(Error::Invalid(format!(
                    "{}: no {what} in this folder (looked for {})",
                    dir.display(),
                    extensions.join(", ")
                )));
            }
            files
        }
        _ => {
            if let Some(dir) = inputs.iter().find(|p| p.is_dir()) {
                return Err(Error::Invalid(format!(
                    "{}: give either one folder or a list of files, not both",
                    dir.display()
                )));
            }
            inputs.to_vec()
        }
    };
    Ok(files)
}

/// Splits a white-sheet listing into the light frames and the dark frame (`dark.*`).
pub fn split_dark(files: Vec<PathBuf>) -> Result<(Vec<PathBuf>, Option<PathBuf>)> {
    let (dark, lights): (Vec<PathBuf>, Vec<PathBuf>) = files.into_iter().partition(|p| {
        p.file_stem()
            .is_some_and(|s| s.to_string_lossy().eq_ignore_ascii_case(DARK_STEM))
    });
    if dark.len() > 1 {
        return Err(Error::Invalid(format!(
            "{} and {}: more than one dark frame",
            dark[0].display(),
            dark[1].display()
        )));
    }
    Ok((lights, dark.into_iter().next()))
}

/// Checks there is one photograph per LED of `rig`.
pub fn check_light_count(files: &[PathBuf], rig: &Rig, what: &str) -> Result<()> {
    if files.len() != rig.leds.len() {
        let listed: Vec<String> = files
            .iter()
            .map(|p| {
                p.file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default()
            })
            .collect();
        return Err(Error::Invalid(format!(
            "{} {what} photographs ({}) for rig \"{}\" with {} LEDs: give one per LED, in LED \
             order (names that sort as L00, L01, ...)",
            files.len(),
            listed.join(", "),
            rig.name,
            rig.leds.len()
        )));
    }
    Ok(())
}

/// A RAW file's CFA samples.
pub fn load_mosaic(path: &Path) -> Result<Mosaic> {
    let raw = read_raw(path)?;
    raw.mosaic.validate().map_err(|e| Error::image(path, e))?;
    Ok(raw.mosaic)
}

/// One photograph as linear RGB planes (module docs); `levels` linearise 16-bit PNG/TIFF.
pub fn load_linear(path: &Path, levels: &Levels) -> Result<LightFrame> {
    match extension(path).as_str() {
        "exr" => {
            let mut planes = read_exr(path, &["R", "G", "B"])?.into_iter();
            let mut next = || planes.next().expect("three channels read");
            let rgb = RgbPlanes {
                r: next(),
                g: next(),
                b: next(),
            };
            // Linear files carry no saturation flags: a value within the RAW decoder's margin
            // of the white level (1.0) is taken as clipped, as it would be in the RAW file.
            let limit = 1.0 - SATURATION_MARGIN;
            let mut saturated = Mask::new(rgb.width(), rgb.height(), false);
            for (i, s) in saturated.data.iter_mut().enumerate() {
                *s = rgb.channels().iter().any(|p| p.data[i] >= limit);
            }
            Ok(LightFrame {
                rgb,
                saturated: Some(saturated),
                cfa: None,
                dn: None,
                cfa_dn: None,
            })
        }
        "png" | "tif" | "tiff" => Ok(read_dn_image(path)?.to_light_frame(levels)),
        _ => {
            let mosaic = load_mosaic(path)?;
            mosaic
                .develop(Resolution::Full)
                .map_err(|e| Error::image(path, e))
        }
    }
}

/// Loads light frames (all the same size) and subtracts the dark frame when there is one.
pub fn load_frames(
    files: &[PathBuf],
    dark: Option<&Path>,
    levels: &Levels,
) -> Result<(Vec<LightFrame>, (usize, usize))> {
    let mut frames = Vec::with_capacity(files.len());
    let mut size = None;
    for path in files {
        let frame = load_linear(path, levels)?;
        let s = (frame.rgb.width(), frame.rgb.height());
        check_size(path, s, &mut size)?;
        frames.push(frame);
    }
    let size = size.ok_or_else(|| Error::Invalid("no photographs given".into()))?;
    if let Some(dark_path) = dark {
        let dark_frame = load_linear(dark_path, levels)?;
        check_size(
            dark_path,
            (dark_frame.rgb.width(), dark_frame.rgb.height()),
            &mut Some(size),
        )?;
        let dark_frame = DarkFrame::of(dark_frame);
        for frame in &mut frames {
            subtract_dark(frame, &dark_frame).map_err(|e| Error::image(dark_path, e))?;
        }
    }
    Ok((frames, size))
}

/// Every photograph of a step has the first one's size.
pub fn check_size(
    path: &Path,
    size: (usize, usize),
    first: &mut Option<(usize, usize)>,
) -> Result<()> {
    match first {
        None => *first = Some(size),
        Some(f) if *f != size => {
            return Err(Error::image(
                path,
                format!(
                    "is {}x{} but the first photograph is {}x{}: one camera, one size",
                    size.0, size.1, f.0, f.1
                ),
            ))
        }
        Some(_) => {}
    }
    Ok(())
}

/// Where `width x height` images sit on `rig`'s sensor: centred, one image pixel every `step`
/// sensor pixels. Without `step`, the images must cover the whole sensor (full size, or
/// binned by the same factor both ways).
pub fn image_window(
    rig: &Rig,
    (width, height): (usize, usize),
    step: Option<f64>,
) -> Result<SensorWindow> {
    let (sw, sh) = (rig.camera.width as usize, rig.camera.height as usize);
    let step = match step {
        Some(s) if s.is_finite() && s > 0.0 => s,
        Some(s) => {
            return Err(Error::Invalid(format!(
                "a sensor step of {s}: must be positive"
            )))
        }
        None => {
            let s = sw as f64 / width as f64;
            // A binned copy of the sensor keeps floor(size / step) pixels each way.
            if (sh as f64 / s).floor() as usize != height
                && (sh as f64 / s).round() as usize != height
            {
                return Err(Error::NeedsValue(Needed::SensorStep {
                    reason: format!(
                        "the photographs are {width}x{height}, which is neither rig \"{}\"'s \
                         {sw}x{sh} sensor nor a binned copy of it",
                        rig.name
                    ),
                }));
            }
            s
        }
    };
    Ok(SensorWindow::centred(sw, sh, width, height, step))
}

/// `rig` with the calibrated camera: the camera step's intrinsics (measured on its
/// photographs, which cover the sensor as [`image_window`] finds) and the table step's pose.
pub fn rig_with_camera(
    rig: &Rig,
    camera: &super::camera::CameraCalibration,
    pose: &super::table::TablePose,
) -> Result<Rig> {
    let i = &camera.intrinsics;
    let window = image_window(rig, (i.width, i.height), None).map_err(|_| {
        Error::Invalid(format!(
            "the camera step's photographs are {}x{}, which is neither rig \"{}\"'s {}x{} \
             sensor nor a binned copy of it: calibrate the camera on full-sensor (or evenly \
             binned) photographs",
            i.width, i.height, rig.name, rig.camera.width, rig.camera.height
        ))
    })?;
    let sensor = i.to_sensor(
        window,
        (rig.camera.width as usize, rig.camera.height as usize),
    );
    Ok(super::table::calibrated_rig(rig, &sensor, pose))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_follow_the_sensor_or_the_given_step() {
        let rig = Rig::default_rig();
        let (w, h) = (rig.camera.width as usize, rig.camera.height as usize);
        assert_eq!(
            image_window(&rig, (w, h), None).unwrap(),
            SensorWindow::FULL
        );
        let binned = image_window(&rig, (w / 8, h / 8), None).unwrap();
        assert_eq!(binned, SensorWindow::centred(w, h, w / 8, h / 8, 8.0));
        let err = image_window(&rig, (1024, 512), None).unwrap_err();
        assert!(
            matches!(err, Error::NeedsValue(Needed::SensorStep { .. })),
            "{err}"
        );
        let given = image_window(&rig, (1024, 512), Some(2.0)).unwrap();
        assert_eq!(given, SensorWindow::centred(w, h, 1024, 512, 2.0));
    }

    #[test]
    fn listings_name_what_is_missing_and_split_off_the_dark_frame() {
        let tmp = tempfile::tempdir().unwrap();
        let missing = tmp.path().join("nope");
        let err = list_images(std::slice::from_ref(&missing), &["exr"], "sheets")
            .unwrap_err()
            .to_string();
        assert!(err.contains("nope"), "{err}");
        let err = list_images(&[tmp.path().to_path_buf()], &["exr"], "white-sheet images")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("no white-sheet images") && err.contains("exr"),
            "{err}"
        );
        for name in ["L01.exr", "L00.exr", "dark.exr", "notes.txt"] {
            std::fs::write(tmp.path().join(name), b"x").unwrap();
        }
        let files = list_images(&[tmp.path().to_path_buf()], &["exr"], "sheets").unwrap();
        let (lights, dark) = split_dark(files).unwrap();
        let names: Vec<_> = lights.iter().map(|p| p.file_name().unwrap()).collect();
        assert_eq!(names, ["L00.exr", "L01.exr"]);
        assert!(dark.unwrap().ends_with("dark.exr"));
        let err = check_light_count(&lights, &Rig::default_rig(), "white-sheet")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("2 white-sheet photographs (L00.exr, L01.exr)") && err.contains("10 LEDs"),
            "{err}"
        );
    }

    #[test]
    fn exr_png16_and_dng_files_load_as_the_same_linear_light() {
        let tmp = tempfile::tempdir().unwrap();
        let rig = Rig::default_rig();
        let levels = Levels::from_sensor(&rig.sensor);
        let window = SensorWindow::centred(4928, 3264, 64, 48, 8.0);
        let sheet = crate::synth::targets::white_sheet(0.9, 0.0, 1);
        let linear =
            crate::synth::targets::render_flat_target(&rig, window, 64, 48, 6, 1.0, &sheet);
        // 16-bit PNG of raw numbers, no noise: within one digital number of the light.
        let dn = crate::synth::expose(&linear, &rig.sensor, crate::synth::Noise::Off, 0);
        let png = tmp.path().join("L06.png");
        std::fs::write(&png, crate::raw::encode_png16(&dn).unwrap()).unwrap();
        let from_png = load_linear(&png, &levels).unwrap();
        let quantum = 1.0 / (levels.white - levels.black) as f32;
        for (a, b) in from_png.rgb.g.data.iter().zip(&linear.g.data) {
            assert!((a - b).abs() <= quantum, "{a} {b}");
        }
        // EXR: exactly what was written, and clipped values flagged.
        let exr = tmp.path().join("L06.exr");
        let mut bright = from_png.rgb.clone();
        bright.g.data[5] = 1.0;
        crate::io::write_exr(
            &exr,
            &[("R", &bright.r), ("G", &bright.g), ("B", &bright.b)],
        )
        .unwrap();
        let from_exr = load_linear(&exr, &levels).unwrap();
        assert_eq!(from_exr.rgb.g.data, bright.g.data);
        let flags = from_exr.saturated.unwrap();
        assert!(flags.data[5] && flags.count() == 1);
        // A DNG of the same light (RGGB mosaic, demosaiced at full resolution): its green
        // agrees with the rendered light to the demosaic's interpolation on a smooth field.
        let mosaic = Mosaic {
            width: 64,
            height: 48,
            pattern: [[0, 1], [1, 2]],
            black: [[rig.sensor.black_level as f32; 2]; 2],
            white: rig.sensor.white_level as f32,
            samples: crate::synth::expose_mosaic(
                &linear,
                [[0, 1], [1, 2]],
                &rig.sensor,
                crate::synth::Noise::Off,
                0,
            ),
        };
        let meta = crate::raw::RawMeta {
            make: "psscan".into(),
            model: "test".into(),
            width: 64,
            height: 48,
            iso: None,
            shutter_s: None,
            aperture: None,
        };
        let dng = tmp.path().join("L06.dng");
        let bytes = crate::raw::encode_dng(
            &mosaic,
            &meta,
            rig.sensor.bits,
            rig.sensor.channel_gain,
            crate::raw::DngStorage::Lossless,
        )
        .unwrap();
        std::fs::write(&dng, bytes).unwrap();
        let from_dng = load_linear(&dng, &levels).unwrap();
        let centre = 24 * 64 + 32;
        let rel = from_dng.rgb.g.data[centre] / linear.g.data[centre] - 1.0;
        assert!(rel.abs() < 0.002, "{rel}");
    }
}
