//! DDS textures with full mip chains, block-compressed through image_dds (ISPC texture
//! compressor): `normal.dds` BC5 (X in red, Y in green, `n * 0.5 + 0.5`; the shader
//! reconstructs Z) from the renormalised normal mips, `albedo.dds` BC7 sRGB from box-filtered
//! linear albedo, and `roughness.dds` BC4 holding the antialiased roughness of each level.

use std::path::Path;

use image_dds::{ImageFormat, Mipmaps, Quality, Surface, SurfaceRgba8};
use rayon::prelude::*;

use super::mips::MipChain;
use super::SolvedMaps;
use crate::error::{Error, Result};
use crate::fsutil::write_atomic;
use crate::maps::srgb::linear_to_srgb;
use crate::maps::NormalConvention;
use crate::plane::Plane;

// intel_tex_2 (image_dds's encoder) ships prebuilt kernels with C++ objects that need the
// C++ runtime's exception personality, and does not link it itself.
#[link(name = "stdc++")]
extern "C" {}

/// Writes the DDS files; `roughness` (one plane per level) adds `roughness.dds`.
pub fn write_all(
    dir: &Path,
    chain: &MipChain,
    maps: &SolvedMaps,
    convention: NormalConvention,
    roughness: Option<&[Plane]>,
) -> Result<()> {
    let (w, h) = (maps.width() as u32, maps.height() as u32);
    let normal = || {
        let levels: Vec<Vec<[u8; 4]>> = chain
            .levels
            .iter()
            .map(|level| {
                let [x, y, _] = level.normals();
                x.data
                    .par_iter()
                    .zip(&y.data)
                    .map(|(&x, &y)| {
                        [
                            unorm8(x * 0.5 + 0.5),
                            unorm8(convention.y(y) * 0.5 + 0.5),
                            0,
                            255,
                        ]
                    })
                    .collect()
            })
            .collect();
        encode(
            &dir.join("normal.dds"),
            w,
            h,
            levels,
            ImageFormat::BC5RgUnorm,
        )
    };
    let albedo = || {
        let mut linear = masked_albedo(maps);
        let mut levels = Vec::with_capacity(chain.levels.len());
        for _ in 0..chain.levels.len() {
            levels.push(
                (0..linear[0].len())
                    .into_par_iter()
                    .map(|i| {
                        let c = |k: usize| unorm8(linear_to_srgb(linear[k].data[i]));
                        [c(0), c(1), c(2), 255]
                    })
                    .collect(),
            );
            linear = linear.map(|p| halve_plane(&p));
        }
        encode(
            &dir.join("albedo.dds"),
            w,
            h,
            levels,
            ImageFormat::BC7RgbaUnormSrgb,
        )
    };
    let rough = || -> Result<()> {
        match roughness {
            Some(levels) => write_roughness(dir, levels),
            None => Ok(()),
        }
    };
    let ((n, a), r) = rayon::join(|| rayon::join(normal, albedo), rough);
    n?;
    a?;
    r
}

/// `roughness.dds`: BC4, one level per plane (full resolution first).
pub fn write_roughness(dir: &Path, levels: &[Plane]) -> Result<()> {
    let (w, h) = (levels[0].width as u32, levels[0].height as u32);
    let levels = levels
        .iter()
        .map(|p| p.data.iter().map(|&r| [unorm8(r), 0, 0, 255]).collect())
        .collect();
    encode(
        &dir.join("roughness.dds"),
        w,
        h,
        levels,
        ImageFormat::BC4RUnorm,
    )
}

fn unorm8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Linear albedo with unsolved pixels black.
fn masked_albedo(maps: &SolvedMaps) -> [Plane; 3] {
    maps.albedo.clone().map(|mut p| {
        for (v, s) in p.data.iter_mut().zip(&maps.solved) {
            if !s {
                *v = 0.0;
            }
        }
        p
    })
}

/// 2 x 2 box average down to `max(1, size / 2)`, the same footprints as the normal mips.
fn halve_plane(p: &Plane) -> Plane {
    super::mips::halve(p)
}

/// Rows per strip handed to one encoder call: a multiple of the 4-row block height, so the
/// strips' blocks concatenate into the level's blocks in the file's row-of-blocks order.
const STRIP_ROWS: usize = 256;

