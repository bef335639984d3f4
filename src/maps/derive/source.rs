//! The maps `derive` works on, read from a finished solve folder with the writers' own EXR
//! reader, or handed over in memory.

use std::path::Path;

use serde_json::Value;

use crate::error::{Error, Result};
use crate::io::read_exr;
use crate::maps::{NormalConvention, REPORT_FILE};
use crate::plane::Plane;
use crate::solve::{PixelStatus, SheenModel, SolveResult};

/// A solve's maps in the world frame, plus what the material needs from its report.
#[derive(Clone, Debug)]
pub struct SolvedMaps {
    /// Unit normals, world frame (+y toward the top of the image: OpenGL).
    pub normal: [Plane; 3],
    /// Linear albedo with sRGB primaries (the display matrix applied).
    pub albedo: [Plane; 3],
    /// Pixels the solve solved; the others hold a flat normal and black albedo.
    pub solved: Vec<bool>,
    /// Millimetres per pixel on the sample; `None` when the solve has no scale.
    pub pixel_mm: Option<f64>,
    /// Where `pixel_mm` came from, or why it is missing.
    pub scale_source: String,
    /// The cloth lobe the solve was given, and how many pixels it fitted.
    pub sheen: Option<SheenModel>,
    /// Pixels where the solve fitted the cloth lobe (their fit is `Sheen`); 0 when none.
    pub sheen_pixels: usize,
}

impl SolvedMaps {
    /// Width of the maps in pixels.
    pub fn width(&self) -> usize {
        self.normal[0].width
    }

    /// Height of the maps in pixels.
    pub fn height(&self) -> usize {
        self.normal[0].height
    }

    /// From a solve in memory (normals in the world frame as the solver gives them).
    pub fn from_result(
        result: &SolveResult,
        display_matrix: Option<&[[f64; 3]; 3]>,
        pixel_mm: Option<f64>,
        sheen: Option<SheenModel>,
    ) -> Self {
        let solved = result
            .status
            .iter()
            .map(|s| *s == PixelStatus::Solved)
            .collect();
        let sheen_pixels = result
            .fit
            .iter()
            .filter(|f| **f == crate::solve::PixelFit::Sheen)
            .count();
        SolvedMaps {
            normal: result.normal.clone(),
            albedo: to_display(result.albedo.clone(), display_matrix),
            solved,
            pixel_mm,
            scale_source: if pixel_mm.is_some() {
                "the rig".into()
            } else {
                "unknown".into()
            },
            sheen,
            sheen_pixels,
        }
    }
}

/// Reads `dir`'s report.json, normal.exr, albedo.exr and confidence.exr.
pub fn load(dir: &Path) -> Result<SolvedMaps> {
    let report_path = dir.join(REPORT_FILE);
    let text = std::fs::read_to_string(&report_path).map_err(|e| Error::io(&report_path, e))?;
    let report: Value = serde_json::from_str(&text)
        .map_err(|e| Error::config(&report_path, "", format!("not a solve report: {e}")))?;
    let convention: NormalConvention = crate::maps::report::normal_convention_of(&report);
    let pixel_mm = report
        .get("pixel_size_mm")
        .and_then(Value::as_f64)
        .filter(|v| *v > 0.0);
    let scale_source = match pixel_mm {
        Some(_) => "report.json pixel_size_mm (the rig's camera at the sample plane)".into(),
        None => "unknown: report.json has no pixel_size_mm (heights in pixel units)".into(),
    };
    let sheen = report
        .pointer("/options/robust/sheen")
        .and_then(|v| serde_json::from_value::<SheenModel>(v.clone()).ok());
    let display: Option<[[f64; 3]; 3]> = report
        .pointer("/decode/camera_to_srgb")
        .and_then(|v| serde_json::from_value(v.clone()).ok());

    let read = |name: &str, channels: &[&str]| -> Result<Vec<Plane>> {
        let path = dir.join(name);
        if !path.exists() {
            return Err(Error::Invalid(format!(
                "{}: missing; derive reads a solve's EXR maps (normal.exr, albedo.exr, confidence.exr), and this solve did not write them",
                path.display()
            )));
        }
        read_exr(&path, channels)
    };
    // The three files are independent: read them side by side (each is one core's work).
    let ((normal, albedo), confidence) = rayon::join(
        || {
            rayon::join(
                || read("normal.exr", &["R", "G", "B"]),
                || read("albedo.exr", &["R", "G", "B"]),
            )
        },
        || read("confidence.exr", &["status", "fit"]),
    );
    let (mut normal, albedo, confidence) = (normal?, albedo?, confidence?);
    let (w, h) = (normal[0].width, normal[0].height);
    if [&albedo[0], &confidence[0]]
        .iter()
        .any(|p| (p.width, p.height) != (w, h))
    {
        return Err(Error::Invalid(format!(
            "{}: normal.exr, albedo.exr and confidence.exr differ in size",
            dir.display()
        )));
    }
    if convention == NormalConvention::DirectX {
        normal[1].data.iter_mut().for_each(|v| *v = -*v);
    }
    let solved = confidence[0].data.iter().map(|&s| s == 0.0).collect();
    let sheen_pixels = confidence[1].data.iter().filter(|&&f| f == 2.0).count();
    let [nx, ny, nz]: [Plane; 3] = normal.try_into().expect("three channels were read");
    let albedo: [Plane; 3] = albedo.try_into().expect("three channels were read");
    Ok(SolvedMaps {
        normal: [nx, ny, nz],
        albedo: to_display(albedo, display.as_ref()),
        solved,
        pixel_mm,
        scale_source,
        sheen,
        sheen_pixels,
    })
}

fn to_display(mut rgb: [Plane; 3], m: Option<&[[f64; 3]; 3]>) -> [Plane; 3] {
    let Some(m) = m else { return rgb };
    for i in 0..rgb[0].len() {
        let v = [rgb[0].data[i], rgb[1].data[i], rgb[2].data[i]].map(f64::from);
        for (c, plane) in rgb.iter_mut().enumerate() {
            plane.data[i] = (m[c][0] * v[0] + m[c][1] * v[1] + m[c][2] * v[2]) as f32;
        }
    }
    rgb
}
