//! The data's one way through the house, as library calls the CLI makes: render a synthetic
//! capture set, solve a capture set into maps and a report, and the demo that does both.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::capture::{
    light_file_name, CameraSettings, CaptureSet, CaptureSetWriter, FrameKind, ImageInfo,
    SyntheticInfo,
};
use crate::error::{Error, Result};
use crate::eval::{self, Stats};
use crate::fsutil::{claim_dir, create_dir_all, record_owned, write_atomic, StagedDir};
use crate::maps::{self, report::Mean, MapOptions, Report, WrittenMaps};
use crate::plane::{Frames, Mask, Plane, RgbPlanes, SensorWindow};
use crate::progress::{Progress, Silent};
use crate::raw::{
    encode_dng, encode_png16, DecodeInfo, DevelopOptions, DngStorage, Levels, Mosaic, RawMeta,
    Resolution,
};
use crate::region::{self, Background, RegionInfo, Roi};
use crate::rig::Rig;
use crate::solve::{self, NoiseModel, SolveInput, SolveOptions};
use crate::synth::{expose, expose_mosaic, FrameEncoding, Scene, SynthSpec};
use crate::timing::StageClock;

pub const TRUTH_DIR: &str = "truth";
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

/// The stage of reading a synthetic set's ground truth.
const TRUTH_READ_STAGE: &str = "read truth";

/// What `write_synthetic_set` produced.
#[derive(Clone, Debug, Serialize)]
pub struct SynthOutcome {
    pub dir: PathBuf,
    pub width: usize,
    pub height: usize,
    pub lights: usize,
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
    calibration: Option<&crate::calibration::bundle::Bundle>,
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
    calibration: Option<&crate::calibration::bundle::Bundle>,
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
    calibration: Option<&crate::calibration::bundle::Bundle>,
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
    let scene = Scene::build(
        rig,
        spec.textile.clone(),
        spec.width,
        spec.height,
        window,
        spec.scene.clone(),
        progress,
    )?;
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
    maps::write::write_exr(
        &truth_dir.join("normal.exr"),
        &[
            ("R", &t.normal[0]),
            ("G", &t.normal[1]),
            ("B", &t.normal[2]),
        ],
    )?;
    maps::write::write_exr(
        &truth_dir.join("albedo.exr"),
        &[
            ("R", &t.albedo[0]),
            ("G", &t.albedo[1]),
            ("B", &t.albedo[2]),
        ],
    )?;
    maps::write::write_exr(&truth_dir.join("height.exr"), &[("Y", &t.height)])?;
    let text = toml::to_string_pretty(spec).expect("a spec always serialises");
    write_atomic(&dir.join(SPEC_FILE), text.as_bytes())
}

/// Ground-truth normal and albedo of a synthetic set for a solve of its frames developed as
/// `decode` says: the stored truth at full resolution; for 2x2-binned RAW frames the stored
/// truth binned the way binning measures the surface ([`bin_truth`]).
pub fn truth_for(
    set: &CaptureSet,
    decode: &DecodeInfo,
) -> Result<Option<([Plane; 3], [Plane; 3])>> {
    let Some((normal, albedo)) = read_truth(set)? else {
        return Ok(None);
    };
    match (decode.resolution, decode.cfa_pattern.as_deref()) {
        (Resolution::Full, _) => Ok(Some((normal, albedo))),
        (Resolution::Half, Some(pattern)) => {
            let pattern = Mosaic::parse_pattern(pattern)
                .ok_or_else(|| Error::Invalid(format!("CFA pattern {pattern}")))?;
            Ok(Some(bin_truth(&normal, &albedo, pattern)))
        }
        (Resolution::Half, None) => Ok(None),
    }
}

