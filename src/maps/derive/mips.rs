//! Mip chains of the normal map and, per level, the roughness that keeps the filtered
//! highlight: each level holds the box average of the full-resolution normals under its
//! texel (not renormalised, so its length says how spread they are) and the averages of
//! `nx^2` and `ny^2` (their variance). From these, three choices of filtered GGX roughness:
//!
//! - `vmf`: seed 004's `ComputeRoughness`: a von Mises-Fisher lobe fitted to the average
//!   normal's length `r`, `kappa = (3r - r^3) / (1 - r^2)`, `alpha'^2 = alpha^2 + 1 / kappa`.
//! - `toksvig`: Toksvig's factor `ft = r` on the Blinn-Phong exponent `s = 2 / alpha^2 - 2`,
//!   `s' = ft s / (ft + s (1 - ft))`, back to `alpha' = sqrt(2 / (s' + 2))`.
//! - `tokuyoshi`: Tokuyoshi-Kaplanyan's projected-space filtering for a static texture: the
//!   variance of the projected normals (`nx`, `ny`) under the texel is the kernel,
//!   `alpha'^2 = alpha^2 + min(2 (var nx + var ny), 0.18)` (seed 000's isotropic form, its
//!   clamp keeping a flat highlight from turning diffuse).
//!
//! Roughness in and out is glTF's perceptual roughness (`alpha = roughness^2`); the filtering
//! is done on GGX's `alpha`.

use rayon::prelude::*;
use serde::Serialize;

use super::RoughnessOptions;
use crate::plane::Plane;

/// How the roughness of a mip level is widened for the normals it averages.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum RoughnessFilter {
    /// Seed 004's von Mises-Fisher fit to the average normal's length.
    Vmf,
    /// Toksvig's factor on the equivalent Blinn-Phong exponent.
    Toksvig,
    /// Tokuyoshi-Kaplanyan projected-space filtering: the variance of `nx` and `ny` widens
    /// `alpha^2`, capped.
    Tokuyoshi,
}

impl RoughnessFilter {
    /// Reads a filter's lowercase name (`vmf`, `toksvig`, `tokuyoshi`); the error message names the
    /// valid ones.
    pub fn parse(text: &str) -> std::result::Result<Self, String> {
        match text {
            "vmf" => Ok(RoughnessFilter::Vmf),
            "toksvig" => Ok(RoughnessFilter::Toksvig),
            "tokuyoshi" => Ok(RoughnessFilter::Tokuyoshi),
            other => Err(format!(
                "\"{other}\" is not a roughness filter (vmf, toksvig, tokuyoshi)"
            )),
        }
    }

    /// Filtered GGX alpha for base `alpha` from a texel's statistics.
    pub fn alpha(self, alpha: f64, texel: &TexelStats) -> f64 {
        let r = texel.mean_length();
        match self {
            RoughnessFilter::Vmf => {
                let kappa = if r < 1.0 {
                    (3.0 * r - r * r * r) / (1.0 - r * r)
                } else {
                    10_000.0
                };
                (alpha * alpha + 1.0 / kappa.max(1e-6)).sqrt()
            }
            RoughnessFilter::Toksvig => {
                let s = 2.0 / (alpha * alpha) - 2.0;
                let ft = r.clamp(1e-6, 1.0);
                let s_filtered = ft * s / (ft + s * (1.0 - ft));
                (2.0 / (s_filtered.max(0.0) + 2.0)).sqrt()
            }
            RoughnessFilter::Tokuyoshi => {
                let var = texel.variance_xy();
                (alpha * alpha + (2.0 * var).min(0.18)).sqrt()
            }
        }
    }
}

/// Averages over a texel's footprint of the full-resolution unit normals.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TexelStats {
    /// Average normal under the texel, not renormalised (its length is 1 only where all agree).
    pub n: [f64; 3],
    /// Average of `nx^2` under the texel.
    pub xx: f64,
    /// Average of `ny^2` under the texel.
    pub yy: f64,
}

impl TexelStats {
    /// Length of the average normal, capped at 1: how tightly the normals under the texel agree.
    pub fn mean_length(&self) -> f64 {
        (self.n[0].powi(2) + self.n[1].powi(2) + self.n[2].powi(2))
            .sqrt()
            .min(1.0)
    }

    /// `var nx + var ny` of the projected normals.
    pub fn variance_xy(&self) -> f64 {
        (self.xx - self.n[0].powi(2) + self.yy - self.n[1].powi(2)).max(0.0)
    }
}

