//! The maps the page shows, at full resolution: read back from a solve folder's files, or
//! borrowed from a solve still in memory (the same values either way, see
//! [`FullMaps::from_result`]).

use std::borrow::Cow;
use std::path::Path;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::read_exr;
use crate::maps::encode::NormalConvention;
use crate::maps::srgb::srgb_to_linear;
use crate::plane::Plane;
use crate::solve::SolveResult;

/// The full-resolution maps of a solve, read back from its folder or borrowed from memory.
pub struct FullMaps<'a> {
    /// Width of the full-resolution maps in pixels.
    pub width: usize,
    /// Height of the full-resolution maps in pixels.
    pub height: usize,
    /// Linear RGB albedo (display primaries, as `albedo.png` holds them).
    pub albedo: Option<AlbedoMap<'a>>,
    /// World-frame normals, OpenGL convention; `None` where the map is missing. Borrowed from
    /// a solve still in memory ([`FullMaps::from_result`]).
    pub normal: Option<[Cow<'a, Plane>; 3]>,
    /// `confidence.exr`'s planes; borrowed from a solve still in memory.
    pub confidence: Option<Confidence<'a>>,
    /// What could not be read, in words (file and cause).
    pub missing: Vec<String>,
}

/// The planes of `confidence.exr` the page shows. The class planes are bytes, as the solve
/// holds them: as `f32` planes, the file's type, they were 128 MB of fresh memory at 16 MP
/// beside a solve that already held the classes.
pub struct Confidence<'a> {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Each pixel's `PixelStatus` as its number ([`SOLVED`] where solved).
    pub status: Cow<'a, [u8]>,
    /// Each pixel's `PixelFit` as its number.
    pub fit: Cow<'a, [u8]>,
    /// Predicted normal error in degrees.
    pub predicted_error_deg: Cow<'a, Plane>,
    /// RMS residual of the luminance fit.
    pub residual: Cow<'a, Plane>,
}

/// A solved pixel's number in the status plane.
pub const SOLVED: u8 = crate::solve::PixelStatus::Solved as u8;

/// The number of a class plane's value in a file that holds no class there (NaN, negative, or
/// past the last number a byte holds): no class has it, so it is counted in no legend and
/// drawn in no class's colour.
pub const NO_CLASS: u8 = u8::MAX;

/// A class plane's value, as `confidence.exr` stores it (a float), as its class number: the
/// whole part of a value in `[0, 255)`, else [`NO_CLASS`].
pub fn class_of(value: f32) -> u8 {
    if value >= 0.0 && value < f32::from(NO_CLASS) {
        value as u8
    } else {
        NO_CLASS
    }
}

/// The albedo the page shows: linear display primaries clamped to [0, 1], black where
/// unsolved, as `albedo.png` holds it.
pub enum AlbedoMap<'a> {
    /// Read back from the solve folder's files.
    Planes([Plane; 3]),
    /// A solve still in memory, each pixel converted as it is read: display planes made first
    /// were 193 MB of fresh memory at 16 MP, for two readers that each read a pixel once.
    Solve {
        /// The solve, whose albedo and pixel status are read.
        result: &'a SolveResult,
        /// Camera to display primaries, when the camera's are not sRGB's.
        display_matrix: Option<[[f64; 3]; 3]>,
    },
}

impl AlbedoMap<'_> {
    /// Pixel `i`'s display albedo: [`AlbedoMap::run_into`] of that one pixel.
    pub fn pixel(&self, i: usize) -> [f32; 3] {
        let [mut r, mut g, mut b] = [[0f32]; 3];
        self.run_into(i, [&mut r, &mut g, &mut b]);
        [r[0], g[0], b[0]]
    }

    /// The display albedo of the pixels from `start` on, as many as `out`'s rows hold, one
    /// channel per row: the variant is matched once, not per pixel.
    pub fn run_into(&self, start: usize, [r, g, b]: [&mut [f32]; 3]) {
        match self {
            AlbedoMap::Planes(planes) => {
                for (plane, out) in planes.iter().zip([r, g, b]) {
                    out.copy_from_slice(&plane.data[start..start + out.len()]);
                }
            }
            AlbedoMap::Solve {
                result,
                display_matrix,
            } => {
                crate::maps::encode::display_albedo_run(
                    result,
                    display_matrix.as_ref(),
                    start,
                    [&mut *r, &mut *g, &mut *b],
                );
                for channel in [r, g, b] {
                    channel.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
                }
            }
        }
    }
}

