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

mod row_sums;

use std::ops::Range;

use rayon::prelude::*;

use self::row_sums::RowSums;
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

    /// Node `i` of `n` along an axis of `len` samples at or below `p`, and `p`'s fraction of
    /// the way to node `i + 1` (node i sits at `i * step`, the last one on the border).
    fn locate(&self, p: usize, n: usize, len: usize) -> (usize, f64) {
        let i = (p / self.step).min(n - 2);
        let lo = i * self.step;
        let hi = ((i + 1) * self.step).min(len - 1);
        let t = if hi > lo {
            (p as f64 - lo as f64) / (hi - lo) as f64
        } else {
            0.0
        };
        (i, t.clamp(0.0, 1.0))
    }

    /// The columns of a row's cell `c` of `count`: `step` wide, the last one to the border
    /// (so the cells cover the row: the last starts at most two samples before its end).
    fn cell_columns(&self, c: usize, count: usize) -> Range<usize> {
        let first = c * self.step;
        let last = if c + 1 == count {
            self.width
        } else {
            (first + self.step).min(self.width)
        };
        first..last
    }

    /// The cells of a row whose node vectors are `nodes` (as [`ShadingField::row_nodes`] gives
    /// them): one between each node column and the next.
    fn row_cells<'a>(&self, nodes: &'a [[f64; 3]]) -> Vec<RowCell<'a>> {
        let f = self.frames;
        (0..self.nx - 1)
            .map(|i| RowCell::new(&nodes[i * f..(i + 1) * f], &nodes[(i + 1) * f..(i + 2) * f]))
            .collect()
    }

    /// Every frame's shading vector on row `y` at each node column:
    /// `out[i * frames + k]`, frame k's vector at node column i.
    fn row_nodes(&self, y: usize) -> Vec<[f64; 3]> {
        let (j, ty) = self.locate(y, self.ny, self.height);
        let per_row = self.nx * self.frames;
        let (above, below) = (
            &self.vectors[j * per_row..(j + 1) * per_row],
            &self.vectors[(j + 1) * per_row..(j + 2) * per_row],
        );
        above
            .iter()
            .zip(below)
            .map(|(a, c)| std::array::from_fn(|m| (1.0 - ty) * a[m] + ty * c[m]))
            .collect()
    }

    /// Every frame's shading vector at sample `(x, y)`, written into `out` (one per frame).
    #[cfg(test)]
    fn at(&self, x: usize, y: usize, out: &mut [[f64; 3]]) {
        let nodes = self.row_nodes(y);
        let (i, tx) = self.locate(x, self.nx, self.width);
        let f = self.frames;
        for (k, o) in out.iter_mut().enumerate() {
            let (a, b) = (nodes[i * f + k], nodes[(i + 1) * f + k]);
            *o = std::array::from_fn(|m| a[m] + tx * (b[m] - a[m]));
        }
    }
}

/// One grid cell of one row: along it every frame's shading vector is linear in the fraction
/// `t` of the way across, `s_k(t) = start_k + t * step_k`, so the normal matrix of a site with
/// every frame usable, `sum_k s_k s_k^T`, is a quadratic in `t` whose coefficients the cell
/// computes once. A site then costs its right-hand side and a 3x3 solve, not ten
/// interpolations and outer products.
struct RowCell<'a> {
    start: &'a [[f64; 3]],
    step: Vec<[f64; 3]>,
    /// `M(t) = m0 + t * m1 + t^2 * m2` over every frame.
    m: [[[f64; 3]; 3]; 3],
    /// `sum_k s_k[2]` = `flat0 + t * flat1`: the shading of a flat site.
    flat: [f64; 2],
}

impl<'a> RowCell<'a> {
    fn new(left: &'a [[f64; 3]], right: &[[f64; 3]]) -> Self {
        let step: Vec<[f64; 3]> = left
            .iter()
            .zip(right)
            .map(|(a, b)| std::array::from_fn(|m| b[m] - a[m]))
            .collect();
        let mut m = [[[0.0; 3]; 3]; 3];
        for (a, d) in left.iter().zip(&step) {
            for r in 0..3 {
                for c in 0..3 {
                    m[0][r][c] += a[r] * a[c];
                    m[1][r][c] += a[r] * d[c] + d[r] * a[c];
                    m[2][r][c] += d[r] * d[c];
                }
            }
        }
        let flat = [
            left.iter().map(|a| a[2]).sum(),
            step.iter().map(|d| d[2]).sum(),
        ];
        RowCell {
            start: left,
            step,
            m,
            flat,
        }
    }

