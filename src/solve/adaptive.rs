//! Adaptive escalation: least squares everywhere, the robust fit only where it is needed.
//!
//! A pixel escalates when its least-squares luminance residual is larger than the noise model
//! allows: the weighted sum of squared residuals `X = sum_k r_k^2 / s_k^2` of a Lambertian
//! pixel with independent Gaussian noise follows a chi-square distribution with `m - 3`
//! degrees of freedom (`m` lights used), and the test rejects at `significance_sigma` of
//! that distribution. The threshold therefore comes from the noise model, not from tuning: on
//! clean data a known small fraction escalates (0.13 % at 3 sigma), and escalating a clean
//! pixel is harmless because the robust fit keeps all lights that agree. Lights that were
//! dark or saturated are already out of the least-squares fit; a pixel with exactly three
//! lights left cannot be tested (any normal fits three lights) and stays least squares.

use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::chi_square::ChiSquare;
use super::fast;
use super::kernel::{Kernel, RowOut, Scratch};
use super::lanes::Real;
use super::options::{Precision, SolveOptions};
use super::{PixelFit, PixelStatus, SolveResult, LUMINANCE_WEIGHTS};
use crate::progress::Progress;

/// The streaming kernel's screen for the adaptive estimator: a chi-square test on the fast
/// least-squares residual against an upper bound of each light's noise variance.
///
/// The fast kernel reports the unweighted residual `S = sum_k r_k^2` over the `m` lights it
/// used, not the per-light variances `s_k^2` the exact test weighs with. Under the noise
/// model a light's luminance variance is `sum_c w_c^2 chi_c (photon I'_c i_c + floor i_c^2)`
/// with `i_c` the light's inverse intensity (raw value to `I'`) and `I'_c = rho_c (n . l)
/// <= rho_c`: bounded by `v_max`, the same expression at `I'_c = rho_c` and the largest
/// inverse intensity of any light near the pixel (the coarse grid below). Then `S / v_max <=
/// sum_k r_k^2 / s_k^2`, the least-squares fit's statistic, whose mean under a Lambertian
/// pixel is about `m - 3`: the screen's threshold is the exact test's chi-square quantile
/// (3 sigma, 0.13 % false alarms for the weighted fit) applied to a statistic that is smaller
/// by `s_k^2 / v_max` per light, so on clean pixels it fails more rarely than the exact test
/// (docs/solve.md). A pixel the screen does not
/// pass goes to the exact kernel, whose own test (exact variances, weighted fit) decides
/// whether the robust fit runs, so the screen can only make escalation rarer. The price is
/// power: a deviation must be larger by `sqrt(v_max / s_k^2)` than the exact test needs; cast
/// shadows and highlights are tens of sigma, and on the cast-shadow scene the streaming
/// adaptive estimator's error matched the exact one's (docs/solve.md; `tests/estimators.rs`
/// holds both to the same bounds).
///
/// Two slack terms keep noise-free inputs from failing: the rounding of `S = |I|^2 - N . b` in
/// the kernel's precision (at most `2 (m + cond^2) u |I|^2`, `|I|^2 <= m rho^2`), and the
/// error of tile-interpolated light directions (at most the tile tolerance per light).
pub(super) struct Screen {
    noise: super::NoiseModel,
    normal_only: bool,
    /// `rel^2 + eps32^2 / 12`: the exact test's model-error and storage-precision variances,
    /// per unit of squared luminance albedo.
    relative_var: f64,
    /// Unit roundoff of the kernel's precision.
    roundoff: f64,
    /// Tile interpolation error (radians; 0 with exact coefficients).
    tile_rad: f64,
    /// The chi-square threshold per degree of freedom (index = dof).
    threshold: Vec<f64>,
    /// The same per number of lights (index = lights, 0..=255; infinite up to three lights,
    /// which fit any normal).
    threshold_f32: [f32; 256],
    grid: InverseIntensityGrid,
    /// Per grid cell, `v_max = c[0] rho_r + c[1] rho_g + c[2] rho_b + c[3] + relative_var
    /// rho_lum^2` (NaN where the lights give no bound: such pixels never pass).
    coefficients: Vec<[f64; 4]>,
}

