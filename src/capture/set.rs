//! A capture set on disk: writing one frame at a time without ever losing what is already
//! there, and reading one back with every check a saved set needs before it is solved.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use rayon::prelude::*;

use super::manifest::{
    CameraSettings, FrameEntry, FrameKind, ImageInfo, Manifest, SyntheticInfo, FORMAT,
    MANIFEST_FILE, VERSION,
};
use crate::error::{Error, Result};
use crate::fsutil::{create_dir_all, record_owned, sha256_hex, write_atomic};
use crate::plane::{Frames, LightFrame};
use crate::progress::Progress;
use crate::raw::{
    check_consistent, check_plausible, decode_codec, develop_frames_timed, finish_decode, Coded,
    DecodeInfo, DecodedFrame, DevelopOptions, Encoding, RawMeta, RawPrep, Resolution, SampleCounts,
    DECODE_STAGES,
};
use crate::rig::Rig;
use crate::timing::{Busy, StageClock};

mod read;
pub use read::{HASH_STAGE, READ_STAGE};

/// The name of the set's copy of its rig, inside the set's folder.
pub const RIG_FILE: &str = "rig.toml";

/// The file name psscan gives LED `k`'s frame.
pub fn light_file_name(k: usize, extension: &str) -> String {
    format!("L{k:02}.{extension}")
}

/// Builds a capture set frame by frame. Each frame is written atomically and the manifest is
/// rewritten atomically after it, so an interruption leaves a valid set of the frames so far.
pub struct CaptureSetWriter {
    dir: PathBuf,
    manifest: Manifest,
}

impl CaptureSetWriter {
    /// Starts a new set in `dir` for `rig`. A folder that already holds a capture set is
    /// refused unless `force`.
    pub fn create(
        dir: &Path,
        rig: &Rig,
        image: ImageInfo,
        camera: CameraSettings,
        force: bool,
    ) -> Result<Self> {
        let manifest_path = dir.join(MANIFEST_FILE);
        if manifest_path.exists() && !force {
            return Err(Error::Exists {
                path: manifest_path,
            });
        }
        create_dir_all(dir)?;
        // Recorded before they are written: a folder psscan stopped in half-way still counts
        // as psscan's, so `--force` may start it over.
        record_owned(dir, [MANIFEST_FILE, RIG_FILE])?;
        rig.save(&dir.join(RIG_FILE))?;
        let writer = CaptureSetWriter {
            dir: dir.to_path_buf(),
            manifest: Manifest {
                format: FORMAT.into(),
                version: VERSION,
                rig_file: RIG_FILE.into(),
                calibration: None,
                image,
                camera,
                synthetic: None,
                frames: Vec::new(),
            },
        };
        writer.write_manifest()?;
        Ok(writer)
    }

    /// Reopens the set in `dir` to complete it. Every frame it lists is checked (there, a
    /// plain file, the SHA-256 recorded); frames that fail are dropped from the manifest,
    /// which is rewritten at once, and returned with the reason, so they are shot again.
    pub fn resume(dir: &Path) -> Result<(Self, Vec<DroppedFrame>)> {
        let set = CaptureSet::open(dir, None)?;
        let mut manifest = set.manifest.clone();
        let mut dropped = Vec::new();
        manifest
            .frames
            .retain(|entry| match set.read_frame_bytes(entry) {
                Ok(_) => true,
                Err(e) => {
                    dropped.push(DroppedFrame {
                        file: entry.file.clone(),
                        reason: e.to_string(),
                    });
                    false
                }
            });
        let writer = CaptureSetWriter {
            dir: dir.to_path_buf(),
            manifest,
        };
        if !dropped.is_empty() {
            writer.write_manifest()?;
        }
        Ok((writer, dropped))
    }