/// What a 2x2-binned pixel of a Lambertian surface measures. Its luminance under a light `l`
/// is `sum_s w_s a_s (n_s . l)` over the cell's four CFA sites `s` (R, B at weight 1, each G
/// at 1/2, times the luminance weight of the site's channel; `a_s` the site's albedo in its
/// channel): exactly the luminance of a surface with scaled normal `N = sum_s w_s a_s n_s`.
/// Its normal is `N / |N|`; the albedo of channel `c` is the scaled normal of that channel's
/// sites projected on it. (Exact while all four sites face the light and see it from the same
/// direction; the few micrometres between sites change the near lights' direction by ~1e-5.)
pub fn bin_truth(
    normal: &[Plane; 3],
    albedo: &[Plane; 3],
    pattern: [[u8; 2]; 2],
) -> ([Plane; 3], [Plane; 3]) {
    let (w, h) = Resolution::Half.size(normal[0].width, normal[0].height);
    let mut n_out: [Plane; 3] = std::array::from_fn(|_| Plane::new(w, h, 0.0));
    let mut a_out: [Plane; 3] = std::array::from_fn(|_| Plane::new(w, h, 0.0));
    let width = normal[0].width;
    for v in 0..h {
        for u in 0..w {
            let mut scaled = nalgebra::Vector3::zeros();
            let mut per_channel = [nalgebra::Vector3::<f64>::zeros(); 3];
            for j in 0..2 {
                for i in 0..2 {
                    let at = (2 * v + j) * width + 2 * u + i;
                    let c = pattern[j][i] as usize;
                    let share = if c == 1 { 0.5 } else { 1.0 };
                    let n = nalgebra::Vector3::from_fn(|k, _| normal[k].data[at] as f64);
                    let a = albedo[c].data[at] as f64;
                    scaled += n * (solve::LUMINANCE_WEIGHTS[c] * share * a);
                    per_channel[c] += n * (share * a);
                }
            }
            let unit = scaled.normalize();
            for k in 0..3 {
                n_out[k].data[v * w + u] = unit[k] as f32;
                a_out[k].data[v * w + u] = per_channel[k].dot(&unit) as f32;
            }
        }
    }
    (n_out, a_out)
}

/// Ground-truth normal and albedo of a synthetic set at the centres of `width x height` pixels
/// at `window`: the scene rebuilt from the stored spec and rig (for example the point truth at
/// the centres of binned cells, to compare with [`bin_truth`]).
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

/// Ground-truth normal and albedo of a synthetic set.
pub fn read_truth(set: &CaptureSet) -> Result<Option<([Plane; 3], [Plane; 3])>> {
    let Some(info) = &set.manifest.synthetic else {
        return Ok(None);
    };
    let dir = set.dir.join(&info.truth_dir);
    let read3 = |name: &str| -> Result<[Plane; 3]> {
        let mut planes = maps::write::read_exr(&dir.join(name), &["R", "G", "B"])?.into_iter();
        Ok(std::array::from_fn(|_| {
            planes.next().expect("three channels")
        }))
    };
    let (normal, albedo) = rayon::join(|| read3("normal.exr"), || read3("albedo.exr"));
    Ok(Some((normal?, albedo?)))
}

/// How to solve a capture set and what to write.
#[derive(Clone, Debug, Default)]
pub struct SolveJob {
    pub options: SolveOptions,
    pub maps: MapOptions,
    /// Use this rig instead of the one stored in the set.
    pub rig: Option<Rig>,
    /// Overwrite an existing solve in the output folder.
    pub force: bool,
    /// Other paths this run reads (the other sets of a batch, the rig file, the bundle): the
    /// output may not be, hold or sit inside any of them, nor inside the set solved.
    pub inputs: Vec<PathBuf>,
    /// How frames are developed (resolution, dark-frame subtraction).
    pub develop: DevelopOptions,
    /// The part of the frames to solve (crop, binning, background mask).
    pub region: RegionJob,
    /// Which calibration bundle supplies the rig (ignored when `rig` is given).
    pub calibration: CalibrationChoice,
    /// Solve with a bundle other than the one the set cites (its id or checksum differ).
    pub allow_calibration_mismatch: bool,
}

