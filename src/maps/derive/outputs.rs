//! The derived maps as image files: height (EXR in mm, 16-bit grey PNG over its range), the
//! normal map in an engine's convention and bit depth (RGB, and the two-channel XY layout of
//! BC5 with Z left for the shader to reconstruct), albedo in sRGB.

use std::path::Path;

use image::{DynamicImage, ImageBuffer};
use rayon::prelude::*;

use super::{HeightReport, SolvedMaps};
use crate::error::{Error, Result};
use crate::io::{write_exr, write_png};
use crate::maps::srgb::linear_to_srgb;
use crate::maps::NormalConvention;
use crate::plane::Plane;

/// Writes `height.exr` (channel `height`, mm or px) and `height.png` (16-bit grey, black at
/// the minimum and white at the maximum, both recorded in the report).
pub fn write_height(dir: &Path, z: &Plane, in_mm: bool) -> Result<HeightReport> {
    write_exr(&dir.join("height.exr"), &[("height", z)])?;
    let (lo, hi) = z
        .data
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    let span = (hi - lo).max(f32::MIN_POSITIVE);
    let grey: Vec<u16> = z
        .data
        .par_iter()
        .map(|&v| (((v - lo) / span) * 65535.0).round() as u16)
        .collect();
    let image = ImageBuffer::from_raw(z.width as u32, z.height as u32, grey)
        .map(DynamicImage::ImageLuma16)
        .ok_or_else(|| Error::image(dir.join("height.png"), "size does not match its data"))?;
    write_png(&dir.join("height.png"), &image)?;
    Ok(HeightReport {
        units: if in_mm { "mm" } else { "px" }.into(),
        min: lo as f64,
        max: hi as f64,
        masked: None,
    })
}

/// Writes `normal.png` (RGB), `normal_xy.png` (X in red, Y in green, blue 0: the BC5 layout)
/// and `albedo.png` (sRGB), at `bits` per channel.
pub fn write_textures(
    dir: &Path,
    maps: &SolvedMaps,
    convention: NormalConvention,
    bits: u8,
) -> Result<()> {
    let (w, h) = (maps.width(), maps.height());
    let unit = |v: f32| v * 0.5 + 0.5;
    let normal = |i: usize, c: usize| unit(normal_component(maps, convention, i, c));
    let xy = |i: usize, c: usize| if c < 2 { normal(i, c) } else { 0.0 };
    let albedo = |i: usize, c: usize| albedo_srgb(maps, i, c);
    let jobs: [(&str, &Texel); 3] = [
        ("normal.png", &normal),
        ("normal_xy.png", &xy),
        ("albedo.png", &albedo),
    ];
    jobs.par_iter()
        .map(|(name, texel)| write_rgb(&dir.join(name), w, h, bits, texel))
        .collect::<Result<Vec<()>>>()?;
    Ok(())
}

/// A texture's value in [0, 1] at pixel `i`, channel `c`.
pub type Texel<'a> = dyn Fn(usize, usize) -> f32 + Sync + 'a;

/// Component `c` of the unit normal at pixel `i`, with Y in `convention`.
pub fn normal_component(
    maps: &SolvedMaps,
    convention: NormalConvention,
    i: usize,
    c: usize,
) -> f32 {
    let v = maps.normal[c].data[i];
    if c == 1 {
        convention.y(v)
    } else {
        v
    }
}

/// Albedo channel `c` at pixel `i`, sRGB-encoded in [0, 1]; unsolved pixels black.
pub fn albedo_srgb(maps: &SolvedMaps, i: usize, c: usize) -> f32 {
    if maps.solved[i] {
        linear_to_srgb(maps.albedo[c].data[i])
    } else {
        0.0
    }
}

/// An RGB texture of `texel` values in [0, 1], quantised straight to an 8- or 16-bit PNG.
pub fn write_rgb(path: &Path, w: usize, h: usize, bits: u8, texel: &Texel) -> Result<()> {
    let bad = || Error::image(path, "size does not match its data");
    let value = |k: usize| texel(k / 3, k % 3).clamp(0.0, 1.0);
    let image = if bits == 8 {
        let v = (0..w * h * 3)
            .into_par_iter()
            .map(|k| (value(k) * 255.0).round() as u8)
            .collect();
        DynamicImage::ImageRgb8(ImageBuffer::from_raw(w as u32, h as u32, v).ok_or_else(bad)?)
    } else {
        let v = (0..w * h * 3)
            .into_par_iter()
            .map(|k| (value(k) * 65535.0).round() as u16)
            .collect();
        DynamicImage::ImageRgb16(ImageBuffer::from_raw(w as u32, h as u32, v).ok_or_else(bad)?)
    };
    write_png(path, &image)
}