    /// The set's folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The manifest as written so far: the frames stored until now.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Stores one frame's encoded bytes as `file` and records it (replacing an earlier entry
    /// for the same frame).
    pub fn add_frame(
        &mut self,
        kind: FrameKind,
        light: Option<usize>,
        file: &str,
        bytes: &[u8],
    ) -> Result<()> {
        record_owned(&self.dir, [file])?;
        write_atomic(&self.dir.join(file), bytes)?;
        let entry = FrameEntry {
            kind,
            light,
            file: file.into(),
            sha256: sha256_hex(bytes),
        };
        self.manifest
            .frames
            .retain(|f| !(f.kind == kind && f.light == light));
        self.manifest.frames.push(entry);
        self.write_manifest()
    }

    /// Records the calibration bundle the set's rig came from.
    pub fn set_calibration(&mut self, calibration: crate::rig::CalibrationRef) -> Result<()> {
        self.manifest.calibration = Some(calibration);
        self.write_manifest()
    }

    /// Records where a synthetic set's ground truth and render specification lie.
    pub fn set_synthetic(&mut self, info: SyntheticInfo) -> Result<()> {
        self.manifest.synthetic = Some(info);
        self.write_manifest()
    }

    fn write_manifest(&self) -> Result<()> {
        write_atomic(
            &self.dir.join(MANIFEST_FILE),
            self.manifest.to_toml_string().as_bytes(),
        )
    }
}

/// A frame an interrupted set listed that could not be kept on resume, and why.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct DroppedFrame {
    /// The frame's file name, as the manifest listed it.
    pub file: String,
    /// Why it could not be kept (missing, not a plain file, or its SHA-256 changed).
    pub reason: String,
}

/// Reads the file `name` of the set in `dir`: a plain file inside the folder, not a link and
/// not reached through one.
pub(crate) fn read_inside(dir: &Path, name: &str) -> Result<(PathBuf, Vec<u8>)> {
    let path = checked_inside(dir, name)?;
    let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
    Ok((path, bytes))
}

/// The path of the file `name` of the set in `dir`, checked to be a plain file inside the
/// folder, not a link and not reached through one.
fn checked_inside(dir: &Path, name: &str) -> Result<PathBuf> {
    let path = dir.join(name);
    super::manifest::check_inside(name).map_err(|m| Error::image(&path, m))?;
    let meta = std::fs::symlink_metadata(&path).map_err(|e| Error::io(&path, e))?;
    if meta.file_type().is_symlink() {
        return Err(Error::image(
            &path,
            "is a symbolic link; capture set frames must be plain files inside the set",
        ));
    }
    let inside = match (dir.canonicalize(), path.canonicalize()) {
        (Ok(dir), Ok(file)) => file.starts_with(dir),
        _ => false,
    };
    if !inside {
        return Err(Error::image(
            &path,
            "lies outside the capture set's folder (a folder on its way is a link); \
             capture set frames must be plain files inside the set",
        ));
    }
    if !meta.is_file() {
        return Err(Error::image(&path, "is not a plain file"));
    }
    Ok(path)
}

/// A set's light frames developed for a solve, and how they were made.
pub struct LoadedFrames {
    /// The light frames in LED order, as linear RGB planes ready for the solve.
    pub frames: Frames,
    /// How the frames were decoded and developed, for the solve's report.
    pub info: DecodeInfo,
}

/// A capture set opened for reading.
pub struct CaptureSet {
    /// The set's folder.
    pub dir: PathBuf,
    /// The set's manifest, parsed and structurally validated.
    pub manifest: Manifest,
    /// The rig the frames are solved with: the set's own copy, or the one given to
    /// [`CaptureSet::open`].
    pub rig: Rig,
}

impl CaptureSet {
    /// Opens `dir`, parsing its manifest and its rig (or `rig`, when given, instead of the
    /// one stored in the set).
    pub fn open(dir: &Path, rig: Option<Rig>) -> Result<CaptureSet> {
        let manifest_path = dir.join(MANIFEST_FILE);
        if !manifest_path.is_file() {
            return Err(Error::capture_set(
                dir,
                format!("no {MANIFEST_FILE}: not a capture set folder"),
            ));
        }
        let text =
            std::fs::read_to_string(&manifest_path).map_err(|e| Error::io(&manifest_path, e))?;
        let manifest = Manifest::parse(&text, &manifest_path)?;
        let rig = match rig {
            Some(rig) => rig,
            None => Rig::load(&dir.join(&manifest.rig_file))?,
        };
        Ok(CaptureSet {
            dir: dir.to_path_buf(),
            manifest,
            rig,
        })
    }

