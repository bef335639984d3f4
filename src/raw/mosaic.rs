//! The colour-filter-array (Bayer) samples of one RAW frame, and the two ways psscan turns a
//! stack of them (one frame per light) into linear RGB planes:
//!
//! - **Half resolution, 2x2 binning.** Each 2x2 CFA cell (one R, two G, one B sample) becomes one
//!   pixel: R and B are the cell's own samples, G the mean of its two greens. Exact, no
//!   interpolation, a quarter of the data. The binned pixel's centre is the cell's centre, so the
//!   frame's [`SensorWindow`] doubles its step and moves half a sensor pixel (see
//!   [`Resolution::window`]). R and B come from sites half a pixel off that centre (diagonally,
//!   in opposite directions); G's two sites are symmetric about it. For a Lambertian surface the
//!   binned pixel measures exactly a surface whose scaled normal is the luminance-weighted sum
//!   of its four sites' scaled normals, which is the ground truth psscan compares it with.
//! - **Full resolution, shading-preserving demosaic** ([`develop_stack`](super::develop_stack)): every pixel keeps its
//!   own sample, and its two missing channels are that sample times the pixel's colour ratios,
//!   which come from the whole stack (they are the same under every light). Each pixel's
//!   shading, which is what photometric stereo reads, is therefore its own, never its
//!   neighbours'. With the lights' shading vectors the ratios come from every site's fitted
//!   albedo, interpolated along the pixel's own material (`shading`, `hue`) and averaged over
//!   the pixels of the same chroma around (`chroma`); without them from
//!   a plain [`bilinear`] demosaic of the stack's sum.
//!
//! Values are linear: `(sample - black[site]) / (white - black[site])`, 1.0 at the white level.
//! A pixel is saturated when a CFA sample whose value it carries is at or near the white level
//! (within [`SATURATION_MARGIN`] of full scale, where real sensors stop being linear): any of the
//! four samples of a binned cell; the own sample at full resolution.

use std::sync::Arc;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::plane::{Dark, DnMosaic, LightFrame, Mask, RgbPlanes, SensorWindow};

mod binning;
pub(super) use binning::{bin_rows, SampleRow};

/// Index of the red channel (the channel indices are those of `RgbPlanes`).
pub const RED: u8 = 0;
/// Index of the green channel.
pub const GREEN: u8 = 1;
/// Index of the blue channel.
pub const BLUE: u8 = 2;

/// A sample this close to the white level (as a fraction of white - black) counts as saturated.
pub const SATURATION_MARGIN: f32 = 0.01;

/// How a frame's CFA samples become RGB pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Resolution {
    /// One RGB pixel per CFA sample, by the shading-preserving demosaic: each pixel keeps its
    /// own sample, its missing channels scaled from it by colour ratios from the whole stack.
    #[default]
    Full,
    /// 2x2 CFA binning: one RGB pixel per 2x2 cell, half the width and height.
    Half,
}

impl Resolution {
    /// The developed image size for a mosaic of `width x height` samples (binning drops an odd
    /// last row or column).
    pub fn size(self, width: usize, height: usize) -> (usize, usize) {
        match self {
            Resolution::Full => (width, height),
            Resolution::Half => (width / 2, height / 2),
        }
    }

    /// Where the developed pixels sit on the sensor, given where the mosaic's samples sit.
    /// A binned pixel `(u, v)` is the mean of samples `2u, 2u+1` (and rows `2v, 2v+1`), whose
    /// centre is at sample coordinate `2u + 0.5`.
    pub fn window(self, mosaic: SensorWindow) -> SensorWindow {
        match self {
            Resolution::Full => mosaic,
            Resolution::Half => SensorWindow {
                x0: mosaic.x0 + 0.5 * mosaic.step,
                y0: mosaic.y0 + 0.5 * mosaic.step,
                step: 2.0 * mosaic.step,
            },
        }
    }

    /// Noise variance of each developed channel relative to one raw sample at the same signal.
    /// Binning: R and B are single samples (1), G the mean of two (1/2), all independent. Full
    /// resolution: each channel is the pixel's own sample times a colour ratio, so the three
    /// share that sample's noise (1 each, and fully correlated: `NoiseModel::shared_cfa_sample`).
    pub fn channel_variance_scale(self) -> [f64; 3] {
        match self {
            Resolution::Half => [1.0, 0.5, 1.0],
            Resolution::Full => [1.0, 1.0, 1.0],
        }
    }

