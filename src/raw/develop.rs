//! From a frame's bytes to linear planes, whatever the frame's encoding, and the checks a set
//! of RAW frames must pass before they are solved together: same camera, same size, same ISO,
//! shutter and aperture.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use rayon::prelude::*;

use super::decode::{decode_raw_keeping, DecodedRaw, RawMeta};
use super::hue::Backing;
use super::linear::{decode_dn_frame, Levels, SizedFrame};
use super::mosaic::{subtract_dark, DarkFrame, LinearMosaic, Resolution, SharedDark};
use super::pass::{self, LinearPass, SampleCounts};
use super::shading::ShadingField;
use super::stack::{develop_stack, Developed};
use crate::error::{Error, Result};
use crate::math::{select::select, MAD_TO_SIGMA};
use crate::plane::LightFrame;
use crate::timing::{Busy, StageClock};

/// How frames are stored in a capture set (`image.encoding` in the manifest).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// 16-bit RGB PNG/TIFF of raw digital numbers.
    Dn16,
    /// Camera RAW files.
    Raw,
}

impl Encoding {
    /// The encoding a manifest names (`dn16`, `raw`); `None` for any other name.
    pub fn parse(name: &str) -> Option<Encoding> {
        match name {
            "dn16" => Some(Encoding::Dn16),
            "raw" => Some(Encoding::Raw),
            _ => None,
        }
    }

    /// The encoding's name as manifests write it (`dn16`, `raw`).
    pub fn name(self) -> &'static str {
        match self {
            Encoding::Dn16 => "dn16",
            Encoding::Raw => "raw",
        }
    }
}

/// How to develop a set's frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct DevelopOptions {
    /// How CFA samples become RGB pixels (RAW frames; dn16 frames are already RGB).
    pub resolution: Resolution,
    /// Subtract the set's all-off frame, when it has one.
    pub subtract_dark: bool,
}

impl Default for DevelopOptions {
    fn default() -> Self {
        DevelopOptions {
            resolution: Resolution::Full,
            subtract_dark: true,
        }
    }
}

/// One frame, decoded and linearised, not yet developed.
#[derive(Clone, Debug)]
pub struct DecodedFrame {
    /// The frame's linear values: RGB planes or CFA samples.
    pub data: FrameData,
    /// The camera's metadata (RAW frames).
    pub meta: Option<RawMeta>,
    /// The levels the frame was linearised with (RAW: the mean of the CFA sites' black levels).
    pub levels: Levels,
    /// The CFA pattern (RAW frames), e.g. "RGGB".
    pub cfa_pattern: Option<String>,
    /// Size of the stored image (RAW: the mosaic).
    pub stored_size: (usize, usize),
    /// White-balanced camera RGB to linear sRGB (RAW frames with a colour matrix).
    pub camera_to_srgb: Option<[[f64; 3]; 3]>,
    /// What the linear pass counted for the plausibility check (RAW frames; zero for dn16).
    pub counts: SampleCounts,
}

/// A decoded frame's values.
#[derive(Clone, Debug)]
pub enum FrameData {
    /// R, G and B at every pixel (dn16 frames).
    Rgb(LightFrame),
    /// CFA samples (RAW frames).
    Mosaic(LinearMosaic),
    /// RAW frames binned 2x2 as they were linearised (`RawPrep::bin`), the dark frame
    /// subtracted where the pass had one.
    Binned(LightFrame),
}

/// What becomes of a RAW frame's samples once decoded: one pass (see `raw::pass`) that
/// linearises them, counts them for the plausibility check, subtracts `pass.dark` and, with
/// `bin`, bins them 2x2.
#[derive(Clone, Copy, Debug, Default)]
pub struct RawPrep<'a> {
    /// The dark frame to subtract and the floor to count below.
    pub pass: LinearPass<'a>,
    /// Bin 2x2 in the pass (half resolution).
    pub bin: bool,
    /// Keep the samples as their DN, linearised where read (`pass::keep_dn`): the light
    /// frames of a full-resolution stack, whose samples are read a row at a time.
    pub keep_dn: bool,
}