    /// Entries of the light frames in LED order; fails naming what is missing or extra.
    pub fn light_entries(&self) -> Result<Vec<&FrameEntry>> {
        let leds = self.rig.leds.len();
        let extra: Vec<usize> = self
            .manifest
            .frames
            .iter()
            .filter_map(|f| f.light)
            .filter(|&k| k >= leds)
            .collect();
        if !extra.is_empty() {
            return Err(Error::capture_set(
                &self.dir,
                format!(
                    "frames for lights {extra:?}, but the rig has only {leds} LEDs (0..{})",
                    leds - 1
                ),
            ));
        }
        let missing: Vec<usize> = (0..leds)
            .filter(|&k| self.manifest.light_frame(k).is_none())
            .collect();
        if !missing.is_empty() {
            return Err(Error::capture_set(
                &self.dir,
                format!("missing frames for lights {missing:?}; resume the capture to shoot them"),
            ));
        }
        Ok((0..leds)
            .map(|k| self.manifest.light_frame(k).expect("checked above"))
            .collect())
    }

    /// Reads a frame's bytes, refusing links (of the file or of a folder on its way) and
    /// checking the recorded SHA-256.
    pub fn read_frame_bytes(&self, entry: &FrameEntry) -> Result<(PathBuf, Vec<u8>)> {
        self.read_frame_bytes_timed(entry, &Busy::new(&[READ_STAGE, HASH_STAGE]), Vec::new())
    }

    /// Verifies and decodes every light frame into linear planes at full resolution, with
    /// the dark frame subtracted when the set has one.
    pub fn load_frames(&self, progress: &dyn Progress) -> Result<Frames> {
        Ok(self
            .load_frames_with(&DevelopOptions::default(), progress)?
            .frames)
    }

    /// Verifies, decodes and develops every light frame (in parallel) as `options` say: RAW
    /// frames binned or demosaiced, the all-off frame subtracted, RAW metadata checked across
    /// the set.
    pub fn load_frames_with(
        &self,
        options: &DevelopOptions,
        progress: &dyn Progress,
    ) -> Result<LoadedFrames> {
        let mut loaded = self.load_frames_timed(options, progress, &mut StageClock::start())?;
        // For callers that read the planes (calibration): dn16 frames' DN become `f32`.
        let lights = std::mem::take(&mut loaded.frames.lights);
        loaded.frames.lights = lights.into_iter().map(LightFrame::with_planes).collect();
        Ok(loaded)
    }