impl SolveJob {
    /// Every input of a solve of `set` with this job: the set, the job's other inputs and the
    /// bundle it names.
    pub fn input_paths<'a>(&'a self, set: &'a Path) -> Vec<&'a Path> {
        let mut inputs = vec![set];
        inputs.extend(self.inputs.iter().map(PathBuf::as_path));
        if let CalibrationChoice::Bundle(dir) = &self.calibration {
            inputs.push(dir);
        }
        inputs
    }
}

/// Where a solve's rig comes from when no rig is given explicitly.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum CalibrationChoice {
    /// The bundle the set's manifest cites, read from the path recorded there; sets that cite
    /// none use their rig copy.
    #[default]
    Cited,
    /// This bundle folder; a set that cites another bundle (or this one before its files
    /// changed) is an error unless the mismatch is allowed.
    Bundle(PathBuf),
    /// No bundle: the set's rig copy.
    Ignore,
}

/// The bundle a solve of `set` uses, checked against the one the set cites; `None`: solve
/// with the set's rig copy.
pub fn resolve_calibration(
    set: &CaptureSet,
    job: &SolveJob,
) -> Result<Option<crate::calibration::bundle::Bundle>> {
    use crate::calibration::bundle;
    let cited = set.manifest.calibration.as_ref();
    let bundle = match (&job.calibration, cited) {
        _ if job.rig.is_some() => return Ok(None),
        (CalibrationChoice::Ignore, _) | (CalibrationChoice::Cited, None) => return Ok(None),
        (CalibrationChoice::Bundle(dir), _) => bundle::read(dir)?,
        (CalibrationChoice::Cited, Some(c)) => {
            if !c.path.join(bundle::INDEX_FILE).is_file() {
                return Err(Error::capture_set(
                    &set.dir,
                    format!(
                        "cites calibration bundle {} at {}, which is not there: pass \
                         --calibration DIR where the bundle is now, or --no-calibration to \
                         solve with the rig copy in the set",
                        c.id,
                        c.path.display()
                    ),
                ));
            }
            bundle::read(&c.path).map_err(|e| {
                Error::capture_set(
                    &set.dir,
                    format!("its calibration bundle {} cannot be used: {e}", c.id),
                )
            })?
        }
    };
    if let Some(c) = cited {
        let (id, sha) = (&bundle.index.id, &bundle.index.sha256);
        if (&c.id != id || &c.sha256 != sha) && !job.allow_calibration_mismatch {
            return Err(Error::capture_set(
                &set.dir,
                format!(
                    "was captured with calibration bundle {} (sha256 {}), but the bundle at {} \
                     is {id} (sha256 {sha}): solve with the bundle the set cites, or pass \
                     --allow-calibration-mismatch to use this one anyway (the report records \
                     both)",
                    c.id,
                    c.sha256,
                    bundle.dir.display()
                ),
            ));
        }
    }
    if bundle.rig.leds.len() != set.rig.leds.len() {
        return Err(Error::capture_set(
            &set.dir,
            format!(
                "has frames for {} LEDs, but calibration bundle {} describes {}",
                set.rig.leds.len(),
                bundle.index.id,
                bundle.rig.leds.len()
            ),
        ));
    }
    Ok(Some(bundle))
}

/// Which pixels a solve covers: crop, then 2x2 binning, then the background mask.
#[derive(Clone, Debug, Default)]
pub struct RegionJob {
    pub roi: Option<Roi>,
    /// 1 (every pixel) or 2 (2x2 blocks: a half-resolution preview).
    pub bin: usize,
    pub background: Background,
}

impl RegionJob {
    pub fn is_full(&self) -> bool {
        self.roi.is_none() && self.bin <= 1 && self.background == Background::None
    }
}

