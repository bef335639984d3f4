//! Image files (DESIGN.md layer 2): 16-bit PNG and float EXR, read and written (atomically),
//! for every reader and writer of the house. Nothing here knows what the pixels mean.

use std::borrow::Cow;
use std::io::Cursor;
use std::path::Path;

use exr::block::lines::LineRefMut;
use exr::image::write::samples::{SamplesWriter, WritableSamples};
use exr::math::RoundingMode;
use exr::meta::attribute::{LevelMode, SampleType};
use exr::meta::header::Header;
use exr::prelude::*;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::DynamicImage;

use crate::error::{Error as PsError, Result};
use crate::fsutil::write_atomic;
use crate::plane::Plane;

mod png16;

pub use png16::{
    encode_frame_png16, encode_png16, encode_png16_into, encode_png16_rows_into, write_png16,
    PngCompression, Rgb16Row,
};

/// Writes an image as a PNG (fast deflate, adaptive filter), atomically.
pub fn write_png(path: &Path, image: &DynamicImage) -> Result<()> {
    let mut bytes = Vec::new();
    let encoder =
        PngEncoder::new_with_quality(&mut bytes, CompressionType::Fast, FilterType::Adaptive);
    image
        .write_with_encoder(encoder)
        .map_err(|e| PsError::image(path, e))?;
    write_atomic(path, &bytes)
}

/// Writes named `f32` channels of one size as a single-layer EXR (lossless RLE compression).
pub fn write_exr(path: &Path, channels: &[(&str, &Plane)]) -> Result<()> {
    let bytes = encode_exr(path, channels)?;
    write_atomic(path, &bytes)
}

/// How an EXR's blocks are stored. Both are lossless.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExrCompression {
    /// Run-length encoded: pays where values repeat (class and count channels). The exr crate
    /// compresses its blocks on all cores.
    Rle,
    /// Stored as they are: for maps of continuous values, where runs are rare and RLE saves
    /// nothing (the 16 MP normal and albedo EXRs came out the same size either way) but costs
    /// an encode pass.
    None,
}

/// Named `f32` channels of one size encoded as single-layer EXR file bytes (RLE, see
/// [`ExrCompression`]); `path` only names the file in errors.
pub fn encode_exr(path: &Path, channels: &[(&str, &Plane)]) -> Result<Vec<u8>> {
    encode_exr_planes(path, channels, ExrCompression::Rle)
}

/// [`encode_exr`] with the compression chosen.
pub fn encode_exr_planes(
    path: &Path,
    channels: &[(&str, &Plane)],
    compression: ExrCompression,
) -> Result<Vec<u8>> {
    let (size, samples) = planes_as_samples(path, channels)?;
    encode_exr_samples(path, size, samples, compression)
}

/// [`encode_exr_planes`] streamed into `out` (see [`encode_exr_samples_into`]).
pub fn encode_exr_planes_into(
    out: impl std::io::Write + std::io::Seek,
    path: &Path,
    channels: &[(&str, &Plane)],
    compression: ExrCompression,
) -> Result<()> {
    let (size, samples) = planes_as_samples(path, channels)?;
    encode_exr_samples_into(out, path, size, samples, compression)
}

/// Planes of one size as single-precision channels (borrowed), and that size.
#[allow(clippy::type_complexity)]
fn planes_as_samples<'a>(
    path: &Path,
    channels: &[(&'a str, &'a Plane)],
) -> Result<((usize, usize), Vec<(&'a str, ExrSamples<'a>)>)> {
    let Some((_, first)) = channels.first() else {
        return Err(PsError::image(path, "no channels to write"));
    };
    let (width, height) = (first.width, first.height);
    if channels
        .iter()
        .any(|(_, p)| p.width != width || p.height != height)
    {
        return Err(PsError::image(path, "channels of different sizes"));
    }
    let samples = channels
        .iter()
        .map(|&(name, plane)| (name, ExrSamples::F32(Cow::Borrowed(&plane.data))))
        .collect();
    Ok(((width, height), samples))
}

/// A channel's samples as an EXR stores them, borrowed where the caller holds them already:
/// the encoder reads each line straight from them (at 16 MP a copy of a map's planes was
/// 190 MB of fresh memory per file).
pub enum ExrSamples<'a> {
    /// Single precision.
    F32(Cow<'a, [f32]>),
    /// Half precision: exact for whole numbers up to 2048 (class and count channels), half
    /// the bytes of `F32`.
    F16(Vec<exr::prelude::f16>),
}

