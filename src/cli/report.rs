//! `psscan report`: rebuilds a solve folder's report.html, or renders its relight on the CPU.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use psscan::maps::html::{self, relight::Brdf, relight::RelightParams};

#[derive(Args)]
pub struct ReportArgs {
    /// A solve's output folder (report.json and the maps).
    solve_dir: PathBuf,
    /// A `psscan derive` folder whose height and roughness the page shows (default: the
    /// solve folder's own derived/, when it has one).
    #[arg(long, value_name = "DIR")]
    derived: Option<PathBuf>,
    /// Render the page's relight under this light direction (x,y,z; world frame, +z toward
    /// the camera) into --render-out instead of rebuilding the page.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        requires = "render_out",
        value_name = "X,Y,Z"
    )]
    render_light: Option<Vec<f32>>,
    /// PNG to write the CPU relight into.
    #[arg(long, requires = "render_light")]
    render_out: Option<PathBuf>,
    /// BRDF of the relight: ggx or cloth.
    #[arg(long, default_value = "ggx")]
    brdf: String,
    /// Uniform roughness of the relight.
    #[arg(long, default_value_t = RelightParams::default().roughness)]
    roughness: f32,
    /// Exposure of the relight (1: a white surface facing the light is white).
    #[arg(long, default_value_t = RelightParams::default().exposure)]
    exposure: f32,
}

pub fn report(args: &ReportArgs, json: bool) -> anyhow::Result<()> {
    if !args.solve_dir.is_dir() {
        anyhow::bail!("{}: not a folder", args.solve_dir.display());
    }
    if let (Some(light), Some(out)) = (&args.render_light, &args.render_out) {
        if light.len() != 3 || light[2] <= 0.0 {
            anyhow::bail!(
                "--render-light takes x,y,z with z > 0 (a light above the sample), got {light:?}"
            );
        }
        let params = RelightParams {
            light: [light[0], light[1], light[2]],
            brdf: Brdf::parse(&args.brdf)?,
            roughness: args.roughness,
            exposure: args.exposure,
        };
        let (w, h) = html::render_relight_png(&args.solve_dir, &params, out)
            .with_context(|| format!("rendering the relight of {}", args.solve_dir.display()))?;
        if json {
            crate::cli::print_json(
                &serde_json::json!({"out": out, "width": w, "height": h, "params": params}),
            );
        } else {
            println!(
                "psscan report: relight {w}x{h} written to {}",
                out.display()
            );
        }
        return Ok(());
    }
    if let Some(dir) = &args.derived {
        if !dir.join(psscan::maps::derive::DERIVE_REPORT).is_file() {
            anyhow::bail!(
                "{}: not a derive folder (it has no {}); run psscan derive first",
                dir.display(),
                psscan::maps::derive::DERIVE_REPORT
            );
        }
    }
    let summary = html::write_report_page_with(&args.solve_dir, args.derived.as_deref())?;
    if json {
        crate::cli::print_json(&summary);
    } else {
        println!(
            "psscan report: {} ({:.1} MB, {}x{} maps shown at {}x{})",
            summary.path.display(),
            summary.bytes as f64 / 1e6,
            summary.width,
            summary.height,
            summary.display.width,
            summary.display.height
        );
        for problem in summary.missing.iter().chain(&summary.report_error) {
            println!("  note: {problem}");
        }
    }
    Ok(())
}
