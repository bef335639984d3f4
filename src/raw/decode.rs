//! Camera RAW files (NEF, CR2, CR3, ARW, RAF, ORF, DNG: whatever rawler decodes) into a
//! [`Mosaic`] of CFA samples and the camera metadata a capture set is checked with.
//!
//! Corrupt input never panics: rawler's decoders run behind `catch_unwind` (ours wraps the
//! whole call, including the parts rawler does not guard), every error names the file, and
//! containers whose headers claim more than the file holds, loop, or announce an implausibly
//! large image are refused before rawler allocates for them (`guard`).

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::sync::Arc;

use rawler::decoders::{RawDecodeParams, WellKnownIFD};
use rawler::imgop::xyz::Illuminant;
use rawler::rawimage::RawPhotometricInterpretation;
use rawler::rawsource::RawSource;
use rawler::tags::TiffCommonTag;
use rawler::{RawImage, RawImageData};
use serde::Serialize;

use super::mosaic::{Mosaic, BLUE, GREEN, RED};
use crate::error::{Error, Result};

pub use super::guard::MAX_SAMPLES;

/// What a RAW file says about how it was shot.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RawMeta {
    /// Camera maker, as the file names it (rawler's cleaned-up name where it has one).
    pub make: String,
    /// Camera model, as the file names it (rawler's cleaned-up name where it has one).
    pub model: String,
    /// Width of the decoded mosaic in pixels (the sensor's active area).
    pub width: usize,
    /// Height of the decoded mosaic in pixels.
    pub height: usize,
    /// ISO sensitivity from the EXIF data; `None` when the file records none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iso: Option<u32>,
    /// Exposure time in seconds; `None` when the file records none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shutter_s: Option<f64>,
    /// Aperture as an f-number (8.0 for f/8); `None` when the file records none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub aperture: Option<f64>,
}

impl RawMeta {
    /// "make model", as people write it.
    pub fn camera(&self) -> String {
        let make = self.make.trim();
        let model = self.model.trim();
        if model.starts_with(make) {
            model.to_string()
        } else {
            format!("{make} {model}").trim().to_string()
        }
    }
}

/// One decoded RAW frame.
#[derive(Clone, Debug)]
pub struct DecodedRaw {
    /// The frame's CFA samples and levels.
    pub mosaic: Mosaic,
    /// What the file says about how it was shot.
    pub meta: RawMeta,
    /// White-balanced camera RGB to linear sRGB, from the file's colour matrix (D65 or
    /// daylight preferred), when it has a usable one.
    pub camera_to_srgb: Option<[[f64; 3]; 3]>,
}

thread_local! {
    /// Set while this thread runs rawler on a file.
    static DECODING: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Installs a panic hook that stays silent for panics raised while rawler decodes a file (in
/// rawler's code, or in the standard library on the decoding thread), which psscan catches
/// and reports as a clean error naming the file, and behaves as before for every other panic.
/// Call once, early (the CLI does).
pub fn quiet_decoder_panics() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let in_rawler = info
                .location()
                .is_some_and(|l| l.file().contains("/rawler-") || l.file().contains("\\rawler-"));
            if !(in_rawler || DECODING.with(|d| d.get())) {
                previous(info);
            }
        }));
    });
}

/// Reads and decodes the RAW file at `path`.
pub fn read_raw(path: &Path) -> Result<DecodedRaw> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_raw(bytes, path)
}

/// Decodes a RAW file already in memory; `path` names it in errors.
pub fn decode_raw(bytes: Vec<u8>, path: &Path) -> Result<DecodedRaw> {
    decode_raw_keeping(bytes, path).0
}

