//! A solve's region as a job: crop, then 2x2 binning, then the background mask, applied to
//! the decoded frames, their noise model and their ground truth alike.

use super::{
    auto_mask, bin2, bin2_mask, crop, crop_mask_to, crop_plane, read_mask, Background, RegionInfo,
    Roi,
};
use crate::error::{Error, Result};
use crate::plane::{Frames, Mask, Plane};
use crate::solve::{LightSource, NoiseModel, LUMINANCE_WEIGHTS};

/// Which pixels a solve covers: crop, then 2x2 binning, then the background mask.
#[derive(Clone, Debug, Default)]
pub struct RegionJob {
    /// The crop, in the decoded frames' pixels; `None`: every pixel.
    pub roi: Option<Roi>,
    /// 1 (every pixel) or 2 (2x2 blocks: a half-resolution preview).
    pub bin: usize,
    /// Which pixels are sample (the rest is left unsolved).
    pub background: Background,
}

impl RegionJob {
    /// Every pixel at full resolution: no crop, no binning, no background mask.
    pub fn is_full(&self) -> bool {
        self.roi.is_none() && self.bin <= 1 && self.background == Background::None
    }
}

/// Applies `job` to decoded frames: returns the frames to solve, the sample mask, the noise
/// model for them, and a note for the report.
pub fn select_region(
    frames: Frames,
    lights: &LightSource,
    noise: NoiseModel,
    job: &RegionJob,
) -> Result<(Frames, Option<Mask>, NoiseModel, RegionInfo)> {
    let (full_w, full_h) = (frames.width, frames.height);
    let mut frames = match &job.roi {
        Some(roi) => crop(&frames, roi)?,
        None => frames,
    };
    let mut noise = noise;
    match job.bin {
        0 | 1 => {}
        2 => {
            frames = bin2(&frames)?;
            // Each value is a mean of four: a quarter of the variance (treated as independent).
            noise.channel_scale = noise.channel_scale.map(|c| c * 0.25);
            noise.shared_cfa_sample = None;
        }
        n => {
            return Err(Error::Invalid(format!(
                "binning by {n}: only 1 (none) and 2 (2x2 blocks) are supported"
            )))
        }
    }
    let mut info = RegionInfo {
        roi: job.roi,
        bin: job.bin.max(1),
        background: "none".into(),
        sample_pixels: frames.width * frames.height,
        auto: None,
    };
    let mask = match &job.background {
        Background::None => None,
        Background::Auto => {
            let (mask, auto) = auto_mask(&frames, lights)?;
            info.background = "auto".into();
            info.auto = Some(auto);
            Some(mask)
        }
        Background::File(path) => {
            let mut mask = read_mask(path)?;
            if mask.width != full_w || mask.height != full_h {
                return Err(Error::Invalid(format!(
                    "background mask {} is {}x{}, the frames are {full_w}x{full_h}",
                    path.display(),
                    mask.width,
                    mask.height
                )));
            }
            if let Some(roi) = &job.roi {
                mask = crop_mask_to(&mask, roi)?;
            }
            if job.bin == 2 {
                mask = bin2_mask(&mask);
            }
            info.background = path.display().to_string();
            Some(mask)
        }
    };
    if let Some(m) = &mask {
        info.sample_pixels = m.count();
    }
    Ok((frames, mask, noise, info))
}

/// Ground truth cropped and binned as `job` does to the frames. Binning averages each
/// channel's scaled normal `a_c n` over the block (what a Lambertian block measures); the
/// normal is that of the luminance, the albedo each channel's projection on it.
pub fn region_truth(
    (normal, albedo): ([Plane; 3], [Plane; 3]),
    job: &RegionJob,
) -> Result<([Plane; 3], [Plane; 3])> {
    let crop = |p: Plane| -> Result<Plane> {
        match &job.roi {
            Some(roi) => {
                roi.check(p.width, p.height)?;
                Ok(crop_plane(&p, roi))
            }
            None => Ok(p),
        }
    };
    let [n0, n1, n2] = normal;
    let [a0, a1, a2] = albedo;
    let normal = [crop(n0)?, crop(n1)?, crop(n2)?];
    let albedo = [crop(a0)?, crop(a1)?, crop(a2)?];
    if job.bin != 2 {
        return Ok((normal, albedo));
    }
    let (w, h) = (normal[0].width / 2, normal[0].height / 2);
    let mut n_out: [Plane; 3] = std::array::from_fn(|_| Plane::new(w, h, 0.0));
    let mut a_out: [Plane; 3] = std::array::from_fn(|_| Plane::new(w, h, 0.0));
    for y in 0..h {
        for x in 0..w {
            let mut per_channel = [nalgebra::Vector3::<f64>::zeros(); 3];
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let i = (2 * y + dy) * normal[0].width + 2 * x + dx;
                let n = nalgebra::Vector3::from_fn(|k, _| normal[k].data[i] as f64);
                for c in 0..3 {
                    per_channel[c] += n * albedo[c].data[i] as f64;
                }
            }
            let lum: nalgebra::Vector3<f64> =
                (0..3).map(|c| per_channel[c] * LUMINANCE_WEIGHTS[c]).sum();
            let unit = lum.normalize();
            for k in 0..3 {
                n_out[k].data[y * w + x] = unit[k] as f32;
                a_out[k].data[y * w + x] = (per_channel[k].dot(&unit) / 4.0) as f32;
            }
        }
    }
    Ok((n_out, a_out))
}
