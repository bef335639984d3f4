//! The per-pixel work: gather the usable measurements, solve the 3x3 (or SVD) least-squares
//! problem for the four right-hand sides, and derive normal, albedo, residual, condition and
//! predicted error.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::chi_square::{ChiSquare, Screened};
use super::lights::Illumination;
use super::measure::{fit_normal_equations, fit_svd, Fit, Measurement};
use super::options::{Estimator, Method, SolveOptions};
use super::predict::{expected_angle_error, DarkTest};
use super::robust;
use super::{NoiseModel, PixelFit, PixelStatus, SolveInput, SolveResult, LUMINANCE_WEIGHTS};
use crate::plane::{FrameRelease, Frames};

/// `lights_used` is stored as a byte.
pub const MAX_LIGHTS: usize = 255;

/// Per-thread buffer reused across pixels so the inner loop does not allocate.
pub struct Scratch {
    measurements: Vec<Measurement>,
    robust: robust::Buffers,
}

impl Scratch {
    pub fn with_capacity(lights: usize) -> Self {
        Scratch {
            measurements: Vec::with_capacity(lights),
            robust: robust::Buffers::default(),
        }
    }
}

/// One row of every output plane, borrowed mutably so rows can be solved in parallel.
pub struct RowOut<'a> {
    pub(super) normal: [&'a mut [f32]; 3],
    pub(super) albedo: [&'a mut [f32]; 3],
    pub(super) residual: &'a mut [f32],
    pub(super) predicted: &'a mut [f32],
    pub(super) condition: &'a mut [f32],
    pub(super) lights: &'a mut [u8],
    pub(super) fit: &'a mut [PixelFit],
    pub status: &'a mut [PixelStatus],
    /// Pixels of this row that the robust fit was run on.
    pub escalated: usize,
}

impl<'a> RowOut<'a> {
    /// True when pixel `x` was solved, by a Lambertian fit.
    pub fn is_lambertian(&self, x: usize) -> bool {
        self.status[x] == PixelStatus::Solved && self.fit[x] != PixelFit::Sheen
    }

    /// Resets pixel `x` of `row` to the unsolved defaults with `status`.
    pub fn reset(&mut self, x: usize, status: PixelStatus) {
        for d in 0..3 {
            self.normal[d][x] = if d == 2 { 1.0 } else { 0.0 };
            self.albedo[d][x] = 0.0;
        }
        self.residual[x] = 0.0;
        self.predicted[x] = 0.0;
        self.condition[x] = 0.0;
        self.lights[x] = 0;
        self.fit[x] = PixelFit::LeastSquares;
        self.status[x] = status;
    }

    pub fn split(result: &'a mut SolveResult) -> Vec<RowOut<'a>> {
        let w = result.width.max(1);
        let [nx, ny, nz] = &mut result.normal;
        let [ar, ag, ab] = &mut result.albedo;
        let mut nx = nx.data.chunks_mut(w);
        let mut ny = ny.data.chunks_mut(w);
        let mut nz = nz.data.chunks_mut(w);
        let mut ar = ar.data.chunks_mut(w);
        let mut ag = ag.data.chunks_mut(w);
        let mut ab = ab.data.chunks_mut(w);
        let mut residual = result.residual.data.chunks_mut(w);
        let mut predicted = result.predicted_error_deg.data.chunks_mut(w);
        let mut condition = result.condition.data.chunks_mut(w);
        let mut lights = result.lights_used.chunks_mut(w);
        let mut status = result.status.chunks_mut(w);
        let mut fit = result.fit.chunks_mut(w);
        (0..result.height)
            .map(|_| RowOut {
                normal: [nx.next(), ny.next(), nz.next()].map(Option::unwrap),
                albedo: [ar.next(), ag.next(), ab.next()].map(Option::unwrap),
                residual: residual.next().unwrap(),
                predicted: predicted.next().unwrap(),
                condition: condition.next().unwrap(),
                lights: lights.next().unwrap(),
                status: status.next().unwrap(),
                fit: fit.next().unwrap(),
                escalated: 0,
            })
            .collect()
    }
}

/// Give-backs in a solve that gives its frames back: the output pages faulted in before the
/// first one are a 32nd of the outputs.
const RELEASE_STEPS: usize = 32;

/// Rows a worker takes at a time in such a solve: the workers take the rows in order, a few
/// at a time, so the rows before the first unfinished one grow steadily and no worker waits
/// for another (a band at a time, the cores waited at each band's end: 0.07 s of a
/// half-resolution solve whose rows' robust fits differ in cost).
const RELEASE_CHUNK_ROWS: usize = 4;

/// Runs `op(state, y, row)` on every row in parallel (rayon; `init` makes each worker's
/// state). With `release` (made from `frames`), the workers take the rows in order, and the
/// frames' rows before the first unfinished one are given back to the kernel
/// ([`FrameRelease`]) each time they have grown by a 32nd of the image: every solver here
/// reads a pixel's frame samples only while it solves that pixel.
pub(super) fn for_each_row<'a, S>(
    rows: Vec<RowOut<'a>>,
    frames: &Frames,
    release: Option<&mut FrameRelease>,
    init: impl Fn() -> S + Sync + Send,
    op: impl Fn(&mut S, usize, RowOut<'a>) + Sync + Send,
) {
    let Some(release) = release else {
        rows.into_par_iter()
            .enumerate()
            .for_each_init(init, |state, (y, row)| op(state, y, row));
        return;
    };
    let height = rows.len();
    let mut rows = rows.into_iter().enumerate();
    let chunks: Vec<Mutex<Vec<(usize, RowOut)>>> =
        std::iter::from_fn(|| Some(rows.by_ref().take(RELEASE_CHUNK_ROWS).collect::<Vec<_>>()))
            .take_while(|chunk| !chunk.is_empty())
            .map(Mutex::new)
            .collect();
    let next = AtomicUsize::new(0);
    let frontier = Mutex::new(Frontier {
        done: vec![false; chunks.len()],
        first_undone: 0,
        given_back_to: 0,
        step: height.div_ceil(RELEASE_STEPS).max(1),
        release,
    });
    rayon::scope(|scope| {
        for _ in 0..rayon::current_num_threads() {
            scope.spawn(|_| {
                let mut state = init();
                loop {
                    let c = next.fetch_add(1, Ordering::Relaxed);
                    let Some(chunk) = chunks.get(c) else {
                        break;
                    };
                    let taken = std::mem::take(&mut *chunk.lock().expect("a worker panicked"));
                    for (y, row) in taken {
                        op(&mut state, y, row);
                    }
                    let mut frontier = frontier.lock().expect("a worker panicked");
                    frontier.finished(c, frames, height);
                }
            });
        }
    });
}

/// Which row chunks of a solve that gives its frames back are done, and what was given back.
struct Frontier<'r> {
    done: Vec<bool>,
    /// The first chunk not done.
    first_undone: usize,
    /// Rows given back so far (those before it).
    given_back_to: usize,
    /// Rows to grow by between two give-backs.
    step: usize,
    release: &'r mut FrameRelease,
}

impl Frontier<'_> {
    /// Chunk `c` is done: gives back the rows before the first unfinished chunk once they have
    /// grown by `step` (or reach the end).
    fn finished(&mut self, c: usize, frames: &Frames, height: usize) {
        self.done[c] = true;
        while self.done.get(self.first_undone) == Some(&true) {
            self.first_undone += 1;
        }
        let end = (self.first_undone * RELEASE_CHUNK_ROWS).min(height);
        if end >= self.given_back_to + self.step || (end == height && end > self.given_back_to) {
            // SAFETY: `release` was made from `frames` (checked by `release_rows_before`);
            // every row before `end` is solved and no solver reads a frame row again once its
            // output row is done; the other workers read only rows from `end` on, which no page
            // given back holds (whole pages before `end`'s first byte); no other thread reads
            // the frames (`solve_releasing`'s contract).
            unsafe { self.release.release_rows_before(frames, end) };
            self.given_back_to = end;
        }
    }
}