/// [`decode_raw`], handing back the buffer `bytes` came in once the decoder is done with it,
/// for the next file's bytes (a 16 MP frame's 60 MB of fresh memory spared); empty where the
/// decoder still holds it.
pub fn decode_raw_keeping(bytes: Vec<u8>, path: &Path) -> (Result<DecodedRaw>, Vec<u8>) {
    if bytes.is_empty() {
        let err = Error::image(path, "is empty (0 bytes): not a RAW file");
        return (Err(err), bytes);
    }
    if let Err(m) = super::guard::check_structure(&bytes) {
        return (Err(Error::image(path, format!("is corrupt: {m}"))), bytes);
    }
    let shared = Arc::new(bytes);
    let decoded = {
        let source = RawSource::new_from_shared_vec(Arc::clone(&shared)).with_path(path);
        DECODING.with(|d| d.set(true));
        let decoded = catch_unwind(AssertUnwindSafe(|| decode_source(&source)));
        DECODING.with(|d| d.set(false));
        decoded
    };
    let result = match decoded {
        Ok(Ok((image, meta))) => to_mosaic(image, meta).map_err(|m| Error::image(path, m)),
        Ok(Err(message)) => Err(Error::image(path, message)),
        Err(_) => Err(Error::image(
            path,
            "the RAW decoder failed on this file (it is corrupt or of an unsupported kind)",
        )),
    };
    (result, Arc::try_unwrap(shared).unwrap_or_default())
}

/// Whether `bytes` are a camera RAW file rawler can read, and the raw image size its header
/// declares where the container says (`None` where it does not, e.g. CR3). Only the
/// container is parsed (after the same structural guard as [`decode_raw`]); no pixel is
/// decoded, so this is cheap enough to run on every frame as it is captured.
pub fn probe_raw(bytes: &[u8]) -> std::result::Result<Option<(usize, usize)>, String> {
    super::guard::check_structure(bytes).map_err(|m| format!("is corrupt: {m}"))?;
    let source = RawSource::new_from_shared_vec(Arc::new(bytes.to_vec()));
    DECODING.with(|d| d.set(true));
    let probed = catch_unwind(AssertUnwindSafe(|| {
        let decoder = rawler::get_decoder(&source)
            .map_err(|e| format!("is not a camera RAW file psscan can read: {e}"))?;
        let dims = match decoder.ifd(WellKnownIFD::Raw) {
            Ok(Some(ifd)) => {
                let dim = |tag| ifd.get_entry(tag).map(|e| e.force_usize(0));
                match (
                    dim(TiffCommonTag::ImageWidth),
                    dim(TiffCommonTag::ImageLength),
                ) {
                    (Some(w), Some(h)) => Some((w, h)),
                    _ => None,
                }
            }
            _ => None,
        };
        Ok(dims)
    }));
    DECODING.with(|d| d.set(false));
    probed.unwrap_or_else(|_| Err("the RAW decoder failed on this file's header".into()))
}

fn decode_source(source: &RawSource) -> std::result::Result<(RawImage, RawMeta), String> {
    let reject = |e: rawler::RawlerError| format!("cannot decode as a camera RAW file: {e}");
    let decoder = rawler::get_decoder(source).map_err(reject)?;
    // Refuse absurd sizes before the decoder allocates for them.
    if let Ok(Some(ifd)) = decoder.ifd(WellKnownIFD::Raw) {
        let dim = |tag| ifd.get_entry(tag).map(|e| e.force_usize(0));
        if let (Some(w), Some(h)) = (
            dim(TiffCommonTag::ImageWidth),
            dim(TiffCommonTag::ImageLength),
        ) {
            if w.saturating_mul(h) > MAX_SAMPLES {
                return Err(format!(
                    "header announces a {w}x{h} image, larger than any camera's: corrupt file"
                ));
            }
        }
    }
    let params = RawDecodeParams::default();
    let image = decoder.raw_image(source, &params, false).map_err(reject)?;
    let metadata = decoder.raw_metadata(source, &params).map_err(reject)?;
    let exif = &metadata.exif;
    let iso = exif
        .iso_speed_ratings
        .map(u32::from)
        .or(exif.iso_speed)
        .or(exif.recommended_exposure_index)
        .filter(|&v| v > 0);
    let positive = |v: f64| (v.is_finite() && v > 0.0).then_some(v);
    let meta = RawMeta {
        make: first_nonempty(&image.clean_make, &image.make),
        model: first_nonempty(&image.clean_model, &image.model),
        width: 0,
        height: 0,
        iso,
        shutter_s: exif
            .exposure_time
            .and_then(|r| positive(r.n as f64 / r.d as f64)),
        aperture: exif.fnumber.and_then(|r| positive(r.n as f64 / r.d as f64)),
    };
    Ok((image, meta))
}