    /// The least-squares scaled normal at fraction `t` from the sums over every frame of
    /// its white-balanced sample times its shading vector's start and step (see
    /// [`RowSums`]), and whether the cell's normal matrix determines it
    /// ([`solve_normal_equations_selected`]; the caller checks the count of frames).
    #[inline(always)]
    fn fit_every_frame_unchecked(
        &self,
        t: f64,
        (r0, r1): ([f64; 3], [f64; 3]),
    ) -> ([f64; 3], bool) {
        // r = sum_k v_k s_k(t) = sum_k v_k start_k + t * sum_k v_k step_k.
        let r = std::array::from_fn(|m| r0[m] + t * r1[m]);
        let m = std::array::from_fn(|a| {
            std::array::from_fn(|b| self.m[0][a][b] + t * (self.m[1][a][b] + t * self.m[2][a][b]))
        });
        solve_normal_equations_selected(m, r)
    }

    /// Frame k's shading vector at fraction `t`.
    fn vector(&self, k: usize, t: f64) -> [f64; 3] {
        std::array::from_fn(|m| self.start[k][m] + t * self.step[k][m])
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
    pub(super) const BLACK: SiteFit = SiteFit {
        albedo: 0.0,
        normal: [0.0, 0.0, 1.0],
    };

    /// A site's result from its fitted scaled normal `fit`; without one (not determined), its
    /// white-balanced `sum` over the summed shading `flat` a flat site would have.
    fn from_fit(fit: Option<[f64; 3]>, sum: f32, flat: f64) -> SiteFit {
        SiteFit::from_fit_selected((fit.unwrap_or([0.0; 3]), fit.is_some()), sum, flat)
    }

    /// [`SiteFit::from_fit`] of `b` where `determined`, else of none; both computed and one
    /// selected, so that a loop over sites vectorises.
    #[inline(always)]
    fn from_fit_selected((b, determined): ([f64; 3], bool), sum: f32, flat: f64) -> SiteFit {
        let a = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
        let fitted = SiteFit {
            albedo: a as f32,
            normal: if a > 0.0 {
                b.map(|v| (v / a) as f32)
            } else {
                [0.0, 0.0, 1.0]
            },
        };
        let unfitted = SiteFit {
            albedo: if flat > 0.0 {
                (sum as f64 / flat) as f32
            } else {
                0.0
            },
            normal: [0.0, 0.0, 1.0],
        };
        if determined {
            fitted
        } else {
            unfitted
        }
    }
}

/// Each site's own-channel albedo `|b|` and normal from a least-squares fit of `b . s_k` to its
/// white-balanced samples `v_k / colours[k][channel]`, saturated samples left out. `sums` are
/// the sites' white-balanced sums over the stack: a site whose sum is at most `floor` is black
/// (0), and one whose fit is not determined (fewer than three usable samples, or shading
/// vectors too close to a plane) takes its sum over the shading a flat site would have, on
/// the same scale.
///
/// Fits a row at a time ([`SiteRows`]): the demosaic fits the rows it is about to read, and
/// keeps the five it reads, rather than every site up front, which held 16 bytes a site
/// (257 MB at 16 MP, every page of it faulted in and zeroed by the kernel, then read back
/// from memory) for a pass that reads each row within two rows of where it is.
pub struct SiteFitter<'a> {
    frames: &'a [LinearMosaic],
    /// White balance as a product: 1 / colour, per frame and channel.
    inverse: Vec<[f64; 3]>,
    field: &'a ShadingField,
    sums: &'a [f32],
    floor: f32,
}

