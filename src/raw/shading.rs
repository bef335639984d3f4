//! The albedo of every CFA site, with the shading divided out: what the full-resolution stack
//! demosaic interpolates to get a pixel's missing channels.
//!
//! Each site holds its own channel's sample under every light. For a Lambertian surface with
//! scaled normal `b` (albedo times unit normal), frame k's white-balanced sample is
//! `b . s_k`, where `s_k` is the frame's *shading vector* at the site (the direction toward the
//! light times its irradiance there). With three or more frames a least-squares fit of `b` to
//! the site's samples gives its albedo `|b|`, whatever the normal: neighbouring sites shaded
//! differently (thread flanks, gaps) then still compare like for like. `raw` does not know what
//! makes the shading vectors (lights, a rig); the caller samples them on a coarse grid.

use rayon::prelude::*;

use super::mosaic::LinearMosaic;
use crate::error::{Error, Result};

/// The frames' shading vectors over the mosaic, sampled every `step` samples and interpolated
/// bilinearly in between (they change slowly across the sensor: lights are far from the
/// sample compared with a pixel). Any factor common to every frame and site may be left out.
#[derive(Clone, Debug)]
pub struct ShadingField {
    width: usize,
    height: usize,
    step: usize,
    nx: usize,
    ny: usize,
    frames: usize,
    /// `vectors[(j * nx + i) * frames + k]`: frame k's vector at grid node (i, j).
    vectors: Vec<[f64; 3]>,
}

impl ShadingField {
    /// Samples `vectors_at(x, y)` (mosaic coordinates; one vector per frame) on a grid of
    /// `step` samples over a `width x height` mosaic, its last row and column on the border.
    pub fn sample<F>(width: usize, height: usize, step: usize, vectors_at: F) -> Result<Self>
    where
        F: Fn(f64, f64) -> Result<Vec<[f64; 3]>> + Sync,
    {
        let step = step.max(1);
        let nodes = |n: usize| n.saturating_sub(2) / step + 2;
        let (nx, ny) = (nodes(width), nodes(height));
        let node = |i: usize, n: usize| (i * step).min(n.saturating_sub(1)) as f64;
        let rows: Vec<Vec<Vec<[f64; 3]>>> = (0..ny)
            .into_par_iter()
            .map(|j| {
                (0..nx)
                    .map(|i| vectors_at(node(i, width), node(j, height)))
                    .collect::<Result<Vec<_>>>()
            })
            .collect::<Result<_>>()?;
        let frames = rows[0][0].len();
        let mut vectors = Vec::with_capacity(nx * ny * frames);
        for per_node in rows.iter().flatten() {
            if per_node.len() != frames || per_node.iter().flatten().any(|v| !v.is_finite()) {
                return Err(Error::Invalid(
                    "shading vectors must be finite, one per frame at every point".into(),
                ));
            }
            vectors.extend_from_slice(per_node);
        }
        Ok(ShadingField {
            width,
            height,
            step,
            nx,
            ny,
            frames,
            vectors,
        })
    }

    /// Frames the field describes.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Every frame's shading vector at sample `(x, y)`, written into `out` (one per frame).
    fn at(&self, x: usize, y: usize, out: &mut [[f64; 3]]) {
        // Node i sits at i * step, the last one on the border (`len - 1`).
        let locate = |p: usize, n: usize, len: usize| {
            let i = (p / self.step).min(n - 2);
            let lo = i * self.step;
            let hi = ((i + 1) * self.step).min(len - 1);
            let t = if hi > lo {
                (p as f64 - lo as f64) / (hi - lo) as f64
            } else {
                0.0
            };
            (i, t.clamp(0.0, 1.0))
        };
        let (i, tx) = locate(x, self.nx, self.width);
        let (j, ty) = locate(y, self.ny, self.height);
        let node = |i: usize, j: usize| &self.vectors[(j * self.nx + i) * self.frames..];
        let (a, b, c, d) = (
            node(i, j),
            node(i + 1, j),
            node(i, j + 1),
            node(i + 1, j + 1),
        );
        let weights = [
            (1.0 - tx) * (1.0 - ty),
            tx * (1.0 - ty),
            (1.0 - tx) * ty,
            tx * ty,
        ];
        for (k, o) in out.iter_mut().enumerate() {
            *o = std::array::from_fn(|m| {
                weights[0] * a[k][m]
                    + weights[1] * b[k][m]
                    + weights[2] * c[k][m]
                    + weights[3] * d[k][m]
            });
        }
    }
}

/// One CFA site's fit: its own channel's albedo and the unit normal (the same for every
/// channel, so comparable between neighbouring sites of different channels).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SiteFit {
    pub albedo: f32,
    pub normal: [f32; 3],
}

impl SiteFit {
    const BLACK: SiteFit = SiteFit {
        albedo: 0.0,
        normal: [0.0, 0.0, 1.0],
    };
}