    /// [`Self::load_frames_with`], timing its stages on `clock`: read, hash check, decode and
    /// linearize (interleaved over the frames, one frame per core), dark subtraction, and
    /// demosaic or binning. Plain-PNG dn16 frames stay as their DN ([`LightFrame::from_dn`]),
    /// for the solver, which reads them through `LightFrame`'s accessors.
    pub fn load_frames_timed(
        &self,
        options: &DevelopOptions,
        progress: &dyn Progress,
        clock: &mut StageClock,
    ) -> Result<LoadedFrames> {
        let entries = self.light_entries()?;
        let image = &self.manifest.image;
        let encoding = Encoding::parse(&image.encoding).ok_or_else(|| {
            Error::Unsupported(format!(
                "{}: frame encoding \"{}\" is not supported by this build",
                self.dir.display(),
                image.encoding
            ))
        })?;
        if encoding == Encoding::Dn16 && options.resolution != Resolution::Full {
            return Err(Error::Unsupported(format!(
                "{}: half resolution is 2x2 CFA binning of RAW frames; this set stores dn16 RGB \
                 frames, solve it at full resolution",
                self.dir.display()
            )));
        }
        let dark = self.manifest.dark_frame();
        let subtracted = dark.filter(|_| options.subtract_dark);
        let jobs: Vec<&FrameEntry> = dark.into_iter().chain(entries.iter().copied()).collect();
        progress.begin("decode", jobs.len() as u64);
        let stages: Vec<&'static str> = [READ_STAGE, HASH_STAGE]
            .into_iter()
            .chain(DECODE_STAGES)
            .collect();
        // Read, hash check and codec of one frame, its size checked against the manifest; read
        // into a buffer an earlier frame is done with (fresh pages cost a fault and zeroing).
        let spare: Mutex<Vec<Vec<u8>>> = Mutex::new(Vec::new());
        let code_one = |entry: &FrameEntry, busy: &Busy| -> Result<(PathBuf, Coded)> {
            let (path, coded) = if encoding == Encoding::Dn16 {
                self.decode_dn16_streamed(entry, &image.levels, busy)?
            } else {
                let buffer = spare
                    .lock()
                    .expect("not poisoned")
                    .pop()
                    .unwrap_or_default();
                let (path, bytes) = self.read_frame_bytes_timed(entry, busy, buffer)?;
                let (coded, bytes) = decode_codec(bytes, &path, encoding, &image.levels, busy);
                if bytes.capacity() > 0 {
                    spare.lock().expect("not poisoned").push(bytes);
                }
                (path, coded?)
            };
            let (w, h) = coded.stored_size();
            if (w, h) != (image.width, image.height) {
                return Err(Error::image(
                    &path,
                    format!(
                        "is {w}x{h}, the manifest says {}x{}",
                        image.width, image.height
                    ),
                ));
            }
            progress.advance(1);
            Ok((path, coded))
        };
        // The dark frame first, codec and linear pass (rawler decodes its tiles on every
        // core); then each light frame's codec and its linear pass in one job, one frame per
        // core, with the dark frame in hand, so each counts its samples against the dark
        // frame's read noise and, at half resolution, subtracts it and bins in the same pass:
        // no full-size linear mosaic of a light frame is made there (`raw::pass`). A frame's
        // stored samples are freed right after its pass, so at half resolution the next
        // frame's decode reuses their memory: with every codec first, all eleven 16 MP mosaics
        // (350 MB) were alive at once, fresh memory each.
        let bin = encoding == Encoding::Raw && options.resolution == Resolution::Half;
        let decoded = clock.time_shared(&stages, "load frames", |busy| {
            let finish = |(path, coded): (PathBuf, Coded), prep: RawPrep| {
                finish_decode(coded, &path, prep, busy)
            };
            let (dark_job, light_jobs) = jobs.split_at(dark.is_some() as usize);
            let dark_frame = dark_job
                .first()
                .map(|entry| finish(code_one(entry, busy)?, RawPrep::default()))
                .transpose()?;
            let prep = RawPrep::for_lights(dark_frame.as_ref(), subtracted.is_some(), bin);
            let lights = light_jobs
                .par_iter()
                .map(|entry| finish(code_one(entry, busy)?, prep))
                .collect::<Result<Vec<DecodedFrame>>>()?;
            Ok::<_, Error>(dark_frame.into_iter().chain(lights).collect::<Vec<_>>())
        })?;
        progress.end();
        if encoding == Encoding::Raw {
            let metas: Vec<(String, &RawMeta)> = jobs
                .iter()
                .zip(&decoded)
                .filter_map(|(e, d)| Some((e.file.clone(), d.meta.as_ref()?)))
                .collect();
            check_consistent(&metas).map_err(|m| Error::capture_set(&self.dir, m))?;
            self.check_camera_settings(&metas)?;
            let lights: Vec<(String, SampleCounts)> = jobs
                .iter()
                .zip(&decoded)
                .skip(dark.is_some() as usize)
                .map(|(e, d)| (e.file.clone(), d.counts))
                .collect();
            clock
                .time("plausibility check", || check_plausible(&lights))
                .map_err(|m| Error::capture_set(&self.dir, m))?;
        }
        let mut decoded = decoded.into_iter();
        let dark_frame = dark.and_then(|_| decoded.next());
        let lights: Vec<DecodedFrame> = decoded.collect();
        let first = &lights[0];
        let full_raw = encoding == Encoding::Raw && options.resolution == Resolution::Full;
        let mut info = DecodeInfo {
            encoding: encoding.name().into(),
            resolution: options.resolution,
            method: match encoding {
                Encoding::Raw => options.resolution.method().into(),
                Encoding::Dn16 => "none: the frames store R, G and B at every pixel".into(),
            },
            cfa_pattern: first.cfa_pattern.clone(),
            levels: first.levels,
            camera: first.meta.clone(),
            camera_to_srgb: first.camera_to_srgb,
            dark_frame: match (dark, subtracted) {
                (Some(d), Some(_)) => format!(
                    "{} subtracted sample by sample (its noise is counted: the noise model's \
                     floor is doubled)",
                    d.file
                ),
                (Some(d), None) => format!("{} present, not subtracted (asked not to)", d.file),
                (None, _) => "none in the set".into(),
            },
            dark_subtracted: subtracted.is_some(),
            noise_channel_scale: match encoding {
                Encoding::Raw => options.resolution.channel_variance_scale(),
                Encoding::Dn16 => [1.0; 3],
            },
            noise_shared_cfa_sample: first.cfa_pattern.clone().filter(|_| full_raw),
            undistortion: String::new(),
            backing: None,
        };
        // The lights' raw colours: the stack demosaic scales each light's missing channels by
        // them (the LEDs' power cancels out).
        let illuminants: Vec<[f64; 3]> = self
            .rig
            .leds
            .iter()
            .map(|led| std::array::from_fn(|c| led.color[c] * self.rig.sensor.channel_gain[c]))
            .collect();
        let shading = full_raw
            .then(|| {
                super::led_shading::led_shading_field(
                    &self.rig,
                    image.width,
                    image.height,
                    image.window,
                )
            })
            .flatten();
        let developed = develop_frames_timed(
            lights,
            // Binned frames had it subtracted in their linear pass.
            dark_frame.filter(|_| subtracted.is_some() && !bin),
            Some(&illuminants),
            shading.as_ref(),
            options.resolution,
            clock,
        )
        .map_err(|e| Error::capture_set(&self.dir, e.to_string()))?;
        info.backing = developed.backing;
        let (width, height) = match encoding {
            Encoding::Raw => options.resolution.size(image.width, image.height),
            Encoding::Dn16 => (image.width, image.height),
        };
        Ok(LoadedFrames {
            frames: Frames {
                width,
                height,
                window: options.resolution.window(image.window),
                lights: developed.frames,
            },
            info,
        })
    }

