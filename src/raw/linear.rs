//! 16-bit RGB images holding raw digital numbers (black level included), as written by the
//! synthetic sensor, and their conversion to linear planes.

use std::path::Path;

use image::DynamicImage;

use crate::error::{Error, Result};
use crate::plane::{DnSamples, LightFrame, Mask};
use crate::rig::Sensor;

/// Raw digital numbers, RGB interleaved, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct DnImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// The samples in DN, `width * height * 3` of them: R, G, B of each pixel, row after row.
    pub data: Vec<u16>,
}

/// The digital levels that map DN to linear light: `(dn - black) / (white - black)`, and at or
/// above `white` the value is clipped.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Levels {
    /// The DN a pixel reads with no light: linear 0.
    pub black: f64,
    /// The DN at which the sensor clips: linear 1.0.
    pub white: f64,
}

impl Levels {
    /// The levels a rig's sensor description gives.
    pub fn from_sensor(sensor: &Sensor) -> Self {
        Levels {
            black: sensor.black_level,
            white: sensor.white_level,
        }
    }
}

impl DnImage {
    /// Linear planes and the saturation mask (a pixel any of whose channels reached the white
    /// level carries no usable value): the frame [`decode_dn_frame`] keeps as DN, as `f32`
    /// planes.
    pub fn to_light_frame(&self, levels: &Levels) -> LightFrame {
        let mut frame = DnRows::new(self.width, self.height, levels);
        for (y, row) in self.data.chunks_exact(self.width * 3).enumerate() {
            frame.row(y, row.chunks_exact(3).map(|px| [px[0], px[1], px[2]]));
        }
        frame.finish().with_planes()
    }
}

/// A dn16 frame filled row by row from DN pixels, kept as its DN (see [`DnSamples`], which
/// linearises them); a pixel is saturated where any channel reached the white level.
struct DnRows {
    samples: DnSamples,
    /// Made at the first row with a saturated pixel, its flags written for such rows only: a
    /// frame that clips nowhere (the usual one) gets none, where a mask written whole was 16 MB
    /// of fresh memory per 16 MP frame, all of it `false`.
    saturated: Option<Mask>,
    /// The smallest DN at or above the white level (65536 where none is): a whole DN `v` has
    /// reached the white level exactly when `v >= saturated_from`.
    saturated_from: u32,
}

impl DnRows {
    fn new(width: usize, height: usize, levels: &Levels) -> Self {
        DnRows {
            samples: DnSamples::new(width, height, levels.black, levels.white),
            saturated: None,
            saturated_from: saturated_from(levels.white),
        }
    }

    /// Row `y` from its pixels (at most `width` of them are read).
    #[inline]
    fn row(&mut self, y: usize, pixels: impl Iterator<Item = [u16; 3]>) {
        let w = self.samples.width;
        let at = y * w..(y + 1) * w;
        let [r, g, b] = &mut self.samples.dn;
        // Zipped iterators, not indexing: no bounds check per sample of a 16 MP frame.
        let outputs = r[at.clone()]
            .iter_mut()
            .zip(&mut g[at.clone()])
            .zip(&mut b[at]);
        let (mut clipped, mut n) = (false, 0);
        for (((r, g), b), px) in outputs.zip(pixels) {
            clipped |= reached_white(px, self.saturated_from);
            [*r, *g, *b] = px;
            n += 1;
        }
        if clipped {
            self.flag_row(y, n);
        }
    }

    /// Writes the saturation flags of row `y`'s first `n` pixels from their stored samples,
    /// making the mask first.
    #[cold]
    fn flag_row(&mut self, y: usize, n: usize) {
        let (w, h) = (self.samples.width, self.samples.height);
        let mask = self.saturated.get_or_insert_with(|| Mask::new(w, h, false));
        let at = y * w..y * w + n;
        let [r, g, b] = &self.samples.dn;
        let samples = r[at.clone()].iter().zip(&g[at.clone()]).zip(&b[at.clone()]);
        for (flag, ((&r, &g), &b)) in mask.data[at].iter_mut().zip(samples) {
            *flag = reached_white([r, g, b], self.saturated_from);
        }
    }

