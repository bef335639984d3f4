//! Everything derived from a solve, and the writers: normal maps (16-bit PNG in OpenGL or
//! DirectX convention, float EXR), albedo (16-bit sRGB PNG, linear EXR), the confidence map
//! (EXR: residual, predicted error, condition, lights used, status, which fit: 0 least
//! squares, 1 robust, 2 sheen) and `report.json`.

pub mod derive;
pub mod encode;
pub mod report;
pub mod write;

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::error::{Error, Result};
use crate::fsutil::create_dir_all;
use crate::plane::Plane;
use crate::solve::SolveResult;

pub use encode::NormalConvention;
pub use report::Report;

/// Which maps to write and how.
#[derive(Clone, Debug, Serialize)]
pub struct MapOptions {
    pub normal_convention: NormalConvention,
    pub png: bool,
    pub exr: bool,
    /// Camera RGB to linear sRGB for the display output (`albedo.png`); the solve's data
    /// outputs (EXR) stay in the camera's white-balanced RGB. `None`: the channels are sRGB's.
    pub display_matrix: Option<[[f64; 3]; 3]>,
}

impl Default for MapOptions {
    fn default() -> Self {
        MapOptions {
            normal_convention: NormalConvention::OpenGl,
            png: true,
            exr: true,
            display_matrix: None,
        }
    }
}

/// Paths of the files written (absent when not requested).
#[derive(Clone, Debug, Default, Serialize)]
pub struct WrittenMaps {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_png: Option<PathBuf>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_exr: Option<PathBuf>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub albedo_png: Option<PathBuf>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub albedo_exr: Option<PathBuf>,
    pub confidence_exr: PathBuf,
}

pub const REPORT_FILE: &str = "report.json";

/// Refuses to write into a folder that already holds a finished solve, unless `force`.
pub fn prepare_output_dir(dir: &Path, force: bool) -> Result<()> {
    let report = dir.join(REPORT_FILE);
    if report.exists() && !force {
        return Err(Error::Exists { path: report });
    }
    create_dir_all(dir)
}

/// Writes the maps of `result` into `dir` (each file atomically; the four encoders run in
/// parallel).
pub fn write_maps(result: &SolveResult, dir: &Path, options: &MapOptions) -> Result<WrittenMaps> {
    let (w, h) = (result.width, result.height);
    let path = |name: &str| dir.join(name);
    let normal_png = || -> Result<Option<PathBuf>> {
        if !options.png {
            return Ok(None);
        }
        let p = path("normal.png");
        write::write_png16(
            &p,
            w,
            h,
            encode::normal_rgb16(result, options.normal_convention),
        )?;
        Ok(Some(p))
    };
    let albedo_png = || -> Result<Option<PathBuf>> {
        if !options.png {
            return Ok(None);
        }
        let p = path("albedo.png");
        write::write_png16(
            &p,
            w,
            h,
            encode::albedo_rgb16(result, options.display_matrix.as_ref()),
        )?;
        Ok(Some(p))
    };
    let exrs = || -> Result<(Option<PathBuf>, Option<PathBuf>, PathBuf)> {
        let (mut normal, mut albedo) = (None, None);
        if options.exr {
            let [nx, ny, nz] = encode::normal_planes(result, options.normal_convention);
            let p = path("normal.exr");
            write::write_exr(&p, &[("R", &nx), ("G", &ny), ("B", &nz)])?;
            normal = Some(p);
            let [r, g, b] = &result.albedo;
            let p = path("albedo.exr");
            write::write_exr(&p, &[("R", r), ("G", g), ("B", b)])?;
            albedo = Some(p);
        }
        let p = path("confidence.exr");
        let lights = Plane::from_vec(w, h, result.lights_used.iter().map(|&v| v as f32).collect())?;
        let status = Plane::from_vec(
            w,
            h,
            result.status.iter().map(|&s| s as u8 as f32).collect(),
        )?;
        let fit = Plane::from_vec(w, h, result.fit.iter().map(|&f| f as u8 as f32).collect())?;
        write::write_exr(
            &p,
            &[
                ("residual", &result.residual),
                ("predicted_error_deg", &result.predicted_error_deg),
                ("condition", &result.condition),
                ("lights_used", &lights),
                ("status", &status),
                ("fit", &fit),
            ],
        )?;
        Ok((normal, albedo, p))
    };
    let ((normal_png, albedo_png), exr) = rayon::join(|| rayon::join(normal_png, albedo_png), exrs);
    let (normal_exr, albedo_exr, confidence_exr) = exr?;
    Ok(WrittenMaps {
        normal_png: normal_png?,
        normal_exr,
        albedo_png: albedo_png?,
        albedo_exr,
        confidence_exr,
    })
}
