//! `report.html`: one self-contained page per solve, built from `report.json` and the maps on
//! disk (everything embedded as `data:` URIs, the script and style inline, no network): the
//! maps at display size with a loupe at full resolution, where the solve went wrong (per-pixel
//! status, fit, predicted error and residual, class shares, warnings with what to do), a
//! WebGL relight under a light dragged over the hemisphere (GGX or seed 004's cloth BRDF) with
//! the rig's LEDs seen from above, and the provenance in `report.json`.
//!
//! A page whose maps are missing or whose `report.json` is damaged says so and shows what is
//! left. `psscan report --render-light` renders the relight on the CPU ([`relight::render`])
//! from the same textures, for comparison with the canvas.

mod class_counts;
pub mod derived;
mod figures;
pub mod frames;
pub mod full_maps;
pub mod images;
mod loupe;
pub mod relight;
mod template;
mod textures;
mod warnings;

use class_counts::class_counts;
pub use figures::MapFigures;

pub use template::escape;
use template::fill;

use std::path::{Path, PathBuf};

use serde::Serialize;
use serde_json::{json, Value};

use crate::error::{Error, Result};
use crate::fsutil::write_atomic;
use crate::maps::encode::NormalConvention;
use crate::maps::REPORT_FILE;
use full_maps::FullMaps;
use images::Reduction;
use loupe::loupe_parts;
use relight::{RelightParams, RelightTextures};

pub use frames::{write_frame_strip, FRAME_STRIP_FILE};

/// The page's file name in the solve folder.
pub const PAGE_FILE: &str = "report.html";

/// The page must stay under this size (a 16 MP solve included).
pub const PAGE_BUDGET_BYTES: usize = 25_000_000;

/// What the page may need beyond the parts it measures (titles, attributes, the data JSON's
/// own fields); the loupe's full-resolution views take the rest of the budget. Above that
/// they first lower their JPEG quality down the ladder below, and only then step down to
/// every 2nd, 3rd ... pixel; the page says which.
const PAGE_MARGIN_BYTES: usize = 200_000;

const TEMPLATE: &str = include_str!("page.html");
const STYLE: &str = include_str!("page.css");
const SCRIPT: &str = include_str!("page.js");
const VERTEX_SHADER: &str = include_str!("relight.vert");
const FRAGMENT_SHADER: &str = include_str!("relight.frag");

/// What building the page found, for `psscan report --json`.
#[derive(Clone, Debug, Serialize)]
pub struct PageSummary {
    /// Where the page is written (`report.html` in the solve folder).
    pub path: PathBuf,
    /// The page's size in bytes (0 from `build_page`, which writes nothing).
    pub bytes: usize,
    /// Width of the full-resolution maps in pixels.
    pub width: usize,
    /// Height of the full-resolution maps in pixels.
    pub height: usize,
    /// How the maps were reduced to display size.
    pub display: Reduction,
    /// 1: the loupe shows every pixel; n: every n-th (to stay within the size budget).
    pub loupe_step: usize,
    /// JPEG quality of the loupe's views (0 when the page has no loupe).
    pub loupe_quality: u8,
    /// Maps that could not be read, in words.
    pub missing: Vec<String>,
    /// The derive folder whose maps the page shows, and which of them it shows.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub derived: Option<PathBuf>,
    /// The derived maps the page shows (`height`, `roughness`); empty without a derive.
    pub derived_maps: Vec<String>,
    /// Why `report.json` could not be used, when it could not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub report_error: Option<String>,
}

/// Reads `report.json`: the value, or why it cannot be used.
fn read_report(dir: &Path) -> std::result::Result<Value, String> {
    let path = dir.join(REPORT_FILE);
    let text = std::fs::read_to_string(&path)
        .map_err(|e| format!("{}: cannot be read ({e})", path.display()))?;
    match serde_json::from_str::<Value>(&text) {
        Ok(v) if v.is_object() => Ok(v),
        Ok(_) => Err(format!("{}: is not a JSON object", path.display())),
        Err(e) => Err(format!("{}: is damaged ({e})", path.display())),
    }
}