/// Reads a 16-bit RGB PNG as three planes of `value(sample)`, one plane per channel, each
/// filled on its own thread.
fn read_png16(
    path: &Path,
    value: impl Fn(u16) -> f32 + Sync,
) -> Result<(usize, usize, [Vec<f32>; 3])> {
    let img = image::open(path)
        .map_err(|e| Error::image(path, e))?
        .into_rgb16();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let samples = img.as_raw();
    let mut out: [Vec<f32>; 3] = Default::default();
    out.par_iter_mut().enumerate().for_each(|(c, plane)| {
        *plane = samples
            .iter()
            .skip(c)
            .step_by(3)
            .map(|&v| value(v))
            .collect();
    });
    Ok((w, h, out))
}

/// `srgb_to_linear(v / 65535)` for every 16-bit value: the same `f32`s as computing it per
/// sample, without a `powf` per sample of a 16 MP map.
fn srgb16_to_linear_table() -> Vec<f32> {
    (0..=u16::MAX)
        .map(|v| srgb_to_linear(v as f32 / 65535.0))
        .collect()
}

fn planes(w: usize, h: usize, data: [Vec<f32>; 3]) -> Result<[Plane; 3]> {
    let [a, b, c] = data;
    Ok([
        Plane::from_vec(w, h, a)?,
        Plane::from_vec(w, h, b)?,
        Plane::from_vec(w, h, c)?,
    ])
}

fn read_albedo(dir: &Path) -> Result<[Plane; 3]> {
    let png = dir.join("albedo.png");
    if png.exists() {
        let table = srgb16_to_linear_table();
        let (w, h, data) = read_png16(&png, |v| table[v as usize])?;
        return planes(w, h, data);
    }
    let exr = dir.join("albedo.exr");
    if exr.exists() {
        let [r, g, b]: [Plane; 3] = read_exr(&exr, &["R", "G", "B"])?
            .try_into()
            .map_err(|_| Error::image(&exr, "expected three channels"))?;
        return Ok([r, g, b]);
    }
    Err(Error::image(
        dir.join("albedo.png"),
        "missing (and no albedo.exr)",
    ))
}

fn read_normal(dir: &Path, convention: NormalConvention) -> Result<[Plane; 3]> {
    let png = dir.join("normal.png");
    let exr = dir.join("normal.exr");
    let [x, mut y, z] = if png.exists() {
        let (w, h, data) = read_png16(&png, |v| v as f32 / 65535.0 * 2.0 - 1.0)?;
        planes(w, h, data)?
    } else if exr.exists() {
        read_exr(&exr, &["R", "G", "B"])?
            .try_into()
            .map_err(|_| Error::image(&exr, "expected three channels"))?
    } else {
        return Err(Error::image(png, "missing (and no normal.exr)"));
    };
    if convention == NormalConvention::DirectX {
        y.data.iter_mut().for_each(|v| *v = -*v);
    }
    Ok([x, y, z])
}

fn read_confidence(dir: &Path) -> Result<Confidence<'static>> {
    let path = dir.join("confidence.exr");
    if !path.exists() {
        return Err(Error::image(path, "missing"));
    }
    let [status, fit, predicted_error_deg, residual]: [Plane; 4] =
        read_exr(&path, &["status", "fit", "predicted_error_deg", "residual"])?
            .try_into()
            .map_err(|_| Error::image(&path, "expected four channels"))?;
    let classes = |plane: Plane| Cow::Owned(plane.data.par_iter().map(|&v| class_of(v)).collect());
    Ok(Confidence {
        width: status.width,
        height: status.height,
        status: classes(status),
        fit: classes(fit),
        predicted_error_deg: Cow::Owned(predicted_error_deg),
        residual: Cow::Owned(residual),
    })
}

fn keep<T>(read: Result<T>, missing: &mut Vec<String>) -> Option<T> {
    read.map_err(|e| missing.push(e.to_string())).ok()
}

