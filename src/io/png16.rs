//! 16-bit RGB PNG writing: the maps' PNGs and capture frames of raw digital numbers, deflated
//! where that pays and stored where it does not, streamed a band of rows at a time.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::file_bound;
use crate::error::{Error as PsError, Result};
use crate::fsutil::write_atomic;

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

    /// The share the deflate must save for a map to be compressed rather than stored: the
    /// fast deflate, streamed, makes incompressible data larger than storing it (up to a
    /// tenth: a normal map's low bytes are noise); the best one always deflates.
    fn min_saving(self) -> Option<f64> {
        (self == PngCompression::Fast).then_some(MIN_PNG_SAVING)
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
    let mut bytes = png16_buffer(width, height);
    encode_png16_into(&mut bytes, path, width, height, rgb, compression)?;
    Ok(bytes)
}

/// Room for a `width x height` 16-bit RGB PNG's bytes at once: a Vec that grows by doubling
/// copies the file several times into fresh memory (and the capacity it never touches costs
/// nothing).
fn png16_buffer(width: usize, height: usize) -> Vec<u8> {
    Vec::with_capacity(file_bound(width * height * 6 + height))
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
    let size = (width, height);
    encode_slice_into(
        out,
        size,
        &rgb,
        compression.deflate(),
        compression.min_saving(),
    )
    .ok_or_else(|| PsError::image(path, "image size does not match its data"))?
    .map_err(|e| PsError::image(path, e))
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
    let (deflate, min_saving) = (compression.deflate(), compression.min_saving());
    encode_rows_into(out, (width, height), fill, deflate, min_saving)
        .map_err(|e| PsError::image(path, e))
}

/// A capture frame of raw digital numbers (interleaved 16-bit RGB, `width * height * 3`
/// samples) as 16-bit RGB PNG file bytes: the fast deflate where it saves at least
/// 30 % of the stored size (`MIN_FRAME_SAVING`), else stored as it is.
pub fn encode_frame_png16(width: usize, height: usize, rgb: &[u16]) -> Result<Vec<u8>> {
    let mut bytes = png16_buffer(width, height);
    let (deflate, min_saving) = (png::Compression::Fast, Some(MIN_FRAME_SAVING));
    encode_slice_into(&mut bytes, (width, height), rgb, deflate, min_saving)
        .ok_or_else(|| PsError::Invalid("DN image size does not match its data".into()))?
        .map_err(|e| PsError::Invalid(format!("PNG encoding failed: {e}")))?;
    Ok(bytes)
}

/// [`encode_rows_into`] of interleaved 16-bit RGB held whole; `None` where `rgb` is not
/// `width * height * 3` samples long.
fn encode_slice_into(
    out: impl std::io::Write,
    (width, height): (usize, usize),
    rgb: &[u16],
    deflate: png::Compression,
    min_saving: Option<f64>,
) -> Option<std::result::Result<(), png::EncodingError>> {
    if rgb.len() != width * height * 3 {
        return None;
    }
    let row = width * 3;
    let fill = |y: usize, out: &mut [u16]| out.copy_from_slice(&rgb[y * row..(y + 1) * row]);
    Some(encode_rows_into(
        out,
        (width, height),
        &fill,
        deflate,
        min_saving,
    ))
}

/// `height` rows that `fill` makes, as a 16-bit RGB PNG written to `out` with `deflate`, or
/// stored where `min_saving` is given and a sample of rows says the deflate would save less.
fn encode_rows_into(
    out: impl std::io::Write,
    (width, height): (usize, usize),
    fill: &Rgb16Row,
    deflate: png::Compression,
    min_saving: Option<f64>,
) -> std::result::Result<(), png::EncodingError> {
    let rows = BigEndianRows { width, fill };
    let deflate = match min_saving {
        Some(saving) if !compresses(&rows, height, saving) => png::Compression::NoCompression,
        _ => deflate,
    };
    png16_stream(out, &rows, height, deflate)
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

/// The least share of the stored size the fast deflate must save for a capture frame to be
/// compressed. A frame is written once and read by every solve of its set, and a 16 MP frame
/// of raw digital numbers saves about a fifth (its low bits are sensor noise): inflating it
/// took about 3 ns of CPU per byte it gives (the 11 frames of a 16 MP dn16 set, 1.06 GB, in
/// 3.3 s of CPU), where a byte read as it is costs its share of the SHA-256 check (about
/// 0.9 ns) and of the read. So deflate saves the reader time only where it saves more than
/// 3 / (0.9 + t) of the bytes, t the storage's ns per byte: never from a disk of 1 GB/s, above
/// 0.29 from one of 100 MB/s. Stored, that set's decode stage went from 1.8-2.9 s to
/// 0.57-0.77 s (three runs each; its frames from 0.82 to 1.00 GB); a frame that compresses
/// well (a dark frame: two thirds) is still compressed.
const MIN_FRAME_SAVING: f64 = 0.3;

/// Whether the fast deflate makes `rows` at least `min_saving` (a share) smaller than storing
/// them, judged on [`PNG_SAMPLE_ROWS`] rows spread over the image.
fn compresses(rows: &BigEndianRows, height: usize, min_saving: f64) -> bool {
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
        Ok(()) => (encoded.len() as f64) <= (1.0 - min_saving) * stored,
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

    /// A ramp under NOISE_BITS bits of noise, as a frame of raw digital numbers holds it: the
    /// fast deflate saves between a tenth and MIN_FRAME_SAVING on it (asserted through the
    /// map writer, which compresses it), so a frame of it is stored; a dark frame (the black
    /// level and a little noise) saves far more and is compressed. Both read back exactly.
    #[test]
    fn frames_the_fast_deflate_saves_under_a_third_on_are_stored_dark_frames_compressed() {
        const NOISE_BITS: u32 = 9;
        let (w, h) = (301, 200);
        let stored = h * (w * 6 + 1);
        let mut state = 7u32;
        let mut noise = move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 16) as u16 >> (16 - NOISE_BITS)
        };
        let lit: Vec<u16> = (0..w * h * 3)
            .map(|i| (i / 3 % w * 40 + i / (w * 3) * 20) as u16 + noise())
            .collect();
        let dark: Vec<u16> = (0..w * h * 3).map(|_| 600 + (noise() >> 7)).collect();
        let as_map = encode_png16(Path::new("x.png"), w, h, lit.clone(), PngCompression::Fast);
        let as_map = as_map.unwrap().len() as f64;
        let saving = 1.0 - as_map / stored as f64;
        assert!(
            (MIN_PNG_SAVING..MIN_FRAME_SAVING).contains(&saving),
            "the fast deflate saves {saving:.3} on the lit frame"
        );
        let frame = encode_frame_png16(w, h, &lit).unwrap();
        assert!(
            frame.len() >= stored,
            "lit {} < stored {stored}",
            frame.len()
        );
        let dark_frame = encode_frame_png16(w, h, &dark).unwrap();
        assert!(
            (dark_frame.len() as f64) < (1.0 - MIN_FRAME_SAVING) * stored as f64,
            "dark {} of {stored}",
            dark_frame.len()
        );
        for (bytes, rgb) in [(frame, lit), (dark_frame, dark)] {
            let back = image::load_from_memory(&bytes).unwrap().into_rgb16();
            assert_eq!(back.into_raw(), rgb);
        }
        let err = encode_frame_png16(w, h, &[0; 5]).unwrap_err();
        assert!(err.to_string().contains("does not match"), "{err}");
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