fn normal_convention(report: Option<&Value>) -> NormalConvention {
    report.map_or(
        NormalConvention::OpenGl,
        crate::maps::report::normal_convention_of,
    )
}

/// The relight textures of the solve in `dir` (what the page's canvas samples).
pub fn relight_textures(dir: &Path) -> Result<RelightTextures> {
    let report = read_report(dir).ok();
    let maps = FullMaps::read(dir, normal_convention(report.as_ref()));
    let reduction = Reduction::for_size(maps.width, maps.height);
    textures::relight_textures(&maps, &reduction).ok_or_else(|| {
        Error::Unsupported(format!(
            "{}: no relight without the albedo and normal maps ({})",
            dir.display(),
            maps.missing.join("; ")
        ))
    })
}

/// Renders the page's relight on the CPU into a PNG at `out`.
pub fn render_relight_png(dir: &Path, params: &RelightParams, out: &Path) -> Result<(u32, u32)> {
    let textures = relight_textures(dir)?;
    let img = relight::render(&textures, params);
    write_atomic(out, &images::png_bytes(&img))?;
    Ok(img.dimensions())
}

/// Builds `report.html` in `dir` from what the folder holds, and writes it atomically.
pub fn write_report_page(dir: &Path) -> Result<PageSummary> {
    write_report_page_with(dir, None)
}

/// [`write_report_page`], showing the height and roughness of the derive in `derived`
/// (default: the solve folder's own `derived/`, when it holds one).
pub fn write_report_page_with(dir: &Path, derived: Option<&Path>) -> Result<PageSummary> {
    write_page(dir, build_page_with(dir, derived))
}

/// [`write_report_page`] for a solve whose maps are still in memory (`psscan solve`): the
/// page's map figures were built from them ([`MapFigures::of_solve`]) instead of from the
/// files just written, the rest (report.json, frame previews) comes from the folder.
pub fn write_report_page_from(dir: &Path, figures: MapFigures) -> Result<PageSummary> {
    let report = read_report(dir);
    write_page(dir, build_page_from(dir, report, figures))
}

fn write_page(dir: &Path, (html, mut summary): (String, PageSummary)) -> Result<PageSummary> {
    summary.path = dir.join(PAGE_FILE);
    summary.bytes = html.len();
    write_atomic(&summary.path, html.as_bytes())?;
    Ok(summary)
}

/// An `<img>` with a `data:` URI.
fn img_tag(id: &str, mime: &str, bytes: &[u8], alt: &str) -> String {
    format!(
        "<img id=\"{id}\" alt=\"{}\" src=\"{}\">",
        escape(alt),
        images::data_uri(mime, bytes)
    )
}

struct Parts {
    maps: String,
    classes: String,
    loupe: String,
    relight: String,
    frames: String,
    data: Value,
}

/// Status classes: name, colour, and the words under the legend.
pub const STATUS_CLASSES: [(&str, [u8; 3], &str); 6] = [
    ("solved", [46, 160, 67], "a normal and albedo were fitted"),
    (
        "outside_mask",
        [110, 110, 110],
        "not part of the mask or region",
    ),
    ("dark", [40, 60, 200], "too few lights above the noise"),
    ("saturated", [250, 220, 40], "too few lights below clipping"),
    ("non_finite", [230, 30, 140], "NaN or infinite input"),
    (
        "degenerate",
        [255, 120, 0],
        "lights left too close to coplanar",
    ),
];

/// Fit classes (for solved pixels); unsolved pixels are drawn black.
pub const FIT_CLASSES: [(&str, [u8; 3], &str); 3] = [
    ("least_squares", [90, 140, 200], "passed the model test"),
    (
        "robust",
        [255, 150, 0],
        "outlier lights dropped or down-weighted",
    ),
    ("sheen", [190, 80, 220], "fitted with the sheen lobe"),
];

