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
use serde::{Deserialize, Serialize};

use crate::error::{Error as PsError, Result};
use crate::fsutil::write_atomic;
use crate::plane::Plane;

/// How hard the PNG maps' deflate works.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PngCompression {
    /// A fast deflate: files a little larger, written several times sooner (the default);
    /// maps it would shrink by less than a tenth are stored as they are.
    #[default]
    Fast,
    /// The smallest files the encoder makes, for archives; much slower.
    Best,
}

impl PngCompression {
    /// The png crate's setting (both with its adaptive per-row filter).
    fn deflate(self) -> png::Compression {
        match self {
            PngCompression::Fast => png::Compression::Fast,
            PngCompression::Best => png::Compression::High,
        }
    }
}

/// Writes interleaved 16-bit RGB as a PNG (fast deflate).
pub fn write_png16(path: &Path, width: usize, height: usize, rgb: Vec<u16>) -> Result<()> {
    let bytes = encode_png16(path, width, height, rgb, PngCompression::Fast)?;
    write_atomic(path, &bytes)
}

/// Interleaved 16-bit RGB encoded as PNG file bytes; `path` only names the file in errors.
pub fn encode_png16(
    path: &Path,
    width: usize,
    height: usize,
    rgb: Vec<u16>,
    compression: PngCompression,
) -> Result<Vec<u8>> {
    // Room for the whole file at once: a Vec that grows by doubling copies the file several
    // times into fresh memory (and the capacity it never touches costs nothing).
    let mut bytes = Vec::with_capacity(file_bound(width * height * 6 + height));
    encode_png16_into(&mut bytes, path, width, height, rgb, compression)?;
    Ok(bytes)
}

/// [`encode_png16`] streamed into `out` (a file: a 16 MP map's bytes need not sit in memory).
pub fn encode_png16_into(
    out: impl std::io::Write,
    path: &Path,
    width: usize,
    height: usize,
    rgb: Vec<u16>,
    compression: PngCompression,
) -> Result<()> {
    if rgb.len() != width * height * 3 {
        return Err(PsError::image(path, "image size does not match its data"));
    }
    let row = width * 3;
    let fill = |y: usize, out: &mut [u16]| out.copy_from_slice(&rgb[y * row..(y + 1) * row]);
    encode_png16_rows_into(out, path, width, height, &fill, compression)
}

/// Row `y` of an image as interleaved 16-bit RGB samples (native byte order), written into a
/// slice `3 width` long.
pub type Rgb16Row<'a> = dyn Fn(usize, &mut [u16]) + Sync + 'a;

/// A 16-bit RGB PNG whose rows `fill` makes as they are written, a band of rows at a time
/// (made in parallel): the image is never interleaved whole (96 MB of fresh memory per 16 MP
/// map); `path` only names the file in errors.
pub fn encode_png16_rows_into(
    out: impl std::io::Write,
    path: &Path,
    width: usize,
    height: usize,
    fill: &Rgb16Row,
    compression: PngCompression,
) -> Result<()> {
    let rows = BigEndianRows { width, fill };
    let mut deflate = compression.deflate();
    // The fast deflate, streamed, makes incompressible data larger than storing it (up to a
    // tenth: a normal map's low bytes are noise). A sample of rows says which it will be.
    if compression == PngCompression::Fast && !compresses(&rows, height) {
        deflate = png::Compression::NoCompression;
    }
    png16_stream(out, &rows, height, deflate).map_err(|e| PsError::image(path, e))
}

/// An image's rows as PNG stores 16-bit samples (big-endian), from a [`Rgb16Row`].
struct BigEndianRows<'a, 'b> {
    width: usize,
    fill: &'a Rgb16Row<'b>,
}

impl BigEndianRows<'_, '_> {
    /// Rows per band: 32 rows of a 16 MP map are under a MiB.
    const BAND: usize = 32;

    /// The rows `ys` into `band`, big-endian, made in parallel.
    fn band(&self, ys: std::ops::Range<usize>, band: &mut Vec<u16>) {
        use rayon::prelude::*;
        let row = self.width * 3;
        band.resize(ys.len() * row, 0);
        band.par_chunks_mut(row.max(1))
            .zip(ys)
            .for_each(|(samples, y)| {
                (self.fill)(y, samples);
                for v in samples {
                    *v = v.to_be();
                }
            });
    }

