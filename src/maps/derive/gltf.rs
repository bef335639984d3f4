//! A glTF 2.0 material on a quad of the sample's physical size: `material.gltf`, its vertex
//! buffer `material.bin` and 8-bit PNG textures (`gltf_basecolor.png` sRGB,
//! `gltf_normal.png` in glTF's +Y-up convention whatever the engine export uses,
//! `gltf_metallic_roughness.png` with roughness in green and metallic 0 in blue). Where the
//! solve fitted the cloth lobe (seed 004 eq. 21-23), `KHR_materials_sheen` carries it:
//!
//! - `sheenColorFactor` = the lobe's Fresnel reflectance at normal incidence `f0` (eq. 23's
//!   F, which scales the velvet distribution as the sheen colour scales Charlie's);
//! - `sheenRoughnessFactor` = `alpha / sqrt(2)`: near grazing, where both lobes live, the
//!   inverted Gaussian's `exp(-cot^2 theta / alpha^2)` and Charlie's `sin^(1/a) theta`
//!   (`a` = sheenRoughness^2) both behave as `exp(-cos^2 theta / width)`, with widths
//!   `alpha^2` and `2 a`; equal widths give `a = alpha^2 / 2`.
//!
//! The document is assembled as JSON, parsed into gltf-json's typed `Root` and checked with
//! its validator before anything is written, so a schema slip fails here, not in an engine.

use std::path::Path;

use rayon::prelude::*;

use gltf_json::validation::Validate;
use serde::Serialize;
use serde_json::json;

use super::outputs::{albedo_srgb, normal_component, write_rgb, Texel};
use super::{fitted_sheen, SolvedMaps};
use crate::error::{Error, Result};
use crate::fsutil::write_atomic;
use crate::maps::NormalConvention;

/// The glTF document's file name in the output folder; it names `material.bin` and the PNG textures
/// beside it.
pub const GLTF_FILE: &str = "material.gltf";

/// The cloth lobe as KHR_materials_sheen parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SheenParams {
    /// `sheenColorFactor`: the lobe's normal-incidence Fresnel reflectance `f0` per RGB channel,
    /// clamped to 0..1.
    pub color: [f64; 3],
    /// `sheenRoughnessFactor`: the lobe width `alpha / sqrt(2)`, clamped to 0..1.
    pub roughness: f64,
}

impl SheenParams {
    /// Seed eq. 23's lobe (`f0`, inverted-Gaussian width `alpha`) in Charlie's terms.
    pub fn from_cloth(f0: [f64; 3], alpha: f64) -> Self {
        SheenParams {
            color: f0.map(|c| c.clamp(0.0, 1.0)),
            roughness: (alpha / std::f64::consts::SQRT_2).clamp(0.0, 1.0),
        }
    }
}

/// Writes the glTF material into `dir`; returns the sheen it carries, if any.
pub fn write(dir: &Path, maps: &SolvedMaps, roughness: f64) -> Result<Option<SheenParams>> {
    let pixel_mm = maps.pixel_mm.ok_or_else(|| {
        Error::Invalid(
            "the glTF quad needs the sample's physical size, but the solve has no scale \
             (report.json has no pixel_size_mm): pass --pixel-mm"
                .into(),
        )
    })?;
    let (w, h) = (maps.width(), maps.height());
    let size_m = [w as f64 * pixel_mm * 1e-3, h as f64 * pixel_mm * 1e-3];
    let sheen = fitted_sheen(maps).map(|m| SheenParams::from_cloth(m.f0, m.alpha));
    let buffer = quad_buffer(size_m);
    let document = document(size_m, buffer.len(), roughness, sheen);
    let text = checked(&document, &dir.join(GLTF_FILE))?;

    let normal =
        |i: usize, c: usize| normal_component(maps, NormalConvention::OpenGl, i, c) * 0.5 + 0.5;
    let albedo = |i: usize, c: usize| albedo_srgb(maps, i, c);
    let metallic_roughness = |_: usize, c: usize| if c == 1 { roughness as f32 } else { 0.0 };
    let textures: [(&str, &Texel); 3] = [
        ("gltf_basecolor.png", &albedo),
        ("gltf_normal.png", &normal),
        ("gltf_metallic_roughness.png", &metallic_roughness),
    ];
    textures
        .par_iter()
        .map(|(name, texel)| write_rgb(&dir.join(name), w, h, 8, texel))
        .collect::<Result<Vec<()>>>()?;
    write_atomic(&dir.join("material.bin"), &buffer)?;
    write_atomic(&dir.join(GLTF_FILE), text.as_bytes())?;
    Ok(sheen)
}

/// Parses `document` into gltf-json's `Root`, validates it, and serialises it back.
fn checked(document: &serde_json::Value, path: &Path) -> Result<String> {
    let root: gltf_json::Root = serde_json::from_value(document.clone())
        .map_err(|e| Error::image(path, format!("glTF document does not parse: {e}")))?;
    let mut problems = Vec::new();
    root.validate(&root, gltf_json::Path::new, &mut |where_, what| {
        problems.push(format!("{}: {what}", where_()))
    });
    if !problems.is_empty() {
        return Err(Error::image(
            path,
            format!("invalid glTF: {}", problems.join("; ")),
        ));
    }
    root.to_string_pretty()
        .map_err(|e| Error::image(path, format!("glTF does not serialise: {e}")))
}