impl Screen {
    pub fn new(
        chi: &ChiSquare,
        options: &SolveOptions,
        input: &super::SolveInput,
        illumination: &super::Illumination,
        tile_error_deg: f64,
    ) -> Self {
        let frames = input.frames;
        let lights = illumination.len();
        let grid = InverseIntensityGrid::new(
            illumination,
            1.0 / input.exposure,
            frames.width,
            frames.height,
        );
        let noise = input.noise;
        let coefficients = grid
            .values
            .iter()
            .map(|inv| variance_coefficients(&noise, options.normal_only, inv))
            .collect();
        Screen {
            noise,
            normal_only: options.normal_only,
            relative_var: options.robust.relative_model_error.powi(2)
                + (f32::EPSILON as f64).powi(2) / 12.0,
            roundoff: match options.kernel.precision() {
                Precision::F32 => f32::EPSILON as f64 / 2.0,
                Precision::F64 => f64::EPSILON / 2.0,
            },
            tile_rad: tile_error_deg.to_radians(),
            threshold: (0..=lights)
                .map(|dof| if dof == 0 { 0.0 } else { chi.threshold(dof) })
                .collect(),
            threshold_f32: std::array::from_fn(|m| {
                if m <= 3 {
                    f32::INFINITY
                } else {
                    chi.threshold(m - 3) as f32
                }
            }),
            grid,
            coefficients,
        }
    }

    /// Collects in `failed` the columns of `row` (frame row `y`) that the fast kernel solved
    /// and whose solution the screen cannot pass.
    pub fn screen_row(&self, row: &RowOut, y: usize, failed: &mut Vec<usize>) {
        failed.clear();
        let w = row.status.len();
        for x0 in (0..w).step_by(CELL) {
            let cell = self.grid.index(x0, y);
            let coefficients = &self.coefficients[cell];
            let x1 = (x0 + CELL).min(w);
            if self.noise.shared_cfa_sample.is_none() && x1 - x0 == CELL {
                self.screen_cell(row, x0, coefficients, failed);
                continue;
            }
            for x in x0..x1 {
                let fast =
                    row.status[x] == PixelStatus::Solved && row.fit[x] == PixelFit::LeastSquares;
                if fast && !self.passes(row, x, y, coefficients, cell) {
                    failed.push(x);
                }
            }
        }
    }

    /// [`Screen::passes`] for the `CELL` pixels from `x0` (independent channels), in `f32`
    /// lanes without branches so that it vectorises: it runs on every pixel, beside a kernel
    /// that takes tens of nanoseconds per pixel. (`f32` is ample for a threshold: the terms
    /// are positive and the comparison is not near a rounding boundary in any way that
    /// matters.)
    #[inline(always)]
    fn screen_cell(
        &self,
        row: &RowOut,
        x0: usize,
        coefficients: &[f64; 4],
        failed: &mut Vec<usize>,
    ) {
        let c = coefficients.map(|v| v as f32);
        let wt = LUMINANCE_WEIGHTS.map(|v| v as f32);
        let relative_var = self.relative_var as f32;
        let (two_u, tile2) = (
            (2.0 * self.roundoff) as f32,
            (self.tile_rad * self.tile_rad) as f32,
        );
        let mut fails = [false; CELL];
        for (l, fail) in fails.iter_mut().enumerate() {
            let x = x0 + l;
            let lights = row.lights[x];
            let m = lights as f32;
            let a = [row.albedo[0][x], row.albedo[1][x], row.albedo[2][x]];
            let rho = if self.normal_only {
                a[0]
            } else {
                wt[0] * a[0] + wt[1] * a[1] + wt[2] * a[2]
            };
            let v_max = c[0] * a[0].max(0.0)
                + c[1] * a[1].max(0.0)
                + c[2] * a[2].max(0.0)
                + c[3]
                + relative_var * rho * rho;
            let cond = row.condition[x];
            let residual = row.residual[x];
            let statistic = residual * residual * m;
            let slack = (two_u * (m + cond * cond) + tile2) * m * rho * rho;
            let threshold = self.threshold_f32[lights as usize];
            let ok = statistic <= threshold * v_max + slack && rho > 0.0 && rho <= f32::MAX;
            let fast = row.status[x] == PixelStatus::Solved && row.fit[x] == PixelFit::LeastSquares;
            *fail = fast && !ok;
        }
        failed.extend(
            fails
                .iter()
                .enumerate()
                .filter(|(_, &f)| f)
                .map(|(l, _)| x0 + l),
        );
    }