    /// Row `y` from a 16-bit RGB PNG row: six bytes a pixel, R, G, B big-endian (a row shorter
    /// than the width fills what it holds). Over slices of one known length, with the white
    /// test on integers and no early exit, the loop has no bounds check per value.
    #[inline]
    fn row_be_bytes(&mut self, y: usize, data: &[u8]) {
        let w = self.samples.width;
        let n = w.min(data.len() / 6);
        let at = y * w..y * w + n;
        let [r, g, b] = &mut self.samples.dn;
        let (r, g, b) = (&mut r[at.clone()], &mut g[at.clone()], &mut b[at]);
        let data = &data[..6 * n];
        let from = self.saturated_from;
        let mut clipped = false;
        for k in 0..n {
            let px = &data[6 * k..6 * k + 6];
            let v = [
                u16::from_be_bytes([px[0], px[1]]),
                u16::from_be_bytes([px[2], px[3]]),
                u16::from_be_bytes([px[4], px[5]]),
            ];
            [r[k], g[k], b[k]] = v;
            clipped |= reached_white(v, from);
        }
        if clipped {
            self.flag_row(y, n);
        }
    }

    fn finish(self) -> LightFrame {
        LightFrame::from_dn(self.samples, self.saturated)
    }
}

/// The smallest whole DN at or above `white` (65536 where none is, NaN included): for every
/// DN `v`, `v as f64 >= white` exactly when `v as u32 >= saturated_from(white)`.
fn saturated_from(white: f64) -> u32 {
    if white.is_nan() {
        65536
    } else {
        white.ceil().clamp(0.0, 65536.0) as u32
    }
}

/// Whether any channel of `px` reached the white level, `saturated_from` being
/// [`saturated_from`] of it (all three compared, no early exit: the row loops vectorise).
#[inline(always)]
fn reached_white(px: [u16; 3], saturated_from: u32) -> bool {
    (px[0] as u32 >= saturated_from)
        | (px[1] as u32 >= saturated_from)
        | (px[2] as u32 >= saturated_from)
}

/// A decoded frame and its stored size (width, height).
pub type SizedFrame = (LightFrame, (usize, usize));

/// Decodes a dn16 frame (a 16-bit RGB PNG or TIFF of raw digital numbers) and returns it with
/// the stored size: [`DnImage::to_light_frame`] of [`decode_dn_image`], value for value. A
/// plain 16-bit RGB PNG (not interlaced, no transparency) is kept as its DN, linearised where
/// read ([`LightFrame::from_dn`]: half the memory of `f32` planes), filled row by row as it is
/// inflated; anything else takes that long way to `f32` planes, which also names what is
/// wrong with the file.
pub fn decode_dn_frame(bytes: &[u8], path: &Path, levels: &Levels) -> Result<SizedFrame> {
    if let Some(decoded) = png_rows_to_frame(bytes, levels) {
        return decoded.map_err(|e| Error::image(path, e));
    }
    let dn = decode_dn_image(bytes, path)?;
    Ok((dn.to_light_frame(levels), (dn.width, dn.height)))
}

/// [`decode_dn_frame`]'s row-by-row path; `None` for anything but a plain 16-bit RGB PNG.
fn png_rows_to_frame(
    bytes: &[u8],
    levels: &Levels,
) -> Option<std::result::Result<SizedFrame, png::DecodingError>> {
    if !bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        return None;
    }
    png_rows_from(std::io::Cursor::new(bytes), levels)
}

