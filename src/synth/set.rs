//! Synthetic capture sets on disk: the scene rendered under each LED and written as a capture
//! would write it (a dark frame, one frame per light, the manifest, the rig copy), with the
//! ground truth beside the frames (`truth/`). The set sources read such sets like any other
//! capture set; only the truth folder tells them apart.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use super::{expose, expose_mosaic, FrameEncoding, Scene, SynthSpec};
use crate::calibration::bundle::Bundle;
use crate::capture::{
    light_file_name, CameraSettings, CaptureSet, CaptureSetWriter, FrameKind, ImageInfo,
    SyntheticInfo,
};
use crate::error::{Error, Result};
use crate::fsutil::{create_dir_all, record_owned, write_atomic, StagedDir};
use crate::plane::{Plane, RgbPlanes, SensorWindow};
use crate::progress::{Progress, Silent};
use crate::raw::{encode_dng, encode_png16, DngStorage, Levels, Mosaic, RawMeta};
use crate::rig::Rig;

/// The folder of a synthetic set's ground truth, inside the set.
pub const TRUTH_DIR: &str = "truth";
/// The scene description a synthetic set was rendered from, inside the set.
pub const SPEC_FILE: &str = "truth/spec.toml";
/// The rig a synthetic set was rendered with (the set's own rig copy is what a capture would
/// store: the calibrated rig, when it cites a bundle).
pub const TRUTH_RIG_FILE: &str = "truth/rig.toml";

/// The CFA layout of psscan's synthetic camera.
pub const SYNTH_CFA: &str = "RGGB";

/// What the synthetic camera writes into its DNG files and the manifest.
fn synthetic_camera(encoding: FrameEncoding) -> (CameraSettings, RawMeta) {
    let meta = RawMeta {
        make: "psscan".into(),
        model: "synthetic camera".into(),
        width: 0,
        height: 0,
        iso: Some(100),
        shutter_s: Some(0.1),
        aperture: Some(8.0),
    };
    let settings = match encoding {
        FrameEncoding::Dn16 => CameraSettings {
            model: "psscan synthetic camera".into(),
            ..Default::default()
        },
        FrameEncoding::Dng => CameraSettings {
            model: meta.camera(),
            iso: meta.iso,
            shutter_s: meta.shutter_s,
            aperture: meta.aperture,
        },
    };
    (settings, meta)
}

/// What `write_synthetic_set` produced.
#[derive(Clone, Debug, Serialize)]
pub struct SynthOutcome {
    /// The set's folder.
    pub dir: PathBuf,
    /// Frame width in pixels.
    pub width: usize,
    /// Frame height in pixels.
    pub height: usize,
    /// Light frames (one per LED).
    pub lights: usize,
    /// Phases (`scene`, `render_and_write`), seconds.
    pub timings_s: BTreeMap<String, f64>,
}

/// Renders the textile under `rig` as `spec` says and writes it as a capture set in `dir`:
/// a dark frame, one frame per LED, the manifest, a copy of the rig, and the ground truth
/// (`truth/normal.exr`, `truth/albedo.exr`, `truth/spec.toml`). Frames are 16-bit PNGs of raw
/// digital numbers (`dn16`) or DNG files of an RGGB mosaic in which each sensor pixel records
/// its own channel of the rendered pixel (`raw`).
pub fn write_synthetic_set(
    rig: &Rig,
    spec: &SynthSpec,
    dir: &Path,
    force: bool,
    progress: &dyn Progress,
) -> Result<SynthOutcome> {
    write_synthetic_set_with(rig, spec, dir, force, None, progress)
}

/// [`write_synthetic_set`], and with `calibration` the set is what a capture with that bundle
/// would be: the scene is rendered with `rig` (the rig as built), while the set's rig copy is
/// the bundle's calibrated rig and the manifest cites the bundle. The rendering rig is kept
/// as `truth/rig.toml`.
pub fn write_synthetic_set_with(
    rig: &Rig,
    spec: &SynthSpec,
    dir: &Path,
    force: bool,
    calibration: Option<&Bundle>,
    progress: &dyn Progress,
) -> Result<SynthOutcome> {
    write_synthetic_set_from(rig, spec, dir, force, calibration, &[], progress)
}

/// [`write_synthetic_set_with`] for a run that reads `inputs` (the rig file, the bundle): the
/// set may not be written into or over any of them. The set is built beside `dir` and renamed
/// into place when complete, so an interrupted render leaves no half-written set.
pub fn write_synthetic_set_from(
    rig: &Rig,
    spec: &SynthSpec,
    dir: &Path,
    force: bool,
    calibration: Option<&Bundle>,
    inputs: &[&Path],
    progress: &dyn Progress,
) -> Result<SynthOutcome> {
    let stage = StagedDir::create(dir, force, inputs)?;
    let mut outcome = render_synthetic_set(rig, spec, stage.path(), calibration, progress)?;
    stage.commit(force, inputs)?;
    outcome.dir = dir.to_path_buf();
    Ok(outcome)
}