    /// How this resolution turns CFA samples into RGB pixels, in words (for reports).
    pub fn method(self) -> &'static str {
        match self {
            Resolution::Half => "2x2 CFA binning (R, mean of the two G, B of each cell)",
            Resolution::Full => {
                "shading-preserving demosaic: each pixel's own CFA sample, the missing channels \
                 scaled from it by the pixel's colour ratios from the whole stack (each CFA \
                 site's albedo fitted under the rig's lights, interpolated along the pixel's own \
                 material, the chroma then averaged over the pixels of the same chroma around; \
                 isolated pixels that show one material through the weave's holes take its \
                 colour, measured on all of them; without the lights, a bilinear demosaic of \
                 the white-balanced sum of all frames)"
            }
        }
    }
}

/// The CFA samples of one frame (the sensor's active area), with their levels.
#[derive(Clone, Debug, PartialEq)]
pub struct Mosaic {
    /// Width in CFA samples.
    pub width: usize,
    /// Height in CFA samples.
    pub height: usize,
    /// Channel of the sample at `(x, y)`: `pattern[y % 2][x % 2]`, a Bayer pattern (one R, one
    /// B and two G on a diagonal).
    pub pattern: [[u8; 2]; 2],
    /// Black level of each CFA site, indexed like `pattern`.
    pub black: [[f32; 2]; 2],
    /// The white level: the raw value (DN) of a full-scale sample.
    pub white: f32,
    /// Row-major samples, `width * height`.
    pub samples: Vec<u16>,
}

impl Mosaic {
    /// Checks the pattern is a 2x2 Bayer layout and the sizes and levels make sense.
    pub fn validate(&self) -> Result<()> {
        if self.samples.len() != self.width * self.height {
            return Err(Error::Invalid(format!(
                "mosaic of {}x{} needs {} samples, has {}",
                self.width,
                self.height,
                self.width * self.height,
                self.samples.len()
            )));
        }
        if self.width < 2 || self.height < 2 {
            return Err(Error::Invalid(format!(
                "a {}x{} mosaic is too small to develop (at least 2x2)",
                self.width, self.height
            )));
        }
        let p = self.pattern;
        let greens_on_a_diagonal =
            (p[0][0] == GREEN && p[1][1] == GREEN) || (p[0][1] == GREEN && p[1][0] == GREEN);
        let mut counts = [0; 3];
        for c in p.iter().flatten() {
            if let Some(n) = counts.get_mut(*c as usize) {
                *n += 1;
            }
        }
        if !greens_on_a_diagonal || counts != [1, 2, 1] {
            return Err(Error::Unsupported(format!(
                "CFA pattern {} is not a Bayer pattern (RGGB, BGGR, GRBG or GBRG)",
                self.pattern_name()
            )));
        }
        for b in self.black.iter().flatten() {
            if !(b.is_finite() && *b >= 0.0 && *b < self.white) {
                return Err(Error::Invalid(format!(
                    "black level {b} does not lie below the white level {}",
                    self.white
                )));
            }
        }
        Ok(())
    }

    /// The pattern as the usual four letters, row by row (e.g. "RGGB").
    pub fn pattern_name(&self) -> String {
        self.pattern
            .iter()
            .flatten()
            .map(|&c| match c {
                RED => 'R',
                GREEN => 'G',
                BLUE => 'B',
                _ => '?',
            })
            .collect()
    }

    /// A pattern from its four letters; `None` for anything but R, G, B.
    pub fn parse_pattern(name: &str) -> Option<[[u8; 2]; 2]> {
        let codes: Vec<u8> = name
            .chars()
            .map(|c| match c {
                'R' => Some(RED),
                'G' => Some(GREEN),
                'B' => Some(BLUE),
                _ => None,
            })
            .collect::<Option<_>>()?;
        (codes.len() == 4).then(|| [[codes[0], codes[1]], [codes[2], codes[3]]])
    }

    /// The mean of the four sites' black levels.
    pub fn mean_black(&self) -> f64 {
        self.black.iter().flatten().map(|&b| b as f64).sum::<f64>() / 4.0
    }

    /// Samples at or above this value are saturated.
    pub fn saturation_threshold(&self) -> f32 {
        let darkest = self.black.iter().flatten().fold(0.0f32, |a, &b| a.max(b));
        self.white - SATURATION_MARGIN * (self.white - darkest)
    }
}