/// Decodes and linearises one frame. `dn16_levels` linearise dn16 frames; RAW frames carry
/// their own.
pub fn decode_frame(
    bytes: Vec<u8>,
    path: &Path,
    encoding: Encoding,
    dn16_levels: &Levels,
) -> Result<DecodedFrame> {
    // Untimed: the stages go to a clock nobody reads.
    let busy = Busy::new(&DECODE_STAGES);
    let coded = decode_codec(bytes, path, encoding, dn16_levels, &busy).0?;
    let mut frame = finish_decode(coded, path, RawPrep::default(), &busy)?;
    // One frame at a time, for readers of its planes: a dn16 frame's DN become `f32` planes.
    if let FrameData::Rgb(f) = frame.data {
        frame.data = FrameData::Rgb(f.with_planes());
    }
    Ok(frame)
}

/// The stages [`decode_codec`] and [`finish_decode`] record: the RAW codec (rawler), the
/// linearisation to `f32` (black and white level), the pass that also subtracts the dark
/// frame and bins (`RawPrep::bin`), a dn16 frame's decode, linearised as it is inflated, and
/// the pass over a RAW light frame kept as DN (`RawPrep::keep_dn`).
pub const DECODE_STAGES: [&str; 5] = [
    "decode",
    "linearize",
    BINNING_PASS_STAGE,
    DN16_DECODE_STAGE,
    KEEP_DN_STAGE,
];

/// The stage name of the pass over a light frame kept as DN (`pass::keep_dn`): its
/// saturation flags and plausibility counts.
pub const KEEP_DN_STAGE: &str = "flag saturation";

/// The stage name of a dn16 frame's decode, which linearises its rows as they are inflated.
pub const DN16_DECODE_STAGE: &str = "decode + linearize";

/// The stage name of the one pass that linearises, subtracts the dark frame and bins 2x2.
pub const BINNING_PASS_STAGE: &str = "linearize, dark, bin 2x2";

impl<'a> RawPrep<'a> {
    /// The light frames' pass of a set: counted against `dark`'s read noise where there is
    /// one (see [`below_black_floor`]); with `bin`, binned 2x2 and, with `subtract`, `dark`
    /// subtracted in the same pass (at full resolution it is subtracted later, with the
    /// stack).
    pub fn for_lights(dark: Option<&'a DecodedFrame>, subtract: bool, bin: bool) -> Self {
        let dark_mosaic = match dark.map(|d| &d.data) {
            Some(FrameData::Mosaic(m)) if bin && subtract => Some(m),
            _ => None,
        };
        RawPrep {
            pass: LinearPass {
                dark: dark_mosaic,
                below_black_floor: dark.and_then(below_black_floor),
            },
            bin,
            keep_dn: !bin,
        }
    }
}

/// A frame through its codec, before its linear pass: a set decodes every frame's codec at
/// once (one per core), then runs the light frames' passes with the dark frame in hand.
pub enum Coded {
    /// A RAW frame's CFA samples as stored.
    Raw(Box<DecodedRaw>),
    /// A dn16 frame, decoded and linearised in one go (see `decode_dn_frame`).
    Done(Box<DecodedFrame>),
}

impl Coded {
    /// A decoded dn16 frame (`decode_dn_frame`), linearised with `levels`.
    pub fn dn16((frame, stored_size): SizedFrame, levels: &Levels) -> Coded {
        Coded::Done(Box::new(DecodedFrame {
            data: FrameData::Rgb(frame),
            meta: None,
            levels: *levels,
            cfa_pattern: None,
            stored_size,
            camera_to_srgb: None,
            counts: SampleCounts::default(),
        }))
    }

    /// The size of the stored image (RAW: the mosaic).
    pub fn stored_size(&self) -> (usize, usize) {
        match self {
            Coded::Raw(raw) => (raw.mosaic.width, raw.mosaic.height),
            Coded::Done(frame) => frame.stored_size,
        }
    }
}

