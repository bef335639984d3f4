//! `psscan derive SOLVE_DIR`: the engine-ready material from a finished solve. One library
//! call (`maps::derive::derive`); this file only turns flags into its options.

use std::path::PathBuf;

use clap::Args;
use psscan::maps::derive::{
    self, DeriveOptions, DeriveReport, DeriveSource, Length, RoughnessFilter, RoughnessOptions,
    TileChoice,
};
use psscan::maps::NormalConvention;

use super::print_json;
use super::progress::Bars;

#[derive(Args)]
pub struct DeriveArgs {
    /// A solve's output folder (report.json, normal.exr, albedo.exr, confidence.exr).
    solve_dir: PathBuf,
    /// Output folder (default: SOLVE_DIR-derived beside the solve; never inside it, since the
    /// solve is this run's input).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Replace an existing derive folder.
    #[arg(long)]
    force: bool,
    /// Normal textures DirectX-style (+Y down) instead of OpenGL-style (+Y up).
    #[arg(long)]
    directx: bool,
    #[command(flatten)]
    flags: DeriveFlags,
}

/// The derive steps and encodings (on `derive`, and on `solve`, which derives from the maps it
/// has just solved into OUT/derived/). The normal convention is each command's `--directx`.
#[derive(Args, Clone)]
pub struct DeriveFlags {
    /// Every output: flatten (10mm unless --flatten), height, roughness mips, textures, DDS,
    /// glTF.
    #[arg(long)]
    all: bool,
    /// Remove tilt and folds longer than this radius (e.g. 10mm, 200px), keeping the detail.
    #[arg(long, value_name = "RADIUS", value_parser = Length::parse)]
    flatten: Option<Length>,
    /// Integrate the normals into height.exr (mm) and height.png (16-bit over its range).
    #[arg(long)]
    height: bool,
    /// Cut a seamless tile: WIDTHxHEIGHT (e.g. 20mmx20mm, 512pxx512px) or auto (the weave's
    /// period from the albedo).
    #[arg(long, value_name = "auto|WxH")]
    tile: Option<String>,
    /// Roughness mips with specular antialiasing: vmf (seed 004), toksvig, tokuyoshi.
    #[arg(long, value_name = "FILTER", value_parser = RoughnessFilter::parse)]
    roughness: Option<RoughnessFilter>,
    /// The material's base (glTF, perceptual) roughness at full resolution.
    #[arg(long, default_value_t = 0.5)]
    base_roughness: f64,
    /// normal.png, normal_xy.png (BC5 layout: X red, Y green) and albedo.png.
    #[arg(long)]
    textures: bool,
    /// Bits per channel of the PNG textures: 8 or 16.
    #[arg(long, default_value_t = 16)]
    bits: u8,
    /// normal.dds (BC5), albedo.dds (BC7 sRGB) and roughness.dds (BC4), full mip chains.
    #[arg(long)]
    dds: bool,
    /// material.gltf with its textures: a quad of the sample's size, sheen where fitted.
    #[arg(long)]
    gltf: bool,
    /// Millimetres per pixel on the sample, when the solve's report has none or is wrong.
    #[arg(long, value_name = "MM")]
    pixel_mm: Option<f64>,
}

impl DeriveFlags {
    /// Whether any step was asked for (a solve derives nothing otherwise).
    pub fn requested(&self) -> bool {
        self.all
            || self.flatten.is_some()
            || self.height
            || self.tile.is_some()
            || self.roughness.is_some()
            || self.textures
            || self.dds
            || self.gltf
    }

    pub fn options(&self, directx: bool) -> anyhow::Result<DeriveOptions> {
        let mut o = if self.all {
            DeriveOptions::all()
        } else {
            DeriveOptions::default()
        };
        if self.flatten.is_some() {
            o.flatten = self.flatten;
        }
        o.height |= self.height;
        o.textures |= self.textures;
        o.dds |= self.dds;
        o.gltf |= self.gltf;
        if let Some(filter) = self.roughness {
            o.roughness = Some(RoughnessOptions {
                filter,
                base: self.base_roughness,
            });
        } else if let Some(r) = &mut o.roughness {
            r.base = self.base_roughness;
        }
        o.tile = self.tile.as_deref().map(parse_tile).transpose()?;
        o.convention = if directx {
            NormalConvention::DirectX
        } else {
            NormalConvention::OpenGl
        };
        o.bits = self.bits;
        o.pixel_mm = self.pixel_mm;
        Ok(o)
    }
}

fn parse_tile(text: &str) -> anyhow::Result<TileChoice> {
    if text == "auto" {
        return Ok(TileChoice::Auto);
    }
    let (w, h) = text
        .split_once('x')
        .filter(|(w, _)| !w.ends_with("p"))
        .or_else(|| {
            // `20pxx20px`: split after "px".
            text.find("pxx").map(|i| (&text[..i + 2], &text[i + 3..]))
        })
        .ok_or_else(|| anyhow::anyhow!("--tile takes auto or WIDTHxHEIGHT, got \"{text}\""))?;
    Ok(TileChoice::Repeat {
        width: Length::parse(w).map_err(anyhow::Error::msg)?,
        height: Length::parse(h).map_err(anyhow::Error::msg)?,
    })
}

pub fn derive(args: &DeriveArgs, json: bool, bars: &Bars) -> anyhow::Result<()> {
    let options = args.flags.options(args.directx)?;
    let out = args.out.clone().unwrap_or_else(|| {
        let mut name = args
            .solve_dir
            .file_name()
            .map(|n| n.to_os_string())
            .unwrap_or_else(|| "solve".into());
        name.push("-derived");
        args.solve_dir.with_file_name(name)
    });
    let report = derive::derive(
        DeriveSource::SolveDir(&args.solve_dir),
        &out,
        &options,
        args.force,
        bars,
    )?;
    if json {
        print_json(&report);
    } else {
        print_summary(&report, &out);
    }
    Ok(())
}

fn print_summary(r: &DeriveReport, out: &std::path::Path) {
    println!("derived {} x {} into {}", r.width, r.height, out.display());
    match r.pixel_mm {
        Some(mm) => println!("  scale: {mm:.5} mm/px ({})", r.scale_source),
        None => println!("  scale: {}", r.scale_source),
    }
    if let Some(t) = &r.tiling {
        println!(
            "  tile: {} x {} px (period {:.2} x {:.2} px{}), seam {:.4} -> {:.4}",
            t.tile_px[0],
            t.tile_px[1],
            t.period_px[0],
            t.period_px[1],
            if t.found_from_albedo { ", found" } else { "" },
            t.seam_excess_crop,
            t.seam_excess_blended
        );
    }
    if let Some(h) = &r.height_map {
        println!("  height: {:.4} .. {:.4} {}", h.min, h.max, h.units);
    }
    if let Some(s) = &r.sheen {
        println!(
            "  sheen: colour {:?}, roughness {:.3}",
            s.color, s.roughness
        );
    }
    for (step, s) in &r.timings_s {
        println!("  {step:>10}: {s:.3} s");
    }
}
