//! The derived maps on the page: height and roughness, when the solve has a derive beside it
//! (`derived/` inside the solve folder, written by `psscan solve` with derive options, or a
//! folder `psscan report --derived DIR` names). Each is shown at display size with a colour
//! scale; a derive that is unreadable or lacks a map says so in the figure.

use std::path::{Path, PathBuf};

use image::RgbImage;
use image_dds::{ddsfile::Dds, Surface};
use serde_json::Value;

use super::images::{self, viridis, Reduction};
use super::{figure, fmt_value, img_tag, missing_figure};
use crate::error::{Error, Result};
use crate::io::read_exr;
use crate::maps::derive::DERIVE_REPORT;
use crate::plane::Plane;

/// The folder inside a solve folder that `solve`'s derive step writes.
pub const DERIVED_DIR: &str = "derived";

/// The derive folder the page shows: the one named, or the solve folder's own `derived/` when
/// it holds a finished derive.
pub fn locate(solve_dir: &Path, named: Option<&Path>) -> Option<PathBuf> {
    match named {
        Some(dir) => Some(dir.to_path_buf()),
        None => {
            let own = solve_dir.join(DERIVED_DIR);
            own.join(DERIVE_REPORT).is_file().then_some(own)
        }
    }
}

/// The figures for the derive in `dir`, and the maps shown (for the page's summary).
pub fn parts(dir: &Path) -> (String, Vec<String>) {
    let report = match read_derive_report(dir) {
        Ok(r) => r,
        Err(why) => return (missing_figure("height and roughness", &why), Vec::new()),
    };
    let mut html = String::new();
    let mut shown = Vec::new();
    if report.get("height_map").is_some() {
        match height_figure(dir, &report) {
            Ok(f) => {
                html += &f;
                shown.push("height".to_string());
            }
            Err(e) => html += &missing_figure("height", &e.to_string()),
        }
    }
    if let Some(roughness) = report.get("roughness") {
        match roughness_figure(dir, roughness) {
            Ok(f) => {
                html += &f;
                shown.push("roughness".to_string());
            }
            Err(e) => html += &missing_figure("roughness", &e.to_string()),
        }
    }
    if shown.is_empty() && html.is_empty() {
        html += &missing_figure(
            "height and roughness",
            &format!(
                "the derive in {} made neither (run derive with --height or --roughness)",
                dir.display()
            ),
        );
    }
    (html, shown)
}