    /// True when the fast kernel's solution at pixel `x` of `row` (frame row `y`, grid cell
    /// `cell` with variance `coefficients`) is within the noise: no robust fit is needed.
    #[inline(always)]
    fn passes(
        &self,
        row: &RowOut,
        x: usize,
        y: usize,
        coefficients: &[f64; 4],
        cell: usize,
    ) -> bool {
        let m = row.lights[x] as usize;
        let dof = m.saturating_sub(3);
        if dof == 0 {
            // Three lights fit any normal: nothing to test, nothing to reject.
            return true;
        }
        let albedo = [0, 1, 2].map(|c| row.albedo[c][x] as f64);
        let rho_lum = if self.normal_only {
            albedo[0]
        } else {
            LUMINANCE_WEIGHTS[0] * albedo[0]
                + LUMINANCE_WEIGHTS[1] * albedo[1]
                + LUMINANCE_WEIGHTS[2] * albedo[2]
        };
        if !(rho_lum > 0.0 && rho_lum <= f32::MAX as f64) {
            return false;
        }
        let v_max = match self.noise.shared_cfa_sample {
            None => {
                let c = coefficients;
                c[0] * albedo[0].max(0.0)
                    + c[1] * albedo[1].max(0.0)
                    + c[2] * albedo[2].max(0.0)
                    + c[3]
                    + self.relative_var * rho_lum * rho_lum
            }
            Some(pattern) => {
                let bound = shared_sample_bound(
                    &self.noise,
                    pattern,
                    &albedo,
                    rho_lum,
                    &self.grid.values[cell],
                    (x, y),
                );
                match bound {
                    Some(v) if !self.normal_only => v + self.relative_var * rho_lum * rho_lum,
                    _ => return false,
                }
            }
        };
        let (mf, cond) = (m as f64, row.condition[x] as f64);
        let residual = row.residual[x] as f64;
        let statistic = residual * residual * mf;
        let slack = (2.0 * (mf + cond * cond) * self.roundoff + self.tile_rad * self.tile_rad)
            * mf
            * rho_lum
            * rho_lum;
        statistic <= self.threshold[dof.min(self.threshold.len() - 1)] * v_max + slack
    }
}

/// The coefficients of `v_max` (see [`Screen`]) for inverse intensities at most `inv`: a
/// light's luminance variance is `sum_c w_c^2 chi_c (photon I'_c i_c + floor i_c^2)`, and
/// `I'_c <= rho_c`. A normal-only solve knows only the luminance albedo: then `sum_c w_c^2
/// chi_c I'_c i_c <= rho_lum max_c (w_c chi_c i_c)` since `sum_c w_c I'_c = I'_lum <= rho_lum`,
/// carried by the first coefficient (its albedo channels all hold `rho_lum`).
fn variance_coefficients(noise: &super::NoiseModel, normal_only: bool, inv: &[f64; 3]) -> [f64; 4] {
    if !inv.iter().all(|i| i.is_finite()) {
        return [f64::NAN; 4];
    }
    let w = LUMINANCE_WEIGHTS;
    let chi = noise.channel_scale;
    let floor = (0..3)
        .map(|c| w[c] * w[c] * chi[c] * noise.floor * inv[c] * inv[c])
        .sum();
    if normal_only {
        let most = (0..3).map(|c| w[c] * chi[c] * inv[c]).fold(0.0, f64::max);
        return [noise.photon * most, 0.0, 0.0, floor];
    }
    let photon = |c: usize| w[c] * w[c] * chi[c] * noise.photon * inv[c];
    [photon(0), photon(1), photon(2), floor]
}

/// `v_max` for frames whose three channels all carry one CFA sample of channel `p` (full
/// resolution RAW): the luminance's variance is `(rho_lum / rho_p)^2 var(I'_p)` (see
/// `NoiseModel`); `None` without a positive albedo in `p`.
fn shared_sample_bound(
    noise: &super::NoiseModel,
    pattern: [[u8; 2]; 2],
    albedo: &[f64; 3],
    rho_lum: f64,
    inv: &[f64; 3],
    (x, y): (usize, usize),
) -> Option<f64> {
    let p = pattern[y % 2][x % 2] as usize;
    let rho_p = albedo[p];
    if !(rho_p > 0.0 && inv[p].is_finite()) {
        return None;
    }
    let ratio = (rho_lum / rho_p).powi(2);
    Some(ratio * (noise.photon * rho_p * inv[p] + noise.floor * inv[p] * inv[p]))
}