impl<'a> FullMaps<'a> {
    /// Reads what the solve folder holds; a missing or unreadable map is noted, not fatal.
    pub fn read(dir: &Path, convention: NormalConvention) -> FullMaps<'static> {
        let mut missing = Vec::new();
        // Three files, read side by side.
        let (albedo, (normal, confidence)) = rayon::join(
            || read_albedo(dir),
            || rayon::join(|| read_normal(dir, convention), || read_confidence(dir)),
        );
        let albedo = keep(albedo, &mut missing);
        let normal = keep(normal, &mut missing).map(|n| n.map(Cow::Owned));
        let confidence = keep(confidence, &mut missing);
        let sizes: Vec<(usize, usize)> = [
            albedo.as_ref().map(|p| &p[0]),
            normal.as_ref().map(|p| &*p[0]),
        ]
        .into_iter()
        .flatten()
        .map(|p| (p.width, p.height))
        .chain(confidence.as_ref().map(|c| (c.width, c.height)))
        .collect();
        let (width, height) = sizes.first().copied().unwrap_or((0, 0));
        let mut maps = FullMaps {
            width,
            height,
            albedo: albedo.map(AlbedoMap::Planes),
            normal,
            confidence,
            missing,
        };
        if sizes.iter().any(|&s| s != (width, height)) {
            maps.missing.push(format!(
                "{}: the maps have different sizes ({sizes:?}); only the first size is shown",
                dir.display()
            ));
            maps.drop_other_sizes();
        }
        maps
    }

    /// The maps of a solve still in memory, as [`FullMaps::read`] reads them back from the
    /// files the solve writes (the albedo through `display_matrix` and clamped to [0, 1] as
    /// `albedo.png` holds it, black where unsolved; the normals in the OpenGL convention; the
    /// confidence planes as `confidence.exr` holds them), without the PNGs' 16-bit rounding
    /// and without reading and decoding half a gigabyte of files at 16 MP. The normals and the
    /// confidence planes are the solve's own, borrowed: copies were 320 MB at 16 MP, all of it
    /// fresh memory.
    pub fn from_result(
        result: &'a SolveResult,
        display_matrix: Option<&[[f64; 3]; 3]>,
    ) -> FullMaps<'a> {
        let (w, h) = (result.width, result.height);
        // As `albedo.png` holds it: display primaries, clamped, black where unsolved.
        let albedo = AlbedoMap::Solve {
            result,
            display_matrix: display_matrix.copied(),
        };
        let normal = result.normal.each_ref().map(Cow::Borrowed);
        let confidence = Confidence {
            width: w,
            height: h,
            status: Cow::Borrowed(bytemuck::cast_slice(&result.status)),
            fit: Cow::Borrowed(bytemuck::cast_slice(&result.fit)),
            predicted_error_deg: Cow::Borrowed(&result.predicted_error_deg),
            residual: Cow::Borrowed(&result.residual),
        };
        FullMaps {
            width: w,
            height: h,
            albedo: Some(albedo),
            normal: Some(normal),
            confidence: Some(confidence),
            missing: Vec::new(),
        }
    }

    /// Maps of only a confidence map (class numbers `status` and `fit`, and the float planes),
    /// for the tests of what the page computes from it.
    #[cfg(test)]
    pub(super) fn of_confidence(
        status: Vec<u8>,
        fit: Vec<u8>,
        [predicted_error_deg, residual]: [Plane; 2],
    ) -> FullMaps<'static> {
        let confidence = Confidence {
            width: residual.width,
            height: residual.height,
            status: Cow::Owned(status),
            fit: Cow::Owned(fit),
            predicted_error_deg: Cow::Owned(predicted_error_deg),
            residual: Cow::Owned(residual),
        };
        FullMaps {
            width: confidence.width,
            height: confidence.height,
            albedo: None,
            normal: None,
            confidence: Some(confidence),
            missing: Vec::new(),
        }
    }

    fn drop_other_sizes(&mut self) {
        let size = (self.width, self.height);
        let same = |p: &Plane| (p.width, p.height) == size;
        if self.normal.as_ref().is_some_and(|n| !same(&n[0])) {
            self.normal = None;
        }
        if self
            .confidence
            .as_ref()
            .is_some_and(|c| (c.width, c.height) != size)
        {
            self.confidence = None;
        }
    }

    /// The status plane (a `PixelStatus` as a number, [`SOLVED`] where solved); `None` where
    /// the confidence map is missing.
    pub fn status(&self) -> Option<&[u8]> {
        self.confidence.as_ref().map(|c| &c.status[..])
    }

    /// Whether pixel `i` holds a solved normal (status [`SOLVED`]; every pixel when the
    /// confidence map is missing).
    pub fn solved(&self, i: usize) -> bool {
        self.status().map_or(true, |s| s[i] == SOLVED)
    }
}
