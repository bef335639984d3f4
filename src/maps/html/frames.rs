//! `frames_preview.jpg`: every light's frame, small, side by side in light order, so the
//! report page can show the frame of the LED clicked (the solve folder does not hold the
//! frames, and a page rebuilt later may not find them).

use std::path::Path;

use image::RgbImage;

use super::images::jpeg_bytes;
use super::relight::linear_to_srgb8;
use crate::error::Result;
use crate::fsutil::write_atomic;
use crate::plane::Frames;

/// The preview's file name in the solve folder.
pub const FRAME_STRIP_FILE: &str = "frames_preview.jpg";

/// Longest side of one frame's tile.
pub const TILE_MAX_SIDE: usize = 256;

/// Tile size of `frames` in the strip.
pub fn tile_size(width: usize, height: usize) -> (usize, usize, usize) {
    let step = width.max(height).div_ceil(TILE_MAX_SIDE).max(1);
    (width.div_ceil(step), height.div_ceil(step), step)
}

/// Writes the strip: one exposure for all frames (the 99.5th percentile of the sampled
/// pixels maps to white) so frames compare by brightness as captured.
pub fn write_frame_strip(frames: &Frames, dir: &Path) -> Result<()> {
    let (tw, th, step) = tile_size(frames.width, frames.height);
    let n = frames.lights.len();
    if n == 0 || frames.width == 0 || frames.height == 0 {
        return Ok(());
    }
    let sample = |k: usize, x: usize, y: usize| -> [f32; 3] {
        frames.lights[k].rgb_at(
            (x * step).min(frames.width - 1),
            (y * step).min(frames.height - 1),
        )
    };
    let mut values: Vec<f32> = (0..n)
        .flat_map(|k| (0..th).flat_map(move |y| (0..tw).map(move |x| (k, x, y))))
        .flat_map(|(k, x, y)| sample(k, x, y))
        .filter(|v| v.is_finite())
        .collect();
    let white = if values.is_empty() {
        1.0
    } else {
        let at = ((values.len() - 1) as f64 * 0.995) as usize;
        let (_, v, _) = values.select_nth_unstable_by(at, f32::total_cmp);
        if *v > 0.0 {
            *v
        } else {
            1.0
        }
    };
    let strip = RgbImage::from_fn((tw * n) as u32, th as u32, |x, y| {
        let (k, x) = (x as usize / tw, x as usize % tw);
        let v = sample(k, x, y as usize);
        image::Rgb(v.map(|c| linear_to_srgb8(c / white)))
    });
    write_atomic(
        &dir.join(FRAME_STRIP_FILE),
        &jpeg_bytes(&strip, 85, jpeg_encoder::SamplingFactor::R_4_2_2),
    )
}