pub struct Kernel<'a> {
    frames: &'a Frames,
    illumination: &'a Illumination<'a>,
    noise: NoiseModel,
    inv_exposure: f64,
    dark: DarkTest,
    options: &'a SolveOptions,
    chi_square: ChiSquare,
    /// Adaptive's second pass on a scene that shows sheen: fit the sheen model everywhere.
    force_sheen: bool,
}

/// Why measurements were dropped at a pixel, to name the reason when too few remain.
#[derive(Default)]
struct Dropped {
    non_finite: usize,
    saturated: usize,
    dark: usize,
}

impl Dropped {
    fn status(&self) -> PixelStatus {
        if self.non_finite >= self.saturated && self.non_finite >= self.dark && self.non_finite > 0
        {
            PixelStatus::NonFinite
        } else if self.saturated >= self.dark && self.saturated > 0 {
            PixelStatus::Saturated
        } else {
            PixelStatus::Dark
        }
    }
}

impl<'a> Kernel<'a> {
    pub fn new(
        input: &'a SolveInput,
        options: &'a SolveOptions,
        illumination: &'a Illumination<'a>,
    ) -> Self {
        Kernel {
            frames: input.frames,
            illumination,
            noise: input.noise,
            inv_exposure: 1.0 / input.exposure,
            dark: input
                .noise
                .dark_test(&LUMINANCE_WEIGHTS, options.dark_threshold_sigma),
            options,
            chi_square: ChiSquare::new(
                options.robust.significance_sigma,
                options.robust.relative_model_error,
            ),
            force_sheen: false,
        }
    }

