//! Writing a [`Mosaic`] as a DNG file through rawler's `DngWriter`: the CFA samples (14-bit,
//! lossless JPEG like a camera's own DNG, or uncompressed), the CFA pattern, per-site black
//! levels, the white level, the camera's make and model, and ISO, shutter and aperture in EXIF.
//! psscan's synthetic capture sets are written this way so they take the decode path real
//! RAW files take.

use std::io::Cursor;

use rawler::decoders::{Camera, RawMetadata};
use rawler::dng::writer::DngWriter;
use rawler::dng::{CropMode, DngCompression, DngPhotometricConversion, DNG_VERSION_V1_4};
use rawler::exif::Exif;
use rawler::formats::tiff::Rational;
use rawler::imgop::xyz::Illuminant;
use rawler::pixarray::PixU16;
use rawler::rawimage::{BlackLevel, CFAConfig, RawPhotometricInterpretation, WhiteLevel};
use rawler::RawImage;

use super::decode::RawMeta;
use super::mosaic::Mosaic;
use crate::error::{Error, Result};

/// How the samples are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DngStorage {
    /// Lossless JPEG (LJPEG-92) tiles at the sensor's bit depth, as cameras write DNG.
    Lossless,
    /// Plain 16-bit samples: larger files, the fastest to read.
    Uncompressed,
}

/// XYZ (D65) to linear sRGB: the synthetic camera's colour matrix (its primaries are sRGB's),
/// so DNG viewers can render the files.
const XYZ_TO_SRGB: [f32; 9] = [
    3.2406, -1.5372, -0.4986, -0.9689, 1.8758, 0.0415, 0.0557, -0.2040, 1.0570,
];

/// Encodes `mosaic` as a DNG. `bits` is the sensor's bit depth (the white level must fit);
/// `neutral` the raw R, G, B response to white (the as-shot white balance).
pub fn encode_dng(
    mosaic: &Mosaic,
    meta: &RawMeta,
    bits: u32,
    neutral: [f64; 3],
    storage: DngStorage,
) -> Result<Vec<u8>> {
    mosaic.validate()?;
    if !(8..=16).contains(&bits) || mosaic.white as f64 > ((1u32 << bits) - 1) as f64 {
        return Err(Error::Invalid(format!(
            "a {bits}-bit DNG cannot hold the white level {}",
            mosaic.white
        )));
    }
    if neutral.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(Error::Invalid(format!(
            "white balance {neutral:?} must be positive"
        )));
    }
    let image = raw_image(mosaic, meta, bits, neutral);
    let metadata = RawMetadata {
        exif: exif(meta),
        make: meta.make.clone(),
        model: meta.model.clone(),
        ..Default::default()
    };
    let failed =
        |e: rawler::dng::writer::DngError| Error::Invalid(format!("DNG encoding failed: {e}"));
    let mut buffer = Cursor::new(Vec::new());
    {
        let mut dng = DngWriter::new(&mut buffer, DNG_VERSION_V1_4).map_err(failed)?;
        let mut raw = dng.subframe_on_root(0);
        let compression = match storage {
            DngStorage::Lossless => DngCompression::Lossless,
            DngStorage::Uncompressed => DngCompression::Uncompressed,
        };
        // Predictor 1 (left neighbour): rawler pairs columns for a 2x2 CFA, so the neighbour
        // is the same colour.
        raw.raw_image(
            &image,
            CropMode::None,
            compression,
            DngPhotometricConversion::Original,
            1,
        )
        .map_err(failed)?;
        raw.finalize().map_err(failed)?;
        dng.load_base_tags(&image).map_err(failed)?;
        dng.load_metadata(&metadata).map_err(failed)?;
        dng.root_ifd_mut()
            .add_tag(rawler::tags::TiffCommonTag::Software, "psscan");
        dng.close().map_err(failed)?;
    }
    Ok(buffer.into_inner())
}

