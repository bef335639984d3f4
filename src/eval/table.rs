//! The evaluation as a Markdown table (one section per set) and an SVG plot of mean error
//! against light count per estimator (plotters).

use std::fmt::Write;
use std::path::Path;

use plotters::prelude::*;

use super::run::{EvalReport, Row};
use crate::error::{Error, Result};
use crate::fsutil::write_atomic;

/// Set names in the order first evaluated.
fn sets(report: &EvalReport) -> Vec<String> {
    let mut names: Vec<String> = Vec::new();
    for r in &report.rows {
        if !names.contains(&r.set) {
            names.push(r.set.clone());
        }
    }
    names
}

/// The published figures for `set` at `lights`, as "method mean" pairs.
fn anchors_text(report: &EvalReport, set: &str, lights: usize) -> String {
    report
        .anchors
        .iter()
        .filter(|a| a.set == set && a.lights == lights)
        .map(|a| format!("{} {:.3}", a.method, a.mean_deg))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The report as Markdown: per set, one row per light count and estimator.
pub fn markdown(report: &EvalReport) -> String {
    let mut md = String::from(
        "# psscan on real captures\n\nMean, median and 95th percentile angular error (degrees) \
         over each set's mask against its ground truth, `psscan eval`. K-light subsets: greedy \
         farthest-point sampling of the light directions from the most frontal light. \
         `trimmed`: per pixel, least squares on the readings left after dropping the darkest \
         and brightest 20 % (psscan computes it). Published: the data folders' READMEs.\n",
    );
    for set in sets(report) {
        let _ = write!(
            md,
            "\n## {set}\n\n| lights | estimator | mean | median | p95 | time (s) | escalated | \
             published |\n| ---: | --- | ---: | ---: | ---: | ---: | ---: | --- |\n"
        );
        let mut last = None;
        for r in report.rows.iter().filter(|r| r.set == set) {
            let published = if last != Some(r.lights) {
                anchors_text(report, &set, r.lights)
            } else {
                String::new()
            };
            last = Some(r.lights);
            let escalated = r
                .escalated
                .map_or(String::from("-"), |e| format!("{e} / {}", r.solved));
            let _ = writeln!(
                md,
                "| {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {} | {} |",
                r.lights,
                r.estimator,
                r.error_deg.mean,
                r.error_deg.median,
                r.error_deg.p95,
                r.seconds,
                escalated,
                published
            );
        }
    }
    md
}

/// Writes `eval.md`, `eval.json` and `eval.svg` into `dir` (created if needed).
pub fn write(report: &EvalReport, dir: &Path) -> Result<()> {
    crate::fsutil::create_dir_all(dir)?;
    write_atomic(&dir.join("eval.md"), markdown(report).as_bytes())?;
    let json = serde_json::to_string_pretty(report).expect("serialisable");
    write_atomic(&dir.join("eval.json"), json.as_bytes())?;
    plot(report, &dir.join("eval.svg"))
}

/// Mean error against light count, one panel per set, one line per estimator.
pub fn plot(report: &EvalReport, path: &Path) -> Result<()> {
    let names = sets(report);
    let fail = |e: &dyn std::fmt::Display| Error::Invalid(format!("plot {}: {e}", path.display()));
    let rows_of_panels = names.len().div_ceil(2).max(1);
    let root = SVGBackend::new(path, (1200, 400 * rows_of_panels as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let panels = root.split_evenly((rows_of_panels, 2));
    for (set, area) in names.iter().zip(panels.iter()) {
        let rows: Vec<&Row> = report.rows.iter().filter(|r| &r.set == set).collect();
        draw_panel(area, set, &rows).map_err(|e| fail(&e))?;
    }
    root.present().map_err(|e| fail(&e))?;
    Ok(())
}

type Panel<'a> = DrawingArea<SVGBackend<'a>, plotters::coord::Shift>;

fn draw_panel(
    area: &Panel,
    set: &str,
    rows: &[&Row],
) -> std::result::Result<(), Box<dyn std::error::Error>> {
    let k_min = rows.iter().map(|r| r.lights).min().unwrap_or(3) as f64;
    let k_max = rows.iter().map(|r| r.lights).max().unwrap_or(3) as f64;
    let e_max = rows.iter().map(|r| r.error_deg.mean).fold(0.0, f64::max) * 1.15;
    let mut chart = ChartBuilder::on(area)
        .caption(set, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(52)
        .build_cartesian_2d((k_min * 0.9..k_max * 1.1).log_scale(), 0.0..e_max.max(1e-3))?;
    chart
        .configure_mesh()
        .x_desc("lights (log)")
        .y_desc("mean angular error (deg)")
        .draw()?;
    let mut estimators: Vec<&str> = Vec::new();
    for r in rows {
        if !estimators.contains(&r.estimator.as_str()) {
            estimators.push(&r.estimator);
        }
    }
    for (i, name) in estimators.iter().enumerate() {
        let colour = HSLColor(i as f64 / estimators.len() as f64, 0.8, 0.4);
        let points: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.estimator == *name)
            .map(|r| (r.lights as f64, r.error_deg.mean))
            .collect();
        chart
            .draw_series(LineSeries::new(points.clone(), colour.stroke_width(2)))?
            .label(name.to_string())
            .legend(move |(x, y)| {
                PathElement::new([(x - 8, y), (x + 8, y)], colour.stroke_width(2))
            });
        chart.draw_series(points.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .label_font(("sans-serif", 11))
        .draw()?;
    Ok(())
}