/// A mosaic's samples in linear units, with their saturation flags.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearMosaic {
    /// Width in CFA samples.
    pub width: usize,
    /// Height in CFA samples.
    pub height: usize,
    /// The CFA pattern, as [`Mosaic::pattern`].
    pub pattern: [[u8; 2]; 2],
    /// Linear samples, row-major: 0 at the site's black level, 1.0 at the white level; empty
    /// when `dn` keeps them.
    pub values: Vec<f32>,
    /// Per sample, whether the raw value was at or near the white level (see
    /// [`Mosaic::saturation_threshold`]); empty when no sample is (a frame kept as DN that
    /// clips nowhere need not write a flag per sample). Read with
    /// [`LinearMosaic::saturated_at`] and [`LinearMosaic::saturated_row`].
    pub saturated: Vec<bool>,
    /// The samples kept as the DN they were decoded as, linearised where read (a light frame
    /// of a full-resolution stack, see `raw::pass::keep_dn`); `values` is then empty. Read
    /// the samples with [`LinearMosaic::value`] and [`LinearMosaic::row`], which serve both.
    pub dn: Option<DnMosaic>,
}

impl LinearMosaic {
    /// Sample `i` (row-major), linear, the dark frame subtracted.
    #[inline]
    pub fn value(&self, i: usize) -> f32 {
        match &self.dn {
            Some(dn) => dn.value(i % self.width, i / self.width),
            None => self.values[i],
        }
    }

    /// Row `y`'s samples: borrowed from `values`, or linearised from the DN into `scratch`.
    pub fn row<'a>(&'a self, y: usize, scratch: &'a mut Vec<f32>) -> &'a [f32] {
        let w = self.width;
        match &self.dn {
            Some(dn) => {
                scratch.resize(w, 0.0);
                dn.row_into(y, scratch);
                scratch
            }
            None => &self.values[y * w..(y + 1) * w],
        }
    }

    /// Whether sample `i` is saturated.
    #[inline]
    pub fn saturated_at(&self, i: usize) -> bool {
        !self.saturated.is_empty() && self.saturated[i]
    }

    /// Row `y`'s saturation flags; `None` when no sample of the mosaic is saturated.
    pub fn saturated_row(&self, y: usize) -> Option<&[bool]> {
        let w = self.width;
        (!self.saturated.is_empty()).then(|| &self.saturated[y * w..(y + 1) * w])
    }

    /// The saturation flags as a mask; `None` when no sample is saturated.
    pub fn saturated_mask(saturated: Vec<bool>, width: usize, height: usize) -> Option<Mask> {
        (!saturated.is_empty()).then_some(Mask {
            width,
            height,
            data: saturated,
        })
    }

    /// Channel of the sample at `(x, y)`.
    #[inline]
    pub fn channel(&self, x: usize, y: usize) -> usize {
        self.pattern[y % 2][x % 2] as usize
    }

    /// Subtracts a dark frame the frames of a stack share, sample by sample (a sample saturated
    /// in either is saturated): a frame that keeps its DN keeps the dark frame's samples too,
    /// and subtracts them where they are read.
    pub fn subtract_shared(&mut self, dark: &SharedDark) -> Result<()> {
        dark.layout
            .check_same_layout(self.width, self.height, self.pattern)?;
        match &mut self.dn {
            Some(dn) => dn.dark = Some(Arc::clone(&dark.values)),
            None => self
                .values
                .par_iter_mut()
                .zip(dark.values.as_slice())
                .for_each(|(v, d)| *v -= d),
        }
        if dark.clips {
            if self.saturated.is_empty() {
                self.saturated = vec![false; self.width * self.height];
            }
            for (s, d) in self.saturated.iter_mut().zip(&dark.layout.saturated) {
                *s |= *d;
            }
        }
        Ok(())
    }

    /// Checks that this dark frame has a light frame's size and CFA pattern.
    pub(super) fn check_same_layout(
        &self,
        width: usize,
        height: usize,
        pattern: [[u8; 2]; 2],
    ) -> Result<()> {
        if (self.width, self.height, self.pattern) == (width, height, pattern) {
            return Ok(());
        }
        let describe = |w: usize, h: usize, pattern: [[u8; 2]; 2]| {
            let names = pattern.map(|row| row.map(|c| ["R", "G", "B"][c as usize].to_string()));
            format!("{w}x{h} {}", names.concat().concat())
        };
        Err(Error::Invalid(format!(
            "the dark frame is a {} mosaic, the light frame {}",
            describe(self.width, self.height, self.pattern),
            describe(width, height, pattern)
        )))
    }