fn legend_classes(classes: &[(&str, [u8; 3], &str)], counts: &[usize]) -> String {
    let total: usize = counts.iter().sum::<usize>().max(1);
    let rows: String = classes
        .iter()
        .zip(counts)
        .map(|((name, c, words), &count)| {
            format!(
                "<tr><td><span class=\"swatch\" style=\"background:rgb({},{},{})\"></span>{}</td>\
                 <td class=\"num\">{count}</td><td class=\"num\">{:.2} %</td><td>{}</td></tr>",
                c[0],
                c[1],
                c[2],
                escape(name),
                100.0 * count as f64 / total as f64,
                escape(words)
            )
        })
        .collect();
    format!("<table class=\"legend\"><tr><th>class</th><th>pixels</th><th>share</th><th></th></tr>{rows}</table>")
}

fn figure(title: &str, img: &str, caption: &str) -> String {
    format!("<figure class=\"map\"><figcaption>{}</figcaption><div class=\"frame\">{img}</div><div class=\"caption\">{caption}</div></figure>", escape(title))
}

fn missing_figure(title: &str, why: &str) -> String {
    format!(
        "<figure class=\"map missing\"><figcaption>{}</figcaption><div class=\"absent\">{}</div></figure>",
        escape(title),
        escape(why)
    )
}

fn class_parts(maps: &FullMaps, r: &Reduction) -> String {
    let Some(conf) = maps.confidence.as_ref() else {
        return missing_figure(
            "per-pixel status, fit, predicted error and residual",
            "confidence.exr is missing or unreadable: no per-pixel classes to show",
        );
    };
    let mut out = String::new();
    let size = (conf.width, conf.height);
    let status = images::class_image(
        size,
        |i| conf.status[i],
        r,
        |c| STATUS_CLASSES.get(c as usize).map_or([0, 0, 0], |s| s.1),
    );
    out += &figure(
        "status",
        &img_tag(
            "img-status",
            "image/png",
            &images::png_bytes(&status),
            "per-pixel status",
        ),
        &legend_classes(&STATUS_CLASSES, &class_counts(&conf.status, maps, false, 6)),
    );
    // Unsolved pixels count as no class, which has no colour of its own: black.
    let fit_or_none = |i| {
        if maps.solved(i) {
            conf.fit[i]
        } else {
            full_maps::NO_CLASS
        }
    };
    let fit_img = images::class_image(size, fit_or_none, r, |c| {
        FIT_CLASSES.get(c as usize).map_or([0, 0, 0], |s| s.1)
    });
    out += &figure(
        "fit",
        &img_tag(
            "img-fit",
            "image/png",
            &images::png_bytes(&fit_img),
            "which fit each pixel got",
        ),
        &(legend_classes(&FIT_CLASSES, &class_counts(&conf.fit, maps, true, 3))
            + "<p class=\"note\">black: not solved</p>"),
    );
    let legend = images::png_bytes(&images::viridis_legend());
    for (plane, id, title, unit) in [
        (
            &conf.predicted_error_deg,
            "img-predicted",
            "predicted normal error",
            "deg",
        ),
        (&conf.residual, "img-residual", "residual", "(relative)"),
    ] {
        let max = images::scale_max(plane, maps);
        let img = images::scalar_image(plane, maps, r, max);
        let scale = format!(
            "<div class=\"scale\"><span>0</span>{}<span>{} {unit}</span></div>\
             <p class=\"note\">block means over solved pixels; the scale ends at the 99th \
             percentile; dark gray: not solved</p>",
            img_tag(
                &format!("{id}-legend"),
                "image/png",
                &legend,
                "colour scale"
            ),
            fmt_value(max)
        );
        out += &figure(
            title,
            &img_tag(id, "image/png", &images::png_bytes(&img), title),
            &scale,
        );
    }
    out
}