impl ExrSamples<'_> {
    /// Whole numbers (each at most 2048) as half-precision samples, which hold them exactly.
    pub fn small_integers(values: impl Iterator<Item = u16>) -> Self {
        ExrSamples::F16(
            values
                .map(|v| {
                    debug_assert!(v <= 2048, "{v} is not exact in half precision");
                    exr::prelude::f16::from_f32(v as f32)
                })
                .collect(),
        )
    }

    fn len(&self) -> usize {
        match self {
            ExrSamples::F32(v) => v.len(),
            ExrSamples::F16(v) => v.len(),
        }
    }

    fn bytes_per_sample(&self) -> usize {
        match self {
            ExrSamples::F32(_) => 4,
            ExrSamples::F16(_) => 2,
        }
    }
}

/// The exr crate's hook for a channel's samples: the file's sample type, and a line reader.
impl<'s> WritableSamples<'s> for ExrSamples<'_> {
    type Writer = ExrLineWriter<'s>;

    fn sample_type(&self) -> SampleType {
        match self {
            ExrSamples::F32(_) => SampleType::F32,
            ExrSamples::F16(_) => SampleType::F16,
        }
    }

    fn infer_level_modes(&self) -> (LevelMode, RoundingMode) {
        (LevelMode::Singular, RoundingMode::Down)
    }

    fn create_samples_writer(&'s self, header: &Header) -> Self::Writer {
        ExrLineWriter {
            width: header.layer_size.width(),
            samples: match self {
                ExrSamples::F32(v) => SampleSlice::F32(v),
                ExrSamples::F16(v) => SampleSlice::F16(v),
            },
        }
    }
}

/// Copies one line of a channel's samples into the block the exr crate is filling.
pub struct ExrLineWriter<'s> {
    width: usize,
    samples: SampleSlice<'s>,
}

enum SampleSlice<'s> {
    F32(&'s [f32]),
    F16(&'s [exr::prelude::f16]),
}

impl SamplesWriter for ExrLineWriter<'_> {
    fn extract_line(&self, line: LineRefMut<'_>) {
        let start = line.location.position.y() * self.width + line.location.position.x();
        let range = start..start + line.location.sample_count;
        // The line's byte slice is sized by the crate from the same header: a mismatch is a
        // bug here, not bad input.
        match self.samples {
            SampleSlice::F32(v) => line.write_samples_from_slice(&v[range]),
            SampleSlice::F16(v) => line.write_samples_from_slice(&v[range]),
        }
        .expect("an EXR line holds its samples");
    }
}

/// Named channels of `size` (width, height) encoded as single-layer EXR file bytes; `path`
/// only names the file in errors.
pub fn encode_exr_samples(
    path: &Path,
    size: (usize, usize),
    channels: Vec<(&str, ExrSamples)>,
    compression: ExrCompression,
) -> Result<Vec<u8>> {
    let bytes: usize = channels
        .iter()
        .map(|(_, s)| s.len() * s.bytes_per_sample())
        .sum();
    let mut cursor = Cursor::new(Vec::with_capacity(file_bound(bytes)));
    encode_exr_samples_into(&mut cursor, path, size, channels, compression)?;
    Ok(cursor.into_inner())
}

/// [`encode_exr_samples`] streamed into `out` (buffered by the caller; a file, so that a
/// 16 MP map's bytes need not sit in memory).
pub fn encode_exr_samples_into(
    out: impl std::io::Write + std::io::Seek,
    path: &Path,
    (width, height): (usize, usize),
    channels: Vec<(&str, ExrSamples)>,
    compression: ExrCompression,
) -> Result<()> {
    if channels.is_empty() {
        return Err(PsError::image(path, "no channels to write"));
    }
    if channels.iter().any(|(_, s)| s.len() != width * height) {
        return Err(PsError::image(path, "channels of different sizes"));
    }
    let list = channels
        .into_iter()
        .map(|(name, samples)| AnyChannel::new(name, samples))
        .collect();
    let encoding = match compression {
        ExrCompression::Rle => Encoding::FAST_LOSSLESS,
        ExrCompression::None => Encoding::UNCOMPRESSED,
    };
    let layer = Layer::new(
        (width, height),
        LayerAttributes::named("psscan"),
        encoding,
        AnyChannels::sort(list),
    );
    Image::from_layer(layer)
        .write()
        .to_unbuffered(out)
        .map_err(|e| PsError::image(path, e))
}