/// Applies `job` to decoded frames: returns the frames to solve, the sample mask, the noise
/// model for them, and a note for the report.
pub fn select_region(
    frames: Frames,
    lights: &solve::LightSource,
    noise: NoiseModel,
    job: &RegionJob,
) -> Result<(Frames, Option<Mask>, NoiseModel, RegionInfo)> {
    let (full_w, full_h) = (frames.width, frames.height);
    let mut frames = match &job.roi {
        Some(roi) => region::crop(&frames, roi)?,
        None => frames,
    };
    let mut noise = noise;
    match job.bin {
        0 | 1 => {}
        2 => {
            frames = region::bin2(&frames)?;
            // Each value is a mean of four: a quarter of the variance (treated as independent).
            noise.channel_scale = noise.channel_scale.map(|c| c * 0.25);
            noise.shared_cfa_sample = None;
        }
        n => {
            return Err(Error::Invalid(format!(
                "--bin {n}: only 1 and 2 are supported"
            )))
        }
    }
    let mut info = RegionInfo {
        roi: job.roi,
        bin: job.bin.max(1),
        background: "none".into(),
        sample_pixels: frames.width * frames.height,
        auto: None,
    };
    let mask = match &job.background {
        Background::None => None,
        Background::Auto => {
            let (mask, auto) = region::auto_mask(&frames, lights)?;
            info.background = "auto".into();
            info.auto = Some(auto);
            Some(mask)
        }
        Background::File(path) => {
            let mut mask = region::read_mask(path)?;
            if mask.width != full_w || mask.height != full_h {
                return Err(Error::Invalid(format!(
                    "background mask {} is {}x{}, the frames are {full_w}x{full_h}",
                    path.display(),
                    mask.width,
                    mask.height
                )));
            }
            if let Some(roi) = &job.roi {
                mask = region::crop_mask_to(&mask, roi)?;
            }
            if job.bin == 2 {
                mask = region::bin2_mask(&mask);
            }
            info.background = path.display().to_string();
            Some(mask)
        }
    };
    if let Some(m) = &mask {
        info.sample_pixels = m.count();
    }
    Ok((frames, mask, noise, info))
}

/// Ground truth cropped and binned as `job` does to the frames. Binning averages each
/// channel's scaled normal `a_c n` over the block (what a Lambertian block measures); the
/// normal is that of the luminance, the albedo each channel's projection on it.
pub fn region_truth(
    (normal, albedo): ([Plane; 3], [Plane; 3]),
    job: &RegionJob,
) -> Result<([Plane; 3], [Plane; 3])> {
    let crop = |p: Plane| -> Result<Plane> {
        match &job.roi {
            Some(roi) => {
                let frames = Frames {
                    width: p.width,
                    height: p.height,
                    window: SensorWindow::FULL,
                    lights: vec![crate::plane::LightFrame {
                        rgb: RgbPlanes {
                            r: p.clone(),
                            g: p.clone(),
                            b: p,
                        },
                        saturated: None,
                    }],
                };
                Ok(region::crop(&frames, roi)?.lights.remove(0).rgb.r)
            }
            None => Ok(p),
        }
    };
    let [n0, n1, n2] = normal;
    let [a0, a1, a2] = albedo;
    let normal = [crop(n0)?, crop(n1)?, crop(n2)?];
    let albedo = [crop(a0)?, crop(a1)?, crop(a2)?];
    if job.bin != 2 {
        return Ok((normal, albedo));
    }
    let (w, h) = (normal[0].width / 2, normal[0].height / 2);
    let mut n_out: [Plane; 3] = std::array::from_fn(|_| Plane::new(w, h, 0.0));
    let mut a_out: [Plane; 3] = std::array::from_fn(|_| Plane::new(w, h, 0.0));
    for y in 0..h {
        for x in 0..w {
            let mut per_channel = [nalgebra::Vector3::<f64>::zeros(); 3];
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let i = (2 * y + dy) * normal[0].width + 2 * x + dx;
                let n = nalgebra::Vector3::from_fn(|k, _| normal[k].data[i] as f64);
                for c in 0..3 {
                    per_channel[c] += n * albedo[c].data[i] as f64;
                }
            }
            let lum: nalgebra::Vector3<f64> = (0..3)
                .map(|c| per_channel[c] * solve::LUMINANCE_WEIGHTS[c])
                .sum();
            let unit = lum.normalize();
            for k in 0..3 {
                n_out[k].data[y * w + x] = unit[k] as f32;
                a_out[k].data[y * w + x] = (per_channel[k].dot(&unit) / 4.0) as f32;
            }
        }
    }
    Ok((n_out, a_out))
}