fn read_derive_report(dir: &Path) -> std::result::Result<Value, String> {
    let path = dir.join(DERIVE_REPORT);
    let text = std::fs::read_to_string(&path)
        .map_err(|e| format!("{}: cannot be read ({e})", path.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("{}: is damaged ({e})", path.display()))
}

fn height_figure(dir: &Path, report: &Value) -> Result<String> {
    let path = dir.join("height.exr");
    let height = read_exr(&path, &["height"])?
        .pop()
        .ok_or_else(|| Error::image(&path, "has no height channel"))?;
    let units = report["height_map"]["units"].as_str().unwrap_or("?");
    let (lo, hi) = finite_range(&height);
    let r = Reduction::for_size(height.width, height.height);
    let img = scalar_view(&height, r.width, r.height, lo, hi);
    let flattening = match report["flatten_radius_px"].as_f64() {
        Some(r) => format!("flattened at a radius of {r:.0} px"),
        None => "not flattened: folds and tilt dominate the range (derive --flatten keeps only \
                 the relief)"
            .to_string(),
    };
    let caption = scale_caption(
        "img-height",
        lo,
        hi,
        units,
        &format!("integrated from the normals (offset arbitrary), {flattening}; block means"),
    );
    Ok(figure(
        "height",
        &img_tag(
            "img-height",
            "image/png",
            &images::png_bytes(&img),
            "height",
        ),
        &caption,
    ))
}

/// The roughness an engine samples when the texture is seen at the page's display size: the
/// mip level whose size is nearest above it, decoded from `roughness.dds`.
fn roughness_figure(dir: &Path, roughness: &Value) -> Result<String> {
    let path = dir.join("roughness.dds");
    let file = std::fs::File::open(&path).map_err(|e| Error::io(&path, e))?;
    let dds = Dds::read(std::io::BufReader::new(file))
        .map_err(|e| Error::image(&path, format!("not a DDS file: {e}")))?;
    let surface =
        Surface::from_dds(&dds).map_err(|e| Error::image(&path, format!("unusable: {e}")))?;
    let full = Reduction::for_size(surface.width as usize, surface.height as usize);
    // Level 0 is the base roughness everywhere (a texel's footprint holds one normal), so the
    // view starts at level 1, shown at the other maps' display size.
    let level = (full.factor.max(2).ilog2()).min(surface.mipmaps.saturating_sub(1));
    let decoded = surface
        .decode_layers_mipmaps_rgba8(0..1, level..level + 1)
        .map_err(|e| Error::image(&path, format!("level {level} does not decode: {e}")))?;
    let (w, h) = (decoded.width as usize, decoded.height as usize);
    let plane = Plane {
        width: w,
        height: h,
        data: decoded
            .data
            .chunks_exact(4)
            .map(|p| p[0] as f32 / 255.0)
            .collect(),
    };
    let (lo, hi) = finite_range(&plane);
    let img = scalar_view(&plane, full.width, full.height, lo, hi);
    let filter = roughness["filter"].as_str().unwrap_or("?");
    let caption = scale_caption(
        "img-roughness",
        lo,
        hi,
        "",
        &format!(
            "mip level {level} ({w} x {h}; level 0 is the base roughness everywhere), \
             {filter} filter from base roughness {}; glTF perceptual roughness",
            roughness["base"]
                .as_f64()
                .map_or("?".into(), |b| format!("{b}"))
        ),
    );
    Ok(figure(
        "roughness",
        &img_tag(
            "img-roughness",
            "image/png",
            &images::png_bytes(&img),
            "roughness",
        ),
        &caption,
    ))
}

/// The smallest and largest finite values (0..1 when there are none or all are equal).
fn finite_range(plane: &Plane) -> (f32, f32) {
    let (lo, hi) = plane
        .data
        .iter()
        .filter(|v| v.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    if lo < hi {
        (lo, hi)
    } else if lo.is_finite() {
        (lo, lo + 1.0)
    } else {
        (0.0, 1.0)
    }
}

/// The plane at `width` x `height` (smaller: block means; larger: each value repeated),
/// over finite values, viridis over `[lo, hi]`.
fn scalar_view(plane: &Plane, width: usize, height: usize, lo: f32, hi: f32) -> RgbImage {
    let (w, h) = (plane.width, plane.height);
    let span = |i: usize, n: usize, full: usize| {
        let start = i * full / n;
        (start, ((i + 1) * full / n).max(start + 1).min(full))
    };
    RgbImage::from_fn(width as u32, height as u32, |x, y| {
        let (x0, x1) = span(x as usize, width, w);
        let (y0, y1) = span(y as usize, height, h);
        let (mut sum, mut count) = (0f64, 0usize);
        for yy in y0..y1 {
            for &v in &plane.data[yy * w + x0..yy * w + x1] {
                if v.is_finite() {
                    sum += v as f64;
                    count += 1;
                }
            }
        }
        image::Rgb(if count == 0 {
            images::NO_VALUE
        } else {
            viridis(((sum / count as f64) as f32 - lo) / (hi - lo))
        })
    })
}

fn scale_caption(id: &str, lo: f32, hi: f32, units: &str, note: &str) -> String {
    let legend = images::png_bytes(&images::viridis_legend());
    format!(
        "<div class=\"scale\"><span>{}</span>{}<span>{} {units}</span></div>\
         <p class=\"note\">{note}</p>",
        fmt_signed(lo),
        img_tag(
            &format!("{id}-legend"),
            "image/png",
            &legend,
            "colour scale"
        ),
        fmt_signed(hi),
    )
}

/// Heights and roughness read best as plain decimals; tiny or huge ones as the page's others.
fn fmt_signed(v: f32) -> String {
    if (0.01..1000.0).contains(&v.abs()) {
        format!("{v:.3}")
    } else if v < 0.0 {
        format!("-{}", fmt_value(-v))
    } else {
        fmt_value(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_view_spans_the_range_and_marks_missing_values() {
        let mut p = Plane::new(4, 2, 0.0);
        p.data = vec![0.0, 1.0, 2.0, 3.0, f32::NAN, 1.0, 2.0, 3.0];
        let (lo, hi) = finite_range(&p);
        assert_eq!((lo, hi), (0.0, 3.0));
        let img = scalar_view(&p, 4, 2, lo, hi);
        assert_eq!(img.get_pixel(0, 0).0, viridis(0.0));
        assert_eq!(img.get_pixel(3, 1).0, viridis(1.0));
        // A lone NaN has no value.
        assert_eq!(img.get_pixel(0, 1).0, images::NO_VALUE);
        // Halved: block means; doubled: each value repeated.
        let half = scalar_view(&p, 2, 1, lo, hi);
        assert_eq!(half.get_pixel(0, 0).0, viridis((2.0f64 / 3.0) as f32 / 3.0));
        let double = scalar_view(&p, 8, 4, lo, hi);
        assert_eq!(double.get_pixel(7, 0).0, viridis(1.0));
        assert_eq!(double.get_pixel(0, 3).0, images::NO_VALUE);
    }

    #[test]
    fn a_flat_plane_gets_a_unit_range_not_a_division_by_zero() {
        let p = Plane::new(3, 3, 0.5);
        assert_eq!(finite_range(&p), (0.5, 1.5));
    }
}
