//! The benchmark's outputs: a markdown table with the speed-target summary, the JSON, and an
//! SVG plot of run time against mean angular error (plotters).

use std::fmt::Write as _;
use std::path::Path;

use plotters::prelude::*;

use super::{BenchResult, Row, EXACT_LS, FAST_ADAPTIVE, FAST_LS, FAST_LS_REUSED, SHEEN_FIT};
use crate::error::{Error, Result};

/// The headline ratios at one size. The speed target is judged on `over_floor`: one solve as
/// `psscan` runs it, allocating its outputs; `reused_over_floor` is the same solve writing
/// into a previous solve's outputs, as a batch of same-size captures can.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Targets {
    /// The Lambertian scene's size, megapixels.
    pub megapixels: f64,
    /// Median time of [`FAST_LS`], the solve as `psscan` runs it, seconds.
    pub fast_s: f64,
    /// Median time of reading every input byte once (the memory-read floor), seconds.
    pub floor_s: f64,
    /// `fast_s` over `floor_s`: what the speed target is judged on.
    pub over_floor: f64,
    /// Median time of [`FAST_LS_REUSED`], seconds; `None` when that variant was not run.
    pub reused_s: Option<f64>,
    /// `reused_s` over `floor_s`; `None` when the variant was not run.
    pub reused_over_floor: Option<f64>,
    /// The NumPy peer's time (its `numpy pinv, 4 solves (distant)` row), seconds; `None` when
    /// the peer was not run.
    pub numpy_s: Option<f64>,
    /// `numpy_s` over `fast_s`: how many times faster psscan's fast solve is than NumPy.
    pub numpy_over_fast: Option<f64>,
    /// `None` with `--speed-only`.
    pub exact_s: Option<f64>,
    /// `exact_s` over `fast_s`; `None` with `--speed-only`.
    pub exact_over_fast: Option<f64>,
}

/// Speed-target figures on the Lambertian scene at each size.
pub fn targets(result: &BenchResult) -> Vec<Targets> {
    let mut sizes: Vec<f64> = result
        .rows
        .iter()
        .filter(|r| r.scene == "lambertian")
        .map(|r| r.megapixels)
        .collect();
    sizes.dedup();
    sizes
        .into_iter()
        .filter_map(|mp| {
            let find = |name: &str| {
                result
                    .rows
                    .iter()
                    .find(|r| r.scene == "lambertian" && r.megapixels == mp && r.variant == name)
            };
            let fast = find(FAST_LS)?;
            let floor = find("memory-read floor")?;
            let exact = find(EXACT_LS).map(|r| r.seconds);
            let reused = find(FAST_LS_REUSED).map(|r| r.seconds);
            let numpy = find("numpy pinv, 4 solves (distant)").map(|r| r.seconds);
            Some(Targets {
                megapixels: mp,
                fast_s: fast.seconds,
                floor_s: floor.seconds,
                over_floor: fast.seconds / floor.seconds,
                reused_s: reused,
                reused_over_floor: reused.map(|r| r / floor.seconds),
                numpy_s: numpy,
                numpy_over_fast: numpy.map(|n| n / fast.seconds),
                exact_s: exact,
                exact_over_fast: exact.map(|e| e / fast.seconds),
            })
        })
        .collect()
}

/// Issue 6's done-when figures for the estimators at one size, from the rows of one run.
#[derive(Clone, Debug, serde::Serialize)]
pub struct EstimatorFigures {
    /// The size the figures are for, megapixels.
    pub megapixels: f64,
    /// Lambertian scene: the adaptive estimator on the streaming kernel over the streaming
    /// least squares it starts from (both f32, tiled).
    pub adaptive_over_ls_time: Option<f64>,
    /// Lambertian scene: pixels the adaptive estimator escalated (its false alarms).
    pub adaptive_false_escalation: Option<f64>,
    /// Mean angular errors: least squares on the Lambertian scene, least squares and the
    /// adaptive estimator with the sheen fit on the shadows + sheen scene.
    pub lambertian_ls_error_deg: Option<f64>,
    /// Mean angular error of least squares on the shadows + sheen scene (degrees).
    pub shadows_sheen_ls_error_deg: Option<f64>,
    /// Mean angular error of the adaptive estimator with the sheen fit on the shadows + sheen scene
    /// (degrees).
    pub shadows_sheen_adaptive_error_deg: Option<f64>,
    /// `1 - adaptive / ls` on the shadows + sheen scene (at least 0.5 to pass).
    pub error_reduction: Option<f64>,
    /// Adaptive on shadows + sheen over least squares on the Lambertian scene (at most 1.5).
    pub over_lambertian_ls: Option<f64>,
}

