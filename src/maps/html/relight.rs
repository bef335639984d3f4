//! The live relight's shading, on the CPU: the same arithmetic, in `f32` and in the same order,
//! as the page's fragment shader (`relight.frag`), on the same 8-bit textures, so the WebGL
//! canvas and `psscan report --render-light` can be compared pixel for pixel.
//!
//! Radiance under a distant light of irradiance `pi * exposure` (a white Lambertian surface
//! facing the light renders as 1.0), viewed from straight above (`v = (0, 0, 1)`):
//! - `Ggx`: Lambertian albedo plus the GGX specular of seed 004 Appendix A (Schlick Fresnel
//!   with F0 = 0.04, Walter's GGX distribution and its Smith visibility term);
//! - `Cloth`: seed 004 eq. 23, `(1 - F) albedo / pi + F D_velvet / (4 (nl + nv - nl nv))`, with
//!   the velvet distribution of eq. 22 (amplitude A = 4).

use image::{Rgb, RgbImage};
use serde::Serialize;

use crate::error::{Error, Result};
use crate::maps::srgb::{self, srgb_to_linear};

/// Which BRDF shades the relight.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Brdf {
    /// Lambertian albedo plus GGX specular with Schlick Fresnel at F0 = 0.04.
    Ggx,
    /// Seed 004's cloth BRDF: Fresnel-weighted Lambertian plus the velvet lobe.
    Cloth,
}

impl Brdf {
    /// Parses `ggx` or `cloth`.
    pub fn parse(text: &str) -> Result<Brdf> {
        match text {
            "ggx" => Ok(Brdf::Ggx),
            "cloth" => Ok(Brdf::Cloth),
            other => Err(Error::Unsupported(format!(
                "unknown BRDF \"{other}\": use ggx or cloth"
            ))),
        }
    }
}

/// One relight: a distant light, the BRDF, a uniform roughness (the solve derives no
/// roughness map) and an exposure.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct RelightParams {
    /// Direction toward the light, world frame (normalised before use).
    pub light: [f32; 3],
    /// Which BRDF shades the surface.
    pub brdf: Brdf,
    /// GGX `m` / velvet `alpha`.
    pub roughness: f32,
    /// Scale on the light's irradiance: at 1 a white Lambertian surface facing the light renders as
    /// 1.0.
    pub exposure: f32,
}

impl Default for RelightParams {
    fn default() -> Self {
        RelightParams {
            light: [0.3, 0.3, 0.9],
            brdf: Brdf::Ggx,
            roughness: 0.5,
            exposure: 1.0,
        }
    }
}

/// What the canvas shows where no normal was solved (8-bit, every channel).
pub const BACKGROUND: u8 = 40;

/// The relight's inputs at display size: sRGB-encoded 8-bit albedo and 8-bit normals stored
/// `n * 0.5 + 0.5` in the OpenGL convention, black (z < 0) where unsolved.
#[derive(Clone, Debug)]
pub struct RelightTextures {
    /// The albedo at display size, sRGB-encoded, 8 bits per channel.
    pub albedo: RgbImage,
    /// The normals at display size, `n * 0.5 + 0.5` in 8 bits, OpenGL convention; black where
    /// unsolved.
    pub normal: RgbImage,
}

const PI: f32 = std::f32::consts::PI;
const F0: f32 = 0.04;
const VELVET_AMPLITUDE: f32 = 4.0;