/// Each site's own-channel albedo `|b|` and normal from a least-squares fit of `b . s_k` to its
/// white-balanced samples `v_k / colours[k][channel]`, saturated samples left out. `sums` are
/// the sites' white-balanced sums over the stack: a site whose sum is at most `floor` is black
/// (0), and one whose fit is not determined (fewer than three usable samples, or shading
/// vectors too close to a plane) takes its sum over the shading a flat site would have, on
/// the same scale. Row-major, like the mosaic.
pub fn site_albedos(
    frames: &[LinearMosaic],
    colours: &[[f32; 3]],
    field: &ShadingField,
    sums: &[f32],
    floor: f32,
) -> Vec<SiteFit> {
    let (w, h) = (frames[0].width, frames[0].height);
    let pattern = frames[0].pattern;
    let mut out = vec![SiteFit::BLACK; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let mut vectors = vec![[0.0f64; 3]; frames.len()];
        for (x, site) in row.iter_mut().enumerate() {
            let i = y * w + x;
            if sums[i] <= floor {
                continue;
            }
            field.at(x, y, &mut vectors);
            let own = pattern[y % 2][x % 2] as usize;
            let samples = frames
                .iter()
                .zip(colours)
                .zip(&vectors)
                .filter(|((f, _), _)| !f.saturated[i])
                .map(|((f, g), s)| (s, f.values[i] as f64 / g[own] as f64));
            *site = match fit_scaled_normal(samples) {
                Some(b) => {
                    let a = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
                    let n = if a > 0.0 {
                        b.map(|v| (v / a) as f32)
                    } else {
                        [0.0, 0.0, 1.0]
                    };
                    SiteFit {
                        albedo: a as f32,
                        normal: n,
                    }
                }
                None => {
                    let flat: f64 = vectors.iter().map(|s| s[2]).sum();
                    SiteFit {
                        albedo: if flat > 0.0 {
                            (sums[i] as f64 / flat) as f32
                        } else {
                            0.0
                        },
                        normal: [0.0, 0.0, 1.0],
                    }
                }
            };
        }
    });
    out
}

/// The least-squares `b` with `b . s = v` over `samples` of `(s, v)`.
fn fit_scaled_normal<'a>(samples: impl Iterator<Item = (&'a [f64; 3], f64)>) -> Option<[f64; 3]> {
    let mut m = [[0.0f64; 3]; 3];
    let mut r = [0.0f64; 3];
    let mut count = 0;
    for (s, v) in samples {
        for a in 0..3 {
            r[a] += s[a] * v;
            for b in 0..3 {
                m[a][b] += s[a] * s[b];
            }
        }
        count += 1;
    }
    if count < 3 {
        return None;
    }
    let cof = |a: usize, b: usize| {
        let (a1, a2) = ((a + 1) % 3, (a + 2) % 3);
        let (b1, b2) = ((b + 1) % 3, (b + 2) % 3);
        m[a1][b1] * m[a2][b2] - m[a1][b2] * m[a2][b1]
    };
    let det = m[0][0] * cof(0, 0) + m[0][1] * cof(0, 1) + m[0][2] * cof(0, 2);
    let trace = m[0][0] + m[1][1] + m[2][2];
    // Shading vectors nearly in a plane leave b's component across it to the noise.
    // (A NaN determinant fails the test too.)
    let determined = det > 1e-9 * trace.powi(3);
    if !determined {
        return None;
    }
    // M is symmetric: its inverse is the cofactor matrix over the determinant.
    Some(std::array::from_fn(|a| {
        (0..3).map(|c| cof(a, c) * r[c]).sum::<f64>() / det
    }))
}

/// `|b|` of [`fit_scaled_normal`].
#[cfg(test)]
fn fit_albedo<'a>(samples: impl Iterator<Item = (&'a [f64; 3], f64)>) -> Option<f64> {
    fit_scaled_normal(samples).map(|b| (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lights() -> Vec<[f64; 3]> {
        (0..8)
            .map(|k| {
                let phi = k as f64 * std::f64::consts::TAU / 8.0;
                let theta = 0.6f64;
                let power = 1.0 + 0.1 * k as f64;
                [
                    power * theta.sin() * phi.cos(),
                    power * theta.sin() * phi.sin(),
                    power * theta.cos(),
                ]
            })
            .collect()
    }

    #[test]
    fn the_fit_returns_the_albedo_whatever_the_normal() {
        let lights = lights();
        for normal in [[0.0, 0.0, 1.0], [0.3, -0.2, 0.93], [-0.5, 0.1, 0.86]] {
            let n = nalgebra::Vector3::from(normal).normalize();
            let samples: Vec<([f64; 3], f64)> = lights
                .iter()
                .map(|s| (*s, 0.37 * n.dot(&nalgebra::Vector3::from(*s))))
                .collect();
            let a = fit_albedo(samples.iter().map(|(s, v)| (s, *v))).unwrap();
            assert!((a - 0.37).abs() < 1e-12, "{normal:?}: {a}");
        }
        // Two samples cannot fix a 3-vector; coplanar shading vectors neither.
        let two = lights.iter().take(2).map(|s| (s, 1.0));
        assert_eq!(fit_albedo(two), None);
        let flat = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]];
        assert_eq!(fit_albedo(flat.iter().map(|s| (s, 1.0))), None);
    }

    #[test]
    fn the_field_interpolates_bilinearly_between_its_nodes() {
        // A field linear in x and y is reproduced exactly everywhere, nodes or not.
        let f = |x: f64, y: f64| Ok(vec![[1.0 + x, 2.0 * y, x - y], [3.0, y, 0.5 * x]]);
        let field = ShadingField::sample(37, 23, 8, f).unwrap();
        let mut out = vec![[0.0; 3]; 2];
        for y in 0..23 {
            for x in 0..37 {
                field.at(x, y, &mut out);
                let want = f(x as f64, y as f64).unwrap();
                for k in 0..2 {
                    for m in 0..3 {
                        assert!((out[k][m] - want[k][m]).abs() < 1e-9, "({x},{y}) {k} {m}");
                    }
                }
            }
        }
    }
}