/// The estimator figures at each size.
pub fn estimator_figures(result: &BenchResult) -> Vec<EstimatorFigures> {
    let mut sizes: Vec<f64> = result.rows.iter().map(|r| r.megapixels).collect();
    sizes.dedup();
    sizes.sort_by(f64::total_cmp);
    sizes.dedup();
    let adaptive_sheen = format!("{FAST_ADAPTIVE}{SHEEN_FIT}");
    sizes
        .into_iter()
        .map(|mp| {
            let find = |scene: &str, name: &str| {
                result
                    .rows
                    .iter()
                    .find(|r| r.scene == scene && r.megapixels == mp && r.variant == name)
            };
            let fast = find("lambertian", FAST_LS);
            let adaptive = find("lambertian", FAST_ADAPTIVE);
            let lambert_ls = find("lambertian", EXACT_LS).map(|r| r.mean_error_deg);
            let ls = find("shadows+sheen", EXACT_LS).map(|r| r.mean_error_deg);
            let ad = find("shadows+sheen", &adaptive_sheen).map(|r| r.mean_error_deg);
            EstimatorFigures {
                megapixels: mp,
                adaptive_over_ls_time: fast.zip(adaptive).map(|(f, a)| a.seconds / f.seconds),
                adaptive_false_escalation: adaptive.map(|a| a.escalated_fraction),
                lambertian_ls_error_deg: lambert_ls,
                shadows_sheen_ls_error_deg: ls,
                shadows_sheen_adaptive_error_deg: ad,
                error_reduction: ls.zip(ad).map(|(l, a)| 1.0 - a / l),
                over_lambertian_ls: lambert_ls.zip(ad).map(|(l, a)| a / l),
            }
        })
        .collect()
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("-".into(), |v| format!("{v:.digits$}"))
}