    /// 2x2 binning: R and B of each cell, the mean of its two G.
    pub(super) fn bin2x2(&self) -> LightFrame {
        let fill_row = |y: usize, row: &mut SampleRow, _: &mut ()| {
            let SampleRow {
                values,
                saturated,
                scratch,
            } = row;
            values.clear();
            values.extend_from_slice(self.row(y, scratch));
            saturated.clear();
            match self.saturated_row(y) {
                Some(flags) => saturated.extend_from_slice(flags),
                None => saturated.resize(self.width, false),
            }
        };
        let (frame, _) = bin_rows((self.width, self.height), self.pattern, || (), fill_row);
        frame
    }
}

/// A dark frame as the light frames of a stack subtract it: its linear samples shared, so that
/// frames kept as DN hold one copy between them.
pub struct SharedDark {
    /// The frame's size, pattern and saturation flags (its `values` moved to `values`).
    layout: LinearMosaic,
    values: Arc<Vec<f32>>,
    /// Whether any of its samples is saturated (looked up once, not once per light frame).
    clips: bool,
}

impl SharedDark {
    /// `dark`'s samples, shared; a dark frame must be linearised (not kept as DN).
    pub fn of(mut dark: LinearMosaic) -> Result<SharedDark> {
        if dark.dn.is_some() {
            return Err(Error::Invalid(
                "a dark frame is subtracted as linear samples, not kept as DN".into(),
            ));
        }
        let values = Arc::new(std::mem::take(&mut dark.values));
        let clips = dark.saturated.par_iter().any(|&s| s);
        Ok(SharedDark {
            layout: dark,
            values,
            clips,
        })
    }
}

/// Mirrors an index about the border of a line of `n` samples (keeps the CFA phase where
/// `n` allows one); indices further out than the line is long stay on the line.
pub(super) fn mirror(i: isize, n: usize) -> usize {
    if i < 0 {
        ((-i) as usize).min(n - 1)
    } else if i as usize >= n {
        (2 * (n - 1)).saturating_sub(i as usize)
    } else {
        i as usize
    }
}

/// Bilinear demosaic of `values` laid out as `pattern`: each pixel keeps its own sample for
/// its own channel; a missing channel is the mean of the nearest samples of that channel (the
/// two horizontal or the two vertical neighbours at a G site; the four edge neighbours for G
/// and the four diagonal ones for R or B at an R or B site). The mosaic is mirrored about its
/// border, which keeps the CFA phase.
pub fn bilinear(width: usize, height: usize, pattern: [[u8; 2]; 2], values: &[f32]) -> RgbPlanes {
    let (w, h) = (width, height);
    let mut rgb = RgbPlanes::new(w, h);
    rgb.par_rows_mut(|y, out| {
        let row = |yy: usize| &values[yy * w..(yy + 1) * w];
        let (up, mid, down) = (
            row(mirror(y as isize - 1, h)),
            row(y),
            row(mirror(y as isize + 1, h)),
        );
        let site_row = y % 2;
        for x in 0..w {
            let xm = mirror(x as isize - 1, w);
            let xp = mirror(x as isize + 1, w);
            let own = pattern[site_row][x % 2] as usize;
            let horizontal = 0.5 * (mid[xm] + mid[xp]);
            let vertical = 0.5 * (up[x] + down[x]);
            out[own][x] = mid[x];
            if own == GREEN as usize {
                let across = pattern[site_row][(x + 1) % 2] as usize;
                let along = pattern[(site_row + 1) % 2][x % 2] as usize;
                out[across][x] = horizontal;
                out[along][x] = vertical;
            } else {
                out[GREEN as usize][x] = 0.5 * (horizontal + vertical);
                out[2 - own][x] = 0.25 * (up[xm] + up[xp] + down[xm] + down[xp]);
            }
        }
    });
    rgb
}

/// A dark frame and its saturation, to subtract from light frames developed the same way.
/// It is shared with the light frames kept as DN ([`LightFrame::from_dn`]), which subtract it
/// as their values are read.
#[derive(Clone, Debug)]
pub struct DarkFrame {
    /// The dark frame's values, as DN or linear planes.
    pub values: Arc<Dark>,
    /// Its pixels clipped at the white level, when known.
    pub saturated: Option<Mask>,
}

