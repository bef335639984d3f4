//! What part of a capture a solve covers, chosen by what the outputs need: a region-of-interest
//! crop, 2x2 binning for a half-resolution preview, and a background mask (what is sample and
//! what is table) so no work is spent outside the sample. Each keeps the frames' sensor window
//! right, so the solver still knows where every pixel sits under the lights.

mod job;

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::plane::{Frames, LightFrame, Mask, Plane, RgbPlanes, SensorWindow};
use crate::solve::{Illumination, LightModel, LightSource, LUMINANCE_WEIGHTS};

pub use job::{region_truth, select_region, RegionJob};

/// A pixel rectangle: top-left corner and size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Roi {
    /// Left edge: the rectangle's first column, pixels.
    pub x: usize,
    /// Top edge: the rectangle's first row, pixels.
    pub y: usize,
    /// Width in pixels (at least 1).
    pub width: usize,
    /// Height in pixels (at least 1).
    pub height: usize,
}

impl Roi {
    /// Parses `x,y,w,h`.
    pub fn parse(text: &str) -> Result<Roi> {
        let parts: Vec<usize> = text
            .split(',')
            .map(|p| p.trim().parse::<usize>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| Error::Invalid(format!("region {text:?}: {e} (expected x,y,w,h)")))?;
        match parts[..] {
            [x, y, width, height] if width > 0 && height > 0 => Ok(Roi {
                x,
                y,
                width,
                height,
            }),
            _ => Err(Error::Invalid(format!(
                "region {text:?}: expected x,y,w,h with w and h > 0"
            ))),
        }
    }

    fn check(&self, width: usize, height: usize) -> Result<()> {
        // Checked sums: a region given as huge numbers must be refused, not overflow.
        let fits = |start: usize, len: usize, limit: usize| {
            start.checked_add(len).is_some_and(|end| end <= limit)
        };
        if !fits(self.x, self.width, width) || !fits(self.y, self.height, height) {
            return Err(Error::Invalid(format!(
                "region {},{} {}x{} does not fit in the {width}x{height} frames",
                self.x, self.y, self.width, self.height
            )));
        }
        Ok(())
    }
}

/// The part of `p` inside `roi` (which the caller has checked against `p`'s size).
fn crop_plane(p: &Plane, roi: &Roi) -> Plane {
    Plane {
        width: roi.width,
        height: roi.height,
        data: crop_rows(&p.data, p.width, roi),
    }
}

fn crop_mask(m: &Mask, roi: &Roi) -> Mask {
    Mask {
        width: roi.width,
        height: roi.height,
        data: crop_rows(&m.data, m.width, roi),
    }
}

/// The samples of a row-major image `width` wide that lie inside `roi`.
fn crop_rows<T: Copy>(data: &[T], width: usize, roi: &Roi) -> Vec<T> {
    let mut out = Vec::with_capacity(roi.width * roi.height);
    for y in roi.y..roi.y + roi.height {
        out.extend_from_slice(&data[y * width + roi.x..y * width + roi.x + roi.width]);
    }
    out
}

/// The frames inside `roi`, with the window moved so each pixel keeps its sensor position.
pub fn crop(frames: &Frames, roi: &Roi) -> Result<Frames> {
    roi.check(frames.width, frames.height)?;
    let w = frames.window;
    Ok(Frames {
        width: roi.width,
        height: roi.height,
        window: SensorWindow {
            x0: w.x0 + w.step * roi.x as f64,
            y0: w.y0 + w.step * roi.y as f64,
            step: w.step,
        },
        lights: frames
            .lights
            .iter()
            .map(|f| {
                let rgb = match (&f.cfa, &f.dn) {
                    (None, None) => RgbPlanes {
                        r: crop_plane(&f.rgb.r, roi),
                        g: crop_plane(&f.rgb.g, roi),
                        b: crop_plane(&f.rgb.b, roi),
                    },
                    // A frame stored as CFA samples (or DN) is cropped to three planes of the
                    // region's pixels (no CFA phase to carry over).
                    _ => f.window_planes(roi.x, roi.y, roi.width, roi.height),
                };
                LightFrame::from_rgb(rgb, f.saturated.as_ref().map(|m| crop_mask(m, roi)))
            })
            .collect(),
    })
}

/// Crops a mask given at the frames' size the same way.
pub fn crop_mask_to(mask: &Mask, roi: &Roi) -> Result<Mask> {
    roi.check(mask.width, mask.height)?;
    Ok(crop_mask(mask, roi))
}

/// Means of 2x2 blocks (a trailing odd row or column is dropped).
pub fn bin2_plane(p: &Plane) -> Plane {
    let (w, h) = (p.width / 2, p.height / 2);
    let mut data = vec![0.0; w * h];
    for y in 0..h {
        let (a, b) = (p.row(2 * y), p.row(2 * y + 1));
        for x in 0..w {
            data[y * w + x] = 0.25 * (a[2 * x] + a[2 * x + 1] + b[2 * x] + b[2 * x + 1]);
        }
    }
    Plane {
        width: w,
        height: h,
        data,
    }
}