/// The markdown report.
pub fn markdown(result: &BenchResult) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# psscan bench\n\n{} threads on {}; whole run {:.0} s. NumPy: {}.\n",
        result.threads,
        result.cpu,
        result.seconds,
        result.numpy.as_deref().unwrap_or("not run")
    );
    let _ = writeln!(
        s,
        "## Speed targets (Lambertian scene, 10 lights, RGB + luminance)\n"
    );
    let _ = writeln!(
        s,
        "The target (within 2x of the floor) is judged on `x floor`: one `{FAST_LS}` solve as \
         `psscan` runs it, allocating fresh outputs (the kernel faults in and zeroes their \
         pages). `reused` writes into the previous solve's outputs instead, as a batch of \
         same-size captures can (`solve_reusing`).\n"
    );
    let _ = writeln!(
        s,
        "| MP | {FAST_LS} (s) | read floor (s) | x floor | reused outputs (s) | reused x floor | NumPy (s) | NumPy / fast | exact kernel / fast |\n|---|---|---|---|---|---|---|---|---|"
    );
    for t in targets(result) {
        let _ = writeln!(
            s,
            "| {:.1} | {:.3} | {:.3} | {:.2} | {} | {} | {} | {} | {} |",
            t.megapixels,
            t.fast_s,
            t.floor_s,
            t.over_floor,
            opt(t.reused_s, 3),
            opt(t.reused_over_floor, 2),
            opt(t.numpy_s, 3),
            opt(t.numpy_over_fast, 2),
            opt(t.exact_over_fast, 1)
        );
    }
    for m in &result.memory {
        let _ = writeln!(
            s,
            "\nPeak memory of `{}` at {:.1} MP: {:.2} GB for {:.2} GB of decoded input = **{:.2}x**.",
            m.variant,
            m.megapixels,
            m.peak_bytes as f64 / 1e9,
            m.input_bytes as f64 / 1e9,
            m.ratio
        );
    }
    let _ = writeln!(
        s,
        "\n## Estimators (issue 6)\n\nLambertian: `{FAST_ADAPTIVE}` over `{FAST_LS}` (time, target <= 1.3) and the pixels it escalated; shadows + sheen: `{FAST_ADAPTIVE}{SHEEN_FIT}` against `{EXACT_LS}` (error reduction, target >= 50 %) and against least squares on the Lambertian scene (target <= 1.5).\n\n| MP | adaptive / ls time | false escalations | ls err, Lambertian | ls err, shadows+sheen | adaptive err, shadows+sheen | reduction | / Lambertian ls |\n|---|---|---|---|---|---|---|---|"
    );
    for f in estimator_figures(result) {
        let _ = writeln!(
            s,
            "| {:.1} | {} | {} | {} | {} | {} | {} | {} |",
            f.megapixels,
            opt(f.adaptive_over_ls_time, 2),
            f.adaptive_false_escalation
                .map_or("-".into(), |v| format!("{:.3} %", 100.0 * v)),
            opt(f.lambertian_ls_error_deg, 4),
            opt(f.shadows_sheen_ls_error_deg, 4),
            opt(f.shadows_sheen_adaptive_error_deg, 4),
            f.error_reduction
                .map_or("-".into(), |v| format!("{:.0} %", 100.0 * v)),
            opt(f.over_lambertian_ls, 2),
        );
    }
    for (mp, tile, err) in &result.tiles {
        let _ = writeln!(
            s,
            "\nTile grid at {mp:.1} MP: {tile} px tiles, estimated interpolation error {err:.5} deg."
        );
    }
    let _ = writeln!(
        s,
        "\n## All runs\n\n`dev` = angle to the exact f64 least-squares kernel's normals on the same frames.\n\n| scene | MP | variant | runs | time (s) | x floor | mean err (deg) | p95 err (deg) | max dev (deg) | mean dev (deg) | solved | escalated |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for r in &result.rows {
        let _ = writeln!(
            s,
            "| {} | {:.1} | {} | {} | {:.3} | {:.2} | {:.4} | {:.4} | {} | {} | {:.2} % | {:.2} % |",
            r.scene,
            r.megapixels,
            r.variant,
            r.runs,
            r.seconds,
            r.over_floor,
            r.mean_error_deg,
            r.p95_error_deg,
            opt(r.max_dev_from_exact_deg, 6),
            opt(r.mean_dev_from_exact_deg, 6),
            100.0 * r.solved_fraction,
            100.0 * r.escalated_fraction
        );
    }
    s
}

/// Writes `bench.md`, `bench.json` and `bench.svg` into `dir`.
pub fn write(result: &BenchResult, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let md = dir.join("bench.md");
    std::fs::write(&md, markdown(result)).map_err(|e| Error::io(&md, e))?;
    let json = dir.join("bench.json");
    let value = serde_json::json!({
        "result": result,
        "targets": targets(result),
        "estimators": estimator_figures(result),
    });
    let text = serde_json::to_string_pretty(&value).expect("serialisable");
    std::fs::write(&json, text).map_err(|e| Error::io(&json, e))?;
    plot(result, &dir.join("bench.svg"))
}