/// A plain 16-bit RGB PNG frame decoded from `reader` row by row as it reads (see
/// [`decode_dn_frame`]), with its size; `None` for anything else, which the caller then reads
/// whole (how much of `reader` was read is not said).
pub fn png_rows_from(
    reader: impl std::io::BufRead + std::io::Seek,
    levels: &Levels,
) -> Option<std::result::Result<SizedFrame, png::DecodingError>> {
    let mut decoder = png::Decoder::new(reader);
    decoder.set_transformations(png::Transformations::IDENTITY);
    // A header the png crate refuses goes the long way, which reports it.
    let mut reader = decoder.read_info().ok()?;
    let info = reader.info();
    let plain = info.color_type == png::ColorType::Rgb
        && info.bit_depth == png::BitDepth::Sixteen
        && !info.interlaced
        && info.trns.is_none();
    if !plain {
        return None;
    }
    let (width, height) = (info.width as usize, info.height as usize);
    let mut frame = DnRows::new(width, height, levels);
    let mut y = 0;
    let decoded = (|| {
        while let Some(row) = reader.next_row()? {
            if y < height {
                frame.row_be_bytes(y, row.data());
            }
            y += 1;
        }
        Ok(())
    })();
    Some(decoded.map(|()| (frame.finish(), (width, height))))
}

/// Reads a 16-bit RGB PNG or TIFF of raw digital numbers.
pub fn read_dn_image(path: &Path) -> Result<DnImage> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_dn_image(&bytes, path)
}

/// Decodes a 16-bit RGB PNG or TIFF already in memory; `path` names it in errors.
pub fn decode_dn_image(bytes: &[u8], path: &Path) -> Result<DnImage> {
    let reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    let decoded = reader.decode().map_err(|e| Error::image(path, e))?;
    let image = match decoded {
        DynamicImage::ImageRgb16(image) => image,
        other => {
            return Err(Error::image(
                path,
                format!(
                    "expected a 16-bit RGB image of raw values, found {:?}",
                    other.color()
                ),
            ))
        }
    };
    let (width, height) = image.dimensions();
    Ok(DnImage {
        width: width as usize,
        height: height as usize,
        data: image.into_raw(),
    })
}