/// Runs a frame's codec (rawler, or the dn16 decoder, which linearises as it goes), its time
/// going to `busy`; hands back the buffer `bytes` came in (empty where the codec still holds
/// it), for the next frame's bytes.
pub fn decode_codec(
    bytes: Vec<u8>,
    path: &Path,
    encoding: Encoding,
    dn16_levels: &Levels,
    busy: &Busy,
) -> (Result<Coded>, Vec<u8>) {
    match encoding {
        Encoding::Dn16 => {
            let decoded = busy.time(DN16_DECODE_STAGE, || {
                decode_dn_frame(&bytes, path, dn16_levels)
            });
            (decoded.map(|frame| Coded::dn16(frame, dn16_levels)), bytes)
        }
        Encoding::Raw => {
            let (raw, bytes) = busy.time("decode", || decode_raw_keeping(bytes, path));
            (raw.map(|raw| Coded::Raw(Box::new(raw))), bytes)
        }
    }
}

/// A RAW frame's linear pass as `prep` says (see `raw::pass`), its time going to `busy`; a
/// dn16 frame is already done.
pub fn finish_decode(
    coded: Coded,
    path: &Path,
    prep: RawPrep,
    busy: &Busy,
) -> Result<DecodedFrame> {
    let raw = match coded {
        Coded::Done(frame) => return Ok(*frame),
        Coded::Raw(raw) => raw,
    };
    let levels = Levels {
        black: raw.mosaic.mean_black(),
        white: raw.mosaic.white as f64,
    };
    let cfa_pattern = Some(raw.mosaic.pattern_name());
    let stored_size = (raw.mosaic.width, raw.mosaic.height);
    let DecodedRaw {
        mosaic,
        meta,
        camera_to_srgb,
    } = *raw;
    let (data, counts) = if prep.bin {
        busy.time(BINNING_PASS_STAGE, || pass::bin2x2(&mosaic, prep.pass))
            .map(|(frame, counts)| (FrameData::Binned(frame), counts))
    } else if prep.keep_dn && prep.pass.dark.is_none() {
        busy.time(KEEP_DN_STAGE, || pass::keep_dn(mosaic, prep.pass))
            .map(|(mosaic, counts)| (FrameData::Mosaic(mosaic), counts))
    } else {
        busy.time("linearize", || pass::linearize(&mosaic, prep.pass))
            .map(|(mosaic, counts)| (FrameData::Mosaic(mosaic), counts))
    }
    .map_err(|e| Error::image(path, e))?;
    Ok(DecodedFrame {
        data,
        counts,
        levels,
        cfa_pattern,
        stored_size,
        meta: Some(meta),
        camera_to_srgb,
    })
}

/// Develops a set's light frames: the dark frame (when given) subtracted, RAW frames binned
/// (half) or demosaiced as a stack (full, see `mosaic::develop_stack`; `illuminants` are the
/// lights' raw colours, one per light frame). Half resolution exists for RAW frames only.
pub fn develop_frames(
    lights: Vec<DecodedFrame>,
    dark: Option<DecodedFrame>,
    illuminants: Option<&[[f64; 3]]>,
    resolution: Resolution,
) -> Result<Vec<LightFrame>> {
    let developed = develop_frames_timed(
        lights,
        dark,
        illuminants,
        None,
        resolution,
        &mut StageClock::start(),
    )?;
    Ok(developed.frames)
}