fn fmt_value(v: f32) -> String {
    if v >= 100.0 {
        format!("{v:.0}")
    } else if v >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3e}")
    }
}

fn map_parts(
    maps: &FullMaps,
    textures: Option<&RelightTextures>,
    derived_dir: Option<&Path>,
) -> (String, Vec<String>) {
    let mut out = String::new();
    match textures {
        Some(t) => {
            out += &figure(
                "albedo",
                &img_tag(
                    "img-albedo",
                    "image/png",
                    &images::png_bytes(&t.albedo),
                    "albedo",
                ),
                "sRGB; hover for the loupe, click to zoom",
            );
            out += &figure(
                "normal",
                &img_tag(
                    "img-normal",
                    "image/png",
                    &images::png_bytes(&t.normal),
                    "normal",
                ),
                "OpenGL convention (+Y up), n * 0.5 + 0.5; hover for the loupe, click to zoom",
            );
        }
        None => {
            for (name, map) in [
                ("albedo", maps.albedo.is_some()),
                ("normal", maps.normal.is_some()),
            ] {
                if !map {
                    out += &missing_figure(name, &format!("{name} map missing or unreadable"));
                }
            }
            if maps.albedo.is_some() != maps.normal.is_some() {
                out += "<p class=\"note\">the map that exists is not shown: the page's views \
                        are built from albedo and normal together</p>";
            }
        }
    }
    let mut shown = Vec::new();
    match derived_dir {
        Some(dir) => {
            let (html, maps) = derived::parts(dir);
            out += &html;
            shown = maps;
        }
        None => {
            out += "<figure class=\"map\"><figcaption>height and roughness</figcaption>\
                    <p class=\"note\">not derived for this solve: run psscan derive (or solve \
                    with --height / --roughness), then psscan report</p></figure>";
        }
    }
    (out, shown)
}

fn frames_part(dir: &Path, report: Option<&Value>) -> (String, Value) {
    let path = dir.join(FRAME_STRIP_FILE);
    let count = report
        .and_then(|r| r.get("lights"))
        .and_then(Value::as_array)
        .map_or(0, Vec::len);
    match std::fs::read(&path) {
        Ok(bytes) if count > 0 => match image::load_from_memory(&bytes) {
            Ok(img) => (
                img_tag(
                    "img-frames",
                    "image/jpeg",
                    &bytes,
                    "the frames, one per light",
                ),
                json!({"count": count, "tile_w": img.width() as usize / count, "tile_h": img.height()}),
            ),
            Err(e) => (
                String::new(),
                json!({"why": format!("{}: unreadable ({e})", path.display())}),
            ),
        },
        Ok(_) => (
            String::new(),
            json!({"why": "frames not available: report.json lists no lights"}),
        ),
        Err(_) => (
            String::new(),
            json!({"why": format!("frames not available: {} is not in the solve folder", FRAME_STRIP_FILE)}),
        ),
    }
}