/// Encodes a surface whose levels the caller made (so the normals are renormalised and the
/// roughness antialiased per level, which a generic mip generator would not do).
///
/// image_dds encodes on one thread; each 4x4 block is compressed on its own, so every level is
/// cut into strips of whole block rows that encode in parallel and are concatenated, giving
/// the same bytes as one call.
fn encode(
    path: &Path,
    width: u32,
    height: u32,
    levels: Vec<Vec<[u8; 4]>>,
    format: ImageFormat,
) -> Result<()> {
    let failed =
        |e: &dyn std::fmt::Display| Error::image(path, format!("DDS encoding failed: {e}"));
    let mipmaps = levels.len() as u32;
    let mut data = Vec::new();
    for (level, texels) in levels.iter().enumerate() {
        let w = (width >> level).max(1) as usize;
        let h = (height >> level).max(1) as usize;
        let strips: Vec<Vec<u8>> = texels
            .par_chunks(w * STRIP_ROWS)
            .map(|strip| encode_strip(strip, w, format))
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| failed(&e))?;
        debug_assert_eq!(texels.len(), w * h);
        data.extend(strips.into_iter().flatten());
    }
    let surface = Surface {
        width,
        height,
        depth: 1,
        layers: 1,
        mipmaps,
        image_format: format,
        data,
    };
    let dds = surface.to_dds().map_err(|e| failed(&e))?;
    let mut bytes = Vec::new();
    dds.write(&mut bytes)
        .map_err(|e| Error::image(path, format!("DDS writing failed: {e}")))?;
    write_atomic(path, &bytes)
}

/// The blocks of `texels` (`width` wide, whole rows), one level without mips.
fn encode_strip(
    texels: &[[u8; 4]],
    width: usize,
    format: ImageFormat,
) -> std::result::Result<Vec<u8>, image_dds::error::SurfaceError> {
    // Whole blocks before any encoder sees them: a level smaller than a block (the last
    // mips) or a strip of odd size would otherwise be padded with black by the encoder, and
    // a block's endpoints would span that black as well as its texels.
    let (padded, pw, ph) = pad_to_blocks(texels, width);
    if format == ImageFormat::BC7RgbaUnormSrgb {
        return Ok(encode_bc7_opaque(&padded, pw, ph));
    }
    let bytes: Vec<u8> = padded.iter().flatten().copied().collect();
    let strip = SurfaceRgba8 {
        width: pw as u32,
        height: ph as u32,
        depth: 1,
        layers: 1,
        mipmaps: 1,
        data: bytes.as_slice(),
    };
    Ok(strip
        .encode(format, Quality::Normal, Mipmaps::Disabled)?
        .data)
}

/// `texels` (`width` wide, whole rows) padded to whole 4 x 4 blocks by repeating the last
/// column and row: the padding then costs a block's palette nothing. Returns the padded
/// texels and their width and height.
fn pad_to_blocks(texels: &[[u8; 4]], width: usize) -> (Vec<[u8; 4]>, usize, usize) {
    let height = texels.len() / width;
    let (pw, ph) = (width.next_multiple_of(4), height.next_multiple_of(4));
    let padded = (0..ph)
        .flat_map(|y| {
            let row = &texels[y.min(height - 1) * width..][..width];
            (0..pw).map(move |x| row[x.min(width - 1)])
        })
        .collect();
    (padded, pw, ph)
}

/// BC7 with the ISPC encoder's opaque "very fast" settings: the albedo has no alpha, and the
/// alpha-capable settings image_dds uses spend their effort on a constant channel. `texels`
/// are whole blocks, `width x height`.
fn encode_bc7_opaque(texels: &[[u8; 4]], width: usize, height: usize) -> Vec<u8> {
    let bytes: Vec<u8> = texels.iter().flatten().copied().collect();
    let surface = intel_tex_2::RgbaSurface {
        data: &bytes,
        width: width as u32,
        height: height as u32,
        stride: (width * 4) as u32,
    };
    intel_tex_2::bc7::compress_blocks(&intel_tex_2::bc7::opaque_very_fast_settings(), &surface)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A level smaller than a block (a 2 x 2 mip of a curved object: four far-apart normals)
    /// keeps BC5's precision: the block's padding repeats its texels, so its endpoints span
    /// only their codes. Padded with black instead, the palette also spans code 0, and its
    /// steps grow from (180 - 60) / 7 to 180 / 7 codes.
    #[test]
    fn a_level_smaller_than_a_block_is_padded_with_its_own_texels() {
        let texels = [
            [60, 180, 0, 255],
            [180, 60, 0, 255],
            [90, 120, 0, 255],
            [150, 100, 0, 255],
        ];
        let blocks = encode_strip(&texels, 2, ImageFormat::BC5RgUnorm).unwrap();
        assert_eq!(blocks.len(), 16, "one BC5 block");
        let surface = Surface {
            width: 4,
            height: 4,
            depth: 1,
            layers: 1,
            mipmaps: 1,
            image_format: ImageFormat::BC5RgUnorm,
            data: blocks,
        };
        let decoded = surface.decode_rgba8().unwrap().data;
        // A palette of 8 levels over 60..180: half a step is 120 / 14 < 9 codes, plus one
        // for the endpoints' rounding.
        for (i, t) in [(0, 0), (1, 1), (4, 2), (5, 3)] {
            for c in 0..2 {
                let got = decoded[i * 4 + c] as i32;
                let want = texels[t][c] as i32;
                assert!(
                    (got - want).abs() <= 10,
                    "texel {t} channel {c}: {got} vs {want}"
                );
            }
        }
    }
}
