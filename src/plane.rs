//! The image-sized buffers every stage hands on: `f32` planes and boolean masks in row-major
//! order with explicit width and height (DESIGN.md: "masks are explicit, never NaN-as-mask"),
//! and `Frames`, one RGB image per light, which is what decoding produces and solving consumes.

mod dn;
mod release;

use rayon::prelude::*;

pub use dn::{Dark, DnMosaic, DnSamples};
pub use release::FrameRelease;

use crate::error::{Error, Result};

/// Asks the CPU to start loading the cache line of `data[i]`, when `i` is inside it (the
/// solver reads many planes at once, more streams than the hardware prefetchers track).
#[inline(always)]
pub fn prefetch_at<T>(data: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if i < data.len() {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: `i` is inside the slice; prefetching never faults.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(data.as_ptr().add(i) as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, i);
}

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

    /// Three planes of no samples (a frame that stores its values elsewhere).
    pub fn empty() -> Self {
        RgbPlanes::new(0, 0)
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

    /// Calls `band(y0, [r, g, b])` with the rows from `y0` of each plane to write, `rows` of
    /// them (fewer in the last band), bands in parallel: for work that carries state from
    /// one row to the next.
    pub fn par_bands_mut<F>(&mut self, rows: usize, band: F)
    where
        F: Fn(usize, [&mut [f32]; 3]) + Sync + Send,
    {
        let n = self.width() * rows.max(1);
        self.r
            .data
            .par_chunks_mut(n.max(1))
            .zip(self.g.data.par_chunks_mut(n.max(1)))
            .zip(self.b.data.par_chunks_mut(n.max(1)))
            .enumerate()
            .for_each(|(i, ((r, g), b))| band(i * rows.max(1), [r, g, b]));
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
///
/// A full-resolution RAW frame stores one sample per pixel and takes its missing channels
/// from colour ratios that every frame of its stack shares ([`CfaColour`]): ten 16 MP frames
/// then take 0.8 GB rather than 1.9 GB with `f32` samples, and 0.5 GB with the samples kept
/// as the DN they were decoded as (`cfa_dn`, as a set's loader keeps them). Read such a
/// frame's values with [`Self::rgb_at`] or [`Self::to_planes`] (or its own sample with
/// [`Self::cfa_sample`], and the others from it with [`CfaColour::rgb`]); its `rgb.r` and
/// `rgb.b` are empty.
#[derive(Clone, Debug)]
pub struct LightFrame {
    /// The linear colour planes; with `cfa`, `g` holds every pixel's own CFA sample (whatever
    /// its channel) and `r` and `b` are empty.
    pub rgb: RgbPlanes,
    /// Pixels clipped at the sensor's white level in this light, when the decoder knows.
    pub saturated: Option<Mask>,
    /// How the missing channels follow from each pixel's own sample, for a frame stored as
    /// one CFA sample per pixel (`None`: `rgb` holds all three planes).
    pub cfa: Option<CfaColour>,
    /// A dn16 frame kept as its 16-bit samples, linearised where read; `rgb`'s planes are
    /// then empty.
    pub dn: Option<DnSamples>,
    /// With `cfa`, the own CFA samples kept as the RAW frame's DN, linearised where read;
    /// `rgb`'s planes are then all empty.
    pub cfa_dn: Option<DnMosaic>,
}

impl LightFrame {
    /// A frame of three full planes.
    pub fn from_rgb(rgb: RgbPlanes, saturated: Option<Mask>) -> Self {
        LightFrame {
            rgb,
            saturated,
            cfa: None,
            dn: None,
            cfa_dn: None,
        }
    }

    /// A dn16 frame kept as its 16-bit samples (see [`DnSamples`]); its `rgb` planes are
    /// left empty.
    pub fn from_dn(samples: DnSamples, saturated: Option<Mask>) -> Self {
        LightFrame {
            rgb: RgbPlanes::empty(),
            saturated,
            cfa: None,
            dn: Some(samples),
            cfa_dn: None,
        }
    }

    /// The frame with `f32` planes in `rgb` (converted from its dn16 samples where it keeps
    /// those), for code that reads the planes directly.
    pub fn with_planes(self) -> Self {
        match &self.dn {
            Some(dn) => LightFrame::from_rgb(dn.to_planes(), self.saturated),
            None => self,
        }
    }

    /// A frame stored as one CFA sample per pixel (`sample`, whatever each pixel's channel),
    /// its missing channels following from `cfa`; its `rgb.r` and `rgb.b` are left empty.
    pub fn from_cfa(sample: Plane, saturated: Option<Mask>, cfa: CfaColour) -> Self {
        LightFrame {
            rgb: RgbPlanes {
                r: Plane::new(0, 0, 0.0),
                g: sample,
                b: Plane::new(0, 0, 0.0),
            },
            saturated,
            cfa: Some(cfa),
            dn: None,
            cfa_dn: None,
        }
    }

    /// [`Self::from_cfa`] with the own samples kept as DN (see [`DnMosaic`]); all of `rgb`'s
    /// planes are left empty.
    pub fn from_cfa_dn(samples: DnMosaic, saturated: Option<Mask>, cfa: CfaColour) -> Self {
        LightFrame {
            rgb: RgbPlanes::empty(),
            saturated,
            cfa: Some(cfa),
            dn: None,
            cfa_dn: Some(samples),
        }
    }

    /// Pixel `i` (at `x`, `y`)'s own CFA sample, for a frame stored as one (`cfa`).
    #[inline(always)]
    pub fn cfa_sample(&self, i: usize, x: usize, y: usize) -> f32 {
        match &self.cfa_dn {
            Some(dn) => dn.value(x, y),
            None => self.rgb.g.data[i],
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.size().0
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.size().1
    }

    /// Width and height, from whichever store holds the frame's samples.
    fn size(&self) -> (usize, usize) {
        match (&self.dn, &self.cfa_dn) {
            (Some(d), _) => (d.width, d.height),
            (None, Some(d)) => (d.width, d.height),
            (None, None) => (self.rgb.g.width, self.rgb.g.height),
        }
    }

    /// The three channels of pixel (`x`, `y`), however the frame stores them.
    #[inline]
    pub fn rgb_at(&self, x: usize, y: usize) -> [f32; 3] {
        let i = y * self.width() + x;
        match (&self.cfa, &self.dn) {
            (Some(cfa), _) => cfa.rgb(self.cfa_sample(i, x, y), i, cfa.own(x, y)),
            (None, Some(dn)) => std::array::from_fn(|c| dn.value(c, i)),
            (None, None) => [self.rgb.r.data[i], self.rgb.g.data[i], self.rgb.b.data[i]],
        }
    }

    /// The frame as three full planes: borrowed when it has them, built from the own samples
    /// and the shared ratios otherwise (for the stages that want planes and run on a small or
    /// binned image: cropping, binning, previews).
    pub fn to_planes(&self) -> std::borrow::Cow<'_, RgbPlanes> {
        match (&self.cfa, &self.dn) {
            (None, None) => std::borrow::Cow::Borrowed(&self.rgb),
            (None, Some(dn)) => std::borrow::Cow::Owned(dn.to_planes()),
            (Some(_), _) => {
                std::borrow::Cow::Owned(self.window_planes(0, 0, self.width(), self.height()))
            }
        }
    }

    /// Three planes of the `width x height` window whose top-left pixel is (`x0`, `y0`)
    /// (which must lie inside the frame).
    pub fn window_planes(&self, x0: usize, y0: usize, width: usize, height: usize) -> RgbPlanes {
        let mut out = RgbPlanes::new(width, height);
        out.par_rows_mut(|y, [r, g, b]| {
            for x in 0..width {
                [r[x], g[x], b[x]] = self.rgb_at(x0 + x, y0 + y);
            }
        });
        out
    }
}

/// The colour of a frame stored as one CFA sample per pixel: channel `c` of pixel `i` is
/// its own sample `v` when `c` is the pixel's own channel, else
/// `v * ratios[c][i] * colour[c] / colour[own]`. The `ratios` (each channel over the pixel's
/// own, the same in every frame of a stack) are shared; `colour` is this frame's illuminant's
/// raw colour (see `raw::develop_stack`).
#[derive(Clone, Debug)]
pub struct CfaColour {
    /// The CFA pattern: `pattern[y % 2][x % 2]` is pixel (x, y)'s own channel.
    pub pattern: [[u8; 2]; 2],
    /// Per pixel, each channel's ratio to its own channel; shared by the frames of a stack.
    pub ratios: std::sync::Arc<RgbPlanes>,
    /// This frame's illuminant colour (raw R, G, B).
    pub colour: [f32; 3],
}

impl CfaColour {
    /// Pixel (`x`, `y`)'s own channel.
    #[inline(always)]
    pub fn own(&self, x: usize, y: usize) -> usize {
        self.pattern[y % 2][x % 2] as usize
    }

    /// Pixel `i`'s three channels from its own sample `v` of channel `own`. The arithmetic
    /// (and so every bit) is what the stack demosaic wrote into full planes.
    #[inline(always)]
    pub fn rgb(&self, v: f32, i: usize, own: usize) -> [f32; 3] {
        let ratios = self.ratios.channels();
        std::array::from_fn(|c| {
            if c == own {
                v
            } else {
                v * ratios[c].data[i] * self.colour[c] / self.colour[own]
            }
        })
    }
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
            let wrong_size = |width: usize, height: usize| {
                Error::Invalid(format!(
                    "frame for light {k} is {width}x{height}, the capture is {}x{}",
                    self.width, self.height
                ))
            };
            let planes = match (&frame.cfa, &frame.dn) {
                (None, None) => frame.rgb.channels().to_vec(),
                (Some(cfa), _) => {
                    if let Some(dn) = &frame.cfa_dn {
                        if (dn.width, dn.height) != (self.width, self.height) {
                            return Err(wrong_size(dn.width, dn.height));
                        }
                        dn.check_size()
                            .map_err(|e| Error::Invalid(format!("frame for light {k} {e}")))?;
                    }
                    let own = frame.cfa_dn.is_none().then_some(&frame.rgb.g);
                    own.into_iter().chain(cfa.ratios.channels()).collect()
                }
                (None, Some(dn)) => {
                    if (dn.width, dn.height) != (self.width, self.height) {
                        return Err(wrong_size(dn.width, dn.height));
                    }
                    dn.check_size()
                        .map_err(|e| Error::Invalid(format!("frame for light {k} {e}")))?;
                    Vec::new()
                }
            };
            for plane in planes {
                if plane.width != self.width
                    || plane.height != self.height
                    || plane.len() != self.width * self.height
                {
                    return Err(wrong_size(plane.width, plane.height));
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
            lights: vec![LightFrame::from_rgb(RgbPlanes::new(4, 3), None)],
        };
        assert!(frames.validate().is_ok());
        frames.lights[0].rgb.g = Plane::new(3, 3, 0.0);
        let err = frames.validate().unwrap_err().to_string();
        assert!(err.contains("light 0"), "{err}");
    }

    /// A 4x3 CFA frame (RGGB) whose ratios and colour make every channel distinct.
    fn cfa_frame() -> LightFrame {
        let (w, h) = (4, 3);
        let sample = Plane::from_vec(w, h, (0..w * h).map(|i| 1.0 + i as f32).collect()).unwrap();
        let mut ratios = RgbPlanes::new(w, h);
        ratios.par_rows_mut(|y, mut rows| {
            for x in 0..w {
                for (c, row) in rows.iter_mut().enumerate() {
                    row[x] = 0.5 + 0.1 * (c + x + 3 * y) as f32;
                }
            }
        });
        LightFrame::from_cfa(
            sample,
            None,
            CfaColour {
                pattern: [[0, 1], [1, 2]],
                ratios: std::sync::Arc::new(ratios),
                colour: [0.8, 1.0, 1.25],
            },
        )
    }

    #[test]
    fn a_cfa_frame_keeps_its_own_sample_and_scales_the_others() {
        let f = cfa_frame();
        let ratios = f.cfa.as_ref().unwrap().ratios.clone();
        let colour = [0.8f32, 1.0, 1.25];
        let planes = f.to_planes();
        for y in 0..3 {
            for x in 0..4 {
                let i = y * 4 + x;
                let own = [[0, 1], [1, 2]][y % 2][x % 2];
                let v = 1.0 + i as f32;
                let want: [f32; 3] = std::array::from_fn(|c| {
                    if c == own {
                        v
                    } else {
                        v * ratios.channels()[c].data[i] * colour[c] / colour[own]
                    }
                });
                assert_eq!(f.rgb_at(x, y), want, "({x}, {y})");
                assert_eq!([0, 1, 2].map(|c| planes.channels()[c].data[i]), want);
            }
        }
        // A window is the same pixels, whatever its CFA phase.
        let window = f.window_planes(1, 1, 3, 2);
        for (y, x) in [(0, 0), (1, 2), (0, 1)] {
            let got = [0, 1, 2].map(|c| window.channels()[c].data[y * 3 + x]);
            assert_eq!(got, f.rgb_at(x + 1, y + 1));
        }
    }

    #[test]
    fn a_cfa_frame_with_ratios_of_another_size_is_rejected() {
        let mut frame = cfa_frame();
        let frames = |frame: LightFrame| Frames {
            width: 4,
            height: 3,
            window: SensorWindow::FULL,
            lights: vec![frame],
        };
        assert!(frames(frame.clone()).validate().is_ok());
        frame.cfa.as_mut().unwrap().ratios = std::sync::Arc::new(RgbPlanes::new(4, 2));
        assert!(frames(frame).validate().is_err());
    }

    #[test]
    fn from_vec_checks_the_sample_count() {
        assert!(Plane::from_vec(2, 2, vec![0.0; 4]).is_ok());
        assert!(Plane::from_vec(2, 2, vec![0.0; 3]).is_err());
    }
}
