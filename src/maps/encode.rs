//! Encodings of the solved maps for game engines: normal maps in OpenGL (+Y up) or DirectX
//! (+Y down) convention stored as `n * 0.5 + 0.5`, and albedo in sRGB for PNG (the curve and
//! its quantisers are in `srgb`).

use std::borrow::Cow;

use serde::{Deserialize, Serialize};

use rayon::prelude::*;

use crate::io::Rgb16Row;
use crate::maps::srgb::{srgb16, srgb16_direct};
use crate::math::round_non_negative;
use crate::plane::Plane;
use crate::solve::{PixelStatus, SolveResult};

/// Which way the stored normal map's Y axis points, as engines disagree on it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum NormalConvention {
    /// +Y toward the top of the image (OpenGL, Blender, Unity).
    #[default]
    OpenGl,
    /// +Y toward the bottom of the image (DirectX, Unreal).
    DirectX,
}

impl NormalConvention {
    /// The stored Y component for a world-frame (+Y up) normal's `y`.
    #[inline]
    pub fn y(self, y: f32) -> f32 {
        match self {
            NormalConvention::OpenGl => y,
            NormalConvention::DirectX => -y,
        }
    }
}

/// The normal map as three planes in the requested convention (unsolved pixels hold the
/// flat normal the solve leaves there): the solve's own planes, borrowed, except Y in the
/// DirectX convention, which is negated into a new plane.
pub fn normal_planes(result: &SolveResult, convention: NormalConvention) -> [Cow<'_, Plane>; 3] {
    let [nx, ny, nz] = &result.normal;
    let y = match convention {
        NormalConvention::OpenGl => Cow::Borrowed(ny),
        NormalConvention::DirectX => {
            let mut y = ny.clone();
            for v in &mut y.data {
                *v = convention.y(*v);
            }
            Cow::Owned(y)
        }
    };
    [Cow::Borrowed(nx), y, Cow::Borrowed(nz)]
}

/// `[-1, 1]` to 16-bit unsigned: `round((v * 0.5 + 0.5) * 65535)`.
#[inline]
pub fn unit_to_u16(v: f32) -> u16 {
    round_non_negative((v.clamp(-1.0, 1.0) * 0.5 + 0.5) * 65535.0) as u16
}

/// 16-bit value back to `[-1, 1]`.
#[inline]
pub fn u16_to_unit(v: u16) -> f32 {
    v as f32 / 65535.0 * 2.0 - 1.0
}

/// Row `y` of the normal map as interleaved 16-bit RGB, for `io::encode_png16_rows_into`.
pub fn normal_rows16(
    result: &SolveResult,
    convention: NormalConvention,
) -> impl Fn(usize, &mut [u16]) + Sync + '_ {
    let [nx, ny, nz] = &result.normal;
    let width = result.width;
    move |y, row| {
        let span = y * width..(y + 1) * width;
        // Row slices zipped, not a pixel index: the loop has no bounds checks and vectorises.
        let (x, yy, z) = (
            &nx.data[span.clone()],
            &ny.data[span.clone()],
            &nz.data[span],
        );
        for (((px, &x), &y), &z) in row.chunks_exact_mut(3).zip(x).zip(yy).zip(z) {
            px[0] = unit_to_u16(x);
            px[1] = unit_to_u16(convention.y(y));
            px[2] = unit_to_u16(z);
        }
    }
}

/// Row `y` of the albedo as interleaved 16-bit sRGB, through `camera_to_srgb` when the
/// camera's primaries are not sRGB's; unsolved pixels are black. One pass, pixel by pixel:
/// the display planes are not built first (193 MB of fresh memory at 16 MP).
pub fn albedo_rows16<'a>(
    result: &'a SolveResult,
    camera_to_srgb: Option<&'a [[f64; 3]; 3]>,
) -> Box<Rgb16Row<'a>> {
    // `round(linear_to_srgb(v) * 65535)` from the table (48 M `powf` at 16 MP otherwise),
    // the same codes; the table takes about 20 ms to build, more than a `powf` per value
    // costs under about 2 MP.
    if result.albedo[0].len() >= SRGB16_TABLE_MIN_PIXELS {
        let table = srgb16();
        Box::new(albedo_rows16_with(result, camera_to_srgb, |v| {
            table.code(v)
        }))
    } else {
        Box::new(albedo_rows16_with(result, camera_to_srgb, srgb16_direct))
    }
}