/// The largest inverse intensity (raw value to `I'`, per channel) over all lights, on cells of
/// `CELL` pixels: each cell holds the largest of its four corners' values with a margin for
/// the curvature of the falloff between them (the LEDs are tens of centimetres away, a cell a
/// few millimetres of sample: the curvature term is under 0.1 %).
struct InverseIntensityGrid {
    cells_x: usize,
    cells_y: usize,
    values: Vec<[f64; 3]>,
}

const CELL: usize = 32;
const CELL_MARGIN: f64 = 1.02;

impl InverseIntensityGrid {
    fn new(illumination: &super::Illumination, inv_exposure: f64, w: usize, h: usize) -> Self {
        let nodes = |size: usize| size.saturating_sub(1).div_ceil(CELL) + 1;
        let (nx, ny) = (nodes(w), nodes(h));
        let node = |j: usize, size: usize| (j * CELL).min(size.saturating_sub(1)) as f64;
        let at_node = |jx: usize, jy: usize| -> [f64; 3] {
            let Some(point) = illumination.point_at(node(jx, w), node(jy, h)) else {
                return [f64::INFINITY; 3];
            };
            let mut most = [0.0f64; 3];
            for k in 0..illumination.len() {
                let falloff = illumination.sample(k, &point).falloff;
                let scale = illumination.rgb_scale(k);
                for c in 0..3 {
                    let inv = if falloff > 0.0 {
                        inv_exposure / (falloff * scale[c])
                    } else {
                        // A light that does not reach the point is dark there, never used.
                        0.0
                    };
                    most[c] = most[c].max(inv);
                }
            }
            most
        };
        let node_values: Vec<[f64; 3]> = (0..ny)
            .flat_map(|jy| (0..nx).map(move |jx| (jx, jy)))
            .map(|(jx, jy)| at_node(jx, jy))
            .collect();
        let (cells_x, cells_y) = ((nx - 1).max(1), (ny - 1).max(1));
        let mut values = Vec::with_capacity(cells_x * cells_y);
        for cy in 0..cells_y {
            for cx in 0..cells_x {
                let mut most = [0.0f64; 3];
                for (jx, jy) in [(cx, cy), (cx + 1, cy), (cx, cy + 1), (cx + 1, cy + 1)] {
                    let v = node_values[jy.min(ny - 1) * nx + jx.min(nx - 1)];
                    for c in 0..3 {
                        most[c] = most[c].max(v[c] * CELL_MARGIN);
                    }
                }
                values.push(most);
            }
        }
        InverseIntensityGrid {
            cells_x,
            cells_y,
            values,
        }
    }

    /// The cell of pixel `(x, y)`.
    #[inline]
    fn index(&self, x: usize, y: usize) -> usize {
        let cx = (x / CELL).min(self.cells_x - 1);
        let cy = (y / CELL).min(self.cells_y - 1);
        cy * self.cells_x + cx
    }
}

/// The adaptive estimator on the streaming kernel: each row is solved by the fast least
/// squares (`row_fn`), then every pixel the [`Screen`] does not pass is solved again by the
/// exact kernel, which runs the exact chi-square test and, where that fails, the robust fit.
/// Returns how many pixels the robust fit ran on.
#[allow(clippy::too_many_arguments)]
pub(super) fn solve_streaming<T: Real>(
    ctx: &fast::Context,
    kernel: &Kernel,
    screen: &Screen,
    illumination: &super::Illumination,
    result: &mut SolveResult,
    progress: &dyn Progress,
    row_fn: fn(&fast::Context, usize, &mut RowOut, &mut fast::RowScratch<T>),
) -> usize {
    let width = result.width;
    let escalated = AtomicUsize::new(0);
    let rows = RowOut::split(result);
    rows.into_par_iter().enumerate().for_each_init(
        || {
            (
                fast::RowScratch::<T>::new(ctx),
                Scratch::with_capacity(illumination.len()),
                Vec::new(),
            )
        },
        |(fast_scratch, exact_scratch, failed), (y, mut row)| {
            row_fn(ctx, y, &mut row, fast_scratch);
            screen.screen_row(&row, y, failed);
            for &x in failed.iter() {
                row.reset(x, PixelStatus::OutsideMask);
                match illumination.point(x, y) {
                    Some(point) => {
                        kernel.solve_pixel(y * width + x, &point, exact_scratch, &mut row, x)
                    }
                    None => row.status[x] = PixelStatus::Degenerate,
                }
            }
            escalated.fetch_add(row.escalated, Ordering::Relaxed);
            progress.advance(1);
        },
    );
    escalated.into_inner()
}