/// Encodes a DN image as a 16-bit RGB PNG: the fast deflate where it saves enough, else
/// stored (noisy raw data barely compresses, and every solve of the set reads the frame: see
/// [`crate::io::encode_frame_png16`]).
pub fn encode_png16(image: &DnImage) -> Result<Vec<u8>> {
    crate::io::encode_frame_png16(image.width, image.height, &image.data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trip_is_exact() {
        let image = DnImage {
            width: 3,
            height: 2,
            data: (0..18).map(|v| v * 1000 + 7).collect(),
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.png");
        std::fs::write(&path, encode_png16(&image).unwrap()).unwrap();
        assert_eq!(read_dn_image(&path).unwrap(), image);
    }

    #[test]
    fn a_png_frame_linearised_row_by_row_equals_the_decoded_image_linearised() {
        let levels = Levels {
            black: 600.0,
            white: 15600.0,
        };
        let (width, height) = (37, 23);
        let mut state = 5u32;
        let image = DnImage {
            width,
            height,
            data: (0..width * height * 3)
                .map(|_| {
                    state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    (state >> 18) as u16 // 0..16383: below black, in range and clipped
                })
                .collect(),
        };
        let path = Path::new("L00.png");
        let bytes = encode_png16(&image).unwrap();
        let (frame, size) = decode_dn_frame(&bytes, path, &levels).unwrap();
        assert_eq!(size, (width, height));
        let expected = decode_dn_image(&bytes, path)
            .unwrap()
            .to_light_frame(&levels);
        assert!(frame.dn.is_some(), "a plain PNG keeps its DN");
        let bits = |f: &LightFrame| -> Vec<u32> {
            f.to_planes()
                .channels()
                .iter()
                .flat_map(|p| p.data.iter().map(|v| v.to_bits()))
                .collect()
        };
        assert_eq!(bits(&frame), bits(&expected));
        let clipped = frame.saturated.as_ref().unwrap();
        assert_eq!(Some(clipped), expected.saturated.as_ref());
        assert!(clipped.data.iter().any(|&c| c) && !clipped.data.iter().all(|&c| c));

        // Cut short: an error that names the file.
        let err = decode_dn_frame(&bytes[..bytes.len() / 2], path, &levels).unwrap_err();
        assert!(err.to_string().contains("L00.png"), "{err}");
        // Not 16-bit RGB: the long way names what it found.
        let mut gray = Vec::new();
        image::DynamicImage::ImageLuma8(image::GrayImage::new(4, 4))
            .write_to(
                &mut std::io::Cursor::new(&mut gray),
                image::ImageFormat::Png,
            )
            .unwrap();
        let err = decode_dn_frame(&gray, path, &levels)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("16-bit RGB") && err.contains("L00.png"),
            "{err}"
        );
    }

    #[test]
    fn light_frame_is_linear_between_the_levels_and_flags_clipped_pixels() {
        let image = DnImage {
            width: 2,
            height: 2,
            data: vec![100, 550, 1000, 64, 325, 775, 999, 999, 999, 1000, 100, 100],
        };
        let levels = Levels {
            black: 100.0,
            white: 1000.0,
        };
        let frame = image.to_light_frame(&levels);
        // (dn - 100) / 900, channel by channel, pixel by pixel.
        let expected = |dn: u16| ((dn as f64 - 100.0) / 900.0) as f32;
        for (c, plane) in [&frame.rgb.r, &frame.rgb.g, &frame.rgb.b]
            .iter()
            .enumerate()
        {
            for i in 0..4 {
                let want = expected(image.data[i * 3 + c]);
                assert!((plane.data[i] - want).abs() <= 1e-7, "c{c} px{i}");
            }
        }
        // Pixels 0 and 3 reached the white level in one channel.
        let clipped = &frame.saturated.as_ref().unwrap().data;
        assert_eq!(clipped, &vec![true, false, false, true]);
        assert!(
            frame.rgb.r.data[1] < 0.0,
            "below black stays negative (noise)"
        );
    }

    /// A frame that clips nowhere gets no mask (none is made); one clipped pixel in a PNG's
    /// last row makes one, flagging that pixel only.
    #[test]
    fn a_mask_is_made_only_for_a_frame_that_clips() {
        let levels = Levels {
            black: 100.0,
            white: 1000.0,
        };
        let mut image = DnImage {
            width: 3,
            height: 2,
            data: vec![500; 18],
        };
        let path = Path::new("L00.png");
        let decode = |image: &DnImage| {
            let bytes = encode_png16(image).unwrap();
            decode_dn_frame(&bytes, path, &levels).unwrap().0
        };
        assert!(decode(&image).saturated.is_none());
        assert!(image.to_light_frame(&levels).saturated.is_none());
        image.data[3 * 4 + 2] = 1000;
        let frame = decode(&image);
        let flags = &frame.saturated.as_ref().expect("a mask").data;
        assert_eq!(flags, &vec![false, false, false, false, true, false]);
        assert_eq!(frame.saturated, image.to_light_frame(&levels).saturated);
    }

    #[test]
    fn the_whole_dn_white_test_is_the_white_level_comparison() {
        let whites = [
            0.0,
            -3.5,
            1.0,
            999.5,
            1000.0,
            65534.2,
            65535.0,
            65535.5,
            1e9,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for white in whites {
            let from = saturated_from(white);
            for v in [0u16, 1, 2, 999, 1000, 1001, 65534, 65535] {
                assert_eq!(v as u32 >= from, v as f64 >= white, "DN {v}, white {white}");
            }
        }
    }

    #[test]
    fn unreadable_and_wrong_kind_images_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("broken.png");
        std::fs::write(&bad, b"\x89PNG\r\n\x1a\nnot really").unwrap();
        let err = read_dn_image(&bad).unwrap_err().to_string();
        assert!(err.contains("broken.png"), "{err}");

        let eight_bit = dir.path().join("eight.png");
        image::RgbImage::new(2, 2).save(&eight_bit).unwrap();
        let err = read_dn_image(&eight_bit).unwrap_err().to_string();
        assert!(err.contains("eight.png") && err.contains("16-bit"), "{err}");

        let err = read_dn_image(&dir.path().join("missing.png"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing.png"), "{err}");
    }
}