/// `(srgb::linear_to_srgb(v) * 255).round()` as a byte, the same byte for every `v`, from a table
/// instead of a `powf` ([`srgb::srgb8`]): the loupe converts every sample of a 16 MP albedo
/// (48 M of them).
#[inline]
pub fn linear_to_srgb8(v: f32) -> u8 {
    srgb::srgb8().code(v) as u8
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn normalize(a: [f32; 3]) -> [f32; 3] {
    let len = dot(a, a).sqrt();
    [a[0] / len, a[1] / len, a[2] / len]
}

/// Seed 004 Appendix A: `GGX_Specular` with a scalar specular albedo.
fn ggx_specular(m: f32, nl: f32, nh: f32, nv: f32, fresnel: f32) -> f32 {
    let m2 = m * m;
    let t = nh * nh * (m2 - 1.0) + 1.0;
    let d = m2 / (PI * t * t);
    let v1 = |x: f32| 1.0 / (x + (m2 + (1.0 - m2) * x * x).sqrt());
    d * fresnel * v1(nl) * v1(nv)
}

/// Seed 004 eq. 22, with `cot^2 = nh^2 / (1 - nh^2)`; 0 exponent term at the pole.
fn velvet_distribution(alpha: f32, nh: f32) -> f32 {
    let a2 = alpha * alpha;
    let sin2 = 1.0 - nh * nh;
    let lobe = if sin2 > 1e-4 {
        VELVET_AMPLITUDE * (-(nh * nh / sin2) / a2).exp() / (sin2 * sin2)
    } else {
        0.0
    };
    (1.0 + lobe) / (PI * (1.0 + VELVET_AMPLITUDE * a2))
}

/// Outgoing linear radiance of one channel with linear albedo `albedo`, given the cosines.
fn shade(albedo: f32, nl: f32, nh: f32, nv: f32, lh: f32, p: &RelightParams) -> f32 {
    let fresnel = F0 + (1.0 - F0) * (1.0 - lh).powf(5.0);
    let brdf = match p.brdf {
        Brdf::Ggx => albedo / PI + ggx_specular(p.roughness, nl, nh, nv, fresnel),
        Brdf::Cloth => {
            (1.0 - fresnel) * albedo / PI
                + fresnel * velvet_distribution(p.roughness, nh) / (4.0 * (nl + nv - nl * nv))
        }
    };
    PI * p.exposure * brdf * nl
}

/// One pixel: 8-bit albedo and normal texels in, 8-bit sRGB out.
pub fn shade_texel(albedo: [u8; 3], normal: [u8; 3], p: &RelightParams) -> [u8; 3] {
    let raw = normal.map(|v| v as f32 / 255.0 * 2.0 - 1.0);
    if raw[2] <= 0.01 {
        return [BACKGROUND; 3];
    }
    let n = normalize(raw);
    let l = normalize(p.light);
    let v = [0.0, 0.0, 1.0];
    let h = normalize([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
    let nl = dot(n, l).max(0.0);
    let nv = dot(n, v).max(1e-4);
    let nh = dot(n, h).clamp(0.0, 1.0);
    let lh = dot(l, h).clamp(0.0, 1.0);
    albedo.map(|a| {
        let value = if nl > 0.0 {
            shade(srgb_to_linear(a as f32 / 255.0), nl, nh, nv, lh, p)
        } else {
            0.0
        };
        linear_to_srgb8(value)
    })
}

/// Renders the relight of `textures` under `params` (the CPU twin of the page's canvas).
pub fn render(textures: &RelightTextures, params: &RelightParams) -> RgbImage {
    let (w, h) = textures.albedo.dimensions();
    RgbImage::from_fn(w, h, |x, y| {
        Rgb(shade_texel(
            textures.albedo.get_pixel(x, y).0,
            textures.normal.get_pixel(x, y).0,
            params,
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::maps::srgb::linear_to_srgb;

    fn flat_white() -> ([u8; 3], [u8; 3]) {
        ([255; 3], [128, 128, 255])
    }

    #[test]
    fn white_lambertian_facing_the_light_is_white_and_follows_the_cosine() {
        // Cloth at the smallest Fresnel (head-on: F = F0) and GGX both add specular; check the
        // diffuse part alone through the cosine law on a grazing light where the GGX lobe at
        // roughness 0.05 is negligible.
        let (a, n) = flat_white();
        let p = RelightParams {
            light: [(60f32).to_radians().sin(), 0.0, (60f32).to_radians().cos()],
            roughness: 0.05,
            ..RelightParams::default()
        };
        let px = shade_texel(a, n, &p);
        let expected = (linear_to_srgb(0.5) * 255.0).round() as u8;
        assert!(
            (px[0] as i32 - expected as i32).abs() <= 1,
            "{px:?} vs {expected}"
        );
    }

    #[test]
    fn light_below_the_horizon_gives_black_and_unsolved_gives_background() {
        let (a, n) = flat_white();
        let p = RelightParams {
            light: [1.0, 0.0, -0.2],
            ..RelightParams::default()
        };
        assert_eq!(shade_texel(a, n, &p), [0; 3]);
        assert_eq!(shade_texel(a, [0, 0, 0], &p), [BACKGROUND; 3]);
    }

    #[test]
    fn ggx_matches_the_textbook_form_of_eq_1() {
        // Appendix A's visibility form equals F G D / (4 nl nv) with Smith G1 of eq. 3.
        let (m, nl, nv, nh, f) = (0.4f32, 0.7f32, 0.9f32, 0.95f32, 0.1f32);
        let a2 = m * m;
        let d = a2 / (PI * (nh * nh * (a2 - 1.0) + 1.0).powi(2));
        let g1 = |x: f32| 2.0 / (1.0 + (1.0 + a2 * (1.0 - x * x) / (x * x)).sqrt());
        let textbook = f * g1(nl) * g1(nv) * d / (4.0 * nl * nv);
        let ours = ggx_specular(m, nl, nh, nv, f);
        assert!(
            (ours - textbook).abs() < 1e-5 * textbook,
            "{ours} {textbook}"
        );
    }

    #[test]
    fn velvet_distribution_is_normalised_over_the_hemisphere() {
        // eq. 22 normalises the projected distribution: integral of D cos(theta) d omega = 1.
        let alpha = 0.5f32;
        let steps = 20000;
        let mut sum = 0.0f64;
        for i in 0..steps {
            let theta = (i as f64 + 0.5) / steps as f64 * std::f64::consts::FRAC_PI_2;
            let d = velvet_distribution(alpha, theta.cos() as f32) as f64;
            sum += d * theta.cos() * theta.sin() * 2.0 * std::f64::consts::PI;
        }
        sum *= std::f64::consts::FRAC_PI_2 / steps as f64;
        assert!((sum - 1.0).abs() < 0.01, "{sum}");
    }
}