/// A 2x2 block is set when any of its pixels is (saturated anywhere, sample anywhere).
pub fn bin2_mask(m: &Mask) -> Mask {
    let (w, h) = (m.width / 2, m.height / 2);
    let at = |x: usize, y: usize| m.data[y * m.width + x];
    let mut data = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            data[y * w + x] = at(2 * x, 2 * y)
                || at(2 * x + 1, 2 * y)
                || at(2 * x, 2 * y + 1)
                || at(2 * x + 1, 2 * y + 1);
        }
    }
    Mask {
        width: w,
        height: h,
        data,
    }
}

/// Half-resolution frames: each pixel the mean of a 2x2 block (4x fewer pixels to solve; each
/// value has a quarter of the noise variance). The window's step doubles and its origin moves
/// to the block centre.
pub fn bin2(frames: &Frames) -> Result<Frames> {
    if frames.width < 2 || frames.height < 2 {
        return Err(Error::Invalid(format!(
            "cannot bin {}x{} frames 2x2",
            frames.width, frames.height
        )));
    }
    let w = frames.window;
    Ok(Frames {
        width: frames.width / 2,
        height: frames.height / 2,
        window: SensorWindow {
            x0: w.x0 + 0.5 * w.step,
            y0: w.y0 + 0.5 * w.step,
            step: 2.0 * w.step,
        },
        lights: frames
            .lights
            .iter()
            .map(|f| {
                let rgb = f.to_planes();
                LightFrame::from_rgb(
                    RgbPlanes {
                        r: bin2_plane(&rgb.r),
                        g: bin2_plane(&rgb.g),
                        b: bin2_plane(&rgb.b),
                    },
                    f.saturated.as_ref().map(bin2_mask),
                )
            })
            .collect(),
    })
}

/// Where the background mask comes from.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum Background {
    /// Solve every pixel.
    #[default]
    None,
    /// Found from the frames ([`auto_mask`]).
    Auto,
    /// An image the size of the frames: non-zero is sample, zero is background.
    File(std::path::PathBuf),
}

impl Background {
    /// The `--background` argument: `none`, `auto`, or else the path of a mask image.
    pub fn parse(text: &str) -> Background {
        match text {
            "none" => Background::None,
            "auto" => Background::Auto,
            path => Background::File(path.into()),
        }
    }
}

/// Reads a mask image (PNG or TIFF, any bit depth): non-zero pixels are sample.
pub fn read_mask(path: &Path) -> Result<Mask> {
    let image = image::open(path)
        .map_err(|e| Error::Invalid(format!("background mask {}: {e}", path.display())))?
        .to_luma16();
    Ok(Mask {
        width: image.width() as usize,
        height: image.height() as usize,
        data: image.pixels().map(|p| p.0[0] > 0).collect(),
    })
}

/// What [`auto_mask`] found.
#[derive(Clone, Debug, Serialize)]
pub struct AutoMask {
    /// Albedo threshold between table and sample (flat-surface estimate); `None` when the
    /// frames show no separate background (everything is sample).
    pub threshold: Option<f64>,
    /// Fraction of pixels that are sample.
    pub sample_fraction: f64,
}

/// Sample pixels against a darker or brighter table, from one photograph: under the most
/// overhead light, each pixel's reading over the light's white-surface signal there is the
/// albedo a flat surface would need (cheap: three planes read once). Otsu's threshold on the
/// log of that splits two populations; it is used only when they are well apart (mean albedos
/// more than 3x apart and each class at least 2 % of the pixels), otherwise every pixel is
/// sample. The table is the class not holding the image centre, where it is connected to the
/// image border (so dark gaps inside the sample stay sample).
pub fn auto_mask(frames: &Frames, lights: &LightSource) -> Result<(Mask, AutoMask)> {
    let ill = Illumination::new(
        lights,
        LightModel::Near,
        frames.width,
        frames.height,
        frames.window,
    )?;
    let (w, h) = (frames.width, frames.height);
    let centre = ill
        .point(w / 2, h / 2)
        .ok_or_else(|| Error::Invalid("image centre misses the sample plane".into()))?;
    let top = (0..ill.len())
        .max_by(|&a, &b| {
            let za = ill.sample(a, &centre).direction.z;
            za.total_cmp(&ill.sample(b, &centre).direction.z)
        })
        .ok_or_else(|| Error::Invalid("no lights".into()))?;
    let frame = &frames.lights[top];
    let scale = ill.rgb_scale(top);
    let mut log_albedo = vec![f64::NAN; w * h];
    for y in 0..h {
        for x in 0..w {
            let Some(p) = ill.point(x, y) else { continue };
            let s = ill.sample(top, &p);
            let white: f64 = (0..3)
                .map(|c| LUMINANCE_WEIGHTS[c] * scale[c] * s.falloff * s.direction.z)
                .sum();
            let i = y * w + x;
            let [r, g, b] = frame.rgb_at(x, y);
            let lum = LUMINANCE_WEIGHTS[0] * r as f64
                + LUMINANCE_WEIGHTS[1] * g as f64
                + LUMINANCE_WEIGHTS[2] * b as f64;
            if white > 0.0 {
                log_albedo[i] = (lum / white).max(1e-4).ln();
            }
        }
    }
    let everything = |fraction| {
        (
            Mask::new(w, h, true),
            AutoMask {
                threshold: None,
                sample_fraction: fraction,
            },
        )
    };
    let Some((threshold, low_mean, high_mean, low_fraction)) = otsu(&log_albedo) else {
        return Ok(everything(1.0));
    };
    if high_mean - low_mean < 3f64.ln() || !(0.02..=0.98).contains(&low_fraction) {
        return Ok(everything(1.0));
    }
    let centre_high = log_albedo[(h / 2) * w + w / 2] > threshold;
    let table_like: Vec<bool> = log_albedo
        .iter()
        .map(|&v| !v.is_finite() || (v > threshold) != centre_high)
        .collect();
    let mask = Mask {
        width: w,
        height: h,
        data: not_reached_from_border(&table_like, w, h),
    };
    let fraction = mask.count() as f64 / (w * h) as f64;
    Ok((
        mask,
        AutoMask {
            threshold: Some(threshold.exp()),
            sample_fraction: fraction,
        },
    ))
}