/// One level: five planes of footprint averages (`nx`, `ny`, `nz`, `nx^2`, `ny^2`).
#[derive(Clone, Debug)]
pub struct Level {
    /// Footprint averages, in order `nx`, `ny`, `nz`, `nx^2`, `ny^2`, all the level's size.
    pub stats: [Plane; 5],
}

impl Level {
    /// The level's width in texels.
    pub fn width(&self) -> usize {
        self.stats[0].width
    }

    /// The level's height in texels.
    pub fn height(&self) -> usize {
        self.stats[0].height
    }

    /// The statistics of texel `i` (row-major index into the level).
    pub fn texel(&self, i: usize) -> TexelStats {
        let s = |k: usize| self.stats[k].data[i] as f64;
        TexelStats {
            n: [s(0), s(1), s(2)],
            xx: s(3),
            yy: s(4),
        }
    }

    /// The level's normals, renormalised (world frame).
    pub fn normals(&self) -> [Plane; 3] {
        let mut out = [
            self.stats[0].clone(),
            self.stats[1].clone(),
            self.stats[2].clone(),
        ];
        let [x, y, z] = &mut out;
        x.data
            .par_iter_mut()
            .zip(y.data.par_iter_mut())
            .zip(z.data.par_iter_mut())
            .for_each(|((x, y), z)| {
                let len = (*x * *x + *y * *y + *z * *z).sqrt();
                if len > 1e-8 {
                    *x /= len;
                    *y /= len;
                    *z /= len;
                } else {
                    (*x, *y, *z) = (0.0, 0.0, 1.0);
                }
            });
        out
    }
}

/// The full chain down to 1 x 1 (each level `max(1, size >> level)`, as DDS expects).
#[derive(Clone, Debug)]
pub struct MipChain {
    /// Level 0 (the full-resolution map) first, then each half the size of the last, down to 1 x 1.
    pub levels: Vec<Level>,
}

impl MipChain {
    /// Builds the chain from a unit normal map by repeated 2 x 2 box averaging.
    pub fn build(normal: &[Plane; 3]) -> Self {
        let square = |p: &Plane| Plane {
            width: p.width,
            height: p.height,
            data: p.data.par_iter().map(|v| v * v).collect(),
        };
        let base = Level {
            stats: [
                normal[0].clone(),
                normal[1].clone(),
                normal[2].clone(),
                square(&normal[0]),
                square(&normal[1]),
            ],
        };
        let mut levels = vec![base];
        loop {
            let last = levels.last().expect("the base level is there");
            if last.width() == 1 && last.height() == 1 {
                break;
            }
            let next = Level {
                stats: std::array::from_fn(|k| halve(&last.stats[k])),
            };
            levels.push(next);
        }
        MipChain { levels }
    }

    /// Perceptual roughness per level for a base perceptual roughness.
    pub fn roughness(&self, filter: RoughnessFilter, base: f64) -> Vec<Plane> {
        let alpha = base * base;
        self.levels
            .iter()
            .enumerate()
            .map(|(l, level)| {
                let n = level.width() * level.height();
                let data = (0..n)
                    .into_par_iter()
                    .map(|i| {
                        if l == 0 {
                            return base as f32;
                        }
                        filter.alpha(alpha, &level.texel(i)).min(1.0).sqrt() as f32
                    })
                    .collect();
                Plane {
                    width: level.width(),
                    height: level.height(),
                    data,
                }
            })
            .collect()
    }
}

/// The next level: 2 x 2 box average (an odd last row or column folds into its neighbour's
/// texel so no full-resolution normal is dropped).
pub(super) fn halve(p: &Plane) -> Plane {
    let (w, h) = (p.width, p.height);
    let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
    let span = |i: usize, n: usize, nn: usize| -> std::ops::Range<usize> {
        let start = (2 * i).min(n - 1);
        let end = if i + 1 == nn { n } else { (2 * i + 2).min(n) };
        start..end
    };
    let mut data = vec![0.0f32; nw * nh];
    data.par_chunks_mut(nw).enumerate().for_each(|(y, row)| {
        let ys = span(y, h, nh);
        for (x, out) in row.iter_mut().enumerate() {
            let xs = span(x, w, nw);
            let mut sum = 0.0f64;
            for yy in ys.clone() {
                for xx in xs.clone() {
                    sum += p.data[yy * w + xx] as f64;
                }
            }
            *out = (sum / (ys.len() * xs.len()) as f64) as f32;
        }
    });
    Plane {
        width: nw,
        height: nh,
        data,
    }
}