/// A capacity that holds an encoded file of `raw` bytes of samples: lossless encoders can
/// expand incompressible data a little (deflate's stored blocks, RLE's literal runs), and
/// headers and offset tables come on top.
fn file_bound(raw: usize) -> usize {
    raw + raw / 64 + (1 << 20)
}

/// Reads the named channels of an EXR's first layer; fails naming a missing channel.
pub fn read_exr(path: &Path, names: &[&str]) -> Result<Vec<Plane>> {
    // Read through a buffer rather than the whole file at once, and move each channel's
    // samples out instead of copying them: at 16 MP the maps are hundreds of megabytes.
    let file = std::fs::File::open(path).map_err(|e| PsError::io(path, e))?;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_unbuffered(file)
        .map_err(|e| PsError::image(path, e))?;
    let (width, height) = (
        image.layer_data.size.width(),
        image.layer_data.size.height(),
    );
    let mut channels: Vec<(String, Option<FlatSamples>)> = image
        .layer_data
        .channel_data
        .list
        .into_iter()
        .map(|c| (c.name.to_string(), Some(c.sample_data)))
        .collect();
    let mut planes = Vec::with_capacity(names.len());
    for (k, name) in names.iter().enumerate() {
        let slot = channels
            .iter_mut()
            .find(|(n, _)| n == name)
            .map(|(_, samples)| samples)
            .ok_or_else(|| PsError::image(path, format!("has no channel \"{name}\"")))?;
        let asked_again = names[k + 1..].contains(name);
        let values = match (slot.take(), asked_again) {
            (Some(FlatSamples::F32(v)), false) => v,
            (Some(samples), _) => {
                let v = samples.values_as_f32().collect();
                *slot = Some(samples);
                v
            }
            (None, _) => unreachable!("a channel is taken only when it is not asked again"),
        };
        planes.push(Plane::from_vec(width, height, values)?);
    }
    Ok(planes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_round_trip_is_exact_and_missing_channels_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.exr");
        let a = Plane::from_vec(3, 2, vec![0.1, -2.0, 3.5, 1e-7, f32::MAX, 0.0]).unwrap();
        let b = Plane::new(3, 2, 0.25);
        write_exr(&path, &[("R", &a), ("residual", &b)]).unwrap();
        let back = read_exr(&path, &["residual", "R"]).unwrap();
        assert_eq!(back[0], b);
        assert_eq!(back[1], a);
        let err = read_exr(&path, &["G"]).unwrap_err().to_string();
        assert!(err.contains("x.exr") && err.contains("\"G\""), "{err}");
        // Uncompressed storage reads back the same samples.
        let channels = [("R", &a), ("residual", &b)];
        let bytes = encode_exr_planes(&path, &channels, ExrCompression::None).unwrap();
        write_atomic(&path, &bytes).unwrap();
        assert_eq!(read_exr(&path, &["R", "residual"]).unwrap(), vec![a, b]);
    }

    #[test]
    fn half_precision_channels_hold_small_integers_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.exr");
        let counts: Vec<u16> = vec![0, 1, 5, 96, 2047, 2048];
        let residual = vec![0.1f32, 2.5e-7, 3.0, -1.0, 1e30, 0.0];
        let bytes = encode_exr_samples(
            &path,
            (3, 2),
            vec![
                ("residual", ExrSamples::F32(Cow::Borrowed(&residual))),
                (
                    "lights_used",
                    ExrSamples::small_integers(counts.iter().copied()),
                ),
            ],
            ExrCompression::None,
        )
        .unwrap();
        std::fs::write(&path, bytes).unwrap();
        let back = read_exr(&path, &["lights_used", "residual"]).unwrap();
        let want: Vec<f32> = counts.iter().map(|&c| c as f32).collect();
        assert_eq!(back[0].data, want);
        assert_eq!(back[1].data, residual);
        // A channel of another size is refused.
        let err = encode_exr_samples(
            &path,
            (3, 2),
            vec![("fit", ExrSamples::small_integers([1u16, 2].into_iter()))],
            ExrCompression::None,
        );
        assert!(err.is_err());
    }
}