/// Run time against mean angular error, one panel per scene at the largest size; the floor
/// is drawn as a vertical line (it has no error).
pub fn plot(result: &BenchResult, path: &Path) -> Result<()> {
    let size = result.rows.iter().map(|r| r.megapixels).fold(0.0, f64::max);
    let scenes: Vec<String> = {
        let mut v: Vec<String> = result.rows.iter().map(|r| r.scene.clone()).collect();
        v.dedup();
        v
    };
    let fail = |e: &dyn std::fmt::Display| Error::Invalid(format!("plot {}: {e}", path.display()));
    let root =
        SVGBackend::new(path, (1200, 420 * scenes.len().div_ceil(2) as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let panels = root.split_evenly((scenes.len().div_ceil(2), 2));
    for (scene, area) in scenes.iter().zip(panels.iter()) {
        let rows: Vec<&Row> = result
            .rows
            .iter()
            .filter(|r| &r.scene == scene && r.megapixels == size)
            .collect();
        draw_panel(area, scene, size, &rows).map_err(|e| fail(&e))?;
    }
    root.present().map_err(|e| fail(&e))?;
    Ok(())
}

type Panel<'a> = DrawingArea<SVGBackend<'a>, plotters::coord::Shift>;

fn draw_panel(
    area: &Panel,
    scene: &str,
    size: f64,
    rows: &[&Row],
) -> std::result::Result<(), Box<dyn std::error::Error>> {
    let timed: Vec<&&Row> = rows.iter().filter(|r| r.seconds > 0.0).collect();
    let t_min = timed.iter().map(|r| r.seconds).fold(f64::MAX, f64::min) / 1.5;
    let t_max = timed.iter().map(|r| r.seconds).fold(0.0, f64::max) * 1.5;
    let solved: Vec<&&Row> = timed
        .iter()
        .copied()
        .filter(|r| r.mean_error_deg > 0.0)
        .collect();
    let e_max = solved.iter().map(|r| r.mean_error_deg).fold(0.0, f64::max) * 1.15;
    // The legend gets its own column beside the axes, so it never covers a data point.
    let (plot_area, legend_area) = area.split_horizontally((area.dim_in_pixel().0 * 3 / 5) as i32);
    let mut chart = ChartBuilder::on(&plot_area)
        .caption(format!("{scene}, {}", size_label(size)), ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(52)
        .build_cartesian_2d((t_min..t_max).log_scale(), 0.0..e_max.max(1e-3))?;
    chart
        .configure_mesh()
        .x_desc("run time (s, log)")
        .y_desc("mean angular error (deg)")
        .draw()?;
    let font = ("sans-serif", 11).into_font();
    let entry_y = |i: usize| 40 + 18 * i as i32;
    for (i, r) in solved.iter().enumerate() {
        let colour = HSLColor(i as f64 / solved.len().max(1) as f64, 0.8, 0.4);
        chart.draw_series(std::iter::once(Circle::new(
            (r.seconds, r.mean_error_deg),
            5,
            colour.filled(),
        )))?;
        legend_area.draw(&Circle::new((12, entry_y(i)), 4, colour.filled()))?;
        legend_area.draw(&Text::new(
            r.variant.clone(),
            (24, entry_y(i) - 6),
            font.clone(),
        ))?;
    }
    if let Some(floor) = rows.iter().find(|r| r.variant == "memory-read floor") {
        chart.draw_series(LineSeries::new(
            [(floor.seconds, 0.0), (floor.seconds, e_max.max(1e-3))],
            BLACK.stroke_width(2),
        ))?;
        let y = entry_y(solved.len());
        legend_area.draw(&PathElement::new(
            [(12, y - 6), (12, y + 6)],
            BLACK.stroke_width(2),
        ))?;
        legend_area.draw(&Text::new("memory-read floor", (24, y - 6), font.clone()))?;
    }
    Ok(())
}

/// A scene size for captions: whole megapixels from 1 MP up; smaller scenes say so, with
/// two decimals (a 0.12 MP scene is not "0 MP").
pub fn size_label(megapixels: f64) -> String {
    if megapixels >= 1.0 && megapixels.fract() == 0.0 {
        format!("{megapixels:.0} MP")
    } else if megapixels >= 1.0 {
        format!("{megapixels:.1} MP")
    } else {
        format!("{megapixels:.2} MP (under 1 MP)")
    }
}
