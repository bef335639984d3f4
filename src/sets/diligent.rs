//! A folder in the DiLiGenT benchmark layout as a set source: distant lights from
//! `light_directions.txt` (divided by `light_intensities.txt`), the object mask, and the
//! ground-truth normals of `Normal_gt.mat` when present; and the same sets loaded whole for
//! `psscan eval`.

use std::path::{Path, PathBuf};

use super::{set_kind, SetKind, SetSource, SolveJob, Truth};
use crate::capture::diligent::{self, DiligentSet};
use crate::error::{Conflict, Error, Result};
use crate::eval;
use crate::maps::report::{LightRecord, Mean};
use crate::maps::Report;
use crate::plane::{Frames, Mask, SensorWindow};
use crate::progress::Progress;
use crate::raw::{DecodeInfo, DevelopOptions, Resolution};
use crate::solve::{LightSource, NoiseModel};
use crate::timing::StageClock;

/// A DiLiGenT-layout set opened for a solve.
///
/// The images carry no sensor description, so the noise model is 16-bit quantisation only
/// (`1/12 DN^2`): the dark threshold drops exact zeros (shadows) and the predicted error would
/// be a lower bound for real photographs (the report gives it as unknown).
pub struct DiligentSource {
    set: DiligentSet,
}

impl DiligentSource {
    /// Opens the set in `dir`; crops, binning, background masks and half resolution apply to
    /// psscan capture sets only and are refused here by name.
    pub fn open(dir: &Path, job: &SolveJob) -> Result<DiligentSource> {
        if !job.region.is_full() {
            return Err(Error::Incompatible(Conflict::RegionOnDiligent {
                dir: dir.to_path_buf(),
            }));
        }
        if job.develop.resolution != Resolution::Full {
            return Err(Error::Unsupported(format!(
                "{}: half resolution is 2x2 CFA binning of RAW frames; DiLiGenT sets store RGB \
                 images, solve them at full resolution",
                dir.display()
            )));
        }
        Ok(DiligentSource {
            set: DiligentSet::open(dir)?,
        })
    }
}

impl SetSource for DiligentSource {
    fn location(&self) -> &Path {
        &self.set.dir
    }

    fn rig_name(&self) -> String {
        format!("DiLiGenT layout, {} distant lights", self.set.files.len())
    }

    fn load(
        &self,
        _develop: &DevelopOptions,
        progress: &dyn Progress,
        clock: &mut StageClock,
    ) -> Result<(Frames, DecodeInfo)> {
        let frames = clock.time("decode", || self.set.load_frames(progress))?;
        Ok((frames, decode_info()))
    }

    fn frame_names(&self) -> Vec<String> {
        self.set.files.clone()
    }

    fn lights(&self) -> LightSource<'_> {
        LightSource::Directions {
            directions: &self.set.directions,
            intensities: &self.set.intensities,
        }
    }

    fn noise(&self, _decode: &DecodeInfo) -> NoiseModel {
        diligent_noise()
    }

    fn mask(&self, frames: &Frames) -> Result<Option<Mask>> {
        self.set.mask(frames.width, frames.height)
    }

    fn truth(&self, width: usize, height: usize, _decode: &DecodeInfo) -> Result<Option<Truth>> {
        Ok(self.set.normal_truth(width, height)?.map(Truth::Normals))
    }

    fn describe(&self, report: &mut Report, _window: &SensorWindow) {
        // The benchmark's sensor noise is not known (only its rounding is modelled), so a
        // predicted error would be a figure for a noise-free camera: reported as unknown.
        report.predicted_normal_error_deg = Mean::UNKNOWN;
        report.lights = (self.set.directions.iter().zip(&self.set.files))
            .map(|(d, file)| LightRecord {
                frame: Some(file.clone()),
                ..LightRecord::toward(*d)
            })
            .collect();
    }
}

/// How a DiLiGenT set's frames are read: as stored.
fn decode_info() -> DecodeInfo {
    DecodeInfo {
        encoding: "diligent-png16".into(),
        resolution: Resolution::Full,
        method: "none: 16-bit RGB PNGs, linear, 65535 = white".into(),
        cfa_pattern: None,
        levels: diligent::LEVELS,
        camera: None,
        camera_to_srgb: None,
        backing: None,
        dark_frame: "none in the set".into(),
        dark_subtracted: false,
        noise_channel_scale: [1.0; 3],
        noise_shared_cfa_sample: None,
        undistortion: "none: the benchmark's images come with distant lights and no camera \
                       model; pixels are not resampled"
            .into(),
    }
}

/// The noise model of a DiLiGenT-layout set: the images carry no sensor description, so
/// 16-bit quantisation only (`1/12 DN^2`).
fn diligent_noise() -> NoiseModel {
    let full_scale = diligent::LEVELS.white - diligent::LEVELS.black;
    NoiseModel {
        photon: 0.0,
        floor: 1.0 / 12.0 / (full_scale * full_scale),
        ..NoiseModel::NONE
    }
}

/// Loads a DiLiGenT-layout set with ground truth for `psscan eval`, through the same
/// [`DiligentSource`] a solve opens; a set without `Normal_gt.mat` is an error that names it.
/// The evaluation draws its light subsets from the loaded frames, so a set is read once for
/// every light count.
pub fn open_eval_set(dir: &Path, progress: &dyn Progress) -> Result<eval::EvalSet> {
    if set_kind(dir)? != SetKind::Diligent {
        return Err(Error::capture_set(
            dir,
            "psscan eval reads DiLiGenT-layout sets with ground truth; this is a psscan capture set",
        ));
    }
    let source = DiligentSource::open(dir, &SolveJob::default())?;
    let name = dir
        .canonicalize()
        .unwrap_or_else(|_| dir.to_path_buf())
        .file_name()
        .map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into());
    eval_set(&source, name, progress)
}

/// A set source's frames, distant lights, noise, mask and ground-truth normals, loaded whole
/// for the evaluation.
fn eval_set(
    source: &dyn SetSource,
    name: String,
    progress: &dyn Progress,
) -> Result<eval::EvalSet> {
    let dir = source.location();
    let mut clock = StageClock::default();
    let (frames, decode) = source.load(&DevelopOptions::default(), progress, &mut clock)?;
    let LightSource::Directions {
        directions,
        intensities,
    } = source.lights()
    else {
        return Err(Error::capture_set(
            dir,
            "psscan eval solves sets lit by distant lights; this set's lights are positions",
        ));
    };
    let (directions, intensities) = (directions.to_vec(), intensities.to_vec());
    let mask = source.mask(&frames)?;
    let truth = match source.truth(frames.width, frames.height, &decode)? {
        Some(Truth::Normals(normal)) | Some(Truth::Surface { normal, .. }) => normal,
        None => {
            return Err(Error::capture_set(
                dir,
                format!(
                    "has no {}: psscan eval needs ground-truth normals",
                    diligent::NORMAL_TRUTH
                ),
            ))
        }
    };
    Ok(eval::EvalSet {
        name,
        noise: source.noise(&decode),
        frames,
        directions,
        intensities,
        mask,
        truth,
    })
}

/// `psscan eval`: every set in `dirs` (loaded one at a time) through [`eval::evaluate`].
pub fn evaluate_sets(
    dirs: &[PathBuf],
    options: &eval::EvalOptions,
    progress: &dyn Progress,
) -> Result<eval::EvalReport> {
    let mut report = eval::EvalReport {
        rows: Vec::new(),
        anchors: Vec::new(),
    };
    for dir in dirs {
        let set = open_eval_set(dir, progress)?;
        eval::evaluate(&set, options, progress, &mut report)?;
    }
    Ok(report)
}
