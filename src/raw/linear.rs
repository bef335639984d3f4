//! 16-bit RGB images holding raw digital numbers (black level included), as written by the
//! synthetic sensor, and their conversion to linear planes.

use std::path::Path;

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ImageBuffer, Rgb};

use crate::error::{Error, Result};
use crate::plane::{LightFrame, Mask, RgbPlanes};
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
    /// level carries no usable value).
    pub fn to_light_frame(&self, levels: &Levels) -> LightFrame {
        let n = self.width * self.height;
        let mut rgb = RgbPlanes::new(self.width, self.height);
        let mut saturated = Mask::new(self.width, self.height, false);
        let scale = 1.0 / (levels.white - levels.black);
        let linear = |v: u16| ((v as f64 - levels.black) * scale) as f32;
        // Zipped iterators, not indexing: no bounds check per sample of a 16 MP frame.
        let pixels = self.data[..n * 3]
            .chunks_exact(3)
            .zip(&mut rgb.r.data)
            .zip(&mut rgb.g.data)
            .zip(&mut rgb.b.data)
            .zip(&mut saturated.data);
        for ((((px, r), g), b), clipped) in pixels {
            *clipped = px.iter().any(|&v| v as f64 >= levels.white);
            (*r, *g, *b) = (linear(px[0]), linear(px[1]), linear(px[2]));
        }
        LightFrame {
            rgb,
            saturated: Some(saturated),
            cfa: None,
        }
    }
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

/// Encodes a DN image as a 16-bit RGB PNG with fast compression (noisy raw data barely
/// compresses; speed matters more).
pub fn encode_png16(image: &DnImage) -> Result<Vec<u8>> {
    let buffer: ImageBuffer<Rgb<u16>, Vec<u16>> =
        ImageBuffer::from_raw(image.width as u32, image.height as u32, image.data.clone())
            .ok_or_else(|| Error::Invalid("DN image size does not match its data".into()))?;
    let mut bytes = Vec::new();
    let encoder = PngEncoder::new_with_quality(&mut bytes, CompressionType::Fast, FilterType::Sub);
    DynamicImage::ImageRgb16(buffer)
        .write_with_encoder(encoder)
        .map_err(|e| Error::Invalid(format!("PNG encoding failed: {e}")))?;
    Ok(bytes)
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