    /// The same kernel fitting the sheen model at every pixel it solves.
    pub fn forcing_sheen(self) -> Self {
        Kernel {
            force_sheen: true,
            ..self
        }
    }

    /// Solves pixel `i` (column `x` of `row`) whose point on the sample is `point`.
    pub fn solve_pixel(
        &self,
        i: usize,
        point: &Vector3<f64>,
        scratch: &mut Scratch,
        row: &mut RowOut,
        x: usize,
    ) {
        let dropped = self.gather(i, point, &mut scratch.measurements);
        let Scratch {
            measurements,
            robust: buffers,
        } = scratch;
        row.lights[x] = measurements.len() as u8;
        if measurements.len() < 3 {
            row.status[x] = dropped.status();
            return;
        }
        let Some(fit) = self.least_squares(measurements) else {
            row.status[x] = PixelStatus::Degenerate;
            return;
        };
        if self.options.estimator() != Estimator::LeastSquares {
            self.chi_square.prepare(measurements);
        }
        // Where the test fails, its weighted fit is the robust fit's start.
        let (escalate, weighted) = match self.options.estimator() {
            Estimator::LeastSquares => (false, None),
            Estimator::Robust => (true, None),
            Estimator::Adaptive if self.force_sheen => (true, None),
            Estimator::Adaptive => match self.chi_square.screen(measurements, &fit.n_lum) {
                Screened::Passes => (false, None),
                Screened::Fails(weighted) => (true, weighted),
            },
        };
        let fit = if escalate {
            row.escalated += 1;
            let context = robust::Context {
                options: &self.options.robust,
                max_condition: self.options.max_condition,
                chi: &self.chi_square,
                view: self.illumination.view(point),
                force_sheen: self.force_sheen || self.options.estimator() == Estimator::Robust,
            };
            robust::refine(&context, measurements, buffers, fit, weighted)
        } else {
            fit
        };
        row.lights[x] = measurements.len() as u8;
        self.write_outputs(&fit, measurements, row, x);
    }

    /// Plain least squares over `measurements` with the options' method; `None` when the light
    /// matrix is singular or worse conditioned than allowed.
    pub(super) fn least_squares(&self, measurements: &[Measurement]) -> Option<Fit> {
        let fit = match self.options.kernel.method() {
            Method::NormalEquations => fit_normal_equations(measurements),
            Method::Svd => fit_svd(measurements),
        };
        fit.filter(|f| f.condition <= self.options.max_condition)
    }

