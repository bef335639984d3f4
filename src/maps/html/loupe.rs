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
        for quality in LOUPE_QUALITIES {
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