impl DarkFrame {
    /// The dark frame of `frame`, kept as it was decoded.
    pub fn of(frame: LightFrame) -> Self {
        let values = match frame.dn {
            Some(dn) => Dark::Dn(dn),
            None => Dark::Planes(frame.rgb),
        };
        DarkFrame {
            values: Arc::new(values),
            saturated: frame.saturated,
        }
    }
}

/// Subtracts a dark frame from a light frame, pixel by pixel: a frame kept as DN gets the dark
/// frame attached (see [`crate::plane::DnSamples`]), one of `f32` planes has it subtracted
/// now, to the same bits. A pixel saturated in either frame is saturated in the result.
pub fn subtract_dark(frame: &mut LightFrame, dark: &DarkFrame) -> Result<()> {
    let (w, h) = (frame.width(), frame.height());
    let (dark_w, dark_h) = dark.values.size();
    if (dark_w, dark_h) != (w, h) {
        return Err(Error::Invalid(format!(
            "the dark frame is {dark_w}x{dark_h}, the light frame {w}x{h}"
        )));
    }
    match &mut frame.dn {
        Some(dn) => dn.dark = Some(Arc::clone(&dark.values)),
        None => {
            let planes = [&mut frame.rgb.r, &mut frame.rgb.g, &mut frame.rgb.b];
            for (c, plane) in planes.into_iter().enumerate() {
                (plane.data.par_iter_mut().enumerate())
                    .for_each(|(i, v)| *v -= dark.values.value(c, i));
            }
        }
    }
    if let Some(dark_sat) = &dark.saturated {
        let mask = frame
            .saturated
            .get_or_insert_with(|| Mask::new(w, h, false));
        for (m, d) in mask.data.iter_mut().zip(&dark_sat.data) {
            *m |= *d;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mosaic whose sample at (x, y) encodes its position, so tests can tell which samples
    /// went where.
    fn mosaic(width: usize, height: usize, pattern: &str) -> Mosaic {
        Mosaic {
            width,
            height,
            pattern: Mosaic::parse_pattern(pattern).unwrap(),
            black: [[100.0, 100.0], [100.0, 100.0]],
            white: 10100.0,
            samples: (0..width * height)
                .map(|i| 100 + (i % width) as u16 * 10 + (i / width) as u16 * 1000)
                .collect(),
        }
    }

    fn linear(m: &Mosaic, x: usize, y: usize) -> f32 {
        (m.samples[y * m.width + x] as f32 - 100.0) / 10000.0
    }

    #[test]
    fn binning_takes_each_channel_from_its_own_sites() {
        for pattern in ["RGGB", "BGGR", "GRBG", "GBRG"] {
            let m = mosaic(6, 4, pattern);
            let f = m.develop(Resolution::Half).unwrap();
            assert_eq!((f.rgb.width(), f.rgb.height()), (3, 2));
            let p = m.pattern;
            for v in 0..2 {
                for u in 0..3 {
                    let mut expected = [0.0f32; 3];
                    for j in 0..2 {
                        for i in 0..2 {
                            let c = p[j][i] as usize;
                            let weight = if c == 1 { 0.5 } else { 1.0 };
                            expected[c] += weight * linear(&m, 2 * u + i, 2 * v + j);
                        }
                    }
                    let got = [f.rgb.r.get(u, v), f.rgb.g.get(u, v), f.rgb.b.get(u, v)];
                    for c in 0..3 {
                        assert!((got[c] - expected[c]).abs() < 1e-6, "{pattern} {u},{v}");
                    }
                }
            }
        }
    }

    #[test]
    fn half_resolution_window_centres_the_cell() {
        let full = SensorWindow {
            x0: 100.0,
            y0: 50.0,
            step: 1.0,
        };
        let half = Resolution::Half.window(full);
        // Binned pixel (3, 2) averages samples x = 6, 7 and y = 4, 5: centre (106.5, 54.5).
        assert_eq!(half.to_sensor(3.0, 2.0), (106.5, 54.5));
        assert_eq!(Resolution::Full.window(full), full);
    }

    #[test]
    fn bilinear_demosaic_reproduces_a_linear_ramp_away_from_the_border() {
        // A ramp is reproduced exactly by linear interpolation, whatever the CFA phase.
        for pattern in ["RGGB", "BGGR", "GRBG", "GBRG"] {
            let m = mosaic(8, 6, pattern);
            let f = m.develop(Resolution::Full).unwrap();
            for y in 1..5 {
                for x in 1..7 {
                    let expected = linear(&m, x, y);
                    for plane in f.rgb.channels() {
                        assert!(
                            (plane.get(x, y) - expected).abs() < 1e-6,
                            "{pattern} ({x},{y}): {} vs {expected}",
                            plane.get(x, y)
                        );
                    }
                }
            }
            // Own channel is the own sample everywhere, border included.
            for y in 0..6 {
                for x in 0..8 {
                    let own = m.pattern[y % 2][x % 2] as usize;
                    assert!((f.rgb.channels()[own].get(x, y) - linear(&m, x, y)).abs() < 1e-6);
                }
            }
        }
    }

    #[test]
    fn saturation_marks_the_pixels_that_carry_a_saturated_sample() {
        let mut m = mosaic(8, 6, "RGGB");
        m.samples[2 * 8 + 3] = 10100; // at the white level
        m.samples[5 * 8 + 7] = (10100.0 - 0.5 * SATURATION_MARGIN * 10000.0) as u16; // near it
        let half = m.develop(Resolution::Half).unwrap().saturated.unwrap();
        let flagged: Vec<usize> = (0..half.data.len()).filter(|&i| half.data[i]).collect();
        // Binned cells (1, 1) and (3, 2).
        assert_eq!(flagged, vec![4 + 1, 2 * 4 + 3]);
        // At full resolution a pixel carries its own sample only (its other channels are that
        // sample scaled by colour ratios).
        let full = m.develop(Resolution::Full).unwrap().saturated.unwrap();
        let flagged: Vec<usize> = (0..full.data.len()).filter(|&i| full.data[i]).collect();
        assert_eq!(flagged, vec![2 * 8 + 3, 5 * 8 + 7]);
    }

    #[test]
    fn binning_noise_scale_matches_a_simulation() {
        // White noise of unit variance through binning: R and B keep it, G halves it.
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        let (w, h) = (256, 256);
        let m = Mosaic {
            width: w,
            height: h,
            pattern: Mosaic::parse_pattern("GRBG").unwrap(),
            black: [[0.0; 2]; 2],
            white: 60000.0,
            samples: (0..w * h).map(|_| rng.gen_range(0..=2000u16)).collect(),
        };
        // Uniform on 0..=2000: variance (2001^2 - 1) / 12 DN^2.
        let sample_var = (2001.0f64 * 2001.0 - 1.0) / 12.0 / 60000f64.powi(2);
        let f = m.develop(Resolution::Half).unwrap();
        let scale = Resolution::Half.channel_variance_scale();
        for (c, plane) in f.rgb.channels().iter().enumerate() {
            let n = plane.len() as f64;
            let mean = plane.data.iter().map(|&v| v as f64).sum::<f64>() / n;
            let var = plane
                .data
                .iter()
                .map(|&v| (v as f64 - mean).powi(2))
                .sum::<f64>()
                / (n - 1.0);
            let ratio = var / sample_var / scale[c];
            // 16k pixels: the sample variance is within a few percent.
            assert!((ratio - 1.0).abs() < 0.05, "channel {c}: {ratio}");
        }
    }

    #[test]
    fn non_bayer_patterns_are_refused() {
        let mut m = mosaic(4, 4, "RGGB");
        m.pattern = Mosaic::parse_pattern("RGBG").unwrap();
        let err = m.develop(Resolution::Half).unwrap_err().to_string();
        assert!(err.contains("RGBG") && err.contains("Bayer"), "{err}");
    }

    #[test]
    fn dark_subtraction_is_per_pixel_and_keeps_saturation() {
        let m = mosaic(4, 4, "RGGB");
        let mut frame = m.develop(Resolution::Half).unwrap();
        let mut dark = m.develop(Resolution::Half).unwrap();
        dark.saturated.as_mut().unwrap().data[3] = true;
        let before = frame.rgb.g.data[1];
        dark.rgb.g.data[1] = 0.25 * before;
        subtract_dark(&mut frame, &DarkFrame::of(dark)).unwrap();
        assert!((frame.rgb.g.data[1] - 0.75 * before).abs() < 1e-7);
        assert_eq!(frame.rgb.r.data[0], 0.0);
        assert_eq!(
            frame.saturated.unwrap().data,
            vec![false, false, false, true]
        );
    }
}