/// Mean roughness per level, for the report.
#[derive(Clone, Debug, Serialize)]
pub struct RoughnessReport {
    /// The filter that widened the roughness.
    pub filter: RoughnessFilter,
    /// The base perceptual roughness, level 0's value.
    pub base: f64,
    /// Mean perceptual roughness of each level, level 0 first.
    pub mean_per_level: Vec<f64>,
}

impl RoughnessReport {
    /// Summarises per-level roughness planes (from [`MipChain::roughness`]) made with `options`.
    pub fn new(options: &RoughnessOptions, levels: &[Plane]) -> Self {
        RoughnessReport {
            filter: options.filter,
            base: options.base,
            mean_per_level: levels
                .iter()
                .map(|p| p.data.iter().map(|&v| v as f64).sum::<f64>() / p.len() as f64)
                .collect(),
        }
    }
}

/// Seed 004 Appendix A: GGX specular with the matching Smith visibility and Schlick Fresnel,
/// times `n.l` (the radiance a unit light gives). `alpha` is the seed's `m`.
pub fn ggx_radiance(alpha: f64, n: [f64; 3], v: [f64; 3], l: [f64; 3], f0: f64) -> f64 {
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let n_dot_l = dot(n, l).clamp(0.0, 1.0);
    if n_dot_l <= 0.0 {
        return 0.0;
    }
    let hv = [v[0] + l[0], v[1] + l[1], v[2] + l[2]];
    let len = dot(hv, hv).sqrt();
    let h = hv.map(|c| c / len);
    let n_dot_h = dot(n, h).clamp(0.0, 1.0);
    let n_dot_v = dot(n, v).max(1e-4);
    let m2 = alpha * alpha;
    let d = m2 / (std::f64::consts::PI * (n_dot_h * n_dot_h * (m2 - 1.0) + 1.0).powi(2));
    let v1 = |x: f64| 1.0 / (x + (m2 + (1.0 - m2) * x * x).sqrt());
    let l_dot_h = dot(l, h).clamp(0.0, 1.0);
    let f = f0 + (1.0 - f0) * (1.0 - l_dot_h).powi(5);
    d * f * v1(n_dot_l) * v1(n_dot_v) * n_dot_l
}

#[cfg(test)]
mod tests {
    use super::*;

    use super::super::normal_field as field;

    #[test]
    fn a_uniform_field_keeps_the_base_roughness_at_every_level() {
        let n = field(16, 8, |_, _| [0.3, -0.2, (1.0f64 - 0.13).sqrt()]);
        let chain = MipChain::build(&n);
        assert_eq!(chain.levels.len(), 5); // 16x8, 8x4, 4x2, 2x1, 1x1
        for filter in [
            RoughnessFilter::Vmf,
            RoughnessFilter::Toksvig,
            RoughnessFilter::Tokuyoshi,
        ] {
            for level in chain.roughness(filter, 0.4) {
                for v in level.data {
                    assert!((v - 0.4).abs() < 2e-3, "{filter:?}: {v}");
                }
            }
        }
    }

    #[test]
    fn two_normals_at_a_known_angle_give_the_closed_forms() {
        // A checkerboard of normals tilted +-theta about y: every level-1 texel holds two of
        // each, average (0, 0, cos theta), var nx = sin^2 theta, var ny = 0.
        let theta = 12f64.to_radians();
        let (s, c) = theta.sin_cos();
        let n = field(8, 8, |x, y| {
            if (x + y) % 2 == 0 {
                [s, 0.0, c]
            } else {
                [-s, 0.0, c]
            }
        });
        let chain = MipChain::build(&n);
        let base: f64 = 0.3;
        let a2 = base.powi(4);
        let kappa = (3.0 * c - c.powi(3)) / (1.0 - c * c);
        let vmf = (a2 + 1.0 / kappa).sqrt().sqrt();
        let sp = 2.0 / a2 - 2.0;
        let toksvig = (2.0 / (c * sp / (c + sp * (1.0 - c)) + 2.0)).sqrt().sqrt();
        let tk = (a2 + (2.0 * s * s).min(0.18)).sqrt().sqrt();
        for (filter, want) in [
            (RoughnessFilter::Vmf, vmf),
            (RoughnessFilter::Toksvig, toksvig),
            (RoughnessFilter::Tokuyoshi, tk),
        ] {
            let levels = chain.roughness(filter, base);
            for l in 1..levels.len() {
                for &v in &levels[l].data {
                    assert!(
                        (v as f64 - want).abs() < 1e-4,
                        "{filter:?} level {l}: {v} vs {want}"
                    );
                }
            }
            assert!(want > base + 0.01, "{filter:?} widens: {want}");
        }
        // Renormalised level normals point straight up.
        let up = chain.levels[1].normals();
        assert!(up[2].data.iter().all(|&z| (z - 1.0).abs() < 1e-6));
    }

