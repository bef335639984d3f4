//! The loupe's sources: the albedo and normal maps at full resolution (or every n-th pixel)
//! as JPEGs sized to what the page's budget leaves.

use image::RgbImage;
use jpeg_encoder::SamplingFactor;
use rayon::prelude::*;

use super::images::{self, FullMaps};

/// JPEG qualities the loupe tries at each sampling, best first. The floor keeps block
/// artefacts below a thread's edge contrast; under it, resolution is given up instead.
const LOUPE_QUALITIES: [u8; 3] = [88, 80, 72];

/// The loupe's views as JPEGs: the finest sampling, then the best quality, that fits the
/// budget.
fn loupe_views(maps: &FullMaps, budget: usize) -> Loupe {
    let mut step = 1;
    loop {
        let (albedo, normal) = images::full_views(maps, step);
        let sources: Vec<(&str, RgbImage)> = [("albedo", albedo), ("normal", normal)]
            .into_iter()
            .filter_map(|(name, img)| img.map(|i| (name, i)))
            .collect();
        let mut base64_bytes = 0;
        for (k, quality) in LOUPE_QUALITIES.into_iter().enumerate() {
            // A full encode at 16 MP takes most of a second: a quality whose sample says it
            // will not fit is skipped (the last one is always tried).
            let last = k + 1 == LOUPE_QUALITIES.len();
            if !last && step < 16 {
                if let Some(predicted) = predicted_bytes(&sources, quality) {
                    if predicted as f64 > budget as f64 * PREDICTION_MARGIN {
                        base64_bytes = predicted;
                        continue;
                    }
                }
            }
            let views: Vec<(String, Vec<u8>)> = sources
                .par_iter()
                .map(|(name, img)| {
                    (
                        name.to_string(),
                        images::jpeg_bytes(img, quality, chroma(name)),
                    )
                })
                .collect();
            base64_bytes = views.iter().map(|(_, b)| b.len() * 4 / 3).sum();
            if base64_bytes <= budget || step >= 16 {
                return Loupe {
                    step,
                    quality,
                    views,
                };
            }
        }
        // Bytes scale with pixels: jump straight to a step that should fit.
        let ratio = (base64_bytes as f64 / budget.max(1) as f64).sqrt();
        step = (step as f64 * ratio).ceil().max(step as f64 + 1.0) as usize;
    }
}

/// A quality is skipped only when its predicted size is over the budget by more than this
/// factor (the prediction from a sample of rows is a few percent off either way).
const PREDICTION_MARGIN: f64 = 1.05;

/// Rows per band of the size sample: a whole number of JPEG blocks (16 for 4:2:0).
const SAMPLE_BAND_ROWS: u32 = 16;

/// One band in this many goes into the size sample.
const SAMPLE_EVERY: u32 = 8;

/// The base64 bytes `sources` would take at `quality`, predicted from a JPEG of every
/// [`SAMPLE_EVERY`]-th band of rows scaled by the rows it stands for; `None` for images too
/// small to sample (encoding them whole is cheap).
fn predicted_bytes(sources: &[(&str, RgbImage)], quality: u8) -> Option<usize> {
    let total: f64 = sources
        .par_iter()
        .map(|(name, img)| {
            let (w, h) = img.dimensions();
            let bands = h / SAMPLE_BAND_ROWS;
            if bands < 4 * SAMPLE_EVERY {
                return None;
            }
            let sampled: Vec<u32> = (0..bands).step_by(SAMPLE_EVERY as usize).collect();
            let rows = sampled.len() as u32 * SAMPLE_BAND_ROWS;
            let mut sample = RgbImage::new(w, rows);
            for (j, &band) in sampled.iter().enumerate() {
                for r in 0..SAMPLE_BAND_ROWS {
                    let (from, to) = (band * SAMPLE_BAND_ROWS + r, j as u32 * SAMPLE_BAND_ROWS + r);
                    let row = (from * w * 3) as usize..((from + 1) * w * 3) as usize;
                    let at = (to * w * 3) as usize;
                    sample.as_mut()[at..at + w as usize * 3].copy_from_slice(&img.as_raw()[row]);
                }
            }
            let bytes = images::jpeg_bytes(&sample, quality, chroma(name)).len();
            Some(bytes as f64 * h as f64 / rows as f64 * 4.0 / 3.0)
        })
        .collect::<Option<Vec<f64>>>()?
        .iter()
        .sum();
    Some(total as usize)
}

/// Chroma sampling of a loupe view: the albedo's colour varies more slowly than its
/// brightness, as photographs' does (4:2:0); the normal map's colour is its X and Y, so it
/// keeps full vertical chroma resolution (4:2:2).
fn chroma(view: &str) -> SamplingFactor {
    if view == "albedo" {
        SamplingFactor::R_4_2_0
    } else {
        SamplingFactor::R_4_2_2
    }
}

/// The loupe's sources: every `step`-th pixel, JPEG at `quality`.
struct Loupe {
    step: usize,
    quality: u8,
    views: Vec<(String, Vec<u8>)>,
}

/// The loupe's `<img>` tags, with its sampling step and JPEG quality (1 and 0 without maps).
pub(super) fn loupe_parts(maps: &FullMaps, budget: usize) -> (usize, u8, String) {
    if maps.albedo.is_none() || maps.normal.is_none() {
        return (1, 0, String::new());
    }
    let loupe = loupe_views(maps, budget);
    let tags = loupe
        .views
        .iter()
        .map(|(name, bytes)| {
            format!(
                "<img class=\"loupe-src\" id=\"loupe-{name}\" alt=\"{name} at full resolution\" src=\"{}\">",
                images::data_uri("image/jpeg", bytes)
            )
        })
        .collect();
    (loupe.step, loupe.quality, tags)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A weave-like test image: threads in two directions, colour steps between them, and
    /// pixel noise (what makes a JPEG large), over `h` rows.
    fn weave(w: u32, h: u32) -> RgbImage {
        let mut state = 12345u32;
        RgbImage::from_fn(w, h, |x, y| {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = (state >> 27) as f32;
            let warp = ((x as f32 * 0.9).sin() * 0.5 + 0.5) * 120.0;
            let weft = ((y as f32 * 0.7).cos() * 0.5 + 0.5) * 90.0;
            let over = (x / 6 + y / 6) % 2 == 0;
            let base = if over { warp } else { weft };
            image::Rgb([
                (base + noise * 2.0) as u8,
                (base * 0.7 + 40.0 + noise) as u8,
                (base * 0.4 + 90.0 + noise * 1.5) as u8,
            ])
        })
    }

    #[test]
    fn the_sampled_size_predicts_the_whole_jpeg() {
        let sources = vec![("albedo", weave(900, 1100)), ("normal", weave(900, 1100))];
        for quality in LOUPE_QUALITIES {
            let predicted = predicted_bytes(&sources, quality).expect("large enough to sample");
            let actual: usize = sources
                .iter()
                .map(|(name, img)| images::jpeg_bytes(img, quality, chroma(name)).len() * 4 / 3)
                .sum();
            let off = predicted as f64 / actual as f64 - 1.0;
            // The sample is an eighth of the rows of an image of uniform texture: its bytes
            // per row are the whole's up to headers and tables (a few hundred bytes) and the
            // texture's row-to-row variation, well under the margin a skip needs.
            assert!(
                off.abs() < PREDICTION_MARGIN - 1.0,
                "q{quality}: predicted {predicted}, actual {actual}"
            );
        }
        // Too few rows to sample: encoded whole.
        assert!(predicted_bytes(&[("albedo", weave(64, 64))], 88).is_none());
    }
}