/// Pixels not connected to the image border through `open` pixels (4-neighbours): the table
/// surrounds the sample, so table-like pixels inside it (gaps between threads, dark threads)
/// stay sample.
fn not_reached_from_border(open: &[bool], w: usize, h: usize) -> Vec<bool> {
    let mut reached = vec![false; w * h];
    let mut stack: Vec<usize> = (0..w)
        .flat_map(|x| [x, (h - 1) * w + x])
        .chain((0..h).flat_map(|y| [y * w, y * w + w - 1]))
        .filter(|&i| open[i])
        .collect();
    for &i in &stack {
        reached[i] = true;
    }
    while let Some(i) = stack.pop() {
        let (x, y) = (i % w, i / w);
        let neighbours = [
            (x > 0).then(|| i - 1),
            (x + 1 < w).then(|| i + 1),
            (y > 0).then(|| i - w),
            (y + 1 < h).then(|| i + w),
        ];
        for j in neighbours.into_iter().flatten() {
            if open[j] && !reached[j] {
                reached[j] = true;
                stack.push(j);
            }
        }
    }
    reached.into_iter().map(|r| !r).collect()
}

/// Otsu's threshold of the finite values (256 bins): (threshold, mean below, mean above,
/// fraction below).
fn otsu(values: &[f64]) -> Option<(f64, f64, f64, f64)> {
    let finite = values.iter().copied().filter(|v| v.is_finite());
    let (lo, hi) = finite.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    if hi <= lo {
        return None;
    }
    const BINS: usize = 256;
    let bin = |v: f64| (((v - lo) / (hi - lo) * BINS as f64) as usize).min(BINS - 1);
    let mut hist = [0f64; BINS];
    let mut total = 0.0;
    for v in values.iter().copied().filter(|v| v.is_finite()) {
        hist[bin(v)] += 1.0;
        total += 1.0;
    }
    let centre = |i: usize| lo + (i as f64 + 0.5) / BINS as f64 * (hi - lo);
    let sum_all: f64 = (0..BINS).map(|i| hist[i] * centre(i)).sum();
    let (mut w0, mut sum0, mut best) = (0.0, 0.0, None::<(f64, usize)>);
    for i in 0..BINS - 1 {
        w0 += hist[i];
        sum0 += hist[i] * centre(i);
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let (m0, m1) = (sum0 / w0, (sum_all - sum0) / w1);
        let between = w0 * w1 * (m0 - m1) * (m0 - m1);
        if best.map_or(true, |(b, _)| between > b) {
            best = Some((between, i));
        }
    }
    let (_, i) = best?;
    let (w0, s0): (f64, f64) = (0..=i).fold((0.0, 0.0), |(a, b), j| {
        (a + hist[j], b + hist[j] * centre(j))
    });
    let threshold = lo + (i as f64 + 1.0) / BINS as f64 * (hi - lo);
    Some((
        threshold,
        s0 / w0,
        (sum_all - s0) / (total - w0),
        w0 / total,
    ))
}

/// What region selection did, for the report.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RegionInfo {
    /// The crop applied, in the pixels of the frames as loaded; `None`: no crop.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roi: Option<Roi>,
    /// Binning factor applied after the crop: 1 (none) or 2 (2x2 blocks).
    pub bin: usize,
    /// `none`, `auto` or the mask file.
    pub background: String,
    /// Pixels inside the background mask (all when there is none).
    pub sample_pixels: usize,
    /// What the automatic background mask found; `None` unless `background` is `auto`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub auto: Option<AutoMask>,
}

#[cfg(test)]
mod tests;