/// [`develop_frames`], timing the dark subtraction and the demosaic (or binning) as stages
/// of `clock`; the full-resolution demosaic interpolates the sites' albedos when `shading`
/// gives the frames' shading vectors (see `stack::develop_stack`).
pub fn develop_frames_timed(
    lights: Vec<DecodedFrame>,
    dark: Option<DecodedFrame>,
    illuminants: Option<&[[f64; 3]]>,
    shading: Option<&ShadingField>,
    resolution: Resolution,
    clock: &mut StageClock,
) -> Result<Developed> {
    let mut rgb = Vec::new();
    let mut mosaics = Vec::new();
    let mut binned = Vec::new();
    for frame in lights {
        match frame.data {
            FrameData::Rgb(f) => rgb.push(f),
            FrameData::Mosaic(m) => mosaics.push(m),
            FrameData::Binned(f) => binned.push(f),
        }
    }
    let kinds = [rgb.len(), mosaics.len(), binned.len()];
    if kinds.iter().filter(|&&n| n > 0).count() > 1 {
        return Err(Error::Invalid(
            "a set mixes RGB frames and RAW frames (or binned and unbinned RAW frames)".into(),
        ));
    }
    if !binned.is_empty() {
        // The linear pass already subtracted the dark frame it was given and binned.
        if resolution != Resolution::Half || dark.is_some() {
            return Err(Error::Invalid(
                "frames binned as they were decoded are developed at half resolution, their \
                 dark frame already subtracted"
                    .into(),
            ));
        }
        return Ok(Developed {
            frames: binned,
            backing: None,
        });
    }
    if !rgb.is_empty() {
        if resolution != Resolution::Full {
            return Err(Error::Unsupported(
                "half resolution is 2x2 CFA binning of RAW frames; this set stores dn16 RGB \
                 frames, solve it at full resolution"
                    .into(),
            ));
        }
        if let Some(dark) = dark {
            let FrameData::Rgb(dark) = dark.data else {
                return Err(Error::Invalid("a RAW dark frame in a dn16 set".into()));
            };
            clock.time(DARK_STAGE, || {
                let dark = DarkFrame::of(dark);
                rgb.par_iter_mut().try_for_each(|f| subtract_dark(f, &dark))
            })?;
        }
        return Ok(Developed {
            frames: rgb,
            backing: None,
        });
    }
    if let Some(dark) = dark {
        let FrameData::Mosaic(dark) = dark.data else {
            return Err(Error::Invalid("an RGB dark frame in a RAW set".into()));
        };
        // Each frame independently: one per core. Frames kept as DN share the dark frame's
        // samples and subtract them where read.
        clock.time(DARK_STAGE, || {
            let dark = SharedDark::of(dark)?;
            mosaics
                .par_iter_mut()
                .try_for_each(|m| m.subtract_shared(&dark))
        })?;
    }
    let stage = match resolution {
        Resolution::Full => "demosaic",
        Resolution::Half => "bin 2x2",
    };
    clock.time(stage, || {
        develop_stack(mosaics, illuminants, shading, resolution)
    })
}

/// The stage name of the dark-frame subtraction.
pub const DARK_STAGE: &str = "dark subtraction";

/// Checks that RAW frames were shot alike: same camera, size, ISO, shutter and aperture.
/// `frames` pairs each file's name with its metadata; the error lists which files hold which
/// value for every property that differs.
pub fn check_consistent(frames: &[(String, &RawMeta)]) -> std::result::Result<(), String> {
    type Property = (&'static str, fn(&RawMeta) -> String);
    let properties: [Property; 5] = [
        ("camera model", |m| m.camera()),
        ("resolution", |m| format!("{}x{}", m.width, m.height)),
        ("ISO", |m| m.iso.map_or("unknown".into(), |v| v.to_string())),
        ("shutter", |m| {
            m.shutter_s
                .map_or("unknown".into(), |v| format!("{v:.6} s"))
        }),
        ("aperture", |m| {
            m.aperture.map_or("unknown".into(), |v| format!("f/{v:.2}"))
        }),
    ];
    let mut problems = Vec::new();
    for (name, value) in properties {
        let mut groups: BTreeMap<String, Vec<&str>> = BTreeMap::new();
        for (file, meta) in frames {
            groups.entry(value(meta)).or_default().push(file);
        }
        if groups.len() > 1 {
            let listed: Vec<String> = groups
                .iter()
                .map(|(v, files)| format!("{v} in {}", files.join(", ")))
                .collect();
            problems.push(format!("{name} differs: {}", listed.join("; ")));
        }
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "the frames were not shot alike ({}); re-shoot the odd frames with the set's settings",
            problems.join(". ")
        ))
    }
}