/// Renders and writes the set into the new folder `dir` (a stage).
fn render_synthetic_set(
    rig: &Rig,
    spec: &SynthSpec,
    dir: &Path,
    calibration: Option<&Bundle>,
    progress: &dyn Progress,
) -> Result<SynthOutcome> {
    if let Some(b) = calibration {
        if b.rig.leds.len() != rig.leds.len() {
            return Err(Error::Invalid(format!(
                "calibration bundle {} describes {} LEDs, the rig renders {}",
                b.index.id,
                b.rig.leds.len(),
                rig.leds.len()
            )));
        }
    }
    let mut timings = BTreeMap::new();
    let start = Instant::now();
    let window = spec.window(rig);
    let scene = spec.scene(rig, progress)?;
    timings.insert("scene".into(), start.elapsed().as_secs_f64());

    let (encoding, extension) = match spec.encoding {
        FrameEncoding::Dn16 => (crate::capture::manifest::ENCODING_DN16, "png"),
        FrameEncoding::Dng => (crate::capture::manifest::ENCODING_RAW, "dng"),
    };
    let image = ImageInfo {
        width: spec.width,
        height: spec.height,
        window,
        levels: Levels::from_sensor(&rig.sensor),
        exposure: spec.exposure,
        encoding: encoding.into(),
    };
    let (camera, raw_meta) = synthetic_camera(spec.encoding);
    let encode_frame = |linear: &RgbPlanes, stream: u64| -> Result<Vec<u8>> {
        match spec.encoding {
            FrameEncoding::Dn16 => encode_png16(&expose(linear, &rig.sensor, spec.noise(), stream)),
            FrameEncoding::Dng => {
                let pattern = Mosaic::parse_pattern(SYNTH_CFA).expect("a valid pattern");
                let black = rig.sensor.black_level as f32;
                let mosaic = Mosaic {
                    width: spec.width,
                    height: spec.height,
                    pattern,
                    black: [[black; 2]; 2],
                    white: rig.sensor.white_level as f32,
                    samples: expose_mosaic(linear, pattern, &rig.sensor, spec.noise(), stream),
                };
                encode_dng(
                    &mosaic,
                    &raw_meta,
                    rig.sensor.bits,
                    rig.sensor.channel_gain,
                    DngStorage::Lossless,
                )
            }
        }
    };
    let stored_rig = calibration.map_or(rig, |b| &b.rig);
    let mut writer = CaptureSetWriter::create(dir, stored_rig, image, camera, true)?;
    if let Some(b) = calibration {
        writer.set_calibration(b.citation())?;
    }
    write_truth(&scene, spec, dir)?;
    rig.save(&dir.join(TRUTH_RIG_FILE))?;
    writer.set_synthetic(SyntheticInfo {
        truth_dir: TRUTH_DIR.into(),
        spec_file: SPEC_FILE.into(),
    })?;

    let start = Instant::now();
    progress.begin("render", rig.leds.len() as u64 + 1);
    let dark = RgbPlanes::new(spec.width, spec.height);
    writer.add_frame(
        FrameKind::Dark,
        None,
        &format!("dark.{extension}"),
        &encode_frame(&dark, 0)?,
    )?;
    progress.advance(1);
    for k in 0..rig.leds.len() {
        let linear = scene.render_light(k, spec.exposure);
        writer.add_frame(
            FrameKind::Light,
            Some(k),
            &light_file_name(k, extension),
            &encode_frame(&linear, k as u64 + 1)?,
        )?;
        progress.advance(1);
    }
    progress.end();
    timings.insert("render_and_write".into(), start.elapsed().as_secs_f64());
    Ok(SynthOutcome {
        dir: dir.to_path_buf(),
        width: spec.width,
        height: spec.height,
        lights: rig.leds.len(),
        timings_s: timings,
    })
}

/// Writes a scene's ground truth (`truth/normal.exr`, `albedo.exr`, `height.exr`, `spec.toml`)
/// into a capture set's folder.
pub fn write_truth(scene: &Scene, spec: &SynthSpec, dir: &Path) -> Result<()> {
    let truth_dir = dir.join(TRUTH_DIR);
    create_dir_all(&truth_dir)?;
    record_owned(
        dir,
        ["normal.exr", "albedo.exr", "height.exr", "spec.toml"].map(|f| format!("{TRUTH_DIR}/{f}")),
    )?;
    let t = &scene.truth;
    crate::io::write_exr(
        &truth_dir.join("normal.exr"),
        &[
            ("R", &t.normal[0]),
            ("G", &t.normal[1]),
            ("B", &t.normal[2]),
        ],
    )?;
    crate::io::write_exr(
        &truth_dir.join("albedo.exr"),
        &[
            ("R", &t.albedo[0]),
            ("G", &t.albedo[1]),
            ("B", &t.albedo[2]),
        ],
    )?;
    crate::io::write_exr(&truth_dir.join("height.exr"), &[("Y", &t.height)])?;
    let text = toml::to_string_pretty(spec).expect("a spec always serialises");
    write_atomic(&dir.join(SPEC_FILE), text.as_bytes())
}

/// Ground-truth normal and albedo of a synthetic set at the centres of `width x height` pixels
/// at `window`: the scene rebuilt from the stored spec and rig (for example the point truth at
/// the centres of binned cells, to compare with [`crate::sets::bin_truth`]).
pub fn truth_at_pixels(
    set: &CaptureSet,
    width: usize,
    height: usize,
    window: SensorWindow,
) -> Result<Option<([Plane; 3], [Plane; 3])>> {
    let Some(info) = &set.manifest.synthetic else {
        return Ok(None);
    };
    let spec_path = set.dir.join(&info.spec_file);
    let text = std::fs::read_to_string(&spec_path).map_err(|e| Error::io(&spec_path, e))?;
    let spec: SynthSpec = toml::from_str(&text)
        .map_err(|e| Error::config(&spec_path, "spec", e.message().to_string()))?;
    // Sets written before truth/rig.toml existed were rendered with their rig copy.
    let truth_rig = set.dir.join(TRUTH_RIG_FILE);
    let rig = if truth_rig.is_file() {
        Rig::load(&truth_rig)?
    } else {
        Rig::load(&set.dir.join(&set.manifest.rig_file))?
    };
    let scene = Scene::build(
        &rig,
        spec.textile,
        width,
        height,
        window,
        spec.scene,
        &Silent,
    )?;
    Ok(Some((scene.truth.normal, scene.truth.albedo)))
}