impl<'a> SiteFitter<'a> {
    /// The fitter of `frames` under illuminants `colours` (one per frame), shaded as `field`
    /// says, with the stack's white-balanced `sums` (row-major, like the mosaic).
    pub fn new(
        frames: &'a [LinearMosaic],
        colours: &[[f32; 3]],
        field: &'a ShadingField,
        sums: &'a [f32],
        floor: f32,
    ) -> Self {
        SiteFitter {
            frames,
            inverse: colours.iter().map(|g| g.map(|v| 1.0 / v as f64)).collect(),
            field,
            sums,
            floor,
        }
    }

    /// Row `y`'s sites into `row` (every one written); `sums_of_row` is scratch kept between
    /// rows.
    fn fit_row(&self, y: usize, row: &mut [SiteFit], sums_of_row: &mut RowSums) {
        let (frames, field, inverse) = (self.frames, self.field, &self.inverse);
        let w = frames[0].width;
        let pattern = frames[0].pattern;
        let n = frames.len();
        let nodes = field.row_nodes(y);
        let cells = field.row_cells(&nodes);
        sums_of_row.accumulate(frames, inverse, field, &cells, y);
        for (c, cell) in cells.iter().enumerate() {
            let columns = field.cell_columns(c, cells.len());
            let (first, last) = (columns.start, columns.end);
            let (lo, hi) = (first, ((c + 1) * field.step).min(field.width - 1));
            let sums = &self.sums[y * w + first..y * w + last];
            fit_run(
                cell,
                (lo, hi),
                first,
                sums_of_row,
                sums,
                &mut row[first..last],
            );
        }
        // Black sites, and sites saturated in some frame (fitted to the other frames).
        let mut samples = Vec::with_capacity(n);
        for (x, site) in row.iter_mut().enumerate() {
            let i = y * w + x;
            if self.sums[i] <= self.floor {
                *site = SiteFit::BLACK;
                continue;
            }
            if !sums_of_row.saturated[x] {
                continue;
            }
            let (c, t) = field.locate(x, field.nx, field.width);
            let cell = &cells[c];
            let own = pattern[y % 2][x % 2] as usize;
            let value = |k: usize| frames[k].value(i) as f64 * inverse[k][own];
            samples.clear();
            samples.extend(
                (0..n)
                    .filter(|&k| !frames[k].saturated_at(i))
                    .map(|k| (cell.vector(k, t), value(k))),
            );
            let fit = fit_scaled_normal(samples.iter().map(|(s, v)| (s, *v)));
            let flat = cell.flat[0] + t * cell.flat[1];
            *site = SiteFit::from_fit(fit, self.sums[i], flat);
        }
    }
}

/// Where the demosaic reads its sites' fits from, a row at a time: fitted as they are needed
/// ([`SiteFitter`]) or already fitted (a slice of every site, row-major).
pub trait SiteRows: Sync {
    /// Buffers carried from one row to the next.
    type Scratch: Default;

    /// Row `y`'s sites into `row` (as many as it holds: the mosaic's width).
    fn site_row(&self, y: usize, row: &mut [SiteFit], scratch: &mut Self::Scratch);
}

/// [`SiteFitter`]'s buffers for a row's fit.
#[derive(Default)]
pub struct FitScratch(RowSums);

impl SiteRows for SiteFitter<'_> {
    type Scratch = FitScratch;

    fn site_row(&self, y: usize, row: &mut [SiteFit], scratch: &mut FitScratch) {
        self.fit_row(y, row, &mut scratch.0);
    }
}

impl SiteRows for [SiteFit] {
    type Scratch = ();

    fn site_row(&self, y: usize, row: &mut [SiteFit], _: &mut ()) {
        let w = row.len();
        row.copy_from_slice(&self[y * w..(y + 1) * w]);
    }
}

/// Every site's fit ([`SiteFitter`]), row-major: the whole mosaic at once, rows in parallel.
#[cfg(test)]
pub fn site_albedos(
    frames: &[LinearMosaic],
    colours: &[[f32; 3]],
    field: &ShadingField,
    sums: &[f32],
    floor: f32,
) -> Vec<SiteFit> {
    let (w, h) = (frames[0].width, frames[0].height);
    let fitter = SiteFitter::new(frames, colours, field, sums, floor);
    let mut out = vec![SiteFit::BLACK; w * h];
    out.par_chunks_mut(w)
        .enumerate()
        .for_each_init(RowSums::default, |sums_of_row, (y, row)| {
            fitter.fit_row(y, row, sums_of_row)
        });
    out
}