/// How many read-noise standard deviations below the black level a sample must lie to be
/// impossible for a working sensor: a Gaussian reaches -6 sigma once in 1e9 samples.
const BELOW_BLACK_SIGMAS: f32 = 6.0;
/// The share of a frame's samples that may lie that far below black (hot and cold pixels,
/// non-Gaussian read-noise tails) before the frame is called garbage: 1e5 times the Gaussian
/// expectation, and at least this many samples in absolute terms.
const BELOW_BLACK_SHARE: f64 = 1e-4;
const BELOW_BLACK_MIN_SAMPLES: usize = 16;

/// Catches RAW frames that decoded to garbage (a damaged compressed stream decodes into
/// samples wandering over the whole range): against the all-off frame's read noise, a light
/// frame may not hold samples far below the black level (the shutter only adds light), and it
/// may not be mostly clipped at the white level. The counts come from each frame's linear
/// pass (`DecodedFrame::counts`), the floor from [`below_black_floor`]; without one only the
/// clipping test runs. `frames` pairs file names with their counts.
pub fn check_plausible(frames: &[(String, SampleCounts)]) -> std::result::Result<(), String> {
    let problems: Vec<String> = frames
        .iter()
        .filter_map(|(name, counts)| {
            let n = counts.samples.max(1);
            if counts.clipped * 2 > n {
                return Some(format!(
                    "{name}: {:.0} % of its samples are clipped at the white level",
                    100.0 * counts.clipped as f64 / n as f64
                ));
            }
            let below = counts.below_floor?;
            let allowed = BELOW_BLACK_MIN_SAMPLES.max((BELOW_BLACK_SHARE * n as f64) as usize);
            (below > allowed).then(|| {
                format!(
                    "{name}: {below} of its {n} samples lie more than {BELOW_BLACK_SIGMAS} \
                     times the dark frame's read noise below its level, which no \
                     exposure gives"
                )
            })
        })
        .collect();
    if problems.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "frames that decode to garbage (a damaged file whose checksum was updated, or a \
             fault in the camera): {}; re-shoot them",
            problems.join("; ")
        ))
    }
}

/// The linear level under which a light frame's sample is impossibly far below black:
/// `BELOW_BLACK_SIGMAS` times the dark frame's read noise (its median absolute deviation,
/// so a few hot pixels do not inflate it) below its median. `None` for a dark frame with no
/// spread (or not a RAW one): the below-black test then does not run.
///
/// Measured on at most 2^20 samples (`FLOOR_SAMPLES`) spread evenly over the frame: the light
/// frames wait for this floor, and the two selections over all of a 16 MP dark frame's
/// samples kept the cores partly idle for about 0.15 s at the start of every solve.
pub fn below_black_floor(dark: &DecodedFrame) -> Option<f32> {
    let FrameData::Mosaic(m) = &dark.data else {
        return None;
    };
    floor_of(&spread_sample(&m.values, FLOOR_SAMPLES))
}

/// [`below_black_floor`] of these dark samples, all of them.
fn floor_of(values: &[f32]) -> Option<f32> {
    let (median, sigma) = median_and_sigma(values);
    (sigma > 0.0).then_some(median - BELOW_BLACK_SIGMAS * sigma)
}

/// Samples the dark frame's floor is measured on. For Gaussian read noise the median and the
/// MAD of `n` samples have standard errors of about `1.25 sigma / sqrt(n)` and
/// `1.17 sigma / sqrt(n)`, so the floor, 6 sigma below the median, has one of about
/// `7.1 sigma / sqrt(n)`: 0.7 % of sigma here. A light frame's count below it changes by a
/// share of its samples far under `BELOW_BLACK_SHARE`.
const FLOOR_SAMPLES: usize = 1 << 20;

/// At most `n` of `values`, every `k`-th from the first, `k` odd so that consecutive picks
/// alternate between the columns (and, row after row, the rows) of each CFA cell's sites.
fn spread_sample(values: &[f32], n: usize) -> std::borrow::Cow<'_, [f32]> {
    if values.len() <= n {
        return std::borrow::Cow::Borrowed(values);
    }
    let k = values.len().div_ceil(n) | 1;
    std::borrow::Cow::Owned(values.iter().step_by(k).copied().collect())
}