fn raw_image(mosaic: &Mosaic, meta: &RawMeta, bits: u32, neutral: [f64; 3]) -> RawImage {
    let pattern_name = mosaic.pattern_name();
    let mut camera = Camera::new();
    camera.make = meta.make.clone();
    camera.model = meta.model.clone();
    camera.clean_make = meta.make.clone();
    camera.clean_model = meta.model.clone();
    camera.cfa = rawler::CFA::new(&pattern_name);
    camera.real_bps = bits as usize;
    camera
        .color_matrix
        .insert(Illuminant::D65, XYZ_TO_SRGB.to_vec());
    let pixels = PixU16::new_with(mosaic.samples.clone(), mosaic.width, mosaic.height);
    let black: Vec<u32> = mosaic
        .black
        .iter()
        .flatten()
        .map(|b| b.round() as u32)
        .collect();
    let photometric = RawPhotometricInterpretation::Cfa(CFAConfig::new_from_camera(&camera));
    // rawler's white-balance coefficients are the reciprocal of the neutral.
    let wb = [
        (1.0 / neutral[0]) as f32,
        (1.0 / neutral[1]) as f32,
        (1.0 / neutral[2]) as f32,
        f32::NAN,
    ];
    RawImage::new(
        camera,
        pixels,
        1,
        wb,
        photometric,
        Some(BlackLevel::new(&black, 2, 2, 1)),
        Some(WhiteLevel::new(vec![mosaic.white.round() as u32])),
        false,
    )
}

fn exif(meta: &RawMeta) -> Exif {
    let rational = |v: f64| {
        // Shutter times below a second as 1/n, everything else with a fixed denominator.
        if v > 0.0 && v < 1.0 && (1.0 / v - (1.0 / v).round()).abs() < 1e-6 {
            Rational::new(1, (1.0 / v).round() as u32)
        } else {
            Rational::new((v * 1000.0).round() as u32, 1000)
        }
    };
    Exif {
        iso_speed_ratings: meta.iso.map(|v| v.min(u16::MAX as u32) as u16),
        exposure_time: meta.shutter_s.map(rational),
        fnumber: meta.aperture.map(rational),
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raw::decode::decode_raw;
    use std::path::Path;

    fn meta() -> RawMeta {
        RawMeta {
            make: "psscan".into(),
            model: "synthetic camera".into(),
            width: 0,
            height: 0,
            iso: Some(100),
            shutter_s: Some(0.1),
            aperture: Some(8.0),
        }
    }

    fn mosaic(pattern: &str) -> Mosaic {
        let (width, height) = (70, 36);
        Mosaic {
            width,
            height,
            pattern: Mosaic::parse_pattern(pattern).unwrap(),
            black: [[600.0, 601.0], [602.0, 603.0]],
            white: 15600.0,
            samples: (0..width * height)
                .map(|i| (600 + (i * 7919) % 15001) as u16)
                .collect(),
        }
    }

    #[test]
    fn dng_round_trip_is_exact_for_both_storages_and_every_bayer_pattern() {
        for storage in [DngStorage::Lossless, DngStorage::Uncompressed] {
            for pattern in ["RGGB", "BGGR", "GRBG", "GBRG"] {
                let m = mosaic(pattern);
                let bytes = encode_dng(&m, &meta(), 14, [0.55, 1.0, 0.72], storage).unwrap();
                let back = decode_raw(bytes, Path::new("x.dng")).unwrap();
                assert_eq!(back.mosaic, m, "{storage:?} {pattern}");
                let expected = RawMeta {
                    width: m.width,
                    height: m.height,
                    ..meta()
                };
                assert_eq!(back.meta, expected);
                // The synthetic camera's primaries are sRGB's: display colour is the data (to
                // the DNG's storage of the matrix as rationals over 10000: a few 1e-4).
                let to_srgb = back.camera_to_srgb.unwrap();
                for (r, row) in to_srgb.iter().enumerate() {
                    for (c, v) in row.iter().enumerate() {
                        assert!((v - (r == c) as u8 as f64).abs() < 5e-4, "{to_srgb:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn levels_that_do_not_fit_the_bit_depth_are_refused() {
        let m = mosaic("RGGB");
        assert!(encode_dng(&m, &meta(), 12, [1.0; 3], DngStorage::Lossless).is_err());
        assert!(encode_dng(&m, &meta(), 14, [0.0, 1.0, 1.0], DngStorage::Lossless).is_err());
    }
}