fn first_nonempty(a: &str, b: &str) -> String {
    if a.trim().is_empty() { b } else { a }.trim().to_string()
}

/// The active area's CFA samples, levels and pattern.
fn to_mosaic(mut image: RawImage, mut meta: RawMeta) -> std::result::Result<DecodedRaw, String> {
    if image.cpp != 1 {
        return Err(format!(
            "holds {} values per pixel (an already demosaiced or linear DNG); psscan needs the \
             camera's CFA samples",
            image.cpp
        ));
    }
    let cfa = match &image.photometric {
        RawPhotometricInterpretation::Cfa(config) => config.cfa.clone(),
        other => {
            return Err(format!(
                "is not a colour-filter-array image ({other:?}); psscan needs Bayer CFA samples"
            ))
        }
    };
    // Taken out of the image: the active area is cropped out of it in place (a second
    // frame-sized buffer per frame would be fresh memory, see `crate::alloc`).
    let data = match std::mem::replace(&mut image.data, RawImageData::Integer(Vec::new())) {
        RawImageData::Integer(data) => data,
        RawImageData::Float(_) => {
            return Err(
                "holds floating-point samples (a processed DNG); psscan needs the camera's integer CFA samples"
                    .into(),
            )
        }
    };
    let (full_w, full_h) = (image.width, image.height);
    if data.len() != full_w * full_h || full_w == 0 || full_h == 0 {
        return Err(format!(
            "decoded {} samples for a {full_w}x{full_h} image",
            data.len()
        ));
    }
    let (x0, y0, width, height) = match image.active_area {
        Some(a) if a.d.w > 0 && a.d.h > 0 && a.p.x + a.d.w <= full_w && a.p.y + a.d.h <= full_h => {
            (a.p.x, a.p.y, a.d.w, a.d.h)
        }
        Some(a) => {
            return Err(format!(
                "active area {a:?} lies outside the {full_w}x{full_h} image"
            ))
        }
        None => (0, 0, full_w, full_h),
    };
    if cfa.width != 2 || cfa.height != 2 {
        return Err(format!(
            "CFA pattern \"{}\" ({}x{}) is not a 2x2 Bayer pattern; psscan develops Bayer sensors only",
            cfa.name, cfa.width, cfa.height
        ));
    }
    let mut pattern = [[0u8; 2]; 2];
    for (j, row) in pattern.iter_mut().enumerate() {
        for (i, site) in row.iter_mut().enumerate() {
            *site = match cfa.color_at(y0 + j, x0 + i) {
                0 => RED,
                1 => GREEN,
                2 => BLUE,
                other => return Err(format!("CFA colour {other} is not R, G or B")),
            };
        }
    }
    let black = site_black_levels(&image, x0, y0)?;
    let white = match image.whitelevel.0.first() {
        Some(&w) if w > 0 => w as f32,
        _ => return Err("has no white level".into()),
    };
    let samples = crop_in_place(data, full_w, (x0, y0, width, height));
    meta.width = width;
    meta.height = height;
    let mosaic = Mosaic {
        width,
        height,
        pattern,
        black,
        white,
        samples,
    };
    mosaic.validate().map_err(|e| e.to_string())?;
    let camera_to_srgb = image
        .color_matrix_find_first([Illuminant::D65, Illuminant::Daylight, Illuminant::D50])
        .or_else(|| {
            image
                .color_matrix
                .iter()
                .next()
                .map(|(i, m)| (*i, m.clone()))
        })
        .and_then(|(_, matrix)| super::colour::camera_to_srgb(&matrix));
    Ok(DecodedRaw {
        mosaic,
        meta,
        camera_to_srgb,
    })
}