    /// Calls `write` with each band of rows `0..height` in order, as bytes.
    fn each_band(
        &self,
        height: usize,
        mut write: impl FnMut(&[u8]) -> std::result::Result<(), png::EncodingError>,
    ) -> std::result::Result<(), png::EncodingError> {
        let mut band = Vec::new();
        for y0 in (0..height).step_by(Self::BAND) {
            self.band(y0..(y0 + Self::BAND).min(height), &mut band);
            write(bytemuck::cast_slice(&band))?;
        }
        Ok(())
    }
}

/// Rows of the sample [`compresses`] encodes: enough to see the image's statistics, a small
/// share of a large image's encoding time.
const PNG_SAMPLE_ROWS: usize = 64;

/// The least share of the stored size the fast deflate must save for a map to be compressed.
/// A solved map's low bits are sensor noise: at 16 MP the albedo map came out 3 % smaller
/// (93.6 MB against 96.5 MB stored) for about 0.2 s of CPU in the deflate and its filters
/// (perf); a tenth is a saving worth a pass over the image. `--png-compression best` always
/// deflates.
const MIN_PNG_SAVING: f64 = 0.1;

/// Whether the fast deflate makes `rows` at least [`MIN_PNG_SAVING`] smaller than storing
/// them, judged on [`PNG_SAMPLE_ROWS`] rows spread over the image.
fn compresses(rows: &BigEndianRows, height: usize) -> bool {
    let count = height.min(PNG_SAMPLE_ROWS);
    if count == 0 {
        return true;
    }
    // The sample is an image of its own: its row `k` is the image's row `k height / count`.
    let sample = BigEndianRows {
        width: rows.width,
        fill: &|k: usize, out: &mut [u16]| (rows.fill)(k * height / count, out),
    };
    let stored = (count * (rows.width * 6 + 1)) as f64;
    let mut encoded = Vec::with_capacity(file_bound(stored as usize));
    match png16_stream(&mut encoded, &sample, count, png::Compression::Fast) {
        Ok(()) => (encoded.len() as f64) <= (1.0 - MIN_PNG_SAVING) * stored,
        Err(_) => true,
    }
}

/// PNG file bytes of `height` rows written to `out`, the deflate output streamed chunk by
/// chunk (1 MiB IDAT chunks), never a whole-image buffer.
fn png16_stream(
    out: impl std::io::Write,
    rows: &BigEndianRows,
    height: usize,
    deflate: png::Compression,
) -> std::result::Result<(), png::EncodingError> {
    use std::io::Write;
    let width = rows.width;
    let mut encoder = png::Encoder::new(out, width as u32, height as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Sixteen);
    encoder.set_compression(deflate);
    // Filters only help deflate find repeats: stored data is written as it is.
    encoder.set_filter(match deflate {
        png::Compression::NoCompression => png::Filter::NoFilter,
        _ => png::Filter::Adaptive,
    });
    let mut writer = encoder.write_header()?;
    if let png::Compression::NoCompression = deflate {
        // Stored blocks written here: the png crate's stored writer builds the whole stream
        // in a buffer of its own first (96 MB at 16 MP), and its streaming one runs zlib at
        // level 0, several times slower.
        let mut idat = StoredIdat::new(&mut writer, height * (width * 6 + 1));
        rows.each_band(height, |band| {
            for row in band.chunks_exact(width * 6) {
                idat.write(&[0])?; // filter type None
                idat.write(row)?;
            }
            Ok(())
        })?;
        idat.finish()?;
    } else {
        let mut stream = writer.stream_writer_with_size(1 << 20)?;
        rows.each_band(height, |band| Ok(stream.write_all(band)?))?;
        stream.finish()?;
    }
    writer.finish()?;
    Ok(())
}

/// A zlib stream of stored (uncompressed) deflate blocks (RFC 1950, RFC 1951 section 3.2.4)
/// of a known length, written as PNG IDAT chunks of about a MiB.
struct StoredIdat<'a, W: std::io::Write> {
    png: &'a mut png::Writer<W>,
    /// Bytes of the stream not yet in a chunk.
    chunk: Vec<u8>,
    /// Data of the block being filled.
    block: Vec<u8>,
    adler: simd_adler32::Adler32,
    /// Data bytes still to come, the block's included.
    left: usize,
}

impl<'a, W: std::io::Write> StoredIdat<'a, W> {
    /// A stored block holds at most this many bytes (its length is 16 bits).
    const BLOCK: usize = 65_535;
    /// IDAT chunk size the stream is cut into.
    const CHUNK: usize = 1 << 20;