    /// The options this kernel solves with.
    pub(super) fn options(&self) -> &SolveOptions {
        self.options
    }

    pub(super) fn chi_square(&self) -> &ChiSquare {
        &self.chi_square
    }

    /// Collects the usable measurements at pixel `i`; returns why the others were dropped.
    fn gather(&self, i: usize, point: &Vector3<f64>, out: &mut Vec<Measurement>) -> Dropped {
        out.clear();
        let mut dropped = Dropped::default();
        let (x, y) = (i % self.frames.width, i / self.frames.width);
        for (k, frame) in self.frames.lights.iter().enumerate() {
            let raw = frame.rgb_at(x, y).map(|v| v as f64);
            if raw.iter().any(|v| !v.is_finite()) {
                dropped.non_finite += 1;
                continue;
            }
            if frame.saturated.as_ref().is_some_and(|m| m.data[i]) {
                dropped.saturated += 1;
                continue;
            }
            if self.dark.is_dark(&raw, (x, y)) {
                dropped.dark += 1;
                continue;
            }
            let light = self.illumination.sample(k, point);
            if light.falloff <= 0.0 {
                dropped.dark += 1;
                continue;
            }
            let scale = self.illumination.rgb_scale(k);
            let mut rgb = [0.0; 3];
            let mut lum = 0.0;
            let mut inv_intensity = [0.0; 3];
            for c in 0..3 {
                inv_intensity[c] = self.inv_exposure / (light.falloff * scale[c]);
                rgb[c] = raw[c] * inv_intensity[c];
                lum += LUMINANCE_WEIGHTS[c] * rgb[c];
            }
            let pixel = (i % self.frames.width, i / self.frames.width);
            let var =
                self.noise
                    .luminance_variance(&raw, &inv_intensity, &LUMINANCE_WEIGHTS, lum, pixel);
            out.push(Measurement {
                l: light.direction,
                rgb,
                lum,
                var,
                test_var: var,
                light: k as u16,
            });
        }
        dropped
    }

    fn write_outputs(&self, fit: &Fit, measurements: &[Measurement], row: &mut RowOut, x: usize) {
        let albedo_lum = fit.n_lum.norm();
        if !(albedo_lum > 1e-12 && albedo_lum.is_finite()) {
            row.status[x] = PixelStatus::Dark;
            return;
        }
        let n = fit.n_lum / albedo_lum;
        // A normal-only solve reports the luminance albedo in every channel.
        let albedo = if self.options.normal_only {
            [albedo_lum; 3]
        } else {
            fit.n_rgb.map(|nc| nc.dot(&n))
        };
        let residual = fit.residual.unwrap_or_else(|| {
            let sum_sq: f64 = measurements
                .iter()
                .map(|m| (m.lum - fit.n_lum.dot(&m.l)).powi(2))
                .sum();
            (sum_sq / measurements.len() as f64).sqrt()
        });
        let predicted = if self.options.predict_error {
            let mut noise = Matrix3::zeros();
            for m in measurements {
                noise += m.l * m.l.transpose() * m.var;
            }
            let cov = if fit.weighted {
                fit.a_inv
            } else {
                fit.a_inv * noise * fit.a_inv
            };
            expected_angle_error(&fit.n_lum, &cov).to_degrees()
        } else {
            0.0
        };
        let values = [
            n.x, n.y, n.z, albedo[0], albedo[1], albedo[2], residual, predicted,
        ];
        if values.iter().any(|v| !v.is_finite()) {
            row.status[x] = PixelStatus::NonFinite;
            return;
        }
        for c in 0..3 {
            row.normal[c][x] = n[c] as f32;
            row.albedo[c][x] = albedo[c] as f32;
        }
        row.residual[x] = residual as f32;
        row.predicted[x] = predicted as f32;
        row.condition[x] = fit.condition as f32;
        row.fit[x] = fit.kind;
        row.status[x] = PixelStatus::Solved;
    }
}
