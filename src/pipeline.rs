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
use crate::error::Result;
use crate::eval::{self, Stats};
use crate::fsutil::{create_dir_all, write_atomic};
use crate::maps::{self, report::Mean, MapOptions, Report, WrittenMaps};
use crate::plane::{Plane, RgbPlanes};
use crate::progress::Progress;
use crate::raw::{encode_png16, Levels};
use crate::rig::Rig;
use crate::solve::{self, NoiseModel, SolveInput, SolveOptions};
use crate::synth::{expose, Scene, SynthSpec};

pub const TRUTH_DIR: &str = "truth";
pub const SPEC_FILE: &str = "truth/spec.toml";

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
/// a dark frame, one 16-bit PNG of raw digital numbers per LED, the manifest, a copy of the
/// rig, and the ground truth (`truth/normal.exr`, `truth/albedo.exr`, `truth/spec.toml`).
pub fn write_synthetic_set(
    rig: &Rig,
    spec: &SynthSpec,
    dir: &Path,
    force: bool,
    progress: &dyn Progress,
) -> Result<SynthOutcome> {
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

    let image = ImageInfo {
        width: spec.width,
        height: spec.height,
        window,
        levels: Levels::from_sensor(&rig.sensor),
        exposure: spec.exposure,
        encoding: "dn16".into(),
    };
    let camera = CameraSettings {
        model: "psscan synthetic camera".into(),
        ..Default::default()
    };
    let mut writer = CaptureSetWriter::create(dir, rig, image, camera, force)?;
    write_truth(&scene, spec, dir)?;
    writer.set_synthetic(SyntheticInfo {
        truth_dir: TRUTH_DIR.into(),
        spec_file: SPEC_FILE.into(),
    })?;

    let start = Instant::now();
    progress.begin("render", rig.leds.len() as u64 + 1);
    let dark = RgbPlanes::new(spec.width, spec.height);
    let dn = expose(&dark, &rig.sensor, spec.noise(), 0);
    writer.add_frame(FrameKind::Dark, None, "dark.png", &encode_png16(&dn)?)?;
    progress.advance(1);
    for k in 0..rig.leds.len() {
        let linear = scene.render_light(k, spec.exposure);
        let dn = expose(&linear, &rig.sensor, spec.noise(), k as u64 + 1);
        writer.add_frame(
            FrameKind::Light,
            Some(k),
            &light_file_name(k, "png"),
            &encode_png16(&dn)?,
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
    Ok(Some((read3("normal.exr")?, read3("albedo.exr")?)))
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
}

/// Solves the capture set in `dir` and writes maps and `report.json` into `out`.
pub fn solve_capture_set(
    dir: &Path,
    out: &Path,
    job: &SolveJob,
    progress: &dyn Progress,
) -> Result<Report> {
    let total = Instant::now();
    maps::prepare_output_dir(out, job.force)?;
    let mut timings = BTreeMap::new();

    let start = Instant::now();
    let set = CaptureSet::open(dir, job.rig.clone())?;
    let frames = set.load_frames(progress)?;
    timings.insert("decode".into(), start.elapsed().as_secs_f64());

    let start = Instant::now();
    let noise = noise_model(&set.rig, &set.manifest.image.levels);
    let input = SolveInput {
        frames: &frames,
        lights: solve::LightSource::Rig(&set.rig),
        noise,
        exposure: set.manifest.image.exposure,
        mask: None,
    };
    let result = solve::solve(&input, &job.options, progress)?;
    timings.insert("solve".into(), start.elapsed().as_secs_f64());
    drop(frames);

    let start = Instant::now();
    let outputs = maps::write_maps(&result, out, &job.maps)?;
    timings.insert("write".into(), start.elapsed().as_secs_f64());

    let mut report = Report::new(dir, &set.rig.name, &result, &job.options, outputs);
    if let Some((normal, albedo)) = read_truth(&set)? {
        report.truth = Some(eval::compare(&result, &normal, &albedo));
    }
    timings.insert("total".into(), total.elapsed().as_secs_f64());
    report.timings_s = timings;
    report.write(&out.join(maps::REPORT_FILE))?;
    Ok(report)
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

/// Renders the synthetic textile with the embedded default rig into `out/capture`, solves it
/// into `out/maps`, and compares with the ground truth. The demo's folder is its own scratch
/// space: earlier demo output there is replaced.
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
        timings_s: timings,
        paths: DemoPaths {
            capture,
            report: maps_dir.join(maps::REPORT_FILE),
            maps: maps_dir,
            outputs: report.outputs.clone(),
        },
    })
}