/// Pixels from which [`albedo_rows16`] quantises through the table.
const SRGB16_TABLE_MIN_PIXELS: usize = 2_000_000;

/// [`albedo_rows16`] with each display value quantised by `code`.
fn albedo_rows16_with<'a>(
    result: &'a SolveResult,
    camera_to_srgb: Option<&'a [[f64; 3]; 3]>,
    code: impl Fn(f32) -> u16 + Sync + 'a,
) -> impl Fn(usize, &mut [u16]) + Sync + 'a {
    let width = result.width;
    move |y, row| {
        // A run of pixels at a time, through the colour matrix channel by channel, then
        // quantised and interleaved (`code(0.0)` is 0: unsolved pixels are black).
        let mut display = [[0f32; RUN]; 3];
        for (k, pixels) in row.chunks_mut(3 * RUN).enumerate() {
            let n = pixels.len() / 3;
            let [r, g, b] = &mut display;
            let (r, g, b) = (&mut r[..n], &mut g[..n], &mut b[..n]);
            display_albedo_run(result, camera_to_srgb, y * width + k * RUN, [r, g, b]);
            for (px, ((&r, &g), &b)) in pixels.chunks_exact_mut(3).zip(r.iter().zip(&*g).zip(&*b)) {
                px.copy_from_slice(&[code(r), code(g), code(b)]);
            }
        }
    }
}

/// Pixels per run of [`display_albedo_run`] in a PNG row.
const RUN: usize = 256;

/// The albedo of the pixels from `start` on, as many as `out`'s rows hold (one channel per
/// row), through `camera_to_srgb` when given (not clamped); 0 where unsolved. In loops over
/// slices that the compiler vectorises (pixel by pixel, the status test and the matrix were a
/// call per pixel: a tenth of the 16 MP maps' encode time).
pub fn display_albedo_run(
    result: &SolveResult,
    camera_to_srgb: Option<&[[f64; 3]; 3]>,
    start: usize,
    [out_r, out_g, out_b]: [&mut [f32]; 3],
) {
    let n = out_r.len();
    let span = start..start + n;
    let status = &result.status[span.clone()];
    let [r, g, b] = result.albedo.each_ref().map(|p| &p.data[span.clone()]);
    let pixels = out_r
        .iter_mut()
        .zip(out_g.iter_mut())
        .zip(out_b.iter_mut())
        .zip(status)
        .zip(r.iter().zip(g).zip(b));
    for ((((out_r, out_g), out_b), &status), ((&r, &g), &b)) in pixels {
        let camera = [r, g, b];
        let display = camera_to_srgb.map_or(camera, |m| display_pixel(m, camera));
        let solved = status == PixelStatus::Solved;
        *out_r = if solved { display[0] } else { 0.0 };
        *out_g = if solved { display[1] } else { 0.0 };
        *out_b = if solved { display[2] } else { 0.0 };
    }
}

/// One pixel through a 3x3 colour matrix (rows: output channels), in double precision.
#[inline]
fn display_pixel(m: &[[f64; 3]; 3], rgb: [f32; 3]) -> [f32; 3] {
    let v = rgb.map(f64::from);
    std::array::from_fn(|c| (m[c][0] * v[0] + m[c][1] * v[1] + m[c][2] * v[2]) as f32)
}