/// Every site of one cell's run of a row (`first` its first column, `(lo, hi)` the cell's
/// node columns) fitted to every frame, as [`RowCell::fit_every_frame`] and
/// [`SiteFit::from_fit`] would, branch-free so that it vectorises; black and saturated sites
/// are redone by the caller.
fn fit_run(
    cell: &RowCell,
    (lo, hi): (usize, usize),
    first: usize,
    sums_of_row: &RowSums,
    sums: &[f32],
    out: &mut [SiteFit],
) {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked above).
        return unsafe { fit_run_avx2(cell, (lo, hi), first, sums_of_row, sums, out) };
    }
    fit_run_portable(cell, (lo, hi), first, sums_of_row, sums, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fit_run_avx2(
    cell: &RowCell,
    (lo, hi): (usize, usize),
    first: usize,
    sums_of_row: &RowSums,
    sums: &[f32],
    out: &mut [SiteFit],
) {
    fit_run_portable(cell, (lo, hi), first, sums_of_row, sums, out)
}

#[inline(always)]
fn fit_run_portable(
    cell: &RowCell,
    (lo, hi): (usize, usize),
    first: usize,
    sums_of_row: &RowSums,
    sums: &[f32],
    out: &mut [SiteFit],
) {
    let frames = cell.start.len();
    for (j, (site, &sum)) in out.iter_mut().zip(sums).enumerate() {
        let x = first + j;
        // `ShadingField::locate`'s fraction.
        let t = if hi > lo {
            (x as f64 - lo as f64) / (hi - lo) as f64
        } else {
            0.0
        };
        let t = t.clamp(0.0, 1.0);
        let fit = cell.fit_every_frame_unchecked(t, sums_of_row.rhs(x));
        let flat = cell.flat[0] + t * cell.flat[1];
        let (b, determined) = fit;
        *site = SiteFit::from_fit_selected((b, determined && frames >= 3), sum, flat);
    }
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
    solve_normal_equations(m, r, count)
}

/// The `b` with `m b = r` for the normal equations `m` of `count` samples; `None` when fewer
/// than three samples or shading vectors too close to a plane leave it undetermined.
fn solve_normal_equations(m: [[f64; 3]; 3], r: [f64; 3], count: usize) -> Option<[f64; 3]> {
    let (b, determined) = solve_normal_equations_selected(m, r);
    (count >= 3 && determined).then_some(b)
}

/// [`solve_normal_equations`] without the count: `b`, whatever it is, and whether `m`
/// determines it. Branch-free, so that a loop over sites vectorises.
#[inline(always)]
fn solve_normal_equations_selected(m: [[f64; 3]; 3], r: [f64; 3]) -> ([f64; 3], bool) {
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
    // M is symmetric: its inverse is the cofactor matrix over the determinant.
    let b = std::array::from_fn(|a| (0..3).map(|c| cof(a, c) * r[c]).sum::<f64>() / det);
    (b, determined)
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

    /// The definition [`site_albedos`] computes faster: every usable frame's shading vector
    /// interpolated at the site, then a least-squares fit of them.
    fn site_albedos_by_definition(
        frames: &[LinearMosaic],
        colours: &[[f32; 3]],
        field: &ShadingField,
        sums: &[f32],
        floor: f32,
    ) -> Vec<SiteFit> {
        let (w, h) = (frames[0].width, frames[0].height);
        let mut vectors = vec![[0.0; 3]; frames.len()];
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if sums[i] <= floor {
                    return SiteFit::BLACK;
                }
                field.at(x, y, &mut vectors);
                let own = frames[0].pattern[y % 2][x % 2] as usize;
                let samples = frames
                    .iter()
                    .zip(colours)
                    .zip(&vectors)
                    .filter(|((f, _), _)| !f.saturated[i])
                    .map(|((f, g), s)| (s, f.values[i] as f64 / g[own] as f64));
                let flat: f64 = vectors.iter().map(|s| s[2]).sum();
                SiteFit::from_fit(fit_scaled_normal(samples), sums[i], flat)
            })
            .collect()
    }

    /// A `w x h` RGGB stack of random samples under lights whose direction and power change
    /// across the mosaic (near lights), sampled every `step` samples, one site in twelve
    /// saturated per frame: the frames, their illuminants' colours, the shading field and the
    /// sites' sums.
    pub(super) fn random_stack(
        (w, h): (usize, usize),
        step: usize,
        seed: u64,
    ) -> (Vec<LinearMosaic>, Vec<[f32; 3]>, ShadingField, Vec<f32>) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let base = lights();
        let field = ShadingField::sample(w, h, step, |x, y| {
            Ok(base
                .iter()
                .map(|s| {
                    [
                        s[0] - 0.01 * x,
                        s[1] + 0.02 * y,
                        s[2] * (1.0 + 0.003 * (x + y)),
                    ]
                })
                .collect())
        })
        .unwrap();
        let colours: Vec<[f32; 3]> = (0..base.len())
            .map(|k| [0.9 + 0.02 * k as f32, 1.0, 1.1 - 0.03 * k as f32])
            .collect();
        let frames: Vec<LinearMosaic> = (0..base.len())
            .map(|_| LinearMosaic {
                width: w,
                height: h,
                pattern: [[0, 1], [1, 2]],
                values: (0..w * h).map(|_| rng.gen_range(0.0..1.0)).collect(),
                saturated: (0..w * h).map(|_| rng.gen_range(0..12) == 0).collect(),
                dn: None,
            })
            .collect();
        let sums: Vec<f32> = (0..w * h)
            .map(|i| frames.iter().map(|f| f.values[i]).sum())
            .collect();
        (frames, colours, field, sums)
    }

    #[test]
    fn the_per_cell_fit_equals_the_fit_by_definition() {
        let (mut frames, colours, field, mut sums) = random_stack((37, 23), 8, 7);
        sums[5] = 0.0; // a black site
        for frame in &mut frames[2..] {
            frame.saturated[9] = true; // two usable samples: no fit, the flat estimate
        }
        let got = site_albedos(&frames, &colours, &field, &sums, 1e-3);
        let want = site_albedos_by_definition(&frames, &colours, &field, &sums, 1e-3);
        // Both compute in f64 from the same inputs in another order (rounding ~1e-15 of a
        // well-conditioned 3x3 system here) and round to f32 once: at most one f32 ulp apart.
        let ulp = f32::EPSILON;
        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
            assert!(
                (a.albedo - b.albedo).abs() <= ulp * b.albedo.abs(),
                "site {i}: {a:?} vs {b:?}"
            );
            for m in 0..3 {
                assert!(
                    (a.normal[m] - b.normal[m]).abs() <= ulp,
                    "site {i}: {a:?} vs {b:?}"
                );
            }
        }
        assert_eq!(got[5], SiteFit::BLACK);
        assert_eq!(got[9].normal, [0.0, 0.0, 1.0]);
    }

    #[test]
    fn ratios_from_rows_fitted_as_they_are_read_equal_those_from_every_site_fitted_first() {
        use super::super::hue::colour_ratios;
        // Taller than two of the demosaic's bands, so that bands start mid-mosaic and
        // refit the rows they share; black sites in runs across band boundaries.
        let (w, h) = (45, 150);
        let (frames, colours, field, mut sums) = random_stack((w, h), 8, 11);
        for i in (0..w * h).step_by(97) {
            sums[i..(i + 3).min(w * h)].fill(0.0);
        }
        let every_site = site_albedos(&frames, &colours, &field, &sums, 1e-3);
        let (want, _) = colour_ratios(w, h, frames[0].pattern, every_site.as_slice());
        let fitter = SiteFitter::new(&frames, &colours, &field, &sums, 1e-3);
        let (got, _) = colour_ratios(w, h, frames[0].pattern, &fitter);
        for (c, (got, want)) in got.channels().iter().zip(want.channels()).enumerate() {
            for (i, (a, b)) in got.data.iter().zip(&want.data).enumerate() {
                assert_eq!(
                    a.to_bits(),
                    b.to_bits(),
                    "channel {c}, pixel {i}: {a} vs {b}"
                );
            }
        }
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