/// The median of `values` and the standard deviation of Gaussian noise about it, from the
/// median absolute deviation; non-finite values are left out. Selected on every core without
/// a copy ([`select`]: the values `select_nth_unstable` finds in a vector of them): a 16 MP
/// dark frame's copy and two selections on one thread took about 0.2 s in which the light
/// frames, which wait for this floor, left the other cores idle.
pub(super) fn median_and_sigma(values: &[f32]) -> (f32, f32) {
    let middle = |n: usize| [n / 2];
    let finite = |i: usize| Some(values[i]).filter(|x| x.is_finite());
    let Some(median) = select(values.len(), finite, middle).map(|s| s.at[0]) else {
        return (0.0, 0.0);
    };
    let deviation = |i: usize| finite(i).map(|x| (x - median).abs());
    let mad = select(values.len(), deviation, middle).map_or(0.0, |s| s.at[0]);
    (median, MAD_TO_SIGMA as f32 * mad)
}

/// How the frames of a solve were decoded and prepared, for the report.
#[derive(Clone, Debug, Serialize)]
pub struct DecodeInfo {
    /// How the frames are stored (`dn16`, `raw`).
    pub encoding: String,
    /// How CFA samples became RGB pixels (RAW sets; dn16 frames are RGB as stored).
    pub resolution: Resolution,
    /// How RGB pixels were made from the stored frames.
    pub method: String,
    /// The CFA pattern of the first light frame (RAW sets), e.g. "RGGB".
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cfa_pattern: Option<String>,
    /// Levels of the first light frame (RAW: the mean black level of its CFA sites).
    pub levels: Levels,
    /// The camera, from the first light frame's metadata (RAW sets).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<RawMeta>,
    /// What was done with the all-off frame.
    pub dark_frame: String,
    /// Whether the all-off frame was subtracted from every light frame.
    pub dark_subtracted: bool,
    /// The noise model's per-channel variance scale (see `NoiseModel::channel_scale`).
    pub noise_channel_scale: [f64; 3],
    /// At full resolution from RAW: every pixel's channels share its own CFA sample's noise;
    /// this is the CFA pattern that says which sample that is (`NoiseModel::shared_cfa_sample`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub noise_shared_cfa_sample: Option<String>,
    /// How lens distortion was handled.
    pub undistortion: String,
    /// The camera's colour matrix as applied to display outputs (`albedo.png`): white-balanced
    /// camera RGB to linear sRGB, from the first light frame; absent when the frames carry
    /// none (dn16 sets, whose channels are taken as sRGB's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera_to_srgb: Option<[[f64; 3]; 3]>,
    /// The material the full-resolution demosaic found seen through the holes of the weave,
    /// whose colour the isolated pixels showing it took (see `hue::backing`); absent where the
    /// isolated pixels agreed on none (or the frames were not demosaiced).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub backing: Option<Backing>,
}