    fn new(png: &'a mut png::Writer<W>, length: usize) -> Self {
        let mut chunk = Vec::with_capacity(Self::CHUNK + Self::BLOCK + 16);
        // CMF: deflate, 32 KiB window; FLG: no dictionary, fastest level, check bits so that
        // CMF * 256 + FLG is a multiple of 31 (0x7801 = 30721 = 31 * 991).
        chunk.extend_from_slice(&[0x78, 0x01]);
        StoredIdat {
            png,
            chunk,
            block: Vec::with_capacity(Self::BLOCK),
            adler: simd_adler32::Adler32::new(),
            left: length,
        }
    }

    fn write(&mut self, mut data: &[u8]) -> std::result::Result<(), png::EncodingError> {
        while !data.is_empty() {
            let take = (Self::BLOCK - self.block.len()).min(data.len());
            self.block.extend_from_slice(&data[..take]);
            data = &data[take..];
            if self.block.len() == Self::BLOCK {
                self.end_block()?;
            }
        }
        Ok(())
    }

    /// Moves the filled block into the stream: header (final flag, type 00), length, its
    /// one's complement, data; the stream's Adler-32 after the last.
    fn end_block(&mut self) -> std::result::Result<(), png::EncodingError> {
        self.left -= self.block.len();
        let last = self.left == 0;
        let len = self.block.len() as u16;
        self.chunk.push(u8::from(last));
        self.chunk.extend_from_slice(&len.to_le_bytes());
        self.chunk.extend_from_slice(&(!len).to_le_bytes());
        self.chunk.extend_from_slice(&self.block);
        self.adler.write(&self.block);
        self.block.clear();
        if last {
            self.chunk
                .extend_from_slice(&self.adler.finish().to_be_bytes());
        }
        if last || self.chunk.len() >= Self::CHUNK {
            self.png.write_chunk(png::chunk::IDAT, &self.chunk)?;
            self.chunk.clear();
        }
        Ok(())
    }