/// Four vertices of a quad lying in glTF's ground plane (x right, -z away: image columns
/// along +x, the image's top at -z), facing +y, centred on the origin.
const VERTICES: usize = 4;

/// Positions, normals, tangents, UVs (f32) and six u16 indices, in that order.
fn quad_buffer(size_m: [f64; 2]) -> Vec<u8> {
    let (hx, hz) = ((size_m[0] / 2.0) as f32, (size_m[1] / 2.0) as f32);
    // Top-left, top-right, bottom-right, bottom-left of the image.
    let corners = [
        (-hx, -hz, 0.0, 0.0),
        (hx, -hz, 1.0, 0.0),
        (hx, hz, 1.0, 1.0),
        (-hx, hz, 0.0, 1.0),
    ];
    let mut b: Vec<u8> = Vec::new();
    let mut put = |v: f32| b.extend_from_slice(&v.to_le_bytes());
    for &(x, z, _, _) in &corners {
        [x, 0.0, z].into_iter().for_each(&mut put);
    }
    for _ in 0..VERTICES {
        [0.0, 1.0, 0.0].into_iter().for_each(&mut put);
    }
    // Tangent +x (u grows to the right); w = 1: bitangent = normal x tangent = -z, the
    // image's up, as glTF's +Y-up normal textures expect.
    for _ in 0..VERTICES {
        [1.0, 0.0, 0.0, 1.0].into_iter().for_each(&mut put);
    }
    for &(_, _, u, v) in &corners {
        [u, v].into_iter().for_each(&mut put);
    }
    // Counter-clockwise seen from +y.
    for i in [0u16, 3, 2, 0, 2, 1] {
        b.extend_from_slice(&i.to_le_bytes());
    }
    b
}

fn document(
    size_m: [f64; 2],
    buffer_len: usize,
    roughness: f64,
    sheen: Option<SheenParams>,
) -> serde_json::Value {
    let (hx, hz) = (size_m[0] / 2.0, size_m[1] / 2.0);
    let n = VERTICES;
    let offsets = [0, 12 * n, 24 * n, 40 * n, 48 * n];
    let view = |offset: usize, len: usize, target: u32| json!({"buffer": 0, "byteOffset": offset, "byteLength": len, "target": target});
    let texture = |image: usize| json!({"sampler": 0, "source": image});
    let mut material = json!({
        "name": "psscan scan",
        "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0},
            "metallicRoughnessTexture": {"index": 2},
            "metallicFactor": 1.0,
            "roughnessFactor": 1.0
        },
        "normalTexture": {"index": 1}
    });
    let mut extensions_used = vec![];
    if let Some(s) = sheen {
        material["extensions"] = json!({"KHR_materials_sheen": {
            "sheenColorFactor": s.color,
            "sheenRoughnessFactor": s.roughness
        }});
        extensions_used.push("KHR_materials_sheen");
    }
    let _ = roughness;
    let mut doc = json!({
        "asset": {"version": "2.0", "generator": concat!("psscan ", env!("CARGO_PKG_VERSION"))},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "sample"}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2, "TEXCOORD_0": 3},
            "indices": 4,
            "material": 0
        }]}],
        "materials": [material],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3",
             "min": [-hx, 0.0, -hz], "max": [hx, 0.0, hz]},
            {"bufferView": 1, "componentType": 5126, "count": n, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": n, "type": "VEC4"},
            {"bufferView": 3, "componentType": 5126, "count": n, "type": "VEC2"},
            {"bufferView": 4, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ],
        "bufferViews": [
            view(offsets[0], 12 * n, 34962),
            view(offsets[1], 12 * n, 34962),
            view(offsets[2], 16 * n, 34962),
            view(offsets[3], 8 * n, 34962),
            view(offsets[4], 12, 34963)
        ],
        "buffers": [{"uri": "material.bin", "byteLength": buffer_len}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}],
        "images": [
            {"uri": "gltf_basecolor.png"},
            {"uri": "gltf_normal.png"},
            {"uri": "gltf_metallic_roughness.png"}
        ],
        "textures": [texture(0), texture(1), texture(2)]
    });
    if !extensions_used.is_empty() {
        doc["extensionsUsed"] = json!(extensions_used);
    }
    doc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cloth_lobe_maps_to_charlie_widths() {
        let s = SheenParams::from_cloth([0.35, 0.2, 1.4], 0.4);
        assert_eq!(s.color, [0.35, 0.2, 1.0]);
        // a = alpha^2 / 2 and sheenRoughness = sqrt(a).
        assert!((s.roughness.powi(2) - 0.4f64.powi(2) / 2.0).abs() < 1e-12);
    }

    #[test]
    fn the_document_passes_gltf_json_validation_with_and_without_sheen() {
        for sheen in [None, Some(SheenParams::from_cloth([0.3; 3], 0.5))] {
            let buffer = quad_buffer([0.1, 0.05]);
            assert_eq!(buffer.len(), 4 * (12 + 12 + 16 + 8) + 12);
            let doc = document([0.1, 0.05], buffer.len(), 0.5, sheen);
            let text = checked(&doc, Path::new("m.gltf")).unwrap();
            assert_eq!(text.contains("KHR_materials_sheen"), sheen.is_some());
        }
    }
}