fn build_parts(
    dir: &Path,
    report: std::result::Result<&Value, &str>,
    figures: MapFigures,
) -> (Parts, PageSummary) {
    let MapFigures {
        maps,
        reduction: r,
        derived,
        textures,
        map_html,
        derived_maps,
        classes,
    } = figures;
    let classes = warnings::render(&warnings::collect(report, &maps)) + &classes;
    let (frames, frames_data) = frames_part(dir, report.ok());
    // The loupe takes what the rest of the page leaves of the budget (the report's JSON, the
    // template, script and shaders, and a margin for the titles).
    let rest = map_html.len()
        + classes.len()
        + frames.len()
        + report.ok().map_or(0, |v| v.to_string().len())
        + TEMPLATE.len()
        + STYLE.len()
        + SCRIPT.len()
        + VERTEX_SHADER.len()
        + FRAGMENT_SHADER.len()
        + PAGE_MARGIN_BYTES;
    let (loupe_step, loupe_quality, loupe) =
        loupe_parts(&maps, PAGE_BUDGET_BYTES.saturating_sub(rest));
    let relight = match &textures {
        Some(_) => String::new(),
        None => {
            "<p class=\"absent\">no relight: it needs both the albedo and normal maps</p>".into()
        }
    };
    let data = json!({
        "report": report.ok(),
        "report_error": report.err(),
        "full": {"width": maps.width, "height": maps.height},
        "display": r,
        "loupe_step": loupe_step,
        "loupe_quality": loupe_quality,
        "relight": textures.is_some(),
        "frames": frames_data,
        "defaults": RelightParams::default(),
        "background": relight::BACKGROUND,
    });
    let summary = PageSummary {
        path: dir.join(PAGE_FILE),
        bytes: 0,
        width: maps.width,
        height: maps.height,
        display: r,
        loupe_step,
        loupe_quality,
        missing: maps.missing.clone(),
        derived,
        derived_maps,
        report_error: report.err().map(str::to_string),
    };
    let parts = Parts {
        maps: map_html,
        classes,
        loupe,
        relight,
        frames,
        data,
    };
    (parts, summary)
}

/// The page for the solve in `dir`, and what was found.
pub fn build_page(dir: &Path) -> (String, PageSummary) {
    build_page_with(dir, None)
}

/// [`build_page`] showing the derive in `derived` (default: the solve's own `derived/`).
pub fn build_page_with(dir: &Path, derived: Option<&Path>) -> (String, PageSummary) {
    let report = read_report(dir);
    let maps = FullMaps::read(dir, normal_convention(report.as_ref().ok()));
    let figures = MapFigures::build(maps, derived::locate(dir, derived));
    build_page_from(dir, report, figures)
}

/// The page from `figures` and the rest of what `dir` holds.
fn build_page_from(
    dir: &Path,
    report: std::result::Result<Value, String>,
    figures: MapFigures,
) -> (String, PageSummary) {
    let (parts, summary) = build_parts(dir, report.as_ref().map_err(String::as_str), figures);
    // The page is built in the solve's staging folder, whose name is temporary: name it after
    // the set it solved.
    let set_name = report
        .as_ref()
        .ok()
        .and_then(|r| r.get("capture")?.as_str().map(PathBuf::from))
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()));
    let title = format!(
        "psscan scan report: {}",
        set_name.unwrap_or_else(|| dir.display().to_string())
    );
    let subtitle = match &report {
        Ok(r) => format!(
            "{} x {} pixels, set {}, rig {}, psscan {}",
            summary.width,
            summary.height,
            r.get("capture")
                .and_then(Value::as_str)
                .unwrap_or("(not recorded)"),
            r.get("rig")
                .and_then(Value::as_str)
                .unwrap_or("(not recorded)"),
            r.get("psscan_version")
                .and_then(Value::as_str)
                .unwrap_or("?")
        ),
        Err(e) => format!("report.json unusable: {e}"),
    };
    // `</` inside a script element would end it early.
    let data = parts.data.to_string().replace("</", "<\\/");
    let html = fill(
        TEMPLATE,
        &[
            ("TITLE", &escape(&title)),
            ("SUBTITLE", &escape(&subtitle)),
            ("STYLE", STYLE),
            ("MAPS", &parts.maps),
            ("CLASSES", &parts.classes),
            ("LOUPE", &parts.loupe),
            ("RELIGHT", &parts.relight),
            ("FRAMES", &parts.frames),
            ("VERTEX_SHADER", VERTEX_SHADER),
            ("FRAGMENT_SHADER", FRAGMENT_SHADER),
            ("DATA", &data),
            ("SCRIPT", SCRIPT),
        ],
    );
    (html, summary)
}

#[cfg(test)]
mod tests;
