//! The image-sized buffers every stage hands on: `f32` planes and boolean masks in row-major
//! order with explicit width and height (DESIGN.md: "masks are explicit, never NaN-as-mask"),
//! and `Frames`, one RGB image per light, which is what decoding produces and solving consumes.

use rayon::prelude::*;

use crate::error::{Error, Result};

/// One channel of an image: `width * height` samples, row-major, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Plane {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// The samples, `width * height` of them, row after row.
    pub data: Vec<f32>,
}

impl Plane {
    /// A `width x height` plane with every sample `fill`.
    pub fn new(width: usize, height: usize, fill: f32) -> Self {
        Plane {
            width,
            height,
            data: vec![fill; width * height],
        }
    }

    /// Wraps existing samples; fails when their count does not match the size.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Result<Self> {
        if data.len() != width * height {
            return Err(Error::Invalid(format!(
                "plane of {width}x{height} needs {} samples, got {}",
                width * height,
                data.len()
            )));
        }
        Ok(Plane {
            width,
            height,
            data,
        })
    }

    /// The sample at column `x`, row `y` (panics outside the plane).
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Row `y`, left to right.
    pub fn row(&self, y: usize) -> &[f32] {
        &self.data[y * self.width..(y + 1) * self.width]
    }

    /// The number of samples, `width * height`.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// Whether the plane has no samples.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

/// A per-pixel yes/no layer (for example "saturated in this light").
#[derive(Clone, Debug, PartialEq)]
pub struct Mask {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// One flag per pixel, row-major like [`Plane::data`].
    pub data: Vec<bool>,
}

impl Mask {
    /// A `width x height` mask with every pixel `fill`.
    pub fn new(width: usize, height: usize, fill: bool) -> Self {
        Mask {
            width,
            height,
            data: vec![fill; width * height],
        }
    }

    /// The number of pixels set.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&b| b).count()
    }
}

/// Where the pixels of a frame sit on the camera sensor: pixel `(u, v)` of the frame has its
/// centre at sensor coordinates `(x0 + step * u, y0 + step * v)`. A full frame is
/// `{0, 0, 1}`; a centred crop has an offset; 2x2 binning has `step = 2` and a half-pixel
/// offset; a coarse synthetic preview may sample every n-th sensor pixel.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SensorWindow {
    /// Sensor column of frame pixel (0, 0)'s centre, in sensor pixels.
    pub x0: f64,
    /// Sensor row of frame pixel (0, 0)'s centre, in sensor pixels.
    pub y0: f64,
    /// Sensor pixels from one frame pixel to the next (1: every pixel, 2: 2x2 binned).
    pub step: f64,
}

impl SensorWindow {
    /// The whole sensor, pixel for pixel.
    pub const FULL: SensorWindow = SensorWindow {
        x0: 0.0,
        y0: 0.0,
        step: 1.0,
    };

    /// A `width x height` window centred on a `sensor_width x sensor_height` sensor, taking
    /// every `step`-th sensor pixel.
    pub fn centred(
        sensor_width: usize,
        sensor_height: usize,
        width: usize,
        height: usize,
        step: f64,
    ) -> Self {
        let sensor_centre_x = (sensor_width as f64 - 1.0) / 2.0;
        let sensor_centre_y = (sensor_height as f64 - 1.0) / 2.0;
        SensorWindow {
            x0: sensor_centre_x - step * (width as f64 - 1.0) / 2.0,
            y0: sensor_centre_y - step * (height as f64 - 1.0) / 2.0,
            step,
        }
    }

    /// The sensor coordinates (column, row) of frame position `(u, v)`.
    #[inline]
    pub fn to_sensor(&self, u: f64, v: f64) -> (f64, f64) {
        (self.x0 + self.step * u, self.y0 + self.step * v)
    }
}

/// An 8-bit grayscale photograph (chessboard views): row-major, one byte per pixel.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GrayImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// One byte per pixel, row-major, 0 black to 255 white.
    pub data: Vec<u8>,
}

impl GrayImage {
    /// Reads any image the `image` crate decodes (PNG, JPEG, TIFF) as 8-bit luminance.
    pub fn load(path: &std::path::Path) -> Result<GrayImage> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let decoded = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| Error::image(path, e))?
            .decode()
            .map_err(|e| Error::image(path, format!("cannot decode: {e}")))?
            .into_luma8();
        Ok(GrayImage {
            width: decoded.width() as usize,
            height: decoded.height() as usize,
            data: decoded.into_raw(),
        })
    }

    /// Writes an 8-bit grayscale PNG.
    pub fn save_png(&self, path: &std::path::Path) -> Result<()> {
        let buffer =
            image::GrayImage::from_raw(self.width as u32, self.height as u32, self.data.clone())
                .ok_or_else(|| Error::image(path, "image data does not match its size"))?;
        let mut bytes = Vec::new();
        buffer
            .write_to(
                &mut std::io::Cursor::new(&mut bytes),
                image::ImageFormat::Png,
            )
            .map_err(|e| Error::image(path, e))?;
        crate::fsutil::write_atomic(path, &bytes)
    }
}