/// The three planes through a 3x3 colour matrix (rows: output channels).
pub fn to_display(rgb: &[Plane; 3], m: &[[f64; 3]; 3]) -> [Plane; 3] {
    let mut out = [rgb[0].clone(), rgb[1].clone(), rgb[2].clone()];
    let [r, g, b] = &mut out;
    r.data
        .par_iter_mut()
        .zip(g.data.par_iter_mut())
        .zip(b.data.par_iter_mut())
        .for_each(|((r, g), b)| {
            [*r, *g, *b] = display_pixel(m, [*r, *g, *b]);
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::maps::srgb::{linear_to_srgb, srgb_to_linear};

    #[test]
    fn unit_encoding_round_trips_within_half_a_step() {
        for &v in &[-1.0f32, -0.5, 0.0, 0.123, 0.999, 1.0] {
            assert!((u16_to_unit(unit_to_u16(v)) - v).abs() <= 1.0 / 65535.0);
        }
        assert_eq!(unit_to_u16(0.0), 32768);
        assert_eq!(unit_to_u16(1.0), 65535);
        assert_eq!(unit_to_u16(-1.0), 0);
    }

    #[test]
    fn srgb_round_trip_and_known_points() {
        for i in 0..=100 {
            let v = i as f32 / 100.0;
            assert!((srgb_to_linear(linear_to_srgb(v)) - v).abs() < 1e-5);
        }
        assert!((linear_to_srgb(0.18) - 0.4614).abs() < 1e-3);
    }

    /// The one-pass albedo encoding against the two passes it replaced: display planes
    /// first, then each sample through the sRGB curve, then unsolved pixels zeroed.
    #[test]
    fn albedo_rows16_are_the_display_planes_encoded_with_unsolved_pixels_black() {
        // Rows over two runs of `display_albedo_run` long, the last one partial.
        let (w, h) = (2 * RUN + 37, 3);
        let mut result = SolveResult::new(w, h);
        for i in 0..w * h {
            for (c, plane) in result.albedo.iter_mut().enumerate() {
                plane.data[i] = (i * 7 + c * 13) as f32 / (w * h) as f32 * 1.3 - 0.1;
            }
            if i % 5 != 0 {
                result.status[i] = PixelStatus::Solved;
            }
        }
        result.albedo[1].data[3] = f32::NAN;
        let matrix = [[1.6, -0.4, -0.2], [-0.2, 1.5, -0.3], [0.0, -0.5, 1.5]];
        for m in [None, Some(&matrix)] {
            let planes = m.map_or(result.albedo.clone(), |m| to_display(&result.albedo, m));
            let mut expected: Vec<u16> = (0..w * h)
                .flat_map(|i| planes.each_ref().map(|p| p.data[i]))
                .map(|v| round_non_negative(linear_to_srgb(v) * 65535.0) as u16)
                .collect();
            for (px, s) in expected.chunks_mut(3).zip(&result.status) {
                if *s != PixelStatus::Solved {
                    px.fill(0);
                }
            }
            assert_eq!(
                rows(w, h, &albedo_rows16(&result, m)),
                expected,
                "matrix {m:?}"
            );
            // The table path, which large maps take, gives the same codes.
            let table = albedo_rows16_with(&result, m, |v| srgb16().code(v));
            assert_eq!(rows(w, h, &table), expected, "matrix {m:?}, table");
        }
    }

    /// A `w x h` image's rows from `fill`, interleaved whole.
    fn rows(w: usize, h: usize, fill: &dyn Fn(usize, &mut [u16])) -> Vec<u16> {
        let mut out = vec![0; w * h * 3];
        for (y, row) in out.chunks_exact_mut(w * 3).enumerate() {
            fill(y, row);
        }
        out
    }

    #[test]
    fn normal_rows16_store_each_component_in_the_convention() {
        let (w, h) = (3, 2);
        let mut result = SolveResult::new(w, h);
        for i in 0..w * h {
            result.normal[0].data[i] = i as f32 / 10.0;
            result.normal[1].data[i] = -(i as f32) / 20.0;
            result.normal[2].data[i] = 1.0 - i as f32 / 30.0;
        }
        for convention in [NormalConvention::OpenGl, NormalConvention::DirectX] {
            let expected: Vec<u16> = (0..w * h)
                .flat_map(|i| {
                    let n = result.normal.each_ref().map(|p| p.data[i]);
                    [n[0], convention.y(n[1]), n[2]].map(unit_to_u16)
                })
                .collect();
            let got = rows(w, h, &normal_rows16(&result, convention));
            assert_eq!(got, expected, "{convention:?}");
        }
    }

    #[test]
    fn directx_flips_only_y() {
        assert_eq!(NormalConvention::OpenGl.y(0.3), 0.3);
        assert_eq!(NormalConvention::DirectX.y(0.3), -0.3);
    }
}