    /// GGX (seed Appendix A) rendered at each mip level three ways, against the supersampled
    /// truth (the full-resolution texels under each mip texel shaded and averaged), over
    /// view/light pairs across the hemisphere. Figures go to docs/derive.md.
    #[test]
    fn filtered_mips_render_closer_to_the_supersampled_truth() {
        let (w, h) = (128, 128);
        // A weave-like bump field: slopes up to about 20 deg at 6-10 px periods.
        let n = field(w, h, |x, y| {
            let (x, y) = (x as f64, y as f64);
            let t = std::f64::consts::TAU;
            let p = 0.25 * (t * x / 6.0).sin() + 0.15 * (t * (x + y) / 10.0).cos();
            let q = 0.25 * (t * y / 8.0).sin() + 0.15 * (t * (x - y) / 10.0).cos();
            let inv = 1.0 / (p * p + q * q + 1.0).sqrt();
            [-p * inv, -q * inv, inv]
        });
        let chain = MipChain::build(&n);
        let base: f64 = 0.35;
        let alpha = base * base;
        let dirs: Vec<([f64; 3], [f64; 3])> = (0..24)
            .map(|k| {
                let phi = k as f64 * 0.9;
                let tv = (k % 4) as f64 * 0.25;
                let tl = ((k / 4) % 3) as f64 * 0.3 + 0.1;
                let v = [tv.sin() * phi.cos(), tv.sin() * phi.sin(), tv.cos()];
                let l = [
                    -tl.sin() * (phi + 0.3).cos(),
                    -tl.sin() * (phi + 0.3).sin(),
                    tl.cos(),
                ];
                (v, l)
            })
            .collect();
        for filter in [
            RoughnessFilter::Vmf,
            RoughnessFilter::Toksvig,
            RoughnessFilter::Tokuyoshi,
        ] {
            let rough = chain.roughness(filter, base);
            let mut figures = Vec::new();
            for l in 1..=4 {
                let level = &chain.levels[l];
                let normals = level.normals();
                let f = 1 << l;
                let (mut e_plain, mut e_filtered, mut e_truth) = (0.0, 0.0, 0.0);
                for ty in 0..level.height() {
                    for tx in 0..level.width() {
                        let i = ty * level.width() + tx;
                        let nm = [0, 1, 2].map(|c| normals[c].data[i] as f64);
                        let a_f = (rough[l].data[i] as f64).powi(2);
                        for &(v, lt) in &dirs {
                            let mut truth = 0.0;
                            for y in ty * f..(ty + 1) * f {
                                for x in tx * f..(tx + 1) * f {
                                    let nf = [0, 1, 2].map(|c| n[c].data[y * w + x] as f64);
                                    truth += ggx_radiance(alpha, nf, v, lt, 0.04);
                                }
                            }
                            truth /= (f * f) as f64;
                            let plain = ggx_radiance(alpha, nm, v, lt, 0.04);
                            let filtered = ggx_radiance(a_f, nm, v, lt, 0.04);
                            e_plain += (plain - truth).powi(2);
                            e_filtered += (filtered - truth).powi(2);
                            e_truth += truth * truth;
                        }
                    }
                }
                let (rp, rf) = ((e_plain / e_truth).sqrt(), (e_filtered / e_truth).sqrt());
                figures.push(format!("level {l}: unfiltered {rp:.3}, filtered {rf:.3}"));
                assert!(
                    rf < rp,
                    "{filter:?} level {l}: filtered {rf} vs unfiltered {rp}"
                );
            }
            eprintln!(
                "GGX relative RMS error vs supersampled, {filter:?}: {}",
                figures.join("; ")
            );
        }
    }
}