    /// RAW metadata against the camera settings the manifest recorded at capture.
    fn check_camera_settings(&self, metas: &[(String, &RawMeta)]) -> Result<()> {
        let settings = &self.manifest.camera;
        let close = |a: f64, b: f64| (a / b - 1.0).abs() <= 0.01;
        let mut odd = Vec::new();
        for (file, meta) in metas {
            if let (Some(want), Some(got)) = (settings.iso, meta.iso) {
                if want != got {
                    odd.push(format!("{file} has ISO {got}, the manifest ISO {want}"));
                }
            }
            if let (Some(want), Some(got)) = (settings.shutter_s, meta.shutter_s) {
                if !close(got, want) {
                    odd.push(format!("{file} has shutter {got} s, the manifest {want} s"));
                }
            }
            if let (Some(want), Some(got)) = (settings.aperture, meta.aperture) {
                if !close(got, want) {
                    odd.push(format!(
                        "{file} has aperture f/{got}, the manifest f/{want}"
                    ));
                }
            }
        }
        if odd.is_empty() {
            Ok(())
        } else {
            Err(Error::capture_set(
                &self.dir,
                format!(
                    "frames disagree with the camera settings recorded at capture: {}",
                    odd.join("; ")
                ),
            ))
        }
    }
}

#[cfg(test)]
mod tests;
