//! Set sources and the one way to solve a set (DESIGN.md, layer 7).
//!
//! A [`SetSource`] is a set of frames opened for solving: a psscan capture set
//! ([`CaptureSource`]), a folder in the DiLiGenT benchmark layout ([`DiligentSource`]), or a
//! synthetic scene in memory (`synth::SceneSource`, beside the renderer, since production code
//! never imports the simulation). Each yields its frames, lights, noise model, mask, decode
//! information and, when it has one, its ground truth. [`solve_set`] and [`solve_source`] run
//! every source through the same sequence: stage the output folder, decode, select the
//! region, solve, write the maps, compare with the truth, write `report.json` and
//! `report.html`, and commit the folder; batches ([`solve_sets`]), the demo and `psscan eval`
//! go through it too.

mod batch;
mod capture;
mod diligent;
mod solve;
mod truth;

use std::path::{Path, PathBuf};

pub use batch::{output_dirs, solve_sets, BatchOptions, BatchSummary, SetOutcome, SetSummary};
pub use capture::{
    decoded_noise_model, noise_model, pixel_size_mm, undistortion_note, CaptureSource,
};
pub use diligent::{evaluate_sets, open_eval_set, DiligentSource};
pub use solve::{relocate, solve_set, solve_set_reusing, solve_source, TRUTH_READ_STAGE};
pub use truth::{bin_truth, read_truth, truth_for};

use serde::Serialize;

use crate::calibration::CalibrationChoice;
use crate::capture::diligent::{self as diligent_layout, DiligentSet};
use crate::capture::manifest::MANIFEST_FILE;
use crate::error::{Error, Result};
use crate::maps::{MapOptions, Report};
use crate::plane::{Frames, Mask, Plane, SensorWindow};
use crate::progress::Progress;
use crate::raw::{DecodeInfo, DevelopOptions};
use crate::region::RegionJob;
use crate::rig::Rig;
use crate::solve::{LightSource, NoiseModel, SolveOptions};
use crate::timing::StageClock;

/// A set opened for solving: what the one solve path asks of every kind of set.
///
/// `Sync`: the truth is read on one core while the maps are written on the others.
pub trait SetSource: Sync {
    /// Where the set is, as the report records it (`capture`).
    fn location(&self) -> &Path;
    /// The rig's name, as the report records it.
    fn rig_name(&self) -> String;
    /// Folders the solve reads besides the set and the job's inputs (a calibration bundle):
    /// the output may not be inside any of them.
    fn other_inputs(&self) -> Vec<PathBuf> {
        Vec::new()
    }
    /// Decodes the frames as `develop` says, timing its stages on `clock`.
    fn load(
        &self,
        develop: &DevelopOptions,
        progress: &dyn Progress,
        clock: &mut StageClock,
    ) -> Result<(Frames, DecodeInfo)>;
    /// The lights the frames were taken under.
    fn lights(&self) -> LightSource<'_>;
    /// The file each light's frame came from, in frame order, for messages that name a
    /// frame (empty when the frames have no files).
    fn frame_names(&self) -> Vec<String> {
        Vec::new()
    }
    /// The noise of frames decoded as `decode` says.
    fn noise(&self, decode: &DecodeInfo) -> NoiseModel;
    /// The set's own mask of pixels to solve (an object mask), at the frames' size.
    fn mask(&self, _frames: &Frames) -> Result<Option<Mask>> {
        Ok(None)
    }
    /// Exposure of the frames relative to the one the rig's LED powers were measured at.
    fn exposure(&self) -> f64 {
        1.0
    }
    /// The ground truth for the `width x height` frames decoded as `decode` says, when the
    /// set has one.
    fn truth(&self, width: usize, height: usize, decode: &DecodeInfo) -> Result<Option<Truth>>;
    /// Fills the report's description of the set (lights, camera, calibration, scale) for
    /// frames that covered `window` of the sensor.
    fn describe(&self, report: &mut Report, window: &SensorWindow);
}

/// A set's ground truth, at the frames' full size (before any crop or binning).
pub enum Truth {
    /// Unit normals and per-channel albedo at every pixel (synthetic sets).
    Surface {
        /// Unit normals in the world frame, x, y and z planes.
        normal: [Plane; 3],
        /// Linear diffuse albedo, R, G and B planes.
        albedo: [Plane; 3],
    },
    /// Unit normals over the solve's mask, zero where unknown (benchmark sets, which have no
    /// albedo truth).
    Normals([Plane; 3]),
}

/// How to solve a set and what to write.
#[derive(Clone, Debug, Default)]
pub struct SolveJob {
    /// The solver's options.
    pub options: SolveOptions,
    /// Which maps to write, and how.
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
    /// Derive the engine-ready material (`psscan derive`'s steps) from the solved maps into
    /// the solve folder's `derived/`, before the report page is built (which then shows the
    /// height and roughness).
    pub derive: Option<crate::maps::derive::DeriveOptions>,
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

/// What kind of set a folder holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SetKind {
    /// A psscan capture set (`manifest.toml`).
    Capture,
    /// The DiLiGenT benchmark layout (`filenames.txt`, `light_directions.txt`, ...).
    Diligent,
}

/// Tells what `dir` holds, or why it is not a set.
pub fn set_kind(dir: &Path) -> Result<SetKind> {
    let meta = match std::fs::metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(Error::capture_set(dir, "no such folder: not a capture set"))
        }
        other => other.map_err(|e| Error::io(dir, e))?,
    };
    if !meta.is_dir() {
        return Err(Error::capture_set(
            dir,
            "is a file, not a capture set folder",
        ));
    }
    if dir.join(MANIFEST_FILE).is_file() {
        Ok(SetKind::Capture)
    } else if DiligentSet::is_diligent(dir) {
        Ok(SetKind::Diligent)
    } else {
        Err(Error::capture_set(
            dir,
            format!(
                "not a capture set: no {MANIFEST_FILE} (psscan) and no {} with {} (DiLiGenT \
                 layout)",
                diligent_layout::FILENAMES,
                diligent_layout::LIGHT_DIRECTIONS
            ),
        ))
    }
}

/// Opens the set in `dir` (either kind) for a solve with `job`.
pub fn open(dir: &Path, job: &SolveJob) -> Result<Box<dyn SetSource>> {
    Ok(match set_kind(dir)? {
        SetKind::Capture => Box::new(CaptureSource::open(dir, job)?),
        SetKind::Diligent => Box::new(DiligentSource::open(dir, job)?),
    })
}