/// Solves the capture set in `dir` and writes maps and `report.json` into `out`. The output
/// is built beside `out` and renamed into place when complete.
pub fn solve_capture_set(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<Report> {
    solve_capture_set_reusing(dir, out, job, progress, &mut None)
}

/// [`solve_capture_set`], solving into `buffers` (a previous set's result, when it has the
/// same size) and leaving this set's result there: a batch of same-size sets then pays for
/// fresh output memory once, not per set (see `solve::solve_reusing`).
pub fn solve_capture_set_reusing(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
    buffers: &mut Option<solve::SolveResult>,
) -> Result<Report> {
    let inputs = job.input_paths(dir);
    let mut clock = StageClock::start();
    let stage = StagedDir::create(out, job.force, &inputs)?;

    let (set, calibration) = clock.time("open set", || -> Result<_> {
        let mut set = CaptureSet::open(dir, job.rig.clone())?;
        let calibration = resolve_calibration(&set, job)?;
        if let Some(bundle) = &calibration {
            crate::fsutil::check_outside_inputs(out, &[&bundle.citation().path])?;
            set.rig = bundle.rig.clone();
        }
        Ok((set, calibration))
    })?;
    let loaded = set.load_frames_timed(&job.develop, progress, &mut clock)?;
    let frames = loaded.frames;
    let mut decode = loaded.info;
    decode.undistortion = undistortion_note(&set.rig);
    let decode_s = clock.elapsed();

    let lights = match calibration.as_ref().and_then(|b| b.gains.as_deref()) {
        Some(gains) => solve::LightSource::Calibrated {
            rig: &set.rig,
            gains,
        },
        None => solve::LightSource::Rig(&set.rig),
    };
    let noise = clock.time("noise model", || decoded_noise_model(&set.rig, &decode));
    let (frames, mask, noise, region_info) = clock.time("region", || {
        select_region(frames, &lights, noise, &job.region)
    })?;
    let input = SolveInput {
        frames: &frames,
        lights,
        noise,
        exposure: set.manifest.image.exposure,
        mask: mask.as_ref(),
    };
    let result = clock.time("solve", || {
        solve::solve_reusing(&input, &job.options, progress, buffers.take())
    })?;
    if job.maps.report_html {
        clock.time("frame previews", || {
            maps::html::write_frame_strip(&frames, stage.path())
        })?;
    }
    let pixel_size_mm = pixel_size_mm(&set.rig, &frames.window);
    clock.time("free frames", || drop(frames));

    let map_options = MapOptions {
        display_matrix: job.maps.display_matrix.or(decode.camera_to_srgb),
        ..job.maps.clone()
    };
    // The ground truth (synthetic sets) is read while the maps are written: reading EXRs
    // and writing them share the cores better than either alone.
    let write_start = clock.elapsed();
    let mut stages = maps::MAP_STAGES.to_vec();
    stages.push(TRUTH_READ_STAGE);
    let (outputs, truth) = clock.time_shared(&stages, "write maps", |busy| {
        rayon::join(
            || maps::write_maps_timed(&result, stage.path(), &map_options, busy),
            || busy.time(TRUTH_READ_STAGE, || truth_for(&set, &decode)),
        )
    });
    let outputs = outputs?;
    let truth = truth?;
    let write_s = clock.elapsed() - write_start;

    let report_start = clock.elapsed();
    let truth = match truth {
        Some(truth) => Some(clock.time("compare with truth", || -> Result<_> {
            let (normal, albedo) = region_truth(truth, &job.region)?;
            let errors: Vec<f64> = eval::normal_errors_deg(&result, &normal)
                .into_iter()
                .flatten()
                .collect();
            Ok((
                eval::compare(&result, &normal, &albedo),
                maps::report::Histogram::of_errors(&errors),
            ))
        })?),
        None => None,
    };
    let mut report = clock.time("report", || {
        let outputs = relocate(outputs, out);
        let mut report = Report::new(dir, &set.rig.name, &result, &job.options, outputs);
        report.normal_convention = map_options.normal_convention;
        report.maps = map_options;
        report.lights = light_records(&set);
        report.camera = serde_json::to_value(&set.manifest.camera).ok();
        report.calibration = calibration.as_ref().map(|b| b.citation());
        report.calibration_cited_by_set = set.manifest.calibration.clone().filter(|c| {
            report
                .calibration
                .as_ref()
                .map_or(true, |used| (&used.id, &used.sha256) != (&c.id, &c.sha256))
        });
        if let Some((comparison, histogram)) = truth {
            report.set_truth(comparison);
            report.normal_error_histogram = Some(histogram);
        }
        if !job.region.is_full() {
            report.set_region(region_info);
        }
        report
    });
    report.decode = Some(decode);
    report.pixel_size_mm = Some(pixel_size_mm);
    let report_s = clock.elapsed() - report_start;
    report.set_stages(&clock);
    let total = report.total_s();
    report.timings_s = BTreeMap::from([
        ("decode".to_string(), decode_s),
        ("solve".to_string(), clock.seconds("solve")),
        ("write".to_string(), write_s),
        ("report".to_string(), report_s),
        ("total".to_string(), total),
    ]);
    report.write(&stage.path().join(maps::REPORT_FILE))?;
    if job.maps.report_html {
        maps::html::write_report_page(stage.path())?;
    }
    stage.commit(job.force, &inputs)?;
    *buffers = Some(result);
    Ok(report)
}

/// The set's lights in frame order, with their frames' files and hashes (for the report page).
fn light_records(set: &CaptureSet) -> Vec<maps::report::LightRecord> {
    let frame = |k: usize| {
        set.manifest
            .frames
            .iter()
            .find(|f| f.kind == FrameKind::Light && f.light == Some(k))
    };
    (set.rig.leds.iter().enumerate())
        .map(|(k, led)| maps::report::LightRecord {
            position_m: Some(led.position_m),
            frame: frame(k).map(|f| f.file.clone()),
            sha256: frame(k).map(|f| f.sha256.clone()),
            ..maps::report::LightRecord::toward(led.position_m)
        })
        .collect()
}

/// Millimetres on the sample plane per map pixel at the image centre: the camera's height
/// above the sample over its focal length, times the sensor pixels per map pixel (binning,
/// synthetic steps). Perspective and tilt change it by well under a per cent across a
/// sample on the seed's rig; `derive` uses it for heights, radii and the glTF quad.
pub fn pixel_size_mm(rig: &Rig, window: &SensorWindow) -> f64 {
    let distance_m = rig.camera.position_m[2] - rig.sample.z_m;
    distance_m / rig.camera.fx * window.step * 1e3
}

/// The written maps' paths under their final folder name.
pub fn relocate(outputs: WrittenMaps, out: &Path) -> WrittenMaps {
    let moved = |p: PathBuf| out.join(p.file_name().expect("map files have names"));
    WrittenMaps {
        normal_png: outputs.normal_png.map(moved),
        normal_exr: outputs.normal_exr.map(moved),
        albedo_png: outputs.albedo_png.map(moved),
        albedo_exr: outputs.albedo_exr.map(moved),
        confidence_exr: moved(outputs.confidence_exr),
    }
}

/// How lens distortion is handled: the frames are never resampled; the solver maps each
/// pixel's centre through the rig camera's model (undistorting its ray) to the point on the
/// sample it sees, so the light directions and falloff are those of the right point.
pub fn undistortion_note(rig: &Rig) -> String {
    let d = rig.camera.distortion;
    if d.iter().all(|&k| k == 0.0) {
        "none needed: the rig's camera has no distortion coefficients (k1 k2 p1 p2 k3 all 0); \
         frames are not resampled"
            .into()
    } else {
        format!(
            "per pixel, no resampling: the solver maps each pixel centre through the rig \
             camera's distortion model (k1 k2 p1 p2 k3 = {d:?}) to the point on the sample it \
             sees; the maps stay in the camera's (distorted) pixel grid"
        )
    }
}

/// The noise of frames developed as `decode` says: the sensor at the frames' levels, each
/// channel's variance scaled by the development, and the dark frame's noise added when it was
/// subtracted (a second read-noise and quantisation floor; the all-off frame holds no signal
/// whose photon noise would count).
pub fn decoded_noise_model(rig: &Rig, decode: &DecodeInfo) -> NoiseModel {
    let mut noise = noise_model(rig, &decode.levels).with_channel_scale(decode.noise_channel_scale);
    if decode.dark_subtracted {
        noise.floor *= 2.0;
    }
    noise.shared_cfa_sample = decode
        .noise_shared_cfa_sample
        .as_deref()
        .and_then(Mosaic::parse_pattern);
    noise
}

/// The sensor's noise at the levels the frames were stored with.
pub fn noise_model(rig: &Rig, levels: &Levels) -> NoiseModel {
    let mut sensor = rig.sensor.clone();
    sensor.black_level = levels.black;
    sensor.white_level = levels.white;
    NoiseModel::from_sensor(&sensor)
}

/// The figures `psscan demo --json` prints.
#[derive(Clone, Debug, Serialize)]
pub struct DemoSummary {
    pub rig: String,
    pub width: usize,
    pub height: usize,
    pub lights: usize,
    pub normal_error_deg: Stats,
    pub predicted_normal_error_deg: Mean,
    pub albedo_rel_error: Stats,
    pub solved_pixels: usize,
    /// The solve's warnings (see `Report::warnings`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    pub timings_s: BTreeMap<String, f64>,
    pub paths: DemoPaths,
}

#[derive(Clone, Debug, Serialize)]
pub struct DemoPaths {
    pub capture: PathBuf,
    pub maps: PathBuf,
    pub report: PathBuf,
    pub outputs: WrittenMaps,
}

/// The demo folder's entries, as its ownership record lists them (sub-folders with records
/// of their own).
pub const DEMO_CAPTURE: &str = "capture/";
pub const DEMO_MAPS: &str = "maps/";

/// Renders the synthetic textile with the embedded default rig into `out/capture`, solves it
/// into `out/maps`, and compares with the ground truth. The demo's folder is its own scratch
/// space: an earlier demo's output there is replaced as a whole (first removed, so an
/// interrupted demo never leaves new frames beside old maps); any other folder is refused.
pub fn run_demo(
    out: &Path,
    spec: &SynthSpec,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<DemoSummary> {
    let total = Instant::now();
    let rig = Rig::default_rig();
    let capture = out.join("capture");
    let maps_dir = out.join("maps");
    claim_dir(out, true, &[], &[DEMO_CAPTURE, DEMO_MAPS])?;
    let synth = write_synthetic_set(&rig, spec, &capture, true, progress)?;
    let job = SolveJob {
        force: true,
        ..job.clone()
    };
    let report = solve_capture_set(&capture, &maps_dir, &job, progress)?;
    let truth = report
        .truth
        .clone()
        .expect("a synthetic set always has ground truth");
    let mut timings = BTreeMap::new();
    for (k, v) in &synth.timings_s {
        timings.insert(format!("synth_{k}"), *v);
    }
    for (k, v) in &report.timings_s {
        timings.insert(format!("solve_{k}"), *v);
    }
    timings.insert("total".into(), total.elapsed().as_secs_f64());
    Ok(DemoSummary {
        rig: rig.name.clone(),
        width: spec.width,
        height: spec.height,
        lights: rig.leds.len(),
        normal_error_deg: truth.normal_error_deg,
        predicted_normal_error_deg: report.predicted_normal_error_deg,
        albedo_rel_error: truth.albedo_rel_error,
        solved_pixels: truth.pixels,
        warnings: report.warnings.clone(),
        timings_s: timings,
        paths: DemoPaths {
            capture,
            report: maps_dir.join(maps::REPORT_FILE),
            maps: maps_dir,
            outputs: report.outputs.clone(),
        },
    })
}