/// The `width x height` window at (`x0`, `y0`) of the row-major image `data` (rows of
/// `full_w`), moved to the front of the same buffer row by row and the rest cut off. Each
/// row moves toward the start, never past a row not yet moved, so no sample is overwritten
/// before it is read.
fn crop_in_place(
    mut data: Vec<u16>,
    full_w: usize,
    (x0, y0, width, height): (usize, usize, usize, usize),
) -> Vec<u16> {
    if (x0, y0, width) != (0, 0, full_w) {
        for y in 0..height {
            let from = (y0 + y) * full_w + x0;
            data.copy_within(from..from + width, y * width);
        }
    }
    data.truncate(width * height);
    data
}

/// The black level of each of the four CFA sites of the active area. rawler's black-level
/// pattern repeats from the image origin; a pattern that is not 1x1 or 2x2 is averaged over
/// the samples of each site within one repeat.
fn site_black_levels(
    image: &RawImage,
    x0: usize,
    y0: usize,
) -> std::result::Result<[[f32; 2]; 2], String> {
    let b = &image.blacklevel;
    let (bw, bh) = (b.width.max(1), b.height.max(1));
    let levels = b.as_vec();
    if levels.len() < bw * bh * b.cpp.max(1) || levels.is_empty() {
        return Err(format!(
            "black level pattern {bw}x{bh} has {} values",
            levels.len()
        ));
    }
    let at = |x: usize, y: usize| levels[((y % bh) * bw + (x % bw)) * b.cpp.max(1)];
    // One repeat of the black pattern that also repeats the CFA: lcm(b, 2) in each direction.
    let (rw, rh) = (
        if bw % 2 == 0 { bw } else { 2 * bw },
        if bh % 2 == 0 { bh } else { 2 * bh },
    );
    let mut black = [[0.0f32; 2]; 2];
    for (j, row) in black.iter_mut().enumerate() {
        for (i, site) in row.iter_mut().enumerate() {
            let mut sum = 0.0f64;
            let mut n = 0usize;
            for y in (j..rh).step_by(2) {
                for x in (i..rw).step_by(2) {
                    sum += at(x0 + x, y0 + y) as f64;
                    n += 1;
                }
            }
            *site = (sum / n as f64) as f32;
        }
    }
    Ok(black)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The active area cropped in place is what copying its rows out gives, for windows at
    /// the origin, offset in x, in y, in both, one row, and the whole image.
    #[test]
    fn cropping_in_place_gives_the_windows_rows() {
        let (full_w, full_h) = (13, 9);
        let image: Vec<u16> = (0..(full_w * full_h) as u16).collect();
        for window in [
            (0, 0, 13, 9),
            (0, 0, 5, 4),
            (3, 0, 10, 9),
            (0, 2, 13, 7),
            (2, 3, 7, 5),
            (4, 8, 9, 1),
        ] {
            let (x0, y0, w, h) = window;
            let want: Vec<u16> = (y0..y0 + h)
                .flat_map(|y| image[y * full_w + x0..y * full_w + x0 + w].to_vec())
                .collect();
            assert_eq!(
                crop_in_place(image.clone(), full_w, window),
                want,
                "{window:?}"
            );
        }
    }
    use crate::raw::mosaic::Resolution;

    /// A RAW file shipped with the tests (tests/data/raw, sources and licences in its README).
    fn shipped(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data/raw")
            .join(name)
    }

    #[test]
    fn the_real_canon_dng_decodes_with_its_levels_and_pattern() {
        let path = shipped("real-canon550d-colorchart.dng");
        let raw = read_raw(&path).unwrap();
        let m = &raw.mosaic;
        assert_eq!(m.pattern_name(), "RGGB");
        assert_eq!(m.black, [[2056.0; 2]; 2]);
        assert_eq!(m.white, 15000.0);
        // The active area (ActiveArea 26, 152, 1182, 1886) of the 1888x1182 sensor read-out;
        // the CFA pattern is relative to it, as dcraw reports ("RG/GB", 1734 x 1156).
        assert_eq!((m.width, m.height), (1734, 1156));
        let camera = raw.meta.camera();
        assert!(
            camera.contains("550D") || camera.contains("Kiss X4"),
            "{:?}",
            raw.meta
        );
        // A real photograph: samples spread over the range, none below the black level by
        // more than noise.
        let min = *m.samples.iter().min().unwrap() as f32;
        let max = *m.samples.iter().max().unwrap() as f32;
        assert!(min > 2056.0 - 200.0 && max > 4000.0, "{min}..{max}");
        // Its colour matrix gives display colour: white stays white, and the 550D's primaries
        // are not sRGB's, so the conversion mixes channels.
        let to_srgb = raw.camera_to_srgb.expect("the DNG carries a colour matrix");
        for row in to_srgb {
            assert!((row.iter().sum::<f64>() - 1.0).abs() < 1e-9, "{to_srgb:?}");
        }
        assert!(to_srgb[0][0] > 1.1 && to_srgb[0][1] < -0.05, "{to_srgb:?}");

        let half = m.develop(Resolution::Half).unwrap();
        assert_eq!((half.rgb.width(), half.rgb.height()), (867, 578));
        // Each binned pixel is its cell's samples, linearised.
        let lin =
            |x: usize, y: usize| (m.samples[y * m.width + x] as f32 - 2056.0) / (15000.0 - 2056.0);
        for &(u, v) in &[(0, 0), (500, 300), (866, 577)] {
            let (x, y) = (2 * u, 2 * v);
            assert!((half.rgb.r.get(u, v) - lin(x, y)).abs() < 1e-6);
            assert!((half.rgb.g.get(u, v) - 0.5 * (lin(x + 1, y) + lin(x, y + 1))).abs() < 1e-6);
            assert!((half.rgb.b.get(u, v) - lin(x + 1, y + 1)).abs() < 1e-6);
        }
        // The saturation mask flags exactly the cells with a sample near the white level.
        let threshold = m.saturation_threshold();
        let sat = half.saturated.as_ref().unwrap();
        let mut expected = 0;
        for v in 0..578 {
            for u in 0..867 {
                let any = (0..4).any(|k| {
                    m.samples[(2 * v + k / 2) * m.width + 2 * u + k % 2] as f32 >= threshold
                });
                assert_eq!(sat.data[v * 867 + u], any);
                expected += any as usize;
            }
        }
        assert_eq!(sat.count(), expected);
    }

    #[test]
    fn stripped_real_files_fail_cleanly_naming_the_file() {
        for name in [
            "stripped-Nikon.nef",
            "stripped-CanonRaw.cr2",
            "stripped-CanonRaw.cr3",
            "stripped-DNG.dng",
        ] {
            let err = read_raw(&shipped(name)).unwrap_err().to_string();
            assert!(err.contains(name), "{name}: {err}");
        }
    }

    #[test]
    fn empty_truncated_and_garbage_files_fail_cleanly_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let real = std::fs::read(shipped("real-canon550d-colorchart.dng")).unwrap();
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("empty.dng", Vec::new()),
            ("header-only.dng", real[..512].to_vec()),
            ("half.dng", real[..real.len() / 2].to_vec()),
            (
                "garbage.nef",
                (0..4096u32)
                    .map(|i| (i.wrapping_mul(2654435761u32) >> 24) as u8)
                    .collect(),
            ),
        ];
        for (name, bytes) in cases {
            let path = dir.path().join(name);
            std::fs::write(&path, &bytes).unwrap();
            let err = read_raw(&path).unwrap_err().to_string();
            assert!(err.contains(name), "{name}: {err}");
        }
        let err = read_raw(&dir.path().join("missing.cr2"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing.cr2"), "{err}");
    }
}