/// The three colour planes of one photograph, in linear units where 1.0 is the sensor's white
/// level after black-level subtraction.
#[derive(Clone, Debug)]
pub struct RgbPlanes {
    /// Red.
    pub r: Plane,
    /// Green.
    pub g: Plane,
    /// Blue.
    pub b: Plane,
}

impl RgbPlanes {
    /// Three `width x height` planes of zeros.
    pub fn new(width: usize, height: usize) -> Self {
        RgbPlanes {
            r: Plane::new(width, height, 0.0),
            g: Plane::new(width, height, 0.0),
            b: Plane::new(width, height, 0.0),
        }
    }

    /// The planes in R, G, B order.
    pub fn channels(&self) -> [&Plane; 3] {
        [&self.r, &self.g, &self.b]
    }

    /// Width in pixels (all three planes share it).
    pub fn width(&self) -> usize {
        self.r.width
    }

    /// Height in pixels (all three planes share it).
    pub fn height(&self) -> usize {
        self.r.height
    }

    /// Calls `row(y, [r, g, b])` with row `y` of each plane to write, rows in parallel.
    pub fn par_rows_mut<F>(&mut self, row: F)
    where
        F: Fn(usize, [&mut [f32]; 3]) + Sync + Send,
    {
        let w = self.width();
        self.r
            .data
            .par_chunks_mut(w)
            .zip(self.g.data.par_chunks_mut(w))
            .zip(self.b.data.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, ((r, g), b))| row(y, [r, g, b]));
    }
}

/// One photograph taken under one light: its linear RGB values and, where the decoder knows
/// it, which pixels were saturated (such a pixel carries no usable value for this light).
#[derive(Clone, Debug)]
pub struct LightFrame {
    /// The linear colour planes.
    pub rgb: RgbPlanes,
    /// Pixels clipped at the sensor's white level in this light, when the decoder knows.
    pub saturated: Option<Mask>,
}

/// A decoded capture: one frame per light, all the same size, plus where they sit on the
/// sensor (the solver needs each pixel's position on the table).
#[derive(Clone, Debug)]
pub struct Frames {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Where the frames' pixels sit on the sensor.
    pub window: SensorWindow,
    /// One frame per light, in the rig's LED order.
    pub lights: Vec<LightFrame>,
}

impl Frames {
    /// Checks that every frame has the frames' size, so the solver can index blindly.
    pub fn validate(&self) -> Result<()> {
        for (k, frame) in self.lights.iter().enumerate() {
            for plane in frame.rgb.channels() {
                if plane.width != self.width
                    || plane.height != self.height
                    || plane.len() != self.width * self.height
                {
                    return Err(Error::Invalid(format!(
                        "frame for light {k} is {}x{}, the capture is {}x{}",
                        plane.width, plane.height, self.width, self.height
                    )));
                }
            }
            if let Some(mask) = &frame.saturated {
                if mask.width != self.width || mask.height != self.height {
                    return Err(Error::Invalid(format!(
                        "saturation mask for light {k} is {}x{}, the capture is {}x{}",
                        mask.width, mask.height, self.width, self.height
                    )));
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centred_window_maps_the_middle_pixel_to_the_sensor_centre() {
        let w = SensorWindow::centred(4928, 3264, 101, 51, 2.0);
        let (x, y) = w.to_sensor(50.0, 25.0);
        assert!((x - 2463.5).abs() < 1e-9 && (y - 1631.5).abs() < 1e-9);
        let (x0, _) = w.to_sensor(0.0, 0.0);
        assert!((x0 - (2463.5 - 100.0)).abs() < 1e-9);
    }

    #[test]
    fn frames_with_a_wrong_sized_plane_are_rejected() {
        let mut frames = Frames {
            width: 4,
            height: 3,
            window: SensorWindow::FULL,
            lights: vec![LightFrame {
                rgb: RgbPlanes::new(4, 3),
                saturated: None,
            }],
        };
        assert!(frames.validate().is_ok());
        frames.lights[0].rgb.g = Plane::new(3, 3, 0.0);
        let err = frames.validate().unwrap_err().to_string();
        assert!(err.contains("light 0"), "{err}");
    }

    #[test]
    fn from_vec_checks_the_sample_count() {
        assert!(Plane::from_vec(2, 2, vec![0.0; 4]).is_ok());
        assert!(Plane::from_vec(2, 2, vec![0.0; 3]).is_err());
    }
}
