//! A psscan capture set as a set source: its frames decoded through `raw`, its rig (or the
//! calibration bundle's), the sensor's noise at the frames' levels, and the ground truth of
//! a synthetic set.

use std::path::{Path, PathBuf};

use super::{truth_for, SetSource, SolveJob, Truth};
use crate::calibration::{bundle::Bundle, choice};
use crate::capture::{CaptureSet, FrameKind};
use crate::error::Result;
use crate::maps::report::LightRecord;
use crate::maps::Report;
use crate::plane::{Frames, SensorWindow};
use crate::progress::Progress;
use crate::raw::{DecodeInfo, DevelopOptions, Levels, Mosaic};
use crate::rig::Rig;
use crate::solve::{GainGrid, LightSource, NoiseModel};
use crate::timing::StageClock;

/// A capture set opened for a solve, with the calibration bundle the solve uses.
pub struct CaptureSource {
    set: CaptureSet,
    calibration: Option<Bundle>,
}

impl CaptureSource {
    /// Opens the set in `dir` with the rig `job` gives, or else the calibration bundle it
    /// chooses (checked against the one the set cites), or else the set's rig copy.
    pub fn open(dir: &Path, job: &SolveJob) -> Result<CaptureSource> {
        let mut set = CaptureSet::open(dir, job.rig.clone())?;
        let calibration = match job.rig {
            Some(_) => None,
            None => choice::resolve(&set, &job.calibration, job.allow_calibration_mismatch)?,
        };
        if let Some(bundle) = &calibration {
            set.rig = bundle.rig.clone();
        }
        Ok(CaptureSource { set, calibration })
    }

    /// The set as opened (its rig replaced by the bundle's when a bundle is used).
    pub fn set(&self) -> &CaptureSet {
        &self.set
    }

    fn gains(&self) -> Option<&[GainGrid]> {
        self.calibration.as_ref().and_then(|b| b.gains.as_deref())
    }

    /// The set's lights in frame order, with their frames' files and hashes.
    fn light_records(&self) -> Vec<LightRecord> {
        let set = &self.set;
        let frame = |k: usize| {
            set.manifest
                .frames
                .iter()
                .find(|f| f.kind == FrameKind::Light && f.light == Some(k))
        };
        (set.rig.leds.iter().enumerate())
            .map(|(k, led)| LightRecord {
                position_m: Some(led.position_m),
                frame: frame(k).map(|f| f.file.clone()),
                sha256: frame(k).map(|f| f.sha256.clone()),
                ..LightRecord::toward(led.position_m)
            })
            .collect()
    }
}

impl SetSource for CaptureSource {
    fn location(&self) -> &Path {
        &self.set.dir
    }

    fn rig_name(&self) -> String {
        self.set.rig.name.clone()
    }

    fn other_inputs(&self) -> Vec<PathBuf> {
        (self.calibration.iter())
            .map(|b| b.citation().path)
            .collect()
    }

    fn load(
        &self,
        develop: &DevelopOptions,
        progress: &dyn Progress,
        clock: &mut StageClock,
    ) -> Result<(Frames, DecodeInfo)> {
        let loaded = self.set.load_frames_timed(develop, progress, clock)?;
        let mut decode = loaded.info;
        decode.undistortion = undistortion_note(&self.set.rig);
        Ok((loaded.frames, decode))
    }

    fn frame_names(&self) -> Vec<String> {
        (self.light_records().into_iter())
            .enumerate()
            .map(|(k, r)| r.frame.unwrap_or_else(|| format!("light {k}")))
            .collect()
    }

    fn lights(&self) -> LightSource<'_> {
        match self.gains() {
            Some(gains) => LightSource::Calibrated {
                rig: &self.set.rig,
                gains,
            },
            None => LightSource::Rig(&self.set.rig),
        }
    }

    fn noise(&self, decode: &DecodeInfo) -> NoiseModel {
        decoded_noise_model(&self.set.rig, decode)
    }

    fn exposure(&self) -> f64 {
        self.set.manifest.image.exposure
    }

    fn truth(&self, _width: usize, _height: usize, decode: &DecodeInfo) -> Result<Option<Truth>> {
        let truth = truth_for(&self.set, decode)?;
        Ok(truth.map(|(normal, albedo)| Truth::Surface { normal, albedo }))
    }

    fn describe(&self, report: &mut Report, window: &SensorWindow) {
        report.lights = self.light_records();
        report.camera = serde_json::to_value(&self.set.manifest.camera).ok();
        report.calibration = self.calibration.as_ref().map(|b| b.citation());
        report.calibration_cited_by_set = self.set.manifest.calibration.clone().filter(|c| {
            report
                .calibration
                .as_ref()
                .map_or(true, |used| (&used.id, &used.sha256) != (&c.id, &c.sha256))
        });
        report.pixel_size_mm = Some(pixel_size_mm(&self.set.rig, window));
    }
}

/// Millimetres on the sample plane per map pixel at the image centre: the camera's height
/// above the sample over its focal length, times the sensor pixels per map pixel (binning,
/// synthetic steps). Perspective and tilt change it by well under a per cent across a
/// sample on the seed's rig; `derive` uses it for heights, radii and the glTF quad.
pub fn pixel_size_mm(rig: &Rig, window: &SensorWindow) -> f64 {
    let distance_m = rig.camera.position_m[2] - rig.sample.z_m;
    distance_m / rig.camera.fx * window.step * 1e3
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