impl DecodeInfo {
    /// Whether each pixel is a 2x2 cell of CFA sites binned (RAW frames at half resolution).
    pub fn binned(&self) -> bool {
        self.resolution == Resolution::Half && self.cfa_pattern.is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta(model: &str, iso: u32, shutter: f64) -> RawMeta {
        RawMeta {
            make: "Nikon".into(),
            model: model.into(),
            width: 4928,
            height: 3264,
            iso: Some(iso),
            shutter_s: Some(shutter),
            aperture: Some(8.0),
        }
    }

    #[test]
    fn frames_shot_alike_pass_and_odd_ones_are_named() {
        let a = meta("D5100", 100, 0.1);
        let b = meta("D5100", 200, 0.1);
        let c = meta("D7000", 100, 0.05);
        let same = vec![("L00.nef".to_string(), &a), ("L01.nef".to_string(), &a)];
        assert!(check_consistent(&same).is_ok());
        let mixed = vec![
            ("L00.nef".to_string(), &a),
            ("L01.nef".to_string(), &b),
            ("L02.nef".to_string(), &c),
        ];
        let err = check_consistent(&mixed).unwrap_err();
        assert!(
            err.contains("camera model differs")
                && err.contains("Nikon D7000 in L02.nef")
                && err.contains("ISO differs")
                && err.contains("200 in L01.nef")
                && err.contains("shutter differs")
                && !err.contains("aperture differs"),
            "{err}"
        );
    }

    #[test]
    fn dn16_frames_have_no_half_resolution() {
        let frame = DecodedFrame {
            data: FrameData::Rgb(LightFrame {
                rgb: crate::plane::RgbPlanes::new(2, 2),
                saturated: None,
                cfa: None,
                dn: None,
                cfa_dn: None,
            }),
            meta: None,
            levels: Levels {
                black: 0.0,
                white: 1.0,
            },
            cfa_pattern: None,
            camera_to_srgb: None,
            stored_size: (2, 2),
            counts: SampleCounts::default(),
        };
        let err = develop_frames(vec![frame], None, None, Resolution::Half)
            .unwrap_err()
            .to_string();
        assert!(err.contains("dn16") && err.contains("RAW"), "{err}");
    }

    /// The floor from the spread sample is the floor from all of a 4 M-sample Gaussian dark
    /// frame within four of its standard errors (about `7.1 sigma / sqrt(n)` for `n` sampled
    /// values: the median's and six times the MAD's, in quadrature), and the sample takes
    /// both columns of the CFA cells.
    #[test]
    fn the_dark_floor_from_a_spread_sample_is_the_whole_frames() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let (level, sigma) = (0.002f32, 0.0004f32);
        let noise = Normal::new(level, sigma).unwrap();
        let values: Vec<f32> = (0..4 << 20).map(|_| noise.sample(&mut rng)).collect();
        let sample = spread_sample(&values, FLOOR_SAMPLES);
        assert!(sample.len() <= FLOOR_SAMPLES && sample.len() > FLOOR_SAMPLES / 2);
        let whole = floor_of(&values).unwrap();
        let spread = floor_of(&sample).unwrap();
        let standard_error = 7.1 * sigma / (sample.len() as f32).sqrt();
        assert!(
            (spread - whole).abs() < 4.0 * standard_error,
            "{spread} vs {whole} (standard error {standard_error})"
        );
        // An even row width: the picks alternate between even and odd columns.
        let width = 4928;
        let k = values.len().div_ceil(FLOOR_SAMPLES) | 1;
        let odd = (0..values.len())
            .step_by(k)
            .filter(|i| i % width % 2 == 1)
            .count();
        assert!(odd * 2 >= sample.len() - 1 && odd * 2 <= sample.len() + 1);
    }

    #[test]
    fn median_and_sigma_are_the_selections_in_a_vector_of_the_finite_values() {
        // Dark-frame-like samples: read noise about a level, hot pixels, NaN and infinities
        // (left out), over more than one block of the selection.
        let mut values: Vec<f32> = (0..(1 << 20) + 4097)
            .map(|i: usize| match i % 1009 {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 => 0.9,
                _ => 0.0015 + ((i * 7919) % 1_048_573) as f32 * 5e-10,
            })
            .collect();
        // An even count, so that the median is the upper of the middle two, as the floor has
        // always taken it.
        if values.iter().filter(|x| x.is_finite()).count() % 2 == 1 {
            values.push(0.0031);
        }
        let mut v: Vec<f32> = values.iter().copied().filter(|x| x.is_finite()).collect();
        let mid = v.len() / 2;
        let median = *v.select_nth_unstable_by(mid, f32::total_cmp).1;
        v.iter_mut().for_each(|x| *x = (*x - median).abs());
        let sigma = 1.4826 * *v.select_nth_unstable_by(mid, f32::total_cmp).1;
        let got = median_and_sigma(&values);
        assert_eq!(
            (got.0.to_bits(), got.1.to_bits()),
            (median.to_bits(), sigma.to_bits()),
            "{got:?} against ({median}, {sigma})"
        );
        assert_eq!(median_and_sigma(&[]), (0.0, 0.0));
        assert_eq!(median_and_sigma(&[f32::NAN, f32::NEG_INFINITY]), (0.0, 0.0));
        assert_eq!(median_and_sigma(&[3.0]), (3.0, 0.0));
    }
}
