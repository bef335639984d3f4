//! The derived maps as image files: height (EXR in mm, 16-bit grey PNG over its range), the
//! normal map in an engine's convention and bit depth (RGB, and the two-channel XY layout of
//! BC5 with Z left for the shader to reconstruct), albedo in sRGB.

use std::path::Path;

use image::{DynamicImage, ImageBuffer};
use rayon::prelude::*;

use super::{HeightReport, SolvedMaps};
use crate::error::{Error, Result};
use crate::io::{write_exr, write_png};
use crate::maps::encode::linear_to_srgb;
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
    let normal = normal_channels(&maps.normal, convention);
    let unit = |v: f32| v * 0.5 + 0.5;
    let rgb = interleave(w * h, |i, c| unit(normal[c][i]));
    let xy = interleave(w * h, |i, c| if c < 2 { unit(normal[c][i]) } else { 0.0 });
    let albedo = albedo_srgb(maps);
    let jobs: [(&str, &Vec<f32>); 3] = [
        ("normal.png", &rgb),
        ("normal_xy.png", &xy),
        ("albedo.png", &albedo),
    ];
    jobs.par_iter()
        .map(|(name, data)| write_rgb(&dir.join(name), w, h, data, bits))
        .collect::<Result<Vec<()>>>()?;
    Ok(())
}

/// The normal's three components in `convention`, as slices.
pub fn normal_channels(normal: &[Plane; 3], convention: NormalConvention) -> [Vec<f32>; 3] {
    let y = normal[1].data.iter().map(|&v| convention.y(v)).collect();
    [normal[0].data.clone(), y, normal[2].data.clone()]
}

/// Albedo as interleaved sRGB-encoded values in [0, 1]; unsolved pixels black.
pub fn albedo_srgb(maps: &SolvedMaps) -> Vec<f32> {
    let n = maps.width() * maps.height();
    interleave(n, |i, c| {
        if maps.solved[i] {
            linear_to_srgb(maps.albedo[c].data[i])
        } else {
            0.0
        }
    })
}

fn interleave(n: usize, f: impl Fn(usize, usize) -> f32 + Sync) -> Vec<f32> {
    (0..n * 3)
        .into_par_iter()
        .map(|k| f(k / 3, k % 3))
        .collect()
}

/// Interleaved RGB values in [0, 1] as an 8- or 16-bit PNG.
pub fn write_rgb(path: &Path, w: usize, h: usize, data: &[f32], bits: u8) -> Result<()> {
    let bad = || Error::image(path, "size does not match its data");
    let image = if bits == 8 {
        let v = data
            .iter()
            .map(|&x| (x.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        DynamicImage::ImageRgb8(ImageBuffer::from_raw(w as u32, h as u32, v).ok_or_else(bad)?)
    } else {
        let v = data
            .iter()
            .map(|&x| (x.clamp(0.0, 1.0) * 65535.0).round() as u16)
            .collect();
        DynamicImage::ImageRgb16(ImageBuffer::from_raw(w as u32, h as u32, v).ok_or_else(bad)?)
    };
    write_png(path, &image)
}