    /// Ends the stream; every byte of the length given to [`StoredIdat::new`] was written.
    fn finish(mut self) -> std::result::Result<(), png::EncodingError> {
        debug_assert_eq!(self.block.len(), self.left, "the stream's stated length");
        if self.left > 0 {
            self.end_block()?;
        }
        Ok(())
    }
}

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

    /// 16-bit RGB of `w x h`: a smooth ramp (deflate shrinks it) or noise in every bit (it
    /// cannot).
    fn rgb16(w: usize, h: usize, noise: bool) -> Vec<u16> {
        let mut state = 99u32;
        (0..w * h * 3)
            .map(|i| {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                if noise {
                    (state >> 16) as u16
                } else {
                    (i / 3 % w * 300 + i % 3) as u16
                }
            })
            .collect()
    }

    /// Stored PNG streams whose length is one block exactly, two blocks exactly, a few
    /// bytes, and over a MiB (several IDAT chunks): every one decodes to its samples, and its
    /// zlib stream ends in the Adler-32 of the filtered rows (computed here by the definition;
    /// the png crate's decoder does not check it).
    #[test]
    fn stored_png_streams_decode_at_block_and_chunk_boundaries() {
        // 14 pixels of 6 bytes and a filter byte: 85 bytes a row, 771 rows = 65535.
        for (w, h) in [(14, 771), (14, 1542), (1, 1), (300, 700)] {
            let rgb = rgb16(w, h, true);
            let samples: Vec<u8> = rgb.iter().flat_map(|v| v.to_be_bytes()).collect();
            let fill = |y: usize, out: &mut [u16]| out.copy_from_slice(&rgb[y * w * 3..][..w * 3]);
            let rows = BigEndianRows {
                width: w,
                fill: &fill,
            };
            let mut bytes = Vec::new();
            png16_stream(&mut bytes, &rows, h, png::Compression::NoCompression).unwrap();
            let back = image::load_from_memory(&bytes).unwrap().into_rgb16();
            assert_eq!(back.into_raw(), rgb, "{w} x {h}");

            let mut idat = Vec::new();
            let mut at = 8;
            while at < bytes.len() {
                let len = u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
                if &bytes[at + 4..at + 8] == b"IDAT" {
                    idat.extend_from_slice(&bytes[at + 8..at + 8 + len]);
                }
                at += 12 + len;
            }
            let (mut a, mut b) = (1u32, 0u32);
            for row in samples.chunks(w * 6) {
                for &byte in std::iter::once(&0u8).chain(row) {
                    a = (a + byte as u32) % 65521;
                    b = (b + a) % 65521;
                }
            }
            let adler = (b << 16) | a;
            assert_eq!(idat[idat.len() - 4..], adler.to_be_bytes(), "{w} x {h}");
            let blocks = (h * (w * 6 + 1)).div_ceil(65_535);
            assert_eq!(
                idat.len(),
                2 + h * (w * 6 + 1) + 5 * blocks + 4,
                "{w} x {h}"
            );
        }
    }

    /// A ramp under 11 bits of noise (a map's sensor noise in its low bits): the fast deflate
    /// saves about 5 % on it, under the tenth it must save to be used; the best one still
    /// deflates.
    #[test]
    fn maps_the_fast_deflate_barely_shrinks_are_stored_and_best_still_deflates_them() {
        let (w, h) = (301, 200);
        let stored = h * (w * 6 + 1);
        let mut state = 99u32;
        let rgb: Vec<u16> = (0..w * h * 3)
            .map(|i| {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let ramp = (i / 3 % w * 100 + i / (w * 3) * 50) as u16;
                ramp.wrapping_add((state >> 16) as u16 >> 5)
            })
            .collect();
        let fast = encode_png16(Path::new("x.png"), w, h, rgb.clone(), PngCompression::Fast);
        let fast = fast.unwrap();
        assert!(
            fast.len() >= stored,
            "fast {} < stored {stored}",
            fast.len()
        );
        let best = encode_png16(Path::new("x.png"), w, h, rgb.clone(), PngCompression::Best);
        let best = best.unwrap();
        assert!(
            best.len() < stored,
            "best {} >= stored {stored}",
            best.len()
        );
        for bytes in [fast, best] {
            let back = image::load_from_memory(&bytes).unwrap().into_rgb16();
            assert_eq!(back.into_raw(), rgb);
        }
    }

    #[test]
    fn png16_round_trips_and_incompressible_data_is_stored_not_inflated() {
        let (w, h) = (301, 200);
        let stored = h * (w * 6 + 1);
        for noise in [false, true] {
            for compression in [PngCompression::Fast, PngCompression::Best] {
                let rgb = rgb16(w, h, noise);
                let bytes =
                    encode_png16(Path::new("x.png"), w, h, rgb.clone(), compression).unwrap();
                let back = image::load_from_memory(&bytes).unwrap().into_rgb16();
                assert_eq!(back.dimensions(), (w as u32, h as u32));
                assert_eq!(back.into_raw(), rgb, "noise {noise}, {compression:?}");
                if noise {
                    // Stored blocks cost 5 bytes per 64 KiB, headers a few hundred bytes;
                    // the streamed fast deflate made such data a tenth larger.
                    assert!(
                        bytes.len() < stored + stored / 1000 + 1024,
                        "{}",
                        bytes.len()
                    );
                } else {
                    assert!(bytes.len() < stored / 2, "{}", bytes.len());
                }
            }
        }
        let err = encode_png16(Path::new("x.png"), w, h, vec![0; 5], PngCompression::Fast);
        assert!(err.unwrap_err().to_string().contains("x.png"));
    }

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

    #[test]
    fn png16_is_written_and_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("n.png");
        let data: Vec<u16> = (0..12).map(|v| v * 5000).collect();
        write_png16(&path, 2, 2, data.clone()).unwrap();
        let back = image::open(&path).unwrap().into_rgb16().into_raw();
        assert_eq!(back, data);
    }

    #[test]
    fn best_png_compression_keeps_the_pixels_and_is_no_larger_than_fast() {
        // A smooth gradient with a little structure: deflate has something to find.
        let (w, h) = (64, 48);
        let data: Vec<u16> = (0..w * h * 3)
            .map(|i| ((i / 3) % w * 900 + (i / 3) / w * 37 + (i % 3) * 5) as u16)
            .collect();
        let path = Path::new("gradient.png");
        let fast = encode_png16(path, w, h, data.clone(), PngCompression::Fast).unwrap();
        let best = encode_png16(path, w, h, data.clone(), PngCompression::Best).unwrap();
        assert_ne!(fast, best, "the flag must change the encoder's settings");
        assert!(
            best.len() <= fast.len(),
            "best {} > fast {}",
            best.len(),
            fast.len()
        );
        for bytes in [&fast, &best] {
            let back = image::load_from_memory(bytes).unwrap().into_rgb16();
            assert_eq!(back.into_raw(), data);
        }
    }
}
